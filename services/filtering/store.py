"""Persistence of one filtering instance: accepted events and the latest models in SQLite.

The store holds what the tracker needs to rebuild every segment by replay: every accepted
event (with its kind, key, identity and event time) and the latest Calibration and the
latest DegradationPosterior of each group, each as the *decoded message re-encoded*, never
the payload as received: fields the schema does not know are dropped, so what a sender
adds to a message cannot grow the file (the payload size limits bound the rest). Each write is
committed *before* the state it leads to is published (a backlog's batch commits in a thread
while the next one folds, :meth:`Store.transaction`, and its states wait for it), so a
SIGKILL loses nothing that was published (WAL journal; ``synchronous=NORMAL`` is durable
against a process crash, which is what the design asks for; power loss may drop the last
transactions: use ``synchronous="FULL"`` for that).

Events older than a segment's latest TRC record can no longer change its state and are
deleted when that record is stored (:meth:`Store.prune`).
"""

from __future__ import annotations

import contextlib
import itertools
import json
import logging
import math
import operator
import sqlite3
import struct
import threading
import time
from collections.abc import Callable, Collection, Iterable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import msgspec
import numpy as np

from schemas import (
    DAY_S,
    SCHEMA_VERSION,
    Calibration,
    DegradationPosterior,
    MaintenanceEvent,
    OnboardIndex,
    SchemaError,
    SegmentState,
    TrcRecord,
    decode,
    decode_many,
    encode,
    keys,
)
from schemas.keys import SegmentId
from services.filtering.tracker import (
    INDEX,
    KIND_NAMES,
    RESTART,
    SUPERSEDE_DAYS,
    TAMPING,
    Checkpoint,
    Event,
    EventMessage,
    Filtered,
    LogColumns,
    ModelMessage,
    SegmentHistory,
    Step,
    Tracker,
    canonical_log,
    event_of,
    index_event,
    model_name,
    models_key,
)

log = logging.getLogger(__name__)
_dumps = json.JSONEncoder().encode  # json.dumps with its defaults, without the per-call setup
_INDEX_PREFIXES: dict[tuple[str, str], str] = {}  # index_identity's, by (train, unit)
_INDEX_PREFIXES_MAX = 65_536  # forgotten beyond this many (a flood of new ids cannot grow it)
# an INSERT of rows run at a transaction's end (Store._defer): its head ("INSERT INTO t (a, b)
# VALUES"), one row's values ("(?, ?)"), its tail (an ON CONFLICT clause or ""), the rows
_Insert = tuple[str, str, str, Sequence[tuple[Any, ...]]]
_INSERT_EVENTS = "INSERT INTO events (line, segment, kind, key, identity, t, payload) VALUES"


def index_identity(train: str, unit: str, t: float) -> str:
    """``json.dumps(["index", train, unit, t])`` (an index's identity as the events table
    stores it; ``t`` finite, as the schema checks), the quoted ids kept per unit: encoding
    each row's identity was 8 % of a backlog's time."""
    prefix = _INDEX_PREFIXES.get((train, unit))
    if prefix is None:
        if len(_INDEX_PREFIXES) >= _INDEX_PREFIXES_MAX:
            _INDEX_PREFIXES.clear()
        prefix = _INDEX_PREFIXES[(train, unit)] = f"{_dumps(['index', train, unit])[:-1]}, "
    return f"{prefix}{float.__repr__(t)}]"


CHECKPOINT_S = 10.0  # worker time between two checkpoints of the changed segments
CHECKPOINT_SLICE = 64  # segments checkpointed per batch once due (~5 ms of writing)
SLICE_EVENTS = 4096  # a batch's events per further slice
CHECKPOINT_CHUNK = 2048  # checkpoint rows (~11 KB each) held at once when writing them all
CACHE_KIB = 65_536  # SQLite page cache: the indexes of a large store stay in memory
WAL_CHECKPOINT_S = 1.0  # the background thread copies the WAL into the database this often
MAX_LOADED = 4096  # segment logs kept in memory (~1 KB an event; least recently used dropped)

_EVENTS_COLUMNS = """(
    seq      INTEGER PRIMARY KEY AUTOINCREMENT,
    line     TEXT NOT NULL,
    segment  TEXT NOT NULL,
    kind     TEXT NOT NULL,     -- index, trc, maintenance
    key      TEXT NOT NULL,     -- key expression it arrived on
    identity TEXT NOT NULL,     -- JSON of the tracker's identity tuple
    t        REAL NOT NULL,     -- epoch s of the event (a tamping's assumed time)
    payload  BLOB NOT NULL      -- the decoded message, re-encoded (unknown fields dropped)
)"""
_SCHEMA = (
    "CREATE TABLE IF NOT EXISTS events "
    + _EVENTS_COLUMNS
    + """;
-- One row per (line, segment, identity): the tracker refuses an event whose identity its
-- log holds (a duplicate), and the one it takes in place of a stored one (a tamping's
-- correction, same event_id) replaces that row (Store.add_events). A UNIQUE index on them
-- (older files: migrated at open, Store._migrate_events) cost each insert a random page
-- of wide keys: 4x the writing of a backlog's row on a 30,000-segment store.
-- An index on (line, segment, t) cost every insert another B-tree (10-18 % of a backlog's
-- time) and is dropped from older files.
DROP INDEX IF EXISTS events_segment_t;
-- a segment's rows: a restart reads its events after its checkpoint's seq, a pruning or a
-- tamping's lookup scans its ~100 rows
CREATE INDEX IF NOT EXISTS events_segment_seq ON events (line, segment, seq);
CREATE TABLE IF NOT EXISTS models (
    name     TEXT PRIMARY KEY,  -- "calibration" or "degradation/{group}"
    kind     TEXT NOT NULL,     -- calibration, degradation
    version  INTEGER NOT NULL,
    key      TEXT NOT NULL,
    payload  BLOB NOT NULL
);
CREATE TABLE IF NOT EXISTS checkpoints (
    line       TEXT NOT NULL,
    segment    TEXT NOT NULL,
    seq        INTEGER NOT NULL,  -- the newest events.seq when written: the log it covers
    last_order TEXT,              -- JSON [t, kind, identity] of the log's last event
    trc_t      REAL,
    grp        TEXT,              -- posterior group of the state
    models     TEXT NOT NULL,     -- the model versions it was folded with (models_key)
    state      BLOB,              -- the Filtered state, exact float64 (pack_state)
    summary    BLOB,              -- its encoded SegmentState, if known
    gen        INTEGER NOT NULL DEFAULT 0,  -- the checkpoint (transaction) that wrote it
    PRIMARY KEY (line, segment)
);
-- published_gen: the newest checkpoint whose states were all published (the one before
-- the latest, or the latest after a clean stop); gen: the newest checkpoint written
CREATE TABLE IF NOT EXISTS checkpoint_meta (
    name  TEXT PRIMARY KEY,
    value INTEGER NOT NULL
);
-- an event deleted or rewritten under a checkpoint (a TRC record pruning, a reported
-- tamping superseding a detected one, a correction) makes it stale: the segment is then
-- replayed from its log at restart
CREATE TRIGGER IF NOT EXISTS events_deleted AFTER DELETE ON events BEGIN
    DELETE FROM checkpoints WHERE line = OLD.line AND segment = OLD.segment;
END;
CREATE TRIGGER IF NOT EXISTS events_updated AFTER UPDATE ON events BEGIN
    DELETE FROM checkpoints WHERE line = OLD.line AND segment = OLD.segment;
END;
-- a segment's log as the columns a re-run folds (tracker.LogColumns, _ColumnsRow), as of
-- the newest events.seq it covers: a model change reads one row and the events after it
-- instead of decoding every stored payload. A cache: any event deleted or rewritten drops
-- it, and a segment without one is read from its events (and cached again)
CREATE TABLE IF NOT EXISTS log_columns (
    line     TEXT NOT NULL,
    segment  TEXT NOT NULL,
    seq      INTEGER NOT NULL,
    columns  BLOB NOT NULL,
    PRIMARY KEY (line, segment)
);
CREATE TRIGGER IF NOT EXISTS events_deleted_columns AFTER DELETE ON events BEGIN
    DELETE FROM log_columns WHERE line = OLD.line AND segment = OLD.segment;
END;
CREATE TRIGGER IF NOT EXISTS events_updated_columns AFTER UPDATE ON events BEGIN
    DELETE FROM log_columns WHERE line = OLD.line AND segment = OLD.segment;
END;
"""
)

_STATE_HEAD = struct.Struct("<2I 4d q 3d")  # ns, n; t_s, last_trc_t, nis, cusum; n_updates; ...


def pack_state(state: Filtered) -> bytes:
    """A Filtered state as bytes: header, then z, P, log_w as exact little-endian float64
    (None of ``last_trc_t``/``nis`` as NaN, as the batched bank holds them)."""
    ns, n = state.z.shape
    head = _STATE_HEAD.pack(
        ns,
        n,
        state.t_s,
        math.nan if state.last_trc_t is None else state.last_trc_t,
        math.nan if state.nis is None else state.nis,
        state.cusum,
        state.n_updates,
        state.cusum_t0,
        state.cusum_t1,
        0.0,
    )
    return head + np.ascontiguousarray(state.buffer(), dtype="<f8").tobytes()


def unpack_state(blob: bytes) -> Filtered:
    """:func:`pack_state` back; ValueError if the bytes are not one."""
    try:
        ns, n, t_s, trc, nis, cusum, n_updates, t0, t1, _ = _STATE_HEAD.unpack_from(blob)
    except struct.error as exc:
        raise ValueError(f"state: {exc}") from None
    sizes = (ns * n, ns * n * n, ns)
    if len(blob) != _STATE_HEAD.size + 8 * sum(sizes) or ns < 1 or n < 1:
        raise ValueError(f"state: {len(blob)} bytes for Ns={ns}, n={n}")
    flat = np.frombuffer(blob, dtype="<f8", offset=_STATE_HEAD.size).astype(np.float64)
    trc_t = None if math.isnan(trc) else trc
    nis_or_none = None if math.isnan(nis) else nis
    return Filtered.of_buffer(flat, ns, n, t_s, trc_t, int(n_updates), nis_or_none, cusum, t0, t1)


_KIND_CODES = {name: code for code, name in KIND_NAMES.items()}


def _order_json(order: tuple[float, int, tuple[Any, ...]] | None) -> str | None:
    return None if order is None else json.dumps([order[0], order[1], list(order[2])])


def _order_of(text: str | None) -> tuple[float, int, tuple[Any, ...]] | None:
    if text is None:
        return None
    t, kind, identity = json.loads(text)
    return (float(t), int(kind), tuple(identity))


class _WalCheckpointer:
    """Copies the write-ahead log into the database file every ``period_s`` from a thread of
    its own, on its own connection (``PRAGMA wal_checkpoint(PASSIVE)``: never waits for the
    writer, which goes on appending meanwhile).

    SQLite's automatic checkpoint runs inside the COMMIT that crosses 1,000 pages, in the
    writer's thread, and with ``synchronous=NORMAL`` it is the only write that syncs the
    file: a backlog's COMMITs paid it every few batches (the worker's slowest commits, up to
    64 ms; the backlog ran 10–40 % faster without it). ``ran`` is set after each checkpoint
    (for tests)."""

    def __init__(self, path: Path, period_s: float | None) -> None:
        self.path, self.period_s = path, period_s
        self.ran = threading.Event()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name="store-wal", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        try:
            db = sqlite3.connect(self.path, isolation_level=None)
        except sqlite3.Error as exc:  # then SQLite's own checkpoint at close is the only one
            log.warning("store %s: no WAL checkpoint thread: %s", self.path, exc)
            return
        try:
            while not self._stop.wait(self.period_s):
                try:
                    db.execute("PRAGMA wal_checkpoint(PASSIVE)").fetchone()
                except sqlite3.Error as exc:  # the writer's COMMIT fails too if the disk does
                    log.warning("store %s: WAL checkpoint failed: %s", self.path, exc)
                    continue
                self.ran.set()
        finally:
            db.close()

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join()


class Store:
    """One SQLite file (created with its directory if missing); close it, or leave it to the OS.

    Parameters
    ----------
    path
        The database file.
    synchronous
        SQLite ``PRAGMA synchronous`` (``NORMAL``: durable against a process crash).
    """

    def __init__(
        self,
        path: str | Path,
        *,
        synchronous: str = "NORMAL",
        wal_checkpoint_s: float | None = WAL_CHECKPOINT_S,
        migrating: Callable[[int], object] | None = None,
    ) -> None:
        if synchronous.upper() not in {"OFF", "NORMAL", "FULL", "EXTRA"}:
            raise ValueError(f"synchronous: {synchronous!r} not OFF, NORMAL, FULL or EXTRA")
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        # One thread at a time: the service opens it, its single worker uses it, and it is
        # closed after the worker has been joined.
        self._conn = sqlite3.connect(self.path, isolation_level=None, check_same_thread=False)
        self._deferred: list[_Insert] = []  # the open transaction's writes not yet run
        self._depth = 0  # transactions open (an inner one's writes are the outer one's)
        self._begun = False  # the open transaction's BEGIN ran (at its first statement)
        self._committing: threading.Thread | None = None  # a commit in the background
        self._failed: BaseException | None = None  # what a background commit raised
        self._gen: int | None = None  # the newest checkpoint generation, once read
        self._max_params = self._conn.getlimit(sqlite3.SQLITE_LIMIT_VARIABLE_NUMBER)
        self._db.execute("PRAGMA journal_mode=WAL")
        self._db.execute(f"PRAGMA synchronous={synchronous.upper()}")
        self._db.execute(f"PRAGMA cache_size={-CACHE_KIB}")
        self._db.executescript(_SCHEMA)
        self._migrate_events(migrating)
        self.wal_checkpoints = _WalCheckpointer(self.path, wal_checkpoint_s)
        if wal_checkpoint_s is not None:  # not in the committing thread: see _WalCheckpointer
            self._db.execute("PRAGMA wal_autocheckpoint=0")
            self.wal_checkpoints.start()

    def _migrate_events(self, migrating: Callable[[int], object] | None) -> None:
        """A file written before the events lost their UNIQUE (line, segment, identity)
        constraint: its ``events`` table is copied into one without it (one transaction;
        every row and ``seq`` kept, and the sequence, so that no ``seq`` a checkpoint
        names is given again), then its index and triggers made again; ``migrating`` is
        told how many events first (87 s for 12.1 M on the reference machine)."""
        names = [row[1] for row in self._db.execute("PRAGMA index_list(events)")]
        if not any(name.startswith("sqlite_autoindex_events") for name in names):
            return
        rows = self.count_events()
        log.info("store %s: migrating %d events to the table without UNIQUE", self.path, rows)
        if migrating is not None:
            migrating(rows)
        columns = "seq, line, segment, kind, key, identity, t, payload"
        with self.transaction():
            (sequence,) = self._db.execute(
                "SELECT COALESCE(MAX(seq), 0) FROM sqlite_sequence WHERE name = 'events'"
            ).fetchone()
            self._db.execute(f"CREATE TABLE events_migrated {_EVENTS_COLUMNS}")
            self._db.execute(
                f"INSERT INTO events_migrated ({columns}) SELECT {columns} FROM events ORDER BY seq"
            )
            self._db.execute("DROP TABLE events")  # and its index and triggers, made again below
            self._db.execute("ALTER TABLE events_migrated RENAME TO events")
            (copied,) = self._db.execute(
                "SELECT COALESCE(MAX(seq), 0) FROM sqlite_sequence WHERE name = 'events'"
            ).fetchone()
            self._db.execute("DELETE FROM sqlite_sequence WHERE name = 'events'")
            self._db.execute(
                "INSERT INTO sqlite_sequence (name, seq) VALUES ('events', ?)",
                (max(sequence, copied),),
            )
        self._db.executescript(_SCHEMA)

    def close(self) -> None:
        """Wait for a commit in the background (its failure is logged: the owner saw it
        at its last access, or stopped before one), then close."""
        self._join()
        if self._failed is not None:
            log.error("store %s: a commit in the background failed: %s", self.path, self._failed)
        self.wal_checkpoints.close()  # first: the last connection to close checkpoints all
        self._conn.close()

    @property
    def _db(self) -> sqlite3.Connection:
        """The connection, for any statement: once the commit in the background (if one
        runs) is done and the open transaction's deferred writes have run, in order."""
        self._ready()
        return self._conn

    def _ready(self) -> None:
        """The commit in the background done, the open transaction begun and its deferred
        writes run: a statement can run now, in order."""
        self.sync()
        if self._depth and not self._begun:
            self._conn.execute("BEGIN")
            self._begun = True
        if self._deferred:
            deferred, self._deferred = self._deferred, []
            self._run(deferred)

    def sync(self) -> None:
        """Wait for the commit in the background, if one runs; raise if it failed (and at
        every later access: the transaction is lost, the owner must stop)."""
        self._join()
        if self._failed is not None:
            failed = self._failed
            if isinstance(failed, sqlite3.Error):
                raise sqlite3.OperationalError(f"a commit in the background failed: {failed}")
            raise RuntimeError(f"a commit in the background failed: {failed!r}")

    def _join(self) -> None:
        if self._committing is not None:
            self._committing.join()
            self._committing = None

    @property
    def committing(self) -> bool:
        """The last transaction's commit is not known to have succeeded yet (it runs in
        the background, or it failed): what it wrote must not be published yet."""
        return self._failed is not None or (
            self._committing is not None and self._committing.is_alive()
        )

    def __enter__(self) -> Store:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()

    @contextmanager
    def transaction(self, *, background: bool = False) -> Iterator[None]:
        """Every write inside the block is committed at its end, at once (or none on error);
        a block inside another one is part of it.

        ``background``: the block's deferred writes (the events' rows, the checkpoint rows:
        :meth:`_defer`) and the COMMIT run in a thread of their own, while the caller goes
        on (SQLite runs them without the GIL: a backlog's next batch folds meanwhile). The
        next access to the store waits for it (:meth:`sync`), and raises if it failed;
        until then (:attr:`committing`) nothing it wrote may be published.

        The BEGIN runs at the block's first statement (a block of deferred writes only, a
        backlog's usual batch, does not wait for the previous commit in the background
        until its end)."""
        if self._depth:
            self._depth += 1
            try:
                yield
            finally:
                self._depth -= 1
            return
        self._depth, self._begun = 1, False
        try:
            yield
        except BaseException:
            self._deferred = []
            # begun: the previous commit was waited for; not begun: the connection may be
            # committing the previous transaction in the background, which is not ours
            if self._begun and self._conn.in_transaction:  # (SQLite may have rolled back)
                self._conn.execute("ROLLBACK")
            raise
        finally:
            self._depth = 0
        deferred, self._deferred = self._deferred, []
        begun, self._begun = self._begun, False
        self.sync()  # the previous commit's failure fails this one, written or not
        if not begun and not deferred:
            return
        if background and deferred:
            self._committing = threading.Thread(
                target=self._commit_in_background,
                args=(deferred, begun),
                name="store-commit",
            )
            self._committing.start()
            return
        try:
            if not begun:
                self._conn.execute("BEGIN")
            self._run(deferred)
            self._conn.execute("COMMIT")
        except BaseException:
            if self._conn.in_transaction:
                self._conn.execute("ROLLBACK")
            raise

    def _commit_in_background(self, deferred: list[_Insert], begun: bool) -> None:
        try:
            if not begun:
                self._conn.execute("BEGIN")
            self._run(deferred)
            self._conn.execute("COMMIT")
        except BaseException as exc:  # the owner sees it at its next access
            self._failed = exc
            with contextlib.suppress(sqlite3.Error):  # no transaction left open
                self._conn.execute("ROLLBACK")

    def _defer(self, insert: _Insert, *, now: bool = False) -> None:
        """Run an INSERT of rows at the end of the open transaction (in the background if
        the transaction is), or ``now`` (in order: after what was deferred), or now
        outside a transaction."""
        if self._depth and not now:
            self._deferred.append(insert)
        else:
            self._ready()
            self._run([insert])

    def _run(self, inserts: Sequence[_Insert]) -> None:
        """Each INSERT of rows as statements of many rows (a power of two each: SQLite's
        cache of statements keeps them): one statement a batch's events, so that a commit in
        the background binds and steps without asking for the GIL for every row, as
        ``executemany`` does (each ask waits up to the switch interval, 5 ms, while the
        owner's thread runs Python)."""
        for head, row, tail, rows in inserts:
            most = 1 << (self._max_params // row.count("?")).bit_length() - 1  # rows at most
            at = 0
            while at < len(rows):
                n = min(most, 1 << (len(rows) - at).bit_length() - 1)
                chunk = rows[at : at + n]
                params = list(itertools.chain.from_iterable(chunk))
                self._conn.execute(f"{head} {', '.join([row] * n)}{tail}", params)
                at += n

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
        self, rows: Iterable[tuple[str, str, str, str, tuple[Any, ...] | str, float, bytes]]
    ) -> None:
        """:meth:`add_event` of several ``(line, segment, kind, key, identity, t, payload)``
        rows, in order, in statements of many rows; an ``identity`` already as its JSON text
        is stored as it is.

        A tamping (``kind`` maintenance) first deletes the segment's stored row of its
        identity (a correction replaces the report); the other kinds are inserted as they
        are: the tracker refuses an event whose identity its log already holds, and the
        store holds that log (see ``_SCHEMA``). Inside a transaction the inserts run at its
        end (:meth:`_defer`)."""
        run: list[tuple[Any, ...]] = []
        for row in rows:
            line, segment, kind, key, identity, t, payload = row
            if type(identity) is not str or type(payload) is not bytes:  # else as it is
                text = identity if isinstance(identity, str) else _dumps(list(identity))
                row = (line, segment, kind, key, text, t, bytes(payload))
            if kind == "maintenance":
                if run:
                    self._defer((_INSERT_EVENTS, "(?, ?, ?, ?, ?, ?, ?)", "", run))
                    run = []
                self._db.execute(
                    "DELETE FROM events WHERE line = ? AND segment = ? AND kind = 'maintenance'"
                    " AND identity = ?",
                    (line, segment, row[4]),
                )
            run.append(row)
        if run:
            self._defer((_INSERT_EVENTS, "(?, ?, ?, ?, ?, ?, ?)", "", run))

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

    def segment_events(
        self, line: str, segment: str, *, indices: bool = True
    ) -> Iterator[tuple[str, str, bytes]]:
        """``(kind, key, payload)`` of one segment's stored events (its log, any order);
        without its indices if not ``indices``."""
        yield from self._db.execute(
            "SELECT kind, key, payload FROM events WHERE line = ? AND segment = ?"
            + ("" if indices else " AND kind != 'index'"),
            (line, segment),
        )

    def segment_index_payloads(self, line: str, segment: str) -> list[bytes]:
        """The payloads of one segment's stored OnboardIndex rows, any order."""
        rows = self._db.execute(
            "SELECT payload FROM events WHERE line = ? AND segment = ? AND kind = 'index'",
            (line, segment),
        ).fetchall()
        return [payload for (payload,) in rows]

    def segment_last_seq(self, line: str, segment: str) -> int:
        """The newest ``seq`` of one segment's stored events (0 if none)."""
        return self._db.execute(
            "SELECT COALESCE(MAX(seq), 0) FROM events WHERE line = ? AND segment = ?",
            (line, segment),
        ).fetchone()[0]

    def segment_events_after(self, line: str, segment: str, seq: int) -> list[tuple[Any, ...]]:
        """``(seq, kind, key, payload)`` of one segment's events newer than ``seq``."""
        return self._db.execute(
            "SELECT seq, kind, key, payload FROM events INDEXED BY events_segment_seq"
            " WHERE line = ? AND segment = ? AND seq > ?",
            (line, segment, seq),
        ).fetchall()

    def cached_columns(self, line: str, segment: str) -> tuple[int, bytes] | None:
        """``(seq, columns)`` of the segment's cached log columns, None if none."""
        return self._db.execute(
            "SELECT seq, columns FROM log_columns WHERE line = ? AND segment = ?",
            (line, segment),
        ).fetchone()

    def put_cached_columns(self, line: str, segment: str, seq: int, columns: bytes) -> None:
        """Cache the segment's log columns as of its event ``seq`` (what it covers)."""
        self._db.execute(
            "INSERT OR REPLACE INTO log_columns (line, segment, seq, columns) VALUES (?, ?, ?, ?)",
            (line, segment, seq, columns),
        )

    def put_checkpoints(self, rows: Iterable[tuple[Any, ...]], *, published: bool = True) -> int:
        """Write checkpoint rows ``(line, segment, last_order, trc_t, grp, models, state,
        summary)`` (replacing each segment's previous one) as a new generation, each
        covering the events stored before it (its ``seq``: the newest events.seq when the
        row is written); unless ``published`` is False the previous generation is then
        marked published (its states were published before this one was written: see
        :meth:`PersistentTracker.checkpoint`). Returns the generation. Inside a transaction
        the rows are written at its end (:meth:`_defer`), after its events."""
        gen = self._latest_gen() + 1
        self._defer(
            (
                "INSERT INTO checkpoint_meta (name, value) VALUES",
                "('gen', ?)",
                " ON CONFLICT (name) DO UPDATE SET value = excluded.value",
                [(gen,)],
            )
        )
        self._gen = gen
        # the same text for every generation (SQLite's cache of statements keeps one per
        # text: a text per generation held ~0.7 MB each), the events' newest seq read once
        head = (
            "INSERT OR REPLACE INTO checkpoints"
            " (line, segment, seq, last_order, trc_t, grp, models, state, summary, gen)"
            " SELECT v.column1, v.column2, m.seq, v.column3, v.column4, v.column5, v.column6,"
            " v.column7, v.column8, v.column9 FROM (VALUES"
        )
        row = "(?, ?, ?, ?, ?, ?, ?, ?, ?)"
        tail = ") AS v, (SELECT COALESCE(MAX(seq), 0) AS seq FROM events) AS m"
        rows = ((*r, gen) for r in rows)
        chunk = list(itertools.islice(rows, CHECKPOINT_CHUNK))
        if len(chunk) < CHECKPOINT_CHUNK:  # a slice: at the end of the transaction
            self._defer((head, row, tail, chunk))
        else:  # every segment's (a model change, a restore): now, a chunk at a time
            while chunk:
                self._defer((head, row, tail, chunk), now=True)
                chunk = list(itertools.islice(rows, CHECKPOINT_CHUNK))
        if published:
            self.set_published(gen - 1)
        return gen

    def set_published(self, gen: int | None = None) -> None:
        """Every checkpoint up to ``gen`` (default: the latest) holds published states."""
        if gen is None:
            gen = self._latest_gen()
        self._defer(
            (
                "INSERT INTO checkpoint_meta (name, value) VALUES",
                "('published_gen', ?)",
                " ON CONFLICT (name) DO UPDATE SET value = MAX(value, excluded.value)",
                [(gen,)],
            )
        )

    def _latest_gen(self) -> int:
        """The newest checkpoint generation: kept in ``checkpoint_meta`` (a scan of the
        checkpoints for MAX(gen) reads every row's pages: an estimated ~0.2 s a slice at
        100,000 segments); a file written before that row existed is scanned once. Read
        once, then counted here (a read would wait for the commit in the background)."""
        if self._gen is not None:
            return self._gen
        row = self._db.execute("SELECT value FROM checkpoint_meta WHERE name = 'gen'").fetchone()
        if row is None:
            row = self._db.execute("SELECT COALESCE(MAX(gen), 0) FROM checkpoints").fetchone()
        self._gen = row[0]
        return self._gen

    def published_gen(self) -> int:
        row = self._db.execute(
            "SELECT value FROM checkpoint_meta WHERE name = 'published_gen'"
        ).fetchone()
        return 0 if row is None else row[0]

    def checkpoints(self) -> Iterator[tuple[Any, ...]]:
        """Every checkpoint row, as :meth:`put_checkpoints` takes them, and its generation."""
        yield from self._db.execute(
            "SELECT line, segment, seq, last_order, trc_t, grp, models, state, summary, gen"
            " FROM checkpoints"
        )

    def tails(self) -> Iterator[tuple[str, str, str, str, bytes]]:
        """``(line, segment, kind, key, payload)`` of the stored events newer than their
        segment's checkpoint."""
        yield from self._db.execute(
            "SELECT e.line, e.segment, e.kind, e.key, e.payload FROM checkpoints c"
            " JOIN events e INDEXED BY events_segment_seq"
            " ON e.line = c.line AND e.segment = c.segment AND e.seq > c.seq"
        )

    def unchecked_segments(self) -> Iterator[tuple[str, str]]:
        """The segments with stored events and no checkpoint: one index seek per segment
        (a skip scan), not a read of every event."""
        checked = set(self._db.execute("SELECT line, segment FROM checkpoints"))
        sid = self._db.execute(
            "SELECT line, segment FROM events ORDER BY line, segment LIMIT 1"
        ).fetchone()
        while sid is not None:
            if sid not in checked:
                yield sid
            sid = self._db.execute(
                "SELECT line, segment FROM events WHERE (line, segment) > (?, ?)"
                " ORDER BY line, segment LIMIT 1",
                sid,
            ).fetchone()

    def delete_checkpoint(self, line: str, segment: str) -> None:
        self._db.execute("DELETE FROM checkpoints WHERE line = ? AND segment = ?", (line, segment))


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


def _indices_of(items: Sequence[tuple[str, bytes]]) -> list[OnboardIndex | None]:
    """Each item's OnboardIndex as :func:`decode_keyed` gives it, for the items on index
    keys, decoded in one call (:func:`schemas.decode_many`); None for the others, and for
    all of them when one does not decode or disagrees with its key (:func:`decode_keyed`
    then says why, one by one)."""
    out: list[OnboardIndex | None] = [None] * len(items)
    at = [i for i, (key, _payload) in enumerate(items) if key.split("/", 2)[1:2] == ["index"]]
    msgs = decode_many([items[i][1] for i in at], OnboardIndex)
    if msgs is None:
        return out
    for i, msg in zip(at, msgs, strict=True):
        if items[i][0].partition("/")[2] != f"index/{msg.line}/{msg.segment}":
            return [None] * len(items)  # keys.check_key's form: {ns}/index/{line}/{segment}
        out[i] = msg
    return out


def _unchecked(message_type: type) -> type:
    """A Struct with the fields (names, types, defaults) of ``message_type`` and none of its
    checks (``__post_init__``): what a stored row of it decodes into."""
    fields: list[tuple[Any, ...]] = []
    for f in msgspec.structs.fields(message_type):
        if f.default is not msgspec.NODEFAULT:
            fields.append((f.name, f.type, f.default))
        elif f.default_factory is not msgspec.NODEFAULT:
            fields.append((f.name, f.type, msgspec.field(default_factory=f.default_factory)))
        else:
            fields.append((f.name, f.type))
    return msgspec.defstruct(
        f"Stored{message_type.__name__}",
        fields,
        kw_only=True,
        frozen=True,
        forbid_unknown_fields=True,
    )


StoredIndex = _unchecked(OnboardIndex)
_STORED = {kind: msgspec.msgpack.Decoder(t) for kind, t in _EVENT_TYPES.items()}
_STORED_INDEX = msgspec.msgpack.Decoder(StoredIndex)


class _FoldedIndex(msgspec.Struct, frozen=True, kw_only=True, gc=False):
    """What the fold reads of a stored OnboardIndex (its other fields are skipped)."""

    v: int = SCHEMA_VERSION
    train: str
    unit: str
    t: float
    top6_mm: float
    align10_mm: float


_STORED_INDICES = msgspec.msgpack.Decoder(list[_FoldedIndex])
_TOP6, _ALIGN10 = operator.attrgetter("top6_mm"), operator.attrgetter("align10_mm")
_TIME, _VERSION, _UNIT = (
    operator.attrgetter("t"),
    operator.attrgetter("v"),
    operator.attrgetter("train", "unit"),
)
_ARRAY32 = struct.Struct(">BI")  # a MessagePack array header: 0xdd, then the count


def log_columns(
    index_payloads: Sequence[bytes], others: Iterable[Event]
) -> tuple[LogColumns, float | None] | None:
    """``(log, trc_t)`` of :func:`canonical_log`, as :class:`LogColumns`, from a segment's
    stored index payloads and its other events (TRC records, tampings); None when an index
    does not pass :func:`_stored_events`' checks (that path then skips it with a warning)
    or two events tie on (time, kind) (their canonical order then compares identities).

    The payloads are decoded in one call, as one MessagePack array of them, and the
    columns built without an Event per index: the same times and values (``math.log``, as
    :func:`~services.filtering.tracker.index_event`), so the fold gives the same bits.
    """
    try:
        msgs = _STORED_INDICES.decode(
            _ARRAY32.pack(0xDD, len(index_payloads)) + b"".join(index_payloads)
        )
    except (msgspec.DecodeError, msgspec.ValidationError):
        return None
    tops, aligns = list(map(_TOP6, msgs)), list(map(_ALIGN10, msgs))
    indices = np.array((tops, aligns))
    if set(map(_VERSION, msgs)) - {SCHEMA_VERSION} or not (
        (indices > 0.0).all() and (indices < math.inf).all()  # NaN fails both
    ):
        return None
    others = list(others)
    restarts = [e.t_s for e in others if e.kind == RESTART]
    trc_t = max(restarts) if restarts else None
    times = np.array(list(map(_TIME, msgs)), dtype=np.float64)
    if trc_t is not None:  # canonical_log keeps the events at or after the latest TRC record
        others = [e for e in others if e.t_s >= trc_t]
        kept = times >= trc_t
        if not kept.all():
            msgs, tops, aligns = (
                [x for x, keep in zip(column, kept.tolist(), strict=True) if keep]
                for column in (msgs, tops, aligns)
            )
            times = times[kept]
    n_index = len(msgs)
    units = list(map(_UNIT, msgs))
    names = {name: code for code, name in enumerate(dict.fromkeys(units))}
    codes = list(map(names.__getitem__, units))
    kinds = np.full(n_index + len(others), INDEX, dtype=np.int8)
    kinds[n_index:] = [e.kind for e in others]
    all_times = np.concatenate([times, [e.t_s for e in others]])
    values = np.zeros((len(kinds), 2))  # (Top6, Align10)
    values[:n_index, 0] = list(map(math.log, tops))
    values[:n_index, 1] = list(map(math.log, aligns))
    for k, e in enumerate(others, start=n_index):
        if e.value is not None:
            values[k] = e.value
    unit_codes = np.full(len(kinds), -1, dtype=np.int32)
    unit_codes[:n_index] = codes
    order = np.lexsort((kinds, all_times))  # by time, then kind
    kinds, all_times = kinds[order], all_times[order]
    if len(order) > 1 and ((all_times[1:] == all_times[:-1]) & (kinds[1:] == kinds[:-1])).any():
        return None
    last_order = None
    if len(order):
        last = int(order[-1])
        if last < n_index:
            m = msgs[last]
            last_order = (m.t, INDEX, ("index", m.train, m.unit, m.t))
        else:
            last_order = others[last - n_index].order
    columns = LogColumns(
        kinds, all_times, values[order], unit_codes[order], tuple(names), last_order
    )
    return columns, trc_t


class _ColumnsRow(msgspec.Struct, array_like=True, frozen=True, gc=False):
    """A :class:`LogColumns` and its ``trc_t`` as stored in ``log_columns``: the arrays as
    their exact little-endian bytes; ``layout`` names this layout (another is not read)."""

    layout: int
    trc_t: float | None
    last_order: tuple[float, int, tuple] | None
    unit_names: tuple[tuple[str, str], ...]
    kinds: bytes  # int8
    times: bytes  # <f8
    values: bytes  # <f8 (L, 2)
    unit_codes: bytes  # <i4


_COLUMNS_LAYOUT = 1
_COLUMNS_ROW = msgspec.msgpack.Decoder(_ColumnsRow)


def pack_columns(columns: LogColumns, trc_t: float | None) -> bytes:
    """A segment's log columns as the bytes the ``log_columns`` cache holds."""
    return encode(
        _ColumnsRow(
            _COLUMNS_LAYOUT,
            trc_t,
            columns.last_order,
            columns.unit_names,
            columns.kinds.astype(np.int8).tobytes(),
            columns.times.astype("<f8").tobytes(),
            columns.values.astype("<f8").tobytes(),
            columns.unit_codes.astype("<i4").tobytes(),
        )
    )


def unpack_columns(blob: bytes) -> tuple[LogColumns, float | None] | None:
    """:func:`pack_columns` back (read-only arrays over the bytes); None if the bytes are
    not one of this layout (the log is then read from its events)."""
    try:
        row = _COLUMNS_ROW.decode(blob)
        kinds = np.frombuffer(row.kinds, dtype=np.int8)
        times = np.frombuffer(row.times, dtype="<f8")
        values = np.frombuffer(row.values, dtype="<f8").reshape(-1, 2)
        codes = np.frombuffer(row.unit_codes, dtype="<i4")
    except (msgspec.DecodeError, msgspec.ValidationError, ValueError):
        return None
    if row.layout != _COLUMNS_LAYOUT or not (
        len(kinds) == len(times) == len(values) == len(codes)
        and (row.last_order is None) == (len(kinds) == 0)
        and (codes < len(row.unit_names)).all()
    ):
        return None
    last = row.last_order
    order = None if last is None else (last[0], last[1], tuple(last[2]))
    return LogColumns(kinds, times, values, codes, row.unit_names, order), row.trc_t


def columns_after(columns: LogColumns, tail: Sequence[Event]) -> LogColumns | None:
    """``columns`` with the segment's newer events ``tail`` (any order) appended: the
    columns :func:`log_columns` gives for the whole log, when every event of the tail is an
    index or a tamping that sorts after the log's last event (time, then kind; no two tied).
    None otherwise (a TRC record, which starts the log again, or a late event: the log is
    then read from its events)."""
    if not tail:
        return columns
    tail = sorted(tail, key=lambda e: e.order)
    keys = [(e.t_s, e.kind) for e in tail]
    if columns.last_order is not None:
        keys.insert(0, columns.last_order[:2])
    if any(e.kind == RESTART for e in tail) or any(map(operator.ge, keys, keys[1:])):
        return None
    names = {name: code for code, name in enumerate(columns.unit_names)}
    values = np.zeros((len(tail), 2))  # a tamping's: zeros
    unit_codes = np.full(len(tail), -1, dtype=np.int32)
    for k, e in enumerate(tail):
        if e.kind == INDEX:
            values[k] = e.value
            unit_codes[k] = names.setdefault((e.message.train, e.message.unit), len(names))
    return LogColumns(
        np.concatenate([columns.kinds, np.array([e.kind for e in tail], dtype=np.int8)]),
        np.concatenate([columns.times, [e.t_s for e in tail]]),
        np.concatenate([columns.values, values]),
        np.concatenate([columns.unit_codes, unit_codes]),
        tuple(names),
        tail[-1].order,
    )


def _stored_events(rows: Iterable[tuple[str, str, bytes]]) -> Iterator[Event]:
    """The core's events of stored ``(kind, key, payload)`` rows.

    The rows are the service's own re-encoding of messages it validated and whose key it
    checked, so they skip what guards the wire (size limit, nesting scan, key check): a
    re-run decodes every stored event, and those checks cost more than the fold. An index
    (nearly every row) is decoded into :data:`StoredIndex`, the same fields without the
    message's checks (13 of a re-run's 28 µs an event went there), and only what the fold
    needs is checked again: the schema version and two positive finite indices. TRC records
    and tampings run their checks. A row failing a check is skipped with a warning.
    """
    for kind, key, payload in rows:
        try:
            if kind == "index":
                msg = _STORED_INDEX.decode(payload)
                if msg.v != SCHEMA_VERSION or not (
                    0.0 < msg.top6_mm < math.inf and 0.0 < msg.align10_mm < math.inf
                ):
                    raise SchemaError(f"v {msg.v}, indices {msg.top6_mm}, {msg.align10_mm}")
                yield index_event(msg)
                continue
            msg = _STORED[kind].decode(payload)
        except (KeyError, msgspec.DecodeError, msgspec.ValidationError, SchemaError) as e:
            log.warning("store: skipping a stored %s that no longer decodes: %s", key, e)
            continue
        yield event_of(msg)


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
        checkpoint_s: float = CHECKPOINT_S,
        max_loaded: int = MAX_LOADED,
    ) -> None:
        self.tracker = tracker
        self.store = store
        self.ns = ns  # the key a detected tamping is stored under
        self.segments = None if segments is None else frozenset(segments)
        self._network_name = network_name
        if tracker.histories.loader is None:
            tracker.histories.loader = self.segment_log
        if tracker.histories.columns is None:
            tracker.histories.columns = self.segment_columns
        self.checkpoint_s = checkpoint_s
        self.max_loaded = max_loaded
        self.broken = False  # set by the owner when a batch failed: no checkpoint then
        self._summaries: dict[SegmentId, SegmentState] = {}  # newest, of dirty segments
        self._checkpointed = time.monotonic()
        self._due: list[SegmentId] | None = None  # a due checkpoint's segments left to write

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
        self,
        items: Iterable[tuple[str, bytes]],
        *,
        summarize: bool = True,
        background: bool = False,
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

        ``background``: the transaction commits in the background
        (:meth:`Store.transaction`), with the checkpoint slice due after it: the call
        returns before its events are stored, and nothing of the batch may be published
        until :attr:`Store.committing` is False (or :meth:`Store.sync` returned). A commit
        that fails raises at the store's next access (the next batch): stop then, as after
        a store error here.
        """
        rejected: list[tuple[str, str, bytes]] = []
        models: list[tuple[ModelMessage, str, bytes]] = []
        events: list[tuple[EventMessage, str, bytes]] = []
        items = list(items)
        indices = _indices_of(items)
        for (key, payload), index in zip(items, indices, strict=True):
            if index is not None:
                msg: EventMessage | ModelMessage | None = index
            else:
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
        with self.store.transaction(background=background):
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
            self._after_batch(states.values(), models=bool(models), events=len(events))
        return BatchResult(
            tuple(states.values()), tuple(rejected), accepted, tuple(detected), tuple(changed)
        )

    def _commit(self, msg: EventMessage | ModelMessage, key: str) -> None:
        self._commit_many([(msg, key)])

    def _commit_many(self, items: Iterable[tuple[EventMessage | ModelMessage, str]]) -> None:
        """Write accepted messages in order: runs of event rows in one :meth:`Store.add_events`; a
        TRC record's prune and a reported tamping's removal of detected ones run after the
        rows before them, as one message at a time would."""
        rows: list[tuple[str, str, str, str, tuple[Any, ...] | str, float, bytes]] = []
        for msg, key in items:
            payload = encode(msg)  # not what was received: unknown fields are not kept
            if type(msg) is OnboardIndex:  # event_of's identity and time, without its logs
                identity = index_identity(msg.train, msg.unit, msg.t)
                rows.append((msg.line, msg.segment, "index", key, identity, msg.t, payload))
                continue
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
        """:meth:`restore`, decoded: the publishable states of every segment."""
        return [decode(payload, SegmentState) for _sid, payload, _new in self.restore()]

    def restore(self) -> list[tuple[SegmentId, bytes, bool]]:
        """Bring the tracker back from the store: ``(segment, encoded SegmentState,
        unpublished)`` of every publishable segment; ``unpublished`` is False for a state
        restored from a checkpoint known to have been published (one older than the last
        checkpoint, or the last one after a clean stop), True otherwise (to publish again).

        Every stored model, then each segment's checkpoint (:meth:`Tracker.restore`): its
        state as stored and its stored SegmentState when nothing came after it; folded on
        over the events stored after it when they all sort after its last one; replayed
        from its whole log (read from the store) when one sorts before (a late event), when
        the models changed since, when it has no checkpoint, or when its row no longer
        decodes. The logs are not read otherwise (they load when a segment needs them).
        A stored row that no longer decodes (written before a schema limit was added) is
        skipped with a warning rather than stopping the service at every start.
        """
        models = [m for m in self._decoded(self.store.models()) if m is not None]
        summaries: dict[SegmentId, bytes] = {}
        published: set[SegmentId] = set()
        published_gen = self.store.published_gen()
        broken: list[SegmentId] = []

        def checkpoints() -> Iterator[Checkpoint]:
            """The stored checkpoints, one at a time (each state goes into the bank as it
            comes: a list of them held every state twice, 1.1 GB more at 100,000)."""
            rows = self.store.checkpoints()
            for line, segment, _seq, order, trc_t, grp, key, blob, summary, gen in rows:
                try:
                    state = None if blob is None else unpack_state(blob)
                    ckpt = Checkpoint(line, segment, trc_t, state, grp, _order_of(order), key)
                except (ValueError, TypeError) as e:
                    log.warning(
                        "store: checkpoint of %s/%s no longer decodes (%s)", line, segment, e
                    )
                    broken.append((line, segment))
                    continue
                if summary is not None:
                    summaries[(line, segment)] = summary
                    if gen <= published_gen:
                        published.add((line, segment))
                yield ckpt

        tails: dict[SegmentId, list[Event]] = {}
        for line, segment, kind, key, payload in self.store.tails():
            for event in _stored_events([(kind, key, payload)]):
                tails.setdefault((line, segment), []).append(event)
        # their logs: by the loader; read after the checkpoints, which add the broken ones
        replay = itertools.chain(broken, self.store.unchecked_segments())
        with self.store.transaction():  # the logs it caches as columns, in one commit
            kept, states = self.tracker.restore(models, checkpoints(), tails, replay)  # type: ignore[arg-type]
        out: list[tuple[SegmentId, bytes, bool]] = []
        unsummarised = []
        for sid in kept:
            if sid in summaries:
                out.append((sid, summaries[sid], sid not in published))
            else:
                unsummarised.append(self.tracker.histories.resting(sid))
        hists = [
            SegmentHistory(c.line, c.segment, (), c.trc_t, c.state, c.group) for c in unsummarised
        ]
        fresh = [s for s in (*states, *self.tracker.segment_states(hists)) if s is not None]
        for state in fresh:
            sid = (state.line, state.segment)
            self._summaries[sid] = state
            self.tracker.histories.dirty.add(sid)
            out.append((sid, encode(state), True))
        # what is restored has not been published again yet: not marked published
        self.checkpoint(published=False)
        return out

    def segment_log(self, line: str, segment: str) -> tuple[tuple[Event, ...], float | None]:
        """The segment's log from the store (:func:`canonical_log`): the tracker's loader."""
        return canonical_log(_stored_events(self.store.segment_events(line, segment)))

    def segment_columns(self, line: str, segment: str) -> tuple[LogColumns, float | None] | None:
        """The segment's log from the store as :class:`LogColumns` (what :meth:`segment_log`
        gives, as columns): the tracker's column loader, for re-runs. None when a stored
        index does not pass :func:`_stored_events`' checks or two events tie on time and
        kind (their order then needs the identities): the re-run reads the log as events.

        From the ``log_columns`` cache when it holds the segment: its row, with the events
        stored after it appended (:func:`columns_after`); otherwise, or when they cannot
        be appended, from the stored events, and the result is cached (with the newer
        events, so the next re-run reads one row again)."""
        store = self.store
        cached = store.cached_columns(line, segment)
        if cached is not None and (read := unpack_columns(cached[1])) is not None:
            newer = store.segment_events_after(line, segment, cached[0])
            tail = list(_stored_events(row[1:] for row in newer))
            columns = columns_after(read[0], tail) if len(tail) == len(newer) else None
            if columns is not None:
                if newer:
                    seq = max(row[0] for row in newer)
                    store.put_cached_columns(line, segment, seq, pack_columns(columns, read[1]))
                return columns, read[1]
        seq = store.segment_last_seq(line, segment)
        read = log_columns(
            store.segment_index_payloads(line, segment),
            _stored_events(store.segment_events(line, segment, indices=False)),
        )
        if read is not None:
            store.put_cached_columns(line, segment, seq, pack_columns(*read))
        return read

    def _after_batch(self, states: Iterable[SegmentState], *, models: bool, events: int) -> None:
        """At the end of a batch's transaction, after its events: note its states;
        checkpoint when due (every ``checkpoint_s`` of worker time, or after a model
        change), in the same transaction, then bound the loaded logs to ``max_loaded``
        (they are all stored once it commits, before any read of the store)."""
        self.note_states(states)
        if models:
            self.checkpoint()
        else:  # a slice per batch, so that the live worker never stalls on one big write
            self.checkpoint_if_due(slices=1 + events // SLICE_EVENTS)

    def checkpoint_if_due(self, slices: int = 1) -> int:
        """Between batches: the next ``slices`` slices (``CHECKPOINT_SLICE`` segments each)
        of the checkpoint when one is due (every ``checkpoint_s`` of worker time) or being
        written; how many segments it wrote (0: none due). An idle owner calls it until 0,
        so that what an instance holds when traffic stops is checkpointed without waiting
        for a batch. A batch writes a slice and one more per ``SLICE_EVENTS`` of its events,
        so that a backlog's big batches move a checkpoint on as fast as small ones."""
        if self._due is not None or time.monotonic() - self._checkpointed >= self.checkpoint_s:
            return self.checkpoint(limit=CHECKPOINT_SLICE * slices)
        return 0

    def note_states(self, states: Iterable[SegmentState]) -> None:
        """The newest SegmentStates summarised for segments changed since the checkpoint:
        the next checkpoint stores each with its state when they still match (else the
        restart summarises it again)."""
        for state in states:
            self._summaries[(state.line, state.segment)] = state

    def checkpoint(self, *, published: bool = True, limit: int | None = None) -> int:
        """Write the checkpoint of every segment changed since the last one (one
        transaction; the tracker must hold what the store holds, i.e. between batches);
        then drop the least recently used logs beyond ``max_loaded``. Returns how many.

        With ``limit``: the segments changed when the checkpoint fell due, at most ``limit``
        per call (each segment's row stands alone), the rest by the next calls; what changes
        meanwhile waits for the next period, which starts once they are all written.

        When the owner publishes a batch's states before it hands over the next batch, the
        previous checkpoint's states have been published when this one is written
        (:meth:`Store.put_checkpoints` marks them so). The service publishes changed
        segments later under a backlog, so it does not rely on the mark: it publishes
        every restored state again (the mark only feeds its log line)."""
        histories = self.tracker.histories
        if limit is None or self._due is None:
            self._due = [sid for sid in histories.dirty if sid in histories]
        write = self._due if limit is None else self._due[:limit]
        self._due = self._due[len(write) :]
        if write:
            with self.store.transaction():
                rows = (self._checkpoint_row(sid) for sid in write)
                self.store.put_checkpoints(rows, published=published)
        for sid in write:
            histories.dirty.discard(sid)
            self._summaries.pop(sid, None)
        if not self._due:
            self._due = None
            self._checkpointed = time.monotonic()
            gone = [sid for sid in histories.dirty if sid not in histories]  # no longer held
            histories.dirty.difference_update(gone)
            histories.trim(self.max_loaded)
        return len(write)

    def _checkpoint_row(self, sid: SegmentId) -> tuple[Any, ...]:
        rest = self.tracker.histories.resting(sid)
        state, summary = rest.state, self._summaries.get(sid)
        if (
            state is None
            or summary is None
            or not (
                summary.t == state.t_s
                and summary.n_updates == state.n_updates
                and summary.nis == state.nis
                and summary.posterior_group == rest.group
            )
        ):
            summary = None  # not known for this state: summarised again at restart
        return (
            *sid,
            _order_json(rest.last_order),
            rest.trc_t,
            rest.group,
            models_key(self.tracker.models, *sid, rest.units),
            None if state is None else pack_state(state),
            None if summary is None else encode(summary),
        )

    def close(self) -> None:
        """At a clean stop: checkpoint what changed (not after a failed batch, when the
        tracker may hold what the store does not)."""
        if not self.broken:
            self.checkpoint()
            self.store.set_published()  # the worker published everything before it ended

    @staticmethod
    def _decoded(
        rows: Iterable[tuple[str, str, bytes]],
    ) -> Iterator[EventMessage | ModelMessage | None]:
        for _kind, key, payload in rows:
            try:
                yield decode_keyed(key, payload)
            except SchemaError as e:
                log.warning("store: skipping a stored %s that no longer decodes: %s", key, e)
