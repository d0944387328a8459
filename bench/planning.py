"""`python -m bench.planning`: the maintenance planner in closed loop on the simulated world.

A simulated year (``simulators.truth.Truth``: the model's degradation and tamping reset)
whose tampings are decided by a policy, week by week; the world's own limit and scheduled
tampings are off. Each line is recorded by a TRC run every ``--trc-weeks`` weeks (log-space
noise sd 0.02). A reached immediate-action limit (IAL) forces an unplanned tamping a week
later. Every line's last TRC run before the year is its record at week 0 (a network has a
recording history: without it no policy knows a segment's level until its line's first run).
Policies, on the same world (paired seeds):

- ``planner``: the planning core, re-planned weekly from the live fused estimate of every
  segment, as in production: the filtering core (:class:`~services.filtering.tracker.Tracker`)
  folds every TRC record, every tamping record and ``--passes`` on-board indices a segment a
  day (the simulator's observation model ``y = H z + b + e``, whose H, b, R it is given), over
  the population's degradation posterior (the simulator's classes and spread); it tamps what
  week 0 of its plan says;
- ``planner-trc``: the same, from the last TRC record of every segment only (no on-board
  data: what the planner is worth without the fusion);
- ``point``: the same optimiser on point forecasts: the same fused estimates' means taken as
  exact, the posterior's mean parameters;
- ``threshold``: tamp (the shortest worksite around it) when the last TRC record exceeds the
  intervention limit, within its line's capacity that week (as every policy's);
- ``cycle``: each line in sections of the week's capacity, each section tamped once every
  ``--cycle-years``, the sections' weeks spread evenly over the cycle;
- ``oracle``: the planning core on the true state and the segment's true parameters.

Figures per policy (sums over the seeds): total cost, the year's cost (the planner's cost
model: tamping, possessions, days above the intervention and immediate-action limits,
unplanned tampings) plus the wear left at the year's end (the planner's wear rule on the
true levels: a policy cannot look cheap by leaving the track worn for the next year),
segment-days above the intervention and IAL limits (and of the IAL days, those ``inherited``:
of segments above the IAL at the start, until their first tamping: a policy can at best
tamp them in week 0), km tamped, possessions, TRC runs; then, per baseline, the price of a
km-day above the IAL at which the planner's runs would cost as much (:func:`break_even`).
Every tamping, planned or unplanned, reaches the planner as a maintenance record.
"""

from __future__ import annotations

import argparse
import copy
import math
import time
from collections import defaultdict

import numpy as np

from schemas import (
    DAY_S,
    INDICATORS,
    Calibration,
    DegradationPosterior,
    MaintenanceEvent,
    OnboardIndex,
    SegmentState,
    TrcRecord,
)
from services.defaults import load_network
from services.filtering.tracker import Tracker
from services.limits import DEFAULT_LIMITS_FILE, load_immediate_action, load_limits
from services.planning.core import Costs, PlanningConfig, PlanningCore, SegmentRef, week_start
from services.planning.testing import f8, make_state
from simulators.index_model import IndexSensorModel
from simulators.network import generate_network, stable_rng
from simulators.truth import Truth, load_config

START = 1_767_571_200.0  # 2026-01-05T00:00:00Z, a Monday
TRC_NOISE = 0.02
POLICIES = ("planner", "planner-trc", "point", "threshold", "cycle", "oracle")
FUSED = ("planner", "point")  # the policies that plan from the filtering core's states


def world_config() -> dict:
    cfg = copy.deepcopy(load_config())
    cfg["maintenance"]["scheduled_period_days"] = 0
    cfg["maintenance"]["interval_fraction"] = 0.0
    return cfg


def population_posterior(cfg: dict, ns: int, seed: int) -> DegradationPosterior:
    """Samples of the simulator's classes by their shares, with its segment spread."""
    rng = np.random.default_rng(seed)
    t = cfg["truth"]
    names = list(t["classes"])
    share = np.array([t["mix"].get(n, 0.0) for n in names])
    k = rng.choice(len(names), ns, p=share / share.sum())
    mu, sigma, zp, szp = [], [], [], []
    for j in range(ns):
        c = t["classes"][names[k[j]]]
        sd = np.asarray(c["sigma_sd"]) * math.exp(t["sigma_spread"] * rng.standard_normal())
        zsd = np.asarray(c["z_plus_sd"])
        mu.append(np.asarray(c["mu"]) * np.exp(t["mu_spread"] * rng.standard_normal(2)))
        sigma.append(np.array([[1, c["corr"]], [c["corr"], 1]]) * np.outer(sd, sd))
        zp.append(np.log(c["z_plus_mm"]))
        szp.append(np.array([[1, c["z_plus_corr"]], [c["z_plus_corr"], 1]]) * np.outer(zsd, zsd))
    return _posterior("net", np.array(mu), np.array(sigma), np.array(zp), np.array(szp))


def _posterior(group, mu, sigma, zp, szp) -> DegradationPosterior:
    return DegradationPosterior(
        group=group, version=1, t=START, indicators=list(INDICATORS), mu=f8(mu),
        sigma=f8(sigma), z_plus=f8(zp), sigma_z_plus=f8(szp), n_increments=1, n_levels=1,
    )  # fmt: skip


class FusedStates:
    """The filtering core on one world: fed what the network would tell it, asked weekly for
    every segment's SegmentState (the planner's input in production)."""

    def __init__(self, refs, cfg: dict, seed: int, posterior: DegradationPosterior, limits,
                 passes: int) -> None:  # fmt: skip
        self.refs = refs
        self.sids = [(r.line, r.segment) for r in refs]
        self.sensor = IndexSensorModel.from_config(cfg)
        self.passes = passes
        self.rng = stable_rng(seed, "bench-onboard")
        self.tracker = Tracker(limits.for_line, limits.levels, detect_maintenance=False)
        calibration = Calibration(
            version=1, t=START, indicators=list(INDICATORS), indices=list(INDICATORS),
            H=f8(self.sensor.H), b=f8(self.sensor.b), R=f8(self.sensor.R), n_pairs=1000,
            r2=f8([0.9, 0.9]),
        )  # fmt: skip
        self.tracker.update_models([calibration, posterior])
        self.pending: list = []

    def trc(self, rows, z_seen: np.ndarray, t: float, run_id: str) -> None:
        for i in rows:
            top, align = np.exp(z_seen[i])
            ref = self.refs[i]
            self.pending.append(TrcRecord(line=ref.line, segment=ref.segment, t=t,
                                          top6_mm=float(top), align10_mm=float(align),
                                          run_id=run_id))  # fmt: skip

    def tamping(self, event: MaintenanceEvent) -> None:
        self.pending.append(event)

    def onboard(self, z: np.ndarray, t: float) -> None:
        """``passes`` indices of every segment of the state ``z`` at ``t``, a minute apart
        (the truth steps a day at a time)."""
        for k in range(self.passes):
            at = t - 60.0 * (self.passes - 1 - k)
            y = self.sensor.indices(z, self.rng)
            for (line, segment), (top, align) in zip(self.sids, y, strict=True):
                self.pending.append(OnboardIndex(
                    line=line, segment=segment, train="T1", unit="u1", t=at,
                    top6_mm=float(top), align10_mm=float(align), speed_mps=30.0, coverage=1.0,
                ))  # fmt: skip

    def states(self) -> list[SegmentState]:
        pending, self.pending = self.pending, []
        reasons, *_ = self.tracker.fold_events(pending)
        refused = [r for r in reasons if r]
        if refused:
            raise RuntimeError(f"the filter refused {len(refused)} events: {refused[0]}")
        return self.tracker.states_of(self.sids)


def exact(state: SegmentState) -> SegmentState:
    """``state`` with its mean taken as exact (the point forecasts' input)."""
    return make_state(state.line, state.segment, state.t, mean_mm=np.exp(state.mean.array()),
                      sd_log=(1e-4, 1e-4), group=state.posterior_group)  # fmt: skip


class Loop:
    """One policy on one seed's world for ``weeks`` weeks."""

    def __init__(self, network, cfg, seed: int, policy: str, args) -> None:
        self.policy = policy
        self.args = args
        self.truth = Truth(network, cfg, START, seed)
        self.truth.log_limits = np.full_like(self.truth.log_limits, np.inf)  # no own tamping
        self.truth.tamping_due[:] = np.inf
        self.refs = [SegmentRef(line.id, seg.id, seg.length_m) for line, seg in network.segments()]
        self.km = np.array([r.length_m for r in self.refs]) / 1000.0
        self.limits = load_limits(DEFAULT_LIMITS_FILE)
        ial = load_immediate_action(DEFAULT_LIMITS_FILE, self.limits)
        il_level = self.limits.levels.index("intervention")
        self.log_il = np.log([self.limits.for_line(r.line)[il_level] for r in self.refs])
        self.log_ial = np.log([ial[self.limits.speed_class(r.line)] for r in self.refs])
        self.config = PlanningConfig(
            capacity_km_per_week=args.capacity,
            milp_s=args.milp_s,
            eps=args.eps,
            posterior_samples=args.posterior_samples,
            min_interval_weeks=args.min_interval_weeks,
            costs=Costs(risk_violation_per_km=args.risk_violation_per_km),
        )
        self.core = PlanningCore(self.config, self.limits, ial, self.refs)
        rng = stable_rng(seed, "bench-trc")
        lines = sorted({r.line for r in self.refs})
        self.trc_phase = {line: int(rng.integers(0, args.trc_weeks)) for line in lines}
        self.trc_seen = np.full((len(self.refs), 2), np.nan)
        self.trc_t = np.full(len(self.refs), np.nan)
        self.trc_rng = stable_rng(seed, "bench-trc-noise")
        self.trc_runs = 0
        self.fused: FusedStates | None = None
        if policy in ("planner", "planner-trc", "point"):
            post = population_posterior(cfg, args.samples, seed)
            if policy in FUSED:
                self.fused = FusedStates(self.refs, cfg, seed, post, self.limits, args.passes)
            if policy == "point":
                mean = lambda a: a.array().mean(axis=0, keepdims=True)  # noqa: E731
                post = _posterior("net", mean(post.mu), mean(post.sigma), mean(post.z_plus),
                                  mean(post.sigma_z_plus))  # fmt: skip
            self.core.on_posterior(post)
        elif policy == "oracle":
            t = self.truth
            for i in range(len(self.refs)):
                self.core.on_posterior(
                    _posterior(
                        f"g{i}",
                        t.mu[i][None],
                        t.sigma[i][None],
                        t.z_plus[i][None],
                        t.sigma_z_plus[i][None],
                    )
                )
        self.k = max(1, math.ceil(self.config.min_worksite_m / np.median(self.km * 1000)))
        self.unplanned_due = np.full(len(self.refs), np.inf)
        # above the IAL at the start, before any decision: no policy can spare their first days
        self.inherited = (self.truth.z > self.log_ial).any(axis=1)
        self.last_tamped = np.full(len(self.refs), -np.inf)
        self.cycle_period, self.cycle_week = self._cycle(seed)
        self.figures = defaultdict(float)

    def _cycle(self, seed: int) -> tuple[int, np.ndarray]:
        """The fixed cycle's week of every segment within its period: each line cut into
        sections of the week's capacity (whole segments, at least the shortest worksite),
        every section tamped once a period, the sections' weeks spread evenly over it in a
        random order (a network in the cycle's steady state: 1/period of it a week)."""
        period = max(1, round(self.args.cycle_years * 52))
        size = max(self.k, int(self.args.capacity // np.median(self.km)))
        line_of = [r.line for r in self.refs]
        section = np.zeros(len(self.refs), int)
        n_sections = start = 0
        for i in range(len(self.refs)):
            new_line = i == 0 or line_of[i] != line_of[i - 1]
            if new_line or (i - start) == size:
                start, n_sections = i, n_sections + 1
            section[i] = n_sections - 1
        order = stable_rng(seed, "bench-cycle").permutation(n_sections)
        return period, (order * period // n_sections)[section]

    # --- observations ----------------------------------------------------------------------

    def trc(self, week: int) -> None:
        for line, phase in self.trc_phase.items():
            # week 0: the line's last recording before the year (a network has a history)
            if week % self.args.trc_weeks != phase and week != 0:
                continue
            self.trc_runs += 1
            rows = [i for i, r in enumerate(self.refs) if r.line == line]
            z = self.truth.z[rows]
            self.trc_seen[rows] = z + TRC_NOISE * self.trc_rng.standard_normal(z.shape)
            self.trc_t[rows] = self.truth.t
            if self.fused is not None:
                self.fused.trc(rows, self.trc_seen, self.truth.t, f"{line}-w{week}")

    def feed(self) -> None:
        if self.fused is not None:
            for state in self.fused.states():
                self.core.on_state(exact(state) if self.policy == "point" else state)
            return
        sd = 1e-4 if self.policy == "oracle" else TRC_NOISE
        for i, ref in enumerate(self.refs):
            if self.policy == "oracle":
                z, t, group = self.truth.z[i], self.truth.t, f"g{i}"
            elif np.isnan(self.trc_t[i]):
                continue
            else:
                z, t, group = self.trc_seen[i], self.trc_t[i], "net"
            self.core.on_state(make_state(ref.line, ref.segment, float(t), mean_mm=np.exp(z),
                                          sd_log=(sd, sd), group=group))  # fmt: skip

    # --- decisions -----------------------------------------------------------------------

    def decide(self, week: int) -> np.ndarray:
        now = self.truth.t
        if self.policy in ("planner", "planner-trc", "point", "oracle"):
            self.feed()
            plan = self.core.plan(now)
            index = {(r.line, r.segment): i for i, r in enumerate(self.refs)}
            return np.array([index[(r.line, r.segment)] for r in plan.rows if r.week == 0], int)
        if self.policy == "threshold":
            over = np.flatnonzero((self.trc_seen > self.log_il).any(axis=1))
            recent = now - self.last_tamped < self.config.min_interval_weeks * 7 * DAY_S
            over = over[~recent[over]]
            order = over[np.argsort(-(self.trc_seen[over] - self.log_il[over]).max(axis=1))]
            chosen: set[int] = set()
            used: dict[str, float] = defaultdict(float)  # km this week, per line
            for i in order:
                line = self.refs[i].line
                site = {j for j in range(i, i + self.k) if j < len(self.refs)
                        and self.refs[j].line == line} - chosen  # fmt: skip
                km = self.km[list(site)].sum()
                if used[line] + km > self.args.capacity:  # the line's capacity, as the planner's
                    continue
                used[line] += km
                chosen |= site
            return np.array(sorted(chosen), int)
        return np.flatnonzero(self.cycle_week == week % self.cycle_period)

    # --- one week ----------------------------------------------------------------------------

    def week(self, week: int) -> None:
        self.trc(week)
        tamp = self.decide(week)
        t_mid = self.truth.t + 3.5 * DAY_S
        self.tamp(tamp, t_mid, planned=True)
        for _ in range(7):
            for done in self.truth.step():
                self.inherited[done.seg] = False
            if self.fused is not None:
                self.fused.onboard(self.truth.z, self.truth.t)
            above_il = (self.truth.z > self.log_il).any(axis=1)
            above_ial = (self.truth.z > self.log_ial).any(axis=1)
            self.figures["days_il"] += above_il.sum()
            self.figures["days_ial"] += above_ial.sum()
            self.figures["days_ial_inherited"] += (above_ial & self.inherited).sum()
            self.figures["km_days_ial"] += self.km[above_ial].sum()
            c = self.config.costs
            self.figures["cost"] += (
                c.intervention_per_km_day * self.km[above_il].sum()
                + c.immediate_action_per_km_day * self.km[above_ial].sum()
            )
            new = above_ial & np.isinf(self.unplanned_due) & np.isinf(self.truth.tamping_due)
            for i in np.flatnonzero(new):  # reached the IAL: an unplanned tamping in a week
                self.unplanned_due[i] = self.truth.t + 7 * DAY_S
                self.truth.tamping_due[i] = self.unplanned_due[i]
                self.figures["unplanned"] += 1
                self.figures["cost"] += c.unplanned_per_km * self.km[i]
                self.record_tamping(i, self.unplanned_due[i])
            self.unplanned_due[self.unplanned_due <= self.truth.t] = np.inf

    def tamp(self, rows: np.ndarray, t: float, planned: bool) -> None:
        rows = rows[np.isinf(self.truth.tamping_due[rows])]
        if not rows.size:
            return
        self.truth.tamping_due[rows] = t
        c = self.config.costs
        runs = 1 + int((np.diff(rows) != 1).sum())
        self.figures["km"] += self.km[rows].sum()
        self.figures["possessions"] += runs
        self.figures["cost"] += c.tamping_per_km * self.km[rows].sum() + c.possession * runs
        for i in rows:
            self.record_tamping(i, t)

    def record_tamping(self, i: int, t: float) -> None:
        """A tamping of segment ``i`` at ``t``, planned or not, as the maintenance record
        tells the planner (it starts the minimum interval)."""
        self.last_tamped[i] = t
        ref = self.refs[i]
        event = MaintenanceEvent(line=ref.line, segment=ref.segment, event_id=f"b{i}-{t:.0f}",
                                 t_start=t, t_end=t)  # fmt: skip
        self.core.on_maintenance(event)
        if self.fused is not None:
            self.fused.tamping(event)

    def wear_left(self) -> float:
        """What the track is worth less at the end than freshly tamped, by the planner's
        wear rule: ``wear_value`` x the tamping cost x the share of the way from the level
        after a tamping to the intervention limit (the largest over indicators, in [0, 1]).
        A policy that defers tampings past the year's end leaves this much to pay."""
        c = self.config.costs
        zp = self.truth.z_plus.mean(axis=0)
        span = np.maximum(self.log_il - zp, 1e-6)
        wear = np.clip((self.truth.z - zp) / span, 0.0, 1.0).max(axis=1)
        return float((c.wear_value * c.tamping_per_km * self.km * wear).sum())


def arguments() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=2)
    parser.add_argument("--weeks", type=int, default=52)
    parser.add_argument("--lines", type=int, default=0,
                        help="also a generated network of this many 20 km lines")  # fmt: skip
    parser.add_argument("--no-demo", action="store_true",
                        help="the generated network (--lines) only")  # fmt: skip
    parser.add_argument("--capacity", type=float, default=2.0, help="km a week per line")
    parser.add_argument("--trc-weeks", type=int, default=9)
    parser.add_argument("--cycle-years", type=float, default=4.0)
    parser.add_argument("--samples", type=int, default=64)
    parser.add_argument("--passes", type=int, default=1,
                        help="on-board indices a segment a day (the fused policies)")  # fmt: skip
    parser.add_argument("--milp-s", type=float, default=1.0, help="HiGHS time per plan")
    parser.add_argument("--policies", default=",".join(POLICIES))
    parser.add_argument(
        "--min-interval-weeks",
        type=float,
        default=PlanningConfig.min_interval_weeks,
        help="between two tampings of a segment (every policy but the cycle)",
    )
    parser.add_argument("--eps", type=float, default=PlanningConfig.eps, help="the risk limit")
    parser.add_argument("--posterior-samples", type=int, default=PlanningConfig.posterior_samples,
                        help="posterior samples the planner's forecasts mix")  # fmt: skip
    parser.add_argument("--risk-violation-per-km", type=float,
                        default=Costs.risk_violation_per_km,
                        help="a km per week late on the risk limit (0: no risk limit)")  # fmt: skip
    return parser


def main(argv: list[str] | None = None) -> int:
    args = arguments().parse_args(argv)
    cfg = world_config()
    networks = [] if args.no_demo else [("demo", load_network(None))]
    if args.lines:
        networks.append((f"{args.lines}x20km", generate_network(args.lines, 20.0, seed=7)))
    assert week_start(START) == START
    for name, network in networks:
        print(f"\n{name}: {network.n_segments} segments, {args.weeks} weeks, seeds "
              f"1..{args.seeds}, capacity {args.capacity:g} km/week a line")  # fmt: skip
        print(f"{'policy':10} {'total cost':>14} {'year':>12} {'wear left':>10} {'days>IL':>9} "
              f"{'days>IAL':>9} {'inherited':>9} {'unplanned':>9} {'km':>7} {'possessions':>11} "
              f"{'TRC runs':>8} {'s':>6}")  # fmt: skip
        totals = {}
        for policy in args.policies.split(","):
            total = totals[policy] = defaultdict(float)
            started = time.perf_counter()
            for seed in range(1, args.seeds + 1):
                loop = Loop(network, cfg, seed, policy, args)
                for week in range(args.weeks):
                    loop.week(week)
                for key, value in loop.figures.items():
                    total[key] += value
                total["trc"] += loop.trc_runs
                total["wear"] += loop.wear_left()
            print(f"{policy:10} {total['cost'] + total['wear']:14,.0f} {total['cost']:12,.0f} "
                  f"{total['wear']:10,.0f} {total['days_il']:9,.0f} "
                  f"{total['days_ial']:9,.0f} {total['days_ial_inherited']:9,.0f} "
                  f"{total['unplanned']:9,.0f} {total['km']:7.1f} "
                  f"{total['possessions']:11,.0f} {total['trc']:8,.0f} "
                  f"{time.perf_counter() - started:6.0f}")  # fmt: skip
        for line in break_even(totals, Costs().immediate_action_per_km_day):
            print(line)
    return 0


def break_even(totals: dict, price: float) -> list[str]:
    """Per baseline, the price of a km-day above the IAL at which the planner's runs would
    cost as much as the baseline's (the same decisions repriced: total cost is linear in
    it). The default prices put a day above the IAL at ``immediate_action_per_km_day``;
    what a railway pays for one (a speed restriction or a closure, every train's delay) is
    its own figure, so this says from which price on the planner is the cheaper."""
    if "planner" not in totals:
        return []
    cost = {p: t["cost"] + t["wear"] for p, t in totals.items()}
    ial = {p: t["km_days_ial"] for p, t in totals.items()}
    out = [f"the planner costs the same as a baseline at an IAL km-day of (default {price:g}):"]
    for policy in totals:
        if policy == "planner":
            continue
        extra_cost, fewer_days = cost["planner"] - cost[policy], ial[policy] - ial["planner"]
        if extra_cost <= 0:
            verdict = "cheaper already"
        elif fewer_days <= 0:
            verdict = "never (it has no fewer IAL km-days)"
        else:
            verdict = f"{price + extra_cost / fewer_days:,.0f}"
        out.append(f"  {policy:10} {verdict}")
    return out


if __name__ == "__main__":
    raise SystemExit(main())
