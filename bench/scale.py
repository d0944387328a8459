"""`make scale`: a national-size deployment on this machine, at growing network sizes.

For each size S in ``--segments`` (default 10,000, 30,000, 100,000 segments of 200 m):

1. **network**: ``generate_network(S / 500, 100 km)``, its lines renamed into four regions
   ``A001, B001, C001, D001, A002, …`` (one key chunk each), so that four key-expression
   selectors ``A$*/**`` … ``D$*/**`` split it into four equal shards. Generation time is
   reported.
2. **processes** (each ``python -m services.cli …`` in its own process group, logs in a
   temporary directory, every one stopped at the end, on error and on Ctrl-C/SIGTERM): two
   routers (router 2 ``--connect``\\ s to router 1), calibration on router 1 with the initial
   models (``--min-pairs`` out of reach, so the models stay at version 1 and the figure is
   the event path's, not model refolds'), four filtering instances, one per selector, each
   with its own SQLite file (shards A and B on router 1, C and D on router 2).
3. **load**: ``simulate --fidelity index --trains T --days D --speedup inf`` on router 1
   (``T`` service passes per line and day, an on-board index per segment and pass, plus the
   world's TRC runs and tampings; every line's first TRC run within the first half day, so
   that every segment's filter starts and has a state). A year at 100,000 segments is tens
   of millions of events, far beyond two cores in minutes, so the default is a few days of
   a light service (``--days``, ``--trains``); the figures say how many events went through.
4. **throughput**: this process subscribes to the events and states; the shards are drained
   when every segment's newest state carries its newest event's time. events/s = events
   on the bus / (drained − simulator start).
5. **memory**: RSS of every process every ``--sample-s``; per filtering instance the peak
   and the value once drained.
6. **restart**: filtering shard A is killed (SIGKILL) and started again on the same
   SQLite file; reported: time to its liveliness token and time until ``q/state`` answers
   every segment of its shard.

Figures go to stdout as a table and to ``--json`` (default ``var/scale.json``).
``--quick``: one small size (2,000 segments, 2 days) as a smoke run in about a minute.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import signal
import sys
import tempfile
import threading
import time
from pathlib import Path

import zenoh

from bench.soak import Child, connect, free_port, rss_mb, threads_each
from schemas import SegmentState, decode, keys
from services.filtering.testing import EVENT_TYPES, LastEvents
from simulators.network import generate_network
from simulators.truth import load_config

SEGMENTS_PER_LINE = 500  # 100 km of 200 m segments
REGIONS = "ABCD"
NS = "scale"
INITIAL_MODELS = Path(__file__).resolve().parents[1] / "services/defaults/initial-models.json5"


def write_sim_config(path: Path) -> None:
    """The default simulator config with every line's first TRC run in the first half day:
    a filter starts at a segment's first TRC record, so a run of a few days then has a
    state for every segment (by default the first runs spread over two weeks)."""
    config = load_config()
    config["trc"]["first_run_days"] = [0.0, 0.5]
    path.write_text(json.dumps(config))


def write_network(segments: int, path: Path, seed: int) -> dict:
    """A generated network of ``segments`` segments in four regions; returns the count of
    segments per region and the generation time."""
    n_lines = max(len(REGIONS), round(segments / SEGMENTS_PER_LINE / len(REGIONS)) * 4)
    started = time.perf_counter()
    network = generate_network(n_lines, SEGMENTS_PER_LINE * 0.2, seed=seed)
    obj = network.to_geojson(include_segments=False)
    per_region = dict.fromkeys(REGIONS, 0)
    for k, (feature, line) in enumerate(zip(obj["features"], network.lines.values(), strict=True)):
        region = REGIONS[k % len(REGIONS)]
        feature["properties"]["id"] = f"{region}{k // len(REGIONS) + 1:03d}"
        per_region[region] += len(line.segments)
    path.write_text(json.dumps(obj))
    return {
        "lines": n_lines,
        "segments": network.n_segments,
        "per_region": per_region,
        "generate_s": round(time.perf_counter() - started, 1),
    }


class Probe:
    """Newest event time and newest state time per segment, from plain subscribers."""

    def __init__(self) -> None:
        self.events = LastEvents()
        self.lock = threading.Lock()
        self.state_t: dict[tuple[str, str], float] = {}
        self.n_events = 0
        self.n_states = 0

    def on_event(self, sample: zenoh.Sample) -> None:
        self.events(sample)
        with self.lock:
            self.n_events += 1

    def on_state(self, sample: zenoh.Sample) -> None:
        state = decode(sample.payload.to_bytes(), SegmentState)
        sid = (state.line, state.segment)
        with self.lock:
            self.n_states += 1
            self.state_t[sid] = max(self.state_t.get(sid, state.t), state.t)

    def behind(self) -> int:
        """Segments whose newest state is older than their newest event."""
        seen = self.events.snapshot()
        with self.lock:
            return sum(self.state_t.get(sid) != t for sid, t in seen.items())


class Deployment:
    """Every process of one run; :meth:`close` stops them all (SIGTERM, then SIGKILL)."""

    def __init__(self, logdir: Path) -> None:
        self.logdir = logdir
        self.children: dict[str, Child] = {}
        self.peak_mb: dict[str, float] = {}
        self._stop = threading.Event()
        self._sampler = threading.Thread(target=self._sample, name="rss", daemon=True)

    def start(self, name: str, *args: str, env: dict[str, str] | None = None) -> Child:
        child = Child(name, self.logdir, list(args), env)
        self.children[name] = child
        if not self._sampler.is_alive():
            self._sampler.start()
        return child

    def rss(self, name: str) -> float:
        return round(rss_mb(self.children[name].pid), 1)

    def check(self) -> None:
        """Raise if a process other than the simulator ended."""
        for name, child in self.children.items():
            code = child.popen.poll()
            if code is not None and name != "simulate":
                tail = child.log_path.read_text()[-2000:]
                raise RuntimeError(f"{name} ended with {code}; its log ends:\n{tail}")

    def _sample(self) -> None:
        while not self._stop.wait(self.sample_s):
            for name, child in list(self.children.items()):
                mb = rss_mb(child.pid)
                if mb == mb:  # not NaN: the process is there
                    self.peak_mb[name] = max(self.peak_mb.get(name, 0.0), mb)

    sample_s = 2.0

    def close(self) -> None:
        self._stop.set()
        for child in reversed(list(self.children.values())):
            child.stop()


def wait(predicate, timeout: float, what: str, deployment: Deployment, step: float = 0.5):
    """Poll ``predicate`` until true; raise with ``what()`` after ``timeout``."""
    end = time.monotonic() + timeout
    while not predicate():
        deployment.check()
        if time.monotonic() > end:
            raise TimeoutError(f"after {timeout:.0f} s: {what()}")
        time.sleep(step)


def count_states(session: zenoh.Session, region: str) -> tuple[int, int]:
    """(segments of ``region`` whose state ``q/state`` answers, answers for other lines:
    a shard's selector must take its own region's lines only)."""
    replies = session.get(
        keys.q_state_keys(NS, f"{region}$*/**"),
        timeout=30.0,
        consolidation=zenoh.ConsolidationMode.NONE,
        congestion_control=zenoh.CongestionControl.BLOCK,  # replies take the query's QoS
    )
    lines = [keys.parse_q_state(str(r.ok.key_expr))[0] for r in replies if r.ok is not None]
    own = sum(line.startswith(region) for line in lines)
    return own, len(lines) - own


def run_size(segments: int, args: argparse.Namespace, workdir: Path) -> dict:
    net_path = workdir / f"net-{segments}.geojson"
    net = write_network(segments, net_path, args.seed)
    print(f"[{segments}] network: {net}", file=sys.stderr, flush=True)
    logdir = workdir / f"logs-{segments}"
    logdir.mkdir()
    r1, r2 = (f"tcp/127.0.0.1:{free_port()}" for _ in range(2))
    deployment = Deployment(logdir)
    stop = threading.Event()
    try:
        deployment.start("router1", "router", "--listen", r1)
        session = connect(r1, stop)
        deployment.start("router2", "router", "--listen", r2, "--connect", r1)
        try:
            return _run(segments, net, net_path, args, deployment, session, r1, r2, workdir)
        finally:
            session.close()
    finally:
        deployment.close()


def _run(segments, net, net_path, args, deployment, session, r1, r2, workdir) -> dict:
    probe = Probe()
    for kind in EVENT_TYPES:
        session.declare_subscriber(keys.segment_keys(NS, kind), probe.on_event)
    session.declare_subscriber(keys.segment_keys(NS, "state"), probe.on_state)
    alive: dict[str, float] = {}

    def on_alive(sample: zenoh.Sample) -> None:
        if sample.kind == zenoh.SampleKind.PUT:
            alive[str(sample.key_expr)] = time.monotonic()
        else:
            alive.pop(str(sample.key_expr), None)

    session.liveliness().declare_subscriber(keys.alive_all(NS), on_alive, history=True)

    def wiring(router: str) -> list[str]:
        return ["--connect", router, "--ns", NS]

    deployment.start(
        "calibration",
        "calibration",
        "--db",
        str(workdir / f"calibration-{segments}.sqlite"),
        "--initial-models",
        str(INITIAL_MODELS),
        "--min-pairs",
        str(10**9),
        "--instance",
        "cal",
        *wiring(r1),
    )

    def start_shard(region: str) -> Child:
        router = r1 if region in "AB" else r2
        return deployment.start(
            f"filtering-{region}",
            "filtering",
            "--selector",
            f"{region}$*/**",
            "--db",
            str(workdir / f"filtering-{region}-{segments}.sqlite"),
            "--instance",
            f"f{region}",
            *wiring(router),
            env={"NUMBA_NUM_THREADS": str(args.threads)},  # the cores shared out, see --threads
        )

    started = time.monotonic()
    for region in REGIONS:
        start_shard(region)
    expected = [keys.alive(NS, "calibration", "cal")]
    expected += [keys.alive(NS, "filtering", f"f{r}") for r in REGIONS]
    wait(
        lambda: all(k in alive for k in expected),
        120,
        lambda: f"alive: {sorted(alive)}",
        deployment,
    )
    startup_s = time.monotonic() - started

    world = ["--network", str(net_path), "--days", str(args.days), "--trains", str(args.trains)]
    write_sim_config(sim_config := workdir / "simulator.json")
    world += ["--sim-config", str(sim_config)]
    sim_started = time.monotonic()
    simulate = deployment.start(
        "simulate",
        "simulate",
        "--fidelity",
        "index",
        *world,
        "--seed",
        str(args.seed),
        "--speedup",
        "inf",
        "--no-progress",
        *wiring(r1),
    )
    wait(
        lambda: simulate.popen.poll() is not None,
        args.timeout,
        lambda: f"simulator still publishing, {probe.n_events} events seen",
        deployment,
    )
    sim_s = time.monotonic() - sim_started
    if simulate.popen.returncode != 0:
        raise RuntimeError(f"simulate ended with {simulate.popen.returncode}")
    published = next(
        json.loads(line)
        for line in reversed(simulate.log_path.read_text().splitlines())
        if line.startswith('{"published"')
    )
    wait(
        lambda: probe.behind() == 0 and len(probe.events.snapshot()) > 0,
        args.timeout,
        lambda: f"{probe.behind()} segments behind their newest event",
        deployment,
        step=1.0,
    )
    drained_s = time.monotonic() - sim_started
    rss_drained = {f"filtering-{r}": deployment.rss(f"filtering-{r}") for r in REGIONS}
    for name in ("router1", "router2", "calibration"):
        rss_drained[name] = deployment.rss(name)

    # restart: SIGKILL shard A, start it again on its file
    token = keys.alive(NS, "filtering", "fA")
    shard = deployment.children.pop("filtering-A")  # its death is wanted
    with contextlib.suppress(ProcessLookupError):
        shard.popen.send_signal(signal.SIGKILL)
    shard.popen.wait(10)
    wait(lambda: token not in alive, 60, lambda: "fA token still held", deployment)
    restarted = time.monotonic()
    start_shard("A")
    wait(lambda: token in alive, 600, lambda: "fA not alive again", deployment)
    alive_s = alive[token] - restarted
    owned = sum(1 for line, _ in probe.events.snapshot() if line.startswith("A"))
    answered = foreign = 0

    def answers_all() -> bool:
        nonlocal answered, foreign
        answered, foreign = count_states(session, "A")
        if foreign:
            raise RuntimeError(f"q/state of shard A answered {foreign} keys of other lines")
        return answered >= owned

    wait(answers_all, 600, lambda: f"q/state answers {answered} of {owned}", deployment)
    query_s = time.monotonic() - restarted

    return {
        "segments": net["segments"],
        "lines": net["lines"],
        "generate_s": net["generate_s"],
        "days": args.days,
        "trains_per_line_day": args.trains,
        "events": probe.n_events,
        "published": published,
        "states_seen": probe.n_states,
        "segments_with_events": len(probe.events.snapshot()),
        "startup_s": round(startup_s, 1),
        "simulate_s": round(sim_s, 1),
        "drained_s": round(drained_s, 1),
        "events_per_s": round(probe.n_events / drained_s),
        "rss_drained_mb": rss_drained,
        "rss_peak_mb": {k: round(v, 1) for k, v in deployment.peak_mb.items()},
        "restart_alive_s": round(alive_s, 1),
        "restart_q_state_s": round(query_s, 1),
        "restart_segments": owned,
    }


def table(rows: list[dict]) -> str:
    head = (
        "| segments | events | events/s (4 shards) | filtering RSS peak / drained (MB, max of 4) "
        "| routers RSS (MB) | restart: token / q/state all (s) | generate (s) |"
    )
    out = [head, "|" + "---|" * 7]
    for r in rows:
        f_peak = max(v for k, v in r["rss_peak_mb"].items() if k.startswith("filtering"))
        f_drained = max(v for k, v in r["rss_drained_mb"].items() if k.startswith("filtering"))
        routers = f"{r['rss_drained_mb']['router1']:.0f} / {r['rss_drained_mb']['router2']:.0f}"
        out.append(
            f"| {r['segments']:,} | {r['events']:,} | {r['events_per_s']:,} "
            f"| {f_peak:.0f} / {f_drained:.0f} | {routers} "
            f"| {r['restart_alive_s']} / {r['restart_q_state_s']} | {r['generate_s']} |"
        )
    return "\n".join(out)


def main(args: argparse.Namespace) -> int:
    def on_term(signum, _frame) -> None:
        raise KeyboardInterrupt(signal.Signals(signum).name)

    signal.signal(signal.SIGTERM, on_term)
    rows = []
    with tempfile.TemporaryDirectory(prefix="tf-scale-") as tmp:
        for segments in args.segments:
            rows.append(run_size(segments, args, Path(tmp)))
            print(json.dumps(rows[-1]), file=sys.stderr, flush=True)
    print(f"{len(REGIONS)} filtering shards, {args.threads} compiled thread(s) each")
    print(table(rows))
    out = Path(args.json)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"args": vars(args), "rows": rows}, indent=1))
    print(f"figures: {out}")
    return 0


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--segments",
        type=lambda s: [int(x) for x in s.split(",")],
        default=[10_000, 30_000, 100_000],
        help="network sizes, comma-separated (default %(default)s)",
    )
    parser.add_argument("--days", type=float, default=3.0, help="simulated days")
    parser.add_argument("--trains", type=int, default=1, help="service passes per line and day")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--timeout", type=float, default=1800.0, help="per phase (s)")
    parser.add_argument("--json", default="var/scale.json")
    parser.add_argument("--quick", action="store_true", help="2,000 segments, 2 days")
    parser.add_argument(
        "--threads",
        type=int,
        default=threads_each(len(REGIONS)),
        help="compiled threads of each filtering shard (NUMBA_NUM_THREADS; default: the "
        "cores shared out over the shards, at least one)",
    )
    args = parser.parse_args(argv)
    if args.quick:
        args.segments, args.days = [2_000], 2.0
    return args


if __name__ == "__main__":
    sys.exit(main(parse_args()))
