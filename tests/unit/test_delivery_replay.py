"""The replay between a producer's outbox and a consumer's position, without Zenoh."""

from __future__ import annotations

import pytest

from services.runtime.delivery import DeliverySettings, Position, serve_replay
from services.runtime.outbox import Outbox


def on_line(line: str):
    return lambda key: key.split("/")[2] == line


@pytest.fixture
def outbox(tmp_path):
    outbox = Outbox(tmp_path / "p.sqlite")
    # seqs 1..12: lines alternate L1, L2
    outbox.append_many([(f"tf/index/L{1 + i % 2}/s{i}", b"%d" % i) for i in range(12)])
    yield outbox
    outbox.close()


def seqs(replay) -> list[int]:
    return [seq for seq, _, _ in replay.entries]


def test_a_consumer_without_position_gets_every_matching_entry(outbox):
    replay = serve_replay(outbox, None, on_line("L1"))
    assert seqs(replay) == [1, 3, 5, 7, 9, 11]
    assert (replay.head, replay.lost, replay.epoch) == (12, 0, outbox.epoch)


def test_a_matching_count_sends_only_what_is_above_the_live_maximum(outbox):
    # W=2; seen live 3, 5, 7 (every L1 entry in (2, 7]): only the L1 entries above 7
    replay = serve_replay(outbox, [outbox.epoch, 2, 7, 3], on_line("L1"))
    assert seqs(replay) == [9, 11]


def test_a_count_short_of_the_producers_resends_everything_above_the_watermark(outbox):
    # seen live 3 and 7 only: 5 went missing, so everything above W=2 again
    replay = serve_replay(outbox, [outbox.epoch, 2, 7, 2], on_line("L1"))
    assert seqs(replay) == [3, 5, 7, 9, 11]


def test_another_epoch_replays_from_the_start(outbox):
    replay = serve_replay(outbox, ["0123456789ab", 10, 10, 0], on_line("L2"))
    assert seqs(replay) == [2, 4, 6, 8, 10, 12]
    assert replay.lost == 0


def test_a_watermark_below_retention_reports_what_was_deleted(tmp_path):
    outbox = Outbox(tmp_path / "p.sqlite", max_bytes=40)
    for i in range(10):
        outbox._next_prune = 0.0  # prune at every commit
        outbox.append(f"tf/index/L1/s{i}", bytes(4))  # 17 bytes each: two kept
    assert outbox.pruned_upto == 8
    replay = serve_replay(outbox, [outbox.epoch, 3, 5, 2], on_line("L1"))
    assert replay.lost == 5  # seqs 4..8, deleted before the consumer got them
    assert seqs(replay) == [9, 10]  # a count over deleted entries is not trusted
    outbox.close()


def test_position_drops_duplicates_and_advances():
    position = Position("e1", watermark=4)
    assert position.request() == ["e1", 4, 4, 0]
    assert not position.take("e1", 3)  # at or below W: already handed on
    assert position.take("e1", 6) and position.take("e1", 9)
    assert not position.take("e1", 6)  # seen live already
    assert position.request() == ["e1", 4, 9, 2]
    assert position.take("e2", 1)  # another numbering: handed on, not noted
    position.advance("e1", 7)
    assert position.request() == ["e1", 7, 9, 1]
    position.restart("e2")
    assert position.request() == ["e2", 0, 0, 0]
    assert Position().request() is None


def test_delivery_settings_check_their_values():
    settings = DeliverySettings.from_options({"replay_s": 2, "outbox": {"max_bytes": 10}})
    assert (settings.replay_s, settings.outbox.max_bytes) == (2, 10)
    with pytest.raises(ValueError, match="replay_s must be a number > 0"):
        DeliverySettings.from_options({"replay_s": 0})
    with pytest.raises(ValueError, match="outbox: unknown key 'size'"):
        DeliverySettings.from_options({"outbox": {"size": 1}})
    with pytest.raises(ValueError, match="outbox.max_bytes must be an integer"):
        DeliverySettings.from_options({"outbox": {"max_bytes": 0.5}})


def test_a_limited_replay_stops_at_the_limit_and_says_how_far_it_looked(outbox):
    replay = serve_replay(outbox, None, on_line("L2"), limit=2)
    assert seqs(replay) == [2, 4]
    assert replay.head == 4  # the consumer asks again after 4
    rest = serve_replay(outbox, [outbox.epoch, 4, 4, 0], on_line("L2"), limit=10)
    assert seqs(rest) == [6, 8, 10, 12]
    assert rest.head == 12


def test_a_limit_not_reached_reports_the_producers_head(outbox):
    replay = serve_replay(outbox, [outbox.epoch, 9, 9, 0], on_line("L1"), limit=5)
    assert seqs(replay) == [11]
    assert replay.head == 12
