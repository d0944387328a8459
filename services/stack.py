"""`trackfusion up`: the whole system on one machine, from ``deploy/stack.json5``.

An embedded Zenoh router (this process), every service and simulator of the stack file as
a child process connected to it, and a live status table: services alive (liveliness
tokens), trains seen, messages per second, segments tracked, alerts raised. Ctrl-C (or
SIGTERM) stops the children (SIGTERM, SIGKILL after 5 s) and then the router.
"""

from __future__ import annotations

import logging
import os
import signal
import subprocess
import sys
import threading
import time
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import TextIO

import json5
import zenoh

from schemas import Alert, SchemaError, decode, keys
from services.runtime.config import zenoh_config

log = logging.getLogger(__name__)
REPO = Path(__file__).resolve().parents[1]
DEFAULT_STACK = REPO / "deploy" / "stack.json5"
STOP_GRACE_S = 5.0
WATCHED = ("state", "index", "alert", "gps", "trc", "maintenance", "deadletter")


@dataclass(frozen=True)
class ProcessSpec:
    name: str  # also what `trackfusion status` lists it as (its --instance)
    command: str  # trackfusion subcommand
    args: tuple[str, ...]


@dataclass(frozen=True)
class Stack:
    ns: str
    listen: str
    state_dir: Path
    processes: tuple[ProcessSpec, ...]


def load_stack(path: str | Path = DEFAULT_STACK, *, ns: str | None = None, listen=None) -> Stack:
    """Read a stack file; SystemExit saying what to fix when it is malformed."""
    try:
        raw = json5.loads(Path(path).read_text())
        processes = tuple(
            ProcessSpec(p["name"], p.get("command", p["name"]), tuple(map(str, p.get("args", []))))
            for p in raw["processes"]
        )
        stack = Stack(
            ns=ns or raw.get("ns", keys.DEFAULT_NS),
            listen=listen or raw["router"]["listen"],
            state_dir=REPO / raw.get("state_dir", "var"),
            processes=processes,
        )
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise SystemExit(f"{path}: not a valid stack file ({type(exc).__name__}: {exc})") from None
    names = [p.name for p in stack.processes]
    if len(set(names)) != len(names):
        raise SystemExit(f"{path}: process names must be unique, got {names}")
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


class StatusBoard:
    """Counts what flows on the bus (fed by subscriber callbacks; cheap and thread-safe)."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.counts: Counter[str] = Counter()
        self.segments: set[str] = set()
        self.trains: set[str] = set()
        self.raised: set[tuple[str, ...]] = set()
        self.alive: set[tuple[str, str]] = set()
        self.viewer_url = ""  # the web viewer's address, once the viewer has printed it

    def on_sample(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        parts = key.split("/")
        with self.lock:
            self.counts[parts[1]] += 1
            if parts[1] == "state":
                self.segments.add("/".join(parts[2:4]))
            elif parts[1] == "gps":
                self.trains.add(parts[2])
            elif parts[1] == "alert":
                try:
                    alert = decode(sample.payload.to_bytes(), Alert)
                except SchemaError:
                    return  # the alerting service's problem; its dead letters say so
                ident = (alert.line, alert.segment, alert.kind, alert.indicator, alert.level)
                if alert.status == "raised":
                    self.raised.add(ident)
                else:
                    self.raised.discard(ident)

    def on_alive(self, sample: zenoh.Sample) -> None:
        _, _, service, instance = str(sample.key_expr).split("/")[:4]
        with self.lock:
            if sample.kind == zenoh.SampleKind.PUT:
                self.alive.add((service, instance))
            else:
                self.alive.discard((service, instance))

    def render(self, stack: Stack, children: dict[str, subprocess.Popen], rates: dict) -> str:
        with self.lock:
            alive_instances = {instance for _, instance in self.alive}
            lines = [f"TrackFusion stack  ns={stack.ns}  router={stack.listen}", ""]
            lines.append(f"{'process':12} {'pid':>7}  {'running':8} alive")
            for spec in stack.processes:
                child = children.get(spec.name)
                running = "yes" if child and child.poll() is None else f"exit {child.returncode}"
                alive = "yes" if spec.name in alive_instances else "-"
                lines.append(
                    f"{spec.name:12} {child.pid if child else '-':>7}  {running:8} {alive}"
                )
            lines.append("")
            if self.viewer_url:
                lines.append(f"viewer: {self.viewer_url}")
            lines.append(
                f"trains {len(self.trains)}   segments tracked {len(self.segments)}   "
                f"alerts raised {len(self.raised)}"
            )
            lines.append(
                "messages/s  " + "  ".join(f"{kind} {rates.get(kind, 0.0):.0f}" for kind in WATCHED)
            )
        return "\n".join(lines)

    def snapshot(self) -> Counter[str]:
        with self.lock:
            return Counter(self.counts)


def main(stack_path: str | Path = DEFAULT_STACK, *, out: TextIO = sys.stdout, **overrides) -> int:
    stack = load_stack(stack_path, **overrides)
    stack.state_dir.mkdir(parents=True, exist_ok=True)
    stop = threading.Event()
    previous = {
        sig: signal.signal(sig, lambda *_: stop.set()) for sig in (signal.SIGINT, signal.SIGTERM)
    }
    router_conf = zenoh_config({"mode": "router", "listen": {"endpoints": [stack.listen]}})
    children: dict[str, subprocess.Popen] = {}
    board = StatusBoard()
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
            env = {**os.environ, "PYTHONUNBUFFERED": "1"}
            for spec in stack.processes:
                log_path = stack.state_dir / f"{spec.name}.log"
                with log_path.open("ab") as log_file:
                    children[spec.name] = subprocess.Popen(
                        command_line(stack, spec),
                        cwd=REPO,
                        stdout=log_file,
                        stderr=subprocess.STDOUT,
                        start_new_session=True,  # Ctrl-C reaches us; we stop them in order
                        env=env,
                    )
            print(f"started {len(children)} processes; logs in {stack.state_dir}/", file=out)
            tty = out.isatty()
            last, last_t = board.snapshot(), time.monotonic()
            while not stop.wait(1.0 if tty else 5.0):
                if not board.viewer_url:
                    board.viewer_url = viewer_url(stack.state_dir / "viewer.log")
                now, now_t = board.snapshot(), time.monotonic()
                rates = {k: (now[k] - last[k]) / (now_t - last_t) for k in WATCHED}
                last, last_t = now, now_t
                text = board.render(stack, children, rates)
                print(("\x1b[H\x1b[J" if tty else "\n") + text, file=out, flush=True)
            for sub in declared:
                sub.undeclare()
    finally:
        stop_children(children)
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    print("stack stopped", file=out)
    return 0


def viewer_url(log_path: Path) -> str:
    """The web viewer's URL, the first line of the viewer's output that is one."""
    try:
        with log_path.open() as log:
            return next((line.strip() for line in log if line.startswith("http")), "")
    except OSError:
        return ""


def stop_children(children: dict[str, subprocess.Popen]) -> None:
    """SIGTERM every child, then SIGKILL whatever is still running after the grace period."""
    for child in children.values():
        if child.poll() is None:
            child.send_signal(signal.SIGTERM)
    deadline = time.monotonic() + STOP_GRACE_S
    for name, child in children.items():
        try:
            child.wait(max(0.0, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            log.warning("%s did not stop within %.0f s: killing it", name, STOP_GRACE_S)
            child.kill()
            child.wait()
