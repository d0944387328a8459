r"""Exact conjugate posterior of the degradation parameters (paper Eq. 1-2 and 13).

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
from scipy import stats

from .regression import CalibrationError, as_finite

__all__ = [
    "DegradationSamples",
    "NIWPosterior",
    "NIWPrior",
    "SegmentIncrements",
    "history_to_increments",
    "posterior_drift_diffusion",
    "sample_degradation_posterior",
    "sample_inverse_wishart",
    "sample_post_tamping",
]


@dataclass(frozen=True)
class NIWPrior:
    r"""Normal-Inverse-Wishart prior :math:`\boldsymbol\mu|\boldsymbol\Sigma \sim
    N(\mathbf m_0, \boldsymbol\Sigma/\lambda_0)`, :math:`\boldsymbol\Sigma \sim IW(\Psi_0, \nu_0)`.

    Attributes
    ----------
    m0 : ndarray, shape (n,)
    lambda0 : float
        Prior weight of ``m0``: days of data for the drift, number of levels for ``z+``.
    Psi0 : ndarray, shape (n, n)
        Inverse-Wishart scale (symmetric positive definite).
    nu0 : float
        Inverse-Wishart degrees of freedom, ``> n - 1``.
    """

    m0: np.ndarray
    lambda0: float
    Psi0: np.ndarray
    nu0: float

    def __post_init__(self):
        m0 = as_finite("m0", self.m0, 1)
        n = m0.size
        Psi0 = as_finite("Psi0", self.Psi0, 2)
        if Psi0.shape != (n, n) or not np.allclose(Psi0, Psi0.T):
            raise ValueError(f"Psi0: must be symmetric ({n}, {n}), got shape {Psi0.shape}")
        if np.linalg.eigvalsh(Psi0)[0] <= 0:
            raise ValueError("Psi0: must be positive definite")
        if not self.lambda0 > 0:
            raise ValueError(f"lambda0: must be > 0, got {self.lambda0}")
        if not self.nu0 > n - 1:
            raise ValueError(f"nu0: must be > n - 1 = {n - 1}, got {self.nu0}")
        object.__setattr__(self, "m0", m0)
        object.__setattr__(self, "Psi0", Psi0)

    @property
    def n(self) -> int:
        return self.m0.size

    @classmethod
    def weak(cls, n: int, *, scale: float, lambda0: float, m0=None) -> NIWPrior:
        r"""Weakly informative prior: :math:`\nu_0 = n + 2`, :math:`\Psi_0 = s^2 I`.

        With :math:`\nu_0 = n + 2` the prior mean of :math:`\boldsymbol\Sigma` is
        :math:`\Psi_0/(\nu_0 - n - 1) = s^2 I` (finite) while its variance is infinite
        (broad); the prior weighs as about :math:`\nu_0` observations for :math:`\Sigma`
        and :math:`\lambda_0` for the mean, so it is swamped by tens of observations.

        Parameters
        ----------
        n : int
            State dimension.
        scale : float
            ``s``: typical standard deviation (per sqrt-day for the diffusion, ln mm for
            post-tamping levels).
        lambda0 : float
            Prior weight of ``m0``.
        m0 : array_like, shape (n,), optional
            Prior mean, zeros by default.
        """
        m0 = np.zeros(n) if m0 is None else np.broadcast_to(np.asarray(m0, float), (n,))
        return cls(m0=m0.copy(), lambda0=float(lambda0), Psi0=scale**2 * np.eye(n), nu0=n + 2.0)

    @classmethod
    def default_drift(cls, n: int = 2) -> NIWPrior:
        """Default prior for (mu, Sigma) in ln-mm/day.

        ``m0 = 0``, ``lambda0 = 1`` day (the drift prior weighs as one day of data; its sd
        ``sqrt(Sigma/1 day)`` ~ 3e-3 /day is ~1 ln unit per year: broad), prior mean of
        ``Sigma`` = (3e-3)^2 I per day, i.e. about 6 % sd of the geometry after a year.
        """
        return cls.weak(n, scale=3e-3, lambda0=1.0)

    @classmethod
    def default_level(cls, n: int = 2) -> NIWPrior:
        """Default prior for (z+, Sigma_z+) in ln mm.

        ``m0 = 0`` (1 mm) with weight ``lambda0 = 0.01`` level (prior sd of ``z+`` about
        3 ln units: broad), prior mean of ``Sigma_z+`` = 0.3^2 I (about 30 % spread).
        """
        return cls.weak(n, scale=0.3, lambda0=0.01)


def sample_inverse_wishart(Psi, nu: float, rng, size: int | None = None) -> np.ndarray:
    r"""Draw :math:`\boldsymbol\Sigma \sim IW(\Psi, \nu)`, one draw per scale matrix.

    Bartlett decomposition: with :math:`\Psi = CC^T` (Cholesky) and :math:`A` lower
    triangular, :math:`A_{ii}^2 \sim \chi^2_{\nu - i}` (i = 0..n-1), :math:`A_{ij} \sim N(0,1)`
    for :math:`i > j`, :math:`W = C^{-T}AA^TC^{-1} \sim W(\Psi^{-1}, \nu)`, hence

    .. math::

        \boldsymbol\Sigma = W^{-1} = M^T M,\qquad M = A^{-1}C^T .

    Vectorised over any number of different scales (``scipy.stats.invwishart`` takes one).

    Parameters
    ----------
    Psi : array_like, shape (n, n) or (k, n, n)
        Scale matrices, symmetric positive definite.
    nu : float
        Degrees of freedom, ``> n - 1``.
    rng : numpy.random.Generator or seed
    size : int, optional
        Number of draws when ``Psi`` is a single (n, n) matrix.

    Returns
    -------
    ndarray, shape (size or k, n, n)
    """
    rng = np.random.default_rng(rng)
    Psi = np.asarray(Psi, dtype=np.float64)
    n = Psi.shape[-1]
    if Psi.ndim == 2:
        Psi = np.broadcast_to(Psi, (1 if size is None else size, n, n))
    elif size is not None and size != Psi.shape[0]:
        raise ValueError(f"size: {size} differs from the number of scales {Psi.shape[0]}")
    if not nu > n - 1:
        raise ValueError(f"nu: must be > n - 1 = {n - 1}, got {nu}")
    k = Psi.shape[0]
    C = np.linalg.cholesky(Psi)
    A = np.tril(rng.standard_normal((k, n, n)), -1)
    idx = np.arange(n)
    A[:, idx, idx] = np.sqrt(rng.chisquare(nu - idx, size=(k, n)))
    M = np.linalg.solve(A, np.swapaxes(C, -1, -2))
    return np.swapaxes(M, -1, -2) @ M


def _sample_mvn(mean, cov, rng) -> np.ndarray:
    """One N(mean_j, cov_j) draw per row j: mean (k, n), cov (k, n, n)."""
    L = np.linalg.cholesky(cov)
    return mean + (L @ rng.standard_normal(mean.shape)[..., None])[..., 0]


@dataclass(frozen=True)
class NIWPosterior:
    r"""NIW posterior :math:`\boldsymbol\mu|\boldsymbol\Sigma \sim N(\mathbf m_n,
    \boldsymbol\Sigma/\lambda_n)`, :math:`\boldsymbol\Sigma \sim IW(\Psi_n, \nu_n)`.

    Marginals used by the interval helpers (:math:`d = \nu_n - n + 1`):

    .. math::

        \boldsymbol\mu \sim t_d\!\left(\mathbf m_n, \frac{\Psi_n}{\lambda_n d}\right),\qquad
        \Sigma_{ii} \sim \mathrm{InvGamma}\!\left(\frac d2, \frac{\Psi_{n,ii}}{2}\right)

    Attributes
    ----------
    m : ndarray, shape (n,)
    lam : float
    Psi : ndarray, shape (n, n)
    nu : float
    n_obs : int
        Number of increments (or levels) the posterior is based on.
    """

    m: np.ndarray
    lam: float
    Psi: np.ndarray
    nu: float
    n_obs: int

    @property
    def n(self) -> int:
        return self.m.size

    def sample(self, ns: int, rng) -> tuple[np.ndarray, np.ndarray]:
        """Draw ``ns`` joint samples: ``mu`` (ns, n), ``Sigma`` (ns, n, n)."""
        rng = np.random.default_rng(rng)
        Sigma = sample_inverse_wishart(self.Psi, self.nu, rng, size=ns)
        mu = _sample_mvn(np.broadcast_to(self.m, (ns, self.n)), Sigma / self.lam, rng)
        return mu, Sigma

    def mean_sigma(self) -> np.ndarray:
        """Posterior mean of Sigma, ``Psi_n / (nu_n - n - 1)`` (needs ``nu_n > n + 1``)."""
        return self.Psi / (self.nu - self.n - 1)

    def mu_interval(self, level: float = 0.95) -> tuple[np.ndarray, np.ndarray]:
        """Equal-tailed marginal credible interval of each component of ``mu``."""
        d = self.nu - self.n + 1
        half = stats.t.ppf(0.5 + level / 2, d) * np.sqrt(np.diag(self.Psi) / (self.lam * d))
        return self.m - half, self.m + half

    def sigma_diag_interval(self, level: float = 0.95) -> tuple[np.ndarray, np.ndarray]:
        """Equal-tailed marginal credible interval of each variance ``Sigma_ii``."""
        ig = stats.invgamma((self.nu - self.n + 1) / 2, scale=np.diag(self.Psi) / 2)
        return ig.ppf((1 - level) / 2), ig.ppf((1 + level) / 2)


def _check_count(what: str, got: int, need: int):
    if got < need:
        raise CalibrationError(f"too few {what}: {got}; need at least {need}")


def posterior_drift_diffusion(
    dz, dt, prior: NIWPrior | None = None, *, min_increments: int | None = None
) -> NIWPosterior:
    r"""Conjugate posterior of drift ``mu`` and diffusion ``Sigma`` from Wiener increments.

    Increments between consecutive TRC records not spanning a tamping satisfy
    :math:`\Delta\mathbf z_i \sim N(\boldsymbol\mu\,\Delta t_i, \boldsymbol\Sigma\,\Delta t_i)`
    (Eq. 1-2). With :math:`\mathbf x_i = \Delta\mathbf z_i/\sqrt{\Delta t_i} \sim
    N(\boldsymbol\mu\sqrt{\Delta t_i}, \boldsymbol\Sigma)` the likelihood times the NIW prior
    is, collecting the terms in :math:`\boldsymbol\mu` (quadratic weight
    :math:`\lambda_0 + \sum_i \Delta t_i`, linear term
    :math:`\lambda_0\mathbf m_0 + \sum_i \sqrt{\Delta t_i}\,\mathbf x_i`), again NIW with

    .. math::

        \lambda_n &= \lambda_0 + \textstyle\sum_i \Delta t_i, \qquad
        \mathbf m_n = \Big(\lambda_0\mathbf m_0 + \textstyle\sum_i \Delta\mathbf z_i\Big)
        \big/\lambda_n, \qquad \nu_n = \nu_0 + N,\\
        \Psi_n &= \Psi_0 + \textstyle\sum_i \Delta\mathbf z_i\Delta\mathbf z_i^T/\Delta t_i
        + \lambda_0\mathbf m_0\mathbf m_0^T - \lambda_n\mathbf m_n\mathbf m_n^T .

    ``Psi_n`` is computed in the equivalent centred form
    :math:`\Psi_0 + \sum_i (\mathbf x_i - \sqrt{\Delta t_i}\mathbf m_n)(\cdot)^T
    + \lambda_0(\mathbf m_n - \mathbf m_0)(\cdot)^T`, which avoids cancellation.

    Parameters
    ----------
    dz : array_like, shape (N, n)
        Increments of ln indicators.
    dt : array_like, shape (N,)
        Their durations in days, > 0.
    prior : NIWPrior, optional
        :meth:`NIWPrior.default_drift` by default.
    min_increments : int, optional
        Smallest N accepted, ``n + 2`` by default.

    Returns
    -------
    NIWPosterior
    """
    dz = as_finite("dz", dz, 2)
    dt = as_finite("dt", dt, 1)
    N, n = dz.shape
    if dt.shape != (N,):
        raise ValueError(f"dt: shape {dt.shape} does not match dz with {N} increments")
    if np.any(dt <= 0):
        raise ValueError(f"dt: durations must be > 0 days, got min {dt.min()}")
    prior = NIWPrior.default_drift(n) if prior is None else prior
    if prior.n != n:
        raise ValueError(f"prior: dimension {prior.n} does not match dz with n={n}")
    need = n + 2 if min_increments is None else min_increments
    _check_count("increments between TRC records (not spanning a tamping)", N, need)
    lam = prior.lambda0 + dt.sum()
    m = (prior.lambda0 * prior.m0 + dz.sum(axis=0)) / lam
    s = np.sqrt(dt)[:, None]
    r = dz / s - s * m
    d0 = m - prior.m0
    Psi = prior.Psi0 + r.T @ r + prior.lambda0 * np.outer(d0, d0)
    return NIWPosterior(m=m, lam=lam, Psi=0.5 * (Psi + Psi.T), nu=prior.nu0 + N, n_obs=N)


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
    _check_count("post-tamping levels", N, n + 2 if min_levels is None else min_levels)
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
    return _sample_mvn(m, Sigma / lam, rng), Sigma


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
