"""Simulator benchmarks: raw-signal generation speed (target >= 200 trains/core).

``bench_raw_generation`` is called by ``bench/__main__.py``; run alone with
``python -m bench.simulator``.
"""

from __future__ import annotations

import math
import time

import numpy as np

from simulators.profile import LineProfile
from simulators.train import TrainSimulator

TARGET_TRAINS = 200  # trains simulated in real time per core


class _StraightLine:
    """A 20 km straight stand-in line with stations every 5 km and one tunnel."""

    length_m = 20_000.0
    stations = [0.0, 5_000.0, 10_000.0, 15_000.0, 20_000.0]
    line_speed_mps = 30.0
    tunnels = [(7_000.0, 7_800.0)]

    def lonlat_at(self, chainage: float) -> tuple[float, float]:
        lat = -27.5
        return 153.0 + math.degrees(chainage / (6_371_000.0 * math.cos(math.radians(lat)))), lat


def bench_raw_generation(trains: int = 20, seconds: int = 30, seed: int = 1) -> float:
    """Generate ``seconds`` of 1 s raw chunks (one unit, 2000 Hz x 7) and 1 Hz GPS fixes
    for ``trains`` trains in this process; print and return trains in real time per core
    (``simulated seconds * trains / wall seconds``)."""
    line = _StraightLine()
    n_seg = int(line.length_m // 200)
    bounds = np.c_[np.arange(n_seg) * 200.0, np.arange(1, n_seg + 1) * 200.0]
    profile = LineProfile("bench", bounds, seed)
    rng = np.random.default_rng(seed)
    profile.update(rng.normal([0.7, 0.4], 0.3, (n_seg, 2)), np.zeros(n_seg, dtype=int))
    sims = [TrainSimulator(f"T{i}", line, profile, seed) for i in range(trains)]
    for sim in sims:  # warm-up: first-call costs (filter design is in the constructor)
        sim.chunk(0)
    start = time.perf_counter()
    samples = 0
    for seq in range(1, seconds + 1):
        for sim in sims:
            t0, x, _ = sim.chunk(seq)
            sim.gps_fixes(t0, t0 + 1.0)
            samples += x.shape[0]
    wall = time.perf_counter() - start
    rate = trains * seconds / wall
    print(
        f"raw generation  {trains} trains x {seconds} s, 1 unit each (2000 Hz x 7 ch) + 1 Hz "
        f"GPS: {wall:.2f} s wall = {rate:.0f} trains in real time per core "
        f"({samples * 7 / wall / 1e6:.1f} M values/s); ratio to target {rate / TARGET_TRAINS:.2f} "
        f"(target >= {TARGET_TRAINS})"
    )
    return rate


if __name__ == "__main__":
    bench_raw_generation()
