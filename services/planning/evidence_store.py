"""The planner's one persisted state: each segment's :class:`~services.planning.core.Evidence`
(the on-board evidence of its closed TRC intervals), one SQLite row a segment.

Everything else the planner holds, it rebuilds at start from ``q/state`` and ``model/**``.
The evidence it cannot: a state carries the log weights of its current TRC interval only, so
a closed interval's are in no message any more. The file is held with an exclusive lock: two
planners never write one file.
"""

from __future__ import annotations

import sqlite3
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from services.planning.evidence import Evidence
from services.runtime.outbox import hold_exclusively

_SCHEMA = """
CREATE TABLE IF NOT EXISTS evidence (
    line TEXT NOT NULL,
    segment TEXT NOT NULL,
    posterior_group TEXT NOT NULL,
    posterior_version INTEGER NOT NULL,
    last_trc_t REAL NOT NULL,
    log_weights BLOB NOT NULL,  -- (Ns,) little-endian float64
    PRIMARY KEY (line, segment)
)
"""


class EvidenceBusy(OSError):
    """Another process holds this evidence file."""


class EvidenceStore:
    """The evidence of every segment in ``path`` (None: in memory, lost with the process)."""

    def __init__(self, path: Path | str | None) -> None:
        self._lockfile = None
        target = ":memory:"
        self.path = None if path is None else Path(path)
        if self.path is not None:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            busy = EvidenceBusy(f"evidence {path}: held by another process")
            self._lockfile = hold_exclusively(self.path, busy)
            target = str(self.path)
        self._db = sqlite3.connect(target, isolation_level=None, check_same_thread=False)
        self._db.execute("PRAGMA journal_mode=WAL")
        self._db.executescript(_SCHEMA)

    def load(self) -> list[tuple[str, str, Evidence]]:
        """``(line, segment, evidence)`` of every segment saved."""
        rows = self._db.execute(
            "SELECT line, segment, posterior_group, posterior_version, last_trc_t, log_weights "
            "FROM evidence ORDER BY line, segment"
        )
        return [
            (
                line,
                segment,
                Evidence(group, int(version), float(t), np.frombuffer(blob, "<f8").copy()),
            )  # fmt: skip
            for line, segment, group, version, t, blob in rows
        ]

    def save(self, items: Iterable[tuple[str, str, Evidence]]) -> int:
        """Write (replace) these segments' evidence in one transaction; how many."""
        rows = [
            (
                line,
                segment,
                ev.group,
                ev.version,
                ev.last_trc_t,
                np.ascontiguousarray(ev.log_weights, "<f8").tobytes(),
            )  # fmt: skip
            for line, segment, ev in items
        ]
        if rows:
            with self._db:
                self._db.execute("BEGIN")
                self._db.executemany("INSERT OR REPLACE INTO evidence VALUES (?,?,?,?,?,?)", rows)
        return len(rows)

    def close(self) -> None:
        self._db.close()
        if self._lockfile is not None:
            self._lockfile.close()
