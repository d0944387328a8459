"""Ingestion core throughput: raw samples per second per core, and per-chunk latency.

Realistic input: ``TRAINS`` simulated trains on the demo network's lines (bogie physics,
2000 Hz x 7 channels, 1 s chunks) and their 1 Hz GPS fixes, packed with plain ``msgpack``
as a gateway would (``simulators.gateway.key_and_payload``), generated before the clock
starts. Measured, in this process: decode (``schemas.decode``) + validate + health +
supply correction + map matching + encode of every PositionedChunk, i.e. what one
ingestion worker does per payload minus Zenoh.

A raw sample is one value of one accelerometer channel (a 1 s chunk is 2000 x 6), the
unit of the target: >= 12 M raw samples/s per core through ingestion AND extraction
together, so ingestion alone has to be well above it. Baseline in the same run: msgspec
decode + encode of the same payloads with nothing done in between (the floor a worker
cannot beat), so the ratio is what the work itself costs.

Run: ``.venv/bin/python -m bench.ingestion``.
"""

from __future__ import annotations

import time

import numpy as np

from schemas import GpsFix, PositionedChunk, RawChunk, decode, encode
from services.defaults import demo_network
from services.ingestion.core import IngestionCore
from simulators.gateway import key_and_payload
from simulators.profile import LineProfile
from simulators.train import TrainSimulator

TARGET_SAMPLES_PER_S = 12e6  # ingestion + extraction, per core (docs/performance.md)
T0 = 1_767_225_600.0


def make_payloads(trains: int, seconds: int, seed: int = 1) -> list[tuple[str, bytes]]:
    """``(kind, payload)`` in publishing order: per second, every train's chunk and fix."""
    network = demo_network()
    lines = list(network.lines.values())
    profiles = {
        line.id: LineProfile(line.id, [(s.start_m, s.end_m) for s in line.segments], seed)
        for line in lines
    }
    rng = np.random.default_rng(seed)
    for line in lines:
        n = len(line.segments)
        profiles[line.id].update(rng.normal([0.7, 0.4], 0.3, (n, 2)), np.zeros(n, dtype=int))
    sims = [
        TrainSimulator(
            f"T{i:03d}",
            lines[i % len(lines)],
            profiles[lines[i % len(lines)].id],
            seed,
            start_t=T0,
        )  # fmt: skip
        for i in range(trains)
    ]
    out: list[tuple[str, bytes]] = []
    for k in range(seconds):
        for sim in sims:
            chunk = sim.raw_chunk(k)[0]
            out.append(("raw", key_and_payload("tf", chunk)[1]))
            for fix in sim.gps_fixes(chunk.t0, chunk.t0 + 1.0):
                out.append(("gps", key_and_payload("tf", fix)[1]))
    return out


def run_core(payloads: list[tuple[str, bytes]]) -> tuple[float, dict, int, int]:
    """Through a fresh core: ``(wall s, latencies s by payload kind, chunks out, samples)``.

    A chunk's work is split: its RawChunk payload is decoded, validated and corrected on
    arrival; it is positioned and encoded when the GPS fix after it arrives.
    """
    core = IngestionCore(demo_network())
    latencies: dict[str, list[float]] = {"raw": [], "gps": []}
    published = samples = 0
    start = time.perf_counter()
    for kind, payload in payloads:
        t = time.perf_counter()
        message = decode(payload, RawChunk if kind == "raw" else GpsFix)
        for out in core.step(message):
            if isinstance(out, PositionedChunk):
                encode(out)
                published += 1
                samples += out.samples.shape[0] * 6
        latencies[kind].append(time.perf_counter() - t)
    for out in core.flush():
        if isinstance(out, PositionedChunk):
            encode(out)
            published += 1
            samples += out.samples.shape[0] * 6
    return time.perf_counter() - start, latencies, published, samples


def run_baseline(payloads: list[tuple[str, bytes]]) -> float:
    """msgspec decode + encode of the same payloads, nothing in between."""
    start = time.perf_counter()
    for kind, payload in payloads:
        encode(decode(payload, RawChunk if kind == "raw" else GpsFix))
    return time.perf_counter() - start


def bench_ingestion(trains: int = 12, seconds: int = 30) -> float:
    """Print and return raw samples/s per core through the ingestion core."""
    payloads = make_payloads(trains, seconds)
    run_core(payloads[: 4 * trains])  # warm-up
    wall, latencies, published, samples = run_core(payloads)
    base = run_baseline(payloads)
    rate = samples / wall
    base_rate = samples / base
    r50, r99 = np.percentile(latencies["raw"], [50, 99]) * 1e3
    g50, g99 = np.percentile(latencies["gps"], [50, 99]) * 1e3
    print(
        f"ingestion  {trains} trains x {seconds} s (2000 Hz x 6 accel + supply, 1 s chunks, "
        f"1 Hz GPS), decode + validate + correct + position + encode: "
        f"{rate / 1e6:.1f} M raw samples/s per core ({published} chunks); latency per "
        f"RawChunk payload p50 {r50:.3f} ms, p99 {r99:.3f} ms, per GpsFix payload (positions "
        f"and encodes the chunks it releases) p50 {g50:.3f} ms, p99 {g99:.3f} ms; baseline "
        f"msgspec decode+encode only {base_rate / 1e6:.1f} M/s, ratio {rate / base_rate:.2f}; "
        f"ratio to the ingestion+extraction target {rate / TARGET_SAMPLES_PER_S:.1f}x "
        f"(target {TARGET_SAMPLES_PER_S / 1e6:.0f} M/s for both together)"
    )
    return rate


if __name__ == "__main__":
    bench_ingestion()
