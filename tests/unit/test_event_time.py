"""The event-time watermark the alerting and planning services share."""

from services.runtime.event_time import NewestTimes


def test_one_segment_dated_ahead_cannot_make_the_quorum_alone():
    times = NewestTimes(3)
    assert times.kth(1) is None
    for t in (10.0, 20.0, 30.0):  # one segment, ever newer: still one segment
        times.note(("L1", "s1"), t)
    times.note(("L1", "s2"), 5.0)
    times.note(("L1", "s3"), 7.0)
    assert len(times) == 3
    assert times.kth(3) == 5.0 and times.kth(1) == 30.0
    times.note(("L1", "s2"), 4.0)  # older than what it has: changes nothing
    assert times.kth(3) == 5.0
    times.note(("L1", "s4"), 99.0)
    assert times.kth(3) == 7.0
