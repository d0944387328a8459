r"""The compiled (numba) loops of the filter: the on-board index step of the filter bank,
one pass over each filter, and the mixture summary's quantiles and exceedances
(:func:`mixture_quantile`, :func:`mixture_survival`), one vectorised pass over the
components per evaluation (:func:`.vecmath.ndtr`) instead of numpy temporaries.

The tracker's fold spends nearly all its time in the index step (predict, the CUSUM score,
update, log-likelihood, NIS) over ``rows x Ns`` filters. Written with numpy that step is
~25 array passes over temporaries per block; here a row's samples are copied into
contiguous scratch rows and stepped by one loop without calls or sums, which the compiler
turns into vector instructions (8 samples at a time with AVX-512; ``exp`` and ``log`` are
:mod:`.vecmath`'s, written out for that), then the weighted sums run in one sequential
pass (``error_model="numpy"``: no zero-division checks in the loop).

Per segment row ``r`` (time step :math:`\Delta t` days since its last event, observation
:math:`y`, model :math:`H, b, R`, weights :math:`w_j \propto e^{\log w_j}` before the update)
and sample :math:`j` (drift :math:`\mu_j`, diffusion :math:`\Sigma_j`), paper Eq. 7-12:

.. math::

    \hat z_j = z_j + \mu_j \Delta t, \qquad P_j = P_j + \Sigma_j \Delta t,

    S_j = H P_j H^T + R, \quad K_j = P_j H^T S_j^{-1}, \quad
    \nu_j = y - H \hat z_j - b,

    z_j^+ = \hat z_j + K_j \nu_j, \qquad
    P_j^+ = (I - K_j H) P_j (I - K_j H)^T + K_j R K_j^T \quad \text{(Joseph form)},

    \mathrm{nis}_j = \nu_j^T S_j^{-1} \nu_j, \qquad
    \log w_j \mathrel{+}= -\tfrac12 (\mathrm{nis}_j + \ln |S_j| + 2 \ln 2\pi),

the NIS of the row :math:`\sum_j w_j \mathrm{nis}_j`, and the CUSUM score of
:func:`services.filtering.banks.low_score` on the prediction,

.. math::

    s = \bar u / \sqrt{\textstyle\sum_j w_j (v_j + u_j^2) - \bar u^2}, \quad
    u_j = \mathbf 1^T (y - H \hat z_j - b), \quad v_j = h^T P_j h + \mathbf 1^T R \mathbf 1,
    \quad h = H^T \mathbf 1 .

``P`` is kept exactly symmetric (``P+_10 := P+_01``). Every number of a row depends on that
row's inputs only, in a fixed order, so a batch of one segment and a re-run of thousands
give the same bits. Compiled on first use and cached next to this file
(``__pycache__``), so later processes load it in milliseconds.
"""

from __future__ import annotations

import math
import threading

import numba
import numpy as np

from services.filtering.vecmath import exp_nonpositive, log_normal, ndtr

DAY_S = 86_400.0
_LOG_2PI = math.log(2.0 * math.pi)


_SCRATCH = 11  # a row's samples and their temporaries (see _load, _update)
_ROWS_PER_TASK = 16  # rows a parallel task steps with one scratch allocation


@numba.njit(cache=True, nogil=True, fastmath={"contract"}, error_model="numpy", inline="always")
def _load(F, row, tmp):
    """Row ``row`` of the bank into the contiguous rows of ``tmp``: z in 0-1, P's three
    distinct entries in 2-4, log_w in 10 (what :func:`_update` steps)."""
    ns = F.shape[1] // 7  # a row: z (Ns, 2), P (Ns, 2, 2), log_w (Ns), each row-major
    op, ow = 2 * ns, 6 * ns  # where P and log_w start
    for j in range(ns):
        tmp[0, j] = F[row, 2 * j]
        tmp[1, j] = F[row, 2 * j + 1]
        tmp[2, j] = F[row, op + 4 * j]
        tmp[3, j] = F[row, op + 4 * j + 1]
        tmp[4, j] = F[row, op + 4 * j + 3]
        tmp[10, j] = F[row, ow + j]


@numba.njit(cache=True, nogil=True, fastmath={"contract"}, error_model="numpy", inline="always")
def _store(F, row, tmp):
    """:func:`_load` back, after at least one :func:`_update` (P kept exactly symmetric)."""
    ns = F.shape[1] // 7
    op, ow = 2 * ns, 6 * ns
    for j in range(ns):
        F[row, 2 * j] = tmp[0, j]
        F[row, 2 * j + 1] = tmp[1, j]
        F[row, op + 4 * j] = tmp[2, j]
        F[row, op + 4 * j + 1] = tmp[3, j]
        F[row, op + 4 * j + 2] = tmp[3, j]
        F[row, op + 4 * j + 3] = tmp[4, j]
        F[row, ow + j] = tmp[10, j]


@numba.njit(cache=True, nogil=True, fastmath={"contract"}, error_model="numpy", inline="always")
def _step(F, t_s, row, t_new, y0, y1, mu, sigma, g, H, b, R, tmp):
    """One index ``(y0, y1)`` at ``t_new`` on row ``row`` of the bank with parameter set
    ``g``, in place; returns the row's ``(nis, score)``: :func:`_load`, :func:`_update`,
    :func:`_store` (inlined into every compiled loop: the same code)."""
    _load(F, row, tmp)
    out = _update(tmp, (t_new - t_s[row]) / DAY_S, y0, y1, mu, sigma, g, H, b, R)
    _store(F, row, tmp)
    t_s[row] = t_new
    return out


@numba.njit(cache=True, nogil=True, fastmath={"contract"}, error_model="numpy", inline="always")
def _update(tmp, dt, y0, y1, mu, sigma, g, H, b, R):
    """One index ``(y0, y1)``, ``dt`` days after the last event, on the samples held in
    ``tmp`` (11, Ns) (:func:`_load`) with parameter set ``g``, in place; returns
    ``(nis, score)``.

    The samples sit in the contiguous rows of ``tmp``, so that the filter loop, ``exp``
    and ``log`` (:mod:`.vecmath`) run over Ns lanes at a time; the weighted sums stay
    sequential in ``j``, in a fixed order. A run of indices on one row
    (:func:`_run_row`) keeps them there from one index to the next.
    """
    ns = tmp.shape[1]
    h00, h01, h10, h11 = H[0, 0], H[0, 1], H[1, 0], H[1, 1]
    r00, r01, r11 = R[0, 0], R[0, 1], R[1, 1]
    b0, b1 = b[0], b[1]
    hs0, hs1 = h00 + h10, h01 + h11  # h = H^T 1
    r_sum = r00 + r01 + R[1, 0] + r11  # 1^T R 1
    b_sum = b0 + b1
    y_sum = y0 + y1
    a0, a1, b00, b01, b11 = tmp[0], tmp[1], tmp[2], tmp[3], tmp[4]  # z, P of the samples
    w, us, vs, nis_s, log_det, log_w = tmp[5], tmp[6], tmp[7], tmp[8], tmp[9], tmp[10]
    for j in range(ns):  # predict: z + mu dt, P + Sigma dt
        a0[j] = a0[j] + mu[g, j, 0] * dt
        a1[j] = a1[j] + mu[g, j, 1] * dt
        b00[j] = b00[j] + sigma[g, j, 0, 0] * dt
        b01[j] = b01[j] + sigma[g, j, 0, 1] * dt
        b11[j] = b11[j] + sigma[g, j, 1, 1] * dt
    top = -np.inf
    for j in range(ns):
        top = max(top, log_w[j])
    for j in range(ns):
        w[j] = exp_nonpositive(log_w[j] - top)
    for j in range(ns):
        z0, z1, p00, p01, p11 = a0[j], a1[j], b00[j], b01[j], b11[j]
        # the CUSUM score's moments on the prediction
        us[j] = y_sum - (z0 * hs0 + z1 * hs1 + b_sum)
        vs[j] = (p00 * hs0 + p01 * hs1) * hs0 + (p01 * hs0 + p11 * hs1) * hs1 + r_sum
        # M = P H^T, S = H M + R
        m00 = p00 * h00 + p01 * h01
        m01 = p00 * h10 + p01 * h11
        m10 = p01 * h00 + p11 * h01
        m11 = p01 * h10 + p11 * h11
        s00 = h00 * m00 + h01 * m10 + r00
        s01 = h00 * m01 + h01 * m11 + r01
        s11 = h10 * m01 + h11 * m11 + r11
        det = s00 * s11 - s01 * s01
        # K = M adj(S) / det
        k00 = (m00 * s11 - m01 * s01) / det
        k01 = (m01 * s00 - m00 * s01) / det
        k10 = (m10 * s11 - m11 * s01) / det
        k11 = (m11 * s00 - m10 * s01) / det
        v0 = y0 - (h00 * z0 + h01 * z1 + b0)
        v1 = y1 - (h10 * z0 + h11 * z1 + b1)
        nis_s[j] = (s11 * v0 * v0 - 2.0 * s01 * v0 * v1 + s00 * v1 * v1) / det
        log_det[j] = log_normal(det)
        a0[j] = z0 + k00 * v0 + k01 * v1
        a1[j] = z1 + k10 * v0 + k11 * v1
        # Joseph form with A = I - K H, C = K R
        a00 = 1.0 - (k00 * h00 + k01 * h10)
        a01 = -(k00 * h01 + k01 * h11)
        a10 = -(k10 * h00 + k11 * h10)
        a11 = 1.0 - (k10 * h01 + k11 * h11)
        c00 = k00 * r00 + k01 * r01
        c01 = k00 * r01 + k01 * r11
        c10 = k10 * r00 + k11 * r01
        c11 = k10 * r01 + k11 * r11
        ap00 = a00 * p00 + a01 * p01
        ap01 = a00 * p01 + a01 * p11
        ap10 = a10 * p00 + a11 * p01
        ap11 = a10 * p01 + a11 * p11
        b00[j] = ap00 * a00 + ap01 * a01 + c00 * k00 + c01 * k01
        b01[j] = ap00 * a10 + ap01 * a11 + c00 * k10 + c01 * k11
        b11[j] = ap10 * a10 + ap11 * a11 + c10 * k10 + c11 * k11
    for j in range(ns):
        log_w[j] += -0.5 * (nis_s[j] + log_det[j] + 2.0 * _LOG_2PI)
    # the weighted sums: four independent chains in one pass, normalised after
    total = 0.0
    mean_u = 0.0
    second = 0.0
    nis_mean = 0.0
    for j in range(ns):
        wj = w[j]
        u = us[j]
        total += wj
        mean_u += wj * u
        second += wj * (vs[j] + u * u)
        nis_mean += wj * nis_s[j]
    mean_u /= total
    second /= total
    nis_mean /= total
    var = second - mean_u * mean_u
    return nis_mean, mean_u / math.sqrt(max(var, 1e-300))


@numba.njit(cache=True, nogil=True, fastmath={"contract"}, error_model="numpy", inline="always")
def _step_row(r, F, t_s, rows, t_new, y, mu, sigma, group, H, b, R, nis_rows, nis, score, tmp):
    """Entry ``r`` of :func:`index_step`: :func:`_step` on row ``rows[r]``."""
    row = rows[r]
    nis_row, score[r] = _step(F, t_s, row, t_new[r], y[r, 0], y[r, 1], mu, sigma, group[r],
                              H, b, R, tmp)  # fmt: skip
    if nis_rows[r]:
        nis[row] = nis_row


@numba.njit(cache=True, nogil=True, fastmath={"contract"}, error_model="numpy")
def _index_step_serial(F, t_s, rows, t_new, y, mu, sigma, group, H, b, R, wn, nis, s):
    tmp = np.empty((_SCRATCH, F.shape[1] // 7))
    for r in range(rows.shape[0]):
        _step_row(r, F, t_s, rows, t_new, y, mu, sigma, group, H, b, R, wn, nis, s, tmp)


@numba.njit(cache=True, nogil=True, fastmath={"contract"}, error_model="numpy", parallel=True)
def _index_step_parallel(F, t_s, rows, t_new, y, mu, sigma, group, H, b, R, wn, nis, s):
    k = rows.shape[0]
    for task in numba.prange((k + _ROWS_PER_TASK - 1) // _ROWS_PER_TASK):
        tmp = np.empty((_SCRATCH, F.shape[1] // 7))
        for r in range(task * _ROWS_PER_TASK, min(k, (task + 1) * _ROWS_PER_TASK)):
            _step_row(r, F, t_s, rows, t_new, y, mu, sigma, group, H, b, R, wn, nis, s, tmp)


PARALLEL_ROWS = 256  # from this many rows a step is spread over the cores
RUN_PARALLEL_ROWS = 64  # and runs of indices (index_runs: a re-run's are ~120 indices long)
_PARALLEL_LOCK = threading.Lock()  # numba's default thread pool takes one caller at a time


def index_step(F, t_s, rows, t_new, y, mu, sigma, group, H, b, R, nis_rows, nis, score, *,
               parallel: bool | None = None):  # fmt: skip
    """Apply one on-board index to each listed row, in place (see the module docstring).

    ``F`` (S, 7 Ns) C-contiguous, ``t_s`` (S,): the bank, a row of ``F`` being a
    segment's ``z`` (Ns, 2), ``P`` (Ns, 2, 2) and ``log_w`` (Ns), each row-major, one after
    the other (:func:`services.filtering.state.state_layout`); ``rows`` (k,) the rows to
    step, ``t_new`` (k,) epoch s, ``y`` (k, 2) log indices;
    ``mu`` (G, Ns, 2), ``sigma`` (G, Ns, 2, 2) and ``group`` (k,) the degradation
    parameters of each row; ``H``, ``b``, ``R`` the observation model (2 x 2);
    ``nis_rows`` (k,) bool: write row ``r``'s NIS into ``nis[rows[r]]``; ``score`` (k,)
    out: the CUSUM score of each row.

    Compiled: on all cores from ``PARALLEL_ROWS`` rows (a re-run, a backlog), else on the
    calling thread (the live step); ``parallel`` True or False chooses instead. The rows
    are independent and each is computed by the same inlined code either way, so the bits
    do not depend on which.
    """
    args = (F, t_s, rows, t_new, y, mu, sigma, group, H, b, R, nis_rows, nis, score)
    if not (len(rows) >= PARALLEL_ROWS if parallel is None else parallel):
        _index_step_serial(*args)
        return
    with _PARALLEL_LOCK:
        _index_step_parallel(*args)


# --- runs of indices, a row at a time (a re-run, a backlog) --------------------------------


@numba.njit(cache=True, nogil=True, inline="always")
def _maximum(a, b):
    """``np.maximum(a, b)`` of two floats, bit for bit (NaN from either; ``b`` if equal)."""
    return a if (a > b or a != a) else b


@numba.njit(cache=True, nogil=True, fastmath={"contract"}, error_model="numpy", inline="always")
def _run_row(
    row, src, at, F, t_s, pos, stop, kinds, times, values, obs_ids, Hs, bs, Rs, mu, sigma, group,
    started, nis, n_updates, cusum, cusum_t0, cusum_t1, cusum_law, folded, missing, tmp,
):  # fmt: skip
    """Row ``row``'s indices from ``pos[row]`` to its next other event (or ``stop[row]``):
    :func:`_update` and the CUSUM step (``_Banks._cusum_step``) of each, the samples
    loaded from ``F[src]`` into ``tmp`` at the first and stored into ``F[at]`` after the
    last; the state's fields are those of ``at`` (``src == at == row``: in place)."""
    index, drift, clip, halt = cusum_law
    k = pos[row]
    end = stop[row]
    loaded = False  # the row's samples in tmp, from its first update to the run's end
    while k < end and kinds[row, k] == index:
        if started[at]:  # an index before any start is skipped
            o = obs_ids[row, k]
            if o < 0:
                missing[row] = True
                break
            if not loaded:
                _load(F, src, tmp)
                loaded = True
            t = times[row, k]
            nis[at], score = _update(tmp, (t - t_s[at]) / DAY_S, values[row, k, 0],
                                     values[row, k, 1], mu, sigma, group[row], Hs[o], bs[o],
                                     Rs[o])  # fmt: skip
            t_s[at] = t
            g_prev = cusum[at]
            g = _maximum(0.0, g_prev - _maximum(score, -clip) - drift)
            cusum[at] = g
            if g == 0.0:
                cusum_t0[at] = t
                cusum_t1[at] = np.nan
            elif g_prev == 0.0:
                cusum_t1[at] = t
            n_updates[at] += 1
            if g >= halt:  # halt = inf: never
                k += 1
                folded[row] = k
                stop[row] = k
                break
        k += 1
    if loaded:
        _store(F, at, tmp)
    pos[row] = k


@numba.njit(cache=True, nogil=True, fastmath={"contract"}, error_model="numpy")
def _runs_serial(rows, srcs, ats, F, t_s, pos, stop, kinds, times, values, obs_ids, Hs, bs, Rs,
                 mu, sigma, group, started, nis, n_updates, cusum, c0, c1, law, folded,
                 missing):  # fmt: skip
    tmp = np.empty((_SCRATCH, F.shape[1] // 7))
    for r in range(rows.shape[0]):
        row = rows[r]
        _run_row(row, srcs[row], ats[row], F, t_s, pos, stop, kinds, times, values, obs_ids, Hs,
                 bs, Rs, mu, sigma, group, started, nis, n_updates, cusum, c0, c1, law, folded,
                 missing, tmp)  # fmt: skip


@numba.njit(cache=True, nogil=True, fastmath={"contract"}, error_model="numpy", parallel=True)
def _runs_parallel(rows, srcs, ats, F, t_s, pos, stop, kinds, times, values, obs_ids, Hs, bs,
                   Rs, mu, sigma, group, started, nis, n_updates, cusum, c0, c1, law, folded,
                   missing):  # fmt: skip
    k = rows.shape[0]
    for task in numba.prange((k + _ROWS_PER_TASK - 1) // _ROWS_PER_TASK):
        tmp = np.empty((_SCRATCH, F.shape[1] // 7))
        for r in range(task * _ROWS_PER_TASK, min(k, (task + 1) * _ROWS_PER_TASK)):
            row = rows[r]
            _run_row(row, srcs[row], ats[row], F, t_s, pos, stop, kinds, times, values, obs_ids,
                     Hs, bs, Rs, mu, sigma, group, started, nis, n_updates, cusum, c0, c1, law,
                     folded, missing, tmp)  # fmt: skip


def index_runs(rows, F, t_s, pos, stop, kinds, times, values, obs_ids, Hs, bs, Rs, mu, sigma,
               group, started, nis, n_updates, cusum, cusum_t0, cusum_t1, cusum_law, folded,
               missing, homes=None):  # fmt: skip
    """Fold each listed row's run of indices, a row at a time, in place: from ``pos[row]``
    while ``kinds[row, k]`` is an index and ``k < stop[row]``, :func:`_step` (the maths of
    :func:`index_step`) then the CUSUM step; ``pos[row]`` ends at the first other event.
    ``cusum_law``: ``(index kind code, drift, clip, halt)`` (the tracker's constants).

    ``kinds``, ``times`` (S, depth), ``values`` (S, depth, 2), ``obs_ids`` (S, depth) the
    rows' logs (an index's model in ``Hs``, ``bs``, ``Rs``); ``group`` (S,) each row's
    parameter set in ``mu``, ``sigma``; ``nis`` gets each update's NIS (the last one
    stays). A row whose CUSUM reaches ``halt`` stops after that index (``folded[row]``,
    ``stop[row]``: how many of its events that was); ``missing[row]`` is set, and the row
    stopped, at an index of a started row without a model. A row's updates run one after
    the other with its state in the cache, and no interpreter between the steps. The same
    bits as :func:`index_step` and ``_cusum_step``.

    ``homes``: ``(srcs, ats)`` (S,) each, the rows of ``F`` and of the state's fields
    (``t_s`` to ``cusum_t1``) that row ``i`` of the logs folds from and into: its samples
    read from ``F[srcs[i]]``, stored into ``F[ats[i]]`` (the fields already at ``ats[i]``).
    A resting segment's state is folded so from its row of the bank into a free one, with
    no copy of it first. None: each row in place.
    """
    if homes is None:
        homes = (np.arange(len(pos)),) * 2
    args = (rows, *homes, F, t_s, pos, stop, kinds, times, values, obs_ids, Hs, bs, Rs, mu,
            sigma, group, started, nis, n_updates, cusum, cusum_t0, cusum_t1, cusum_law, folded,
            missing)  # fmt: skip
    if len(rows) < RUN_PARALLEL_ROWS:
        _runs_serial(*args)
        return
    with _PARALLEL_LOCK:
        _runs_parallel(*args)


# --- the mixture quantile (services.filtering.mixture._mixture_quantile) -----------------

_SQRT_2PI = math.sqrt(2.0 * math.pi)


@numba.njit(cache=True, nogil=True, fastmath={"contract"}, inline="always", error_model="numpy")
def _quantile_row(i, q, z_q, m, s, w, weighted, tail, tol, max_iter, out):
    """One row of :func:`mixture_quantile` (inlined into both compiled loops)."""
    ns = m.shape[1]
    # the moment-matched Gaussian's quantile: the first guess
    mean = 0.0
    for j in range(ns):
        mean += w[i, j] * m[i, j] if weighted else m[i, j]
    if not weighted:
        mean /= ns
    second = 0.0
    for j in range(ns):
        d = m[i, j] - mean
        v = s[i, j] * s[i, j] + d * d
        second += w[i, j] * v if weighted else v
    if not weighted:
        second /= ns
    x = mean + math.sqrt(second) * z_q[i]
    lo, hi = math.inf, -math.inf
    points = 0
    for j in range(ns):
        lo = min(lo, m[i, j] - tail * s[i, j])
        hi = max(hi, m[i, j] + tail * s[i, j])
        if s[i, j] == 0.0:
            points += 1
    if points == ns:  # point masses only: the (weighted) empirical quantile
        order = np.argsort(m[i])
        if weighted:
            rank, cum = 0, 0.0
            for k in range(ns):
                cum += w[i, order[k]]
                if cum >= q[i] - 1e-12:
                    rank = k
                    break
        else:
            rank = max(int(math.ceil(q[i] * ns - 1e-12)) - 1, 0)
        out[i] = m[i, order[rank]]
        return
    cs, ps, dps = np.empty(ns), np.empty(ns), np.empty(ns)
    for _ in range(max_iter):
        for j in range(ns):  # no calls, no sums: vectorised
            sj = s[i, j]
            u = (x - m[i, j]) / sj
            p = exp_nonpositive(-0.5 * u * u) / (_SQRT_2PI * sj)
            point = sj == 0.0  # a point mass: an exact step
            cs[j] = (1.0 if x >= m[i, j] else 0.0) if point else ndtr(u)
            ps[j] = 0.0 if point else p
            dps[j] = 0.0 if point else -p * u / sj  # d pdf / dx
        cdf, pdf, slope = 0.0, 0.0, 0.0
        for j in range(ns):
            if weighted:
                cdf += w[i, j] * cs[j]
                pdf += w[i, j] * ps[j]
                slope += w[i, j] * dps[j]
            else:
                cdf += cs[j]
                pdf += ps[j]
                slope += dps[j]
        if not weighted:
            cdf /= ns
            pdf /= ns
            slope /= ns
        if cdf < q[i]:
            lo = x
        else:
            hi = x
        step = 0.5 * (lo + hi)
        f = cdf - q[i]
        denominator = 2.0 * pdf * pdf - f * slope
        if pdf > 0.0 and denominator > 0.0:
            halley = x - 2.0 * f * pdf / denominator
            if lo <= halley <= hi:  # closed: a converged step lands on the end just moved
                step = halley
        done = abs(step - x) < tol or hi - lo < tol
        x = step
        if done:
            break
    out[i] = x


@numba.njit(cache=True, nogil=True, fastmath={"contract"}, error_model="numpy")
def _quantile_serial(q, z_q, m, s, w, weighted, tail, tol, max_iter, out):
    for i in range(m.shape[0]):
        _quantile_row(i, q, z_q, m, s, w, weighted, tail, tol, max_iter, out)


@numba.njit(cache=True, nogil=True, fastmath={"contract"}, error_model="numpy", parallel=True)
def _quantile_parallel(q, z_q, m, s, w, weighted, tail, tol, max_iter, out):
    for i in numba.prange(m.shape[0]):
        _quantile_row(i, q, z_q, m, s, w, weighted, tail, tol, max_iter, out)


PARALLEL_QUANTILES = 512  # from this many mixtures the quantiles are spread over the cores


def mixture_quantile(q, z_q, m, s, w, tail: float, tol: float, max_iter: int) -> np.ndarray:
    r"""Quantile :math:`\inf\{x : F(x) \ge q_i\}` of each mixture
    :math:`F(x) = \sum_j w_j \Phi((x - m_{ij}) / s_{ij})`, compiled.

    ``q``, ``z_q`` (rows,): the levels and :math:`\Phi^{-1}(q)`; ``m``, ``s`` (rows, Ns)
    contiguous; ``w`` (rows, Ns) weights summing to 1, or None for :math:`1 / N_s`.
    Safeguarded Halley iteration (cubic convergence; :math:`f = F - q`,
    :math:`x \leftarrow x - 2 f f' / (2 f'^2 - f f'')`) from the moment-matched Gaussian's
    quantile inside the bracket
    :math:`[\min_j (m_j - \text{tail}\, s_j), \max_j (m_j + \text{tail}\, s_j)]`, kept
    with :math:`F(lo) < q \le F(hi)` (also right at a point mass's jump), bisecting
    whenever the step leaves it, until the step or the bracket is below ``tol``. A
    mixture of point masses only is the (weighted) empirical quantile. Each row's number
    depends on that row only, in a fixed order, serial or spread over the cores.
    """
    out = np.empty(m.shape[0])
    weighted = w is not None
    weights = w if weighted else np.empty((0, 0))
    args = (q, z_q, m, s, weights, weighted, tail, tol, max_iter, out)
    if m.shape[0] < PARALLEL_QUANTILES:
        _quantile_serial(*args)
    else:
        with _PARALLEL_LOCK:
            _quantile_parallel(*args)
    return out


@numba.njit(cache=True, nogil=True, fastmath={"contract"}, error_model="numpy")
def _survival(x, rows, m, s, w, weighted, out):
    ns = m.shape[1]
    cs = np.empty(ns)
    for k in range(x.shape[0]):
        i = rows[k]
        for j in range(ns):  # vectorised; a point mass (sj = 0) is an exact step
            sj = s[i, j]
            c = ndtr((m[i, j] - x[k]) / sj)
            cs[j] = c if sj != 0.0 else (1.0 if x[k] < m[i, j] else 0.0)
        total = 0.0
        for j in range(ns):
            total += w[i, j] * cs[j] if weighted else cs[j]
        if not weighted:
            total /= ns
        out[k] = min(max(total, 0.0), 1.0)  # weights sum to 1 only up to round-off


def mixture_survival(x, rows, m, s, w) -> np.ndarray:
    r"""Survival :math:`1 - F_i(x_k) = \sum_j w_j \Phi((m_{ij} - x_k) / s_{ij})` of mixture
    ``i = rows[k]`` at each ``x_k``, compiled; ``m``, ``s``, ``w`` as in
    :func:`mixture_quantile` (a component with :math:`s = 0` is a point mass: 1 when
    :math:`x < m`). Kept in [0, 1]."""
    out = np.empty(x.shape[0])
    weighted = w is not None
    _survival(x, rows, m, s, w if weighted else np.empty((0, 0)), weighted, out)
    return out
