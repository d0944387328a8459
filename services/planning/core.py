r"""Maintenance planner core: segment states and degradation posteriors in, a tamping plan out.

Pure: no Zenoh, no clock, no I/O. Time is event time; the caller says what "now" is.

The plan covers ``horizon_weeks`` weeks; week 0 starts on the Monday 00:00 UTC at or before
"now" (so a plan's weeks stay put for a week, and a re-plan after one segment's change
recomputes that segment's costs only). Per segment ``i`` and option (tamped by the end of
week ``w``, or not in the horizon) the cost is (services/planning/README.md has the whole
formulation):

.. math::

    c_{i,w} = T_i (1 - G_i(w)) + U_i G_i(w) + \sum_{u \le w} E^{pre}_i(u)
              + \ell_i \sum_{u > w} E^{post}(u - w - 1) + V_i(w) + R_i L_i(w)

    c_{i,\varnothing} = \sum_{u < W} E^{pre}_i(u) + U_i F_i(W) + V_i(\varnothing) + R_i L_i(W)

with :math:`T_i` the tamping cost, :math:`E^{pre}_i(u)` the expected exposure cost of week
``u`` untamped: :math:`7\ell_i c_{IL}` times the probability of being above the intervention
limit at mid-week (:mod:`services.planning.risk`) and not yet tamped unplanned, plus
:math:`d\,\ell_i c_{IAL}` times the probability of reaching the immediate-action limit (IAL)
in week ``u`` (its unplanned tamping follows ``d`` = ``unplanned_delay_days`` later);
:math:`F_i(u)` the probability of reaching the IAL before the end of week ``u - 1`` (first
passage), :math:`U_i` the unplanned intervention that follows ``d`` days after a path reaches
the IAL, :math:`G_i(w) = F_i` at :math:`7w + 3.5 - d` days (0 before week 0): the paths whose
unplanned tamping comes before the planned one at mid-week ``w`` and replaces it (it resets
the segment, and the minimum interval rules the planned one out; the planned work pre-empts
the others), :math:`V` the wear value
at the horizon's end and :math:`R_i` the risk violation cost of a week late:
:math:`L_i(w) = \sum_{e_i < u \le w,\ F_i(u + 1) > \varepsilon} (1 + F_i(u + 1))`
counts the weeks after the first allowed one :math:`e_i` whose tamping would miss the risk
limit, the likelier to be at the IAL the heavier (not tamping counts as week ``W``, with
:math:`F_i(W + 1) \ge F_i(W)`). The segment's *deadline* is the last week whose tamping
keeps :math:`F \le \varepsilon`; one already past it at week 0 is tamped as early as
capacity allows.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field, fields
from typing import Any

import numpy as np

from schemas import DAY_S, INDICATORS, DegradationPosterior, MaintenanceEvent, SegmentState
from schemas.keys import SegmentId
from services.limits import Limits
from services.planning import evidence, risk
from services.planning.evidence import Evidence
from services.planning.solver import NONE, Problem, Solution, run_starts, solve

WEEK_S = 7 * DAY_S
MONDAY_OFFSET_S = 4 * DAY_S  # epoch 0 was a Thursday: Monday 00:00 UTC is 4 days later
DEFAULT_SEGMENT_M = 200.0  # length of a segment the network does not know


def _at_days(fp: np.ndarray, days: np.ndarray) -> np.ndarray:
    """First-passage rows ``fp`` (rows, W+1) at the end of weeks -1..W-1, at ``days`` after
    week 0 starts, linear between them (0 before week 0)."""
    x = np.clip(np.asarray(days, float) / 7.0, 0.0, fp.shape[1] - 1)
    lo = np.minimum(np.floor(x).astype(int), fp.shape[1] - 2)
    frac = x - lo
    out = fp[:, lo] * (1.0 - frac) + fp[:, lo + 1] * frac
    return np.where(np.asarray(days) < 0.0, 0.0, out)


def week_start(t: float) -> float:
    """Monday 00:00 UTC at or before ``t`` (epoch s)."""
    return math.floor((t - MONDAY_OFFSET_S) / WEEK_S) * WEEK_S + MONDAY_OFFSET_S


@dataclass(frozen=True)
class Costs:
    tamping_per_km: float = 20000.0
    possession: float = 8000.0
    intervention_per_km_day: float = 20.0
    immediate_action_per_km_day: float = 400.0
    unplanned_per_km: float = 60000.0
    risk_violation_per_km: float = 1e6
    wear_value: float = 1.0


@dataclass(frozen=True)
class PlanningConfig:
    """The planner's settings; :meth:`from_dict` reads ``services/defaults/planning.json5``."""

    horizon_weeks: int = 26
    eps: float = 0.05
    min_interval_weeks: float = 26.0  # the horizon: one tamping per segment in it, exactly
    min_worksite_m: float = 1000.0
    costs: Costs = field(default_factory=Costs)
    capacity_km_per_week: float | None = 2.0  # of a region `regions` does not name
    regions: Mapping[str, float | None] = field(default_factory=dict)  # region -> km/week
    region_of_line: Mapping[str, str] = field(default_factory=dict)
    budget: float | None = None
    target_gap: float = 0.01
    milp_s: float = 10.0  # s of the regions' optimisation after which no integer program starts
    unplanned_delay_days: float = 7.0  # from reaching the IAL to the unplanned tamping
    posterior_samples: int = 64
    quadrature_nodes: int = 5
    replan_quiet_s: float = 2.0
    replan_max_wait_s: float = 30.0

    def __post_init__(self) -> None:
        if not 1 <= self.horizon_weeks <= 104:
            raise ValueError(f"horizon_weeks: 1 to 104, got {self.horizon_weeks}")
        if not 0.0 < self.eps < 1.0:
            raise ValueError(f"eps: a probability in (0, 1), got {self.eps}")
        for name in ("min_interval_weeks", "min_worksite_m", "replan_quiet_s",
                     "unplanned_delay_days"):  # fmt: skip
            if not (math.isfinite(getattr(self, name)) and getattr(self, name) >= 0):
                raise ValueError(f"{name}: must be >= 0, got {getattr(self, name)}")
        if not self.replan_max_wait_s >= self.replan_quiet_s:
            raise ValueError("replan.max_wait_s: must be >= replan.quiet_s")
        for f in fields(Costs):
            value = getattr(self.costs, f.name)
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"costs.{f.name}: must be a number >= 0, got {value}")
        for name, cap in [
            ("default_km_per_week", self.capacity_km_per_week),
            *self.regions.items(),
        ]:
            if cap is not None and not (math.isfinite(cap) and cap >= 0):
                raise ValueError(f"capacity {name}: km per week >= 0 or null, got {cap}")
        unknown = set(self.region_of_line.values()) - set(self.regions)
        if unknown:
            raise ValueError(f"capacity.lines: regions {sorted(unknown)} not in capacity.regions")
        if self.budget is not None and not (math.isfinite(self.budget) and self.budget >= 0):
            raise ValueError(f"budget: >= 0 or null, got {self.budget}")
        if not (math.isfinite(self.milp_s) and self.milp_s >= 0):
            raise ValueError(f"milp_s: seconds >= 0, got {self.milp_s}")
        if not 0.0 < self.target_gap < 1.0:
            raise ValueError(f"target_gap: in (0, 1), got {self.target_gap}")
        if self.posterior_samples < 1 or self.quadrature_nodes < 1:
            raise ValueError("forecast: posterior_samples and quadrature_nodes must be >= 1")

    @classmethod
    def from_dict(cls, raw: Mapping[str, Any]) -> PlanningConfig:
        """Build from the object of ``planning.json5``; ValueError names what is wrong."""
        top = {
            "horizon_weeks", "eps", "min_interval_weeks", "min_worksite_m", "costs",
            "capacity", "budget", "target_gap", "milp_s", "forecast", "replan",
            "unplanned_delay_days",
        }  # fmt: skip
        _known("planning config", raw, top)
        try:
            kwargs: dict[str, Any] = {}
            for name in ("eps", "min_interval_weeks", "min_worksite_m", "target_gap", "milp_s",
                         "unplanned_delay_days"):  # fmt: skip
                if name in raw:
                    kwargs[name] = float(raw[name])
            if "horizon_weeks" in raw:
                kwargs["horizon_weeks"] = int(raw["horizon_weeks"])
            if raw.get("budget") is not None:
                kwargs["budget"] = float(raw["budget"])
            costs = dict(raw.get("costs", {}))
            _known("costs", costs, {f.name for f in fields(Costs)})
            kwargs["costs"] = Costs(**{k: float(v) for k, v in costs.items()})
            cap = dict(raw.get("capacity", {}))
            _known("capacity", cap, {"default_km_per_week", "regions", "lines"})
            if "default_km_per_week" in cap:
                kwargs["capacity_km_per_week"] = _opt_float(cap["default_km_per_week"])
            kwargs["regions"] = {k: _opt_float(v) for k, v in dict(cap.get("regions", {})).items()}
            kwargs["region_of_line"] = {k: str(v) for k, v in dict(cap.get("lines", {})).items()}
            forecast = dict(raw.get("forecast", {}))
            _known("forecast", forecast, {"posterior_samples", "quadrature_nodes"})
            for name in ("posterior_samples", "quadrature_nodes"):
                if name in forecast:
                    kwargs[name] = int(forecast[name])
            replan = dict(raw.get("replan", {}))
            _known("replan", replan, {"quiet_s", "max_wait_s"})
            if "quiet_s" in replan:
                kwargs["replan_quiet_s"] = float(replan["quiet_s"])
            if "max_wait_s" in replan:
                kwargs["replan_max_wait_s"] = float(replan["max_wait_s"])
        except (TypeError, ValueError) as exc:
            raise ValueError(f"planning config: {exc}") from None
        return cls(**kwargs)


def _known(where: str, raw: Mapping[str, Any], allowed: set[str]) -> None:
    unknown = set(raw) - allowed
    if unknown:
        raise ValueError(f"{where}: unknown key(s) {sorted(unknown)}; known: {sorted(allowed)}")


def _opt_float(value: Any) -> float | None:
    return None if value is None else float(value)


@dataclass(frozen=True)
class SegmentRef:
    """A segment as the network lists it: line, id, length; order along the line."""

    line: str
    segment: str
    length_m: float


@dataclass(frozen=True)
class PlannedSegment:
    """One row of a plan: a segment tamped, or one whose risk limit the plan does not meet."""

    line: str
    segment: str
    week: int  # 0-based week of the tamping; -1: not tamped in the horizon
    worksite: int  # possession id (one per run of adjacent segments and week); -1
    length_km: float
    deadline_week: int  # last week whose tamping meets the risk limit; -1 none; W: none needed
    p_reach_ial: float  # P(reaching the immediate-action limit before the tamping / horizon end)
    risk_met: bool
    cost: float  # expected cost of the chosen option
    cost_untamped: float  # expected cost of not tamping it in the horizon
    speed_class: str  # the line's speed class: the intervention and immediate-action limits


@dataclass(frozen=True)
class Plan:
    """The plan and how good it is."""

    t: float  # epoch s of the start of week 0
    horizon_weeks: int
    rows: list[PlannedSegment]
    objective: float
    bound: float
    gap: float
    status: str
    seconds: float
    km_per_week: list[float]
    possessions: int
    money: float  # tamping + possession money of the plan
    segments: int  # segments with a state and a model, planned
    without_model: int  # segments with a state but no posterior of their group yet
    solution: Solution | None = None


class PlanningCore:
    """Holds every segment's state, the posteriors and the last tampings; :meth:`plan`.

    ``network``: the segments of every line in chainage order (adjacent segments share a
    possession). A state of a segment the network does not know is planned on its own.
    """

    def __init__(
        self,
        config: PlanningConfig,
        limits: Limits,
        immediate_action: Mapping[str, np.ndarray],
        network: Iterable[SegmentRef] = (),
    ) -> None:
        il_level = limits.levels.index("intervention")
        self.config = config
        self.limits = limits
        self.immediate_action = immediate_action
        self._il_level = il_level
        self.refs: list[SegmentRef] = []
        self.index: dict[SegmentId, int] = {}
        for ref in network:
            self._add(ref)
        self.states: dict[int, SegmentState] = {}
        self.posteriors: dict[str, tuple[int, risk.Posterior]] = {}
        self.last_tamped: dict[int, float] = {}
        # per segment, the highest-ranked MaintenanceEvent of each event_id (withdrawals too)
        self.tampings: dict[int, dict[str, MaintenanceEvent]] = {}
        # per segment, the on-board evidence of its TRC intervals before the current one
        self.evidence: dict[int, Evidence] = {}
        self.evidence_changed: set[int] = set()  # not yet taken by take_changed_evidence
        self._rows: dict[int, tuple[Any, np.ndarray, np.ndarray]] = {}  # i -> (key, cost, F)
        self._solved: dict[bytes, tuple] = {}  # regions' solutions by their problem's digest
        self.version = 0  # changes that can move the plan

    def _add(self, ref: SegmentRef) -> int:
        where = (ref.line, ref.segment)
        if where not in self.index:
            self.index[where] = len(self.refs)
            self.refs.append(ref)
        return self.index[where]

    def snapshot(self) -> PlanningCore:
        """A copy of the inputs to plan from while this core goes on taking new ones.

        The segments, states, posteriors and last tampings are copied (the messages
        themselves are immutable); the caches of cost rows and of regions' solutions are
        shared, so one plan after another recomputes only what changed. Plan from one
        snapshot at a time: the caches are not locked.
        """
        frozen = copy.copy(self)
        frozen.refs = list(self.refs)
        frozen.index = dict(self.index)
        frozen.states = dict(self.states)
        frozen.posteriors = dict(self.posteriors)
        frozen.last_tamped = dict(self.last_tamped)
        frozen.evidence = dict(self.evidence)
        return frozen

    # --- inputs --------------------------------------------------------------------------

    def on_state(self, state: SegmentState) -> bool:
        """Keep a segment's newest state; True if it changed."""
        i = self.index.get((state.line, state.segment))
        if i is None:
            i = self._add(SegmentRef(state.line, state.segment, DEFAULT_SEGMENT_M))
        held = self.states.get(i)
        if held is not None and (held.t, held.posterior_version) > (
            state.t,
            state.posterior_version,
        ):
            return False
        if held == state:
            return False
        missing = [name for name in INDICATORS if name not in state.indicators]
        if missing:
            raise ValueError(f"SegmentState {state.line}/{state.segment}: lacks {missing}")
        if held is not None:
            self._close_interval(i, held, state)
        self.states[i] = state
        self.version += 1
        return True

    def _close_interval(self, i: int, held: SegmentState, new: SegmentState) -> None:
        """When ``new`` starts a TRC interval after ``held``'s, count ``held``'s log weights
        in the segment's :class:`~services.planning.evidence.Evidence`."""
        post = self.posteriors.get(held.posterior_group)
        samples = post[1].source_samples or len(post[1].mu) if post is not None else None
        if held.log_weights is not None and samples not in (None, held.log_weights.array().size):
            return  # weights over other samples than the group's posterior: not evidence
        ev = evidence.closed_interval(self.evidence.get(i), held, new)
        if ev is not None:
            self.evidence[i] = ev
            self.evidence_changed.add(i)

    def take_changed_evidence(self) -> list[tuple[str, str, Evidence]]:
        """``(line, segment, evidence)`` of the segments whose evidence changed since the
        last call (what to persist)."""
        changed, self.evidence_changed = self.evidence_changed, set()
        return [(self.refs[i].line, self.refs[i].segment, self.evidence[i]) for i in changed]

    def restore_evidence(self, items: Iterable[tuple[str, str, Evidence]]) -> None:
        """Take back evidence persisted from :meth:`take_changed_evidence`."""
        for line, segment, ev in items:
            i = self.index.get((line, segment))
            if i is None:
                i = self._add(SegmentRef(line, segment, DEFAULT_SEGMENT_M))
            self.evidence[i] = ev
        self.version += 1

    def on_posterior(self, posterior: DegradationPosterior) -> bool:
        """Keep a group's newest posterior; True if it changed."""
        held = self.posteriors.get(posterior.group)
        if held is not None and held[0] >= posterior.version:
            return False
        cols = [posterior.indicators.index(name) for name in INDICATORS]
        mu = posterior.mu.array()[:, cols]
        sigma = posterior.sigma.array()[:, cols][:, :, cols]
        zp = posterior.z_plus.array()[:, cols]
        szp = posterior.sigma_z_plus.array()[:, cols][:, :, cols]
        post = risk.Posterior.from_samples(mu, sigma, zp, szp, self.config.posterior_samples)
        self.posteriors[posterior.group] = (posterior.version, post)
        self.version += 1
        return True

    def on_maintenance(self, event: MaintenanceEvent) -> bool:
        """A tamping starts the minimum interval; True if the segment's last tamping moved.

        Of each ``event_id`` the highest-ranked message holds (``MaintenanceEvent.rank``),
        whatever the order of arrival; one that is a withdrawal (a detection filtering no
        longer makes) is no tamping. The last tamping is the latest middle of those held."""
        i = self.index.get((event.line, event.segment))
        if i is None:
            i = self._add(SegmentRef(event.line, event.segment, DEFAULT_SEGMENT_M))
        known = self.tampings.setdefault(i, {})
        held = known.get(event.event_id)
        if held is not None and event.rank <= held.rank:
            return False
        known[event.event_id] = event
        times = [0.5 * (e.t_start + e.t_end) for e in known.values() if not e.withdrawn]
        last = max(times, default=None)
        if last == self.last_tamped.get(i):
            return False
        if last is None:
            del self.last_tamped[i]
        else:
            self.last_tamped[i] = last
        self.version += 1
        return True

    # --- the plan --------------------------------------------------------------------------

    def plan(self, now_t: float, *, weeks: int | None = None, budget: float | None = None) -> Plan:
        """The plan from the week of ``now_t``; ``weeks`` and ``budget`` override the config."""
        cfg = self.config
        n_weeks = int(weeks if weeks is not None else cfg.horizon_weeks)
        if not 1 <= n_weeks <= 104:
            raise ValueError(f"weeks: 1 to 104, got {n_weeks}")
        budget = budget if budget is not None else cfg.budget
        t0 = week_start(now_t)
        planned = [
            i
            for i, s in self.states.items()
            if s.posterior_group in self.posteriors or len(self.posteriors) == 1
        ]
        without_model = len(self.states) - len(planned)
        costs, fp = self.cost_rows(planned, t0, n_weeks)
        problem, order, blocks_of_segment = self.optimisation_problem(
            planned, costs, fp, n_weeks, budget
        )
        if problem is None:
            return Plan(t0, n_weeks, self._risk_rows(planned, costs, fp, n_weeks), 0.0, 0.0,
                        0.0, "optimal", 0.0, [0.0] * n_weeks, 0, 0.0, len(planned),
                        without_model)  # fmt: skip
        solution = solve(problem, target_gap=cfg.target_gap, milp_s=cfg.milp_s, solved=self._solved)
        return self._result(
            t0, n_weeks, planned, costs, fp, problem, order, solution, without_model
        )

    def _segment_rows(self, idx: Sequence[int], t0: float, weeks: int, start=None):
        """Cost rows (len, W+1) and first-passage rows F(0..W) of segments ``idx``; ``start``
        ``(m, v, offset_days)`` replaces their states' means, variances and ages."""
        cfg, c = self.config, self.config.costs
        n = len(idx)
        m, v, offset, log_il, log_ial, km, earliest, groups = self._segment_inputs(idx, t0)
        if start is not None:
            m, v, offset = (np.asarray(a, float) for a in start)
        cost = np.empty((n, weeks + 1))
        fp_out = np.zeros((n, weeks + 1))
        week = np.arange(weeks)
        mid = 7.0 * week + 3.5
        ends = 7.0 * np.arange(weeks + 1)
        for group, rows in groups.items():
            version, post = self.posteriors[group]
            r = np.array(rows)
            w = self._weights([idx[k] for k in rows], post, version)
            tau_mid = np.maximum(offset[r, None] + mid[None, :], 0.0)
            tau_end = np.maximum(offset[r, None] + ends[None, :], 1e-6)
            p_il = risk.above_any(m[r], v[r], post, tau_mid, log_il[r], w)
            fp = np.zeros((len(r), weeks + 1))
            bound = 2.0 * risk.above_each(m[r], v[r], post, tau_end[:, -1], log_ial[r], w).sum(-1)
            hot = (bound >= risk.NEGLIGIBLE) | (not post.drift_nonnegative)
            hot |= (m[r] >= log_ial[r]).any(axis=1)
            if hot.any():
                fp[hot] = risk.first_passage(
                    m[r][hot], v[r][hot], post, tau_end[hot], log_ial[r][hot],
                    cfg.quadrature_nodes, w[hot],
                )  # fmt: skip
            fp[:, 0] = np.where((m[r] >= log_ial[r]).any(axis=1), fp[:, 0], 0.0)
            # reaching the IAL forces an unplanned tamping unplanned_delay_days later: that
            # long above the IAL, then tamped (no longer above either limit untamped)
            reset = _at_days(fp, mid - cfg.unplanned_delay_days)
            above_il = np.clip(p_il - reset, 0.0, 1.0)
            pre = km[r, None] * (
                7.0 * c.intervention_per_km_day * above_il
                + cfg.unplanned_delay_days * c.immediate_action_per_km_day * np.diff(fp, axis=1)
            )
            # after a tamping: per pair of limits (one per speed class), ages at mid-week;
            # a tamping in week w leaves W - w - 1 weeks, the first ones after a tamping
            post_sum = self._cost_after_tamping(post, log_il[r], log_ial[r], weeks, w)
            cum_pre = np.cumsum(pre, axis=1)  # cost of weeks 0..w untamped
            tamp = c.tamping_per_km * km[r]
            zp = w @ post.z_plus  # (rows, n): each segment's mixture
            mu = w @ post.mu
            span = np.maximum(log_il[r] - zp, 1e-6)
            wear_tamped = np.clip(
                (mu[:, None, :] * 7.0 * (weeks - week - 1)[None, :, None]) / span[:, None, :],
                0.0,
                1.0,
            ).max(axis=-1)
            end_mean = m[r] + mu * tau_end[:, -1:]
            wear_none = np.clip((end_mean - zp) / span, 0.0, 1.0).max(axis=-1)
            unplanned = c.unplanned_per_km * km[r]
            late = self._weeks_late(fp, earliest[r], weeks)
            violation = c.risk_violation_per_km * km[r, None] * late
            # a path whose unplanned tamping comes before week w's mid-week work pays U
            # instead of T: the unplanned work resets the segment and the minimum interval
            # then rules the planned one out
            cost_w = (
                tamp[:, None] * (1.0 - reset)
                + unplanned[:, None] * reset
                + cum_pre
                + km[r, None] * post_sum
                + c.wear_value * tamp[:, None] * wear_tamped
                + violation[:, :weeks]
            )
            cost_w[week[None, :] < earliest[r, None]] = np.inf
            cost_none = (
                cum_pre[:, -1] + unplanned * fp[:, -1] + c.wear_value * tamp * wear_none
                + violation[:, weeks]
            )  # fmt: skip
            cost[r, :weeks] = cost_w
            cost[r, weeks] = cost_none
            fp_out[r] = fp
        return cost, fp_out

    def _weeks_late(self, fp: np.ndarray, earliest: np.ndarray, weeks: int) -> np.ndarray:
        """(rows, W+1): the weeks by which a tamping in week w (column W: not in the horizon,
        counted as week W) misses the risk limit, beyond the first allowed week, each
        weighted 1 + F(u+1).

        A tamping in week u meets the limit when F(u+1) <= eps. Each week after the first
        allowed one that a tamping could not meet it in counts at least once, so a late
        tamping costs more the later it is, not tamping costs the most, and a segment that
        no allowed week can save (already past its deadline at week 0, or held off by the
        minimum interval) is still tamped as early as capacity allows, paying nothing for
        the part no plan avoids. The weight 1 + F(u+1) (1 to 2) puts first, when capacity
        cannot take every late segment, those likeliest to be at the IAL by then: a segment
        already above it before one merely past its deadline.
        """
        risk = fp[:, 1:]
        risk = np.c_[risk, risk[:, -1:]]  # after the horizon: as its last week, at least
        missed = risk > self.config.eps  # a tamping in week u misses the limit
        after_first = np.arange(weeks + 1)[None, :] > earliest[:, None]
        return np.cumsum(np.where(missed & after_first, 1.0 + risk, 0.0), axis=1)

    def _segment_inputs(self, idx: Sequence[int], t0: float):
        """Per segment of ``idx``: mean and variance of the indicators, age in days at ``t0``,
        log limits (intervention, immediate action), km, the first allowed week; and the rows
        of each posterior group."""
        cfg = self.config
        n = len(idx)
        m = np.empty((n, 2))
        v = np.empty((n, 2))
        offset = np.empty(n)
        log_il = np.empty((n, 2))
        log_ial = np.empty((n, 2))
        km = np.empty(n)
        earliest = np.zeros(n)
        groups: dict[str, list[int]] = {}
        for r, i in enumerate(idx):
            s = self.states[i]
            cols = [s.indicators.index(name) for name in INDICATORS]
            m[r] = s.mean.array()[cols]
            v[r] = np.diag(s.cov.array())[cols]
            offset[r] = (t0 - s.t) / DAY_S
            ref = self.refs[i]
            log_il[r] = np.log(self.limits.for_line(ref.line)[self._il_level])
            log_ial[r] = np.log(self.immediate_action[self.limits.speed_class(ref.line)])
            km[r] = ref.length_m / 1000.0
            last = self.last_tamped.get(i)
            if last is not None:
                due = last + cfg.min_interval_weeks * WEEK_S
                earliest[r] = math.ceil(max(0.0, (due - t0) / WEEK_S - 1.0))
            group = s.posterior_group if s.posterior_group in self.posteriors else None
            groups.setdefault(group or next(iter(self.posteriors)), []).append(r)
        return m, v, offset, log_il, log_ial, km, earliest, groups

    def _weights(self, idx: Sequence[int], post: risk.Posterior, version: int) -> np.ndarray:
        """(len(idx), S): each segment's mixture weights over ``post``'s samples, from its
        state's ``log_weights`` when they are of this posterior version (equal otherwise)."""
        out = risk.equal_weights(len(idx), post)
        for r, i in enumerate(idx):
            s = self.states[i]
            lw = evidence.log_weights(self.evidence.get(i), s, version)
            if lw is not None:
                out[r] = post.weights(lw)
        return out

    def _cost_after_tamping(self, post, log_il, log_ial, weeks: int, w) -> np.ndarray:
        """(rows, W): the limit costs a km from a tamping in week w to the horizon's end, per
        pair of limits (one pair per speed class), at mid-week ages after the tamping, under
        each segment's mixture weights ``w`` (rows, S): a tamping keeps them, as the filter
        does."""
        c = self.config.costs
        week = np.arange(weeks)
        mid = 7.0 * week + 3.5
        pairs, inverse = np.unique(np.c_[log_il, log_ial], axis=0, return_inverse=True)
        inverse = inverse.ravel()
        out = np.empty((len(log_il), weeks))
        for k, pair in enumerate(pairs):
            q_il = risk.above_any_after_tamping(post, mid, pair[:2])  # (S, W)
            q_ial = risk.above_any_after_tamping(post, mid, pair[2:])
            per_week = 7.0 * (
                c.intervention_per_km_day * q_il + c.immediate_action_per_km_day * q_ial
            )
            cum = np.c_[np.zeros(len(per_week)), np.cumsum(per_week, axis=1)]  # (S, W + 1)
            rows = inverse == k
            out[rows] = w[rows] @ cum[:, weeks - week - 1]
        return out

    def trc_value(
        self, now_t: float, *, weeks: int | None = None, nodes: int = 3, noise_sd: float = 0.02
    ) -> list[tuple[str, float, int]]:
        r"""Lines ranked by the value of a TRC run now: ``(line, value, segments)``.

        Per segment, the expected fall of its plan cost from knowing its level (to the TRC's
        log-space noise ``noise_sd``) before deciding (the expected value of sample
        information, each segment on its own; worksites and capacity are left out):

        .. math:: VOI_i = \min_k \mathbb{E}_z[c_{i,k}(z)] - \mathbb{E}_z[\min_k c_{i,k}(z)]
                  \ge 0,

        over the level now predicted by the mixture (``nodes`` x ``nodes`` Gauss-Hermite
        points of each indicator's predictive normal). A line's value is its segments' sum.
        """
        n_weeks = int(weeks if weeks is not None else self.config.horizon_weeks)
        t0 = week_start(now_t)
        planned = [
            i
            for i, s in self.states.items()
            if s.posterior_group in self.posteriors or len(self.posteriors) == 1
        ]
        if not planned:
            return []
        m = np.empty((len(planned), 2))
        v = np.empty((len(planned), 2))
        for r, i in enumerate(planned):
            s = self.states[i]
            group = s.posterior_group if s.posterior_group in self.posteriors else None
            post = self.posteriors[group or next(iter(self.posteriors))][1]
            cols = [s.indicators.index(name) for name in INDICATORS]
            tau = max(0.0, (now_t - s.t) / DAY_S)
            m[r] = s.mean.array()[cols] + post.mu.mean(axis=0) * tau
            v[r] = (np.diag(s.cov.array())[cols] + post.var.mean(axis=0) * tau
                    + post.mu.var(axis=0) * tau**2)  # fmt: skip
        x, w = np.polynomial.hermite_e.hermegauss(nodes)
        w = w / w.sum()
        offset = np.full(len(planned), (t0 - now_t) / DAY_S)
        expected = np.zeros((len(planned), n_weeks + 1))
        best = np.zeros(len(planned))
        for a in range(nodes):
            for b in range(nodes):
                z = m + np.sqrt(v) * np.array([x[a], x[b]])
                rows, _ = self._segment_rows(
                    planned, t0, n_weeks, (z, np.full_like(v, noise_sd**2), offset)
                )
                expected += w[a] * w[b] * rows
                best += w[a] * w[b] * rows.min(axis=1)
        value = np.maximum(expected.min(axis=1) - best, 0.0)
        by_line: dict[str, list[float]] = {}
        for r, i in enumerate(planned):
            by_line.setdefault(self.refs[i].line, []).append(float(value[r]))
        ranked = [(line, float(sum(vals)), len(vals)) for line, vals in by_line.items()]
        return sorted(ranked, key=lambda item: (-item[1], item[0]))

    def cost_rows(self, planned: list[int], t0: float, weeks: int):
        """Cost and first-passage rows of every planned segment, cached per segment (a row is
        recomputed when its state, posterior, last tamping, week 0 or horizon change)."""
        keys = {}
        stale = []
        for i in planned:
            s = self.states[i]
            group = s.posterior_group if s.posterior_group in self.posteriors else ""
            version = self.posteriors[group][0] if group else -1
            key = (t0, weeks, s.t, id(s), group, version, self.last_tamped.get(i))
            keys[i] = key
            held = self._rows.get(i)
            if held is None or held[0] != key:
                stale.append(i)
        if stale:
            cost, fp = self._segment_rows(stale, t0, weeks)
            for r, i in enumerate(stale):
                self._rows[i] = (keys[i], cost[r], fp[r])
        cost = np.array([self._rows[i][1] for i in planned]).reshape(len(planned), weeks + 1)
        fp = np.array([self._rows[i][2] for i in planned]).reshape(len(planned), weeks + 1)
        return cost, fp

    def optimisation_problem(self, planned, costs, fp, weeks, budget):
        """The optimisation over the blocks around the candidate segments (those for which
        some tamping week is cheaper than none, or whose risk limit needs a tamping), each
        widened by the shortest worksite on both sides along its line."""
        cfg = self.config
        if not planned:
            return None, None, None
        row_of = {i: r for r, i in enumerate(planned)}
        candidate = (costs[:, :weeks].min(axis=1) < costs[:, weeks]) | (fp[:, weeks] > cfg.eps)
        by_line: dict[str, list[int]] = {}
        for i, ref in enumerate(self.refs):
            by_line.setdefault(ref.line, []).append(i)
        seg_idx, starts, ks, regions = [], [0], [], []
        region_names: dict[str, int] = {}
        caps: list[float] = []
        for line, members in by_line.items():
            cand = np.array([i in row_of and candidate[row_of[i]] for i in members])
            if not cand.any():
                continue
            lengths = np.array([self.refs[i].length_m for i in members])
            k = int(min(len(members), max(1, math.ceil(cfg.min_worksite_m / np.median(lengths)))))
            keep = np.convolve(cand.astype(int), np.ones(2 * k - 1, int), "same") > 0
            region = cfg.region_of_line.get(line, f"line:{line}")
            if region not in region_names:
                region_names[region] = len(region_names)
                cap = cfg.regions.get(region, cfg.capacity_km_per_week)
                caps.append(np.inf if cap is None else cap)
            edges = np.flatnonzero(np.diff(np.r_[0, keep.astype(int), 0]))
            for a, b in zip(edges[::2], edges[1::2], strict=True):
                seg_idx.extend(members[a:b])
                starts.append(len(seg_idx))
                ks.append(k)
                regions.append(region_names[region])
        if not seg_idx:
            return None, None, None
        c = self.config.costs
        order = np.array(seg_idx)
        cost = np.empty((len(order), weeks + 1))
        for r, i in enumerate(order):
            if i in row_of:
                cost[r] = costs[row_of[i]]
            else:  # no state: tamped only to complete a worksite, at its tamping cost
                cost[r, :weeks] = c.tamping_per_km * self.refs[i].length_m / 1000.0
                cost[r, weeks] = 0.0
        km = np.array([self.refs[i].length_m / 1000.0 for i in order])
        problem = Problem(
            cost=cost,
            starts=np.array(starts, np.int64),
            k=np.array(ks, np.int64),
            possession=np.full(len(ks), c.possession),
            region=np.array(regions, np.int64),
            km=km,
            money=c.tamping_per_km * km,
            capacity=np.repeat(np.array(caps)[:, None], weeks, axis=1),
            budget=budget,
        )
        return problem, order, None

    def _risk_rows(self, planned, costs, fp, weeks) -> list[PlannedSegment]:
        rows = []
        for r, i in enumerate(planned):
            if fp[r, weeks] > self.config.eps:
                rows.append(self._row(i, NONE, -1, costs[r], fp[r], weeks))
        return rows

    def _row(self, i, week, worksite, cost_row, fp_row, weeks) -> PlannedSegment:
        ref = self.refs[i]
        eps = self.config.eps
        # F grows with time: the weeks whose tamping meets the limit are the first ones
        deadline = weeks if fp_row[weeks] <= eps else int((fp_row[1:] <= eps).sum()) - 1
        p = float(fp_row[weeks] if week == NONE else fp_row[week + 1])
        return PlannedSegment(
            line=ref.line,
            segment=ref.segment,
            week=int(week),
            worksite=int(worksite),
            length_km=ref.length_m / 1000.0,
            deadline_week=deadline,
            p_reach_ial=min(max(p, 0.0), 1.0),
            risk_met=p <= self.config.eps,
            cost=float(cost_row[weeks if week == NONE else week]),
            cost_untamped=float(cost_row[weeks]),
            speed_class=self.limits.speed_class(ref.line),
        )

    def _result(self, t0, weeks, planned, costs, fp, problem, order, solution, without_model):
        row_of = {i: r for r, i in enumerate(planned)}
        starts = run_starts(problem, solution.choice).astype(bool)
        worksite = np.cumsum(starts) - 1
        rows: list[PlannedSegment] = []
        in_problem = set(order.tolist())
        km_week = np.zeros(weeks)
        for r, i in enumerate(order):
            w = int(solution.choice[r])
            if w >= 0:
                km_week[w] += problem.km[r]
            cost_row = problem.cost[r]
            fp_row = fp[row_of[i]] if i in row_of else np.zeros(weeks + 1)
            if w >= 0 or fp_row[weeks] > self.config.eps:
                rows.append(self._row(i, w, worksite[r] if w >= 0 else -1, cost_row, fp_row,
                                      weeks))  # fmt: skip
        for r, i in enumerate(planned):
            if i not in in_problem and fp[r, weeks] > self.config.eps:
                rows.append(self._row(i, NONE, -1, costs[r], fp[r], weeks))
        # the segments outside the optimisation are not tamped: their cost is a constant
        outside = [row_of[i] for i in planned if i not in in_problem]
        constant = float(costs[outside, weeks].sum()) if outside else 0.0
        rows.sort(key=lambda p: (p.week if p.week >= 0 else weeks, p.line, p.segment))
        tamped = solution.choice >= 0
        money = float((problem.money * tamped).sum() + self.config.costs.possession * starts.sum())
        return Plan(
            t=t0,
            horizon_weeks=weeks,
            rows=rows,
            objective=solution.cost + constant,
            bound=solution.bound + constant,
            gap=solution.gap,
            status=solution.status,
            seconds=solution.seconds,
            km_per_week=km_week.tolist(),
            possessions=int(starts.sum()),
            money=money,
            segments=len(planned),
            without_model=without_model,
            solution=solution,
        )
