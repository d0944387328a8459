"""The alerting service in-process on a real router: states in, alerts out, queryables,
dead letters, and a restart that keeps the raised set."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import msgpack
import numpy as np
import pytest
import zenoh
from support import ServiceThread

from schemas import (
    DAY_S,
    Alert,
    DeadLetter,
    InspectionPlan,
    RaisedAlerts,
    TrcRecord,
    decode,
    encode,
    keys,
)
from services.alerting import service as alerting
from services.alerting.testing import T0, make_state, p_top6
from services.defaults import DEMO_NETWORK, demo_network

TIMEOUT_S = 5.0


@pytest.fixture
def running(service_config, service_thread) -> Callable[[Path], ServiceThread]:
    """``with running(db):`` the service in a thread, entered once its token is alive."""

    def start(db: Path) -> ServiceThread:
        return service_thread(
            "alerting",
            lambda stop: alerting.main(service_config, db=db, stop=stop, handle_signals=False),
            alive=keys.alive(service_config.ns, alerting.SERVICE, "test"),
        )

    return start


def query(session: zenoh.Session, key: str) -> list[bytes]:
    replies = session.get(key, timeout=TIMEOUT_S)
    return [r.ok.payload.to_bytes() for r in replies if r.ok is not None]


def letters_and_alerts(client: zenoh.Session, ns: str, collector) -> tuple:
    """Collectors of the service's dead letters and of the alerts it publishes."""
    letters = collector(lambda s: decode(s.payload.to_bytes(), DeadLetter))
    client.declare_subscriber(keys.deadletter(ns, alerting.SERVICE), letters)
    alerts = collector(lambda s: decode(s.payload.to_bytes(), Alert))
    client.declare_subscriber(keys.segment_keys(ns, "alert"), alerts)
    return letters, alerts


def test_state_raises_alert_queryables_answer_and_restart_keeps_it(
    open_session, service_config, running, collector, until_matched, tmp_path
):
    ns = service_config.ns
    db = tmp_path / "alerting.sqlite"
    client = open_session()
    alerts = collector(lambda s: (str(s.key_expr), decode(s.payload.to_bytes(), Alert)))
    client.declare_subscriber(keys.segment_keys(ns, "alert"), alerts)
    letters = collector(lambda s: decode(s.payload.to_bytes(), DeadLetter))
    client.declare_subscriber(keys.deadletter(ns, alerting.SERVICE), letters)
    state_pub = client.declare_publisher(keys.state(ns, "L1", "s1"))
    trc_pub = client.declare_publisher(keys.trc(ns, "L1", "s1"))

    with running(db):
        until_matched(state_pub)
        until_matched(trc_pub)
        trc_pub.put(
            encode(TrcRecord(line="L1", segment="s1", t=T0, top6_mm=3, align10_mm=2, run_id="r1"))
        )
        # Order holds per key, not across the trc and state subscriptions: a rejected record
        # behind the run on its key is dead-lettered only after the one worker has handled it.
        trc_pub.put(b"not msgpack")
        assert letters.get().reason
        state_pub.put(encode(make_state(T0 + DAY_S, p_exceed=p_top6(1, 0.72))))

        key, alert = alerts.get()
        assert key == keys.alert(ns, "L1", "s1")
        assert (alert.kind, alert.status, alert.indicator, alert.level) == (
            "exceedance",
            "raised",
            "top6",
            "intervention",
        )
        assert alert.message == (
            "Top6 likely above intervention limit 8.0 mm (p=0.72), speed class 80<v<=120"
        )
        assert alert.speed_class == "80<v<=120"

        (body,) = query(client, keys.q_alerts(ns))
        assert decode(body, RaisedAlerts).alerts == [alert]
        (body,) = query(client, keys.q_alerts(ns) + "?line=L2")
        assert decode(body, RaisedAlerts).alerts == []

        (body,) = query(client, keys.q_plan(ns))
        plan = decode(body, InspectionPlan)
        assert plan.v == 1 and plan.t == T0 + DAY_S
        (row,) = plan.rows
        assert (row.line, row.segment, row.level) == ("L1", "s1", "intervention")
        assert row.next_trc_t == T0 + 70 * DAY_S  # one run seen: the default interval
        assert np.isclose(row.probability, 0.72) and row.indicator == "top6"
        (body,) = query(client, keys.q_plan(ns) + "?limit=0")
        assert decode(body, InspectionPlan).rows == []
        (bad,) = client.get(keys.q_plan(ns) + "?limit=x", timeout=TIMEOUT_S)
        assert bad.err is not None and b"limit" in bad.err.payload.to_bytes()

    with running(db):
        # restarted: the raised alert is still there and the same condition does not repeat it
        (body,) = query(client, keys.q_alerts(ns))
        assert decode(body, RaisedAlerts).alerts == [alert]
        state_pub = client.declare_publisher(keys.state(ns, "L1", "s1"))
        until_matched(state_pub)
        state_pub.put(encode(make_state(T0 + 2 * DAY_S, p_exceed=p_top6(1, 0.8))))
        state_pub.put(encode(make_state(T0 + 3 * DAY_S, p_exceed=p_top6(1, 0.1))))
        _, cleared = alerts.get()
        assert (cleared.kind, cleared.status, cleared.t) == (
            "exceedance",
            "cleared",
            T0 + 3 * DAY_S,
        )
        assert alerts.empty()
        state_pub.undeclare()


def test_malformed_payload_goes_to_dead_letter(
    open_session, service_config, running, collector, until_matched, tmp_path
):
    ns = service_config.ns
    client = open_session()
    letters, alerts = letters_and_alerts(client, ns, collector)
    pub = client.declare_publisher(keys.state(ns, "L1", "s1"))

    with running(tmp_path / "a.sqlite"):
        until_matched(pub)
        pub.put(b"\x81\xa1v\x01")  # a map {v: 1}: fields missing
        pub.put(msgpack.packb({**msgpack.unpackb(encode(make_state(T0))), "v": 2}))
        client.put(keys.state(ns, "L1", "other"), encode(make_state(T0)))  # key mismatch
        # the worker keeps going: a good state after the bad ones still raises
        pub.put(encode(make_state(T0, nis=50.0)))

        reasons = [letters.get().reason for _ in range(3)]
        assert reasons[0].startswith("SegmentState: Object missing required field")
        assert "unknown schema version 2" in reasons[1]
        assert reasons[2] == "SegmentState: key says L1/other, message says L1/s1"
        assert alerts.get().kind == "sudden_change"
    pub.undeclare()


def test_a_message_on_a_segment_not_in_its_network_is_a_dead_letter(
    open_session, service_config, service_thread, collector, until_matched, tmp_path
):
    """With ``--network``, states, TRC records and tamping records of segments the network
    lacks are refused with the reason; those of its segments are judged as before."""
    ns = service_config.ns
    client = open_session()
    letters, alerts = letters_and_alerts(client, ns, collector)
    segment = demo_network().lines["L2"].segments[3].id
    known = client.declare_publisher(keys.state(ns, "L2", segment))
    unknown = client.declare_publisher(keys.state(ns, "L2", "nowhere"))
    trc = client.declare_publisher(keys.trc(ns, "L9", "s1"))

    def main(stop):
        return alerting.main(
            service_config, network=DEMO_NETWORK, db=tmp_path / "a.sqlite", stop=stop,
            handle_signals=False,
        )  # fmt: skip

    with service_thread("alerting", main, alive=keys.alive(ns, alerting.SERVICE, "test")):
        for publisher in (known, unknown, trc):
            until_matched(publisher)
        unknown.put(encode(make_state(T0, line="L2", segment="nowhere", nis=50.0)))
        trc.put(encode(TrcRecord(line="L9", segment="s1", t=T0, top6_mm=3, align10_mm=2,
                                 run_id="r1")))  # fmt: skip
        reasons = sorted(letters.get().reason for _ in range(2))
        assert reasons == [
            f"SegmentState: segment L2/nowhere is not in the network {DEMO_NETWORK.name}",
            f"TrcRecord: segment L9/s1 is not in the network {DEMO_NETWORK.name}",
        ]
        known.put(encode(make_state(T0, line="L2", segment=segment, nis=50.0)))
        alert = alerts.get()
        assert (alert.line, alert.segment, alert.kind) == ("L2", segment, "sudden_change")
        (body,) = query(client, keys.q_alerts(ns))
        assert [(a.line, a.segment) for a in decode(body, RaisedAlerts).alerts] == [("L2", segment)]
    for publisher in (known, unknown, trc):
        publisher.undeclare()


def test_at_start_it_asks_q_state_for_the_states_it_cannot_recover(
    open_session, service_config, running, collector, tmp_path
):
    """A segment's state with no publisher cache behind it (a key past filtering's cached
    publishers, or published before alerting ever ran) comes from q/state at start; a
    reply on a malformed key is skipped."""
    ns = service_config.ns
    client = open_session()
    alerts = collector(lambda s: decode(s.payload.to_bytes(), Alert))
    client.declare_subscriber(keys.segment_keys(ns, "alert"), alerts)
    state = make_state(T0 + DAY_S, p_exceed=p_top6(1, 0.72))

    def answer(query: zenoh.Query) -> None:
        query.reply(keys.q_state(ns, "L1", "s0") + "/extra", encode(state))  # skipped
        query.reply(keys.q_state(ns, "L1", "s1"), encode(state))

    queryable = client.declare_queryable(keys.q_state_all(ns), answer)
    try:
        with running(tmp_path / "alerting.sqlite"):
            alert = alerts.get()
            assert (alert.line, alert.segment, alert.kind, alert.status, alert.level) == (
                "L1",
                "s1",
                "exceedance",
                "raised",
                "intervention",
            )
            (body,) = query(client, keys.q_alerts(ns))
            assert decode(body, RaisedAlerts).alerts == [alert]
    finally:
        queryable.undeclare()
