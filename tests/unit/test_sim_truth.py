"""The simulator's truth, TRC runs, index sensor model and ground-truth file."""

from __future__ import annotations

import copy
import heapq
import itertools

import numpy as np
import pytest

from schemas import DAY_S, MaintenanceEvent, OnboardIndex, TrcRecord, decode, encode
from simulators.groundtruth import GroundTruthWriter, load_truth
from simulators.index_model import IndexSensorModel
from simulators.trc import trc_events, trc_schedule
from simulators.truth import Truth, TruthConfig, truth_events
from simulators.world import index_pass_events

T0 = 1767225600.0  # 2026-01-01T00:00:00Z


def _history(truth: Truth, days: int):
    """Daily states (days + 1, S, 2), epochs and the tampings of ``days`` steps."""
    z, ep, taps = [truth.z], [truth.epoch.copy()], []
    for _ in range(days):
        taps.extend(truth.step())
        z.append(truth.z)
        ep.append(truth.epoch.copy())
    return np.stack(z), np.stack(ep), taps


def _bytes(events) -> list[bytes]:
    return [encode(m) for _, msgs in events for m in msgs]


def _all_events(net, cfg, seed, days=30):
    return list(
        heapq.merge(
            truth_events(net, cfg, T0, days, seed),
            trc_events(net, cfg, T0, days, seed),
            index_pass_events(net, Truth(net, cfg, T0, seed), 1, days, seed, config=cfg),
            key=lambda e: e[0],
        )
    )


def test_same_seed_same_bytes_other_seed_other_bytes(net, cfg):
    a, b = _all_events(net, cfg, 5), _all_events(net, cfg, 5)
    assert _bytes(a) == _bytes(b) and len(a) > 5_000
    assert {type(m) for _, msgs in a for m in msgs} == {MaintenanceEvent, TrcRecord, OnboardIndex}
    assert _bytes(a) != _bytes(_all_events(net, cfg, 6))
    t = [t for t, _ in a]
    assert t == sorted(t)


def test_truth_does_not_depend_on_line_order(net, cfg):
    reordered = copy.copy(net)
    reordered.lines = dict(reversed(list(net.lines.items())))
    a, b = Truth(net, cfg, T0, 3), Truth(reordered, cfg, T0, 3)
    a.advance_to(T0 + 200 * DAY_S)
    b.advance_to(T0 + 200 * DAY_S)
    for line in net.lines:
        np.testing.assert_array_equal(a.z[a.line_slices[line]], b.z[b.line_slices[line]])


def _no_tamping_config(cfg, **truth):
    raw = copy.deepcopy(cfg)
    raw["truth"].update(truth)
    raw["maintenance"].update(limits_mm=[1e9, 1e9], scheduled_period_days=0)
    return raw


def test_increments_have_the_class_mu_and_sigma(net, cfg):
    """Sample mean and covariance of dz / dt against the class values (no spread)."""
    raw = _no_tamping_config(cfg, mix={"typical": 1.0}, mu_spread=0.0, sigma_spread=0.0)
    raw["truth"]["step_days"] = 2.0
    z, _, taps = _history(Truth(net, raw, T0, 11), 300)
    assert not taps
    dt = 2.0
    dz = np.diff(z, axis=0).reshape(-1, 2)
    n = len(dz)
    c = TruthConfig.from_config(raw).classes["typical"]
    mean_sd = np.sqrt(np.diag(c.sigma) / dt / n)
    assert (np.abs(dz.mean(axis=0) / dt - c.mu) < 5 * mean_sd).all()
    cov = np.cov(dz.T) / dt
    s = c.sigma
    cov_sd = np.sqrt((np.outer(np.diag(s), np.diag(s)) + s**2) / n)
    assert (np.abs(cov - s) < 5 * cov_sd).all()


def test_increments_are_the_wiener_model_per_segment(net, cfg):
    """With segment spread and tampings: whitened increments of untamped steps are N(0, I)."""
    truth = Truth(net, cfg, T0, 12)
    z, ep, taps = _history(truth, 400)
    assert taps  # tampings happened; their steps are left out
    untamped = np.diff(ep, axis=0) == 0
    u = np.diff(z, axis=0) - truth.mu  # (days, S, 2): one-day increments minus the drift
    w = np.linalg.solve(np.linalg.cholesky(truth.sigma), u[..., None])[..., 0]
    w = w[untamped]
    n = len(w)
    hotelling = n * w.mean(axis=0) @ np.linalg.inv(np.cov(w.T)) @ w.mean(axis=0)
    assert hotelling < 18.4  # chi2(2) 0.9999 quantile
    assert np.abs(np.cov(w.T) - np.eye(2)).max() < 5 * np.sqrt(2 / n)


def test_tamping_follows_limit_crossing_and_resets_to_z_plus(net, cfg):
    truth = Truth(net, cfg, T0, 21)
    days = 3 * 365
    z, ep, taps = _history(truth, days)
    t_grid = T0 + np.arange(days + 1) * DAY_S
    lo, hi = cfg["maintenance"]["delay_days"]
    over = (z > truth.log_limits).any(axis=2)  # (days + 1, S)
    n_limit = 0
    for tp in taps:
        assert truth.epoch[tp.seg] >= tp.epoch
        if tp.cause != "limit":
            continue
        n_limit += 1
        # The crossing that triggered it: the first day over the limit since the last reset.
        before = np.flatnonzero(t_grid < tp.t)
        k = before[-1]
        previous = ep[: k + 1, tp.seg] < tp.epoch - 1
        start = np.flatnonzero(previous)[-1] + 1 if previous.any() else 0
        crossed = start + np.flatnonzero(over[start : k + 1, tp.seg])[0]
        delay = (tp.t - t_grid[crossed]) / DAY_S
        assert lo <= delay <= hi + 1e-9
    assert n_limit > 20
    # Every crossing early enough got its tamping (limit or scheduled, whichever first).
    for s in np.flatnonzero(over[: days - int(hi) - 1].any(axis=0)):
        assert ep[-1, s] > 0
    # Epoch counts tampings; levels right after a tamping are N(z_plus, Sigma_z+).
    np.testing.assert_array_equal(
        ep[-1], np.bincount([tp.seg for tp in taps], minlength=truth.n_segments)
    )
    seg = np.array([tp.seg for tp in taps])
    dev = np.array([tp.z_after for tp in taps]) - truth.z_plus[seg]
    w = np.linalg.solve(np.linalg.cholesky(truth.sigma_z_plus[seg]), dev[..., None])[..., 0]
    assert len(w) > 100
    assert (np.abs(w.mean(axis=0)) < 4 / np.sqrt(len(w))).all()
    assert (np.abs(w.std(axis=0) - 1) < 0.15).all()
    assert {tp.cause for tp in taps} == {"limit", "scheduled"}


def test_interval_events_contain_the_true_time(net, cfg):
    truth = Truth(net, cfg, T0, 31)
    seen: list = []
    events = list(
        truth_events(net, cfg, T0, 2 * 365, 31, truth=truth, on_step=lambda tr, t: seen.extend(t))
    )
    true = {tp.event_id: tp for tp in seen}
    msgs = [m for _, ms in events for m in ms]
    assert len(msgs) <= len(true) and len(msgs) > 100
    intervals = 0
    for t, ms in events:
        for m in ms:
            m = decode(encode(m), MaintenanceEvent)
            tp = true[m.event_id]
            assert m.t_start <= tp.t <= m.t_end and t == m.t_end
            intervals += m.t_start < m.t_end
            if m.t_start == m.t_end:
                assert m.t_start == tp.t
    assert 0.1 < intervals / len(msgs) < 0.4  # configured 0.25


def test_z_at_interpolates_and_follows_tamping(net, cfg):
    truth = Truth(net, cfg, T0, 41)
    np.testing.assert_array_equal(truth.z_at(T0), truth.z)
    taps = []
    while not taps:
        z_prev = truth.z.copy()
        taps = truth.step()
    tp = taps[0]
    np.testing.assert_allclose(truth.z_at(tp.t, tp.seg), tp.z_after)
    np.testing.assert_allclose(truth.z_at(tp.t - 1e-3, tp.seg), tp.z_before, atol=1e-6)
    np.testing.assert_array_equal(truth.z_at(truth.t), truth.z)
    mid = truth.t - 0.5 * DAY_S
    other = (tp.seg + 1) % truth.n_segments
    if other not in {x.seg for x in taps}:
        np.testing.assert_allclose(truth.z_at(mid, other), 0.5 * (z_prev[other] + truth.z[other]))
    with pytest.raises(ValueError, match="window"):
        truth.z_at(T0 - DAY_S)


def test_bad_config_is_refused(cfg):
    raw = copy.deepcopy(cfg)
    raw["truth"]["mix"] = {"fast": 1.0, "medium": 1.0}
    with pytest.raises(ValueError, match="truth.mix"):
        TruthConfig.from_config(raw)
    raw = copy.deepcopy(cfg)
    raw["maintenance"]["limits_mm"] = [6.0]
    with pytest.raises(ValueError, match="limits_mm"):
        TruthConfig.from_config(raw)


def test_trc_schedule_like_table_1(net, cfg):
    runs = trc_schedule(net, cfg, T0, 3 * 365, 1)
    for line in net.lines:
        mine = [r for r in runs if r.line == line]
        gaps = np.diff([r.t_start for r in mine]) / (7 * DAY_S)
        assert ((gaps >= 8) & (gaps <= 11)).all() and len(mine) >= 14
        assert 0 <= (mine[0].t_start - T0) / DAY_S <= 14
        assert [r.onboard for r in mine] == [k < 5 for k in range(len(mine))]
        assert len({r.run_id for r in mine}) == len(mine)


def test_trc_records_and_campaign_indices(net, cfg):
    events = list(trc_events(net, cfg, T0, 200, 2))
    trc = [m for _, ms in events for m in ms if isinstance(m, TrcRecord)]
    onboard = [m for _, ms in events for m in ms if isinstance(m, OnboardIndex)]
    for m in trc + onboard:
        assert decode(encode(m), type(m)) == m
    runs = trc_schedule(net, cfg, T0, 200, 2)
    assert len(trc) == sum(len(net.lines[r.line].segments) for r in runs)
    assert len(onboard) == len(trc)  # every run in 200 days is a campaign run
    assert all(o.train == "TRC" and o.unit == "onboard" and o.run_id for o in onboard)
    assert {(o.run_id, o.segment, o.t) for o in onboard} == {
        (r.run_id, r.segment, r.t) for r in trc
    }
    # Within a run the car moves at its speed along the chainage.
    line = net.lines["L1"]
    first = [r for r in trc if r.run_id == "TRC-L1-000"]
    dt = first[-1].t - first[0].t
    assert dt == pytest.approx((line.segments[-1].mid_m - line.segments[0].mid_m) / 22.0)
    raw = list(trc_events(net, cfg, T0, 200, 2, fidelity="raw"))
    assert all(isinstance(m, TrcRecord) for _, ms in raw for m in ms)


def test_index_sensor_model(cfg):
    model = IndexSensorModel.from_config(cfg)
    z = np.log(np.random.default_rng(1).uniform(1.5, 8.0, (100_000, 2)))
    y = np.log(model.indices(z, np.random.default_rng(2)))
    e = y - z @ model.H.T - model.b
    assert np.abs(e.mean(axis=0)).max() < 0.003
    np.testing.assert_allclose(np.cov(e.T), model.R, atol=0.001)
    assert (y.mean(axis=0) < z.mean(axis=0)).all()  # on-board reads low
    with pytest.raises(ValueError, match="index.R"):
        IndexSensorModel(model.H, model.b, -model.R)


def test_index_passes_cover_every_segment(net, cfg):
    events = list(index_pass_events(net, Truth(net, cfg, T0, 4), 3, 2, 4, config=cfg))
    msgs = [m for _, ms in events for m in ms]
    assert len(msgs) == 2 * 3 * net.n_segments
    for m in msgs[:: len(msgs) // 50]:
        assert decode(encode(m), OnboardIndex) == m
    t = [t for t, _ in events]
    assert t == sorted(t)
    day0 = [m for m in msgs if m.t < T0 + DAY_S and m.line == "L2"]
    for _, passes in itertools.groupby(sorted(day0, key=lambda m: m.train), lambda m: m.train):
        passes = list(passes)
        assert len(passes) == len(net.lines["L2"].segments)
        assert T0 + 5 * 3600 <= min(p.t for p in passes) <= max(p.t for p in passes)
        assert max(p.t for p in passes) <= T0 + 23 * 3600


def test_ground_truth_file_round_trip(net, cfg, tmp_path):
    days, seed = 30, 9
    path = tmp_path / "truth.sqlite"
    published = _all_events(net, cfg, seed, days)
    with GroundTruthWriter(path, net, cfg, T0, days, seed) as gt:
        for t, msgs in published:
            gt.record(t, msgs)
    d = load_truth(path)
    truth = Truth(net, cfg, T0, seed)
    z, ep, taps = _history(truth, days)
    np.testing.assert_array_equal(d["z"], z)
    np.testing.assert_array_equal(d["epoch"], ep)
    np.testing.assert_array_equal(d["t"], T0 + np.arange(days + 1) * DAY_S)
    np.testing.assert_array_equal(d["mu"], truth.mu)
    np.testing.assert_array_equal(d["sigma"], truth.sigma)
    assert d["line"].tolist() == [k[0] for k in truth.keys]
    assert taps and d["tamping_event_id"].tolist() == [tp.event_id for tp in taps]
    assert d["meta"]["seed"] == str(seed) and float(d["meta"]["days"]) == days
    trc = [m for _, ms in published for m in ms if isinstance(m, TrcRecord)]
    assert len(d["trc_t"]) == len(trc)
    onboard = [m for _, ms in published for m in ms if isinstance(m, OnboardIndex)]
    assert len(d["onboard_t"]) == len(onboard) and set(d["onboard_train"]) >= {"TRC"}
    # TRC records are exp(z + small noise) of the z stored beside them.
    r = np.log(d["trc_mm"]) - d["trc_z"]
    assert np.abs(r.mean(axis=0)).max() < 0.01 and (np.abs(r.std(axis=0) - 0.02) < 0.005).all()
