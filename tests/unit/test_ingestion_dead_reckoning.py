"""Ingestion positions a chunk as soon as it arrives: between fixes by interpolation, past the
last fix by dead reckoning (at most ``extrapolate_s``), and the trajectory it publishes is
never revised afterwards (later fixes' corrections are spread over ``correction_s``).
Compared with ``extrapolate_s = 0``, which holds every chunk until the fix after it."""

from __future__ import annotations

import itertools
from functools import cache

import msgspec
import numpy as np
import pytest

from schemas import GpsFix, NDArray, PositionedChunk, RawChunk
from services.defaults import demo_network
from services.extraction.pipeline import Extractor
from services.ingestion.config import IngestionConfig
from services.ingestion.core import IngestionCore
from simulators.profile import LineProfile
from simulators.train import RAW_CHANNELS, TrainSimulator
from track.segments import SegmentTable

T0 = 1_767_225_600.0
N = 2000
HOLD = IngestionConfig(extrapolate_s=0.0)  # every chunk held until the fix after its last sample


@cache
def network():
    return demo_network()


def quiet_chunk(seq: int, train: str = "T1") -> RawChunk:
    rng = np.random.default_rng(seq)
    samples = np.zeros((N, 7), np.float32)
    samples[:, :6] = rng.normal(0.0, 0.01, (N, 6))
    samples[:, [0, 3]] += 1.0
    samples[:, 6] = 5.0
    return RawChunk(
        train=train,
        unit="u0",
        seq=seq,
        t0=T0 + seq,
        rate_hz=2000.0,
        channels=RAW_CHANNELS,
        samples=NDArray.of(samples, "f4"),
    )


@cache
def l3_train(seconds: int = 300, bogie: bool = False):
    """A train leaving L3's start; per second its chunk, then the fix at the chunk's start
    (the simulator's publishing order: a chunk arrives before the fixes it covers)."""
    line = network().lines["L3"]
    profile = LineProfile("L3", [(s.start_m, s.end_m) for s in line.segments], 1)
    rng = np.random.default_rng(1)
    n = len(line.segments)
    profile.update(rng.normal([0.7, 0.4], 0.3, (n, 2)), np.zeros(n, dtype=int))
    sim = TrainSimulator("T1", line, profile, 1, start_t=T0, phase_s=0.0)
    events: list[RawChunk | GpsFix] = []
    for k in range(seconds):
        events.append(sim.raw_chunk(k)[0] if bogie else quiet_chunk(k))
        events += sim.gps_fixes(T0 + k, T0 + k + 1)
    return sim, events


def positioned(outputs) -> list[PositionedChunk]:
    return [o for o in outputs if isinstance(o, PositionedChunk)]


def chainage_at(c: PositionedChunk, t: np.ndarray) -> np.ndarray:
    return np.interp(t, c.knot_t.array(), c.knot_chainage_m.array())


def t_last(c: PositionedChunk) -> float:
    return c.t0 + (c.samples.shape[0] - 1) / c.rate_hz


def test_a_chunk_goes_out_on_arrival_its_tail_dead_reckoned():
    sim, events = l3_train()
    core = IngestionCore(network())
    for e in events[: events.index(quiet_chunk(40))]:
        core.step(e)
    (c,) = positioned(core.step(quiet_chunk(40)))  # out at once: the last fix is T0 + 39
    kt = c.knot_t.array()
    assert c.seq == 40 and c.position_ok
    assert kt[0] <= c.t0 and kt[-1] == pytest.approx(t_last(c))
    assert kt[kt <= c.t0].size == 1  # then only dead-reckoned knots: no fix after T0 + 39
    truth = sim.position(kt)[0]
    assert np.abs(c.knot_chainage_m.array() - truth).max() < 4.0  # GPS error + 2 s of DR
    stats = core.train_stats("T1")
    # held: only while the train starts off and its direction is not known yet
    assert stats.extrapolated >= 33 and stats.held <= 6


def test_a_chunk_farther_than_the_horizon_from_the_last_fix_waits_for_one():
    _, events = l3_train()
    lost = {T0 + 50, T0 + 51, T0 + 52}  # fixes lost (not even a no-fix heartbeat)
    events = [e for e in events if not (isinstance(e, GpsFix) and e.t in lost)]
    core = IngestionCore(network())
    for e in events[: events.index(quiet_chunk(51))]:
        core.step(e)
    held = core.train_stats("T1").held  # the first chunks, while the train starts off
    assert positioned(core.step(quiet_chunk(51))) == []  # 2.9995 s past the fix at T0 + 49
    assert positioned(core.step(quiet_chunk(52))) == []
    assert positioned(core.step(quiet_chunk(53))) == []
    fix = next(e for e in events if isinstance(e, GpsFix) and e.t == T0 + 53)
    out = positioned(core.step(fix))
    assert [c.seq for c in out] == [51, 52, 53]  # 53 is 0.9995 s past that fix
    assert all(c.position_ok for c in out)  # knots 2 s apart: within dead_reckon_s
    assert out[0].knot_t.array()[-1] == T0 + 53  # 51, 52: between the published trajectory and it
    assert core.train_stats("T1").held == held + 3


def test_the_published_trajectory_is_never_revised_and_never_steps_back():
    _, events = l3_train()
    chunks = positioned(IngestionCore(network()).run(events))
    seen: dict[float, float] = {}
    for c in chunks:
        for t, x in zip(c.knot_t.array(), c.knot_chainage_m.array(), strict=True):
            assert seen.setdefault(float(t), float(x)) == x  # the same knot, the same place
    t = np.array(sorted(seen))
    x = np.array([seen[k] for k in t])
    # the train runs up the line: never backwards, once its direction is known (the fixes'
    # own knots jitter back and forth while it starts off: 12 m to tell the direction)
    assert np.all(np.diff(x[t >= T0 + 10]) >= 0.0)
    for a, b in itertools.pairwise(chunks):  # no jump from one chunk to the next
        end_a = chainage_at(a, np.array([t_last(a)]))[0]
        assert chainage_at(b, np.array([b.t0]))[0] == pytest.approx(end_a, abs=0.05)


def test_dead_reckoned_positions_agree_with_the_hold_on_smooth_motion():
    sim, events = l3_train()
    fast = positioned(IngestionCore(network()).run(events))
    hold = positioned(IngestionCore(network(), HOLD).run(events))
    assert [c.seq for c in fast] == [c.seq for c in hold]
    diff, stretch = [], {"fast": [], "hold": []}
    for a, b in zip(fast[10:-1], hold[10:-1], strict=True):  # once the train is under way
        t = a.t0 + np.arange(0, N, 50) / 2000.0
        diff.append(chainage_at(a, t) - chainage_at(b, t))
        ends = t[[0, -1]]
        run = np.diff(sim.position(ends)[0])[0]
        if run > 10.0:  # metres per chunk; at a standstill a ratio means nothing
            for name, c in (("fast", a), ("hold", b)):
                stretch[name].append(abs(np.diff(chainage_at(c, ends))[0] / run - 1))
    diff = np.abs(np.concatenate(diff))
    # a dead-reckoned position differs from the fix knots by about 0.3 of the GPS error
    # (the share of it the fused knots take in)
    assert np.median(diff) < 1.0 and np.percentile(diff, 99) < 3.0  # m
    # distance per chunk against the truth (the scale of the time-to-distance resampling):
    # as good as through the fix knots alone
    assert np.median(stretch["fast"]) < np.median(stretch["hold"]) + 0.005
    assert np.median(stretch["fast"]) < 0.03
    truth = sim.position(np.concatenate([c.knot_t.array() for c in fast]))[0]
    err = np.abs(np.concatenate([c.knot_chainage_m.array() for c in fast]) - truth)
    assert np.median(err) < 2.0 and err.max() < 8.0  # as the fixes' own knots


def _fix(chainage: float, t: float, speed: float = 20.0) -> GpsFix:
    line = network().lines["L3"]
    lon, lat = network().to_lonlat(line.xy_at(chainage))
    return GpsFix(train="T1", t=t, lat_deg=float(lat), lon_deg=float(lon), speed_mps=speed, hdop=1)


def test_a_large_correction_marks_the_chunks_it_is_spread_over_poor():
    """A fix 40 m ahead of where the train was dead-reckoned (beyond the fusion gate, so it is
    taken as is): the published trajectory catches up over ``correction_s``, and the chunks whose
    positions carry that catching-up are not position_ok; afterwards they are again."""
    core = IngestionCore(network())
    out = []
    for k in range(20):
        out += core.step(quiet_chunk(k))
        jump = 40.0 if k >= 10 else 0.0
        out += core.step(_fix(1000.0 + 20.0 * k + jump, T0 + k))
    ok = {c.seq: c.position_ok for c in positioned(out)}
    assert all(ok[k] for k in range(3, 11))
    assert not ok[11] and not ok[12]
    assert all(ok[k] for k in range(13, 20))
    assert core.train_stats("T1").max_correction_m == pytest.approx(40.0, abs=1.0)


def indices(config: IngestionConfig) -> list:
    _, events = l3_train(360, bogie=True)
    extractor = Extractor(SegmentTable.from_network(network()))
    out = []
    for c in positioned(IngestionCore(network(), config).run(events)):
        out += extractor.process(c)
    return out


def test_indices_through_dead_reckoning_equal_those_through_the_hold():
    fast, hold = indices(IngestionConfig()), indices(HOLD)
    assert len(hold) >= 10
    assert [i.segment for i in fast] == [i.segment for i in hold]
    for a, b in zip(fast, hold, strict=True):
        assert a.t == pytest.approx(b.t, abs=0.2)
        assert abs(np.log(a.top6_mm / b.top6_mm)) < 0.05
        assert abs(np.log(a.align10_mm / b.align10_mm)) < 0.05


def test_after_a_stop_inside_a_tunnel_the_trajectory_jumps_back_to_the_fixes():
    """L2's tunnel has a station: the fixes' own knots are reckoned on through the stop
    (hundreds of metres too far); at the exit they snap back, and so does the published
    trajectory (a jump, marked poor), instead of spreading or holding a correction that large."""
    line = network().lines["L2"]
    profile = LineProfile("L2", [(s.start_m, s.end_m) for s in line.segments], 1)
    probe = TrainSimulator("T1", line, profile, 1, start_t=0.0, phase_s=0.0)
    i = int(np.argmax((probe._x >= 11_000.0) & (probe._dir == 1)))
    sim = TrainSimulator("T1", line, profile, 1, start_t=T0, phase_s=float(probe._t[i]))
    events: list[RawChunk | GpsFix] = []
    for k in range(200):
        events.append(quiet_chunk(k))
        events += sim.gps_fixes(T0 + k, T0 + k + 1)
    core = IngestionCore(network())
    chunks = positioned(core.run(events))
    assert core.train_stats("T1").max_correction_m > 100.0  # the stop was reckoned through
    exit_m = line.tunnels[0][1]
    for c in chunks:
        t = np.array([c.t0, t_last(c)])
        truth = sim.position(t)[0]
        if truth[0] > exit_m + 150.0:  # well out of the tunnel: good fixes again
            assert c.position_ok, c.seq
            assert np.abs(chainage_at(c, t) - truth).max() < 8.0, c.seq
        elif sim.in_tunnel(truth).all() and truth[0] > line.tunnels[0][0] + 100.0:
            assert not c.position_ok, c.seq
    assert sim.position(np.array([chunks[-1].t0]))[0][0] > exit_m + 1_000.0


def test_every_unit_of_a_train_gets_the_same_trajectory_whenever_its_chunk_arrives():
    _, events = l3_train(60)
    late = []  # unit u1's chunks arrive a second late, after the next fix
    mixed: list[RawChunk | GpsFix] = []
    for e in events:
        mixed.append(e)
        if isinstance(e, RawChunk):
            mixed += late
            late = [msgspec.structs.replace(e, unit="u1")]
    out = positioned(IngestionCore(network()).run(mixed + late))
    by_unit = {u: {c.seq: c for c in out if c.unit == u} for u in ("u0", "u1")}
    assert sorted(by_unit["u0"]) == sorted(by_unit["u1"]) == list(range(60))
    for seq, a in by_unit["u0"].items():
        b = by_unit["u1"][seq]
        assert a.knot_t == b.knot_t and a.knot_chainage_m == b.knot_chainage_m
        assert a.position_ok == b.position_ok
