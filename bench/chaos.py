"""Seeded random faults on a running stack; afterwards every segment's final state compared,
byte for byte, with the same inputs folded by an undisturbed filter: ``make soak-chaos``.

The stack, each part its own process as deployed: a router (``trackfusion router``),
calibration, filtering (its store on a small filesystem of its own when this process may
mount one, its link to the router through a proxy that can be cut), alerting, ingestion,
extraction, the simulator publishing a seeded index-fidelity world (the on-board indices, TRC
runs and tampings a fleet and its recording car would send) paced to end before the faults
do, and a raw fleet (``--raw-trains``, ``simulate --fidelity raw --gateway-only`` in real
time, its gateway's outbox on disk) whose chunks and fixes go through ingestion and
extraction into the same filtering. A supervisor here starts again any process that exits,
as ``trackfusion up`` does.

While the world is published, faults are drawn from ``random.Random(--seed)`` at
exponential intervals (mean ``--mean-gap-s``):

* ``kill:<process>``: SIGKILL (the router included; the supervisor starts it again);
* ``stop:<process>``: SIGSTOP for 2–15 s, then SIGCONT;
* ``disk-full``: filtering's filesystem filled for 5–20 s (needs root for the mount; without
  it the fault is reported as not injected);
* ``link-cut``: filtering's link to the router cut for 2–15 s, then restored;
* ``clock-jump``: a gateway whose GPS clock jumps an hour ahead, then an hour back;
* ``old-burst``: one GPS fix from each of 300 train ids, dated an hour back;
* ``duplicates``: 500 events of the world already published, sent again (late and twice);
* ``hostile``: the malformed messages of :mod:`bench.hostile`.

Every input is recorded: the world is a pure function of the simulator's flags
(:func:`simulators.world.world_events`, the same bytes), and the injected messages are
kept here; the raw fleet's messages are what its gateway recorded in its outbox. Afterwards
the gateway's messages go, in its order, through the ingestion and extraction cores in this
process (an undisturbed raw chain), and the indices extraction published (its outbox) are
compared with those: none missing, none extra. The final models are read from calibration,
the world and those indices are folded by :class:`services.filtering.tracker.Tracker` in
this process with them (what an undisturbed filtering instance holds), and every segment's
``q/state`` reply is compared with it byte for byte (a differing pair is written to
``differ.jsonl`` in the output directory). Alerting's raised set (``q/alerts``) is checked
against those states: every exceedance and predicted alert a segment's final state decides
on its own
(:meth:`services.alerting.core.AlertingCore.implied`: a probability at or above the raise
threshold, or at or below the clear one) must be raised or not as it says; between the
two thresholds the path of states decides, and such alerts are counted, not compared.
*Recovered* is the time from a fault's end until every service's liveliness token is back.

Run: ``python -m bench.chaos [--network demo|SEGMENTS] [--minutes 30] [--seed 1]
[--out DIR] [--json FILE]``; ``make soak-chaos`` runs the demo network and a generated
25,000-segment network for 30 minutes each.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import random
import signal
import sqlite3
import subprocess
import sys
import tempfile
import threading
import time
from collections import Counter
from dataclasses import asdict, dataclass
from datetime import datetime
from pathlib import Path

import msgspec
import zenoh

from bench.hostile import hostile_messages
from bench.linkproxy import LinkProxy
from bench.soak import Child, connect, free_port, outbox_config, pct
from schemas import (
    Calibration,
    DegradationPosterior,
    GpsFix,
    MaintenanceEvent,
    OnboardIndex,
    PositionedChunk,
    RaisedAlerts,
    SegmentState,
    TrcRecord,
    decode,
    encode,
    keys,
)
from services.alerting.core import AlertingCore, alert_key
from services.alerting.service import load_alerting_config
from services.defaults import default_file, load_network
from services.extraction.pipeline import Extractor
from services.filtering.tracker import Tracker
from services.ingestion.config import IngestionConfig
from services.ingestion.core import IngestionCore
from services.ingestion.service import decode_gateway
from services.limits import DEFAULT_LIMITS_FILE, Limits, load_limits, network_line_speeds
from simulators.gateway import key_and_payload
from simulators.network import DEFAULT_ORIGIN, generate_network
from simulators.run import DEFAULT_START
from simulators.truth import load_config
from simulators.world import WorldSpec, world_events
from track.segments import SegmentTable

SERVICES = ("calibration", "filtering", "alerting", "ingestion", "extraction")
KILLABLE = (*SERVICES, "router", "simulator")
# The raw fleet's world starts a month before the index world's: no index identity shared.
FLEET_START = "2025-12-01T00:00:00+00:00"
FLEET_PART = 0.7  # the fleet publishes in real time for this part of the faults' duration
EVENTS = (OnboardIndex, TrcRecord, MaintenanceEvent)
FAULT_WEIGHTS = {
    "kill": 4,
    "stop": 3,
    "disk-full": 1,
    "link-cut": 2,
    "clock-jump": 1,
    "old-burst": 1,
    "duplicates": 2,
    "hostile": 1,
}
RECOVER_TIMEOUT_S = 180.0
SETTLE_TIMEOUT_S = 600.0  # after the last fault: the states must converge within this
PUBLISHED = "published; lingering"  # the simulator's log line once its world is out
RESTART_DELAY_S = 1.0
QUERY_TIMEOUT_S = 120.0


@dataclass
class Fault:
    kind: str
    target: str
    at_s: float  # from the start of the faults
    held_s: float
    recovered_s: float | None = None  # from the fault's end to every token back
    injected: bool = True
    note: str = ""


class Tokens:
    """The liveliness tokens of the namespace, as they come and go."""

    def __init__(self) -> None:
        self.alive: set[str] = set()
        self.changed = threading.Condition()

    def __call__(self, sample: zenoh.Sample) -> None:
        name = keys.parse_alive(str(sample.key_expr))[1]
        with self.changed:
            if sample.kind == zenoh.SampleKind.PUT:
                self.alive.add(name)
            else:
                self.alive.discard(name)
            self.changed.notify_all()

    def until(self, names: tuple[str, ...], timeout: float) -> bool:
        with self.changed:
            return self.changed.wait_for(lambda: all(n in self.alive for n in names), timeout)


class Stack:
    """The stack's processes, started again whenever one exits (unless held by a fault)."""

    def __init__(self, args: argparse.Namespace, out: Path, network: Path, store: Path) -> None:
        self.ns = f"chaos{os.getpid()}"
        self.port = free_port()
        self.endpoint = f"tcp/127.0.0.1:{self.port}"
        self.proxy = LinkProxy(self.port)
        self.out, self.network, self.store, self.args = out, network, store, args
        self.children: dict[str, Child] = {}
        self.restarts: Counter[str] = Counter()
        self.held: set[str] = set()  # stopped or killed on purpose: the fault restarts them
        self.simulator_done = False
        self.fleet_done = not args.raw_trains
        self.world_s = args.days * 86400 / args.speedup  # wall time of the first publication
        self.world_started = time.monotonic()
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._supervise, name="supervise", daemon=True)

    def command(self, name: str) -> list[str]:
        wiring = ["--connect", self.endpoint, "--ns", self.ns, "--instance", name]
        net = ["--network", str(self.network)]
        match name:
            case "router":
                return ["router", "--listen", self.endpoint, "--ns", self.ns]
            case "calibration":
                initial = str(default_file("initial-models.json5"))
                db = str(self.out / "calibration.sqlite")
                return ["calibration", "--db", db, "--initial-models", initial, *net, *wiring]
            case "filtering":
                via = ["--connect", self.proxy.endpoint, "--ns", self.ns, "--instance", name]
                return ["filtering", "--db", str(self.store / "filtering.sqlite"), *net, *via]
            case "alerting":
                return ["alerting", "--db", str(self.out / "alerting.sqlite"), *net, *wiring]
            case "ingestion" | "extraction":
                db = str(self.out / f"{name}.sqlite")  # its checkpoint, outbox beside it
                return [name, "--db", db, *net, *wiring]
            case "fleet":
                # the gateways, in real time, their outbox in the output directory
                config = ("--config", str(outbox_config(self.out)))
                return ["simulate", *self.fleet_flags(), "--speedup", "1", "--linger", "86400",
                        "--no-progress", *config, *net, *wiring]  # fmt: skip
            case "simulator":
                world = self.world_flags()
                # a restarted simulator publishes its whole world again, ten times faster:
                # late duplicates of everything, which the filter must fold to the same bytes
                speedup = self.args.speedup * (10 if self.restarts[name] else 1)
                return ["simulate", *world, "--speedup", str(speedup), "--linger", "86400",
                        "--no-progress", *net, *wiring]  # fmt: skip
        raise ValueError(name)

    def fleet_flags(self) -> list[str]:
        a = self.args
        days = FLEET_PART * a.minutes * 60 / 86400
        return ["--fidelity", "raw", "--gateway-only", "--trains", str(a.raw_trains),
                "--days", f"{days:.6f}", "--seed", str(a.seed), "--start", FLEET_START]  # fmt: skip

    def world_flags(self) -> list[str]:
        a = self.args
        return ["--fidelity", "index", "--days", str(a.days), "--trains", str(a.trains),
                "--seed", str(a.seed)]  # fmt: skip

    def start(self, name: str) -> None:
        """Start ``name`` (its log ``{name}.{n}.log``, n its restarts so far)."""
        if name == "simulator":
            self.simulator_done = False
        if name == "fleet":
            self.fleet_done = False
        log_name = f"{name}.{self.restarts[name]}"
        self.children[name] = Child(log_name, self.out, self.command(name))

    def start_services(self, tokens: Tokens) -> None:
        """The services, then (all alive) the simulator and the supervision."""
        for name in SERVICES:
            self.start(name)
        if not tokens.until(SERVICES, RECOVER_TIMEOUT_S):
            raise RuntimeError(f"the services did not start: alive {sorted(tokens.alive)}")
        self.start("simulator")
        if self.args.raw_trains:
            self.start("fleet")
        self.world_started = time.monotonic()
        self._thread.start()

    def _exited(self) -> list[str]:
        with self._lock:
            return [
                name
                for name, child in self.children.items()
                if name not in self.held
                and child.popen.poll() is not None
                and not (name in ("simulator", "fleet") and child.popen.returncode == 0)
            ]

    def _supervise(self) -> None:
        while not self._stop.wait(0.2):
            if exited := self._exited():
                time.sleep(RESTART_DELAY_S)  # as `up` backs off: the port and the peers settle
                with self._lock:
                    for name in exited:
                        if name not in self.held and self.children[name].popen.poll() is not None:
                            self.restarts[name] += 1
                            self.start(name)
            simulator = self.children["simulator"].log_path
            if not self.simulator_done and PUBLISHED in simulator.read_text(errors="replace"):
                self.simulator_done = True
            fleet = self.children.get("fleet")
            if (
                fleet
                and not self.fleet_done
                and PUBLISHED in fleet.log_path.read_text(errors="replace")
            ):
                self.fleet_done = True

    def hold(self, name: str) -> None:
        with self._lock:
            self.held.add(name)

    def release(self, name: str, *, restart: bool) -> None:
        with self._lock:
            self.held.discard(name)
            if restart and self.children[name].popen.poll() is not None:
                self.restarts[name] += 1
                self.start(name)

    def signal(self, name: str, signum: int) -> None:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(self.children[name].pid, signum)

    def close(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(5)
        for name in ("simulator", "fleet", *SERVICES, "router"):
            if name in self.children:
                self.signal(name, signal.SIGCONT)
                self.children[name].stop()
        self.proxy.close()


class SmallDisk:
    """Filtering's store on a tmpfs of its own, which a filler file can fill up."""

    def __init__(self, path: Path, size_mb: int) -> None:
        self.path = path
        path.mkdir(parents=True, exist_ok=True)
        mount = ["mount", "-t", "tmpfs", "-o", f"size={size_mb}m", "tmpfs", str(path)]
        self.mounted = subprocess.run(mount, capture_output=True).returncode == 0
        self.filler = path / "filler"

    def fill(self) -> bool:
        if not self.mounted:
            return False
        free = os.statvfs(self.path).f_bavail * os.statvfs(self.path).f_frsize
        with self.filler.open("wb") as f, contextlib.suppress(OSError):
            os.posix_fallocate(f.fileno(), 0, free)
        return True

    def empty(self) -> None:
        self.filler.unlink(missing_ok=True)

    def close(self) -> None:
        self.empty()
        if self.mounted:
            subprocess.run(["umount", "-l", str(self.path)], capture_output=True)


def simulated_world(network: str | Path, days: float, seed: int, trains: int) -> list:
    """The events ``trackfusion simulate --fidelity index`` publishes with these flags (same
    seed, same bytes)."""
    start = datetime.fromisoformat(DEFAULT_START).timestamp()
    spec = WorldSpec(load_network(str(network)), load_config(None), start, days, seed, trains)
    return [m for _, batch in world_events(spec) for m in batch if isinstance(m, EVENTS)]


def network_limits(network: str | Path | None) -> Limits:
    """The default limits with ``network``'s line speeds, as a service given ``--network``
    reads them (the speed class of a line the limits file does not name)."""
    speeds = None if network is None else network_line_speeds(load_network(str(network)))
    return load_limits(DEFAULT_LIMITS_FILE, speeds)


def undisturbed_states(
    ns: str, world: list, models: dict[str, bytes], network: str | Path | None = None
) -> dict[str, bytes]:
    """``{q/state key: payload}`` one filtering instance (given ``network``) reaches on
    ``world`` with ``models`` (``{model key: payload}``, as calibration answers them): the
    models installed, then the world folded as the live service folds it, detection of
    unreported tampings included."""
    limits = network_limits(network)
    decoded = [
        decode(p, Calibration if keys.model_kind(k) == "calibration" else DegradationPosterior)
        for k, p in models.items()
    ]
    tracker = Tracker(limits.for_line, limits.levels)
    tracker.update_models(decoded)
    tracker.fold_events(world)
    states = tracker.states_of(list(tracker.histories))
    return {keys.q_state(ns, s.line, s.segment): encode(s) for s in states}


def gateway_entries(path: Path) -> list[tuple[str, bytes]]:
    """``(key, payload)`` of what a gateway recorded in its outbox, in its order (read only:
    the gateway may still be up)."""
    db = sqlite3.connect(f"file:{path}?mode=ro", uri=True)
    try:
        return db.execute("SELECT key, payload FROM entries ORDER BY seq").fetchall()
    finally:
        db.close()


def raw_chain_indices(entries: list[tuple[str, bytes]], network: str | Path) -> set[bytes]:
    """The encoded OnboardIndex messages the ingestion and extraction cores give, in one
    undisturbed pass, for a gateway's recorded messages in its order."""
    net = load_network(str(network))
    core = IngestionCore(net, IngestionConfig())
    extractor = Extractor(SegmentTable.from_network(net))
    out: set[bytes] = set()
    for key, payload in entries:
        kind = "raw" if key.split("/")[1] == "raw" else "gps"
        for chunk in core.step(decode_gateway(kind, key, payload), time.time()):
            if isinstance(chunk, PositionedChunk):
                out |= {encode(index) for index in extractor.process(chunk)}
    return out


def compare_raw_chain(out: Path, expected: set[bytes]) -> dict:
    """Extraction's published indices (its outbox) against the undisturbed raw chain's."""
    path = out / "outbox-extraction-extraction.sqlite"
    published = {p for _, p in gateway_entries(path)} if path.exists() else set()
    return {
        "indices": len(expected),
        "published": len(published),
        "missing": len(expected - published),
        "extra": len(published - expected),
    }


def inject(
    kind: str, rng: random.Random, stack: Stack, session: zenoh.Session, world: list, line: str
) -> str:
    """Publish one burst of bad, old, jumped or repeated input; returns what was sent."""
    now = time.time()
    lon, lat = DEFAULT_ORIGIN
    block = zenoh.CongestionControl.BLOCK
    sent: list[tuple[str, bytes]] = []
    if kind == "clock-jump":
        train = f"chaos-gw-{rng.randrange(10**6)}"
        for i, offset in enumerate((0, 3600, 3601, -3600, -3599, 1)):
            fix = GpsFix(train=train, t=now + offset + i, lat_deg=lat, lon_deg=lon)
            sent.append((keys.gps(stack.ns, train), encode(fix)))
    elif kind == "old-burst":
        for i in range(300):
            fix = GpsFix(train=f"chaos-old-{i}", t=now - 3600, lat_deg=lat, lon_deg=lon)
            sent.append((keys.gps(stack.ns, fix.train), encode(fix)))
    elif kind == "duplicates":
        elapsed = time.monotonic() - stack.world_started
        published = world[: max(1, int(len(world) * min(1.0, elapsed / stack.world_s)))]
        sent = [key_and_payload(stack.ns, m) for m in rng.choices(published, k=500)]
    elif kind == "hostile":
        sent = [(h.key, h.payload) for h in hostile_messages(stack.ns, line, now)]
    for key, payload in sent:
        session.put(key, payload, congestion_control=block)
    return f"{len(sent)} messages"


def run_fault(
    kind: str, rng: random.Random, stack: Stack, disk: SmallDisk, session, world, line
) -> tuple[str, float, bool, str]:
    """Inject one fault; returns (target, held_s, injected, note) once it has ended."""
    held = rng.uniform(2.0, 15.0)
    if kind == "kill":
        target = rng.choice(KILLABLE)
        stack.hold(target)
        stack.signal(target, signal.SIGKILL)
        stack.children[target].popen.wait(10)
        time.sleep(RESTART_DELAY_S)
        stack.release(target, restart=True)
        return target, 0.0, True, ""
    if kind == "stop":
        target = rng.choice(KILLABLE)
        stack.hold(target)
        stack.signal(target, signal.SIGSTOP)
        time.sleep(held)
        stack.signal(target, signal.SIGCONT)
        stack.release(target, restart=True)
        return target, held, True, ""
    if kind == "disk-full":
        held = rng.uniform(5.0, 20.0)
        if not disk.fill():
            return "filtering", 0.0, False, "no small filesystem (mount needs root)"
        time.sleep(held)
        disk.empty()
        return "filtering", held, True, ""
    if kind == "link-cut":
        stack.proxy.cut()
        time.sleep(held)
        stack.proxy.restore()
        return "filtering", held, True, ""
    return "bus", 0.0, True, inject(kind, rng, stack, session, world, line)


class Reference:
    """The states an undisturbed filter reaches on the world with the given models (folded
    again only when the models change)."""

    def __init__(self, ns: str, world: list, network: Path | None, out: Path) -> None:
        self.network, self.out = network, out
        self.ns, self.world = ns, world
        self._models: dict[str, bytes] = {}
        self.states: dict[str, bytes] = {}

    def update(self, models: dict[str, bytes]) -> None:
        if models != self._models:
            self.states = undisturbed_states(self.ns, self.world, models, self.network)
            self._models = models


def answers(session: zenoh.Session, selector: str) -> dict[str, bytes]:
    """Every reply to ``selector`` (generous timeout: 25,000 states on a loaded machine)."""
    block = zenoh.CongestionControl.BLOCK
    replies = session.get(selector, timeout=QUERY_TIMEOUT_S, congestion_control=block)
    return {str(r.ok.key_expr): r.ok.payload.to_bytes() for r in replies if r.ok is not None}


def compare(session: zenoh.Session, reference: Reference) -> dict:
    """Every segment's state against the undisturbed fold of the world with the final models."""
    reference.update(answers(session, keys.model_all(reference.ns)))
    expected = reference.states
    states = answers(session, keys.q_state_all(reference.ns))
    missing = [k for k in expected if k not in states]
    differ = [k for k in expected if k in states and states[k] != expected[k]]
    fewer_updates = 0
    how: Counter[str] = Counter()  # what a differing state differs in, to find the cause
    for k in differ:
        ref, got = decode(expected[k], SegmentState), decode(states[k], SegmentState)
        if ref.last_trc_t == got.last_trc_t:
            fewer_updates += max(0, ref.n_updates - got.n_updates)
        how.update(
            name
            for name in ("t", "last_trc_t", "n_updates", "calibration_version",
                         "posterior_version", "posterior_group")
            if getattr(ref, name) != getattr(got, name)
        )  # fmt: skip
        if ref.n_updates != got.n_updates:
            how["more_updates" if got.n_updates > ref.n_updates else "fewer_updates"] += 1
    if differ:  # the evidence, for finding the cause after the stack is gone
        with (reference.out / "differ.jsonl").open("w") as f:
            for k in differ:
                both = {"live": states[k], "reference": expected[k]}
                pairs = {w: msgspec.to_builtins(decode(p, SegmentState)) for w, p in both.items()}
                f.write(json.dumps({"key": k, **pairs}) + "\n")
    return {
        "segments": len(expected),
        "answered": len(states),
        "missing": len(missing),
        "differ": len(differ),
        "updates_missing_on_same_trc": fewer_updates,
        "differ_in": dict(sorted(how.items())),
        "examples": (missing + differ)[:5],
    }


def compare_alerts(session: zenoh.Session, reference: Reference) -> dict:
    """Alerting's raised set against what the reference's final states imply."""
    replies = answers(session, keys.q_alerts(reference.ns))
    if not replies:
        return {"answered": False}
    raised = {alert_key(a) for p in replies.values() for a in decode(p, RaisedAlerts).alerts}
    judge = AlertingCore(load_alerting_config(), network_limits(reference.network))
    implied: dict = {}
    for payload in reference.states.values():
        implied.update(judge.implied(decode(payload, SegmentState)))
    missing = [k for k, must in implied.items() if must is True and k not in raised]
    stale = [k for k, must in implied.items() if must is False and k in raised]
    return {
        "answered": True,
        "raised": len(raised),
        "implied_raised": sum(must is True for must in implied.values()),
        "missing": len(missing),
        "stale": len(stale),
        "in_band": sum(must is None for must in implied.values()),
        "other_kinds_raised": sum(
            k[2] not in ("exceedance", "predicted_exceedance") for k in raised
        ),  # fmt: skip
        "examples": ["/".join(k) for k in (missing + stale)[:5]],
    }


def settle(
    session, stack: Stack, world: list, tokens: Tokens, raw_expected: set[bytes] | None
) -> dict:
    """Compare until equal, or until ``SETTLE_TIMEOUT_S`` (the last comparison)."""
    reference = Reference(stack.ns, world, stack.network, stack.out)
    deadline = time.monotonic() + SETTLE_TIMEOUT_S
    while True:
        tokens.until(SERVICES, RECOVER_TIMEOUT_S)
        result = compare(session, reference)
        raw = None if raw_expected is None else compare_raw_chain(stack.out, raw_expected)
        raw_done = raw is None or raw["missing"] == 0
        if (result["missing"] == result["differ"] == 0 and raw_done) or time.monotonic() > deadline:
            alerts = compare_alerts(session, reference)
            late = alerts.get("missing") or alerts.get("stale")
            if late and time.monotonic() <= deadline:  # alerting may still be folding states
                time.sleep(10.0)
                continue
            result["alerts"] = alerts
            result["raw_chain"] = raw
            result["settled_s"] = round(SETTLE_TIMEOUT_S - (deadline - time.monotonic()), 1)
            return result
        time.sleep(10.0)


def network_file(args: argparse.Namespace, out: Path) -> tuple[Path, str]:
    """The network (demo, or generated with about ``--network`` segments) and one line id."""
    if args.network == "demo":
        path = Path(default_file("demo-network.geojson"))
    else:
        segments = int(args.network)
        length_km = 100.0
        lines = max(1, round(segments * 0.2 / length_km))
        path = out / "network.geojson"
        path.write_text(json.dumps(generate_network(lines, length_km, args.seed).to_geojson()))
    line = next(iter(load_network(str(path)).lines))
    return path, line


def run(args: argparse.Namespace) -> dict:
    out = Path(args.out or tempfile.mkdtemp(prefix="chaos-"))
    out.mkdir(parents=True, exist_ok=True)
    network, line = network_file(args, out)
    world = simulated_world(network, args.days, args.seed, args.trains)
    args.speedup = args.speedup or args.days * 86400 / (0.7 * args.minutes * 60)
    disk = SmallDisk(out / "store", args.store_mb)
    stack = Stack(args, out, network, disk.path)
    rng = random.Random(args.seed)
    faults: list[Fault] = []
    session = None
    try:
        stack_tokens = Tokens()
        stack.start("router")
        session = connect(stack.endpoint, threading.Event())
        liveliness = session.liveliness().declare_subscriber(
            keys.alive_all(stack.ns), stack_tokens, history=True
        )
        stack.start_services(stack_tokens)
        t0 = time.monotonic()
        end = t0 + args.minutes * 60
        kinds, weights = zip(*FAULT_WEIGHTS.items(), strict=True)
        while (now := time.monotonic()) < end:
            time.sleep(min(rng.expovariate(1.0 / args.mean_gap_s), max(0.0, end - now)))
            if time.monotonic() >= end:
                break
            kind = rng.choices(kinds, weights)[0]
            at = time.monotonic() - t0
            target, held, injected, note = run_fault(kind, rng, stack, disk, session, world, line)
            ended = time.monotonic()
            recovered = stack_tokens.until(SERVICES, RECOVER_TIMEOUT_S)
            fault = Fault(kind, target, round(at, 1), round(held, 1), injected=injected, note=note)
            fault.recovered_s = round(time.monotonic() - ended, 2) if recovered else None
            faults.append(fault)
            print(f"{at:7.0f} s  {kind}:{target}  {note}", file=sys.stderr)
        wait_s = stack.world_s * 10 + RECOVER_TIMEOUT_S
        deadline = time.monotonic() + wait_s
        while not (stack.simulator_done and stack.fleet_done) and time.monotonic() < deadline:
            time.sleep(1.0)
        reference_world, raw_expected = world, None
        if args.raw_trains:  # the raw chain's indices, from what the gateway recorded
            entries = gateway_entries(out / "outbox-gateway-fleet.sqlite")
            raw_expected = raw_chain_indices(entries, network)
            raw_world = [decode(p, OnboardIndex) for p in sorted(raw_expected)]
            reference_world = [*world, *raw_world]
            print(f"raw chain: {len(entries)} gateway messages, {len(raw_expected)} indices",
                  file=sys.stderr)  # fmt: skip
        result = settle(session, stack, reference_world, stack_tokens, raw_expected)
        liveliness.undeclare()
    finally:
        if session is not None:
            session.close()
        stack.close()
        disk.close()
    recoveries = [f.recovered_s for f in faults if f.injected and f.recovered_s is not None]
    by_kind = Counter(f"{f.kind}:{f.target}" if f.kind in ("kill", "stop") else f.kind
                      for f in faults if f.injected)  # fmt: skip
    return {
        "network": args.network,
        "minutes": args.minutes,
        "seed": args.seed,
        "world": {
            "days": args.days,
            "trains": args.trains,
            "raw_trains": args.raw_trains,
            "events": len(world),
            "speedup": round(args.speedup, 1),
        },  # fmt: skip
        "faults": dict(sorted(by_kind.items())),
        "not_injected": [asdict(f) for f in faults if not f.injected][:3],
        "not_recovered": sum(f.injected and f.recovered_s is None for f in faults),
        "recovery_s": {
            "p50": pct(recoveries, 50),
            "p99": pct(recoveries, 99),
            "max": max(recoveries, default=None),
        },
        "restarts": dict(stack.restarts),
        "states": result,
        "simulator_finished": stack.simulator_done,
        "out": str(out),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.chaos", description=__doc__)
    parser.add_argument("--network", default="demo", help="'demo' or a segment count")
    parser.add_argument("--minutes", type=float, default=30.0, help="how long faults go on")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--days", type=float, default=365.0, help="simulated days")
    parser.add_argument("--trains", type=int, default=4)
    parser.add_argument(
        "--raw-trains", type=int, default=1, help="trains of raw data through the raw chain"
    )
    parser.add_argument("--speedup", type=float, help="default: the world ends at 70 %% of it")
    parser.add_argument("--mean-gap-s", type=float, default=20.0, help="between two faults")
    parser.add_argument("--store-mb", type=int, default=2048, help="filtering's filesystem")
    parser.add_argument("--out", help="logs and stores (default: a new temporary directory)")
    parser.add_argument("--json", help="write the summary here too")
    args = parser.parse_args(argv)
    summary = run(args)
    text = json.dumps(summary, indent=2)
    print(text)
    if args.json:
        Path(args.json).write_text(text)
    states = summary["states"]
    raw = states.get("raw_chain") or {"missing": 0, "extra": 0}
    ok = (
        states["missing"] == states["differ"] == 0
        and raw["missing"] == raw["extra"] == 0
        and not summary["not_recovered"]
    )
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
