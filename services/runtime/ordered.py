"""In-order delivery of the raw chain: each producer's messages reach the consumer once, in
the order of the producer's outbox, live or fetched from it.

The event streams (:mod:`services.runtime.delivery`) may deliver out of order and twice,
because their folds are idempotent and order-free. A stage of the raw chain is not: ingestion
reorders within a short window and extraction needs each unit's chunks in order. It also
keeps state between messages, so it must resume after a restart at the exact message where
its checkpoint (:mod:`services.runtime.checkpoint`) stopped. So the raw chain reads its
producers (gateways ``gateway/{id}``, ingestion) through :class:`OrderedSubscription`:

* Per producer it keeps the epoch and the next seq it expects. A live message with that seq
  is queued at once; one farther on (a message was missed: a restart, a cut link, a full
  queue) is not queued, and the producer's outbox is asked for everything after the last
  queued seq (the replay query of :mod:`services.runtime.delivery`, with a ``limit`` so
  that an hour of backlog comes in pieces). The entries come back in seq order and are
  queued in that order, so the consumer sees each producer's stream as the producer wrote
  it, with no gap and no repeat.
* The queue is bounded in bytes: when it is full, live messages are not queued but fetched
  later from the outbox. A slow consumer costs no memory, and the Zenoh callbacks never wait.
* Every ``replay_s``, and when a producer's liveliness token appears, each producer is asked
  for what follows its last queued seq, so the tail of a stream is not lost when its last
  live message was.
* A producer met for the first time (no position) is read from the start of its retained
  outbox; one whose epoch changed (its outbox file was replaced) from the start of the new
  one; entries its retention deleted first are counted in :attr:`OrderedSubscription.lost`.
* A message without the outbox attachment (a gateway that keeps no outbox) is queued as it
  comes, at most once and with no position.
"""

from __future__ import annotations

import logging
import queue
import threading
from collections import deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass

import msgpack
import zenoh

from services.runtime.delivery import (
    JOIN_TIMEOUT_S,
    REPLY_IDLE_S,
    DeliverySettings,
    outbox_all,
    outbox_key,
)

log = logging.getLogger(__name__)

FETCH_LIMIT = 256  # entries per fetch: a raw chunk is ~50 kB, so at most ~13 MB in flight
DEFAULT_SETTINGS = DeliverySettings()
CAPACITY_BYTES = 32 * 1024 * 1024  # queued for the consumer before live messages wait in the outbox


@dataclass(frozen=True)
class Item:
    """One message for the consumer; ``producer`` None for a plain put (no position)."""

    producer: str | None
    epoch: str | None
    seq: int
    kind: str
    key: str
    payload: bytes


@dataclass
class _Stream:
    epoch: str | None = None  # None: not met yet, read from the start of its outbox
    next: int = 1  # the seq expected next
    wanted: bool = True  # ask the producer for what follows ``next - 1``


class OrderedSubscription:
    """Subscriptions ``{kind: key expression}`` whose messages from the producers accepted by
    ``producers`` are queued once each, in each producer's order (see the module docstring);
    the consumer drains them with :meth:`take`. ``positions`` ``{producer: (epoch, seq)}``:
    where a restarted consumer resumes (the last seq it handled)."""

    def __init__(
        self,
        session: zenoh.Session,
        ns: str,
        subscriptions: Mapping[str, str],
        producers: Callable[[str], bool],
        *,
        settings: DeliverySettings = DEFAULT_SETTINGS,
        positions: Mapping[str, tuple[str, int]] | None = None,
        capacity_bytes: int = CAPACITY_BYTES,
        fetch_limit: int = FETCH_LIMIT,
    ) -> None:
        self._session = session
        self._ns = ns
        self._kinds = [(kind, zenoh.KeyExpr(key)) for kind, key in subscriptions.items()]
        self._accepts = producers
        self._settings = settings
        self._capacity = capacity_bytes
        self._limit = fetch_limit
        self._cond = threading.Condition()
        self._streams = {p: _Stream(e, s + 1) for p, (e, s) in (positions or {}).items()}
        self._ready: deque[Item] = deque()
        self._ready_bytes = 0
        self._closed = False
        self._wake = threading.Event()
        self._silent: set[str] = set()  # producers that did not answer their last fetch
        self.lost = 0  # entries a producer's retention deleted before this consumer got them
        self.fetched = 0  # entries that came by a fetch rather than live
        self.dropped_plain = 0  # plain puts not queued, the queue being full
        self._subscribers = [
            session.declare_subscriber(key, self._on_live(kind))
            for kind, key in subscriptions.items()
        ]
        self._watch = session.liveliness().declare_subscriber(outbox_all(ns), self._on_token)
        self._thread = threading.Thread(target=self._fetch_loop, name="fetch", daemon=True)
        self._thread.start()

    # --- the consumer's side -------------------------------------------------------------

    def take(self, max_items: int, timeout: float | None) -> list[Item] | None:
        """Up to ``max_items`` queued items ([] at ``timeout``); None once undeclared and
        drained."""
        with self._cond:
            self._cond.wait_for(lambda: self._ready or self._closed, timeout)
            if not self._ready:
                return None if self._closed else []
            batch = [self._ready.popleft() for _ in range(min(max_items, len(self._ready)))]
            self._ready_bytes -= sum(len(item.payload) for item in batch)
            self._cond.notify_all()
            return batch

    def depth(self) -> tuple[int, int]:
        """(items, bytes) queued for the consumer."""
        with self._cond:
            return len(self._ready), self._ready_bytes

    def undeclare(self) -> None:
        with self._cond:
            self._closed = True
            self._cond.notify_all()
        self._wake.set()
        for subscriber in (*self._subscribers, self._watch):
            try:
                subscriber.undeclare()
            except zenoh.ZError as e:
                log.warning("undeclare subscriber: %s", e)
        self._thread.join(timeout=JOIN_TIMEOUT_S)

    # --- live ---------------------------------------------------------------------------------

    def _room(self, size: int) -> bool:
        return not self._ready or self._ready_bytes + size <= self._capacity

    def _append(self, item: Item) -> None:
        self._ready.append(item)
        self._ready_bytes += len(item.payload)
        self._cond.notify_all()

    def _on_live(self, kind: str) -> Callable[[zenoh.Sample], None]:
        def on_sample(sample: zenoh.Sample) -> None:
            key, payload = str(sample.key_expr), sample.payload.to_bytes()
            position = _position(sample.attachment)
            with self._cond:
                if self._closed:
                    return
                if position is None or not self._accepts(position[0]):
                    if self._room(len(payload)):
                        self._append(Item(None, None, 0, kind, key, payload))
                    else:
                        self.dropped_plain += 1
                    return
                producer, epoch, seq = position
                stream = self._streams.setdefault(producer, _Stream())
                if stream.epoch == epoch and seq < stream.next:
                    return  # had it
                if stream.epoch == epoch and seq == stream.next and self._room(len(payload)):
                    self._append(Item(producer, epoch, seq, kind, key, payload))
                    stream.next = seq + 1
                    return
                stream.wanted = True  # a gap, a new epoch or a full queue: fetch
            self._wake.set()

        return on_sample

    def _on_token(self, sample: zenoh.Sample) -> None:
        if sample.kind != zenoh.SampleKind.PUT:
            return
        producer = str(sample.key_expr).removeprefix(outbox_key(self._ns, ""))
        if self._accepts(producer):
            with self._cond:
                self._streams.setdefault(producer, _Stream()).wanted = True
            self._wake.set()

    # --- fetches --------------------------------------------------------------------------

    def _fetch_loop(self) -> None:
        poll_all = True  # at start, and every replay_s: every producer present
        while not self._closed:
            try:
                if poll_all:
                    self._discover()
                with self._cond:
                    wanted = [p for p, s in self._streams.items() if s.wanted]
                for producer in wanted:
                    if self._closed:
                        return
                    self._fetch(producer)
            except zenoh.ZError as e:
                log.warning("fetch: %s", e)
            except Exception:
                log.exception("fetch")
            with self._cond:
                more = any(s.wanted for s in self._streams.values())
            poll_all = not more and not self._wake.wait(self._settings.replay_s)
            self._wake.clear()

    def _discover(self) -> None:
        """Mark every producer whose liveliness token is present: its tail may have been
        missed, and a producer never heard from live is read from its start."""
        tokens = self._session.liveliness().get(outbox_all(self._ns), timeout=REPLY_IDLE_S)
        prefix = outbox_key(self._ns, "")
        for reply in tokens:
            if reply.ok is None:
                continue
            producer = str(reply.ok.key_expr).removeprefix(prefix)
            if self._accepts(producer):
                with self._cond:
                    self._streams.setdefault(producer, _Stream()).wanted = True

    def _fetch(self, producer: str) -> None:
        """Ask ``producer`` for up to ``fetch_limit`` entries after the last queued one and
        queue them in seq order."""
        with self._cond:
            stream = self._streams.setdefault(producer, _Stream())
            stream.wanted = False  # a live gap during the fetch sets it again
            # [epoch, W, M, C] with nothing counted above W: every entry after next - 1
            at = (
                None
                if stream.epoch is None
                else [stream.epoch, stream.next - 1, stream.next - 1, 0]
            )
        request = {"keys": [str(k) for _, k in self._kinds], "at": at, "limit": self._limit}
        replies: queue.SimpleQueue[zenoh.Reply | None] = queue.SimpleQueue()
        self._session.get(
            outbox_key(self._ns, producer),
            zenoh.handlers.Callback(replies.put, lambda: replies.put(None)),
            payload=msgpack.packb(request),
            timeout=self._settings.replay_timeout_s,
            consolidation=zenoh.ConsolidationMode.NONE,
            accept_replies=zenoh.ReplyKeyExpr.ANY,
            congestion_control=zenoh.CongestionControl.BLOCK,
        )
        entries: list[tuple[int, str, str, bytes]] = []
        end = None
        while True:
            try:
                reply = replies.get(timeout=REPLY_IDLE_S)
            except queue.Empty:  # the producer went away mid-answer: the next round
                with self._cond:
                    stream.wanted = True
                return
            if reply is None:
                break
            if reply.ok is None:
                log.warning(
                    "fetch %s: error reply %r", producer, reply.err.payload.to_bytes()[:200]
                )
                continue
            sample = reply.ok
            if sample.attachment is None:
                _, epoch, end = msgpack.unpackb(sample.payload.to_bytes())
                continue
            _, epoch, seq = msgpack.unpackb(sample.attachment.to_bytes())
            key = str(sample.key_expr)
            kind = self._kind(key)
            if kind is not None:
                entries.append((seq, kind, key, sample.payload.to_bytes()))
        if end is None:  # no answer: the producer is gone (its token will bring it back)
            if producer not in self._silent:
                self._silent.add(producer)
                log.warning(
                    "producer %s does not answer on %s: its messages wait until it does (a "
                    "sender without an outbox must not attach a position)",
                    producer, outbox_key(self._ns, producer),
                )  # fmt: skip
            return
        self._silent.discard(producer)
        with self._cond:
            if stream.epoch != epoch:
                if stream.epoch is not None:
                    log.warning(
                        "producer %s numbers anew (epoch %s, was %s): reading all it keeps",
                        producer, epoch, stream.epoch,
                    )  # fmt: skip
                stream.epoch, stream.next = epoch, 1
            if end["lost"]:
                self.lost += end["lost"]
                log.error("lost beyond retention: %d entries of producer %s", end["lost"], producer)
        for seq, kind, key, payload in sorted(entries):
            with self._cond:
                self._cond.wait_for(lambda p=payload: self._closed or self._room(len(p)))
                if self._closed:
                    return
                if stream.epoch == epoch and seq >= stream.next:
                    self._append(Item(producer, epoch, seq, kind, key, payload))
                    stream.next = seq + 1
                    self.fetched += 1
        with self._cond:
            if stream.epoch == epoch:
                stream.next = max(stream.next, end["head"] + 1)
                if len(entries) >= self._limit:
                    stream.wanted = True  # more after this piece

    def _kind(self, key: str) -> str | None:
        ke = zenoh.KeyExpr(key)
        return next((kind for kind, expr in self._kinds if expr.intersects(ke)), None)


def _position(attachment: zenoh.ZBytes | None) -> tuple[str, str, int] | None:
    if attachment is None:
        return None
    try:
        producer, epoch, seq = msgpack.unpackb(attachment.to_bytes())
    except (ValueError, TypeError, msgpack.UnpackException):
        return None
    return producer, epoch, seq
