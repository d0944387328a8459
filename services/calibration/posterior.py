r"""Exact conjugate posterior of the degradation parameters (paper Eq. 1-2 and 13); its
drift-diffusion part is :mod:`services.drift_diffusion`.

Pure core: numpy/scipy only, no I/O. State ``z`` = ln TRC indicators (n dims, ln mm);
time in days, so ``mu`` is in ln-mm/day and ``Sigma`` in ln-mm^2/day.

The paper draws :math:`(\boldsymbol\mu, \boldsymbol\Sigma, \mathbf z^+, \boldsymbol\Sigma_{z^+})`
by MCMC; here the Wiener increments and the post-tamping levels each have a
Normal-Inverse-Wishart (NIW) conjugate prior, so the posterior draws are exact and cheap.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from services.drift_diffusion import (
    NIWPosterior,
    NIWPrior,
    as_finite,
    check_count,
    posterior_drift_diffusion,
    sample_inverse_wishart,
    sample_mvn,
)

__all__ = [
    "DegradationSamples",
    "SegmentIncrements",
    "history_to_increments",
    "sample_degradation_posterior",
    "sample_post_tamping",
]


def sample_post_tamping(
    level, age, mu, rng, prior: NIWPrior | None = None, *, min_levels: int | None = None
) -> tuple[np.ndarray, np.ndarray]:
    r"""Draw ``(z+, Sigma_z+)`` given post-tamping levels, one draw per drift sample.

    A level observed ``a_i`` days after a tamping is modelled as
    :math:`\mathbf l_i = \mathbf z^+_i + \boldsymbol\mu a_i`,
    :math:`\mathbf z^+_i \sim N(\mathbf z^+, \boldsymbol\Sigma_{z^+})` iid. For each drift
    draw :math:`\boldsymbol\mu_j` the corrected levels
    :math:`\mathbf c_i^j = \mathbf l_i - \boldsymbol\mu_j a_i` get the plain iid NIW update
    (:math:`\bar{\mathbf c}^j`, :math:`S^j = \sum_i (\mathbf c_i^j - \bar{\mathbf c}^j)(\cdot)^T`)

    .. math::

        \lambda_n = \lambda_0 + N,\quad
        \mathbf m_n^j = \frac{\lambda_0\mathbf m_0 + N\bar{\mathbf c}^j}{\lambda_n},\quad
        \nu_n = \nu_0 + N,\quad
        \Psi_n^j = \Psi_0 + S^j + \frac{\lambda_0 N}{\lambda_n}
        (\bar{\mathbf c}^j - \mathbf m_0)(\cdot)^T

    and one draw :math:`\boldsymbol\Sigma_{z^+}^j \sim IW(\Psi_n^j, \nu_n)`,
    :math:`\mathbf z^{+j} \sim N(\mathbf m_n^j, \boldsymbol\Sigma_{z^+}^j/\lambda_n)`.
    Carrying the drift draw through propagates its uncertainty into ``z+``.

    What the correction ignores: the diffusion accumulated since the tamping,
    :math:`\boldsymbol\Sigma a_i`, is not removed, so it inflates ``Sigma_z+`` (by about
    :math:`\boldsymbol\Sigma\bar a`), and the levels are not used to inform ``mu``. Use
    levels recorded soon after the tamping (small ``a_i``, see ``max_age`` of
    :func:`history_to_increments`), where both effects are negligible.

    Parameters
    ----------
    level : array_like, shape (N, n)
        ln indicators of the first TRC record after each tamping.
    age : array_like, shape (N,)
        Days since the tamping, >= 0.
    mu : array_like, shape (ns, n)
        Drift draws (ln-mm/day).
    rng : numpy.random.Generator or seed
    prior : NIWPrior, optional
        :meth:`NIWPrior.default_level` by default.
    min_levels : int, optional
        Smallest N accepted, ``n + 2`` by default.

    Returns
    -------
    z_plus : ndarray, shape (ns, n)
    Sigma_z_plus : ndarray, shape (ns, n, n)
    """
    rng = np.random.default_rng(rng)
    level = as_finite("level", level, 2)
    age = as_finite("age", age, 1)
    mu = as_finite("mu", mu, 2)
    N, n = level.shape
    if age.shape != (N,):
        raise ValueError(f"age: shape {age.shape} does not match level with {N} levels")
    if np.any(age < 0):
        raise ValueError(f"age: must be >= 0 days, got min {age.min()}")
    if mu.shape[1] != n:
        raise ValueError(f"mu: shape {mu.shape} does not match level with n={n}")
    prior = NIWPrior.default_level(n) if prior is None else prior
    if prior.n != n:
        raise ValueError(f"prior: dimension {prior.n} does not match level with n={n}")
    check_count("post-tamping levels", N, n + 2 if min_levels is None else min_levels)
    c = level[None] - mu[:, None, :] * age[None, :, None]  # (ns, N, n)
    cbar = c.mean(axis=1)
    r = c - cbar[:, None, :]
    lam = prior.lambda0 + N
    m = (prior.lambda0 * prior.m0 + N * cbar) / lam
    d0 = cbar - prior.m0
    Psi = (
        prior.Psi0
        + np.einsum("jia,jib->jab", r, r)
        + (prior.lambda0 * N / lam) * d0[:, :, None] * d0[:, None, :]
    )
    Sigma = sample_inverse_wishart(0.5 * (Psi + np.swapaxes(Psi, 1, 2)), prior.nu0 + N, rng)
    return sample_mvn(m, Sigma / lam, rng), Sigma


class SegmentIncrements(NamedTuple):
    """Output of :func:`history_to_increments` (all arrays float64)."""

    dz: np.ndarray  # (K, n) increments not spanning a tamping
    dt: np.ndarray  # (K,) their durations, days
    level: np.ndarray  # (P, n) first record after each tamping
    age: np.ndarray  # (P,) its days since that tamping


def history_to_increments(t, z, tamping_t=(), *, max_age: float | None = None) -> SegmentIncrements:
    """Split one segment's TRC history into Wiener increments and post-tamping levels.

    A tamping at ``t_m`` belongs to the interval ``(t_{i-1}, t_i]`` holding it (paper
    Eq. 2), so a record at the same instant as a tamping counts as after it (age 0). An
    increment whose interval holds a tamping is dropped. The first record at or after a
    tamping is a post-tamping level with ``age = t_i - t_m``; when several tampings precede
    the same record, the latest one is used. When only a tamping interval is known, pass
    its midpoint (the paper's mid-interval rule).

    Parameters
    ----------
    t : array_like, shape (L,)
        Record times in days (any origin), distinct; sorted here if needed.
    z : array_like, shape (L, n)
        ln indicators of each record.
    tamping_t : array_like, shape (M,)
        Tamping times in days, same origin as ``t``.
    max_age : float, optional
        Drop levels older than this many days (the diffusion since tamping inflates
        ``Sigma_z+``; see :func:`sample_post_tamping`).

    Returns
    -------
    SegmentIncrements
    """
    t = as_finite("t", t, 1)
    z = as_finite("z", z, 2)
    tm = as_finite("tamping_t", np.asarray(tamping_t, dtype=np.float64).reshape(-1), 1)
    if z.shape[0] != t.size:
        raise ValueError(f"z: {z.shape[0]} rows do not match t with {t.size} times")
    order = np.argsort(t, kind="stable")
    t, z = t[order], z[order]
    if np.any(np.diff(t) == 0):
        raise ValueError("t: duplicate record times; deduplicate TRC records first")
    first = np.searchsorted(t, tm, side="left")  # first record at or after each tamping
    ok = first < t.size
    first, tm = first[ok], tm[ok]
    spans = np.zeros(t.size, dtype=bool)
    spans[first] = True
    keep = ~spans[1:]
    dz, dt = np.diff(z, axis=0)[keep], np.diff(t)[keep]
    # latest tamping per post-tamping record
    latest = np.full(t.size, -np.inf)
    np.maximum.at(latest, first, tm)
    rec = np.flatnonzero(np.isfinite(latest))
    age = t[rec] - latest[rec]
    if max_age is not None:
        rec, age = rec[age <= max_age], age[age <= max_age]
    return SegmentIncrements(dz=dz, dt=dt, level=z[rec], age=age)


@dataclass(frozen=True)
class DegradationSamples:
    """``ns`` joint posterior draws of the degradation parameters (ln mm, days).

    Attributes
    ----------
    mu : ndarray, shape (ns, n)
        Drift, ln-mm/day.
    sigma : ndarray, shape (ns, n, n)
        Diffusion, ln-mm^2/day.
    z_plus : ndarray, shape (ns, n)
        Mean post-tamping level, ln mm.
    sigma_z_plus : ndarray, shape (ns, n, n)
        Covariance of the post-tamping level, ln-mm^2.
    """

    mu: np.ndarray
    sigma: np.ndarray
    z_plus: np.ndarray
    sigma_z_plus: np.ndarray

    @property
    def ns(self) -> int:
        return self.mu.shape[0]


def sample_degradation_posterior(
    dz,
    dt,
    level,
    age,
    *,
    ns: int,
    rng,
    drift_prior: NIWPrior | None = None,
    level_prior: NIWPrior | None = None,
    min_increments: int | None = None,
    min_levels: int | None = None,
) -> DegradationSamples:
    """Draw ``ns`` posterior samples of ``(mu, Sigma, z+, Sigma_z+)`` (input of Eq. 13).

    ``(mu, Sigma)`` come from :func:`posterior_drift_diffusion` on the increments (pooled
    over the segments of a group, e.g. concatenated :func:`history_to_increments`
    outputs); ``(z+, Sigma_z+)`` from :func:`sample_post_tamping` with the same ``mu``
    draws, so draw j is a coherent joint sample.

    Raises
    ------
    CalibrationError
        Too few increments or levels.
    ValueError
        Malformed input (message names the argument).
    """
    if not (isinstance(ns, int | np.integer) and ns >= 1):
        raise ValueError(f"ns: must be a positive int, got {ns!r}")
    rng = np.random.default_rng(rng)
    post = posterior_drift_diffusion(dz, dt, drift_prior, min_increments=min_increments)
    mu, sigma = post.sample(ns, rng)
    z_plus, sigma_z_plus = sample_post_tamping(
        level, age, mu, rng, level_prior, min_levels=min_levels
    )
    return DegradationSamples(mu=mu, sigma=sigma, z_plus=z_plus, sigma_z_plus=sigma_z_plus)


def group_rng(seed: int, group: str, version: int) -> np.random.Generator:
    """The generator of a posterior's draws: a pure function of (seed, group, version)."""
    g = int.from_bytes(hashlib.sha256(group.encode()).digest()[:8], "little")
    return np.random.default_rng(np.random.SeedSequence([seed, g, version]))


def sample_prior(prior: NIWPrior, ns: int, rng: np.random.Generator):
    """Draws of (mean, cov) from the NIW prior itself (no data)."""
    return NIWPosterior(
        m=prior.m0, lam=prior.lambda0, Psi=prior.Psi0, nu=prior.nu0, n_obs=0
    ).sample(ns, rng)
