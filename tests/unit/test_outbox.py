"""The durable outbox: numbering, reading, restart continuity, retention, a full disk."""

from __future__ import annotations

import pytest

from services.runtime.outbox import Outbox, OutboxBusy, OutboxFull


class Clock:
    def __init__(self) -> None:
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now


def test_append_numbers_and_reads_in_order(tmp_path):
    outbox = Outbox(tmp_path / "p.sqlite")
    assert outbox.append_many([("a/1", b"x"), ("a/2", b"y")]) == [1, 2]
    assert outbox.append("a/1", b"z") == 3
    assert [(e.seq, e.key, e.payload) for e in outbox.entries(0)] == [
        (1, "a/1", b"x"),
        (2, "a/2", b"y"),
        (3, "a/1", b"z"),
    ]
    assert [e.seq for e in outbox.entries(1, upto=2)] == [2]
    assert outbox.head == 3
    assert outbox.bytes == 3 * 4
    outbox.close()


def test_numbering_and_epoch_continue_after_a_restart(tmp_path):
    outbox = Outbox(tmp_path / "p.sqlite")
    outbox.append_many([("k", b"1"), ("k", b"2")])
    epoch = outbox.epoch
    outbox.close()
    again = Outbox(tmp_path / "p.sqlite")
    assert again.epoch == epoch
    assert again.append("k", b"3") == 3
    assert [e.payload for e in again.entries(0)] == [b"1", b"2", b"3"]
    again.close()
    other = Outbox(tmp_path / "other.sqlite")
    assert other.epoch != epoch  # a new file, a new numbering
    other.close()


def test_retention_by_age_deletes_oldest_and_keeps_numbering(tmp_path):
    clock = Clock()
    outbox = Outbox(tmp_path / "p.sqlite", max_age_s=100.0, clock=clock)
    outbox.append_many([("k", b"old")] * 3)
    clock.now += 150.0
    outbox.append("k", b"new")  # the commit that prunes the three old ones
    assert [e.seq for e in outbox.entries(0)] == [4]
    assert outbox.pruned_upto == 3
    assert outbox.bytes == len("k") + len(b"new")
    clock.now += 150.0
    outbox.append("k", b"newer")
    outbox.close()
    reopened = Outbox(tmp_path / "p.sqlite", max_age_s=100.0, clock=clock)
    assert reopened.pruned_upto == 4
    assert reopened.append("k", b"after") == 6  # the numbering survives an emptied log
    reopened.close()


def test_retention_by_bytes_keeps_the_newest(tmp_path):
    clock = Clock()
    outbox = Outbox(tmp_path / "p.sqlite", max_bytes=50, clock=clock)
    for _ in range(10):
        clock.now += 2.0  # past the prune interval, so every commit prunes
        outbox.append("k", bytes(9))  # 10 bytes each
    assert outbox.bytes <= 50
    assert [e.seq for e in outbox.entries(0)] == [6, 7, 8, 9, 10]
    assert outbox.pruned_upto == 5
    outbox.close()


def test_a_full_disk_raises_and_leaves_the_log_consistent(tmp_path):
    outbox = Outbox(tmp_path / "p.sqlite")
    outbox.append("k", b"before")
    (pages,) = outbox._db.execute("PRAGMA page_count").fetchone()
    outbox._db.execute(f"PRAGMA max_page_count = {pages}")  # a disk with no room left
    with pytest.raises(OutboxFull, match="full"):
        outbox.append_many([("k", bytes(4096))] * 50)
    assert outbox.head == 1
    assert [e.payload for e in outbox.entries(0)] == [b"before"]
    outbox._db.execute("PRAGMA max_page_count = 1000000")  # room again
    assert outbox.append("k", b"after") == 2
    outbox.close()


def test_one_process_at_a_time_holds_an_outbox(tmp_path):
    outbox = Outbox(tmp_path / "p.sqlite")
    with pytest.raises(OutboxBusy, match="held by another process"):
        Outbox(tmp_path / "p.sqlite")  # another open file description: as another process
    outbox.close()
    Outbox(tmp_path / "p.sqlite").close()  # released with its holder


@pytest.mark.parametrize("where", ["memory", "file"])
def test_appends_go_on_while_a_replay_reads(tmp_path, where):
    """A replay holds its read open across appends (as a slow consumer's replay does):
    neither side fails, and the reader sees every entry up to the head it started from."""
    outbox = Outbox(None if where == "memory" else tmp_path / "p.sqlite")
    outbox.append_many([("k", b"%d" % i) for i in range(100)])
    reading = outbox.entries(0)
    first = next(reading)
    for i in range(50):  # appends while the read is open
        outbox.append("k", b"late %d" % i)
    rest = list(reading)
    assert [first.seq, *(e.seq for e in rest)] == list(range(1, 101))
    assert outbox.head == 150
    assert [e.seq for e in outbox.entries(100)] == list(range(101, 151))
    outbox.close()
