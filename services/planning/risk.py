r"""Forecasts of a segment under the degradation model, as the planner needs them.

Pure numpy/scipy. A segment's state is its filter's mixture summary, ``mean`` and ``cov`` of
``z = [ln Top6_mm, ln Align10_mm]`` at event time ``t_s``; the degradation posterior of its
group gives samples ``j`` of :math:`(\mu_j, \Sigma_j, z^+_j, \Sigma_{z^+,j})` (per day).
The forecast is the mixture over ``j`` of

.. math::

    z(t_s + \tau) \sim N(m + \mu_j \tau,\; P + \Sigma_j \tau)               \quad\text{untamped,}

    z(t_m + a) \sim N(z^+_j + \mu_j a,\; \Sigma_{z^+,j} + \Sigma_j a)    \quad\text{tamped at } t_m.

with the segment's own weights :math:`w_j` (``SegmentState.log_weights``: the likelihood
of its on-board data since its last TRC record, so a segment that degrades faster than its
group is forecast with the samples that explain it; equal weights when it has none).

What the planner asks of it, per indicator ``i`` and then over the indicators:

- the probability of being above a limit at a time (the marginal of each indicator; above
  any of them: :math:`1 - \prod_i (1 - p_i)` within each sample ``j``, then the mixture);
- the probability of reaching the limit *before* a time (first passage). For one sample and a
  known start :math:`z_0 < b` (distance :math:`d = b - z_0`) a Wiener path with drift
  :math:`\mu` and variance :math:`s^2` per day first reaches ``b`` within :math:`\tau` with

  .. math::

     F(\tau) = \Phi\Big(\frac{\mu\tau - d}{s\sqrt\tau}\Big)
       + e^{2\mu d/s^2}\,\Phi\Big(\frac{-d - \mu\tau}{s\sqrt\tau}\Big),

  and 1 when :math:`z_0 \ge b`. The start is uncertain, :math:`z_0 \sim N(m_i, P_{ii})`:
  :math:`P(z_0 \ge b)` exactly, plus Gauss-Legendre quadrature over the quantiles of
  the start below ``b`` (a smooth integrand, unlike over the whole normal). Indicators
  combine by the union bound :math:`\min(1, F_{top} + F_{align})`, which never understates
  the risk.
  With :math:`\mu \ge 0` a path that reached ``b`` is above it at :math:`\tau` with
  probability at least 1/2, so :math:`F(\tau) \le 2\,P(z(\tau) > b)`: segments whose bound is
  negligible skip the quadrature.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np
from numpy.polynomial.legendre import leggauss
from scipy.special import ndtr, ndtri

NEGLIGIBLE = 1e-7  # a first-passage bound below this is taken as 0


@dataclass(frozen=True)
class Posterior:
    """Samples of the degradation parameters of one group, diagonal parts only (the
    marginals of each indicator need no more). Shapes (S, n)."""

    mu: np.ndarray  # drift per day
    var: np.ndarray  # diagonal of Sigma, per day
    z_plus: np.ndarray  # mean level after tamping
    var_plus: np.ndarray  # diagonal of Sigma_z+
    source_samples: int = 0  # samples of the posterior these were taken from (0: these)
    step: int = 1  # every step-th of them

    @classmethod
    def from_samples(cls, mu, sigma, z_plus, sigma_z_plus, max_samples: int) -> Posterior:
        """Every ``len // max_samples``-th sample (at most ``max_samples`` of them)."""
        mu = np.asarray(mu, float)
        step = max(1, -(-mu.shape[0] // max_samples))
        take = slice(None, None, step)
        return cls(
            mu[take],
            np.diagonal(np.asarray(sigma, float), axis1=-2, axis2=-1)[take].copy(),
            np.asarray(z_plus, float)[take],
            np.diagonal(np.asarray(sigma_z_plus, float), axis1=-2, axis2=-1)[take].copy(),
            source_samples=mu.shape[0],
            step=step,
        )

    @property
    def drift_nonnegative(self) -> bool:
        return bool((self.mu >= 0).all())

    def weights(self, log_weights: np.ndarray | None) -> np.ndarray:
        """(S,) mixture weights of these samples for a segment whose state carries
        ``log_weights`` over the posterior's samples (None, or of another posterior's
        length: equal weights). The kept samples' weights, normalised: Bayes' rule on the
        thinned prior sample."""
        s = self.mu.shape[0]
        source = self.source_samples or s
        if log_weights is None or len(log_weights) != source:
            return np.full(s, 1.0 / s)
        kept = np.asarray(log_weights, float)[:: self.step][:s]
        w = np.exp(kept - kept.max())
        return w / w.sum()


def equal_weights(n_rows: int, post: Posterior) -> np.ndarray:
    """(n_rows, S) equal mixture weights."""
    s = post.mu.shape[0]
    return np.full((n_rows, s), 1.0 / s)


def _above(mean, var, log_limit):
    """P(N(mean, var) > log_limit), elementwise (var > 0)."""
    return ndtr((mean - log_limit) / np.sqrt(var))


def _rows_weights(w, n_rows: int, post: Posterior) -> np.ndarray:
    return equal_weights(n_rows, post) if w is None else np.ascontiguousarray(w, float)


def above_any(m, v, post: Posterior, tau, log_limit, w=None) -> np.ndarray:
    """P(any indicator above its limit) at times ``tau`` (days after the state), untamped.

    ``m``, ``v`` (N, n): state mean and variances; ``tau`` (N, T) days >= 0; ``log_limit``
    (N, n); ``w`` (N, S) each segment's mixture weights (None: equal). Returns (N, T).
    """
    return _above_any_kernel(
        np.ascontiguousarray(m, float), np.ascontiguousarray(v, float),
        np.ascontiguousarray(tau, float), np.ascontiguousarray(log_limit, float),
        post.mu, post.var, _rows_weights(w, len(m), post),
    )  # fmt: skip


def above_each(m, v, post: Posterior, tau, log_limit, w=None) -> np.ndarray:
    """P(indicator above its limit) per indicator at one time per segment, ``tau`` (N,) days,
    untamped: (N, n)."""
    t = np.asarray(tau, float)[:, None, None]
    mean = m[:, None, :] + post.mu[None] * t
    var = v[:, None, :] + post.var[None] * t
    p = _above(mean, np.maximum(var, 1e-12), log_limit[:, None, :])  # (N, S, n)
    return np.einsum("isk,is->ik", p, _rows_weights(w, len(m), post))


def above_any_after_tamping(post: Posterior, age, log_limit) -> np.ndarray:
    """P(any indicator above ``log_limit`` (n,)) at ages ``age`` (A,) days after a tamping,
    per sample: (S, A) (a segment's forecast: its weights times these)."""
    a = np.asarray(age, float)[None, :, None]
    mean = post.z_plus[:, None, :] + post.mu[:, None, :] * a
    var = post.var_plus[:, None, :] + post.var[:, None, :] * a
    p = _above(mean, np.maximum(var, 1e-12), np.asarray(log_limit)[None, None, :])
    return 1.0 - np.prod(1.0 - p, axis=-1)


def first_passage(m, v, post: Posterior, tau, log_limit, nodes: int = 5, w=None) -> np.ndarray:
    """P(some indicator reaches its limit within ``tau`` days), untamped: module docstring.

    ``m``, ``v`` (N, n), ``tau`` (N, T) days, ``log_limit`` (N, n), ``w`` (N, S) mixture
    weights (None: equal). Returns (N, T), the union bound over indicators of the mixture's
    first-passage probabilities. The start above the limit counts exactly; below it,
    Gauss-Legendre quadrature over the start's quantile.
    """
    x, gl = leggauss(nodes)
    sd0 = np.sqrt(np.maximum(v, 0.0))
    safe = np.maximum(sd0, 1e-12)
    below = np.where(sd0 > 0, ndtr((log_limit - m) / safe), (m < log_limit).astype(float))
    u = below[..., None] * (x + 1.0) / 2.0  # (N, n, K) quantiles of the start below the limit
    z0 = m[..., None] + sd0[..., None] * ndtri(np.clip(u, 1e-300, 1.0))
    weight = below[..., None] * gl / 2.0
    return _first_passage_kernel(
        np.ascontiguousarray(log_limit[..., None] - z0), np.ascontiguousarray(weight),
        1.0 - below, np.ascontiguousarray(tau, float), post.mu, post.var,
        _rows_weights(w, len(m), post),
    )  # fmt: skip


_SQRT2 = math.sqrt(2.0)
_LOG_SQRT_2PI = 0.5 * math.log(2.0 * math.pi)


@numba.njit(cache=True, nogil=True, inline="always")
def _ndtr(x):  # pragma: no cover - compiled
    return 0.5 * math.erfc(-x / _SQRT2)


@numba.njit(cache=True, nogil=True, inline="always")
def _log_ndtr(x):  # pragma: no cover - compiled
    if x > -20.0:
        return math.log(0.5 * math.erfc(-x / _SQRT2))
    # asymptotic series of the lower tail (relative error below 1e-9 here)
    x2 = x * x
    return -0.5 * x2 - math.log(-x) - _LOG_SQRT_2PI + math.log(1.0 - 1.0 / x2 + 3.0 / (x2 * x2))


@numba.njit(cache=True, nogil=True, parallel=True)
def _above_any_kernel(m, v, tau, log_limit, mu, var, w):  # pragma: no cover - compiled
    n_seg, n_t = tau.shape
    n_s, n = mu.shape
    out = np.empty((n_seg, n_t))
    for i in numba.prange(n_seg):
        for u in range(n_t):
            t = tau[i, u]
            total = 0.0
            for j in range(n_s):
                below = 1.0
                for k in range(n):
                    sd = math.sqrt(max(v[i, k] + var[j, k] * t, 1e-12))
                    below *= 1.0 - _ndtr((m[i, k] + mu[j, k] * t - log_limit[i, k]) / sd)
                total += w[i, j] * (1.0 - below)
            out[i, u] = total
    return out


@numba.njit(cache=True, nogil=True, parallel=True)
def _first_passage_kernel(dist, weight, above, tau, mu, var, w):  # pragma: no cover
    n_seg, n_t = tau.shape
    n_s, n = mu.shape
    out = np.empty((n_seg, n_t))
    for i in numba.prange(n_seg):
        for u in range(n_t):
            t = max(tau[i, u], 1e-9)
            total = 0.0
            for k in range(n):
                total += above[i, k]
                for q in range(dist.shape[2]):
                    d = dist[i, k, q]
                    if d <= 0.0:
                        total += weight[i, k, q]
                        continue
                    f = 0.0
                    for j in range(n_s):
                        s2 = max(var[j, k], 1e-18)
                        st = math.sqrt(s2 * t)
                        drift = mu[j, k] * t
                        first = _ndtr((drift - d) / st)
                        log_second = 2.0 * mu[j, k] * d / s2 + _log_ndtr((-d - drift) / st)
                        f += w[i, j] * min(first + math.exp(min(log_second, 0.0)), 1.0)
                    total += weight[i, k, q] * f
            out[i, u] = min(total, 1.0)
    return out
