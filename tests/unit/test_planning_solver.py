"""The plan's optimisation against brute-force enumeration of every plan of small problems."""

from __future__ import annotations

import dataclasses
import itertools

import numpy as np
import pytest

from services.planning import dynamic_programs, solver
from services.planning.core import PlanningConfig, PlanningCore, week_start
from services.planning.solver import NONE, Problem, plan_cost, run_starts, solve
from services.planning.testing import T0, make_limits, make_posterior, random_network


def brute_force(problem: Problem) -> float:
    """The cheapest feasible plan's cost, by enumerating every choice vector."""
    n, weeks = problem.cost.shape[0], problem.weeks
    best = np.inf
    blocks = np.repeat(np.arange(problem.n_blocks), np.diff(problem.starts))
    for combo in itertools.product(range(-1, weeks), repeat=n):
        choice = np.array(combo)
        if not np.isfinite(problem.cost[np.arange(n), np.where(choice < 0, weeks, choice)]).all():
            continue
        if not worksites_long_enough(problem, choice):
            continue
        total, km, money = plan_cost(problem, choice)
        load = np.zeros_like(problem.capacity)
        np.add.at(load, problem.region, km)
        if (load > problem.capacity + 1e-9).any():
            continue
        if problem.budget is not None and money.sum() > problem.budget + 1e-9:
            continue
        best = min(best, total)
    assert blocks.size == n
    return best


def worksites_long_enough(problem: Problem, choice: np.ndarray) -> bool:
    starts = run_starts(problem, choice).astype(bool)
    for b in range(problem.n_blocks):
        lo, hi = problem.starts[b], problem.starts[b + 1]
        i = lo
        while i < hi:
            if choice[i] == NONE:
                i += 1
                continue
            j = i + 1
            while j < hi and choice[j] == choice[i] and not starts[j]:
                j += 1
            if j - i < problem.k[b]:
                return False
            i = j
    return True


def random_problem(seed: int, *, coupled: bool) -> Problem:
    rng = np.random.default_rng(seed)
    weeks = int(rng.integers(1, 4))
    sizes = [int(s) for s in rng.integers(1, 4, size=int(rng.integers(1, 3)))]
    n = sum(sizes)
    if n > 6:
        sizes, n = sizes[:1], sizes[0]
    cost = rng.uniform(0, 10, (n, weeks + 1))
    cost[:, weeks] = rng.uniform(0, 25, n)  # not tamping: sometimes the dearest
    cost[rng.random((n, weeks + 1)) < 0.1] = np.inf
    cost[:, weeks] = np.where(np.isfinite(cost[:, weeks]), cost[:, weeks], 30.0)
    n_b = len(sizes)
    km = rng.uniform(0.1, 0.3, n)
    capacity = np.full((2, weeks), np.inf)
    budget = None
    if coupled:
        capacity = rng.uniform(0.2, 0.6, (2, weeks))
        budget = float(rng.uniform(5, 40))
    return Problem(
        cost=cost,
        starts=np.r_[0, np.cumsum(sizes)].astype(np.int64),
        k=rng.integers(1, 3, n_b).astype(np.int64),
        possession=rng.uniform(0, 6, n_b),
        region=rng.integers(0, 2, n_b),
        km=km,
        money=rng.uniform(1, 5, n),
        capacity=capacity,
        budget=budget,
    )


@pytest.mark.parametrize("seed", range(40))
def test_uncoupled_plan_is_the_brute_force_optimum(seed):
    problem = random_problem(seed, coupled=False)
    solution = solve(problem)
    assert solution.status == "optimal"
    assert solution.cost == pytest.approx(brute_force(problem), rel=1e-9)
    assert worksites_long_enough(problem, solution.choice)


@pytest.mark.parametrize("seed", range(40))
def test_coupled_plan_is_feasible_and_its_bound_holds(seed):
    problem = random_problem(seed, coupled=True)
    solution = solve(problem)
    best = brute_force(problem)
    total, km, money = plan_cost(problem, solution.choice)
    load = np.zeros_like(problem.capacity)
    np.add.at(load, problem.region, km)
    assert (load <= problem.capacity + 1e-9).all() and money.sum() <= problem.budget + 1e-9
    assert worksites_long_enough(problem, solution.choice)
    assert total == pytest.approx(solution.cost)
    assert solution.bound <= best + 1e-7 * max(1, abs(best))  # a bound, never above the optimum
    assert solution.cost >= best - 1e-7 * max(1, abs(best))
    assert solution.status in ("optimal", "within_gap")
    assert solution.cost <= best + 0.01 * abs(solution.cost) + 1e-9
    if solution.status == "optimal":
        assert solution.cost == pytest.approx(best, rel=1e-7)


def test_the_integer_master_near_the_lp_is_feasible_and_no_worse_than_the_rounded_lp():
    # worn lines sharing 1 km a week: the capacity, not the costs, decides the weeks
    config = PlanningConfig(regions={"R": 1.0}, region_of_line={"L1": "R", "L2": "R"})
    limits, ial = make_limits()
    refs, states = random_network(2, 60, seed=3, max_age=1.1)
    core = PlanningCore(config, limits, ial, refs)
    core.on_posterior(make_posterior())
    for state in states:
        core.on_state(state)
    planned = list(core.states)
    costs, fp = core.cost_rows(planned, week_start(T0), 26)
    problem, _, _ = core.optimisation_problem(planned, costs, fp, 26, None)
    worksites = solver._Worksites(problem)
    worksites.add(solver.dp_blocks(problem.cost, problem.starts, problem.k,
                                   problem.possession)[0])  # fmt: skip
    cap_rows = np.argwhere(np.isfinite(problem.capacity))
    cost, _, a_seg, a_cap, b_cap = worksites.matrices(cap_rows, np.inf)
    x, reduced = worksites.relaxation(cost, a_seg, a_cap, b_cap)
    rounded, taken = worksites.rounded(cost, x)
    columns = worksites.near_relaxation(x, reduced, taken, solver.NEAR_LP_COLUMNS)
    assert len(columns) < worksites.n
    found = worksites.master_milp(cap_rows, np.inf, 0.01, 30.0, columns)
    total, km, _ = plan_cost(problem, found)
    load = np.zeros_like(problem.capacity)
    np.add.at(load, problem.region, km)
    assert (load <= problem.capacity + 1e-9).all() and worksites_long_enough(problem, found)
    assert total <= plan_cost(problem, rounded)[0] + 1e-6


def test_the_rounded_plan_lengthens_a_worksite_into_the_capacity_whole_worksites_leave():
    # one block of 8 segments of 0.2 km, worksites of at least 3, 1.0 km a week: a whole
    # worksite of 3 (0.6 km) leaves 0.4 km, too little for another but enough for 2 more
    # segments of the same worksite, at no other possession
    n, weeks = 8, 1
    cost = np.zeros((n, weeks + 1))
    cost[:, 0] = -100.0  # tamping any segment this week is worth it
    cost[5:, 0] = 50.0  # but not these three
    problem = Problem(
        cost=cost, starts=np.array([0, n]), k=np.array([3]), possession=np.array([10.0]),
        region=np.array([0]), km=np.full(n, 0.2), money=np.full(n, 1.0),
        capacity=np.array([[1.0]]),
    )  # fmt: skip
    worksites = solver._Worksites(problem)
    three = np.array([0, 0, 0, NONE, NONE, NONE, NONE, NONE])
    worksites.add(three)
    x = np.zeros(worksites.n)
    x[0] = 1.0
    choice, taken = worksites.rounded(np.full(worksites.n, -290.0), x)
    assert choice.tolist() == [0, 0, 0, 0, 0, NONE, NONE, NONE]  # not into the dear ones
    assert [(worksites.first[c], worksites.length[c]) for c in taken] == [(0, 5)]
    assert worksites_long_enough(problem, choice)


@pytest.mark.parametrize("seed", range(40))
def test_the_week_dp_finds_the_cheapest_worksites_that_fit_one_week(seed):
    rng = np.random.default_rng(seed)
    sizes = [int(s) for s in rng.integers(1, 6, size=int(rng.integers(1, 3)))]
    n = sum(sizes)
    starts = np.r_[0, np.cumsum(sizes)].astype(np.int64)
    k = rng.integers(1, 4, size=len(sizes)).astype(np.int64)
    poss = rng.uniform(0, 5, size=len(sizes))
    value = rng.normal(-3, 4, size=n)
    value[rng.random(n) < 0.15] = np.inf  # not allowed this week
    units = rng.integers(1, 3, size=n).astype(np.int64)
    cap = int(rng.integers(0, 8))
    tamped = dynamic_programs.week_runs(value, starts, k, poss, units, cap)

    def cost(t) -> float:
        if units[t].sum() > cap or not np.isfinite(value[t]).all():
            return np.inf
        total = float(value[t].sum())
        for b, (lo, hi) in enumerate(zip(starts[:-1], starts[1:], strict=True)):
            i = lo
            while i < hi:
                if not t[i]:
                    i += 1
                    continue
                j = i
                while j < hi and t[j]:
                    j += 1
                if j - i < k[b]:
                    return np.inf
                total += poss[b]
                i = j
        return total

    best = min(cost(np.array(t, bool)) for t in itertools.product((False, True), repeat=n))
    assert cost(tamped) == pytest.approx(best, abs=1e-9)


@pytest.mark.parametrize("seed", range(40))
def test_the_week_by_week_plan_keeps_every_capacity_and_worksite_length(seed):
    problem = dataclasses.replace(random_problem(seed, coupled=True), budget=None)
    best = brute_force(problem)
    for urgent in (False, True):
        choice = dynamic_programs.week_by_week(problem, urgent)
        total, km, _ = plan_cost(problem, choice)
        load = np.zeros_like(problem.capacity)
        np.add.at(load, problem.region, km)
        assert (load <= problem.capacity + 1e-9).all()
        assert worksites_long_enough(problem, choice) and np.isfinite(total)
        assert total >= best - 1e-9
    solution = solve(problem)
    assert solution.bound <= best + 1e-6 <= solution.cost + 2e-6
