"""What the calibration core keeps and a store persists: pairs, models as stored, the
changes to write, and the identities that make events duplicates."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from schemas import Calibration, DegradationPosterior, MaintenanceEvent, OnboardIndex, TrcRecord

CALIBRATION_KEY = "calibration"  # ModelEntry.key of the Calibration; posteriors use their group


def unit_key(train: str, unit: str) -> str:
    """ModelEntry.key of a unit's own Calibration."""
    return f"{CALIBRATION_KEY}/{train}/{unit}"


def is_calibration_key(key: str) -> bool:
    """The fleet's or a unit's Calibration (a posterior group never has a ``/``)."""
    return key == CALIBRATION_KEY or key.startswith(CALIBRATION_KEY + "/")


Event = TrcRecord | OnboardIndex | MaintenanceEvent
Model = Calibration | DegradationPosterior


@dataclass(frozen=True)
class Pair:
    """One (TRC record, on-board index) pair: ``z`` and ``y`` in ln mm, ``t`` the index's (s)."""

    line: str
    segment: str
    run_id: str  # the TRC record's
    index_id: str
    t: float
    z: tuple[float, float]
    y: tuple[float, float]

    @property
    def unit(self) -> tuple[str, str]:
        """``(train, unit)`` of the index (from its id, :func:`index_id`)."""
        parts = self.index_id.split("/")
        return parts[2], parts[3]


@dataclass(frozen=True)
class Quarantine:
    """Something left out of a fit or a posterior, to report (a dead letter): ``kind`` is the
    key kind of what caused it (``trc`` or ``index``), ``message`` the record when kept."""

    kind: str
    line: str
    segment: str
    reason: str
    message: TrcRecord | None = None


@dataclass(frozen=True)
class ModelEntry:
    """A model as stored: ``key`` is ``"calibration"`` or the posterior's group.

    A model in force carries the event time it was published at (None for an initial model,
    or one stored before publication times were kept: the next version is not rate-limited);
    a held candidate (accepted, not published) carries None.
    """

    key: str
    message: Model
    fingerprint: str = ""  # of the posterior's inputs; "" for the calibration
    prior: bool = False  # an initial model (no data behind it)
    published_at: float | None = None  # epoch s of event time


@dataclass
class StoredState:
    """Everything a :class:`Calibrator` needs to continue: what a store loads."""

    trc: list[TrcRecord] = field(default_factory=list)
    maintenance: list[MaintenanceEvent] = field(default_factory=list)
    pending: list[OnboardIndex] = field(default_factory=list)  # unpaired, in arrival order
    pairs: list[Pair] = field(default_factory=list)  # in arrival order
    quarantined: list[Pair] = field(default_factory=list)  # left out of fits
    # pairs of indices of some indices only (y NaN at the others): for their unit's model
    partial_pairs: list[Pair] = field(default_factory=list)
    models: list[ModelEntry] = field(default_factory=list)  # in force (published)
    held: list[ModelEntry] = field(default_factory=list)  # accepted, not (yet) published
    meta: dict[str, Any] = field(default_factory=dict)
    # producer -> (epoch, seq): where the replay of its outbox resumes (the service's, not
    # the core's: services.runtime.delivery)
    positions: dict[str, tuple[str, int]] = field(default_factory=dict)


@dataclass
class Changes:
    """What changed since the last :meth:`Calibrator.drain_changes`: what a store writes."""

    trc: list[TrcRecord] = field(default_factory=list)
    maintenance: list[MaintenanceEvent] = field(default_factory=list)
    pending_added: list[OnboardIndex] = field(default_factory=list)
    pending_removed: list[str] = field(default_factory=list)  # index ids
    pairs: list[Pair] = field(default_factory=list)
    partial_pairs: list[Pair] = field(default_factory=list)
    quarantined: list[str] = field(default_factory=list)  # index ids of pairs set aside
    models: list[ModelEntry] = field(default_factory=list)  # published, in order
    held: dict[str, ModelEntry | None] = field(default_factory=dict)  # key -> held now, or None
    meta: dict[str, Any] | None = None  # the whole meta when it changed
    positions: dict[str, tuple[str, int]] = field(default_factory=dict)  # replay positions

    def __bool__(self) -> bool:
        return bool(
            self.trc
            or self.maintenance
            or self.pending_added
            or self.pending_removed
            or self.pairs
            or self.partial_pairs
            or self.quarantined
            or self.models
            or self.held
            or self.meta is not None
            or self.positions
        )


def trc_id(rec: TrcRecord) -> str:
    return f"{rec.line}/{rec.segment}/{rec.run_id}"


def index_id(idx: OnboardIndex) -> str:
    return f"{idx.line}/{idx.segment}/{idx.train}/{idx.unit}/{idx.t!r}"


def maintenance_id(ev: MaintenanceEvent) -> str:
    return f"{ev.line}/{ev.segment}/{ev.event_id}"
