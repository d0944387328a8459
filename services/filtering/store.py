"""Persistence of one filtering instance: accepted events and the latest models in SQLite.

The store holds what the tracker needs to rebuild every segment by replay: every accepted
event (with its kind, key, identity and event time) and the latest Calibration and the
latest DegradationPosterior of each group, each as the *decoded message re-encoded*, never
the payload as received: fields the schema does not know are dropped, so what a sender
adds to a message cannot grow the file (the payload size limits bound the rest). Each write is
its own committed transaction, done *before* the state it leads to is published, so a
SIGKILL loses nothing that was published (WAL journal; ``synchronous=NORMAL`` is durable
against a process crash, which is what the design asks for; power loss may drop the last
transactions: use ``synchronous="FULL"`` for that).

Events older than a segment's latest TRC record can no longer change its state and are
deleted when that record is stored (:meth:`Store.prune`).
"""

from __future__ import annotations

import json
import logging
import sqlite3
from collections.abc import Collection, Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from schemas import (
    DAY_S,
    Calibration,
    DegradationPosterior,
    MaintenanceEvent,
    OnboardIndex,
    SchemaError,
    SegmentState,
    TrcRecord,
    decode,
    encode,
    keys,
)
from schemas.keys import SegmentId
from services.filtering.tracker import (
    KIND_NAMES,
    RESTART,
    SUPERSEDE_DAYS,
    TAMPING,
    EventMessage,
    ModelMessage,
    Step,
    Tracker,
    event_of,
    model_name,
)

log = logging.getLogger(__name__)
_dumps = json.JSONEncoder().encode  # json.dumps with its defaults, without the per-call setup


_SCHEMA = """
CREATE TABLE IF NOT EXISTS events (
    seq      INTEGER PRIMARY KEY AUTOINCREMENT,
    line     TEXT NOT NULL,
    segment  TEXT NOT NULL,
    kind     TEXT NOT NULL,     -- index, trc, maintenance
    key      TEXT NOT NULL,     -- key expression it arrived on
    identity TEXT NOT NULL,     -- JSON of the tracker's identity tuple
    t        REAL NOT NULL,     -- epoch s of the event (a tamping's assumed time)
    payload  BLOB NOT NULL,     -- the decoded message, re-encoded (unknown fields dropped)
    UNIQUE (line, segment, identity)
);
CREATE INDEX IF NOT EXISTS events_segment_t ON events (line, segment, t);
CREATE TABLE IF NOT EXISTS models (
    name     TEXT PRIMARY KEY,  -- "calibration" or "degradation/{group}"
    kind     TEXT NOT NULL,     -- calibration, degradation
    version  INTEGER NOT NULL,
    key      TEXT NOT NULL,
    payload  BLOB NOT NULL
);
"""


class Store:
    """One SQLite file (created with its directory if missing); close it, or leave it to the OS.

    Parameters
    ----------
    path
        The database file.
    synchronous
        SQLite ``PRAGMA synchronous`` (``NORMAL``: durable against a process crash).
    """

    def __init__(self, path: str | Path, *, synchronous: str = "NORMAL") -> None:
        if synchronous.upper() not in {"OFF", "NORMAL", "FULL", "EXTRA"}:
            raise ValueError(f"synchronous: {synchronous!r} not OFF, NORMAL, FULL or EXTRA")
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        # One thread at a time: the service opens it, its single worker uses it, and it is
        # closed after the worker has been joined.
        self._db = sqlite3.connect(self.path, isolation_level=None, check_same_thread=False)
        self._db.execute("PRAGMA journal_mode=WAL")
        self._db.execute(f"PRAGMA synchronous={synchronous.upper()}")
        self._db.executescript(_SCHEMA)

    def close(self) -> None:
        self._db.close()

    def __enter__(self) -> Store:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()

    @contextmanager
    def transaction(self) -> Iterator[None]:
        """Every write inside the block is committed at its end, at once (or none on error)."""
        self._db.execute("BEGIN")
        try:
            yield
        except BaseException:
            self._db.execute("ROLLBACK")
            raise
        self._db.execute("COMMIT")

    def add_event(
        self,
        *,
        line: str,
        segment: str,
        kind: str,
        key: str,
        identity: tuple[Any, ...],
        t: float,
        payload: bytes,
    ) -> None:
        """Commit one accepted event; one row per identity, so a tamping report that the
        tracker accepted as a correction of its ``event_id`` replaces the stored one."""
        self.add_events([(line, segment, kind, key, identity, t, payload)])

    def add_events(
        self, rows: Iterable[tuple[str, str, str, str, tuple[Any, ...], float, bytes]]
    ) -> None:
        """:meth:`add_event` of several ``(line, segment, kind, key, identity, t, payload)``
        rows, in order, in one ``executemany``."""
        self._db.executemany(
            "INSERT INTO events (line, segment, kind, key, identity, t, payload)"
            " VALUES (?, ?, ?, ?, ?, ?, ?)"
            " ON CONFLICT (line, segment, identity) DO UPDATE SET"
            " kind = excluded.kind, key = excluded.key, t = excluded.t, payload = excluded.payload",
            [
                (line, segment, kind, key, _dumps(list(identity)), t, bytes(payload))
                for line, segment, kind, key, identity, t, payload in rows
            ],
        )

    def delete_detected(self, line: str, segment: str, t: float, within_s: float) -> int:
        """Delete the segment's detected tampings within ``within_s`` of ``t`` (a reported
        tamping replaces them); returns how many."""
        rows = self._db.execute(
            "SELECT rowid, payload FROM events WHERE line = ? AND segment = ?"
            " AND kind = 'maintenance' AND t BETWEEN ? AND ?",
            (line, segment, t - within_s, t + within_s),
        ).fetchall()
        gone = [(rowid,) for rowid, payload in rows if decode(payload, MaintenanceEvent).detected]
        self._db.executemany("DELETE FROM events WHERE rowid = ?", gone)
        return len(gone)

    def prune(self, line: str, segment: str, before_t: float) -> int:
        """Delete the segment's events older than ``before_t`` (its latest TRC record)."""
        cur = self._db.execute(
            "DELETE FROM events WHERE line = ? AND segment = ? AND t < ?",
            (line, segment, before_t),
        )
        return cur.rowcount

    def put_model(self, *, name: str, kind: str, version: int, key: str, payload: bytes) -> None:
        """Commit the latest model of ``name`` (the caller checked it is newer)."""
        self._db.execute(
            "INSERT INTO models (name, kind, version, key, payload) VALUES (?, ?, ?, ?, ?)"
            " ON CONFLICT (name) DO UPDATE SET kind = excluded.kind,"
            " version = excluded.version, key = excluded.key, payload = excluded.payload",
            (name, kind, version, key, bytes(payload)),
        )

    def models(self) -> Iterator[tuple[str, str, bytes]]:
        """``(kind, key, payload)`` of every stored model."""
        yield from self._db.execute("SELECT kind, key, payload FROM models ORDER BY name")

    def events(self) -> Iterator[tuple[str, str, bytes]]:
        """``(kind, key, payload)`` of every stored event, in the order they were accepted."""
        yield from self._db.execute("SELECT kind, key, payload FROM events ORDER BY seq")

    def count_events(self) -> int:
        return self._db.execute("SELECT COUNT(*) FROM events").fetchone()[0]


_EVENT_TYPES = {"index": OnboardIndex, "trc": TrcRecord, "maintenance": MaintenanceEvent}
_MODEL_TYPES = {"calibration": Calibration, "degradation": DegradationPosterior}


def decode_keyed(key: str, payload: bytes) -> EventMessage | ModelMessage | None:
    """Decode a payload by the kind chunk of its key; None for a model kind we do not use.

    Raises SchemaError when the payload is malformed or disagrees with its key.
    """
    kind = keys.kind(key)
    message_type: type[EventMessage | ModelMessage]
    if kind in _EVENT_TYPES:
        message_type = _EVENT_TYPES[kind]
    elif kind != "model":
        raise SchemaError(f"key {key}: not an index, trc, maintenance or model key")
    elif keys.model_kind(key) in _MODEL_TYPES:
        message_type = _MODEL_TYPES[keys.model_kind(key)]
    else:
        return None
    message = decode(payload, message_type)
    keys.check_key(key, message)
    return message


@dataclass(frozen=True)
class BatchResult:
    """What a batch did: the newest changed state of each segment, and what was refused."""

    states: tuple[SegmentState, ...]
    rejected: tuple[tuple[str, str, bytes], ...]  # (key, reason, payload): dead letters
    accepted: int
    detected: tuple[MaintenanceEvent, ...] = ()  # tamping found in the data: to publish
    # with ``summarize=False``: the segments the batch's events changed (not in ``states``)
    changed: tuple[SegmentId, ...] = ()


class PersistentTracker:
    """A :class:`Tracker` whose accepted inputs are committed to a :class:`Store` first.

    ``handle(key, payload)`` decodes, steps the tracker and, if the message was accepted,
    commits it before returning the states to publish. ``rebuild()`` replays the store.
    """

    def __init__(
        self,
        tracker: Tracker,
        store: Store,
        *,
        segments: Collection[SegmentId] | None = None,
        network_name: str = "the network",
        ns: str = keys.DEFAULT_NS,
    ) -> None:
        self.tracker = tracker
        self.store = store
        self.ns = ns  # the key a detected tamping is stored under
        self.segments = None if segments is None else frozenset(segments)
        self._network_name = network_name

    def _check_known(self, msg: EventMessage) -> None:
        """An event on a segment the network does not have is refused (when one is given):
        a sender cannot make the service hold segment histories for ids that do not exist."""
        if self.segments is not None and (msg.line, msg.segment) not in self.segments:
            raise SchemaError(
                f"{type(msg).__name__}: segment {msg.line}/{msg.segment} is not in "
                f"{self._network_name}"
            )

    def handle(self, key: str, payload: bytes) -> Step:
        msg = decode_keyed(key, payload)
        if msg is None:
            return Step(False, "not a model this service uses")
        if not isinstance(msg, Calibration | DegradationPosterior):
            self._check_known(msg)
        step = self.tracker.step(msg)
        if step.accepted:
            self._commit(msg, str(key))
            self._commit_detected(step.detected)
        return step

    def _commit_detected(self, found: Iterable[MaintenanceEvent]) -> None:
        for msg in found:
            self._commit(msg, keys.maintenance(self.ns, msg.line, msg.segment))

    def handle_batch(
        self, items: Iterable[tuple[str, bytes]], *, summarize: bool = True
    ) -> BatchResult:
        """Several ``(key, payload)`` in one store transaction.

        Model messages go first and are coalesced (:meth:`Tracker.update_models`): of
        several versions of one model only the newest is applied, each is validated, and
        the segments they affect are re-run once, in one batched pass. Then the
        events in the order given. Everything accepted is committed at the end, before the
        caller publishes the states; a payload that does not decode, or that the core
        refuses (a model that fails validation), is returned in ``rejected`` with the
        reason. A store error (``sqlite3.Error``) propagates: nothing of the batch is then
        persisted, and the caller must not go on with this tracker (nor after any other
        exception out of this method: the tracker may have moved on without the store).

        ``summarize=False``: the events' states are not summarised; ``changed`` lists the
        segments they changed, whose states :meth:`Tracker.states_of` gives when the
        caller publishes them (a model update's re-run states are in ``states`` still).
        The accepted rows go to the store grouped (:meth:`Store.add_events`), in order.
        """
        rejected: list[tuple[str, str, bytes]] = []
        models: list[tuple[ModelMessage, str, bytes]] = []
        events: list[tuple[EventMessage, str, bytes]] = []
        for key, payload in items:
            try:
                msg = decode_keyed(key, payload)
            except SchemaError as e:
                rejected.append((key, str(e), payload))
                continue
            if msg is None:
                continue
            if isinstance(msg, Calibration | DegradationPosterior):
                models.append((msg, key, payload))
                continue
            try:
                self._check_known(msg)
            except SchemaError as e:
                rejected.append((key, str(e), payload))
                continue
            events.append((msg, key, payload))
        states: dict[SegmentId, SegmentState] = {}

        def keep(new_states: Iterable[SegmentState]) -> None:
            for state in new_states:
                states.pop((state.line, state.segment), None)  # the newest, last
                states[(state.line, state.segment)] = state

        accepted = 0
        detected: list[MaintenanceEvent] = []
        changed: list[SegmentId] = []
        with self.store.transaction():
            if models:
                origin = {id(msg): (key, payload) for msg, key, payload in models}
                update = self.tracker.update_models([msg for msg, _, _ in models])
                for msg, reason in update.refused:
                    key, payload = origin[id(msg)]
                    rejected.append((key, reason, payload))
                self._commit_many([(msg, origin[id(msg)][0]) for msg in update.accepted])
                accepted += len(update.accepted)
                keep(update.states)
            try:
                if summarize:
                    reasons, event_states, found = self.tracker.step_events(
                        [msg for msg, _, _ in events]
                    )
                else:
                    reasons, changed, found = self.tracker.fold_events(
                        [msg for msg, _, _ in events]
                    )
                    event_states = ()
            except Exception:  # one of them cannot be folded: find it, one at a time
                log.info("a batch of %d events failed; stepping them one by one", len(events))
                for msg, key, payload in events:
                    try:
                        step = self.tracker.step(msg)
                    except ValueError as e:  # an event the core refuses
                        rejected.append((key, str(e), payload))
                        continue
                    except Exception as e:  # a bug: the letter says what, the batch goes on
                        log.exception("error stepping %s", key)
                        rejected.append((key, f"{type(e).__name__}: {e}", payload))
                        continue
                    if step.accepted:
                        accepted += 1
                        self._commit(msg, key)
                        self._commit_detected(step.detected)
                        detected.extend(step.detected)
                        keep(step.states)
            else:
                # detected ones first: a report later in the batch that supersedes one of
                # them then deletes its row, as the tracker dropped it from the log
                self._commit_detected(found)
                detected.extend(found)
                taken = [
                    (msg, key)
                    for (msg, key, _payload), reason in zip(events, reasons, strict=True)
                    if not reason
                ]
                accepted += len(taken)
                self._commit_many(taken)
                keep(event_states)
        return BatchResult(
            tuple(states.values()), tuple(rejected), accepted, tuple(detected), tuple(changed)
        )

    def _commit(self, msg: EventMessage | ModelMessage, key: str) -> None:
        self._commit_many([(msg, key)])

    def _commit_many(self, items: Iterable[tuple[EventMessage | ModelMessage, str]]) -> None:
        """Write accepted messages in order: runs of event rows in one ``executemany``; a
        TRC record's prune and a reported tamping's removal of detected ones run after the
        rows before them, as one message at a time would."""
        rows: list[tuple[str, str, str, str, tuple[Any, ...], float, bytes]] = []
        for msg, key in items:
            payload = encode(msg)  # not what was received: unknown fields are not kept
            match msg:
                case Calibration():
                    self.store.put_model(
                        name=model_name(msg),  # a unit's own model beside the fleet's
                        kind="calibration",
                        version=msg.version,
                        key=key,
                        payload=payload,
                    )
                case DegradationPosterior():
                    self.store.put_model(
                        name=f"degradation/{msg.group}",
                        kind="degradation",
                        version=msg.version,
                        key=key,
                        payload=payload,
                    )
                case OnboardIndex():  # event_of's identity and time, without its logs
                    rows.append(
                        (msg.line, msg.segment, "index", key,
                         ("index", msg.train, msg.unit, msg.t), msg.t, payload)
                    )  # fmt: skip
                case _:
                    event = event_of(msg)
                    kind = KIND_NAMES[event.kind]
                    line, segment = msg.line, msg.segment
                    rows.append((line, segment, kind, key, event.identity, event.t_s, payload))
                    if event.kind == RESTART:
                        self.store.add_events(rows)
                        rows = []
                        self.store.prune(line, segment, event.t_s)
                    elif event.kind == TAMPING and not msg.detected:
                        self.store.add_events(rows)
                        rows = []
                        self.store.delete_detected(line, segment, event.t_s, SUPERSEDE_DAYS * DAY_S)
        if rows:
            self.store.add_events(rows)

    def rebuild(self) -> list[SegmentState]:
        """Load every stored model and event into the tracker: the publishable states.

        A stored row that no longer decodes (written before a schema limit was added) is
        skipped with a warning rather than stopping the service at every start.
        """
        models = [m for m in self._decoded(self.store.models()) if m is not None]
        events = list(self._decoded(self.store.events()))
        return self.tracker.load(models, events)  # type: ignore[arg-type]

    @staticmethod
    def _decoded(
        rows: Iterable[tuple[str, str, bytes]],
    ) -> Iterator[EventMessage | ModelMessage | None]:
        for _kind, key, payload in rows:
            try:
                yield decode_keyed(key, payload)
            except SchemaError as e:
                log.warning("store: skipping a stored %s that no longer decodes: %s", key, e)
