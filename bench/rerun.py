"""Model-change re-run of the filtering core: events replayed per second, summaries included.

A new Calibration re-runs every segment of :class:`services.filtering.tracker.Tracker` from
its last TRC record (issue 12: calibration publishes often in the live demo). Workload:
``SEGMENTS`` segments at Ns = 200, each a TRC record and ``EVENTS - 1`` on-board indices
(a tamping on every tenth segment); the figure is events replayed per second by
``Tracker.update_models([calibration])``, which re-runs them in one batched pass and
summarises every state (mixture, intervals, exceedances, forecasts).

Baselines in the same run: the filter bank alone (``FilterBank`` replay of the same events,
sample-updates/s turned into events/s at Ns = 200: the rate of the maths without
summaries or messages) and the one-segment-at-a-time re-run (``replay`` then
``segment_state`` per segment, what ``_rerun`` did before), on a subset of the segments.

Run: ``.venv/bin/python -m bench.rerun [segments]``.
"""

from __future__ import annotations

import sys
import time

import numpy as np

from schemas import MaintenanceEvent, OnboardIndex, TrcRecord
from services.filtering.bank import FilterBank
from services.filtering.testing import example_models
from services.filtering.tracker import DAY_S, Tracker, replay
from services.limits import load_limits

NS_SAMPLES, SEGMENTS, EVENTS, BASELINE_SEGMENTS = 200, 2000, 50, 100
T0 = 1_767_225_600.0


def _events(rng: np.random.Generator, segments: int) -> list:
    msgs: list = []
    y = np.exp(rng.normal([0.8, 0.5], 0.1, (segments, EVENTS - 1, 2))).tolist()
    for s in range(segments):
        seg = f"s{s:05d}"
        msgs.append(
            TrcRecord(line="L1", segment=seg, t=T0, top6_mm=3.0, align10_mm=2.4, run_id="r0")
        )
        for k in range(1, EVENTS):
            t = T0 + (3 * k + (s % 3)) * DAY_S
            if s % 10 == 5 and k == EVENTS // 2:
                msgs.append(
                    MaintenanceEvent(line="L1", segment=seg, event_id="m", t_start=t, t_end=t)
                )
                continue
            msgs.append(
                OnboardIndex(
                    line="L1",
                    segment=seg,
                    train="T1",
                    unit="u1",
                    t=t,
                    top6_mm=y[s][k - 1][0],
                    align10_mm=y[s][k - 1][1],
                    speed_mps=30.0,
                    coverage=1.0,
                )
            )
    return msgs


def bench_rerun(segments: int = SEGMENTS) -> None:
    rng = np.random.default_rng(5)
    calibration, posterior = example_models(NS_SAMPLES, seed=7)
    limits = load_limits()
    tracker = Tracker(limits.for_line, limits.levels)
    tracker.load([calibration, posterior], _events(rng, segments))
    n_events = sum(len(track.log) for track in tracker.tracks.values())
    new_calibration = calibration.__class__(
        **{f: getattr(calibration, f) for f in calibration.__struct_fields__} | {"version": 2}
    )
    started = time.perf_counter()
    update = tracker.update_models([new_calibration])
    batched_s = time.perf_counter() - started
    assert len(update.states) == segments
    rate = n_events / batched_s

    # Baseline 1: the filter bank alone on the same events (restart, then one observe or a
    # tamping per event position over every segment).
    params = tracker.models.params["net"]
    obs = tracker.models.observation
    tracks = list(tracker.tracks.values())
    kinds = np.array([[e.kind for e in t.log] for t in tracks])  # same length: EVENTS
    t_days = (np.array([[e.t_s for e in t.log] for t in tracks]) - T0) / DAY_S
    y = np.array([[np.zeros(2) if e.value is None else e.value for e in t.log] for t in tracks])
    everyone = np.arange(segments)
    started = time.perf_counter()
    bank = FilterBank(segments, params)
    bank.restart(everyone, y[:, 0], 0.0)
    for k in range(1, EVENTS):
        idx, tamp = everyone[kinds[:, k] == 2], everyone[kinds[:, k] == 1]
        bank.observe(idx, t_days[idx, k], y[idx, k], obs)
        if len(tamp):
            bank.predict_to(tamp, t_days[tamp, k], tamping_age=np.zeros(len(tamp)))
    bank_s = time.perf_counter() - started
    bank_rate = segments * EVENTS / bank_s  # events/s = sample-updates/s / Ns
    same = all(
        np.allclose(t.state.z, bank.z[i], rtol=0, atol=1e-9)
        and np.allclose(t.state.P, bank.P[i], rtol=0, atol=1e-12)
        for i, t in enumerate(tracker.tracks.values())
    )

    # Baseline 2: one segment at a time, on a subset.
    subset = tracks[:BASELINE_SEGMENTS]
    started = time.perf_counter()
    for track in subset:
        tracker.segment_state(replay(track, tracker.models))
    one_s = time.perf_counter() - started
    one_rate = sum(len(t.log) for t in subset) / one_s

    print(
        f"model-change re-run  Ns={NS_SAMPLES}, {segments} segments x {EVENTS} events: "
        f"batched {batched_s:.2f} s = {rate:,.0f} events/s with summaries (target >= 200,000); "
        f"filter bank alone {bank_rate:,.0f} events/s ({bank_rate * NS_SAMPLES / 1e6:.1f} M "
        f"sample-updates/s): ratio {rate / bank_rate:.2f}; one segment at a time "
        f"{one_rate:,.0f} events/s (on {len(subset)} segments): ratio {rate / one_rate:.1f}x; "
        f"same numbers as the bank: {same}"
    )


if __name__ == "__main__":
    bench_rerun(int(sys.argv[1]) if len(sys.argv) > 1 else SEGMENTS)
