"""`python -m bench.planning_scale`: the maintenance plan of a national network.

100,000 segments of 200 m (``--lines`` x ``--segments-per-line``) in regions of
``--lines-per-region`` lines sharing a tamping capacity (``--capacity`` km a week), each
segment at a random age since its last tamping (``services.planning.testing.random_network``,
``--max-age``), one degradation posterior; a plan of 26 weeks. Printed: the time to the
first plan (forecasts, deadlines and costs of every segment, then the optimisation) and
its gap to the bound, the same plan with the regions solved one at a time (from cold caches),
then a re-plan after one segment's new state.

Baseline, in the same process: HiGHS's MILP over every (segment, week) option
(``services.planning.solver.compact_milp``) on the first ``--baseline`` segments of one
region of the same problem (the whole region is beyond it); the ratio compares segments
planned per second.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from services.planning import solver
from services.planning.core import PlanningConfig, PlanningCore, week_start
from services.planning.testing import T0, make_limits, make_posterior, make_state, random_network


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--lines", type=int, default=400)
    parser.add_argument("--segments-per-line", type=int, default=250)
    parser.add_argument("--lines-per-region", type=int, default=10)
    parser.add_argument("--capacity", type=float, default=2.0, help="km per week per region")
    parser.add_argument("--max-age", type=float, default=1.0)
    parser.add_argument("--weeks", type=int, default=26)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--baseline", type=int, default=500, help="segments of the baseline")
    parser.add_argument("--milp-s", type=float, default=PlanningConfig.milp_s,
                        help="the planner's milp_s: s for integer programs")  # fmt: skip
    args = parser.parse_args(argv)

    started = time.perf_counter()
    refs, states = random_network(
        args.lines, args.segments_per_line, seed=args.seed, max_age=args.max_age
    )
    regions = {f"R{k // args.lines_per_region}" for k in range(args.lines)}
    config = PlanningConfig(
        horizon_weeks=args.weeks,
        milp_s=args.milp_s,
        regions={r: args.capacity for r in regions},
        region_of_line={f"L{k + 1}": f"R{k // args.lines_per_region}" for k in range(args.lines)},
    )
    limits, ial = make_limits()
    core = PlanningCore(config, limits, ial, refs)
    core.on_posterior(make_posterior(ns=200))
    for state in states:
        core.on_state(state)
    print(f"network: {len(refs):,} segments, {len(regions)} regions "
          f"({time.perf_counter() - started:.1f} s to build)")  # fmt: skip
    solver.dp_blocks(np.zeros((1, 2)), np.array([0, 1]), np.array([1]), np.zeros(1))  # compile
    core.plan(T0 - 30 * 86400.0, weeks=2)  # compiles the forecast kernels on a small horizon

    t = time.perf_counter()
    plan = core.plan(T0)
    first = time.perf_counter() - t
    tamped = sum(r.week >= 0 for r in plan.rows)
    print(
        f"plan: {first:.1f} s for {len(refs):,} segments x {args.weeks} weeks "
        f"(optimisation {plan.seconds:.1f} s: {plan.solution.timings if plan.solution else {}})"
    )
    print(f"  {plan.status}, gap {100 * plan.gap:.3f} % to the bound; {tamped:,} segments "
          f"({sum(plan.km_per_week):.0f} km) in {plan.possessions:,} possessions; "
          f"{sum(not r.risk_met for r in plan.rows):,} segments miss the risk limit")  # fmt: skip

    # the regions solved one at a time, in the same process, from cold caches
    threads, solver.REGION_THREADS = solver.REGION_THREADS, 1
    cold = PlanningCore(config, limits, ial, refs)
    cold.on_posterior(make_posterior(ns=200))
    for state in states:
        cold.on_state(state)
    t = time.perf_counter()
    single = cold.plan(T0)
    one = time.perf_counter() - t
    solver.REGION_THREADS = threads
    print(f"  the same plan with the regions one at a time: {one:.1f} s (optimisation "
          f"{single.seconds:.1f} s, gap {100 * single.gap:.3f} %); {threads} threads: "
          f"{one / first:.2f}x faster")  # fmt: skip

    k = len(states) // 2
    core.on_state(make_state(states[k].line, states[k].segment, T0 + 3600.0, mean_mm=(9.0, 7.6)))
    t = time.perf_counter()
    again = core.plan(T0 + 3600.0)
    replan = time.perf_counter() - t
    print(f"re-plan after one segment's new state: {replan:.2f} s ({first / replan:.0f}x faster; "
          f"{again.status}, gap {100 * again.gap:.3f} %)")  # fmt: skip

    # baseline: the MILP over every (segment, week) of the first region
    planned = list(core.states)
    costs, fp = core.cost_rows(planned, week_start(T0), args.weeks)
    problem, order, _ = core.optimisation_problem(planned, costs, fp, args.weeks, None)
    blocks = np.flatnonzero(problem.region == 0)
    blocks = blocks[problem.starts[blocks + 1] <= problem.starts[blocks[0]] + args.baseline]
    sub, rows = solver.subproblem(problem, blocks)
    n_region = len(rows)
    solver.COMPACT_MAX_VARIABLES = 10**7
    t = time.perf_counter()
    found = solver.compact_milp(sub, config.target_gap, time_limit=120.0)
    base = time.perf_counter() - t
    if found is None:
        print("baseline: HiGHS found no plan in 120 s")
        return 0
    base_cost = solver.plan_cost(sub, found[0])[0]
    ours = solver.solve(sub, target_gap=config.target_gap)
    rate, base_rate = len(refs) / first, n_region / base
    print(f"baseline (HiGHS MILP over every (segment, week), {n_region:,} segments of a region):"
          f" {base:.1f} s, cost {base_cost:,.0f}, HiGHS's bound {found[1]:,.0f}; ours on it: "
          f"{ours.cost:,.0f} in {ours.seconds:.2f} s, our bound {ours.bound:,.0f}")  # fmt: skip
    print(
        f"segments planned per second: {rate:,.0f} vs baseline {base_rate:,.0f}: "
        f"{rate / base_rate:.1f}x; target <= 60 s: {'met' if first <= 60 else 'NOT met'}"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
