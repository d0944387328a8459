"""Restart and model change of a filtering instance holding many segments.

A store of ``--segments`` segments (lines of ``LINE_SEGMENTS``), each with a TRC record and
``2 × --days`` OnboardIndex since (Ns = 200 posterior samples), is written directly with
SQL (the rows the service itself writes: re-encoded payloads, identities, times) together
with the models. Then the real service (``trackfusion filtering`` in its own process, a
router in this one on loopback) is started on it, four times:

1. *first start*: no checkpoint, every segment replayed from its log (what every restart
   cost before checkpoints), then a clean stop (SIGTERM: checkpoints written);
2. *restart*: from the checkpoints;
3. *model change*: a new Calibration published; time until every segment's state with
   the new version has arrived here; then one unit's own calibration (its train ran over a
   tenth of the segments: those are re-run and published, no other); then one new index on
   every tenth segment and SIGKILL before the next checkpoint;
4. *restart after SIGKILL*: checkpoints and the events stored after them.

Ready is the service's liveliness token; *answering* is a ``q/state`` query here returning
every segment. The time is from the process start (interpreter and imports included).
RSS is the service process's, summed over the instances (``VmHWM``: peak; ``VmRSS`` once
ready). Baseline in this process: :func:`services.filtering.fold.fold_many` of the same
events, alone, on a sample of segments, extrapolated per event.

``--shards S`` runs S instances instead of one, each on its own store and ``--selector``
(``A$*/**``, ``B$*/**``, …: the segments split into S runs of lines), the times then to the
last instance's token and every segment's state; on 2 cores this is how the Python half of
a re-run (one thread an instance) gets the second core.

``--router-process``: the router runs as its own process (``trackfusion router``, as
deployed) instead of a session of this one (which then holds only the receiving client).

Run: ``python -m bench.restart [--segments 100000 --days 60 --shards 2 --router-process]``.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import signal
import socket
import sqlite3
import subprocess
import sys
import tempfile
import threading
import time
from collections import Counter
from pathlib import Path

import msgspec
import numpy as np
import zenoh

from bench.soak import threads_each
from schemas import (
    DAY_S,
    Calibration,
    OnboardIndex,
    TrcRecord,
    encode,
    keys,
)
from services.filtering.events import canonical_log
from services.filtering.fold import fold_many
from services.filtering.models import Models, parse_model
from services.filtering.payloads import stored_events
from services.filtering.store import Store
from services.filtering.testing import example_models, onboard_index, sample_state
from services.runtime.config import users_env, zenoh_config

NS_SAMPLES = 200
T0 = 1_767_225_600.0
BLOCK = zenoh.CongestionControl.BLOCK  # the bench's puts: Zenoh's default drops under congestion
READY_S = 1800.0  # upper bound of a start at the largest size
CHUNK = 2000  # segments written per executemany


def build_store(
    db: Path, segments: int, days: int, ns: str, models, shard: int = 0, shards: int = 1
) -> int:
    """The store the service would have written for these events (the segments of ``shard``
    of ``shards``: :func:`shard_of`); returns the event count."""
    rng = np.random.default_rng(1)
    with Store(db) as store:
        for msg in models:
            name = "calibration" if msg.__class__.__name__ == "Calibration" else "degradation/net"
            key = keys.calibration(ns) if name == "calibration" else keys.degradation(ns, "net")
            store.put_model(
                name=name, kind=name.split("/")[0], version=1, key=key, payload=encode(msg)
            )
    db_ = sqlite3.connect(db, isolation_level=None)
    db_.execute("PRAGMA synchronous=OFF")
    n = 0
    times = T0 + (np.arange(2 * days) // 2 + 0.25 + 0.5 * (np.arange(2 * days) % 2)) * DAY_S
    mine = [k for k in range(segments) if shard_of(k, segments, shards) == shard]
    for first in range(0, len(mine), CHUNK):
        rows = []
        for k in mine[first : first + CHUNK]:
            seg, line = f"s{k:06d}", line_of(k, segments, shards)
            trc = TrcRecord(line=line, segment=seg, t=T0, top6_mm=3.0, align10_mm=2.4, run_id="r0")
            rows.append(
                (
                    line,
                    seg,
                    "trc",
                    keys.trc(ns, line, seg),
                    json.dumps(["trc", "r0", T0]),
                    T0,
                    encode(trc),
                )
            )
            y = np.exp(rng.normal([0.8, 0.5], 0.1, (len(times), 2))).tolist()
            key = keys.index(ns, line, seg)
            for i, t in enumerate(times.tolist()):
                train = _train(k, segments, i)
                msg = onboard_index(line, seg, t, *y[i], train=train)
                identity = json.dumps(["index", train, "u1", t])
                rows.append((line, seg, "index", key, identity, t, encode(msg)))
        db_.execute("BEGIN")
        db_.executemany(
            "INSERT INTO events (line, segment, kind, key, identity, t, payload)"
            " VALUES (?, ?, ?, ?, ?, ?, ?)",
            rows,
        )
        db_.execute("COMMIT")
        n += len(rows)
    db_.close()
    return n


REGIONS = 10  # each pair of trains runs over a tenth of the segments
LINE_SEGMENTS = 1000  # segments a line (200 km of 200 m segments)


def shard_of(segment: int, segments: int, shards: int) -> int:
    """The shard of segment number ``segment``: ``shards`` equal runs of numbers."""
    return segment * shards // segments


def line_of(segment: int, segments: int, shards: int = 1) -> str:
    """The line of segment number ``segment``: consecutive numbers, ``LINE_SEGMENTS`` a line
    (a network's layout; one line of 100,000 would make Zenoh's routing of the states the
    figure), named after its shard's letter (its selector ``X$*/**``)."""
    letter = chr(ord("A") + shard_of(segment, segments, shards))
    return f"{letter}{segment // LINE_SEGMENTS + 1:03d}"


def _train(segment: int, segments: int, i: int) -> str:
    """The train of pass ``i`` over segment number ``segment``: two per region."""
    return f"R{segment * REGIONS // segments}-{i % 2}"


def fold_rate(db: Path, models, sids: list[tuple[str, str]]) -> float:
    """Events/s of ``fold_many`` alone over the logs of the segments ``sids`` of the store,
    read as the tracker's loader reads them."""
    with Store(db) as store:
        logs = [canonical_log(stored_events(store.segment_events(*sid)))[0] for sid in sids]
    calibration, posterior = models
    tracker_models = Models(
        calibration=calibration,
        observation=parse_model(calibration),
        posteriors={"net": posterior},
        params={"net": parse_model(posterior)},
    )
    params = tracker_models.params["net"]
    started = time.perf_counter()
    fold_many([None] * len(logs), logs, [params] * len(logs), tracker_models)
    return sum(map(len, logs)) / (time.perf_counter() - started)


class Watcher:
    """This process's view of the service: its token, its states, q/state.

    Each wait's condition is kept by the state callback (counts, a set of what is still
    awaited), so that a wake costs O(1): a predicate over every segment re-evaluated at
    each of 100,000 arrivals made this bench quadratic, and its slow callback held the
    service's BLOCK publications back."""

    def __init__(self, session: zenoh.Session, ns: str) -> None:
        self.session, self.ns = session, ns
        self.tokens: set[str] = set()  # the instances alive
        self.cond = threading.Condition()
        self.versions: dict[str, int] = {}  # segment -> calibration version of its newest state
        self.at_version: Counter[int] = Counter()  # version -> segments whose newest has it
        self.awaited: dict[str, float | None] = {}  # segment -> the t awaited (None: any)
        self.expected: set[str] = set()  # every segment of the last expect()
        self.others = 0  # states of other segments since the last expect()
        alive_key = keys.alive(ns, "filtering", "bench") + "$*"  # benchA, benchB, …
        self._tokens = session.liveliness().declare_subscriber(alive_key, self._on_token)
        self._states = session.declare_subscriber(keys.segment_keys(ns, "state"), self._on_state)

    def _on_token(self, sample: zenoh.Sample) -> None:
        with self.cond:
            if sample.kind == zenoh.SampleKind.PUT:
                self.tokens.add(str(sample.key_expr))
            else:
                self.tokens.discard(str(sample.key_expr))
            self.cond.notify_all()

    def wait_alive(self, instances: int, timeout: float) -> bool:
        with self.cond:
            return self.cond.wait_for(lambda: len(self.tokens) >= instances, timeout)

    def _on_state(self, sample: zenoh.Sample) -> None:
        state = sample_state(sample)
        with self.cond:
            old = self.versions.get(state.segment)
            if old is not None:
                self.at_version[old] -= 1
            self.versions[state.segment] = state.calibration_version
            self.at_version[state.calibration_version] += 1
            self.others += state.segment not in self.expected
            if state.segment in self.awaited and self.awaited[state.segment] in (None, state.t):
                del self.awaited[state.segment]
            self.cond.notify_all()

    def reset(self) -> None:
        """Forget the tokens and states seen (new processes declare and publish again)."""
        with self.cond:
            self.tokens.clear()
            self.versions.clear()
            self.at_version.clear()

    def all_at(self, version: int, segments: int, timeout: float) -> bool:
        with self.cond:
            return self.cond.wait_for(lambda: self.at_version[version] >= segments, timeout)

    def expect(self, awaited: dict[str, float | None]) -> None:
        """Before a put: the segments whose state to wait for (with that t, or any)."""
        with self.cond:
            self.awaited, self.expected, self.others = dict(awaited), set(awaited), 0

    def wait_expected(self, timeout: float) -> bool:
        with self.cond:
            return self.cond.wait_for(lambda: not self.awaited, timeout)

    def answered(self) -> int:
        replies = self.session.get(
            keys.q_state_all(self.ns),
            timeout=READY_S,
            congestion_control=zenoh.CongestionControl.BLOCK,
        )
        return sum(r.ok is not None for r in replies)

    def close(self) -> None:
        self._tokens.undeclare()
        self._states.undeclare()


def rss_mb(pid: int) -> tuple[float, float]:
    """(VmRSS, VmHWM) of a process, MB."""
    fields = {}
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        name, _, value = line.partition(":")
        fields[name] = value
    return tuple(float(fields[k].split()[0]) / 1024 for k in ("VmRSS", "VmHWM"))  # type: ignore[return-value]


class Instances:
    """The service's processes: one, or one per shard, each on its own store and selector."""

    def __init__(self, argsets: list[list[str]], log: Path, env: dict[str, str]) -> None:
        self.argsets, self.log, self.env = argsets, log, env
        self.procs: list[subprocess.Popen] = []

    def start(self, watcher: Watcher, segments: int) -> tuple[float, float, float, float]:
        """Start every instance: ``(ready_s, answering_s, rss, peak)``, ready when the last
        token came, RSS summed over the instances."""
        watcher.reset()
        started = time.perf_counter()
        self.procs = [
            subprocess.Popen(
                [sys.executable, "-m", "services.cli", *args],
                stdout=self.log.open("ab"),
                stderr=subprocess.STDOUT,
                start_new_session=True,
                env=self.env,
            )
            for args in self.argsets
        ]
        while not watcher.wait_alive(len(self.procs), 1.0):  # or a process ended
            ended = [p.poll() for p in self.procs if p.poll() is not None]
            if ended or time.perf_counter() - started > READY_S:
                self.kill()
                raise RuntimeError(f"not ready ({ended}):\n{self.log.read_text()[-2000:]}")
        ready = time.perf_counter() - started
        got = watcher.answered()
        answering = time.perf_counter() - started
        if got != segments:
            raise RuntimeError(f"q/state answered {got} of {segments} segments; see {self.log}")
        return (ready, answering, *self.rss())

    def rss(self) -> tuple[float, float]:
        """(VmRSS, VmHWM) summed over the instances, MB."""
        both = [rss_mb(p.pid) for p in self.procs]
        return sum(r for r, _ in both), sum(h for _, h in both)

    def stop(self, sig: int, timeout: float) -> None:
        for p in self.procs:
            p.send_signal(sig)
        for p in self.procs:
            p.wait(timeout)

    def kill(self) -> None:
        for p in self.procs:
            if p.poll() is None:
                p.kill()


class _Done(Exception):
    pass


def bench_restart(
    segments: int = 2000,
    days: int = 60,
    sample: int = 500,
    service_log: Path | None = None,
    restart_only: bool = False,
    shards: int = 1,
    router_process: bool = False,
    threads: int | None = None,
) -> None:
    threads = threads or threads_each(shards)
    env = {**os.environ, "NUMBA_NUM_THREADS": str(threads)}
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        endpoint = f"tcp/127.0.0.1:{s.getsockname()[1]}"
    ns = f"tfrestart_{os.getpid()}"
    models = example_models(NS_SAMPLES, seed=3)
    router_conf = {"mode": "router", "listen": {"endpoints": [endpoint]}, "scouting": {"delay": 0}}
    client = {"mode": "client", "connect": {"endpoints": [endpoint]}}
    with tempfile.TemporaryDirectory() as tmp, contextlib.ExitStack() as stack:
        log = Path(tmp) / "service.log"
        if router_process:  # as deployed: `trackfusion router`, not a session of this process
            router = subprocess.Popen(
                [sys.executable, "-m", "services.cli", "router", "--listen", endpoint, "--ns", ns],
                stdout=log.open("ab"),
                stderr=subprocess.STDOUT,
                start_new_session=True,
                env=users_env(),
            )
            stack.callback(router.wait, 30)
            stack.callback(router.terminate)
        else:
            stack.enter_context(zenoh.open(zenoh_config(router_conf)))
        dbs = [Path(tmp) / f"filtering-{chr(ord('A') + k)}.sqlite" for k in range(shards)]
        started = time.perf_counter()
        n_events = sum(
            build_store(db, segments, days, ns, models, k, shards) for k, db in enumerate(dbs)
        )
        built = time.perf_counter() - started
        sampled = [
            (line_of(k, segments, shards), f"s{k:06d}")
            for k in range(min(sample, segments // shards))
            if shard_of(k, segments, shards) == 0
        ]
        rate = fold_rate(dbs[0], models, sampled)
        argsets = [
            [
                *("filtering", "--connect", endpoint, "--ns", ns),
                *("--instance", f"bench{chr(ord('A') + k)}", "--db", str(db)),
                *("--selector", f"{chr(ord('A') + k)}$*/**", "--log-level", "info"),
            ]
            for k, db in enumerate(dbs)
        ]
        service = Instances(argsets, log, env)
        rows = []
        with _client(zenoh_config(client)) as session:
            watcher = Watcher(session, ns)
            try:
                first = service.start(watcher, segments)
                t = time.perf_counter()
                service.stop(signal.SIGTERM, READY_S)
                stop_s = time.perf_counter() - t
                rows.append(("first start (no checkpoint: full replay)", *first))
                _progress(rows[-1])

                again = service.start(watcher, segments)
                rows.append(("restart from checkpoints", *again))
                _progress(rows[-1])
                if restart_only:
                    service.stop(signal.SIGTERM, READY_S)
                    raise _Done
                # the restored states are published again in the background (a first put
                # per key declares its publisher); the worker waits for it
                t = time.perf_counter()
                if not watcher.all_at(1, segments, READY_S):
                    raise RuntimeError(f"the restored states did not all arrive; see {log}")
                republish_s = time.perf_counter() - t
                _progress(("republish_s", republish_s))

                calibration = msgspec.structs.replace(models[0], version=2)
                t = time.perf_counter()
                session.put(keys.calibration(ns), encode(calibration), congestion_control=BLOCK)
                if not watcher.all_at(2, segments, READY_S):
                    raise RuntimeError(f"model change incomplete; see {log}")
                change_s = time.perf_counter() - t
                _progress(("change_s", change_s))
                change_rss = service.rss()

                # one unit's own calibration: the segments its train ran over, nothing else
                unit = Calibration(
                    **msgspec.structs.asdict(models[0]) | {"train": "R0-0", "unit": "u1"}
                )
                mine = {f"s{k:06d}" for k in range(segments) if _train(k, segments, 0) == "R0-0"}
                watcher.expect(dict.fromkeys(mine))
                t = time.perf_counter()
                session.put(
                    keys.unit_calibration(ns, "R0-0", "u1"), encode(unit), congestion_control=BLOCK
                )
                if not watcher.wait_expected(READY_S):
                    raise RuntimeError(f"unit calibration incomplete; see {log}")
                unit_s = time.perf_counter() - t
                _progress(("unit_s", unit_s))
                with watcher.cond:  # the re-run publishes the unit's segments, no other
                    if watcher.cond.wait_for(lambda: watcher.others > 0, 1.0):
                        raise RuntimeError(f"states of other segments: {log}")

                tail = _tail(segments, days, shards)
                watcher.expect({m.segment: m.t for m in tail})  # published after commit
                for msg in tail:
                    key = keys.index(ns, msg.line, msg.segment)
                    session.put(key, encode(msg), congestion_control=BLOCK)
                done = watcher.wait_expected(READY_S)
                if not done:
                    raise RuntimeError(f"the tail's states did not all arrive; see {log}")
                service.stop(signal.SIGKILL, 60)
                killed = service.start(watcher, segments)
                rows.append(
                    (f"restart after SIGKILL ({len(tail)} events after checkpoint)", *killed)
                )
                service.stop(signal.SIGTERM, READY_S)
            except _Done:
                pass
            finally:
                service.kill()
                watcher.close()
                if service_log is not None:  # kept when a step fails too: what to read then
                    service_log.write_bytes(log.read_bytes())
        size_mb = sum(db.stat().st_size for db in dbs) / 1e6

    fold_all = n_events / rate
    print(
        f"filtering restart, Ns = {NS_SAMPLES}, {segments:,} segments × {days} days × 2 passes"
        f" = {n_events:,} events since the TRC records (store {size_mb:,.0f} MB, built in"
        f" {built:.0f} s), {shards} instance(s) of {threads} compiled thread(s) each"
        " (NUMBA_NUM_THREADS; RSS summed over them):"
    )
    print(f"  fold_many alone: {rate:,.0f} events/s, i.e. {fold_all:.1f} s for every event")
    for name, ready, answering, rss, peak in rows:
        print(
            f"  {name}: ready (token) {ready:.1f} s, q/state answering all {answering:.1f} s"
            f" ({answering / fold_all:.2f}x the fold alone); RSS {rss:,.0f} MB, peak {peak:,.0f} MB"
        )
    print(f"  clean stop (checkpoints of every segment) {stop_s:.1f} s")
    if restart_only:
        return
    print(f"  restored states published again (background, after ready) in {republish_s:.1f} s")
    print(
        f"  model change (new Calibration, every segment re-run, summarised, checkpointed,"
        f" published, received here): {change_s:.1f} s ({change_s / fold_all:.2f}x the fold"
        f" alone); RSS then {change_rss[0]:,.0f} MB, peak {change_rss[1]:,.0f} MB"
    )
    print(
        f"  one unit's own calibration (the {segments // REGIONS:,} segments its train ran"
        f" over re-run and published, no other): {unit_s:.1f} s; the restart after SIGKILL"
        f" above came after it (the other segments' checkpoints stayed valid)"
    )


def _progress(row: tuple) -> None:
    """A phase's raw figures as soon as measured (stderr), so a later hang loses none."""
    print("  measured:", *row, file=sys.stderr, flush=True)


def _tail(segments: int, days: int, shards: int) -> list[OnboardIndex]:
    t = T0 + (days + 0.5) * DAY_S
    return [
        onboard_index(line_of(k, segments, shards), f"s{k:06d}", t, 2.5, 2.0, train="T9")
        for k in range(0, segments, 10)
    ]


def _client(conf) -> zenoh.Session:
    """A client session of the router (a router process takes a moment to listen)."""
    for _ in range(60):
        try:
            return zenoh.open(conf)
        except zenoh.ZError:
            time.sleep(0.5)
    raise RuntimeError("no router to connect to")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--segments", type=int, default=2000)
    parser.add_argument("--days", type=int, default=60)
    parser.add_argument("--service-log", type=Path, help="keep the service's log there")
    parser.add_argument("--restart-only", action="store_true", help="no model change")
    parser.add_argument(
        "--shards", type=int, default=1, help="filtering instances, each on its own lines"
    )
    parser.add_argument(
        "--router-process",
        action="store_true",
        help="the router as its own process (`trackfusion router`), not a session of the bench",
    )
    parser.add_argument(
        "--threads",
        type=int,
        help="compiled threads of each instance (NUMBA_NUM_THREADS; default: the cores / shards)",
    )
    args = parser.parse_args(argv)
    bench_restart(
        args.segments,
        args.days,
        service_log=args.service_log,
        restart_only=args.restart_only,
        shards=args.shards,
        router_process=args.router_process,
        threads=args.threads,
    )


if __name__ == "__main__":
    main()
