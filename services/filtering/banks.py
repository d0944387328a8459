"""In-memory banks of segment states: the stacked rows a fold steps together
(:class:`Banks`), the reused buffer a fold runs in (:class:`Scratch`), the bank that holds
the resting segments' states (:class:`RestingBank`, a state there being a :class:`BankRow`),
and each row's degradation parameters (:class:`RowParams`)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from types import SimpleNamespace
from typing import NamedTuple

import numpy as np

from schemas import DAY_S
from services.filtering.degradation import DegradationParams, transition_unchecked
from services.filtering.kalman import (
    BLOCK_FILTERS,
    ObservationModel,
    contiguous_rows,
    update_unchecked,
)
from services.filtering.kernel import index_step
from services.filtering.state import Filtered, stack_rows, state_layout, state_views

# Detected maintenance (see :func:`services.filtering.segment.detect`): a one-sided CUSUM of
# how far below their prediction the indices read, in predictive standard deviations.
CUSUM_DRIFT = 1.0  # kappa: a reading 1 sd low adds nothing
CUSUM_CLIP = 6.0  # one index adds at most 6 - kappa = 5: a detection needs two at least
CUSUM_THRESHOLD = 8.0  # h: the CUSUM at which a tamping is looked for
RESTING_GROWTH = 1024  # rows a bank of resting states grows by at least (11 MB at Ns = 200)


class Scratch:
    """A buffer that a fold copying its states out (``copy=True``) reuses for its stacked
    states, batch after batch: a fresh one would be new memory each time, page-faulted
    afresh."""

    def __init__(self) -> None:
        self._buffer = np.empty(0)

    def rows(self, size: int, width: int) -> np.ndarray:
        """A (size, width) float64 array (contents undefined), valid until the next call."""
        if self._buffer.size < size * width:
            self._buffer = np.empty(size * width)
        return self._buffer[: size * width].reshape(size, width)


class Banks:
    r"""The filter banks of ``S`` segments (one sample count ``Ns``) as stacked arrays.

    The fold of many segments at once: :meth:`restart`, :meth:`tamping` and :meth:`index`
    apply one event to each of the listed rows in one vectorised call, in blocks of about
    ``BLOCK_FILTERS`` filters. Every operation is elementwise over segments and samples, or
    a sum over the samples of one segment, so a segment's numbers do not depend on the
    other rows of the call: a batch of one is the live, one-event step, and a re-run of
    thousands of segments gives the same bits (``update_unchecked`` is written so).

    ``F`` (S, W) holds each row's ``z``, ``P`` and ``log_w`` in one buffer
    (:func:`state_layout`); ``z``, ``P``, ``log_w`` are views of it. With ``scratch`` it is
    the scratch's buffer: take the states out with ``copy=True`` before its next use.
    """

    def __init__(
        self, starts: Sequence[Filtered | None], ns: int, n: int, scratch: Scratch | None = None
    ) -> None:
        size = len(starts)
        rows = [row for row, state in enumerate(starts) if state is not None]
        have = [starts[row] for row in rows]
        width = state_layout(ns, n)[2]
        out = None if scratch is None else scratch.rows(size, width)
        if have and len(have) == size:  # every row started (a backlog): one copy, no zeros
            self.F = stack_rows([state.buffer() for state in have], out)
        elif out is None:
            self.F = np.zeros((size, width))
        else:
            self.F = out
            self.F[:] = 0.0
        if self.F.shape != (size, width):
            raise ValueError(f"states of shape {self.F.shape[1:]}, not ({width},) (Ns={ns})")
        self.z, self.P, self.log_w = state_views(self.F, ns, n)
        self.ns, self.n = ns, n
        self.t_s = np.zeros(size)
        self.last_trc_t = np.full(size, np.nan)  # NaN: None
        self.n_updates = np.zeros(size, dtype=np.int64)
        self.nis = np.full(size, np.nan)  # NaN: None
        self.started = np.zeros(size, dtype=bool)
        self.cusum = np.zeros(size)
        self.cusum_t0 = np.full(size, np.nan)
        self.cusum_t1 = np.full(size, np.nan)
        self.trc_absent = np.zeros(size, dtype=np.int64)
        if have:  # one copy per field for all started rows (a backlog starts ~1,000)
            nan = float("nan")
            if len(have) < size:
                self.F[rows] = stack_rows([state.buffer() for state in have])
            self.cusum[rows] = [state.cusum for state in have]
            self.cusum_t0[rows] = [state.cusum_t0 for state in have]
            self.cusum_t1[rows] = [state.cusum_t1 for state in have]
            self.trc_absent[rows] = [state.trc_absent for state in have]
            self.t_s[rows] = [state.t_s for state in have]
            self.n_updates[rows] = [state.n_updates for state in have]
            self.last_trc_t[rows] = [
                nan if state.last_trc_t is None else state.last_trc_t for state in have
            ]
            self.nis[rows] = [nan if state.nis is None else state.nis for state in have]
            self.started[rows] = True
        self._block = max(1, BLOCK_FILTERS // max(ns, 1))

    SCALARS = (
        "t_s", "last_trc_t", "n_updates", "nis", "started", "cusum", "cusum_t0", "cusum_t1",
        "trc_absent",
    )  # fmt: skip

    def grow(self, size: int) -> None:
        """``size`` rows, the new ones zeros (unstarted); the arrays are reallocated in
        place (``ndarray.resize``: a large one is remapped, not copied, so a bank of 1 GB
        does not need 2 GB to grow). Only for a stack no view of which is held (the
        bank's: its states go out as copies)."""
        self.F.resize((size, self.F.shape[1]), refcheck=False)
        self.z, self.P, self.log_w = state_views(self.F, self.ns, self.n)
        for name in Banks.SCALARS:
            getattr(self, name).resize(size, refcheck=False)

    def put(self, row: int, state: Filtered) -> None:
        """Row ``row`` becomes ``state`` (a copy)."""
        nan = float("nan")
        self.F[row] = state.buffer()
        self.t_s[row] = state.t_s
        self.last_trc_t[row] = nan if state.last_trc_t is None else state.last_trc_t
        self.n_updates[row] = state.n_updates
        self.nis[row] = nan if state.nis is None else state.nis
        self.started[row] = True
        self.cusum[row] = state.cusum
        self.cusum_t0[row] = state.cusum_t0
        self.cusum_t1[row] = state.cusum_t1
        self.trc_absent[row] = state.trc_absent

    def states(self, rows: Sequence[int], *, copy: bool = False) -> list[Filtered | None]:
        """Each of ``rows`` as a :class:`Filtered`, None if unstarted: views of the stacked
        arrays, or copies (``copy``: a state kept alone does not hold the whole stack's
        memory); the scalars read in one pass."""
        out: list[Filtered | None] = []
        fields = zip(
            self.started[rows].tolist(),
            self.t_s[rows].tolist(),
            self.last_trc_t[rows].tolist(),
            self.n_updates[rows].tolist(),
            self.nis[rows].tolist(),
            self.cusum[rows].tolist(),
            self.cusum_t0[rows].tolist(),
            self.cusum_t1[rows].tolist(),
            self.trc_absent[rows].tolist(),
            strict=True,
        )
        ns, n = self.ns, self.n
        at_p, at_w, _ = state_layout(ns, n)  # F's rows are of its width (__init__)
        make, F, isnan = Filtered._on_buffer, self.F, math.isnan
        for row, (started, t_s, last_trc_t, n_updates, nis, cusum, t0, t1, absent) in zip(
            rows, fields, strict=True
        ):
            if not started:
                out.append(None)
                continue
            flat = F[row].copy() if copy else F[row]
            last_trc_t = None if isnan(last_trc_t) else last_trc_t
            nis = None if isnan(nis) else nis
            scalars = (t_s, last_trc_t, n_updates, nis, cusum, t0, t1, absent)
            out.append(make(flat, ns, n, at_p, at_w, *scalars))
        return out

    def _blocks(self, rows: np.ndarray):
        """``(part, rows)`` in blocks; ``part`` indexes ``rows``; consecutive rows as a slice."""
        for first in range(0, len(rows), self._block):
            part = slice(first, first + self._block)
            yield part, contiguous_rows(rows[part])

    def restart(self, rows: np.ndarray, t_s: np.ndarray, z: np.ndarray, params) -> None:
        """TRC record: every sample at ``z`` (k, n), ``P = 0``, equal weights, no NIS.

        A record of some indicators only (``z`` NaN at the others) is :meth:`restart_partial`."""
        partial = np.isnan(z).any(axis=1)
        if partial.any():
            self.restart_partial(rows[partial], t_s[partial], z[partial], params)
            rows, t_s, z = rows[~partial], t_s[~partial], z[~partial]
        self.z[rows] = z[:, None, :]
        self.P[rows] = 0.0
        self.log_w[rows] = 0.0
        self.t_s[rows] = self.last_trc_t[rows] = t_s
        self.n_updates[rows] = 0
        self.nis[rows] = np.nan
        self.started[rows] = True
        self.trc_absent[rows] = 0
        self._cusum_reset(rows, t_s)

    def restart_partial(self, rows: np.ndarray, t_s: np.ndarray, z: np.ndarray, params) -> None:
        r"""TRC record of the indicators ``o`` where ``z`` (k, n) is finite, the others
        not measured: predict to ``t_s`` (Eq. 7-8), then observe ``z_o`` exactly (R = 0),
        per sample the conditional Gaussian

        .. math::

            \hat z \leftarrow \hat z + P_{:o} P_{oo}^{+} (z_{TRC,o} - \hat z_o), \qquad
            P \leftarrow P - P_{:o} P_{oo}^{+} P_{o:}

        (``P_oo`` pseudo-inverted: a row measured exactly at this same time has no variance
        and moves nothing), with ``z_o`` set to the record and ``P``'s rows and columns
        ``o`` to 0 exactly. A row without state is left so: a record of some indicators
        gives the others no value to start from. The weights are kept (the indicators not
        measured still carry the on-board data since the last full restart), and the
        record is one more step of the CUSUM, scored like an index with no measurement
        error (:func:`low_score` of ``z_o``): a record far below its prediction is the
        sign of a tamping missed before it, which the indices of the indicators it did not
        measure then confirm. The update count and NIS restart, as after any TRC record.
        """
        started = self.started[rows]
        rows, t_s, z = rows[started], t_s[started], z[started]
        observed = ~np.isnan(z)
        for mask in np.unique(observed, axis=0):
            pick = (observed == mask).all(axis=1)
            sel, t_sel = rows[pick], t_s[pick]
            o = np.flatnonzero(mask)
            dt = (t_sel - self.t_s[sel]) / DAY_S
            zp, P = transition_unchecked(self.z[sel], self.P[sel], params(sel), dt)
            log_w = self.log_w[sel]
            w = np.exp(log_w - log_w.max(-1, keepdims=True))
            w /= w.sum(-1, keepdims=True)
            exact = SimpleNamespace(H=np.eye(self.n)[o], b=np.zeros(len(o)), R=np.zeros(1))
            self._cusum_step(sel, t_sel, low_score(zp, P, z[pick][:, o], exact, w))
            P_oo = P[..., o[:, None], o]
            gain = P[..., :, o] @ np.linalg.pinv(P_oo, hermitian=True)
            zp = zp + (gain @ (z[pick][:, None, o, None] - zp[..., o, None]))[..., 0]
            P = P - gain @ P[..., o, :]
            P = 0.5 * (P + np.swapaxes(P, -1, -2))
            zp[..., o] = z[pick][:, None, o]
            P[..., o, :] = 0.0
            P[..., :, o] = 0.0
            self.z[sel], self.P[sel] = zp, P
            self.t_s[sel] = self.last_trc_t[sel] = t_sel
            self.n_updates[sel] = 0
            self.nis[sel] = np.nan
            self.trc_absent[sel] = int(sum(1 << i for i in np.flatnonzero(~mask)))

    def _cusum_step(self, rows: np.ndarray, t_s: np.ndarray, score: np.ndarray) -> None:
        r"""One index of the one-sided CUSUM of low readings (see :func:`detect`):

        .. math:: g_k = \max(0,\ g_{k-1} - \max(s_k, -c) - \kappa)

        with :math:`c` = ``CUSUM_CLIP`` (one wild index cannot make a detection alone) and
        :math:`\kappa` = ``CUSUM_DRIFT``; ``cusum_t0`` is the last index at which g was 0 and
        ``cusum_t1`` the first index after it.
        """
        g_prev = self.cusum[rows]
        g = np.maximum(0.0, g_prev - np.maximum(score, -CUSUM_CLIP) - CUSUM_DRIFT)
        zero = g == 0.0
        self.cusum[rows] = g
        self.cusum_t0[rows] = np.where(zero, t_s, self.cusum_t0[rows])
        self.cusum_t1[rows] = np.where(
            zero, np.nan, np.where(g_prev == 0.0, t_s, self.cusum_t1[rows])
        )

    def _cusum_reset(self, rows: np.ndarray, t_s: np.ndarray) -> None:
        """A start (TRC record or tamping) at ``t_s``: nothing has read low since."""
        self.cusum[rows] = 0.0
        self.cusum_t0[rows] = t_s
        self.cusum_t1[rows] = np.nan

    def tamping(self, rows: np.ndarray, t_s: np.ndarray, params) -> None:
        r"""Tamping at ``t_s``: the transition with tamping age 0 (Eq. 2), a reset to

        .. math:: \hat z = z^+ + \mu \cdot 0, \qquad P = \Sigma_{z^+} + \Sigma \cdot 0.

        A row without state starts here (``z = P = 0`` first, never used) with equal
        weights; a started row keeps its weights, update count and NIS.
        """
        fresh = rows[~self.started[rows]]
        if len(fresh):
            self.z[fresh], self.P[fresh], self.log_w[fresh] = 0.0, 0.0, 0.0
            self.t_s[fresh] = t_s[~self.started[rows]]
            self.last_trc_t[fresh], self.n_updates[fresh], self.nis[fresh] = np.nan, 0, np.nan
            self.started[fresh] = True
        for part, sel in self._blocks(rows):
            dt = (t_s[part] - self.t_s[sel]) / DAY_S
            self.z[sel], self.P[sel] = transition_unchecked(
                self.z[sel], self.P[sel], params(sel), dt, 0.0
            )
        self.t_s[rows] = t_s
        self._cusum_reset(rows, t_s)

    def index(self, rows, t_s, y, params, obs: ObservationModel, last=None) -> None:
        r"""On-board index ``y`` (k, m) at ``t_s`` on started rows (paper Eq. 7-12).

        Predict over :math:`\Delta t` days, update in Joseph form, and add each sample's
        log-likelihood to its log weight; the NIS is the mean over samples weighted by
        the weights before the update,

        .. math::

            \overline{\nu} = \sum_j w_j \nu_j, \quad
            w_j \propto \exp(\log w_j), \qquad
            \log w_j \mathrel{+}= \log \mathcal N(\nu_j; 0, S_j).

        ``last`` (k,) bool: the rows whose last update this is; only their NIS is computed
        (a later update would overwrite it). None: every row.

        With a 2 x 2 observation model (Top6 and Align10 read by two indices, the system's
        case) the whole step is one compiled pass (:func:`kernel.index_step`); the numpy
        form below serves any other shape. The fold of the system's case goes through
        :func:`kernel.index_runs` instead (:func:`_fold_runs`, the same inlined step), so
        this per-step compiled path is the runs' per-event reference (the kernel tests,
        ``bench.kernel``) rather than the service's.
        """
        if obs.H.shape == (2, 2) and self.z.shape[-1] == 2:
            self.index_compiled(rows, t_s, y, params, obs, last)
        else:
            self.index_numpy(rows, t_s, y, params, obs, last)

    def index_compiled(self, rows, t_s, y, params, obs: ObservationModel, last=None) -> None:
        """:meth:`index` for n = m = 2 through :func:`kernel.index_step` (the same maths)."""
        score = np.empty(len(rows))
        index_step(
            self.F,
            self.t_s,
            np.ascontiguousarray(rows, dtype=np.int64),
            np.ascontiguousarray(t_s, dtype=np.float64),
            np.ascontiguousarray(y, dtype=np.float64),
            params.stack.mu,
            params.stack.sigma,
            params.row_group[rows],
            obs.H,
            obs.b,
            obs.R,
            np.ones(len(rows), dtype=bool) if last is None else np.asarray(last, dtype=bool),
            self.nis,
            score,
        )
        self._cusum_step(rows, t_s, score)
        self.n_updates[rows] += 1

    def index_numpy(self, rows, t_s, y, params, obs: ObservationModel, last=None) -> None:
        """:meth:`index` for any n, m with numpy (the reference of the compiled step)."""
        for part, sel in self._blocks(rows):
            dt = (t_s[part] - self.t_s[sel]) / DAY_S
            z, P = transition_unchecked(self.z[sel], self.P[sel], params(sel), dt)
            # the weights before the update: weights_from_log without its check (log_w is
            # the fold's own), for the CUSUM's score and the NIS
            log_w = self.log_w[sel]
            w = np.exp(log_w - log_w.max(-1, keepdims=True))
            w /= w.sum(-1, keepdims=True)
            self._cusum_step(rows[part], t_s[part], low_score(z, P, y[part], obs, w))
            z, P, nis, loglik = update_unchecked(z, P, y[part], obs.H, obs.b, obs.R, loglik=True)
            want = slice(None) if last is None else last[part]
            at = rows[part][want]
            if len(at):
                # a sum over the last axis, not ``w @ nis``: BLAS dot's order depends on the call
                self.nis[at] = (w[want] * nis[want]).sum(-1)
            self.z[sel], self.P[sel] = z, P
            self.log_w[sel] += loglik
            self.n_updates[sel] += 1
        self.t_s[rows] = t_s


def index_partial(banks: Banks, rows, t_s, y, params, obs: ObservationModel) -> None:
    r"""On-board index ``y`` (k, m) of some indices only (NaN at the others) on started
    rows: :meth:`Banks.index_numpy` with the observed rows ``o`` of the model,

    .. math:: y_o = H_{o:} z + b_o + e_o, \qquad e_o \sim N(0, R_{oo}),

    the marginal of Eq. 3-4 (a vertical-only unit reads Top6 through its row of H). The
    log weight adds the likelihood of ``y_o``; the NIS is of ``y_o``; the CUSUM scores the
    sum of the observed indices against its prediction."""
    observed = ~np.isnan(y)
    for mask in np.unique(observed, axis=0):
        pick = (observed == mask).all(axis=1)
        o = np.flatnonzero(mask)
        part = ObservationModel(obs.H[o], obs.b[o], obs.R[np.ix_(o, o)])
        sub = np.ascontiguousarray(rows[pick])
        banks.index_numpy(sub, t_s[pick], np.ascontiguousarray(y[pick][:, o]), params, part)


def low_score(z, P, y, obs: ObservationModel, w) -> np.ndarray:
    r"""How far below its prediction an index reads, in predictive standard deviations.

    For the sum of the indicators :math:`u = \mathbf 1^T y` the mixture predictive has, per
    sample :math:`j`, mean :math:`\mathbf 1^T (H \hat z_j + b)` and variance
    :math:`v_j = h^T P_j h + \mathbf 1^T R \mathbf 1` with :math:`h = H^T \mathbf 1`; with
    the weights :math:`w_j` and :math:`\nu_j = u - \mathbf 1^T (H \hat z_j + b)`,

    .. math::

        s = \frac{\bar\nu}{\sqrt{\sum_j w_j (v_j + \nu_j^2) - \bar\nu^2}}, \qquad
        \bar\nu = \sum_j w_j \nu_j .

    A tamping lowers every indicator at once, so its indices give :math:`s \ll 0`.
    ``z`` (k, Ns, n), ``P`` (k, Ns, n, n) predicted; ``y`` (k, m); ``w`` (k, Ns), normalised.
    """
    h = obs.H.sum(axis=0)  # H^T 1
    if len(h) == 2:  # the tracker's state: elementwise, without stacked matmuls' overhead
        h0, h1 = h.tolist()
        zh = z[..., 0] * h0 + z[..., 1] * h1
        Ph = (P[..., 0, 0] * h0 + P[..., 0, 1] * h1) * h0
        Ph += (P[..., 1, 0] * h0 + P[..., 1, 1] * h1) * h1
    else:
        zh, Ph = z @ h, (P @ h) @ h
    nu = y.sum(-1)[:, None] - (zh + obs.b.sum())
    v = Ph + obs.R.sum()
    mean = (w * nu).sum(-1)
    var = (w * (v + nu * nu)).sum(-1) - mean * mean
    return mean / np.sqrt(np.maximum(var, 1e-300))


class BankRow(NamedTuple):
    """A state held as row ``row`` of a bank of resting states (:class:`RestingBank`)
    instead of as a :class:`Filtered` of its own: a resting segment's, or a backlog fold's
    result in a free row until the swap makes it the segment's (:meth:`Histories.rest`).
    Only the fold and :class:`Histories` hold one; :meth:`state` reads it out (a copy)."""

    banks: Banks
    row: int

    def state(self) -> Filtered:
        state = self.banks.states([self.row], copy=True)[0]
        assert state is not None  # only started states are held as rows
        return state

    @property
    def cusum(self) -> float:
        return float(self.banks.cusum[self.row])


def as_filtered(state: Filtered | BankRow | None) -> Filtered | None:
    """``state`` as a :class:`Filtered` (read out of its row if it is a :class:`BankRow`)."""
    return state.state() if isinstance(state, BankRow) else state


class RestingBank:
    """The states of the resting segments with one ``(Ns, n)``: rows of one
    :class:`Banks`, grown by half (at least ``RESTING_GROWTH`` rows) when every row is
    taken, a freed row taken first.

    A backlog folds a resting segment's indices from its row into a free one
    (:func:`fold_many_counted` with ``into``), which becomes the segment's at the swap while its
    old row is freed (:meth:`Histories.rest`, :meth:`Histories.settle`): no state
    object per event, and no copy of a state in or out."""

    def __init__(self, ns: int, n: int) -> None:
        self.banks = Banks([], ns, n)
        self.free: list[int] = []

    def take(self, count: int) -> list[int]:
        """``count`` free rows (taken)."""
        if len(self.free) < count:
            size = len(self.banks.t_s)
            grown = size + max(count - len(self.free), size // 2, RESTING_GROWTH)
            self.banks.grow(grown)
            self.free.extend(range(grown - 1, size - 1, -1))
        taken = self.free[-count:] if count else []
        del self.free[len(self.free) - count :]
        return taken


class RowParams:
    """The degradation parameters of each row of a fold: ``(rows) -> DegradationParams``.

    ``mu`` (G, Ns, n), ``sigma`` (G, Ns, n, n) stack the distinct parameter sets (one when
    every row shares it) and ``row_group`` (S,) says which one each row uses.
    """

    def __init__(self, params: Sequence[DegradationParams]) -> None:
        first = params[0]
        self.shared = first if all(p is first for p in params) else None
        unique: dict[int, int] = {}
        for p in params:
            unique.setdefault(id(p), len(unique))
        groups = {id(p): p for p in params}
        stack = DegradationParams.__new__(DegradationParams)
        for name in ("mu", "sigma", "z_plus", "sigma_z_plus"):
            object.__setattr__(stack, name, np.stack([getattr(groups[k], name) for k in unique]))
        self.stack = stack
        self.row_group = np.array([unique[id(p)] for p in params], dtype=np.int64)

    def __call__(self, rows) -> DegradationParams:
        return self.shared if self.shared is not None else self.stack.take(self.row_group[rows])
