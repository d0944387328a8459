"""`trackfusion gateway check --train T [--seconds S]`: a fleet gateway against the contract.

Subscribes ``{ns}/raw/{T}/**``, ``{ns}/gps/{T}`` and ``{ns}/deadletter/ingestion`` (the
letters about T), for S seconds or until Ctrl-C, and runs every message through the same
decoding (:func:`services.ingestion.service.decode_gateway`) and the same core
(:class:`services.ingestion.core.IngestionCore`: validation, units, the train's clock,
sequencing) as ingestion, without map matching (the contract says nothing about where a
train runs; ``unpositioned`` is no deviation here). It prints what it saw and every
deviation with the rule it breaks (schemas/README.md, "The gateway contract").

Exit code: 0 clean, 1 deviations found, 2 nothing arrived.

:class:`GatewayCheck` is the pure part (payloads and arrival times in, a report out);
:func:`main` is the Zenoh loop around it.
"""

from __future__ import annotations

import argparse
import math
import queue
import signal
import sys
import threading
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TextIO

import numpy as np
import zenoh

from schemas import (
    ACCEL_CHANNELS,
    SUPPLY_CHANNEL,
    DeadLetter,
    GpsFix,
    RawChunk,
    SchemaError,
    decode,
    keys,
)
from schemas.wire import check_id
from services.ingestion.config import IngestionConfig
from services.ingestion.core import IngestionCore, Rejection
from services.ingestion.service import SERVICE as INGESTION
from services.ingestion.service import decode_gateway, ingestion_config
from services.runtime.config import RuntimeConfig, add_zenoh_arguments
from services.runtime.service import run_command

EXIT_CLEAN, EXIT_DEVIATIONS, EXIT_NOTHING = 0, 1, 2


class _NoNetwork:
    """No lines: the core checks the contract and never positions (no map matching)."""

    lines: dict = {}

    @staticmethod
    def to_xy(lonlat: np.ndarray) -> np.ndarray:
        return lonlat


@dataclass
class _Unit:
    chunks: int = 0
    first_t0: float = math.nan
    last_t0: float = math.nan
    samples_before_last: int = 0  # samples of every chunk but the newest (rate measurement)
    last_n: int = 0
    backwards: int = 0  # t0 not after the previous chunk's
    supply_v: list[float] = field(default_factory=lambda: [math.inf, -math.inf])
    vertical_g: list[float] = field(default_factory=lambda: [math.inf, -math.inf])


def _gateway_train(key: str) -> str | None:
    """The train of a gateway's key (raw or GPS); None for another key."""
    try:
        return keys.parse_raw(key)[0] if keys.kind(key) == "raw" else keys.parse_gps(key)
    except SchemaError:
        return None


class GatewayCheck:
    """Everything one train's gateway sends, checked; :meth:`report` says what was found."""

    def __init__(self, train: str, config: IngestionConfig | None = None) -> None:
        check_id("train", train)
        self.train = train
        self.core = IngestionCore(_NoNetwork(), config)
        self.seen: Counter[str] = Counter()  # messages per key
        self.deviations: dict[str, list] = {}  # rule -> [count, first reason]
        self.units: dict[str, _Unit] = {}
        self.fixes = 0
        self.fix_backwards = 0
        self.last_fix_t: float | None = None
        self.wall: list[float] = [math.inf, -math.inf]  # first and last arrival
        self.fix_wall: list[float] = []  # arrival times of fixes
        self.chunk_wall: list[float] = []
        self.fix_lag_s: list[float] = []  # arrival (receiver's clock) - fix t
        self.chunk_vs_fix_s: list[float] = []  # chunk's last sample - newest fix t

    @property
    def messages(self) -> int:
        return sum(self.seen.values())

    def feed(self, kind: str, key: str, payload: bytes, arrived: float) -> None:
        """One message: ``kind`` is "raw", "gps" or "deadletter"; ``arrived`` wall epoch s."""
        if kind == "deadletter":
            self._letter(payload)
            return
        self.seen[key] += 1
        self.wall = [min(self.wall[0], arrived), max(self.wall[1], arrived)]
        try:
            message = decode_gateway(kind, key, payload)
        except SchemaError as exc:
            self._deviation(str(exc))
            return
        if message.train != self.train:
            self._deviation(f"{type(message).__name__}: train {message.train} is not {self.train}")
        if isinstance(message, RawChunk):
            self._measure_chunk(message, arrived)
        else:
            self._measure_fix(message, arrived)
        for out in self.core.step(message, arrived):
            if isinstance(out, Rejection) and "unpositioned" not in out.reason:
                self._deviation(out.reason)

    def _letter(self, payload: bytes) -> None:
        try:
            letter = decode(payload, DeadLetter)
        except SchemaError:
            return
        if _gateway_train(letter.key) == self.train:
            self._deviation(f"ingestion refused ({letter.key}): {letter.reason}", "ingestion")

    def _deviation(self, reason: str, rule: str | None = None) -> None:
        if rule is None:  # "RawChunk: samples: …" -> "RawChunk samples"
            head = reason.split(":", 2)
            rule = " ".join(h.strip() for h in head[:2]) if len(head) > 2 else head[0]
        entry = self.deviations.setdefault(rule, [0, reason])
        entry[0] += 1

    def _measure_chunk(self, chunk: RawChunk, arrived: float) -> None:
        self.chunk_wall.append(arrived)
        u = self.units.setdefault(chunk.unit, _Unit())
        n = chunk.samples.shape[0]
        if u.chunks and chunk.t0 <= u.last_t0:
            u.backwards += 1
        elif u.chunks:
            u.samples_before_last += u.last_n
        else:
            u.first_t0 = chunk.t0
        if not u.chunks or chunk.t0 > u.last_t0:
            u.last_t0, u.last_n = chunk.t0, n
        u.chunks += 1
        a = chunk.samples.array()
        if SUPPLY_CHANNEL in chunk.channels and n:
            v = a[:, chunk.channels.index(SUPPLY_CHANNEL)]
            u.supply_v = [min(u.supply_v[0], float(v.min())), max(u.supply_v[1], float(v.max()))]
        for name in (ACCEL_CHANNELS[0], ACCEL_CHANNELS[3]):
            if name in chunk.channels and n:
                g = float(a[:, chunk.channels.index(name)].mean(dtype=np.float64))
                u.vertical_g = [min(u.vertical_g[0], g), max(u.vertical_g[1], g)]
        if self.last_fix_t is not None and chunk.rate_hz > 0:
            self.chunk_vs_fix_s.append(chunk.t0 + (n - 1) / chunk.rate_hz - self.last_fix_t)

    def _measure_fix(self, fix: GpsFix, arrived: float) -> None:
        self.fixes += 1
        self.fix_wall.append(arrived)
        self.fix_lag_s.append(arrived - fix.t)
        if self.last_fix_t is not None and fix.t <= self.last_fix_t:
            self.fix_backwards += 1
        self.last_fix_t = fix.t if self.last_fix_t is None else max(self.last_fix_t, fix.t)

    def report(self) -> tuple[str, int]:
        """The printed report and the exit code."""
        lines = [f"gateway check of train {self.train}"]
        deviations = {rule: list(entry) for rule, entry in self.deviations.items()}
        if not self.messages:
            lines.append("nothing arrived: is the gateway publishing, on this namespace?")
            return "\n".join(lines) + "\n", EXIT_NOTHING
        span = max(self.wall[1] - self.wall[0], 1e-9)
        lines.append(f"messages per key ({self.messages} in {span:.1f} s):")
        lines += [f"  {key}: {n}" for key, n in sorted(self.seen.items())]
        lines.append(
            f"rates: {_rate(self.chunk_wall):.2f} chunks/s, {_rate(self.fix_wall):.2f} fixes/s "
            "(contract: one ~1 s chunk per unit per second, fixes at 1 Hz)"
        )
        for name, u in sorted(self.units.items()):
            dt = u.last_t0 - u.first_t0
            rate = f"{u.samples_before_last / dt:.1f} Hz" if dt > 0 else "n/a (one chunk)"
            lines.append(
                f"unit {name}: {u.chunks} chunks, sample rate measured {rate} (contract "
                f"2000 Hz ± 1 %), supply_v {u.supply_v[0]:.3f}..{u.supply_v[1]:.3f} V "
                f"(2.5..7.5), vertical mean {u.vertical_g[0]:.3f}..{u.vertical_g[1]:.3f} g "
                f"(≈ +1 g; ≈ 9.81 means m/s²), t0 backwards {u.backwards}"
            )
            h = self.core.health(self.train, name)
            lines.append(
                f"  sequencing: {h.missing} missing, {h.duplicates} duplicates, "
                f"{h.late} late, {h.restarts} counter restarts"
            )
            if h.missing:
                deviations[f"seq gaps {name}"] = [h.missing, f"seq: {h.missing} chunks missing"]
            if h.restarts:
                deviations[f"seq restart {name}"] = [h.restarts, "seq: the counter restarted"]
        lines.append(
            f"fixes: {self.fixes}, not after the previous fix {self.fix_backwards}; "
            f"clock: arrival - fix t median {_median(self.fix_lag_s)}, "
            f"chunk end - newest fix median {_median(self.chunk_vs_fix_s)}"
        )
        stats = self.core.train_stats(self.train)
        if stats.rebases:
            lines.append(f"clock re-based {stats.rebases} times (the gateway's clock jumped)")
        if not deviations:
            lines.append("no deviation from the gateway contract")
            return "\n".join(lines) + "\n", EXIT_CLEAN
        lines.append(f"deviations ({sum(n for n, _ in deviations.values())}):")
        for rule, (n, first) in sorted(deviations.items()):
            lines.append(f"  [{rule}] ×{n}: {first}")
        return "\n".join(lines) + "\n", EXIT_DEVIATIONS


def _rate(times: list[float]) -> float:
    if len(times) < 2:
        return 0.0
    return (len(times) - 1) / max(times[-1] - times[0], 1e-9)


def _median(values: list[float]) -> str:
    return f"{float(np.median(values)):+.3f} s" if values else "n/a"


def main(
    conf: RuntimeConfig,
    train: str,
    seconds: float | None = None,
    *,
    out: TextIO | None = None,
    stop: threading.Event | None = None,
    handle_signals: bool = True,
    on_message: Callable[[GatewayCheck], None] | None = None,
) -> int:
    """Check train ``train``'s gateway for ``seconds`` (None: until ``stop``/Ctrl-C).

    ``on_message`` is called after every message (tests wait on it).
    """
    out = out or sys.stdout
    check = GatewayCheck(train, ingestion_config(conf))
    stop = stop or threading.Event()
    if handle_signals:
        for signum in (signal.SIGINT, signal.SIGTERM):
            signal.signal(signum, lambda *_: stop.set())
    inbox: queue.SimpleQueue[tuple[str, str, bytes, float]] = queue.SimpleQueue()
    ns = conf.ns
    subscriptions = {
        "raw": keys.raw_of_train(ns, train),
        "gps": keys.gps(ns, train),
        "deadletter": keys.deadletter(ns, INGESTION),
    }
    deadline = math.inf if seconds is None else time.monotonic() + seconds
    with zenoh.open(conf.zenoh_config()) as session:
        subscribers = [
            session.declare_subscriber(
                key,
                lambda s, kind=kind: inbox.put(
                    (kind, str(s.key_expr), s.payload.to_bytes(), time.time())
                ),
            )
            for kind, key in subscriptions.items()
        ]
        try:
            while not stop.is_set() and time.monotonic() < deadline:
                try:
                    item = inbox.get(timeout=min(0.2, max(deadline - time.monotonic(), 0.0)))
                except queue.Empty:
                    continue
                check.feed(*item)
                if on_message is not None:
                    on_message(check)
        finally:
            for subscriber in subscribers:
                subscriber.undeclare()
    while True:  # what arrived before the subscribers went
        try:
            check.feed(*inbox.get_nowait())
        except queue.Empty:
            break
    text, code = check.report()
    out.write(text)
    out.flush()
    return code


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """``trackfusion gateway check``."""
    parser.description = (
        "Subscribe to {ns}/raw/TRAIN/**, {ns}/gps/TRAIN and ingestion's dead letters for S "
        "seconds (or until Ctrl-C), check every message as ingestion does and print a "
        "report. Exit code 0 clean, 1 deviations found, 2 nothing arrived."
    )
    parser.add_argument("--train", required=True, help="the train id the gateway publishes as")
    parser.add_argument(
        "--seconds", type=float, metavar="S", help="how long (default: until Ctrl-C)"
    )
    add_zenoh_arguments(parser)


def run(args: argparse.Namespace) -> int:
    return run_command(args, main, train=args.train, seconds=args.seconds)
