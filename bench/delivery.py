"""What at-least-once delivery costs and what it recovers, through a router on loopback.

1. Throughput: ``ReliablePublisher`` (each message recorded in the producer's outbox, then
   put with its position) against plain ``put`` of the same messages on ``SEGMENTS`` keys,
   each received by a consumer (a ``ReliableSubscription``, a plain subscriber).
2. An outage, for each ``--keys N``: the consumer is away while the producer publishes one
   message on each of N keys; it comes back and replays. Reports the messages lost (must be
   0), the time from its return to the last message, and the outbox's size on disk.

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

SEGMENTS, ROUNDS, PAYLOAD = 300, 20, b"x" * 200  # an OnboardIndex is about 200 bytes
WARM_UP = b"w" * 200
WAIT_S = 600.0


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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--keys", type=int, nargs="+", default=[SEGMENTS])
    bench_delivery(tuple(parser.parse_args().keys))


if __name__ == "__main__":
    main()
