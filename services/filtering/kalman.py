"""Kalman filter bank: one filter per (segment, posterior sample), vectorised (Eq. 7-12)."""

from __future__ import annotations

import threading
from dataclasses import dataclass

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

# Large batches are processed in blocks of about this many filters: every temporary then
# stays below glibc's mmap threshold (128 KiB) and in cache, instead of being mapped and
# page-faulted afresh by each of the ~100 elementwise operations of an update.
BLOCK_FILTERS = 8192
_LOG_2PI = float(np.log(2.0 * np.pi))


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


def update(z, P, y, H, b, R, loglik: bool = False):
    r"""Kalman update of every filter with one on-board observation (paper Eq. 9-12).

    .. math::

        S = H P H^T + R, \qquad K = P H^T S^{-1}, \qquad
        \hat z^+ = \hat z + K (y - H \hat z - b),

    and, in Joseph form for round-off robustness, then symmetrised,

    .. math::

        P^+ = (I - K H) P (I - K H)^T + K R K^T, \qquad
        \nu = (y - H \hat z - b)^T S^{-1} (y - H \hat z - b).

    With ``loglik``, also the log-likelihood of the observation under each filter's
    one-step prediction, the term of the prediction error decomposition that the
    filtering core accumulates into the mixture weights (``mixture.weights_from_log``):

    .. math::

        \log \mathcal N(y - H \hat z - b; 0, S) = -\tfrac12 \left(\nu + \ln |S|
        + m \ln 2\pi\right).

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
    loglik : bool
        Also return the log-likelihood.

    Returns
    -------
    z_post : ndarray, shape (..., Ns, n)
    P_post : ndarray, shape (..., Ns, n, n)
    nis : ndarray, shape (..., Ns)
        Normalised innovation squared :math:`\nu`.
    loglik : ndarray, shape (..., Ns)
        Only with ``loglik``: :math:`\log \mathcal N(y - H \hat z - b; 0, S)`.
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
    return update_unchecked(z, P, y, H, b, R, loglik)


def update_unchecked(z, P, y, H, b, R, loglik: bool = False):
    """:func:`update` without validation; dispatches to closed-form 2x2 algebra if n = m = 2."""
    if H.shape == (2, 2):
        z_post, P_post, nis, logdet = _update_2x2(z, P, y, H, b, R, loglik)
    else:
        z_post, P_post, nis, logdet = _update_general(z, P, y, H, b, R, loglik)
    if not loglik:
        return z_post, P_post, nis
    # -(nis + ln|S| + m ln 2 pi) / 2, in place on the fresh ln|S| array
    logdet += nis
    logdet += H.shape[0] * _LOG_2PI
    logdet *= -0.5
    return z_post, P_post, nis, logdet


def _update_general(z, P, y, H, b, R, logdet: bool = False):
    """Any n, m via batched solves; returns ``(z, P, nis, ln |S| or None)``."""
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
    return z_post, P_post, nis, np.linalg.slogdet(S)[1] if logdet else None


_COEFFS_2X2: dict = {}
_WORK_2X2 = threading.local()
# z_post = z + K v from the rows (k00 v0, k01 v1, k10 v0, k11 v1, z0, z1)
_Z_POST = np.array([[1.0, 0.0], [1.0, 0.0], [0.0, 1.0], [0.0, 1.0], [1.0, 0.0], [0.0, 1.0]])
_Z_POST.flags.writeable = False


def _coeffs_2x2(H, b, R):
    """Constant coefficient matrices of :func:`_update_2x2` for this (H, b, R), cached."""
    key = (H.dtype.char + b.dtype.char + R.dtype.char, H.tobytes(), b.tobytes(), R.tobytes())
    coeffs = _COEFFS_2X2.get(key)
    if coeffs is not None:
        return coeffs
    (h00, h01), (h10, h11) = h = np.asarray(H, dtype=np.float64).tolist()
    (r00, r01), (_, r11) = np.asarray(R, dtype=np.float64).tolist()
    b0, b1 = np.asarray(b, dtype=np.float64).tolist()
    # x = lin @ (p00, p01, p10, p11, 1) (p10 unused: P is symmetric), from M = P H^T and
    # adj(S) = [[s11, -s01], [-s01, s00]], S = H M + R:
    m00, m01 = [h00, h01, 0.0, 0.0, 0.0], [h10, h11, 0.0, 0.0, 0.0]
    m10, m11 = [0.0, h00, 0.0, h01, 0.0], [0.0, h10, 0.0, h11, 0.0]
    s00 = [h00 * h00, 2.0 * h00 * h01, 0.0, h01 * h01, r00]
    s01 = [-h00 * h10, -(h00 * h11 + h01 * h10), 0.0, -h01 * h11, -r01]  # -s01
    s11 = [h10 * h10, 2.0 * h10 * h11, 0.0, h11 * h11, r11]
    lin = np.array(
        [m00, m00, m10, m10, m01, m01, m11, m11]  # x[0:8] * x[8:16] -> products of M adj(S)
        + [s11, s01, s11, s01, s01, s00, s01, s00]  # x[10:14] = adj(S)
        + [s00, s01]  # x[8:10] * x[16:18] -> s11 s00, s01^2
    )
    # g = kmap @ (k00, k01, k10, k11, 1): rows K_jl, A_jl, C_jl by (l, j), with A = I - K H
    # and C = K R; A is also read as (k, i): A_ik.
    r = [[r00, r01], [r01, r11]]
    kmap = []
    for part in range(3):
        for l in (0, 1):
            for j in (0, 1):
                if part == 0:  # K_jl
                    kmap.append([float((q, m) == (j, l)) for q in (0, 1) for m in (0, 1)] + [0.0])
                elif part == 1:  # A_jl = d_jl - sum_m k_jm h_ml
                    row = [-h[m][l] if q == j else 0.0 for q in (0, 1) for m in (0, 1)]
                    kmap.append(row + [float(j == l)])
                else:  # C_jl = sum_m k_jm r_ml
                    kmap.append(
                        [r[m][l] if q == j else 0.0 for q in (0, 1) for m in (0, 1)] + [0.0]
                    )
    neg_hb = np.array([[-h00, -h01, -b0], [-h10, -h11, -b1]])  # -(H z + b)
    coeffs = (lin, np.array(kmap), neg_hb)
    for a in coeffs:
        a.flags.writeable = False
    if len(_COEFFS_2X2) >= 64:
        _COEFFS_2X2.clear()
    _COEFFS_2X2[key] = coeffs
    return coeffs


def _work_2x2(n: int):
    """Per-thread scratch arrays for ``n`` filters: no allocation (nor page faults) per call."""
    cache = getattr(_WORK_2X2, "cache", None)
    if cache is None:
        cache = _WORK_2X2.cache = {}
    work = cache.get(n)
    if work is None:
        if len(cache) >= 8:
            cache.clear()
        work = cache[n] = tuple(np.empty((rows, n)) for rows in (5, 18, 10, 5, 16, 16, 7, 4))
        work[0][4] = work[3][4] = work[6][6] = 1.0  # constant rows of p, k and zk
    return work


def _update_2x2(z, P, y, H, b, R, logdet: bool = False):
    r"""n = m = 2 in closed form, on stacked component rows: one numpy call per step.

    With the 3 distinct entries of the symmetric P, per filter,

    .. math::

        M = P H^T, \qquad S = H M + R, \qquad
        K = M \operatorname{adj}(S) / \det S, \qquad
        \operatorname{adj}(S) = \begin{pmatrix} s_{11} & -s_{01} \\ -s_{01} & s_{00}
        \end{pmatrix},

        v = y - H \hat z - b, \qquad \hat z^+ = \hat z + K v, \qquad
        \nu = v^T \operatorname{adj}(S)\, v / \det S
        = (s_{11} v_0^2 - 2 s_{01} v_0 v_1 + s_{00} v_1^2) / \det S,

        P^+ = A P A^T + K R K^T, \quad A = I - K H: \quad
        P^+_{ij} = \textstyle\sum_l (B_{il} A_{jl} + C_{il} K_{jl}), \quad B = A P, \; C = K R.

    The N filters are columns of (rows, N) arrays: the entries of M and adj(S) (repeated as
    the products need them) are one matrix product of constant coefficients with the rows
    (p00, p01, p10, p11, 1); A, K and C one product with (k00, k01, k10, k11, 1); the rest
    are a few elementwise calls on whole row blocks. So the cost is ~20 numpy calls whatever
    the batch, and scratch arrays are reused (per thread) rather than allocated per call.

    Assumes P and R symmetric (``update`` checks it, the bank maintains it); the output P is
    exactly symmetric, which is what the final symmetrisation of the general path does.
    Returns ``(z, P, nis, ln det S or None)`` (``ln det S`` only with ``logdet``).
    """
    lin, kmap, neg_hb = _coeffs_2x2(H, b, R)
    ns = z.shape[-2]
    lead = z.shape[:-2]
    if P.shape[:-2] != z.shape[:-1] or y.shape[:-1] != lead:
        shape = np.broadcast_shapes(z.shape[:-1], P.shape[:-2], y.shape[:-1] + (1,))
        lead, ns = shape[:-1], shape[-1]
        z = np.broadcast_to(z, shape + (2,))
        P = np.broadcast_to(P, shape + (2, 2))
        y = np.broadcast_to(y, lead + (2,))
    n = z.size // 2
    if n == 1:
        # One filter: numpy would hand the products below to BLAS gemv instead of gemm,
        # whose roundings differ; two copies keep the one-filter result bit-identical to
        # that filter's in any batch.
        twice = _update_2x2(
            np.concatenate([z.reshape(1, 2)] * 2),
            np.concatenate([P.reshape(1, 2, 2)] * 2),
            y.reshape(2),
            H,
            b,
            R,
            logdet,
        )
        return tuple(
            None if a is None else a[:1].reshape(lead + (ns,) + a.shape[1:]) for a in twice
        )
    p, x, q, k, g, t, zk, vv = _work_2x2(n)
    np.copyto(p[:4], P.reshape(n, 4).T)
    np.matmul(lin, p, x)
    np.multiply(x[:10], x[8:], q)
    det = q[9]
    np.subtract(q[8], det, det)
    np.add(q[:4], q[4:8], k[:4])
    np.divide(k[:4], det, k[:4])  # K = M adj(S) / det(S)
    # innovation v = y - b - H z, nis = v^T adj(S) v / det(S)
    np.copyto(zk[4:6], z.reshape(n, 2).T)
    v = q[:2]
    np.matmul(neg_hb, zk[4:], v)
    v3 = v.reshape(2, -1, ns)
    np.add(v3, y.reshape(-1, 2).T[:, :, None], v3)
    vv3 = vv.reshape(2, 2, n)
    np.multiply(v[:, None], v, vv3)
    np.multiply(vv, x[10:14], vv)
    # Three adds in a fixed order rather than ``ones @ vv``: BLAS gemv sums a column in an
    # order that depends on its position in the batch, and a filter's numbers must not
    # depend on which other filters share the call (the tracker's batched re-run).
    nis = vv[0] + vv[1]
    nis += vv[2]
    nis += vv[3]
    np.divide(nis, det, nis)
    log_det = np.log(det).reshape(lead + (ns,)) if logdet else None  # det is scratch
    np.multiply(k[:4].reshape(2, 2, n), v, zk[:4].reshape(2, 2, n))  # k_ij v_j
    z_post = zk[:6].T @ _Z_POST
    # Joseph form: P+_ij = sum_l (C_il K_jl + B_il A_jl), B = A P, C = K R
    np.matmul(kmap, k, g[:12])
    ap = x[:8].reshape(2, 2, 2, n)  # (k, l, i): A_ik P_kl
    np.multiply(g[4:8].reshape(2, 1, 2, n), p[:4].reshape(2, 2, 1, n), ap)
    np.add(ap[0], ap[1], g[12:].reshape(2, 2, n))
    f, gg = g[8:].reshape(2, 2, 2, 1, n), g[:8].reshape(2, 2, 1, 2, n)
    np.multiply(f, gg, t.reshape(2, 2, 2, 2, n))  # (part, l, i, j)
    P_post = np.empty((n, 4))
    np.add.reduce(t.reshape(4, 4, n), axis=0, out=P_post.T)
    P_post[:, 2] = P_post[:, 1]  # symmetric: P+_10 := P+_01
    return (
        z_post.reshape(lead + (ns, 2)),
        P_post.reshape(lead + (ns, 2, 2)),
        nis.reshape(lead + (ns,)),
        log_det,
    )


@dataclass(frozen=True)
class ObservationModel:
    """The observation model y = H z + b + e, e ~ N(0, R) (Eq. 3-4), validated once.

    ``R`` must be positive definite: right after a TRC restart P = 0 and S = R.
    """

    H: np.ndarray  # (m, n)
    b: np.ndarray  # (m,)
    R: np.ndarray  # (m, m)

    def __post_init__(self):
        H = as_finite("H", self.H)
        if H.ndim != 2:
            raise ValueError(f"H: expected shape (m, n), got {H.shape}")
        _, H, b, R = _check_observation(np.zeros(H.shape[0]), H, self.b, self.R, H.shape[1])
        for name, value in (("H", H), ("b", b), ("R", R)):
            value = value.copy()
            value.flags.writeable = False
            object.__setattr__(self, name, value)

    @property
    def m(self) -> int:
        return self.H.shape[0]

    @property
    def n(self) -> int:
        return self.H.shape[1]


def contiguous_rows(rows: np.ndarray) -> np.ndarray | slice:
    """``rows`` as a slice when they are consecutive: views instead of gathered copies."""
    first, last = int(rows[0]), int(rows[-1])
    if last - first == len(rows) - 1 and (len(rows) == 1 or (np.diff(rows) == 1).all()):
        return slice(first, last + 1)
    return rows


class FilterBank:
    r"""State of ``S`` segments x ``Ns`` posterior samples, advanced one event per segment.

    Each method takes ``idx``, an array of distinct segment indices, and applies one event
    to each listed segment in one vectorised call (in blocks of ``BLOCK_FILTERS`` filters).

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
    log_w : ndarray, shape (S, Ns)
        Log-likelihood of each segment's on-board observations since its last restart under
        each sample, :math:`\sum_k \log \mathcal N(\nu_{jk}; 0, S_{jk})`: the
        unnormalised log mixture weights (``mixture.weights_from_log``). 0 (equal weights)
        after a restart, or when a tamping starts a segment without state.
    params : DegradationParams
    """

    def __init__(self, n_segments: int, params: DegradationParams):
        self.params = params
        self.z = np.full((n_segments, params.ns, params.n), np.nan)
        self.P = np.full((n_segments, params.ns, params.n, params.n), np.nan)
        self.t = np.full(n_segments, np.nan)
        self.log_w = np.zeros((n_segments, params.ns))
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

    def _blocks(self, k: int):
        """Slices of ``range(k)`` holding about BLOCK_FILTERS filters each."""
        step = max(1, BLOCK_FILTERS // self.z.shape[1])
        return [slice(i, i + step) for i in range(0, k, step)]

    def restart(self, idx, z_trc, t) -> None:
        """TRC record at day ``t``: every sample gets ``z = z_trc`` (k, n), ``P = 0``, log_w 0."""
        idx = self._idx(idx)
        z_trc = as_finite("z_trc", z_trc)
        if z_trc.shape != (len(idx), self.z.shape[-1]):
            raise ValueError(f"z_trc: expected shape {(len(idx), self.z.shape[-1])}")
        self.t[idx] = self._time(idx, t)
        self.z[idx] = z_trc[:, None, :]
        self.P[idx] = 0.0
        self.log_w[idx] = 0.0

    def _prepare_predict(self, idx, t, tamping_age):
        """Checked (t, dt, tamping_age) of a prediction to day ``t``; may reset unstarted rows."""
        t = self._time(idx, t)
        dt = t - self.t[idx]
        unstarted = np.isnan(dt)
        if unstarted.any():
            if tamping_age is None:
                raise ValueError("idx: segment without state (no TRC restart or tamping yet)")
            # A tamping resets the state, so the missing prior state is never used.
            age = np.broadcast_to(np.asarray(tamping_age, dtype=np.float64), idx.shape)
            dt = np.where(unstarted, age, dt)
            self.z[idx[unstarted]], self.P[idx[unstarted]] = 0.0, 0.0
            self.log_w[idx[unstarted]] = 0.0
            if np.isnan(dt).any():
                raise ValueError("idx: segment without state (no TRC restart or tamping yet)")
        return t, dt, check_tamping_age(tamping_age, dt)

    def predict_to(self, idx, t, tamping_age=None) -> None:
        """Advance to day ``t``; ``tamping_age`` (k,), NaN = no tamping (see ``transition``).

        A segment without state yet may only be advanced through a tamping, which resets it.
        """
        idx = self._idx(idx)
        t, dt, tamping_age = self._prepare_predict(idx, t, tamping_age)
        for block in self._blocks(len(idx)):
            rows = contiguous_rows(idx[block])
            age = None if tamping_age is None else np.broadcast_to(tamping_age, idx.shape)[block]
            self.z[rows], self.P[rows] = transition_unchecked(
                self.z[rows], self.P[rows], self.params.take(rows), dt[block], age
            )
        self.t[idx] = t

    def _check_update(self, idx, y, model: ObservationModel) -> np.ndarray:
        if not isinstance(model, ObservationModel):
            raise ValueError(f"model: expected an ObservationModel, got {type(model).__name__}")
        if model.n != self.z.shape[-1]:
            raise ValueError(f"model: H has n = {model.n}, the bank {self.z.shape[-1]}")
        y = as_finite("y", y)
        if y.shape != (len(idx), model.m):
            raise ValueError(f"y: expected shape {(len(idx), model.m)}, got {y.shape}")
        return y

    def update(self, idx, y, model: ObservationModel) -> np.ndarray:
        """On-board observation ``y`` (k, m) at each segment's current time; returns NIS (k, Ns).

        Adds each sample's log-likelihood of ``y`` to :attr:`log_w`.
        """
        idx = self._idx(idx)
        if np.isnan(self.t[idx]).any():
            raise ValueError("idx: segment without state (no TRC restart or tamping yet)")
        y = self._check_update(idx, y, model)
        nis = np.empty((len(idx), self.z.shape[1]))
        for block in self._blocks(len(idx)):
            rows = contiguous_rows(idx[block])
            self.z[rows], self.P[rows], nis[block], loglik = update_unchecked(
                self.z[rows], self.P[rows], y[block], model.H, model.b, model.R, loglik=True
            )
            self.log_w[rows] += loglik
        return nis

    def observe(self, idx, t, y, model: ObservationModel, tamping_age=None) -> np.ndarray:
        """``predict_to(idx, t, tamping_age)`` then ``update(idx, y, model)``, in one pass.

        The usual on-board event; one gather and one scatter of the state instead of two.
        Returns the NIS (k, Ns).
        """
        idx = self._idx(idx)
        y = self._check_update(idx, y, model)
        t, dt, tamping_age = self._prepare_predict(idx, t, tamping_age)
        nis = np.empty((len(idx), self.z.shape[1]))
        for block in self._blocks(len(idx)):
            rows = contiguous_rows(idx[block])
            age = None if tamping_age is None else np.broadcast_to(tamping_age, idx.shape)[block]
            z, P = transition_unchecked(
                self.z[rows], self.P[rows], self.params.take(rows), dt[block], age
            )
            self.z[rows], self.P[rows], nis[block], loglik = update_unchecked(
                z, P, y[block], model.H, model.b, model.R, loglik=True
            )
            self.log_w[rows] += loglik
        self.t[idx] = t
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

    def get_state(self, idx) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Copies of ``(z, P, t, log_w)`` of segments ``idx``."""
        idx = self._idx(idx)
        return self.z[idx].copy(), self.P[idx].copy(), self.t[idx].copy(), self.log_w[idx].copy()

    def set_state(self, idx, z, P, t, log_w=0.0) -> None:
        """Restore ``(z, P, t, log_w)`` of segments ``idx``, e.g. from :meth:`get_state`.

        ``log_w`` defaults to equal weights.
        """
        idx = self._idx(idx)
        self.z[idx], self.P[idx], self.t[idx], self.log_w[idx] = z, P, t, log_w

    def copy(self) -> FilterBank:
        """Independent snapshot of the whole bank (params are immutable and shared)."""
        other = object.__new__(FilterBank)
        other.params = self.params
        other.z, other.P, other.t = self.z.copy(), self.P.copy(), self.t.copy()
        other.log_w = self.log_w.copy()
        return other
