"""Test doubles that ship with the extraction service: a line of equal segments and the
positioned chunks of one on-board unit."""

from __future__ import annotations

import numpy as np

from schemas import ACCEL_CHANNELS, NDArray, PositionedChunk
from track.segments import LineSegments, SegmentTable

RATE_HZ = 2000.0  # the reference unit's sampling rate


def line_table(n_segments: int, length_m: float = 200.0) -> SegmentTable:
    """Line ``L1``: ``n_segments`` segments ``s00000``, ``s00001``, … of ``length_m`` each,
    the first starting at chainage 0."""
    starts = np.arange(n_segments) * length_m
    ids = tuple(f"s{i:05d}" for i in range(n_segments))
    return SegmentTable({"L1": LineSegments("L1", ids, starts, starts + length_m)})


def positioned_chunk(samples, t0, knot_t, knot_c, knot_v, seq=0, **fields) -> PositionedChunk:
    """A chunk of unit ``u0`` of train ``T1`` on line ``L1`` at ``RATE_HZ``: the accelerations
    ``samples`` (n, 6) in m/s², the knots (time, chainage, speed); ``fields``: the other
    fields of a PositionedChunk (``position_ok`` True unless given)."""
    return PositionedChunk(
        train="T1",
        unit="u0",
        seq=seq,
        t0=float(t0),
        rate_hz=RATE_HZ,
        channels=list(ACCEL_CHANNELS),
        samples=NDArray.of(samples, "f4"),
        line="L1",
        knot_t=NDArray.of(knot_t),
        knot_chainage_m=NDArray.of(knot_c),
        knot_speed_mps=NDArray.of(knot_v),
        position_ok=fields.pop("position_ok", True),
        **fields,
    )
