"""Real processes: `trackfusion router` and `trackfusion deadletters` start, serve and stop
with exit code 0 on SIGTERM and on SIGINT."""

from __future__ import annotations

import signal

import pytest
import zenoh

from schemas import DeadLetter, encode, keys
from services.runtime.config import zenoh_config

STOP_S = 5.0  # a stopped service must exit within this
READY_S = 20.0  # generous: interpreter start + imports on a loaded CI machine


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGINT], ids=["SIGTERM", "SIGINT"])
def test_router_and_deadletters_serve_and_stop_cleanly(
    signum, stack, spawn, free_port, namespace, until_matched, liveliness_events
):
    endpoint = f"tcp/127.0.0.1:{free_port}"
    router = spawn("router", "router", "--listen", endpoint)
    service = spawn(
        "deadletters",
        *("deadletters", "--connect", endpoint, "--ns", namespace, "--instance", "e2e"),
    )

    # The test's own client: zenoh retries the connection until the router listens.
    settings = {"connect": {"endpoints": [endpoint], "timeout_ms": int(READY_S * 1000)}}
    session = stack.enter_context(zenoh.open(zenoh_config(settings)))
    alive = keys.alive(namespace, "deadletters", "e2e")
    events = liveliness_events(session, alive)
    assert events.get(READY_S) == (zenoh.SampleKind.PUT, alive), service.log()

    publisher = session.declare_publisher(keys.deadletter(namespace, "e2e"))
    stack.callback(publisher.undeclare)
    until_matched(publisher)
    letter = DeadLetter(
        service="e2e",
        key=f"{namespace}/raw/t1/u1",
        reason="v: unknown schema version 9",
        payload_head=b"\x82\xa1v\x09",
        received_at=1.0,
    )
    publisher.put(encode(letter))
    assert service.line(STOP_S) == f"e2e {namespace}/raw/t1/u1 v: unknown schema version 9"

    service.signal(signum)
    assert service.wait(STOP_S) == 0, service.log()
    assert events.get(STOP_S) == (zenoh.SampleKind.DELETE, alive)  # token gone with it
    router.signal(signum)
    assert router.wait(STOP_S) == 0, router.log()
