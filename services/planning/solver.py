r"""The plan's optimisation: which segment is tamped in which week.

Pure numpy/scipy/numba. The problem (:class:`Problem`): segments grouped in *blocks* (a
stretch of one line: adjacent segments in chainage order); per segment ``i`` a cost
:math:`c_{i,w}` of being tamped in week ``w`` (0 … W-1) and :math:`c_{i,\varnothing}` of not
being tamped in the horizon (at most one tamping per segment in the horizon). Adjacent
segments tamped in the same week form a *worksite* (one possession, cost ``P``) which must be
at least ``k`` segments long. Coupling constraints: tamping capacity (km per week per
region) and a budget (tamping and possession money over the horizon).

**Per block** the problem without the coupling constraints is a shortest path over the
segments, with states "not tamped" and "tamped in week w, the worksite so far r segments
long" (r capped at k): :func:`dp_blocks` solves every block exactly in
O(n W k) (compiled).

**Coupling**: Dantzig-Wolfe column generation. The restricted master LP (HiGHS, through
``scipy.optimize.linprog``) chooses a convex combination of known block plans per block under
the capacity and budget rows; its duals :math:`y \le 0` price the weeks,

.. math:: \tilde c_{i,w} = c_{i,w} - y_{r(i),w}\,\ell_i - y_B\,m_i, \qquad
          \tilde P = P\,(1 - y_B),

(:math:`\ell_i` km, :math:`m_i` tamping money), and the block DP with these costs gives each
block's best new plan (a column) and the Lagrangian bound

.. math:: LB(y) = \sum_b \min_{\text{plans of } b} \tilde c + \sum_{r,w} y_{r,w}\,
          \mathrm{cap}_{r,w} + y_B\,B \;\le\; \text{optimum},

a bound at least as tight as the LP relaxation of the MILP over (segment, week). Column
generation stops when no block has a negative reduced cost, or the LP is within a quarter of
the target gap of the bound. Without a budget the regions are independent: only the regions
whose blocks' best plans break their capacity go through it, each on its own (and a re-plan
reuses the solution of a region whose problem did not change).

**The plan** is a set of *worksites* (one run of adjacent segments, one week) taken from the
block plans found, each also in every other week all its segments may be tamped and cut into
pieces that fit a week's capacity. Their set-packing LP (every segment in at most one
worksite, capacity and budget rows) is rounded greedily, and each worksite of the rounded
plan lengthened into the capacity whole worksites leave over; when that is further than the
target gap from the bound, the set-packing MILP (HiGHS through ``scipy.optimize.milp``)
restricted to the worksites near the LP's (a fraction of the time), then over every
worksite, within a time budget, then for at most ``COMPACT_MAX_VARIABLES / 2`` (segment, week)
options the MILP over them; the better plan and the better bound are kept. Last, without a
budget, a plan that fills each week in turn with its cheapest worksites
(:func:`week_by_week`, an exact DP per week) replaces it when cheaper: where the capacity
binds every week and the integer programs got little time, that packing is what the
rounded LP lacks. The plan's cost
against the best bound is the reported gap.
"""

from __future__ import annotations

import hashlib
import os
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np
from scipy import sparse
from scipy.optimize import Bounds, LinearConstraint, linprog, milp

from services.planning.dynamic_programs import NONE, dp_blocks, week_by_week

MAX_COLUMN_ROUNDS = 60  # column generation rounds at most
MILP_TIME_LIMIT_S = 5.0  # per integer master or compact MILP
REGION_THREADS = min(4, os.cpu_count() or 1)  # regions solved at once
MILP_REL_GAP = 0.002  # HiGHS stops the integer master within this of its own bound
NEAR_LP_COLUMNS = 5  # the restricted integer master: this many worksites of least reduced
# cost per worksite in the LP's support (with the support and the rounded plan's)


@dataclass
class Problem:
    """Everything the optimisation needs; arrays over N segments in block order.

    ``cost`` (N, W+1): column ``w < W`` tamped in week ``w`` (``inf``: not allowed), column
    ``W`` not tamped. ``starts`` (B+1,) block offsets; ``k`` (B,) shortest worksite in
    segments; ``possession`` (B,) cost of a possession; ``region`` (B,) region index;
    ``km`` (N,) length; ``money`` (N,) tamping money (what the budget counts);
    ``capacity`` (R, W) km per week (``inf``: none); ``budget`` or None.
    """

    cost: np.ndarray
    starts: np.ndarray
    k: np.ndarray
    possession: np.ndarray
    region: np.ndarray
    km: np.ndarray
    money: np.ndarray
    capacity: np.ndarray
    budget: float | None = None

    @property
    def weeks(self) -> int:
        return self.cost.shape[1] - 1

    @property
    def n_blocks(self) -> int:
        return len(self.starts) - 1


@dataclass
class Solution:
    """The chosen week per segment (-1: none), its cost, the bound and how it was found."""

    choice: np.ndarray  # (N,)
    cost: float
    bound: float
    status: str  # "optimal" (cost == bound), "within_gap", "gap_above_target"
    rounds: int = 0
    columns: int = 0
    seconds: float = 0.0
    timings: dict[str, float] = field(default_factory=dict)

    @property
    def gap(self) -> float:
        """(cost - bound) / |cost|: 0 when proven optimal."""
        return max(0.0, self.cost - self.bound) / max(abs(self.cost), 1e-12)


def block_of(problem: Problem) -> np.ndarray:
    """Block index of every segment."""
    return np.repeat(np.arange(problem.n_blocks), np.diff(problem.starts))


def plan_cost(problem: Problem, choice: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Per block: (cost, km per week (B, W), money) of a choice vector."""
    c, weeks, blocks = problem.cost, problem.weeks, block_of(problem)
    col = np.where(choice < 0, weeks, choice)
    seg_cost = c[np.arange(len(choice)), col]
    starts_run = run_starts(problem, choice)
    poss = problem.possession[blocks] * starts_run
    cost_b = np.bincount(blocks, seg_cost + poss, minlength=problem.n_blocks)
    tamped = choice >= 0
    km = np.zeros((problem.n_blocks, weeks))
    np.add.at(km, (blocks[tamped], choice[tamped]), problem.km[tamped])
    money = np.bincount(blocks, problem.money * tamped + poss, minlength=problem.n_blocks)
    return float(cost_b.sum()), km, money


def run_starts(problem: Problem, choice: np.ndarray) -> np.ndarray:
    """1 where a worksite starts (a tamped segment whose block predecessor is not tamped in
    the same week), else 0."""
    first = np.zeros(len(choice), bool)
    first[problem.starts[:-1]] = True
    prev = np.r_[NONE, choice[:-1]]
    return ((choice >= 0) & (first | (prev != choice))).astype(float)


def _priced(problem: Problem, y_cap, y_budget, pi=None):
    """Costs relative to "not tamped" under the duals (module docstring): column ``W`` is 0,
    column ``w`` the reduced cost of tamping the segment in week ``w``; and the possession's."""
    blocks = block_of(problem)
    weeks = problem.weeks
    cost = np.zeros_like(problem.cost)
    cost[:, :weeks] = problem.cost[:, :weeks] - problem.cost[:, weeks : weeks + 1]
    cost[:, :weeks] -= y_cap[problem.region[blocks]] * problem.km[:, None]
    cost[:, :weeks] -= y_budget * problem.money[:, None]
    if pi is not None:
        cost[:, :weeks] -= pi[:, None]
    return cost, problem.possession * (1.0 - y_budget)


def solve(
    problem: Problem,
    *,
    target_gap: float = 0.01,
    milp_s: float = 30.0,
    solved: dict[bytes, tuple] | None = None,
) -> Solution:
    """The plan of ``problem``: every block's best plan; where that breaks a capacity or the
    budget, column generation and the integer master (module docstring). Without a budget the
    regions are independent and each is solved on its own, ``REGION_THREADS`` at once.
    ``milp_s``: seconds from the start of the regions that need column generation (their LPs
    included) after which no integer master starts; what is left is shared evenly by the
    regions still to solve, and a region without time keeps its rounded LP. ``solved``: the
    regions' solutions by their problem's digest, kept between calls, so that a re-plan
    solves again only the regions whose costs changed."""
    started = time.perf_counter()
    timings = {"dp": 0.0, "lp": 0.0, "milp": 0.0}
    cap = problem.capacity
    budget = problem.budget if problem.budget is not None else np.inf
    t = time.perf_counter()
    choice, value = dp_blocks(problem.cost, problem.starts, problem.k, problem.possession)
    timings["dp"] += time.perf_counter() - t
    _, km, money = plan_cost(problem, choice)
    load = np.zeros_like(cap)
    np.add.at(load, problem.region, km)
    over = np.flatnonzero((load > cap + 1e-9).any(axis=1))
    rounds = columns = 0
    bound = float(value.sum())
    if money.sum() > budget + 1e-9:
        choice, bound, rounds, columns = _coupled(problem, target_gap, timings, milp_s)
    elif over.size:
        # regions within their capacity keep their blocks' best plans (optimal there)
        regions = _solve_regions(problem, over, target_gap, milp_s, solved, timings)
        for rows, blocks, (sub_choice, sub_bound, n_rounds, n_columns) in regions:
            choice[rows] = sub_choice
            bound += sub_bound - value[blocks].sum()
            rounds = max(rounds, n_rounds)
            columns += n_columns
    total = plan_cost(problem, choice)[0]
    bound = min(bound, total)
    gap = max(0.0, total - bound) / max(abs(total), 1e-12)
    status = "within_gap" if gap <= target_gap else "gap_above_target"
    status = "optimal" if gap <= 1e-9 else status
    return Solution(choice, total, float(bound), status, rounds, columns,
                    time.perf_counter() - started, timings)  # fmt: skip


def _solve_regions(problem, over, target_gap, milp_s, solved, timings) -> list[tuple]:
    """``(rows, blocks, (choice, bound, rounds, columns))`` of each region of ``over``, solved
    on its own (:func:`_coupled`) by ``REGION_THREADS`` threads: the LPs and integer programs
    (HiGHS) and the block DP (numba) release the GIL. A region starting with ``T`` s left
    of ``milp_s`` and ``L`` regions not started gets ``T x threads / L`` s; a region whose
    problem is in ``solved`` takes that solution; ``solved`` keeps the regions' solutions
    only."""
    threads = min(REGION_THREADS, len(over))
    deadline = time.perf_counter() + milp_s
    lock = threading.Lock()
    started = [0]

    def region(r: int):
        blocks = np.flatnonzero(problem.region == r)
        sub, rows = subproblem(problem, blocks)
        key = _digest(sub, target_gap)
        with lock:
            share = max(0.0, deadline - time.perf_counter()) * threads / (len(over) - started[0])
            started[0] += 1
        mine = {"dp": 0.0, "lp": 0.0, "milp": 0.0}
        if solved is not None and key in solved:
            found = solved[key]
        else:
            found = _coupled(sub, target_gap, mine, share)
        return key, rows, blocks, found, mine

    if threads > 1:
        with ThreadPoolExecutor(threads, thread_name_prefix="planning:region") as pool:
            results = list(pool.map(region, over.tolist()))
    else:
        results = [region(r) for r in over.tolist()]
    for _, _, _, _, mine in results:
        for name, seconds in mine.items():
            timings[name] = timings.get(name, 0.0) + seconds
    if solved is not None:
        used = {key: found for key, _, _, found, _ in results}
        for key in set(solved) - set(used):  # regions whose costs changed since
            del solved[key]
        solved.update(used)
    return [(rows, blocks, found) for _, rows, blocks, found, _ in results]


def _digest(problem: Problem, target_gap: float) -> bytes:
    """What identifies a problem's solution: every array of it, and the target."""
    h = hashlib.blake2b(digest_size=16)
    for a in (problem.cost, problem.starts, problem.k, problem.possession, problem.region,
              problem.km, problem.money, problem.capacity):  # fmt: skip
        h.update(np.ascontiguousarray(a).tobytes())
    h.update(repr((problem.budget, target_gap)).encode())
    return h.digest()


def subproblem(problem: Problem, blocks: np.ndarray) -> tuple[Problem, np.ndarray]:
    """The problem of some blocks of one region, and the rows of their segments."""
    lo, hi = problem.starts[blocks], problem.starts[blocks + 1]
    rows = np.concatenate([np.arange(a, b) for a, b in zip(lo, hi, strict=True)])
    region = problem.region[blocks[0]]
    sub = Problem(
        cost=problem.cost[rows],
        starts=np.r_[0, np.cumsum(hi - lo)].astype(np.int64),
        k=problem.k[blocks],
        possession=problem.possession[blocks],
        region=np.zeros(len(blocks), np.int64),
        km=problem.km[rows],
        money=problem.money[rows],
        capacity=problem.capacity[region : region + 1],
        budget=problem.budget,
    )
    return sub, rows


def _coupled(problem: Problem, target_gap: float, timings: dict[str, float], milp_s: float):
    """Column generation and the integer master: (choice, bound, rounds, columns).

    The bound and the duals come from the Dantzig-Wolfe master over whole block plans; the
    plan from the set-packing MILP over every worksite of those plans, which may recombine
    worksites of different plans of one block (finer than choosing one plan per block).
    """
    weeks = problem.weeks
    cap = problem.capacity
    budget = problem.budget if problem.budget is not None else np.inf

    def dp(cost, poss):
        t = time.perf_counter()
        out = dp_blocks(cost, problem.starts, problem.k, poss)
        timings["dp"] += time.perf_counter() - t
        return out

    plans = _Columns(problem.n_blocks, weeks)
    worksites = _Worksites(problem)
    for choice in (np.full(len(problem.km), NONE), dp(problem.cost, problem.possession)[0]):
        _, km_c, money_c = plan_cost(problem, choice)
        plans.add_all(choice, _block_costs(problem, choice), km_c, money_c, problem.starts)
        worksites.add(choice)
    cap_rows = np.argwhere(np.isfinite(cap))  # (r, w) pairs with a capacity
    best_bound = -np.inf
    rounds = 0
    for rounds in range(1, MAX_COLUMN_ROUNDS + 1):  # noqa: B007 (rounds is reported)
        t = time.perf_counter()
        lp_value, pi, y_cap, y_budget = _master_lp(plans, cap, cap_rows, budget, problem.region)
        timings["lp"] += time.perf_counter() - t
        cost, poss = _priced(problem, y_cap, y_budget)
        choice, value = dp(cost, poss)  # relative to "not tamped": add that back
        value = value + np.bincount(block_of(problem), problem.cost[:, weeks], problem.n_blocks)
        bound = value.sum() + (y_cap[cap_rows[:, 0], cap_rows[:, 1]] * cap[
            cap_rows[:, 0], cap_rows[:, 1]]).sum()  # fmt: skip
        bound += y_budget * budget if np.isfinite(budget) else 0.0
        best_bound = max(best_bound, float(bound))
        new = np.flatnonzero(value - pi < -1e-9 * (1.0 + np.abs(pi)))
        # no new plan, or the LP within a quarter of the target of the bound: more columns
        # could not show a better plan than the target allows
        if new.size == 0 or lp_value - best_bound <= target_gap / 4 * max(1.0, abs(lp_value)):
            break
        _, km_c, money_c = plan_cost(problem, choice)
        plans.add_some(new, choice, _block_costs(problem, choice), km_c, money_c, problem.starts)
        worksites.add(choice)
    t = time.perf_counter()
    # the LP over the worksites, rounded: often within the target already
    cost, _, a_seg, a_cap, b_cap = worksites.matrices(cap_rows, budget)
    x, reduced = worksites.relaxation(cost, a_seg, a_cap, b_cap)
    choice, taken = worksites.rounded(cost, x)
    total = plan_cost(problem, choice)[0]
    timings["rounding"] = timings.get("rounding", 0.0) + time.perf_counter() - t
    # the integer master over the worksites near the LP's (fast), then over all of them
    for columns in (worksites.near_relaxation(x, reduced, taken, NEAR_LP_COLUMNS), None):
        if total - best_bound <= target_gap * max(abs(total), 1e-12) or milp_s < 0.05:
            break
        t = time.perf_counter()
        found = worksites.master_milp(
            cap_rows, budget, target_gap, min(milp_s, MILP_TIME_LIMIT_S), columns
        )
        if found is not None and plan_cost(problem, found)[0] < total:
            choice, total = found, plan_cost(problem, found)[0]
        timings["milp"] += time.perf_counter() - t
        milp_s -= time.perf_counter() - t
    left = milp_s
    if total - best_bound > target_gap * max(abs(total), 1e-12) and left >= 0.2:
        # the worksites found are not enough: the MILP over (segment, week), if not too large
        t = time.perf_counter()
        found = compact_milp(problem, target_gap, min(left, MILP_TIME_LIMIT_S))
        timings["compact_milp"] = timings.get("compact_milp", 0.0) + time.perf_counter() - t
        if found is not None:
            compact_choice, compact_bound = found
            best_bound = max(best_bound, compact_bound)
            if (compact_total := plan_cost(problem, compact_choice)[0]) < total:
                choice, total = compact_choice, compact_total
    # where the capacity binds every week and the integer programs got little time, a plan
    # that packs each week exactly often beats theirs and the rounded LP's
    t = time.perf_counter()
    for urgent in (False, True):
        packed = week_by_week(problem, urgent)
        if packed is not None and (packed_total := plan_cost(problem, packed)[0]) < total:
            choice, total = packed, packed_total
    timings["rounding"] += time.perf_counter() - t
    return choice, best_bound, rounds, plans.n + worksites.n


def _block_costs(problem: Problem, choice: np.ndarray) -> np.ndarray:
    blocks = block_of(problem)
    col = np.where(choice < 0, problem.weeks, choice)
    seg = problem.cost[np.arange(len(choice)), col] + problem.possession[blocks] * run_starts(
        problem, choice
    )
    return np.bincount(blocks, seg, minlength=problem.n_blocks)


class _Columns:
    """Known plans of every block (the Dantzig-Wolfe master's columns): cost, km per week,
    money."""

    def __init__(self, n_blocks: int, weeks: int) -> None:
        self.block: list[int] = []
        self.cost: list[float] = []
        self.km: list[np.ndarray] = []
        self.money: list[float] = []
        self.seen: set[tuple[int, bytes]] = set()

    @property
    def n(self) -> int:
        return len(self.block)

    def add_all(self, choice, cost, km, money, starts) -> None:
        self.add_some(np.arange(len(starts) - 1), choice, cost, km, money, starts)

    def add_some(self, blocks, choice, cost, km, money, starts) -> None:
        for b in blocks:
            part = choice[starts[b] : starts[b + 1]].copy()
            key = (int(b), part.tobytes())
            if key in self.seen:
                continue
            self.seen.add(key)
            self.block.append(int(b))
            self.cost.append(float(cost[b]))
            self.km.append(km[b].copy())
            self.money.append(float(money[b]))

    def matrices(self, cap, cap_rows, budget, block_region):
        """(c, A_eq, A_ub, b_ub): the master's cost, convexity rows, capacity/budget rows."""
        n, n_b = self.n, max(self.block) + 1 if self.block else 0
        c = np.array(self.cost)
        blocks = np.array(self.block)
        a_eq = sparse.csr_matrix((np.ones(n), (blocks, np.arange(n))), shape=(n_b, n))
        km = np.array(self.km)  # (n, W)
        row_of = {(int(r), int(w)): i for i, (r, w) in enumerate(cap_rows)}
        rows, cols, vals = [], [], []
        regions = block_region[blocks]
        nz_c, nz_w = np.nonzero(km)
        for ci, w in zip(nz_c, nz_w, strict=True):
            i = row_of.get((int(regions[ci]), int(w)))
            if i is not None:
                rows.append(i)
                cols.append(ci)
                vals.append(km[ci, w])
        n_ub = len(cap_rows) + (1 if np.isfinite(budget) else 0)
        if np.isfinite(budget):
            rows += [len(cap_rows)] * n
            cols += list(range(n))
            vals += self.money
        a_ub = sparse.csr_matrix((vals, (rows, cols)), shape=(n_ub, n))
        b_ub = np.r_[cap[cap_rows[:, 0], cap_rows[:, 1]], [budget] if np.isfinite(budget) else []]
        return c, a_eq, n_b, a_ub, b_ub


def _master_lp(columns: _Columns, cap, cap_rows, budget, block_region):
    c, a_eq, n_b, a_ub, b_ub = columns.matrices(cap, cap_rows, budget, block_region)
    res = linprog(
        c,
        A_ub=a_ub if a_ub.shape[0] else None,
        b_ub=b_ub if a_ub.shape[0] else None,
        A_eq=a_eq,
        b_eq=np.ones(n_b),
        bounds=(0, None),
        method="highs",
    )
    if res.status != 0:
        raise RuntimeError(f"master LP: {res.message}")
    y = res.ineqlin.marginals if a_ub.shape[0] else np.zeros(0)
    y_cap = np.zeros_like(cap)
    y_cap[cap_rows[:, 0], cap_rows[:, 1]] = y[: len(cap_rows)]
    y_budget = float(y[len(cap_rows)]) if np.isfinite(budget) else 0.0
    return float(res.fun), res.eqlin.marginals, y_cap, y_budget


class _Worksites:
    """The master's columns: worksites (a run of adjacent segments of one block, one week).

    Master: :math:`\\min \\sum_c (P + \\sum_{i \\in c} c_{i,w_c} - c_{i,\\varnothing})\\,\\theta_c`
    with every segment in at most one chosen worksite, capacity and budget rows; a plan is
    the union of the chosen worksites (adjacent ones in one week merge, sharing a
    possession, which only lowers the cost).
    """

    def __init__(self, problem: Problem) -> None:
        self.problem = problem
        self.blocks = block_of(problem)
        self.first: list[int] = []  # first segment
        self.length: list[int] = []
        self.week: list[int] = []
        self.seen: dict[tuple[int, int, int], int] = {}  # (first, length, week) -> index

    @property
    def n(self) -> int:
        return len(self.first)

    def add(self, choice: np.ndarray) -> int:
        """Add the worksites of a plan not known yet, each also in every other week it may be
        tamped, and cut into pieces that fit a week's capacity when it does not; how many were
        new."""
        p = self.problem
        starts = np.flatnonzero(run_starts(p, choice))
        new = 0
        for a in starts:
            b = a + 1
            while b < len(choice) and choice[b] == choice[a] and self.blocks[b] == self.blocks[a]:
                b += 1
            new += self._insert(int(a), int(b - a), int(choice[a]))
            region = p.region[self.blocks[a]]
            cap = p.capacity[region].min()
            km = np.cumsum(p.km[a:b])
            if km[-1] <= cap:
                continue
            longest = int(np.searchsorted(km, cap, side="right"))  # segments within capacity
            k = int(p.k[self.blocks[a]])
            if longest < k:
                continue
            for offset in range(longest):
                cuts = [a, *range(a + offset, b, longest)[offset == 0 :], b]
                for lo, hi in zip(cuts[:-1], cuts[1:], strict=True):
                    if k <= hi - lo <= longest:
                        new += self._insert(lo, hi - lo, int(choice[a]))
        return new

    def _insert(self, first: int, length: int, week: int) -> int:
        """A worksite in ``week`` and in every other week all its segments may be tamped."""
        allowed = np.isfinite(self.problem.cost[first : first + length, : self.problem.weeks])
        new = 0
        for w in np.flatnonzero(allowed.all(axis=0)):
            before = self.n
            self._index(first, length, int(w))
            new += self.n - before
        return new

    def _index(self, first: int, length: int, week: int) -> int:
        """The index of a worksite, added if new."""
        key = (first, length, week)
        if key not in self.seen:
            self.seen[key] = self.n
            self.first.append(first)
            self.length.append(length)
            self.week.append(week)
        return self.seen[key]

    def matrices(self, cap_rows, budget):
        p = self.problem
        weeks = p.weeks
        n = self.n
        first, length, week = (np.array(x, np.int64) for x in (self.first, self.length, self.week))
        seg = np.repeat(first, length) + (np.arange(length.sum()) - np.repeat(
            np.cumsum(length) - length, length))  # fmt: skip
        col = np.repeat(np.arange(n), length)
        rel = p.cost[seg, week[col]] - p.cost[seg, weeks]
        poss = p.possession[self.blocks[first]]
        cost = np.bincount(col, rel, minlength=n) + poss
        km = np.bincount(col, p.km[seg], minlength=n)
        money = np.bincount(col, p.money[seg], minlength=n) + poss
        used, seg_row = np.unique(seg, return_inverse=True)
        a_seg = sparse.csr_matrix((np.ones(len(seg)), (seg_row, col)), shape=(len(used), n))
        row_of = {(int(r), int(w)): i for i, (r, w) in enumerate(cap_rows)}
        region = p.region[self.blocks[first]]
        pairs = zip(region.tolist(), week.tolist(), strict=True)
        rows = np.array([row_of.get(pair, -1) for pair in pairs], np.int64)
        has = rows >= 0
        n_ub = len(cap_rows) + (1 if np.isfinite(budget) else 0)
        r_idx = list(rows[has])
        c_idx = list(np.flatnonzero(has))
        vals = list(km[has])
        if np.isfinite(budget):
            r_idx += [len(cap_rows)] * n
            c_idx += list(range(n))
            vals += list(money)
        a_cap = sparse.csr_matrix((vals, (r_idx, c_idx)), shape=(n_ub, n))
        b_cap = p.capacity[cap_rows[:, 0], cap_rows[:, 1]]
        if np.isfinite(budget):
            b_cap = np.r_[b_cap, budget]
        return cost, used, a_seg, a_cap, b_cap

    def relaxation(self, cost, a_seg, a_cap, b_cap) -> tuple[np.ndarray, np.ndarray]:
        """The set-packing LP: every worksite's value and reduced cost."""
        a_ub = sparse.vstack([a_seg, a_cap]).tocsr()
        b_ub = np.r_[np.ones(a_seg.shape[0]), b_cap]
        res = linprog(cost, A_ub=a_ub, b_ub=b_ub, bounds=(0, 1), method="highs")
        if res.x is None:
            return np.zeros(self.n), cost
        return res.x, cost - a_ub.T @ res.ineqlin.marginals

    def rounded(self, cost, x) -> tuple[np.ndarray, np.ndarray]:
        """Worksites by their LP value ``x`` (then cost), each taken if it still fits; then
        every other worksite that lowers the cost, cheapest first, while it fits; then each
        worksite lengthened where that lowers the cost (:meth:`_lengthened`). The plan and
        its worksites (added to the known ones where new)."""
        p = self.problem
        first, length, week = (np.array(v, np.int64) for v in (self.first, self.length, self.week))
        cum_km = np.r_[0.0, np.cumsum(p.km)]
        cum_money = np.r_[0.0, np.cumsum(p.money)]
        km = cum_km[first + length] - cum_km[first]
        region = p.region[self.blocks[first]]
        money = cum_money[first + length] - cum_money[first] + p.possession[self.blocks[first]]
        left = p.capacity.astype(float).copy()
        budget = p.budget if p.budget is not None else np.inf
        free = np.ones(len(p.km), bool)
        choice = np.full(len(p.km), NONE)
        support = np.flatnonzero(x > 1e-6)
        rest = np.setdiff1d(np.flatnonzero(cost < 0), support)
        order = np.r_[
            support[np.lexsort((cost[support], -x[support]))], rest[np.argsort(cost[rest])]
        ]
        for c in order.tolist():
            lo, hi, w, r = first[c], first[c] + length[c], week[c], region[c]
            if km[c] <= left[r, w] + 1e-9 and money[c] <= budget + 1e-9 and free[lo:hi].all():
                free[lo:hi] = False
                left[r, w] -= km[c]
                budget -= money[c]
                choice[lo:hi] = w
        choice = self._lengthened(choice, left, budget)
        return choice, self.of_plan(choice)

    def of_plan(self, choice: np.ndarray) -> np.ndarray:
        """The worksites of a plan (added to the known ones where new)."""
        taken = []
        for a in np.flatnonzero(run_starts(self.problem, choice)).tolist():
            b = a + 1
            while b < len(choice) and choice[b] == choice[a] and self.blocks[b] == self.blocks[a]:
                b += 1
            taken.append(self._index(a, b - a, int(choice[a])))
        return np.array(taken, np.int64)

    def _lengthened(self, choice: np.ndarray, left: np.ndarray, budget: float) -> np.ndarray:
        """``choice`` with each worksite lengthened, at either end, by the untamped segments
        of its block whose tamping in its week lowers the cost most, within the capacity
        ``left`` (region, week) and the ``budget`` left. A week's capacity left over by whole
        worksites is often less than the shortest worksite; a longer worksite needs no other
        possession, so it can use it."""
        p = self.problem
        weeks = p.weeks
        relative = p.cost[:, :weeks] - p.cost[:, weeks : weeks + 1]
        choice = choice.copy()
        block_lo = p.starts[self.blocks]
        block_hi = p.starts[self.blocks + 1]
        for a in np.flatnonzero(run_starts(p, choice)).tolist():
            w = int(choice[a])
            b = a
            while b < block_hi[a] and choice[b] == w:
                b += 1
            r = p.region[self.blocks[a]]
            for step, edge, stop in ((1, b, block_hi[a]), (-1, a - 1, block_lo[a] - 1)):
                total = best = 0.0
                km = money = 0.0
                reach = edge
                j = edge
                while j != stop and choice[j] == NONE and np.isfinite(relative[j, w]):
                    km += p.km[j]
                    money += p.money[j]
                    if km > left[r, w] + 1e-9 or money > budget + 1e-9:
                        break
                    total += relative[j, w]
                    if total < best:
                        best, reach = total, j + step
                    j += step
                if reach == edge:
                    continue
                lo, hi = (edge, reach) if step == 1 else (reach + 1, edge + 1)
                choice[lo:hi] = w
                left[r, w] -= p.km[lo:hi].sum()
                budget -= p.money[lo:hi].sum()
        return choice

    def near_relaxation(self, x, reduced, taken, per_support: int) -> np.ndarray:
        """The worksites an integer master restricted to them can do well with: the LP's
        support, the ``per_support`` x as many of least reduced cost, and ``taken`` (so
        its optimum is no worse than that plan)."""
        support = np.flatnonzero(x > 1e-6)
        cheapest = np.argsort(reduced)[: per_support * max(len(support), 1)]
        return np.union1d(np.union1d(support, cheapest), taken)

    def master_milp(
        self, cap_rows, budget, target_gap, time_limit: float, columns=None
    ) -> np.ndarray | None:
        """The best set of known worksites (of ``columns`` only, when given), as a choice
        vector; None when HiGHS finds none in the time."""
        cost, used, a_seg, a_cap, b_cap = self.matrices(cap_rows, budget)
        a = sparse.vstack([a_seg, a_cap]).tocsr()
        cols = np.arange(self.n) if columns is None else np.asarray(columns)
        res = milp(
            cost[cols],
            constraints=[
                LinearConstraint(a[:, cols], -np.inf, np.r_[np.ones(a_seg.shape[0]), b_cap])
            ],
            integrality=np.ones(len(cols)),
            bounds=Bounds(0, 1),
            options={"time_limit": time_limit, "mip_rel_gap": target_gap / 4},
        )
        if res.x is None:
            return None
        choice = np.full(len(self.problem.km), NONE)
        for c in cols[res.x > 0.5]:
            choice[self.first[c] : self.first[c] + self.length[c]] = self.week[c]
        return choice


COMPACT_MAX_VARIABLES = 20_000  # (segment, week) options the compact MILP takes at most


def compact_milp(
    problem: Problem, target_gap: float, time_limit: float = MILP_TIME_LIMIT_S
) -> tuple[np.ndarray, float] | None:
    """The MILP over (segment, week): x[i,w] tamped, s[i,w] a worksite starts; (choice,
    HiGHS's dual bound), or None when it is too large or finds nothing.

    .. math::
        \\min \\sum_{i,w} (c_{i,w} - c_{i,\\varnothing}) x_{i,w} + P s_{i,w}
        \\;\\text{s.t.}\\; \\sum_w x_{i,w} \\le 1,\\;
        s_{i,w} \\ge x_{i,w} - x_{i-1,w},\\; s_{i,w} \\le x_{i+m,w}\\ (0 \\le m < k),
    capacity and budget rows.
    """
    weeks = problem.weeks
    blocks = block_of(problem)
    seg = np.flatnonzero(np.isfinite(problem.cost[:, :weeks]).any(axis=1))
    allowed = np.isfinite(problem.cost[seg, :weeks])
    n_opt = int(allowed.sum())
    if n_opt == 0 or 2 * n_opt > COMPACT_MAX_VARIABLES:
        return None
    # variable index of x[i, w] and s[i, w]; -1 where not allowed
    xi = np.full((len(problem.km), weeks), -1)
    xi[seg[:, None].repeat(weeks, 1)[allowed], np.nonzero(allowed)[1]] = np.arange(n_opt)
    si = np.where(xi >= 0, xi + n_opt, -1)
    none_cost = problem.cost[:, weeks]
    c = np.zeros(2 * n_opt)
    rr, ww = np.nonzero(xi >= 0)
    c[xi[rr, ww]] = problem.cost[rr, ww] - none_cost[rr]
    c[si[rr, ww]] = problem.possession[blocks[rr]]
    rows, cols, vals, lo, hi = [], [], [], [], []

    def row(entries, low, high):
        for col, val in entries:
            rows.append(len(lo))
            cols.append(col)
            vals.append(val)
        lo.append(low)
        hi.append(high)

    first = np.zeros(len(problem.km), bool)
    first[problem.starts[:-1]] = True
    last = np.zeros(len(problem.km), bool)
    last[problem.starts[1:] - 1] = True
    k_of = problem.k[blocks]
    for i in seg:
        opts = [(int(xi[i, w]), 1.0) for w in range(weeks) if xi[i, w] >= 0]
        if len(opts) > 1:
            row(opts, -np.inf, 1.0)
        for w in range(weeks):
            if xi[i, w] < 0:
                continue
            x, s = int(xi[i, w]), int(si[i, w])
            entries = [(s, 1.0), (x, -1.0)]
            if not first[i] and xi[i - 1, w] >= 0:
                entries.append((int(xi[i - 1, w]), 1.0))
            row(entries, 0.0, np.inf)  # s >= x - x_prev
            for m in range(int(k_of[i])):
                j = i + m
                if j > i and (last[j - 1] or xi[j, w] < 0):  # the worksite cannot fit
                    row([(s, 1.0)], -np.inf, 0.0)
                    break
                row([(s, 1.0), (int(xi[j, w]), -1.0)], -np.inf, 0.0)
    region_of = problem.region[blocks]
    for r, w in np.argwhere(np.isfinite(problem.capacity)):
        members = [(int(xi[i, w]), float(problem.km[i])) for i in seg if region_of[i] == r
                   and xi[i, w] >= 0]  # fmt: skip
        if members:
            row(members, -np.inf, float(problem.capacity[r, w]))
    if problem.budget is not None:
        pairs = list(zip(rr, ww, strict=True))
        entries = [(int(xi[i, w]), float(problem.money[i])) for i, w in pairs]
        entries += [(int(si[i, w]), float(problem.possession[blocks[i]])) for i, w in pairs]
        row(entries, -np.inf, float(problem.budget))
    a = sparse.csr_matrix((vals, (rows, cols)), shape=(len(lo), 2 * n_opt))
    res = milp(
        c,
        constraints=[LinearConstraint(a, np.array(lo), np.array(hi))],
        integrality=np.ones(2 * n_opt),
        bounds=Bounds(0, 1),
        options={"time_limit": time_limit, "mip_rel_gap": target_gap / 4},
    )
    if res.x is None:
        return None
    x = np.round(res.x[:n_opt]) > 0.5
    choice = np.full(len(problem.km), NONE)
    choice[rr[x]] = ww[x]
    dual = getattr(res, "mip_dual_bound", None)
    bound = -np.inf if dual is None else float(dual) + none_cost.sum()
    return choice, bound
