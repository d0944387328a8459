"""The filtering service's publication rule on a real runtime, store and router:
under a backlog the changed segments wait as dirty (a batch's until its commit in the
background is done) and the oldest are published first;
once the backlog is gone every one is published with the state of its last event."""

from __future__ import annotations

import threading

import zenoh

from schemas import DAY_S, OnboardIndex, SegmentState, TrcRecord, decode, encode, keys
from services.filtering import service
from services.filtering.coordinator import PersistentTracker
from services.filtering.store import Store
from services.filtering.testing import example_models
from services.filtering.tracker import Tracker
from services.limits import load_limits
from services.runtime.inbox import Inbox
from services.runtime.service import ServiceRuntime

T0 = 1_767_225_600.0
LIMITS = load_limits()
SEGMENTS = [f"s{k:02d}" for k in range(20)]


def stream(passes: int = 3) -> list:
    """Models, a TRC record per segment, then ``passes`` passes over every segment."""
    msgs: list = [*example_models(30, seed=2)]
    msgs += [
        TrcRecord(line="L1", segment=seg, t=T0, top6_mm=3.0, align10_mm=2.5, run_id="r1")
        for seg in SEGMENTS
    ]
    for k in range(1, passes + 1):
        msgs += [
            OnboardIndex(
                line="L1",
                segment=seg,
                train="T1",
                unit="u1",
                t=T0 + (7 * k + 0.1 * i) * DAY_S,
                top6_mm=2.4 + 0.01 * i,
                align10_mm=1.8 - 0.1 * k,
                speed_mps=30.0,
                coverage=1.0,
            )
            for i, seg in enumerate(SEGMENTS)
        ]
    return msgs


def published(adapter: service.FilteringAdapter, ns: str) -> dict[str, bytes]:
    """What q/state answers, by segment."""
    found = adapter.latest.matching(zenoh.KeyExpr(keys.q_state_keys(ns, "**")))
    return {decode(payload, SegmentState).segment: payload for _key, payload in found}


def started_adapter(rt: ServiceRuntime, store: Store) -> service.FilteringAdapter:
    """The service's adapter on a fresh tracker, its publisher declared and its inbox
    empty, without its subscriptions: the test hands it the batches."""
    node = PersistentTracker(Tracker(LIMITS.for_line, LIMITS.levels), store)
    adapter = service.FilteringAdapter(rt, node, "**")
    adapter.states_out = rt.reliable_publisher()
    adapter.inbox = Inbox()
    return adapter


def test_dirty_segments_wait_under_a_backlog_and_all_go_out_after_it(
    service_config, tmp_path, monkeypatch
):
    monkeypatch.setattr(service, "PUBLISH_SHARE", 0.0)  # one chunk per batch under a backlog
    msgs = stream()
    core = Tracker(LIMITS.for_line, LIMITS.levels)
    for msg in msgs:
        core.step(msg)
    ns = service_config.ns
    batch = [("", keys.key_of(ns, m), encode(m)) for m in msgs]
    with (
        Store(tmp_path / "filtering.sqlite") as store,
        ServiceRuntime(service.SERVICE, service_config, handle_signals=False) as rt,
    ):
        adapter = started_adapter(rt, store)
        for _ in range(service.BACKLOG):  # a backlog waiting in the worker's inbox
            adapter.inbox.put("index", keys.index(ns, "L1", "s00"), b"")

        committing = threading.Event()  # the batch's commit in the background, held
        commit = store._commit_in_background

        def held(*args):
            committing.wait(30)
            commit(*args)

        monkeypatch.setattr(store, "_commit_in_background", held)
        adapter._handle_batch(batch[:-1])  # everything but s19's last pass
        assert store.committing
        assert published(adapter, ns) == {}  # none before its commit
        assert list(adapter.dirty) == [("L1", s) for s in SEGMENTS]
        committing.set()
        adapter._handle_batch([])  # the next batch, once the commit is done
        assert not store.committing
        assert list(published(adapter, ns)) == SEGMENTS[: service.SUMMARY_CHUNK]  # oldest
        assert list(adapter.dirty) == [("L1", s) for s in SEGMENTS[service.SUMMARY_CHUNK :]]
        assert store.count_events() == len(msgs) - 3  # committed before any publication

        assert len(adapter.inbox.take(service.BACKLOG)) == service.BACKLOG  # backlog gone
        adapter._handle_batch(batch[-1:])
        assert not adapter.dirty
        assert published(adapter, ns) == {
            segment: encode(core.state_of("L1", segment)) for segment in SEGMENTS
        }


def test_a_failed_commit_in_the_background_stops_the_instance_with_nothing_of_it_published(
    service_config, tmp_path
):
    """A backlog's batch commits in the background; the disk is full (SQLite's limit on
    the file's pages), so the commit fails: none of its states goes out, and the next
    batch stops the instance with EXIT_STORE_FAILED (its supervisor restarts it from what
    the store holds) instead of folding on over events the store lost."""
    msgs = stream(passes=4)
    ns = service_config.ns
    batch = [("", keys.key_of(ns, m), encode(m)) for m in msgs]
    first = len(msgs) - 4 * len(SEGMENTS)  # models and TRC records: committed at once
    with (
        Store(tmp_path / "filtering.sqlite") as store,
        ServiceRuntime(service.SERVICE, service_config, handle_signals=False) as rt,
    ):
        adapter = started_adapter(rt, store)
        node = adapter.node
        adapter._handle_batch(batch[:first])
        before = published(adapter, ns)
        assert len(before) == len(SEGMENTS) and not adapter.dirty

        (pages,) = store._db.execute("PRAGMA page_count").fetchone()
        store._db.execute(f"PRAGMA max_page_count = {pages}")  # the disk is full
        for _ in range(service.BACKLOG):
            adapter.inbox.put("index", keys.index(ns, "L1", "s00"), b"")
        adapter._handle_batch(batch[first:])  # 80 indices, a backlog: in the background
        assert published(adapter, ns) == before
        assert not rt.stopping

        adapter._handle_batch(batch[first:][:1])  # the next batch finds the failed commit
        assert rt.stopping and rt.exit_code == service.EXIT_STORE_FAILED
        assert node.broken  # no checkpoint at the stop of what the store does not hold
        assert published(adapter, ns) == before
