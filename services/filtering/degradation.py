"""Multivariate Wiener degradation model with tamping resets (paper Eq. 1-2, 7-8).

Time is in days, the state is ``z = [ln Top6_mm, ln Align10_mm]`` (any ``n``), and every
array carries leading batch axes: ``(..., Ns, n)`` for vectors, ``(..., Ns, n, n)`` for
matrices, where ``Ns`` indexes posterior samples and ``...`` e.g. segments.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np


def as_finite(name: str, a, min_ndim: int = 0) -> np.ndarray:
    """Return ``a`` as a float64 array, or raise ValueError naming it if not finite."""
    try:
        arr = np.asarray(a, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name}: not a numeric array ({exc})") from None
    if arr.ndim < min_ndim:
        raise ValueError(f"{name}: needs at least {min_ndim} dimensions, got shape {arr.shape}")
    if not np.isfinite(arr).all():
        raise ValueError(f"{name}: contains NaN or inf")
    return arr


def check_covariance(name: str, a: np.ndarray, definite: bool = False) -> None:
    """Raise ValueError naming ``a`` unless it is a stack of symmetric PSD (or PD) matrices."""
    if a.ndim < 2 or a.shape[-1] != a.shape[-2]:
        raise ValueError(f"{name}: expected (..., n, n) matrices, got shape {a.shape}")
    scale = np.abs(a).max(axis=(-2, -1), initial=0.0)
    if (np.abs(a - np.swapaxes(a, -1, -2)).max(axis=(-2, -1), initial=0.0) > 1e-12 * scale).any():
        raise ValueError(f"{name}: not symmetric")
    eig = np.linalg.eigvalsh(a)
    if definite and (eig[..., 0] <= 0).any():
        raise ValueError(f"{name}: not positive definite")
    # Relative tolerance: eigvalsh of an exactly singular PSD matrix may come out at -1e-17.
    if (eig[..., 0] < -1e-12 * np.abs(eig).max(axis=-1, initial=0.0)).any():
        raise ValueError(f"{name}: not positive semi-definite")


@dataclass(frozen=True)
class DegradationParams:
    """Posterior samples of the degradation parameters, one row per sample.

    Parameters
    ----------
    mu : array_like, shape (..., Ns, n)
        Drift per day.
    sigma : array_like, shape (..., Ns, n, n)
        Diffusion covariance per day.
    z_plus : array_like, shape (..., Ns, n)
        Mean state right after tamping.
    sigma_z_plus : array_like, shape (..., Ns, n, n)
        Covariance of the state right after tamping.

    Notes
    -----
    All four share the leading axes ``(..., Ns)``; ``...`` (e.g. segments) is optional and
    broadcasts against the state. Arrays are copied, made read-only, and the covariances
    checked to be symmetric positive semi-definite.
    """

    mu: np.ndarray
    sigma: np.ndarray
    z_plus: np.ndarray
    sigma_z_plus: np.ndarray

    def __post_init__(self):
        for f in fields(self):
            arr = as_finite(f.name, getattr(self, f.name), min_ndim=2).copy()
            arr.flags.writeable = False
            object.__setattr__(self, f.name, arr)
        if self.z_plus.shape != self.mu.shape:
            raise ValueError(f"z_plus: shape {self.z_plus.shape} != mu shape {self.mu.shape}")
        for name in ("sigma", "sigma_z_plus"):
            arr = getattr(self, name)
            if arr.shape != self.mu.shape + self.mu.shape[-1:]:
                raise ValueError(f"{name}: shape {arr.shape} does not match mu {self.mu.shape}")
            check_covariance(name, arr)

    @property
    def n(self) -> int:
        """State dimension."""
        return self.mu.shape[-1]

    @property
    def ns(self) -> int:
        """Number of posterior samples."""
        return self.mu.shape[-2]

    def take(self, idx) -> DegradationParams:
        """Rows ``idx`` of the leading (segment) axis; shared parameters are returned as is."""
        if self.mu.ndim == 2:
            return self
        rows = object.__new__(DegradationParams)
        for name in _PARAM_FIELDS:  # rows of validated arrays are valid: skip the eigen-check
            object.__setattr__(rows, name, getattr(self, name)[idx])
        return rows


_PARAM_FIELDS = tuple(f.name for f in fields(DegradationParams))


def mid_interval_age(dt):
    """Tamping age under the paper's rule that tamping happened mid-interval: ``dt / 2``."""
    return 0.5 * np.asarray(dt, dtype=np.float64)


def transition(z, P, params: DegradationParams, dt, tamping_age=None):
    r"""Propagate state mean and covariance over ``dt`` days (paper Eq. 1-2, 7-8).

    Without tamping in :math:`(t_{k-1}, t_k]`:

    .. math::

        \hat z_{k|k-1} = \hat z_{k-1} + \mu \Delta t, \qquad
        P_{k|k-1} = P_{k-1} + \Sigma \Delta t.

    With a tamping at :math:`t_m \in (t_{k-1}, t_k]` and age :math:`a = t_k - t_m`:

    .. math::

        \hat z_{k|k-1} = z^+ + \mu a, \qquad P_{k|k-1} = \Sigma_{z^+} + \Sigma a,

    which is the paper's Eq. 2 for :math:`a = \Delta t / 2` (:func:`mid_interval_age`).

    Parameters
    ----------
    z : array_like, shape (..., Ns, n)
    P : array_like, shape (..., Ns, n, n)
    params : DegradationParams
        Broadcasts against ``z`` and ``P``.
    dt : array_like, broadcastable to ``z.shape[:-2]``
        Interval length in days, ``>= 0``.
    tamping_age : array_like or None, broadcastable like ``dt``
        Days from tamping to the end of the interval, in ``[0, dt]``; NaN means no tamping
        in that interval, so one call mixes tamped and untamped batch entries.

    Returns
    -------
    z_pred, P_pred : ndarray
        Predicted mean ``(..., Ns, n)`` and covariance ``(..., Ns, n, n)``.
    """
    z = as_finite("z", z, min_ndim=2)
    P = as_finite("P", P, min_ndim=3)
    if P.shape != z.shape + z.shape[-1:]:
        raise ValueError(f"P: shape {P.shape} does not match z {z.shape}")
    if z.shape[-2:] != (params.ns, params.n):
        raise ValueError(f"params: (Ns, n) = {(params.ns, params.n)} but z has {z.shape[-2:]}")
    check_covariance("P", P)
    dt = as_finite("dt", dt)
    if (dt < 0).any():
        raise ValueError("dt: negative interval")
    try:
        batch = np.broadcast_shapes(z.shape[:-2], params.mu.shape[:-2])
    except ValueError:
        raise ValueError(f"params: leading shape does not broadcast to {z.shape[:-2]}") from None
    try:
        dt = np.broadcast_to(dt, batch)
    except ValueError:
        raise ValueError(f"dt: shape {dt.shape} does not broadcast to {z.shape[:-2]}") from None
    return transition_unchecked(z, P, params, dt, check_tamping_age(tamping_age, dt))


def check_tamping_age(tamping_age, dt):
    """Return ``tamping_age`` as floats (or None), raising ValueError unless NaN or in [0, dt]."""
    if tamping_age is None:
        return None
    try:
        tamping_age = np.asarray(tamping_age, dtype=np.float64)
        age = np.broadcast_to(np.nan_to_num(tamping_age, nan=0.0, posinf=np.inf), dt.shape)
    except (TypeError, ValueError):
        raise ValueError("tamping_age: not numeric or does not broadcast to dt") from None
    if not np.isfinite(age).all():
        raise ValueError("tamping_age: contains inf")
    if (age < 0).any() or (age > dt).any():
        raise ValueError("tamping_age: outside [0, dt]")
    return tamping_age


def transition_unchecked(z, P, params: DegradationParams, dt, tamping_age=None):
    """:func:`transition` without input validation, for callers holding trusted state."""
    dt = np.asarray(dt, dtype=np.float64)[..., None, None]
    z_pred = z + params.mu * dt
    P_pred = P + params.sigma * dt[..., None]
    if tamping_age is None:
        return z_pred, P_pred
    age = np.asarray(tamping_age, dtype=np.float64)[..., None, None]
    tamped = ~np.isnan(age)
    if not tamped.any():
        return z_pred, P_pred
    age = np.where(tamped, age, 0.0)
    z_pred = np.where(tamped, params.z_plus + params.mu * age, z_pred)
    P_pred = np.where(
        tamped[..., None], params.sigma_z_plus + params.sigma * age[..., None], P_pred
    )
    return z_pred, P_pred
