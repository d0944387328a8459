"""Persistence of one filtering instance: accepted events and the latest models in SQLite.

The store holds what the tracker needs to rebuild every segment by replay: every accepted
event (with its kind, key, identity and event time) and the latest Calibration and the
latest DegradationPosterior of each group, each as the *decoded message re-encoded*, never
the payload as received: fields the schema does not know are dropped, so what a sender
adds to a message cannot grow the file (the payload size limits bound the rest). Each write is
committed *before* the state it leads to is published (a backlog's batch commits in a thread
while the next one folds, :meth:`Store.transaction`, and its states wait for it), so a
SIGKILL loses nothing that was published (WAL journal; ``synchronous=NORMAL`` is durable
against a process crash; power loss may drop the last transactions: use
``synchronous="FULL"`` for that). Each segment's checkpoint (its state without its log) is
stored too, so that a restart does not replay every log.

Events older than a segment's latest TRC record can no longer change its state and are
deleted when that record is stored (:meth:`Store.prune`).
"""

from __future__ import annotations

import contextlib
import itertools
import json
import logging
import sqlite3
import threading
from collections.abc import Callable, Iterable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from schemas import MaintenanceEvent, decode

log = logging.getLogger(__name__)
_dumps = json.JSONEncoder().encode  # json.dumps with its defaults, without the per-call setup
_INDEX_PREFIXES: dict[tuple[str, str], str] = {}  # index_identity's, by (train, unit)
_INDEX_PREFIXES_MAX = 65_536  # forgotten beyond this many (a flood of new ids cannot grow it)
# an INSERT of rows run at a transaction's end (Store._defer): its head ("INSERT INTO t (a, b)
# VALUES"), one row's values ("(?, ?)"), its tail (an ON CONFLICT clause or ""), the rows
_Insert = tuple[str, str, str, Sequence[tuple[Any, ...]]]
_INSERT_EVENTS = "INSERT INTO events (line, segment, kind, key, identity, t, payload) VALUES"
_PUT_POSITIONS = (
    "INSERT INTO delivery_positions (producer, epoch, seq) VALUES",
    "(?, ?, ?)",
    " ON CONFLICT (producer) DO UPDATE SET epoch = excluded.epoch, seq = excluded.seq",
)


def index_identity(train: str, unit: str, t: float) -> str:
    """``json.dumps(["index", train, unit, t])`` (an index's identity as the events table
    stores it; ``t`` finite, as the schema checks), the quoted ids kept per unit, so that a
    row's identity is one string format rather than a JSON encoding."""
    prefix = _INDEX_PREFIXES.get((train, unit))
    if prefix is None:
        if len(_INDEX_PREFIXES) >= _INDEX_PREFIXES_MAX:
            _INDEX_PREFIXES.clear()
        prefix = _INDEX_PREFIXES[(train, unit)] = f"{_dumps(['index', train, unit])[:-1]}, "
    return f"{prefix}{float.__repr__(t)}]"


CHECKPOINT_CHUNK = 2048  # checkpoint rows (~11 KB each) held at once when writing them all
CACHE_KIB = 65_536  # SQLite page cache: the indexes of a large store stay in memory
WAL_CHECKPOINT_S = 1.0  # the background thread copies the WAL into the database this often

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


def _dropped_with_events(table: str, suffix: str) -> str:
    """The triggers ``events_deleted{suffix}`` and ``events_updated{suffix}``: an event
    deleted or rewritten deletes its segment's rows of ``table``."""
    return "".join(
        f"CREATE TRIGGER IF NOT EXISTS events_{done}{suffix} AFTER {op} ON events BEGIN\n"
        f"    DELETE FROM {table} WHERE line = OLD.line AND segment = OLD.segment;\nEND;\n"
        for op, done in (("DELETE", "deleted"), ("UPDATE", "updated"))
    )


_SCHEMA = (
    "CREATE TABLE IF NOT EXISTS events "
    + _EVENTS_COLUMNS
    + """;
-- One row per (line, segment, identity): the tracker refuses an event whose identity its
-- log holds (a duplicate), and the one it takes in place of a stored one (a tamping's
-- correction, same event_id) replaces that row (Store.add_events). There is no UNIQUE
-- index on them: it would cost each insert a random page of wide keys (a file that has one
-- is migrated at open, Store._migrate_events). Nor an index on (line, segment, t): it would
-- cost every insert another B-tree (a file that has one loses it here).
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
-- per producer of the streams filtering reads (services.runtime.delivery), the seq up to
-- which its outbox's messages are folded into this store: a restart replays from there
CREATE TABLE IF NOT EXISTS delivery_positions (
    producer TEXT PRIMARY KEY,  -- "{service}/{instance}"
    epoch    TEXT NOT NULL,     -- the producer's numbering (its outbox file)
    seq      INTEGER NOT NULL
);
CREATE TABLE IF NOT EXISTS checkpoint_meta (
    name  TEXT PRIMARY KEY,
    value INTEGER NOT NULL
);
-- an event deleted or rewritten under a checkpoint (a TRC record pruning, a reported
-- tamping superseding a detected one, a correction) makes it stale: the segment is then
-- replayed from its log at restart
"""
    + _dropped_with_events("checkpoints", "")
    + """-- a segment's log as the columns a re-run folds (tracker.LogColumns, _ColumnsRow), as of
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
"""
    + _dropped_with_events("log_columns", "_columns")
)


def order_json(order: tuple[float, int, tuple[Any, ...]] | None) -> str | None:
    """A checkpoint's ``last_order`` (an event's canonical order key) as its stored text."""
    return None if order is None else json.dumps([order[0], order[1], list(order[2])])


def order_of(text: str | None) -> tuple[float, int, tuple[Any, ...]] | None:
    """:func:`order_json` back."""
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
    file: a backlog's COMMITs would pay it every few batches, in the worker's thread.
    ``ran`` is set after each checkpoint (for tests)."""

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
        """A file whose ``events`` table has a UNIQUE (line, segment, identity) constraint:
        the table is copied into one without it (one transaction; every row and ``seq``
        kept, and the sequence, so that no ``seq`` a checkpoint names is given again), then
        its index and triggers made again; ``migrating`` is told how many events first (the
        copy takes a time proportional to them)."""
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

    def delete_tamping(self, line: str, segment: str, identity: tuple[Any, ...]) -> int:
        """Delete the segment's stored tamping of ``identity`` (a detection the log no
        longer holds); returns how many rows."""
        cur = self._db.execute(
            "DELETE FROM events WHERE line = ? AND segment = ? AND kind = 'maintenance'"
            " AND identity = ?",
            (line, segment, _dumps(list(identity))),
        )
        return cur.rowcount

    def prune(self, line: str, segment: str, before_t: float) -> int:
        """Delete the segment's events older than ``before_t`` (its latest TRC record) but
        the reported tampings, which its log keeps (``events.outlives_restart``)."""
        cur = self._db.execute(
            "DELETE FROM events WHERE line = ? AND segment = ? AND t < ? AND kind != 'maintenance'",
            (line, segment, before_t),
        )
        rows = self._db.execute(
            "SELECT rowid, payload FROM events WHERE line = ? AND segment = ?"
            " AND kind = 'maintenance' AND t < ?",
            (line, segment, before_t),
        ).fetchall()
        found = [(rowid,) for rowid, payload in rows if decode(payload, MaintenanceEvent).detected]
        self._db.executemany("DELETE FROM events WHERE rowid = ?", found)
        return cur.rowcount + len(found)

    def put_positions(self, rows: Sequence[tuple[str, str, int]]) -> None:
        """Store ``(producer, epoch, seq)`` delivery positions, with the open transaction's
        events (at its end, like them)."""
        if rows:
            self._defer((*_PUT_POSITIONS, list(rows)))

    def positions(self) -> dict[str, tuple[str, int]]:
        """``{producer: (epoch, seq)}``: where the replay of each producer resumes."""
        rows = self._db.execute("SELECT producer, epoch, seq FROM delivery_positions")
        return {producer: (epoch, seq) for producer, epoch, seq in rows}

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
        # text), the events' newest seq read once
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
        checkpoints for MAX(gen) reads every row's pages); a file without that row is
        scanned once. Read once, then counted here (a read would wait for the commit in
        the background)."""
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
