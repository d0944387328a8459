"""Summaries of the Gaussian mixture over posterior samples (paper Eq. 13-14)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.special import ndtr, ndtri

from .degradation import DegradationParams, as_finite, check_covariance, transition_unchecked

_QUANTILE_TOL = 1e-11  # bisection bracket width in log space; the brief asks for 1e-10
_MAX_ITERATIONS = 200  # bisection alone reaches the tolerance from any bracket in < 60
_SQRT_2PI = np.sqrt(2 * np.pi)
_TAIL_SIGMAS = 40.0  # ndtr(-40) ~ 4e-350 underflows to 0: a bracket certain to hold a quantile


@dataclass(frozen=True)
class MixtureSummary:
    """Summary of :math:`f_Z` (Eq. 13); batch axes ``...`` as in the input, log-space unless mm."""

    mean: np.ndarray  # (..., n)
    cov: np.ndarray  # (..., n, n) total covariance
    ci_low: np.ndarray  # (..., n)
    ci_high: np.ndarray  # (..., n)
    ci_low_mm: np.ndarray  # (..., n)
    ci_high_mm: np.ndarray  # (..., n)
    width: np.ndarray  # (...,) W of the total covariance, Eq. 14
    p_exceed: np.ndarray | None  # (..., n) P(z_i > ln limit_i), None without limits


def _check_mixture(z, P):
    z = as_finite("z", z, min_ndim=2)
    P = as_finite("P", P, min_ndim=3)
    if P.shape != z.shape + z.shape[-1:]:
        raise ValueError(f"P: shape {P.shape} does not match z {z.shape}")
    check_covariance("P", P)
    return z, P


def _check_limits(limits_mm, n):
    if limits_mm is None:
        return None
    limits_mm = as_finite("limits_mm", limits_mm, min_ndim=1)
    if limits_mm.shape[-1] != n or (limits_mm <= 0).any():
        raise ValueError(f"limits_mm: expected positive values with last axis {n}")
    return np.log(limits_mm)


def credibility_width(P) -> np.ndarray:
    r"""Width of the credibility zone (paper Eq. 14), vectorised over leading axes.

    .. math::

        W = |P|^{1/n}

    A determinant that rounds to zero or below (singular PSD ``P``) gives ``W = 0``.
    """
    P = as_finite("P", P, min_ndim=2)
    if P.shape[-1] != P.shape[-2]:
        raise ValueError(f"P: expected (..., n, n), got shape {P.shape}")
    sign, logdet = np.linalg.slogdet(P)
    return np.where(sign > 0, np.exp(logdet / P.shape[-1]), 0.0)


def _marginal_cdf(x, m, s, upper=False):
    """Mixture CDF (or survival) at ``x`` (..., 1) of components ``m, s`` (..., Ns).

    Zero-variance components are point masses: an exact step, no division by zero.
    """
    point = s == 0
    u = (x - m) / np.where(point, 1.0, s)
    if upper:
        return np.where(point, x < m, ndtr(-u)).mean(-1)
    return np.where(point, x >= m, ndtr(u)).mean(-1)


def _mixture_quantile(q, m, s):
    r"""Equal-weight mixture quantile :math:`\inf\{x : F(x) \ge q\}`, vectorised.

    ``q`` broadcasts against ``m.shape[:-1]``; ``m, s`` (..., Ns) are component means and
    standard deviations. Safeguarded Newton: start from the moment-matched Gaussian, keep a
    bracket with ``F(lo) < q <= F(hi)`` (also the right invariant at the jumps of point-mass
    components) and bisect whenever the Newton step leaves it; only the mixtures not yet
    converged are iterated. A mixture of point masses only is the empirical quantile.
    """
    shape = np.broadcast_shapes(q.shape, m.shape[:-1])
    ns = m.shape[-1]
    m = np.broadcast_to(m, shape + (ns,)).reshape(-1, ns)
    s = np.broadcast_to(s, shape + (ns,)).reshape(-1, ns)
    q = np.broadcast_to(q, shape).reshape(-1)
    mean = m.mean(-1)
    sd = np.sqrt((s**2).mean(-1) + m.var(-1))
    x = mean + sd * ndtri(q)
    lo = (m - _TAIL_SIGMAS * s).min(-1)
    hi = (m + _TAIL_SIGMAS * s).max(-1)
    points_only = (s == 0).all(-1)
    if points_only.any():
        rank = np.maximum(np.ceil(q[points_only] * ns - 1e-12).astype(int) - 1, 0)
        x[points_only] = np.take_along_axis(np.sort(m[points_only], -1), rank[:, None], -1)[:, 0]
    active = np.flatnonzero(~points_only)
    for _ in range(_MAX_ITERATIONS):
        if active.size == 0:
            break
        xa, ma, sa, qa = x[active], m[active], s[active], q[active]
        point = sa == 0
        u = (xa[:, None] - ma) / np.where(point, 1.0, sa)
        cdf = np.where(point, xa[:, None] >= ma, ndtr(u)).mean(-1)
        pdf = np.where(point, 0.0, np.exp(-0.5 * u * u) / (_SQRT_2PI * np.where(point, 1.0, sa)))
        pdf = pdf.mean(-1)
        below = cdf < qa
        lo[active] = np.where(below, xa, lo[active])
        hi[active] = np.where(below, hi[active], xa)
        la, ha = lo[active], hi[active]
        with np.errstate(divide="ignore", invalid="ignore"):
            newton = xa - (cdf - qa) / pdf
        # Closed bracket: a converged Newton step lands on the end just moved to xa.
        inside = (pdf > 0) & (newton >= la) & (newton <= ha)
        step = np.where(inside, newton, 0.5 * (la + ha))
        x[active] = step
        done = (np.abs(step - xa) < _QUANTILE_TOL) | (ha - la < _QUANTILE_TOL)
        active = active[~done]
    return x.reshape(shape)


def summarize(z, P, limits_mm=None, level: float = 0.95) -> MixtureSummary:
    r"""Summarise the equal-weight Gaussian mixture of the ``Ns`` filters (paper Eq. 13-14).

    .. math::

        f_Z(z) = \frac{1}{N_s} \sum_{j=1}^{N_s} \mathcal N(z; \hat z^j, P^j), \qquad
        \bar z = \frac{1}{N_s} \sum_j \hat z^j, \qquad
        \bar P = \frac{1}{N_s} \sum_j \left[P^j + (\hat z^j - \bar z)(\hat z^j - \bar z)^T\right].

    Credible bounds solve :math:`F_i(x) = (1 \mp \text{level})/2` for the exact mixture
    marginal :math:`F_i(x) = N_s^{-1} \sum_j \Phi((x - \hat z^j_i) / \sqrt{P^j_{ii}})`,
    and the exceedance is :math:`1 - F_i(\ln \text{limit}_i)`.

    Parameters
    ----------
    z : array_like, shape (..., Ns, n)
    P : array_like, shape (..., Ns, n, n)
    limits_mm : array_like or None, shape (n,) or broadcastable to (..., n)
        Positive limits in mm.
    level : float
        Credible level of the equal-tailed intervals.
    """
    z, P = _check_mixture(z, P)
    log_limits = _check_limits(limits_mm, z.shape[-1])
    if not 0 < level < 1:
        raise ValueError(f"level: {level} not in (0, 1)")
    mean = z.mean(-2)
    dev = z - mean[..., None, :]
    cov = P.mean(-3) + np.einsum("...si,...sj->...ij", dev, dev) / z.shape[-2]
    m = np.swapaxes(z, -1, -2)  # (..., n, Ns): one mixture per marginal
    # PSD was checked up to round-off, so a variance of -1e-18 is a point mass, not an error.
    s = np.sqrt(np.maximum(np.swapaxes(np.diagonal(P, axis1=-2, axis2=-1), -1, -2), 0.0))
    q = np.array([0.5 * (1 - level), 0.5 * (1 + level)]).reshape((2,) + (1,) * (m.ndim - 1))
    ci_low, ci_high = _mixture_quantile(q, m, s)
    p_exceed = None
    if log_limits is not None:
        p_exceed = _marginal_cdf(log_limits[..., None], m, s, upper=True)
    return MixtureSummary(
        mean=mean,
        cov=cov,
        ci_low=ci_low,
        ci_high=ci_high,
        ci_low_mm=np.exp(ci_low),
        ci_high_mm=np.exp(ci_high),
        width=credibility_width(cov),
        p_exceed=p_exceed,
    )


def forecast(
    z, P, params: DegradationParams, horizons_days, limits_mm=None, level: float = 0.95
) -> MixtureSummary:
    r"""Summaries of the state ``horizons_days`` ahead without updates or tamping.

    .. math::

        \hat z^j(h) = \hat z^j + \mu_j h, \qquad P^j(h) = P^j + \Sigma_j h

    Returns a :class:`MixtureSummary` whose fields have a leading horizon axis.
    """
    z, P = _check_mixture(z, P)
    if z.shape[-2:] != (params.ns, params.n):
        raise ValueError(f"params: (Ns, n) = {(params.ns, params.n)} but z has {z.shape[-2:]}")
    h = as_finite("horizons_days", horizons_days)
    if h.ndim != 1 or (h < 0).any():
        raise ValueError("horizons_days: expected a 1-d array of days >= 0")
    h = h.reshape((-1,) + (1,) * (z.ndim - 2))
    z_h, P_h = transition_unchecked(z[None], P[None], params, h)
    return summarize(z_h, P_h, limits_mm, level)
