"""Ingestion core: RawChunk + GpsFix in, PositionedChunk + rejections out. Pure.

No Zenoh, no clock, no I/O: time is the data's event time. The adapter
(``services/ingestion/service.py``) feeds one ordered stream of decoded messages through
:meth:`IngestionCore.step` and publishes what comes out; tests do the same with lists.

The chain, per message:

1. **Validation** beyond the schema (:func:`inspect_chunk`): the channel set holds the six
   accelerometer channels and ``supply_v``; the sample rate is within ``rate_tolerance`` of
   the unit's expected rate; the samples are floats (an integer dtype carries no scale on
   the wire: refused); ``t0`` is in the valid time range; every value is finite; the
   accelerations are in g (:func:`vertical_unit_reason`: a vertical channel's mean is
   gravity, so a mean beyond ``vertical_max_g`` is m/s² at ≈ 9.81, or counts); the supply
   voltage is plausible (``supply_min_v``..``supply_max_v``). A failure is a
   :class:`Rejection` with a reason.

   **The train's clock.** Event time is the gateway's, so one wrong time must not become
   "now". A fix's ``t`` and a chunk's ``t0`` outside ``[valid_t_min, valid_t_max)``
   (2000..2100) are refused. A fix or chunk more than ``max_ahead_s`` (300 s) ahead of the
   train's last accepted fix *and* of the fleet's clock (the median of the other trains'
   last fixes; when there are none, of the train's alone) is refused as a clock jump, as is
   a fix more than ``max_ahead_s`` behind the train's last fix: neither moves the train's
   event time, its reorder windows or its knot horizon. A train whose gateway clock really
   moved is **re-based**: ``rebase_fixes`` (5) consecutive refused fixes, each 0 <
   Δt <= ``rebase_gap_s`` (10 s) after the one before, make the last of them the train's
   new timeline (what is held is released first; the units' sequencing starts over with
   ``gap_before``; a warning is logged; :attr:`TrainStats.rebases`). A fix far behind the
   train that agrees with the fleet's clock re-bases it at once (a train whose timeline
   was wrong). One fix on the train's timeline ends a run of refused fixes, so a single
   outlier, or outliers among good fixes, never re-base anything.
2. **Sequencing** per (train, unit) (:func:`step_unit`): ``t0`` must agree with ``seq``
   (``t0 ≈ t0_ref + (seq - seq_ref) * chunk duration`` within ``t0_tolerance_s``);
   duplicates (same seq) are dropped and counted, not dead-lettered (re-delivery is normal
   and harmless; the first copy wins); chunks are reordered within a window of
   ``reorder_chunks`` chunks or ``reorder_s`` of event time; when the window passes a missing
   seq, the next chunk carries ``gap_before``. A chunk arriving after its slot was declared
   missing is rejected as ``late``. A seq that jumps backwards while ``t0`` moves forwards
   is a restarted gateway counter: the unit starts over with ``gap_before``.
3. **Health and correction** (:func:`inspect_chunk`, vectorised over the chunk): clipping
   (any ``|a| >= clip_g``), flatline per channel (a share of exactly repeated consecutive
   values; a held non-zero value), dropout per channel (the same, stuck at exactly 0),
   supply deviation from 5.0 V; then the ratiometric correction
   ``a_mps2 = a_g * (supply_nominal_v / V) * 9.80665`` per sample.
4. **Positioning** per train (:func:`step_train`): every fix with ``fix_quality > 0`` is
   projected onto the network lines and becomes a knot ``(t, line, chainage, speed, ok)``;
   fixes without a position (tunnels) become dead-reckoned knots (last speed, direction of
   travel), trusted for ``dead_reckon_s`` after the last good fix. A chunk goes out as soon
   as its samples can be positioned: between knots by interpolation and, past the last
   knot, by dead reckoning from it (its speed and the acceleration between the last two
   knots, stopping at 0) when its last sample is at most ``extrapolate_s`` (2 s) past that
   knot and the train's direction is known (or it stands still). GPS is 1 Hz and a gateway
   sends a ~1 s chunk at its end, so the fix after a chunk's last sample is usually not
   there yet; waiting for it cost about a second per chunk, longer through outages. A
   chunk farther from the last knot (an outage without heartbeat fixes, a train starting
   off) is held until a knot at or after its last sample exists (at most ``max_hold_s`` of
   the train's event time), as with ``extrapolate_s = 0`` every chunk is.

   The knots a chunk goes out with are the **published track** (:func:`_publish_track`):
   what went out is never revised, so every chunk of a train (and of each of its units)
   continues the previous one. When a later fix moves the track away from a dead-reckoned
   position, the correction (usually well under a metre: the fused knots take in 0.3 of
   the GPS error) is spread linearly over ``correction_s``; one larger than
   ``correction_ok_m`` (a stop inside a tunnel, a reversal at a terminus found 12 m late)
   is jumped, as the fix knots themselves jump, and marked poor for ``correction_s``.

Map matching keeps **continuity**: a train stays on its line while the fixes are within
``switch_lateral_m`` of it; only ``switch_fixes`` consecutive fixes farther away, with
another line clearly fitting (within ``acquire_m``, ``ambiguity_m`` closer than any other),
move it. Acquisition needs the same clear fit. Two lines 30 m apart (the demo's L1/L3) are
therefore never confused by a few metres of GPS error. Chainage is projected on a window of
the current line around the predicted position (no jumps to another part of a curving
line) and kept monotone in the direction of travel: a backwards step smaller than
``reverse_m`` (GPS jitter at a standstill) holds the previous chainage; a larger one is a
reversal (a terminus).

``position_ok`` is False when a bracketing knot is missing, any knot of the chunk is poor
(no fix and dead reckoning longer than ``dead_reckon_s`` after the last good fix, or past
the last knot longer than ``extrapolate_s``; hdop above ``hdop_max``; lateral offset above
``lateral_ok_m``; off the line while a switch is pending; within ``correction_s`` after a
correction larger than ``correction_ok_m``), knots are more than ``dead_reckon_s`` apart, or
the chunk straddles a line change (rare: the chunk then keeps only the knots on the new
line). :class:`TrainStats` counts the chunks ``extrapolated`` (a dead-reckoned tail) and
``held`` (waited for a knot) and the largest correction.

A chunk of a train that has never been matched to any line cannot be positioned: after
``max_hold_s`` it is rejected with reason ``unpositioned`` (a dead letter, so it is counted
and visible, never silently lost).
"""

from __future__ import annotations

import logging
import math
from bisect import bisect_left, bisect_right
from collections import deque
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field, fields, replace
from datetime import UTC, datetime
from typing import Any

import numpy as np

from schemas import ACCEL_CHANNELS, SUPPLY_CHANNEL, GpsFix, NDArray, PositionedChunk, RawChunk

log = logging.getLogger(__name__)

G_MPS2 = 9.80665
CHANNELS = list(ACCEL_CHANNELS)  # output columns (supply_v dropped after the correction)
_CANONICAL = [*ACCEL_CHANNELS, SUPPLY_CHANNEL]


@dataclass(frozen=True)
class IngestionConfig:
    """Thresholds of the ingestion core (``services.ingestion`` section of the config file)."""

    rate_hz: float = 2000.0  # expected sample rate of a unit
    rate_overrides: Mapping[str, float] = field(default_factory=dict)  # "train/unit" -> Hz
    rate_tolerance: float = 0.01  # relative
    supply_nominal_v: float = 5.0  # ratiometric reference
    supply_min_v: float = 2.5  # outside [min, max]: implausible, the chunk is rejected
    supply_max_v: float = 7.5
    supply_flag_deviation: float = 0.05  # relative deviation of any sample -> flag "supply"
    clip_g: float = 15.9  # |a| at or above: clipped (full scale 16 g)
    flat_fraction: float = 0.05  # share of repeated consecutive values -> flatline/dropout
    t0_tolerance_s: float = 0.05  # t0 against seq
    reorder_chunks: int = 5  # reorder window, chunks ...
    reorder_s: float = 5.0  # ... or event time past the missing chunk's start
    max_hold_s: float = 10.0  # longest wait for the GPS knot after a chunk
    dead_reckon_s: float = 3.0  # trust dead reckoning / knot spacing up to this
    # A chunk whose last sample is at most this far past the train's last knot goes out at
    # once, its tail dead-reckoned from that knot; 0: every chunk waits for a knot at or
    # after its last sample (up to max_hold_s), as before.
    extrapolate_s: float = 2.0
    extrapolate_accel_max_mps2: float = 1.5  # bound on the acceleration dead reckoning uses
    correction_s: float = 2.0  # a later fix's correction of a published position: spread
    correction_ok_m: float = 5.0  # larger: not spread but jumped, and marked poor for a while
    hdop_max: float = 5.0
    lateral_ok_m: float = 15.0  # a fix farther from its line is a poor match
    switch_lateral_m: float = 25.0  # "clearly off the current line"
    switch_fixes: int = 3  # consecutive fixes off the line before a switch
    acquire_m: float = 15.0  # a line "fits" within this lateral distance ...
    ambiguity_m: float = 10.0  # ... and this much closer than any other line
    reverse_m: float = 12.0  # backwards movement that means a reversal, not jitter
    fuse_gain: float = 0.3  # weight of the projection against the speed prediction
    fuse_gate_m: float = 20.0  # projections farther from the prediction are taken as is
    search_m: float = 300.0  # projection window around the predicted chainage
    knot_keep_s: float = 60.0  # knots kept behind the train's event time
    # Time plausibility ("the train's clock", module docstring): event times outside
    # [valid_t_min, valid_t_max) are refused; a fix or chunk more than max_ahead_s ahead of
    # the train's last fix and of the fleet's median is refused as a clock jump, and
    # rebase_fixes consecutive fixes at the new time (each within rebase_gap_s of the one
    # before) re-base the train there.
    valid_t_min: float = 946_684_800.0  # 2000-01-01T00:00:00Z
    valid_t_max: float = 4_102_444_800.0  # 2100-01-01T00:00:00Z
    max_ahead_s: float = 300.0
    rebase_fixes: int = 5
    rebase_gap_s: float = 10.0
    # Units: the mean of a vertical channel over a chunk is gravity, +1 g; beyond this many g
    # the samples are not in g (m/s^2 reads 9.81, counts read hundreds or thousands).
    vertical_max_g: float = 2.5

    @classmethod
    def from_dict(cls, raw: Mapping[str, Any]) -> IngestionConfig:
        names = {f.name for f in fields(cls)}
        unknown = set(raw) - names
        if unknown:
            raise ValueError(
                f"unknown ingestion settings {sorted(unknown)}; known: {sorted(names)}"
            )
        return cls(**raw)

    def expected_rate(self, train: str, unit: str) -> float:
        return float(self.rate_overrides.get(f"{train}/{unit}", self.rate_hz))


# --- outputs ---------------------------------------------------------------------------------


@dataclass(frozen=True)
class Rejection:
    """A message the core refuses; the adapter publishes it as a dead letter."""

    reason: str
    message: RawChunk | GpsFix


Output = PositionedChunk | Rejection


@dataclass
class UnitHealth:
    """Counters of one (train, unit); :meth:`IngestionCore.health` returns a copy."""

    chunks: int = 0  # accepted (validated) chunks
    samples: int = 0  # accepted sample rows
    published: int = 0  # PositionedChunks emitted
    rejected: int = 0  # validation / sequencing rejections
    duplicates: int = 0
    late: int = 0
    missing: int = 0  # seqs declared lost (gaps)
    restarts: int = 0  # seq counter restarts
    clipped_samples: int = 0  # values with |a| >= clip_g
    clipping_chunks: int = 0
    flatline_chunks: dict[str, int] = field(default_factory=dict)  # by channel
    dropout_chunks: dict[str, int] = field(default_factory=dict)  # by channel
    supply_chunks: int = 0  # chunks flagged "supply"
    supply_min_v: float = math.inf
    supply_max_v: float = -math.inf
    last_clip_fraction: float = 0.0
    last_flags: tuple[str, ...] = ()

    @property
    def clip_fraction(self) -> float:
        return self.clipped_samples / max(1, 6 * self.samples)


@dataclass
class TrainStats:
    """Positioning counters of one train."""

    fixes: int = 0
    no_fix: int = 0  # fix_quality 0
    matched: int = 0  # knots from a good match
    poor: int = 0  # knots marked not ok
    switches: int = 0  # line changes
    duplicates: int = 0
    unpositioned: int = 0
    extrapolated: int = 0  # chunks whose tail was dead-reckoned past the last knot
    held: int = 0  # chunks that had to wait for a knot (none close enough before them)
    max_correction_m: float = 0.0  # largest later correction of a dead-reckoned position
    clock_jumps: int = 0  # fixes and chunks refused as ahead of (or far behind) the clock
    rebases: int = 0  # times the train's clock was re-based to a new timeline


# --- chunk inspection (vectorised) ------------------------------------------------------------


@dataclass(frozen=True)
class Inspected:
    """A validated, corrected chunk waiting for its neighbours and its position."""

    raw: RawChunk
    samples: np.ndarray  # (n, 6) float32 m/s^2, supply-corrected, canonical order
    flags: tuple[str, ...]
    t_last: float  # epoch s of the last sample
    duration_s: float  # n / rate
    clipped: int
    supply_min_v: float
    supply_max_v: float


def _column_order(channels: list[str]) -> list[int] | None:
    if channels == _CANONICAL:
        return None  # the usual case: no gather
    where = {name: i for i, name in enumerate(channels)}
    return [where[name] for name in _CANONICAL]


def inspect_chunk(chunk: RawChunk, cfg: IngestionConfig) -> Inspected | str:
    """Validate, check health and correct one chunk; a string is the rejection reason.

    .. math::

        a_{m/s^2}[k] = a_g[k] \\cdot \\frac{V_{nominal}}{V[k]} \\cdot 9.80665

    (the sensor output is ratiometric: proportional to the supply voltage ``V[k]``).
    """
    missing = [c for c in _CANONICAL if c not in chunk.channels]
    if missing:
        return f"channels: missing {missing} (have {chunk.channels})"
    expected = cfg.expected_rate(chunk.train, chunk.unit)
    if abs(chunk.rate_hz - expected) > cfg.rate_tolerance * expected:
        return (
            f"rate_hz: {chunk.rate_hz:g} Hz outside {expected:g} Hz "
            f"± {cfg.rate_tolerance * 100:g} %"
        )
    if chunk.samples.dtype[0] != "f":
        return (
            f"samples: dtype {chunk.samples.dtype} is an integer type, whose scale the wire "
            "does not carry; send f4 (or f8) with accelerations in g and supply_v in V "
            "(counts × your sensor's g per count)"
        )
    a = chunk.samples.array()
    n = a.shape[0]
    if n < 2:
        return f"samples: {n} rows, need at least 2"
    bad = time_range_reason("t0", chunk.t0, cfg)
    if bad:
        return bad
    order = _column_order(chunk.channels)
    if order is not None:
        a = a[:, order]
    if a.dtype != np.float32:
        a = a.astype(np.float32)
    acc, volts = a[:, :6], a[:, 6]
    # Whole-array reductions over the contiguous block are several times faster than
    # per-column (axis=0) ones; NaN propagates through max/min, so they check finiteness.
    top, bottom = float(a.max()), float(a.min())
    if not (math.isfinite(top) and math.isfinite(bottom)):
        return "samples: contain NaN or inf"
    unit = vertical_unit_reason(acc, cfg)
    if unit:
        return unit
    vmin, vmax = float(volts.min()), float(volts.max())
    if vmin < cfg.supply_min_v or vmax > cfg.supply_max_v:
        return (
            f"supply_v: {vmin:.3f}..{vmax:.3f} V outside the plausible "
            f"{cfg.supply_min_v:g}..{cfg.supply_max_v:g} V"
        )
    flags: list[str] = []
    clipped = 0
    if top >= cfg.clip_g or bottom <= -cfg.clip_g:
        clipped = int(np.count_nonzero(np.abs(acc) >= cfg.clip_g))
        if clipped:
            flags.append("clipping")
    # flatline / dropout: exactly repeated consecutive values (MEMS noise makes them
    # practically impossible in a live float signal); per channel only when there are some
    same = a[1:] == a[:-1]
    limit = cfg.flat_fraction * (n - 1)
    if np.count_nonzero(same) - np.count_nonzero(same[:, 6]) >= limit:
        repeats = np.count_nonzero(same[:, :6], axis=0)
        for c in np.flatnonzero(repeats >= limit):
            # stuck at exactly zero is a dropout (signal lost); at any other value, a flatline
            if np.count_nonzero(acc[:, c] == 0.0) >= cfg.flat_fraction * n:
                flags.append(f"dropout:{ACCEL_CHANNELS[c]}")
            else:
                flags.append(f"flatline:{ACCEL_CHANNELS[c]}")
    nominal = cfg.supply_nominal_v
    if max(nominal - vmin, vmax - nominal) > cfg.supply_flag_deviation * nominal:
        flags.append("supply")
    scale = np.float32(nominal * G_MPS2) / volts
    samples = acc * scale[:, None]
    return Inspected(
        raw=chunk,
        samples=samples,
        flags=tuple(flags),
        t_last=chunk.t0 + (n - 1) / chunk.rate_hz,
        duration_s=n / chunk.rate_hz,
        clipped=clipped,
        supply_min_v=vmin,
        supply_max_v=vmax,
    )


def time_range_reason(name: str, t: float, cfg: IngestionConfig) -> str | None:
    """Why an event time is outside the valid range, or None."""
    if cfg.valid_t_min <= t < cfg.valid_t_max:
        return None
    return (
        f"{name}: {t:.3f} ({_iso(t)}) outside the valid time range "
        f"{_iso(cfg.valid_t_min)} .. {_iso(cfg.valid_t_max)} (UTC epoch seconds)"
    )


def vertical_unit_reason(acc: np.ndarray, cfg: IngestionConfig) -> str | None:
    """Why the accelerations are not in g, judged by gravity on the vertical channels.

    Over a chunk a vertical channel averages to gravity, +1 g (the bogie's vibration averages
    out). A mean beyond ``vertical_max_g`` on either of ``left_z``/``right_z`` is no
    acceleration in g: about 9.81 is m/s², anything larger counts or another scale.
    """
    means = acc[:, [0, 3]].mean(axis=0, dtype=np.float64)
    worst = float(means[np.argmax(np.abs(means))])
    if abs(worst) <= cfg.vertical_max_g:
        return None
    if abs(abs(worst) - G_MPS2) <= cfg.vertical_max_g:
        return (
            f"samples: vertical mean {worst:.2f} looks like m/s² (gravity reads ≈ 9.81); "
            f"send accelerations in g (m/s² ÷ {G_MPS2}): gravity must read ≈ +1"
        )
    return (
        f"samples: vertical mean {worst:.4g} is no acceleration in g (gravity must read ≈ +1, "
        f"at most ±{cfg.vertical_max_g:g}): raw counts or another scale? send f4 in g"
    )


def _iso(t: float) -> str:
    try:
        return datetime.fromtimestamp(t, UTC).strftime("%Y-%m-%dT%H:%M:%SZ")
    except (OverflowError, OSError, ValueError):
        return "beyond the calendar"


def _account(h: UnitHealth, item: Inspected) -> None:
    """Count an accepted chunk's samples and findings."""
    h.chunks += 1
    h.samples += item.samples.shape[0]
    if item.clipped:
        h.clipped_samples += item.clipped
        h.clipping_chunks += 1
    h.last_clip_fraction = item.clipped / item.samples.size
    for flag in item.flags:
        kind, _, channel = flag.partition(":")
        if kind == "flatline":
            h.flatline_chunks[channel] = h.flatline_chunks.get(channel, 0) + 1
        elif kind == "dropout":
            h.dropout_chunks[channel] = h.dropout_chunks.get(channel, 0) + 1
        elif kind == "supply":
            h.supply_chunks += 1
    h.supply_min_v = min(h.supply_min_v, item.supply_min_v)
    h.supply_max_v = max(h.supply_max_v, item.supply_max_v)
    h.last_flags = item.flags


# --- sequencing per (train, unit) ------------------------------------------------------------


@dataclass
class UnitState:
    """Reorder buffer and sequence bookkeeping of one (train, unit)."""

    health: UnitHealth = field(default_factory=UnitHealth)
    next_seq: int | None = None  # next seq to release; None before the first release
    last_t0: float = 0.0  # of the last released chunk
    last_duration: float = 0.0
    ref: tuple[int, float, float] | None = None  # (seq, t0, duration) of the highest seq
    buffer: dict[int, Inspected] = field(default_factory=dict)
    gap_pending: bool = False
    lost: deque[int] = field(default_factory=lambda: deque(maxlen=256))  # declared missing


def step_unit(
    state: UnitState, item: Inspected, cfg: IngestionConfig
) -> tuple[UnitState, list[tuple[Inspected, bool]], str | None]:
    """Sequence one inspected chunk: ``(state, released [(chunk, gap_before)], rejection)``."""
    chunk = item.raw
    seq, h = chunk.seq, state.health
    released: list[tuple[Inspected, bool]] = []
    if state.ref is not None:
        ref_seq, ref_t0, ref_dur = state.ref
        expected = ref_t0 + (seq - ref_seq) * ref_dur
        if abs(chunk.t0 - expected) > cfg.t0_tolerance_s:
            if seq < ref_seq and chunk.t0 > ref_t0 + ref_dur - cfg.t0_tolerance_s:
                # the gateway's counter restarted: finish the old run, start a new one
                released += release_unit(state, cfg, force=True)
                state.next_seq, state.ref, state.gap_pending = seq, None, True
                state.lost.clear()
                h.restarts += 1
            else:
                h.rejected += 1
                return (
                    state,
                    released,
                    f"t0: {chunk.t0:.3f} inconsistent with seq {seq} "
                    f"(expected {expected:.3f} ± {cfg.t0_tolerance_s:g} s from seq {ref_seq})",
                )
    if seq in state.buffer or (
        state.next_seq is not None and seq < state.next_seq and seq not in state.lost
    ):
        h.duplicates += 1
        return state, released, None
    if state.next_seq is not None and seq < state.next_seq:
        h.late += 1
        h.rejected += 1
        return state, released, f"late: seq {seq} arrived after its gap was reported"
    state.buffer[seq] = item
    if state.ref is None or seq > state.ref[0]:
        state.ref = (seq, chunk.t0, item.duration_s)
    _account(h, item)
    released += release_unit(state, cfg)
    return state, released, None


def release_unit(
    state: UnitState, cfg: IngestionConfig, *, now: float | None = None, force: bool = False
) -> list[tuple[Inspected, bool]]:
    """Release what the reorder window allows (everything with ``force``)."""
    out: list[tuple[Inspected, bool]] = []
    buffer = state.buffer
    while buffer:
        nxt = state.next_seq
        if nxt is None and 0 in buffer:
            nxt = state.next_seq = 0  # a counter starts at 0: nothing can come before it
        if nxt is not None and nxt in buffer:
            item = buffer.pop(nxt)
            out.append((item, state.gap_pending))
            state.gap_pending = False
            state.next_seq = nxt + 1
            state.last_t0, state.last_duration = item.raw.t0, item.duration_s
            continue
        oldest = min(buffer)
        newest_t0 = max(state.ref[1] if state.ref else -math.inf, now or -math.inf)
        waiting_since = (
            buffer[oldest].raw.t0 if nxt is None else state.last_t0 + state.last_duration
        )
        window_passed = (
            len(buffer) >= cfg.reorder_chunks or newest_t0 - waiting_since >= cfg.reorder_s
        )
        if not (force or window_passed):
            break
        if nxt is not None:
            state.lost.extend(range(nxt, oldest))
            state.health.missing += oldest - nxt
            state.gap_pending = True
        state.next_seq = oldest
    return out


# --- positioning per train -------------------------------------------------------------------


@dataclass(frozen=True)
class Knot:
    t: float
    line: str
    chainage_m: float
    speed_mps: float
    ok: bool


@dataclass(frozen=True)
class _LineGeometry:
    id: str
    length_m: float
    a: np.ndarray  # (pieces, 2) start points
    d: np.ndarray  # (pieces, 2) piece vectors
    dd: np.ndarray  # (pieces,) squared lengths
    chainage_m: np.ndarray  # (pieces + 1,)

    @classmethod
    def of(cls, line: Any) -> _LineGeometry:
        xy = np.asarray(line.xy, dtype=np.float64)
        d = np.diff(xy, axis=0)
        return cls(line.id, float(line.length_m), xy[:-1], d, (d * d).sum(axis=1), line.chainage_m)

    def project(self, p: np.ndarray, lo: float = -math.inf, hi: float = math.inf):
        """``(chainage, lateral)`` of the nearest point of the pieces overlapping [lo, hi].

        Lateral is signed, positive left of increasing chainage (as ``Line.project``).
        """
        c = self.chainage_m
        i0 = 0 if lo == -math.inf else max(0, int(np.searchsorted(c, lo, side="right")) - 1)
        i1 = len(self.a) if hi == math.inf else max(i0 + 1, int(np.searchsorted(c, hi)))
        a, d, dd = self.a[i0:i1], self.d[i0:i1], self.dd[i0:i1]
        q = p - a
        f = np.clip((q * d).sum(axis=1) / dd, 0.0, 1.0)
        r = q - f[:, None] * d
        dist2 = (r * r).sum(axis=1)
        j = int(dist2.argmin())
        cross = d[j, 0] * q[j, 1] - d[j, 1] * q[j, 0]
        chain = float(c[i0 + j] + f[j] * math.sqrt(dd[j]))
        return chain, math.copysign(math.sqrt(float(dist2[j])), cross)


@dataclass
class TrainState:
    """Map-matching state and the chunks of one train waiting for their knots."""

    stats: TrainStats = field(default_factory=TrainStats)
    line: str | None = None
    direction: int = 0  # +1 / -1 along the chainage, 0 not known yet
    extreme_m: float = 0.0  # farthest chainage reached in ``direction`` (or the start)
    off_count: int = 0
    last_fix_t: float | None = None
    last_good_t: float | None = None
    now: float = -math.inf  # newest event time of the train
    knots: list[Knot] = field(default_factory=list)  # from the fixes (map matching)
    knot_t: list[float] = field(default_factory=list)
    # the published track: what PositionedChunks carried, never changed afterwards
    pub: list[Knot] = field(default_factory=list)
    pub_t: list[float] = field(default_factory=list)
    # corrections of the published track being spread: (from t, offset m, until t)
    corrections: list[tuple[float, float, float]] = field(default_factory=list)
    poor_until: float = -math.inf  # published knots before this follow a large correction
    pending: list[tuple[Inspected, bool]] = field(default_factory=list)
    units: list[UnitState] = field(default_factory=list)  # the train's units, for windows
    # times of the current run of consecutive fixes refused as a clock jump (a re-base
    # candidate); cleared by a fix on the train's timeline
    suspects: list[float] = field(default_factory=list)


class Positioner:
    """Map matching on a network (lines with ``id``, ``xy``, ``chainage_m``, ``length_m``)."""

    def __init__(self, network: Any, cfg: IngestionConfig) -> None:
        self.cfg = cfg
        self.to_xy = network.to_xy
        self.lines = {line_id: _LineGeometry.of(line) for line_id, line in network.lines.items()}

    def best_line(self, p: np.ndarray, exclude: str | None = None) -> tuple[str, float] | None:
        """The line that clearly fits ``p`` and its chainage, or None (none or ambiguous)."""
        cfg = self.cfg
        fits = sorted(
            (abs(lat), line_id, chain)
            for line_id, g in self.lines.items()
            if line_id != exclude
            for chain, lat in [g.project(p)]
        )
        if not fits or fits[0][0] > cfg.acquire_m:
            return None
        if len(fits) > 1 and fits[1][0] - fits[0][0] < cfg.ambiguity_m:
            return None
        return fits[0][1], fits[0][2]

    def knot(self, st: TrainState, fix: GpsFix) -> Knot | None:
        """A knot for one fix (matched or dead-reckoned), updating the matching state."""
        cfg = self.cfg
        last = st.knots[-1] if st.knots else None
        if fix.fix_quality == 0:
            st.stats.no_fix += 1
            if st.line is None or last is None or last.line != st.line:
                return None
            g = self.lines[st.line]
            dt = fix.t - last.t
            chain = min(max(last.chainage_m + st.direction * last.speed_mps * dt, 0.0), g.length_m)
            ok = st.last_good_t is not None and fix.t - st.last_good_t <= cfg.dead_reckon_s
            return Knot(fix.t, st.line, chain, last.speed_mps, ok)
        p = self.to_xy(np.array([fix.lon_deg, fix.lat_deg]))
        if st.line is None:
            found = self.best_line(p)
            if found is None:
                return None
            st.line, st.direction, st.extreme_m, st.off_count = found[0], 0, found[1], 0
            last = None
        g = self.lines[st.line]
        if last is not None and last.line == st.line:
            reach = cfg.search_m + last.speed_mps * (fix.t - last.t) * 1.5
            chain, lat = g.project(p, last.chainage_m - reach, last.chainage_m + reach)
            if abs(lat) > cfg.switch_lateral_m:  # lost the thread (long outage): whole line
                chain, lat = g.project(p)
        else:
            chain, lat = g.project(p)
        off = abs(lat) > cfg.switch_lateral_m
        if off:
            st.off_count += 1
            if st.off_count >= cfg.switch_fixes:
                found = self.best_line(p, exclude=st.line)
                if found is not None:
                    st.stats.switches += 1
                    st.line, st.direction, st.extreme_m, st.off_count = found[0], 0, found[1], 0
                    g, last = self.lines[st.line], None
                    chain, lat = g.project(p)
                    off = False
        else:
            st.off_count = 0
        chain = self._smooth(st, last, fix, self._monotone(st, chain), chain)
        if fix.speed_mps is not None:
            speed = fix.speed_mps
        elif last is not None and last.line == st.line and fix.t > last.t:
            speed = abs(chain - last.chainage_m) / (fix.t - last.t)
        else:
            speed = 0.0
        ok = (
            not off
            and abs(lat) <= cfg.lateral_ok_m
            and (fix.hdop is None or fix.hdop <= cfg.hdop_max)
        )
        if ok:
            st.last_good_t = fix.t
        return Knot(fix.t, st.line, chain, speed, ok)

    def _smooth(
        self, st: TrainState, last: Knot | None, fix: GpsFix, held: float, measured: float
    ) -> float:
        r"""Blend the projection with the chainage predicted from the fix speeds.

        .. math::

            \hat c = c_{k-1} + d\,\tfrac{v_{k-1} + v_k}{2}\,\Delta t, \qquad
            c_k = \hat c + g\,(c_{meas} - \hat c)

        GPS speed is far less noisy than GPS position, so this cuts the white position
        noise (to about ``sqrt(g / (2 - g))`` of it) and keeps a standing train still. Off
        the gate (after an outage, a reversal being detected) the projection is used as is.
        """
        cfg = self.cfg
        if (
            last is None
            or last.line != st.line
            or st.direction == 0
            or fix.speed_mps is None
            or fix.t - last.t > cfg.dead_reckon_s
        ):
            return held
        dt = fix.t - last.t
        pred = last.chainage_m + st.direction * 0.5 * (last.speed_mps + fix.speed_mps) * dt
        if abs(measured - pred) > cfg.fuse_gate_m:
            return held
        fused = pred + cfg.fuse_gain * (measured - pred)
        if st.direction * (fused - last.chainage_m) < 0:  # never backwards
            return last.chainage_m
        return fused

    def _monotone(self, st: TrainState, chain: float) -> float:
        """Chainage kept monotone in the direction of travel (GPS jitter at a standstill)."""
        reverse = self.cfg.reverse_m
        if st.direction == 0:
            if abs(chain - st.extreme_m) > reverse:
                st.direction = 1 if chain > st.extreme_m else -1
                st.extreme_m = chain
            return chain
        ahead = st.direction * (chain - st.extreme_m)
        if ahead >= 0:
            st.extreme_m = chain
            return chain
        if -ahead > reverse:  # a reversal (terminus): follow it
            st.direction, st.extreme_m = -st.direction, chain
            return chain
        return st.extreme_m


def step_train(
    st: TrainState,
    event: GpsFix | tuple[Inspected, bool] | None,
    pos: Positioner,
    *,
    final: bool = False,
) -> tuple[TrainState, list[Output]]:
    """One fix or one released chunk for a train; ``(state, outputs)``.

    ``event`` None with ``final`` releases every held chunk (end of the stream).
    """
    out: list[Output] = []
    cfg = pos.cfg
    if isinstance(event, GpsFix):
        fix = event
        if st.last_fix_t is not None and fix.t <= st.last_fix_t:
            if fix.t == st.last_fix_t:
                st.stats.duplicates += 1
                return st, out
            return st, [
                Rejection(f"GpsFix: t {fix.t:.3f} before the previous fix {st.last_fix_t:.3f}", fix)
            ]
        st.last_fix_t = fix.t
        st.now = max(st.now, fix.t)
        st.stats.fixes += 1
        knot = pos.knot(st, fix)
        if knot is not None:
            st.knots.append(knot)
            st.knot_t.append(knot.t)
            if knot.ok:
                st.stats.matched += 1
            else:
                st.stats.poor += 1
    elif event is not None:
        item = event[0]
        st.now = max(st.now, item.t_last)
        st.pending.append(event)
    keep: list[tuple[Inspected, bool]] = []
    for entry in st.pending:
        item, gap = entry
        if st.pub_t and st.pub_t[-1] >= item.t_last:
            pass  # published already (for another unit of the train)
        elif st.knot_t and st.knot_t[-1] >= item.t_last:
            _publish_track(st, pos, item.t_last)
        elif _can_extrapolate(st, pos, item.t_last):
            _publish_track(st, pos, item.t_last, extrapolate=True)
            st.stats.extrapolated += 1
        elif final or st.now - item.t_last > cfg.max_hold_s:
            _publish_track(st, pos, item.t_last)  # as far as the knots go: not bracketed
        else:
            keep.append(entry)
            continue
        out.append(_positioned(st, item, gap, cfg))
    if event is not None and not isinstance(event, GpsFix) and keep and keep[-1] is event:
        st.stats.held += 1
    st.pending = keep
    horizon = st.now - cfg.knot_keep_s
    drop = bisect_left(st.knot_t, horizon) - 1  # keep one knot before the horizon
    if drop > 0:
        del st.knots[:drop], st.knot_t[:drop]
    drop = bisect_left(st.pub_t, horizon) - 1
    if drop > 0:
        del st.pub[:drop], st.pub_t[:drop]
    return st, out


STANDING_MPS = 0.5  # slower than this, a train of unknown direction is taken as standing
_DR_STEP_S = 0.5  # knot spacing of a dead-reckoned stretch with acceleration (a parabola)


class _Track:
    """The fix knots of one line as a function of time: linear between knots, dead-reckoned
    past the last one (its speed, and the acceleration between the last two knots)."""

    def __init__(self, st: TrainState, line: str, pos: Positioner) -> None:
        cfg = pos.cfg
        self.knots = [k for k in st.knots if k.line == line]
        self.t = [k.t for k in self.knots]
        self.line, self.cfg = line, cfg
        self.length_m = pos.lines[line].length_m
        self.direction = st.direction if line == st.line else 0
        self.last_good_t = st.last_good_t
        self.accel = 0.0
        if len(self.knots) >= 2 and self.direction:
            k0, k1 = self.knots[-2], self.knots[-1]
            dt = k1.t - k0.t
            if 0 < dt <= cfg.dead_reckon_s:
                bound = cfg.extrapolate_accel_max_mps2
                self.accel = min(max((k1.speed_mps - k0.speed_mps) / dt, -bound), bound)

    def at(self, t: float) -> Knot:
        ks = self.knots
        i = bisect_right(self.t, t)
        if i == 0:  # before the line's first knot (a line change): its first position
            return Knot(t, self.line, ks[0].chainage_m, ks[0].speed_mps, False)
        a = ks[i - 1]
        if a.t == t:
            return a
        if i < len(ks):
            b = ks[i]
            f = (t - a.t) / (b.t - a.t)
            return Knot(
                t,
                self.line,
                a.chainage_m + f * (b.chainage_m - a.chainage_m),
                a.speed_mps + f * (b.speed_mps - a.speed_mps),
                a.ok and b.ok,
            )
        return self.reckon(t)

    def reckon(self, t: float) -> Knot:
        r"""Dead reckoning from the last knot ``r`` over ``tau = t - t_r``:

        .. math::

            c = c_r + d\,(v_r \tau + \tfrac{1}{2} a \tau^2), \qquad v = v_r + a \tau

        until the speed reaches 0 (a stop), never past a line end. Trusted (ok) while ``tau``
        is within ``extrapolate_s`` and the last good fix within ``dead_reckon_s``.
        """
        cfg, r = self.cfg, self.knots[-1]
        tau, v, a = t - r.t, r.speed_mps, self.accel
        if a < 0 and v + a * tau < 0:
            tau_stop = -v / a
            dist, speed = v * tau_stop + 0.5 * a * tau_stop**2, 0.0
        else:
            dist, speed = v * tau + 0.5 * a * tau**2, v + a * tau
        chain = r.chainage_m + self.direction * dist  # not past a line end (nor back from r)
        chain = min(max(chain, min(0.0, r.chainage_m)), max(self.length_m, r.chainage_m))
        ok = (
            r.ok
            and tau <= cfg.extrapolate_s
            and self.last_good_t is not None
            and t - self.last_good_t <= cfg.dead_reckon_s
        )
        return Knot(t, self.line, chain, speed, ok)


def _can_extrapolate(st: TrainState, pos: Positioner, t_last: float) -> bool:
    """Whether a chunk ending at ``t_last`` can go out now, its tail dead-reckoned."""
    cfg = pos.cfg
    if cfg.extrapolate_s <= 0 or st.line is None:
        return False
    last = next((k for k in reversed(st.knots) if k.line == st.line), None)
    if last is None or t_last - last.t > cfg.extrapolate_s:
        return False
    return st.direction != 0 or last.speed_mps <= STANDING_MPS


def _publish_track(st: TrainState, pos: Positioner, t_to: float, *, extrapolate=False) -> None:
    """Extend the published track (``st.pub``) towards ``t_to``.

    It takes the fix knots after its end up to the first one at or after ``t_to`` and, with
    ``extrapolate``, dead-reckons from the last fix knot to ``t_to`` when no knot reaches it.
    What was published stays. Where the fix knots have since moved the track away from the
    published end (a dead-reckoned position that a later fix corrects), that correction is
    spread linearly over the next ``correction_s`` (each new correction on its own schedule,
    added to those still running), so the published chainage is continuous: a correction
    never reads as a jump, or backwards as a reversal, in the extraction. A correction larger
    than ``correction_ok_m`` is no dead-reckoning error (a stop inside a tunnel, where the
    fix knots themselves were reckoned on): the track jumps to the fix knots, as they do,
    and its knots for ``correction_s`` are marked poor. The track never steps backwards
    while the fix knots move forwards (a spread correction never reverses it). Without dead
    reckoning there is nothing to correct and the published track is the fix knots.
    """
    cfg = pos.cfg
    pub, end = st.pub, (st.pub[-1] if st.pub else None)
    t_end = -math.inf if end is None else end.t
    i = bisect_right(st.knot_t, t_end)
    j = bisect_left(st.knot_t, t_to, lo=i)
    new = st.knots[i : j + 1]  # up to the first knot at or after t_to, if there is one
    track: _Track | None = None
    if extrapolate and j >= len(st.knot_t) and st.line is not None:
        track = _Track(st, st.line, pos)
        if track.knots and t_to > max(track.t[-1], t_end):
            r = track.t[-1]
            steps = []
            if track.accel:
                steps = [r + _DR_STEP_S * m for m in range(1, int((t_to - r) / _DR_STEP_S) + 1)]
            new += [track.reckon(t) for t in [*steps, t_to] if t_end < t < t_to or t == t_to]
    if not new:
        return
    prev_base = None
    if end is None or not any(k.line == end.line for k in st.knots):
        st.corrections = []
    else:
        ref = track if track is not None and track.line == end.line else _Track(st, end.line, pos)
        if ref.t[0] > end.t:  # the knots around the end are gone (a long pause)
            st.corrections = []
        else:
            prev_base = ref.at(end.t).chainage_m
            st.corrections = [c for c in st.corrections if c[2] > end.t]
            residual = end.chainage_m - prev_base - _correction(st, end.t)
            st.stats.max_correction_m = max(st.stats.max_correction_m, abs(residual))
            if abs(residual) > cfg.correction_ok_m:
                # not a dead-reckoning error to smooth over (a stop in a tunnel, a reversal
                # found late): jump to the fixes' track, as they do, and mark it poor
                st.corrections, prev_base = [], None
                st.poor_until = end.t + cfg.correction_s
            elif abs(residual) > 1e-9 and cfg.correction_s > 0:
                st.corrections.append((end.t, residual, end.t + cfg.correction_s))
            times = {k.t for k in new}
            for _, _, until in st.corrections:  # where a correction ends: a knot
                if new[0].t < until < new[-1].t and until not in times:
                    new.append(ref.at(until))
                    times.add(until)
            new.sort(key=lambda k: k.t)
    for k in new:
        if end is not None and k.line != end.line:  # no blending across a line change
            st.corrections, prev_base, end = [], None, None
        offset = _correction(st, k.t)
        chain = k.chainage_m + offset
        poor = k.t < st.poor_until
        if pub and pub[-1].line == k.line and prev_base is not None and st.direction:
            d, last = st.direction, pub[-1].chainage_m
            if d * (chain - last) < 0 <= d * (k.chainage_m - prev_base):
                chain = last  # the correction would step back: hold until the track passes
        prev_base = k.chainage_m
        pub.append(Knot(k.t, k.line, chain, k.speed_mps, k.ok and not poor))
        st.pub_t.append(k.t)


def _correction(st: TrainState, t: float) -> float:
    """The sum of the corrections still being spread at ``t`` (m)."""
    return sum(
        offset * (until - t) / (until - since)
        for since, offset, until in st.corrections
        if t < until
    )


def _positioned(st: TrainState, item: Inspected, gap_before: bool, cfg: IngestionConfig) -> Output:
    raw = item.raw
    if not st.pub:
        st.stats.unpositioned += 1
        return Rejection(
            f"unpositioned: no map-matched GPS position of train {raw.train} around "
            f"t0 {raw.t0:.3f}",
            raw,
        )
    kt = st.pub_t
    i0 = bisect_right(kt, raw.t0) - 1
    i1 = bisect_left(kt, item.t_last)
    bracketed = i0 >= 0 and i1 < len(kt)
    knots = st.pub[max(i0, 0) : min(i1, len(kt) - 1) + 1]
    line = knots[-1].line
    single_line = all(k.line == line for k in knots)
    if not single_line:
        knots = [k for k in knots if k.line == line]
    t = np.array([k.t for k in knots])
    gaps_ok = len(t) < 2 or float(np.diff(t).max()) <= cfg.dead_reckon_s
    ok = bracketed and single_line and gaps_ok and all(k.ok for k in knots)
    return PositionedChunk(
        train=raw.train,
        unit=raw.unit,
        seq=raw.seq,
        t0=raw.t0,
        rate_hz=raw.rate_hz,
        channels=CHANNELS,
        samples=NDArray(dtype="f4", shape=list(item.samples.shape), data=item.samples.tobytes()),
        line=line,
        knot_t=NDArray.of(t),
        knot_chainage_m=NDArray.of([k.chainage_m for k in knots]),
        knot_speed_mps=NDArray.of([k.speed_mps for k in knots]),
        position_ok=ok,
        gap_before=gap_before,
        sensor_flags=list(item.flags),
    )


# --- the whole core --------------------------------------------------------------------------


class IngestionCore:
    """Per-unit sequencing and health, per-train positioning; one ordered event stream.

    Parameters
    ----------
    network : simulators.network.Network (or alike)
        Lines with ``id``, ``xy``, ``chainage_m``, ``length_m`` and ``to_xy(lonlat)``.
    config : IngestionConfig
    """

    def __init__(self, network: Any, config: IngestionConfig | None = None) -> None:
        self.cfg = config or IngestionConfig()
        self.positioner = Positioner(network, self.cfg)
        self.units: dict[tuple[str, str], UnitState] = {}
        self.trains: dict[str, TrainState] = {}

    def step(self, event: RawChunk | GpsFix) -> list[Output]:
        """One decoded message in arrival order; what it releases comes out."""
        match event:
            case RawChunk():
                return self._on_chunk(event)
            case GpsFix():
                return self._on_fix(event)
        raise TypeError(f"ingestion takes RawChunk or GpsFix, not {type(event).__name__}")

    def run(self, events: Iterable[RawChunk | GpsFix], *, flush: bool = True) -> list[Output]:
        """Every event through :meth:`step` (then :meth:`flush`): lists in, lists out."""
        out: list[Output] = []
        for event in events:
            out += self.step(event)
        if flush:
            out += self.flush()
        return out

    def flush(self) -> list[Output]:
        """End of the stream: release every buffered and held chunk (gaps flagged)."""
        out: list[Output] = []
        for st in self.trains.values():
            for unit in st.units:
                for released in release_unit(unit, self.cfg, force=True):
                    out += self._to_train(st, released)
            out += self._count(step_train(st, None, self.positioner, final=True)[1])
        return out

    def health(self, train: str, unit: str) -> UnitHealth:
        """A copy of the counters of one unit (zeros for a unit never seen)."""
        h = self.units.get((train, unit))
        if h is None:
            return UnitHealth()
        h = h.health
        return replace(
            h, flatline_chunks=dict(h.flatline_chunks), dropout_chunks=dict(h.dropout_chunks)
        )

    def train_stats(self, train: str) -> TrainStats:
        st = self.trains.get(train)
        return replace(st.stats) if st else TrainStats()

    # --- internals ----------------------------------------------------------------------

    def _train(self, train: str) -> TrainState:
        st = self.trains.get(train)
        if st is None:
            st = self.trains[train] = TrainState()
        return st

    def fleet_t(self, train: str) -> float | None:
        """The fleet's clock: the median of the other trains' last accepted fix times."""
        times = [
            st.last_fix_t
            for name, st in self.trains.items()
            if name != train and st.last_fix_t is not None
        ]
        return float(np.median(times)) if times else None

    def _ahead(self, train: str, st: TrainState, name: str, t: float) -> str | None:
        """Why ``t`` is too far ahead of the train's clock and of the fleet's, or None."""
        cfg, last = self.cfg, st.last_fix_t
        if last is not None and t - last <= cfg.max_ahead_s:
            return None
        fleet = self.fleet_t(train)
        if fleet is not None and t - fleet <= cfg.max_ahead_s:
            return None  # the train was away (an outage, a depot night): the fleet agrees
        if last is None and fleet is None:
            return None  # nothing to compare with
        against = []
        if last is not None:
            against.append(f"{t - last:.0f} s ahead of the train's last fix {last:.3f}")
        if fleet is not None:
            against.append(f"{t - fleet:.0f} s ahead of the fleet's clock {fleet:.3f}")
        return (
            f"{name}: {t:.3f} is {' and '.join(against)} (more than {cfg.max_ahead_s:g} s): "
            "refused as a clock jump"
        )

    def _clock_check(self, fix: GpsFix, st: TrainState) -> tuple[str | None, bool]:
        """``(reason, rebase)``: why a fix is off the train's timeline (None: on it) and
        whether the train re-bases to it now (the rule in the module docstring)."""
        cfg, last, t = self.cfg, st.last_fix_t, fix.t
        reason = self._ahead(fix.train, st, "t", t)
        if reason is None and last is not None and last - t > cfg.max_ahead_s:
            fleet = self.fleet_t(fix.train)
            if fleet is not None and abs(t - fleet) <= cfg.max_ahead_s:
                return None, True  # back on the fleet's clock: re-base at once
            reason = (
                f"t: {t:.3f} is {last - t:.0f} s behind the train's last fix {last:.3f} "
                f"(more than {cfg.max_ahead_s:g} s): refused as a clock jump"
            )
        if reason is None:
            st.suspects.clear()
            return None, False
        run = st.suspects
        if run and 0 < t - run[-1] <= cfg.rebase_gap_s:
            run.append(t)
        else:
            run[:] = [t]
        if len(run) >= cfg.rebase_fixes:
            return None, True
        return (
            f"{reason} ({cfg.rebase_fixes - len(run)} more consecutive fixes at the new "
            "time re-base the train there)",
            False,
        )

    def _rebase(self, st: TrainState, fix: GpsFix) -> list[Output]:
        """Start the train's timeline over at ``fix``: what is held goes out first."""
        out: list[Output] = []
        for unit in st.units:
            for released in release_unit(unit, self.cfg, force=True):
                out += self._to_train(st, released)
        out += self._count(step_train(st, None, self.positioner, final=True)[1])
        log.warning(
            "train %s: clock re-based from %s to %s (%d consecutive fixes at the new time)",
            fix.train,
            "none" if st.last_fix_t is None else f"{st.last_fix_t:.3f}",
            f"{fix.t:.3f}",
            len(st.suspects),
        )
        for unit in st.units:  # sequencing starts over too: t0 against seq at the new time
            unit.next_seq, unit.ref, unit.gap_pending = None, None, True
            unit.lost.clear()
        fresh = TrainState(stats=st.stats, units=st.units)
        fresh.stats.rebases += 1
        self.trains[fix.train] = fresh
        return out

    def _on_chunk(self, chunk: RawChunk) -> list[Output]:
        key = (chunk.train, chunk.unit)
        st = self._train(chunk.train)
        unit = self.units.get(key)
        if unit is None:
            unit = self.units[key] = UnitState()
            st.units.append(unit)
        inspected = inspect_chunk(chunk, self.cfg)
        if isinstance(inspected, str):
            unit.health.rejected += 1
            return [Rejection(f"RawChunk: {inspected}", chunk)]
        jump = self._ahead(chunk.train, st, "t0", chunk.t0)
        if jump is not None:
            unit.health.rejected += 1
            st.stats.clock_jumps += 1
            return [Rejection(f"RawChunk: {jump}", chunk)]
        unit, released, reason = step_unit(unit, inspected, self.cfg)
        out: list[Output] = [] if reason is None else [Rejection(f"RawChunk: {reason}", chunk)]
        if reason is None:
            st.now = max(st.now, inspected.t_last)  # the train's event time moves on
        for r in released:
            out += self._to_train(st, r)
        if not released:  # held chunks of the train may have timed out
            out += self._count(step_train(st, None, self.positioner)[1])
        return out

    def _on_fix(self, fix: GpsFix) -> list[Output]:
        st = self._train(fix.train)
        out: list[Output] = []
        bad = time_range_reason("t", fix.t, self.cfg)
        if bad is not None:
            return [Rejection(f"GpsFix: {bad}", fix)]
        reason, rebase = self._clock_check(fix, st)
        if reason is not None:
            st.stats.clock_jumps += 1
            return [Rejection(f"GpsFix: {reason}", fix)]
        if rebase:
            out += self._rebase(st, fix)
            st = self.trains[fix.train]
        # the fix's time also closes the reorder windows of the train's units
        for unit in st.units:
            if unit.buffer:
                for released in release_unit(unit, self.cfg, now=fix.t):
                    out += self._to_train(st, released)
        out += self._count(step_train(st, fix, self.positioner)[1])
        return out

    def _to_train(self, st: TrainState, released: tuple[Inspected, bool]) -> list[Output]:
        return self._count(step_train(st, released, self.positioner)[1])

    def _count(self, outputs: list[Output]) -> list[Output]:
        for o in outputs:
            if isinstance(o, PositionedChunk):
                self.units[(o.train, o.unit)].health.published += 1
        return outputs
