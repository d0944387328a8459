"""The one way a service starts and stops on Zenoh.

::

    def main(conf: RuntimeConfig) -> int:
        with ServiceRuntime("filtering", conf, handle_signals=True) as rt:
            rt.subscribe_in_order({"index": keys.segment_keys(rt.ns, "index")}, on_index)
            rt.declare_queryable(keys.q_alerts(rt.ns), on_query)
            return rt.run()  # liveliness token = ready; waits for SIGINT/SIGTERM/stop()

Leaving the block undeclares everything (subscribers first, so workers drain and end; then
queryables, publishers, the dead-letter publisher and the liveliness token) and closes the
session. Tests use the same object in-process and call :meth:`ServiceRuntime.stop`.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import signal
import threading
import time
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path
from types import FrameType
from typing import Any, Protocol, Self, TypeVar

import msgpack
import zenoh

from schemas import SchemaError, keys
from services.defaults import add_network_argument
from services.runtime import systemd
from services.runtime.checkpoint import CheckpointBusy, CheckpointStore
from services.runtime.config import (
    RuntimeConfig,
    add_zenoh_arguments,
    config_from_args,
    default_instance,
    endpoints,
    zenoh_config,
)
from services.runtime.deadletter_publisher import DeadLetterPublisher
from services.runtime.delivery import (
    DEFAULT_OUTBOX_DIR,
    MARK,
    DeliverySettings,
    ReliablePublisher,
    ReliableSubscription,
)
from services.runtime.inbox import DEFAULT_MEMORY_BYTES, Inbox, Item
from services.runtime.ordered import OrderedSubscription

log = logging.getLogger(__name__)

DEFAULT_CAPACITY = 1024  # samples a latest-only subscription holds (the oldest are dropped)
JOIN_TIMEOUT_S = 2.0  # per worker at shutdown; the whole stop must stay well under 5 s
DRAIN_S = 1.5  # at a stop, a worker goes on with its queued items for at most this long
CONNECT_TIMEOUT_S = 30.0  # how long to keep retrying the first connection at startup
FLUSH_TIMEOUT_S = 2.0  # at most this long waiting for the router's answer at close
_RETRY_S = 0.5
HEALTH_INTERVAL_S = 5.0  # how often a service checks that the router still holds its token
DEAF_AFTER_S = 15.0  # token not seen at the router for this long: the session is lost
HUNG_AFTER_S = 300.0  # a worker on one batch for longer stops feeding the systemd watchdog
BACKLOG_REPORT_S = 60.0  # how often a backlog is logged
EXIT_SESSION_LOST = 75  # EX_TEMPFAIL: a supervisor should restart the process
_IDLE_POLL_S = 1.0  # an idle worker wakes this often (watchdog bookkeeping, stop)
MAX_ORDERED_BATCH = 64  # items a raw-chain worker takes at once
CHECKPOINT_S = 2.0  # a stage of the raw chain saves its checkpoint this often while it works


class _Undeclarable(Protocol):
    def undeclare(self) -> None: ...


_U = TypeVar("_U", bound=_Undeclarable)


class ServiceRuntime:
    """Session, liveliness token, dead letters, worker threads and one stop event.

    Parameters
    ----------
    service
        Service name: the ``{service}`` chunk of ``{ns}/alive/{service}/{instance}`` and of
        ``{ns}/deadletter/{service}``.
    conf
        Where to connect (see :mod:`services.runtime.config`).
    handle_signals
        Install SIGINT/SIGTERM handlers that call :meth:`stop` (only possible, and only done,
        in the main thread; previous handlers are restored on exit).
    connect_timeout
        Seconds to keep retrying to open the session when the router is not up yet.
    stop_event
        Use this event as the stop event (lets a test or a supervisor stop the service).
    """

    def __init__(
        self,
        service: str,
        conf: RuntimeConfig,
        *,
        handle_signals: bool = False,
        connect_timeout: float = CONNECT_TIMEOUT_S,
        stop_event: threading.Event | None = None,
        health_interval_s: float = HEALTH_INTERVAL_S,
        deaf_after_s: float = DEAF_AFTER_S,
    ) -> None:
        self.service = service
        self.conf = conf
        self.ns = conf.ns
        self.instance = conf.instance or default_instance()
        self.alive_key = keys.alive(self.ns, service, self.instance)  # checks the chunks
        self.stop_event = stop_event if stop_event is not None else threading.Event()
        self.delivery = DeliverySettings.from_options(
            conf.options("delivery", (f.name for f in dataclasses.fields(DeliverySettings)))
        )
        self.exit_code = 0  # what run() returns; EXIT_SESSION_LOST when the session is lost
        self._handle_signals = handle_signals
        self._connect_timeout = connect_timeout
        self._health_interval_s = health_interval_s
        self._deaf_after_s = deaf_after_s
        self._session: zenoh.Session | None = None
        self._deadletters: DeadLetterPublisher | None = None
        self._token: zenoh.LivelinessToken | None = None
        self._subscribers: list[_Undeclarable] = []
        self._declared: list[_Undeclarable] = []
        self._inboxes: list[Inbox] = []
        self._threads: list[threading.Thread] = []
        self._busy_since: dict[str, float] = {}  # worker name -> monotonic start of its batch
        self._previous_handlers: dict[int, Any] = {}

    # --- lifecycle ---------------------------------------------------------------------

    def __enter__(self) -> Self:
        if self._handle_signals:
            self._install_signal_handlers()
        try:
            self._session = self._open()
            self._deadletters = DeadLetterPublisher(self._session, self.ns, self.service)
        except BaseException:
            self.close()
            raise
        log.info("%s/%s connected (zid %s)", self.service, self.instance, self._session.zid())
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()

    @property
    def session(self) -> zenoh.Session:
        if self._session is None:
            raise RuntimeError(f"{self.service}: session not open (use `with ServiceRuntime(…)`)")
        return self._session

    @property
    def deadletters(self) -> DeadLetterPublisher:
        if self._deadletters is None:
            raise RuntimeError(f"{self.service}: session not open (use `with ServiceRuntime(…)`)")
        return self._deadletters

    @property
    def stopping(self) -> bool:
        return self.stop_event.is_set()

    def stop(self) -> None:
        """Ask the service to stop (thread-safe; what the signal handlers call)."""
        self.stop_event.set()

    def announce(self) -> None:
        """Declare the liveliness token ``{ns}/alive/{service}/{instance}`` (idempotent).

        Call it once subscriptions and queryables are declared: the token means "ready".
        """
        if self._token is None:
            self._token = self.session.liveliness().declare_token(self.alive_key)
            log.info("alive: %s", self.alive_key)
            systemd.notify("READY=1")
            self.spawn(self._watch_health, name=f"{self.service}:health")

    def wait(self, timeout: float | None = None) -> bool:
        """Block until :meth:`stop` (or a signal); True if stopped, False on timeout."""
        return self.stop_event.wait(timeout)

    def run(self) -> int:
        """Announce, wait for the stop event, return the exit code (leave the block to close):
        0 after a stop, :data:`EXIT_SESSION_LOST` when the session was found deaf."""
        self.announce()
        self.wait()
        log.info("%s/%s stopping", self.service, self.instance)
        return self.exit_code

    def close(self) -> None:
        """Stop workers, undeclare everything, close the session. Idempotent."""
        self.stop_event.set()
        started = time.monotonic()
        for sub in reversed(self._subscribers):
            _undeclare(sub)
        self._subscribers.clear()
        for inbox in self._inboxes:  # workers take what is queued, then end
            inbox.close()
        for thread in self._threads:
            if thread is not threading.current_thread():
                thread.join(JOIN_TIMEOUT_S)
                if thread.is_alive():
                    log.warning("worker %s did not stop within %.1f s", thread.name, JOIN_TIMEOUT_S)
        self._threads.clear()
        self._inboxes.clear()
        for entity in reversed(self._declared):
            _undeclare(entity)
        self._declared.clear()
        if self._deadletters is not None:
            _undeclare(self._deadletters)
        if self._session is not None:
            self._flush()
        if self._token is not None:
            _undeclare(self._token)
            self._token = None
        if self._session is not None:
            try:
                self._session.close()
            except zenoh.ZError as e:
                log.warning("closing session: %s", e)
            self._session = None
            log.info(
                "%s/%s closed in %.2f s", self.service, self.instance, time.monotonic() - started
            )
        self._restore_signal_handlers()

    def _flush(self) -> None:
        """Let what this session put reach the router before it closes.

        Closing drops what still waits in the session's queues (seen: most of the last
        second of 56 kB raw chunks of a fast simulator). A liveliness query is answered by
        the router over the same link, after the puts queued before it, so its answer means
        they have left this process.
        """
        try:
            replies = self._session.liveliness().get(self.alive_key, timeout=FLUSH_TIMEOUT_S)
            for _ in replies:
                pass
        except zenoh.ZError as e:
            log.warning("flushing before close: %s", e)

    # --- declarations (all undeclared by close) ------------------------------------------

    def subscribe_in_order(
        self,
        subscriptions: Mapping[str, str],
        handle: Callable[[str, str, bytes], object],
        *,
        on_end: Callable[[], None] | None = None,
        reliable: bool = False,
        memory_bytes: int = DEFAULT_MEMORY_BYTES,
    ) -> Inbox:
        """Several subscriptions ``{kind: key expression}`` into ONE :class:`Inbox` drained by
        ONE worker thread calling ``handle(kind, key, payload)``, so a core stays
        single-threaded. A SchemaError (or any other error) becomes a dead letter and the
        worker goes on. See :meth:`subscribe_batches`."""

        def handle_batch(batch: list[Item]) -> None:
            for kind, key, payload in batch:
                self.guarded(handle, kind, key, payload)

        return self.subscribe_batches(
            subscriptions,
            handle_batch,
            max_batch=1,
            on_end=on_end,
            reliable=reliable,
            memory_bytes=memory_bytes,
        )

    def subscribe_batches(
        self,
        subscriptions: Mapping[str, str],
        handle_batch: Callable[[list[Item]], object],
        *,
        max_batch: int = 1024,
        on_end: Callable[[], None] | None = None,
        on_idle: Callable[[], None] | None = None,
        idle_s: float = _IDLE_POLL_S,
        reliable: bool = False,
        positions: Mapping[str, tuple[str, int]] | None = None,
        memory_bytes: int = DEFAULT_MEMORY_BYTES,
    ) -> Inbox:
        """Subscriptions ``{kind: key expression}`` → one :class:`Inbox` → one worker thread
        calling ``handle_batch([(kind, key, payload), …])`` with what is queued (up to
        ``max_batch`` items, in arrival order; order is kept per key, not across keys, since
        Zenoh calls each subscription's callback on its own thread).

        The Zenoh callbacks only append to the inbox, which never waits for the worker (it
        spills to disk beyond ``memory_bytes``): a slow worker cannot stall the session, so
        the session keeps its lease and nothing is dropped under any backlog. The worker is
        what is slow, and its backlog is visible in the inbox's stats. ``handle_batch``
        must turn bad items into dead letters itself (:meth:`guarded`); an exception that
        escapes it is logged and the worker goes on. ``on_idle`` runs when nothing arrived
        for ``idle_s``; ``on_end`` once the subscriptions are undeclared and the inbox is
        drained. Returns the inbox (a start-up query may put its replies into it).

        ``reliable``: at least once, live or replayed from the producers' outboxes (a
        :class:`~services.runtime.delivery.ReliableSubscription`); items may then arrive
        more than once. With ``positions`` (``{producer: (epoch, W)}``, what the consumer
        persisted, possibly empty), the consumer persists its watermarks itself: its batches
        also carry items ``(MARK, producer, msgpack([epoch, head]))``, each after the items
        of that producer's replay, to be stored with the batch (the replay resumes from
        them after a restart); without, the marks are taken out of the batches and the
        replay starts from what the producers retain.
        """
        inbox = Inbox(memory_bytes=memory_bytes)
        self._inboxes.append(inbox)
        name = f"{self.service}:worker" + (
            f"{len(self._inboxes)}" if len(self._inboxes) > 1 else ""
        )

        def callback(kind: str) -> Callable[[zenoh.Sample], None]:
            def on_sample(sample: zenoh.Sample) -> None:
                inbox.put(kind, str(sample.key_expr), sample.payload.to_bytes())

            return on_sample

        def work() -> None:
            stopping_since = None
            while True:
                batch = inbox.take(max_batch, timeout=idle_s)
                if batch is None:
                    break
                if self.stopping:  # drain what is queued, but not past the stop's deadline
                    stopping_since = stopping_since or time.monotonic()
                    if time.monotonic() - stopping_since > DRAIN_S:
                        log.warning(
                            "%s: stopping with %d queued items not handled",
                            self.service, len(inbox) + len(batch),
                        )  # fmt: skip
                        break
                if not batch:
                    if on_idle is not None:
                        self.guarded(on_idle)
                    continue
                marks = [item for item in batch if item[0] == MARK]
                if marks and positions is None:
                    batch = [item for item in batch if item[0] != MARK]
                self._busy_since[name] = time.monotonic()
                try:
                    if batch:
                        handle_batch(batch)
                except Exception:
                    log.exception("%s: error handling a batch of %d", self.service, len(batch))
                finally:
                    self._busy_since.pop(name, None)
                if subscription is not None:
                    for _, producer, position in marks:
                        subscription.confirm(producer, *msgpack.unpackb(position))
            if on_end is not None:
                on_end()

        subscription = None
        if reliable:

            def mark(producer: str, epoch: str, head: int) -> None:
                inbox.put(MARK, producer, msgpack.packb([epoch, head]))

            subscription = ReliableSubscription(
                self.session, self.ns, subscriptions, inbox.put, mark,
                settings=self.delivery, positions=positions,
            )  # fmt: skip
            self._subscribers.append(subscription)
        else:
            for kind, key in subscriptions.items():
                self.declare_subscriber(key, callback(kind))
        self.spawn(work, name=name)
        return inbox

    def subscribe_checkpointed(
        self,
        subscriptions: Mapping[str, str],
        handle: Callable[[str, str, bytes], object],
        *,
        producers: Callable[[str], bool],
        checkpoint: CheckpointStore,
        positions: Mapping[str, tuple[str, int]],
        snapshot: Callable[[], bytes],
        fingerprint: str,
        outputs: ReliablePublisher | None,
        every_s: float = CHECKPOINT_S,
    ) -> OrderedSubscription:
        """A stage of the raw chain: the messages of the producers accepted by ``producers``
        in each producer's order, once each (:class:`~services.runtime.ordered.
        OrderedSubscription`, resuming after ``positions``), to ``handle(kind, key,
        payload)`` in ONE worker thread, as :meth:`subscribe_in_order` does.

        Every ``every_s`` while it works, and when it stops, the worker waits until
        ``outputs`` has recorded what the handler put, then saves ``snapshot()`` (the core's
        state) and the last seq handled per producer in ``checkpoint``, in one transaction:
        what the checkpoint counts is acknowledged (see :mod:`services.runtime.checkpoint`).
        """
        subscription = OrderedSubscription(
            self.session, self.ns, subscriptions, producers,
            settings=self.delivery, positions=positions,
        )  # fmt: skip
        self._subscribers.append(subscription)
        handled = dict(positions)
        name = f"{self.service}:worker"

        def save() -> None:
            if outputs is not None and not outputs.flush(FLUSH_TIMEOUT_S):
                log.warning("%s: outputs not recorded yet; checkpoint postponed", self.service)
                return
            checkpoint.save(snapshot(), fingerprint, handled)

        def work() -> None:
            dirty, saved = False, time.monotonic()
            try:
                while not self.stopping:
                    items = subscription.take(MAX_ORDERED_BATCH, timeout=_IDLE_POLL_S)
                    if items is None:
                        break
                    self._busy_since[name] = time.monotonic()
                    for item in items:
                        self.guarded(handle, item.kind, item.key, item.payload)
                        if item.producer is not None:
                            handled[item.producer] = (item.epoch, item.seq)
                            dirty = True
                    self._busy_since.pop(name, None)
                    if dirty and time.monotonic() - saved >= every_s:
                        self.guarded(save)
                        dirty, saved = False, time.monotonic()
                if dirty:
                    self.guarded(save)
            finally:
                checkpoint.close()

        self.spawn(work, name=name)
        return subscription

    def guarded(
        self,
        handle: Callable[..., object],
        *args: Any,
        refusals: tuple[type[Exception], ...] = (SchemaError,),
    ) -> Any:
        """``handle(*args)``; an exception becomes a dead letter (when ``args`` are
        ``(kind, key, payload)``) or a log line, never the end of the worker. The message of
        one of ``refusals`` (bad input) is the letter's reason; any other error is a bug and
        is logged with its traceback."""
        try:
            return handle(*args)
        except refusals as e:
            if len(args) == 3:
                self.deadletters.reject(args[1], str(e), args[2])
            else:
                log.warning("%s: %s", self.service, e)
        except Exception as e:
            log.exception("%s: error in %s", self.service, getattr(handle, "__name__", handle))
            if len(args) == 3:
                self.deadletters.reject(args[1], f"{type(e).__name__}: {e}", args[2])
        return None

    def subscribe(
        self,
        key: str,
        on_sample: Callable[[zenoh.Sample], None],
        *,
        capacity: int = DEFAULT_CAPACITY,
    ) -> zenoh.Subscriber:
        """A latest-only subscription for displays: a Zenoh ``RingChannel(capacity)`` that
        drops the oldest sample when full (never blocks the session), read by a worker
        thread calling ``on_sample``. Streams where nothing may be lost use
        :meth:`subscribe_in_order` or :meth:`subscribe_batches`. An exception from
        ``on_sample`` becomes a dead letter."""
        subscriber = self.session.declare_subscriber(key, zenoh.handlers.RingChannel(capacity))
        self._subscribers.append(subscriber)
        self.spawn(self._consume, subscriber, on_sample, name=f"{self.service}:{key}")
        return subscriber

    def declare_subscriber(self, key: str, handler: Any = None, **kwargs: Any) -> Any:
        """A subscriber (your handler or channel), undeclared first at close."""
        subscriber = self.session.declare_subscriber(key, handler, **kwargs)
        self._subscribers.append(subscriber)
        return subscriber

    def ask(self, selector: str, timeout: float) -> Iterator[tuple[str, bytes]]:
        """``(key, payload)`` of every reply to a start-up query (ends when all replied or at
        ``timeout``); an error reply is logged and skipped: it must not stop the service."""
        # replies take the query's QoS: BLOCK, so that none is dropped under congestion
        block = zenoh.CongestionControl.BLOCK
        for reply in self.session.get(selector, timeout=timeout, congestion_control=block):
            if reply.ok is None:
                log.warning("%s: error reply %r", selector, reply.err.payload.to_bytes()[:200])
                continue
            yield str(reply.ok.key_expr), reply.ok.payload.to_bytes()

    def declare_queryable(self, key: str, handler: Any = None, **kwargs: Any) -> zenoh.Queryable:
        """A queryable; a callback handler may reply directly (keep it short)."""
        return self.undeclare_at_close(self.session.declare_queryable(key, handler, **kwargs))

    def declare_publisher(self, key: str, **kwargs: Any) -> zenoh.Publisher:
        """A long-lived publisher (do not declare one per changing key, see zenoh#1518)."""
        return self.undeclare_at_close(self.session.declare_publisher(key, **kwargs))

    def reliable_publisher(
        self,
        beside: Path | str | None = None,
        *,
        durable: bool = True,
        service: str | None = None,
        raw: bool = False,
    ) -> ReliablePublisher:
        """``put(key, payload)`` recorded in this process's outbox
        ``outbox-{service}-{instance}.sqlite`` and replayed to returning consumers (at least
        once, see :mod:`services.runtime.delivery`); BLOCK congestion control. The file is
        in ``services.delivery.outbox.dir`` if set, else in the directory of ``beside`` (the
        service's store), else in ``var/``. ``durable=False``: an outbox in memory, for a
        process whose messages need not outlive it (the simulator). One per process and
        producer: the outbox is the producer ``{service}/{instance}``, with the configured
        instance id, else
        ``default`` (so that a restart finds its outbox again), else, when another process
        of this service holds that one, this process's own ``{hostname}-{pid}``. ``service``:
        publish as another producer than this service (the simulator's gateway); ``raw``:
        with the raw chain's retention (``services.delivery.raw_outbox``)."""
        directory = Path(beside).parent if beside is not None else DEFAULT_OUTBOX_DIR
        names = [self.conf.instance or "default", self.instance]
        publisher = ReliablePublisher.open_named(
            self.session, self.ns, service or self.service, names, self.delivery,
            directory if durable else None, raw=raw,
        )  # fmt: skip
        return self.undeclare_at_close(publisher)

    def undeclare_at_close(self, entity: _U) -> _U:
        """Undeclare ``entity`` at close (reliable publishers, matching listeners, …)."""
        self._declared.append(entity)
        return entity

    def spawn(self, target: Callable[..., object], *args: Any, name: str) -> threading.Thread:
        """Start a worker thread joined at close; it should return once ``stopping``."""
        thread = threading.Thread(target=self._guard, args=(target, *args), name=name, daemon=True)
        self._threads.append(thread)
        thread.start()
        return thread

    # --- internals -------------------------------------------------------------------------

    def _open(self) -> zenoh.Session:
        """Open the session, retrying while the router is not reachable yet."""
        deadline = time.monotonic() + self._connect_timeout
        while True:
            try:
                return zenoh.open(zenoh_config(self.conf))
            except zenoh.ZError as e:
                if self.stopping:  # asked to stop while waiting: a clean stop
                    log.info("%s: stopped before connecting", self.service)
                    raise SystemExit(0) from None
                if time.monotonic() >= deadline:
                    raise SystemExit(
                        f"{self.service}: cannot open a Zenoh session in {self.conf.mode} mode "
                        f"(connect {endpoints(self.conf, 'connect')}): {e}; is the router "
                        "running (`trackfusion router`) and --connect right?"
                    ) from None
                log.warning("%s: waiting for the router: %s", self.service, e)
                # backoff between attempts, cut short by stop(), not a wait for a result
                self.stop_event.wait(_RETRY_S)

    def _consume(
        self, subscriber: zenoh.Subscriber, on_sample: Callable[[zenoh.Sample], None]
    ) -> None:
        for sample in subscriber.handler:  # ends when the subscriber is undeclared
            try:
                on_sample(sample)
            except SchemaError as e:
                self.deadletters.reject_sample(sample, str(e))
            except Exception as e:
                log.exception("%s: error handling %s", self.service, sample.key_expr)
                self.deadletters.reject_sample(sample, f"{type(e).__name__}: {e}")

    def _watch_health(self) -> None:
        """Every ``health_interval_s``: ask the router for this service's own liveliness token.

        A session whose link was closed (a router restart, a cut link, a lease that expired)
        reconnects and re-declares by itself; one that did not is deaf: no token at the
        router, no subscriptions, yet nothing fails locally. When the token has not been seen
        for ``deaf_after_s``, the process stops with :data:`EXIT_SESSION_LOST` so that its
        supervisor (``trackfusion up``, systemd) restarts it. While healthy and no worker has
        been stuck on one batch for ``HUNG_AFTER_S``, it feeds the systemd watchdog.
        """
        last_seen = next_report = time.monotonic()
        while not self.stop_event.wait(self._health_interval_s):
            if self._token_at_router():
                last_seen = time.monotonic()
            elif time.monotonic() - last_seen >= self._deaf_after_s:
                log.error(
                    "%s/%s: the router has not held this service's token %s for %.0f s: the "
                    "session is lost; exiting with %d so that the supervisor restarts it",
                    self.service, self.instance, self.alive_key,
                    time.monotonic() - last_seen, EXIT_SESSION_LOST,
                )  # fmt: skip
                self.exit_code = EXIT_SESSION_LOST
                self.stop()
                return
            else:
                log.warning("%s: own liveliness token not seen at the router", self.service)
            now = time.monotonic()
            if now >= next_report:
                next_report = now + BACKLOG_REPORT_S
                self._report_backlog()
            hung = [n for n, t in list(self._busy_since.items()) if now - t > HUNG_AFTER_S]
            if hung:
                log.error(
                    "%s: %s busy on one batch for over %.0f s", self.service, hung, HUNG_AFTER_S
                )
            else:
                systemd.ping_watchdog()

    def _report_backlog(self) -> None:
        """A log line per inbox that has a backlog or spilled since the last line, and one
        per reliable publisher or subscription that delivery lost messages on (published
        without a record, deleted by a producer's retention before this consumer got them)."""
        for entity in self._declared + self._subscribers:
            unrecorded = getattr(entity, "unrecorded", 0)
            lost = getattr(entity, "lost", 0)
            if unrecorded or lost:
                log.warning(
                    "%s delivery: %d messages published without a record (at most once), "
                    "%d lost beyond a producer's retention, since the start",
                    self.service, unrecorded, lost,
                )  # fmt: skip
        for i, inbox in enumerate(self._inboxes):
            stats = inbox.stats()
            if stats.depth or stats.spilled:
                log.info(
                    "%s inbox %d: %d waiting (%.1f MB in memory, %.1f MB on disk), "
                    "%d received, %d spilled in all, longest callback %.1f ms",
                    self.service, i, stats.depth, stats.memory_bytes / 1e6,
                    stats.spill_bytes / 1e6, stats.received, stats.spilled,
                    stats.max_put_s * 1e3,
                )  # fmt: skip

    def _token_at_router(self) -> bool:
        try:
            replies = self.session.liveliness().get(
                self.alive_key, timeout=min(self._health_interval_s, 5.0)
            )
            return any(r.ok is not None and str(r.ok.key_expr) == self.alive_key for r in replies)
        except zenoh.ZError as e:
            log.warning("%s: liveliness query failed: %s", self.service, e)
            return False

    def _guard(self, target: Callable[..., object], *args: Any) -> None:
        try:
            target(*args)
        except Exception:
            log.exception("%s: worker %s failed; stopping", self.service, target)
            self.stop()

    def _install_signal_handlers(self) -> None:
        if threading.current_thread() is not threading.main_thread():
            log.debug("not in the main thread: no signal handlers, use stop()")
            return
        for signum in (signal.SIGINT, signal.SIGTERM):
            self._previous_handlers[signum] = signal.signal(signum, self._on_signal)

    def _restore_signal_handlers(self) -> None:
        for signum, handler in self._previous_handlers.items():
            signal.signal(signum, handler)
        self._previous_handlers.clear()

    def _on_signal(self, signum: int, _frame: FrameType | None) -> None:
        log.info("%s: received %s", self.service, signal.Signals(signum).name)
        # Event.set takes a lock the interrupted main thread may hold: set it from a thread.
        threading.Thread(target=self.stop, name="stop", daemon=True).start()


def run_service(
    service: str,
    conf: RuntimeConfig,
    setup: Callable[[ServiceRuntime], object],
    *,
    handle_signals: bool = True,
    stop_event: threading.Event | None = None,
) -> int:
    """Open, ``setup(rt)`` (declare subscriptions…), announce, wait for the stop, close: 0."""
    with ServiceRuntime(service, conf, handle_signals=handle_signals, stop_event=stop_event) as rt:
        setup(rt)
        return rt.run()


def run_command(args: argparse.Namespace, main: Callable[..., int], **options: Any) -> int:
    """What ``trackfusion <service>`` runs: log lines at ``--log-level``, then
    ``main(conf, **options)`` with the configuration of the Zenoh flags
    (:func:`~services.runtime.config.config_from_args`)."""
    configure_logging(args.log_level)
    return main(config_from_args(args), **options)


def network_stage_command(
    main: Callable[..., int], description: str, network: str, db: str
) -> tuple[Callable[[argparse.ArgumentParser], None], Callable[[argparse.Namespace], int]]:
    """``(add_arguments, run)`` of a stage of the raw chain, whose flags are ``--network``
    (``network`` says what it is for), ``--db`` (its checkpoint: ``db`` says what it holds)
    and the Zenoh flags: ``run`` calls ``main(conf, network_path=…, db=…)``."""

    def add_arguments(parser: argparse.ArgumentParser) -> None:
        parser.description = description
        add_network_argument(parser, network)
        parser.add_argument(
            "--db",
            metavar="FILE",
            type=Path,
            help=f"SQLite file of {db} (default: checkpoint-{{service}}-{{instance}}.sqlite "
            "beside the outboxes, services.delivery.outbox.dir or ./var)",
        )
        add_zenoh_arguments(parser)

    def run(args: argparse.Namespace) -> int:
        return run_command(args, main, network_path=args.network, db=args.db)

    return add_arguments, run


def open_checkpoint(rt: ServiceRuntime, db: str | Path | None) -> CheckpointStore:
    """The checkpoint of a stage of the raw chain: ``db``, else
    ``checkpoint-{service}-{instance}.sqlite`` in the outboxes' directory, with the
    configured instance id, else ``default``, else (another process holds that one) this
    process's own ``{hostname}-{pid}``, as the outboxes are named."""
    if db is not None:
        return CheckpointStore(db)
    directory = Path(rt.delivery.outbox.dir or DEFAULT_OUTBOX_DIR)
    names = [rt.conf.instance or "default", rt.instance]
    for name in names[:-1]:
        try:
            return CheckpointStore(directory / f"checkpoint-{rt.service}-{name}.sqlite")
        except CheckpointBusy as e:
            log.warning("%s; checkpointing as %s", e, names[-1])
    return CheckpointStore(directory / f"checkpoint-{rt.service}-{names[-1]}.sqlite")


def _undeclare(entity: _Undeclarable) -> None:
    try:
        entity.undeclare()
    except zenoh.ZError as e:
        log.warning("undeclare %s: %s", type(entity).__name__, e)


def configure_logging(level: str = "info") -> None:
    """Log lines to stderr (stdout stays for a command's output)."""
    logging.basicConfig(
        level=level.upper(),
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )
