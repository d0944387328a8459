"""Validation beyond the schema, health and correction of one chunk (vectorised). Pure.

**Validation** beyond the schema (:func:`inspect_chunk`): the channel set holds
``supply_v`` and the vertical pair (``left_z``, ``right_z``), the lateral pair (``left_y``,
``right_y``) or both (:func:`channels_reason`: a vertical-only sensor measures Top6 only);
the longitudinal channels are passed on when present; the sample rate is within
``rate_tolerance`` of the unit's expected rate; the samples are floats (an integer dtype
carries no scale on the wire: refused); ``t0`` is in the valid time range; every value is
finite; the accelerations are in g (:func:`vertical_unit_reason`: a vertical channel's mean is
gravity, so a mean beyond ``vertical_max_g`` is m/s² at ≈ 9.81, or counts; a chunk without
vertical channels has no such check); the supply
voltage is plausible (``supply_min_v``..``supply_max_v``). A failure is a
reason (the core makes it a :class:`~services.ingestion.core.Rejection`).

**Health and correction** (:func:`inspect_chunk`, vectorised over the chunk): clipping
(any ``|a| >= clip_g``), flatline per channel (a share of exactly repeated consecutive
values; a held non-zero value), dropout per channel (the same, stuck at exactly 0),
supply deviation from 5.0 V; then the ratiometric correction
``a_mps2 = a_g * (supply_nominal_v / V) * 9.80665`` per sample.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from datetime import UTC, datetime

import numpy as np

from schemas import ACCEL_CHANNELS, SUPPLY_CHANNEL, RawChunk
from services.ingestion.config import IngestionConfig

G_MPS2 = 9.80665
_CANONICAL = [*ACCEL_CHANNELS, SUPPLY_CHANNEL]
# the channel pairs an indicator needs, both rails: Top6 from the vertical, Align10 from the
# lateral accelerations (docs/science.md, signal chain)
INDICATOR_CHANNELS = {"top6": ("left_z", "right_z"), "align10": ("left_y", "right_y")}


@dataclass
class UnitHealth:
    """Counters of one (train, unit); :meth:`IngestionCore.health` returns a copy."""

    chunks: int = 0  # accepted (validated) chunks
    samples: int = 0  # accepted sample rows
    values: int = 0  # accepted acceleration values (rows x accelerometer channels)
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
        return self.clipped_samples / max(1, self.values)


@dataclass(frozen=True)
class Inspected:
    """A validated, corrected chunk waiting for its neighbours and its position."""

    raw: RawChunk
    channels: list[str]  # the accelerometer channels of ``samples``, in ACCEL_CHANNELS order
    samples: np.ndarray  # (n, len(channels)) float32 m/s^2, supply-corrected
    flags: tuple[str, ...]
    t_last: float  # epoch s of the last sample
    duration_s: float  # n / rate
    clipped: int
    supply_min_v: float
    supply_max_v: float


def _column_order(channels: list[str], accel: list[str]) -> list[int] | None:
    if channels == _CANONICAL:
        return None  # the usual case: no gather
    where = {name: i for i, name in enumerate(channels)}
    return [where[name] for name in [*accel, SUPPLY_CHANNEL]]


def channels_reason(channels: list[str]) -> str | None:
    """Why a chunk's channels cannot give an index, or None: it needs ``supply_v`` (the
    ratiometric correction) and both rails of the vertical or of the lateral accelerations."""
    if SUPPLY_CHANNEL not in channels:
        return f"channels: missing ['{SUPPLY_CHANNEL}'] (have {channels})"
    if any(all(c in channels for c in pair) for pair in INDICATOR_CHANNELS.values()):
        return None
    need = " or ".join(str(list(pair)) for pair in INDICATOR_CHANNELS.values())
    return f"channels: need {need}, each with '{SUPPLY_CHANNEL}' (have {channels})"


def inspect_chunk(chunk: RawChunk, cfg: IngestionConfig) -> Inspected | str:
    """Validate, check health and correct one chunk; a string is the rejection reason.

    .. math::

        a_{m/s^2}[k] = a_g[k] \\cdot \\frac{V_{nominal}}{V[k]} \\cdot 9.80665

    (the sensor output is ratiometric: proportional to the supply voltage ``V[k]``).
    """
    bad_channels = channels_reason(chunk.channels)
    if bad_channels:
        return bad_channels
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
    accel = [c for c in ACCEL_CHANNELS if c in chunk.channels]
    k = len(accel)
    order = _column_order(chunk.channels, accel)
    if order is not None:
        a = a[:, order]
    if a.dtype != np.float32:
        a = a.astype(np.float32)
    acc, volts = a[:, :k], a[:, k]
    # Whole-array reductions over the contiguous block are several times faster than
    # per-column (axis=0) ones; NaN propagates through max/min, so they check finiteness.
    top, bottom = float(a.max()), float(a.min())
    if not (math.isfinite(top) and math.isfinite(bottom)):
        return "samples: contain NaN or inf"
    vertical = [accel.index(c) for c in INDICATOR_CHANNELS["top6"] if c in accel]
    unit = vertical_unit_reason(acc[:, vertical], cfg) if vertical else None
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
    if np.count_nonzero(same) - np.count_nonzero(same[:, k]) >= limit:
        repeats = np.count_nonzero(same[:, :k], axis=0)
        for c in np.flatnonzero(repeats >= limit):
            # stuck at exactly zero is a dropout (signal lost); at any other value, a flatline
            if np.count_nonzero(acc[:, c] == 0.0) >= cfg.flat_fraction * n:
                flags.append(f"dropout:{accel[c]}")
            else:
                flags.append(f"flatline:{accel[c]}")
    nominal = cfg.supply_nominal_v
    if max(nominal - vmin, vmax - nominal) > cfg.supply_flag_deviation * nominal:
        flags.append("supply")
    scale = np.float32(nominal * G_MPS2) / volts
    samples = acc * scale[:, None]
    return Inspected(
        raw=chunk,
        channels=accel,
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
    """Why the accelerations are not in g, judged by gravity on the vertical channels
    (``acc``: the columns of ``left_z``/``right_z`` present).

    Over a chunk a vertical channel averages to gravity, +1 g (the bogie's vibration averages
    out). A mean beyond ``vertical_max_g`` on either of ``left_z``/``right_z`` is no
    acceleration in g: about 9.81 is m/s², anything larger counts or another scale.
    """
    means = acc.mean(axis=0, dtype=np.float64)
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


def account(h: UnitHealth, item: Inspected) -> None:
    """Count an accepted chunk's samples and findings."""
    h.chunks += 1
    h.samples += item.samples.shape[0]
    h.values += item.samples.size
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
