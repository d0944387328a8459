"""A segment's events in the filter's terms: :class:`Event` (kind, time, identity, value)
made from a decoded message, a log's canonical order, and the log as columns
(:class:`LogColumns`)."""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np

from schemas import (
    DAY_S,
    Calibration,
    DegradationPosterior,
    MaintenanceEvent,
    OnboardIndex,
    TrcRecord,
)

TAMPING, RESTART, INDEX = 0, 1, 2  # kind priority at equal times: a TRC record after a tamping
KIND_NAMES = {RESTART: "trc", TAMPING: "maintenance", INDEX: "index"}

EventMessage = OnboardIndex | TrcRecord | MaintenanceEvent
ModelMessage = Calibration | DegradationPosterior


class Event(NamedTuple):
    """One segment event in the core's terms; ``order`` is its canonical sort key.

    A named tuple (immutable, compared field by field like a frozen dataclass): a re-run
    makes one per stored event, and a tuple is quicker to make than a dataclass."""

    kind: int  # RESTART, TAMPING or INDEX
    t_s: float  # epoch s of the event (a tamping's assumed time)
    identity: tuple[Any, ...]
    # z of a restart (an array) or y of an index (a pair) in log mm, NaN at an indicator the
    # record or index did not measure; None for a tamping
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
            if msg.top6_mm is not None and msg.align10_mm is not None:
                z = np.log([msg.top6_mm, msg.align10_mm])
                return Event(RESTART, msg.t, ("trc", msg.run_id, msg.t), z, msg)
            # a partial record: NaN where it measured nothing; its identity names what it
            # measured, so a level-only and an alignment-only record of one run are two
            z = np.log([math.nan if v is None else v for v in msg.values_mm])
            identity = ("trc", msg.run_id, msg.t, *msg.indicators)
            return Event(RESTART, msg.t, identity, z, msg)
        case MaintenanceEvent():
            return Event(TAMPING, tamping_time(msg), ("maintenance", msg.event_id), None, msg)
    raise TypeError(f"not a segment event: {type(msg).__name__}")


def is_full_restart(event: Event) -> bool:
    """A TRC record of every indicator: the state after it depends on nothing before it,
    so a segment's log starts at its latest one."""
    return event.kind == RESTART and not np.isnan(event.value).any()


def index_event(msg: Any) -> Event:
    """The core's event of an OnboardIndex, or of a stored one decoded without its checks
    (:func:`services.filtering.payloads.stored_events`): anything with its fields."""
    top, align = msg.top6_mm, msg.align10_mm
    if top is None or align is None:  # a unit measuring some indices only: NaN at the others
        y = (
            math.nan if top is None else math.log(top),
            math.nan if align is None else math.log(align),
        )
    else:
        y = (math.log(top), math.log(align))  # a tuple: an array each costs more
    return Event(INDEX, msg.t, ("index", msg.train, msg.unit, msg.t), y, msg)


@dataclass(frozen=True, eq=False)
class LogColumns:
    """A segment's canonical log as columns, without an object per event: what a re-run of
    a resting segment folds (a model change reads every segment's log, and an Event each
    would cost more than its fold). :func:`fold_many` takes it where it takes a tuple of
    Events, with the same bits: the same times and values, in the same order.

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


def log_units(log: Iterable[Event] | LogColumns) -> frozenset[tuple[str, str]]:
    """The ``(train, unit)`` of the indices of a log: whose calibrations its fold reads."""
    if isinstance(log, LogColumns):
        return frozenset(log.unit_names)
    return frozenset((e.message.train, e.message.unit) for e in log if e.kind == INDEX)


def outlives_restart(event: Event) -> bool:
    """A reported tamping stays in the log before a later TRC record: the restart makes it
    change nothing of the state, and it still decides which report of its ``event_id``
    holds (a lower-ranked one arriving later is refused, whatever the order)."""
    return event.kind == TAMPING and not event.message.detected


def canonical_log(events: Iterable[Event]) -> tuple[tuple[Event, ...], float | None]:
    """``(log, trc_t)`` of a segment's stored events (any order): the events at or after
    the latest TRC record of every indicator (:func:`is_full_restart`) and the reported
    tampings before it (:func:`outlives_restart`), in canonical order. The store holds
    exactly the accepted log (duplicates refused, superseded tampings and the other events
    before such a record deleted)."""
    events = list(events)
    restarts = [e.t_s for e in events if is_full_restart(e)]
    trc_t = max(restarts) if restarts else None
    kept = [e for e in events if trc_t is None or e.t_s >= trc_t or outlives_restart(e)]
    kept.sort(key=lambda e: e.order)
    return tuple(kept), trc_t
