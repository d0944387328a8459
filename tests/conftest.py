"""Shared fixtures: a free port, a unique namespace, an in-process Zenoh router on loopback,
client sessions and service configs connected to it, event-based waits, `trackfusion`
processes (``spawn``) and services in threads (``service_thread``), both from
``tests/support.py``.

Every session, process and thread started here is closed or stopped at teardown.
"""

from __future__ import annotations

import contextlib
import queue
import socket
import threading
import time
import uuid
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

import pytest
import zenoh
from support import TIMEOUT_S, Process, ServiceThread, cli, closed_at_exit

from bench.linkproxy import LinkProxy
from services.runtime.config import RuntimeConfig, reserve_rx_threads, zenoh_config

reserve_rx_threads()  # the router and its clients share this process


@pytest.fixture
def free_port() -> int:
    """A TCP port on 127.0.0.1 that was free a moment ago."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def link_proxy() -> Iterator[Callable[[int], LinkProxy]]:
    """``link_proxy(target_port)``: a :class:`LinkProxy` to cut and restore; closed at teardown."""
    proxies: list[LinkProxy] = []

    def start(target_port: int) -> LinkProxy:
        proxies.append(LinkProxy(target_port))
        return proxies[-1]

    yield start
    for proxy in proxies:
        proxy.close()


@pytest.fixture
def stack() -> Iterator[contextlib.ExitStack]:
    """An ExitStack for what a test opens itself (sessions, declarations), closed at teardown."""
    with contextlib.ExitStack() as stack:
        yield stack


@pytest.fixture
def namespace() -> str:
    """A key namespace of its own, so tests never see each other's messages."""
    return f"tftest_{uuid.uuid4().hex[:12]}"


@pytest.fixture
def router(free_port: int) -> Iterator[str]:
    """An in-process Zenoh router on tcp/127.0.0.1:{free_port}; yields its endpoint."""
    endpoint = f"tcp/127.0.0.1:{free_port}"
    settings = {
        "mode": "router",
        "listen": {"endpoints": [endpoint]},
        "scouting": {"delay": 0},  # nothing to scout: open at once instead of after 500 ms
    }
    session = zenoh.open(zenoh_config(settings))
    try:
        yield endpoint
    finally:
        session.close()


@pytest.fixture
def open_session(router: str) -> Iterator[Callable[..., zenoh.Session]]:
    """``open_session(mode="client")``: a session connected to ``router``, closed at teardown."""

    def open_(mode: str = "client") -> zenoh.Session:
        return zenoh.open(zenoh_config({"mode": mode, "connect": {"endpoints": [router]}}))

    with closed_at_exit(open_) as opened:
        yield opened


@pytest.fixture
def service_config(router: str, namespace: str, tmp_path: Path) -> RuntimeConfig:
    """A service configuration: client of ``router``, in ``namespace``, instance "test",
    producers' outboxes under ``tmp_path``."""
    return RuntimeConfig(
        ns=namespace,
        instance="test",
        zenoh={"mode": "client", "connect": {"endpoints": [router]}},
        services={"delivery": {"outbox": {"dir": str(tmp_path / "outbox")}}},
    )


@pytest.fixture
def until_matched() -> Callable[..., None]:
    """``until_matched(publisher)``: wait until a subscriber matches ``publisher``.

    A put right after another session declared its subscriber may reach the router first;
    a publisher's matching status says the router knows the subscriber.
    """

    def wait(publisher: zenoh.Publisher, timeout: float = TIMEOUT_S) -> None:
        matched = threading.Event()

        def on_status(status: zenoh.MatchingStatus) -> None:
            if status.matching:
                matched.set()

        listener = publisher.declare_matching_listener(on_status)
        try:
            if not publisher.matching_status.matching:  # a MatchingStatus, not a bool
                assert matched.wait(timeout), f"no subscriber matched {publisher.key_expr}"
        finally:
            listener.undeclare()

    return wait


class Collector:
    """A callback handler that puts what it receives on a queue, read with a timeout."""

    def __init__(self, transform: Callable[[Any], Any] = lambda x: x) -> None:
        self.queue: queue.Queue[Any] = queue.Queue()
        self._transform = transform

    def __call__(self, item: Any) -> None:
        self.queue.put(self._transform(item))  # short: the work happens in the test thread

    def get(self, timeout: float = TIMEOUT_S) -> Any:
        try:
            return self.queue.get(timeout=timeout)
        except queue.Empty:
            raise AssertionError(f"nothing received within {timeout} s") from None

    def empty(self) -> bool:
        return self.queue.empty()


@pytest.fixture
def collector() -> Callable[..., Collector]:
    """``collector(transform)``: a new :class:`Collector` to pass as a Zenoh callback."""
    return Collector


class Tokens(Collector):
    """A :class:`Collector` of ``(kind, key)`` liveliness changes, with the readiness waits."""

    def until_alive(self, *keys: str, timeout: float = TIMEOUT_S) -> None:
        """Take changes until every token of ``keys`` is up (other tokens' changes pass by)."""
        deadline = time.monotonic() + timeout
        down = set(keys)
        while down:
            try:
                kind, key = self.get(max(deadline - time.monotonic(), 0.0))
            except AssertionError:
                raise AssertionError(f"not up within {timeout} s: {sorted(down)}") from None
            if kind == zenoh.SampleKind.PUT:
                down.discard(key)
            elif key in keys:
                down.add(key)

    def next_change(self, key: str, timeout: float = TIMEOUT_S) -> zenoh.SampleKind:
        """The kind of the next change of the token ``key`` (others' changes pass by)."""
        deadline = time.monotonic() + timeout
        while True:
            try:
                kind, changed = self.get(max(deadline - time.monotonic(), 0.0))
            except AssertionError:
                raise AssertionError(f"no change of {key} within {timeout} s") from None
            if changed == key:
                return kind


@pytest.fixture
def liveliness_events() -> Iterator[Callable[[zenoh.Session, str], Tokens]]:
    """``liveliness_events(session, keyexpr)``: :class:`Tokens`, the ``(kind, key)``
    liveliness changes (current tokens first, as PUT); the subscriber is undeclared at
    teardown.

    Only changes are collected: a token declared while the subscriber is being declared can
    arrive twice, once in the history and once live.
    """
    subscribers: list[zenoh.Subscriber] = []

    def watch(session: zenoh.Session, keyexpr: str) -> Tokens:
        events = Tokens()
        alive: set[str] = set()
        lock = threading.Lock()

        def on_sample(sample: zenoh.Sample) -> None:
            key, put = str(sample.key_expr), sample.kind == zenoh.SampleKind.PUT
            with lock:
                if put == (key in alive):
                    return  # no change
                if put:
                    alive.add(key)
                else:
                    alive.discard(key)
                events((sample.kind, key))

        subscribers.append(
            session.liveliness().declare_subscriber(keyexpr, on_sample, history=True)
        )
        return events

    try:
        yield watch
    finally:
        for subscriber in subscribers:
            subscriber.undeclare()


@pytest.fixture
def spawn(tmp_path: Path) -> Iterator[Callable[..., Process]]:
    """``spawn(name, *args)``: start `trackfusion ARGS…`; ``spawn(name, argv=[…], cwd=…)``:
    another command line (:class:`support.Process`, its log ``{tmp_path}/{name}-{n}.log``).
    Every one still running is stopped at teardown."""
    started: list[Process] = []

    def start(
        name: str, *args: str, argv: Sequence[str] | None = None, cwd: Path | None = None
    ) -> Process:
        assert argv is None or not args, "trackfusion arguments or a command line, not both"
        log_path = tmp_path / f"{name}-{len(started)}.log"
        process = Process(log_path, cli(*args) if argv is None else argv, cwd=cwd)
        started.append(process)
        return process

    yield start
    for process in started:
        process.stop()


@pytest.fixture
def service_thread(
    open_session: Callable[..., zenoh.Session],
    liveliness_events: Callable[[zenoh.Session, str], Tokens],
) -> Iterator[Callable[..., ServiceThread]]:
    """``service_thread(name, main, alive=key)``: ``main(stop_event)`` in a thread
    (:class:`support.ServiceThread`); with ``alive``, returned once that liveliness token is
    up (again, after a restart). Each one still running is stopped at teardown; one that
    does not then exit with 0, or raised, fails the test there."""
    started: list[ServiceThread] = []
    tokens: dict[str, Tokens] = {}
    observer: list[zenoh.Session] = []

    def start(
        name: str, main: Callable[[threading.Event], int | None], *, alive: str | None = None
    ) -> ServiceThread:
        if alive is not None and alive not in tokens:
            if not observer:
                observer.append(open_session())
            tokens[alive] = liveliness_events(observer[0], alive)
        service = ServiceThread(name, main).start()
        started.append(service)
        if alive is not None:  # after a restart: past the DELETE of the previous run's token
            tokens[alive].until_alive(alive)
        return service

    yield start
    for service in started:
        if service.running:  # told to stop, a service exits with 0
            assert service.stop() == 0, f"{service.name} did not exit with 0 on its stop event"
