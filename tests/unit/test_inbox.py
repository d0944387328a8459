"""The runtime's inbox: FIFO across memory and the disk spill, never waiting in put()."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from services.runtime.inbox import Inbox, LatestInbox


def items(n: int, seed: int = 0) -> list[tuple[str, str, bytes]]:
    rng = np.random.default_rng(seed)
    sizes = rng.integers(0, 3000, n)
    return [(f"k{i % 3}", f"ns/x/{i}", rng.bytes(int(size))) for i, size in enumerate(sizes)]


def test_order_is_kept_across_memory_and_spill_with_a_concurrent_worker():
    inbox = Inbox(memory_bytes=20_000)
    sent = items(5_000)
    got: list = []

    def work() -> None:
        rng = np.random.default_rng(1)
        while (batch := inbox.take(int(rng.integers(1, 64)), timeout=5.0)) is not None:
            got.extend(batch)

    worker = threading.Thread(target=work)
    worker.start()
    for item in sent:
        inbox.put(*item)
    inbox.close()
    worker.join(30)
    assert got == sent
    stats = inbox.stats()
    assert stats.spilled > 0 and stats.received == stats.taken == len(sent)
    assert (stats.depth, stats.memory_bytes, stats.spill_bytes) == (0, 0, 0)


def test_a_backlog_beyond_memory_waits_on_disk_and_comes_back_in_order():
    inbox = Inbox(memory_bytes=10_000)
    sent = items(2_000, seed=2)
    for item in sent:
        inbox.put(*item)  # nobody takes: memory fills, the rest goes to disk
    stats = inbox.stats()
    assert stats.memory_bytes <= 10_000 and stats.spill_bytes > 0 and stats.depth == len(sent)
    got = []
    while len(got) < len(sent):
        got.extend(inbox.take(100, timeout=0))
    assert got == sent
    inbox.put("k", "ns/after", b"x")  # the spill file starts again from its beginning
    assert inbox.take(10, timeout=0) == [("k", "ns/after", b"x")]


def test_a_batch_from_the_spill_file_is_as_large_as_asked():
    """A worker that asks for a backlog's batch gets it from disk too, not one slice of the
    spill file (the filtering service's batches of a deep backlog were ~6,000 messages)."""
    inbox = Inbox(memory_bytes=50_000)
    sent = items(3_000, seed=3)  # ~4.5 MB: almost all of it spilled, several slices
    for item in sent:
        inbox.put(*item)
    assert inbox.stats().spill_bytes > 3 * (1 << 20)
    assert inbox.take(2_500, timeout=0) == sent[:2_500]
    assert inbox.take(2_500, timeout=0) == sent[2_500:]
    assert inbox.stats().depth == 0


def test_take_times_out_empty_and_ends_once_closed_and_drained():
    inbox = Inbox()
    assert inbox.take(5, timeout=0.01) == []
    inbox.put("k", "ns/a", b"1")
    inbox.close()
    inbox.put("k", "ns/b", b"2")  # after close: ignored
    assert inbox.take(5, timeout=0.01) == [("k", "ns/a", b"1")]
    assert inbox.take(5, timeout=0.01) is None


def test_memory_budget_must_be_positive():
    with pytest.raises(ValueError, match="memory_bytes"):
        Inbox(memory_bytes=0)


def test_the_latest_inbox_keeps_the_newest_of_a_key_and_every_unkeyed_item():
    # items (key, version): key None queues in order
    inbox = LatestInbox(2, key=lambda item: item[0], version=lambda item: item[1])
    for item in (("a", 1), ("a", 3), ("a", 2)):  # a late older item does not win
        inbox.put(item)
    for item in (("b", 1), (None, 5), (None, 4)):
        inbox.put(item)
    assert inbox.take(timeout=0) == [("a", 3), ("b", 1), (None, 5), (None, 4)]
    assert inbox.superseded == 2 and inbox.dropped == 0
    for item in (("a", 1), ("b", 1), ("c", 1), (None, 1), (None, 2), (None, 3)):
        inbox.put(item)  # capacity 2: the oldest key and the oldest queued item go
    assert inbox.take(timeout=0) == [("b", 1), ("c", 1), (None, 2), (None, 3)]
    assert inbox.dropped == 2
    assert inbox.take(timeout=0) == []
    inbox.put(("a", 9))
    inbox.close()
    inbox.put(("b", 9))  # after close: ignored
    assert inbox.take(timeout=None) == [("a", 9)]
    assert inbox.take(timeout=None) is None


def test_the_latest_inbox_wakes_its_worker():
    inbox = LatestInbox(4, key=lambda item: item, version=lambda item: 0.0)
    got: list = []
    worker = threading.Thread(target=lambda: got.append(inbox.take(timeout=None)))
    worker.start()
    inbox.put("x")
    worker.join(timeout=10)
    assert got == [["x"]]
