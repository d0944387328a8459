r"""The drift-diffusion model of track degradation and its exact conjugate posterior.

Between two TRC records that do not span a tamping, the ln indicators ``z`` (n dims, ln mm)
follow a Wiener process with drift ``mu`` (ln-mm/day) and diffusion ``Sigma``
(ln-mm^2/day): :math:`\Delta\mathbf z \sim N(\boldsymbol\mu\,\Delta t,
\boldsymbol\Sigma\,\Delta t)` (paper Eq. 1-2). With a Normal-Inverse-Wishart (NIW) prior
the posterior of ``(mu, Sigma)`` is NIW again, so its draws are exact and cheap
(:func:`posterior_drift_diffusion`).

Calibration fits the degradation models from it (:mod:`services.calibration.posterior`)
and the frequency study draws the parameters of its simulated segments from it, so it lives
with the other pieces every service may use. Pure: numpy/scipy only, no I/O.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import stats

__all__ = [
    "CalibrationError",
    "NIWPosterior",
    "NIWPrior",
    "as_finite",
    "check_count",
    "posterior_drift_diffusion",
    "sample_inverse_wishart",
    "sample_mvn",
]


class CalibrationError(ValueError):
    """The data cannot support the requested estimate; the message says what is missing."""


def as_finite(name: str, x, ndim: int) -> np.ndarray:
    """Return ``x`` as a finite float64 array of ``ndim`` dims or raise ValueError naming it.

    A 1-D array where 2-D is expected is taken as a single column (n = 1).
    """
    a = np.asarray(x, dtype=np.float64)
    if ndim == 2 and a.ndim == 1:
        a = a[:, None]
    if a.ndim != ndim:
        raise ValueError(f"{name}: expected a {ndim}-D array, got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(
            f"{name}: contains NaN or inf at {np.argwhere(~np.isfinite(a))[:3].tolist()}"
        )
    return a


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


def sample_mvn(mean, cov, rng) -> np.ndarray:
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
        mu = sample_mvn(np.broadcast_to(self.m, (ns, self.n)), Sigma / self.lam, rng)
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


def check_count(what: str, got: int, need: int):
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
    check_count("increments between TRC records (not spanning a tamping)", N, need)
    lam = prior.lambda0 + dt.sum()
    m = (prior.lambda0 * prior.m0 + dz.sum(axis=0)) / lam
    s = np.sqrt(dt)[:, None]
    r = dz / s - s * m
    d0 = m - prior.m0
    Psi = prior.Psi0 + r.T @ r + prior.lambda0 * np.outer(d0, d0)
    return NIWPosterior(m=m, lam=lam, Psi=0.5 * (Psi + Psi.T), nu=prior.nu0 + N, n_obs=N)
