# Each target sets up .venv itself, so a fresh machine needs only python3 (>= 3.11).
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: run test bench scale soak soak-demo soak-trains soak-order soak-chaos pictures lint format clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -e '.[dev]'
	touch $(STAMP)

run: $(STAMP)
	$(BIN)/trackfusion up

test: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	$(BIN)/pytest -q

bench: $(STAMP)
	$(BIN)/python -m bench

# `make scale`: a national deployment on this machine (bench/scale.py): two routers, four
# filtering shards by selector, calibration, a fast-mode simulator, at 10,000, 30,000 and
# 100,000 segments (~15-20 min); events/s, memory per instance, restart of one shard. Not
# part of `make bench` or `make test`. A smoke run: `make scale SCALE_ARGS=--quick`.
scale: $(STAMP)
	$(BIN)/python -m bench.scale $(SCALE_ARGS)

# `make soak`: first what `make run` starts, left running for 30 minutes with a headless
# browser on the web viewer (bench/demo_soak.py: alive, state gaps, q/state, memory, first
# picture), then the whole stack under 100 raw trains for 10 minutes (bench/soak.py), then
# filtering's order check (bench/order_check.py). Each alone: `make soak-demo DEMO_SOAK_ARGS="--minutes 15"`, `make soak-trains
# SOAK_ARGS="--minutes 3 --trains 100,70,50"`.
soak: soak-demo soak-trains soak-order soak-chaos

soak-demo: $(STAMP)
	$(BIN)/python -m bench.demo_soak $(DEMO_SOAK_ARGS)

soak-trains: $(STAMP)
	$(BIN)/python -m bench.soak $(SOAK_ARGS)

# 200 random event sequences, 3 deliveries each (shuffled, duplicated, late), through one
# message at a time, batches and a restart: filtering must end as in canonical order.
soak-order: $(STAMP)
	$(BIN)/python -m bench.order_check $(ORDER_ARGS)

# Seeded random faults for 30 minutes on the demo network, then on a generated 25,000-segment
# one (bench/chaos.py): SIGKILL and SIGSTOP of any process and the router, filtering's disk
# full, a cut link, clock jumps, old-dated bursts, duplicates, hostile messages; then every
# segment's state compared byte for byte with the undisturbed fold of the same inputs.
# A short run: `make soak-chaos CHAOS_ARGS="--minutes 3 --days 30"`.
soak-chaos: $(STAMP)
	$(BIN)/python -m bench.chaos --network demo $(CHAOS_ARGS)
	$(BIN)/python -m bench.chaos --network 25000 --days 10 --trains 1 $(CHAOS_ARGS)

# `make pictures`: the pictures of docs/operating.md's real-network walk-through, made by
# running it on tests/fixtures/osm/riviera.json (bench/walkthrough_pictures.py, a few
# minutes; needs /usr/bin/chromium).
pictures: $(STAMP)
	$(BIN)/python -m bench.walkthrough_pictures

lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .

format: $(STAMP)
	$(BIN)/ruff format .
	$(BIN)/ruff check --fix .

clean:
	rm -rf $(VENV) build *.egg-info
