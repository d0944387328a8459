"""What every tier of the tests shares: one launcher of processes (`trackfusion …` or another
command line), one service-in-a-thread, one bounded wait for conditions that have no event.

The fixtures of ``tests/conftest.py`` (``spawn``, ``service_thread``) hand these out and clean
up after them; a module that manages its own (the fuzz harness) uses the classes directly.
"""

from __future__ import annotations

import contextlib
import json
import os
import queue
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

TIMEOUT_S = 5.0  # upper bound of a wait in-process; tests normally go on in milliseconds
STOP_S = 10.0  # a stopped service thread must have returned within this
STOP_GRACE_S = 15.0  # process teardown: SIGTERM, then SIGKILL; `up` gives its children 5 s
POLL_S = 0.05  # wait_for's interval: only for conditions that signal nothing


def cli(*args: str) -> list[str]:
    """The command line of `trackfusion ARGS…` run by this interpreter."""
    return [sys.executable, "-m", "services.cli", *args]


def run_cli(*args: str, timeout: float = 120.0) -> subprocess.CompletedProcess[str]:
    """Run a `trackfusion` command to its end; its exit code, stdout and stderr."""
    return subprocess.run(cli(*args), capture_output=True, text=True, timeout=timeout)


def wait_for(
    predicate: Callable[[], object],
    timeout: float,
    what: str | Callable[[], str],
    *,
    poll_s: float = POLL_S,
) -> object:
    """Poll ``predicate`` every ``poll_s`` seconds until it returns something true (returned)
    or fail after ``timeout`` seconds saying ``what`` did not happen (a function: called
    then, to tell what was last seen).

    Only for conditions that signal nothing (a file another process writes, a port it
    opens, the answers of its queryables, a counter with no event); where an event, a
    condition variable or a queue exists, wait on that instead.
    """
    deadline = time.monotonic() + timeout
    while not (result := predicate()):
        if time.monotonic() >= deadline:
            raise AssertionError(
                f"not within {timeout} s: {what if isinstance(what, str) else what()}"
            )
        time.sleep(poll_s)
    return result


def accepts_connections(port: int) -> bool:
    """Whether something listens on 127.0.0.1:``port`` (a real connect, closed at once)."""
    try:
        socket.create_connection(("127.0.0.1", port), timeout=1).close()
    except OSError:
        return False
    return True


class Process:
    """A process (``argv``: usually :func:`cli`'s `trackfusion …`) in its own process group,
    so that a signal reaches its whole group as Ctrl-C in a terminal does.

    Its stderr and stdout both go to ``log_path``; stdout's lines can also be read one by
    one as they come (:meth:`line`) or whole once it has exited (:meth:`stdout`).
    """

    def __init__(self, log_path: Path, argv: Sequence[str], *, cwd: Path | None = None) -> None:
        self.name, self.log_path = log_path.stem, log_path
        # append mode: the child's stderr and the reader's stdout lines share the file
        self._log = log_path.open("a", buffering=1)
        try:
            self.popen = subprocess.Popen(
                list(argv),
                cwd=cwd,
                stdout=subprocess.PIPE,
                stderr=self._log,
                stdin=subprocess.DEVNULL,
                text=True,
                errors="replace",
                start_new_session=True,
            )
        except BaseException:
            self._log.close()
            raise
        self._lines: queue.Queue[str] = queue.Queue()
        self._stdout: list[str] = []
        self._reader = threading.Thread(target=self._read, name=f"{self.name}-stdout", daemon=True)
        self._reader.start()

    def _read(self) -> None:
        """Until the pipe's end; then it closes the pipe and its side of the log (this thread
        alone uses them, so nothing is closed under it)."""
        assert self.popen.stdout is not None
        with self.popen.stdout, self._log:
            for line in self.popen.stdout:
                self._stdout.append(line)
                self._lines.put(line.rstrip("\n"))
                self._log.write(line)

    @property
    def running(self) -> bool:
        return self.popen.poll() is None

    def signal(self, signum: int) -> None:
        """Send ``signum`` to the process group."""
        os.killpg(self.popen.pid, signum)

    def wait(self, timeout: float) -> int:
        """Its exit code; fails with its log if it still runs after ``timeout`` seconds."""
        try:
            return self.popen.wait(timeout)
        except subprocess.TimeoutExpired:
            raise AssertionError(
                f"{self.name} still running after {timeout} s{self.log()}"
            ) from None

    def line(self, timeout: float) -> str:
        """The next line it prints on stdout; fails with its log if none comes in time."""
        try:
            return self._lines.get(timeout=timeout)
        except queue.Empty:
            raise AssertionError(
                f"{self.name} printed nothing in {timeout} s{self.log()}"
            ) from None

    def stdout(self) -> str:
        """Everything it printed on stdout; call after it has exited."""
        assert not self.running, f"{self.name} is still running"
        self._reader.join(STOP_S)
        return "".join(self._stdout)

    def until(
        self,
        predicate: Callable[[], object],
        timeout: float,
        what: str | Callable[[], str],
        *,
        poll_s: float = POLL_S,
    ) -> object:
        """:func:`wait_for` that fails at once, with the log, if the process exits first."""

        def check() -> object:
            assert self.running, f"{self.name} exited ({self.popen.returncode}){self.log()}"
            return predicate()

        def failure() -> str:
            return f"{what if isinstance(what, str) else what()}{self.log()}"

        return wait_for(check, timeout, failure, poll_s=poll_s)

    def log(self) -> str:
        return f"\n--- {self.log_path.name} ---\n{self.log_path.read_text()}"

    def stop(self) -> None:
        """Teardown: SIGTERM, then SIGKILL after a grace period; reap it.

        `up` must be asked rather than killed: it stops its children, which run in sessions
        of their own that a SIGKILL to it would orphan."""
        if self.running:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(self.popen.pid, signal.SIGTERM)
            try:
                self.popen.wait(STOP_GRACE_S)
            except subprocess.TimeoutExpired:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(self.popen.pid, signal.SIGKILL)
                self.popen.wait(5)
        self._reader.join(STOP_S)  # the pipe ends with the process (and whatever inherited it)


class ServiceThread:
    """A service's ``main(stop_event)`` in a thread, as its process runs it, until
    :meth:`stop` sets the event; as a context manager, stopped at the end of the block and
    checked to have exited with 0."""

    def __init__(self, name: str, main: Callable[[threading.Event], int | None]) -> None:
        self.name = name
        self.stop_event = threading.Event()
        self.exit_code: int | None = None
        self._main = main
        self._error: BaseException | None = None
        self.thread = threading.Thread(target=self._run, name=f"{name}-under-test")

    def _run(self) -> None:
        try:
            self.exit_code = self._main(self.stop_event)
        except SystemExit as exc:  # what the CLI would turn into the process's exit code
            self.exit_code = exc.code if isinstance(exc.code, int) else 1
        except BaseException as exc:  # re-raised in the test's thread by stop()
            self._error = exc

    def start(self) -> ServiceThread:
        self.thread.start()
        return self

    def __enter__(self) -> ServiceThread:
        return self

    def __exit__(self, exc_type: object, *_: object) -> None:
        """Stop it; when the block ended normally, its exit code must be 0."""
        if exc_type is not None:
            with contextlib.suppress(Exception):  # the block's own failure is the one to see
                self.stop()
            return
        code = self.stop()
        assert code == 0, f"{self.name} exited with {code}"

    @property
    def running(self) -> bool:
        return self.thread.is_alive()

    def stop(self, timeout: float = STOP_S) -> int | None:
        """Set the stop event; the exit code once ``main`` has returned (what it raised, raised
        here); fails if it has not returned within ``timeout`` seconds."""
        self.stop_event.set()
        self.thread.join(timeout)
        assert not self.thread.is_alive(), f"{self.name} still running {timeout} s after stop"
        if self._error is not None:
            error, self._error = self._error, None
            raise error
        return self.exit_code


@contextlib.contextmanager
def closed_at_exit(open_: Callable[..., Any]) -> Iterator[Callable[..., Any]]:
    """``open_`` whose sessions (anything with ``close()``) are all closed, newest first,
    when the block ends."""
    sessions: list[Any] = []

    def opened(*args, **kwargs) -> Any:
        session = open_(*args, **kwargs)
        sessions.append(session)
        return session

    try:
        yield opened
    finally:
        for session in reversed(sessions):
            session.close()


def ready_querier(session: Any, key_expr: str, timeout: float = TIMEOUT_S) -> Any:
    """A ``zenoh.Querier`` on ``key_expr`` of ``session`` once the router knows a queryable
    matching it (the matching listener's event, not a sleep)."""
    matched = threading.Event()
    querier = session.declare_querier(key_expr, timeout=timeout)
    listener = querier.declare_matching_listener(lambda s: matched.set() if s.matching else None)
    try:
        assert querier.matching_status.matching or matched.wait(timeout), "no queryable matched"
    finally:
        listener.undeclare()
    return querier


def outbox_config(directory: Path) -> Path:
    """A service configuration file (``--config``) that keeps producers' outboxes in
    ``directory`` rather than in ``./var`` of the checkout."""
    path = directory / "outbox.json5"
    path.write_text(json.dumps({"services": {"delivery": {"outbox": {"dir": str(directory)}}}}))
    return path
