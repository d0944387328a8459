"""Raw samples per second per core through the extraction core, and per-chunk latency.

Workload: 120 s of realistic 1 s PositionedChunks (simulated bogie physics on a 3 km
stand-in line, supply-corrected, knots from the true position) replayed through
``UNITS`` independent :class:`~services.extraction.pipeline.UnitPipeline` instances in
round robin (as a service sees many trains), in-process, one thread. Raw samples count
every accelerometer value (rows x 6 channels), like the 12 M/s target
(1,000 trains x 2,000 Hz x 6). Baselines measured in the same run: the target, and
``scipy.signal.sosfiltfilt`` (order-4 Butterworth band-pass at 2000 Hz, zero-phase, one
block) over the same samples, i.e. the textbook offline processing without decimation.

Run: ``.venv/bin/python -m bench.extraction``.
"""

from __future__ import annotations

import time

import numpy as np
from scipy import signal

from schemas import PositionedChunk
from services.extraction.pipeline import UnitPipeline
from services.extraction.testing import line_table, positioned_chunk
from simulators.profile import LineProfile
from simulators.train import TrainSimulator
from track.segments import SegmentTable

TARGET = 12e6  # raw samples / s / core, ingestion + extraction together (docs/performance.md)
UNITS, SECONDS, REPEATS = 16, 120, 2
G_MPS2 = 9.80665
EPOCH = 1_767_225_600.0  # 2026-01-01: event times must lie in the schemas' window


class _StandIn:
    id, length_m, stations, tunnels, line_speed_mps = "L1", 3000.0, [], [], 25.0

    def lonlat_at(self, chainage):
        return np.stack([153.0 + np.asarray(chainage) * 1e-5, np.full_like(chainage, -27.0)], -1)


def make_chunks(seconds: int = SECONDS) -> tuple[list[PositionedChunk], SegmentTable]:
    bounds = np.stack([np.arange(15) * 200.0, np.arange(1, 16) * 200.0], 1)
    profile = LineProfile("L1", bounds, seed=3)
    profile.update(np.log(np.random.default_rng(3).uniform(1, 4, (15, 2))), np.zeros(15, int))
    sim = TrainSimulator("T1", _StandIn(), profile, seed=3, start_t=EPOCH + 1000.0, phase_s=0.0)
    chunks = []
    for k in range(seconds):
        t0, raw, _ = sim.chunk(k)
        acc = raw[:, :6] * (5.0 / raw[:, 6:7]) * np.float32(G_MPS2)
        kt = np.array([t0, t0 + 1.0])
        c, v, _, _ = sim.position(kt)
        chunks.append(positioned_chunk(acc, t0, kt, c, v, seq=k))
    return chunks, line_table(15)


def bench_extraction() -> dict:
    chunks, table = make_chunks()
    rows = sum(c.samples.shape[0] for c in chunks)
    best = np.inf
    latencies: list[float] = []
    indexed = 0
    for _ in range(REPEATS):
        pipelines = [UnitPipeline("T1", f"u{u}", table) for u in range(UNITS)]
        start = time.perf_counter()
        for c in chunks:
            for p in pipelines:
                t = time.perf_counter()
                p.process(c)
                latencies.append(time.perf_counter() - t)
        best = min(best, time.perf_counter() - start)
        indexed = pipelines[0].counters.passes_indexed
    raw = rows * UNITS * 6
    rate = raw / best
    p50, p99 = np.percentile(latencies, [50, 99]) * 1e3

    block = np.concatenate([c.samples.array() for c in chunks]).astype(np.float64)
    sos = signal.butter(4, [0.8, 40.0], btype="bandpass", fs=2000.0, output="sos")
    start = time.perf_counter()
    for _ in range(UNITS):
        signal.sosfiltfilt(sos, block, axis=0)
    base = time.perf_counter() - start
    base_rate = raw / base
    print(
        f"extraction core  {UNITS} units x {SECONDS} x 1 s chunks (2000 Hz x 6 channels): "
        f"{rate / 1e6:.1f} M raw samples/s/core ({rate / 12e3:.0f} trains in real time); "
        f"ratio to the 12 M target {rate / TARGET:.2f}x; sosfiltfilt baseline "
        f"{base_rate / 1e6:.1f} M/s, ratio {rate / base_rate:.2f}x; per chunk p50 {p50:.3f} ms, "
        f"p99 {p99:.3f} ms; {indexed} passes indexed per unit"
    )
    return {"rate": rate, "base_rate": base_rate, "p50_ms": p50, "p99_ms": p99}


def main() -> None:
    bench_extraction()


if __name__ == "__main__":
    main()
