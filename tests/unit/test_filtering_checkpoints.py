"""Filtering checkpoints and lazily loaded logs: a restart from checkpoints, or a segment
whose log was dropped from memory, gives the bits of a full replay of the same events."""

from __future__ import annotations

import logging
import socket
import sqlite3
from dataclasses import replace

import msgspec
import numpy as np
import pytest

from schemas import OnboardIndex, TrcRecord, encode
from services.filtering import service as filtering_service
from services.filtering import store as store_module
from services.filtering import tracker as tracker_module
from services.filtering.columns import log_columns
from services.filtering.coordinator import PersistentTracker
from services.filtering.events import canonical_log, event_of, log_units
from services.filtering.fold import fold_many
from services.filtering.payloads import StoredIndex
from services.filtering.segment import publishable
from services.filtering.state import Filtered, pack_state, unpack_state
from services.filtering.store import Store
from tests.unit.test_filtering_tracker import (
    MODELS,
    MU,
    Z_PLUS,
    Z_WORN,
    assert_same_states,
    calibration,
    history,
    index,
    keyed,
    new_tracker,
    onboard_days,
    posterior,
    run,
    tamping,
    trc,
    unit_calibration,
)

SEGMENTS = ("s1", "s2", "s3", "s4")


class CountingLoader:
    """The store's loaders (events, columns), counting which segments' logs were read."""

    def __init__(self, node: PersistentTracker) -> None:
        self.node = node
        self.read: list[tuple[str, str]] = []

    def __call__(self, line: str, segment: str):
        self.read.append((line, segment))
        return self.node.segment_log(line, segment)

    def columns(self, line: str, segment: str):
        self.read.append((line, segment))
        return self.node.segment_columns(line, segment)


def node_on(db, **kw) -> PersistentTracker:
    return PersistentTracker(new_tracker(), Store(db), **kw)


def restarted(db) -> tuple[PersistentTracker, dict, CountingLoader]:
    node = node_on(db)
    loader = CountingLoader(node)
    node.tracker.histories.loader = loader
    node.tracker.histories.columns = loader.columns
    states = {sid: payload for sid, payload, _new in node.restore()}
    return node, states, loader


def on(msg, segment: str, **changes):
    return msgspec.structs.replace(msg, segment=segment, **changes)


def in_time_order(events):
    return sorted(events, key=lambda m: getattr(m, "t", getattr(m, "t_start", 0.0)))


def assert_restored(node: PersistentTracker, states: dict, reference) -> None:
    """The restored tracker equals ``reference`` (arrays, logs, SegmentState bytes), and
    the states the restart returns are the reference's, for every publishable segment."""
    want = {
        sid: encode(s) for sid in reference.histories if (s := reference.state_of(*sid)) is not None
    }
    assert states == want
    assert_same_states(reference, node.tracker)


def test_state_bytes_round_trip_exactly():
    rng = np.random.default_rng(0)
    for trc_t, nis, t1 in ((None, None, float("nan")), (5.0, 0.25, 7.0)):
        state = Filtered(
            rng.normal(size=(7, 2)),
            rng.normal(size=(7, 2, 2)),
            123.5,
            trc_t,
            4,
            nis,
            rng.normal(size=7),
            1.5,
            3.0,
            t1,
        )
        back = unpack_state(pack_state(state))
        for name in ("z", "P", "log_w"):
            assert getattr(back, name).tobytes() == getattr(state, name).tobytes()
        assert (back.t_s, back.last_trc_t, back.n_updates, back.nis, back.cusum) == (
            123.5,
            trc_t,
            4,
            nis,
            1.5,
        )
        assert back.cusum_t0 == 3.0 and np.array_equal([back.cusum_t1], [t1], equal_nan=True)
    with pytest.raises(ValueError):
        unpack_state(pack_state(state)[:-3])


def test_restart_from_checkpoints_folds_on_over_the_newer_events_only(tmp_path):
    events = in_time_order(history(np.random.default_rng(3), SEGMENTS))
    db = tmp_path / "f.sqlite"
    first = node_on(db)
    first.handle_batch([keyed(m) for m in [*MODELS, *events[:50]]])  # models: checkpointed
    first.handle_batch([keyed(m) for m in events[50:60]])
    assert first.checkpoint() > 0
    first.handle_batch([keyed(m) for m in events[60:70]])  # not checkpointed (no close)

    node, states, loader = restarted(db)
    reference, _ = run([*MODELS, *events[:70]])
    # replayed from their log's start: only the segments whose TRC record after the
    # checkpoint pruned their older events (a log of two events then)
    pruned = {("L1", m.segment) for m in events[60:70] if isinstance(m, TrcRecord)}
    assert pruned and sorted(loader.read) == sorted(pruned)
    assert node.tracker.histories.n_loaded == 0
    assert_restored(node, states, reference)

    # a clean stop checkpoints; the next restart restores every state as stored
    node.handle_batch([keyed(m) for m in events[70:]])
    node.close()
    again, states, loader = restarted(db)
    reference, _ = run([*MODELS, *events])
    assert loader.read == []
    assert_restored(again, states, reference)


def test_a_late_event_after_the_checkpoint_replays_its_segment(tmp_path):
    events = in_time_order(history(np.random.default_rng(4), SEGMENTS))
    late = next(m for m in events[:40] if m.segment == "s2" and type(m).__name__ == "OnboardIndex")
    early = [m for m in events[:40] if m is not late]
    db = tmp_path / "f.sqlite"
    first = node_on(db)
    first.handle_batch([keyed(m) for m in [*MODELS, *early]])
    first.checkpoint()
    first.handle_batch([keyed(m) for m in [late, *events[40:45]]])

    node, states, loader = restarted(db)
    assert set(loader.read) == {("L1", "s2")}
    assert_restored(node, states, run([*MODELS, *events[:45]])[0])


def test_a_duplicate_after_restart_is_refused(tmp_path):
    events = in_time_order(history(np.random.default_rng(5), SEGMENTS))
    db = tmp_path / "f.sqlite"
    first = node_on(db)
    first.handle_batch([keyed(m) for m in [*MODELS, *events[:50]]])
    first.close()
    node, _, _ = restarted(db)
    stored = node.store.count_events()
    done = node.handle_batch([keyed(m) for m in events[30:50]])  # all already stored
    assert done.accepted == 0 and done.states == () and node.store.count_events() == stored
    assert_same_states(run([*MODELS, *events[:50]])[0], node.tracker)


def test_models_changed_after_the_checkpoint_rerun_every_affected_segment(tmp_path):
    events = in_time_order(history(np.random.default_rng(6), SEGMENTS))
    db = tmp_path / "f.sqlite"
    first = node_on(db)
    first.handle_batch([keyed(m) for m in [*MODELS, *events]])
    first.checkpoint()
    first.handle(*keyed(calibration(2, 1.05)))  # stored, never checkpointed (handle())

    node, states, loader = restarted(db)
    assert sorted(loader.read) == [("L1", s) for s in SEGMENTS]
    assert_restored(node, states, run([calibration(2, 1.05), posterior(), *events])[0])


def test_missing_and_broken_checkpoints_replay_their_segments(tmp_path, caplog):
    events = in_time_order(history(np.random.default_rng(7), SEGMENTS))
    db = tmp_path / "f.sqlite"
    first = node_on(db)
    first.handle_batch([keyed(m) for m in [*MODELS, *events]])
    first.close()
    first.store.delete_checkpoint("L1", "s1")
    first.store._db.execute("UPDATE checkpoints SET state = x'00ff' WHERE segment = 's3'")

    with caplog.at_level(logging.WARNING):
        node, states, loader = restarted(db)
    assert "checkpoint of L1/s3 no longer decodes" in caplog.text
    assert sorted(loader.read) == [("L1", "s1"), ("L1", "s3")]
    assert_restored(node, states, run([*MODELS, *events])[0])
    node.close()  # the replayed segments get their checkpoints back
    assert node.store._db.execute("SELECT COUNT(*) FROM checkpoints").fetchone()[0] == 4


def test_a_pruning_trc_record_or_a_superseding_report_invalidates_the_checkpoint(tmp_path):
    db = tmp_path / "f.sqlite"
    first = node_on(db)
    first.handle_batch([keyed(m) for m in [*MODELS, trc(0.0), index(3.0, 2.2, 2.0)]])
    first.handle_batch([keyed(m) for m in [index(9.0, 2.3, 2.1), trc(0.0, segment="s2")]])
    first.checkpoint()
    rows = "SELECT segment FROM checkpoints ORDER BY segment"
    assert [r[0] for r in first.store._db.execute(rows)] == ["s1", "s2"]
    tail = [trc(10.0, 2.0, 1.9), index(12.0, 2.1, 2.0), tamping(5.0, 8.0, segment="s2")]
    first.handle_batch([keyed(m) for m in tail])
    assert [r[0] for r in first.store._db.execute(rows)] == ["s2"]  # s1's events pruned

    node, states, loader = restarted(db)
    assert loader.read == [("L1", "s1")]
    assert_restored(node, states, run([*MODELS, trc(0.0), trc(0.0, segment="s2"), *tail])[0])


def test_a_dropped_log_is_read_again_when_needed(tmp_path):
    """LRU bound of the loaded logs: an evicted segment steps, refuses duplicates and
    re-runs on a model change exactly as one held in memory."""
    events = in_time_order(history(np.random.default_rng(8), SEGMENTS))
    node = node_on(tmp_path / "f.sqlite", max_loaded=1)
    node.handle_batch([keyed(m) for m in [*MODELS, *events[:60]]])
    node.checkpoint()
    assert node.tracker.histories.n_loaded == 1 and len(node.tracker.histories) == 4
    assert node.handle_batch([keyed(events[10])]).accepted == 0  # duplicate of a dropped one
    node.handle_batch([keyed(m) for m in events[60:]])
    node.checkpoint()
    assert_same_states(run([*MODELS, *events])[0], node.tracker)


def test_a_model_change_reruns_in_chunks_without_keeping_the_logs(tmp_path, monkeypatch):
    monkeypatch.setattr(tracker_module, "RERUN_CHUNK", 3)
    events = in_time_order(history(np.random.default_rng(9), SEGMENTS))
    node = node_on(tmp_path / "f.sqlite", max_loaded=0)
    node.handle_batch([keyed(m) for m in [*MODELS, *events]])
    node.checkpoint()
    assert node.tracker.histories.n_loaded == 0
    done = node.handle_batch([keyed(calibration(2, 1.1)), keyed(posterior(version=2, seed=3))])
    assert done.accepted == 2 and len(done.states) == 4
    assert node.tracker.histories.n_loaded == 0
    reference = run([calibration(2, 1.1), posterior(version=2, seed=3), *events])[0]
    assert {(s.line, s.segment): encode(s) for s in done.states} == {
        sid: encode(reference.state_of(*sid)) for sid in reference.histories
    }
    assert_same_states(reference, node.tracker)


def test_a_restart_republishes_only_what_may_not_have_been_published(tmp_path):
    """A checkpoint's states were published once the next one is written (the owner
    publishes a batch before the next), or at a clean stop; the rest is published again."""
    db = tmp_path / "f.sqlite"
    first = node_on(db)
    first.handle_batch([keyed(m) for m in [*MODELS, trc(0.0), trc(0.0, segment="s2")]])
    first.checkpoint()  # generation 2 (the models' was 1): s1, s2
    first.handle_batch([keyed(index(3.0, 2.2, 2.0, segment="s2"))])
    first.checkpoint()  # generation 3: s2; generation 2 is now known published
    first.handle_batch([keyed(trc(0.0, segment="s3"))])  # committed, no checkpoint

    def unpublished(db) -> dict:
        node = node_on(db)
        return node, {sid[1]: new for sid, _payload, new in node.restore()}

    node, flags = unpublished(db)
    assert flags == {"s1": False, "s2": True, "s3": True}
    # killed again before publishing anything: the same ones are still to publish
    assert unpublished(db)[1] == {"s1": False, "s2": True, "s3": True}
    node.close()  # a clean stop: everything restored was published at start
    assert unpublished(db)[1] == {"s1": False, "s2": False, "s3": False}


def test_a_due_checkpoint_is_written_a_slice_per_batch(tmp_path):
    """Live, the worker writes at most CHECKPOINT_SLICE segments per batch (no stall on one
    big write); the period restarts once every changed segment is written, and a restart
    from those slices is the full replay."""
    events = in_time_order(history(np.random.default_rng(5), SEGMENTS))
    db = tmp_path / "f.sqlite"
    node = node_on(db)
    node.handle_batch([keyed(m) for m in [*MODELS, *events[:40]]])  # models: all written
    node.handle_batch([keyed(m) for m in events[40:80]])
    changed = len(node.tracker.histories.dirty)
    assert changed == len(SEGMENTS)
    written = [node.checkpoint(limit=1) for _ in range(changed + 1)]
    assert written == [1] * changed + [0]
    assert not node.tracker.histories.dirty
    restored, states, loader = restarted(db)
    reference, _ = run([*MODELS, *events[:80]])
    assert loader.read == []  # every segment from its checkpoint
    assert_restored(restored, states, reference)


def test_the_generation_goes_on_from_a_file_written_before_it_was_kept(tmp_path):
    """The newest generation is kept in checkpoint_meta (no scan of the checkpoints per
    slice); a file without that row goes on from its newest checkpoint row."""
    db = tmp_path / "f.sqlite"
    store = Store(db)
    assert store.put_checkpoints([]) == 1
    row = ("L1", "s1", None, None, "", "", None, None)
    assert store.put_checkpoints([row]) == 2
    store._db.execute("DELETE FROM checkpoint_meta WHERE name = 'gen'")  # an older file
    assert store.put_checkpoints([row, ("L1", "s2", *row[2:])]) == 3
    assert store.put_checkpoints([]) == 4
    assert store.published_gen() == 3
    store.set_published()
    assert store.published_gen() == 4
    store.close()


@pytest.mark.parametrize("own_process", [False, True])
def test_the_service_freezes_what_survives_only_in_its_own_process(
    own_process, tmp_path, monkeypatch
):
    """The worker moves what survived into the GC's permanent generation every FREEZE_S
    (no full collection walks the logs and states again) and collects the young objects
    itself (no automatic collection in between), only with ``freeze_gc``."""
    import gc

    from services.filtering.service import FilteringAdapter

    freezes = []  # the calls of gc.freeze (the frozen count also drops as frozen objects die)
    freeze = gc.freeze
    monkeypatch.setattr(gc, "freeze", lambda: (freezes.append(1), freeze())[1])
    node = node_on(tmp_path / "f.sqlite")
    adapter = FilteringAdapter(None, node, "**", freeze_gc=own_process)  # type: ignore[arg-type]
    before = gc.get_freeze_count()
    try:
        adapter._freeze()
        assert (gc.get_freeze_count() > before) == own_process
        assert gc.isenabled() != own_process
        assert len(freezes) == own_process
        adapter._freeze()  # within FREEZE_S of the last: nothing more
        assert len(freezes) == own_process
    finally:
        gc.unfreeze()  # this is pytest's process
        gc.enable()
        node.store.close()


def test_an_idle_instance_writes_its_due_checkpoint_without_waiting_for_a_batch(
    tmp_path, monkeypatch
):
    """Live, a due checkpoint goes a slice per batch; when traffic stops the worker's idle
    hook writes the rest, so a kill of an idle instance replays nothing."""
    from services.filtering import coordinator
    from services.filtering.service import FilteringAdapter

    monkeypatch.setattr(coordinator, "CHECKPOINT_SLICE", 1)

    events = in_time_order(history(np.random.default_rng(6), SEGMENTS))
    db = tmp_path / "f.sqlite"
    node = node_on(db, checkpoint_s=0.0)
    node.handle_batch([keyed(m) for m in [*MODELS, *events[:40]]])
    node.handle_batch([keyed(m) for m in events[40:80]])  # wrote its first slice
    assert node.tracker.histories.dirty  # the rest waits for a batch
    adapter = FilteringAdapter(None, node, "**")  # type: ignore[arg-type]
    adapter._idle()
    assert not node.tracker.histories.dirty
    node.store.close()  # killed: no checkpoint at the stop
    _restored, _states, loader = restarted(db)
    assert loader.read == []  # every segment from its checkpoint


def test_the_write_ahead_log_is_copied_back_by_a_thread_not_by_the_commits(tmp_path):
    """The committing connection never checkpoints (no sync inside a COMMIT); the store's
    own thread does, so the log does not grow past what was written since its last run."""
    store = Store(tmp_path / "f.sqlite", wal_checkpoint_s=0.01)
    wal = tmp_path / "f.sqlite-wal"
    try:
        assert store._db.execute("PRAGMA wal_autocheckpoint").fetchone()[0] == 0
        rows = [("L1", f"s{k}", "index", "k", ("index", k), 0.0, bytes(2000)) for k in range(100)]
        sizes = []
        for batch in range(20):  # ~4 MB in all, 200 KB a batch
            with store.transaction():
                store.add_events([(*r[:4], (*r[4], batch), *r[5:]) for r in rows])
            store.wal_checkpoints.ran.clear()
            assert store.wal_checkpoints.ran.wait(10), "no WAL checkpoint ran"
            sizes.append(wal.stat().st_size)
        assert max(sizes[5:]) < 1_500_000  # reused from its start, not grown to ~4 MB
        assert store.count_events() == 2000
    finally:
        store.close()
    assert not store.wal_checkpoints._thread.is_alive()


def test_stored_indices_decode_without_the_message_checks_but_not_into_the_fold(tmp_path, caplog):
    """A stored index decodes into the unchecked twin (same fields as the message); a row the
    fold cannot use (index not positive, unknown schema version) is skipped with a warning,
    never folded, and the segment's other events replay as before."""
    assert msgspec.structs.fields(StoredIndex) == msgspec.structs.fields(OnboardIndex)
    db = tmp_path / "f.sqlite"
    first = node_on(db, max_loaded=0)
    kept = [trc(0.0), index(3.0, 2.2, 2.0), index(6.0, 2.3, 2.1)]
    first.handle_batch([keyed(m) for m in [*MODELS, *kept]])
    first.close()
    bad = {9.0: {"top6_mm": -1.0}, 12.0: {"v": 99}}
    for day, change in bad.items():
        msg = index(day, 2.0, 2.0)
        first.store.add_event(
            line="L1",
            segment="s1",
            kind="index",
            key=keyed(msg)[0],
            identity=("index", msg.train, msg.unit, msg.t),
            t=msg.t,
            payload=msgspec.msgpack.encode(msgspec.to_builtins(msg) | change),
        )
    first.store.delete_checkpoint("L1", "s1")

    with caplog.at_level(logging.WARNING):
        node, states, _loader = restarted(db)
    assert caplog.text.count("no longer decodes") == 2
    assert_restored(node, states, run([*MODELS, *kept])[0])


def test_a_unit_calibration_reruns_and_invalidates_only_the_segments_with_its_indices(tmp_path):
    """A unit's own calibration concerns the segments whose logs hold its indices: only
    their logs are read and re-run, and every other segment's checkpoint stays valid, so a
    restart after it does not replay them (at national scale: seconds instead of minutes)."""
    events = []
    for k, seg in enumerate(SEGMENTS):
        train = "T1" if k < 2 else "T2"  # s1, s2 read by T1's unit; s3, s4 by T2's
        events.append(trc(0.0, segment=seg))
        for week in range(1, 6):
            events.append(index(7.0 * week + 0.1 * k, 2.0, 1.8, segment=seg, train=train))
    db = tmp_path / "f.sqlite"
    first = node_on(db, max_loaded=0)
    first.handle_batch([keyed(m) for m in [*MODELS, *events]])
    first.checkpoint()
    loader = CountingLoader(first)
    first.tracker.histories.loader = loader
    first.tracker.histories.columns = loader.columns
    done = first.handle_batch([keyed(unit_calibration("T1", "u1"))])
    assert sorted((s.line, s.segment) for s in done.states) == [("L1", "s1"), ("L1", "s2")]
    assert sorted(loader.read) == [("L1", "s1"), ("L1", "s2")]
    first.close()

    node, states, loader = restarted(db)
    assert loader.read == []  # every checkpoint still valid
    assert_restored(node, states, run([*MODELS, unit_calibration("T1", "u1"), *events])[0])
    node.close()

    again, _states, loader = restarted(db)  # the units come from the checkpoints
    again.handle_batch([keyed(unit_calibration("T2", "u1"))])
    assert sorted(loader.read) == [("L1", "s3"), ("L1", "s4")]
    reference = [*MODELS, unit_calibration("T1", "u1"), unit_calibration("T2", "u1"), *events]
    assert_same_states(run(reference)[0], again.tracker)


def test_a_log_read_as_columns_folds_to_the_bits_of_its_events(tmp_path):
    """A re-run reads a resting log as columns (no Event per index): the same fold, bit for
    bit, the same end and units; a log whose order needs the identities is read as events."""
    rng = np.random.default_rng(5)
    events = []
    for k, seg in enumerate(SEGMENTS):
        if seg != "s4":  # s4: no TRC record, started by its tamping
            events.append(trc(0.0, 3.0 + k, 2.5, segment=seg))
        for week in range(1, 12):
            top6, align10 = np.exp(rng.normal([0.8, 0.5], 0.1)).tolist()
            train = "T2" if week % 3 == 0 else "T1"
            events.append(index(7.0 * week + 0.5 * k, top6, align10, segment=seg, train=train))
        events.append(tamping(30.0, segment=seg) if k % 2 else tamping(29.0, 33.0, segment=seg))
    events.append(index(14.0, 2.0, 2.0, segment="s1", train="T2"))  # ties s1's T1 index
    node = node_on(tmp_path / "f.sqlite", max_loaded=0)
    own = unit_calibration("T2", "u1")  # its indices are read with their own model
    node.handle_batch([keyed(m) for m in [*MODELS, own, *in_time_order(events)]])
    models = node.tracker.models
    params = models.params[models.group_for("L1", "s2")]
    uncalibrated = replace(models, calibration=None, observation=None)  # T1 has no model then
    for seg in SEGMENTS:
        read = node.segment_columns("L1", seg)
        log, trc_t = node.segment_log("L1", seg)
        if seg == "s1":
            assert read is None
            continue
        columns, columns_trc_t = read
        assert columns_trc_t == trc_t and len(columns) == len(log) == 12 + (seg != "s4")
        assert columns.last_order == log[-1].order
        assert log_units(columns) == log_units(log) == {("T1", "u1"), ("T2", "u1")}
        assert publishable(columns, models) and publishable(log, models)
        assert publishable(columns, uncalibrated) == publishable(log, uncalibrated) is False
        a, b = fold_many([None, None], [columns, log], [params, params], models)
        for name in ("z", "P", "log_w"):
            assert getattr(a, name).tobytes() == getattr(b, name).tobytes()
        assert (a.t_s, a.n_updates, a.nis, a.cusum, a.last_trc_t) == (
            b.t_s,
            b.n_updates,
            b.nis,
            b.cusum,
            b.last_trc_t,
        )
        fleet_only = fold_many([None], [columns], [params], models.observation)[0]
        assert not np.array_equal(fleet_only.z, a.z)  # the unit's own model was used

    # an index older than the latest TRC record is left out, as canonical_log does
    old, new = index(3.0, 2.0, 2.0, segment="s9"), index(9.0, 2.1, 1.9, segment="s9")
    record = trc(5.0, segment="s9")
    columns, trc_t = log_columns([encode(old), encode(new)], [event_of(record)])
    log, log_trc_t = canonical_log([event_of(m) for m in (old, new, record)])
    assert trc_t == log_trc_t == record.t and len(columns) == len(log) == 2
    assert columns.times.tolist() == [e.t_s for e in log]
    assert columns.last_order == log[-1].order and columns.unit_names == (("T1", "u1"),)


def test_a_model_change_reads_each_log_from_its_cached_columns(tmp_path, monkeypatch):
    """A re-run caches each log it reads as columns (``log_columns``); the next one reads
    that row and the events stored after it (in-order indices, a new unit, a tamping),
    which gives the bits of a replay of every event. A late index, a pruning TRC record
    and a row that no longer decodes send their segment back to its stored events."""
    rng = np.random.default_rng(10)
    segments = ("s1", "s2", "s3", "s4", "s5")
    events = []
    for seg in segments:
        events.append(trc(0.0, segment=seg))
        for day in range(1, 40, 3):
            top6, align10 = np.exp(rng.normal([0.8, 0.5], 0.1)).tolist()
            events.append(index(day + 0.1, top6, align10, segment=seg))
    own = unit_calibration("T2", "u1")  # T2's indices are read with their own model
    node = node_on(tmp_path / "f.sqlite", max_loaded=0)
    node.handle_batch([keyed(m) for m in [*MODELS, own, *in_time_order(events)]])
    node.checkpoint()
    full_reads: list[str] = []
    payloads = node.store.segment_index_payloads

    def counted(line, segment):
        full_reads.append(segment)
        return payloads(line, segment)

    monkeypatch.setattr(node.store, "segment_index_payloads", counted)
    cached = "SELECT segment, seq FROM log_columns ORDER BY segment"

    def cached_seqs():
        return dict(node.store._db.execute(cached).fetchall())

    node.handle_batch([keyed(calibration(2, 1.1))])
    assert sorted(full_reads) == list(segments)
    assert cached_seqs() == {seg: node.store.segment_last_seq("L1", seg) for seg in segments}

    newer = [
        index(41.0, 2.4, 1.7, segment="s1", train="T2"),  # in order, a unit new to s1
        index(42.0, 2.5, 1.8, segment="s1"),
        tamping(43.0, segment="s2"),  # in order
        index(44.0, 2.2, 1.9, segment="s2", train="T2"),
        index(20.5, 2.2, 1.9, segment="s3"),  # late
        trc(45.0, 2.0, 1.8, segment="s4"),  # prunes s4's log: its row goes
    ]
    node.handle_batch([keyed(m) for m in newer])
    assert "s4" not in cached_seqs()
    node.store._db.execute("UPDATE log_columns SET columns = x'00ff' WHERE segment = 's5'")
    node.checkpoint()
    full_reads.clear()
    done = node.handle_batch([keyed(calibration(3, 0.95))])
    assert sorted(full_reads) == ["s3", "s4", "s5"]
    reference = run([*MODELS, own, *in_time_order(events), *newer, calibration(3, 0.95)])[0]
    assert {(s.line, s.segment): encode(s) for s in done.states} == {
        sid: encode(reference.state_of(*sid)) for sid in reference.histories
    }
    assert_same_states(reference, node.tracker)
    assert cached_seqs() == {seg: node.store.segment_last_seq("L1", seg) for seg in segments}

    full_reads.clear()  # every row current: the next change reads no stored event
    node.handle_batch([keyed(calibration(4, 1.02))])
    assert full_reads == []
    node.close()


def test_in_order_indices_on_resting_segments_fold_without_reading_their_logs(tmp_path):
    """After a restart every segment rests (state, no log). A batch of indices after each
    log's end folds them onto the resting states and leaves the logs unread; one whose
    CUSUM reaches the threshold inside the batch reads its log there and detects the
    tamping; a late index and a duplicate read theirs. Bits of one message at a time."""
    rng = np.random.default_rng(8)
    tamped = onboard_days(rng, np.arange(1, 90), Z_WORN, MU, t_tamp=50.3, z_plus=Z_PLUS)
    calm = [on(m, "s2") for m in onboard_days(rng, np.arange(1, 90), Z_WORN, MU)]
    first_part = [trc(0.0, *np.exp(Z_WORN).tolist()), trc(0.0, 4.0, 3.0, segment="s2")]
    first_part += [*tamped[:40], *calm[:40]]
    db = tmp_path / "f.sqlite"
    first = node_on(db)
    first.handle_batch([keyed(m) for m in [*MODELS, *first_part]])
    first.close()

    node, _, loader = restarted(db)
    done = node.handle_batch([keyed(m) for m in calm[40:60]])  # in order: no log read
    assert done.accepted == 20 and not done.rejected and len(done.states) == 1
    assert loader.read == [] and node.tracker.histories.n_loaded == 0

    done = node.handle_batch([keyed(m) for m in [*tamped[40:], *calm[60:]]])
    assert done.accepted == len(tamped[40:]) + len(calm[60:]) and len(done.detected) == 1
    assert loader.read == [("L1", "s1")]  # the detection's, once
    late, duplicate = on(calm[30], "s2", t=calm[30].t + 3600.0), calm[50]
    done = node.handle_batch([keyed(m) for m in [late, duplicate]])
    assert done.accepted == 1 and len(done.rejected) == 0  # a duplicate is no error
    assert ("L1", "s2") in loader.read

    one, _ = run([*MODELS, *first_part, *calm[40:60], *tamped[40:], *calm[60:], late])
    assert_same_states(one, node.tracker)
    detected = [m for sid in one.histories for m in one.histories[sid].log if m.kind == 0]
    assert len(detected) == 1


OLD_EVENTS = """CREATE TABLE events_old (
    seq INTEGER PRIMARY KEY AUTOINCREMENT, line TEXT NOT NULL, segment TEXT NOT NULL,
    kind TEXT NOT NULL, key TEXT NOT NULL, identity TEXT NOT NULL, t REAL NOT NULL,
    payload BLOB NOT NULL, UNIQUE (line, segment, identity))"""


def test_a_file_with_unique_identities_is_migrated_keeping_every_row_seq_and_checkpoint(tmp_path):
    """A store written before the events lost their UNIQUE constraint: opened, its events
    are the same rows with the same seq, the sequence goes on after the largest seq ever
    given (not the largest left), its checkpoints still restore without a replay, and the
    triggers that invalidate them are there again."""
    events = in_time_order(history(np.random.default_rng(5), SEGMENTS))
    db = tmp_path / "f.sqlite"
    first = node_on(db)
    first.handle_batch([keyed(m) for m in [*MODELS, *events[:60]]])
    first.close()
    first.store.close()
    raw = sqlite3.connect(db, isolation_level=None)  # rewritten as an older file
    raw.executescript(
        f"BEGIN; {OLD_EVENTS}; INSERT INTO events_old SELECT * FROM events ORDER BY seq;"
        " DROP TABLE events; ALTER TABLE events_old RENAME TO events;"
        " UPDATE sqlite_sequence SET seq = seq + 7 WHERE name = 'events'; COMMIT;"
    )
    raw.executescript(store_module._SCHEMA)  # the index and triggers an older file had
    assert any(
        r[1].startswith("sqlite_autoindex") for r in raw.execute("PRAGMA index_list(events)")
    )
    rows = raw.execute("SELECT * FROM events ORDER BY seq").fetchall()
    checkpoints = raw.execute("SELECT * FROM checkpoints ORDER BY line, segment").fetchall()
    (sequence,) = raw.execute("SELECT seq FROM sqlite_sequence WHERE name = 'events'").fetchone()
    raw.close()
    assert sequence == rows[-1][0] + 7 and checkpoints

    told: list[int] = []
    Store(db, migrating=told.append).close()  # opening migrates, and says how much first
    assert told == [len(rows)]
    node, states, loader = restarted(db)
    store = node.store._db
    assert not any(
        r[1].startswith("sqlite_autoindex") for r in store.execute("PRAGMA index_list(events)")
    )
    assert store.execute("SELECT * FROM events ORDER BY seq").fetchall() == rows
    assert (
        store.execute("SELECT * FROM checkpoints ORDER BY line, segment").fetchall() == checkpoints
    )
    triggers = {
        r[0] for r in store.execute("SELECT name FROM sqlite_master WHERE type = 'trigger'")
    }
    assert triggers == {
        "events_deleted",
        "events_updated",
        "events_deleted_columns",
        "events_updated_columns",
    }
    assert loader.read == []  # every segment from its checkpoint
    assert_restored(node, states, run([*MODELS, *events[:60]])[0])

    assert store.execute("SELECT seq FROM sqlite_sequence WHERE name = 'events'").fetchall() == [
        (sequence,)
    ]
    node.handle_batch([keyed(m) for m in events[60:]])
    given = "SELECT COUNT(*) FROM events WHERE seq > ? AND seq <= ?"
    assert store.execute(given, (rows[-1][0], sequence)).fetchone() == (0,)  # none twice
    assert store.execute(given, (sequence, sequence + len(events))).fetchone()[0] > 0
    assert_same_states(run([*MODELS, *events])[0], node.tracker)
    node.store.close()


def test_a_migration_asks_systemd_for_the_start_time_it_needs(tmp_path, monkeypatch):
    """Run by systemd (``NOTIFY_SOCKET``), the service extends its start timeout by the
    time a migration of that many events may take, before it starts."""
    path = tmp_path / "notify"
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as sock:
        sock.bind(str(path))
        sock.settimeout(10)
        monkeypatch.setenv("NOTIFY_SOCKET", str(path))
        filtering_service.extend_start_timeout(12_100_000)
        message = sock.recv(256).decode()
    seconds = 60.0 + 12_100_000 * filtering_service.MIGRATE_S_PER_EVENT
    assert message == f"EXTEND_TIMEOUT_USEC={int(seconds * 1e6)}"
    assert seconds > 3 * 87.4  # the migration of 12.1 M events measured, with margin


def _resting_arrays(tracker) -> dict:
    return {
        sid: (state.z.copy(), state.P.copy(), state.log_w.copy(), state.t_s, state.cusum)
        for sid in tracker.histories
        if (state := tracker.histories.resting(sid).state) is not None
    }


def test_resting_states_live_in_the_bank_fold_there_and_change_only_when_the_batch_does(
    tmp_path, monkeypatch
):
    """Resting states are rows of the histories' bank: a batch of in-order indices folds
    each from its row into a free one, which the segment then rests in, its old row given
    back (the bits of one message at a time; no row lost); a state read out
    (``resting``) is a copy that a later fold does not touch; a batch that fails after the
    fold leaves every segment in its row with its state, and gives the rows it took back."""
    rng = np.random.default_rng(9)
    days = {
        s: [on(m, s) for m in onboard_days(rng, np.arange(1, 40), Z_WORN, MU)] for s in SEGMENTS
    }
    first_part = [trc(0.0, 4.0, 3.0, segment=s) for s in SEGMENTS]
    first_part += in_time_order([m for s in SEGMENTS for m in days[s][:20]])
    db = tmp_path / "f.sqlite"
    first = node_on(db)
    first.handle_batch([keyed(m) for m in [*MODELS, *first_part]])
    first.close()
    first.store.close()

    node, _, loader = restarted(db)
    histories = node.tracker.histories
    (bank,) = histories._banks.values()

    def rows() -> dict:
        got = {sid: histories.resting_entry(sid).state for sid in histories}
        assert len({r.row for r in got.values()}) == len(SEGMENTS)  # one each
        assert len(bank.free) + len(SEGMENTS) == len(bank.banks.t_s)  # and none lost
        return got

    before_rows = rows()
    read_out = histories.resting(("L1", "s1")).state
    kept = read_out.z.copy()

    second = in_time_order([m for s in SEGMENTS for m in days[s][20:30]])
    done = node.handle_batch([keyed(m) for m in second])
    assert done.accepted == len(second) and loader.read == [] and histories.n_loaded == 0
    assert rows() != before_rows  # each in the row its fold went to
    assert np.array_equal(read_out.z, kept)  # the copy read out did not move
    one, _ = run([*MODELS, *first_part, *second])
    assert_same_states(one, node.tracker)  # (reads every log: loaded)
    histories.trim(0)  # all resting again

    before_rows = rows()
    before = _resting_arrays(node.tracker)
    third = in_time_order([m for s in SEGMENTS for m in days[s][30:]])

    def broken(*_a, **_k):
        raise RuntimeError("summaries failed")

    monkeypatch.setattr(node.tracker, "segment_states", broken)
    decoded = [msgspec.msgpack.decode(encode(m), type=OnboardIndex) for m in third]
    with pytest.raises(RuntimeError):
        node.tracker.step_events(decoded)
    assert rows() == before_rows and histories.n_loaded == 0
    after = _resting_arrays(node.tracker)
    assert after.keys() == before.keys()
    for sid, (z, P, log_w, t_s, cusum) in before.items():
        az, aP, alog_w, at_s, acusum = after[sid]
        assert np.array_equal(z, az) and np.array_equal(P, aP) and np.array_equal(log_w, alog_w)
        assert (t_s, cusum) == (at_s, acusum)
