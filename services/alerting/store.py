"""SQLite persistence of the alerting core: raised alerts, per-segment memory, TRC runs,
the detected tampings held (withdrawals included).

One file per instance. Each message's changes are written in one transaction, so a restart
(even after SIGKILL) reloads exactly what the core held after the last processed message:
raised alerts are neither raised again nor forgotten, and stale detection and the plan
still know every segment.
"""

from __future__ import annotations

import sqlite3
from collections.abc import Iterable
from pathlib import Path

from schemas import Alert, MaintenanceEvent, SegmentState, decode, encode
from services.alerting.core import SegmentMemory, alert_key

_SCHEMA = """
CREATE TABLE IF NOT EXISTS raised (
    line TEXT, segment TEXT, kind TEXT, indicator TEXT, level TEXT,
    alert BLOB NOT NULL,
    PRIMARY KEY (line, segment, kind, indicator, level)
);
CREATE TABLE IF NOT EXISTS segments (
    line TEXT, segment TEXT,
    state BLOB NOT NULL,
    calm_updates INTEGER NOT NULL,
    PRIMARY KEY (line, segment)
);
CREATE TABLE IF NOT EXISTS trc_runs (
    line TEXT, run_id TEXT,
    t REAL NOT NULL,
    PRIMARY KEY (line, run_id)
);
CREATE TABLE IF NOT EXISTS detections (
    line TEXT, segment TEXT, event_id TEXT,
    event BLOB NOT NULL,
    PRIMARY KEY (line, segment, event_id)
);
"""


class AlertStore:
    """Read everything back with :meth:`load`; write one message's changes with :meth:`save`."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        if str(path) != ":memory:":
            self.path.parent.mkdir(parents=True, exist_ok=True)
        # written by the service's single worker; opened in the main thread
        self._db = sqlite3.connect(str(path), check_same_thread=False)
        self._db.execute("PRAGMA journal_mode=WAL")
        self._db.execute("PRAGMA synchronous=NORMAL")  # WAL: durable across a process kill
        self._db.executescript(_SCHEMA)

    def load(
        self,
    ) -> tuple[
        list[Alert], list[SegmentMemory], list[tuple[str, str, float]], list[MaintenanceEvent]
    ]:
        """(raised alerts, segment memories, TRC runs as (line, run_id, t), detections held)."""
        alerts = [decode(row[0], Alert) for row in self._db.execute("SELECT alert FROM raised")]
        memories = [
            SegmentMemory(decode(state, SegmentState), int(calm))
            for state, calm in self._db.execute("SELECT state, calm_updates FROM segments")
        ]
        runs = [
            (str(line), str(run_id), float(t))
            for line, run_id, t in self._db.execute("SELECT line, run_id, t FROM trc_runs")
        ]
        detections = [
            decode(row[0], MaintenanceEvent)
            for row in self._db.execute("SELECT event FROM detections")
        ]
        return alerts, memories, runs, detections

    def save(
        self,
        alerts: Iterable[Alert] = (),
        memory: SegmentMemory | None = None,
        run: tuple[str, str, float] | None = None,
        detection: MaintenanceEvent | None = None,
    ) -> None:
        """In one transaction: raised alerts stored, cleared ones deleted, the segment's
        memory, a TRC run and a detected tamping held upserted."""
        with self._db:
            for alert in alerts:
                key = alert_key(alert)
                if alert.status == "raised":
                    self._db.execute(
                        "INSERT OR REPLACE INTO raised VALUES (?, ?, ?, ?, ?, ?)",
                        (*key, encode(alert)),
                    )
                else:
                    self._db.execute(
                        "DELETE FROM raised WHERE line=? AND segment=? AND kind=? "
                        "AND indicator=? AND level=?",
                        key,
                    )
            if memory is not None:
                self._db.execute(
                    "INSERT OR REPLACE INTO segments VALUES (?, ?, ?, ?)",
                    (
                        memory.state.line,
                        memory.state.segment,
                        encode(memory.state),
                        memory.calm_updates,
                    ),
                )
            if run is not None:
                self._db.execute("INSERT OR REPLACE INTO trc_runs VALUES (?, ?, ?)", run)
            if detection is not None:
                self._db.execute(
                    "INSERT OR REPLACE INTO detections VALUES (?, ?, ?, ?)",
                    (detection.line, detection.segment, detection.event_id, encode(detection)),
                )

    def close(self) -> None:
        self._db.close()
