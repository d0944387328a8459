"""Extraction core: PositionedChunks of one unit in, OnboardIndex per segment pass out. Pure.

No Zenoh, no clock, no I/O: time is the data's event time. The adapter
(``services/extraction/service.py``) feeds every decoded chunk to :meth:`Extractor.process`
and publishes what comes out; tests and benchmarks do the same with lists.

The chain of one (train, unit), streaming (every filter carries its state across chunks,
memory is bounded by a few seconds of samples and one segment of versine samples):

1. **Decimation** 2000 -> 500 Hz: a 41-tap linear-phase FIR (Kaiser, flat to 40 Hz,
   < -85 dB from 460 Hz, the band that would alias into 0-40 Hz), evaluated only at the
   kept samples (polyphase, ``scipy.signal.upfirdn``) with the decimation phase carried
   across chunks. Its delay of 20 input samples (10 ms) is taken off the output times.
2. **Band-pass and double integration** in one causal IIR per indicator:

   .. math::

       G(s) = \\frac{B_N(s)}{s^2}

   where ``B_N`` is the analog Butterworth band-pass of order 4 between ``f_lo`` and 40 Hz
   (0.8 Hz for Top6, 0.5 Hz for Align10: the chord's wavelength at the 5 m/s reference
   speed, paper 3.2). ``B_N`` has N zeros at s = 0, two of which cancel the double
   integrator exactly, so gravity and sensor offsets (DC) give no output and drift cannot
   build up; seen from the displacement, the chain is exactly the band-pass ``B_N``.
   Discretised by the bilinear transform at 500 Hz (integrator gain error < 0.4 % below
   17 Hz) and run as second-order sections.
3. **Time to distance**: the positioned chainage is interpolated linearly between the
   chunk's knots. The band-pass delays what it passes: a sample leaving it at time t shows
   the track the unit was over at ``t - tau``, with ``tau`` the band-pass's phase delay at
   the frequency ``v / (2 L)`` (speed v, chord L; where the index's energy is, after the
   wheelbase filter). The samples are then interpolated linearly onto the 0.25 m grid
   ``x_j = j * 0.25 m`` from chainage 0 (the simulator's profile grid, for any segment
   bounds). When chainage decreases the grid is walked downwards; the chord versine is
   symmetric, so each grid point gets the same versine in either direction.
4. **Chord versine** (6 m on the vertical channels, 10 m on the lateral ones) and **the
   segment statistic** (both from :mod:`services.extraction.versine`) over the versine
   samples whose whole chord lies in the segment at least ``END_GUARD_M`` (1 m) from its
   ends (the shared statistic's support), per rail (left,
   right accelerometer), then ``min(left, right)`` per indicator, in mm.

Channels: Top6 comes from the vertical pair (``left_z``, ``right_z``), Align10 from the
lateral pair (``left_y``, ``right_y``). A unit whose chunks carry one pair only (a
vertical-only sensor) gets the chain of that indicator only, and its OnboardIndex lists
that indicator only (``indicators``; the other value is None); a change of channel set
restarts the unit's chain, as a gap does. A chunk with neither pair is refused
(SchemaError; ingestion refuses such a RawChunk before it gets here).

A segment's OnboardIndex is emitted once the versine of every indicator measured has passed the
last chord centre of the segment (``end - L/2 - guard``), i.e. when the unit is the 1 m
guard short of the segment's end (plus ``v tau``, the filter's delay, and one grid step):
nothing past the end is needed. It comes out of the very chunk that holds that sample
(plus the FIR's 10 ms),
whatever the chunking (``tests/unit/test_extraction_latency.py``). ``tau`` is clamped at 0
and is 0 at every speed of the demo network: below the band's centre frequency the
band-pass's phase is a lead, not a delay.

Validity, per sample and rail: ``position_ok`` of its chunk; at least ``settle_s`` after
a reset (gap, start, line change); the rail's channel not flagged (``flatline:`` or
``dropout:`` by ingestion) in this chunk, nor within ``settle_s`` after a flagged chunk
(the filter's transient). A versine sample is valid when its three profile points are.

Passes are skipped, counted and never guessed (:class:`Counters`), in this order:

* ``skipped_position``: a versine centre of the segment from a chunk with ``position_ok``
  False;
* ``skipped_slow``: the unit ran below ``v_ref_mps`` (5 m/s) over part of the segment
  (the band-pass would cut the chord's wavelengths);
* ``skipped_coverage``: no rail of an indicator has valid versine samples on at least
  ``min_coverage`` (0.9) of the segment's grid points: the unit entered or left the
  segment in a gap, a reset's settling time or a reversal, or a rail was flagged too long.

Direction: on the return trip the vehicle's left accelerometer is over the track's right
rail (the train reverses without turning). ``min(left, right)`` is symmetric, and the
lateral sign flip does not change a standard deviation, so a pass gives the same index in
either direction.

Quality: ``coverage`` (the smaller of the measured indicators' best rail coverage), halved when
an indicator had only one usable rail (``min(L, R)`` could not reject a one-rail outlier),
times 0.9 when ingestion flagged the segment's chunks with chunk-wide findings
(``clipping``, ``supply``).
"""

from __future__ import annotations

import itertools
import math
from collections import deque
from dataclasses import dataclass, field, fields

import numpy as np
from scipy import signal

from schemas import INDICATORS, OnboardIndex, PositionedChunk, SchemaError
from schemas.messages import INDEX_MAX_MM
from track.segments import LineSegments, SegmentTable
from track.versine import (
    ALIGN_CHORD_M,
    TOP_CHORD_M,
    chord_versine,
    half_chord_samples,
    segment_statistic,
    statistic_centres,
    statistic_inset_m,
)

__all__ = [
    "Counters",
    "ExtractionConfig",
    "Extractor",
    "UnitPipeline",
]

_CHANNEL_SIDES = {  # channel -> (indicator, side): 0 = top6 (z), 1 = align10 (y)
    "left_z": (0, 0),
    "right_z": (0, 1),
    "left_y": (1, 0),
    "right_y": (1, 1),
}
_INDICATOR_COLUMNS = (("left_z", "right_z"), ("left_y", "right_y"))  # by indicator, both rails
_RAIL_FLAGS = ("flatline", "dropout")  # ingestion's per-channel findings that void a rail
_CHUNK_FLAGS = ("clipping", "supply")  # chunk-wide findings: lower the quality only


@dataclass(frozen=True)
class ExtractionConfig:
    """Signal-chain constants (paper 3.2); the defaults are the signal chain of
    docs/science.md#signal-chain-paper-section-3."""

    rate_hz: float = 2000.0  # input sample rate
    decimation: int = 4  # 2000 -> 500 Hz
    fir_taps: int = 41  # anti-alias FIR; (taps - 1) must be a multiple of ``decimation``
    fir_cutoff_hz: float = 220.0
    fir_beta: float = 8.0  # Kaiser window
    v_ref_mps: float = 5.0  # minimum reference speed
    high_hz: float = 40.0  # upper band edge of both indicators
    order: int = 4  # Butterworth band-pass order (>= 3: the band-pass must cancel 1/s^2)
    spacing_m: float = 0.25  # distance grid
    min_coverage: float = 0.9
    settle_cycles: float = 4.0  # settling time = settle_cycles / low band edge
    delay_wavelength_chords: float = 2.0  # tau is the phase delay at v / (this * chord)
    max_delay_s: float = 1.5

    def __post_init__(self) -> None:
        if self.order < 3:
            raise ValueError(
                f"order: must be >= 3 to cancel the double integrator, got {self.order}"
            )
        if (self.fir_taps - 1) % self.decimation:
            raise ValueError("fir_taps - 1 must be a multiple of decimation (integer delay)")
        if not 0 < self.min_coverage <= 1:
            raise ValueError(f"min_coverage: must be in (0, 1], got {self.min_coverage}")
        fs = self.rate_hz / self.decimation
        if not self.high_hz < 0.5 * fs:
            raise ValueError(f"high_hz {self.high_hz} must be below the decimated Nyquist {fs / 2}")

    @property
    def fs_hz(self) -> float:
        """Sample rate after decimation."""
        return self.rate_hz / self.decimation


# The paper's bands are 0.8-40 Hz (Top6, 6 m) and 0.5-40 Hz (Align10, 10 m): v_ref / L is
# 0.833 and 0.5 Hz; the paper rounds the first to 0.8. The bands are fixed here as the
# paper states them.
BANDS_HZ = {TOP_CHORD_M: 0.8, ALIGN_CHORD_M: 0.5}
INDICATOR_CHORDS_M = (TOP_CHORD_M, ALIGN_CHORD_M)
RECENT_CHUNKS = 256  # per unit, the chunk identities a duplicate is looked for among


@dataclass
class Counters:
    """What one pipeline (or the sum of all) did; every pass is either indexed or skipped.

    ``passes_indexed`` OnboardIndex emitted; ``skipped_position``, ``skipped_slow``,
    ``skipped_coverage``, ``skipped_implausible`` (a statistic above the schemas'
    ``INDEX_MAX_MM``: not geometry but a fault) passes skipped by reason (module
    docstring); ``chunks`` and
    ``samples`` (rows of 6 accelerometer channels) processed; ``resets`` restarts of the
    streaming state (gap_before, first chunk, line change, time running backwards);
    ``reversals`` changes of the direction of travel; ``unknown_line`` chunks on a line
    the segment table does not know (dropped); ``duplicates`` chunks dropped because the
    unit's chunk with the same ``seq`` and ``t0`` was processed already (a restarted
    ingestion sends again what it sent after its last checkpoint).
    """

    passes_indexed: int = 0
    skipped_position: int = 0
    skipped_slow: int = 0
    skipped_coverage: int = 0
    skipped_implausible: int = 0
    chunks: int = 0
    samples: int = 0
    resets: int = 0
    reversals: int = 0
    unknown_line: int = 0
    duplicates: int = 0

    def add(self, other: Counters) -> None:
        for f in fields(self):
            setattr(self, f.name, getattr(self, f.name) + getattr(other, f.name))

    def as_dict(self) -> dict[str, int]:
        return {f.name: getattr(self, f.name) for f in fields(self)}

    @property
    def passes(self) -> int:
        return (
            self.passes_indexed
            + self.skipped_position
            + self.skipped_slow
            + self.skipped_coverage
            + self.skipped_implausible
        )


# --- filters -----------------------------------------------------------------------------


def decimation_fir(cfg: ExtractionConfig) -> np.ndarray:
    """The anti-alias FIR (linear phase, unit DC gain)."""
    return signal.firwin(
        cfg.fir_taps, cfg.fir_cutoff_hz, fs=cfg.rate_hz, window=("kaiser", cfg.fir_beta)
    )


def displacement_sos(cfg: ExtractionConfig, low_hz: float) -> np.ndarray:
    """Second-order sections of ``G(s) = B_N(s) / s^2`` at the decimated rate.

    Input acceleration (m/s^2), output displacement (m) band-passed to ``[low_hz, high_hz]``.
    """
    w = 2 * np.pi * np.array([low_hz, cfg.high_hz])
    z, p, k = signal.butter(cfg.order, w, btype="bandpass", analog=True, output="zpk")
    z = z[np.argsort(np.abs(z))][2:]  # two of the N zeros at s = 0 cancel 1/s^2 exactly
    zd, pd, kd = signal.bilinear_zpk(z, p, k, cfg.fs_hz)
    return signal.zpk2sos(zd, pd, kd)


def phase_delay_table(sos: np.ndarray, fs_hz: float, f_lo: float) -> tuple[np.ndarray, np.ndarray]:
    """Phase delay (s) of the displacement band-pass ``s^2 G`` on a log grid of frequencies."""
    f = np.geomspace(0.25 * f_lo, 0.45 * fs_hz, 256)
    _, h = signal.sosfreqz(sos, worN=f, fs=fs_hz)
    phase = np.unwrap(np.angle(-h))  # -(2 pi f)^2 > 0 scaling aside: s^2 = -(w^2)
    phase -= 2 * np.pi * np.round(phase[-1] / (2 * np.pi))  # no whole turns at high f
    return f, np.maximum(-phase / (2 * np.pi * f), 0.0)


# --- one indicator: filter, time -> distance, versine, segments --------------------------


@dataclass
class _SegmentAcc:
    """Versine samples of one segment pass of one indicator, in travel order."""

    k: int
    values: list[np.ndarray] = field(default_factory=list)  # (2, m) mm
    valid: list[np.ndarray] = field(default_factory=list)  # (2, m) bool
    x: list[np.ndarray] = field(default_factory=list)
    t: list[np.ndarray] = field(default_factory=list)
    v: list[np.ndarray] = field(default_factory=list)
    pos_bad: bool = False
    slow: bool = False
    chunk_flags: bool = False


@dataclass(frozen=True)
class _IndicatorResult:
    """One indicator's view of one segment pass."""

    indicator: int  # 0 top6, 1 align10
    k: int
    direction: int
    run: int
    stat_mm: tuple[float | None, float | None]  # per rail, None when below min_coverage
    coverage: tuple[float, float]
    t_mid: float
    speed_mps: float
    pos_bad: bool
    slow: bool
    chunk_flags: bool


class _IndicatorChain:
    """Band-pass + double integration, time -> distance and versine for two rails."""

    def __init__(self, cfg: ExtractionConfig, indicator: int) -> None:
        chord_m = INDICATOR_CHORDS_M[indicator]
        self.cfg, self.chord_m, self.indicator = cfg, chord_m, indicator
        self.low_hz = BANDS_HZ[chord_m]
        self.sos = displacement_sos(cfg, self.low_hz)
        self.sos_zi = signal.sosfilt_zi(self.sos)  # (sections, 2)
        self.delay_f, self.delay_s = phase_delay_table(self.sos, cfg.fs_hz, self.low_hz)
        self.delay_lambda = cfg.delay_wavelength_chords * chord_m
        self.settle_s = cfg.settle_cycles / self.low_hz
        self.h = half_chord_samples(cfg.spacing_m, chord_m)
        self.inset_m = statistic_inset_m(chord_m)
        self.reset(-math.inf)

    def reset(self, t_start: float) -> None:
        """Forget the filter state; samples before ``t_start + settle_s`` are invalid."""
        self.zi: np.ndarray | None = None
        self.valid_from = t_start + self.settle_s
        self.bad_until = np.full(2, -math.inf)  # per rail: flagged channel + settling
        self._end_run()

    def _end_run(self) -> None:
        """Forget the distance-domain state (gap, reversal): the grid restarts."""
        self.direction = 0
        self.prev: tuple[np.ndarray, np.ndarray] | None = None  # last sample's packed rows
        self.next_j: int | None = None
        self.tail: tuple[np.ndarray, np.ndarray] | None = None  # last 2h grid points
        self.acc: _SegmentAcc | None = None

    def filter(self, x: np.ndarray) -> np.ndarray:
        """Acceleration (2, m) m/s^2 at 500 Hz -> band-passed displacement (2, m) in m."""
        if self.zi is None:  # steady state for the first value: no gravity step transient
            self.zi = self.sos_zi[:, None, :] * x[None, :, :1]
        y, self.zi = signal.sosfilt(self.sos, x, axis=-1, zi=self.zi)
        return y

    def delay(self, v: np.ndarray) -> np.ndarray:
        """Band-pass delay (s) at the speed-dependent frequency of the index's energy."""
        f = np.maximum(v, 1e-3) / self.delay_lambda
        return np.minimum(np.interp(f, self.delay_f, self.delay_s), self.cfg.max_delay_s)

    def flag_rail(self, side: int, until: float) -> None:
        self.bad_until[side] = max(self.bad_until[side], until + self.settle_s)

    def distance(
        self,
        c: np.ndarray,
        t: np.ndarray,
        v: np.ndarray,
        d: np.ndarray,
        pos_ok: bool,
        chunk_flags: bool,
        line: LineSegments,
        run: int,
        counters: Counters,
    ) -> list[_IndicatorResult]:
        """Samples at chainages ``c`` (m,) -> grid -> versine -> finished segment passes."""
        m = c.size
        # Packed per-sample rows. Floats: travel coordinate u (set per piece), t, v, the two
        # rails' displacement. Flags: rail ok (2), position ok, no chunk-wide finding.
        fl = np.empty((5, m))
        fl[1], fl[2], fl[3:] = t, v, d
        ok = np.empty((4, m), dtype=bool)
        np.greater_equal(
            t[None, :], np.maximum(self.valid_from, self.bad_until)[:, None], out=ok[:2]
        )
        ok[2], ok[3] = pos_ok, not chunk_flags
        out: list[_IndicatorResult] = []
        # Direction of travel per sample; a standstill keeps the current direction.
        step = np.empty(m)
        step[0] = c[0] - (c[0] if self.prev is None else self.prev[0][0] * self.direction)
        step[1:] = c[1:] - c[:-1]
        np.sign(step, out=step)
        start = 0
        while start < m:
            if self.direction == 0:
                nz = np.flatnonzero(step[start:])
                if nz.size == 0:
                    break  # no motion yet: nothing to place on the grid
                self.direction = int(step[start + nz[0]])
            turn = np.flatnonzero(step[start:] == -self.direction)
            stop = m if turn.size == 0 else start + int(turn[0])
            if stop > start:
                sl = slice(start, stop)
                fl[0, sl] = self.direction * c[sl]
                out += self._piece(fl[:, sl], ok[:, sl], line, run)
            if stop < m:  # reversal: finish what is open, restart the grid
                out += self._finish(line, run)
                counters.reversals += 1
                last = self.prev
                self._end_run()
                self.direction = int(step[stop])
                if last is not None:  # the turning point starts the new run's grid
                    last[0][0] = -last[0][0]
                    self.prev = last
            start = stop
        return out

    def _piece(self, fl: np.ndarray, ok: np.ndarray, line, run) -> list[_IndicatorResult]:
        """Monotone samples in travel coordinate ``u = fl[0] = direction * chainage``."""
        dx = self.cfg.spacing_m
        if self.prev is not None:
            fl = np.concatenate([self.prev[0][:, None], fl], axis=1)
            ok = np.concatenate([self.prev[1][:, None], ok], axis=1)
        self.prev = (fl[:, -1].copy(), ok[:, -1].copy())
        u = fl[0]
        if self.next_j is None:
            self.next_j = math.ceil(u[0] / dx - 1e-9)
        j1 = math.floor(u[-1] / dx + 1e-9)
        if j1 < self.next_j or u.size < 2:
            return []
        j = np.arange(self.next_j, j1 + 1, dtype=np.float64)
        self.next_j = j1 + 1
        uj = j * dx
        i = np.searchsorted(u, uj, side="right") - 1
        np.clip(i, 0, u.size - 2, out=i)
        lo, hi = fl[:, i], fl[:, i + 1]
        f = np.clip((uj - lo[0]) / np.maximum(hi[0] - lo[0], 1e-12), 0.0, 1.0)
        grid = lo + f * (hi - lo)
        grid[0] = j  # rows: grid index, t, v, d_left, d_right
        gok = ok[:, i] & ok[:, i + 1]
        return self._versine(grid, gok, line, run)

    def _versine(self, grid, gok, line: LineSegments, run: int) -> list[_IndicatorResult]:
        h = self.h
        if self.tail is not None:
            c0 = max(h, self.tail[0].shape[1] - h)
            grid = np.concatenate([self.tail[0], grid], axis=1)
            gok = np.concatenate([self.tail[1], gok], axis=1)
        else:
            c0 = h
        n = grid.shape[1]
        keep = max(0, n - 2 * h)
        self.tail = (grid[:, keep:], gok[:, keep:])
        c1 = n - h  # centres [c0, c1)
        if c1 <= c0:
            return []
        vers = chord_versine(grid[3:, c0 - h : c1 + h], self.cfg.spacing_m, self.chord_m)
        vers *= 1e3  # mm
        cen = slice(c0, c1)
        valid = gok[:2, c0 - h : c1 - h] & gok[:2, cen] & gok[:2, c0 + h : c1 + h]
        x = (self.direction * self.cfg.spacing_m) * grid[0, cen]
        tv = grid[1:3, cen]
        flags = gok[2:, cen]
        seg = line.locate(x, self.inset_m)  # the statistic's chord centres only
        out = []
        # split the centres into runs of one segment (usually one or two per chunk)
        bounds = [0, *(np.flatnonzero(seg[1:] != seg[:-1]) + 1).tolist(), seg.size]
        for a, b in itertools.pairwise(bounds):
            k = int(seg[a])
            if self.acc is not None and self.acc.k != k:
                out += self._finish(line, run)
            if k < 0:
                continue
            if self.acc is None:
                self.acc = _SegmentAcc(k)
            acc, s = self.acc, slice(a, b)
            acc.values.append(vers[:, s])
            acc.valid.append(valid[:, s])
            acc.x.append(x[s])
            acc.t.append(tv[0, s])
            acc.v.append(tv[1, s])
            acc.pos_bad |= not bool(flags[0, s].all())
            acc.slow |= bool((tv[1, s] < self.cfg.v_ref_mps).any())
            acc.chunk_flags |= not bool(flags[1, s].all())
        return out

    def _finish(self, line: LineSegments, run: int) -> list[_IndicatorResult]:
        """Close the open segment pass (the versine has left it, or the run ended)."""
        acc, self.acc = self.acc, None
        if acc is None:
            return []
        cfg = self.cfg
        j_lo, j_hi = statistic_centres(
            line.starts[acc.k], line.ends[acc.k], cfg.spacing_m, self.chord_m
        )
        n_expected = j_hi - j_lo
        values = np.concatenate(acc.values, axis=1)
        valid = np.concatenate(acc.valid, axis=1)
        x, t, v = (np.concatenate(a) for a in (acc.x, acc.t, acc.v))
        stats: list[float | None] = []
        cover = []
        for side in range(2):
            m = valid[side]
            cov = min(1.0, int(m.sum()) / n_expected)
            cover.append(cov)
            ok = cov >= cfg.min_coverage
            stats.append(float(segment_statistic(values[side, m])) if ok else None)
        mid = 0.5 * (line.starts[acc.k] + line.ends[acc.k])
        order = np.argsort(x, kind="stable")
        t_mid = float(np.interp(mid, x[order], t[order]))
        return [
            _IndicatorResult(
                self.indicator,
                acc.k,
                self.direction,
                run,
                (stats[0], stats[1]),
                (cover[0], cover[1]),
                t_mid,
                float(v.mean()),
                acc.pos_bad,
                acc.slow,
                acc.chunk_flags,
            )  # fmt: skip
        ]

    def finish(self, line: LineSegments | None, run: int) -> list[_IndicatorResult]:
        out = self._finish(line, run) if line is not None else []
        self._end_run()
        return out


# --- one unit ----------------------------------------------------------------------------


class UnitPipeline:
    """The streaming extraction of one (train, unit); feed its chunks in order.

    Parameters
    ----------
    train, unit : str
        Whose chunks these are (copied into the OnboardIndex).
    segments : SegmentTable
        The network's segments.
    config : ExtractionConfig
    """

    def __init__(
        self, train: str, unit: str, segments: SegmentTable, config: ExtractionConfig | None = None
    ) -> None:
        self.train, self.unit, self.segments = train, unit, segments
        self.cfg = cfg = config or ExtractionConfig()
        self.fir = decimation_fir(cfg)
        self.fir_delay_s = (cfg.fir_taps - 1) / 2 / cfg.rate_hz
        self.chains = [_IndicatorChain(cfg, i) for i in range(len(INDICATOR_CHORDS_M))]
        self.counters = Counters()
        self._recent: deque[tuple[int, float]] = deque(maxlen=RECENT_CHUNKS)  # (seq, t0) seen
        # channel names -> (their columns in the order of _INDICATOR_COLUMNS, -1 absent;
        # the indicators they allow)
        self._columns: tuple[tuple[str, ...], np.ndarray, tuple[int, ...]] | None = None
        self._measured: tuple[int, ...] = ()  # the indicators of the chunks in this run
        self._pending: dict[tuple[int, int, int], _IndicatorResult] = {}
        self._run = 0
        self._line: LineSegments | None = None
        self._reset_needed = True
        self._hist: np.ndarray | None = None
        self._skip = 0
        self._knots = np.empty((3, 0))
        self._t_end = -math.inf

    # -- state ------------------------------------------------------------------------------

    def _reset(self, t0: float) -> list[OnboardIndex]:
        """Restart every filter (a gap, the first chunk, a line change, time backwards)."""
        out = self._finish_all()
        self._hist = None  # last (taps - 1) input samples (4, taps - 1)
        self._skip = 0  # index in the next chunk of the next kept sample
        self._knots = np.empty((3, 0))  # (t, chainage, speed) kept from earlier chunks
        self._t_end = -math.inf
        for chain in self.chains:
            chain.reset(t0)
        self._run += 1
        self.counters.resets += 1
        self._reset_needed = False
        return out

    def _finish_all(self) -> list[OnboardIndex]:
        results: list[_IndicatorResult] = []
        for chain in self.chains:
            results += chain.finish(self._line, self._run)
        out = self._combine(results)
        for key in list(self._pending):  # the other indicator can no longer deliver
            out += self._decide(self._pending.pop(key), None)
        return out

    def flush(self) -> list[OnboardIndex]:
        """End of the stream: close the open passes (they are partial: counted, skipped)."""
        out = self._finish_all()
        self._reset_needed = True
        return out

    # -- one chunk --------------------------------------------------------------------------

    def _columns_of(self, chunk: PositionedChunk) -> tuple[np.ndarray, tuple[int, ...]]:
        """The columns of top6 left, right, align10 left, right (-1: absent) and the
        indicators whose two rails are both there (Top6 needs the vertical channels, Align10
        the lateral ones)."""
        names = tuple(chunk.channels)
        if self._columns is None or self._columns[0] != names:
            measured = tuple(
                i for i, pair in enumerate(_INDICATOR_COLUMNS) if all(c in names for c in pair)
            )
            if not measured:
                need = " or ".join(str(list(pair)) for pair in _INDICATOR_COLUMNS)
                raise SchemaError(f"channels: need {need}, have {list(names)}")
            cols = [
                names.index(c) if c in names else -1 for pair in _INDICATOR_COLUMNS for c in pair
            ]
            self._columns = (names, np.array(cols), measured)
        return self._columns[1], self._columns[2]

    def process(self, chunk: PositionedChunk) -> list[OnboardIndex]:
        """One chunk in; the OnboardIndex of every segment pass it completed out."""
        cfg = self.cfg
        if abs(chunk.rate_hz - cfg.rate_hz) > 1e-6 * cfg.rate_hz:
            raise SchemaError(f"rate_hz: {chunk.rate_hz} Hz, extraction expects {cfg.rate_hz} Hz")
        cols, measured = self._columns_of(chunk)
        identity = (chunk.seq, chunk.t0)  # after the checks: a refused chunk is not seen
        if identity in self._recent:
            self.counters.duplicates += 1
            return []
        self._recent.append(identity)
        line = self.segments.lines.get(chunk.line)
        if line is None:
            self.counters.unknown_line += 1
            return self.flush()
        samples = chunk.samples.array()
        n = samples.shape[0]
        self.counters.chunks += 1
        self.counters.samples += n
        out: list[OnboardIndex] = []
        fs_in = cfg.rate_hz
        if (
            self._reset_needed
            or chunk.gap_before
            or line is not self._line
            or chunk.t0 < self._t_end - 0.5 / fs_in
            or measured != self._measured
        ):
            out += self._reset(chunk.t0)
            self._line = line
            self._measured = measured
        self._t_end = chunk.t0 + n / fs_in
        if n == 0:
            return out
        x = np.zeros((4, n))  # an absent channel's rows stay 0; its chain does not run
        x[cols >= 0] = samples[:, cols[cols >= 0]].T
        y, t = self._decimate(x, chunk.t0)
        self._flag_rails(chunk)
        chunk_flags = any(f.split(":", 1)[0] in _CHUNK_FLAGS for f in chunk.sensor_flags)
        if y.shape[1] == 0:
            self._keep_knots(chunk)
            return out
        kt, kc, kv = self._knots_with(chunk)
        v = np.interp(t, kt, kv)
        results: list[_IndicatorResult] = []
        for i in measured:
            chain = self.chains[i]
            d = chain.filter(y[2 * i : 2 * i + 2])
            ts = t - chain.delay(v)  # when the unit was over what this output shows
            c = np.interp(ts, kt, kc)
            vs = np.interp(ts, kt, kv)
            results += chain.distance(
                c, ts, vs, d, chunk.position_ok, chunk_flags, line, self._run, self.counters
            )
        self._keep_knots(chunk)
        out += self._combine(results)
        return out

    def _decimate(self, x: np.ndarray, t0: float) -> tuple[np.ndarray, np.ndarray]:
        """Streaming polyphase FIR decimation; returns (4, m) and the m output times."""
        cfg = self.cfg
        q, taps = cfg.decimation, cfg.fir_taps
        if self._hist is None:  # steady state: the first sample held in the past
            self._hist = np.repeat(x[:, :1], taps - 1, axis=1)
        buf = np.concatenate([self._hist, x], axis=1)
        n, skip = x.shape[1], self._skip
        idx = np.arange(skip, n, q)  # kept samples, as indices in this chunk
        m = idx.size
        if m:
            # upfirdn output k*q is the FIR window ending at buf[skip + k*q]; the window
            # ending at chunk index i (buf index i + taps - 1) is output (taps - 1) / q + k.
            first = (taps - 1) // q
            y = signal.upfirdn(self.fir, buf[:, skip:], 1, q, axis=-1)[:, first : first + m]
        else:
            y = np.empty((4, 0))
        self._hist = buf[:, -(taps - 1) :]
        self._skip = skip + q * m - n
        t = t0 + idx / cfg.rate_hz - self.fir_delay_s
        return y, t

    def _flag_rails(self, chunk: PositionedChunk) -> None:
        if not chunk.sensor_flags:
            return
        t_end = chunk.t0 + chunk.samples.shape[0] / chunk.rate_hz
        for flag in chunk.sensor_flags:
            kind, _, channel = flag.partition(":")
            if kind in _RAIL_FLAGS and channel in _CHANNEL_SIDES:
                ind, side = _CHANNEL_SIDES[channel]
                self.chains[ind].flag_rail(side, t_end)

    def _knots_with(self, chunk: PositionedChunk) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        kt = chunk.knot_t.array()
        old = self._knots[:, self._knots[0] < kt[0]]
        new = (kt, chunk.knot_chainage_m.array(), chunk.knot_speed_mps.array())
        return tuple(np.concatenate([o, n]) for o, n in zip(old, new, strict=True))

    def _keep_knots(self, chunk: PositionedChunk) -> None:
        """Keep the knots of the last few seconds: the band-pass delay looks back <= 1.5 s."""
        kt, kc, kv = self._knots_with(chunk)
        keep = kt >= kt[-1] - 2.0 * self.cfg.max_delay_s - 1.0
        keep[-2:] = True
        self._knots = np.stack([kt[keep], kc[keep], kv[keep]])

    # -- passes -----------------------------------------------------------------------------

    def _combine(self, results: list[_IndicatorResult]) -> list[OnboardIndex]:
        """Gather the measured indicators' views of a pass; decide once all are in."""
        out: list[OnboardIndex] = []
        for r in results:
            if len(self._measured) == 1:  # one indicator measured: nothing to wait for
                out += self._decide(r, None)
                continue
            key = (r.run, r.k, r.direction)
            other = self._pending.pop(key, None)
            if other is None:
                self._pending[key] = r
                continue
            out += self._decide(other, r)
        return out

    def _decide(self, a: _IndicatorResult, b: _IndicatorResult | None) -> list[OnboardIndex]:
        """The index of a pass from the views of the indicators measured (``b`` None: ``a``
        alone, which is a pass skipped when the unit measures both)."""
        c = self.counters
        views = sorted([a] if b is None else [a, b], key=lambda r: r.indicator)
        if any(r.pos_bad for r in views):
            c.skipped_position += 1
            return []
        if any(r.slow for r in views):
            c.skipped_slow += 1
            return []
        if len(views) < len(self._measured) or any(
            all(s is None for s in r.stat_mm) for r in views
        ):
            c.skipped_coverage += 1
            return []
        line = self._line
        assert line is not None
        stats: dict[int, float] = {}
        single = False
        for r in views:
            usable = [s for s in r.stat_mm if s is not None]
            single |= len(usable) < 2
            stats[r.indicator] = min(usable)
        if min(stats.values()) <= 0.0:
            c.skipped_coverage += 1
            return []
        if max(stats.values()) > INDEX_MAX_MM:  # not track geometry: a sensor fault
            c.skipped_implausible += 1
            return []
        coverage = min(max(r.coverage) for r in views)
        quality = (
            coverage
            * (0.5 if single else 1.0)
            * (0.9 if any(r.chunk_flags for r in views) else 1.0)
        )
        c.passes_indexed += 1
        first = views[0]  # Top6's view when measured: its chord's times and speeds
        return [
            OnboardIndex(
                line=line.line,
                segment=line.ids[first.k],
                train=self.train,
                unit=self.unit,
                t=first.t_mid,
                top6_mm=stats.get(0),
                align10_mm=stats.get(1),
                speed_mps=max(0.0, first.speed_mps),
                coverage=min(1.0, coverage),
                quality=min(1.0, quality),
                indicators=[INDICATORS[i] for i in sorted(stats)],
            )
        ]


class Extractor:
    """Pipelines per (train, unit), created on demand; the core the adapter drives.

    ``process(chunk)`` returns the OnboardIndex messages the chunk completed. Chunks of one
    unit must come in order (ingestion reorders and drops duplicates; it marks a gap with
    ``gap_before``, which restarts that unit's state). A chunk with the ``(seq, t0)`` of one
    of the unit's last ``RECENT_CHUNKS`` is dropped and counted (``duplicates``): a
    restarted ingestion sends again, identical, what it sent after its last checkpoint.
    """

    def __init__(self, segments: SegmentTable, config: ExtractionConfig | None = None) -> None:
        self.segments = segments
        self.config = config or ExtractionConfig()
        self.pipelines: dict[tuple[str, str], UnitPipeline] = {}

    def process(self, chunk: PositionedChunk) -> list[OnboardIndex]:
        key = (chunk.train, chunk.unit)
        pipeline = self.pipelines.get(key)
        if pipeline is None:
            pipeline = self.pipelines[key] = UnitPipeline(
                chunk.train, chunk.unit, self.segments, self.config
            )
        return pipeline.process(chunk)

    def flush(self) -> list[OnboardIndex]:
        """Close every open pass (end of a replay)."""
        out: list[OnboardIndex] = []
        for pipeline in self.pipelines.values():
            out += pipeline.flush()
        return out

    def counters(self) -> Counters:
        """The sum over all units."""
        total = Counters()
        for pipeline in self.pipelines.values():
            total.add(pipeline.counters)
        return total
