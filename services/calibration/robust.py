r"""Robustness rules of the calibration core: which TRC records, increments and
pairs are implausible, and whether a model may be published at all. Pure: numpy only.

Conventions as in :mod:`services.calibration.posterior`: ``z`` in ln mm, time in days.

Two tests judge the change between two records ``a < b`` of one segment with no tamping
between them (``dz = z_b - z_a``, ``dt = t_b - t_a``):

* **hard** (physical): every ``|dz_i| <= max_rate * dt + max_jump``. Geometry does not grow
  (or shrink, without a tamping) by a factor ``e`` in a month: ``max_rate`` = 1/30 ln mm per
  day; ``max_jump`` (0.5 ln mm) leaves room for the diffusion and the TRC's own noise over a
  short ``dt``;
* **soft** (robust, when the reference has enough increments): the standardised increment
  :math:`\mathbf x = \Delta\mathbf z/\sqrt{\Delta t}` (under the Wiener model
  :math:`N(\boldsymbol\mu\sqrt{\Delta t}, \boldsymbol\Sigma)`) is within ``k`` robust sd of
  the network's: :math:`|x_i - \operatorname{med}_i| \le k\cdot 1.4826\,\mathrm{MAD}_i`.

A record is blamed (quarantined) only when the data say it is the odd one out
(:func:`screen_segment`): a spike (implausible against both neighbours while they agree with
each other), the newest record of a run beyond the hard bound (until a later record confirms a
step), the oldest beyond the hard bound against a consistent pair after it, a post-tamping
level beyond ``k`` robust sd of the network's levels, or a record dated more than
``max_ahead_days`` after event time. Two consecutive records that agree make a step (an
unreported tamping, a real defect), not an outlier: they are kept.

A record of some indicators only (``z`` NaN for the others) is judged on the indicators it
measured: a test on an indicator that one of the two records lacks passes (NaN compares
false), and the references are per indicator over the values there are.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from schemas import Calibration, DegradationPosterior

__all__ = [
    "Reference",
    "Rules",
    "check_model",
    "network_references",
    "raw_pieces",
    "reference",
    "screen_segment",
]

MAD_TO_SD = 1.4826  # 1 / Phi^-1(3/4): MAD of a Gaussian in standard deviations
INCREMENT_SD_FLOOR = 1e-3  # ln mm / sqrt(day): the robust sd of increments is at least this
LEVEL_SD_FLOOR = 1e-2  # ln mm: and that of post-tamping levels


@dataclass(frozen=True)
class Reference:
    """Median and robust sd (1.4826 MAD, floored) per indicator of ``n`` samples."""

    median: np.ndarray
    scale: np.ndarray
    n: int

    def outlying(self, x: np.ndarray, k: float) -> np.ndarray:
        """Per row of ``x`` (..., n_ind): beyond ``k`` robust sd in some indicator."""
        return np.any(np.abs(x - self.median) > k * self.scale, axis=-1)


def reference(samples: np.ndarray, *, min_count: int, floor: float) -> Reference | None:
    """The robust reference of ``samples`` (N, n_ind; NaN where a record did not measure an
    indicator), per indicator on its finite values; NaN for an indicator with fewer than
    ``min_count`` (no soft test on it: NaN compares false), None when every one has."""
    samples = np.asarray(samples, dtype=np.float64)
    if not np.isnan(samples).any():
        if len(samples) < min_count:
            return None
        med = np.median(samples, axis=0)
        mad = np.median(np.abs(samples - med), axis=0)
        return Reference(med, np.maximum(MAD_TO_SD * mad, floor), len(samples))
    med, scale = np.full(samples.shape[1], np.nan), np.full(samples.shape[1], np.nan)
    counts = np.isfinite(samples).sum(axis=0)
    for i in np.flatnonzero(counts >= min_count):
        x = samples[np.isfinite(samples[:, i]), i]
        med[i] = np.median(x)
        scale[i] = max(MAD_TO_SD * float(np.median(np.abs(x - med[i]))), floor)
    if not np.isfinite(med).any():
        return None
    return Reference(med, scale, int(counts.max()))


def network_references(
    raw: list[tuple[np.ndarray, np.ndarray]], n: int, min_count: int
) -> tuple[Reference | None, Reference | None]:
    """The references of the standardised increments and of the post-tamping levels over
    every segment's :func:`raw_pieces` (``raw``; ``n`` indicators)."""
    empty = np.empty((0, n))
    x = np.concatenate([x for x, _ in raw] or [empty])
    levels = np.concatenate([lv for _, lv in raw] or [empty])
    return (
        reference(x, min_count=min_count, floor=INCREMENT_SD_FLOOR),
        reference(levels, min_count=min_count, floor=LEVEL_SD_FLOOR),
    )


def _runs(t: np.ndarray, tamping: np.ndarray) -> np.ndarray:
    """Run number of each record (sorted ``t``): a tamping in ``(t_{i-1}, t_i]`` starts one."""
    first = np.searchsorted(t, tamping, side="left")
    starts = np.zeros(t.size, dtype=np.int64)
    np.add.at(starts, first[first < t.size], 1)
    starts[0] = 0
    return np.cumsum(starts > 0)


def raw_pieces(t, z, tamping) -> tuple[np.ndarray, np.ndarray]:
    """The standardised increments ``dz / sqrt(dt)`` between consecutive records of a run, and
    the post-tamping levels (first record of a run after a tamping), before any screening:
    what :func:`reference` is built from (robust, so the outliers may stay in)."""
    t, z = np.asarray(t, dtype=np.float64), np.asarray(z, dtype=np.float64)
    if t.size == 0:
        return np.empty((0, z.shape[-1])), np.empty((0, z.shape[-1]))
    run = _runs(t, np.asarray(tamping, dtype=np.float64))
    same = run[1:] == run[:-1]
    x = np.diff(z, axis=0)[same] / np.sqrt(np.diff(t)[same])[:, None]
    starts = np.flatnonzero(np.r_[True, ~same])
    tamped = np.searchsorted(np.asarray(tamping, dtype=np.float64), t[starts], side="right") > 0
    return x, z[starts[tamped]]


@dataclass(frozen=True)
class Rules:
    """Thresholds of :func:`screen_segment` (from ``CalibratorConfig``)."""

    max_rate: float  # ln mm / day
    max_jump: float  # ln mm
    k: float  # robust sd
    max_ahead_days: float


def screen_segment(
    t,
    z,
    tamping,
    *,
    now_days: float,
    rules: Rules,
    increments: Reference | None,
    levels: Reference | None,
) -> dict[int, str]:
    """Records of one segment to leave out, ``{position in sorted t: reason}``.

    ``t`` sorted (days), ``z`` (L, n) ln mm, ``tamping`` sorted days, ``now_days`` event time.
    See the module docstring for the rules.
    """
    t, z = np.asarray(t, dtype=np.float64), np.asarray(z, dtype=np.float64)
    tamping = np.asarray(tamping, dtype=np.float64)
    out: dict[int, str] = {}
    if t.size == 0:
        return out
    ahead = t > now_days + rules.max_ahead_days
    for i in np.flatnonzero(ahead):
        out[int(i)] = (
            f"dated {t[i] - now_days:.0f} days after event time (more than "
            f"{rules.max_ahead_days:g}): left out until event time reaches it"
        )
    run = _runs(t, tamping)

    def why(a: int, b: int, soft: bool) -> str | None:
        dz, dt = z[b] - z[a], t[b] - t[a]
        bound = rules.max_rate * dt + rules.max_jump
        if np.any(np.abs(dz) > bound):
            i = int(np.nanargmax(np.abs(dz) - bound))
            return (
                f"change {dz[i]:+.3f} ln mm in {dt:.1f} days beyond {bound:.3f} "
                f"({rules.max_rate:.3g} ln mm/day + {rules.max_jump:g})"
            )
        if soft and increments is not None:
            x = dz / np.sqrt(dt)
            if increments.outlying(x, rules.k):
                d = np.abs(x - increments.median) / increments.scale
                i = int(np.nanargmax(d))
                return (
                    f"increment {dz[i]:+.3f} ln mm in {dt:.1f} days is {d[i]:.1f} robust sd "
                    f"from the network's (more than {rules.k:g})"
                )
        return None

    for r in np.unique(run[~ahead]):
        idx = [int(i) for i in np.flatnonzero((run == r) & ~ahead)]
        starts_after_tamping = bool(np.any(tamping <= t[idx[0]]))
        kept: list[int] = []  # records of the run kept so far: a left-out one is no neighbour
        for j, i in enumerate(idx):
            p = kept[-1] if kept else None
            q = idx[j + 1] if j + 1 < len(idx) else None
            reason = None
            if p is not None and q is not None:
                into, out_of = why(p, i, True), why(i, q, True)
                if into and out_of and why(p, q, True) is None:
                    reason = f"a spike: {into}; back {out_of}"
            elif p is not None:
                into = why(p, i, False)
                if into:
                    reason = f"{into} (until a later record confirms it)"
            elif q is not None and j + 2 < len(idx):
                out_of = why(i, q, False)
                if out_of and why(q, idx[j + 2], False) is None:
                    reason = f"against the records after it: {out_of}"
            level = reason is None and not kept and starts_after_tamping
            if level and levels is not None and levels.outlying(z[i], rules.k):
                d = np.abs(z[i] - levels.median) / levels.scale
                m = int(np.nanargmax(d))
                reason = (
                    f"post-tamping level {z[i][m]:.3f} ln mm is {d[m]:.1f} robust sd from "
                    f"the network's {levels.median[m]:.3f} (more than {rules.k:g})"
                )
            if reason is None:
                kept.append(i)
            else:
                out[i] = reason
    return out


def _spd(name: str, a: np.ndarray) -> str | None:
    if not np.allclose(a, np.swapaxes(a, -1, -2), rtol=1e-9, atol=0.0):
        return f"{name} is not symmetric"
    try:
        np.linalg.cholesky(a)
    except np.linalg.LinAlgError:
        return f"{name} is not positive definite"
    return None


def check_model(msg: Calibration | DegradationPosterior) -> str | None:
    """Why ``msg`` must not be published (NaN/inf, a covariance that is not symmetric
    positive definite), or None."""
    if isinstance(msg, Calibration):
        arrays = {"H": msg.H, "b": msg.b, "R": msg.R, "r2": msg.r2}
        covs = ("R",)
    else:
        arrays = {
            "mu": msg.mu,
            "sigma": msg.sigma,
            "z_plus": msg.z_plus,
            "sigma_z_plus": msg.sigma_z_plus,
        }
        covs = ("sigma", "sigma_z_plus")
    values = {k: np.asarray(v.array(), dtype=np.float64) for k, v in arrays.items()}
    for name, a in values.items():
        if not np.all(np.isfinite(a)):
            return f"{name} holds NaN or inf"
    for name in covs:
        if (reason := _spd(name, values[name])) is not None:
            return reason
    return None
