"""Kalman filter bank: one filter per (segment, posterior sample), vectorised (Eq. 7-12)."""

from __future__ import annotations

import numpy as np

from .degradation import (
    DegradationParams,
    as_finite,
    check_covariance,
    check_tamping_age,
    transition,
    transition_unchecked,
)

predict = transition  # the prediction step is exactly the degradation transition (Eq. 7-8)


def _check_observation(y, H, b, R, n: int):
    """Validate the observation model; returns float arrays ``y, H, b, R``."""
    H = as_finite("H", H)
    if H.ndim != 2 or H.shape[1] != n:
        raise ValueError(f"H: expected shape (m, {n}), got {H.shape}")
    m = H.shape[0]
    b = as_finite("b", b)
    if b.shape != (m,):
        raise ValueError(f"b: expected shape ({m},), got {b.shape}")
    R = as_finite("R", R)
    if R.shape != (m, m):
        raise ValueError(f"R: expected shape ({m}, {m}), got {R.shape}")
    check_covariance("R", R, definite=True)  # S = R when P = 0 right after a TRC restart
    y = as_finite("y", y, min_ndim=1)
    if y.shape[-1] != m:
        raise ValueError(f"y: last axis {y.shape[-1]} != m = {m}")
    return y, H, b, R


def update(z, P, y, H, b, R):
    r"""Kalman update of every filter with one on-board observation (paper Eq. 9-12).

    .. math::

        S = H P H^T + R, \qquad K = P H^T S^{-1}, \qquad
        \hat z^+ = \hat z + K (y - H \hat z - b),

    and, in Joseph form for round-off robustness, then symmetrised,

    .. math::

        P^+ = (I - K H) P (I - K H)^T + K R K^T, \qquad
        \nu = (y - H \hat z - b)^T S^{-1} (y - H \hat z - b).

    Parameters
    ----------
    z : array_like, shape (..., Ns, n)
    P : array_like, shape (..., Ns, n, n)
    y : array_like, shape (..., m)
        One observation per batch entry, shared by its ``Ns`` samples.
    H : array_like, shape (m, n)
    b : array_like, shape (m,)
    R : array_like, shape (m, m)
        Positive definite.

    Returns
    -------
    z_post : ndarray, shape (..., Ns, n)
    P_post : ndarray, shape (..., Ns, n, n)
    nis : ndarray, shape (..., Ns)
        Normalised innovation squared :math:`\nu`.
    """
    z = as_finite("z", z, min_ndim=2)
    P = as_finite("P", P, min_ndim=3)
    if P.shape != z.shape + z.shape[-1:]:
        raise ValueError(f"P: shape {P.shape} does not match z {z.shape}")
    check_covariance("P", P)
    y, H, b, R = _check_observation(y, H, b, R, z.shape[-1])
    try:
        np.broadcast_shapes(y.shape[:-1], z.shape[:-2])
    except ValueError:
        raise ValueError(f"y: shape {y.shape} does not broadcast to {z.shape[:-2]}") from None
    return update_unchecked(z, P, y, H, b, R)


def update_unchecked(z, P, y, H, b, R):
    """:func:`update` without validation; dispatches to closed-form 2x2 algebra if n = m = 2."""
    if H.shape == (2, 2):
        return _update_2x2(z, P, y, H, b, R)
    return _update_general(z, P, y, H, b, R)


def _update_general(z, P, y, H, b, R):
    """Any n, m via batched solves."""
    innovation = y[..., None, :] - z @ H.T - b  # (..., Ns, m)
    PHt = P @ H.T  # (..., Ns, n, m)
    S = H @ PHt + R
    # K = P H^T S^-1  <=>  K^T = S^-T (P H^T)^T
    K = np.swapaxes(np.linalg.solve(np.swapaxes(S, -1, -2), np.swapaxes(PHt, -1, -2)), -1, -2)
    z_post = z + (K @ innovation[..., None])[..., 0]
    A = np.eye(z.shape[-1]) - K @ H
    P_post = A @ P @ np.swapaxes(A, -1, -2) + K @ R @ np.swapaxes(K, -1, -2)
    P_post = 0.5 * (P_post + np.swapaxes(P_post, -1, -2))
    nis = (innovation * np.linalg.solve(S, innovation[..., None])[..., 0]).sum(-1)
    return z_post, P_post, nis


def _update_2x2(z, P, y, H, b, R):
    """n = m = 2 by elementwise closed forms on the 3 distinct entries of the symmetric P.

    Assumes P and R symmetric (``update`` checks it, the bank maintains it); the output P is
    symmetric by construction, which is what the final symmetrisation of the general path does.
    """
    (h00, h01), (h10, h11) = H.tolist()
    (r00, r01), (_, r11) = R.tolist()
    p00, p01, p11 = P[..., 0, 0], P[..., 0, 1], P[..., 1, 1]
    # M = P H^T, S = H M + R, K = M S^-1 with the adjugate inverse of S
    m00, m01 = p00 * h00 + p01 * h01, p00 * h10 + p01 * h11
    m10, m11 = p01 * h00 + p11 * h01, p01 * h10 + p11 * h11
    s00 = h00 * m00 + h01 * m10 + r00
    s01 = h00 * m01 + h01 * m11 + r01
    s11 = h10 * m01 + h11 * m11 + r11
    inv_det = 1.0 / (s00 * s11 - s01 * s01)
    k00, k01 = (m00 * s11 - m01 * s01) * inv_det, (m01 * s00 - m00 * s01) * inv_det
    k10, k11 = (m10 * s11 - m11 * s01) * inv_det, (m11 * s00 - m10 * s01) * inv_det
    z0, z1 = z[..., 0], z[..., 1]
    v0 = y[..., None, 0] - (h00 * z0 + h01 * z1 + b[0])
    v1 = y[..., None, 1] - (h10 * z0 + h11 * z1 + b[1])
    z_post = np.empty(np.broadcast_shapes(z.shape, v0.shape + (2,)))
    z_post[..., 0] = z0 + k00 * v0 + k01 * v1
    z_post[..., 1] = z1 + k10 * v0 + k11 * v1
    # Joseph form A P A^T + K R K^T with A = I - K H, via B = A P and C = K R
    a00, a01 = 1.0 - (k00 * h00 + k01 * h10), -(k00 * h01 + k01 * h11)
    a10, a11 = -(k10 * h00 + k11 * h10), 1.0 - (k10 * h01 + k11 * h11)
    b00, b01 = a00 * p00 + a01 * p01, a00 * p01 + a01 * p11
    b10, b11 = a10 * p00 + a11 * p01, a10 * p01 + a11 * p11
    c00, c01 = k00 * r00 + k01 * r01, k00 * r01 + k01 * r11
    c10, c11 = k10 * r00 + k11 * r01, k10 * r01 + k11 * r11
    P_post = np.empty(z_post.shape + (2,))
    P_post[..., 0, 0] = b00 * a00 + b01 * a01 + c00 * k00 + c01 * k01
    P_post[..., 1, 1] = b10 * a10 + b11 * a11 + c10 * k10 + c11 * k11
    P_post[..., 0, 1] = P_post[..., 1, 0] = b00 * a10 + b01 * a11 + c00 * k10 + c01 * k11
    nis = (s11 * v0 * v0 - 2.0 * s01 * v0 * v1 + s00 * v1 * v1) * inv_det
    return z_post, P_post, nis


class FilterBank:
    """State of ``S`` segments x ``Ns`` posterior samples, advanced one event per segment.

    Each method takes ``idx``, an array of distinct segment indices, and applies one event
    to each listed segment in one vectorised call.

    Parameters
    ----------
    n_segments : int
    params : DegradationParams
        Shared ``(Ns, n)`` or per segment ``(n_segments, Ns, n)``.

    Attributes
    ----------
    z : ndarray, shape (S, Ns, n)
    P : ndarray, shape (S, Ns, n, n)
    t : ndarray, shape (S,)
        Day of each segment's last event; NaN (and NaN state) before its first restart.
    params : DegradationParams
    """

    def __init__(self, n_segments: int, params: DegradationParams):
        self.params = params
        self.z = np.full((n_segments, params.ns, params.n), np.nan)
        self.P = np.full((n_segments, params.ns, params.n, params.n), np.nan)
        self.t = np.full(n_segments, np.nan)
        if params.mu.ndim > 2 and params.mu.shape[:-2] != (n_segments,):
            raise ValueError(f"params: leading shape {params.mu.shape[:-2]} != ({n_segments},)")

    def _idx(self, idx) -> np.ndarray:
        idx = np.atleast_1d(np.asarray(idx))
        if idx.ndim != 1 or not np.issubdtype(idx.dtype, np.integer):
            raise ValueError(f"idx: expected a 1-d integer array, got {idx.dtype} {idx.shape}")
        if ((idx < 0) | (idx >= len(self.t))).any():
            raise ValueError(f"idx: out of range [0, {len(self.t)})")
        if len(idx) > 1 and len(np.unique(idx)) != len(idx):
            raise ValueError("idx: duplicate segments (one event per segment per call)")
        return idx

    def _time(self, idx, t) -> np.ndarray:
        t = np.broadcast_to(as_finite("t", t), idx.shape)
        if (t < self.t[idx]).any():  # NaN (no state yet) compares False
            raise ValueError("t: earlier than the segment's last event")
        return t

    def restart(self, idx, z_trc, t) -> None:
        """TRC record at day ``t``: every sample gets ``z = z_trc`` (shape (k, n)), ``P = 0``."""
        idx = self._idx(idx)
        z_trc = as_finite("z_trc", z_trc)
        if z_trc.shape != (len(idx), self.z.shape[-1]):
            raise ValueError(f"z_trc: expected shape {(len(idx), self.z.shape[-1])}")
        self.t[idx] = self._time(idx, t)
        self.z[idx] = z_trc[:, None, :]
        self.P[idx] = 0.0

    def predict_to(self, idx, t, tamping_age=None) -> None:
        """Advance to day ``t``; ``tamping_age`` (k,), NaN = no tamping (see ``transition``).

        A segment without state yet may only be advanced through a tamping, which resets it.
        """
        idx = self._idx(idx)
        t = self._time(idx, t)
        dt = t - self.t[idx]
        z, P = self.z[idx], self.P[idx]
        unstarted = np.isnan(dt)
        if unstarted.any() and tamping_age is not None:
            # A tamping resets the state, so the missing prior state is never used.
            age = np.broadcast_to(np.asarray(tamping_age, dtype=np.float64), idx.shape)
            dt = np.where(unstarted, age, dt)
            z[unstarted], P[unstarted] = 0.0, 0.0
        if np.isnan(dt).any():
            raise ValueError("idx: segment without state (no TRC restart or tamping yet)")
        tamping_age = check_tamping_age(tamping_age, dt)
        self.z[idx], self.P[idx] = transition_unchecked(
            z, P, self.params.take(idx), dt, tamping_age
        )
        self.t[idx] = t

    def update(self, idx, y, H, b, R) -> np.ndarray:
        """On-board observation ``y`` (k, m) at each segment's current time; returns NIS (k, Ns)."""
        idx = self._idx(idx)
        if np.isnan(self.t[idx]).any():
            raise ValueError("idx: segment without state (no TRC restart or tamping yet)")
        y, H, b, R = _check_observation(y, H, b, R, self.z.shape[-1])
        if y.shape != (len(idx), H.shape[0]):
            raise ValueError(f"y: expected shape {(len(idx), H.shape[0])}, got {y.shape}")
        self.z[idx], self.P[idx], nis = update_unchecked(self.z[idx], self.P[idx], y, H, b, R)
        return nis

    def set_params(self, idx, params: DegradationParams) -> None:
        """New parameters for segments ``idx``: shared ``(Ns, n)`` or per segment ``(k, Ns, n)``."""
        idx = self._idx(idx)
        if (params.ns, params.n) != (self.params.ns, self.params.n):
            raise ValueError(f"params: (Ns, n) = {(params.ns, params.n)} != bank's")
        if params.mu.ndim > 2 and params.mu.shape[0] != len(idx):
            raise ValueError(f"params: {params.mu.shape[0]} rows for {len(idx)} segments")
        rows = {}
        for name, tail in (("mu", 2), ("sigma", 3), ("z_plus", 2), ("sigma_z_plus", 3)):
            old = getattr(self.params, name)
            rows[name] = np.broadcast_to(old, (len(self.t),) + old.shape[-tail:]).copy()
            rows[name][idx] = getattr(params, name)
        self.params = DegradationParams(**rows)

    def get_state(self, idx) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Copies of ``(z, P, t)`` of segments ``idx``."""
        idx = self._idx(idx)
        return self.z[idx].copy(), self.P[idx].copy(), self.t[idx].copy()

    def set_state(self, idx, z, P, t) -> None:
        """Restore ``(z, P, t)`` of segments ``idx``, e.g. from :meth:`get_state`."""
        idx = self._idx(idx)
        self.z[idx], self.P[idx], self.t[idx] = z, P, t

    def copy(self) -> FilterBank:
        """Independent snapshot of the whole bank (params are immutable and shared)."""
        other = object.__new__(FilterBank)
        other.params = self.params
        other.z, other.P, other.t = self.z.copy(), self.P.copy(), self.t.copy()
        return other
