"""Alerting core: SegmentStates in, raised/cleared Alerts out; the TRC inspection plan.

Pure: no Zenoh, no clock, no I/O. Time is the event time of the messages (UTC epoch s);
"now" is whatever the caller says it is (the adapter passes the newest event time seen).

Alert kinds, per segment (an alert is identified by ``(line, segment, kind, indicator,
level)``; only transitions are emitted, never a repeat):

``exceedance``
    ``P(indicator > limit now)`` per indicator and level (alert, intervention), with
    hysteresis: raised at ``p >= raise``, cleared only at ``p <= clear`` (``clear < raise``).
``predicted_exceedance``
    the largest forecast exceedance probability of the ``level`` limit (intervention) over
    the state's forecast horizons ``<= within_days`` (30 and 90 of 30/90/180 with the
    default 90), same hysteresis. ``horizon_days`` is the first horizon whose probability
    reaches the raise threshold. The forecasts are marginal probabilities at each horizon,
    so their maximum is a lower bound of the probability of a crossing within the horizon
    (for a driftless Wiener path the crossing probability is twice the marginal one at the
    horizon, by the reflection principle). Hence the lower default thresholds, 0.3 / 0.18
    (the 0.6 clear-to-raise ratio of ``exceedance``): a marginal 0.3 is a crossing-within-
    the-horizon probability between 0.3 and about 0.6. Measured by ``bench.correctness``
    (one simulated year): 14 of 14 intervention crossings preceded (12 of 14 at 0.5), at
    about twice the raises not followed by a crossing within 90 days (29 vs 15, most of
    them on segments tamped within those 90 days).
``sudden_change``
    the normalised innovation squared of the last on-board update beyond the chi-square
    quantile with ``dof`` (m = 2) degrees of freedom at ``tail_probability`` (0.999 → 13.8):
    a new defect or a sensor fault. Cleared after ``clear_after`` consecutive updates with a
    normal NIS (states without a NIS, e.g. right after a TRC restart, do not count).
    ``probability`` is the chi-square CDF of the NIS (how unusual it is).
``stale``
    no state for more than ``stale_days`` of event time. The core has no clock:
    :meth:`AlertingCore.check_stale` compares every segment's last state time with the
    ``now_t`` it is given; the adapter calls it with :attr:`AlertingCore.newest_t`, the
    event-time **watermark** of every line (states and TRC records), so a line whose data
    stop entirely is still caught. Cleared by the segment's next state. ``probability`` is 1.

    The watermark is not the newest time seen, which one far-future record (a TRC export
    dated year 3000, a gateway's clock jump) would make "now" for every segment, raising
    ``stale`` everywhere. It is the newest time that ``k`` segments agree on: the ``k``-th
    largest of the segments' newest event times (state or TRC record), with
    ``k = min(stale.watermark_quorum (3), max(1, segments // 2))``. So one, or ``k - 1``,
    segments far ahead move nothing; a network of fewer than four segments cannot tell an
    outlier from the rest (``k = 1``: the newest time).

Probabilities: the state's own ``p_exceed`` / ``forecast_p_exceed`` (exact mixture values) are
used when the state was computed against the same limits as ours (``services.limits``);
otherwise (another limits file in filtering, or a level the state lacks) they are
recomputed from a normal approximation in log space (mean and variance for now; the 95%
interval for the forecasts) and counted in :attr:`AlertingCore.approximated`.

States older than the segment's last state are ignored (late duplicates); a state with the
same time (a re-run after a new calibration) is evaluated again but does not count as a new
on-board update for ``sudden_change``.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from datetime import UTC, datetime
from typing import Any

import numpy as np
from scipy import stats

from schemas import DAY_S, INDICATORS, Alert, MaintenanceEvent, PlanRow, SegmentState, TrcRecord
from schemas.keys import SegmentId
from services.limits import Limits
from services.runtime.event_time import NewestTimes

_Z975 = float(stats.norm.ppf(0.975))
INDICATOR_LABELS = {"top6": "Top6", "align10": "Align10"}

AlertKey = tuple[str, str, str, str, str]  # line, segment, kind, indicator, level
CONFIRM_DAYS = 30.0  # a reported tamping this close to a detected one confirms it


def _day(t: float) -> str:
    return datetime.fromtimestamp(t, UTC).strftime("%Y-%m-%d %H:%M")


def alert_key(alert: Alert) -> AlertKey:
    return (alert.line, alert.segment, alert.kind, alert.indicator, alert.level)


def _label(indicator: str) -> str:
    return INDICATOR_LABELS.get(indicator, indicator)


# --- configuration -------------------------------------------------------------------------


@dataclass(frozen=True)
class Hysteresis:
    """Raise at ``p >= raise_at``; once raised, clear only at ``p <= clear_at``."""

    raise_at: float
    clear_at: float

    def __post_init__(self) -> None:
        if not 0.0 <= self.clear_at < self.raise_at <= 1.0:
            raise ValueError(
                f"hysteresis: need 0 <= clear < raise <= 1, got raise={self.raise_at} "
                f"clear={self.clear_at}"
            )


# Marginal forecast probabilities bound the crossing probability from below: a lower raise
# threshold than ``exceedance`` (module docstring).
PREDICTED_HYSTERESIS = Hysteresis(0.3, 0.18)


@dataclass(frozen=True)
class AlertingConfig:
    """Thresholds of every alert kind and of the plan; :meth:`from_dict` reads the
    ``services/defaults/alerting.json5`` layout."""

    exceedance: Mapping[str, Hysteresis] = field(
        default_factory=lambda: {
            "alert": Hysteresis(0.5, 0.3),
            "intervention": Hysteresis(0.5, 0.3),
        }
    )
    predicted: Hysteresis = PREDICTED_HYSTERESIS
    predicted_level: str = "intervention"
    predicted_within_days: float = 90.0
    nis_tail_probability: float = 0.999
    nis_dof: int = 2
    nis_clear_after: int = 3
    stale_days: float = 21.0
    watermark_quorum: int = 3  # segments that must agree on "now" (module docstring)
    plan_level: str = "intervention"
    default_trc_interval_days: float = 70.0

    def __post_init__(self) -> None:
        if not 0.0 < self.nis_tail_probability < 1.0:
            raise ValueError(f"sudden_change.tail_probability: {self.nis_tail_probability}")
        if self.watermark_quorum < 1:
            raise ValueError(f"stale.watermark_quorum: must be >= 1, got {self.watermark_quorum}")
        if self.nis_dof < 1 or self.nis_clear_after < 1:
            raise ValueError("sudden_change: dof and clear_after must be >= 1")
        for name in ("predicted_within_days", "stale_days", "default_trc_interval_days"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name}: must be a positive number of days, got {value}")

    @property
    def nis_threshold(self) -> float:
        """Chi-square quantile: 13.8 for dof 2 at 0.999."""
        return float(stats.chi2.ppf(self.nis_tail_probability, self.nis_dof))

    @classmethod
    def from_dict(cls, raw: Mapping[str, Any]) -> AlertingConfig:
        """Build from the object of ``services/defaults/alerting.json5``; ValueError names what
        is wrong."""
        sections = {"exceedance", "predicted_exceedance", "sudden_change", "stale", "plan"}
        unknown = set(raw) - sections
        if unknown:
            raise ValueError(f"alerting config: unknown section(s) {sorted(unknown)}")

        def section(name: str, allowed: set[str]) -> dict[str, Any]:
            value = dict(raw.get(name, {}))
            extra = set(value) - allowed
            if extra:
                raise ValueError(f"alerting config: {name}: unknown key(s) {sorted(extra)}")
            return value

        try:
            kwargs: dict[str, Any] = {}
            if "exceedance" in raw:
                kwargs["exceedance"] = {
                    level: Hysteresis(float(v["raise"]), float(v["clear"]))
                    for level, v in dict(raw["exceedance"]).items()
                }
            pred = section("predicted_exceedance", {"level", "within_days", "raise", "clear"})
            if "raise" in pred or "clear" in pred:
                kwargs["predicted"] = Hysteresis(
                    float(pred.get("raise", PREDICTED_HYSTERESIS.raise_at)),
                    float(pred.get("clear", PREDICTED_HYSTERESIS.clear_at)),
                )
            if "level" in pred:
                kwargs["predicted_level"] = str(pred["level"])
            if "within_days" in pred:
                kwargs["predicted_within_days"] = float(pred["within_days"])
            sudden = section("sudden_change", {"tail_probability", "dof", "clear_after"})
            if "tail_probability" in sudden:
                kwargs["nis_tail_probability"] = float(sudden["tail_probability"])
            if "dof" in sudden:
                kwargs["nis_dof"] = int(sudden["dof"])
            if "clear_after" in sudden:
                kwargs["nis_clear_after"] = int(sudden["clear_after"])
            stale = section("stale", {"stale_days", "watermark_quorum"})
            if "stale_days" in stale:
                kwargs["stale_days"] = float(stale["stale_days"])
            if "watermark_quorum" in stale:
                kwargs["watermark_quorum"] = int(stale["watermark_quorum"])
            plan = section("plan", {"level", "default_trc_interval_days"})
            if "level" in plan:
                kwargs["plan_level"] = str(plan["level"])
            if "default_trc_interval_days" in plan:
                kwargs["default_trc_interval_days"] = float(plan["default_trc_interval_days"])
        except (KeyError, TypeError) as exc:
            raise ValueError(f"alerting config: {type(exc).__name__}: {exc}") from None
        return cls(**kwargs)


# --- per-segment memory and the TRC schedule ------------------------------------------------


@dataclass
class SegmentMemory:
    """What the core remembers of a segment: its last state and the calm-update count."""

    state: SegmentState
    calm_updates: int = 0  # consecutive normal-NIS updates since the last abnormal one


class TrcSchedule:
    """Next TRC run per line, learnt from TrcRecords.

    A run is a ``run_id``; its time is the earliest record of that run on the line. The
    typical interval of a line is the median gap between its consecutive runs (two runs at
    least), else ``default_interval_days``. The next run is the last run + that interval.
    """

    def __init__(self, default_interval_days: float = 70.0) -> None:
        self.default_interval_days = default_interval_days
        self.runs: dict[str, dict[str, float]] = {}  # line -> run_id -> start t

    def observe(self, line: str, run_id: str, t: float) -> bool:
        """Record one TRC record; True if the line's run table changed."""
        runs = self.runs.setdefault(line, {})
        if run_id in runs and runs[run_id] <= t:
            return False
        runs[run_id] = t
        return True

    def interval_days(self, line: str) -> float:
        starts = sorted(self.runs.get(line, {}).values())
        if len(starts) < 2:
            return self.default_interval_days
        return float(np.median(np.diff(starts))) / DAY_S

    def last_run_t(self, line: str) -> float | None:
        runs = self.runs.get(line)
        return max(runs.values()) if runs else None

    def next_run_t(self, line: str, fallback_last_t: float | None = None) -> float | None:
        """Last run (or ``fallback_last_t``) + typical interval; None if neither is known."""
        last = self.last_run_t(line)
        if last is None:
            last = fallback_last_t
        return None if last is None else last + self.interval_days(line) * DAY_S


# --- probabilities --------------------------------------------------------------------------


def horizon_probability(
    h_days: float | np.ndarray,
    p_now: np.ndarray,
    horizons_days: np.ndarray,
    p_forecast: np.ndarray,
) -> np.ndarray:
    """Probability of exceeding a limit before ``h_days``, per indicator.

    Piecewise-linear in the horizon through the knots ``(0, p_now)`` and
    ``(horizons_days[k], p_forecast[k])``, held constant beyond the last horizon (no
    extrapolation), then the maximum over ``[0, h]``:

    .. math:: p(h) = \\max\\Big(\\tilde p(h),\\ \\max_{h_k \\le h} p_k\\Big)

    Parameters: ``p_now`` (n,), ``horizons_days`` (h,) increasing, ``p_forecast`` (h, n).
    """
    x = np.concatenate(([0.0], np.asarray(horizons_days, float)))
    y = np.vstack((np.asarray(p_now, float)[None, :], np.asarray(p_forecast, float)))
    if np.any(np.diff(x) <= 0):
        raise ValueError(f"horizons_days: must be positive and increasing, got {x[1:]}")
    h = max(float(h_days), 0.0)
    at_h = np.array([np.interp(h, x, y[:, i]) for i in range(y.shape[1])])
    return np.maximum(at_h, y[x <= h].max(axis=0))


def _normal_sf(log_limit: np.ndarray, mean: np.ndarray, sd: np.ndarray) -> np.ndarray:
    with np.errstate(divide="ignore", invalid="ignore"):
        z = (log_limit - mean) / sd
    exact = (mean > log_limit).astype(float)
    return np.where(sd > 0, stats.norm.sf(z), exact)


# --- the core -------------------------------------------------------------------------------


class AlertingCore:
    """Per-segment alert state machine; feed it with :meth:`on_state`, :meth:`on_trc` and
    :meth:`check_stale`, read :attr:`raised` and :meth:`plan`.

    Every method returns the Alerts it emits (transitions only), in a deterministic order.
    """

    def __init__(self, config: AlertingConfig, limits: Limits) -> None:
        for level in (*config.exceedance, config.predicted_level, config.plan_level):
            if level not in limits.levels:
                raise ValueError(f"alerting config: level {level!r} not in limits {limits.levels}")
        self.config = config
        self.limits = limits
        self.raised: dict[AlertKey, Alert] = {}
        self.segments: dict[SegmentId, SegmentMemory] = {}
        # per segment, the highest-ranked detected MaintenanceEvent of each event_id
        # (MaintenanceEvent.rank): a withdrawal held there voids its detection in any order
        self.detections: dict[SegmentId, dict[str, MaintenanceEvent]] = {}
        self.schedule = TrcSchedule(config.default_trc_interval_days)
        self._times = NewestTimes(config.watermark_quorum)
        self.approximated = 0  # probabilities recomputed because the state's limits differ
        self._nis_threshold = config.nis_threshold
        self._stale_s = config.stale_days * DAY_S
        self._stale_due = math.inf  # no segment can be stale before this event time

    # --- inputs --------------------------------------------------------------------------

    def on_state(self, state: SegmentState) -> list[Alert]:
        """Evaluate one state; the raised/cleared transitions it causes."""
        where = (state.line, state.segment)
        memory = self.segments.get(where)
        if memory is not None and state.t < memory.state.t:
            return []  # a late duplicate: the newer state already decided
        new_update = memory is None or state.t > memory.state.t
        previous_t = state.t if memory is None else memory.state.t
        if memory is None:
            memory = self.segments[where] = SegmentMemory(state)
        memory.state = state
        self._times.note(where, state.t)
        self._stale_due = min(self._stale_due, state.t + self._stale_s)

        out: list[Alert] = []
        stale = self.raised.get((*where, "stale", "", ""))
        if stale is not None and new_update:
            days = (state.t - previous_t) / DAY_S
            out += self._clear(stale, state.t, 1.0, f"Data again after {days:.0f} days")
        for level, hyst in self.config.exceedance.items():
            out += self._exceedance(state, level, hyst)
        out += self._predicted(state)
        out += self._sudden(state, memory, new_update)
        return out

    def on_maintenance(self, event: MaintenanceEvent) -> list[Alert]:
        """A detected tamping raises ``detected_maintenance`` for an operator to confirm; a
        reported tamping of the segment within ``CONFIRM_DAYS`` of it clears it, and so does
        filtering's withdrawal of the segment's last detection still held.

        Of each detected ``event_id`` the highest-ranked message holds (:attr:`detections`):
        a detection that arrives after its withdrawal raises nothing, one found again
        (a higher revision) raises again."""
        key = (event.line, event.segment, "detected_maintenance", "", "")
        held = self.raised.get(key)
        if event.detected:
            if not self._hold_detection(event):
                return []
            if event.withdrawn:
                standing = self.detections[(event.line, event.segment)].values()
                if held is None or any(not e.withdrawn for e in standing):
                    return []
                return self._clear(
                    held,
                    max(held.t, event.t_end),
                    0.0,
                    f"Withdrawn: the on-board data no longer show {event.event_id}",
                )
            if held is not None:
                return []
            alert = Alert(
                line=event.line,
                segment=event.segment,
                t=event.t_end,
                kind="detected_maintenance",
                status="raised",
                indicator="",
                level="",
                probability=1.0,
                message=(
                    f"Tamping detected in the on-board data between {_day(event.t_start)} and "
                    f"{_day(event.t_end)}, not reported: confirm with a maintenance record "
                    f"({event.event_id})"
                ),
            )
            self.raised[key] = alert
            return [alert]
        middle = 0.5 * (event.t_start + event.t_end)
        if held is None or abs(middle - held.t) > CONFIRM_DAYS * DAY_S:
            return []
        return self._clear(held, max(held.t, event.t_end), 1.0, f"Reported: {event.event_id}")

    def _hold_detection(self, event: MaintenanceEvent) -> bool:
        """Keep ``event`` if it outranks what is held of its ``event_id``; True if it did."""
        known = self.detections.setdefault((event.line, event.segment), {})
        prior = known.get(event.event_id)
        if prior is not None and event.rank <= prior.rank:
            return False
        known[event.event_id] = event
        return True

    def on_trc(self, record: TrcRecord) -> bool:
        """Learn the line's TRC schedule; True if it changed (to persist)."""
        self._times.note((record.line, record.segment), record.t)
        return self.schedule.observe(record.line, record.run_id, record.t)

    def check_stale(self, now_t: float) -> list[Alert]:
        """Raise ``stale`` for every segment whose last state is older than ``stale_days``."""
        if now_t < self._stale_due:
            return []
        out: list[Alert] = []
        due = math.inf
        for (line, segment), memory in sorted(self.segments.items()):
            key = (line, segment, "stale", "", "")
            if key in self.raised:
                continue
            last = memory.state.t
            if now_t - last > self._stale_s:
                days = (now_t - last) / DAY_S
                out += self._raise(
                    memory.state,
                    now_t,
                    "stale",
                    "",
                    "",
                    1.0,
                    f"No data for {days:.0f} days (stale after {self.config.stale_days:g})",
                )
            else:
                due = min(due, last + self._stale_s)
        self._stale_due = due
        return out

    def restore(
        self,
        raised: Iterable[Alert],
        segments: Iterable[SegmentMemory],
        trc_runs: Iterable[tuple[str, str, float]],
        detections: Iterable[MaintenanceEvent] = (),
    ) -> None:
        """Reload what :attr:`raised`, :attr:`segments`, the schedule and
        :attr:`detections` held (a restart)."""
        for event in detections:
            self._hold_detection(event)
        for alert in raised:
            self.raised[alert_key(alert)] = alert
        for memory in segments:
            self.segments[(memory.state.line, memory.state.segment)] = memory
            self._times.note((memory.state.line, memory.state.segment), memory.state.t)
            self._stale_due = min(self._stale_due, memory.state.t + self._stale_s)
        for line, run_id, t in trc_runs:
            self.schedule.observe(line, run_id, t)
            self._times.note((line, ""), t)  # the run's segments are not stored: its line stands in

    # --- outputs -------------------------------------------------------------------------

    def implied(self, state: SegmentState) -> dict[AlertKey, bool | None]:
        """What ``state`` alone decides of its segment's exceedance and predicted alerts, by
        key: True raised (p at or above the raise threshold), False not (at or below the
        clear threshold), None either (between them, the segment's history decides). The
        raised set of a core whose newest state of the segment is ``state`` agrees with
        every True and False, whatever states came before (the check ``bench.chaos`` runs
        on the alerts)."""
        out: dict[AlertKey, bool | None] = {}

        def verdict(p: float, hyst: Hysteresis) -> bool | None:
            return True if p >= hyst.raise_at else False if p <= hyst.clear_at else None

        for level, hyst in self.config.exceedance.items():
            _, p_now, _, names = self._probabilities(state, level)
            for i, name in enumerate(names):
                key = (state.line, state.segment, "exceedance", name, level)
                out[key] = verdict(float(p_now[i]), hyst)
        level, hyst = self.config.predicted_level, self.config.predicted
        _, _, p_fc, names = self._probabilities(state, level)
        within = state.horizons_days.array() <= self.config.predicted_within_days
        for i, name in enumerate(names):
            key = (state.line, state.segment, "predicted_exceedance", name, level)
            out[key] = verdict(float(p_fc[within, i].max()), hyst) if within.any() else False
        return out

    def raised_alerts(self, line: str | None = None) -> list[Alert]:
        """The currently raised alerts (their raise messages), by line, segment, kind."""
        return [a for k, a in sorted(self.raised.items()) if line is None or a.line == line]

    def next_trc_t(self, line: str) -> float:
        """Expected next TRC run of ``line`` (epoch s).

        Last run seen on ``{ns}/trc/**`` (else the newest ``last_trc_t`` of the line's
        states, else the newest event time) + the typical interval (default 70 days). A run
        that is overdue is expected now (the newest event time).
        """
        fallback = max(
            (
                m.state.last_trc_t
                for (ln, _), m in self.segments.items()
                if ln == line and m.state.last_trc_t is not None
            ),
            default=self.newest_t,
        )
        next_t = self.schedule.next_run_t(line, fallback)
        now = self.newest_t if self.newest_t is not None else 0.0
        return now if next_t is None else max(next_t, now)

    def plan(
        self, next_trc_t: Mapping[str, float] | None = None, *, line: str | None = None
    ) -> list[PlanRow]:
        """The TRC inspection plan: segments ranked by the probability of exceeding the
        ``plan.level`` limit (any indicator) before the line's next TRC run.

        ``next_trc_t`` overrides the learnt schedule per line (epoch s). The probability is
        :func:`horizon_probability` at ``next_trc_t - state.t`` days.
        """
        given = dict(next_trc_t or {})
        next_by_line: dict[str, float] = {}
        rows: list[PlanRow] = []
        level = self.config.plan_level
        for (ln, segment), memory in self.segments.items():
            if line is not None and ln != line:
                continue
            if ln not in next_by_line:
                next_by_line[ln] = given[ln] if ln in given else self.next_trc_t(ln)
            state = memory.state
            limit, p_now, p_fc, names = self._probabilities(state, level)
            horizon = max(next_by_line[ln] - state.t, 0.0) / DAY_S
            p = horizon_probability(horizon, p_now, state.horizons_days.array(), p_fc)
            i = int(np.argmax(p))
            rows.append(
                PlanRow(
                    line=ln,
                    segment=segment,
                    probability=float(np.clip(p[i], 0.0, 1.0)),
                    indicator=names[i],
                    level=level,
                    limit_mm=float(limit[i]),
                    next_trc_t=next_by_line[ln],
                    horizon_days=horizon,
                    p_now=float(p_now[i]),
                    state_t=state.t,
                    estimate_mm=float(np.exp(state.mean.array()[i])),
                    ci_low_mm=float(state.ci_low_mm.array()[i]),
                    ci_high_mm=float(state.ci_high_mm.array()[i]),
                    speed_class=self.limits.speed_class(ln),
                )
            )
        rows.sort(key=lambda r: (-r.probability, r.line, r.segment))
        return rows

    # --- alert kinds ---------------------------------------------------------------------

    def _exceedance(self, state: SegmentState, level: str, hyst: Hysteresis) -> list[Alert]:
        limit, p_now, _, names = self._probabilities(state, level)
        band = self.limits.describe(state.line)
        out: list[Alert] = []
        for i, name in enumerate(names):
            p = float(p_now[i])
            key = (state.line, state.segment, "exceedance", name, level)
            what = f"{_label(name)} {{}} {level} limit {limit[i]:.1f} mm (p={p:.2f}), {band}"
            if key in self.raised:
                if p <= hyst.clear_at:
                    out += self._clear(self.raised[key], state.t, p, what.format("back below"))
            elif p >= hyst.raise_at:
                out += self._raise(
                    state, state.t, "exceedance", name, level, p, what.format("likely above")
                )
        return out

    def _predicted(self, state: SegmentState) -> list[Alert]:
        level, hyst = self.config.predicted_level, self.config.predicted
        limit, _, p_fc, names = self._probabilities(state, level)
        band = self.limits.describe(state.line)
        horizons = state.horizons_days.array()
        within = horizons <= self.config.predicted_within_days
        if not within.any():
            return []
        p_fc, horizons = p_fc[within], horizons[within]
        out: list[Alert] = []
        for i, name in enumerate(names):
            p_max = float(p_fc[:, i].max())
            key = (state.line, state.segment, "predicted_exceedance", name, level)
            if key in self.raised:
                if p_max <= hyst.clear_at:
                    msg = (
                        f"{_label(name)} no longer forecast above {level} limit "
                        f"{limit[i]:.1f} mm within {self.config.predicted_within_days:g} days "
                        f"(p={p_max:.2f}), {band}"
                    )
                    out += self._clear(self.raised[key], state.t, p_max, msg)
            elif p_max >= hyst.raise_at:
                k = int(np.argmax(p_fc[:, i] >= hyst.raise_at))
                h, p = float(horizons[k]), float(p_fc[k, i])
                msg = (
                    f"{_label(name)} likely above {level} limit {limit[i]:.1f} mm "
                    f"within {h:g} days (p={p:.2f}), {band}"
                )
                out += self._raise(
                    state, state.t, "predicted_exceedance", name, level, p, msg, horizon_days=h
                )
        return out

    def _sudden(self, state: SegmentState, memory: SegmentMemory, new_update: bool) -> list[Alert]:
        if state.nis is None or not new_update:
            return []
        key = (state.line, state.segment, "sudden_change", "", "")
        nis, threshold = state.nis, self._nis_threshold
        p = float(stats.chi2.cdf(nis, self.config.nis_dof))
        if nis > threshold:
            memory.calm_updates = 0
            if key in self.raised:
                return []
            msg = (
                f"Sudden change: NIS {nis:.1f} > {threshold:.1f} (chi-square, "
                f"{self.config.nis_dof} dof, tail {1 - self.config.nis_tail_probability:g}): "
                "a new defect or a sensor fault"
            )
            return self._raise(state, state.t, "sudden_change", "", "", p, msg)
        memory.calm_updates += 1
        if key in self.raised and memory.calm_updates >= self.config.nis_clear_after:
            msg = f"Sudden change over: {memory.calm_updates} normal updates (NIS {nis:.1f})"
            return self._clear(self.raised[key], state.t, p, msg)
        return []

    # --- helpers -------------------------------------------------------------------------

    def _probabilities(
        self, state: SegmentState, level: str
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[str]]:
        """(limit_mm (n,), p_now (n,), p_forecast (h, n), indicator names) for ``level``.

        Indicators without a configured limit are left out.
        """
        ours = self.limits.for_line(state.line)[self.limits.levels.index(level)]
        cols = [i for i, name in enumerate(state.indicators) if name in INDICATORS]
        names = [state.indicators[i] for i in cols]
        limit = np.array([ours[INDICATORS.index(name)] for name in names])
        if level in state.limit_levels:
            j = state.limit_levels.index(level)
            if np.allclose(state.limits_mm.array()[j, cols], limit, rtol=1e-9, atol=1e-12):
                p_now = state.p_exceed.array()[j, cols]
                p_fc = state.forecast_p_exceed.array()[:, j, cols]
                return limit, p_now, p_fc, names
        self.approximated += 1
        log_limit = np.log(limit)
        mean = state.mean.array()[cols]
        sd = np.sqrt(np.clip(np.diag(state.cov.array())[cols], 0.0, None))
        p_now = _normal_sf(log_limit, mean, sd)
        f_mean = state.forecast_mean.array()[:, cols]
        lo = state.forecast_ci_low_mm.array()[:, cols]
        hi = state.forecast_ci_high_mm.array()[:, cols]
        f_sd = (np.log(hi) - np.log(lo)) / (2 * _Z975)
        return limit, p_now, _normal_sf(log_limit, f_mean, f_sd), names

    @property
    def newest_t(self) -> float | None:
        """The event-time watermark: the newest time ``k`` segments agree on (module
        docstring, ``stale``); None before any data."""
        k = min(self.config.watermark_quorum, max(1, len(self._times) // 2))
        return self._times.kth(k)

    def _raise(
        self,
        state: SegmentState,
        t: float,
        kind: Any,
        indicator: str,
        level: str,
        p: float,
        message: str,
        horizon_days: float | None = None,
    ) -> list[Alert]:
        alert = Alert(
            line=state.line,
            segment=state.segment,
            t=t,
            kind=kind,
            status="raised",
            indicator=indicator,
            level=level,
            probability=min(max(p, 0.0), 1.0),
            horizon_days=horizon_days,
            message=message,
            speed_class=self.limits.speed_class(state.line) if level else "",
        )
        self.raised[alert_key(alert)] = alert
        return [alert]

    def _clear(self, raised: Alert, t: float, p: float, message: str) -> list[Alert]:
        del self.raised[alert_key(raised)]
        return [
            Alert(
                line=raised.line,
                segment=raised.segment,
                t=t,
                kind=raised.kind,
                status="cleared",
                indicator=raised.indicator,
                level=raised.level,
                probability=min(max(p, 0.0), 1.0),
                horizon_days=raised.horizon_days,
                message=message,
                speed_class=raised.speed_class,
            )
        ]
