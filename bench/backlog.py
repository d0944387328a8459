"""Backlog throughput of one filtering instance, in process (target: >= 50,000
events/s per instance with a backlog, docs/performance.md).

Workload: ``SEGMENTS`` segments at Ns = 200, each with a TRC record, then ``EVENTS``
OnboardIndex in time order on random segments (a backfill, a consumer catching up), as
``(key, payload)`` in batches of the service's ``BATCH``, through
:meth:`PersistentTracker.handle_batch` on a real SQLite file (decode, fold, commit in one
transaction per batch) with ``summarize=False``, as the service does under a backlog: the
changed segments are marked dirty and published later. The final publication of every
dirty segment (summary and encoded SegmentState, what the service puts once the backlog is
gone) is timed separately. The garbage collector's generations are frozen after the setup and
every ``FREEZE_S`` of the loop, with no automatic collection in between, as the service
does (a full collection otherwise walks every segment's log and state: a quarter of the
time; the young generations' collections 10-18 %).

Baseline in the same run: the fold alone (:func:`fold_many` on the same batches, each
segment's events of a batch from its state, the events prepared beforehand, the states
copied in and out of a reused :class:`Scratch` as the service's fold does), i.e. the
filter bank's maths without messages or SQLite, run after the backlog: each batch commits
in the background while the next one folds, as the service does under a backlog
(``handle_batch(background=True)``), so the backlog's time runs from its first batch to
the end of its last commit, with nothing else in between.

``--history DAYS``: the segments instead come from a store of ``DAYS`` × 2 indices each
(bench.restart's), and the instance is restarted from its checkpoints before the backlog,
so that every segment rests (its state in memory, its log in the store): a consumer
catching up after a restart, on logs of a national network's length.

Run: ``.venv/bin/python -m bench.backlog [segments events] [--history DAYS] [--profile]``.
"""

from __future__ import annotations

import argparse
import cProfile
import gc
import pstats
import tempfile
import time
from pathlib import Path

import numpy as np

from bench.restart import build_store
from schemas import DAY_S, OnboardIndex, TrcRecord, encode, keys
from services.filtering.banks import Scratch
from services.filtering.coordinator import PersistentTracker
from services.filtering.events import event_of
from services.filtering.fold import fold_many
from services.filtering.service import BATCH, FREEZE_S
from services.filtering.store import Store
from services.filtering.testing import example_models
from services.filtering.tracker import Tracker
from services.limits import load_limits

NS_SAMPLES, SEGMENTS, EVENTS = 200, 20_000, 4 * BATCH  # four of the service's batches
T0 = 1_767_225_600.0
NS = "tfbench"


def _segment(k: int) -> str:
    return f"s{k:05d}"


def _indices(
    rng: np.random.Generator, sids: list[tuple[str, str]], n: int, t0: float
) -> list[OnboardIndex]:
    """``n`` indices in time order (one every 10 s of event time from ``t0``) on random
    segments of ``sids``."""
    where = rng.integers(len(sids), size=n).tolist()
    y = np.exp(rng.normal([0.8, 0.5], 0.1, (n, 2))).tolist()
    return [
        OnboardIndex(
            line=sids[where[i]][0],
            segment=sids[where[i]][1],
            train="T1",
            unit="u1",
            t=t0 + 10.0 * i,
            top6_mm=y[i][0],
            align10_mm=y[i][1],
            speed_mps=30.0,
            coverage=1.0,
        )
        for i in range(n)
    ]


def _fresh_segments(node: PersistentTracker, models, segments: int) -> list[tuple[str, str]]:
    """Every segment with a TRC record and nothing else, in memory (the default case)."""
    node.handle_batch([(keys.key_of(NS, m), encode(m)) for m in models])
    trcs = [
        TrcRecord(line="L1", segment=_segment(k), t=T0, top6_mm=3.0, align10_mm=2.4, run_id="r0")
        for k in range(segments)
    ]
    for i in range(0, segments, BATCH):
        node.handle_batch([(keys.key_of(NS, m), encode(m)) for m in trcs[i : i + BATCH]])
    return [("L1", _segment(k)) for k in range(segments)]


def _restarted_on_history(db: Path, models, segments: int, days: int) -> PersistentTracker:
    """A store of ``segments`` × (a TRC record, ``2 days`` indices) (bench.restart's), a
    first start (full replay) and a clean stop, then the instance restarted from its
    checkpoints: every segment resting (its state in memory, its log in the store)."""
    build_store(db, segments, days, NS, models)
    limits = load_limits()
    first = PersistentTracker(Tracker(limits.for_line, limits.levels), Store(db))
    first.restore()
    first.close()
    first.store.close()
    node = PersistentTracker(Tracker(limits.for_line, limits.levels), Store(db))
    node.restore()
    return node


def bench_backlog(
    segments: int = SEGMENTS, events: int = EVENTS, profile: bool = False, history: int = 0
) -> None:
    rng = np.random.default_rng(16)
    models = example_models(NS_SAMPLES, seed=3)
    limits = load_limits()

    with tempfile.TemporaryDirectory() as tmp:
        db = Path(tmp) / "b.db"
        if history:
            node = _restarted_on_history(db, models, segments, history)
            sids = list(node.tracker.histories)
            t0 = T0 + (history + 1) * DAY_S
        else:
            node = PersistentTracker(Tracker(limits.for_line, limits.levels), Store(db))
            sids = _fresh_segments(node, models, segments)
            t0 = T0 + 3600.0
        indices = _indices(rng, sids, events, t0)
        items = [(keys.key_of(NS, m), encode(m)) for m in indices]
        batches = [items[i : i + BATCH] for i in range(0, len(items), BATCH)]
        prepared = [[event_of(m) for m in indices[i : i + BATCH]] for i in range(0, events, BATCH)]
        tracker = node.tracker
        params, obs = tracker.models.params["net"], tracker.models.observation
        bank_states = {sid: tracker.histories.resting(sid).state for sid in tracker.histories}
        resting = len(sids) - tracker.histories.n_loaded
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
        gc.disable()  # the young objects collected every FREEZE_S only, as the service does
        profiler = cProfile.Profile() if profile else None
        for batch in batches:
            started = time.perf_counter()
            if profiler is not None:
                profiler.enable()
            done = node.handle_batch(batch, summarize=False, background=True)
            if profiler is not None:
                profiler.disable()
            service_s += time.perf_counter() - started
            if service_s - freeze_s >= FREEZE_S:
                started = time.perf_counter()
                gc.collect(1)
                gc.freeze()
                freeze_s = service_s = service_s + time.perf_counter() - started
            assert done.accepted == len(batch) and not done.rejected
            started = time.perf_counter()
            for sid in done.changed:
                dirty[sid] = None
            service_s += time.perf_counter() - started
        started = time.perf_counter()
        node.store.sync()  # the last batch's commit
        service_s += time.perf_counter() - started

        for evs in prepared:
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
        gc.enable()

    rate, bank_rate = events / service_s, events / bank_s
    if history:
        print(
            f"backlog on a restarted instance: {segments:,} segments each with a log of "
            f"{2 * history + 1} events in the store, {resting:,} of them resting at the start"
        )
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


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("segments", type=int, nargs="?", default=SEGMENTS)
    parser.add_argument("events", type=int, nargs="?", default=EVENTS)
    parser.add_argument("--profile", action="store_true", help="cProfile the service's part")
    parser.add_argument(
        "--history",
        type=int,
        default=0,
        metavar="DAYS",
        help="segments with DAYS x 2 stored indices each, the instance restarted from its "
        "checkpoints (every segment resting) before the backlog",
    )
    args = parser.parse_args(argv)
    bench_backlog(args.segments, args.events, args.profile, args.history)


if __name__ == "__main__":
    main()
