"""Simulator physics: profiles, versine contract, bogie signal chain, trains and GPS."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from scipy import signal

from simulators.bogie import BogiePhysics, BogieUnit, Kinematics
from simulators.profile import LineProfile, TrackSpectrum
from simulators.train import TrainConfig, TrainSimulator
from track import versine

QUIET = BogiePhysics(
    outlier_rate_hz=0.0, flatline_rate_hz=0.0, sag_rate_hz=0.0, missing_chunk_prob=0.0
)


class StraightLine:
    """A stand-in line: straight, east from (153 E, 27.5 S), two stations and a tunnel."""

    def __init__(self, length_m: float = 6000.0) -> None:
        self.length_m = length_m
        self.stations = [0.0, length_m / 2, length_m]
        self.line_speed_mps = 30.0
        self.tunnels = [(1000.0, 1600.0)]

    def lonlat_at(self, chainage: float) -> tuple[float, float]:
        lat = -27.5
        return 153.0 + np.degrees(chainage / (6_371_000.0 * np.cos(np.radians(lat)))), lat


T0 = 1_767_225_600.0  # 2026-01-01: fixes must lie in the schemas' time window


def make_profile(length_m=6000.0, seed=7, top_mm=2.0, align_mm=1.5, **kw) -> LineProfile:
    s = int(length_m // 200)
    bounds = np.c_[np.arange(s) * 200.0, np.arange(1, s + 1) * 200.0]
    lp = LineProfile("L1", bounds, seed, **kw)
    lp.update(np.log(np.c_[np.full(s, top_mm), np.full(s, align_mm)]), np.zeros(s, int))
    return lp


def standing(n: int, t0: float = 0.0, chainage: float = 2500.0) -> Kinematics:
    t = t0 + np.arange(n) / 2000.0
    zero = np.zeros(n)
    return Kinematics(t, zero + chainage, zero, zero, np.ones(n), zero)


def moving(n: int, t0: float = 0.0, speed: float = 25.0) -> Kinematics:
    t = t0 + np.arange(n) / 2000.0
    return Kinematics(t, 300.0 + speed * t, np.full(n, speed), np.zeros(n), np.ones(n), speed * t)


# -- versine contract ----------------------------------------------------------------


@pytest.mark.parametrize("chord", [versine.TOP_CHORD_M, versine.ALIGN_CHORD_M])
def test_versine_of_a_sinusoid_and_its_valid_slice(chord):
    dx, lam = 0.25, 17.0
    x = np.arange(2000) * dx
    v = versine.chord_versine(np.sin(2 * np.pi * x / lam), dx, chord)
    h = versine.half_chord_samples(dx, chord)
    assert v.shape == (2000 - 2 * h,)
    expected = (1 - np.cos(np.pi * chord / lam)) * np.sin(2 * np.pi * x[h:-h] / lam)
    assert np.allclose(v, expected, atol=1e-12)
    assert np.isclose(versine.segment_statistic(v), np.std(expected))
    with pytest.raises(ValueError):
        versine.chord_versine(x, 0.4, chord)


# -- profiles ------------------------------------------------------------------------


def test_segment_statistic_equals_exp_z_exactly_for_both_indicators_and_rails():
    lp = make_profile()
    rng = np.random.default_rng(1)
    z = rng.normal([0.7, 0.3], 0.4, (lp.n_segments, 2))
    epoch = rng.integers(0, 3, lp.n_segments)
    lp.update(z, epoch)
    for k in (0, 7, lp.n_segments - 1):
        _, p, inner = lp.segment_profile(k)
        for c, chord in enumerate(
            (versine.TOP_CHORD_M, versine.TOP_CHORD_M, versine.ALIGN_CHORD_M, versine.ALIGN_CHORD_M)
        ):
            h = versine.half_chord_samples(lp.spacing_m, chord)
            g = round(versine.END_GUARD_M / lp.spacing_m)  # whole chords, 1 m inside the ends
            v = versine.chord_versine(p[c, inner.start + g : inner.stop - g], lp.spacing_m, chord)
            assert v.size == inner.stop - inner.start - 2 * (h + g)
            assert versine.segment_statistic(v) == pytest.approx(np.exp(z[k, c // 2]), rel=1e-9)
    # A tamping (new epoch) draws a fresh shape, still scaled exactly.
    before = lp.segment_profile(3)[1].copy()
    epoch[3] += 1
    assert list(lp.update(z, epoch)) == [3]
    assert not np.allclose(lp.segment_profile(3)[1], before)
    assert np.allclose(lp.segment_statistics(3), np.exp(z[3, [0, 0, 1, 1]]), rtol=1e-9)


def test_line_profile_is_close_to_the_segment_profiles_and_left_right_correlated():
    lp = make_profile()
    x, p, inner = lp.segment_profile(5)
    mid = slice(inner.start + 40, inner.stop - 40)  # away from the cross-fades
    assert np.allclose(lp.sample(x[mid]), p[:, mid])
    corr = np.corrcoef(lp.line)
    assert corr[0, 1] > 0.6 and corr[2, 3] > 0.6


def test_profile_psd_has_the_intended_shape():
    lp = make_profile(length_m=20000.0)
    f, pxx = signal.welch(lp.line[0], fs=1 / lp.spacing_m, nperseg=2048)
    lam = 1 / f[1:]
    pxx = pxx[1:]
    long_, short = (lam > 20) & (lam < 60), (lam > 1.2) & (lam < 5)
    assert pxx[long_].mean() > 100 * pxx[short].mean()
    # Shape against the spectrum: ratio between 30 m and 3 m wavelengths within 2x.
    spec = TrackSpectrum()
    got = np.interp([30, 3], lam[::-1], pxx[::-1])
    want = spec.psd(2 * np.pi / np.array([30.0, 3.0]))
    assert 0.5 < (got[0] / got[1]) / (want[0] / want[1]) < 2.0
    assert pxx[lam < 0.9].max() < 1e-6 * pxx.max()  # band-limited at 1 m


# -- bogie ---------------------------------------------------------------------------


def test_accelerometer_noise_floor_matches_300_ug_per_root_hz():
    bogie = BogieUnit(make_profile(top_mm=1e-6, align_mm=1e-6), QUIET, 3, "T1", 0)
    chunks = [bogie.chunk(q, standing(2000, q))[0] for q in range(20)]
    x = np.concatenate(chunks)[:, :6].astype(np.float64)
    f, pxx = signal.welch(x, fs=2000.0, nperseg=1024, axis=0)
    band = (f > 200) & (f < 900)
    assert pxx[band].mean() == pytest.approx(300e-6**2, rel=0.1)
    assert np.allclose(x[:, [0, 3]].mean(axis=0), 1.0, atol=0.05)  # gravity on z


def test_clipping_at_16_g():
    bogie = BogieUnit(make_profile(top_mm=5e4, align_mm=5e4), QUIET, 3, "T1", 0)
    x, _ = bogie.chunk(0, moving(2000))
    assert np.abs(x[:, :6]).max() == 16.0
    assert (np.abs(x[:, :6]) == 16.0).mean() > 0.01


def test_chunks_concatenated_equal_one_long_block():
    lp = make_profile(jointed_fraction=1.0)
    kin = moving(8000)
    one = BogieUnit(lp, QUIET, 3, "T1", 0).dynamics(kin)
    bogie = BogieUnit(lp, QUIET, 3, "T1", 0)
    parts = [
        bogie.dynamics(Kinematics(*(a[i : i + 2000] for a in kin))) for i in range(0, 8000, 2000)
    ]
    assert np.allclose(np.concatenate(parts, axis=1), one, rtol=0, atol=1e-12)
    # The joints make impulses: with them off, the signal differs.
    calm = BogieUnit(lp, replace(QUIET, impulse_g=0.0), 3, "T1", 0).dynamics(kin)
    assert np.abs(one - calm).max() > 0.2


def test_outliers_hit_one_rail_at_a_time():
    phys = replace(QUIET, outlier_rate_hz=0.5, outlier_g=2.0)
    bogie = BogieUnit(make_profile(top_mm=1e-6, align_mm=1e-6), phys, 5, "T1", 0)
    x = np.concatenate([bogie.chunk(q, standing(2000, q))[0] for q in range(40)])
    hit = np.abs(x[:, [0, 3]] - 1.0) > 0.15
    assert hit[:, 0].sum() > 100 and hit[:, 1].sum() > 100
    assert not (hit[:, 0] & hit[:, 1]).any()


def test_supply_voltage_scales_the_accelerometers():
    phys = replace(QUIET, supply_fluct=0.2, sag_rate_hz=2.0)
    bogie = BogieUnit(make_profile(top_mm=1e-6, align_mm=1e-6), phys, 5, "T1", 0)
    x = np.concatenate([bogie.chunk(q, standing(2000, 100 * q))[0] for q in range(10)])
    volts, z = x[:, 6].astype(float), x[:, [0, 3]].astype(float)
    assert volts.std() > 0.1
    assert np.corrcoef(volts, z[:, 0])[0, 1] > 0.95
    assert np.allclose(z * (5.0 / volts[:, None]), 1.0, atol=0.05)  # the correction


def test_dropouts_and_missing_chunks():
    phys = replace(QUIET, flatline_rate_hz=3.0, missing_chunk_prob=1.0)
    bogie = BogieUnit(make_profile(), phys, 5, "T1", 0)
    x, dropped = bogie.chunk(0, moving(2000))
    assert dropped
    flat = (np.diff(x[:, :6], axis=0) == 0).sum(axis=0)
    assert flat.max() > 50


# -- trains and GPS ------------------------------------------------------------------


def make_train(seed=11, **kw) -> TrainSimulator:
    line = StraightLine()
    return TrainSimulator("T1", line, make_profile(seed=seed), seed, **kw)


def test_same_seed_same_bytes():
    a, b = make_train(units=2, start_t=T0), make_train(units=2, start_t=T0)
    c = make_train(seed=12, units=2, start_t=T0)
    for q in range(3):
        for u in range(2):
            ta, xa, da = a.chunk(q, u)
            tb, xb, db = b.chunk(q, u)
            assert (ta, da, xa.tobytes()) == (tb, db, xb.tobytes())
            assert xa.tobytes() != c.chunk(q, u)[1].tobytes()
    assert a.gps_fixes(T0, T0 + 50) == b.gps_fixes(T0, T0 + 50)


def test_speed_profile_has_stops_slow_stretches_and_bounded_acceleration():
    tr = make_train()
    t = np.arange(0.0, 2 * tr.cycle_s, 0.5)
    s, v, a, d = tr.position(t)
    cfg = TrainConfig()
    assert v.max() > 0.85 * 30.0 and v.min() == 0.0
    assert a.max() <= cfg.accel_mps2 + 1e-9 and a.min() >= -cfg.brake_mps2 - 1e-9
    assert ((v > 0) & (v < 5)).mean() > 0.02  # approaches and the speed restriction
    stopped = np.diff(np.r_[0, (v == 0).astype(int), 0])
    dwell = (np.flatnonzero(stopped == -1) - np.flatnonzero(stopped == 1)) * 0.5
    assert dwell.size >= 4 and dwell.min() >= 29.0 and dwell.max() <= 61.0
    assert set(np.unique(d)) == {-1, 1} and s.min() == 0.0 and s.max() == 6000.0
    moving_ = v > 0
    assert (
        np.sign(np.diff(s))[moving_[1:] & moving_[:-1]] == d[1:][moving_[1:] & moving_[:-1]]
    ).all()


def test_gps_drops_out_in_tunnels_and_is_noisy_in_the_open():
    tr = make_train(start_t=T0)
    fixes = tr.gps_fixes(T0, T0 + tr.cycle_s)
    t = np.array([f.t for f in fixes])
    s, v, _, _ = tr.position(t)
    q = np.array([f.fix_quality for f in fixes])
    inside = (s >= 1000) & (s <= 1600)
    assert inside.sum() > 20 and (q[inside] == 0).all()
    open_ = (~inside) & (q > 0)
    assert open_.mean() > 0.8
    lon = np.array([f.lon_deg for f in fixes])[open_]
    truth = np.array([tr.line.lonlat_at(c)[0] for c in s[open_]])
    err_m = np.radians(lon - truth) * 6_371_000.0 * np.cos(np.radians(27.5))
    assert 1.0 < np.sqrt(np.mean(err_m**2)) < 6.0
