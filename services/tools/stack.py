"""`trackfusion up`: the whole system on one machine, from ``services/defaults/stack.json5``.

An embedded Zenoh router (this process), every service and simulator of the stack file as
a child process connected to it, and a live status table: services alive (liveliness
tokens), trains seen in the last minutes, messages per second, segments tracked, alerts
raised.

``up`` supervises its children: a process that exits is started again (per its ``restart``
policy), and so is one whose liveliness token has been missing for ``token_missing_s``
after it was first seen (SIGTERM, SIGKILL after the grace period), with an exponential
backoff. The board flags stalled flows (indices arriving but no state published, GPS but
no index) and is written each second to ``{state_dir}/health.json`` for programs to read
and published on ``{ns}/health/stack`` (a StackHealth) for the viewer's health board.
Supervision runs on ``time.monotonic()``: it is about wall time, not event time.
``up --network FILE`` runs the stack on another network: ``{network}`` in the processes'
args (the default stack gives it to every process that reads a network) becomes FILE.
Ctrl-C (or SIGTERM) stops the children (SIGTERM, SIGKILL after 5 s) and then the router.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import os
import signal
import subprocess
import sys
import threading
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, fields
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, TextIO

import zenoh

from schemas import Alert, SchemaError, ServiceHealth, StackHealth, decode, encode, keys
from services.defaults import default_file
from services.runtime.config import default_instance, read_json5, zenoh_config
from services.runtime.service import configure_logging

log = logging.getLogger(__name__)
DEFAULT_STACK = default_file("stack.json5")
# In a stack file's args: the directory of the packaged default files (services/defaults/),
# so that a stack names them wherever the package is installed and `up` is run.
DEFAULTS = "{defaults}"
# In a stack file's args: the network file, `up --network FILE` or the demo network.
NETWORK = "{network}"
DEMO_NETWORK_ARG = f"{DEFAULTS}/demo-network.geojson"
WATCHED = ("state", "index", "alert", "gps", "trc", "maintenance", "deadletter")
RESTART_POLICIES = ("always", "on-failure", "never")
TICK_S = 0.5  # supervision step
REFRESH_S = 1.0  # health file and rates (the board on a terminal; every 5 s otherwise)
TRAIN_SEEN_S = 300.0  # a train counts as seen for this long after its last GPS fix
HEALTH_FILE = "health.json"
# Environment of `up` that must not reach the children: a child would talk to the
# systemd notify socket of `up`'s unit as if it were the unit's main process.
NOT_INHERITED = ("NOTIFY_SOCKET", "WATCHDOG_USEC", "WATCHDOG_PID")


@dataclass(frozen=True)
class ProcessSpec:
    name: str  # also what `trackfusion status` lists it as (its --instance)
    command: str  # trackfusion subcommand
    args: tuple[str, ...]
    # "always": start again whatever the exit code; "on-failure": unless it exits 0 (the
    # default of `simulate`, which finishes its world); "never": leave it stopped.
    restart: str = "always"

    @property
    def instance(self) -> str | None:
        """The ``--instance`` it is given, if any (its liveliness token's last chunk)."""
        args = list(self.args)
        for i, arg in enumerate(args):
            if arg == "--instance" and i + 1 < len(args):
                return args[i + 1]
            if arg.startswith("--instance="):
                return arg.split("=", 1)[1]
        return None


@dataclass(frozen=True)
class Supervision:
    """Thresholds of the supervision (seconds of wall time); the stack file's ``supervision``."""

    token_missing_s: float = 15.0  # token gone this long after it was first seen: restart
    backoff_initial_s: float = 1.0  # first restart delay, doubled on each quick failure…
    backoff_max_s: float = 60.0  # …up to this
    backoff_reset_s: float = 180.0  # a run this long resets the delay to the first one
    stop_grace_s: float = 5.0  # SIGTERM, then SIGKILL after this
    stalled_state_s: float = 30.0  # indices arriving, no state published this long: stalled
    stalled_index_s: float = 60.0  # GPS arriving, no index this long: stalled


@dataclass(frozen=True)
class Stack:
    ns: str
    listen: str
    state_dir: Path
    processes: tuple[ProcessSpec, ...]
    supervision: Supervision = field(default_factory=Supervision)
    network: str | None = None  # the network file of its processes' {network}; None: none


def _process_spec(raw: dict[str, Any], network: str) -> ProcessSpec:
    command = raw.get("command", raw["name"])
    restart = raw.get("restart", "on-failure" if command == "simulate" else "always")
    if restart not in RESTART_POLICIES:
        raise ValueError(f"{raw['name']}: restart must be one of {RESTART_POLICIES}")
    defaults = str(DEFAULT_STACK.parent)
    args = tuple(
        str(arg).replace(NETWORK, network).replace(DEFAULTS, defaults)
        for arg in raw.get("args", [])
    )
    return ProcessSpec(raw["name"], command, args, restart)


def _supervision(raw: dict[str, Any]) -> Supervision:
    unknown = set(raw) - {f.name for f in fields(Supervision)}
    if unknown:
        raise ValueError(f"supervision: unknown settings {sorted(unknown)}")
    settings = Supervision(**{k: float(v) for k, v in raw.items()})
    if any(v <= 0 for v in asdict(settings).values()):
        raise ValueError(f"supervision: every setting must be > 0, got {raw}")
    return settings


def load_stack(
    path: str | Path = DEFAULT_STACK, *, ns: str | None = None, listen=None, network=None
) -> Stack:
    """Read a stack file; ValueError saying what to fix when it is malformed.

    ``{network}`` in its args becomes ``network`` (absolute), by default the demo network;
    a ``network`` given to a stack file that has no ``{network}`` is an error, not ignored.
    """
    network_arg = str(Path(network).absolute()) if network is not None else DEMO_NETWORK_ARG
    raw = read_json5(path)
    try:
        uses_network = any(
            NETWORK in str(arg) for p in raw["processes"] for arg in p.get("args", [])
        )
        stack = Stack(
            ns=ns or raw.get("ns", keys.DEFAULT_NS),
            listen=listen or raw["router"]["listen"],
            state_dir=Path(raw.get("state_dir", "var")).absolute(),  # where `up` runs
            processes=tuple(_process_spec(p, network_arg) for p in raw["processes"]),
            supervision=_supervision(raw.get("supervision", {})),
            network=network_arg.replace(DEFAULTS, str(DEFAULT_STACK.parent))
            if uses_network
            else None,
        )
    except (ValueError, KeyError, TypeError) as exc:
        raise ValueError(f"{path}: not a valid stack file ({type(exc).__name__}: {exc})") from None
    names = [p.name for p in stack.processes]
    if len(set(names)) != len(names):
        raise ValueError(f"{path}: process names must be unique, got {names}")
    if network is not None and not uses_network:
        raise ValueError(
            f"--network {network}: the stack file {path} has no {NETWORK} in its processes' "
            f'args; give them "--network", "{NETWORK}"'
        )
    return stack


def command_line(stack: Stack, spec: ProcessSpec) -> list[str]:
    return [
        sys.executable,
        "-m",
        "services.cli",
        spec.command,
        "--connect",
        stack.listen,
        "--ns",
        stack.ns,
        *spec.args,
    ]


def backoff_s(failures: int, settings: Supervision) -> float:
    """Delay before a restart after ``failures`` quick failures in a row: 1, 2, 4 … 60 s."""
    return min(settings.backoff_initial_s * 2.0 ** min(failures, 32), settings.backoff_max_s)


def exit_text(code: int | None) -> str:
    if code is None:
        return "-"
    if code < 0:
        with contextlib.suppress(ValueError):
            return signal.Signals(-code).name
    return str(code)


def duration_text(seconds: float | None) -> str:
    if seconds is None:
        return "-"
    s = int(seconds)
    if s < 60:
        return f"{s} s"
    if s < 3600:
        return f"{s // 60} m {s % 60:02d} s"
    return f"{s // 3600} h {s % 3600 // 60:02d} m"


class Child:
    """One process of the stack across its runs: started, exited, stopped, started again.

    Only the main loop of `up` touches it (no lock): :meth:`step` once per tick.
    """

    def __init__(self, stack: Stack, spec: ProcessSpec, env: dict[str, str]) -> None:
        self.stack, self.spec, self.env = stack, spec, env
        self.settings = stack.supervision
        self.log_path = stack.state_dir / f"{spec.name}.log"
        self.popen: subprocess.Popen | None = None
        self.started_at: float | None = None  # monotonic, of the current run
        self.restarts = 0
        self.failures = 0  # quick failures in a row: the backoff exponent
        self.last_exit: int | None = None
        self.next_start: float | None = None  # monotonic, while waiting to start again
        self.kill_at: float | None = None  # SIGKILL deadline while stopping it ourselves
        self.reason = ""  # why it is (being) restarted
        self.token_seen = False  # its token has been seen during this run
        self.token_missing_since: float | None = None
        self.finished = False  # ended and its policy says leave it

    @property
    def instance(self) -> str | None:
        """The last key chunk of its token: its --instance, else the runtime's default."""
        if self.spec.instance is not None:
            return self.spec.instance
        if self.popen is None:
            return None
        host = default_instance().rsplit("-", 1)[0]  # the runtime's {hostname}-{pid}
        return f"{host}-{self.popen.pid}"

    @property
    def running(self) -> bool:
        return self.popen is not None and self.popen.poll() is None

    def start(self, now: float) -> None:
        if self.restarts:
            line = f"{datetime.now(UTC).isoformat(timespec='seconds')} restarted by up: "
            with self.log_path.open("a") as log_file:
                print(line + self.reason, file=log_file)
        with self.log_path.open("ab") as log_file:
            self.popen = subprocess.Popen(
                command_line(self.stack, self.spec),  # in `up`'s working directory
                stdout=log_file,
                stderr=subprocess.STDOUT,
                stdin=subprocess.DEVNULL,
                start_new_session=True,  # Ctrl-C reaches us; we stop them in order
                env=self.env,
            )
        self.started_at, self.next_start, self.kill_at = now, None, None
        self.token_seen, self.token_missing_since = False, None

    def terminate(self, now: float) -> None:
        """SIGTERM (and SIGCONT, so that a stopped process gets it); SIGKILL comes later."""
        if not self.running:
            return
        assert self.popen is not None
        with contextlib.suppress(ProcessLookupError):
            self.popen.send_signal(signal.SIGTERM)
            self.popen.send_signal(signal.SIGCONT)
        self.kill_at = now + self.settings.stop_grace_s

    def kill(self) -> None:
        """SIGKILL to its whole process group (it runs in a session of its own)."""
        assert self.popen is not None
        with contextlib.suppress(ProcessLookupError, PermissionError):
            os.killpg(self.popen.pid, signal.SIGKILL)
        with contextlib.suppress(ProcessLookupError):
            self.popen.kill()

    def step(self, now: float, alive: set[str]) -> None:
        """Start, restart, kill or leave it, given the instances whose token is present."""
        if self.finished:
            return
        if self.popen is None or self.next_start is not None:
            if self.next_start is None or now >= self.next_start:
                if self.popen is not None:
                    self.restarts += 1
                    log.warning("%s: restart %d (%s)", self.spec.name, self.restarts, self.reason)
                self.start(now)
            return
        code = self.popen.poll()
        if code is None:
            if self.kill_at is not None:
                if now >= self.kill_at:
                    log.warning(
                        "%s did not stop within %.0f s: killing it",
                        self.spec.name,
                        self.settings.stop_grace_s,
                    )
                    self.kill()
                    self.kill_at = now + self.settings.stop_grace_s
                return
            self._watch_token(now, alive)
            return
        self._ended(now, code)

    def _watch_token(self, now: float, alive: set[str]) -> None:
        if self.instance in alive:
            self.token_seen, self.token_missing_since = True, None
            return
        if not self.token_seen:
            return  # still starting: supervision of the token begins once it is seen
        if self.token_missing_since is None:
            self.token_missing_since = now
            log.info("%s: liveliness token %s gone", self.spec.name, self.instance)
        missing_s = now - self.token_missing_since
        if missing_s > self.settings.token_missing_s and self.spec.restart != "never":
            self.reason = f"liveliness token missing for {missing_s:.0f} s"
            log.warning("%s: %s; stopping it to start it again", self.spec.name, self.reason)
            self.terminate(now)

    def _ended(self, now: float, code: int) -> None:
        self.last_exit = code
        assert self.started_at is not None
        ran_s = now - self.started_at
        if self.kill_at is not None:  # we stopped it: the reason is already set
            self.kill_at = None
        elif self.spec.restart == "never" or (self.spec.restart == "on-failure" and code == 0):
            self.finished = True
            log.info("%s exited with %s after %.0f s", self.spec.name, exit_text(code), ran_s)
            return
        else:
            self.reason = f"exited with {exit_text(code)} after {ran_s:.0f} s"
        if ran_s >= self.settings.backoff_reset_s:
            self.failures = 0
        delay = backoff_s(self.failures, self.settings)
        self.failures += 1
        self.next_start = now + delay
        log.warning("%s %s; starting it again in %.0f s", self.spec.name, self.reason, delay)

    def health(self, now: float, alive: set[str]) -> dict[str, Any]:
        running = self.running
        if running:
            state = "stopping" if self.kill_at is not None else "running"
            if state == "running" and not self.token_seen:
                state = "starting"  # no token yet
        elif self.finished:
            state = "finished" if self.last_exit == 0 else "failed"
        else:
            state = "waiting" if self.next_start is not None else "exited"  # till the next tick
        return {
            "pid": self.popen.pid if self.popen else None,
            "running": running,
            "state": state,
            "alive": running and self.instance in alive,
            "restarts": self.restarts,
            "uptime_s": (
                round(now - self.started_at, 1) if running and self.started_at is not None else None
            ),
            "last_exit": self.last_exit,
            "last_restart_reason": self.reason or None,
            "next_start_in_s": (
                round(max(0.0, self.next_start - now), 1) if self.next_start is not None else None
            ),
            "restart": self.spec.restart,
        }


@dataclass
class Flow:
    """Messages of ``source`` arriving and none of ``result``: stalled after ``after_s``.

    Fed from message counts once per tick (the callbacks only count), so its times are
    the ticks' and good to half a second.
    """

    source: str
    result: str
    after_s: float
    last_source: float | None = None  # when source messages last arrived
    waiting_since: float | None = None  # first source message after the last result

    def update(self, now: float, source_arrived: bool, result_arrived: bool) -> None:
        if source_arrived:
            self.last_source = now
            if self.waiting_since is None:
                self.waiting_since = now
        if result_arrived:
            self.waiting_since = None

    def stalled(self, now: float) -> bool:
        return (
            self.waiting_since is not None
            and self.last_source is not None
            and now - self.waiting_since >= self.after_s
            and now - self.last_source <= self.after_s
        )

    def text(self, now: float) -> str:
        assert self.waiting_since is not None
        verb = "published" if self.result == "state" else "made"
        return (
            f"{self.source} arriving but no {self.result} {verb} "
            f"for {now - self.waiting_since:.0f} s"
        )


class StatusBoard:
    """Counts what flows on the bus, fed by subscriber callbacks that only count under a
    lock (and keep alert payloads for the main loop); thread-safe. ``network``: the
    ``line/segment`` ids that count as tracked (None: any), so that states a sender puts on
    segments that do not exist neither inflate the count nor grow this process's memory.
    Trains are not known ahead: one counts for ``TRAIN_SEEN_S`` after its last GPS fix, and
    is forgotten then. ``clock``: monotonic seconds."""

    def __init__(
        self, network: frozenset[str] | None = None, clock: Callable[[], float] = time.monotonic
    ) -> None:
        self.lock = threading.Lock()
        self.network = network
        self.counts: Counter[str] = Counter()
        self.segments: set[str] = set()
        self.trains: dict[str, float] = {}  # train -> when its last GPS fix came
        self.clock = clock
        self.raised: set[tuple[str, ...]] = set()
        self.alerts: list[bytes] = []  # payloads not decoded yet
        self.alive: set[tuple[str, str]] = set()
        self.viewer_url = ""  # the web viewer's address, once the viewer has printed it

    def on_sample(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        kind = keys.kind(key)  # the subscriptions are {ns}/{kind}/**
        payload = sample.payload.to_bytes() if kind == "alert" else b""
        try:
            ids = keys.parse_segment_key(key)[2:] if kind == "state" else ()
            train = keys.parse_gps(key) if kind == "gps" else ""
        except SchemaError:
            ids, train = (), ""  # a key of another form: counted, not listed
        with self.lock:
            self.counts[kind] += 1
            if ids:
                if self.network is None or "/".join(ids) in self.network:
                    self.segments.add("/".join(ids))
            elif train:
                self.trains[train] = self.clock()
            elif payload:
                self.alerts.append(payload)  # decoded by the main loop, off the Zenoh thread

    def take_alerts(self) -> None:
        """Decode the alerts received since the last call into the set of raised alerts."""
        with self.lock:
            payloads, self.alerts = self.alerts, []
        for payload in payloads:
            try:
                alert = decode(payload, Alert)
            except SchemaError:
                continue  # the alerting service's problem; its dead letters say so
            ident = (alert.line, alert.segment, alert.kind, alert.indicator, alert.level)
            with self.lock:
                if alert.status == "raised":
                    self.raised.add(ident)
                else:
                    self.raised.discard(ident)

    def on_alive(self, sample: zenoh.Sample) -> None:
        try:
            service, instance = keys.parse_alive(str(sample.key_expr))
        except SchemaError:
            return  # not a service's token
        with self.lock:
            if sample.kind == zenoh.SampleKind.PUT:
                self.alive.add((service, instance))
            else:
                self.alive.discard((service, instance))

    def alive_instances(self) -> set[str]:
        with self.lock:
            return {instance for _, instance in self.alive}

    def snapshot(self) -> Counter[str]:
        with self.lock:
            return Counter(self.counts)

    def totals(self) -> tuple[int, int, int]:
        with self.lock:
            since = self.clock() - TRAIN_SEEN_S
            self.trains = {t: seen for t, seen in self.trains.items() if seen >= since}
            return len(self.trains), len(self.segments), len(self.raised)


class Supervisor:
    """The children, the flows and the health summary; driven by :meth:`tick`."""

    def __init__(self, stack: Stack, board: StatusBoard) -> None:
        self.stack, self.board = stack, board
        env = {k: v for k, v in os.environ.items() if k not in NOT_INHERITED}
        env["PYTHONUNBUFFERED"] = "1"
        self.children = {spec.name: Child(stack, spec, env) for spec in stack.processes}
        s = stack.supervision
        self.flows = (
            Flow("index", "state", s.stalled_state_s),
            Flow("gps", "index", s.stalled_index_s),
        )
        self.started = time.monotonic()
        self.counts = board.snapshot()
        self.rates: dict[str, float] = {kind: 0.0 for kind in WATCHED}
        self.rates_at = self.started
        self._rate_base = self.counts

    def tick(self, now: float) -> None:
        self.board.take_alerts()
        alive = self.board.alive_instances()
        for child in self.children.values():
            child.step(now, alive)
        counts = self.board.snapshot()
        for flow in self.flows:
            flow.update(
                now,
                counts[flow.source] > self.counts[flow.source],
                counts[flow.result] > self.counts[flow.result],
            )
        if now - self.rates_at >= REFRESH_S:
            dt = now - self.rates_at
            self.rates = {k: (counts[k] - self._rate_base[k]) / dt for k in WATCHED}
            self.rates_at, self._rate_base = now, counts
        self.counts = counts

    def stalled(self, now: float) -> list[str]:
        return [flow.text(now) for flow in self.flows if flow.stalled(now)]

    def health(self, now: float, *, running: bool = True) -> dict[str, Any]:
        """The machine-readable board (docs/operating.md#varhealthjson)."""
        alive = self.board.alive_instances()
        processes = {name: c.health(now, alive) for name, c in self.children.items()}
        stalled = self.stalled(now)
        trains, segments, raised = self.board.totals()
        return {
            "written_at": round(time.time(), 3),  # wall clock: how fresh this file is
            "up": {
                "pid": os.getpid(),
                "running": running,
                "uptime_s": round(now - self.started, 1),
            },
            "ns": self.stack.ns,
            "router": self.stack.listen,
            "processes": processes,
            "rates": {k: round(v, 1) for k, v in self.rates.items()},
            "counts": {k: self.counts[k] for k in WATCHED},
            "flows": [
                {
                    "source": f.source,
                    "result": f.result,
                    "after_s": f.after_s,
                    "stalled": f.stalled(now),
                    "waiting_s": (
                        round(now - f.waiting_since, 1) if f.waiting_since is not None else None
                    ),
                }
                for f in self.flows
            ],
            "stalled": stalled,
            "trains": trains,
            "segments": segments,
            "alerts_raised": raised,
            "viewer_url": self.board.viewer_url or None,
            "healthy": running
            and not stalled
            and all(p["alive"] or p["state"] == "finished" for p in processes.values()),
        }

    def write_health(self, health: dict[str, Any]) -> None:
        """Replace ``{state_dir}/health.json`` at once (readers never see half a file)."""
        path = self.stack.state_dir / HEALTH_FILE
        tmp = path.with_suffix(".json.tmp")
        tmp.write_text(json.dumps(health, indent=1) + "\n")
        os.replace(tmp, path)

    def render(self, health: dict[str, Any]) -> str:
        lines = [f"TrackFusion stack  ns={self.stack.ns}  router={self.stack.listen}", ""]
        lines.append(
            f"{'process':12} {'pid':>7}  {'running':14} {'alive':5} {'restarts':>8}  "
            f"{'uptime':>10}  last exit"
        )
        for name, p in health["processes"].items():
            if p["state"] == "waiting":
                running = f"again in {p['next_start_in_s']:.0f} s"
            else:
                running = {"running": "yes", "starting": "yes"}.get(p["state"], p["state"])
            lines.append(
                f"{name:12} {p['pid'] or '-':>7}  {running:14} {'yes' if p['alive'] else '-':5} "
                f"{p['restarts']:>8}  {duration_text(p['uptime_s']):>10}  "
                f"{exit_text(p['last_exit'])}"
            )
        lines.append("")
        for text in health["stalled"]:
            lines.append(f"STALLED: {text}")
        if health["viewer_url"]:
            lines.append(f"viewer: {health['viewer_url']}")
        lines.append(
            f"trains {health['trains']}   segments tracked {health['segments']}   "
            f"alerts raised {health['alerts_raised']}"
        )
        lines.append("messages/s  " + "  ".join(f"{k} {v:.0f}" for k, v in health["rates"].items()))
        return "\n".join(lines)

    def stop(self) -> None:
        """SIGTERM every child, then SIGKILL whatever is still running after the grace period."""
        now = time.monotonic()
        for child in self.children.values():
            child.terminate(now)
        deadline = now + self.stack.supervision.stop_grace_s
        for name, child in self.children.items():
            if child.popen is None:
                continue
            try:
                child.popen.wait(max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                log.warning(
                    "%s did not stop within %.0f s: killing it",
                    name,
                    self.stack.supervision.stop_grace_s,
                )
                child.kill()
                child.popen.wait()


def network_segments(path: str | None) -> frozenset[str] | None:
    """The ``line/segment`` ids of a network file (None: None); ValueError saying what to
    fix when the file is bad, so that a bad file stops `up` now, not each child."""
    if path is None:
        return None
    from services.defaults import load_network

    return frozenset(f"{line.id}/{seg.id}" for line, seg in load_network(path).segments())


def main(stack_path: str | Path = DEFAULT_STACK, *, out: TextIO = sys.stdout, **overrides) -> int:
    stack = load_stack(stack_path, **overrides)
    segments = network_segments(stack.network)
    stack.state_dir.mkdir(parents=True, exist_ok=True)
    stop = threading.Event()
    previous = {
        sig: signal.signal(sig, lambda *_: stop.set()) for sig in (signal.SIGINT, signal.SIGTERM)
    }
    router_conf = zenoh_config({"mode": "router", "listen": {"endpoints": [stack.listen]}})
    board = StatusBoard(segments)
    supervisor = Supervisor(stack, board)
    try:
        try:
            session = zenoh.open(router_conf)
        except zenoh.ZError as exc:
            raise SystemExit(
                f"cannot listen on {stack.listen} ({exc}): is another stack up?"
            ) from None
        with session:
            declared = [
                session.declare_subscriber(f"{stack.ns}/{kind}/**", board.on_sample)
                for kind in WATCHED
            ]
            declared.append(
                session.liveliness().declare_subscriber(
                    keys.alive_all(stack.ns), board.on_alive, history=True
                )
            )
            supervisor.tick(time.monotonic())  # starts every process
            print(
                f"started {len(supervisor.children)} processes; logs in {stack.state_dir}/",
                file=out,
            )
            tty = out.isatty()
            refreshes = 0
            next_refresh = time.monotonic() + REFRESH_S
            while not stop.wait(TICK_S):
                now = time.monotonic()
                supervisor.tick(now)
                if now < next_refresh:
                    continue
                next_refresh = now + REFRESH_S
                if not board.viewer_url:
                    board.viewer_url = viewer_url(stack.state_dir / "viewer.log")
                health = supervisor.health(now)
                try:  # on the bus too, for the viewer's health board
                    session.put(keys.stack_health(stack.ns), encode(health_message(health)))
                except zenoh.ZError as exc:
                    log.warning("cannot publish the health report: %s", exc)
                try:
                    supervisor.write_health(health)
                except OSError as exc:  # a full disk must not stop the supervision
                    log.warning("cannot write %s: %s", HEALTH_FILE, exc)
                refreshes += 1
                if tty or refreshes % 5 == 0:
                    text = supervisor.render(health)
                    print(("\x1b[H\x1b[J" if tty else "\n") + text, file=out, flush=True)
            for sub in declared:
                sub.undeclare()
    finally:
        supervisor.stop()
        with contextlib.suppress(OSError):
            supervisor.write_health(supervisor.health(time.monotonic(), running=False))
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    print("stack stopped", file=out)
    return 0


def health_message(health: dict[str, Any]) -> StackHealth:
    """The StackHealth message of a :meth:`Supervisor.health` dict (what the viewer shows)."""
    return StackHealth(
        written_at=health["written_at"],
        processes=[
            ServiceHealth(
                name=name,
                state=p["state"],
                alive=bool(p["alive"]),
                restarts=p["restarts"],
                last_restart_reason=p["last_restart_reason"] or "",
                pid=p["pid"],
                uptime_s=p["uptime_s"],
            )
            for name, p in health["processes"].items()
        ],
        stalled=list(health["stalled"]),
        counts=dict(health["counts"]),
        healthy=bool(health["healthy"]),
        viewer_url=health["viewer_url"] or "",
    )


def viewer_url(log_path: Path) -> str:
    """The web viewer's URL, the first line of the viewer's output that is one."""
    try:
        with log_path.open() as log:
            return next((line.strip() for line in log if line.startswith("http")), "")
    except OSError:
        return ""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """``trackfusion up``."""
    parser.description = (
        "Start everything of the stack file with a live status table; Ctrl-C stops it all."
    )
    parser.add_argument(
        "--stack", default=str(DEFAULT_STACK), help="stack file (default: %(default)s)"
    )
    parser.add_argument("--ns", help="namespace (stack file's by default)")
    parser.add_argument("--listen", metavar="ENDPOINT", help="router endpoint (stack file's)")
    parser.add_argument(
        "--network",
        metavar="FILE.geojson",
        help="network file for every process ({network} in the stack file; default: the demo), "
        "e.g. from `trackfusion network import-osm`",
    )
    parser.add_argument("--log-level", default="warning", choices=["debug", "info", "warning"])


def run(args: argparse.Namespace) -> int:
    configure_logging(args.log_level)
    return main(args.stack, ns=args.ns, listen=args.listen, network=args.network)
