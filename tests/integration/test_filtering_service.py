"""The filtering service in-process on a real router: models, events, states, queries,
dead letters and the selector."""

from __future__ import annotations

import contextlib
import dataclasses
import sqlite3
import threading
import time
from collections.abc import Callable, Iterator

import msgspec
import numpy as np
import pytest
import zenoh

from schemas import (
    DAY_S,
    Calibration,
    DeadLetter,
    DegradationPosterior,
    MaintenanceEvent,
    NDArray,
    OnboardIndex,
    SegmentState,
    TrcRecord,
    decode,
    encode,
    keys,
)
from services.filtering import service
from services.filtering.testing import example_models, onboard_index, sample_state
from services.filtering.tracker import Tracker
from services.limits import load_limits
from services.runtime.delivery import DeliverySettings, OutboxSettings, ReliablePublisher

T0 = 1_767_225_600.0
NS = 30
LIMITS = load_limits()


def models() -> list[Calibration | DegradationPosterior]:
    return example_models(NS, seed=0)


def events(line: str = "L1", segment: str = "s1") -> list[TrcRecord | OnboardIndex]:
    out: list[TrcRecord | OnboardIndex] = [
        TrcRecord(line=line, segment=segment, t=T0, top6_mm=3.0, align10_mm=2.5, run_id="r1")
    ]
    for k, (top6, align10) in enumerate([(2.4, 1.7), (2.6, 1.6), (2.5, 1.9)]):
        out.append(onboard_index(line, segment, T0 + (k + 1) * 7 * DAY_S, top6, align10))
    return out


def expected(messages) -> SegmentState:
    tracker = Tracker(LIMITS.for_line, LIMITS.levels)
    states = [s for msg in messages for s in tracker.step(msg).states]
    return states[-1]


@pytest.fixture
def start_filtering(service_config, tmp_path, service_thread) -> Callable[..., None]:
    """``start_filtering(selector)``: the service in a thread, ready when it returns."""

    def start(selector: str = "**", conf=None):
        return service_thread(
            "filtering",
            lambda stop: service.main(
                conf or service_config,
                selector=selector,
                db=tmp_path / "filtering.sqlite",
                stop=stop,
                handle_signals=False,
            ),
            alive=keys.alive(service_config.ns, service.SERVICE, "test"),
        )

    return start


@pytest.fixture
def model_queryable(open_session, namespace) -> Iterator[zenoh.Session]:
    """Stands in for the calibration service: answers the latest models on model/**."""
    session = open_session()
    latest = [(keys.key_of(namespace, m), encode(m)) for m in models()]

    def on_query(query: zenoh.Query) -> None:
        for key, payload in latest:
            if query.key_expr.intersects(zenoh.KeyExpr(key)):
                query.reply(key, payload)

    queryable = session.declare_queryable(keys.model_all(namespace), on_query)
    yield session
    queryable.undeclare()


def put_all(session: zenoh.Session, until_matched, items) -> None:
    """Put ``(key, payload)`` items, each key's publisher matched first."""
    publishers: dict[str, zenoh.Publisher] = {}
    try:
        for key, payload in items:
            if key not in publishers:
                publishers[key] = session.declare_publisher(key)
                until_matched(publishers[key])
            publishers[key].put(payload)
    finally:
        for publisher in publishers.values():
            publisher.undeclare()


def letters_and_states(session: zenoh.Session, collector, ns: str):
    """Collectors of the service's dead letters and of the states it publishes."""
    letters = collector(lambda s: decode(s.payload.to_bytes(), DeadLetter))
    session.declare_subscriber(keys.deadletter(ns, service.SERVICE), letters)
    states = collector(sample_state)
    session.declare_subscriber(keys.segment_keys(ns, "state"), states)
    return letters, states


def query_states(session: zenoh.Session, selector: str) -> dict[str, bytes]:
    replies = session.get(selector, timeout=5)
    return {str(r.ok.key_expr): r.ok.payload.to_bytes() for r in replies if r.ok is not None}


def test_states_from_late_joined_models_and_events_equal_the_core(
    namespace, open_session, collector, until_matched, model_queryable, start_filtering
):
    session = open_session()
    states = collector(lambda s: (str(s.key_expr), sample_state(s)))
    session.declare_subscriber(keys.segment_keys(namespace, "state"), states)
    start_filtering()  # gets the models from the queryable at start

    msgs = events()
    # One event at a time: order is kept per key, not across the trc and index keys (each
    # subscription has its own callback thread), and this test looks at every intermediate
    # state. The final state does not depend on the order (see the tracker's tests).
    received = []
    for m in msgs:
        put_all(session, until_matched, [(keys.key_of(namespace, m), encode(m))])
        received.append(states.get())
    key, last = received[-1]
    assert key == keys.state(namespace, "L1", "s1")
    assert [s.n_updates for _, s in received] == [0, 1, 2, 3]
    want = expected([*models(), *msgs])
    assert encode(last) == encode(want)  # every number, bit for bit
    assert last.posterior_group == "net" and last.calibration_version == 1
    assert last.forecast_p_exceed.shape == [3, 2, 2]

    for selector in (keys.q_state_all(namespace), f"{namespace}/q/state/L1/**"):
        assert query_states(session, selector) == {
            keys.q_state(namespace, "L1", "s1"): encode(want)
        }
    assert query_states(session, f"{namespace}/q/state/L2/**") == {}


def test_malformed_payload_is_dead_lettered_and_the_service_goes_on(
    namespace, open_session, collector, until_matched, start_filtering
):
    session = open_session()
    letters, states = letters_and_states(session, collector, namespace)
    start_filtering()

    put_all(session, until_matched, [(keys.key_of(namespace, m), encode(m)) for m in models()])
    bad_key = keys.index(namespace, "L1", "s1")
    trc = events()[0]
    put_all(
        session,
        until_matched,
        [
            (bad_key, b"\x81\xa1v\x01"),  # a map with only v: fields missing
            (keys.trc(namespace, "L1", "other"), encode(trc)),  # key disagrees with payload
            (keys.trc(namespace, "L1", "s1"), encode(trc)),
        ],
    )
    # the index and trc subscriptions run on their own threads: the letters in either order
    reasons = {letter.key: letter.reason for letter in (letters.get(), letters.get())}
    assert reasons[bad_key].startswith("OnboardIndex:")
    assert "key says L1/other, message says" in reasons[keys.trc(namespace, "L1", "other")]
    assert states.get().n_updates == 0  # still serving


def test_an_instance_owning_l1_ignores_l2(
    namespace, open_session, collector, until_matched, model_queryable, start_filtering
):
    session = open_session()
    states = collector(sample_state)
    session.declare_subscriber(keys.segment_keys(namespace, "state"), states)
    start_filtering("L1/**")

    l2, l1 = events("L2", "s9")[0], events("L1", "s1")[0]
    for msg in (l2, l1):
        # The L2 put has no subscriber to match: put it straight from the session.
        session.put(keys.key_of(namespace, msg), encode(msg))
    put_all(session, until_matched, [(keys.key_of(namespace, l1), encode(l1))])  # a duplicate
    assert states.get().line == "L1"
    assert set(query_states(session, keys.q_state_all(namespace))) == {
        keys.q_state(namespace, "L1", "s1")
    }


def test_a_refused_model_is_dead_lettered_and_the_one_in_force_stays(
    namespace, open_session, collector, until_matched, model_queryable, start_filtering
):
    """A Calibration whose indices disagree with the filter's (m = 3 here) is a
    dead letter and the good one stays in force: it must not make every later index fail
    until a restart."""
    session = open_session()
    letters, states = letters_and_states(session, collector, namespace)
    start_filtering()
    trc, *indices = events()
    put_all(session, until_matched, [(keys.key_of(namespace, trc), encode(trc))])
    assert states.get().n_updates == 0

    good = next(m for m in models() if isinstance(m, Calibration))
    bad = Calibration(
        version=good.version + 1,
        t=good.t,
        indicators=good.indicators,
        indices=["top6", "align10", "twist3"],
        H=NDArray.of(np.ones((3, 2))),
        b=NDArray.of(np.zeros(3)),
        R=NDArray.of(np.eye(3) * 0.01),
        n_pairs=good.n_pairs,
        r2=NDArray.of(np.full(3, 0.9)),
    )
    put_all(session, until_matched, [(keys.calibration(namespace), encode(bad))])
    letter = letters.get()
    assert letter.key == keys.calibration(namespace)
    assert "indices" in letter.reason, letter.reason

    put_all(session, until_matched, [(keys.key_of(namespace, m), encode(m)) for m in indices])
    last = states.get()
    while last.n_updates < len(indices):
        last = states.get()
    assert last.calibration_version == good.version
    assert encode(last) == encode(expected([*models(), trc, *indices]))


def test_an_unreported_tamping_is_published_as_detected_maintenance(
    namespace, open_session, collector, until_matched, model_queryable, start_filtering
):
    session = open_session()
    found = collector(lambda s: (str(s.key_expr), decode(s.payload.to_bytes(), MaintenanceEvent)))
    session.declare_subscriber(keys.segment_keys(namespace, "maintenance"), found)
    start_filtering()
    cal, post = models()[0], models()[1]
    H, b = cal.H.array(), cal.b.array()
    worn, fresh = np.log([4.5, 3.5]), post.z_plus.array().mean(axis=0)
    record = TrcRecord(line="L1", segment="s1", t=T0, top6_mm=4.5, align10_mm=3.5, run_id="r1")
    passes = []
    for day in range(1, 31):
        top6, align10 = np.exp(H @ (worn if day <= 20 else fresh) + b).tolist()
        passes.append(
            OnboardIndex(
                line="L1", segment="s1", train="T1", unit="u1", t=T0 + day * DAY_S,
                top6_mm=top6, align10_mm=align10, speed_mps=30.0, coverage=1.0,
            )
        )  # fmt: skip
    items = [(keys.trc(namespace, "L1", "s1"), encode(record))]
    items += [(keys.index(namespace, "L1", "s1"), encode(m)) for m in passes]
    put_all(session, until_matched, items[:1])
    put_all(session, until_matched, items[1:])
    key, event = found.get()
    assert key == keys.maintenance(namespace, "L1", "s1") and event.detected
    assert event.t_start == T0 + 20 * DAY_S and event.t_end == T0 + 21 * DAY_S
    assert not event.withdrawn and event.revision > 0

    # a report of the tamping supersedes the detection: filtering publishes its withdrawal,
    # the detection as published with a higher revision
    at = T0 + 20.5 * DAY_S
    report = MaintenanceEvent(line="L1", segment="s1", event_id="m1", t_start=at, t_end=at)
    put_all(session, until_matched, [(keys.maintenance(namespace, "L1", "s1"), encode(report))])
    assert found.get() == (key, report)  # the report itself, on the same key
    key, gone = found.get()
    assert key == keys.maintenance(namespace, "L1", "s1") and gone.withdrawn
    assert msgspec.structs.replace(gone, withdrawn=False, revision=event.revision) == event
    assert gone.rank > event.rank


def test_a_restarted_instance_replays_from_the_positions_in_its_store(
    namespace, open_session, collector, model_queryable, start_filtering, service_config, tmp_path
):
    """The replay positions are stored with the events they brought; the instance, stopped
    and started again on its store, resumes from them: the event published while it was
    down arrives by the replay, and every event is stored once."""
    delivery = {"replay_s": 0.5, **service_config.services["delivery"]}
    conf = dataclasses.replace(service_config, services={"delivery": delivery})
    extraction = ReliablePublisher.open(
        open_session(), namespace, "extraction", "a",
        DeliverySettings(outbox=OutboxSettings(dir=str(tmp_path / "extraction"))),
    )  # fmt: skip
    states = collector(sample_state)
    open_session().declare_subscriber(keys.segment_keys(namespace, "state"), states)
    msgs = events()
    running = start_filtering(conf=conf)
    for m in msgs[:-1]:
        extraction.put(keys.key_of(namespace, m), encode(m))
    store = tmp_path / "filtering.sqlite"

    def until_stored(seq: int) -> None:
        """Until the store holds ``seq`` as the extraction's position (a replay round's
        mark, committed with a batch), checked every 0.1 s for at most 30 s."""
        deadline, found = time.monotonic() + 30, None
        while found != (extraction.outbox.epoch, seq):
            assert time.monotonic() < deadline, f"position {found}, not {seq}"
            threading.Event().wait(0.1)
            with contextlib.closing(sqlite3.connect(store)) as db:
                found = db.execute("SELECT epoch, seq FROM delivery_positions").fetchone()

    until_stored(len(msgs) - 1)
    assert running.stop() == 0
    extraction.put(keys.key_of(namespace, msgs[-1]), encode(msgs[-1]))  # while it is down
    assert extraction.flush(10)
    start_filtering(conf=conf)
    while states.get().n_updates < len(msgs) - 1:  # the last index, replayed
        pass
    until_stored(len(msgs))
    with contextlib.closing(sqlite3.connect(store)) as db:
        (stored,) = db.execute("SELECT count(*) FROM events").fetchone()
    assert stored == len(msgs)  # every event once
    extraction.undeclare()
