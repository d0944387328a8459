"""A producer's durable outbox: every message it publishes, numbered, in a SQLite file.

One file per producer identity ``{service}/{instance}``, held by one process at a time (an
exclusive lock on ``{file}.lock``; a second process gets :class:`OutboxBusy`)
(``{dir}/{service}-{instance}.sqlite``): an append-only log ``entries(seq, key, payload,
t_wall)``. ``seq`` numbers the producer's messages 1, 2, 3 … and continues after a restart
on the same file (the last number is kept in ``meta`` even when retention emptied the log),
so a consumer's position in a producer's stream survives both ends restarting. ``epoch``, a
random id made with the file, tells a consumer that a producer's numbering started over
(its file was removed).

Appends are batched: :meth:`Outbox.append_many` writes a batch in one transaction (WAL,
``synchronous=NORMAL``: a committed batch survives the process being killed; a power cut
may lose the last commits). Measured on the 2-core reference machine, 200-byte payloads:
35 µs per message committed one by one, under 5 µs per message in batches of 500; the
publisher (:mod:`services.runtime.delivery`) commits whatever is queued at once, so under a
backlog batches grow and the cost per message falls.

Retention: after a commit (at most once a second), entries older than ``max_age_s`` and,
oldest first, entries beyond ``max_bytes`` (keys plus payloads) are deleted.
``pruned_upto`` is the newest seq deleted by retention: a consumer whose position is below
it has lost what lay between.

A full disk (``sqlite3.OperationalError``: database or disk is full) or any other SQLite
error in an append rolls the batch back and raises :class:`OutboxFull`; the caller publishes
the batch live without sequence numbers and counts it (at most once for those messages).
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import sqlite3
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import IO

DEFAULT_MAX_BYTES = 2_000_000_000  # keys plus payloads kept per producer (2 GB)
DEFAULT_MAX_AGE_S = 7 * 86400.0  # how long an entry is kept (7 days)
PRUNE_EVERY_S = 1.0  # retention is applied after a commit at most this often

_SCHEMA = """
CREATE TABLE IF NOT EXISTS entries (
    seq INTEGER PRIMARY KEY, key TEXT NOT NULL, payload BLOB NOT NULL, t_wall REAL NOT NULL
);
CREATE TABLE IF NOT EXISTS meta (name TEXT PRIMARY KEY, value);
"""


def hold_exclusively(path: Path | str, busy: Exception) -> IO[str]:
    """``{path}.lock``, held with an exclusive lock until it is closed; ``busy`` raised when
    another process holds it (two writers never share one file)."""
    lockfile = open(f"{path}.lock", "a")  # noqa: SIM115 (held until the caller closes it)
    try:
        fcntl.flock(lockfile, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        lockfile.close()
        raise busy from None
    return lockfile


class OutboxBusy(Exception):
    """Another process holds this outbox (two producers may not share a numbering)."""


class OutboxFull(Exception):
    """An append could not be written (disk full, read-only file …); nothing was kept."""


@dataclass(frozen=True)
class Entry:
    seq: int
    key: str
    payload: bytes


class Outbox:
    """The append-only log of one producer. Thread-safe (one lock; appends and reads are
    short, and reads run on their own connection so that a long replay does not hold
    appends back)."""

    def __init__(
        self,
        path: Path | str | None,
        *,
        max_bytes: int = DEFAULT_MAX_BYTES,
        max_age_s: float = DEFAULT_MAX_AGE_S,
        clock: Callable[[], float] = time.time,
    ) -> None:
        self._lockfile = None
        if path is None:  # in memory: as long as the process lives (one URI, two connections)
            self.path, uri = None, f"file:outbox-{os.urandom(8).hex()}?mode=memory&cache=shared"
        else:
            self.path, uri = Path(path), f"file:{path}"
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._lockfile = hold_exclusively(
                path, OutboxBusy(f"outbox {path}: held by another process")
            )
        self.max_bytes = max_bytes
        self.max_age_s = max_age_s
        self._clock = clock
        self._lock = threading.Lock()
        self._db = self._connect(uri)
        self._db.execute("PRAGMA journal_mode=WAL")
        self._db.execute("PRAGMA synchronous=NORMAL")
        self._db.executescript(_SCHEMA)
        self._reader = self._connect(uri)
        if path is None:
            # A shared-cache database locks per table: a replay reading while an append
            # writes would fail one of them ("database table is locked"). Reading
            # uncommitted rows is safe here: a reader stops at the head committed before it
            # started, and rows past it are never asked for.
            self._reader.execute("PRAGMA read_uncommitted = 1")
        self._read_lock = threading.Lock()
        meta = dict(self._db.execute("SELECT name, value FROM meta"))
        if "epoch" not in meta:
            meta = {"epoch": os.urandom(6).hex(), "last_seq": 0, "pruned_upto": 0, "bytes": 0}
            self._db.executemany("INSERT INTO meta VALUES (?, ?)", meta.items())
        self.epoch: str = meta["epoch"]
        self._last_seq: int = meta["last_seq"]
        self._pruned_upto: int = meta["pruned_upto"]
        self._bytes: int = meta["bytes"]
        self._next_prune = 0.0

    @staticmethod
    def _connect(uri: str) -> sqlite3.Connection:
        return sqlite3.connect(uri, uri=True, isolation_level=None, check_same_thread=False)

    # --- writing ---------------------------------------------------------------------------

    def append_many(self, items: Sequence[tuple[str, bytes]]) -> list[int]:
        """Write ``(key, payload)`` items in one transaction; their seqs, in order.
        OutboxFull when the transaction failed (nothing written, numbering unchanged)."""
        if not items:
            return []
        now = self._clock()
        with self._lock:
            first = self._last_seq + 1
            rows = [(first + i, key, payload, now) for i, (key, payload) in enumerate(items)]
            size = sum(len(key) + len(payload) for key, payload in items)
            try:
                self._db.execute("BEGIN")
                self._db.executemany("INSERT INTO entries VALUES (?, ?, ?, ?)", rows)
                last, total = first + len(rows) - 1, self._bytes + size
                self._set_meta(last_seq=last, bytes=total)
                self._db.execute("COMMIT")
            except sqlite3.Error as e:
                self._rollback()
                raise OutboxFull(f"outbox {self.path}: {e}") from e
            self._last_seq, self._bytes = last, total
            self._prune(now)
        return [row[0] for row in rows]

    def append(self, key: str, payload: bytes) -> int:
        (seq,) = self.append_many([(key, payload)])
        return seq

    def _prune(self, now: float) -> None:
        """Delete, oldest first, what retention no longer keeps (called with the lock held,
        at most once per ``PRUNE_EVERY_S``). A failure leaves the entries for a later
        prune."""
        if now < self._next_prune:
            return
        self._next_prune = now + PRUNE_EVERY_S
        too_old, excess = now - self.max_age_s, self._bytes - self.max_bytes
        cutoff, freed = self._pruned_upto, 0
        for seq, t_wall, size in self._db.execute(
            "SELECT seq, t_wall, length(key) + length(payload) FROM entries WHERE seq > ? "
            "ORDER BY seq",
            (cutoff,),
        ):
            if t_wall >= too_old and freed >= excess:
                break
            cutoff, freed = seq, freed + size
        if cutoff == self._pruned_upto:
            return
        try:
            self._db.execute("BEGIN")
            self._db.execute("DELETE FROM entries WHERE seq <= ?", (cutoff,))
            self._set_meta(pruned_upto=cutoff, bytes=self._bytes - freed)
            self._db.execute("COMMIT")
        except sqlite3.Error:
            self._rollback()
            return
        self._pruned_upto, self._bytes = cutoff, self._bytes - freed

    def _set_meta(self, **values: int) -> None:
        self._db.executemany(
            "UPDATE meta SET value = ? WHERE name = ?", ((v, k) for k, v in values.items())
        )

    def _rollback(self) -> None:
        with contextlib.suppress(sqlite3.Error):  # no transaction left open
            self._db.execute("ROLLBACK")

    # --- reading ---------------------------------------------------------------------------

    @property
    def head(self) -> int:
        """The last seq written (0 before the first)."""
        return self._last_seq

    @property
    def pruned_upto(self) -> int:
        """The newest seq retention deleted (0 when none was)."""
        return self._pruned_upto

    @property
    def bytes(self) -> int:
        """Keys plus payloads kept."""
        return self._bytes

    def entries(self, after: int, upto: int | None = None) -> Iterator[Entry]:
        """The kept entries with ``after < seq <= upto`` (no upper bound when None), in seq
        order. Hold no lock of the caller while iterating: a generator left open holds the
        read connection."""
        upto = self._last_seq if upto is None else upto
        with self._read_lock:
            cursor = self._reader.execute(
                "SELECT seq, key, payload FROM entries WHERE seq > ? AND seq <= ? ORDER BY seq",
                (after, upto),
            )
            try:
                for seq, key, payload in cursor:
                    yield Entry(seq, key, payload)
            finally:
                cursor.close()

    def close(self) -> None:
        with self._lock, self._read_lock:
            self._reader.close()
            self._db.close()
            if self._lockfile is not None:
                self._lockfile.close()  # releases the lock
