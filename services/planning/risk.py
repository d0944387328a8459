r"""Forecasts of a segment under the degradation model, as the planner needs them.

Pure numpy/scipy. A segment's state is its filter's mixture summary, ``mean`` and ``cov`` of
``z = [ln Top6_mm, ln Align10_mm]`` at event time ``t_s``; the degradation posterior of its
group gives samples ``j`` of :math:`(\mu_j, \Sigma_j, z^+_j, \Sigma_{z^+,j})` (per day).
The forecast is the mixture over ``j`` (equal weights) of

.. math::

    z(t_s + \tau) \sim N(m + \mu_j \tau,\; P + \Sigma_j \tau)               \quad\text{untamped,}

    z(t_m + a) \sim N(z^+_j + \mu_j a,\; \Sigma_{z^+,j} + \Sigma_j a)    \quad\text{tamped at } t_m.

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
  Gauss-Hermite quadrature over it. Indicators combine by the union bound
  :math:`\min(1, F_{top} + F_{align})`, which never understates the risk.
  With :math:`\mu \ge 0` a path that reached ``b`` is above it at :math:`\tau` with
  probability at least 1/2, so :math:`F(\tau) \le 2\,P(z(\tau) > b)`: segments whose bound is
  negligible skip the quadrature.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.polynomial.hermite_e import hermegauss
from scipy.special import log_ndtr, ndtr

CHUNK = 2048  # segments per vectorised block: (CHUNK, samples, times, 2) arrays of ~30 MB
NEGLIGIBLE = 1e-7  # a first-passage bound below this is taken as 0


@dataclass(frozen=True)
class Posterior:
    """Samples of the degradation parameters of one group, diagonal parts only (the
    marginals of each indicator need no more). Shapes (S, n)."""

    mu: np.ndarray  # drift per day
    var: np.ndarray  # diagonal of Sigma, per day
    z_plus: np.ndarray  # mean level after tamping
    var_plus: np.ndarray  # diagonal of Sigma_z+

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
        )

    @property
    def drift_nonnegative(self) -> bool:
        return bool((self.mu >= 0).all())


def _above(mean, var, log_limit):
    """P(N(mean, var) > log_limit), elementwise (var > 0)."""
    return ndtr((mean - log_limit) / np.sqrt(var))


def above_any(m, v, post: Posterior, tau, log_limit) -> np.ndarray:
    """P(any indicator above its limit) at times ``tau`` (days after the state), untamped.

    ``m``, ``v`` (N, n): state mean and variances; ``tau`` (N, T) days >= 0; ``log_limit``
    (N, n). Returns (N, T).
    """
    out = np.empty(tau.shape)
    for lo in range(0, m.shape[0], CHUNK):
        s = slice(lo, lo + CHUNK)
        t = tau[s][:, None, :, None]  # (c, 1, T, 1)
        mean = m[s][:, None, None, :] + post.mu[None, :, None, :] * t  # (c, S, T, n)
        var = v[s][:, None, None, :] + post.var[None, :, None, :] * t
        p = _above(mean, np.maximum(var, 1e-12), log_limit[s][:, None, None, :])
        out[s] = (1.0 - np.prod(1.0 - p, axis=-1)).mean(axis=1)
    return out


def above_each(m, v, post: Posterior, tau, log_limit) -> np.ndarray:
    """P(indicator above its limit) per indicator at one time per segment, ``tau`` (N,) days,
    untamped: (N, n)."""
    t = np.asarray(tau, float)[:, None, None]
    mean = m[:, None, :] + post.mu[None] * t
    var = v[:, None, :] + post.var[None] * t
    return _above(mean, np.maximum(var, 1e-12), log_limit[:, None, :]).mean(axis=1)


def above_any_after_tamping(post: Posterior, age, log_limit) -> np.ndarray:
    """P(any indicator above ``log_limit`` (n,)) at ages ``age`` (A,) days after a tamping."""
    a = np.asarray(age, float)[None, :, None]
    mean = post.z_plus[:, None, :] + post.mu[:, None, :] * a
    var = post.var_plus[:, None, :] + post.var[:, None, :] * a
    p = _above(mean, np.maximum(var, 1e-12), np.asarray(log_limit)[None, None, :])
    return (1.0 - np.prod(1.0 - p, axis=-1)).mean(axis=0)


def first_passage(m, v, post: Posterior, tau, log_limit, nodes: int = 5) -> np.ndarray:
    """P(some indicator reaches its limit within ``tau`` days), untamped: module docstring.

    ``m``, ``v`` (N, n), ``tau`` (N, T) days, ``log_limit`` (N, n). Returns (N, T), the union
    bound over indicators of the mixture's first-passage probabilities.
    """
    x, w = hermegauss(nodes)
    w = w / w.sum()
    out = np.empty(tau.shape)
    for lo in range(0, m.shape[0], CHUNK):
        s = slice(lo, lo + CHUNK)
        z0 = m[s][:, None, :] + np.sqrt(np.maximum(v[s], 0.0))[:, None, :] * x[None, :, None]
        d = (log_limit[s][:, None, :] - z0)[:, None, :, None, :]  # (c, 1, K, 1, n)
        t = np.maximum(tau[s], 1e-9)[:, None, None, :, None]  # (c, 1, 1, T, 1)
        mu = post.mu[None, :, None, None, :]  # (1, S, 1, 1, n)
        s2 = np.maximum(post.var, 1e-18)[None, :, None, None, :]
        sd = np.sqrt(s2 * t)
        with np.errstate(over="ignore", invalid="ignore"):
            first = ndtr((mu * t - d) / sd)
            second = np.exp(np.minimum(2.0 * mu * d / s2 + log_ndtr((-d - mu * t) / sd), 0.0))
            f = np.where(d > 0, np.minimum(first + second, 1.0), 1.0)  # (c, S, K, T, n)
        f = np.tensordot(f.mean(axis=1), w, axes=([1], [0]))  # (c, T, n)
        out[s] = np.minimum(f.sum(axis=-1), 1.0)
    return out
