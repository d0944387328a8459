"""The closed-loop bench's baselines and its break-even price (``bench/planning.py``)."""

import argparse

import numpy as np
import pytest

from bench.planning import Loop, arguments, break_even, world_config
from services.defaults import load_network


def _totals(**policies):
    return {p: {"cost": cost, "wear": 0.0, "km_days_ial": days} for p, (cost, days) in
            policies.items()}  # fmt: skip


def test_break_even_reprices_the_ial_km_days_the_planner_spares():
    lines = break_even(
        _totals(
            planner=(1_100.0, 2.0),
            cycle=(1_000.0, 12.0),
            threshold=(1_200.0, 20.0),
            point=(900.0, 1.0),
        ),  # fmt: skip
        price=400.0,
    )
    said = dict(line.split(maxsplit=1) for line in lines[1:])
    assert said["cycle"] == "410"  # 100 more for 10 km-days fewer: +10 a km-day
    assert said["threshold"] == "cheaper already"
    assert said["point"].startswith("never")


def test_break_even_needs_the_planner():
    assert break_even(_totals(cycle=(1.0, 1.0)), price=400.0) == []


def _args(*argv: str) -> argparse.Namespace:
    return arguments().parse_args(["--samples", "8", *argv])


@pytest.mark.parametrize("years", [1.0, 4.0])
def test_the_cycle_tamps_every_segment_once_a_period_within_a_line_s_capacity(years):
    network = load_network(None)
    loop = Loop(network, world_config(), 1, "cycle", _args("--cycle-years", str(years)))
    period = loop.cycle_period
    assert period == round(52 * years)
    weeks = [loop.decide(w) for w in range(period)]
    tamped = np.concatenate(weeks)
    assert sorted(tamped) == list(range(len(loop.refs)))  # each once in a period
    for rows in weeks:
        for line in {loop.refs[i].line for i in rows}:
            km = sum(loop.km[i] for i in rows if loop.refs[i].line == line)
            assert km <= 2.0 + 1e-9


def test_the_threshold_rule_keeps_each_line_s_capacity():
    network = load_network(None)
    loop = Loop(network, world_config(), 1, "threshold", _args("--capacity", "0.6"))
    loop.trc_seen = loop.log_il + 1.0  # every segment over the intervention limit
    rows = loop.decide(0)
    lines = {r.line for r in loop.refs}
    assert {loop.refs[i].line for i in rows} == lines  # every line gets its share
    for line in lines:
        assert sum(loop.km[i] for i in rows if loop.refs[i].line == line) <= 0.6 + 1e-9
