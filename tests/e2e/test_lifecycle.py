"""Real processes: `trackfusion router` and `trackfusion deadletters` start, serve and stop
with exit code 0 on SIGTERM and on SIGINT."""

from __future__ import annotations

import os
import queue
import signal
import subprocess
import sys
import threading
from collections.abc import Iterator
from contextlib import ExitStack, suppress
from pathlib import Path

import pytest
import zenoh

from schemas import DeadLetter, encode, keys
from services.runtime.config import zenoh_config

STOP_S = 5.0  # a stopped service must exit within this
READY_S = 20.0  # generous: interpreter start + imports on a loaded CI machine


class Process:
    """A `trackfusion …` subprocess in its own process group; stdout lines on a queue."""

    def __init__(self, stack: ExitStack, log_dir: Path, name: str, *args: str) -> None:
        self.name = name
        self.log_path = log_dir / f"{name}.log"
        log = stack.enter_context(self.log_path.open("w"))
        self.popen = subprocess.Popen(
            [sys.executable, "-m", "services.cli", *args],
            stdout=subprocess.PIPE,
            stderr=log,
            stdin=subprocess.DEVNULL,
            text=True,
            start_new_session=True,
        )
        stack.callback(self.kill)
        self.lines: queue.Queue[str] = queue.Queue()
        self._reader = threading.Thread(target=self._read, name=f"{name}-stdout", daemon=True)
        self._reader.start()

    def _read(self) -> None:
        assert self.popen.stdout is not None
        for line in self.popen.stdout:
            self.lines.put(line.rstrip("\n"))

    def line(self, timeout: float) -> str:
        try:
            return self.lines.get(timeout=timeout)
        except queue.Empty:
            raise AssertionError(
                f"{self.name} printed nothing in {timeout} s{self.log()}"
            ) from None

    def signal(self, signum: int) -> None:
        os.killpg(self.popen.pid, signum)  # the whole group, as Ctrl-C in a terminal does

    def wait(self, timeout: float) -> int:
        try:
            return self.popen.wait(timeout)
        except subprocess.TimeoutExpired:
            raise AssertionError(
                f"{self.name} still running after {timeout} s{self.log()}"
            ) from None

    def log(self) -> str:
        return f"\n--- {self.name} log ---\n{self.log_path.read_text()}"

    def kill(self) -> None:
        """Teardown: kill what is left, reap it, close the pipe."""
        if self.popen.poll() is None:
            with suppress(ProcessLookupError):
                os.killpg(self.popen.pid, signal.SIGKILL)
            self.popen.wait(STOP_S)
        self._reader.join(STOP_S)
        if self.popen.stdout is not None:
            self.popen.stdout.close()


@pytest.fixture
def stack() -> Iterator[ExitStack]:
    with ExitStack() as stack:
        yield stack


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGINT], ids=["SIGTERM", "SIGINT"])
def test_router_and_deadletters_serve_and_stop_cleanly(
    signum, stack, tmp_path, free_port, namespace, until_matched, liveliness_events
):
    endpoint = f"tcp/127.0.0.1:{free_port}"
    router = Process(stack, tmp_path, "router", "router", "--listen", endpoint)
    service = Process(
        stack,
        tmp_path,
        "deadletters",
        *("deadletters", "--connect", endpoint, "--ns", namespace, "--instance", "e2e"),
    )

    # The test's own client: zenoh retries the connection until the router listens.
    settings = {"connect": {"endpoints": [endpoint], "timeout_ms": int(READY_S * 1000)}}
    session = stack.enter_context(zenoh.open(zenoh_config(settings)))
    alive = keys.alive(namespace, "deadletters", "e2e")
    events = liveliness_events(session, alive)
    assert events.get(READY_S) == (zenoh.SampleKind.PUT, alive), service.log()

    publisher = session.declare_publisher(keys.deadletter(namespace, "e2e"))
    stack.callback(publisher.undeclare)
    until_matched(publisher)
    letter = DeadLetter(
        service="e2e",
        key=f"{namespace}/raw/t1/u1",
        reason="v: unknown schema version 9",
        payload_head=b"\x82\xa1v\x09",
        received_at=1.0,
    )
    publisher.put(encode(letter))
    assert service.line(STOP_S) == f"e2e {namespace}/raw/t1/u1 v: unknown schema version 9"

    service.signal(signum)
    assert service.wait(STOP_S) == 0, service.log()
    assert events.get(STOP_S) == (zenoh.SampleKind.DELETE, alive)  # token gone with it
    router.signal(signum)
    assert router.wait(STOP_S) == 0, router.log()
