"""LatestValues: the late-joiner queryable of calibration (models) and filtering (states),
over a real router on loopback."""

from __future__ import annotations

import threading

import pytest
import zenoh

from services.runtime.latest import LatestValues

TIMEOUT_S = 5.0
LARGE_QUERY_TIMEOUT_S = 60.0  # 10,000 replies of 2 kB


def _ready_querier(session: zenoh.Session, key_expr: str) -> zenoh.Querier:
    """A querier on ``key_expr`` once the router knows a queryable matching it."""
    matched = threading.Event()
    querier = session.declare_querier(key_expr, timeout=TIMEOUT_S)
    listener = querier.declare_matching_listener(lambda s: matched.set() if s.matching else None)
    try:
        assert querier.matching_status.matching or matched.wait(TIMEOUT_S), "no queryable matched"
    finally:
        listener.undeclare()
    return querier


def _ask(session: zenoh.Session, key_expr: str) -> dict[str, bytes]:
    none = zenoh.ConsolidationMode.NONE  # every reply, not one per key
    replies = session.get(key_expr, timeout=TIMEOUT_S, consolidation=none)
    out: dict[str, bytes] = {}
    for reply in replies:
        assert reply.ok is not None, reply.err.payload.to_bytes()
        key = str(reply.ok.key_expr)
        assert key not in out, f"{key} answered twice"
        out[key] = reply.ok.payload.to_bytes()
    return out


def test_a_query_gets_the_latest_value_of_each_key_it_matches(open_session, namespace):
    ns = namespace
    latest = LatestValues()
    for key, payload in [
        (f"{ns}/m/calibration", b"c1"),
        (f"{ns}/m/degradation/net", b"d1"),
        (f"{ns}/m/degradation/L1", b"e1"),
        (f"{ns}/m/calibration", b"c2"),  # replaces c1
    ]:
        latest.put(key, payload)
    server, client = open_session(), open_session()
    queryable = server.declare_queryable(f"{ns}/m/**", latest.on_query)
    querier = _ready_querier(client, f"{ns}/m/**")
    try:
        everything = {
            f"{ns}/m/calibration": b"c2",
            f"{ns}/m/degradation/net": b"d1",
            f"{ns}/m/degradation/L1": b"e1",
        }
        assert _ask(client, f"{ns}/m/**") == everything
        assert _ask(client, f"{ns}/m/degradation/*") == {
            k: v for k, v in everything.items() if "degradation" in k
        }
        assert _ask(client, f"{ns}/m/degradation/L$*") == {f"{ns}/m/degradation/L1": b"e1"}
        assert _ask(client, f"{ns}/m/calibration") == {f"{ns}/m/calibration": b"c2"}
        assert _ask(client, f"{ns}/m/degradation/none") == {}

        latest.put(f"{ns}/m/degradation/net", b"d2")  # a newer value is answered at once
        assert _ask(client, f"{ns}/m/degradation/net") == {f"{ns}/m/degradation/net": b"d2"}
    finally:
        querier.undeclare()
        queryable.undeclare()


def test_only_concrete_keys_are_kept():
    latest = LatestValues()
    for wildcard in ("tf/m/*", "tf/m/**", "tf/m/a$*"):
        with pytest.raises(ValueError, match="wildcards"):
            latest.put(wildcard, b"x")
    assert latest.matching(zenoh.KeyExpr("tf/**")) == []


def test_one_query_answered_by_several_instances_gets_every_reply(open_session, namespace):
    """Filtering shards each answer q/state for their lines; a viewer asks them all at once.
    Thousands of replies from two processes through a router that shares this process's
    rx threads deadlocked it (2 threads on 2 cores: every reply lost after the first
    thousands, the transports closed 5 s later) until the process reserved more
    (``reserve_rx_threads``, as conftest does)."""
    ns, per_shard = namespace, 5000
    payload = bytes(2000)  # about a SegmentState
    servers = []
    for shard in "AB":
        latest = LatestValues()
        for i in range(per_shard):
            latest.put(f"{ns}/q/state/{shard}001/s{i:05d}", payload)
        server = open_session()
        servers.append(server.declare_queryable(f"{ns}/q/state/{shard}$*/**", latest.on_query))
    client = open_session()
    queriers = [_ready_querier(client, f"{ns}/q/state/{shard}001/**") for shard in "AB"]
    try:
        block = zenoh.CongestionControl.BLOCK  # as ServiceRuntime.ask
        # The deadline only bounds a stalled run (0.1 s here; the deadlock closes the
        # transports after 5 s whatever it is). CI once got 9,467 of 10,000 replies at a 5-s
        # deadline, cause unseen: a deadline shows as an error reply ("Timeout"), the
        # deadlock as replies missing without one.
        replies = client.get(
            f"{ns}/q/state/**", timeout=LARGE_QUERY_TIMEOUT_S, congestion_control=block
        )
        keys, errors = [], []
        for reply in replies:
            if reply.ok is not None:
                keys.append(str(reply.ok.key_expr))
            else:
                errors.append(reply.err.payload.to_bytes()[:200])
        assert not errors, f"{len(keys)} replies, then error replies {errors[:3]}"
        assert len(keys) == len(set(keys)) == 2 * per_shard
    finally:
        for entity in (*queriers, *servers):
            entity.undeclare()
