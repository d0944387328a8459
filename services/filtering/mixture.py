"""Summaries of the Gaussian mixture over posterior samples (paper Eq. 13-14).

Every summary takes optional mixture weights ``w_j`` (default: the paper's equal weights
``1 / Ns``). The filtering core passes the weights of :func:`weights_from_log`: each
sample's likelihood of the segment's own on-board data since its last TRC restart, a
Bayesian update of the parameter posterior (see :func:`weights_from_log`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.special import ndtri

from .degradation import DegradationParams, as_finite, check_covariance, transition_unchecked
from .kernel import mixture_quantile, mixture_survival

_QUANTILE_TOL = 1e-11  # bisection bracket width in log space; the brief asks for 1e-10
_MAX_ITERATIONS = 200  # bisection alone reaches the tolerance from any bracket in < 60
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


def _check_weights(weights, z):
    """None, or ``weights`` (..., Ns) >= 0 broadcast to ``z.shape[:-1]``, summing to 1."""
    if weights is None:
        return None
    w = as_finite("weights", weights, min_ndim=1)
    try:
        w = np.broadcast_to(w, np.broadcast_shapes(w.shape, z.shape[:-1]))
    except ValueError:
        raise ValueError(f"weights: shape {w.shape} does not broadcast to {z.shape[:-1]}") from None
    if (w < 0).any() or (np.abs(w.sum(-1) - 1.0) > 1e-9).any():
        raise ValueError("weights: expected non-negative weights summing to 1 over samples")
    return w


def weights_from_log(log_w) -> np.ndarray:
    r"""Normalised mixture weights from unnormalised log weights, over the last axis.

    The filtering core accumulates, for posterior sample :math:`j`, the log-likelihood of
    the segment's on-board indices :math:`y_k` since its last TRC restart (the prediction
    error decomposition of the Kalman filter, paper Eq. 9-12),

    .. math::

        \log \tilde w_j = \sum_k \log \mathcal N(\nu_{jk}; 0, S_{jk}), \qquad
        \nu_{jk} = y_k - H \hat z^j_{k|k-1} - b, \quad S_{jk} = H P^j_{k|k-1} H^T + R,

    so that :math:`w_j \propto \prod_k \mathcal N(\nu_{jk}; 0, S_{jk})` is the
    posterior probability of sample :math:`j` given those data (the samples being equally
    likely a priori), and normalises in log space (the maximum is subtracted first, so a
    long record cannot underflow every weight):

    .. math::

        w_j = \frac{\exp(\log \tilde w_j - m)}{\sum_i \exp(\log \tilde w_i - m)},
        \qquad m = \max_i \log \tilde w_i.

    Equal log weights (no on-board data) give the paper's equal weights :math:`1 / N_s`
    (Eq. 13). No floor and no tempering: the weights collapse only on segments that their
    pooled posterior fits badly, where the weighted intervals still cover better than the
    equal-weight ones, and neither a floor (a share of the mass on equal weights) nor
    tempering (the likelihood to a power below 1) improves coverage, RMSE or crossing
    times on ``bench.correctness``.
    """
    log_w = as_finite("log_w", log_w, min_ndim=1)
    w = np.exp(log_w - log_w.max(-1, keepdims=True))
    return w / w.sum(-1, keepdims=True)


def effective_sample_size(weights) -> np.ndarray:
    r"""Effective number of samples of normalised weights (last axis): :math:`1 / \sum_j w_j^2`.

    ``Ns`` for equal weights, 1 when a single sample carries all the weight.
    """
    w = as_finite("weights", weights, min_ndim=1)
    return 1.0 / (w * w).sum(-1)


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


def _exceedance(x, m, s, w=None):
    r"""Mixture survival :math:`1 - F(x) = \sum_j w_j \Phi((m_j - x) / s_j)` at ``x`` (...,
    1) of components ``m, s`` (..., Ns), compiled (:func:`.kernel.mixture_survival`).

    ``w`` (..., Ns): component weights summing to 1, None for equal weights. Zero-variance
    components are point masses: an exact step, no division by zero.
    """
    shape = np.broadcast_shapes(x.shape[:-1], m.shape[:-1])
    ns = m.shape[-1]
    mixtures = m.shape[:-1]
    m = np.ascontiguousarray(m.reshape(-1, ns))
    s = np.ascontiguousarray(s.reshape(-1, ns))
    if w is not None:
        w = np.ascontiguousarray(np.broadcast_to(w, mixtures + (ns,)).reshape(-1, ns))
    rows = np.broadcast_to(np.arange(m.shape[0]).reshape(mixtures), shape).reshape(-1)
    x = np.broadcast_to(x[..., 0], shape).reshape(-1).astype(np.float64)
    return mixture_survival(x, np.ascontiguousarray(rows), m, s, w).reshape(shape)


def _mixture_quantile(q, m, s, w=None):
    r"""Mixture quantile :math:`\inf\{x : F(x) \ge q\}`, vectorised.

    ``q`` broadcasts against ``m.shape[:-1]``; ``m, s`` (..., Ns) are component means and
    standard deviations, ``w`` (..., Ns) their weights (None: equal). Safeguarded Newton
    from the moment-matched Gaussian, compiled (:func:`.kernel.mixture_quantile`); a
    mixture of point masses only is the (weighted) empirical quantile. Components of
    weight 0 only widen the initial bracket.
    """
    shape = np.broadcast_shapes(q.shape, m.shape[:-1])
    ns = m.shape[-1]
    m = np.ascontiguousarray(np.broadcast_to(m, shape + (ns,)).reshape(-1, ns))
    s = np.ascontiguousarray(np.broadcast_to(s, shape + (ns,)).reshape(-1, ns))
    q = np.ascontiguousarray(np.broadcast_to(q, shape).reshape(-1), dtype=np.float64)
    if w is not None:
        w = np.ascontiguousarray(np.broadcast_to(w, shape + (ns,)).reshape(-1, ns))
    x = mixture_quantile(q, ndtri(q), m, s, w, _TAIL_SIGMAS, _QUANTILE_TOL, _MAX_ITERATIONS)
    return x.reshape(shape)


def summarize(z, P, limits_mm=None, level: float = 0.95, weights=None) -> MixtureSummary:
    r"""Summarise the Gaussian mixture of the ``Ns`` filters (paper Eq. 13-14).

    .. math::

        f_Z(z) = \sum_{j=1}^{N_s} w_j\, \mathcal N(z; \hat z^j, P^j), \qquad
        \bar z = \sum_j w_j \hat z^j, \qquad
        \bar P = \sum_j w_j \left[P^j + (\hat z^j - \bar z)(\hat z^j - \bar z)^T\right],

    with the paper's equal weights :math:`w_j = 1 / N_s` (Eq. 13) unless ``weights`` are
    given (e.g. :func:`weights_from_log`, :math:`w_j \propto \prod_k \mathcal N(\nu_{jk};
    0, S_{jk})`). Credible bounds solve :math:`F_i(x) = (1 \mp \text{level})/2` for the
    exact mixture marginal :math:`F_i(x) = \sum_j w_j \Phi((x - \hat z^j_i) /
    \sqrt{P^j_{ii}})`, and the exceedance is :math:`1 - F_i(\ln \text{limit}_i)`.

    Parameters
    ----------
    z : array_like, shape (..., Ns, n)
    P : array_like, shape (..., Ns, n, n)
    limits_mm : array_like or None, shape (n,) or broadcastable to (..., n)
        Positive limits in mm.
    level : float
        Credible level of the equal-tailed intervals.
    weights : array_like or None, shape broadcastable to (..., Ns)
        Non-negative component weights summing to 1 over the samples; None for ``1 / Ns``.
    """
    z, P = _check_mixture(z, P)
    w = _check_weights(weights, z)
    log_limits = _check_limits(limits_mm, z.shape[-1])
    if not 0 < level < 1:
        raise ValueError(f"level: {level} not in (0, 1)")
    return _summarize(z, P, log_limits, level, w)


def summarize_unchecked(z, P, limits_mm=None, level: float = 0.95, weights=None):
    """:func:`summarize` without the checks of ``z``, ``P`` and ``weights``.

    For callers holding trusted filter states (the tracker): the eigenvalue check of every
    ``P`` costs as much as the moments. Same numbers as :func:`summarize`, bit for bit.
    """
    z = np.asarray(z, dtype=np.float64)
    P = np.asarray(P, dtype=np.float64)
    w = None
    if weights is not None:
        weights = np.asarray(weights, dtype=np.float64)
        w = np.broadcast_to(weights, np.broadcast_shapes(weights.shape, z.shape[:-1]))
    return _summarize(z, P, _check_limits(limits_mm, z.shape[-1]), level, w)


def _summarize(z, P, log_limits, level: float, w) -> MixtureSummary:
    """:func:`summarize` on checked inputs.

    Every sum over the samples is a sum over the last axis of a contiguous array, so a
    mixture's numbers depend on its own components only, never on the batch around it
    (the tracker's batched re-run must equal its one-segment steps bit for bit; einsum's
    order of summation depends on the shapes).
    """
    m = np.ascontiguousarray(np.swapaxes(z, -1, -2))  # (..., n, Ns): a mixture per marginal
    if w is None:
        mean = z.mean(-2)
        dev = z - mean[..., None, :]
        cov = P.mean(-3) + np.einsum("...si,...sj->...ij", dev, dev) / z.shape[-2]
    else:
        mean = (m * w[..., None, :]).sum(-1)
        devt = m - mean[..., None]
        wij = w[..., None, None, :]
        cov = (np.ascontiguousarray(np.moveaxis(P, -3, -1)) * wij).sum(-1) + (
            devt[..., :, None, :] * devt[..., None, :, :] * wij
        ).sum(-1)
        w = w[..., None, :]  # (..., 1, Ns): the same weights for every marginal
    # PSD was checked up to round-off, so a variance of -1e-18 is a point mass, not an error.
    var = np.ascontiguousarray(np.swapaxes(np.diagonal(P, axis1=-2, axis2=-1), -1, -2))
    s = np.sqrt(np.maximum(var, 0.0))
    q = np.array([0.5 * (1 - level), 0.5 * (1 + level)]).reshape((2,) + (1,) * (m.ndim - 1))
    ci_low, ci_high = _mixture_quantile(q, m, s, w)
    p_exceed = None
    if log_limits is not None:
        p_exceed = _exceedance(log_limits[..., None], m, s, w)
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
    z,
    P,
    params: DegradationParams,
    horizons_days,
    limits_mm=None,
    level: float = 0.95,
    weights=None,
) -> MixtureSummary:
    r"""Summaries of the state ``horizons_days`` ahead without updates or tamping.

    .. math::

        \hat z^j(h) = \hat z^j + \mu_j h, \qquad P^j(h) = P^j + \Sigma_j h,

    mixed with the current ``weights`` :math:`w_j` (no data arrive in between, so the
    weights do not change; None for ``1 / Ns``, see :func:`summarize`).
    Returns a :class:`MixtureSummary` whose fields have a leading horizon axis.
    """
    z, P = _check_mixture(z, P)
    if z.shape[-2:] != (params.ns, params.n):
        raise ValueError(f"params: (Ns, n) = {(params.ns, params.n)} but z has {z.shape[-2:]}")
    w = _check_weights(weights, z)
    h = as_finite("horizons_days", horizons_days)
    if h.ndim != 1 or (h < 0).any():
        raise ValueError("horizons_days: expected a 1-d array of days >= 0")
    h = h.reshape((-1,) + (1,) * (z.ndim - 2))
    z_h, P_h = transition_unchecked(z[None], P[None], params, h)
    return summarize(z_h, P_h, limits_mm, level, None if w is None else w[None])
