"""Backlog throughput of one filtering instance, in process (issue 16, DESIGN: >= 50,000
events/s per instance with a backlog).

Workload: ``SEGMENTS`` segments at Ns = 200, each with a TRC record, then ``EVENTS``
OnboardIndex in time order on random segments (a backfill, a consumer catching up), as
``(key, payload)`` in batches of the service's ``BATCH``, through
:meth:`PersistentTracker.handle_batch` on a real SQLite file (decode, fold, commit in one
transaction per batch) with ``summarize=False``, as the service does under a backlog: the
changed segments are marked dirty and published later. The final publication of every
dirty segment (summary and encoded SegmentState, what the service puts once the backlog is
gone) is timed separately. The garbage collector's generations are frozen after the setup and
every ``FREEZE_S`` of the loop, as the service does (a full collection otherwise
walks every segment's log and state: a quarter of the time).

Baseline in the same run: the fold alone (:func:`fold_many` on the same batches, each
segment's events of a batch from its state, the events prepared beforehand, the states
copied in and out of a reused :class:`Scratch` as the service's fold does), i.e. the
filter bank's maths without messages or SQLite. Interleaved per batch so that both see the
same load on a shared machine.

Run: ``.venv/bin/python -m bench.backlog [segments events] [--profile]``.
"""

from __future__ import annotations

import cProfile
import gc
import pstats
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from schemas import OnboardIndex, TrcRecord, encode, keys
from services.filtering.service import BATCH, FREEZE_S
from services.filtering.store import PersistentTracker, Store
from services.filtering.testing import example_models
from services.filtering.tracker import Scratch, Tracker, event_of, fold_many
from services.limits import load_limits

NS_SAMPLES, SEGMENTS, EVENTS = 200, 20_000, 60_000  # about 1 min with the machine loaded
T0 = 1_767_225_600.0
NS = "tfbench"


def _segment(k: int) -> str:
    return f"s{k:05d}"


def _indices(rng: np.random.Generator, segments: int, n: int) -> list[OnboardIndex]:
    """``n`` indices in time order (one every 10 s of event time) on random segments."""
    where = rng.integers(segments, size=n).tolist()
    y = np.exp(rng.normal([0.8, 0.5], 0.1, (n, 2))).tolist()
    return [
        OnboardIndex(
            line="L1",
            segment=_segment(where[i]),
            train="T1",
            unit="u1",
            t=T0 + 3600.0 + 10.0 * i,
            top6_mm=y[i][0],
            align10_mm=y[i][1],
            speed_mps=30.0,
            coverage=1.0,
        )
        for i in range(n)
    ]


def bench_backlog(segments: int = SEGMENTS, events: int = EVENTS, profile: bool = False) -> None:
    rng = np.random.default_rng(16)
    models = example_models(NS_SAMPLES, seed=3)
    limits = load_limits()
    trcs = [
        TrcRecord(line="L1", segment=_segment(k), t=T0, top6_mm=3.0, align10_mm=2.4, run_id="r0")
        for k in range(segments)
    ]
    indices = _indices(rng, segments, events)
    items = [(keys.key_of(NS, m), encode(m)) for m in indices]
    batches = [items[i : i + BATCH] for i in range(0, len(items), BATCH)]
    prepared = [[event_of(m) for m in indices[i : i + BATCH]] for i in range(0, events, BATCH)]

    with tempfile.TemporaryDirectory() as tmp:
        node = PersistentTracker(Tracker(limits.for_line, limits.levels), Store(Path(tmp) / "b.db"))
        node.handle_batch([(keys.key_of(NS, m), encode(m)) for m in models])
        for i in range(0, segments, BATCH):
            node.handle_batch([(keys.key_of(NS, m), encode(m)) for m in trcs[i : i + BATCH]])
        tracker = node.tracker
        params, obs = tracker.models.params["net"], tracker.models.observation
        bank_states = {sid: hist.state for sid, hist in tracker.histories.items()}
        # warm-up (numba's compiled kernels load on first use), results discarded
        for rows in (8, 512):
            warm = [[event_of(m)] for m in indices[:rows]]
            sids = [(m.line, m.segment) for m in indices[:rows]]
            fold_many([bank_states[sid] for sid in sids], warm, [params] * rows, obs)

        scratch = Scratch()  # states copied out of a reused buffer, as the service's fold does
        dirty: dict = {}
        service_s = bank_s = 0.0
        freeze_s = 0.0  # as the service does every FREEZE_S (FilteringAdapter._freeze)
        gc.collect(1)
        gc.freeze()
        profiler = cProfile.Profile() if profile else None
        for batch, evs in zip(batches, prepared, strict=True):
            started = time.perf_counter()
            if profiler is not None:
                profiler.enable()
            done = node.handle_batch(batch, summarize=False)
            if profiler is not None:
                profiler.disable()
            service_s += time.perf_counter() - started
            if service_s - freeze_s >= FREEZE_S:
                started = time.perf_counter()
                gc.collect(1)
                gc.freeze()
                freeze_s = service_s = service_s + time.perf_counter() - started
            assert done.accepted == len(batch) and not done.rejected
            for sid in done.changed:
                dirty[sid] = None

            logs: dict = {}
            for e in evs:
                logs.setdefault((e.message.line, e.message.segment), []).append(e)
            started = time.perf_counter()
            folded = fold_many(
                [bank_states[sid] for sid in logs],
                list(logs.values()),
                [params] * len(logs),
                obs,
                scratch,
            )
            bank_s += time.perf_counter() - started
            bank_states.update(zip(logs, folded, strict=True))

        started = time.perf_counter()
        payloads = [encode(state) for state in tracker.states_of(dirty)]
        publish_s = time.perf_counter() - started
        same = all(
            np.array_equal(bank_states[sid].z, tracker.histories[sid].state.z)
            and np.array_equal(bank_states[sid].P, tracker.histories[sid].state.P)
            for sid in bank_states
        )
        stored = node.store.count_events()
        node.store.close()
        gc.unfreeze()

    rate, bank_rate = events / service_s, events / bank_s
    print(
        f"backlog  Ns={NS_SAMPLES}, {segments:,} segments, {events:,} OnboardIndex in time order, "
        f"batches of {BATCH}: handle_batch (decode, fold, SQLite commit) {rate:,.0f} events/s "
        f"(target >= 50,000); the fold alone (fold_many, same batches) {bank_rate:,.0f} events/s; "
        f"ratio {rate / bank_rate:.2f}; same bits: {same}; {stored:,} rows stored"
    )
    print(
        f"  then publishing the {len(payloads):,} dirty segments' newest states (summary + "
        f"encode): {publish_s:.1f} s = {len(payloads) / publish_s:,.0f} segments/s; backlog "
        f"and publication together {events / (service_s + publish_s):,.0f} events/s"
    )
    if profiler is not None:
        pstats.Stats(profiler).sort_stats("cumulative").print_stats(25)
        pstats.Stats(profiler).sort_stats("tottime").print_stats(20)


if __name__ == "__main__":
    args = [a for a in sys.argv[1:] if not a.startswith("--")]
    sizes = [int(a) for a in args] or [SEGMENTS, EVENTS]
    bench_backlog(*sizes, profile="--profile" in sys.argv)
