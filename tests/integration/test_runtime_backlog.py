"""A service slower than its inputs: the inbox holds the backlog and Zenoh never waits.

A subscription callback that blocks on a full queue while the worker is busy, with the
service's own traffic waiting on the same link, gets the link closed by the router after
``wait_before_close`` (5 s) and what was queued dropped: a deaf service
(tests/e2e/test_filtering_flood.py shows it with real processes). The inbox
(services/runtime/inbox.py) never blocks a callback. This test holds the worker still while
80 MB arrive, then lets it go: every message must be handled, the backlog must have gone to
the disk spill, the token never withdrawn, and no callback may have waited. (A stalled worker
alone, with no outgoing traffic, keeps its session even with a blocking queue: this test
checks the inbox, the e2e test the loss.)
"""

from __future__ import annotations

import threading
import time

import zenoh
from support import wait_for

from schemas import keys
from services.runtime.service import EXIT_SESSION_LOST, ServiceRuntime

FLOOD = 20_000
PAYLOAD = bytes(4096)  # 80 MB in all: beyond the in-memory budget, so the disk spill is used
WAIT_S = 90.0


def test_a_stalled_worker_neither_loses_its_session_nor_messages(
    open_session, service_config, liveliness_events, until_matched
):
    observer = open_session()
    token_events = liveliness_events(observer, keys.alive_all(service_config.ns))
    gate = threading.Event()  # the worker is "busy" until the flood is in
    handled = 0
    all_handled = threading.Event()

    def handle(_kind: str, _key: str, payload: bytes) -> None:
        nonlocal handled
        gate.wait()
        assert payload == PAYLOAD
        handled += 1
        if handled == FLOOD:
            all_handled.set()

    with ServiceRuntime("probe", service_config) as rt:
        inbox = rt.subscribe_in_order({"in": f"{rt.ns}/in/**"}, handle)
        rt.announce()
        alive = token_events.get()
        assert alive == (zenoh.SampleKind.PUT, rt.alive_key)
        publisher = observer.declare_publisher(
            f"{rt.ns}/in/a", congestion_control=zenoh.CongestionControl.BLOCK
        )
        until_matched(publisher)

        started = time.monotonic()
        for _ in range(FLOOD):
            publisher.put(PAYLOAD)
        # the flood is in flight; hold the worker until all of it is in the inbox (a session
        # whose callbacks blocked would have been cut by the router's 5 s wait_before_close
        # long before, and what was queued on it lost)
        flood_s = time.monotonic() - started
        wait_for(
            lambda: inbox.stats().received >= FLOOD,
            WAIT_S,
            lambda: f"the flood in the inbox ({inbox.stats()})",
        )
        gate.set()

        assert all_handled.wait(WAIT_S), f"handled {handled} of {FLOOD} ({inbox.stats()})"
        stats = inbox.stats()
        assert stats.received == FLOOD
        assert stats.spilled > 0  # the backlog went to disk, not to the network
        assert stats.max_put_s < 0.5, f"a callback waited {stats.max_put_s:.3f} s"
        assert token_events.empty(), "the service's token was withdrawn during the flood"
        print(f"flood put in {flood_s:.1f} s; longest callback {stats.max_put_s * 1e3:.1f} ms")
        publisher.undeclare()


def test_a_service_whose_token_is_gone_from_the_router_exits_non_zero(service_config):
    with ServiceRuntime("probe", service_config, health_interval_s=0.2, deaf_after_s=1.0) as rt:
        rt.announce()
        # What a lost session looks like from the router: the token is not there any more,
        # though nothing failed in this process.
        rt._token.undeclare()
        assert rt.stop_event.wait(10.0), "a deaf service kept running"
        assert rt.run() == EXIT_SESSION_LOST
