"""What at-least-once delivery costs: messages per second through a router on loopback,
``ReliablePublisher`` (cached advanced publishers, one per key) against plain ``put`` of
the same messages on the same keys, received by a recovering advanced subscriber and a
plain one respectively; and how long a returning subscriber takes to get the history of
every key (``SEGMENTS`` keys × ``cache_samples`` messages).

Run: ``.venv/bin/python -m bench.delivery``.
"""

from __future__ import annotations

import socket
import threading
import time
from collections.abc import Callable

import zenoh

from services.runtime.config import zenoh_config
from services.runtime.delivery import (
    DeliverySettings,
    ReliablePublisher,
    declare_reliable_subscriber,
)

SEGMENTS, ROUNDS, PAYLOAD = 300, 20, b"x" * 200  # an OnboardIndex is about 200 bytes
WARM_UP = b"w" * 200
WAIT_S = 60.0


class Counter:
    """Counts the samples whose payload is ``counted`` (warm-up traffic carries another)."""

    def __init__(self, counted: bytes = PAYLOAD) -> None:
        self.n = 0
        self.counted = counted
        self.cond = threading.Condition()

    def __call__(self, sample: zenoh.Sample) -> None:
        if sample.payload.to_bytes() != self.counted:
            return
        with self.cond:
            self.n += 1
            if self.n % 100 == 0:
                self.cond.notify_all()

    def wait(self, n: int) -> None:
        with self.cond:
            assert self.cond.wait_for(lambda: self.n >= n, WAIT_S), f"{self.n} of {n}"


def _throughput(
    sub: zenoh.Session, key_all: str, declare: Callable, put: Callable[[str, bytes], None]
) -> float:
    counter, warm = Counter(), Counter(WARM_UP)
    subscriber = declare(sub, key_all, lambda s: (counter(s), warm(s)))
    keys = [key_all.removesuffix("**") + f"s{i:03d}" for i in range(SEGMENTS)]
    while not warm.n:  # until the subscriber's route has reached the router
        put(keys[0], WARM_UP)
        with warm.cond:
            warm.cond.wait_for(lambda: warm.n > 0, 0.05)
    for key in keys:  # declare the publishers outside the clock
        put(key, WARM_UP)
    total = SEGMENTS * ROUNDS
    started = time.perf_counter()
    for _ in range(ROUNDS):
        for key in keys:
            put(key, PAYLOAD)
    counter.wait(total)
    elapsed = time.perf_counter() - started
    subscriber.undeclare()
    return SEGMENTS * ROUNDS / elapsed


def bench_delivery() -> None:
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
    reliable = ReliablePublisher(pub, DeliverySettings(cache_samples=64))
    try:
        plain_rate = _throughput(
            sub,
            "bench/plain/**",
            lambda s, k, h: s.declare_subscriber(k, h),
            lambda k, p: pub.put(k, p, congestion_control=zenoh.CongestionControl.BLOCK),
        )
        reliable_rate = _throughput(
            sub, "bench/reliable/**", declare_reliable_subscriber, reliable.put
        )
        counter = Counter()
        started = time.perf_counter()
        late = declare_reliable_subscriber(sub, "bench/reliable/**", counter)
        history = SEGMENTS * ROUNDS  # the cache holds them all (64 per key)
        counter.wait(history)
        history_s = time.perf_counter() - started
        late.undeclare()
    finally:
        reliable.undeclare()
        pub.close()
        sub.close()
        router.close()
    print(
        f"delivery: reliable {reliable_rate:,.0f} msg/s vs plain put {plain_rate:,.0f} msg/s "
        f"(ratio {reliable_rate / plain_rate:.2f}; {SEGMENTS} keys, 200 B); a returning "
        f"subscriber gets the history of {history:,} messages ({SEGMENTS} keys) in "
        f"{history_s:.2f} s"
    )


if __name__ == "__main__":
    bench_delivery()
