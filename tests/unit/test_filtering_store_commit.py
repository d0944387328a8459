"""The store's commit in the background (a backlog's batch commits while the
next one folds): its rows land in order, with the checkpoint after them, and a failed
commit stops everything that follows instead of being lost."""

from __future__ import annotations

import sqlite3
import threading

import pytest

from services.filtering import store as store_module
from services.filtering.store import Store


def rows(n: int, first: int = 0) -> list[tuple]:
    return [
        ("L1", f"s{k % 7}", "index", "ns/index/L1", f'["index", "T1", "u1", {k}.0]', float(k),
         bytes([k % 251]) * 40)
        for k in range(first, first + n)
    ]  # fmt: skip


def test_a_commit_in_the_background_stores_every_row_in_order_then_its_checkpoint(tmp_path):
    store = Store(tmp_path / "f.sqlite")
    try:
        with store.transaction(background=True):
            store.add_events(rows(3001))  # 2048 + 512 + 256 + ... + 1: one INSERT each
            store.add_events(rows(5, first=3001))
            gen = store.put_checkpoints([("L1", "s1", None, None, "", "", None, None)])
        store.sync()
        assert not store.committing
        stored = store._db.execute(
            "SELECT seq, line, segment, kind, key, identity, t, payload FROM events ORDER BY seq"
        ).fetchall()
        assert [row[1:] for row in stored] == rows(3006)
        assert [row[0] for row in stored] == list(range(1, 3007))
        (checkpoint,) = store.checkpoints()
        assert checkpoint[:3] == ("L1", "s1", 3006)  # covers the events written before it
        assert checkpoint[-1] == gen
    finally:
        store.close()


def test_a_failed_commit_in_the_background_raises_at_every_later_access(tmp_path):
    """A full disk (SQLite's own limit on the file's pages) fails the commit in the
    background: the next access raises, and every one after it (the owner must stop), and
    none of the transaction's rows is stored; what was committed before stays."""
    path = tmp_path / "f.sqlite"
    store = Store(path)
    with store.transaction(background=True):
        store.add_events(rows(10))
    store.sync()
    (pages,) = store._db.execute("PRAGMA page_count").fetchone()
    store._db.execute(f"PRAGMA max_page_count = {pages}")
    with store.transaction(background=True):
        store.add_events(rows(2000, first=10))
    for _ in range(2):
        with pytest.raises(sqlite3.OperationalError, match="in the background failed.*full"):
            store.count_events()
    with pytest.raises(sqlite3.OperationalError), store.transaction(background=True):
        pass  # the next batch's, even one that writes nothing, stops there
    assert store.committing  # nothing of it may be published
    store.close()
    db = sqlite3.connect(path)
    assert db.execute("SELECT COUNT(*) FROM events").fetchone() == (10,)
    db.close()


def test_a_block_that_fails_leaves_the_commit_in_the_background_alone(tmp_path, monkeypatch):
    """A batch that raises before its first statement rolls nothing back: the connection's
    open transaction is the previous batch's, still committing in the background."""
    store = Store(tmp_path / "f.sqlite")
    inserted, release = threading.Event(), threading.Event()
    run = store._run

    def held(deferred):  # the commit holds its transaction open until released
        run(deferred)
        inserted.set()
        release.wait(30)

    try:
        monkeypatch.setattr(store, "_run", held)
        with store.transaction(background=True):
            store.add_events(rows(4096))
        assert inserted.wait(30)
        with pytest.raises(ZeroDivisionError), store.transaction(background=True):
            store.add_events(rows(5, first=4096))
            raise ZeroDivisionError("a bug in the fold")
        release.set()
        assert store.count_events() == 4096
    finally:
        store.close()


def test_every_segment_s_checkpoint_is_written_a_chunk_at_a_time_after_the_events(
    tmp_path, monkeypatch
):
    """A checkpoint of every segment (a model change, a restore) does not hold all its rows
    (~11 KB each) at once: they are written in chunks as they come, after the events."""
    monkeypatch.setattr(store_module, "CHECKPOINT_CHUNK", 4)
    store = Store(tmp_path / "f.sqlite")
    made = []

    def checkpoint_rows(n):
        for k in range(n):
            made.append(k)
            if k >= 4:  # the chunk before this one is written by now
                assert store._conn.execute("SELECT COUNT(*) FROM checkpoints").fetchone()[0] >= 4
            yield ("L1", f"s{k}", None, None, "", "", None, None)

    try:
        with store.transaction():
            store.add_events(rows(10))
            store.put_checkpoints(checkpoint_rows(11))
        assert len(made) == 11
        seqs = store._db.execute("SELECT DISTINCT seq FROM checkpoints").fetchall()
        assert seqs == [(10,)] and len(list(store.checkpoints())) == 11
    finally:
        store.close()


def test_every_checkpoint_generation_writes_with_the_same_statements(tmp_path, monkeypatch):
    """SQLite's cache keeps a prepared statement per text: a text per checkpoint (its
    generation written into it) held ~0.7 MB each, 100 MB in a 15-minute demo run."""
    store = Store(tmp_path / "f.sqlite")
    texts = set()
    run = store._run

    def recording(inserts):
        texts.update((head, row, tail) for head, row, tail, _rows in inserts)
        run(inserts)

    monkeypatch.setattr(store, "_run", recording)
    try:
        for gen in range(1, 6):
            with store.transaction():
                store.add_events(rows(1, first=gen))
                assert store.put_checkpoints([("L1", "s1", None, None, "", "", None, None)]) == gen
        assert len(texts) == 4  # events, checkpoints, the generation, the one published
        assert [c[2:3] + c[-1:] for c in store.checkpoints()] == [(5, 5)]  # seq, gen
    finally:
        store.close()


@pytest.mark.parametrize("background", [False, True])
def test_delivery_positions_are_stored_with_the_transaction(tmp_path, background):
    store = Store(tmp_path / "f.sqlite")
    with store.transaction(background=background):
        store.put_positions([("extraction/a", "e1", 5), ("calibration/a", "e2", 2)])
        store.add_events(rows(3))
    with store.transaction(background=background):
        store.put_positions([("extraction/a", "e1", 9)])
    store.sync()
    assert store.positions() == {"extraction/a": ("e1", 9), "calibration/a": ("e2", 2)}
    with pytest.raises(RuntimeError), store.transaction():
        store.put_positions([("extraction/a", "e3", 1)])
        raise RuntimeError("the batch failed")
    store.close()
    assert Store(tmp_path / "f.sqlite").positions()["extraction/a"] == ("e1", 9)
