"""When the extraction publishes a segment's index: as soon as the unit's samples reach the
last chord of the statistic, 1 m (END_GUARD_M) short of the segment's end (plus one grid
step and the decimation FIR's 10 ms), and no later, whatever the chunking."""

from __future__ import annotations

from functools import cache

import numpy as np
import pytest

from schemas import ACCEL_CHANNELS, NDArray, PositionedChunk
from services.extraction.pipeline import ExtractionConfig, UnitPipeline
from track.segments import LineSegments, SegmentTable
from track.versine import END_GUARD_M

FS = 2000
EPOCH = 1_767_225_600.0  # 2026-01-01: event times must lie in the schemas' window
G = 9.80665
V = 20.0  # m/s
X0 = 2.0  # chainage at t = 0
SECONDS = 58


def accelerations(t: np.ndarray) -> np.ndarray:
    """A unit at V over sinusoidal vertical and lateral profiles (4 m and 7 m)."""
    x = X0 + V * t
    s = np.zeros((t.size, 6))
    for lam, amp, col in ((4.0, 1e-3, (0, 3)), (7.0, 1.5e-3, (1, 4))):
        w = 2 * np.pi / lam
        s[:, col] += (-amp * (w * V) ** 2 * np.sin(w * x))[:, None]
    s[:, [0, 3]] += G
    return s


def pieces(bounds_s: np.ndarray) -> list[PositionedChunk]:
    """The run cut at ``bounds_s`` (seconds, multiples of 1 / FS)."""
    out = []
    for seq, (a, b) in enumerate(zip(bounds_s[:-1], bounds_s[1:], strict=True)):
        n = round((b - a) * FS)
        t = a + np.arange(n) / FS
        kt = np.array([a, b])
        out.append(
            PositionedChunk(
                train="T1",
                unit="u0",
                seq=seq,
                t0=EPOCH + float(a),
                rate_hz=float(FS),
                channels=list(ACCEL_CHANNELS),
                samples=NDArray.of(accelerations(t), "f4"),
                line="L1",
                knot_t=NDArray.of(EPOCH + kt),
                knot_chainage_m=NDArray.of(X0 + V * kt),
                knot_speed_mps=NDArray.of([V, V]),
                position_ok=True,
            )
        )
    return out


def table() -> SegmentTable:
    starts = np.arange(6) * 200.0
    ids = tuple(f"s{i:05d}" for i in range(6))
    return SegmentTable({"L1": LineSegments("L1", ids, starts, starts + 200.0)})


def emitted(chunks: list[PositionedChunk]) -> dict[str, tuple[float, float, float]]:
    """segment -> (end time of the chunk that emitted its index, Top6, Align10)."""
    p = UnitPipeline("T1", "u0", table())
    out = {}
    for c in chunks:
        for ix in p.process(c):
            t_end = round(c.t0 - EPOCH + c.samples.shape[0] / FS, 6)  # relative, to the µs
            out[ix.segment] = (t_end, ix.top6_mm, ix.align10_mm)
    return out


@cache
def fine_run() -> dict[str, tuple[float, float, float]]:
    """:func:`emitted` for the run cut in 20 ms pieces (both tests read it; computed once)."""
    return emitted(pieces(np.arange(0, SECONDS * FS + 1, 40) / FS))


def test_an_index_is_published_once_the_unit_reaches_the_segment_end():
    fine = fine_run()
    assert {"s00001", "s00002", "s00003", "s00004"} <= set(fine)  # (s00000: settling)
    fir_delay = (ExtractionConfig().fir_taps - 1) / 2 / FS
    for seg, (t_emit, _, _) in fine.items():
        end = 200.0 * (int(seg[1:]) + 1)
        # where the unit was at the last output sample of the piece that emitted it
        past = X0 + V * (t_emit - 1 / FS - fir_delay) - end
        assert -END_GUARD_M <= past < -END_GUARD_M + V * 0.02 + 0.25, seg
        assert past < 0  # before the unit reaches the end: never the chunk after it


def test_one_second_chunks_publish_with_the_chunk_holding_that_sample():
    fine = fine_run()
    coarse = emitted(pieces(np.arange(0, SECONDS + 1, 1.0)))
    assert set(coarse) == set(fine)
    for seg, (t_emit, top, align) in coarse.items():
        assert t_emit == np.ceil(fine[seg][0])  # the 1 s chunk that holds the sample
        assert top == pytest.approx(fine[seg][1], rel=1e-6)
        assert align == pytest.approx(fine[seg][2], rel=1e-6)
