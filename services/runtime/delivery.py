"""At-least-once delivery of the event and model streams: a durable outbox per producer, and
consumers that replay from it.

A plain ``put`` reaches the subscribers connected at that moment and no one else: a
subscriber being restarted, a router being restarted or a cut link loses it. The index,
model, state and plan streams therefore go through :class:`ReliablePublisher` and are read
with :class:`ReliableSubscription`:

* **Producer** ``{service}/{instance}``: :meth:`ReliablePublisher.put` queues the message; a
  writer thread appends what is queued to the producer's :class:`~services.runtime.outbox.
  Outbox` in one transaction (seq numbers 1, 2, 3 … that survive a restart), then puts each
  message on its key with the attachment ``[producer, epoch, seq]`` (MessagePack). Nothing
  goes out before it is on disk, so whatever a consumer saw can be replayed, even after the
  producer was killed and started again on its file.
* **Replay**: every producer answers queries on ``{ns}/q/outbox/{service}/{instance}`` (and
  holds a liveliness token on that key). A consumer keeps, per producer, a watermark W
  (every matching message with seq <= W handed to its handler) and the seqs above W it
  got live. At start, when a producer's token appears, and every ``replay_s`` it asks each
  producer whose token is present, on the producer's own key (access control names the
  keys a role may query); the query's payload (MessagePack; a payload and not selector
  parameters, because one query carries several key expressions) is
  ``{"keys": [...], "at": [epoch, W, M, C]}`` (``at`` None without a position), with
  M the highest seq seen live and C the number of distinct seqs seen live in (W, M]. Each
  producer counts its entries in (W, M] whose key intersects one of the key expressions:
  equal to C, it sends only the entries above M; otherwise every entry above W (the
  consumer drops the seqs it already has). Each entry is a reply on its own key with the
  live attachment (so the router's access control treats it as the live message); the
  last reply, on the queryable's key, carries the producer's head H (and how many entries
  retention already deleted above W). Once the replayed entries have been handed to the
  handler, W := H. A different epoch (a producer whose file was replaced) or no position
  at all means a replay from the start of what is retained.
* **Retention**: a W below the producer's oldest retained entry means the entries between
  are gone: the consumer logs ``lost beyond retention: N producer X`` and counts them in
  :attr:`ReliableSubscription.lost` (N counts every seq retention deleted in that range, so
  it is an upper bound of what matched the consumer's keys).
* **A full disk** at the producer: the batch is put live without an attachment (at most
  once for those messages, as a plain put), logged, and counted in
  :attr:`ReliablePublisher.unrecorded`.

Delivery is at least once: the replay repeats what a consumer may already have (a live
message racing the replay, a consumer killed before it persisted W). Every consumer's fold
is idempotent (the filtering fold, calibration's pairing, alerting's hysteresis, the
planner's newest state per segment), so the effect is exactly once. Order across keys and
between a live message and a replayed one is not kept.

A consumer that persists W (filtering and calibration, in the transaction of what the
replay brought, see :meth:`services.runtime.service.ServiceRuntime.subscribe_batches`'s
``positions``) replays after a restart only what came after; one that does not (alerting,
planning) replays everything retained when it starts.

Settings (``services.delivery``): ``replay_s`` (10 s: the longest a message missed live
waits for its replay), ``replay_timeout_s`` (600 s: the longest one replay may take; an
unfinished replay is asked again whole, so raise it for a consumer that replays a whole
retention at national scale) and ``outbox``: ``dir`` (default: beside the service's store,
``var/`` for one without), ``max_bytes`` (2 GB per producer), ``max_age_s`` (7 days).
"""

from __future__ import annotations

import dataclasses
import logging
import queue
import threading
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from contextlib import closing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import msgpack
import zenoh

from services.runtime.outbox import (
    DEFAULT_MAX_AGE_S,
    DEFAULT_MAX_BYTES,
    Outbox,
    OutboxBusy,
    OutboxFull,
)

log = logging.getLogger(__name__)

QUEUE_LIMIT = 20_000  # messages queued for the outbox before put() blocks the caller
REPLY_IDLE_S = 5.0  # a replay round with no reply for this long is abandoned
JOIN_TIMEOUT_S = 2.0  # at close, the longest wait for a replay or a flush to end
OUTBOX_CHUNKS = ("q", "outbox")
DEFAULT_OUTBOX_DIR = "var"  # {ns}/q/outbox/{service}/{instance}


def outbox_key(ns: str, producer: str) -> str:
    """The replay queryable (and liveliness token) of ``producer`` (``service/instance``)."""
    return "/".join((ns, *OUTBOX_CHUNKS, producer))


def outbox_all(ns: str) -> str:
    return "/".join((ns, *OUTBOX_CHUNKS, "**"))


@dataclass(frozen=True)
class OutboxSettings:
    dir: str | None = None  # None: beside the service's store, else DEFAULT_OUTBOX_DIR
    max_bytes: int = DEFAULT_MAX_BYTES
    max_age_s: float = DEFAULT_MAX_AGE_S


RAW_MAX_BYTES = 1_000_000_000  # the raw chain's outboxes: 1 GB per producer …
RAW_MAX_AGE_S = 3600.0  # … and one hour (raw data is ~50 kB/s per unit)


@dataclass(frozen=True)
class DeliverySettings:
    """Where producers keep their outboxes and how often consumers replay."""

    replay_s: float = 10.0
    replay_timeout_s: float = 600.0
    outbox: OutboxSettings = field(default_factory=OutboxSettings)
    # the raw chain (gateways, ingestion): the dir is outbox.dir's, retention its own
    raw_outbox: OutboxSettings = field(
        default_factory=lambda: OutboxSettings(max_bytes=RAW_MAX_BYTES, max_age_s=RAW_MAX_AGE_S)
    )

    @classmethod
    def from_options(cls, options: Mapping[str, Any]) -> DeliverySettings:
        """From the ``services.delivery`` section (its keys checked by the config loader);
        ValueError says which value to fix."""
        options = dict(options)
        sections = {}
        for name, default in (("outbox", OutboxSettings()), ("raw_outbox", cls().raw_outbox)):
            section = dict(options.pop(name, {}))
            known = {f for f in OutboxSettings.__dataclass_fields__}
            for key in section:
                if key not in known:
                    raise ValueError(
                        f"services.delivery.{name}: unknown key {key!r}; known keys: "
                        f"{', '.join(sorted(known))}"
                    )
            sections[name] = dataclasses.replace(default, **section)
        settings = cls(**options, **sections)
        for name, value in (
            ("replay_s", settings.replay_s),
            ("replay_timeout_s", settings.replay_timeout_s),
            ("outbox.max_age_s", settings.outbox.max_age_s),
            ("raw_outbox.max_age_s", settings.raw_outbox.max_age_s),
        ):
            if not (isinstance(value, int | float) and value > 0):
                raise ValueError(f"services.delivery.{name} must be a number > 0, got {value!r}")
        for name, max_bytes in (
            ("outbox", settings.outbox.max_bytes),
            ("raw_outbox", settings.raw_outbox.max_bytes),
        ):
            if not (isinstance(max_bytes, int) and max_bytes >= 1):
                raise ValueError(
                    f"services.delivery.{name}.max_bytes must be an integer ≥ 1, got {max_bytes!r}"
                )
        return settings


# --- the replay, pure of Zenoh -----------------------------------------------------------


@dataclass(frozen=True)
class Replay:
    """A producer's answer to one consumer's position."""

    epoch: str
    entries: Iterator[tuple[int, str, bytes]]  # (seq, key, payload) in seq order
    head: int  # every entry up to here is in ``entries`` or was already the consumer's
    lost: int  # entries retention deleted above the consumer's W (0 when it had none)


def serve_replay(
    outbox: Outbox,
    position: list[Any] | None,
    matches: Callable[[str], bool],
    limit: int | None = None,
) -> Replay:
    """What ``outbox`` sends a consumer at ``position`` (``[epoch, W, M, C]`` or None for
    none): the matching entries above M when the consumer has all C matching entries of
    (W, M], else above W; from the start when the epoch is not this outbox's. With
    ``limit``, at most that many entries, and the head is the seq of the last entry looked
    at (every matching entry up to it is sent): the consumer asks again from there."""
    head, pruned = outbox.head, outbox.pruned_upto
    lost = 0
    if position is None or position[0] != outbox.epoch:
        after = 0
    else:
        _, after, upto, count = position
        upto = min(upto, head)
        lost = max(0, pruned - after)
        if upto > after and count > 0:
            have = sum(1 for e in outbox.entries(after, upto) if matches(e.key))
            if have == count and not lost:
                after = upto
    if limit is None:
        return Replay(outbox.epoch, _matching(outbox.entries(after, head), matches), head, lost)
    sent: list[tuple[int, str, bytes]] = []
    last = head
    with closing(outbox.entries(after, head)) as entries:  # closed: frees the read connection
        for entry in entries:
            if matches(entry.key):
                sent.append((entry.seq, entry.key, entry.payload))
                if len(sent) == limit:
                    last = entry.seq
                    break
    return Replay(outbox.epoch, iter(sent), last, lost)


def _matching(entries: Iterable[Any], matches: Callable[[str], bool]) -> Iterator[Any]:
    return ((e.seq, e.key, e.payload) for e in entries if matches(e.key))


class Position:
    """What a consumer has of one producer's stream: W, its epoch, and the seqs above W it
    got live. Not thread-safe (the subscription holds a lock)."""

    def __init__(self, epoch: str | None = None, watermark: int = 0) -> None:
        self.epoch = epoch
        self.watermark = watermark
        self.seen: set[int] = set()

    def request(self) -> list[Any] | None:
        """``[epoch, W, M, C]`` for the replay query, None when the stream is unknown."""
        if self.epoch is None:
            return None
        top = max(self.seen, default=self.watermark)
        return [self.epoch, self.watermark, top, len(self.seen)]

    def take(self, epoch: str, seq: int) -> bool:
        """Whether the message ``seq`` is new to the consumer (and note it when it is).
        A message of another epoch is new and not noted: the replay will sort it out."""
        if epoch != self.epoch:
            return True
        if seq <= self.watermark or seq in self.seen:
            return False
        self.seen.add(seq)
        return True

    def restart(self, epoch: str) -> None:
        """The producer answered with another numbering: start over on it."""
        self.epoch, self.watermark, self.seen = epoch, 0, set()

    def advance(self, epoch: str, head: int) -> None:
        """Everything up to ``head`` was handed to the handler."""
        if epoch != self.epoch:
            return
        self.watermark = max(self.watermark, head)
        self.seen = {s for s in self.seen if s > self.watermark}


# --- producer --------------------------------------------------------------------------------


class ReliablePublisher:
    """``put(key, payload)`` on any concrete key, recorded in ``outbox`` first and then put
    live with its position (see the module docstring); answers the replay queries.

    ``put`` returns once the message is queued (it blocks while ``QUEUE_LIMIT`` messages wait
    for the writer: back-pressure); :meth:`flush` waits until everything queued is out.
    ``congestion_control`` BLOCK (the default) makes a slow router slow the writer down
    instead of dropping. Thread-safe. :meth:`undeclare` flushes, then undeclares and closes
    the outbox.
    """

    def __init__(
        self,
        session: zenoh.Session,
        ns: str,
        producer: str,
        outbox: Outbox,
        *,
        congestion_control: zenoh.CongestionControl = zenoh.CongestionControl.BLOCK,
    ) -> None:
        self._session = session
        self.producer = producer
        self.outbox = outbox
        self._congestion_control = congestion_control
        self._queue: list[tuple[str, bytes]] = []
        self._busy = False
        self._closed = False
        self._cond = threading.Condition()
        self.unrecorded = 0  # messages put live only, the outbox being unwritable
        key = outbox_key(ns, producer)
        self._queryable = session.declare_queryable(key)
        self._token = session.liveliness().declare_token(key)
        self._key = key
        self._writer = threading.Thread(target=self._write, name=f"outbox:{producer}", daemon=True)
        self._server = threading.Thread(target=self._serve, name=f"replay:{producer}", daemon=True)
        self._writer.start()
        self._server.start()

    @classmethod
    def open(
        cls,
        session: zenoh.Session,
        ns: str,
        service: str,
        instance: str,
        settings: DeliverySettings = DeliverySettings(),
        directory: Path | str | None = DEFAULT_OUTBOX_DIR,
        *,
        raw: bool = False,
    ) -> ReliablePublisher:
        """The publisher of ``service/instance`` on its outbox file
        ``{dir}/outbox-{service}-{instance}.sqlite``: ``settings.outbox.dir`` if set, else
        ``directory``; with neither (``directory`` None), an outbox in memory that lives as
        long as the process. ``raw``: the raw chain's retention (``settings.raw_outbox``)."""
        where = settings.outbox.dir or directory
        path = None if where is None else Path(where) / f"outbox-{service}-{instance}.sqlite"
        retention = settings.raw_outbox if raw else settings.outbox
        outbox = Outbox(path, max_bytes=retention.max_bytes, max_age_s=retention.max_age_s)
        return cls(session, ns, f"{service}/{instance}", outbox)

    @classmethod
    def open_named(
        cls,
        session: zenoh.Session,
        ns: str,
        service: str,
        names: Sequence[str],
        settings: DeliverySettings = DeliverySettings(),
        directory: Path | str | None = DEFAULT_OUTBOX_DIR,
        *,
        raw: bool = False,
    ) -> ReliablePublisher:
        """:meth:`open` under the first of ``names`` whose outbox no other process holds."""
        for name in names[:-1]:
            try:
                return cls.open(session, ns, service, name, settings, directory, raw=raw)
            except OutboxBusy as e:
                log.warning("%s; publishing as %s/%s", e, service, names[-1])
        return cls.open(session, ns, service, names[-1], settings, directory, raw=raw)

    def put(self, key: str, payload: bytes) -> None:
        with self._cond:
            while len(self._queue) >= QUEUE_LIMIT and not self._closed:
                self._cond.wait()
            if self._closed:
                raise RuntimeError(f"{self.producer}: publisher undeclared")
            self._queue.append((key, payload))
            self._cond.notify_all()

    def flush(self, timeout: float | None = None) -> bool:
        """Wait until every queued message is recorded and put; False at ``timeout``."""
        with self._cond:
            return self._cond.wait_for(lambda: not self._queue and not self._busy, timeout)

    def undeclare(self) -> None:
        if not self.flush(JOIN_TIMEOUT_S):
            log.warning("%s: closing with messages not yet recorded", self.producer)
        with self._cond:
            self._closed = True
            self._cond.notify_all()
        self._writer.join()
        for entity in (self._token, self._queryable):
            try:
                entity.undeclare()
            except zenoh.ZError as e:
                log.warning("undeclare %s: %s", self._key, e)
        self._server.join(timeout=5.0)
        self.outbox.close()

    def _write(self) -> None:
        while True:
            with self._cond:
                self._cond.wait_for(lambda: self._queue or self._closed)
                if not self._queue:
                    return
                batch, self._queue, self._busy = self._queue, [], True
                self._cond.notify_all()
            try:
                self._publish(batch)
            finally:
                with self._cond:
                    self._busy = False
                    self._cond.notify_all()

    def _publish(self, batch: list[tuple[str, bytes]]) -> None:
        try:
            seqs: list[int | None] = list(self.outbox.append_many(batch))
        except OutboxFull as e:
            if not self.unrecorded:
                log.error(
                    "%s: %s; publishing without a record (at most once) until it can write",
                    self.producer, e,
                )  # fmt: skip
            self.unrecorded += len(batch)
            seqs = [None] * len(batch)
        epoch = self.outbox.epoch
        for (key, payload), seq in zip(batch, seqs, strict=True):
            attachment = None if seq is None else msgpack.packb([self.producer, epoch, seq])
            try:
                self._session.put(
                    key, payload, attachment=attachment, congestion_control=self._congestion_control
                )
            except zenoh.ZError as e:  # recorded: the replay delivers it
                log.warning("%s: put %s: %s", self.producer, key, e)

    def _serve(self) -> None:
        for query in self._queryable.handler:  # ends when the queryable is undeclared
            try:
                self._answer(query)
            except Exception:
                log.exception("%s: replay query", self.producer)
            finally:
                query.drop()  # the querier's get ends when its query is dropped

    def _answer(self, query: zenoh.Query) -> None:
        request = msgpack.unpackb(query.payload.to_bytes()) if query.payload else {}
        exprs = [zenoh.KeyExpr(k) for k in request.get("keys", ["**"])]

        def matches(key: str) -> bool:
            ke = zenoh.KeyExpr(key)
            return any(e.intersects(ke) for e in exprs)

        replay = serve_replay(self.outbox, request.get("at"), matches, request.get("limit"))
        for seq, key, payload in replay.entries:
            # on the entry's own key, so the router's access control applies to a replay
            # as it does to the live message
            query.reply(key, payload, attachment=msgpack.packb([self.producer, replay.epoch, seq]))
        end = {"head": replay.head, "lost": replay.lost}
        query.reply(self._key, msgpack.packb([self.producer, replay.epoch, end]))


# --- consumer ----------------------------------------------------------------------------------

MARK = "@replayed"  # the kind of an inbox item that says a producer's replay was handed on


class ReliableSubscription:
    """Subscriptions ``{kind: key expression}`` whose messages reach ``deliver(kind, key,
    payload)`` at least once, live or replayed from the producers' outboxes.

    After a producer's replay, ``mark(producer, epoch, head)`` is called in the order of the
    deliveries (it goes through the consumer's queue); the consumer calls :meth:`confirm`
    with the same arguments once what came before it has been handled (and persisted, for a
    consumer that keeps ``positions``). ``positions`` ``{producer: (epoch, W)}`` is where a
    consumer that persisted its watermarks resumes. A new replay round waits until the
    previous one was confirmed.
    """

    def __init__(
        self,
        session: zenoh.Session,
        ns: str,
        subscriptions: Mapping[str, str],
        deliver: Callable[[str, str, bytes], None],
        mark: Callable[[str, str, int], None],
        *,
        settings: DeliverySettings = DeliverySettings(),
        positions: Mapping[str, tuple[str, int]] | None = None,
    ) -> None:
        self._session = session
        self._ns = ns
        self._kinds = [(kind, zenoh.KeyExpr(key)) for kind, key in subscriptions.items()]
        self._deliver = deliver
        self._mark = mark
        self._settings = settings
        self._lock = threading.Lock()
        self._positions = {p: Position(e, w) for p, (e, w) in (positions or {}).items()}
        self._pending: set[tuple[str, str, int]] = set()  # marks not confirmed yet
        self._wake = threading.Event()
        self._stop = threading.Event()
        self.lost = 0  # entries deleted by a producer's retention before this consumer got them
        self.rounds = 0  # replay rounds completed
        self._subscribers = [
            session.declare_subscriber(key, self._on_live(kind))
            for kind, key in subscriptions.items()
        ]
        self._watch = session.liveliness().declare_subscriber(
            outbox_all(ns), lambda s: self._wake.set() if s.kind == zenoh.SampleKind.PUT else None
        )
        self._thread = threading.Thread(target=self._replay_loop, name="replay", daemon=True)
        self._thread.start()

    def positions(self) -> dict[str, tuple[str | None, int]]:
        with self._lock:
            return {p: (pos.epoch, pos.watermark) for p, pos in self._positions.items()}

    def confirm(self, producer: str, epoch: str, head: int) -> None:
        with self._lock:
            self._positions.setdefault(producer, Position()).advance(epoch, head)
            self._pending.discard((producer, epoch, head))
            if not self._pending:
                self.rounds += 1

    def undeclare(self) -> None:
        self._stop.set()
        self._wake.set()
        for subscriber in (*self._subscribers, self._watch):
            try:
                subscriber.undeclare()
            except zenoh.ZError as e:
                log.warning("undeclare subscriber: %s", e)
        self._thread.join(timeout=JOIN_TIMEOUT_S)

    def _on_live(self, kind: str) -> Callable[[zenoh.Sample], None]:
        def on_sample(sample: zenoh.Sample) -> None:
            attachment = sample.attachment
            if attachment is not None:
                try:
                    producer, epoch, seq = msgpack.unpackb(attachment.to_bytes())
                except (ValueError, TypeError, msgpack.UnpackException):
                    producer = None
                if producer is not None:
                    # delivered under the lock: a replay's mark never overtakes a message
                    # its watermark counts as handed on
                    with self._lock:
                        position = self._positions.get(producer)
                        if position is None or position.take(epoch, seq):
                            self._deliver(kind, str(sample.key_expr), sample.payload.to_bytes())
                    return
            self._deliver(kind, str(sample.key_expr), sample.payload.to_bytes())

        return on_sample

    def _replay_loop(self) -> None:
        while not self._stop.is_set():
            with self._lock:
                idle = not self._pending
            if idle:
                try:
                    self._round()
                except zenoh.ZError as e:
                    log.warning("replay query: %s", e)
                except Exception:
                    log.exception("replay round")
            self._wake.wait(self._settings.replay_s if idle else 0.2)
            self._wake.clear()

    def _round(self) -> None:
        """Ask every producer whose token is present for what this consumer lacks."""
        tokens = self._session.liveliness().get(outbox_all(self._ns), timeout=REPLY_IDLE_S)
        prefix = outbox_key(self._ns, "")
        producers = sorted(
            str(r.ok.key_expr).removeprefix(prefix)
            for r in tokens
            if r.ok is not None and str(r.ok.key_expr).startswith(prefix)
        )
        for producer in producers:
            if self._stop.is_set():
                return
            self._replay_from(producer)

    def _replay_from(self, producer: str) -> None:
        """One producer's replay (a query on its own key, so that access control can name
        the producers a role may ask)."""
        with self._lock:
            position = self._positions.get(producer)
            at = None if position is None else position.request()
        request = msgpack.packb({"keys": [str(k) for _, k in self._kinds], "at": at})
        replies: queue.SimpleQueue[zenoh.Reply | None] = queue.SimpleQueue()
        self._session.get(
            outbox_key(self._ns, producer),
            zenoh.handlers.Callback(replies.put, lambda: replies.put(None)),
            payload=request,
            timeout=self._settings.replay_timeout_s,
            consolidation=zenoh.ConsolidationMode.NONE,
            accept_replies=zenoh.ReplyKeyExpr.ANY,
            congestion_control=zenoh.CongestionControl.BLOCK,
        )
        finished = None
        while not self._stop.is_set():
            try:
                reply = replies.get(timeout=REPLY_IDLE_S)
            except queue.Empty:  # a query sent while the link was down: the next round
                log.warning("replay: no reply for %.0f s, round abandoned", REPLY_IDLE_S)
                return
            if reply is None:  # every reply is in (they may come in any order)
                if finished is not None:
                    self._finish(*finished)
                return
            if reply.ok is None:
                log.warning("replay: error reply %r", reply.err.payload.to_bytes()[:200])
                continue
            sample = reply.ok
            if sample.attachment is None:  # the producer's head
                producer, epoch, end = msgpack.unpackb(sample.payload.to_bytes())
                finished, entry = (producer, epoch, end), None
            else:
                producer, epoch, seq = msgpack.unpackb(sample.attachment.to_bytes())
                entry = (str(sample.key_expr), sample.payload.to_bytes())
            with self._lock:
                position = self._positions.setdefault(producer, Position())
                if position.epoch != epoch:
                    if position.epoch is not None:
                        log.warning(
                            "producer %s numbers anew (epoch %s, was %s): replaying all it keeps",
                            producer, epoch, position.epoch,
                        )  # fmt: skip
                    position.restart(epoch)
                if entry is not None and position.take(epoch, seq):
                    key, payload = entry
                    ke = zenoh.KeyExpr(key)
                    for kind, expr in self._kinds:
                        if expr.intersects(ke):
                            self._deliver(kind, key, payload)

    def _finish(self, producer: str, epoch: str, end: dict[str, int]) -> None:
        """A producer's replay is all handed on: its mark follows it."""
        with self._lock:
            if end["lost"]:
                self.lost += end["lost"]
                log.error(
                    "lost beyond retention: %d producer %s (entries its retention "
                    "deleted before this consumer got them)",
                    end["lost"], producer,
                )  # fmt: skip
            self._pending.add((producer, epoch, end["head"]))
        self._mark(producer, epoch, end["head"])  # after the replay's entries (same thread)
