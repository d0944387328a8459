"""Accuracy of the signal chain on simulated raw data of the demo network.

Simulates trains with the full bogie physics (``simulators.train``, ``simulators.bogie``)
on ``services/defaults/demo-network.geojson`` with the profiles scaled to the true state, runs a
minimal stand-in for ingestion (supply-voltage correction ``5.0 / V``, g -> m/s^2, knots
at each chunk's ends from the train's true position), extracts on-board indices with
:class:`services.extraction.pipeline.Extractor` and compares them with the truth (the
segment statistic of the profile the TRC would measure: ``exp(z)`` at the pass time):

* log-space Pearson correlation of on-board vs true, per indicator;
* ``H, b, R`` fitted by :func:`services.calibration.regression.fit_observation`;
* the fraction of segment passes that yield an index, and the skip counters.

Run: ``.venv/bin/python -m bench.extraction_accuracy [--trains 9] [--seconds 2400]``.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from schemas import ACCEL_CHANNELS, NDArray, OnboardIndex, PositionedChunk
from services.calibration.regression import fit_observation
from services.defaults import demo_network
from services.extraction.pipeline import Extractor
from simulators.profile import LineProfile
from simulators.train import TrainSimulator
from simulators.truth import Truth, load_config
from track.network import Network
from track.segments import SegmentTable

G_MPS2 = 9.80665
START_T = 1_767_225_600.0  # 2026-01-01


class Route:
    """A line as the train simulator sees it, without stops closer than 50 m to a terminus.

    Works around a simulator issue: a station within one profile step (1 m) of a terminus
    (the demo's L3 has one at 15059 m of 15059.99 m) gives two adjacent stops and a route
    cycle of 2e9 s (``dt = 2 dx / max(v_i + v_i+1, 1e-9)`` in ``simulators/train.py``).
    """

    def __init__(self, line) -> None:
        self.id, self.length_m, self.tunnels = line.id, line.length_m, line.tunnels
        self.line_speed_mps, self.lonlat_at = line.line_speed_mps, line.lonlat_at
        self.stations = [c for c in line.stations if 50.0 < c < line.length_m - 50.0]


def mini_ingestion(train: TrainSimulator, seq: int, line: str, gap: bool):
    """One PositionedChunk of unit 0 the way ingestion would make it (true position)."""
    t0, raw, dropped = train.chunk(seq)
    if dropped:
        return None
    acc = raw[:, :6] * (5.0 / raw[:, 6:7]) * np.float32(G_MPS2)
    kt = np.array([t0, t0 + raw.shape[0] / train.fs_hz])
    chain, speed, _, _ = train.position(kt)
    return PositionedChunk(
        train=train.train_id,
        unit="u0",
        seq=seq,
        t0=t0,
        rate_hz=train.fs_hz,
        channels=list(ACCEL_CHANNELS),
        samples=NDArray.of(acc, "f4"),
        line=line,
        knot_t=NDArray.of(kt),
        knot_chainage_m=NDArray.of(chain),
        knot_speed_mps=NDArray.of(speed),
        position_ok=True,
        gap_before=gap,
    )


def simulate(network: Network, trains: int, seconds: int, seed: int = 1):
    """Indices, their true z and the extractor's counters."""
    truth = Truth(network, load_config(), START_T, seed)
    lines = list(network.lines.values())
    profiles = {}
    for line in lines:
        profile = LineProfile(line.id, [(s.start_m, s.end_m) for s in line.segments], seed)
        rows = truth.line_slices[line.id]
        profile.update(truth.z[rows], truth.epoch[rows])
        profiles[line.id] = profile
    sims = [
        TrainSimulator(
            f"T{i:03d}",
            Route(lines[i % len(lines)]),
            profiles[lines[i % len(lines)].id],
            seed,
            start_t=START_T,
        )  # fmt: skip
        for i in range(trains)
    ]
    extractor = Extractor(SegmentTable.from_network(network))
    position = {key: i for i, key in enumerate(truth.keys)}
    indices: list[OnboardIndex] = []
    gap = dict.fromkeys(range(trains), False)
    for k in range(seconds):
        for i, sim in enumerate(sims):
            chunk = mini_ingestion(sim, k, sim.line.id, gap[i])
            if chunk is None:
                gap[i] = True
                continue
            gap[i] = False
            indices += extractor.process(chunk)
    z_true = truth.z[[position[(ix.line, ix.segment)] for ix in indices]]
    return indices, z_true, extractor.counters()


def report(indices: list[OnboardIndex], z_true: np.ndarray, counters) -> dict:
    y = np.log([[ix.top6_mm, ix.align10_mm] for ix in indices])
    corr = [float(np.corrcoef(z_true[:, i], y[:, i])[0, 1]) for i in range(2)]
    fit = fit_observation(z_true, y)
    speeds = np.array([ix.speed_mps for ix in indices])
    return {
        "passes": counters.passes,
        "indexed": counters.passes_indexed,
        "fraction_indexed": counters.passes_indexed / max(1, counters.passes),
        "counters": counters.as_dict(),
        "corr_log": corr,
        "H": fit.H,
        "b": fit.b,
        "R": fit.R,
        "r2": fit.r2,
        "resid_std": fit.resid_std,
        "speed_range": (float(speeds.min()), float(speeds.max())) if speeds.size else None,
    }


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--trains", type=int, default=9)
    parser.add_argument("--seconds", type=int, default=2400, help="simulated seconds")
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args(argv)
    network = demo_network()
    start = time.perf_counter()
    indices, z_true, counters = simulate(network, args.trains, args.seconds, args.seed)
    elapsed = time.perf_counter() - start
    out = report(indices, z_true, counters)
    np.set_printoptions(precision=3, suppress=True)
    print(
        f"extraction accuracy: {args.trains} trains x {args.seconds} s on the demo network "
        f"({elapsed:.0f} s wall)"
    )
    print(
        f"  passes {out['passes']}, indexed {out['indexed']} "
        f"({100 * out['fraction_indexed']:.1f} %); counters {out['counters']}"
    )
    print(f"  log-space correlation on-board vs true: Top6 {out['corr_log'][0]:.3f}, "
          f"Align10 {out['corr_log'][1]:.3f}")  # fmt: skip
    print(f"  H = {out['H'].tolist()}")
    print(f"  b = {out['b'].tolist()}")
    print(f"  R = {out['R'].tolist()}")
    print(f"  r2 = {out['r2'].tolist()}, residual sd = {out['resid_std'].tolist()}")
    return out


if __name__ == "__main__":
    main()
