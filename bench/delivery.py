"""What at-least-once delivery costs and what it recovers, through a router on loopback.

1. Throughput: ``ReliablePublisher`` (each message recorded in the producer's outbox, then
   put with its position) against plain ``put`` of the same messages on ``SEGMENTS`` keys,
   each received by a consumer (a ``ReliableSubscription``, a plain subscriber).
2. An outage, for each ``--keys N``: the consumer is away while the producer publishes one
   message on each of N keys; it comes back and replays. Reports the messages lost (must be
   0), the time from its return to the last message, and the outbox's size on disk.

3. The raw chain: 56 kB chunks of 10 units from a gateway's outbox to an in-order consumer
   (``OrderedSubscription``) against plain ``put`` to a plain subscriber; then the consumer
   stops halfway, the gateway publishes as much again, and a consumer resuming at the first
   one's position gets the rest: in order, none twice, none lost.

Run: ``.venv/bin/python -m bench.delivery [--keys 300 100000]``.
"""

from __future__ import annotations

import argparse
import socket
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path

import zenoh

from services.runtime.config import zenoh_config
from services.runtime.delivery import (
    DeliverySettings,
    OutboxSettings,
    ReliablePublisher,
    ReliableSubscription,
)
from services.runtime.ordered import OrderedSubscription

SEGMENTS, ROUNDS, PAYLOAD = 300, 20, b"x" * 200  # an OnboardIndex is about 200 bytes
WARM_UP = b"w" * 200
WAIT_S = 600.0
RAW_CHUNKS, RAW_PAYLOAD = 2000, b"r" * 56_000  # a 1 s chunk at 2000 Hz of 7 channels


class Counter:
    """Counts the distinct keys of ``counted`` payloads (warm-up traffic carries another)."""

    def __init__(self, counted: bytes = PAYLOAD) -> None:
        self.n = 0
        self.keys: set[str] = set()
        self.counted = counted
        self.cond = threading.Condition()

    def __call__(self, key: str, payload: bytes) -> None:
        if payload != self.counted:
            return
        with self.cond:
            self.n += 1
            self.keys.add(key)
            if self.n % 100 == 0:
                self.cond.notify_all()

    def wait(self, n: int, timeout: float = WAIT_S) -> bool:
        with self.cond:
            return self.cond.wait_for(lambda: self.n >= n, timeout)


def _throughput(
    subscribe: Callable[[Callable[[str, bytes], None]], Callable[[], None]],
    prefix: str,
    put: Callable[[str, bytes], None],
) -> float:
    counter, warm = Counter(), Counter(WARM_UP)
    unsubscribe = subscribe(lambda k, p: (counter(k, p), warm(k, p)))
    keys = [f"{prefix}/s{i:03d}" for i in range(SEGMENTS)]
    while not warm.n:  # until the subscriber's route has reached the router
        put(keys[0], WARM_UP)
        with warm.cond:
            warm.cond.wait_for(lambda: warm.n > 0, 0.05)
    total = SEGMENTS * ROUNDS
    started = time.perf_counter()
    for _ in range(ROUNDS):
        for key in keys:
            put(key, PAYLOAD)
    assert counter.wait(total), f"{counter.n} of {total}"
    elapsed = time.perf_counter() - started
    unsubscribe()
    return total / elapsed


def _replaying(
    session: zenoh.Session,
    key: str,
    on: Callable[[str, bytes], None],
    settings: DeliverySettings,
    positions: dict[str, tuple[str | None, int]] | None = None,
) -> tuple[ReliableSubscription, Callable[[], None]]:
    """A consumer resuming at ``positions`` (as one that persisted them would)."""
    kept = {p: (e, w) for p, (e, w) in (positions or {}).items() if e is not None}
    subscription: list[ReliableSubscription] = []
    subscription.append(
        ReliableSubscription(
            session,
            "bench",
            {"k": key},
            lambda _kind, k, p: on(k, p),
            lambda *mark: subscription[0].confirm(*mark),
            settings=settings,
            positions=kept,
        )  # fmt: skip
    )
    return subscription[0], subscription[0].undeclare


def bench_delivery(outage_keys: tuple[int, ...] = (SEGMENTS,)) -> None:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        endpoint = f"tcp/127.0.0.1:{s.getsockname()[1]}"
    router = zenoh.open(
        zenoh_config(
            {"mode": "router", "listen": {"endpoints": [endpoint]}, "scouting": {"delay": 0}}
        )
    )
    client = {"mode": "client", "connect": {"endpoints": [endpoint]}}
    pub, sub = zenoh.open(zenoh_config(client)), zenoh.open(zenoh_config(client))
    with tempfile.TemporaryDirectory() as tmp:
        settings = DeliverySettings(replay_s=1.0, outbox=OutboxSettings(dir=tmp))
        reliable = ReliablePublisher.open(pub, "bench", "bench", "a", settings)
        try:
            plain_rate = _throughput(
                lambda on: (
                    sub.declare_subscriber(
                        "bench/plain/**", lambda s: on(str(s.key_expr), s.payload.to_bytes())
                    ).undeclare
                ),
                "bench/plain",
                lambda k, p: pub.put(k, p, congestion_control=zenoh.CongestionControl.BLOCK),
            )
            reliable_rate = _throughput(
                lambda on: _replaying(sub, "bench/reliable/**", on, settings)[1],
                "bench/reliable",
                reliable.put,
            )
            print(
                f"delivery: reliable {reliable_rate:,.0f} msg/s vs plain put "
                f"{plain_rate:,.0f} msg/s (ratio {reliable_rate / plain_rate:.2f}; "
                f"{SEGMENTS} keys, 200 B)"
            )
            for n in outage_keys:
                _outage(sub, reliable, settings, n, Path(tmp))
            _raw_chain(pub, sub, settings)
        finally:
            reliable.undeclare()
            pub.close()
            sub.close()
            router.close()


def _outage(
    sub: zenoh.Session,
    reliable: ReliablePublisher,
    settings: DeliverySettings,
    n: int,
    tmp: Path,
) -> None:
    """The consumer away while ``n`` keys get a message each; then it returns."""
    prefix = f"bench/outage{n}"
    counter = Counter()
    subscription, undeclare = _replaying(sub, f"{prefix}/**", counter, settings)
    # it has seen the producer (one round), then leaves; only the outbox sees what follows
    deadline = time.monotonic() + WAIT_S
    while not subscription.rounds:
        assert time.monotonic() < deadline, "no replay round"
        threading.Event().wait(0.05)
    positions = subscription.positions()
    undeclare()
    started = time.perf_counter()
    for i in range(n):
        reliable.put(f"{prefix}/s{i:06d}", PAYLOAD)
    reliable.flush()
    publish_s = time.perf_counter() - started
    counter = Counter()
    back = time.perf_counter()
    _, undeclare = _replaying(sub, f"{prefix}/**", counter, settings, positions)
    counter.wait(n)
    replay_s = time.perf_counter() - back
    undeclare()
    size = sum(f.stat().st_size for f in tmp.iterdir())
    print(
        f"delivery outage, {n:,} keys: lost {n - len(counter.keys):,}, published in "
        f"{publish_s:.2f} s, replayed {len(counter.keys):,} in {replay_s:.2f} s after the "
        f"consumer's return; outbox {size / 1e6:.1f} MB on disk ({reliable.outbox.head:,} "
        "entries in all)"
    )


def _raw_chain(pub: zenoh.Session, sub: zenoh.Session, settings: DeliverySettings) -> None:
    """Raw chunks in order from a gateway's outbox, against plain puts; then a resume."""
    keys = [f"bench/raw/T{i:02d}/u0" for i in range(10)]
    counter, warm = Counter(RAW_PAYLOAD), Counter(WARM_UP)
    plain = sub.declare_subscriber(
        "bench/raw/**",
        lambda s: (
            k := str(s.key_expr),
            p := s.payload.to_bytes(),
            counter(k, p),
            warm(k, p),
        ),  # fmt: skip
    )
    while not warm.n:  # until the subscriber's route has reached the router
        pub.put(keys[0], WARM_UP)
        with warm.cond:
            warm.cond.wait_for(lambda: warm.n > 0, 0.05)
    started = time.perf_counter()
    for i in range(RAW_CHUNKS):
        pub.put(keys[i % 10], RAW_PAYLOAD, congestion_control=zenoh.CongestionControl.BLOCK)
    assert counter.wait(RAW_CHUNKS), f"{counter.n} of {RAW_CHUNKS}"
    plain_s = time.perf_counter() - started
    plain.undeclare()

    gateway = ReliablePublisher.open(pub, "bench", "gateway", "raw", settings, raw=True)

    def consumer(positions=None) -> OrderedSubscription:
        return OrderedSubscription(
            sub, "bench", {"raw": "bench/raw/**"}, lambda p: p.startswith("gateway/"),
            settings=settings, positions=positions,
        )  # fmt: skip

    def take(subscription: OrderedSubscription, n: int) -> list:
        got: list = []
        while len(got) < n:
            batch = subscription.take(n - len(got), timeout=WAIT_S)
            assert batch, f"{len(got)} of {n}"
            got += batch
        return got

    try:
        first = consumer()
        started = time.perf_counter()
        for i in range(RAW_CHUNKS):
            gateway.put(keys[i % 10], RAW_PAYLOAD)
        got = take(first, RAW_CHUNKS // 2)
        first.undeclare()  # stops halfway: the rest stays in the gateway's outbox
        ordered_s = time.perf_counter() - started
        for i in range(RAW_CHUNKS):
            gateway.put(keys[i % 10], RAW_PAYLOAD)
        assert gateway.flush(WAIT_S)
        back = time.perf_counter()
        second = consumer({gateway.producer: (got[-1].epoch, got[-1].seq)})
        rest = take(second, RAW_CHUNKS * 2 - len(got))
        resume_s = time.perf_counter() - back
        fetched = second.fetched
        second.undeclare()
    finally:
        gateway.undeclare()
    seqs = [item.seq for item in got + rest]
    in_order = seqs == list(range(1, 2 * RAW_CHUNKS + 1))
    mb = len(RAW_PAYLOAD) / 1e6
    plain_rate, ordered_rate = RAW_CHUNKS / plain_s, RAW_CHUNKS / 2 / ordered_s
    print(
        f"raw chain: in order from the gateway's outbox {ordered_rate:,.0f} chunks/s "
        f"({ordered_rate * mb:,.0f} MB/s) vs plain put {plain_rate:,.0f} chunks/s "
        f"({plain_rate * mb:,.0f} MB/s), ratio {ordered_rate / plain_rate:.2f} (56 kB chunks); "
        f"a consumer resuming at its position got the other {len(rest):,} in {resume_s:.2f} s "
        f"({fetched:,} fetched from the outbox): "
        f"{'in order, none twice, none lost' if in_order else 'NOT IN ORDER OR INCOMPLETE'}"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--keys", type=int, nargs="+", default=[SEGMENTS])
    bench_delivery(tuple(parser.parse_args().keys))


if __name__ == "__main__":
    main()
