"""Spatial track irregularity profiles: what the TRC measures and what the wheels roll over.

Every segment has four profiles in mm on a uniform grid (``spacing_m``, default 0.25 m):
vertical (longitudinal level) and lateral (alignment), left and right rail, in the order
``PROFILE_CHANNELS``. A segment's shape is random with the one-sided spectrum of the
German/FRA track spectra (``TrackSpectrum``), band-limited to wavelengths 1-70 m, and is
fixed between tampings: it is seeded by ``(seed, line, segment index, epoch)``, where the
caller bumps ``epoch`` at every tamping. Its amplitude follows the true state ``z``:

* each rail is scaled on its own, so that for BOTH rails
  ``segment_statistic(chord_versine(p, dx, 6 m)) == exp(z_top)`` (vertical) and
  ``... 10 m ... == exp(z_align)`` (lateral) over the segment's samples, exactly. The TRC
  value therefore refers to either rail (both are equal). This makes ``min(left, right)``
  of the on-board indices a sensible estimator: without artefacts both sides estimate the
  same number, and a one-rail outlier can only raise one side.
* left and right share a common component plus a smaller independent one
  (``independent_ratio`` of the common amplitude, before scaling), as measured rails do.

The line-continuous profile (``LineProfile.sample``) is built from the segments' shapes:
each shape extends ``margin_m`` beyond its segment's ends, and neighbours are cross-faded
over ``[boundary - margin, boundary + margin]`` with power-preserving weights
(``cos``/``sin`` of a ramp, so the variance of two independent shapes is kept). Within
``margin_m`` of a boundary the wheels thus roll over a blend of two segments: the on-board
index of a segment differs slightly from its TRC value, as a realistic source of noise.
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass

import numpy as np
from scipy import fft

from track.versine import (
    ALIGN_CHORD_M,
    END_GUARD_M,
    TOP_CHORD_M,
    chord_versine,
    half_chord_samples,
    segment_statistic,
)

PROFILE_CHANNELS = ("vertical_left", "vertical_right", "lateral_left", "lateral_right")
_CHORDS_M = (TOP_CHORD_M, TOP_CHORD_M, ALIGN_CHORD_M, ALIGN_CHORD_M)
_JOINT_TAG = 0x4A4F494E  # "JOIN": keeps the joints' random stream apart from the shapes'


@dataclass(frozen=True)
class TrackSpectrum:
    """One-sided irregularity spectrum (German track spectra form), per rad/m.

    .. math::

        S(\\Omega) = \\frac{A\\,\\Omega_c^2}{(\\Omega^2 + \\Omega_r^2)(\\Omega^2 + \\Omega_c^2)},
        \\qquad \\frac{2\\pi}{\\lambda_{max}} \\le \\Omega \\le \\frac{2\\pi}{\\lambda_{min}}

    ``A`` is irrelevant here (every shape is rescaled to ``exp(z)``); the defaults are the
    low-disturbance values of the German spectrum (``Omega_c`` = 0.8246, ``Omega_r`` =
    0.0206 rad/m), used for both level and alignment. Below ``lambda ~ 2 pi / Omega_c``
    = 7.6 m the spectrum falls as ``Omega^-4``, between that and ``2 pi / Omega_r`` as
    ``Omega^-2``: most of the energy sits at the long wavelengths.
    """

    omega_c: float = 0.8246  # rad/m
    omega_r: float = 0.0206  # rad/m
    min_wavelength_m: float = 1.0
    max_wavelength_m: float = 70.0

    def psd(self, omega) -> np.ndarray:
        """``S(Omega)`` (A = 1) inside the band, 0 outside."""
        om = np.asarray(omega, dtype=np.float64)
        s = self.omega_c**2 / ((om**2 + self.omega_r**2) * (om**2 + self.omega_c**2))
        band = (om >= 2 * np.pi / self.max_wavelength_m) & (om <= 2 * np.pi / self.min_wavelength_m)
        return np.where(band, s, 0.0)


def line_rng(seed: int, line_id: str, *stream: int) -> np.random.Generator:
    """A generator seeded by ``(seed, crc32(line_id), *stream)``: stable across runs."""
    return np.random.default_rng([seed, zlib.crc32(line_id.encode()), *stream])


class LineProfile:
    """The four irregularity profiles of one line, built from its segments' shapes.

    Parameters
    ----------
    line_id : str
        Stable line id (seeds the shapes).
    segment_bounds : array_like, shape (S, 2)
        ``[start, end)`` chainages in metres, contiguous and increasing; snapped to the
        grid. Every segment must be longer than ``2 * margin_m``.
    seed : int
        World seed.
    spacing_m : float
        Grid spacing; half of each chord must be a whole number of steps.
    margin_m : float
        Extension of each shape beyond its segment, and half-width of the cross-fade;
        at least half the longest chord (5 m) so the TRC versine of every sample of the
        segment is defined by its own shape.
    spectrum : TrackSpectrum
        Wavelength content.
    independent_ratio : float
        Amplitude of each rail's independent component relative to the common one.
    jointed_fraction : float
        Fraction of the line (by 1 km blocks) on jointed rail; the rest is welded.

    Attributes
    ----------
    joints_m : ndarray, shape (J,)
        Sorted chainages of rail joints and welds (impulsive events).
    joint_gain : ndarray, shape (J,)
        Relative severity: 1 around a joint, 0.1-0.4 at a weld.
    """

    def __init__(
        self,
        line_id: str,
        segment_bounds,
        seed: int,
        spacing_m: float = 0.25,
        margin_m: float = 5.0,
        spectrum: TrackSpectrum | None = None,
        independent_ratio: float = 0.5,
        jointed_fraction: float = 0.2,
    ) -> None:
        bounds = np.asarray(segment_bounds, dtype=np.float64)
        if bounds.ndim != 2 or bounds.shape[1] != 2 or len(bounds) == 0:
            raise ValueError(f"segment_bounds: expected shape (S, 2), got {bounds.shape}")
        if not np.allclose(bounds[1:, 0], bounds[:-1, 1]):
            raise ValueError("segment_bounds: segments must be contiguous")
        if margin_m < ALIGN_CHORD_M / 2:
            raise ValueError(f"margin_m must be >= {ALIGN_CHORD_M / 2} m, got {margin_m}")
        for chord in _CHORDS_M:
            half_chord_samples(spacing_m, chord)  # raises unless the grid fits the chords
        self.line_id, self.seed, self.spacing_m = line_id, seed, spacing_m
        self.spectrum = spectrum or TrackSpectrum()
        self.independent_ratio = independent_ratio
        self.hm = round(margin_m / spacing_m)  # margin in samples
        self.guard = round(END_GUARD_M / spacing_m)  # the statistic's end guard in samples
        # Line grid x_i = x0 + i dx covers [first start - margin, last end + margin].
        self.x0 = bounds[0, 0] - self.hm * spacing_m
        edges = np.round((np.r_[bounds[:, 0], bounds[-1, 1]] - self.x0) / spacing_m).astype(int)
        if (np.diff(edges) <= 2 * self.hm).any():
            raise ValueError(f"every segment must be longer than 2 * margin_m = {2 * margin_m} m")
        self.edges = edges  # segment k owns grid samples [edges[k], edges[k+1])
        self.n_segments = len(bounds)
        self.line = np.zeros((4, edges[-1] + self.hm + 1))
        self._z = np.full((self.n_segments, 2), np.nan)
        self._epoch = np.full(self.n_segments, -1, dtype=np.int64)
        self._shapes: dict[int, tuple[int, np.ndarray]] = {}  # k -> (epoch, unit shape)
        ramp = (np.arange(2 * self.hm) + 0.5) * (np.pi / 2) / (2 * self.hm)
        self._rise, self._fall = np.sin(ramp), np.cos(ramp)
        self.joints_m, self.joint_gain = self._make_joints(jointed_fraction)

    # -- segments --------------------------------------------------------------------

    def extent(self, k: int) -> tuple[int, int]:
        """Grid index range ``[e0, e1)`` of segment ``k``'s extended shape."""
        return int(self.edges[k] - self.hm), int(self.edges[k + 1] + self.hm)

    def unit_shape(self, k: int, epoch: int) -> np.ndarray:
        """Segment ``k``'s shape at ``epoch``, scaled so each channel's statistic is 1 mm.

        Returns
        -------
        ndarray, shape (4, n_ext)
            ``PROFILE_CHANNELS`` over ``extent(k)``.

        Notes
        -----
        White Gaussian Fourier coefficients are shaped by ``sqrt(S(Omega))`` and inverse
        transformed on a periodic grid padded by ``max_wavelength_m``, so the slice taken
        is a stationary sample with the full long-wavelength content. Each rail is
        ``c + r d`` (common ``c``, independent ``d``, ratio ``r``), then divided by its
        own segment statistic.
        """
        cached = self._shapes.get(k)
        if cached is not None and cached[0] == epoch:
            return cached[1]
        e0, e1 = self.extent(k)
        n_ext, dx = e1 - e0, self.spacing_m
        n = fft.next_fast_len(n_ext + int(np.ceil(self.spectrum.max_wavelength_m / dx)), real=True)
        omega = 2 * np.pi * fft.rfftfreq(n, dx)
        amp = np.sqrt(self.spectrum.psd(omega))
        rng = line_rng(self.seed, self.line_id, k, epoch)
        coef = rng.standard_normal((6, omega.size)) + 1j * rng.standard_normal((6, omega.size))
        w = fft.irfft(coef * amp, n, axis=-1)[:, :n_ext]  # [c_v, d_vl, d_vr, c_l, d_ll, d_lr]
        r = self.independent_ratio
        shape = np.stack([w[0] + r * w[1], w[0] + r * w[2], w[3] + r * w[4], w[3] + r * w[5]])
        shape /= self._statistics(shape)[:, None]
        self._shapes[k] = (epoch, shape)
        return shape

    def _statistics(self, ext: np.ndarray) -> np.ndarray:
        """Segment statistic per channel of an extended shape, over the segment's samples."""
        out = np.empty(4)
        for c, chord in enumerate(_CHORDS_M):
            g = self.hm + self.guard  # the segment's own samples, less the end guard
            own = ext[c, g : ext.shape[1] - g]
            out[c] = segment_statistic(chord_versine(own, self.spacing_m, chord))
        return out

    def segment_profile(self, k: int) -> tuple[np.ndarray, np.ndarray, slice]:
        """Segment ``k``'s own (unblended) profile: what the TRC measures.

        Returns
        -------
        x : ndarray, shape (n_ext,)
            Chainages of the extended shape (m).
        p : ndarray, shape (4, n_ext)
            ``PROFILE_CHANNELS`` in mm, scaled to ``exp(z)``.
        inner : slice
            The segment's own samples within ``x`` (chainage in ``[start, end)``).
        """
        if np.isnan(self._z[k]).any():
            raise ValueError(f"segment {k}: no state yet, call update() first")
        e0, e1 = self.extent(k)
        p = self.unit_shape(k, int(self._epoch[k])) * self._scale(k)[:, None]
        return self.x0 + self.spacing_m * np.arange(e0, e1), p, slice(self.hm, e1 - e0 - self.hm)

    def segment_statistics(self, k: int) -> np.ndarray:
        """The four channels' segment statistics of segment ``k`` (equal to ``exp(z)``)."""
        return self._statistics(self.segment_profile(k)[1])

    def _scale(self, k: int) -> np.ndarray:
        ez = np.exp(self._z[k])
        return np.array([ez[0], ez[0], ez[1], ez[1]])

    # -- the line ----------------------------------------------------------------------

    def update(self, z, epoch) -> np.ndarray:
        """Set the true state of every segment; rebuild the line where it changed.

        Parameters
        ----------
        z : array_like, shape (S, 2)
            ``[ln Top6_mm, ln Align10_mm]`` per segment.
        epoch : array_like, shape (S,)
            Tamping count per segment: a new value draws a fresh shape.

        Returns
        -------
        ndarray
            Indices of the rebuilt segments.
        """
        z = np.asarray(z, dtype=np.float64)
        epoch = np.asarray(epoch, dtype=np.int64)
        if z.shape != (self.n_segments, 2) or epoch.shape != (self.n_segments,):
            raise ValueError(f"z, epoch: expected ({self.n_segments}, 2), ({self.n_segments},)")
        if not np.isfinite(z).all():
            raise ValueError("z: contains NaN or inf")
        changed = np.flatnonzero((z != self._z).any(axis=1) | (epoch != self._epoch))
        self._z[changed], self._epoch[changed] = z[changed], epoch[changed]
        for k in changed:  # a loop over segments, not samples
            e0, e1 = self.extent(k)
            self.line[:, e0:e1] = 0.0
            for j in (k - 1, k, k + 1):
                if 0 <= j < self.n_segments and not np.isnan(self._z[j, 0]):
                    a0, a1 = self.extent(j)
                    lo, hi = max(a0, e0), min(a1, e1)
                    contrib = self._weight(j) * self.unit_shape(j, int(self._epoch[j]))
                    self.line[:, lo:hi] += self._scale(j)[:, None] * contrib[:, lo - a0 : hi - a0]
        return changed

    def _weight(self, k: int) -> np.ndarray:
        """Cross-fade weight of segment ``k`` over its extent (1 at the line's two ends)."""
        e0, e1 = self.extent(k)
        w = np.ones(e1 - e0)
        m2 = 2 * self.hm
        if k > 0:
            w[:m2] = self._rise
        if k < self.n_segments - 1:
            w[-m2:] = self._fall
        return w

    def sample(self, chainage_m, which: int | str | None = None) -> np.ndarray:
        """Profile displacement (mm) at chainages, by linear interpolation on the grid.

        Parameters
        ----------
        chainage_m : array_like, shape (...)
            Chainages; clamped to the grid's range.
        which : int or str or None
            One of ``PROFILE_CHANNELS`` (name or index), or None for all four.

        Returns
        -------
        ndarray, shape (...) or (4, ...)
        """
        u = (np.asarray(chainage_m, dtype=np.float64) - self.x0) / self.spacing_m
        u = np.clip(u, 0.0, self.line.shape[1] - 1.000001)
        i = u.astype(np.intp)
        f = u - i
        rows = self.line if which is None else self.line[_channel(which)]
        return rows[..., i] * (1.0 - f) + rows[..., i + 1] * f

    def _make_joints(self, jointed_fraction: float) -> tuple[np.ndarray, np.ndarray]:
        """Joints every 25 m (+-0.3 m jitter) on jointed 1 km blocks, welds every 60-180 m."""
        rng = line_rng(self.seed, self.line_id, _JOINT_TAG)
        start = self.x0 + self.hm * self.spacing_m
        end = self.x0 + self.edges[-1] * self.spacing_m
        pos, gain = [], []
        for b0 in np.arange(start, end, 1000.0):  # per kilometre block
            b1 = min(b0 + 1000.0, end)
            if rng.random() < jointed_fraction:
                x = np.arange(b0 + 12.5, b1, 25.0)
                x = x + rng.normal(0.0, 0.3, x.size)
                g = rng.uniform(0.7, 1.3, x.size)
            else:
                x = b0 + np.cumsum(rng.uniform(60.0, 180.0, int((b1 - b0) // 60) + 1))
                x = x[x < b1]
                g = rng.uniform(0.1, 0.4, x.size)
            pos.append(x)
            gain.append(g)
        x, g = np.concatenate(pos), np.concatenate(gain)
        order = np.argsort(x, kind="stable")
        return x[order], g[order]


def _channel(which: int | str) -> int:
    if isinstance(which, str):
        if which not in PROFILE_CHANNELS:
            raise ValueError(f"which: {which!r} not in {PROFILE_CHANNELS}")
        return PROFILE_CHANNELS.index(which)
    return int(which)
