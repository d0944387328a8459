"""The plan's dynamic programs, compiled (numba; they release the GIL).

- :func:`dp_blocks`: every block's best plan over the weeks without the coupling rows (a
  shortest path over "not tamped" and "week w, the worksite so far r segments long").
- :func:`week_runs`: one week's best worksites over blocks sharing one capacity (a shortest
  path over segment, capacity used and worksite length), and :func:`week_by_week`, a plan
  that fills the weeks in turn with it.

Their callers, the problem and its notation: :mod:`services.planning.solver`.
"""

from __future__ import annotations

import numba
import numpy as np

NONE = -1  # a segment's choice: not tamped in the horizon


@numba.njit(cache=True, nogil=True)
def dp_blocks(cost, starts, k, poss):  # pragma: no cover - compiled
    """Best plan of every block: choice (N,) (-1 or week) and its cost (B,)."""
    n_seg, width = cost.shape
    weeks = width - 1
    choice = np.empty(n_seg, np.int64)
    value = np.empty(starts.shape[0] - 1)
    for b in range(starts.shape[0] - 1):
        lo, hi = starts[b], starts[b + 1]
        kk = k[b]
        p = poss[b]
        n_states = 1 + weeks * kk
        v = np.full(n_states, np.inf)
        vn = np.full(n_states, np.inf)
        back = np.zeros((hi - lo, n_states), np.int32)
        v[0] = cost[lo, weeks]
        for w in range(weeks):
            v[1 + w * kk] = cost[lo, w] + p
        for i in range(1, hi - lo):
            row = lo + i
            # best and second best closed state (none, or a worksite k long), with its week
            best, best_s, best_w = v[0], 0, -1
            second, second_s = np.inf, 0
            for w in range(weeks):
                s = 1 + w * kk + kk - 1
                if v[s] < best:
                    second, second_s = best, best_s
                    best, best_s, best_w = v[s], s, w
                elif v[s] < second:
                    second, second_s = v[s], s
            vn[0] = cost[row, weeks] + best
            back[i, 0] = best_s
            for w in range(weeks):
                c = cost[row, w]
                base = 1 + w * kk
                if best_w != w:
                    prev, prev_s = best, best_s
                else:
                    prev, prev_s = second, second_s
                if kk == 1:
                    if v[base] <= prev + p:
                        vn[base] = c + v[base]
                        back[i, base] = base
                    else:
                        vn[base] = c + prev + p
                        back[i, base] = prev_s
                    continue
                vn[base] = c + prev + p
                back[i, base] = prev_s
                for r in range(1, kk - 1):
                    vn[base + r] = c + v[base + r - 1]
                    back[i, base + r] = base + r - 1
                a, z = v[base + kk - 2], v[base + kk - 1]
                if a <= z:
                    vn[base + kk - 1] = c + a
                    back[i, base + kk - 1] = base + kk - 2
                else:
                    vn[base + kk - 1] = c + z
                    back[i, base + kk - 1] = base + kk - 1
            v, vn = vn, v
        best, s = v[0], 0
        for w in range(weeks):
            t = 1 + w * kk + kk - 1
            if v[t] < best:
                best, s = v[t], t
        value[b] = best
        for i in range(hi - lo - 1, -1, -1):
            choice[lo + i] = NONE if s == 0 else (s - 1) // kk
            if i > 0:
                s = back[i, s]
    return choice, value


@numba.njit(cache=True, nogil=True)
def week_runs(value, starts, k, poss, units, cap):  # pragma: no cover - compiled
    """The cheapest worksites of one week over blocks sharing one capacity: tamped (N,) bool.

    ``value`` (N,): a segment's cost of being tamped this week less its cost untamped (inf:
    not allowed); ``units`` (N,) its km in capacity units, ``cap`` the week's units. A
    shortest path over (segment, units used, run length r capped at the block's k), a run
    ending only at r = k, each run paying its block's possession."""
    n = value.shape[0]
    kmax = 1
    for b in range(starts.shape[0] - 1):
        kmax = max(kmax, k[b])
    v = np.full((cap + 1, kmax + 1), np.inf)
    vn = np.empty_like(v)
    back = np.full((n, cap + 1, kmax + 1), -1, np.int16)  # the run length before
    v[0, 0] = 0.0
    prev_k = 0
    for b in range(starts.shape[0] - 1):
        kk, p = k[b], poss[b]
        for i in range(starts[b], starts[b + 1]):
            first = i == starts[b]
            vn[:] = np.inf
            u = units[i]
            for c in range(cap + 1):
                # untamped: a run so far, if any, is long enough
                closed, from_r = v[c, 0], 0
                last = prev_k if first else kk
                if last > 0 and v[c, last] < closed:
                    closed, from_r = v[c, last], last
                vn[c, 0] = closed
                back[i, c, 0] = from_r
                if not np.isfinite(value[i]) or c + u > cap:
                    continue
                # tamped: a new run (after a closed state), or the run goes on
                cn = c + u
                start = closed + p + value[i]
                if start < vn[cn, 1]:
                    vn[cn, 1] = start
                    back[i, cn, 1] = from_r
                if first:
                    continue
                for r in range(1, kk + 1):
                    if not np.isfinite(v[c, r]):
                        continue
                    rn = min(r + 1, kk)
                    if v[c, r] + value[i] < vn[cn, rn]:
                        vn[cn, rn] = v[c, r] + value[i]
                        back[i, cn, rn] = r
            v, vn = vn, v
        prev_k = kk
    best, bc, br = np.inf, 0, 0
    for c in range(cap + 1):
        for r in (0, prev_k):
            if v[c, r] < best:
                best, bc, br = v[c, r], c, r
    tamped = np.zeros(n, np.bool_)
    c, r = bc, br
    for i in range(n - 1, -1, -1):
        before = back[i, c, r]
        if r > 0:
            tamped[i] = True
            c -= units[i]
        r = before
    return tamped


WEEK_UNITS = 100  # a week's capacity in units at most (week_by_week)
WEEK_STATES = 20_000_000  # segments x units x run lengths week_by_week takes at most


def week_by_week(problem, urgent: bool) -> np.ndarray | None:
    """A plan of ``problem`` (a :class:`~services.planning.solver.Problem`) that fills each
    week's capacity in turn with its cheapest worksites (:func:`week_runs`, exact for one
    week) among the segments earlier weeks left; None with a budget, a week without a
    capacity, or too many states. ``urgent``: a segment's value in week w is what tamping it
    then saves over its best later week (or none), so that what cannot wait goes first;
    else its cost itself. Greedy over the weeks, so a candidate next to the rounded LP's
    plan, not a bound."""
    if problem.budget is not None or not np.isfinite(problem.capacity).all():
        return None
    weeks = problem.weeks
    relative = problem.cost[:, :weeks] - problem.cost[:, weeks : weeks + 1]
    later = np.zeros_like(relative)  # the best of the weeks after w, or none
    for w in range(weeks - 2, -1, -1):
        later[:, w] = np.minimum(later[:, w + 1], relative[:, w + 1])
    choice = np.full(len(problem.km), NONE)
    for r in np.unique(problem.region):
        blocks = np.flatnonzero(problem.region == r)
        lo, hi = problem.starts[blocks], problem.starts[blocks + 1]
        rows = np.concatenate([np.arange(a, b) for a, b in zip(lo, hi, strict=True)])
        starts = np.r_[0, np.cumsum(hi - lo)].astype(np.int64)
        km = problem.km[rows]
        unit = max(float(km.min()), float(problem.capacity[r].max()) / WEEK_UNITS, 1e-9)
        units = np.ceil(km / unit - 1e-9).astype(np.int64)
        k = problem.k[blocks]
        if len(rows) * (WEEK_UNITS + 1) * (int(k.max()) + 1) > WEEK_STATES:
            return None
        for w in range(weeks):
            value = relative[rows, w] - (later[rows, w] if urgent else 0.0)
            value[choice[rows] != NONE] = np.inf
            cap = int(np.floor(problem.capacity[r, w] / unit + 1e-9))
            tamped = week_runs(value, starts, k, problem.possession[blocks], units, cap)
            choice[rows[tamped]] = w
    return choice
