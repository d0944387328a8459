"""`trackfusion simulate` and `trackfusion network generate`: the simulator's entry points."""

from __future__ import annotations

import argparse
import json
import logging
import math
import sys
import time
from datetime import datetime
from pathlib import Path

from schemas import DAY_S, GpsFix, RawChunk
from services.defaults import add_network_argument, load_network
from services.runtime.config import RuntimeConfig, add_zenoh_arguments, flag_values
from services.runtime.service import run_command
from simulators.gateway import publish
from simulators.groundtruth import GroundTruthWriter
from simulators.network import generate_network
from simulators.truth import load_config
from simulators.world import WorldSpec, message_count, world_events

log = logging.getLogger(__name__)
DEFAULT_START = "2026-01-01T00:00:00+00:00"


def main_simulate(
    conf: RuntimeConfig,
    *,
    network_path: str | None,
    trains: int,
    days: float,
    speedup: float,
    fidelity: str,
    seed: int,
    start_t: float,
    truth_path: str | None,
    config_path: str | None,
    units: int = 1,
    progress: bool = True,
    stop=None,
    from_day: float = 0.0,
    to_day: float | None = None,
    linger_s: float = 0.0,
    gateway_only: bool = False,
) -> int:
    """Publish the simulated world on Zenoh (and write its ground truth to ``truth_path``).
    ``gateway_only``: only what the trains' gateways send (raw chunks and GPS fixes).

    Only the events in ``[from_day, to_day)`` days of the world are published: a world cut
    in two such runs publishes exactly what one run would (the world itself is the same).
    The event streams go through an outbox in memory (at least once while the process
    lives, :mod:`services.runtime.delivery`); ``linger_s`` keeps the process and its outbox
    up that long after the last message, so that a consumer returning meanwhile still gets
    what it missed (a stop ends it early).
    """
    from tqdm import tqdm

    from services.runtime.service import ServiceRuntime

    network = load_network(network_path)
    config = load_config(config_path)
    spec = WorldSpec(network, config, start_t, days, seed, trains, fidelity, units)
    truth = (
        GroundTruthWriter(truth_path, network, config, start_t, days, seed) if truth_path else None
    )
    counts: dict[str, int] = {}
    bar = tqdm(total=round(days * DAY_S), unit="sim-s", disable=not progress, desc="simulating")
    last = [start_t]

    def on_batch(t: float, messages) -> None:
        for name, n in message_count(messages).items():
            counts[name] = counts.get(name, 0) + n
        if truth:
            truth.record(t, messages)
        bar.update(round(t - last[0]))
        last[0] = t
        bar.set_postfix(counts, refresh=False)

    started = time.monotonic()
    with ServiceRuntime("simulator", conf, handle_signals=True, stop_event=stop) as rt:
        rt.announce()
        lo, hi = start_t + from_day * DAY_S, start_t + (days if to_day is None else to_day) * DAY_S
        events = ((t, m) for t, m in world_events(spec) if lo <= t < hi)
        if gateway_only:
            events = ((t, [m for m in ms if isinstance(m, RawChunk | GpsFix)]) for t, ms in events)
        total = publish(
            rt.session,
            rt.ns,
            events,
            reliable=rt.reliable_publisher(durable=False),
            # the fleet's gateway keeps its outbox on disk, as a train's gateway would
            gateway=rt.reliable_publisher(service="gateway", raw=True)
            if fidelity == "raw"
            else None,
            speedup=speedup,
            stop=rt.stop_event,
            on_batch=on_batch,
        )
        if linger_s > 0 and not rt.stopping:
            log.info("published; lingering %.0f s for returning subscribers", linger_s)
            rt.wait(linger_s)
    bar.close()
    if truth:
        truth.close(finish=not (stop and stop.is_set()))
    log.info(
        "published %d messages in %.1f s: %s", total, time.monotonic() - started, json.dumps(counts)
    )
    print(json.dumps({"published": total, "by_type": counts}), flush=True)
    return 0


def main_network_generate(
    *, lines: int, length_km: float, seed: int, segment_length_m: float, out: str | None
) -> int:
    """Write a generated network as GeoJSON (lines and segments) to ``out`` or stdout."""
    if lines < 1 or length_km <= 0 or segment_length_m <= 0:
        raise ValueError("--lines >= 1, --length-km > 0, --segment-m > 0")
    network = generate_network(lines, length_km, seed, segment_length_m=segment_length_m)
    text = json.dumps(network.to_geojson(include_segments=True))
    if out:
        Path(out).write_text(text)
        print(f"{out}: {len(network.lines)} lines, {network.n_segments} segments", file=sys.stderr)
    else:
        print(text)
    return 0


def parse_speedup(text: str) -> float:
    value = math.inf if text in ("inf", "max") else float(text)
    if not value > 0:
        raise ValueError("speedup must be > 0 (or 'inf')")
    return value


def _speedup(text: str) -> float:
    try:
        return parse_speedup(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def simulate_add_arguments(parser: argparse.ArgumentParser) -> None:
    """``trackfusion simulate``."""
    parser.description = (
        "Run the fleet simulator on a network and publish its gateways' raw data "
        "(--fidelity raw) or on-board indices (--fidelity index), TRC records and tamping."
    )
    add_network_argument(parser, "the lines the trains run on")
    parser.add_argument(
        "--trains", type=int, default=6, help="raw: trains; index: passes per line per day"
    )
    parser.add_argument(
        "--days", type=float, default=1.0, help="simulated days (default %(default)g)"
    )
    parser.add_argument(
        "--speedup", type=_speedup, default=1.0, help="simulated s per wall s, or 'inf'"
    )
    parser.add_argument("--fidelity", choices=["raw", "index"], default="index")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--units", type=int, default=1, help="on-board units per train (raw)")
    parser.add_argument(
        "--from-day", type=float, default=0.0, help="publish only from this day of the world"
    )
    parser.add_argument("--to-day", type=float, help="publish only up to this day of the world")
    parser.add_argument("--start", default=DEFAULT_START, help="ISO start time (UTC)")
    parser.add_argument("--truth", metavar="FILE.sqlite", help="write the ground truth here")
    parser.add_argument(
        "--sim-config", metavar="FILE.json5", help="default: services/defaults/simulator.json5"
    )
    parser.add_argument(
        "--gateway-only",
        action="store_true",
        help="raw: publish only the gateways' raw chunks and GPS fixes (no TRC, no tamping)",
    )
    parser.add_argument("--no-progress", action="store_true")
    parser.add_argument(
        "--linger",
        type=float,
        default=0.0,
        metavar="S",
        help="stay up S seconds after the last message, serving its outbox to consumers "
        "that come back (default %(default)g)",
    )
    add_zenoh_arguments(parser)


# The flags of `trackfusion simulate` named after main_simulate's keywords.
SIMULATE_FLAGS = ("trains", "days", "speedup", "fidelity", "seed", "units", "from_day", "to_day")


def simulate_run(args: argparse.Namespace) -> int:
    try:
        start_t = datetime.fromisoformat(args.start).timestamp()
    except ValueError:
        raise ValueError(f"--start {args.start!r}: not an ISO date, e.g. 2026-01-01") from None
    return run_command(
        args,
        main_simulate,
        **flag_values(args, SIMULATE_FLAGS),
        network_path=args.network,
        start_t=start_t,
        truth_path=args.truth,
        config_path=args.sim_config,
        progress=not args.no_progress and sys.stderr.isatty(),
        linger_s=args.linger,
        gateway_only=args.gateway_only,
    )


def network_generate_add_arguments(parser: argparse.ArgumentParser) -> None:
    """``trackfusion network generate``."""
    parser.add_argument("--lines", type=int, default=40)
    parser.add_argument("--length-km", type=float, default=50.0)
    parser.add_argument("--segment-m", type=float, default=200.0)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--out", metavar="FILE.geojson", help="default: stdout")


def network_generate_run(args: argparse.Namespace) -> int:
    flags = flag_values(args, ("lines", "length_km", "seed", "out"))
    return main_network_generate(**flags, segment_length_m=args.segment_m)
