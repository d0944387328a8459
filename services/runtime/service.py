"""The one way a service starts and stops on Zenoh.

::

    def main(conf: RuntimeConfig) -> int:
        with ServiceRuntime("filtering", conf, handle_signals=True) as rt:
            rt.subscribe(keys.segment_keys(rt.ns, "index"), on_index)  # worker thread
            rt.declare_queryable(keys.q_alerts(rt.ns), on_query)
            return rt.run()  # liveliness token = ready; waits for SIGINT/SIGTERM/stop()

Leaving the block undeclares everything (subscribers first, so workers drain and end; then
queryables, publishers, the dead-letter publisher and the liveliness token) and closes the
session. Tests use the same object in-process and call :meth:`ServiceRuntime.stop`.
"""

from __future__ import annotations

import dataclasses
import logging
import queue
import signal
import threading
import time
from collections.abc import Callable, Mapping
from types import FrameType
from typing import Any, Protocol, Self, TypeVar

import zenoh

from schemas import SchemaError, keys
from services.runtime.config import RuntimeConfig, default_instance, endpoints, zenoh_config
from services.runtime.deadletter import DeadLetterPublisher
from services.runtime.delivery import (
    DeliverySettings,
    ReliablePublisher,
    declare_reliable_subscriber,
)

log = logging.getLogger(__name__)

DEFAULT_CAPACITY = 1024  # samples buffered per subscription before the receive thread blocks
JOIN_TIMEOUT_S = 2.0  # per worker at shutdown; the whole stop must stay well under 5 s
CONNECT_TIMEOUT_S = 30.0  # how long to keep retrying the first connection at startup
FLUSH_TIMEOUT_S = 2.0  # at most this long waiting for the router's answer at close
_RETRY_S = 0.5


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
    ) -> None:
        self.service = service
        self.conf = conf
        self.ns = conf.ns
        self.instance = conf.instance or default_instance()
        self.alive_key = keys.alive(self.ns, service, self.instance)  # checks the chunks
        self.stop_event = stop_event if stop_event is not None else threading.Event()
        self.delivery = DeliverySettings.from_options(conf.options("delivery"))
        self._handle_signals = handle_signals
        self._connect_timeout = connect_timeout
        self._session: zenoh.Session | None = None
        self._deadletters: DeadLetterPublisher | None = None
        self._token: zenoh.LivelinessToken | None = None
        self._subscribers: list[_Undeclarable] = []
        self._declared: list[_Undeclarable] = []
        self._threads: list[threading.Thread] = []
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

    def wait(self, timeout: float | None = None) -> bool:
        """Block until :meth:`stop` (or a signal); True if stopped, False on timeout."""
        return self.stop_event.wait(timeout)

    def run(self) -> int:
        """Announce, wait for the stop event, return exit code 0 (leave the block to close)."""
        self.announce()
        self.wait()
        log.info("%s/%s stopping", self.service, self.instance)
        return 0

    def close(self) -> None:
        """Stop workers, undeclare everything, close the session. Idempotent."""
        self.stop_event.set()
        started = time.monotonic()
        for sub in reversed(self._subscribers):  # ends the workers' channel iteration
            _undeclare(sub)
        self._subscribers.clear()
        for thread in self._threads:
            if thread is not threading.current_thread():
                thread.join(JOIN_TIMEOUT_S)
                if thread.is_alive():
                    log.warning("worker %s did not stop within %.1f s", thread.name, JOIN_TIMEOUT_S)
        self._threads.clear()
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
        capacity: int = DEFAULT_CAPACITY,
        reliable: bool = False,
    ) -> None:
        """Several subscriptions ``{kind: key expression}`` into ONE bounded queue drained by
        ONE worker thread calling ``handle(kind, key, payload)``, so a core stays
        single-threaded. Order is kept per key (each subscription's callback runs on its own
        Zenoh thread, so not across them). A full queue blocks the receive thread: nothing is
        dropped. A SchemaError (or any other error) becomes a dead letter and the worker goes
        on; ``on_end`` runs once every subscription has been undeclared. ``reliable``: see
        :meth:`declare_subscriber`.
        """
        inbox: queue.Queue[Any] = queue.Queue(capacity)
        ended = object()

        def callback(kind: str) -> zenoh.handlers.Callback:
            def on_sample(sample: zenoh.Sample) -> None:
                inbox.put((kind, str(sample.key_expr), sample.payload.to_bytes()))

            return zenoh.handlers.Callback(on_sample, lambda: inbox.put(ended))

        def work() -> None:
            remaining = len(subscriptions)
            while remaining:
                item = inbox.get()
                if item is ended:
                    remaining -= 1
                    continue
                kind, key, payload = item
                try:
                    handle(kind, key, payload)
                except SchemaError as e:
                    self.deadletters.reject(key, str(e), payload)
                except Exception as e:
                    log.exception("%s: error handling %s", self.service, key)
                    self.deadletters.reject(key, f"{type(e).__name__}: {e}", payload)
            if on_end is not None:
                on_end()

        for kind, key in subscriptions.items():
            self.declare_subscriber(key, callback(kind), reliable=reliable)
        self.spawn(work, name=f"{self.service}:worker")

    def subscribe(
        self,
        key: str,
        on_sample: Callable[[zenoh.Sample], None],
        *,
        capacity: int = DEFAULT_CAPACITY,
        latest_only: bool = False,
        dead_letter_errors: bool = True,
    ) -> zenoh.Subscriber:
        """Subscribe to ``key`` and call ``on_sample`` in a worker thread, never in Zenoh's.

        The subscription is buffered in a ``FifoChannel(capacity)`` (nothing dropped; a full
        buffer slows the sender down) or, with ``latest_only``, a ``RingChannel(capacity)``
        that drops the oldest (for displays). An exception from ``on_sample`` becomes a dead
        letter (``SchemaError``: its message is the reason) unless ``dead_letter_errors`` is
        False; the worker keeps going either way.
        """
        channel: Any = (
            zenoh.handlers.RingChannel(capacity)
            if latest_only
            else zenoh.handlers.FifoChannel(capacity)
        )
        subscriber = self.session.declare_subscriber(key, channel)
        self._subscribers.append(subscriber)
        self.spawn(
            self._consume, subscriber, on_sample, dead_letter_errors, name=f"{self.service}:{key}"
        )
        return subscriber

    def declare_subscriber(
        self, key: str, handler: Any = None, *, reliable: bool = False, **kwargs: Any
    ) -> Any:
        """A subscriber (your handler or channel), undeclared first at close.

        ``reliable``: an advanced subscriber that also gets the cached history of every
        :meth:`reliable_publisher` on ``key`` and recovers what it missed (see
        :mod:`services.runtime.delivery`); messages may then arrive more than once.
        """
        if reliable:
            subscriber = declare_reliable_subscriber(self.session, key, handler)
        else:
            subscriber = self.session.declare_subscriber(key, handler, **kwargs)
        self._subscribers.append(subscriber)
        return subscriber

    def declare_queryable(self, key: str, handler: Any = None, **kwargs: Any) -> zenoh.Queryable:
        """A queryable; a callback handler may reply directly (keep it short)."""
        return self.track(self.session.declare_queryable(key, handler, **kwargs))

    def declare_publisher(self, key: str, **kwargs: Any) -> zenoh.Publisher:
        """A long-lived publisher (do not declare one per changing key, see zenoh#1518)."""
        return self.track(self.session.declare_publisher(key, **kwargs))

    def reliable_publisher(self, cache_samples: int | None = None) -> ReliablePublisher:
        """``put(key, payload)`` with a per-key cache for late and returning subscribers
        (at-least-once, see :mod:`services.runtime.delivery`); BLOCK congestion control.
        ``cache_samples`` overrides the configured cache size (messages kept per key)."""
        settings = self.delivery
        if cache_samples is not None:
            settings = dataclasses.replace(settings, cache_samples=cache_samples)
        return self.track(ReliablePublisher(self.session, settings))

    def track(self, entity: _U) -> _U:
        """Undeclare ``entity`` at close (advanced subscribers, matching listeners, …)."""
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
        self,
        subscriber: zenoh.Subscriber,
        on_sample: Callable[[zenoh.Sample], None],
        dead_letter_errors: bool,
    ) -> None:
        for sample in subscriber.handler:  # ends when the subscriber is undeclared
            try:
                on_sample(sample)
            except SchemaError as e:
                if dead_letter_errors:
                    self.deadletters.reject_sample(sample, str(e))
                else:
                    log.warning("rejected %s: %s", sample.key_expr, e)
            except Exception as e:
                log.exception("%s: error handling %s", self.service, sample.key_expr)
                if dead_letter_errors:
                    self.deadletters.reject_sample(sample, f"{type(e).__name__}: {e}")

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


def _undeclare(entity: _Undeclarable) -> None:
    try:
        entity.undeclare()
    except zenoh.ZError as e:
        log.warning("undeclare %r: %s", entity, e)


def configure_logging(level: str = "info") -> None:
    """Log lines to stderr (stdout stays for a command's output)."""
    logging.basicConfig(
        level=level.upper(),
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )
