"""Shared fixtures: a free port, a unique namespace, an in-process Zenoh router on loopback,
client sessions and service configs connected to it, and event-based waits.

Every session opened here is closed at teardown; nothing waits with ``time.sleep``.
"""

from __future__ import annotations

import contextlib
import os
import queue
import signal
import socket
import subprocess
import sys
import threading
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
import zenoh
from linkproxy import LinkProxy

from services.runtime.config import RuntimeConfig, zenoh_config

TIMEOUT_S = 5.0  # upper bound of every wait; tests normally go on in milliseconds
STOP_GRACE_S = 15.0  # teardown: SIGTERM, then SIGKILL; `up` gives its children 5 s of it


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
    sessions: list[zenoh.Session] = []

    def open_(mode: str = "client") -> zenoh.Session:
        session = zenoh.open(zenoh_config({"mode": mode, "connect": {"endpoints": [router]}}))
        sessions.append(session)
        return session

    try:
        yield open_
    finally:
        for session in reversed(sessions):
            session.close()


@pytest.fixture
def service_config(router: str, namespace: str) -> RuntimeConfig:
    """A service configuration: client of ``router``, in ``namespace``, instance "test"."""
    return RuntimeConfig(
        ns=namespace,
        instance="test",
        zenoh={"mode": "client", "connect": {"endpoints": [router]}},
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


@pytest.fixture
def liveliness_events() -> Iterator[Callable[[zenoh.Session, str], Collector]]:
    """``liveliness_events(session, keyexpr)``: a Collector of ``(kind, key)`` liveliness
    changes (current tokens first, as PUT); the subscriber is undeclared at teardown.

    Only changes are collected: a token declared while the subscriber is being declared can
    arrive twice, once in the history and once live.
    """
    subscribers: list[zenoh.Subscriber] = []

    def watch(session: zenoh.Session, keyexpr: str) -> Collector:
        events = Collector()
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


class TrackfusionProcess:
    """A `trackfusion …` subprocess in its own process group, its output to a log file."""

    def __init__(self, log_path: Path, *args: str) -> None:
        self.log_path = log_path
        with log_path.open("w") as log:
            self.popen = subprocess.Popen(
                [sys.executable, "-m", "services.cli", *args],
                stdout=log,
                stderr=subprocess.STDOUT,
                stdin=subprocess.DEVNULL,
                start_new_session=True,
            )

    def signal(self, signum: int) -> None:
        os.killpg(self.popen.pid, signum)

    def wait(self, timeout: float) -> int:
        return self.popen.wait(timeout)

    def log(self) -> str:
        return f"\n--- {self.log_path.name} ---\n{self.log_path.read_text()}"

    def stop(self) -> None:
        """SIGTERM, then SIGKILL after a grace period. `up` must be asked: it stops its
        children, which run in sessions of their own that a SIGKILL to it would orphan."""
        if self.popen.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(self.popen.pid, signal.SIGTERM)
            try:
                self.popen.wait(STOP_GRACE_S)
            except subprocess.TimeoutExpired:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(self.popen.pid, signal.SIGKILL)
                self.popen.wait(5)


@pytest.fixture
def spawn(tmp_path: Path) -> Iterator[Callable[..., TrackfusionProcess]]:
    """Start `trackfusion ARGS…` processes; every one still running is stopped at teardown."""
    started: list[TrackfusionProcess] = []

    def start(name: str, *args: str) -> TrackfusionProcess:
        process = TrackfusionProcess(tmp_path / f"{name}-{len(started)}.log", *args)
        started.append(process)
        return process

    yield start
    for process in started:
        process.stop()
