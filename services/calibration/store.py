"""Persistence of the calibration core: what :meth:`Calibrator.drain_changes` says changed.

:class:`SqliteStore` (stdlib ``sqlite3``, one file per instance) and :class:`MemoryStore` (the
test double) both ``apply(changes)`` atomically and ``load()`` a :class:`StoredState` that
:class:`Calibrator` continues from: the models in force with the event time each was published
at (``models.published_at``, the rate limit's bookkeeping), and the accepted models not
published yet (``held``). Messages are kept as their wire bytes and floats as SQLite
REALs (IEEE doubles), so a restart gives back bit-identical models.
"""

from __future__ import annotations

import copy
import json
import math
import sqlite3
import threading
from pathlib import Path

from schemas import (
    Calibration,
    DegradationPosterior,
    MaintenanceEvent,
    OnboardIndex,
    TrcRecord,
    decode,
    encode,
)
from services.calibration.state import (
    Changes,
    ModelEntry,
    Pair,
    StoredState,
    index_id,
    is_calibration_key,
    maintenance_id,
    trc_id,
)

__all__ = ["MemoryStore", "SqliteStore"]

_SCHEMA = """
CREATE TABLE IF NOT EXISTS trc (id TEXT PRIMARY KEY, payload BLOB NOT NULL);
CREATE TABLE IF NOT EXISTS maintenance (id TEXT PRIMARY KEY, payload BLOB NOT NULL);
CREATE TABLE IF NOT EXISTS pending (id TEXT PRIMARY KEY, payload BLOB NOT NULL);
CREATE TABLE IF NOT EXISTS pairs (
    seq INTEGER PRIMARY KEY, line TEXT NOT NULL, segment TEXT NOT NULL, run_id TEXT NOT NULL,
    index_id TEXT NOT NULL UNIQUE, t REAL NOT NULL,
    z0 REAL NOT NULL, z1 REAL NOT NULL, y0 REAL NOT NULL, y1 REAL NOT NULL,
    quarantined INTEGER NOT NULL DEFAULT 0
);
CREATE TABLE IF NOT EXISTS partial_pairs (
    seq INTEGER PRIMARY KEY, line TEXT NOT NULL, segment TEXT NOT NULL, run_id TEXT NOT NULL,
    index_id TEXT NOT NULL UNIQUE, t REAL NOT NULL,
    z0 REAL NOT NULL, z1 REAL NOT NULL, y0 REAL, y1 REAL  -- NULL: an index not measured
);
CREATE TABLE IF NOT EXISTS models (
    key TEXT PRIMARY KEY, payload BLOB NOT NULL, fingerprint TEXT NOT NULL, prior INTEGER NOT NULL,
    published_at REAL
);
CREATE TABLE IF NOT EXISTS held (
    key TEXT PRIMARY KEY, payload BLOB NOT NULL, fingerprint TEXT NOT NULL, prior INTEGER NOT NULL
);
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
-- per producer, the seq up to which its outbox's messages are in this store: the replay
-- resumes there (services.runtime.delivery)
CREATE TABLE IF NOT EXISTS delivery_positions (
    producer TEXT PRIMARY KEY, epoch TEXT NOT NULL, seq INTEGER NOT NULL
);
"""


class MemoryStore:
    """In-memory store with the same contract as :class:`SqliteStore` (tests, dry runs)."""

    def __init__(self) -> None:
        self._state = StoredState()

    def apply(self, changes: Changes) -> None:
        s = self._state
        s.trc.extend(changes.trc)
        s.maintenance.extend(changes.maintenance)
        s.pending.extend(changes.pending_added)
        removed = set(changes.pending_removed)
        s.pending = [i for i in s.pending if index_id(i) not in removed]
        s.pairs.extend(changes.pairs)
        s.partial_pairs.extend(changes.partial_pairs)
        out = set(changes.quarantined)
        s.quarantined.extend(p for p in s.pairs if p.index_id in out)
        s.pairs = [p for p in s.pairs if p.index_id not in out]
        models = {e.key: e for e in s.models}
        models.update({e.key: e for e in changes.models})
        s.models = list(models.values())
        held = {e.key: e for e in s.held}
        held.update(changes.held)
        s.held = [e for e in held.values() if e is not None]
        if changes.meta is not None:
            s.meta = copy.deepcopy(changes.meta)
        s.positions.update(changes.positions)

    def load(self) -> StoredState:
        return copy.deepcopy(self._state)

    def close(self) -> None:
        pass


class SqliteStore:
    """One SQLite file; every :meth:`apply` is one transaction (WAL, survives SIGKILL)."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        # the service's single worker is the only user, but it is not the opening thread
        self._db = sqlite3.connect(self.path, check_same_thread=False, isolation_level=None)
        self._db.execute("PRAGMA journal_mode=WAL")
        self._db.execute("PRAGMA synchronous=NORMAL")  # durable against a killed process
        self._db.executescript(_SCHEMA)
        columns = {row[1] for row in self._db.execute("PRAGMA table_info(models)")}
        if "published_at" not in columns:  # a file from before publication times were kept
            self._db.execute("ALTER TABLE models ADD COLUMN published_at REAL")
        # close() may come from the opening thread while the worker is still in apply() (a
        # worker that did not stop within the runtime's grace): closing a connection in use
        # crashes the interpreter, so both hold this lock; apply() after close() raises.
        self._lock = threading.Lock()

    def apply(self, changes: Changes) -> None:
        if not changes:
            return
        with self._lock:
            self._apply(changes)

    def _apply(self, changes: Changes) -> None:
        db = self._db
        db.execute("BEGIN")
        try:
            db.executemany(
                "INSERT OR REPLACE INTO trc VALUES (?, ?)",
                [(trc_id(r), encode(r)) for r in changes.trc],
            )
            db.executemany(
                "INSERT OR REPLACE INTO maintenance VALUES (?, ?)",
                [(maintenance_id(e), encode(e)) for e in changes.maintenance],
            )
            db.executemany(
                "INSERT OR REPLACE INTO pending VALUES (?, ?)",
                [(index_id(i), encode(i)) for i in changes.pending_added],
            )
            db.executemany(
                "DELETE FROM pending WHERE id = ?", [(i,) for i in changes.pending_removed]
            )
            db.executemany(
                "INSERT INTO pairs (line, segment, run_id, index_id, t, z0, z1, y0, y1) "
                "VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?)",
                [(p.line, p.segment, p.run_id, p.index_id, p.t, *p.z, *p.y) for p in changes.pairs],
            )
            db.executemany(
                "INSERT INTO partial_pairs (line, segment, run_id, index_id, t, z0, z1, y0, y1) "
                "VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?)",
                [
                    (p.line, p.segment, p.run_id, p.index_id, p.t, *p.z,
                     *(None if math.isnan(y) else y for y in p.y))
                    for p in changes.partial_pairs
                ],
            )  # fmt: skip
            db.executemany(
                "UPDATE pairs SET quarantined = 1 WHERE index_id = ?",
                [(i,) for i in changes.quarantined],
            )
            db.executemany(
                "INSERT OR REPLACE INTO models (key, payload, fingerprint, prior, published_at) "
                "VALUES (?, ?, ?, ?, ?)",
                [
                    (e.key, encode(e.message), e.fingerprint, int(e.prior), e.published_at)
                    for e in changes.models
                ],
            )
            db.executemany(
                "INSERT OR REPLACE INTO held VALUES (?, ?, ?, ?)",
                [
                    (e.key, encode(e.message), e.fingerprint, int(e.prior))
                    for e in changes.held.values()
                    if e is not None
                ],
            )
            db.executemany(
                "DELETE FROM held WHERE key = ?",
                [(k,) for k, e in changes.held.items() if e is None],
            )
            if changes.meta is not None:
                db.execute(
                    "INSERT OR REPLACE INTO meta VALUES ('state', ?)", (json.dumps(changes.meta),)
                )
            db.executemany(
                "INSERT OR REPLACE INTO delivery_positions VALUES (?, ?, ?)",
                [(p, epoch, seq) for p, (epoch, seq) in changes.positions.items()],
            )
            db.execute("COMMIT")
        except BaseException:
            db.execute("ROLLBACK")
            raise

    def load(self) -> StoredState:
        db = self._db
        state = StoredState(
            trc=[decode(p, TrcRecord) for (p,) in db.execute("SELECT payload FROM trc")],
            maintenance=[
                decode(p, MaintenanceEvent)
                for (p,) in db.execute("SELECT payload FROM maintenance ORDER BY rowid")
            ],
            pending=[
                decode(p, OnboardIndex)
                for (p,) in db.execute("SELECT payload FROM pending ORDER BY rowid")
            ],
        )
        for line, segment, run_id, iid, t, z0, z1, y0, y1, out in db.execute(
            "SELECT line, segment, run_id, index_id, t, z0, z1, y0, y1, quarantined FROM pairs "
            "ORDER BY seq"
        ):
            pair = Pair(line, segment, run_id, iid, t, (z0, z1), (y0, y1))
            (state.quarantined if out else state.pairs).append(pair)
        for line, segment, run_id, iid, t, z0, z1, *y in db.execute(
            "SELECT line, segment, run_id, index_id, t, z0, z1, y0, y1 FROM partial_pairs "
            "ORDER BY seq"
        ):
            y = tuple(math.nan if v is None else v for v in y)
            state.partial_pairs.append(Pair(line, segment, run_id, iid, t, (z0, z1), y))
        for key, payload, fingerprint, prior, at in db.execute(
            "SELECT key, payload, fingerprint, prior, published_at FROM models ORDER BY key"
        ):
            kind = Calibration if is_calibration_key(key) else DegradationPosterior
            state.models.append(
                ModelEntry(key, decode(payload, kind), fingerprint, bool(prior), at)
            )
        for key, payload, fingerprint, prior in db.execute(
            "SELECT key, payload, fingerprint, prior FROM held ORDER BY key"
        ):
            kind = Calibration if is_calibration_key(key) else DegradationPosterior
            state.held.append(ModelEntry(key, decode(payload, kind), fingerprint, bool(prior)))
        row = db.execute("SELECT value FROM meta WHERE key = 'state'").fetchone()
        if row is not None:
            state.meta = json.loads(row[0])
        state.positions = {
            p: (epoch, seq)
            for p, epoch, seq in db.execute("SELECT producer, epoch, seq FROM delivery_positions")
        }
        return state

    def close(self) -> None:
        with self._lock:
            self._db.close()
