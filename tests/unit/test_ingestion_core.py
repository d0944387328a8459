"""The ingestion core with lists in, lists out: validation, sequencing, health, correction,
map matching on the demo network."""

from __future__ import annotations

from functools import cache

import msgspec
import numpy as np
import pytest

from schemas import ACCEL_CHANNELS, GpsFix, NDArray, PositionedChunk, RawChunk, encode
from services.defaults import demo_network
from services.ingestion.config import IngestionConfig
from services.ingestion.core import IngestionCore, Rejection
from services.ingestion.health import G_MPS2
from services.ingestion.matching import _LineGeometry
from simulators.profile import LineProfile
from simulators.train import RAW_CHANNELS, TrainSimulator
from track.network import Network

T0 = 1_767_225_600.0
N = 2000  # samples per 1 s chunk at 2000 Hz


@cache
def network():
    return demo_network()


def chunk(seq: int, *, train="T1", unit="u0", t0=None, samples=None, **kw) -> RawChunk:
    """A quiet 1 s chunk: z at +1 g, small noise, supply 5.0 V."""
    if samples is None:
        rng = np.random.default_rng(seq)
        samples = np.zeros((N, 7), np.float32)
        samples[:, :6] = rng.normal(0.0, 0.01, (N, 6))
        samples[:, [0, 3]] += 1.0
        samples[:, 6] = 5.0
    fields = dict(
        train=train,
        unit=unit,
        seq=seq,
        t0=T0 + seq if t0 is None else t0,
        rate_hz=2000.0,
        channels=RAW_CHANNELS,
        samples=NDArray.of(samples, "f4"),
    )
    return RawChunk(**(fields | kw))


def train_on(
    line_id: str, seconds: int, *, at_m: float = 0.0, direction: int = 1, on: Network | None = None
):
    """A simulated train on ``line_id`` of ``on`` (the demo network), starting where it
    passes ``at_m`` in ``direction``; returns ``(sim, events)``: one quiet chunk and one GPS
    fix per second."""
    line = (on or network()).lines[line_id]
    profile = LineProfile(line_id, [(s.start_m, s.end_m) for s in line.segments], 1)
    probe = TrainSimulator("T1", line, profile, 1, start_t=0.0, phase_s=0.0)
    passed = probe._x >= at_m if direction > 0 else probe._x <= at_m
    i = int(np.argmax(passed & (probe._dir == direction)))
    sim = TrainSimulator("T1", line, profile, 1, start_t=T0, phase_s=float(probe._t[i]))
    events: list[RawChunk | GpsFix] = []
    for k in range(seconds):
        events.append(chunk(k))
        events += sim.gps_fixes(T0 + k, T0 + k + 1)
    return sim, events


def positioned(outputs) -> list[PositionedChunk]:
    return [o for o in outputs if isinstance(o, PositionedChunk)]


def rejections(outputs) -> list[Rejection]:
    return [o for o in outputs if isinstance(o, Rejection)]


@cache
def l3_run():
    sim, events = train_on("L3", 400)
    return sim, events, IngestionCore(network()).run(events)


# --- the clean path ------------------------------------------------------------------------


def test_every_chunk_comes_out_positioned_and_bracketed():
    _, events, out = l3_run()
    chunks = positioned(out)
    assert rejections(out) == []
    assert [c.seq for c in chunks] == list(range(400))
    # the last one too: its tail is dead-reckoned from the last fix, as every chunk's is
    for c in chunks:
        kt = c.knot_t.array()
        assert c.position_ok and c.line == "L3" and not c.gap_before
        assert kt[0] <= c.t0 and kt[-1] >= c.t0 + (N - 1) / 2000.0
        assert c.channels == list(ACCEL_CHANNELS) and c.samples.shape == [N, 6]
    assert [c.seq for c in positioned(IngestionCore(network()).run(events))] == list(range(400))


def test_without_dead_reckoning_chunks_wait_for_the_fix_after_them():
    """With ``extrapolate_s = 0`` a chunk waits for a knot at or after its last sample; the
    last one, flushed without it, is not bracketed (position not ok)."""
    _, events, _ = l3_run()
    core = IngestionCore(network(), IngestionConfig(extrapolate_s=0.0))
    assert positioned(core.step(events[0])) == []  # chunk 0 [T0, T0 + 1)
    assert positioned(core.step(events[1])) == []  # fix T0: not after its last sample
    assert positioned(core.step(events[2])) == []  # chunk 1
    assert [c.seq for c in positioned(core.step(events[3]))] == [0]  # fix T0 + 1
    chunks = positioned(core.run(events[4:]))
    assert [c.seq for c in chunks] == list(range(1, 400))
    assert all(c.position_ok for c in chunks[:-1]) and not chunks[-1].position_ok


def test_parallel_lines_train_on_l3_stays_on_l3_within_metres_of_truth():
    sim, _, out = l3_run()
    chunks = positioned(out)
    assert {c.line for c in chunks} == {"L3"}
    t = np.concatenate([c.knot_t.array() for c in chunks])
    chain = np.concatenate([c.knot_chainage_m.array() for c in chunks])
    truth, _, _, _ = sim.position(t)
    assert truth.max() > 4_900  # the run covers the 5 km next to L1
    err = np.abs(chain - truth)
    assert np.median(err) < 2.0 and err.max() < 8.0


def test_parallel_lines_train_on_l1_stays_on_l1():
    sim, events = train_on("L1", 300, at_m=7_900.0)
    chunks = positioned(IngestionCore(network()).run(events))
    assert {c.line for c in chunks} == {"L1"}
    t = np.concatenate([c.knot_t.array() for c in chunks])
    truth = sim.position(t)[0]
    assert truth.min() < 8_100 and truth.max() > 12_900  # L3 runs beside 8-13 km
    err = np.abs(np.concatenate([c.knot_chainage_m.array() for c in chunks]) - truth)
    assert np.median(err) < 2.0 and err.max() < 8.0


def _fix_at(line_id: str, chainage: float, t: float, offset_m: float = 0.0) -> GpsFix:
    line = network().lines[line_id]
    xy = line.xy_at(chainage)
    h = line.heading_at(chainage)
    xy = xy + offset_m * np.array([-np.sin(h), np.cos(h)])  # to the left
    lon, lat = network().to_lonlat(xy)
    return GpsFix(train="T1", t=t, lat_deg=float(lat), lon_deg=float(lon), speed_mps=20.0, hdop=1.0)


def test_map_matching_switches_only_after_several_clear_fixes():
    """On the parallel stretch: one outlier fix on L1 does not move the train off L3;
    fixes consistently on L1 do, after ``switch_fixes`` of them."""
    cfg = IngestionConfig()
    core = IngestionCore(network(), cfg)
    l1 = network().lines["L1"]
    l3 = network().lines["L3"]
    fixes = [_fix_at("L3", 1000 + 20 * k, T0 + k) for k in range(5)]
    c = float(l1.project(network().to_xy([fixes[-1].lon_deg, fixes[-1].lat_deg]))[0])
    fixes.append(_fix_at("L1", c + 20, T0 + 5))  # one outlier onto L1
    fixes += [_fix_at("L3", 1120 + 20 * k, T0 + 6 + k) for k in range(3)]
    for f in fixes:
        core.step(f)
    assert core.trains["T1"].line == "L3" and core.train_stats("T1").switches == 0
    c = float(l1.project(l3.xy_at(1200.0))[0])
    for k in range(cfg.switch_fixes):
        core.step(_fix_at("L1", c + 20 * k, T0 + 9 + k))
    assert core.trains["T1"].line == "L1" and core.train_stats("T1").switches == 1


def test_tunnel_marks_position_not_ok_and_recovers_after():
    sim, events = train_on("L1", 110, at_m=4_900.0)
    chunks = positioned(IngestionCore(network()).run(events))
    assert {c.line for c in chunks} == {"L1"}
    cfg = IngestionConfig()
    tunnel = network().lines["L1"].tunnels[0]
    for c in chunks[:-1]:
        chain, _, _, _ = sim.position(np.array([c.t0, c.t0 + 1.0]))
        inside_long = sim.in_tunnel(chain).all() and chain[0] > tunnel[0] + 30 * cfg.dead_reckon_s
        far_out = (chain < tunnel[0] - 50).all() or (chain > tunnel[1] + 50).all()
        if inside_long:
            assert not c.position_ok, c.seq
        elif far_out:
            assert c.position_ok, c.seq
    assert sum(not c.position_ok for c in chunks) >= 30  # ~1.2 km at <= 27 m/s
    assert chunks[-2].position_ok


def test_projection_agrees_with_line_project():
    line = network().lines["L1"]
    geometry = _LineGeometry.of(line)
    rng = np.random.default_rng(3)
    for c in rng.uniform(0, line.length_m, 20):
        p = line.xy_at(c) + rng.normal(0, 20, 2)
        want = line.project(p)
        got = geometry.project(p)
        assert np.allclose(got, [float(want[0]), float(want[1])], atol=1e-6)


# --- validation: a dead letter with a reason, the good data around it goes through ----------


def _with_nan(c: RawChunk) -> RawChunk:
    a = c.samples.array().copy()
    a[5, 2] = np.nan
    bad = NDArray.of(c.samples.array(), "f4")
    msgspec.structs.force_setattr(bad, "data", a.tobytes())  # the schema would refuse it
    return msgspec.structs.replace(c, samples=bad)


def _low_supply(c: RawChunk) -> RawChunk:
    a = c.samples.array().copy()
    a[:, 6] = 1.2
    return msgspec.structs.replace(c, samples=NDArray.of(a, "f4"))


BAD = {
    "rate": (lambda c: msgspec.structs.replace(c, rate_hz=1000.0), "rate_hz"),
    "channels": (
        lambda c: msgspec.structs.replace(c, channels=["x7", "x8", *RAW_CHANNELS[2:]]),
        "channels: need ['left_z', 'right_z'] or ['left_y', 'right_y']",
    ),
    "nan": (_with_nan, "NaN"),
    "supply": (_low_supply, "supply_v"),
    "t0": (lambda c: msgspec.structs.replace(c, t0=c.t0 + 0.5), "t0"),
}


@pytest.mark.parametrize("kind", sorted(BAD))
def test_invalid_chunk_is_rejected_with_a_reason_and_neighbours_pass(kind):
    spoil, words = BAD[kind]
    _, events = train_on("L3", 12)
    bad = spoil(chunk(6))
    events = [e for e in events if not (isinstance(e, RawChunk) and e.seq == 6)]
    events.insert(events.index(chunk(5)) + 1, bad)
    core = IngestionCore(network())
    out = core.run(events)
    (rejection,) = rejections(out)
    assert rejection.message is bad and words in rejection.reason
    assert rejection.reason.startswith("RawChunk: ")
    chunks = positioned(out)
    assert [c.seq for c in chunks] == [s for s in range(12) if s != 6]
    assert [c.seq for c in chunks if c.gap_before] == [7]
    assert core.health("T1", "u0").rejected == 1


def test_gps_going_backwards_is_rejected_duplicate_fix_is_dropped():
    _, events = train_on("L3", 6)
    fixes = [e for e in events if isinstance(e, GpsFix)]
    core = IngestionCore(network())
    out = core.run([*events[:6], fixes[1], fixes[2], *events[6:]])
    (rejection,) = rejections(out)
    assert rejection.message is fixes[1] and "before the previous fix" in rejection.reason
    assert core.train_stats("T1").duplicates == 1
    assert len(positioned(out)) == 6


def test_late_chunk_after_gap_reported_is_rejected():
    _, events = train_on("L3", 14)
    late = chunk(3)
    events = [e for e in events if e != late] + [late]
    core = IngestionCore(network())
    out = core.run(events)
    (rejection,) = rejections(out)
    assert rejection.message is late and "late" in rejection.reason
    assert [c.seq for c in positioned(out) if c.gap_before] == [4]


def test_unmatched_train_chunks_are_dead_lettered_not_lost():
    far = GpsFix(train="T9", t=T0, lat_deg=-30.0, lon_deg=150.0, speed_mps=0.0, hdop=1.0)
    out = IngestionCore(network()).run([chunk(0, train="T9"), far])
    (rejection,) = rejections(out)
    assert rejection.reason.startswith("unpositioned")


# --- duplicates, reordering, gaps --------------------------------------------------------------


def test_duplicates_and_reordering_give_the_in_order_output():
    _, events = train_on("L3", 40)
    want = IngestionCore(network()).run(events)
    shuffled = list(events)
    idx = [i for i, e in enumerate(shuffled) if isinstance(e, RawChunk)]
    rng = np.random.default_rng(7)
    for a in range(0, len(idx) - 4, 4):  # permute chunks within windows of 4
        block = [shuffled[i] for i in idx[a : a + 4]]
        for i, e in zip(idx[a : a + 4], rng.permutation(block), strict=True):
            shuffled[i] = e
    for k in (3, 10, 11, 25):  # duplicates, some right away, some later
        shuffled.insert(rng.integers(idx[k], idx[k] + 8), chunk(k))
    core = IngestionCore(network())
    got = core.run(shuffled)
    assert rejections(got) == []

    def by_seq(outputs):
        return sorted(positioned(outputs), key=lambda c: c.seq)

    # Samples, order, gaps: the same. Positions: a chunk goes out with what is known when
    # it is released (a reordered chunk waits for its predecessor, by when more fixes are
    # in), so they agree within the dead reckoning's error, not to the bit.
    for a, b in zip(by_seq(got), by_seq(want), strict=True):
        same_knots = {f: getattr(b, f) for f in ("knot_t", "knot_chainage_m", "knot_speed_mps")}
        assert encode(msgspec.structs.replace(a, **same_knots)) == encode(b)
        t = a.t0 + np.arange(0, N, 100) / 2000.0
        assert np.abs(_chainage_at(a, t) - _chainage_at(b, t)).max() < 3.0  # m
    assert core.health("T1", "u0").duplicates == 4
    # without dead reckoning, positions only ever come from the fixes around a chunk
    hold = IngestionConfig(extrapolate_s=0.0)
    got, want = (
        IngestionCore(network(), hold).run(shuffled),
        IngestionCore(network(), hold).run(events),
    )
    assert [encode(c) for c in by_seq(got)] == [encode(c) for c in by_seq(want)]


def _chainage_at(c: PositionedChunk, t: np.ndarray) -> np.ndarray:
    return np.interp(t, c.knot_t.array(), c.knot_chainage_m.array())


def test_missing_chunk_flags_gap_on_the_next():
    _, events = train_on("L3", 20)
    events = [e for e in events if e != chunk(8)]
    core = IngestionCore(network())
    chunks = positioned(core.run(events))
    assert [c.seq for c in chunks] == [s for s in range(20) if s != 8]
    assert [c.seq for c in chunks if c.gap_before] == [9]
    assert core.health("T1", "u0").missing == 1


def test_gap_is_declared_only_after_the_reorder_window():
    core = IngestionCore(network())
    cfg = core.cfg
    outs = [core.step(chunk(0))]
    for k in range(2, 2 + cfg.reorder_chunks - 1):  # seq 1 missing, window still open
        outs.append(core.step(chunk(k)))
    assert core.units[("T1", "u0")].next_seq == 1
    core.step(chunk(2 + cfg.reorder_chunks - 1))  # the window closes
    assert core.units[("T1", "u0")].next_seq == 2 + cfg.reorder_chunks
    assert core.health("T1", "u0").missing == 1


def test_restarted_counter_starts_over_with_a_gap():
    _, events = train_on("L3", 12)
    restarted = [
        chunk(k - 8, t0=T0 + k) if isinstance(e, RawChunk) and e.seq >= 8 else e
        for k, e in ((e.seq if isinstance(e, RawChunk) else -1, e) for e in events)
    ]
    core = IngestionCore(network())
    chunks = positioned(core.run(restarted))
    assert [c.seq for c in chunks] == [*range(8), *range(4)]
    assert [c.t0 - T0 for c in chunks if c.gap_before] == [8.0]
    assert core.health("T1", "u0").restarts == 1


# --- correction and health ---------------------------------------------------------------------


def test_supply_correction_recovers_the_unscaled_physics():
    rng = np.random.default_rng(11)
    physics_g = rng.normal(0.0, 0.3, (N, 6))
    physics_g[:, [0, 3]] += 1.0
    volts = 5.0 * (1 + 0.03 * np.sin(np.arange(N) / 300.0)) + rng.normal(0, 0.002, N)
    volts[700:900] *= 0.88  # a sag
    raw = np.empty((N, 7), np.float32)
    raw[:, :6] = physics_g * (volts / 5.0)[:, None]  # the ratiometric sensor
    raw[:, 6] = volts
    _, events = train_on("L3", 3)
    events[0] = chunk(0, samples=raw)
    out = positioned(IngestionCore(network()).run(events))
    got = out[0].samples.array()
    assert got.dtype == np.float32 and out[0].channels == list(ACCEL_CHANNELS)
    want = physics_g * G_MPS2
    # float32 in, float32 out: a few units in the last place of |a| ~ 10-30 m/s^2
    assert np.allclose(got, want, rtol=1e-6, atol=2e-6)
    assert "supply" in out[0].sensor_flags


def test_supply_correction_on_simulated_bogie_chunk_keeps_gravity_in_z():
    line = network().lines["L3"]
    profile = LineProfile("L3", [(s.start_m, s.end_m) for s in line.segments], 1)
    sim = TrainSimulator("T1", line, profile, 1, start_t=T0, phase_s=120.0)
    events = []
    for k in range(3):
        t0, x, _ = sim.chunk(k)
        events.append(chunk(k, samples=x, t0=t0))
        events += sim.gps_fixes(t0, t0 + 1.0)
    out = positioned(IngestionCore(network()).run(events))
    assert len(out) == 3
    for c, raw in zip(out, (e for e in events if isinstance(e, RawChunk)), strict=True):
        a, v = raw.samples.array()[:, :6].astype(np.float64), raw.samples.array()[:, 6]
        assert np.allclose(c.samples.array(), a * (5.0 / v)[:, None] * G_MPS2, rtol=1e-6)
        z = c.samples.array()[:, [0, 3]].mean()
        assert abs(z - G_MPS2) < 0.2  # gravity stays in z


def test_clipping_flatline_and_dropout_flags_and_counters():
    base = chunk(0).samples.array().copy()
    clipped = base.copy()
    clipped[100:140, 0] = 16.0  # 40 samples at full scale
    flat = base.copy()
    flat[500:900, 4] = flat[500, 4]  # held value on right_y
    flat[1000:1400, 2] = 0.0  # stuck at zero on left_x
    _, events = train_on("L3", 3)
    events[0] = chunk(0, samples=clipped)
    events[events.index(chunk(1))] = chunk(1, samples=flat)
    core = IngestionCore(network())
    out = positioned(core.run(events))
    assert out[0].sensor_flags == ["clipping"]
    assert out[1].sensor_flags == ["dropout:left_x", "flatline:right_y"]
    assert out[2].sensor_flags == []
    h = core.health("T1", "u0")
    assert (h.clipped_samples, h.clipping_chunks, h.chunks) == (40, 1, 3)
    assert h.flatline_chunks == {"right_y": 1} and h.dropout_chunks == {"left_x": 1}
    assert h.clip_fraction == pytest.approx(40 / (3 * N * 6))
    assert core.health("T1", "nope").chunks == 0


def test_channels_in_another_order_are_put_in_canonical_order():
    order = [6, 3, 4, 5, 0, 1, 2]
    c = chunk(0)
    shuffled = msgspec.structs.replace(
        c,
        channels=[RAW_CHANNELS[i] for i in order],
        samples=NDArray.of(c.samples.array()[:, order], "f4"),
    )
    _, events = train_on("L3", 2)
    want = positioned(IngestionCore(network()).run(events))[0]
    events[0] = shuffled
    got = positioned(IngestionCore(network()).run(events))[0]
    assert encode(got) == encode(want)


@pytest.mark.parametrize(
    "channels",
    [["right_z", "supply_v", "left_z"], ["left_y", "right_y", "right_x", "supply_v"]],
)
def test_a_chunk_of_one_channel_pair_is_passed_on_with_those_channels(channels):
    """A vertical-only (or lateral-only) sensor: its channels are corrected and passed on
    in canonical order, as the same columns of a full chunk are."""
    _, events = train_on("L3", 2)
    full = positioned(IngestionCore(network()).run(events))[0]
    cols = [RAW_CHANNELS.index(c) for c in channels]
    raw = events[0]
    events[0] = msgspec.structs.replace(
        raw, channels=channels, samples=NDArray.of(raw.samples.array()[:, cols], "f4")
    )
    core = IngestionCore(network())
    got = positioned(core.run(events))[0]
    kept = [c for c in ACCEL_CHANNELS if c in channels]
    assert got.channels == kept and got.samples.shape == [N, len(kept)]
    want = full.samples.array()[:, [ACCEL_CHANNELS.index(c) for c in kept]]
    assert np.array_equal(got.samples.array(), want)
    assert core.health("T1", "u0").values == N * (len(kept) + 6)  # and the full second one


def test_a_chunk_of_neither_pair_is_refused_with_the_channels_it_needs():
    raw = chunk(0)
    cols = [RAW_CHANNELS.index(c) for c in ("left_z", "left_y", "supply_v")]
    bad = msgspec.structs.replace(
        raw,
        channels=["left_z", "left_y", "supply_v"],
        samples=NDArray.of(raw.samples.array()[:, cols], "f4"),
    )
    (rejection,) = rejections(IngestionCore(network()).run([bad]))
    assert rejection.reason.startswith(
        "RawChunk: channels: need ['left_z', 'right_z'] or ['left_y', 'right_y'], each with"
    )
    no_supply = msgspec.structs.replace(raw, channels=RAW_CHANNELS[:6] + ["v"])
    (rejection,) = rejections(IngestionCore(network()).run([no_supply]))
    assert rejection.reason.startswith("RawChunk: channels: missing ['supply_v']")


def test_config_from_dict_refuses_unknown_keys():
    assert IngestionConfig.from_dict({"rate_hz": 1000}).rate_hz == 1000
    with pytest.raises(ValueError, match="unknown"):
        IngestionConfig.from_dict({"rate": 1})
