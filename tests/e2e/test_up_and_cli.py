"""`trackfusion up` with a small stack file, and every operator command against it; Ctrl-C
(SIGINT) stops the whole stack with exit code 0."""

from __future__ import annotations

import csv
import io
import json
import signal

import json5
import zenoh
from support import run_cli

from schemas import keys
from services.runtime.config import zenoh_config


def test_up_runs_the_stack_and_answers_every_command(
    free_port, namespace, spawn, collector, liveliness_events, tmp_path
):
    endpoint = f"tcp/127.0.0.1:{free_port}"
    state_dir = tmp_path / "var"
    stack = {
        "ns": namespace,
        "router": {"listen": endpoint},
        "state_dir": str(state_dir),
        "processes": [
            {
                "name": "calibration",
                "args": [
                    "--db", str(state_dir / "cal.sqlite"), "--instance", "calibration",
                    "--initial-models", "{defaults}/initial-models.json5",
                ],
            },
            {"name": "filtering", "args": ["--db", str(state_dir / "f.sqlite")]},
            {"name": "alerting", "args": ["--db", str(state_dir / "a.sqlite")]},
            {
                "name": "simulator",
                "command": "simulate",
                "args": ["--fidelity", "index", "--days", "30", "--trains", "1",
                         "--speedup", "200000", "--no-progress"],
            },
        ],
    }  # fmt: skip
    stack_file = tmp_path / "stack.json5"
    stack_file.write_text(json5.dumps(stack))
    up = spawn("up", "up", "--stack", str(stack_file))

    client = {"mode": "client", "connect": {"endpoints": [endpoint], "timeout_ms": 60000}}
    with zenoh.open(zenoh_config(client)) as s:  # waits for the router of `up`
        alive = liveliness_events(s, keys.alive_all(namespace))
        services = set()
        while not {"calibration", "filtering", "alerting"} <= services:
            kind, key = alive.get(timeout=60)
            services.add(keys.parse_alive(key)[0])
        states = collector()
        s.declare_subscriber(keys.segment_keys(namespace, "state"), states)
        first = states.get(timeout=60)  # a TRC run and the initial models make states
        _, _, line, segment = keys.parse_segment_key(str(first.key_expr))

        # The simulator outruns filtering on purpose: a query waits behind the queued events
        # (under load, more than the default 10 s), so the commands get a longer bound.
        wiring = ("--connect", endpoint, "--ns", namespace, "--timeout", "60")
        status = run_cli("status", *wiring)
        assert status.returncode == 0 and "filtering" in status.stdout, status.stderr
        state = run_cli("state", f"{line}/{segment}", *wiring)
        assert state.returncode == 0 and f"{line}/{segment}" in state.stdout, state.stderr
        assert "95% [" in state.stdout and "in  180 d" in state.stdout
        assert run_cli("state", "nonsense", *wiring).returncode != 0
        alerts = run_cli("alerts", *wiring)
        assert alerts.returncode == 0, alerts.stderr
        plan = run_cli("plan", "--limit", "3", *wiring)
        assert plan.returncode == 0 and "rank" in plan.stdout, plan.stderr
        exported = run_cli("export", "states", "--format", "csv", *wiring)
        rows = list(csv.DictReader(io.StringIO(exported.stdout)))
        assert exported.returncode == 0 and rows and float(rows[0]["top6_mm"]) > 0
        geo = run_cli("export", "states", "--format", "geojson", *wiring)
        features = json.loads(geo.stdout)["features"]
        assert features and features[0]["geometry"]["type"] == "LineString"
        geo_alerts = run_cli("export", "alerts", "--format", "geojson", *wiring)
        assert json.loads(geo_alerts.stdout)["type"] == "FeatureCollection"

    up.signal(signal.SIGINT)
    assert up.wait(20) == 0, up.log()
    assert "stack stopped" in up.log_path.read_text()
    for name in ("calibration", "filtering", "alerting", "simulator"):
        assert (state_dir / f"{name}.log").exists()
    health = json.loads((state_dir / "health.json").read_text())  # the last one, on stopping
    assert not health["up"]["running"]
    assert set(health["processes"]) == {"calibration", "filtering", "alerting", "simulator"}
    assert all(p["restarts"] == 0 for p in health["processes"].values()), health
