"""Pure: a segment's on-board evidence from its closed TRC intervals, and the mixture log
weights the plan gives it (services/planning/README.md#formulation)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from schemas import SegmentState


@dataclass(frozen=True)
class Evidence:
    """A segment's on-board evidence over its posterior group's samples from its TRC
    intervals before the current one.

    The filter restarts the mixture weights at every TRC record (paper Eq. 13: equal
    weights), so a state's ``log_weights`` hold the likelihood of the on-board data since the
    last record only. Given sample j, the intervals' data are independent (each starts from
    its own record), so the segment's weights over all of them are

        log w_j = Σ_k log p(y_k | θ_j) = Σ_{closed k} ℓ_kj + ℓ_now,j,

    each ``ℓ_kj`` the last ``log_weights`` seen of interval k: a segment slower or faster
    than its group keeps being forecast so after the next record."""

    group: str
    version: int  # the posterior version whose samples these weigh
    last_trc_t: float  # the start of the newest interval counted
    log_weights: np.ndarray  # (Ns,) summed, max 0


def closed_interval(ev: Evidence | None, held: SegmentState, new: SegmentState) -> Evidence | None:
    """The evidence once ``new`` has come after ``held``: with ``held``'s log weights added
    when ``new`` starts a later TRC interval (``held``'s weights being its interval's last);
    None when nothing changes. Weights of another posterior group or version than
    ``new``'s, or an interval already counted, add nothing; evidence of another posterior
    than ``new``'s, or over another number of samples, is dropped (other samples)."""
    if held.last_trc_t is None or new.last_trc_t is None or new.last_trc_t <= held.last_trc_t:
        return None
    posterior = (new.posterior_group, new.posterior_version)
    if ev is not None and (ev.group, ev.version) != posterior:
        ev = None
    if held.log_weights is None or (held.posterior_group, held.posterior_version) != posterior:
        return None
    lw = held.log_weights.array().astype(float)
    if ev is not None and ev.log_weights.shape != lw.shape:
        ev = None  # counted over another number of samples: not these
    if ev is not None and held.last_trc_t <= ev.last_trc_t:
        return None
    total = lw if ev is None else ev.log_weights + lw
    return Evidence(*posterior, held.last_trc_t, total - total.max())


def log_weights(ev: Evidence | None, state: SegmentState, version: int) -> np.ndarray | None:
    """The log weights of ``state``'s segment over the samples of its group's posterior
    ``version``: its closed intervals' evidence plus the state's own (each counted when of
    that version and of the same length); None: equal weights."""
    lw = state.log_weights.array() if state.log_weights is not None else None
    if lw is not None and state.posterior_version != version:
        lw = None
    if ev is not None and (ev.group, ev.version) == (state.posterior_group, version):
        if lw is None:
            return ev.log_weights
        if lw.shape == ev.log_weights.shape:
            return ev.log_weights + lw
    return lw
