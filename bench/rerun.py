"""Model-change re-run of the filtering core: events replayed per second, summaries included.

A new Calibration re-runs every segment of :class:`services.filtering.tracker.Tracker` from
its last TRC record (calibration publishes a new version about twice a month of event
time). Workload:
``SEGMENTS`` segments at Ns = 200, each a TRC record and ``EVENTS - 1`` on-board indices
(a tamping on every tenth segment); the figure is events replayed per second by
``Tracker.update_models([calibration])``, which re-runs them in one batched pass and
summarises every state (mixture, intervals, exceedances, forecasts).

Baselines in the same run: the filter bank alone (``FilterBank`` replay of the same events,
sample-updates/s turned into events/s at Ns = 200: the rate of the maths without
summaries or messages) and the one-segment-at-a-time re-run (``replay`` then
``segment_state`` per segment, what ``_rerun`` did before), on a subset of the segments,
whose states must be the batched ones bit for bit. The three are interleaved and the best
of two runs of each counts (the machine is shared).

Run: ``.venv/bin/python -m bench.rerun [segments]``.
"""

from __future__ import annotations

import sys
import time

import numpy as np

from schemas import DAY_S, MaintenanceEvent, OnboardIndex, TrcRecord, encode
from services.filtering.events import INDEX, TAMPING
from services.filtering.kalman import FilterBank
from services.filtering.segment import replay
from services.filtering.testing import example_models
from services.filtering.tracker import Tracker
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


def _bank_replay(hists, params, obs) -> FilterBank:
    """The filter bank alone on the histories' events: restart, then one call per kind and
    event position over every segment."""
    kinds = np.array([[e.kind for e in t.log] for t in hists])  # same length: EVENTS
    t_days = (np.array([[e.t_s for e in t.log] for t in hists]) - T0) / DAY_S
    y = np.array([[np.zeros(2) if e.value is None else e.value for e in t.log] for t in hists])
    everyone = np.arange(len(hists))
    bank = FilterBank(len(hists), params)
    bank.restart(everyone, y[:, 0], 0.0)
    for k in range(1, EVENTS):
        idx, tamp = everyone[kinds[:, k] == INDEX], everyone[kinds[:, k] == TAMPING]
        bank.observe(idx, t_days[idx, k], y[idx, k], obs)
        if len(tamp):
            bank.predict_to(tamp, t_days[tamp, k], tamping_age=np.zeros(len(tamp)))
    return bank


def bench_rerun(segments: int = SEGMENTS, repeats: int = 2) -> None:
    rng = np.random.default_rng(5)
    calibration, posterior = example_models(NS_SAMPLES, seed=7)
    limits = load_limits()
    tracker = Tracker(limits.for_line, limits.levels)
    tracker.load([calibration, posterior], _events(rng, segments))
    n_events = sum(len(hist.log) for hist in tracker.histories.values())
    hists = list(tracker.histories.values())
    subset = hists[:BASELINE_SEGMENTS]
    fields = {f: getattr(calibration, f) for f in calibration.__struct_fields__}
    batched_s = bank_s = one_s = np.inf
    # Interleaved and best of ``repeats``: the machine is shared, so the three figures are
    # taken as close together as possible and the least disturbed run counts.
    for repeat in range(repeats):
        newer = type(calibration)(**fields | {"version": 2 + repeat})
        started = time.perf_counter()
        update = tracker.update_models([newer])
        batched_s = min(batched_s, time.perf_counter() - started)
        assert len(update.states) == segments

        started = time.perf_counter()
        bank = _bank_replay(hists, tracker.models.params["net"], tracker.models.observation)
        bank_s = min(bank_s, time.perf_counter() - started)

        started = time.perf_counter()
        alone = [tracker.segment_state(replay(hist, tracker.models)) for hist in subset]
        one_s = min(one_s, time.perf_counter() - started)
    rate = n_events / batched_s
    bank_rate = segments * EVENTS / bank_s  # events/s = sample-updates/s / Ns
    one_rate = sum(len(t.log) for t in subset) / one_s
    same_bits = [encode(s) for s in alone] == [encode(s) for s in update.states[: len(subset)]]
    close_to_bank = all(
        np.allclose(t.state.z, bank.z[i], rtol=0, atol=1e-9)
        and np.allclose(t.state.P, bank.P[i], rtol=0, atol=1e-12)
        for i, t in enumerate(tracker.histories.values())
    )
    print(
        f"model-change re-run  Ns={NS_SAMPLES}, {segments} segments x {EVENTS} events "
        f"(best of {repeats}): batched {batched_s:.2f} s = {rate:,.0f} events/s with summaries "
        f"(target >= 200,000); filter bank alone {bank_rate:,.0f} events/s "
        f"({bank_rate * NS_SAMPLES / 1e6:.1f} M sample-updates/s), ratio {rate / bank_rate:.2f}; "
        f"one segment at a time {one_rate:,.0f} events/s (on {len(subset)} segments), ratio "
        f"{rate / one_rate:.1f}x; same bits as one at a time: {same_bits}; same numbers as "
        f"the bank: {close_to_bank}"
    )


if __name__ == "__main__":
    bench_rerun(int(sys.argv[1]) if len(sys.argv) > 1 else SEGMENTS)
