"""The signal chain as real processes through a real router: `trackfusion simulate
--fidelity raw` → `trackfusion ingestion` → `trackfusion extraction`. Every segment the
train fully passed at speed, with its data and position intact, gets an OnboardIndex."""

from __future__ import annotations

import signal

import numpy as np

from schemas import DAY_S, DeadLetter, OnboardIndex, decode, keys
from services.defaults import demo_network
from simulators.profile import LineProfile
from simulators.train import TrainSimulator

START = 1_767_225_600.0  # the simulator's default start, 2026-01-01T00:00:00Z
SECONDS = 900
SEED = 11
MARGIN_M = 30.0  # beyond the segment: the chords and the filters' settling need it
V_MIN = 5.5  # a little above the 5 m/s reference speed
TAIL_S = 30.0  # a pass this close to the end may still be in the pipeline


def passed_at_speed() -> set[str]:
    """Segments of train T000 (the simulator's first train, on the first line) whose whole
    extended range was run at speed, outside tunnels, with every chunk and fix present."""
    line = next(iter(demo_network().lines.values()))
    profile = LineProfile(line.id, [(s.start_m, s.end_m) for s in line.segments], SEED)
    train = TrainSimulator("T000", line, profile, SEED, units=1, start_t=START)
    t = START + np.arange(0.0, SECONDS, 0.1)
    chainage, speed, _, _ = train.position(t)
    dropped = {k for k in range(SECONDS) if train.chunk(k)[2]}
    no_fix = {
        round(f.t - START) for f in train.gps_fixes(START, START + SECONDS) if f.fix_quality == 0
    }
    tunnels = np.asarray(line.tunnels, float).reshape(-1, 2)
    expected = set()
    for seg in line.segments:
        lo, hi = seg.start_m - MARGIN_M, seg.end_m + MARGIN_M
        inside = (chainage >= lo) & (chainage <= hi)
        if not inside.any() or ((tunnels[:, 0] < hi) & (tunnels[:, 1] > lo)).any():
            continue
        first, last = np.flatnonzero(inside)[[0, -1]]
        span = chainage[first : last + 1]
        seconds = set(range(int(t[first] - START) - 3, int(t[last] - START) + 4))
        if (
            np.all(inside[first : last + 1])  # one pass, no turning back inside
            and span.min() <= lo + 5.0
            and span.max() >= hi - 5.0  # the whole extended range (10 Hz samples of it)
            and speed[first : last + 1].min() >= V_MIN
            and t[last] < START + SECONDS - TAIL_S
            and not seconds & (dropped | no_fix)
        ):
            expected.add(seg.id)
    return expected


def test_every_segment_passed_at_speed_gets_an_index(
    router, namespace, open_session, collector, signal_chain, spawn
):
    expected = passed_at_speed()
    assert len(expected) >= 20, "the scenario should pass many segments at speed"
    session = open_session()
    indices = collector(lambda s: decode(s.payload.to_bytes(), OnboardIndex))
    session.declare_subscriber(keys.segment_keys(namespace, "index"), indices)
    letters = collector(lambda s: decode(s.payload.to_bytes(), DeadLetter))
    session.declare_subscriber(keys.deadletter_all(namespace), letters)
    wiring = ["--connect", router, "--ns", namespace]
    ingestion, extraction = signal_chain(session, wiring)

    world = ["--fidelity", "raw", "--trains", "1", "--days", str(SECONDS / DAY_S)]
    simulate = spawn(
        "simulate", "simulate", *world, "--speedup", "60", "--seed", str(SEED), *wiring
    )
    assert simulate.wait(120) == 0, simulate.log()

    got: set[str] = set()
    while not expected <= got:
        try:
            index = indices.get(timeout=30)
        except AssertionError:
            missing = sorted(expected - got)
            reasons = []
            while not letters.empty():
                letter = letters.get()
                reasons.append(f"{letter.service} {letter.key} {letter.reason}")
            for process in (ingestion, extraction):
                process.signal(signal.SIGTERM)  # they log their counters on the way out
                process.wait(10)
            raise AssertionError(
                f"dead letters: {reasons}\n"
                f"no index for {missing}{ingestion.log()[-2000:]}{extraction.log()[-2000:]}"
            ) from None
        assert index.train == "T000" and index.line == "L1"
        assert index.speed_mps >= 5.0 and 0.9 <= index.coverage <= 1.0
        assert 0.1 < index.top6_mm < 50 and 0.1 < index.align10_mm < 50
        got.add(index.segment)
