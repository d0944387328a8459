"""Model versions the calibration service publishes on the demo.

Runs the demo world of ``services/defaults/stack.json5`` (the demo network, fast mode
``fidelity="index"``, 4 service passes per line and day, seed 1, one year from 2026-01-01)
through the :class:`~services.calibration.calibrator.Calibrator` core in process, started
from ``services/defaults/initial-models.json5`` with the service's default settings, and counts the
models :meth:`Calibrator.flush` returns (what the service publishes, and what makes the
filtering service re-run its segments) per simulated calendar month.

The service flushes once per batch of queued samples (at most 512); a worker that keeps
up sees small batches. ``--flush tick`` (default) flushes after every instant of the world
stream (the messages sharing one timestamp): the most often the service could flush, so an
upper bound of what it publishes; ``--flush N`` flushes every N messages; ``--flush day`` at
the first event of each simulated day (as ``bench/correctness.py`` does).

Run: ``.venv/bin/python -m bench.calibration_versions [--days D] [--flush tick|N] [--json]``.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from collections import Counter
from datetime import UTC, datetime
from pathlib import Path

from schemas import DAY_S, Calibration
from services.calibration.calibrator import Calibrator
from services.calibration.config import CalibratorConfig
from services.calibration.service import load_initial_models
from services.defaults import default_file, demo_network
from simulators.truth import load_config
from simulators.world import WorldSpec, world_events

START_T = 1_767_225_600.0  # 2026-01-01T00:00Z, the simulator's default start
ROOT = Path(__file__).resolve().parents[1]
INITIAL_MODELS = default_file("initial-models.json5")


def month_of(t: float) -> str:
    return datetime.fromtimestamp(t, UTC).strftime("%Y-%m")


def run(
    days: float = 365.0, flush: str = "tick", trains: int = 4, seed: int = 1
) -> dict[str, object]:
    """Versions published per month: ``{"calibration": {month: n}, "posterior": {...}}``."""
    config = CalibratorConfig()
    core = Calibrator(config)
    cal0, posts0 = load_initial_models(INITIAL_MODELS, config)
    core.install_initial(cal0, posts0)
    spec = WorldSpec(demo_network(), load_config(), START_T, days, seed, trains, fidelity="index")
    every = None if flush in ("tick", "day") else int(flush)
    day = -1
    counts: dict[str, Counter[str]] = {"calibration": Counter(), "posterior": Counter()}
    groups: Counter[str] = Counter()
    n_flush = n_msgs = 0
    wall = time.perf_counter()

    def do_flush(t: float) -> None:
        nonlocal n_flush
        n_flush += 1
        for m in core.flush():
            kind = "calibration" if isinstance(m, Calibration) else "posterior"
            counts[kind][month_of(t)] += 1
            if kind == "posterior":
                groups[m.group.split(".")[0]] += 1

    t = START_T
    for t, msgs in world_events(spec):
        if flush == "day" and (d := int((t - START_T) // DAY_S)) != day:
            day = d
            do_flush(t)
        for msg in msgs:
            core.ingest(msg)
            n_msgs += 1
            if every is not None and n_msgs % every == 0:
                do_flush(t)
        if flush == "tick":
            do_flush(t)
    do_flush(t)
    months = sorted(
        {month_of(START_T + d * DAY_S) for d in range(math.ceil(days))}
        | set(counts["calibration"])
        | set(counts["posterior"])
    )
    return {
        "days": days,
        "flush": flush,
        "months": months,
        "calibration": {m: counts["calibration"][m] for m in months},
        "posterior": {m: counts["posterior"][m] for m in months},
        "posterior_by_kind": dict(groups),
        "final": {
            "calibration_version": core.calibration.version if core.calibration else None,
            "posterior_versions": {g: p.version for g, p in core.posteriors.items()},
        },
        "stats": dict(core.stats),
        "flushes": n_flush,
        "messages": n_msgs,
        "wall_s": time.perf_counter() - wall,
    }


def table(res: dict) -> str:
    months = res["months"]
    cal, post = res["calibration"], res["posterior"]
    lines = [
        f"model versions published per simulated month (demo world, {res['days']:g} days, "
        f"flush every {res['flush']})",
        f"{'month':<8}  {'Calibration':>11}  {'posteriors':>10}",
    ]
    for m in months:
        lines.append(f"{m:<8}  {cal[m]:>11}  {post[m]:>10}")
    n_cal, n_post = sum(cal.values()), sum(post.values())
    lines.append(f"{'total':<8}  {n_cal:>11}  {n_post:>10}")
    lines.append(
        f"posterior versions by group kind: {res['posterior_by_kind']}; "
        f"{res['flushes']} flushes, {res['messages']} messages, {res['wall_s']:.1f} s wall"
    )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--days", type=float, default=365.0)
    p.add_argument("--flush", default="tick", help="tick (default), day, or every N messages")
    p.add_argument("--trains", type=int, default=4, help="service passes per line and day (4)")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--json", action="store_true")
    a = p.parse_args(argv)
    res = run(a.days, a.flush, a.trains, a.seed)
    print(json.dumps(res, indent=1) if a.json else table(res))
    return 0


if __name__ == "__main__":
    sys.exit(main())
