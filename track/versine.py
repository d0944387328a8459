"""Chord versine and THE segment statistic: the contract between simulator and extraction.

Both the simulator (which scales each segment's irregularity profile so that a TRC would
record ``exp(z)``) and the extraction service (which computes the on-board index from a
reconstructed profile) call these two functions, so the on-board index and the TRC value
are defined by the same arithmetic.

Profiles are in millimetres, sampled uniformly in distance along the track.
"""

from __future__ import annotations

import math

import numpy as np

TOP_CHORD_M = 6.0  # Top6: longitudinal level, vertical profile, 6 m chord
ALIGN_CHORD_M = 10.0  # Align10: alignment, lateral profile, 10 m chord
#: The statistic leaves this much of each segment end out: a chord that close to a boundary
#: may straddle it once positions are off by a metre (GPS, dead reckoning), and an
#: on-board unit then has the segment's value a little before it reaches the end — within
#: the same ~1 s raw chunk — rather than in the next chunk (at 40 m/s the decimation FIR's
#: 10 ms and one 0.25 m grid step take 0.65 m).
END_GUARD_M = 1.0


def statistic_inset_m(chord_m: float) -> float:
    """How far inside each segment end the statistic's chord centres start: ``L/2 + guard``."""
    return chord_m / 2.0 + END_GUARD_M


def statistic_centres(start_m: float, end_m: float, spacing_m: float, chord_m: float):
    """``(j_lo, j_hi)``: the grid points ``x_j = j dx`` that are the statistic's chord centres
    on the segment ``[start_m, end_m)``, ``j_lo <= j < j_hi``: those in ``[start + L/2 + g,
    end - L/2 - g)`` (:func:`statistic_inset_m`), a point on a bound to 1e-9 steps counted
    on the bound."""
    inset = statistic_inset_m(chord_m)
    return (
        math.ceil((start_m + inset) / spacing_m - 1e-9),
        math.ceil((end_m - inset) / spacing_m - 1e-9),
    )


def half_chord_samples(spacing_m: float, chord_m: float) -> int:
    """Half the chord in samples, ``h = L / (2 dx)``; ValueError unless it is a whole number."""
    if not (spacing_m > 0 and chord_m > 0):
        raise ValueError(f"spacing_m and chord_m must be > 0, got {spacing_m}, {chord_m}")
    h = round(chord_m / (2.0 * spacing_m))
    if h < 1 or abs(h * spacing_m - chord_m / 2.0) > 1e-9 * chord_m:
        raise ValueError(f"half chord {chord_m / 2} m is not a whole number of {spacing_m} m steps")
    return h


def chord_versine(profile, spacing_m: float, chord_m: float) -> np.ndarray:
    """Mid-chord versine of a uniformly sampled profile, along the last axis.

    .. math::

        v(x) = p(x) - \\tfrac{1}{2}\\left[p(x - L/2) + p(x + L/2)\\right]

    Parameters
    ----------
    profile : array_like, shape (..., n)
        Displacement in mm at ``x_i = x_0 + i dx``.
    spacing_m : float
        Sample spacing ``dx``; ``L / 2`` must be a whole number ``h`` of steps.
    chord_m : float
        Chord length ``L`` (``TOP_CHORD_M`` or ``ALIGN_CHORD_M``).

    Returns
    -------
    ndarray, shape (..., n - 2h)
        Only the points whose whole chord lies inside the array: ``v[..., j]`` is the
        versine at profile index ``j + h``, i.e. the valid slice is ``profile[..., h:n-h]``
        (``slice(h, n - h)`` with ``h = half_chord_samples(spacing_m, chord_m)``).
        Empty when ``n <= 2h``.

    Notes
    -----
    The versine is a linear, shift-invariant filter with the gain
    ``|1 - cos(pi L / lambda)|`` for a sinusoid of wavelength ``lambda``: it passes
    wavelengths around ``L`` (up to 2 at ``lambda = L``) and suppresses long ones.
    """
    p = np.asarray(profile, dtype=np.float64)
    h = half_chord_samples(spacing_m, chord_m)
    n = p.shape[-1]
    if n <= 2 * h:
        return p[..., :0]
    return p[..., h : n - h] - 0.5 * (p[..., : n - 2 * h] + p[..., 2 * h :])


def segment_statistic(versine, axis: int = -1) -> np.ndarray | float:
    """THE segment statistic: standard deviation of the chord versine over a segment, in mm.

    .. math::

        s = \\sqrt{\\frac{1}{N} \\sum_{i=1}^{N} (v_i - \\bar v)^2}

    over the ``N`` versine samples whose whole chord lies in the segment at least
    ``END_GUARD_M`` from its ends, i.e. chord centres in ``[start + L/2 + g, end - L/2 -
    g)`` (:func:`statistic_inset_m`): ``segment_statistic(chord_versine(p_seg, dx, L))``
    of the segment's own profile samples less the guard, ``p_seg`` (population standard
    deviation, ``ddof = 0``). A segment's value thus depends on its own track only, and an
    on-board unit has it just before it reaches the segment's end (not half a chord
    after).
    EN 13848-6 rates longitudinal level and alignment
    quality by standard deviations over 200 m; the standard deviation is preferred to
    the peak because it is stable under resampling, noise and short artefacts, and its
    log is close to Gaussian (paper Fig. 3). It is linear in the profile's amplitude,
    ``s(a p) = |a| s(p)``, which is how the simulator scales a profile to ``exp(z)``.

    Parameters
    ----------
    versine : array_like, shape (..., N)
        Versine samples (mm) of one segment; NaN samples are not allowed.
    axis : int
        Axis over the segment's samples.
    """
    return np.std(np.asarray(versine, dtype=np.float64), axis=axis)
