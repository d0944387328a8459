"""The checkpoint of a stateful stage of the raw chain: its core's state and, per producer,
how far into that producer's outbox the core has read, saved together in one SQLite row.

A stage that reads an ordered stream (:class:`~services.runtime.ordered.OrderedSubscription`)
and keeps state between messages (ingestion's reorder buffers and trajectories, extraction's
filters and passes) cannot rebuild that state from its outputs. It saves
``(state, positions)`` in one transaction every few seconds, after its outputs up to that
point are in its own outbox; a restarted stage loads them and asks each producer for what
came after its position. The messages it handled between the checkpoint and its end are
handled again from the same state, so they give the same outputs again, which the next
stage drops as duplicates. A message is **acknowledged** once a checkpoint counts it: it is
then in the stage's state or in its outbox, and no restart loses it.

The file is held with an exclusive lock: two processes never write one checkpoint.
"""

from __future__ import annotations

import hashlib
import io
import json
import logging
import pickle
import sqlite3
import time
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from services.runtime.outbox import hold_exclusively

log = logging.getLogger(__name__)

_SCHEMA = """
CREATE TABLE IF NOT EXISTS checkpoint (
    id INTEGER PRIMARY KEY CHECK (id = 1),
    saved_at REAL NOT NULL,
    fingerprint TEXT NOT NULL,
    positions TEXT NOT NULL,
    state BLOB NOT NULL
)
"""


def fingerprint(network_path: Path | str | None, config: object) -> str:
    """What a stage's saved state was built on: the network file's bytes (the packaged demo
    network when None) and its configuration's repr. A checkpoint with another one keeps its
    positions and drops its state."""
    data = Path(network_path).read_bytes() if network_path is not None else b"demo"
    return hashlib.sha256(data + repr(config).encode()).hexdigest()[:16]


def dumps(state: object, shared: Mapping[str, object]) -> bytes:
    """``state`` pickled, each object of ``shared`` (the network, what is built from it:
    large, and the same after a restart) by its name only."""
    names = {id(obj): name for name, obj in shared.items()}
    buffer = io.BytesIO()
    pickler = pickle.Pickler(buffer, protocol=pickle.HIGHEST_PROTOCOL)
    pickler.persistent_id = lambda obj: names.get(id(obj))  # type: ignore[method-assign]
    pickler.dump(state)
    return buffer.getvalue()


def loads(data: bytes, shared: Mapping[str, object]) -> Any:
    """What :func:`dumps` pickled, its shared objects replaced by those of ``shared``."""
    unpickler = pickle.Unpickler(io.BytesIO(data))
    unpickler.persistent_load = lambda name: shared[name]  # type: ignore[method-assign]
    return unpickler.load()


class CheckpointBusy(Exception):
    """Another process holds the checkpoint file."""


@dataclass(frozen=True)
class Checkpoint:
    state: bytes
    fingerprint: str  # what the state was built on (the network); another one discards it
    positions: dict[str, tuple[str, int]]  # {producer: (epoch, last seq handled)}
    saved_at: float


def resume(
    store: CheckpointStore, fingerprint: str, shared: Mapping[str, object], what: str
) -> tuple[Any, dict[str, tuple[str, int]]]:
    """``(state, positions)`` of ``store``'s checkpoint: the state (None without one, or when
    it was saved on another network or configuration ``fingerprint``: then only the
    positions are kept, and a warning names ``what`` starts anew) and the positions."""
    saved = store.load()
    if saved is None:
        return None, {}
    if saved.fingerprint != fingerprint:
        log.warning(
            "the checkpoint %s was saved on another network or configuration: resuming its "
            "positions with a new %s", store.path, what,
        )  # fmt: skip
        return None, saved.positions
    log.info("resumed from the checkpoint %s of %s", store.path, time.ctime(saved.saved_at))
    return loads(saved.state, shared), saved.positions


class CheckpointStore:
    """One stage's checkpoint in ``path`` (None: in memory, for a stage run in a test)."""

    def __init__(self, path: Path | str | None) -> None:
        self._lockfile = None
        if path is None:
            self.path, target = None, ":memory:"
        else:
            self.path = Path(path)
            self.path.parent.mkdir(parents=True, exist_ok=True)
            busy = CheckpointBusy(f"checkpoint {path}: held by another process")
            self._lockfile = hold_exclusively(path, busy)
            target = str(path)
        self._db = sqlite3.connect(target, isolation_level=None, check_same_thread=False)
        self._db.execute("PRAGMA journal_mode=WAL")
        self._db.executescript(_SCHEMA)

    def load(self) -> Checkpoint | None:
        row = self._db.execute(
            "SELECT state, fingerprint, positions, saved_at FROM checkpoint WHERE id = 1"
        ).fetchone()
        if row is None:
            return None
        state, fingerprint, positions, saved_at = row
        decoded = {p: (e, int(s)) for p, (e, s) in json.loads(positions).items()}
        return Checkpoint(bytes(state), fingerprint, decoded, saved_at)

    def save(self, state: bytes, fingerprint: str, positions: dict[str, tuple[str, int]]) -> None:
        """Replace the checkpoint (one transaction: state and positions never disagree)."""
        self._db.execute(
            "INSERT OR REPLACE INTO checkpoint VALUES (1, ?, ?, ?, ?)",
            (time.time(), fingerprint, json.dumps(positions, sort_keys=True), state),
        )

    def close(self) -> None:
        self._db.close()
        if self._lockfile is not None:
            self._lockfile.close()
