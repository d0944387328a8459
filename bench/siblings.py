"""What a put costs next to many cached keys of the same parent.

Found while measuring ``bench.restart`` at 100,000 segments on one line: its restored
states went out at ~1,000/s, 0.95 ms a put. The cause is Zenoh's, not the filter's: a put
on a key whose parent holds many declared resources (a filtering instance's advanced
publishers, ``services.delivery.max_publishers`` = 2,000 by default, are siblings of the
keys it puts plainly past that bound) costs time in proportion to those siblings, whichever
session puts it and whether or not the key is new.

Workload: a router and three client sessions on loopback, a subscriber on ``NS/**``;
``SIBLINGS`` advanced publishers (the project's ``ReliablePublisher`` settings) on
``NS/state/L1/p…``; then ``PUTS`` plain puts (BLOCK, 2 kB) from another session on
``NS/state/L1/s…`` (siblings of the publishers), and the same number on keys of other
lines (``NS/state/Lk/s…``, 100 segments a line, no publisher beside them). Baseline in the
same run: the same puts with no publisher declared. Figure: µs a put, and the ratios.

Run: ``.venv/bin/python -m bench.siblings [siblings]``.
"""

from __future__ import annotations

import sys
import threading
import time

import zenoh

from bench.soak import free_port
from services.runtime.config import zenoh_config
from services.runtime.delivery import DeliverySettings, ReliablePublisher

SIBLINGS, PUTS, PAYLOAD = 2000, 5000, b"x" * 2000
NS = "tfsiblings"
BLOCK = zenoh.CongestionControl.BLOCK


def _put_us(session: zenoh.Session, keys: list[str]) -> float:
    started = time.perf_counter()
    for key in keys:
        session.put(key, PAYLOAD, congestion_control=BLOCK)
    return (time.perf_counter() - started) / len(keys) * 1e6


def bench_siblings(siblings: int = SIBLINGS) -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = zenoh.open(zenoh_config({"mode": "router", "listen": {"endpoints": [endpoint]}}))
    client = {"mode": "client", "connect": {"endpoints": [endpoint]}}
    sessions = [zenoh.open(zenoh_config(client)) for _ in range(3)]
    listener, publishing, putting = sessions
    received, cond = [0], threading.Condition()

    def on_sample(_sample: zenoh.Sample) -> None:
        with cond:
            received[0] += 1
            cond.notify_all()

    subscriber = listener.declare_subscriber(f"{NS}/**", on_sample)
    publisher = ReliablePublisher(publishing, DeliverySettings(max_publishers=siblings))
    try:
        same_line = [f"{NS}/state/L1/s{i:06d}" for i in range(PUTS)]
        other_lines = [f"{NS}/state/L{100 + i // 100:03d}/s{i:06d}" for i in range(PUTS)]
        alone_same, alone_other = _put_us(putting, same_line), _put_us(putting, other_lines)
        for i in range(siblings):
            publisher.put(f"{NS}/state/L1/p{i:06d}", PAYLOAD)
        beside_same, beside_other = _put_us(putting, same_line), _put_us(putting, other_lines)
        with cond:  # every put arrived (BLOCK: none dropped)
            arrived = cond.wait_for(lambda: received[0] >= 4 * PUTS + siblings, 120.0)
    finally:
        publisher.undeclare()
        subscriber.undeclare()
        for session in sessions:
            session.close()
        router.close()
    print(
        f"siblings  a plain put (BLOCK, 2 kB) from a session without publishers: with no"
        f" publisher declared {alone_same:.1f} µs; beside {siblings:,} cached publishers of"
        f" the same line {beside_same:.1f} µs (ratio {beside_same / alone_same:.0f}x), on other"
        f" lines {beside_other:.1f} µs (ratio {beside_other / alone_other:.1f}x, alone"
        f" {alone_other:.1f}); every put arrived: {arrived}"
    )


if __name__ == "__main__":
    bench_siblings(*(int(a) for a in sys.argv[1:]))
