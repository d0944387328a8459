"""The one inbox of a service: Zenoh callbacks → one FIFO → one worker, never blocking Zenoh.

Why it exists. A Zenoh callback runs on the session's receive thread. If it blocks (a full
bounded queue waiting for a slow worker), the session stops reading its link; the router's
queue towards it fills, the router waits ``wait_before_close`` (5 s by default) for room
for a BLOCK message and then **closes the link**, dropping everything queued on it: a flood
would be lost without a trace and the service would go deaf (docs/architecture.md, "No
callback blocks a session"). So :meth:`Inbox.put` never waits on the
worker: it appends to memory while the backlog is small and, beyond ``memory_bytes``,
appends to a spill file on local disk (an anonymous temporary file, gone with the
process), which the worker reads back in order once memory has drained. Back-pressure is
therefore disk, not the network: the session keeps its lease under any backlog, and nothing
is dropped. What is in the inbox when the process dies is lost like any in-flight message;
the at-least-once streams replay it from their producers' outboxes
(:mod:`services.runtime.delivery`).

Order: FIFO over every ``put``; Zenoh calls each subscription's callback on its own thread,
so order holds per key, not across keys.

:class:`LatestInbox` is the variant for a consumer that needs only the newest item of a key
(the viewer draws the latest state of a segment): it holds one item per key, in memory,
bounded, and still never waits in ``put``.
"""

from __future__ import annotations

import logging
import os
import struct
import tempfile
import threading
import time
from collections import deque
from collections.abc import Callable, Hashable
from dataclasses import dataclass
from typing import Generic, TypeVar

log = logging.getLogger(__name__)

Item = tuple[str, str, bytes]  # (kind, key, payload)
T = TypeVar("T")

DEFAULT_MEMORY_BYTES = 64 << 20  # backlog held in memory before it spills to disk
_HEADER = struct.Struct("<III")  # lengths of kind, key, payload
_READ_CHUNK = 1 << 20
_REFILL_BYTES = 1 << 20  # read back from the spill file per refill (under the lock)


@dataclass(frozen=True)
class InboxStats:
    """Counters of an inbox since it was made (for the log, the bench and the health line)."""

    received: int  # items put
    taken: int  # items handed to the worker
    spilled: int  # items that went through the spill file
    depth: int  # items waiting (memory + spill)
    memory_bytes: int  # payload bytes waiting in memory
    spill_bytes: int  # bytes waiting in the spill file
    max_put_s: float  # the longest time a callback spent in put()


class Inbox:
    """A FIFO of ``(kind, key, payload)`` with a memory budget and an on-disk overflow.

    Parameters
    ----------
    memory_bytes
        Payload bytes held in memory; the rest of a backlog goes to the spill file.
    """

    def __init__(self, *, memory_bytes: int = DEFAULT_MEMORY_BYTES) -> None:
        if memory_bytes < 1:
            raise ValueError(f"memory_bytes must be >= 1, got {memory_bytes}")
        self._memory_budget = memory_bytes
        self._items: deque[Item] = deque()
        self._memory = 0
        self._cond = threading.Condition()
        self._closed = False
        self._spill_fd: int | None = None
        self._spill_read = 0  # file offsets of the next record to read / write
        self._spill_write = 0
        self._spill_items = 0
        self._received = self._taken = self._spilled = self._spill_errors = 0
        self._max_put_s = 0.0

    # --- the callback side ---------------------------------------------------------------

    def put(self, kind: str, key: str, payload: bytes) -> None:
        """Append one item; O(1) in memory, one ``pwrite`` when spilling; never waits."""
        started = time.perf_counter()
        with self._cond:
            if self._closed:
                return
            self._received += 1
            size = len(payload) + len(key)
            if self._spill_items == 0 and self._memory + size <= self._memory_budget:
                self._items.append((kind, key, payload))
                self._memory += size
            else:  # keep FIFO: once spilling, everything goes behind the spilled items
                try:
                    self._spill(kind, key, payload)
                except OSError as e:  # disk full: keep it in memory, out of order, not lost
                    self._spill_errors += 1
                    if self._spill_errors == 1 or self._spill_errors % 10_000 == 0:
                        log.error("inbox spill failed (%s): %d items kept in memory", e,
                                  self._spill_errors)  # fmt: skip
                    self._items.append((kind, key, payload))
                    self._memory += size
            self._cond.notify()
            elapsed = time.perf_counter() - started
            if elapsed > self._max_put_s:
                self._max_put_s = elapsed

    def close(self) -> None:
        """No more items; the worker takes what is left, then :meth:`take` returns None."""
        with self._cond:
            self._closed = True
            self._cond.notify_all()

    # --- the worker side -----------------------------------------------------------------

    def take(self, max_items: int = 1, timeout: float | None = None) -> list[Item] | None:
        """Up to ``max_items`` items in order; [] on timeout; None once closed and empty.

        A backlog on disk comes back a slice at a time (:meth:`_refill`), the lock released
        between slices so that puts go on, until ``max_items`` are taken: a worker's batch
        is as large from the spill file as from memory (it was one slice, ~6,000 on-board
        indices, whatever the worker asked for)."""
        batch: list[Item] = []
        with self._cond:
            deadline = None if timeout is None else time.monotonic() + timeout
            while not self._items and self._spill_items == 0:
                if self._closed:
                    self._release_spill()
                    return None
                remaining = None if deadline is None else deadline - time.monotonic()
                if remaining is not None and remaining <= 0:
                    return []
                self._cond.wait(remaining)
            spilled = self._take_into(batch, max_items)
        while spilled and len(batch) < max_items:  # (the live path never loops)
            time.sleep(0)  # the callbacks' puts first
            with self._cond:
                spilled = self._take_into(batch, max_items)
        return batch

    def _take_into(self, batch: list[Item], max_items: int) -> bool:
        """Under the lock: items into ``batch`` up to ``max_items``, reading at most one slice
        back from the spill file first when memory is empty; whether items remain on disk."""
        if not self._items and self._spill_items:
            self._refill()
        taken = 0
        while self._items and len(batch) < max_items:
            item = self._items.popleft()
            self._memory -= len(item[2]) + len(item[1])
            batch.append(item)
            taken += 1
        self._taken += taken
        return self._spill_items > 0

    def stats(self) -> InboxStats:
        with self._cond:
            return InboxStats(
                received=self._received,
                taken=self._taken,
                spilled=self._spilled,
                depth=len(self._items) + self._spill_items,
                memory_bytes=self._memory,
                spill_bytes=self._spill_write - self._spill_read,
                max_put_s=self._max_put_s,
            )

    def __len__(self) -> int:
        with self._cond:
            return len(self._items) + self._spill_items

    # --- the spill file (under the lock) ---------------------------------------------------

    def _spill(self, kind: str, key: str, payload: bytes) -> None:
        if self._spill_fd is None:
            fd, path = tempfile.mkstemp(prefix="trackfusion-inbox-")
            os.unlink(path)  # anonymous: gone with the process
            self._spill_fd = fd
        k, q = kind.encode(), key.encode()
        record = _HEADER.pack(len(k), len(q), len(payload)) + k + q + payload
        if os.pwrite(self._spill_fd, record, self._spill_write) != len(record):
            raise OSError("short write to the spill file (disk full?)")
        self._spill_write += len(record)
        self._spill_items += 1
        self._spilled += 1

    def _refill(self) -> None:
        """Move spilled items back to memory: a slice small enough that the lock is held
        briefly (puts wait on it), at least one item."""
        assert self._spill_fd is not None
        budget = max(1, min(self._memory_budget // 2, _REFILL_BYTES))
        buf, at = b"", 0  # bytes read from the file's read offset, and the next record in it
        while self._spill_items and self._memory < budget:
            if len(buf) - at < _HEADER.size:
                buf = buf[at:] + os.pread(
                    self._spill_fd, _READ_CHUNK, self._spill_read + len(buf) - at
                )
                at = 0
            lk, lq, lp = _HEADER.unpack_from(buf, at)
            end = at + _HEADER.size + lk + lq + lp
            if len(buf) < end:
                buf = buf[at:] + os.pread(
                    self._spill_fd,
                    max(_READ_CHUNK, end - len(buf)),
                    self._spill_read + len(buf) - at,
                )
                end -= at
                at = 0
            start = at + _HEADER.size
            kind = buf[start : start + lk].decode()
            key = buf[start + lk : start + lk + lq].decode()
            payload = buf[start + lk + lq : end]
            self._items.append((kind, key, payload))
            self._memory += len(payload) + len(key)
            self._spill_read += end - at
            self._spill_items -= 1
            at = end
        if self._spill_items == 0:  # drained: start the file again from its beginning
            self._spill_read = self._spill_write = 0
            os.ftruncate(self._spill_fd, 0)

    def _release_spill(self) -> None:
        if self._spill_fd is not None:
            os.close(self._spill_fd)
            self._spill_fd = None


class LatestInbox(Generic[T]):
    """What callbacks hand to one worker when only the newest item of a key matters.

    An item whose ``key(item)`` is not None replaces the held item of that key unless that
    one has the larger ``version`` (an older item arriving late is not written over a newer
    one); items whose key is None queue in order. Both parts hold at most ``capacity``
    items; when full, the oldest entry goes (counted in ``dropped``). :meth:`put` never
    waits on the worker.
    """

    def __init__(
        self,
        capacity: int,
        *,
        key: Callable[[T], Hashable | None],
        version: Callable[[T], float],
    ) -> None:
        if capacity < 1:
            raise ValueError(f"capacity must be >= 1, got {capacity}")
        self._key = key
        self._version = version
        self._keyed: dict[Hashable, T] = {}  # insertion order = age
        self._queued: deque[T] = deque(maxlen=capacity)
        self._capacity = capacity
        self._cond = threading.Condition()
        self._closed = False
        self.dropped = 0  # items lost to a full inbox
        self.superseded = 0  # items replaced by a newer one of their key before being taken

    def put(self, item: T) -> None:
        key = self._key(item)
        with self._cond:
            if self._closed:
                return
            if key is None:
                if len(self._queued) == self._capacity:
                    self.dropped += 1
                self._queued.append(item)
            else:
                held = self._keyed.pop(key, None)  # re-inserted last: the newest entry
                if held is not None:
                    self.superseded += 1
                    if self._version(held) > self._version(item):
                        item = held
                elif len(self._keyed) >= self._capacity:
                    del self._keyed[next(iter(self._keyed))]
                    self.dropped += 1
                self._keyed[key] = item
            self._cond.notify()

    def take(self, timeout: float | None) -> list[T] | None:
        """Everything held, the keyed items first ([] after ``timeout``); None once closed
        and empty."""
        with self._cond:
            self._cond.wait_for(lambda: self._keyed or self._queued or self._closed, timeout)
            if not self._keyed and not self._queued and self._closed:
                return None
            items = [*self._keyed.values(), *self._queued]
            self._keyed.clear()
            self._queued.clear()
            return items

    def close(self) -> None:
        """No more items; the worker takes what is left, then :meth:`take` returns None."""
        with self._cond:
            self._closed = True
            self._cond.notify_all()
