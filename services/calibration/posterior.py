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
    "PartialDriftPosterior",
    "SegmentIncrements",
    "history_to_increments",
    "partial_drift_posterior",
    "segment_increments",
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
    """Output of :func:`history_to_increments` and :func:`segment_increments` (all arrays
    float64)."""

    dz: np.ndarray  # (K, n) increments not spanning a tamping
    dt: np.ndarray  # (K,) their durations, days
    level: np.ndarray  # (P, n) first record after each tamping
    age: np.ndarray  # (P,) its days since that tamping
    # per indicator i, (dz_i (K_i,), dt_i (K_i,)): the increments between consecutive records
    # that measured i (complete or not); empty when every record is complete
    chains: tuple[tuple[np.ndarray, np.ndarray], ...] = ()
    # per indicator i, the records of some indicators only that measured i / did not
    partial_with: tuple[int, ...] = ()
    partial_without: tuple[int, ...] = ()


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


def segment_increments(t, z, tamping_t=(), *, max_age: float | None = None) -> SegmentIncrements:
    """:func:`history_to_increments` of a history whose records may miss indicators (``z``
    NaN where a record did not measure one: a level-only TRC car).

    ``dz, dt, level, age`` are those of the complete records alone (an increment between
    two consecutive complete records, a post-tamping level from the first complete record
    after a tamping, aged from the tamping). When some record is partial, ``chains[i]`` holds
    the increments of indicator ``i`` between consecutive records that measured it, with the
    same tamping rule; :func:`partial_drift_posterior` uses them. A history of complete
    records gives exactly :func:`history_to_increments`.
    """
    t = as_finite("t", t, 1)
    z = np.asarray(z, dtype=np.float64)
    if z.ndim != 2 or z.shape[0] != t.size:
        raise ValueError(f"z: shape {z.shape} does not match t with {t.size} times")
    seen = np.isfinite(z)
    if np.isinf(z).any() or not seen.any(axis=1).all():
        raise ValueError("z: each record needs a finite value of some indicator, NaN elsewhere")
    complete = seen.all(axis=1)
    base = history_to_increments(t[complete], z[complete], tamping_t, max_age=max_age)
    if complete.all():
        return base
    partial = ~complete
    chains = []
    for i in range(z.shape[1]):
        own = history_to_increments(t[seen[:, i]], z[seen[:, i], i : i + 1], tamping_t)
        chains.append((own.dz[:, 0], own.dt))
    with_i = seen[partial].sum(axis=0)
    return base._replace(
        chains=tuple(chains),
        partial_with=tuple(int(c) for c in with_i),
        partial_without=tuple(int(partial.sum() - c) for c in with_i),
    )


@dataclass(frozen=True)
class PartialDriftPosterior:
    r"""Posterior of ``(mu, Sigma)`` from complete increments and the increments of one
    indicator ``j`` alone; built by :func:`partial_drift_posterior`.

    Write the state's other indicators as ``r``. The Wiener process factorises as
    :math:`z_j(t)` with drift :math:`\mu_j` and diffusion :math:`\Sigma_{jj}`, and
    :math:`\mathbf z_r(t) = \boldsymbol\alpha t + \mathbf B z_j(t) + \mathbf W_{r\cdot j}(t)`
    with :math:`\mathbf B = \boldsymbol\Sigma_{rj}/\Sigma_{jj}`,
    :math:`\boldsymbol\alpha = \boldsymbol\mu_r - \mathbf B\mu_j` and
    :math:`\mathbf W_{r\cdot j}` of covariance :math:`\boldsymbol\Sigma_{r\cdot j} =
    \boldsymbol\Sigma_{rr} - \mathbf B\boldsymbol\Sigma_{jr}` independent of :math:`z_j`.
    The likelihood of a history whose records measured ``j`` (all of them) and ``r`` (the
    complete ones) is then the product of that of ``j``'s increments between consecutive
    records measuring ``j`` (``marginal``'s data) and, over each interval between consecutive
    complete records, that of :math:`\Delta\mathbf z_r` given :math:`\Delta z_j`. The NIW
    prior factorises the same way: :math:`(\mu_j, \Sigma_{jj})` is independent of
    :math:`(\boldsymbol\alpha, \mathbf B, \boldsymbol\Sigma_{r\cdot j})`. So the posterior is
    exact and the product of

    * ``marginal``: the one-indicator NIW update of :math:`(\mu_j, \Sigma_{jj})` from the prior's
      marginal :math:`(m_{0,j}, \lambda_0, \Psi_{0,jj}, \nu_0 - n + 1)` with every increment of
      ``j``;
    * the conditional part of ``complete`` (the NIW update from the complete increments),
      with :math:`\Psi_{r\cdot j} = \Psi_{rr} - \Psi_{rj}\Psi_{jr}/\Psi_{jj}`:

      .. math::

          \boldsymbol\Sigma_{r\cdot j} \sim IW(\Psi_{r\cdot j}, \nu_n),\quad
          \mathbf B \sim N(\Psi_{rj}/\Psi_{jj}, \boldsymbol\Sigma_{r\cdot j}/\Psi_{jj}),\quad
          \boldsymbol\alpha \sim N(\mathbf m_r - \mathbf B m_j,
          \boldsymbol\Sigma_{r\cdot j}/\lambda_n).

    When ``marginal`` holds the complete increments' ``j`` only, this is the distribution of
    ``complete`` itself.
    """

    complete: NIWPosterior
    marginal: NIWPosterior
    j: int

    @property
    def n_obs(self) -> int:
        return self.marginal.n_obs

    def sample(self, ns: int, rng) -> tuple[np.ndarray, np.ndarray]:
        """Draw ``ns`` joint samples: ``mu`` (ns, n), ``Sigma`` (ns, n, n)."""
        rng = np.random.default_rng(rng)
        c, j = self.complete, self.j
        r = np.flatnonzero(np.arange(c.n) != j)
        s_jj = sample_inverse_wishart(self.marginal.Psi, self.marginal.nu, rng, size=ns)[:, 0, 0]
        mu_j = self.marginal.m[0] + np.sqrt(s_jj / self.marginal.lam) * rng.standard_normal(ns)
        psi_jj, psi_rj = c.Psi[j, j], c.Psi[r, j]
        psi_r_j = c.Psi[np.ix_(r, r)] - np.outer(psi_rj, psi_rj) / psi_jj
        s_r_j = sample_inverse_wishart(0.5 * (psi_r_j + psi_r_j.T), c.nu, rng, size=ns)
        zero = np.zeros((ns, r.size))
        B = psi_rj / psi_jj + sample_mvn(zero, s_r_j / psi_jj, rng)
        alpha = c.m[r] - B * c.m[j] + sample_mvn(zero, s_r_j / c.lam, rng)
        mu = np.empty((ns, c.n))
        mu[:, j], mu[:, r] = mu_j, alpha + B * mu_j[:, None]
        sigma = np.empty((ns, c.n, c.n))
        sigma[:, j, j] = s_jj
        sigma[:, r, j] = sigma[:, j, r] = B * s_jj[:, None]
        sigma[:, r[:, None], r] = s_r_j + s_jj[:, None, None] * B[:, :, None] * B[:, None, :]
        return mu, sigma


def partial_drift_posterior(
    dz, dt, j: int, dz_j, dt_j, prior: NIWPrior | None = None, *, min_increments: int
) -> PartialDriftPosterior:
    """:class:`PartialDriftPosterior` from the complete increments ``dz, dt`` (any number,
    none included) and the ``min_increments`` or more increments ``dz_j, dt_j`` of
    indicator ``j`` between consecutive records that measured it."""
    dz = np.asarray(dz, dtype=np.float64)
    n = dz.shape[1]
    prior = NIWPrior.default_drift(n) if prior is None else prior
    one = NIWPrior(
        m0=prior.m0[[j]],
        lambda0=prior.lambda0,
        Psi0=prior.Psi0[[j]][:, [j]],
        nu0=prior.nu0 - (n - 1),
    )
    dz_j = as_finite("dz_j", dz_j, 1)
    return PartialDriftPosterior(
        complete=posterior_drift_diffusion(dz, dt, prior, min_increments=0),
        marginal=posterior_drift_diffusion(dz_j[:, None], dt_j, one, min_increments=min_increments),
        j=j,
    )


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
