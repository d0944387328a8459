"""LatestValues: the late-joiner queryable of calibration (models) and filtering (states),
over a real router on loopback."""

from __future__ import annotations

import pytest
import zenoh
from support import ready_querier

from services.runtime.latest import LatestValues

TIMEOUT_S = 5.0


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
    querier = ready_querier(client, f"{ns}/m/**")
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
