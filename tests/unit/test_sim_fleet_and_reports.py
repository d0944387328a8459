"""The simulator's unkind world: unreported and late maintenance, a mixed fleet."""

from __future__ import annotations

import copy

import numpy as np
import pytest

from schemas import DAY_S, OnboardIndex, RawChunk
from services.defaults import demo_network
from simulators.fleet import MIXED, Fleet
from simulators.groundtruth import GroundTruthWriter, load_truth
from simulators.truth import Truth, truth_events
from simulators.world import VERTICAL_CHANNELS, WorldSpec, index_pass_events, raw_train_events

T0 = 1767225600.0  # 2026-01-01T00:00:00Z


def unkind(cfg, unreported=0.3, late=0.4):
    out = copy.deepcopy(cfg)
    out["maintenance"].update(unreported_fraction=unreported, late_fraction=late, late_days=[5, 9])
    return out


def run_truth(net, cfg, days=3 * 365, seed=31):
    seen: list = []
    events = list(
        truth_events(net, cfg, T0, days, seed, on_step=lambda tr, taps: seen.extend(taps))
    )
    return seen, events


def test_unreported_and_late_tampings_change_only_the_reports(net, cfg):
    kind_taps, kind_events = run_truth(net, cfg)
    taps, events = run_truth(net, unkind(cfg))
    # the same tampings happen (the reporting draws have keys of their own)
    assert [(tp.event_id, tp.t, tp.t_start, tp.t_end) for tp in taps] == [
        (tp.event_id, tp.t, tp.t_start, tp.t_end) for tp in kind_taps
    ]
    assert {tp.report for tp in kind_taps} == {"on_time"}
    reports = np.array([tp.report for tp in taps])
    assert len(taps) > 300
    never = np.mean(reports == "never")
    assert 0.24 < never < 0.36  # configured 0.3
    assert 0.33 < np.sum(reports == "late") / np.sum(reports != "never") < 0.47  # 0.4
    published = {m.event_id: t for t, ms in events for m in ms}
    by_id = {tp.event_id: tp for tp in taps}
    end = T0 + 3 * 365 * DAY_S
    for tp in taps:
        if tp.report == "never":
            assert tp.event_id not in published and tp.t_reported is None
        elif tp.t_reported < end:
            assert published[tp.event_id] == tp.t_reported
            delay = (tp.t_reported - tp.t_end) / DAY_S
            assert delay == 0 if tp.report == "on_time" else 5 <= delay <= 9
    assert all(by_id[i].report != "never" for i in published)
    assert [t for t, _ in events] == sorted(t for t, _ in events)


def test_the_default_fleet_is_the_index_model_for_every_unit(cfg):
    fleet = Fleet.from_config(cfg, 3)
    for train in ("TL1-00", "TL2-05"):
        u = fleet.unit(train, "bogie1")
        assert u.vehicle_class == "standard" and u.gain == 1.0
        np.testing.assert_array_equal(u.model.H, fleet.base.H)
        np.testing.assert_array_equal(u.model.b, fleet.base.b)


def test_a_mixed_fleet_draws_classes_by_share_and_sensors_within_their_spread(cfg):
    fleet = Fleet.from_config({**cfg, "fleet": MIXED}, 3)
    units = [fleet.unit(f"T{i:04d}", "bogie1") for i in range(3000)]
    classes = np.array([u.vehicle_class for u in units])
    for name, c in MIXED["classes"].items():
        assert abs(np.mean(classes == name) - c["share"]) < 0.03
    gains = np.array([u.gain for u in units])
    assert 0.9 <= gains.min() < 0.91 and 1.09 < gains.max() <= 1.1
    offsets = np.array([u.offset for u in units])
    np.testing.assert_allclose(offsets.std(axis=0), MIXED["offset_sd"], rtol=0.08)
    again = fleet.unit("T0007", "bogie1")  # a unit keeps its model
    assert again.gain == units[7].gain and np.array_equal(again.model.b, units[7].model.b)
    u = units[7]
    klass = next(c for n, c in MIXED["classes"].items() if n == u.vehicle_class)
    np.testing.assert_allclose(
        u.model.b, fleet.base.b + klass["b_shift"] + np.log(u.gain) + u.offset
    )
    with pytest.raises(ValueError, match="gain_spread"):
        Fleet.from_config({**cfg, "fleet": {**MIXED, "gain_spread": 1.5}}, 3)


def test_passes_follow_their_units_model_and_the_ground_truth_records_it(net, cfg, tmp_path):
    mixed = {**cfg, "fleet": MIXED}
    days, seed = 8, 5  # a few dozen passes per train: the residual bound scales with them
    path = tmp_path / "truth.sqlite"
    events = list(index_pass_events(net, Truth(net, mixed, T0, seed), 4, days, seed, config=mixed))
    with GroundTruthWriter(path, net, mixed, T0, days, seed) as gt:
        for t, msgs in events:
            gt.record(t, msgs)
    d = load_truth(path)
    assert len(set(d["units_train"])) == 4 * len(net.lines)
    fleet = Fleet.from_config(mixed, seed)
    for k, train in enumerate(d["units_train"]):
        u = fleet.unit(str(train), str(d["units_unit"][k]))
        assert d["units_vehicle_class"][k] == u.vehicle_class and d["units_gain"][k] == u.gain
        sel = d["onboard_train"] == train
        # residual of each pass against its own unit's model: mean ~0, spread ~sqrt(R)
        y = np.log(d["onboard_mm"][sel])
        r = y - (d["onboard_z"][sel] @ u.model.H.T + u.model.b)
        assert (
            np.abs(r.mean(axis=0)).max()
            < 4 * np.sqrt(np.diag(u.model.R)).max() / np.sqrt(sel.sum()) + 1e-9
        )
    # different units read the same track differently
    b = np.stack([d["units_b_top"], d["units_b_align"]], -1)
    assert np.ptp(b[:, 0]) > 0.1


def test_onboard_messages_are_unchanged_by_the_default_fleet_section(net, cfg):
    explicit = {**cfg, "fleet": {"classes": {"standard": {"share": 1.0}}}}
    a = list(index_pass_events(net, Truth(net, cfg, T0, 2), 2, 2, 2, config=cfg))
    b = list(index_pass_events(net, Truth(net, explicit, T0, 2), 2, 2, 2, config=explicit))
    assert a == b and all(isinstance(m, OnboardIndex) for _, ms in a for m in ms)


def test_raw_mode_units_read_with_their_gain_and_tilt_and_classes_change_the_bogie(cfg):
    from simulators.bogie import BogiePhysics
    from simulators.profile import LineProfile
    from simulators.train import TrainConfig, TrainSimulator

    line = demo_network().lines["L1"]
    profile = LineProfile(line.id, [(s.start_m, s.end_m) for s in line.segments], 3)
    quiet = TrainConfig(physics=BogiePhysics(noise_density_g=0.0, outlier_rate_hz=0.0,
                                             flatline_rate_hz=0.0, supply_fluct=0.0,
                                             supply_noise_v=0.0, sag_rate_hz=0.0))  # fmt: skip

    def samples(sensors):
        sim = TrainSimulator("T000", line, profile, 3, units=1, config=quiet, sensors=sensors)
        return np.vstack([sim.chunk(k)[1] for k in range(300, 310)]).astype(np.float64)

    exact, gained, tilted = samples(None), samples([(1.1, 0.0)]), samples([(1.0, 0.03)])
    np.testing.assert_allclose(gained[:, :6], 1.1 * exact[:, :6], rtol=1e-5, atol=1e-5)
    # a tilt of 0.03 rad puts ~0.03 g of gravity into the lateral channels
    assert abs((tilted[:, 1] - exact[:, 1]).mean() - np.sin(0.03)) < 0.005
    fleet = Fleet.from_config({**cfg, "fleet": MIXED}, 3)
    trains = [f"T{i:03d}" for i in range(40)]
    loco = next(t for t in trains if fleet.vehicle_class(t).name == "loco_hauled")
    conf = fleet.train_config(loco)
    assert conf.physics.wheelbase_m == 2.8 and conf.cruise_factor == (0.6, 0.8)
    assert Fleet.from_config(cfg, 3).train_config("T000") == TrainConfig()  # the default fleet


def test_vertical_only_units_send_top6_indices_and_vertical_channels(net, cfg):
    half = copy.deepcopy(cfg)
    half.setdefault("fleet", {})["vertical_only_share"] = 0.5
    fleet = Fleet.from_config(half, 5)
    flags = [fleet.unit(f"T{i:03d}", "u0").vertical_only for i in range(200)]
    assert 70 < sum(flags) < 130
    base = Fleet.from_config(cfg, 5).unit("T000", "u0")
    same = fleet.unit("T000", "u0")  # the share draws on a stream of its own
    assert (same.gain, same.mount_rad) == (base.gain, base.mount_rad)
    msgs = [
        m for _, ms in index_pass_events(net, Truth(net, half, T0, 2), 4, 1, 2, config=half)
        for m in ms
    ]  # fmt: skip
    kinds = {m.train: tuple(m.indicators) for m in msgs}
    assert set(kinds.values()) == {("top6",), ("top6", "align10")}
    for m in msgs:
        assert (m.align10_mm is None) == (kinds[m.train] == ("top6",))
    with pytest.raises(ValueError, match="vertical_only_share"):
        Fleet.from_config({**cfg, "fleet": {"vertical_only_share": 2}}, 5)


def test_a_vertical_only_raw_unit_sends_the_vertical_channels_and_supply(cfg):
    config = copy.deepcopy(cfg)
    config.setdefault("fleet", {})["vertical_only_share"] = 1.0
    spec = WorldSpec(demo_network(), config, T0, 30 / DAY_S, 3, 1, "raw")
    chunks = [m for _, ms in raw_train_events(spec) for m in ms if isinstance(m, RawChunk)]
    assert chunks and all(c.channels == list(VERTICAL_CHANNELS) for c in chunks)
    assert all(c.samples.shape[1] == 3 for c in chunks)
