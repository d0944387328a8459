"""At-least-once delivery (services/runtime/delivery.py) through a real router on loopback:
a subscriber that was away — restarted, behind a restarted router, behind a cut link —
gets every message published meanwhile, once the link is back, with no manual step."""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterator

import pytest
import zenoh

from bench.linkproxy import LinkProxy
from services.runtime.config import RuntimeConfig, zenoh_config
from services.runtime.delivery import DeliverySettings, ReliablePublisher
from services.runtime.service import ServiceRuntime

TIMEOUT_S = 20.0
SEGMENTS = 40


class Received:
    """(key, payload) pairs a subscriber got, with a wait for a set of them."""

    def __init__(self) -> None:
        self.items: list[tuple[str, bytes]] = []
        self._cond = threading.Condition()

    def __call__(self, sample: zenoh.Sample) -> None:
        with self._cond:
            self.items.append((str(sample.key_expr), sample.payload.to_bytes()))
            self._cond.notify_all()

    def wait_for(self, expected: set[tuple[str, bytes]], timeout: float = TIMEOUT_S) -> None:
        with self._cond:
            ok = self._cond.wait_for(lambda: expected <= set(self.items), timeout)
            missing = expected - set(self.items)
        assert ok, f"{len(missing)} of {len(expected)} never arrived, e.g. {sorted(missing)[:3]}"


def batch(ns: str, round_: int) -> list[tuple[str, bytes]]:
    return [
        (f"{ns}/index/L1/s{i:03d}", f"round {round_} seg {i}".encode()) for i in range(SEGMENTS)
    ]


def client_conf(ns: str, endpoint: str, instance: str) -> RuntimeConfig:
    return RuntimeConfig(
        ns=ns, instance=instance, zenoh={"mode": "client", "connect": {"endpoints": [endpoint]}}
    )


@pytest.fixture
def publisher(open_session) -> Iterator[ReliablePublisher]:
    publisher = ReliablePublisher(open_session(), DeliverySettings(cache_samples=8))
    yield publisher
    publisher.undeclare()


def put_all(publisher: ReliablePublisher, items: list[tuple[str, bytes]]) -> None:
    for key, payload in items:
        publisher.put(key, payload)


def routed(session: zenoh.Session, listener: zenoh.Session, ns: str) -> None:
    """Returns once everything ``session`` put so far has passed the router: a marker put
    after it reaches ``listener`` (a session's puts of one priority leave, and are routed,
    in order). Without it a put may still be in flight when a subscriber is declared."""
    arrived = threading.Event()
    subscriber = listener.declare_subscriber(f"{ns}/marker", lambda _sample: arrived.set())
    try:
        for _ in range(int(TIMEOUT_S / 0.2)):  # until the subscription has reached the router
            session.put(f"{ns}/marker", b"")
            if arrived.wait(0.2):
                return
        raise AssertionError("the marker never arrived")
    finally:
        subscriber.undeclare()


def test_a_returning_subscriber_gets_what_it_missed_and_a_late_one_the_history(
    publisher: ReliablePublisher, router: str, namespace: str
) -> None:
    first, second = batch(namespace, 1), batch(namespace, 2)
    put_all(publisher, first)  # nobody listens yet: only the caches have them
    got = Received()
    with ServiceRuntime("filtering", client_conf(namespace, router, "a")) as rt:
        rt.declare_subscriber(f"{namespace}/index/**", got, reliable=True)
        got.wait_for(set(first))
    put_all(publisher, second)  # published while the subscriber is down
    again = Received()
    with ServiceRuntime("filtering", client_conf(namespace, router, "a")) as rt:
        rt.declare_subscriber(f"{namespace}/index/**", again, reliable=True)
        again.wait_for(set(first) | set(second))  # both rounds are within the cache (8 per key)


def test_the_cache_window_is_per_key_and_bounded(open_session, router: str, namespace: str) -> None:
    publisher = ReliablePublisher(open_session(), DeliverySettings(cache_samples=2))
    rounds = [batch(namespace, r) for r in range(4)]
    for items in rounds:
        put_all(publisher, items)
    got = Received()
    with ServiceRuntime("filtering", client_conf(namespace, router, "a")) as rt:
        rt.declare_subscriber(f"{namespace}/index/**", got, reliable=True)
        got.wait_for(set(rounds[2]) | set(rounds[3]))  # the last two per key
        assert not set(rounds[0]) & set(got.items)  # older than the window: gone
    assert len(publisher) == SEGMENTS
    publisher.undeclare()


def test_messages_published_while_the_router_restarts_arrive_after_it(
    free_port: int, namespace: str
) -> None:
    endpoint = f"tcp/127.0.0.1:{free_port}"
    settings = {"mode": "router", "listen": {"endpoints": [endpoint]}, "scouting": {"delay": 0}}
    router = zenoh.open(zenoh_config(settings))
    sessions: list[zenoh.Session] = []
    try:
        pub_session = zenoh.open(
            zenoh_config({"mode": "client", "connect": {"endpoints": [endpoint]}})
        )
        sessions.append(pub_session)
        publisher = ReliablePublisher(pub_session, DeliverySettings(cache_samples=8))
        got = Received()
        with ServiceRuntime("filtering", client_conf(namespace, endpoint, "a")) as rt:
            rt.declare_subscriber(f"{namespace}/index/**", got, reliable=True)
            put_all(publisher, batch(namespace, 1))
            got.wait_for(set(batch(namespace, 1)))
            router.close()
            put_all(publisher, batch(namespace, 2))  # nobody can route these now
            router = zenoh.open(zenoh_config(settings))  # same port: clients come back
            got.wait_for(set(batch(namespace, 2)), timeout=30)
            put_all(publisher, batch(namespace, 3))
            got.wait_for(set(batch(namespace, 3)))
        publisher.undeclare()
    finally:
        for session in sessions:
            session.close()
        router.close()


def test_messages_published_while_a_link_is_cut_arrive_once_it_is_back(
    publisher: ReliablePublisher,
    router: str,
    namespace: str,
    link_proxy: Callable[[int], LinkProxy],
) -> None:
    proxy = link_proxy(int(router.rsplit(":", 1)[1]))
    got = Received()
    with ServiceRuntime("filtering", client_conf(namespace, proxy.endpoint, "a")) as rt:
        rt.declare_subscriber(f"{namespace}/index/**", got, reliable=True)
        put_all(publisher, batch(namespace, 1))
        got.wait_for(set(batch(namespace, 1)))
        proxy.cut()
        put_all(publisher, batch(namespace, 2))
        proxy.restore()
        assert proxy.wait_connections(2, TIMEOUT_S), "the client did not reconnect"
        put_all(publisher, batch(namespace, 3))
        got.wait_for(set(batch(namespace, 2)) | set(batch(namespace, 3)))


def test_a_publisher_bounded_below_its_keys_delivers_every_key_live(
    open_session, router: str, namespace: str
) -> None:
    publisher = ReliablePublisher(
        open_session(), DeliverySettings(cache_samples=8, max_publishers=10)
    )
    got = Received()
    with ServiceRuntime("filtering", client_conf(namespace, router, "a")) as rt:
        rt.declare_subscriber(f"{namespace}/index/**", got, reliable=True)
        # a first message proves the subscription is routed before the rounds begin
        publisher.put(f"{namespace}/index/L0/s000", b"hello")
        got.wait_for({(f"{namespace}/index/L0/s000", b"hello")})
        for r in range(3):  # 40 keys, 10 publishers: 9 keys cached, 31 put plainly
            put_all(publisher, batch(namespace, r))
        got.wait_for(set().union(*(batch(namespace, r) for r in range(3))))
    assert len(publisher) == 10 and publisher.plain_puts == 3 * (SEGMENTS - 9)
    publisher.undeclare()


def test_a_returning_subscriber_recovers_the_keys_within_the_bound(
    open_session, router: str, namespace: str
) -> None:
    session, listener = open_session(), open_session()
    publisher = ReliablePublisher(session, DeliverySettings(cache_samples=8, max_publishers=10))
    first, second = batch(namespace, 1), batch(namespace, 2)
    put_all(publisher, first)  # nobody listens: only the first 10 keys have caches
    routed(session, listener, namespace)
    cached = {(key, payload) for key, payload in first if publisher.cached(key)}
    assert len(cached) == 10
    got = Received()
    with ServiceRuntime("filtering", client_conf(namespace, router, "a")) as rt:
        rt.declare_subscriber(f"{namespace}/index/**", got, reliable=True)
        got.wait_for(cached)
    put_all(publisher, second)  # published while the subscriber is down
    routed(session, listener, namespace)
    again = Received()
    with ServiceRuntime("filtering", client_conf(namespace, router, "a")) as rt:
        rt.declare_subscriber(f"{namespace}/index/**", again, reliable=True)
        missed = {(key, payload) for key, payload in second if publisher.cached(key)}
        again.wait_for(cached | missed)
        # what was put plainly reached nobody and is not recovered
        assert set(again.items) <= cached | missed
    assert not set(got.items) - cached
    publisher.undeclare()
