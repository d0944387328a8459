"""At-least-once delivery (services/runtime/delivery.py) through a real router on loopback:
a consumer that was away (restarted, behind a restarted router, behind a cut link) gets
every message published meanwhile, on any number of keys, and a producer restarted on its
outbox still serves what it published before."""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
import zenoh

from bench.linkproxy import LinkProxy
from services.runtime.config import RuntimeConfig, zenoh_config
from services.runtime.delivery import DeliverySettings, OutboxSettings, ReliablePublisher
from services.runtime.service import ServiceRuntime

TIMEOUT_S = 30.0
SEGMENTS = 40
MANY_KEYS = 3000  # more keys than any per-key cache could hold
REPLAY_S = 0.5


class Received:
    """(key, payload) pairs a consumer's batches held, with a wait for a set of them."""

    def __init__(self) -> None:
        self.items: list[tuple[str, bytes]] = []
        self._cond = threading.Condition()

    def __call__(self, batch: list[tuple[str, str, bytes]]) -> None:
        with self._cond:
            self.items.extend((key, payload) for _, key, payload in batch)
            self._cond.notify_all()

    def wait_for(self, expected: set[tuple[str, bytes]], timeout: float = TIMEOUT_S) -> None:
        with self._cond:
            ok = self._cond.wait_for(lambda: expected <= set(self.items), timeout)
            missing = expected - set(self.items)
        assert ok, f"{len(missing)} of {len(expected)} never arrived, e.g. {sorted(missing)[:3]}"


def batch(ns: str, round_: int, keys: int = SEGMENTS) -> list[tuple[str, bytes]]:
    return [(f"{ns}/index/L1/s{i:04d}", f"round {round_} seg {i}".encode()) for i in range(keys)]


def settings(tmp_path: Path) -> DeliverySettings:
    return DeliverySettings(replay_s=REPLAY_S, outbox=OutboxSettings(dir=str(tmp_path / "ob")))


def client_conf(ns: str, endpoint: str, instance: str) -> RuntimeConfig:
    return RuntimeConfig(
        ns=ns,
        instance=instance,
        zenoh={"mode": "client", "connect": {"endpoints": [endpoint]}},
        services={"delivery": {"replay_s": REPLAY_S}},
    )


def consume(rt: ServiceRuntime, got: Received) -> None:
    rt.subscribe_batches({"index": f"{rt.ns}/index/**"}, got, reliable=True)


@pytest.fixture
def publisher(open_session, namespace: str, tmp_path: Path) -> Iterator[ReliablePublisher]:
    publisher = ReliablePublisher.open(
        open_session(), namespace, "extraction", "a", settings(tmp_path)
    )
    yield publisher
    publisher.undeclare()


def put_all(publisher: ReliablePublisher, items: list[tuple[str, bytes]]) -> None:
    for key, payload in items:
        publisher.put(key, payload)
    assert publisher.flush(TIMEOUT_S)


def test_a_returning_consumer_gets_what_it_missed_on_3000_keys(
    publisher: ReliablePublisher, router: str, namespace: str
) -> None:
    first, second = batch(namespace, 1), batch(namespace, 2, MANY_KEYS)
    put_all(publisher, first)  # nobody listens yet: only the outbox has them
    got = Received()
    with ServiceRuntime("filtering", client_conf(namespace, router, "a")) as rt:
        consume(rt, got)
        got.wait_for(set(first))
    put_all(publisher, second)  # published while the consumer is down
    again = Received()
    with ServiceRuntime("filtering", client_conf(namespace, router, "a")) as rt:
        consume(rt, again)
        again.wait_for(set(first) | set(second))
    assert publisher.outbox.head == SEGMENTS + MANY_KEYS


def test_a_producer_restarted_on_its_outbox_serves_what_it_published_before(
    open_session, router: str, namespace: str, tmp_path: Path
) -> None:
    session = open_session()
    publisher = ReliablePublisher.open(session, namespace, "extraction", "a", settings(tmp_path))
    first = batch(namespace, 1, 500)
    put_all(publisher, first)
    session.close()  # the process dies: nothing undeclared, the outbox file stays
    publisher.outbox.close()
    again = ReliablePublisher.open(open_session(), namespace, "extraction", "a", settings(tmp_path))
    assert again.outbox.head == 500  # the numbering continues
    got = Received()
    with ServiceRuntime("filtering", client_conf(namespace, router, "a")) as rt:
        consume(rt, got)
        got.wait_for(set(first))
        second = batch(namespace, 2)
        put_all(again, second)
        got.wait_for(set(second))
    assert again.outbox.head == 500 + SEGMENTS
    again.undeclare()


def test_messages_published_while_the_router_restarts_arrive_after_it(
    free_port: int, namespace: str, tmp_path: Path
) -> None:
    endpoint = f"tcp/127.0.0.1:{free_port}"
    conf = {"mode": "router", "listen": {"endpoints": [endpoint]}, "scouting": {"delay": 0}}
    router = zenoh.open(zenoh_config(conf))
    sessions: list[zenoh.Session] = []
    try:
        pub_session = zenoh.open(
            zenoh_config({"mode": "client", "connect": {"endpoints": [endpoint]}})
        )
        sessions.append(pub_session)
        publisher = ReliablePublisher.open(
            pub_session, namespace, "extraction", "a", settings(tmp_path)
        )
        got = Received()
        with ServiceRuntime("filtering", client_conf(namespace, endpoint, "a")) as rt:
            consume(rt, got)
            put_all(publisher, batch(namespace, 1))
            got.wait_for(set(batch(namespace, 1)))
            router.close()
            put_all(publisher, batch(namespace, 2, MANY_KEYS))  # nobody can route these now
            router = zenoh.open(zenoh_config(conf))  # same port: clients come back
            got.wait_for(set(batch(namespace, 2, MANY_KEYS)), timeout=60)
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
        consume(rt, got)
        put_all(publisher, batch(namespace, 1))
        got.wait_for(set(batch(namespace, 1)))
        proxy.cut()
        put_all(publisher, batch(namespace, 2))
        proxy.restore()
        assert proxy.wait_connections(2, TIMEOUT_S), "the client did not reconnect"
        put_all(publisher, batch(namespace, 3))
        got.wait_for(set(batch(namespace, 2)) | set(batch(namespace, 3)))


def test_a_full_outbox_still_publishes_live(
    publisher: ReliablePublisher, router: str, namespace: str
) -> None:
    got = Received()
    with ServiceRuntime("filtering", client_conf(namespace, router, "a")) as rt:
        consume(rt, got)
        put_all(publisher, batch(namespace, 1, 1))
        got.wait_for(set(batch(namespace, 1, 1)))  # the subscription is routed
        (pages,) = publisher.outbox._db.execute("PRAGMA page_count").fetchone()
        publisher.outbox._db.execute(f"PRAGMA max_page_count = {pages}")  # no room left
        big = [(key, payload * 500) for key, payload in batch(namespace, 2)]
        put_all(publisher, big)
        got.wait_for(set(big))
    assert publisher.unrecorded == SEGMENTS
