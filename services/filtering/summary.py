"""SegmentState summaries of filter states: the mixture's mean, credible intervals,
exceedance probabilities and forecasts (paper Eq. 13-14), many segments in one call."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from schemas import INDICATORS, NDArray, SegmentState
from schemas.wire import unchecked_copy
from services.filtering.degradation import DegradationParams, transition_unchecked
from services.filtering.histories import SegmentHistory
from services.filtering.mixture import summarize_unchecked, weights_from_log
from services.filtering.state import Filtered, stack_rows


def state_weights(state: Filtered) -> np.ndarray:
    """Normalised mixture weights (Ns,) of a state (``mixture.weights_from_log``)."""
    return weights_from_log(state.log_w)


def trc_indicators(state: Filtered) -> list[str]:
    """The indicators the state's last TRC record measured; empty before any."""
    if state.last_trc_t is None:
        return []
    return [name for i, name in enumerate(INDICATORS) if not state.trc_absent >> i & 1]


def _stacked(params: Sequence[DegradationParams]) -> DegradationParams:
    """Per-row parameters ``(S, 1, Ns, ...)`` (a horizon axis to broadcast), or the shared one."""
    first = params[0]
    if all(p is first for p in params):
        return first
    rows = DegradationParams.__new__(DegradationParams)
    for name in ("mu", "sigma", "z_plus", "sigma_z_plus"):
        stack = np.stack([getattr(p, name) for p in params])[:, None]
        object.__setattr__(rows, name, stack)
    return rows


def summarize_states(
    hists: Sequence[SegmentHistory],
    params: Sequence[DegradationParams],
    limits_mm: Sequence[np.ndarray],
    limit_levels: list[str],
    horizons_days: np.ndarray,
    *,
    calibration_version: int,
    posterior_versions: Sequence[int],
) -> list[SegmentState]:
    r"""Mixture summaries, exceedances and forecasts of many filter banks (Eq. 13-14).

    Every history must have a state, with the same ``Ns``. Each summary is the mixture of
    its ``Ns`` filters with the weights :func:`state_weights` (the likelihood of the
    segment's on-board data since its TRC restart), now and at each horizon :math:`h`
    without data in between (Eq. 2):

    .. math::

        \hat z^j(h) = \hat z^j + \mu_j h, \qquad P^j(h) = P^j + \Sigma_j h.

    All segments and horizons go through one :func:`mixture.summarize_unchecked` call
    (row 0 of the horizon axis is now), whose quantile search is most of the cost; a
    segment's numbers do not depend on the others in the call, so a batch gives the bits
    of :func:`summarize_state`.
    """
    state_list = [hist.state for hist in hists]
    z = stack_rows([state.z for state in state_list])[:, None]  # (S, 1, Ns, n)
    P = stack_rows([state.P for state in state_list])[:, None]
    log_w = stack_rows([state.log_w for state in state_list])
    w = weights_from_log(log_w)[:, None]
    rel_log_w = _relative_log_weights(log_w)
    h = np.concatenate(([0.0], horizons_days))
    z_all, P_all = transition_unchecked(z, P, _stacked(params), h)  # (S, 1 + h, Ns, n)
    limits = np.stack(limits_mm, axis=1)[:, :, None, :]  # (L, S, 1, n)
    both = summarize_unchecked(z_all, P_all, limits, weights=w)
    p_exceed = both.p_exceed  # (L, S, 1 + h, n)
    # Every number of the batch is checked here at once as SegmentState checks its arrays
    # (finite, probabilities in [0, 1]); then the first state is built checked and the
    # others as copies of it with their own arrays (same dtypes and shapes) and scalars,
    # whose checks run, rather than each state's 11 arrays checked one by one. A batch
    # that fails is built state by state, which raises the reason.
    numbers = (both.mean, both.cov, both.ci_low_mm, both.ci_high_mm, both.width, *limits_mm)
    checked = all(np.isfinite(a).all() for a in numbers) and bool(
        ((p_exceed >= 0) & (p_exceed <= 1)).all()
    )
    out: list[SegmentState] = []
    for row, (hist, state) in enumerate(zip(hists, state_list, strict=True)):
        arrays = {
            "mean": both.mean[row, 0],
            "cov": both.cov[row, 0],
            "ci_low_mm": both.ci_low_mm[row, 0],
            "ci_high_mm": both.ci_high_mm[row, 0],
            "limits_mm": limits_mm[row],
            "p_exceed": p_exceed[:, row, 0],
            "forecast_mean": both.mean[row, 1:],
            "forecast_ci_low_mm": both.ci_low_mm[row, 1:],
            "forecast_ci_high_mm": both.ci_high_mm[row, 1:],
            "forecast_p_exceed": np.swapaxes(p_exceed[:, row, 1:], 0, 1),
        }
        scalars = {
            "line": hist.line,
            "segment": hist.segment,
            "t": state.t_s,
            "width": float(both.width[row, 0]),
            "last_trc_t": state.last_trc_t,
            "last_trc_indicators": trc_indicators(state),
            "n_updates": state.n_updates,
            "nis": state.nis,
            "posterior_version": posterior_versions[row],
            "posterior_group": hist.group,
            "log_weights": rel_log_w[row],
        }
        if out and checked:
            first = out[0]
            copies = {
                name: unchecked_copy(getattr(first, name), data=_f8_bytes(a))
                for name, a in arrays.items()
            }
            summary = unchecked_copy(first, **scalars, **copies)
            summary.check_scalars()
        else:
            summary = SegmentState(
                indicators=list(INDICATORS),
                limit_levels=list(limit_levels),
                horizons_days=NDArray.of(horizons_days),
                calibration_version=calibration_version,
                **scalars,
                **{name: NDArray.of(a) for name, a in arrays.items()},
            )
        out.append(summary)
    return out


def _relative_log_weights(log_w: np.ndarray) -> list[NDArray | None]:
    """Each row's log weights (S, Ns) relative to its largest, as SegmentState carries them
    (None for a row whose weights are equal: no on-board update since its TRC restart)."""
    rel = np.maximum(log_w - log_w.max(axis=1, keepdims=True), np.finfo(np.float32).min)
    equal = (log_w == log_w[:, :1]).all(axis=1)
    return [None if same else NDArray.of(r, "f4") for r, same in zip(rel, equal, strict=True)]


def _f8_bytes(a: np.ndarray) -> bytes:
    """The bytes :meth:`NDArray.of` holds for ``a``."""
    return np.ascontiguousarray(a, dtype=np.float64).tobytes()


def summarize_state(
    line: str,
    segment: str,
    state: Filtered,
    params: DegradationParams,
    limits_mm: np.ndarray,
    limit_levels: list[str],
    horizons_days: np.ndarray,
    **versions: Any,
) -> SegmentState:
    """:func:`summarize_states` of one filter bank (paper Eq. 13-14)."""
    hist = SegmentHistory(line, segment, state=state, group=versions.get("posterior_group", ""))
    (out,) = summarize_states(
        [hist],
        [params],
        [np.asarray(limits_mm, dtype=np.float64)],
        limit_levels,
        horizons_days,
        calibration_version=versions.get("calibration_version", 0),
        posterior_versions=[versions.get("posterior_version", 0)],
    )
    return out
