"""Per-segment live filtering as a pure function of events (no Zenoh, no clock, no I/O).

Each segment keeps the log of the events that can still change its state and, when the
models allow, the filter bank of its ``Ns`` posterior samples (paper Eq. 7-13). The state is
always the fold of :func:`apply_event` over the log in canonical order with the current
models, so the order in which events arrive, duplicates, and when the models arrive do not
change it:

- **Canonical order** of a log: ``(t, kind priority, identity)`` with the priority
  ``tamping < restart < index`` for equal times (a TRC record at a tamping's time is the
  exact measurement after it, so it wins); identities are ``(run_id, t)`` for a TRC
  record, ``event_id`` for a tamping and ``(train, unit, t)`` for an on-board index. A second
  event with an identity already in the log is a duplicate and is ignored, except that a
  tamping report replaces the one held under its ``event_id`` when it ranks higher
  (``MaintenanceEvent.rank``: higher ``revision``, then the narrower interval, then the later
  time), so that a correction wins whatever the order of arrival.
- **Log window**: every event at or after the segment's latest TRC record (every event while
  there is none). A TRC record drops the events before it; an event older than the latest
  TRC record cannot change the state and is refused (``accepted`` False, reason given).
- **Incremental or replay**: an event after the last one of the log is applied to the
  current state; a late one is inserted and the log replayed from its start. Both run the
  same fold, so they give bit-identical arrays.
- **Events** (time in the maths is days, ``t_s / DAY_S``):

  * ``TrcRecord``: restart, ``z = ln [top6_mm, align10_mm]`` in every sample, ``P = 0``.
  * ``MaintenanceEvent`` (tamping): at ``t_start`` if ``t_start == t_end``, else at the
    middle of the *reported* interval ``(t_start + t_end) / 2``. The paper (Eq. 2) assumes
    the middle of the filter interval ``(t_{k-1}, t_k]`` in which a tamping is known to
    have happened; a maintenance report's interval is that knowledge, narrowed, so its
    middle is Eq. 2's rule on the report. It does not depend on the other events of the
    log (an on-board index inside the reported interval does not move it). The filter
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
  then ``net``. A model with a version not newer than the one held is ignored; a model is
  checked completely (:func:`parse_model`) before it may replace the one held, and a
  refused one leaves the models and segment histories as they were. A new calibration re-runs every
  segment, a new posterior the segments that now use its group; several models at once
  (:meth:`Tracker.update_models`) re-run the union of their segments once.
- **Batched re-run**: a re-run (model change, restart) folds all its segments together
  (:func:`fold_many`: one vectorised step per event position over the segments still
  holding an event there, split by kind) and summarises them together
  (:func:`summarize_states`). A segment's numbers never depend on the other segments of a
  call, so the re-run, a replay of one segment and the live one-event step give the same
  bits.
- ``nis`` is the mean over samples of the per-sample NIS of the last update since the start
  of the state (a tamping keeps it; a TRC restart clears it to None), weighted by the
  mixture weights before that update (the predictive distribution the index is checked
  against); ``n_updates`` counts the updates since the last TRC record (or since the
  tamping that started the state).
- **Logs held lazily** (:class:`Histories`): a segment's log can rest outside memory (in
  the store) while its state stays; it is read back through a loader the first time it
  is needed (a late event, a duplicate check, detection, a re-run). A re-run of every
  segment goes through them in chunks (``RERUN_CHUNK``), so it holds one chunk of logs.

:class:`Tracker` keeps the segment histories (:class:`Histories`) and the models; its
:meth:`step` returns a :class:`Step` (accepted or not, why, and the SegmentStates to publish), its
:meth:`~Tracker.update_models` a :class:`ModelUpdate`.
"""

from __future__ import annotations

import bisect
import json
import math
from collections import OrderedDict
from collections.abc import Callable, Iterable, Iterator, Mapping, MutableMapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any, NamedTuple, TypeVar

import numpy as np

from schemas import (
    DAY_S,
    INDICATORS,
    ONBOARD_INDICES,
    Calibration,
    DegradationPosterior,
    MaintenanceEvent,
    NDArray,
    OnboardIndex,
    SegmentState,
    TrcRecord,
)
from schemas.keys import SegmentId
from schemas.wire import unchecked_copy
from services.filtering.bank import (
    BLOCK_FILTERS,
    ObservationModel,
    _contiguous,
    update_unchecked,
)
from services.filtering.degradation import DegradationParams, transition_unchecked
from services.filtering.kernel import index_runs, index_step
from services.filtering.mixture import summarize_unchecked, weights_from_log

HORIZONS_DAYS = (30.0, 90.0, 180.0)
TAMPING, RESTART, INDEX = 0, 1, 2  # kind priority at equal times: a TRC record after a tamping
KIND_NAMES = {RESTART: "trc", TAMPING: "maintenance", INDEX: "index"}
SUMMARY_SEGMENTS = 32  # segments per batched summary: 512 quantile searches, spread over the cores
RERUN_CHUNK = 2048  # segments re-run together: one chunk of logs in memory at a time
# Detected maintenance (see :func:`detect`): a one-sided CUSUM of how far below their
# prediction the indices read, in predictive standard deviations.
CUSUM_DRIFT = 1.0  # kappa: a reading 1 sd low adds nothing
CUSUM_CLIP = 6.0  # one index adds at most 6 - kappa = 5: a detection needs two at least
CUSUM_THRESHOLD = 8.0  # h
SUPERSEDE_DAYS = 30.0  # a reported tamping this close to a detected one replaces it

EventMessage = OnboardIndex | TrcRecord | MaintenanceEvent
ModelMessage = Calibration | DegradationPosterior


class Event(NamedTuple):
    """One segment event in the core's terms; ``order`` is its canonical sort key.

    A named tuple (immutable, compared field by field like a frozen dataclass): a re-run
    makes one per stored event, and a tuple is made in a third of a dataclass's time."""

    kind: int  # RESTART, TAMPING or INDEX
    t_s: float  # epoch s of the event (a tamping's assumed time)
    identity: tuple[Any, ...]
    # z of a restart (an array) or y of an index (a pair) in log mm, None for a tamping
    value: np.ndarray | tuple[float, float] | None
    message: EventMessage

    @property
    def order(self) -> tuple[float, int, tuple[Any, ...]]:
        return (self.t_s, self.kind, self.identity)

    @property
    def t_days(self) -> float:
        return self.t_s / DAY_S


def tamping_time(msg: MaintenanceEvent) -> float:
    """Epoch s the filter assumes for a tamping: known time, else the middle of the
    reported interval (Eq. 2's mid-interval rule on the report's interval)."""
    if msg.t_start == msg.t_end:
        return msg.t_start
    return 0.5 * (msg.t_start + msg.t_end)


def event_of(msg: EventMessage) -> Event:
    """The core's event for a decoded message."""
    match msg:
        case OnboardIndex():
            return index_event(msg)
        case TrcRecord():
            z = np.log([msg.top6_mm, msg.align10_mm])
            return Event(RESTART, msg.t, ("trc", msg.run_id, msg.t), z, msg)
        case MaintenanceEvent():
            return Event(TAMPING, tamping_time(msg), ("maintenance", msg.event_id), None, msg)
    raise TypeError(f"not a segment event: {type(msg).__name__}")


def index_event(msg: Any) -> Event:
    """The core's event of an OnboardIndex, or of a stored one decoded without its checks
    (:func:`services.filtering.store._stored_events`): anything with its fields."""
    y = (math.log(msg.top6_mm), math.log(msg.align10_mm))  # no array: 7 % of a backlog
    return Event(INDEX, msg.t, ("index", msg.train, msg.unit, msg.t), y, msg)


@dataclass(frozen=True, eq=False)
class LogColumns:
    """A segment's canonical log as columns, without an object per event: what a re-run of
    a resting segment folds (a model change reads every segment's log; an Event each was
    half of its time). :func:`fold_many` takes it where it takes a tuple of Events, with
    the same bits: the same times and values, in the same order.

    ``values[k]``: the z of a restart, the y of an index, zeros for a tamping;
    ``unit_codes[k]``: the position in ``unit_names`` of an index's ``(train, unit)``,
    -1 for the other kinds; ``last_order``: the :attr:`Event.order` of the last event.
    """

    kinds: np.ndarray  # (L,) int8: RESTART, TAMPING or INDEX
    times: np.ndarray  # (L,) epoch s
    values: np.ndarray  # (L, n)
    unit_codes: np.ndarray  # (L,) int32
    unit_names: tuple[tuple[str, str], ...]
    last_order: tuple[float, int, tuple[Any, ...]] | None

    def __len__(self) -> int:
        return len(self.kinds)


Log = tuple[Event, ...] | LogColumns


@dataclass(frozen=True)
class Models:
    """The latest calibration and degradation posteriors (by group), as the core uses them."""

    calibration: Calibration | None = None
    observation: ObservationModel | None = None
    posteriors: Mapping[str, DegradationPosterior] = field(default_factory=dict)
    params: Mapping[str, DegradationParams] = field(default_factory=dict)
    # the units' own calibrations, by (train, unit); a unit without one uses the fleet's
    unit_calibrations: Mapping[tuple[str, str], Calibration] = field(default_factory=dict)
    unit_observations: Mapping[tuple[str, str], ObservationModel] = field(default_factory=dict)

    def observation_for(self, train: str, unit: str) -> ObservationModel | None:
        """The model an index of ``(train, unit)`` is read with: its own, else the fleet's."""
        return self.unit_observations.get((train, unit), self.observation)

    def observation_for_event(self, event: Event) -> ObservationModel | None:
        msg = event.message
        return self.observation_for(msg.train, msg.unit)

    def group_for(self, line: str, segment: str) -> str | None:
        """The most specific posterior group available for the segment, or None."""
        for group in (f"seg.{line}.{segment}", f"line.{line}", "net"):
            if group in self.params:
                return group
        return None


def model_name(msg: ModelMessage) -> str:
    """The name a model is versioned under: ``calibration`` or ``degradation/{group}``."""
    match msg:
        case Calibration():
            return f"calibration/{msg.train}/{msg.unit}" if msg.train else "calibration"
        case DegradationPosterior():
            return f"degradation/{msg.group}"
    raise TypeError(f"not a model: {type(msg).__name__}")


def _field(kind: str, name: str, value, shape: tuple[int | None, ...]) -> np.ndarray:
    """A model field as float64 of ``shape`` (None: any extent >= 1), or ValueError naming it."""
    try:
        arr = np.asarray(value.array(), dtype=np.float64)
    except (AttributeError, TypeError, ValueError) as exc:
        raise ValueError(f"{kind}.{name}: not a numeric array ({exc})") from None
    if arr.ndim != len(shape) or any(
        got < 1 if want is None else got != want for want, got in zip(shape, arr.shape, strict=True)
    ):
        want_s = ", ".join("Ns" if w is None else str(w) for w in shape)
        raise ValueError(f"{kind}.{name}: shape {arr.shape}, expected ({want_s})")
    if not np.isfinite(arr).all():
        raise ValueError(f"{kind}.{name}: contains NaN or inf")
    return arr


def parse_model(msg: ModelMessage) -> ObservationModel | DegradationParams:
    """The core's form of a model message, checked completely; ValueError naming the field.

    Everything the fold and the summaries use is checked here, before a model may replace
    the one held: the state and index names and order, every array's exact shape, finite
    values, ``R`` symmetric positive definite (right after a TRC restart ``S = R``), the
    posterior covariances ``Sigma`` and ``Sigma_z+`` symmetric positive semi-definite, and
    a version >= 1.
    """
    kind = type(msg).__name__
    if not isinstance(msg, Calibration | DegradationPosterior):
        raise TypeError(f"not a model: {kind}")
    if not isinstance(msg.version, int) or msg.version < 1:
        raise ValueError(f"{kind}.version: {msg.version!r}, expected an integer >= 1")
    if tuple(msg.indicators) != INDICATORS:
        raise ValueError(f"{kind}.indicators: {list(msg.indicators)} != {list(INDICATORS)}")
    n = len(INDICATORS)
    if isinstance(msg, Calibration):
        if tuple(msg.indices) != ONBOARD_INDICES:
            raise ValueError(f"{kind}.indices: {list(msg.indices)} != {list(ONBOARD_INDICES)}")
        m = len(ONBOARD_INDICES)
        H = _field(kind, "H", msg.H, (m, n))
        b = _field(kind, "b", msg.b, (m,))
        R = _field(kind, "R", msg.R, (m, m))
        try:
            return ObservationModel(H, b, R)
        except ValueError as exc:  # "R: not positive definite" and the like
            raise ValueError(f"{kind}.{exc}") from None
    mu = _field(kind, "mu", msg.mu, (None, n))
    ns = mu.shape[0]
    arrays = {
        "mu": mu,
        "sigma": _field(kind, "sigma", msg.sigma, (ns, n, n)),
        "z_plus": _field(kind, "z_plus", msg.z_plus, (ns, n)),
        "sigma_z_plus": _field(kind, "sigma_z_plus", msg.sigma_z_plus, (ns, n, n)),
    }
    try:
        return DegradationParams(**arrays)
    except ValueError as exc:  # "sigma: not positive semi-definite" and the like
        raise ValueError(f"{kind}.{exc}") from None


def _with_parsed(models: Models, msg: ModelMessage, parsed) -> Models:
    if isinstance(msg, Calibration) and msg.train:
        unit = (msg.train, msg.unit)
        return replace(
            models,
            unit_calibrations={**models.unit_calibrations, unit: msg},
            unit_observations={**models.unit_observations, unit: parsed},
        )
    if isinstance(msg, Calibration):
        return replace(models, calibration=msg, observation=parsed)
    return replace(
        models,
        posteriors={**models.posteriors, msg.group: msg},
        params={**models.params, msg.group: parsed},
    )


def held_version(models: Models, msg: ModelMessage) -> int | None:
    """The version of the model held under ``msg``'s name, None if none is held."""
    if isinstance(msg, Calibration):
        held = (
            models.unit_calibrations.get((msg.train, msg.unit)) if msg.train else models.calibration
        )
    else:
        held = models.posteriors.get(msg.group)
    return None if held is None else held.version


def with_model(models: Models, msg: ModelMessage) -> Models | None:
    """``models`` with ``msg`` in it, None if not newer than the one held; ValueError if invalid."""
    held = held_version(models, msg)
    if held is not None and msg.version <= held:
        return None
    return _with_parsed(models, msg, parse_model(msg))


def state_layout(ns: int, n: int) -> tuple[int, int, int]:
    """Where a segment's ``z`` (Ns, n), ``P`` (Ns, n, n) and ``log_w`` (Ns) lie in its one
    float64 buffer (:attr:`Filtered.flat`, a row of :attr:`_Banks.F`, the arrays of a
    stored checkpoint): ``(start of P, start of log_w, width)``, each array row-major."""
    return ns * n, ns * n + ns * n * n, ns * (n + n * n + 1)


def _state_views(flat: np.ndarray, ns: int, n: int):
    """``(z, P, log_w)`` as views of ``flat`` ((W,) one segment, or (S, W) stacked rows)."""
    at_p, at_w, width = state_layout(ns, n)
    if flat.shape[-1] != width:
        raise ValueError(f"state buffer of width {flat.shape[-1]}, not {width} (Ns={ns}, n={n})")
    lead = flat.shape[:-1]
    z = np.reshape(flat[..., :at_p], (*lead, ns, n), copy=False)
    P = np.reshape(flat[..., at_p:at_w], (*lead, ns, n, n), copy=False)
    return z, P, flat[..., at_w:]


@dataclass(frozen=True)
class Filtered:
    """The filter bank of one segment after the last event of its log.

    ``flat``, when set, is the one buffer whose views ``z``, ``P`` and ``log_w`` are
    (:func:`state_layout`): a fold then copies each state in and out as one array
    (three small copies a segment were a third of a backlog's time)."""

    z: np.ndarray  # (Ns, n)
    P: np.ndarray  # (Ns, n, n)
    t_s: float  # epoch s of the last applied event
    last_trc_t: float | None
    n_updates: int
    nis: float | None
    log_w: np.ndarray  # (Ns,) log-likelihood of the on-board data since the TRC restart
    cusum: float = 0.0  # one-sided CUSUM of the indices reading lower than predicted
    cusum_t0: float = float("nan")  # the last index (or start) at which the CUSUM was 0
    cusum_t1: float = float("nan")  # the first index after it (NaN while the CUSUM is 0)
    flat: np.ndarray | None = field(default=None, repr=False, compare=False)

    def buffer(self) -> np.ndarray:
        """``z``, ``P`` and ``log_w`` in one (W,) float64 array (``flat`` or a new one)."""
        if self.flat is not None:
            return self.flat
        return np.concatenate([self.z.ravel(), self.P.ravel(), self.log_w.ravel()])

    @staticmethod
    def of_buffer(flat: np.ndarray, ns: int, n: int, *scalars: Any) -> Filtered:
        """A state on ``flat`` (W,) contiguous (:func:`state_layout`); ``scalars``: ``t_s``
        to ``cusum_t1`` in field order. Made without the frozen dataclass's ``__init__``
        (a fold makes one per segment: its eleven guarded assignments were a tenth of a
        backlog's fold); the same object."""
        at_p, at_w, width = state_layout(ns, n)
        if flat.shape != (width,):
            raise ValueError(f"state buffer of shape {flat.shape}, not ({width},) (Ns={ns})")
        return Filtered._on_buffer(flat, ns, n, at_p, at_w, *scalars)

    @staticmethod
    def _on_buffer(flat, ns, n, at_p, at_w, t_s, last_trc_t, n_updates, nis, cusum, cusum_t0,
                   cusum_t1) -> Filtered:  # fmt: skip
        """:meth:`of_buffer` with ``flat``'s shape known and its layout given."""
        new = object.__new__(Filtered)
        new.__dict__.update(
            z=flat[:at_p].reshape(ns, n),  # views: flat is one contiguous row
            P=flat[at_p:at_w].reshape(ns, n, n),
            t_s=t_s,
            last_trc_t=last_trc_t,
            n_updates=n_updates,
            nis=nis,
            log_w=flat[at_w:],
            cusum=cusum,
            cusum_t0=cusum_t0,
            cusum_t1=cusum_t1,
            flat=flat,
        )
        return new


def _stack(arrays: Sequence[np.ndarray], out: np.ndarray | None = None) -> np.ndarray:
    """``np.stack(arrays)`` of equal-shaped arrays, as one concatenation (``np.stack``
    expands each array in Python first: 5x slower on a backlog's 1,000 small states),
    into ``out`` if given (its first ``len(arrays)`` rows)."""
    shape = arrays[0].shape
    if not all(a.shape == shape for a in arrays):
        raise ValueError(f"cannot stack arrays of shapes {sorted({a.shape for a in arrays})}")
    if out is None:
        return np.concatenate(arrays).reshape(len(arrays), *shape)
    rows = out[: len(arrays)]
    np.concatenate(arrays, out=rows.reshape(-1))
    return rows


class Scratch:
    """A buffer that a fold copying its states out (``copy=True``) reuses for its stacked
    states, batch after batch: a fresh one is new memory each time, and its page faults
    (~3 µs a 4 KiB page on this machine) were a quarter of a backlog's time."""

    def __init__(self) -> None:
        self._buffer = np.empty(0)

    def rows(self, size: int, width: int) -> np.ndarray:
        """A (size, width) float64 array (contents undefined), valid until the next call."""
        if self._buffer.size < size * width:
            self._buffer = np.empty(size * width)
        return self._buffer[: size * width].reshape(size, width)


class _Banks:
    r"""The filter banks of ``S`` segments (one sample count ``Ns``) as stacked arrays.

    The fold of many segments at once: :meth:`restart`, :meth:`tamping` and :meth:`index`
    apply one event to each of the listed rows in one vectorised call, in blocks of about
    ``BLOCK_FILTERS`` filters. Every operation is elementwise over segments and samples, or
    a sum over the samples of one segment, so a segment's numbers do not depend on the
    other rows of the call: a batch of one is the live, one-event step, and a re-run of
    thousands of segments gives the same bits (``update_unchecked`` is written so).

    ``F`` (S, W) holds each row's ``z``, ``P`` and ``log_w`` in one buffer
    (:func:`state_layout`); ``z``, ``P``, ``log_w`` are views of it. With ``scratch`` it is
    the scratch's buffer: take the states out with ``copy=True`` before its next use.
    """

    def __init__(
        self, starts: Sequence[Filtered | None], ns: int, n: int, scratch: Scratch | None = None
    ) -> None:
        size = len(starts)
        rows = [row for row, state in enumerate(starts) if state is not None]
        have = [starts[row] for row in rows]
        width = state_layout(ns, n)[2]
        out = None if scratch is None else scratch.rows(size, width)
        if have and len(have) == size:  # every row started (a backlog): one copy, no zeros
            self.F = _stack([state.buffer() for state in have], out)
        elif out is None:
            self.F = np.zeros((size, width))
        else:
            self.F = out
            self.F[:] = 0.0
        if self.F.shape != (size, width):
            raise ValueError(f"states of shape {self.F.shape[1:]}, not ({width},) (Ns={ns})")
        self.z, self.P, self.log_w = _state_views(self.F, ns, n)
        self.ns, self.n = ns, n
        self.t_s = np.zeros(size)
        self.last_trc_t = np.full(size, np.nan)  # NaN: None
        self.n_updates = np.zeros(size, dtype=np.int64)
        self.nis = np.full(size, np.nan)  # NaN: None
        self.started = np.zeros(size, dtype=bool)
        self.cusum = np.zeros(size)
        self.cusum_t0 = np.full(size, np.nan)
        self.cusum_t1 = np.full(size, np.nan)
        if have:  # one copy per field for all started rows (a backlog starts ~1,000)
            nan = float("nan")
            if len(have) < size:
                self.F[rows] = _stack([state.buffer() for state in have])
            self.cusum[rows] = [state.cusum for state in have]
            self.cusum_t0[rows] = [state.cusum_t0 for state in have]
            self.cusum_t1[rows] = [state.cusum_t1 for state in have]
            self.t_s[rows] = [state.t_s for state in have]
            self.n_updates[rows] = [state.n_updates for state in have]
            self.last_trc_t[rows] = [
                nan if state.last_trc_t is None else state.last_trc_t for state in have
            ]
            self.nis[rows] = [nan if state.nis is None else state.nis for state in have]
            self.started[rows] = True
        self._block = max(1, BLOCK_FILTERS // max(ns, 1))

    SCALARS = ("t_s", "last_trc_t", "n_updates", "nis", "started", "cusum", "cusum_t0", "cusum_t1")

    def grow(self, size: int) -> None:
        """``size`` rows, the new ones zeros (unstarted); the arrays are reallocated in
        place (``ndarray.resize``: a large one is remapped, not copied, so a bank of 1 GB
        does not need 2 GB to grow). Only for a stack no view of which is held (the
        bank's: its states go out as copies)."""
        self.F.resize((size, self.F.shape[1]), refcheck=False)
        self.z, self.P, self.log_w = _state_views(self.F, self.ns, self.n)
        for name in _Banks.SCALARS:
            getattr(self, name).resize(size, refcheck=False)

    def put(self, row: int, state: Filtered) -> None:
        """Row ``row`` becomes ``state`` (a copy)."""
        nan = float("nan")
        self.F[row] = state.buffer()
        self.t_s[row] = state.t_s
        self.last_trc_t[row] = nan if state.last_trc_t is None else state.last_trc_t
        self.n_updates[row] = state.n_updates
        self.nis[row] = nan if state.nis is None else state.nis
        self.started[row] = True
        self.cusum[row] = state.cusum
        self.cusum_t0[row] = state.cusum_t0
        self.cusum_t1[row] = state.cusum_t1

    def states(self, rows: Sequence[int], *, copy: bool = False) -> list[Filtered | None]:
        """Each of ``rows`` as a :class:`Filtered`, None if unstarted: views of the stacked
        arrays, or copies (``copy``: a state kept alone does not hold the whole stack's
        memory); the scalars read in one pass."""
        out: list[Filtered | None] = []
        fields = zip(
            self.started[rows].tolist(),
            self.t_s[rows].tolist(),
            self.last_trc_t[rows].tolist(),
            self.n_updates[rows].tolist(),
            self.nis[rows].tolist(),
            self.cusum[rows].tolist(),
            self.cusum_t0[rows].tolist(),
            self.cusum_t1[rows].tolist(),
            strict=True,
        )
        ns, n = self.ns, self.n
        at_p, at_w, _ = state_layout(ns, n)  # F's rows are of its width (__init__)
        make, F, isnan = Filtered._on_buffer, self.F, math.isnan
        for row, (started, t_s, last_trc_t, n_updates, nis, cusum, t0, t1) in zip(
            rows, fields, strict=True
        ):
            if not started:
                out.append(None)
                continue
            flat = F[row].copy() if copy else F[row]
            last_trc_t = None if isnan(last_trc_t) else last_trc_t
            nis = None if isnan(nis) else nis
            out.append(
                make(flat, ns, n, at_p, at_w, t_s, last_trc_t, n_updates, nis, cusum, t0, t1)
            )
        return out

    def _blocks(self, rows: np.ndarray):
        """``(part, rows)`` in blocks; ``part`` indexes ``rows``; consecutive rows as a slice."""
        for first in range(0, len(rows), self._block):
            part = slice(first, first + self._block)
            yield part, _contiguous(rows[part])

    def restart(self, rows: np.ndarray, t_s: np.ndarray, z: np.ndarray) -> None:
        """TRC record: every sample at ``z`` (k, n), ``P = 0``, equal weights, no NIS."""
        self.z[rows] = z[:, None, :]
        self.P[rows] = 0.0
        self.log_w[rows] = 0.0
        self.t_s[rows] = self.last_trc_t[rows] = t_s
        self.n_updates[rows] = 0
        self.nis[rows] = np.nan
        self.started[rows] = True
        self._cusum_reset(rows, t_s)

    def _cusum_step(self, rows: np.ndarray, t_s: np.ndarray, score: np.ndarray) -> None:
        r"""One index of the one-sided CUSUM of low readings (see :func:`detect`):

        .. math:: g_k = \max(0,\ g_{k-1} - \max(s_k, -c) - \kappa)

        with :math:`c` = ``CUSUM_CLIP`` (one wild index cannot make a detection alone) and
        :math:`\kappa` = ``CUSUM_DRIFT``; ``cusum_t0`` is the last index at which g was 0 and
        ``cusum_t1`` the first index after it.
        """
        g_prev = self.cusum[rows]
        g = np.maximum(0.0, g_prev - np.maximum(score, -CUSUM_CLIP) - CUSUM_DRIFT)
        zero = g == 0.0
        self.cusum[rows] = g
        self.cusum_t0[rows] = np.where(zero, t_s, self.cusum_t0[rows])
        self.cusum_t1[rows] = np.where(
            zero, np.nan, np.where(g_prev == 0.0, t_s, self.cusum_t1[rows])
        )

    def _cusum_reset(self, rows: np.ndarray, t_s: np.ndarray) -> None:
        """A start (TRC record or tamping) at ``t_s``: nothing has read low since."""
        self.cusum[rows] = 0.0
        self.cusum_t0[rows] = t_s
        self.cusum_t1[rows] = np.nan

    def tamping(self, rows: np.ndarray, t_s: np.ndarray, params) -> None:
        r"""Tamping at ``t_s``: the transition with tamping age 0 (Eq. 2), a reset to

        .. math:: \hat z = z^+ + \mu \cdot 0, \qquad P = \Sigma_{z^+} + \Sigma \cdot 0.

        A row without state starts here (``z = P = 0`` first, never used) with equal
        weights; a started row keeps its weights, update count and NIS.
        """
        fresh = rows[~self.started[rows]]
        if len(fresh):
            self.z[fresh], self.P[fresh], self.log_w[fresh] = 0.0, 0.0, 0.0
            self.t_s[fresh] = t_s[~self.started[rows]]
            self.last_trc_t[fresh], self.n_updates[fresh], self.nis[fresh] = np.nan, 0, np.nan
            self.started[fresh] = True
        for part, sel in self._blocks(rows):
            dt = (t_s[part] - self.t_s[sel]) / DAY_S
            self.z[sel], self.P[sel] = transition_unchecked(
                self.z[sel], self.P[sel], params(sel), dt, 0.0
            )
        self.t_s[rows] = t_s
        self._cusum_reset(rows, t_s)

    def index(self, rows, t_s, y, params, obs: ObservationModel, last=None) -> None:
        r"""On-board index ``y`` (k, m) at ``t_s`` on started rows (paper Eq. 7-12).

        Predict over :math:`\Delta t` days, update in Joseph form, and add each sample's
        log-likelihood to its log weight; the NIS is the mean over samples weighted by
        the weights before the update,

        .. math::

            \overline{\nu} = \sum_j w_j \nu_j, \quad
            w_j \propto \exp(\log w_j), \qquad
            \log w_j \mathrel{+}= \log \mathcal N(\nu_j; 0, S_j).

        ``last`` (k,) bool: the rows whose last update this is; only their NIS is computed
        (a later update would overwrite it). None: every row.

        With a 2 x 2 observation model (Top6 and Align10 read by two indices, the system's
        case) the whole step is one compiled pass (:func:`kernel.index_step`); the numpy
        form below serves any other shape. The fold of the system's case goes through
        :func:`kernel.index_runs` instead (:func:`_fold_runs`, the same inlined step), so
        this per-step compiled path is the runs' per-event reference (the kernel tests,
        ``bench.kernel``) rather than the service's.
        """
        if obs.H.shape == (2, 2) and self.z.shape[-1] == 2:
            self.index_compiled(rows, t_s, y, params, obs, last)
        else:
            self.index_numpy(rows, t_s, y, params, obs, last)

    def index_compiled(self, rows, t_s, y, params, obs: ObservationModel, last=None) -> None:
        """:meth:`index` for n = m = 2 through :func:`kernel.index_step` (the same maths)."""
        score = np.empty(len(rows))
        index_step(
            self.F,
            self.t_s,
            np.ascontiguousarray(rows, dtype=np.int64),
            np.ascontiguousarray(t_s, dtype=np.float64),
            np.ascontiguousarray(y, dtype=np.float64),
            params.stack.mu,
            params.stack.sigma,
            params.row_group[rows],
            obs.H,
            obs.b,
            obs.R,
            np.ones(len(rows), dtype=bool) if last is None else np.asarray(last, dtype=bool),
            self.nis,
            score,
        )
        self._cusum_step(rows, t_s, score)
        self.n_updates[rows] += 1

    def index_numpy(self, rows, t_s, y, params, obs: ObservationModel, last=None) -> None:
        """:meth:`index` for any n, m with numpy (the reference of the compiled step)."""
        for part, sel in self._blocks(rows):
            dt = (t_s[part] - self.t_s[sel]) / DAY_S
            z, P = transition_unchecked(self.z[sel], self.P[sel], params(sel), dt)
            # the weights before the update: weights_from_log without its check (log_w is
            # the fold's own), for the CUSUM's score and the NIS
            log_w = self.log_w[sel]
            w = np.exp(log_w - log_w.max(-1, keepdims=True))
            w /= w.sum(-1, keepdims=True)
            self._cusum_step(rows[part], t_s[part], low_score(z, P, y[part], obs, w))
            z, P, nis, loglik = update_unchecked(z, P, y[part], obs.H, obs.b, obs.R, loglik=True)
            want = slice(None) if last is None else last[part]
            at = rows[part][want]
            if len(at):
                # a sum over the last axis, not ``w @ nis``: BLAS dot's order depends on the call
                self.nis[at] = (w[want] * nis[want]).sum(-1)
            self.z[sel], self.P[sel] = z, P
            self.log_w[sel] += loglik
            self.n_updates[sel] += 1
        self.t_s[rows] = t_s


def low_score(z, P, y, obs: ObservationModel, w) -> np.ndarray:
    r"""How far below its prediction an index reads, in predictive standard deviations.

    For the sum of the indicators :math:`u = \mathbf 1^T y` the mixture predictive has, per
    sample :math:`j`, mean :math:`\mathbf 1^T (H \hat z_j + b)` and variance
    :math:`v_j = h^T P_j h + \mathbf 1^T R \mathbf 1` with :math:`h = H^T \mathbf 1`; with
    the weights :math:`w_j` and :math:`\nu_j = u - \mathbf 1^T (H \hat z_j + b)`,

    .. math::

        s = \frac{\bar\nu}{\sqrt{\sum_j w_j (v_j + \nu_j^2) - \bar\nu^2}}, \qquad
        \bar\nu = \sum_j w_j \nu_j .

    A tamping lowers every indicator at once, so its indices give :math:`s \ll 0`.
    ``z`` (k, Ns, n), ``P`` (k, Ns, n, n) predicted; ``y`` (k, m); ``w`` (k, Ns), normalised.
    """
    h = obs.H.sum(axis=0)  # H^T 1
    if len(h) == 2:  # the tracker's state: elementwise, 3x faster than stacked matmuls
        h0, h1 = h.tolist()
        zh = z[..., 0] * h0 + z[..., 1] * h1
        Ph = (P[..., 0, 0] * h0 + P[..., 0, 1] * h1) * h0
        Ph += (P[..., 1, 0] * h0 + P[..., 1, 1] * h1) * h1
    else:
        zh, Ph = z @ h, (P @ h) @ h
    nu = y.sum(-1)[:, None] - (zh + obs.b.sum())
    v = Ph + obs.R.sum()
    mean = (w * nu).sum(-1)
    var = (w * (v + nu * nu)).sum(-1) - mean * mean
    return mean / np.sqrt(np.maximum(var, 1e-300))


class BankRow(NamedTuple):
    """A state held as row ``row`` of a bank of resting states (:class:`_RestingBank`)
    instead of as a :class:`Filtered` of its own: a resting segment's, or a backlog fold's
    result in a free row until the swap makes it the segment's (:meth:`Histories.rest`).
    Only the fold and :class:`Histories` hold one; :meth:`state` reads it out (a copy)."""

    banks: _Banks
    row: int

    def state(self) -> Filtered:
        state = self.banks.states([self.row], copy=True)[0]
        assert state is not None  # only started states are held as rows
        return state

    @property
    def cusum(self) -> float:
        return float(self.banks.cusum[self.row])


def _state_of(state: Filtered | BankRow | None) -> Filtered | None:
    """``state`` as a :class:`Filtered` (read out of its row if it is a :class:`BankRow`)."""
    return state.state() if isinstance(state, BankRow) else state


class _RestingBank:
    """The states of the resting segments with one ``(Ns, n)``: rows of one
    :class:`_Banks`, grown by half (at least ``RESTING_GROWTH`` rows) when every row is
    taken, a freed row taken first.

    A backlog folds a resting segment's indices from its row into a free one
    (:func:`_fold_many` with ``into``), which becomes the segment's at the swap while its
    old row is freed (:meth:`Histories.rest`, :meth:`Histories.settle`): no state
    object per event, and no copy of a state in or out."""

    def __init__(self, ns: int, n: int) -> None:
        self.banks = _Banks([], ns, n)
        self.free: list[int] = []

    def take(self, count: int) -> list[int]:
        """``count`` free rows (taken)."""
        if len(self.free) < count:
            size = len(self.banks.t_s)
            grown = size + max(count - len(self.free), size // 2, RESTING_GROWTH)
            self.banks.grow(grown)
            self.free.extend(range(grown - 1, size - 1, -1))
        taken = self.free[-count:] if count else []
        del self.free[len(self.free) - count :]
        return taken


RESTING_GROWTH = 1024  # rows a bank of resting states grows by at least (11 MB at Ns = 200)


class _RowParams:
    """The degradation parameters of each row of a fold: ``(rows) -> DegradationParams``.

    ``mu`` (G, Ns, n), ``sigma`` (G, Ns, n, n) stack the distinct parameter sets (one when
    every row shares it) and ``row_group`` (S,) says which one each row uses.
    """

    def __init__(self, params: Sequence[DegradationParams]) -> None:
        first = params[0]
        self.shared = first if all(p is first for p in params) else None
        unique: dict[int, int] = {}
        for p in params:
            unique.setdefault(id(p), len(unique))
        groups = {id(p): p for p in params}
        stack = DegradationParams.__new__(DegradationParams)
        for name in ("mu", "sigma", "z_plus", "sigma_z_plus"):
            object.__setattr__(stack, name, np.stack([getattr(groups[k], name) for k in unique]))
        self.stack = stack
        self.row_group = np.array([unique[id(p)] for p in params], dtype=np.int64)

    def __call__(self, rows) -> DegradationParams:
        return self.shared if self.shared is not None else self.stack.take(self.row_group[rows])


def fold_many(
    starts: Sequence[Filtered | None],
    logs: Sequence[Sequence[Event]],
    params: Sequence[DegradationParams],
    obs: ObservationModel | Models | None,
    scratch: Scratch | None = None,
) -> list[Filtered | None]:
    """Fold each ``logs[i]`` from ``starts[i]`` with ``params[i]``, all segments at once.

    One vectorised step per event position ``k``: the segments are ordered by decreasing
    log length, so those still holding a k-th event are a prefix, and split by the kind of
    that event (and an index's rows by the observation model of its unit). Bit-identical to
    folding each segment alone (see :class:`_Banks`). Every ``params[i]`` must have the same
    ``(Ns, n)``; ``obs`` is one observation model for every index, or the :class:`Models`
    whose :meth:`~Models.observation_for` gives each index its unit's; there must be one
    for an index that follows a start (the caller checks it, see :func:`_publishable`).
    Without ``scratch`` the states are views of the call's stacked arrays; with it they are
    copies, the fold having run in the scratch's reused buffer.
    """
    return _fold_many(starts, logs, params, obs, scratch=scratch)[0]


def _fold_many(
    starts,
    logs,
    params,
    obs,
    halt_cusum: float | None = None,
    copy=False,
    scratch=None,
    into: _RestingBank | None = None,
):
    """:func:`fold_many`, and how many events of each log were folded: ``(states, folded)``.

    ``halt_cusum``: a segment stops after the first index that leaves its CUSUM at or above
    this (:func:`detect`'s condition), its state the one after that index, and ``folded[i]``
    says how many of its events that was. Every index's NIS is then computed (a halted
    row's last update is not known in advance); the bits do not change, since the NIS of a
    row is a sum over its own samples. ``copy``: each state owns its arrays
    (:meth:`_Banks.states`); ``scratch`` (a :class:`Scratch`): the fold runs in its buffer
    and the states are copied out. ``into``: ``starts`` are all rows of that bank of
    resting states (:class:`BankRow`) and ``logs`` hold indices only; each is folded from
    its row into a free row of the bank (:func:`kernel.index_runs`' ``homes``), and the
    states are returned as those rows (:class:`BankRow`, taken: :meth:`Histories.settle`
    gives back the ones no segment keeps).
    """
    # one model for every index (no unit has its own): no per-event look-up
    per_unit = isinstance(obs, Models) and bool(obs.unit_observations)
    shared = obs.observation if isinstance(obs, Models) else obs
    size = len(logs)
    if size == 0:
        return [], []
    ns, n = params[0].ns, params[0].n
    order = sorted(range(size), key=lambda i: -len(logs[i]))
    depth = len(logs[order[0]])
    kinds = np.full((size, depth), -1, dtype=np.int8)
    times = np.zeros((size, depth))
    values = np.zeros((size, depth, n))
    obs_ids = np.full((size, depth), -1, dtype=np.int32)  # an index's model in ``observations``
    observations: list[ObservationModel] = []
    known: dict[int, int] = {}
    zero = np.zeros(n)

    def model_id(model: ObservationModel | None) -> int:
        if model is None:
            return -1
        if id(model) not in known:
            known[id(model)] = len(observations)
            observations.append(model)
        return known[id(model)]

    # the Events of every row in one pass (a backlog folds ~1,000 rows of one index each:
    # filling them row by row was a tenth of its fold), LogColumns row by row
    at_row: list[int] = []
    at_k: list[int] = []
    events: list[Event] = []
    for row, i in enumerate(order):
        log = logs[i]
        if not isinstance(log, LogColumns):
            at_row.extend([row] * len(log))
            at_k.extend(range(len(log)))
            events.extend(log)
            continue
        kinds[row, : len(log)] = log.kinds
        times[row, : len(log)] = log.times
        values[row, : len(log)] = log.values
        if per_unit and log.unit_names:
            ids = np.array([model_id(obs.observation_for(*u)) for u in log.unit_names])
            at = np.flatnonzero(log.unit_codes >= 0)
            obs_ids[row, at] = ids[log.unit_codes[at]]
    if events:
        kinds[at_row, at_k] = [e.kind for e in events]
        times[at_row, at_k] = [e.t_s for e in events]
        values[at_row, at_k] = [zero if e.value is None else e.value for e in events]
        if per_unit:
            for row, k, e in zip(at_row, at_k, events, strict=True):
                if e.kind == INDEX:
                    obs_ids[row, k] = model_id(obs.observation_for_event(e))
    if not per_unit and shared is not None:
        observations.append(shared)
        obs_ids[kinds == INDEX] = 0
    runs = n == 2 and all(model.H.shape == (2, 2) for model in observations)
    homes = None
    if into is not None and not runs:  # (no model of the system's shape) from copies
        starts = [start.state() for start in starts]
    elif into is not None:
        if not (kinds[kinds >= 0] == INDEX).all():
            raise ValueError("a fold from resting rows takes indices only")
        banks = into.banks
        srcs = np.array([starts[i].row for i in order], dtype=np.int64)
        ats = np.array(into.take(size), dtype=np.int64)
        for name in _Banks.SCALARS:  # the fields go first; the samples with the fold
            values_of = getattr(banks, name)
            values_of[ats] = values_of[srcs]
        homes = (srcs, ats)
    else:
        banks = _Banks([starts[i] for i in order], ns, n, scratch)
    copy = copy or scratch is not None
    rows_params = _RowParams([params[i] for i in order])
    lengths = np.array([len(logs[i]) for i in order])
    folded = lengths.copy()  # events folded per row (fewer if halted)
    if runs:
        _fold_runs(banks, kinds, times, values, obs_ids, observations, rows_params, lengths,
                   folded, halt_cusum, homes)  # fmt: skip
    else:
        _fold_steps(banks, kinds, times, values, obs_ids, observations, rows_params, lengths,
                    folded, halt_cusum, homes)  # fmt: skip
    out: list[Filtered | BankRow | None] = [None] * size
    counts = [0] * size
    states = (
        [BankRow(banks, row) for row in homes[1].tolist()]
        if homes is not None
        else banks.states(range(size), copy=copy)
    )
    for i, state, count in zip(order, states, folded.tolist(), strict=True):
        out[i] = state
        counts[i] = count
    return out, counts


def _fold_steps(
    banks,
    kinds,
    times,
    values,
    obs_ids,
    observations,
    rows_params,
    lengths,
    folded,
    halt_cusum,
    homes=None,
):
    """:func:`_fold_many`'s fold one event position at a time over every row (any ``n``, any
    observation model: :meth:`_Banks.index`); ``folded`` gets a halted row's count. The
    rows are ordered by decreasing log length."""
    if homes is not None:
        raise ValueError("a fold from resting rows (homes) is _fold_runs' only")
    depth = kinds.shape[1]
    # position of each row's last index: the NIS of a state is that of its last update
    last_index = depth - 1 - np.argmax(kinds[:, ::-1] == INDEX, axis=1)
    for k in range(depth):
        active = int(np.count_nonzero(lengths > k))
        kind = kinds[:active, k]
        for code in (RESTART, TAMPING, INDEX):
            rows = np.flatnonzero(kind == code)
            if code == INDEX:
                rows = rows[banks.started[rows]]  # an index before any start is skipped
            if len(rows) == 0:
                continue
            if code == RESTART:
                banks.restart(rows, times[rows, k], values[rows, k])
            elif code == TAMPING:
                banks.tamping(rows, times[rows, k], rows_params)
            else:
                ids = obs_ids[rows, k]
                assert (ids >= 0).all()
                for j in np.unique(ids):  # the rows whose index is read by model j
                    sub = rows if len(observations) == 1 else rows[ids == j]
                    last = None if halt_cusum is not None else last_index[sub] == k
                    banks.index(
                        sub, times[sub, k], values[sub, k], rows_params, observations[j], last
                    )
                    if halt_cusum is not None:
                        halted = sub[banks.cusum[sub] >= halt_cusum]
                        kinds[halted, k + 1 :] = -1  # nothing more is folded on these rows
                        folded[halted] = k + 1


def _fold_runs(
    banks, kinds, times, values, obs_ids, observations, params, lengths, folded, halt, homes=None
):
    """:func:`_fold_many`'s fold for ``n = m = 2`` (the system's case) as runs: the restarts
    and tampings at each row's position, vectorised over the rows (:meth:`_Banks.restart`,
    :meth:`_Banks.tamping`), then each row's indices up to its next other event, a row at
    a time (:func:`kernel.index_runs`), until every log is folded. The rows are independent,
    so the order across rows does not change a bit (:func:`_fold_steps` gives the same).
    ``homes``: index_runs' (indices only)."""
    if observations:
        Hs, bs, Rs = (np.stack([getattr(o, name) for o in observations]) for name in "HbR")
    else:  # no model: an index on a started row is then an error (reported below)
        Hs, bs, Rs = np.zeros((1, 2, 2)), np.zeros((1, 2)), np.zeros((1, 2, 2))
    pos = np.zeros(len(lengths), dtype=np.int64)  # each row's next event
    stop = lengths.astype(np.int64)  # a halted row's stops after the halting index
    missing = np.zeros(len(lengths), dtype=bool)
    while True:
        moved = True
        while moved:  # the restarts and tampings at the rows' positions
            live = np.flatnonzero(pos < stop)
            kind = kinds[live, pos[live]]
            moved = False
            for code in (RESTART, TAMPING):
                rows = live[kind == code]
                if len(rows):
                    at = pos[rows]
                    if code == RESTART:
                        banks.restart(rows, times[rows, at], values[rows, at])
                    else:
                        banks.tamping(rows, times[rows, at], params)
                    pos[rows] += 1
                    moved = True
        rows = np.flatnonzero(pos < stop)  # each at an index
        if len(rows) == 0:
            return
        index_runs(
            rows, banks.F, banks.t_s, pos, stop, kinds, times, values, obs_ids, Hs, bs, Rs,
            params.stack.mu, params.stack.sigma, params.row_group, banks.started, banks.nis,
            banks.n_updates, banks.cusum, banks.cusum_t0, banks.cusum_t1,
            (INDEX, CUSUM_DRIFT, CUSUM_CLIP, math.inf if halt is None else float(halt)),
            folded, missing, homes,
        )  # fmt: skip
        if missing.any():
            raise AssertionError("an index on a started state without an observation model")


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
    :func:`fold_many` with one segment and one event, so it gives the re-run's bits.
    """
    return fold_many([state], [(event,)], [params], obs)[0]


@dataclass(frozen=True)
class SegmentHistory:
    """One segment's history: its event log (canonical order), the filter state folded from
    it, the posterior group it used."""

    line: str
    segment: str
    log: Log = ()  # columns only inside a re-run of a resting segment (Histories.load_columns)
    trc_t: float | None = None  # epoch s of the latest TRC record: the log's lower bound
    state: Filtered | None = None
    group: str | None = None  # posterior group of ``state``


@dataclass(frozen=True)
class Checkpoint:
    """A segment's fold without its log: what a checkpoint stores and a restart restores.

    ``last_order`` is the canonical order key of the log's last event (None: empty log);
    an event stored later with a smaller key is a late one, and the segment must then be
    replayed from its log's start. ``models_key`` (:func:`models_key`) names the model
    versions ``state`` was folded with.
    """

    line: str
    segment: str
    trc_t: float | None
    state: Filtered | None
    group: str | None
    last_order: tuple[float, int, tuple[Any, ...]] | None
    models_key: str = ""
    # the (train, unit) of every index in the log ``state`` folds (or more); None: unknown
    units: frozenset[tuple[str, str]] | None = None


def log_units(log: Iterable[Event] | LogColumns) -> frozenset[tuple[str, str]]:
    """The ``(train, unit)`` of the indices of a log: whose calibrations its fold reads."""
    if isinstance(log, LogColumns):
        return frozenset(log.unit_names)
    return frozenset((e.message.train, e.message.unit) for e in log if e.kind == INDEX)


def checkpoint_of(hist: SegmentHistory) -> Checkpoint:
    """``hist`` without its log: its state, where its log ends and whose indices it read."""
    if isinstance(hist.log, LogColumns):
        last_order = hist.log.last_order
    else:
        last_order = hist.log[-1].order if hist.log else None
    return Checkpoint(
        hist.line,
        hist.segment,
        hist.trc_t,
        hist.state,
        hist.group,
        last_order,
        units=log_units(hist.log),
    )


def models_key(
    models: Models, line: str, segment: str, units: Iterable[tuple[str, str]] | None = None
) -> str:
    """The versions of the models a segment's fold uses: the fleet calibration, the
    calibration of each of the log's ``units`` (0: the unit has none of its own; None:
    every unit calibration held, when the log's units are not known), its posterior group
    and that group's version. Two folds of one log with equal keys are the same bits."""
    group = models.group_for(line, segment)
    if units is None:
        versions = sorted([*unit, cal.version] for unit, cal in models.unit_calibrations.items())
    else:
        held = models.unit_calibrations
        versions = sorted([*unit, held[unit].version if unit in held else 0] for unit in units)
    return json.dumps(
        {
            "calibration": models.calibration.version if models.calibration else 0,
            "units": versions,
            "known_units": units is not None,
            "group": group,
            "posterior": models.posteriors[group].version if group is not None else 0,
        }
    )


def key_units(key: str) -> frozenset[tuple[str, str]] | None:
    """The log's units a :func:`models_key` was written for (None: not known, or a key
    written before they were kept: it matches no current key, so its segment replays)."""
    try:
        parsed = json.loads(key)
    except ValueError:
        return None
    if not isinstance(parsed, dict) or parsed.get("known_units") is not True:
        return None
    return frozenset((train, unit) for train, unit, _version in parsed["units"])


LogLoader = Callable[[str, str], tuple[tuple[Event, ...], float | None]]
ColumnLoader = Callable[[str, str], tuple[LogColumns, float | None] | None]


class Histories(MutableMapping[SegmentId, SegmentHistory]):
    """The segment histories by ``(line, segment)``: a dict whose logs load lazily.

    A segment is either *loaded* (a :class:`SegmentHistory` with its log) or *resting*
    (a :class:`Checkpoint`: its state without the log, e.g. restored from a checkpoint or
    evicted by :meth:`trim`). Reading a resting segment (``[sid]``, ``get``) asks
    ``loader(line, segment) -> (log, trc_t)`` for its log in canonical order (the store
    supplies it; the core does no I/O) and keeps it loaded. Iteration and ``len`` cover
    every known segment; ``items()``/``values()`` load every log, so the core iterates the
    keys and uses :meth:`resting` where the state alone is enough. Every assignment marks
    the segment ``dirty`` (its checkpoint is out of date) until the owner clears it.
    ``columns(line, segment) -> (LogColumns, trc_t) | None``, when given, reads a resting
    log as columns for a re-run (:meth:`load_columns`; None: read it as events).

    A resting segment's state is a row of the bank of its sample count
    (:class:`_RestingBank`), not a :class:`Filtered` of its own: :meth:`resting` reads it
    out (a copy); only the tracker's fold sees the row (:meth:`resting_entry`), folds from
    it into a free row, and hands that back with the segment's new Checkpoint at the swap
    (:meth:`rest` keeps it there and frees the old row; :meth:`settle` frees the rows a
    failed or superseded fold took).
    """

    def __init__(self, loader: LogLoader | None = None) -> None:
        self.loader = loader
        self.columns: ColumnLoader | None = None
        self._loaded: OrderedDict[SegmentId, SegmentHistory] = OrderedDict()
        # a resting segment's Checkpoint, its state (if any) a BankRow of ``_banks``
        self._resting: dict[SegmentId, Checkpoint] = {}
        self._banks: dict[tuple[int, int], _RestingBank] = {}  # by (Ns, n)
        self.dirty: set[SegmentId] = set()

    def _release(self, rest: Checkpoint | None) -> None:
        """``rest``'s row (if it has one) back to its bank, once it no longer rests."""
        if rest is not None and isinstance(rest.state, BankRow):
            self._free(rest.state)

    def _free(self, row: BankRow) -> None:
        self._banks[(row.banks.ns, row.banks.n)].free.append(row.row)

    def bank(self, ns: int, n: int) -> _RestingBank:
        """The bank of the resting states of ``(ns, n)``."""
        bank = self._banks.get((ns, n))
        if bank is None:
            self._banks[(ns, n)] = bank = _RestingBank(ns, n)
        return bank

    def __getitem__(self, sid: SegmentId) -> SegmentHistory:
        hist = self._loaded.get(sid)
        if hist is not None:
            self._loaded.move_to_end(sid)
            return hist
        hist = self.load(sid)
        self._release(self._resting.pop(sid))
        self._loaded[sid] = hist
        return hist

    def load(self, sid: SegmentId) -> SegmentHistory:
        """The segment's history with its log, without keeping a resting one's log loaded."""
        hist = self._loaded.get(sid)
        if hist is not None:
            return hist
        rest = self._resting[sid]  # KeyError: unknown segment
        if self.loader is None:
            raise LookupError(f"segment {sid}: log not loaded and no loader")
        log, trc_t = self.loader(rest.line, rest.segment)
        return SegmentHistory(
            rest.line, rest.segment, log, trc_t, _state_of(rest.state), rest.group
        )

    def load_columns(self, sid: SegmentId) -> SegmentHistory:
        """:meth:`load`, with a resting segment's log as :class:`LogColumns` when the
        column loader gives it, and then without its state, which a re-run recomputes from
        the log (a re-run's read, not kept: never assign the result)."""
        rest = self._resting.get(sid)
        if rest is None or self.columns is None:
            return self.load(sid)
        read = self.columns(rest.line, rest.segment)
        if read is None:
            return self.load(sid)
        log, trc_t = read
        return SegmentHistory(rest.line, rest.segment, log, trc_t, None, rest.group)

    def __setitem__(self, sid: SegmentId, hist: SegmentHistory) -> None:
        self._release(self._resting.pop(sid, None))
        self._loaded[sid] = hist
        self._loaded.move_to_end(sid)
        self.dirty.add(sid)

    def __delitem__(self, sid: SegmentId) -> None:
        if self._loaded.pop(sid, None) is None:
            self._release(self._resting.pop(sid))
        self.dirty.discard(sid)

    def __contains__(self, sid: object) -> bool:
        return sid in self._loaded or sid in self._resting

    def __iter__(self) -> Iterator[SegmentId]:
        yield from list(self._loaded)
        yield from list(self._resting)

    def __len__(self) -> int:
        return len(self._loaded) + len(self._resting)

    def rest(self, sid: SegmentId, checkpoint: Checkpoint, *, dirty: bool = False) -> None:
        """Hold ``sid`` as its state alone (its log is then read again when needed): the
        state is copied into the segment's row of the bank (its own row again if it has
        one of that shape), or, a row of the bank already (a backlog's fold), kept there."""
        self._loaded.pop(sid, None)
        old = self._resting.get(sid)
        state = checkpoint.state
        if state is None:
            self._release(old)
        elif isinstance(state, BankRow):
            if old is not None and old.state != state:
                self._release(old)
        else:
            row = self._row_for(old, *state.z.shape)
            row.banks.put(row.row, state)
            checkpoint = _evolve(checkpoint, state=row)
        self._resting[sid] = checkpoint
        if dirty:
            self.dirty.add(sid)

    def _row_for(self, old: Checkpoint | None, ns: int, n: int) -> BankRow:
        """The row a resting segment's state of ``(ns, n)`` goes in: its own (``old``'s)
        if of that shape, else a free one."""
        if old is not None and isinstance(old.state, BankRow):
            if (old.state.banks.ns, old.state.banks.n) == (ns, n):
                return old.state
            self._release(old)
        bank = self.bank(ns, n)
        return BankRow(bank.banks, bank.take(1)[0])

    def settle(self, taken: Iterable[tuple[SegmentId, BankRow]]) -> None:
        """Free each row of ``taken`` (``(segment, row)``: rows a fold took for segments)
        that its segment does not rest in (after the swap, or after a failed batch)."""
        for sid, row in taken:
            rest = self._resting.get(sid)
            if rest is None or rest.state != row:
                self._free(row)

    def resting(self, sid: SegmentId) -> Checkpoint:
        """The segment's state without loading its log (``models_key`` left empty)."""
        rest = self._resting.get(sid)
        if rest is not None:
            if isinstance(rest.state, BankRow):
                return _evolve(rest, state=rest.state.state())
            return rest
        return checkpoint_of(self._loaded[sid])

    def resting_many(self, sids: Sequence[SegmentId]) -> list[Checkpoint]:
        """:meth:`resting` of each of ``sids``, the states read out of each bank in one
        pass (:meth:`_Banks.states`)."""
        out = [self.resting_entry(sid) for sid in sids]
        blocks: dict[int, tuple[_Banks, list[int]]] = {}
        for k, rest in enumerate(out):
            if isinstance(rest.state, BankRow):
                blocks.setdefault(id(rest.state.banks), (rest.state.banks, []))[1].append(k)
        for banks, ks in blocks.values():
            states = banks.states([out[k].state.row for k in ks], copy=True)
            for k, state in zip(ks, states, strict=True):
                out[k] = _evolve(out[k], state=state)
        return out

    def resting_entry(self, sid: SegmentId) -> Checkpoint:
        """:meth:`resting`, a resting segment's state left as its :class:`BankRow` (what
        the fold folds from; never kept, nor given out)."""
        rest = self._resting.get(sid)
        return rest if rest is not None else checkpoint_of(self._loaded[sid])

    def units(self, sid: SegmentId) -> frozenset[tuple[str, str]]:
        """The ``(train, unit)`` whose indices the segment's log holds (or a superset),
        reading the log only when a resting segment does not know them."""
        hist = self._loaded.get(sid)
        if hist is not None:
            return log_units(hist.log)
        units = self._resting[sid].units
        return log_units(self.load(sid).log) if units is None else units

    def is_loaded(self, sid: SegmentId) -> bool:
        return sid in self._loaded

    @property
    def n_loaded(self) -> int:
        return len(self._loaded)

    def trim(self, max_loaded: int) -> int:
        """Drop the logs of the least recently used segments beyond ``max_loaded`` (their
        states stay); only call it when the loader returns those logs (stored); returns
        how many were dropped."""
        dropped = 0
        while len(self._loaded) > max_loaded:
            sid = next(iter(self._loaded))
            self.rest(sid, checkpoint_of(self._loaded[sid]))
            dropped += 1
        return dropped


def canonical_log(events: Iterable[Event]) -> tuple[tuple[Event, ...], float | None]:
    """``(log, trc_t)`` of a segment's stored events (any order): the events at or after
    the latest TRC record, in canonical order. The store holds exactly the accepted log
    (duplicates refused, superseded tampings and events before a TRC record deleted), except
    a tamping correction that moved before the latest TRC record, which this drops."""
    events = list(events)
    restarts = [e.t_s for e in events if e.kind == RESTART]
    trc_t = max(restarts) if restarts else None
    kept = [e for e in events if trc_t is None or e.t_s >= trc_t]
    kept.sort(key=lambda e: e.order)
    return tuple(kept), trc_t


def _rested(ckpt: Checkpoint, state, group, tail: Sequence[Event]) -> Checkpoint:
    """``ckpt`` folded on over ``tail`` (in canonical order, after its last event)."""
    trc_t = ckpt.trc_t
    for event in tail:
        if event.kind == RESTART and (trc_t is None or event.t_s > trc_t):
            trc_t = event.t_s
    units = ckpt.units
    if units is not None:  # a superset is safe
        read = log_units(tail)
        if not read <= units:
            units = units | read
    changes = {"trc_t": trc_t, "state": state, "group": group, "units": units}
    changes["last_order"] = tail[-1].order
    return _replaced(ckpt, changes)  # a backlog's per segment: _evolve without its check


def _summarised(hist: SegmentHistory | Checkpoint) -> SegmentHistory:
    """What a summary reads of a segment (its log is not): a resting one without its log."""
    if isinstance(hist, SegmentHistory):
        return hist
    state = _state_of(hist.state)
    return SegmentHistory(hist.line, hist.segment, (), hist.trc_t, state, hist.group)


_Frozen = TypeVar("_Frozen", "SegmentHistory", "Checkpoint")


def _evolve(hist: _Frozen, **changes: Any) -> _Frozen:
    """``dataclasses.replace(hist, **changes)`` of a SegmentHistory or a Checkpoint, without
    its per-call field introspection (a tenth of a backlog's time): every field, whatever
    they are, copied, then changed."""
    cls = type(hist)
    if not changes.keys() <= cls.__dataclass_fields__.keys():
        raise TypeError(f"{cls.__name__} has no field {set(changes) - set(vars(hist))}")
    return _replaced(hist, changes)


def _replaced(hist: _Frozen, changes: dict[str, Any]) -> _Frozen:
    """:func:`_evolve` without the check that ``changes`` names fields of ``hist``."""
    new = object.__new__(type(hist))
    new.__dict__.update(hist.__dict__)
    new.__dict__.update(changes)
    return new


def _publishable(log: Sequence[Event] | LogColumns, models: Models, started=False) -> bool:
    """False if the fold of ``log`` (from a started state if ``started``) needs an update
    without a calibration (neither the index's unit's nor the fleet's)."""
    if models.observation is not None:
        return True
    if isinstance(log, LogColumns):
        units = [models.observation_for(*u) is not None for u in log.unit_names]
        for kind, code in zip(log.kinds.tolist(), log.unit_codes.tolist(), strict=True):
            if kind != INDEX:
                started = True
            elif started and not units[code]:
                return False
        return True
    for event in log:
        if event.kind != INDEX:
            started = True
        elif started and models.observation_for_event(event) is None:
            return False
    return True


def _fold(hist: SegmentHistory, models: Models, events: Sequence[Event], start: Filtered | None):
    """Fold ``events`` from ``start``; (state, group) or (None, group) if not publishable."""
    group = models.group_for(hist.line, hist.segment)
    if group is None:
        return None, group
    if not _publishable(events, models, started=start is not None):
        return None, group
    return fold_many([start], [events], [models.params[group]], models)[0], group


def replay_many(hists: Sequence[SegmentHistory], models: Models) -> list[SegmentHistory]:
    """The histories with their states recomputed from the start of their logs, in one pass.

    Segments of every posterior group go through one :func:`fold_many` per sample count
    ``Ns``; a segment without a group, or needing an update without a calibration, gets
    no state. Bit-identical to :func:`replay` of each history.
    """
    out = list(hists)
    jobs: dict[int, list[tuple[int, str]]] = {}
    for i, hist in enumerate(hists):
        group = models.group_for(hist.line, hist.segment)
        if group is None or not _publishable(hist.log, models):
            out[i] = replace(hist, state=None, group=group)
        else:
            jobs.setdefault(models.params[group].ns, []).append((i, group))
    for job in jobs.values():
        states = fold_many(
            [None] * len(job),
            [hists[i].log for i, _ in job],
            [models.params[group] for _, group in job],
            models,
        )
        for (i, group), state in zip(job, states, strict=True):
            out[i] = replace(hists[i], state=state, group=group)
    return out


def replay(hist: SegmentHistory, models: Models) -> SegmentHistory:
    """The history with its state recomputed from the start of its log."""
    return replay_many([hist], models)[0]


def add_event(hist: SegmentHistory, event: Event) -> tuple[SegmentHistory, str]:
    """Insert ``event`` into the log (state untouched): ``(hist, "")`` or ``(hist, reason)``.

    A tamping report that outranks the one held under its ``event_id`` (``MaintenanceEvent.rank``)
    replaces it, and is accepted even when its time is now before the latest TRC record:
    the held report then leaves the log (the TRC record already measured the tamping).
    """
    held = next((e for e in hist.log if e.identity == event.identity), None)
    log, trc_t = hist.log, hist.trc_t
    if event.kind == TAMPING and held is None:
        near = [
            e for e in log if e.kind == TAMPING and abs(e.t_s - event.t_s) <= SUPERSEDE_DAYS * DAY_S
        ]
        if event.message.detected:
            if any(not e.message.detected for e in near):
                return hist, "a reported tamping is within 30 days"
        else:  # a reported tamping replaces the detected ones near it
            log = tuple(e for e in log if not (e in near and e.message.detected))
    if held is not None:
        if event.kind != TAMPING or event.message.rank <= held.message.rank:
            return hist, "duplicate"
        log = tuple(e for e in log if e is not held)
        if trc_t is not None and event.t_s < trc_t:
            return replace(hist, log=log), ""
    elif trc_t is not None and event.t_s < trc_t:
        return hist, "older than the latest TRC record"
    if event.kind == RESTART:
        log = tuple(e for e in log if e.t_s >= event.t_s)  # a restart forgets what precedes it
        trc_t = event.t_s if trc_t is None else max(trc_t, event.t_s)
    at = bisect.bisect([e.order for e in log], event.order)
    return replace(hist, log=(*log[:at], event, *log[at:]), trc_t=trc_t), ""


def step_segment(hist: SegmentHistory, event: Event, models: Models) -> tuple[SegmentHistory, str]:
    """Add one event to a segment and bring its state up to date: ``(hist, reason)``.

    ``reason`` is empty when the event was accepted, else why it was refused.
    """
    new, reason = add_event(hist, event)
    if reason:
        return hist, reason
    replaced = any(e.identity == event.identity for e in hist.log)
    appended = bool(new.log) and new.log[-1] is event and not replaced
    if appended and (event.kind == RESTART or hist.state is not None):
        # ``hist.state`` is the fold of the log before ``event``: one more step of it.
        state, group = _fold(new, models, (event,), hist.state)
        return replace(new, state=state, group=group), ""
    return replay(new, models), ""


def detect(hist: SegmentHistory, models: Models) -> tuple[SegmentHistory, MaintenanceEvent | None]:
    r"""A tamping that no feed reported, found in the segment's on-board indices.

    The fold keeps a one-sided CUSUM (Page's test) of the standardised amount by which each
    index reads below the mixture's prediction (:func:`low_score`):
    :math:`g_k = \max(0, g_{k-1} - \max(s_k, -c) - \kappa)`, reset to 0 by a TRC record or a
    tamping. A tamping lowers both indicators to about :math:`z^+` at once, so the indices
    after it read several standard deviations low and :math:`g` grows; degradation and noise
    do not. When :math:`g \ge h` the tamping lies in one of the intervals between the
    consecutive events since the CUSUM last was 0 (``cusum_t0``); for each the segment is
    re-run with a tamping there (Eq. 2: at the interval's middle), and the interval whose
    re-run gives the on-board data the highest marginal likelihood
    :math:`\log \frac{1}{N_s}\sum_j e^{\log w_j}` is reported as the detected
    maintenance ``[t_a, t_b]``. ``(hist, None)`` when nothing is detected, or when a
    reported tamping within ``SUPERSEDE_DAYS`` already explains the data.
    """
    state = hist.state
    if state is None or state.cusum < CUSUM_THRESHOLD or np.isnan(state.cusum_t1):
        return hist, None
    times = sorted({e.t_s for e in hist.log if e.t_s >= state.cusum_t0})
    best: tuple[float, SegmentHistory, MaintenanceEvent] | None = None
    for t_a, t_b in zip(times, times[1:], strict=False):
        msg = MaintenanceEvent(
            line=hist.line,
            segment=hist.segment,
            event_id=f"detected-{int(t_b)}",
            t_start=t_a,
            t_end=t_b,
            detected=True,
        )
        new, reason = step_segment(hist, event_of(msg), models)
        if reason or new.state is None:
            continue
        log_w = new.state.log_w
        evidence = float(log_w.max() + np.log(np.exp(log_w - log_w.max()).mean()))
        if best is None or evidence > best[0]:
            best = (evidence, new, msg)
    return (hist, None) if best is None else (best[1], best[2])


@dataclass(frozen=True)
class Step:
    """What one message did: accepted (else ``reason``), the states to publish, and the
    tampings it made :func:`detect` find (to be stored and published like a report)."""

    accepted: bool
    reason: str = ""
    states: tuple[SegmentState, ...] = ()
    detected: tuple[MaintenanceEvent, ...] = ()


@dataclass(frozen=True)
class ModelUpdate:
    """What :meth:`Tracker.update_models` did with each model message, and the new states.

    ``accepted``: applied (the newest version per model name); ``ignored``: not newer than
    the one held or superseded by a newer one in the same update, with why; ``refused``:
    invalid (the reason names the field) or its re-run failed; ``states``: the re-run
    segments' publishable states.
    """

    accepted: list[ModelMessage] = field(default_factory=list)
    ignored: list[tuple[ModelMessage, str]] = field(default_factory=list)
    refused: list[tuple[ModelMessage, str]] = field(default_factory=list)
    states: tuple[SegmentState, ...] = ()


class Tracker:
    """Every segment's :class:`SegmentHistory` (dict by ``(line, segment)``) and the models.

    Parameters
    ----------
    limits_mm
        ``limits_mm(line) -> (L, n)`` mm, e.g. ``services.limits.Limits.for_line``.
    limit_levels
        The ``L`` level names, e.g. ``Limits.levels``.
    horizons_days
        Forecast horizons.
    detect_maintenance
        Look for unreported tampings in the on-board data after each index (:func:`detect`).
    """

    def __init__(
        self,
        limits_mm,
        limit_levels: Iterable[str],
        horizons_days: Iterable[float] = HORIZONS_DAYS,
        *,
        detect_maintenance: bool = True,
        loader: LogLoader | None = None,
    ) -> None:
        self.detect_maintenance = detect_maintenance  # :func:`detect` after each index
        self.histories = Histories(loader)
        self.models = Models()
        self._scratch = Scratch()  # the stacked states of the live and backlog folds
        # the rows of the bank a batch's fold took for resting segments, until the swap
        self._taken: list[tuple[SegmentId, BankRow]] = []
        self._limits_mm = limits_mm
        self.limit_levels = list(limit_levels)
        self.horizons_days = np.asarray(tuple(horizons_days), dtype=np.float64)

    def step(self, msg: EventMessage | ModelMessage) -> Step:
        """Apply one decoded message; the returned states are the segments it changed.

        A model is :meth:`update_models` of that one message; an invalid one raises
        ValueError with the reason (the service turns it into a dead letter).
        """
        if isinstance(msg, Calibration | DegradationPosterior):
            update = self.update_models([msg])
            if update.refused:
                raise ValueError(update.refused[0][1])
            if update.ignored:
                return Step(False, update.ignored[0][1])
            return Step(True, "", update.states)
        event = event_of(msg)
        sid = (msg.line, msg.segment)
        hist = self.histories.get(sid) or SegmentHistory(msg.line, msg.segment)
        hist, reason = step_segment(hist, event, self.models)
        if reason:
            return Step(False, reason)
        hist, found = self._detect(hist)
        out = self.segment_state(hist)  # before the swap: if it raises, nothing changed
        self.histories[sid] = hist
        return Step(True, "", () if out is None else (out,), () if found is None else (found,))

    def _detect(self, hist: SegmentHistory) -> tuple[SegmentHistory, MaintenanceEvent | None]:
        return detect(hist, self.models) if self.detect_maintenance else (hist, None)

    def step_events(self, msgs: Sequence[EventMessage]) -> tuple[list[str], tuple, list]:
        """Fold several events and summarise each changed segment once, in batches.

        Returns ``(reasons, states, detected)``: per message ``""`` if accepted, else why
        not; the newest SegmentState of each changed, publishable segment; and the tampings
        :func:`detect` found on the way. The histories are the same as after stepping the
        messages one by one, bit for bit (:meth:`fold_events`), and so are the final states
        (:meth:`segment_states` is :meth:`segment_state` in batches); only the intermediate
        states of a segment are not summarised. If anything raises, nothing is changed.
        """
        try:
            reasons, changed, detected = self._fold_events(msgs)
            states = self.segment_states([_summarised(h) for h in changed.values()])
        except BaseException:  # before the swap: nothing changed
            self._settle()
            raise
        self._swap(changed)
        self._settle()
        return reasons, tuple(state for state in states if state is not None), detected

    def fold_events(self, msgs: Sequence[EventMessage]) -> tuple[list[str], list, list]:
        """:meth:`step_events` without the summaries: ``(reasons, changed, detected)``, with
        the ids of the segments whose history changed (their states: :meth:`states_of`)."""
        try:
            reasons, changed, detected = self._fold_events(msgs)
        except BaseException:  # nothing changed
            self._settle()
            raise
        self._swap(changed)
        self._settle()
        return reasons, list(changed), detected

    def _settle(self) -> None:
        """Give back the rows the last batch's fold took and no segment rests in."""
        taken, self._taken = self._taken, []
        self.histories.settle(taken)

    def states_of(self, sids: Iterable[SegmentId]) -> list[SegmentState]:
        """The publishable SegmentStates of the segments ``sids`` (in batches; a resting
        segment's log is not read)."""
        known = [sid for sid in sids if sid in self.histories]
        resting = iter(
            self.histories.resting_many([s for s in known if not self.histories.is_loaded(s)])
        )
        hists = [
            _summarised(
                self.histories.load(sid) if self.histories.is_loaded(sid) else next(resting)
            )
            for sid in known
        ]
        return [state for state in self.segment_states(hists) if state is not None]

    def _fold_events(self, msgs: Sequence[EventMessage]):
        """``(reasons, changed, detected)`` of stepping ``msgs`` one by one, nothing swapped.

        The usual event, an on-board index after the last event of its segment's log on a
        segment with a state (live, a backfill in time order), is appended and left
        pending; the pending indices of all segments are folded from their states in one
        :func:`fold_many` at the end (several per segment: the logs differ in length).
        Anything else (a late index, a duplicate, a TRC record, a tamping, a segment
        without a state or a calibration for the index's unit) first folds its segment's
        pending indices, then takes the exact path of :meth:`step` (:func:`step_segment`,
        :func:`detect`). Detection runs after each index one by one: the batched fold halts
        a segment at the first index whose CUSUM reaches ``CUSUM_THRESHOLD``, runs
        :func:`detect` there and steps the segment's later indices one by one, so the
        result is bit for bit that of :meth:`step` per message (the fold does not depend
        on the other segments of a call, see :class:`_Banks`).
        """
        models = self.models
        # a segment's history after this batch's events so far; a resting one's (its log
        # not read) as a Checkpoint, its indices of this batch in ``tails``
        changed: dict[SegmentId, SegmentHistory | Checkpoint] = {}
        tails: dict[SegmentId, list[Event]] = {}
        pending: dict[SegmentId, list[tuple[int, Event]]] = {}  # appended, not yet folded
        folds_from: dict[SegmentId, SegmentHistory | Checkpoint] = {}  # base() of a pending one
        reasons = [""] * len(msgs)
        detected: list[tuple[int, MaintenanceEvent]] = []  # (message position, tamping)

        def base(sid: SegmentId) -> SegmentHistory | Checkpoint | None:
            """The segment as of this batch so far, a resting one without reading its log."""
            got = changed.get(sid)
            if got is not None:
                return got
            if self.histories.is_loaded(sid):
                return self.histories[sid]
            return self.histories.resting_entry(sid) if sid in self.histories else None

        def current(sid: SegmentId, msg: EventMessage) -> SegmentHistory:
            """The segment with its log: a resting one's read from the store (where this
            batch's events are not yet) and this batch's indices appended."""
            got = base(sid)
            if got is None:
                return SegmentHistory(msg.line, msg.segment)
            if isinstance(got, Checkpoint):
                stored = self.histories.load(sid)
                log = stored.log + tuple(tails.get(sid, ()))
                state = _state_of(got.state)
                got = _evolve(stored, log=log, trc_t=got.trc_t, state=state, group=got.group)
            return got

        def change(sid: SegmentId, hist: SegmentHistory) -> None:
            changed[sid] = hist
            tails.pop(sid, None)  # in its log now

        def exact(i: int, sid: SegmentId, hist: SegmentHistory, event: Event) -> None:
            hist, reason = step_segment(hist, event, models)
            reasons[i] = reason
            if not reason:
                hist, found = self._detect(hist)
                if found is not None:
                    detected.append((i, found))
                change(sid, hist)

        def flush(sids: Sequence[SegmentId]) -> None:
            """Fold the pending indices of ``sids``; a resting segment's from its row of the
            bank into a free row (``self._taken``), which it rests in after the swap."""
            if not sids:
                return
            hists = [folds_from.pop(sid) for sid in sids]  # each has a state
            groups = [group_of[sid] for sid in sids]
            queues = [pending.pop(sid) for sid in sids]  # (message position, event)
            logs = [[event for _, event in queued] for queued in queues]
            jobs: dict[tuple[int, bool], list[int]] = {}  # by Ns, and whether from the bank
            for k, group in enumerate(groups):
                ns, n = shape_of[group]
                state = hists[k].state
                banked = isinstance(state, BankRow) and (state.banks.ns, state.banks.n) == (ns, n)
                jobs.setdefault((ns, banked), []).append(k)
            halt = CUSUM_THRESHOLD if self.detect_maintenance else None
            for (ns, banked), job in jobs.items():
                states, folded = _fold_many(
                    [hists[k].state if banked else _state_of(hists[k].state) for k in job],
                    [logs[k] for k in job],
                    [models.params[groups[k]] for k in job],
                    models,
                    halt,
                    scratch=self._scratch,  # each state copied out: keeps no batch's arrays
                    into=self.histories.bank(ns, hists[job[0]].state.banks.n) if banked else None,
                )
                if banked and isinstance(states[0], BankRow):  # rows of the bank, all of them
                    self._taken.extend((sids[k], own) for k, own in zip(job, states, strict=True))
                    cusums = states[0].banks.cusum[[own.row for own in states]].tolist()
                else:  # (a model of another shape folds from copies: Filtered states)
                    cusums = [math.nan if own is None else own.cusum for own in states]
                for k, own, count, cusum in zip(job, states, folded, cusums, strict=True):
                    was, sid, log = hists[k], sids[k], logs[k]
                    tail = log if count == len(log) else log[:count]
                    if isinstance(was, Checkpoint):  # it stays resting: the log is not read
                        changed[sid] = _rested(was, own, groups[k], tail)
                        got = tails.get(sid)
                        if got is None:
                            tails[sid] = list(tail)
                        else:
                            got.extend(tail)
                    else:
                        changed[sid] = _evolve(
                            was, log=was.log + tuple(tail), state=own, group=groups[k]
                        )
                    if count < len(log) or halt is not None and cusum >= halt:
                        queued = queues[k]
                        hist, found = self._detect(current(sid, msgs[queued[0][0]]))
                        if found is not None:
                            detected.append((queued[count - 1][0], found))
                        change(sid, hist)
                        for i, event in queued[count:]:
                            exact(i, sid, changed[sid], event)

        group_of: dict[SegmentId, str | None] = {}  # the models do not change in a batch
        shape_of = {group: (p.ns, p.n) for group, p in models.params.items()}
        for i, msg in enumerate(msgs):
            sid = (msg.line, msg.segment)
            event = index_event(msg) if type(msg) is OnboardIndex else event_of(msg)
            queued = pending.get(sid)
            if event.kind == INDEX:
                if queued:
                    last = queued[-1][1].order
                else:
                    hist = base(sid)
                    if hist is None or hist.state is None:
                        last = None
                    elif isinstance(hist, Checkpoint):
                        last = hist.last_order
                    else:
                        last = hist.log[-1].order if hist.log else None
                group = group_of.get(sid, False)
                if group is False:
                    group = group_of[sid] = models.group_for(msg.line, msg.segment)
                if (
                    last is not None
                    and (event.t_s > last[0] or event.order > last)
                    and group is not None
                    and models.observation_for(msg.train, msg.unit) is not None
                ):
                    if not queued:
                        pending[sid] = queued = []
                        folds_from[sid] = hist  # what base(sid) stays until its flush
                    queued.append((i, event))
                    continue
            if queued:
                flush([sid])
            exact(i, sid, current(sid, msg), event)
        flush(list(pending))
        detected.sort(key=lambda found: found[0])
        return reasons, changed, [found for _, found in detected]

    def update_models(self, msgs: Sequence[ModelMessage]) -> ModelUpdate:
        """Apply several model messages at once, re-running each affected segment once.

        Keeps the newest version per model name (``calibration``,
        ``degradation/{group}``) among the valid messages newer than the one held, checks
        each completely (:func:`parse_model`) before anything is replaced, then re-runs the
        union of the segments they affect in one batched pass (:func:`replay_many`). The
        swap is atomic: if the re-run fails, the models and histories stay as they were and
        the messages are refused with the reason (one by one if there were several, so
        that a good one still applies). Same final states as stepping the messages one by
        one, in any order.
        """
        models, newest, ignored, refused = self._newest_models(msgs)
        if not newest:
            return ModelUpdate([], ignored, refused)
        calibrated = any(isinstance(m, Calibration) and not m.train for m in newest.values())
        units = {
            (m.train, m.unit) for m in newest.values() if isinstance(m, Calibration) and m.train
        }
        groups = {msg.group for msg in newest.values() if isinstance(msg, DegradationPosterior)}
        affected = [
            sid
            for sid in self.histories
            if calibrated
            or models.group_for(*sid) in groups
            or (units and not units.isdisjoint(self.histories.units(sid)))
        ]
        accepted = [msg for msg in msgs if newest.get(model_name(msg)) is msg]
        try:
            hists, states = self._rerun(models, affected)
        except (ValueError, ArithmeticError) as exc:
            if len(accepted) == 1:
                refused.append((accepted[0], f"re-run with this model failed: {exc}"))
                return ModelUpdate([], ignored, refused)
            one_by_one = [self.update_models([msg]) for msg in accepted]
            return ModelUpdate(
                [m for u in one_by_one for m in u.accepted],
                ignored + [m for u in one_by_one for m in u.ignored],
                refused + [m for u in one_by_one for m in u.refused],
                tuple(state for u in one_by_one for state in u.states),
            )
        self.models = models
        self._swap(hists)
        return ModelUpdate(accepted, ignored, refused, states)

    def _newest_models(self, msgs: Iterable[ModelMessage]):
        """``(models, newest, ignored, refused)``: the held models with the newest valid
        message per name applied (``newest`` by name), and the messages left out, with why."""
        ignored: list[tuple[ModelMessage, str]] = []
        refused: list[tuple[ModelMessage, str]] = []
        newest: dict[str, tuple[ModelMessage, Any]] = {}
        for msg in msgs:
            name = model_name(msg)
            held = held_version(self.models, msg)
            if held is not None and msg.version <= held:
                ignored.append((msg, "version not newer than the one held"))
                continue
            try:
                parsed = parse_model(msg)
            except ValueError as exc:
                refused.append((msg, str(exc)))
                continue
            previous = newest.get(name)
            if previous is not None:
                if msg.version <= previous[0].version:
                    why = f"superseded by version {previous[0].version} in the same update"
                    ignored.append((msg, why))
                    continue
                why = f"superseded by version {msg.version} in the same update"
                ignored.append((previous[0], why))
            newest[name] = (msg, parsed)
        models = self.models
        for msg, parsed in newest.values():
            models = _with_parsed(models, msg, parsed)
        return models, {name: msg for name, (msg, _) in newest.items()}, ignored, refused

    def load(self, models: Iterable[ModelMessage], events: Iterable[EventMessage]) -> list:
        """Rebuild from stored models and events (any order): the publishable states.

        A stored model that is no longer valid is skipped (:meth:`update_models` says why),
        so that it cannot stop a restart.
        """
        for msg in events:
            sid = (msg.line, msg.segment)
            hist = self.histories.get(sid) or SegmentHistory(msg.line, msg.segment)
            self.histories[sid] = add_event(hist, event_of(msg))[0]
        models_in, *_ = self._newest_models(models)
        hists, states = self._rerun(models_in, list(self.histories))
        self.models = models_in
        self._swap(hists)
        return list(states)

    def restore(
        self,
        models: Iterable[ModelMessage],
        checkpoints: Iterable[Checkpoint],
        tails: Mapping[SegmentId, Sequence[Event]],
        replay: Iterable[SegmentId] = (),
    ) -> tuple[list[SegmentId], list[SegmentState]]:
        """Restart from checkpoints: ``(kept, states)``.

        ``checkpoints``: each segment's last checkpoint (read once, in order: a stream
        keeps one state at a time besides the bank); ``tails``: per segment, the stored
        events its checkpoint does not cover; ``replay``: segments without a usable
        checkpoint (replayed from the log start, read through the loader; read after
        ``checkpoints``). A checkpoint
        folded with other models than the current ones (:func:`models_key` over the units
        its key names: a calibration of a unit its log does not read leaves it valid), or
        one written without its log's units, or followed
        by an event that sorts before its last one (a late event), is replayed from the
        log start too; one followed by newer events only is folded on over them (one
        :func:`fold_many` for all), which is the fold of the whole log, bit for bit.
        ``kept`` are the segments restored unchanged (their stored SegmentState still
        holds), ``states`` the SegmentStates of the others. The restored segments rest
        (their logs load when needed).
        """
        self.models, *_ = self._newest_models(models)
        full: set[SegmentId] = set()
        kept: list[SegmentId] = []
        on: list[tuple[SegmentId, Checkpoint, tuple[Event, ...]]] = []
        for ckpt in checkpoints:
            sid = (ckpt.line, ckpt.segment)
            units = key_units(ckpt.models_key)  # the units of its log, as written
            ckpt = replace(ckpt, units=units)
            self.histories.rest(sid, ckpt)
            tail = sorted(tails.get(sid, ()), key=lambda e: e.order)
            if (
                units is None
                or ckpt.models_key != models_key(self.models, *sid, units)
                or (tail and ckpt.last_order is not None and tail[0].order <= ckpt.last_order)
            ):
                full.add(sid)
            elif tail:
                on.append((sid, ckpt, tuple(tail)))
            else:
                kept.append(sid)
        full.update(replay)  # after the checkpoints: a stream of them may add to it
        for sid in full:
            if sid not in self.histories:  # no (usable) checkpoint: all from its log
                self.histories.rest(sid, Checkpoint(*sid, None, None, None, None), dirty=True)
        rested = self._fold_on(on)
        hists, states = self._rerun(self.models, sorted(full))
        self._swap(hists)
        for sid in hists:
            self.histories.dirty.add(sid)
        return kept, [*self._swap_states(rested), *states]

    def _fold_on(self, on: Sequence[tuple[SegmentId, Checkpoint, tuple[Event, ...]]]):
        """Fold each checkpoint on over its newer events (:meth:`restore`)."""
        out: dict[SegmentId, Checkpoint] = {}
        jobs: dict[int, list[int]] = {}
        for i, (sid, ckpt, tail) in enumerate(on):
            group = self.models.group_for(*sid)
            start = ckpt.state
            if group is None or not _publishable(tail, self.models, started=start is not None):
                out[sid] = _rested(ckpt, None, group, tail)
            else:
                jobs.setdefault(self.models.params[group].ns, []).append(i)
        for job in jobs.values():
            states = fold_many(
                [on[i][1].state for i in job],
                [on[i][2] for i in job],
                [self.models.params[self.models.group_for(*on[i][0])] for i in job],
                self.models,
            )
            for i, state in zip(job, states, strict=True):
                sid, ckpt, tail = on[i]
                out[sid] = _rested(ckpt, state, self.models.group_for(*sid), tail)
        return out

    def _swap_states(self, rested: Mapping[SegmentId, Checkpoint]) -> list[SegmentState]:
        for sid, ckpt in rested.items():
            self.histories.rest(sid, ckpt, dirty=True)
        hists = [_summarised(c) for c in rested.values()]
        return [s for s in self.segment_states(hists) if s is not None]

    def _swap(self, hists: Mapping[SegmentId, SegmentHistory | Checkpoint]) -> None:
        """Put re-run results in place: a history, or a resting state (log not kept)."""
        for sid, hist in hists.items():
            if isinstance(hist, Checkpoint):
                self.histories.rest(sid, hist, dirty=True)
            else:
                self.histories[sid] = hist

    def _rerun(
        self, models: Models, sids: Sequence[SegmentId]
    ) -> tuple[dict[SegmentId, SegmentHistory | Checkpoint], tuple[SegmentState, ...]]:
        """Re-run ``sids`` with ``models``; nothing is changed in place.

        In chunks of ``RERUN_CHUNK`` segments (one batched :func:`replay_many` and
        summary each): a segment whose log was not loaded is read for its chunk only (as
        columns when the store gives them: :meth:`Histories.load_columns`) and comes back
        resting (a :class:`Checkpoint`), so a re-run of every segment holds one chunk of
        logs at a time.
        """
        out: dict[SegmentId, SegmentHistory | Checkpoint] = {}
        states: list[SegmentState] = []
        for first in range(0, len(sids), RERUN_CHUNK):
            chunk = sids[first : first + RERUN_CHUNK]
            hists = replay_many([self.histories.load_columns(sid) for sid in chunk], models)
            states.extend(s for s in self.segment_states(hists, models) if s is not None)
            for sid, hist in zip(chunk, hists, strict=True):
                if self.histories.is_loaded(sid):
                    out[sid] = hist
                else:
                    out[sid] = checkpoint_of(hist)
        return out, tuple(states)

    def segment_states(
        self, hists: Sequence[SegmentHistory], models: Models | None = None
    ) -> list[SegmentState | None]:
        """The SegmentState messages of histories (None if not publishable), in batches."""
        models = self.models if models is None else models
        out: list[SegmentState | None] = [None] * len(hists)
        jobs: dict[int, list[int]] = {}
        for i, hist in enumerate(hists):
            if hist.state is not None and hist.group is not None:
                jobs.setdefault(hist.state.z.shape[0], []).append(i)
        limits: dict[str, np.ndarray] = {}
        for job in jobs.values():
            for first in range(0, len(job), SUMMARY_SEGMENTS):
                chunk = job[first : first + SUMMARY_SEGMENTS]
                for line in {hists[i].line for i in chunk} - limits.keys():
                    limits[line] = np.asarray(self._limits_mm(line), dtype=np.float64)
                states = summarize_states(
                    [hists[i] for i in chunk],
                    [models.params[hists[i].group] for i in chunk],
                    [limits[hists[i].line] for i in chunk],
                    self.limit_levels,
                    self.horizons_days,
                    calibration_version=(models.calibration.version if models.calibration else 0),
                    posterior_versions=[models.posteriors[hists[i].group].version for i in chunk],
                )
                for i, state in zip(chunk, states, strict=True):
                    out[i] = state
        return out

    def segment_state(self, hist: SegmentHistory) -> SegmentState | None:
        """The SegmentState message of a history (None if not publishable)."""
        return self.segment_states([hist])[0]

    def state_of(self, line: str, segment: str) -> SegmentState | None:
        hist = self.histories.get((line, segment))
        return None if hist is None else self.segment_state(hist)


def state_weights(state: Filtered) -> np.ndarray:
    """Normalised mixture weights (Ns,) of a state (``mixture.weights_from_log``)."""
    return weights_from_log(state.log_w)


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
    z = _stack([state.z for state in state_list])[:, None]  # (S, 1, Ns, n)
    P = _stack([state.P for state in state_list])[:, None]
    w = weights_from_log(_stack([state.log_w for state in state_list]))[:, None]
    h = np.concatenate(([0.0], horizons_days))
    z_all, P_all = transition_unchecked(z, P, _stacked(params), h)  # (S, 1 + h, Ns, n)
    limits = np.stack(limits_mm, axis=1)[:, :, None, :]  # (L, S, 1, n)
    both = summarize_unchecked(z_all, P_all, limits, weights=w)
    p_exceed = both.p_exceed  # (L, S, 1 + h, n)
    # Every number of the batch is checked here at once as SegmentState checks its arrays
    # (finite, probabilities in [0, 1]); then the first state is built checked and the
    # others as copies of it with their own arrays (same dtypes and shapes) and scalars,
    # whose checks run: a third of a summary's time was each state's 11 arrays checked
    # one by one. A batch that fails is built state by state, which raises the reason.
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
            "n_updates": state.n_updates,
            "nis": state.nis,
            "posterior_version": posterior_versions[row],
            "posterior_group": hist.group,
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
