"""Per-segment live filtering as a pure function of events (no Zenoh, no clock, no I/O).

Each segment keeps the log of the events that can still change its state and, when the
models allow, the filter bank of its ``Ns`` posterior samples (paper Eq. 7-13). The state is
always the fold of :func:`apply_event` over the log in canonical order with the current
models, so the order in which events arrive, duplicates, and when the models arrive do not
change it:

- **Canonical order** of a log: ``(t, kind priority, identity)`` with the priority
  ``restart < tamping < index`` for equal times; identities are ``(run_id, t)`` for a TRC
  record, ``event_id`` for a tamping and ``(train, unit, t)`` for an on-board index. A second
  event with an identity already in the log is a duplicate and is ignored (the first wins).
- **Log window**: every event at or after the segment's latest TRC record (every event while
  there is none). A TRC record drops the events before it; an event older than the latest
  TRC record cannot change the state and is refused (``accepted`` False, reason given).
- **Incremental or replay**: an event after the last one of the log is applied to the
  current state; a late one is inserted and the log replayed from its start. Both run the
  same fold, so they give bit-identical arrays.
- **Events** (time in the maths is days, ``t_s / 86400``):

  * ``TrcRecord``: restart, ``z = ln [top6_mm, align10_mm]`` in every sample, ``P = 0``.
  * ``MaintenanceEvent`` (tamping): at ``t_start`` if ``t_start == t_end``, else at the
    mid-point ``(t_start + t_end) / 2`` (the paper's mid-interval rule, Eq. 2). The filter
    predicts to that time with ``tamping_age = 0``, i.e. resets to ``(z+, Sigma_z+)`` of
    each sample; the next event then degrades from there (Eq. 7-8 with the tamping age).
    A tamping also starts a state on a segment without any TRC record yet.
  * ``OnboardIndex``: predict to ``t`` and update with ``y = ln [top6_mm, align10_mm]``
    (Eq. 9-12, Joseph form), and add each sample's log-likelihood of ``y`` to its log
    weight (below).

- **Mixture weights** (a departure from Eq. 13's equal weights ``1 / Ns``): the posterior
  samples ``j`` are the segment's line (or network) pooled degradation posterior, so a
  segment degrading faster than its pool would be forecast with the pool's drift. Each
  state therefore carries ``log_w[j] = sum_k log N(nu_jk; 0, S_jk)`` over its on-board
  updates since the last TRC restart (innovation ``nu``, innovation covariance ``S`` of
  sample ``j``; the Kalman prediction error decomposition of the likelihood of the
  segment's own data), and the summaries weight sample ``j`` by
  ``w_j ∝ exp(log_w[j])`` (``mixture.weights_from_log``): Bayes' rule on the equally
  likely samples. A TRC restart resets ``log_w`` to 0 (equal weights), a tamping keeps it
  (the data still speak for the segment's parameters), a tamping that starts a state
  starts it at 0. ``log_w`` is part of the fold, so it is as deterministic as ``z, P``
  and is rebuilt by the same replay (nothing extra is stored).

- **Not publishable yet** (events are kept, no state is output): no TRC record or tamping
  to start from, no degradation posterior for the segment, or an on-board index in the log
  while there is no calibration. Indices before the first start of a segment without a
  TRC record are kept in the log but skipped by the fold (there is nothing to update).
- **Models**: one Calibration (``H, b, R``) and DegradationPosteriors per group. A segment
  uses the most specific group available: ``seg.{line}.{segment}``, then ``line.{line}``,
  then ``net``. A model with a version not newer than the one held is ignored. A new
  calibration re-runs every segment, a new posterior the segments that now use its group.
- ``nis`` is the mean over samples of the per-sample NIS of the last update since the start
  of the state (a tamping keeps it; a TRC restart clears it to None), weighted by the
  mixture weights before that update (the predictive distribution the index is checked
  against); ``n_updates`` counts the updates since the last TRC record (or since the
  tamping that started the state).

:class:`Tracker` keeps the per-segment tracks in a dict and the models; its :meth:`step`
returns a :class:`Step` (accepted or not, why, and the SegmentStates to publish).
"""

from __future__ import annotations

import bisect
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field, fields, replace
from typing import Any

import numpy as np

from schemas import (
    INDICATORS,
    Calibration,
    DegradationPosterior,
    MaintenanceEvent,
    NDArray,
    OnboardIndex,
    SegmentState,
    TrcRecord,
)
from services.filtering.bank import ObservationModel, update_unchecked
from services.filtering.degradation import DegradationParams, transition_unchecked
from services.filtering.mixture import MixtureSummary, summarize, weights_from_log

DAY_S = 86400.0
HORIZONS_DAYS = (30.0, 90.0, 180.0)
RESTART, TAMPING, INDEX = 0, 1, 2  # kind priority at equal times
KIND_NAMES = {RESTART: "trc", TAMPING: "maintenance", INDEX: "index"}

SegmentId = tuple[str, str]  # (line, segment)
EventMessage = OnboardIndex | TrcRecord | MaintenanceEvent
ModelMessage = Calibration | DegradationPosterior


@dataclass(frozen=True)
class Event:
    """One segment event in the core's terms; ``order`` is its canonical sort key."""

    kind: int  # RESTART, TAMPING or INDEX
    t_s: float  # epoch s of the event (a tamping's assumed time)
    identity: tuple[Any, ...]
    value: np.ndarray | None  # z of a restart or y of an index (log mm), None for a tamping
    message: EventMessage

    @property
    def order(self) -> tuple[float, int, tuple[Any, ...]]:
        return (self.t_s, self.kind, self.identity)

    @property
    def t_days(self) -> float:
        return self.t_s / DAY_S


def tamping_time(msg: MaintenanceEvent) -> float:
    """Epoch s the filter assumes for a tamping: known time, else mid-interval (Eq. 2)."""
    if msg.t_start == msg.t_end:
        return msg.t_start
    return 0.5 * (msg.t_start + msg.t_end)


def event_of(msg: EventMessage) -> Event:
    """The core's event for a decoded message."""
    match msg:
        case OnboardIndex():
            y = np.log([msg.top6_mm, msg.align10_mm])
            return Event(INDEX, msg.t, ("index", msg.train, msg.unit, msg.t), y, msg)
        case TrcRecord():
            z = np.log([msg.top6_mm, msg.align10_mm])
            return Event(RESTART, msg.t, ("trc", msg.run_id, msg.t), z, msg)
        case MaintenanceEvent():
            return Event(TAMPING, tamping_time(msg), ("maintenance", msg.event_id), None, msg)
    raise TypeError(f"not a segment event: {type(msg).__name__}")


@dataclass(frozen=True)
class Models:
    """The latest calibration and degradation posteriors (by group), as the core uses them."""

    calibration: Calibration | None = None
    observation: ObservationModel | None = None
    posteriors: Mapping[str, DegradationPosterior] = field(default_factory=dict)
    params: Mapping[str, DegradationParams] = field(default_factory=dict)

    def group_for(self, line: str, segment: str) -> str | None:
        """The most specific posterior group available for the segment, or None."""
        for group in (f"seg.{line}.{segment}", f"line.{line}", "net"):
            if group in self.params:
                return group
        return None


def with_model(models: Models, msg: ModelMessage) -> Models | None:
    """``models`` with ``msg`` in it, or None if ``msg`` is not newer than the one held."""
    match msg:
        case Calibration():
            held = models.calibration
            if held is not None and msg.version <= held.version:
                return None
            if tuple(msg.indicators) != INDICATORS:
                raise ValueError(f"Calibration: indicators {msg.indicators} != {INDICATORS}")
            observation = ObservationModel(msg.H.array(), msg.b.array(), msg.R.array())
            return replace(models, calibration=msg, observation=observation)
        case DegradationPosterior():
            held_p = models.posteriors.get(msg.group)
            if held_p is not None and msg.version <= held_p.version:
                return None
            if tuple(msg.indicators) != INDICATORS:
                raise ValueError(f"DegradationPosterior: indicators {msg.indicators}")
            params = DegradationParams(
                msg.mu.array(), msg.sigma.array(), msg.z_plus.array(), msg.sigma_z_plus.array()
            )
            return replace(
                models,
                posteriors={**models.posteriors, msg.group: msg},
                params={**models.params, msg.group: params},
            )
    raise TypeError(f"not a model: {type(msg).__name__}")


@dataclass(frozen=True)
class Filtered:
    """The filter bank of one segment after the last event of its log."""

    z: np.ndarray  # (Ns, n)
    P: np.ndarray  # (Ns, n, n)
    t_s: float  # epoch s of the last applied event
    last_trc_t: float | None
    n_updates: int
    nis: float | None
    log_w: np.ndarray  # (Ns,) log-likelihood of the on-board data since the TRC restart


def apply_event(
    state: Filtered | None, event: Event, params: DegradationParams, obs: ObservationModel | None
) -> Filtered | None:
    r"""One step of the fold (paper Eq. 2, 7-12), vectorised over the ``Ns`` samples.

    An index also adds each sample's log-likelihood of it to the log weights,

    .. math::

        \log w_j \mathrel{+}= \log \mathcal N(\nu_j; 0, S_j), \qquad
        \nu_j = y - H \hat z^j_{k|k-1} - b, \quad S_j = H P^j_{k|k-1} H^T + R,

    which a TRC restart resets to 0 (equal weights).

    Returns None while nothing has started the state (an index before any start).
    ``obs`` must not be None for an index on a started state (the caller checks it).
    """
    ns, n = params.ns, params.n
    if event.kind == RESTART:
        z = np.broadcast_to(event.value, (ns, n)).copy()
        return Filtered(z, np.zeros((ns, n, n)), event.t_s, event.t_s, 0, None, np.zeros(ns))
    if state is None:
        if event.kind == INDEX:
            return None
        z, P = np.zeros((ns, n)), np.zeros((ns, n, n))
        state = Filtered(z, P, event.t_s, None, 0, None, np.zeros(ns))
    dt = (event.t_s - state.t_s) / DAY_S
    if event.kind == TAMPING:
        z, P = transition_unchecked(state.z, state.P, params, dt, 0.0)
        return replace(state, z=z, P=P, t_s=event.t_s)
    assert obs is not None
    z, P = transition_unchecked(state.z, state.P, params, dt)
    z, P, nis, loglik = update_unchecked(z, P, event.value, obs.H, obs.b, obs.R, loglik=True)
    nis_mean = float(weights_from_log(state.log_w) @ nis)
    return Filtered(
        z, P, event.t_s, state.last_trc_t, state.n_updates + 1, nis_mean, state.log_w + loglik
    )


@dataclass(frozen=True)
class Track:
    """One segment: its event log (canonical order), the filter state, the models it used."""

    line: str
    segment: str
    log: tuple[Event, ...] = ()
    trc_t: float | None = None  # epoch s of the latest TRC record: the log's lower bound
    state: Filtered | None = None
    group: str | None = None  # posterior group of ``state``


def _fold(track: Track, models: Models, events: Iterable[Event], start: Filtered | None):
    """Fold ``events`` from ``start``; (state, group) or (None, group) if not publishable."""
    group = models.group_for(track.line, track.segment)
    if group is None:
        return None, group
    params, obs = models.params[group], models.observation
    state = start
    for event in events:
        if event.kind == INDEX and obs is None and state is not None:
            return None, group  # an update to make without a calibration
        state = apply_event(state, event, params, obs)
    return state, group


def replay(track: Track, models: Models) -> Track:
    """The track with its state recomputed from the start of its log."""
    state, group = _fold(track, models, track.log, None)
    return replace(track, state=state, group=group)


def add_event(track: Track, event: Event) -> tuple[Track, str]:
    """Insert ``event`` into the log (state untouched): ``(track, "")`` or ``(track, reason)``."""
    if track.trc_t is not None and event.t_s < track.trc_t:
        return track, "older than the latest TRC record"
    if any(e.identity == event.identity for e in track.log):
        return track, "duplicate"
    log, trc_t = track.log, track.trc_t
    if event.kind == RESTART:
        log = tuple(e for e in log if e.t_s >= event.t_s)  # a restart forgets what precedes it
        trc_t = event.t_s if trc_t is None else max(trc_t, event.t_s)
    at = bisect.bisect([e.order for e in log], event.order)
    return replace(track, log=(*log[:at], event, *log[at:]), trc_t=trc_t), ""


def step_segment(track: Track, event: Event, models: Models) -> tuple[Track, str]:
    """Add one event to a segment and bring its state up to date: ``(track, reason)``.

    ``reason`` is empty when the event was accepted, else why it was refused.
    """
    new, reason = add_event(track, event)
    if reason:
        return track, reason
    if new.log[-1] is event and (event.kind == RESTART or track.state is not None):
        # ``track.state`` is the fold of the log before ``event``: one more step of it.
        state, group = _fold(new, models, (event,), track.state)
        return replace(new, state=state, group=group), ""
    return replay(new, models), ""


@dataclass(frozen=True)
class Step:
    """What one message did: accepted (else ``reason``), and the states to publish."""

    accepted: bool
    reason: str = ""
    states: tuple[SegmentState, ...] = ()


class Tracker:
    """Every segment's :class:`Track` (dict by ``(line, segment)``) and the models.

    Parameters
    ----------
    limits_mm
        ``limits_mm(line) -> (L, n)`` mm, e.g. ``services.limits.Limits.for_line``.
    limit_levels
        The ``L`` level names, e.g. ``Limits.levels``.
    horizons_days
        Forecast horizons.
    """

    def __init__(
        self,
        limits_mm,
        limit_levels: Iterable[str],
        horizons_days: Iterable[float] = HORIZONS_DAYS,
    ) -> None:
        self.tracks: dict[SegmentId, Track] = {}
        self.models = Models()
        self._limits_mm = limits_mm
        self.limit_levels = list(limit_levels)
        self.horizons_days = np.asarray(tuple(horizons_days), dtype=np.float64)

    def step(self, msg: EventMessage | ModelMessage) -> Step:
        """Apply one decoded message; the returned states are the segments it changed."""
        if isinstance(msg, Calibration | DegradationPosterior):
            models = with_model(self.models, msg)
            if models is None:
                return Step(False, "version not newer than the one held")
            self.models = models
            return Step(True, "", tuple(self._rerun(self._affected(msg))))
        event = event_of(msg)
        sid = (msg.line, msg.segment)
        track = self.tracks.get(sid) or Track(msg.line, msg.segment)
        track, reason = step_segment(track, event, self.models)
        if reason:
            return Step(False, reason)
        self.tracks[sid] = track
        out = self.segment_state(track)
        return Step(True, "", () if out is None else (out,))

    def load(self, models: Iterable[ModelMessage], events: Iterable[EventMessage]) -> list:
        """Rebuild from stored models and events (any order): the publishable states."""
        for msg in models:
            self.models = with_model(self.models, msg) or self.models
        for msg in events:
            sid = (msg.line, msg.segment)
            track = self.tracks.get(sid) or Track(msg.line, msg.segment)
            self.tracks[sid] = add_event(track, event_of(msg))[0]
        return self._rerun(self.tracks)

    def _affected(self, msg: ModelMessage) -> list[SegmentId]:
        if isinstance(msg, Calibration):
            return list(self.tracks)
        return [sid for sid in self.tracks if self.models.group_for(*sid) == msg.group]

    def _rerun(self, sids: Iterable[SegmentId]) -> list[SegmentState]:
        states = []
        for sid in list(sids):
            track = replay(self.tracks[sid], self.models)
            self.tracks[sid] = track
            out = self.segment_state(track)
            if out is not None:
                states.append(out)
        return states

    def segment_state(self, track: Track) -> SegmentState | None:
        """The SegmentState message of a track (None if not publishable)."""
        state = track.state
        if state is None or track.group is None:
            return None
        return summarize_state(
            track.line,
            track.segment,
            state,
            self.models.params[track.group],
            self._limits_mm(track.line),
            self.limit_levels,
            self.horizons_days,
            calibration_version=self.models.calibration.version if self.models.calibration else 0,
            posterior_version=self.models.posteriors[track.group].version,
            posterior_group=track.group,
        )

    def state_of(self, line: str, segment: str) -> SegmentState | None:
        track = self.tracks.get((line, segment))
        return None if track is None else self.segment_state(track)


def state_weights(state: Filtered) -> np.ndarray:
    """Normalised mixture weights (Ns,) of a state (``mixture.weights_from_log``)."""
    return weights_from_log(state.log_w)


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
    """Mixture summary, exceedance and forecasts of one filter bank (paper Eq. 13-14).

    The mixture weights are :func:`state_weights` (the likelihood of the segment's on-board
    data since its TRC restart), the same now and at every forecast horizon.
    """
    limits = np.asarray(limits_mm, dtype=np.float64)  # (L, n)
    # "Now" and the forecasts (Eq. 2 without updates, as mixture.forecast) in one summary
    # call: row 0 is now, rows 1.. the horizons; limits (L, 1, n) give p_exceed (L, 1+h, n).
    # One call instead of two halves the cost, which is almost all in the quantile search.
    h = np.concatenate(([0.0], horizons_days))
    z_all, P_all = transition_unchecked(state.z[None], state.P[None], params, h)
    both = summarize(z_all, P_all, limits[:, None, :], weights=state_weights(state))
    now, ahead = _rows(both, 0), _rows(both, slice(1, None))
    return SegmentState(
        line=line,
        segment=segment,
        t=state.t_s,
        indicators=list(INDICATORS),
        mean=NDArray.of(now.mean),
        cov=NDArray.of(now.cov),
        ci_low_mm=NDArray.of(now.ci_low_mm),
        ci_high_mm=NDArray.of(now.ci_high_mm),
        width=float(now.width),
        limit_levels=list(limit_levels),
        limits_mm=NDArray.of(limits),
        p_exceed=NDArray.of(now.p_exceed),
        horizons_days=NDArray.of(horizons_days),
        forecast_mean=NDArray.of(ahead.mean),
        forecast_ci_low_mm=NDArray.of(ahead.ci_low_mm),
        forecast_ci_high_mm=NDArray.of(ahead.ci_high_mm),
        forecast_p_exceed=NDArray.of(np.swapaxes(ahead.p_exceed, 0, 1)),  # (h, L, n)
        last_trc_t=state.last_trc_t,
        n_updates=state.n_updates,
        nis=state.nis,
        **versions,
    )


def _rows(summary: MixtureSummary, rows) -> MixtureSummary:
    """Rows of the horizon axis of every field (second axis of p_exceed, first elsewhere)."""
    parts = {f.name: getattr(summary, f.name)[rows] for f in fields(summary)}
    parts["p_exceed"] = summary.p_exceed[:, rows]
    return MixtureSummary(**parts)
