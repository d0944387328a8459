"""Nothing a gateway sends locks a train out. Time plausibility (the receiving clock as the
bound on the future, the train's clock, its re-base) and units (m/s², counts, integer
samples) in the ingestion core."""

from __future__ import annotations

import logging

import msgspec
import numpy as np
from test_ingestion_core import T0, N, chunk, network, positioned, rejections, train_on

from schemas import DAY_S, NDArray, encode
from services.ingestion.config import IngestionConfig
from services.ingestion.core import IngestionCore
from services.ingestion.health import G_MPS2, time_range_reason

YEAR_3000 = 32_503_680_000.0
YEAR_2099 = 4_070_908_800.0  # inside the schemas' valid range: only the clock rule refuses it


def test_times_outside_the_valid_range_are_refused_by_name():
    cfg = IngestionConfig()
    assert time_range_reason("t", T0, cfg) is None
    reason = time_range_reason("t", YEAR_3000, cfg)
    assert reason and reason.startswith("t: 32503680000.000") and "valid time range" in reason
    assert "outside" in (time_range_reason("t0", 0.0, cfg) or "")


def test_one_fix_dated_2099_is_refused_and_the_train_goes_on():
    _, events = train_on("L3", 60)
    core = IngestionCore(network())
    out = core.run(events[:40], flush=False)
    fix = next(e for e in events[:40] if hasattr(e, "lat_deg"))
    letters = rejections(core.step(msgspec.structs.replace(fix, t=YEAR_2099)))
    assert len(letters) == 1 and letters[0].reason.startswith("GpsFix: t: 4070908800.000")
    assert "clock jump" in letters[0].reason
    out += core.run(events[40:])
    assert rejections(out) == []
    assert [c.seq for c in positioned(out)] == list(range(60))
    assert all(c.position_ok for c in positioned(out)[:-1])


def test_a_fix_hours_ahead_is_a_clock_jump_that_does_not_become_now():
    """Within the valid range but 6 h ahead: refused, naming the field and the jump; the
    train's event time, reorder windows and knots stay where they were."""
    _, events = train_on("L3", 60)
    core = IngestionCore(network())
    out = core.run(events[:40], flush=False)
    fix = next(e for e in reversed(events[:40]) if hasattr(e, "lat_deg"))
    letters = rejections(core.step(msgspec.structs.replace(fix, t=fix.t + 6 * 3600)))
    assert len(letters) == 1
    reason = letters[0].reason
    assert reason.startswith("GpsFix: t: ") and "21600 s ahead of the train's last fix" in reason
    assert "clock jump" in reason and "4 more consecutive fixes" in reason
    assert core.trains["T1"].now < fix.t + 2
    out += core.run(events[40:])
    assert rejections(out) == [] and [c.seq for c in positioned(out)] == list(range(60))
    assert core.train_stats("T1").clock_jumps == 1 and core.train_stats("T1").rebases == 0


def test_a_chunk_far_ahead_is_refused_and_its_unit_goes_on():
    """A restarted counter with t0 a day ahead would have reset the unit's sequencing."""
    _, events = train_on("L3", 40)
    core = IngestionCore(network())
    out = core.run(events[:20], flush=False)
    letters = rejections(core.step(chunk(0, t0=T0 + DAY_S)))
    assert len(letters) == 1 and letters[0].reason.startswith("RawChunk: t0: ")
    assert "86" in letters[0].reason and "ahead of the train's last fix" in letters[0].reason
    out += core.run(events[20:])
    assert rejections(out) == [] and [c.seq for c in positioned(out)] == list(range(40))


def test_a_train_whose_clock_really_moved_is_rebased_after_five_fixes(caplog):
    """The gateway's clock steps 1 h ahead and stays there: four fixes (and the chunks with
    them) are refused, the fifth consecutive consistent one re-bases the train, with a log
    line, and its chunks are positioned again on the new timeline."""
    sim, events = train_on("L3", 80)
    shift = 3600.0
    core = IngestionCore(network())
    out = core.run(events[:80], flush=False)  # 40 s on the old clock
    later = []
    for k in range(40, 80):
        later.append(chunk(k, t0=T0 + k + shift))
        later += [
            msgspec.structs.replace(f, t=f.t + shift) for f in sim.gps_fixes(T0 + k, T0 + k + 1)
        ]
    with caplog.at_level(logging.WARNING, logger="services.ingestion.core"):
        after = core.run(later)
    refused = rejections(after)
    assert {r.reason.split(":")[0] for r in refused} == {"GpsFix", "RawChunk"}
    assert sum(r.reason.startswith("GpsFix") for r in refused) == 4
    assert core.train_stats("T1").rebases == 1
    assert any("clock re-based" in r.getMessage() for r in caplog.records)
    new = [c for c in positioned(after) if c.t0 > T0 + shift]
    assert new and new[0].gap_before and all(c.position_ok for c in new[1:-1])
    assert [c.seq for c in new] == list(range(new[0].seq, 80))
    assert new[0].seq <= 47  # a few seconds lost, not the rest of the run
    assert all(c.seq < 40 for c in positioned(out))


def test_interleaved_outliers_never_rebase():
    _, events = train_on("L3", 60)
    core = IngestionCore(network())
    out = []
    for e in events:
        out += core.step(e)
        if hasattr(e, "lat_deg"):
            out += core.step(msgspec.structs.replace(e, t=e.t + 7200.0, lat_deg=e.lat_deg))
    out += core.flush()
    assert core.train_stats("T1").rebases == 0
    assert all("clock jump" in r.reason for r in rejections(out))
    assert [c.seq for c in positioned(out)] == list(range(60))


def _arrival(event) -> float:
    """The receiving machine's clock when ``event`` arrives live: half a second after it."""
    return (event.t if hasattr(event, "lat_deg") else event.t0 + 1.0) + 0.5


def _live(core: IngestionCore, events) -> list:
    out = []
    for event in events:
        out += core.step(event, _arrival(event))
    return out


def test_old_dated_messages_of_many_trains_do_not_refuse_a_live_train():
    """Fifty trains' fixes and chunks dated an hour back arrive first (a backlog coming
    through); the live train's fixes and chunks are all taken, exactly as without them."""
    _, events = train_on("L3", 60)
    fix = next(e for e in events if hasattr(e, "lat_deg"))
    hour = 3600.0
    burst = []
    for k in range(50):
        burst.append(msgspec.structs.replace(fix, train=f"B{k}", t=fix.t - hour))
        burst.append(chunk(0, train=f"B{k}", t0=T0 - hour))
    core = IngestionCore(network())
    for event in burst:
        core.step(event, T0)
    out = _live(core, events) + core.flush()
    alone = IngestionCore(network())
    expected = _live(alone, events) + alone.flush()
    assert rejections(out) == []
    assert [c.seq for c in positioned(out)] == list(range(60))
    assert [encode(c) for c in positioned(out)] == [encode(c) for c in positioned(expected)]


def test_a_time_ahead_of_the_receiving_clock_is_refused_and_never_rebases():
    """A gateway an hour ahead of the receiver, however consistent: every fix and chunk is
    refused as in the future, and the train is not re-based there."""
    sim, events = train_on("L3", 30)
    core = IngestionCore(network())
    out = _live(core, events[:20])
    ahead = []
    for k in range(10, 30):
        ahead.append(chunk(k, t0=T0 + k + 3600.0))
        ahead += [
            msgspec.structs.replace(f, t=f.t + 3600.0) for f in sim.gps_fixes(T0 + k, T0 + k + 1)
        ]
    refused = rejections([o for e in ahead for o in core.step(e, T0 + 30.0)])
    assert len(refused) == len(ahead)
    assert all("ahead of the receiving clock" in r.reason for r in refused)
    assert core.train_stats("T1").rebases == 0 and core.trains["T1"].now < T0 + 31.0
    out += core.flush()
    assert all(c.t0 < T0 + 30.0 for c in positioned(out))


def test_a_train_back_live_after_hours_away_is_no_clock_jump():
    """Six hours after its last fix, a fix the receiving clock agrees with is taken; the
    same fix replayed without the receiving clock is a jump of the train's clock."""
    _, events = train_on("L3", 20)
    fix = next(e for e in reversed(events) if hasattr(e, "lat_deg"))
    back = msgspec.structs.replace(fix, t=fix.t + 6 * 3600.0)
    live = IngestionCore(network())
    _live(live, events)
    assert rejections(live.step(back, back.t + 0.5)) == []
    replayed = IngestionCore(network())
    replayed.run(events, flush=False)
    [letter] = rejections(replayed.step(back))
    assert "ahead of the train's last fix" in letter.reason


def test_a_new_train_ahead_of_the_receiving_clock_is_refused():
    _, events = train_on("L3", 10)
    fix = next(e for e in events if hasattr(e, "lat_deg"))
    core = IngestionCore(network())
    [letter] = core.step(msgspec.structs.replace(fix, train="T2", t=fix.t + DAY_S), fix.t)
    assert "86400 s ahead of the receiving clock" in letter.reason
    late = msgspec.structs.replace(fix, train="T2", t=fix.t - DAY_S)
    assert rejections(core.step(late, fix.t)) == []  # a day late is no jump


# --- units -----------------------------------------------------------------------------------


def _scaled(c, factor: float, dtype: str = "f4"):
    a = c.samples.array().astype(np.float64)
    a[:, :6] *= factor
    return msgspec.structs.replace(c, samples=NDArray.of(a, dtype))


def test_samples_in_mps2_are_refused_saying_to_send_g():
    core = IngestionCore(network())
    [letter] = core.step(_scaled(chunk(0), G_MPS2))
    assert letter.reason.startswith("RawChunk: samples: vertical mean 9.8")
    assert "looks like m/s²" in letter.reason and "send accelerations in g" in letter.reason


def test_samples_in_counts_are_refused():
    core = IngestionCore(network())
    [letter] = core.step(_scaled(chunk(0), 2048.0))
    assert "no acceleration in g" in letter.reason and "counts" in letter.reason


def test_integer_samples_are_refused_with_their_reason():
    core = IngestionCore(network())
    a = np.round(chunk(0).samples.array() * 1000).astype(np.int16)
    [letter] = core.step(msgspec.structs.replace(chunk(0), samples=NDArray.of(a, "i2")))
    assert "dtype i2 is an integer type" in letter.reason and "send f4" in letter.reason


def test_samples_in_g_pass_the_unit_check_also_with_a_dead_vertical_channel():
    c = chunk(0)
    a = c.samples.array().copy()
    a[:, 0] = 0.0  # left_z dropout: flagged, not refused
    core = IngestionCore(network())
    assert rejections(core.step(msgspec.structs.replace(c, samples=NDArray.of(a, "f4")))) == []
    assert a.shape == (N, 7)
