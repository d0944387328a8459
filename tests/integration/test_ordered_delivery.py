"""In-order delivery of the raw chain (services/runtime/ordered.py) through a real router on
loopback: each producer's messages reach the consumer once each, in the producer's order,
whether they came live or were fetched from its outbox (a queue too small to hold them, a
consumer that was away), and a restarted consumer resumes right after its position."""

from __future__ import annotations

from pathlib import Path

import zenoh

from services.runtime.delivery import DeliverySettings, OutboxSettings, ReliablePublisher
from services.runtime.ordered import Item, OrderedSubscription

TIMEOUT_S = 30.0
SUBSCRIPTIONS = {"raw": "{ns}/raw/**", "gps": "{ns}/gps/*"}


def messages(ns: str, first: int, n: int) -> list[tuple[str, bytes]]:
    """A gateway's stream: two units' chunks and the train's fixes, interleaved."""
    keys = [f"{ns}/raw/T1/u0", f"{ns}/gps/T1", f"{ns}/raw/T1/u1"]
    return [(keys[i % 3], b"%06d" % i + bytes(1000)) for i in range(first, first + n)]


def settings(tmp_path: Path) -> DeliverySettings:
    return DeliverySettings(replay_s=0.5, outbox=OutboxSettings(dir=str(tmp_path)))


def subscribe(session, ns, tmp_path, **options) -> OrderedSubscription:
    subscriptions = {kind: key.format(ns=ns) for kind, key in SUBSCRIPTIONS.items()}
    return OrderedSubscription(
        session,
        ns,
        subscriptions,
        lambda producer: producer.startswith("gateway/"),
        settings=settings(tmp_path),
        **options,
    )


def take(subscription: OrderedSubscription, n: int) -> list[Item]:
    got: list[Item] = []
    while len(got) < n:
        batch = subscription.take(n - len(got), timeout=TIMEOUT_S)
        assert batch, f"only {len(got)} of {n} items within {TIMEOUT_S} s"
        got += batch
    return got


def publish(publisher: ReliablePublisher, items: list[tuple[str, bytes]]) -> None:
    for key, payload in items:
        publisher.put(key, payload)
    assert publisher.flush(TIMEOUT_S)


def test_a_stream_larger_than_the_queue_arrives_once_in_order(open_session, namespace, tmp_path):
    session = open_session()
    gateway = ReliablePublisher.open(session, namespace, "gateway", "a", settings(tmp_path))
    subscription = subscribe(
        open_session(), namespace, tmp_path, capacity_bytes=20_000, fetch_limit=40
    )
    try:
        sent = messages(namespace, 0, 600)
        publish(gateway, sent)  # the consumer takes nothing meanwhile: its queue overflows
        got = take(subscription, len(sent))
        assert [(item.key, item.payload) for item in got] == sent
        assert [item.seq for item in got] == list(range(1, 601))
        assert {item.producer for item in got} == {"gateway/a"}
        assert [item.kind for item in got[:3]] == ["raw", "gps", "raw"]
        assert subscription.fetched > 0  # what the queue could not hold came from the outbox
        assert subscription.take(10, timeout=1.0) == []  # nothing twice
    finally:
        subscription.undeclare()
        gateway.undeclare()


def test_a_consumer_resumes_right_after_its_position(open_session, namespace, tmp_path):
    session = open_session()
    gateway = ReliablePublisher.open(session, namespace, "gateway", "a", settings(tmp_path))
    first = subscribe(open_session(), namespace, tmp_path)
    try:
        publish(gateway, messages(namespace, 0, 100))
        handled = take(first, 60)  # then it stops: 40 it had queued are not handled
    finally:
        first.undeclare()
    try:
        publish(gateway, messages(namespace, 100, 100))  # while no consumer is there
        position = {"gateway/a": (handled[-1].epoch, handled[-1].seq)}
        second = subscribe(open_session(), namespace, tmp_path, positions=position)
        got = take(second, 140)
        assert [item.seq for item in got] == list(range(61, 201))
        assert [item.payload for item in got] == [p for _, p in messages(namespace, 60, 140)]
        publish(gateway, messages(namespace, 200, 5))  # and live after that
        assert [item.seq for item in take(second, 5)] == list(range(201, 206))
        second.undeclare()
    finally:
        gateway.undeclare()


def test_a_producer_with_a_new_outbox_is_read_from_its_start(open_session, namespace, tmp_path):
    session = open_session()
    old = ReliablePublisher.open(session, namespace, "gateway", "a", settings(tmp_path / "old"))
    old_epoch = old.outbox.epoch
    old.undeclare()
    gateway = ReliablePublisher.open(session, namespace, "gateway", "a", settings(tmp_path / "new"))
    subscription = subscribe(
        open_session(), namespace, tmp_path, positions={"gateway/a": (old_epoch, 500)}
    )
    try:
        publish(gateway, messages(namespace, 0, 30))
        got = take(subscription, 30)
        assert [item.seq for item in got] == list(range(1, 31))
        assert {item.epoch for item in got} == {gateway.outbox.epoch}
    finally:
        subscription.undeclare()
        gateway.undeclare()


def test_plain_puts_and_other_producers_pass_as_they_come(open_session, namespace, tmp_path):
    session = open_session()
    subscription = subscribe(open_session(), namespace, tmp_path)
    other = ReliablePublisher.open(session, namespace, "replayer", "x", settings(tmp_path))
    try:
        session.put(
            f"{namespace}/gps/T9", b"plain", congestion_control=zenoh.CongestionControl.BLOCK
        )
        publish(other, [(f"{namespace}/raw/T9/u0", b"other")])
        got = take(subscription, 2)
        assert sorted((item.producer, item.payload) for item in got) == [
            (None, b"other"),
            (None, b"plain"),
        ]
    finally:
        other.undeclare()
        subscription.undeclare()
