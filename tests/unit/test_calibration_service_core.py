"""Unit tests of the live calibration core (services/calibration/calibrator.py): lists in,
lists out; persistence through the in-memory and the SQLite store."""

from __future__ import annotations

import functools
import sqlite3
from pathlib import Path

import msgspec
import numpy as np
import pytest

from schemas import (
    DAY_S,
    Calibration,
    DegradationPosterior,
    MaintenanceEvent,
    NDArray,
    TrcRecord,
    decode,
    encode,
)
from services.alerting.testing import make_index
from services.calibration.calibrator import Calibrator
from services.calibration.config import CalibratorConfig
from services.calibration.initial import initial_models
from services.calibration.moves import calibration_change, posterior_change
from services.calibration.posterior import group_rng
from services.calibration.refit import mean_loglik
from services.calibration.regression import fit_observation
from services.calibration.robust import check_model
from services.calibration.state import Quarantine
from services.calibration.store import MemoryStore, SqliteStore
from services.defaults import default_file
from services.runtime.config import read_json5

T0 = 1_700_000_000.0
H = np.array([[0.9, 0.05], [0.05, 0.75]])
B = np.array([-0.25, -0.35])
R = np.array([[0.010, 0.002], [0.002, 0.030]])
MU = np.array([1.0e-3, 5.0e-4])  # ln mm / day
SIGMA = np.array([[1.0e-4, 2.8e-5], [2.8e-5, 4.9e-5]])
REPO = Path(__file__).resolve().parents[2]
# the publication rule off: every accepted change is published at once (tests of the fits)
EVERY_CHANGE = {"material_se": 0.0, "min_publish_interval_days": 0.0}
# These tests are of the fleet model's rules (pairing, swap, publication, posteriors): the
# units' own models are left out here and tested in test_calibration_units.py.
FleetOnly = functools.partial(CalibratorConfig, unit_models=False)


def trc(line, seg, run, t, z):
    top, align = (float(v) for v in np.exp(z))
    return TrcRecord(line=line, segment=seg, t=t, top6_mm=top, align10_mm=align, run_id=run)


def index(line, seg, t, y, run="", train="T1", unit="u1", quality=1.0):
    top, align = (float(v) for v in np.exp(y))
    return make_index(
        t, line=line, segment=seg, train=train, unit=unit, top6_mm=top, align10_mm=align,
        speed_mps=30.0, quality=quality, run_id=run,
    )  # fmt: skip


def campaign(n_pairs, rng, *, line="L1", start=0, H=H, B=B, R=R, t0=T0):
    """``n_pairs`` (TRC record, index of the unit on the TRC) of distinct segments."""
    events = []
    for k in range(start, start + n_pairs):
        z = rng.normal([1.1, 0.9], [0.35, 0.3])
        y = H @ z + B + rng.multivariate_normal([0, 0], R)
        t = t0 + k * 60.0
        events += [
            trc(line, f"c{k}", f"run{k}", t, z),
            index(line, f"c{k}", t + 5, y, run=f"run{k}"),
        ]
    return events


def histories(rng, *, lines=("L1", "L2"), segs=4, records=8, tamp_every=3):
    """TRC histories every ~60 days with a Wiener degradation and a tamping every few records."""
    events = []
    for line in lines:
        for s in range(segs):
            z = rng.normal([1.0, 0.8], 0.1)
            t = T0 + rng.uniform(0, 20) * DAY_S
            for r in range(records):
                if r and r % tamp_every == 0:
                    tm = t - 10 * DAY_S
                    events.append(
                        MaintenanceEvent(
                            line=line, segment=f"s{s}", event_id=f"m{r}", t_start=tm, t_end=tm
                        )
                    )
                    z = rng.normal([0.7, 0.6], 0.1) + MU * 10
                events.append(trc(line, f"s{s}", f"r{r}", t, z))
                dt = rng.uniform(56, 77)
                z = z + MU * dt + rng.multivariate_normal([0, 0], SIGMA * dt)
                t += dt * DAY_S
    return events


# ---------------------------------------------------------------- pairing


def test_pairs_by_run_id_in_either_order_and_ignores_duplicates():
    core = Calibrator(FleetOnly(tolerance_days=None))
    z, y = np.log([3.0, 2.0]), np.log([2.5, 1.5])
    idx = index("L1", "s1", T0 + 9 * DAY_S, y, run="R7")  # 9 days off: only run_id pairs it
    core.step([idx, idx])
    assert core.pairs == [] and core.n_pending() == 1
    rec = trc("L1", "s1", "R7", T0, z)
    core.step([rec, rec, trc("L1", "s2", "R7", T0, z)])
    (pair,) = core.pairs
    assert (pair.run_id, pair.t) == ("R7", idx.t)
    np.testing.assert_allclose(pair.z, z)
    np.testing.assert_allclose(pair.y, y)
    core.step([idx, index("L1", "s1", T0, y, run="R8")])  # duplicate; other run: waits
    assert len(core.pairs) == 1 and core.n_pending() == 1
    assert core.stats["index_duplicates"] == 2 and core.stats["trc_duplicates"] == 1


def test_pairs_by_tolerance_with_the_nearest_record():
    core = Calibrator(FleetOnly(tolerance_days=1.0))
    z1, z2, y = np.log([3.0, 2.0]), np.log([4.0, 2.5]), np.log([2.5, 1.5])
    core.step([trc("L1", "s1", "A", T0, z1), trc("L1", "s1", "B", T0 + 1.5 * DAY_S, z2)])
    core.step(
        [
            index("L1", "s1", T0 + 0.5 * DAY_S, y, train="T1"),  # nearer A
            index("L1", "s1", T0 + 1.0 * DAY_S, y, train="T2"),  # nearer B
            index("L1", "s1", T0 + 3.0 * DAY_S, y, train="T3"),  # too far from both: waits
            index("L1", "s2", T0, y, train="T4"),  # other segment: waits
        ]
    )
    assert [p.run_id for p in core.pairs] == ["A", "B"]
    assert core.n_pending() == 2
    core.step([trc("L1", "s2", "C", T0 + 0.9 * DAY_S, z1)])  # completes the waiting index
    assert [p.run_id for p in core.pairs] == ["A", "B", "C"]


def test_time_pairing_off_low_quality_and_the_waiting_window():
    core = Calibrator(
        FleetOnly(tolerance_days=None, index_window_days=10, max_pending_per_segment=3)
    )
    y = np.log([2.5, 1.5])
    core.step([index("L1", "s1", T0, y), index("L1", "s1", T0, y, train="T9", quality=0.1)])
    assert core.n_pending() == 1 and core.stats["index_low_quality"] == 1
    core.step([trc("L1", "s1", "A", T0, y)])
    assert core.pairs == []  # no run_id and time pairing off
    # events of other segments, however new, do not expire it
    core.step([trc("L1", "s2", "B", T0 + 99 * DAY_S, y)])
    assert core.n_pending() == 1
    # a TRC record of its own segment 11 days later does; older indices are not kept
    core.step([trc("L1", "s1", "C", T0 + 11 * DAY_S, y), index("L1", "s1", T0 - DAY_S, y, run="Q")])
    assert core.n_pending() == 0 and core.stats["index_expired"] == 2
    # at most max_pending_per_segment wait, the newest
    core.step([index("L1", "s3", T0 + k, y, run="Z") for k in (5, 1, 4, 2)])
    assert core.n_pending() == 3 and core.stats["index_expired"] == 3


# ---------------------------------------------------------------- fitting and swap rule


def test_first_fit_at_min_pairs_then_refit_cadence_and_versions():
    rng = np.random.default_rng(1)
    core = Calibrator(FleetOnly(min_pairs=30, refit_every=10, **EVERY_CHANGE))
    assert core.step(campaign(29, rng)) == []
    (cal,) = core.step(campaign(1, rng, start=29))
    assert isinstance(cal, Calibration) and (cal.version, cal.n_pairs) == (1, 30)
    assert cal.t == max(p.t for p in core.pairs)
    assert core.step(campaign(9, rng, start=30)) == []  # 39 pairs: not yet
    (cal2,) = core.step(campaign(1, rng, start=39))
    assert (cal2.version, cal2.n_pairs) == (2, 40)
    out = core.step(campaign(200, rng, start=40))  # one batch: one refit
    assert [(m.version, m.n_pairs) for m in out] == [(3, 240)]
    assert core.stats["fits_accepted"] == 3 and core.stats["fits_rejected"] == 0
    np.testing.assert_allclose(out[0].H.array(), H, atol=0.1)
    np.testing.assert_allclose(out[0].b.array(), B, atol=0.12)
    np.testing.assert_allclose(out[0].R.array(), R, atol=0.01)


def test_worse_refit_is_rejected_with_a_reason_and_a_better_one_accepted():
    rng = np.random.default_rng(2)
    core = Calibrator(FleetOnly(min_pairs=30, refit_every=10, **EVERY_CHANGE))
    (cal,) = core.step(campaign(30, rng))
    # a faulty unit: on-board indices unrelated to the TRC values
    garbage = campaign(15, rng, start=30, H=np.zeros((2, 2)), B=np.zeros(2), R=0.5 * np.eye(2))
    assert core.step(garbage) == []
    assert core.calibration == cal and core.stats["fits_rejected"] == 1
    (reason,) = core.rejections
    assert "rejected against version 1" in reason and ("R²" in reason or "log-likelihood" in reason)
    # the garbage is quarantined: left out of later fits, its indices still duplicates
    assert len(core.pairs) == 30 and len(core.quarantined) == 15
    assert core.step(garbage[1::2]) == [] and core.stats["index_duplicates"] == 15
    # good pairs: the next refit is better, accepted as version 2
    (cal2,) = core.step(campaign(10, rng, start=45))
    assert cal2.version == 2 and cal2.n_pairs == 40
    assert core.stats["fits_rejected"] == 1 and core.stats["pairs_quarantined"] == 15


def test_swap_rule_loglik_threshold():
    """Rule 2 alone: same R² but a shifted bias costs log-likelihood on the old pairs."""
    rng = np.random.default_rng(3)
    core = Calibrator(FleetOnly(min_pairs=30, refit_every=30, max_r2_drop=1.0))
    (cal,) = core.step(campaign(30, rng))
    assert core.step(campaign(30, rng, start=30, B=B + 0.5)) == []
    assert "log-likelihood per pair on the 30 pairs" in core.rejections[-1]
    Z = np.array([p.z for p in core.pairs[:30]])
    Y = np.array([p.y for p in core.pairs[:30]])
    ll = mean_loglik(cal.H.array(), cal.b.array(), cal.R.array(), Z, Y)
    # the current model is the ML fit of its pairs: the closed form -(m/2)(log 2π + 1) - ½log|R|
    expected = -(np.log(2 * np.pi) + 1) - 0.5 * np.linalg.slogdet(cal.R.array())[1]
    assert ll == pytest.approx(expected)


def test_initial_calibration_replaced_by_first_fit():
    spec = read_json5(default_file("initial-models.json5"))
    cal0, posts = initial_models(spec, samples=50, seed=4)
    assert cal0 is not None and cal0.version == 1 and [p.group for p in posts] == ["net"]
    assert posts[0].mu.shape == [50, 2]
    core = Calibrator(FleetOnly(min_pairs=30, samples=50))
    assert core.install_initial(cal0, posts) == [cal0, posts[0]]
    assert core.install_initial(cal0, posts) == []  # only where nothing exists
    rng = np.random.default_rng(5)
    (cal,) = core.step(campaign(30, rng))
    assert cal.version == 2 and cal.n_pairs == 30
    # the same file and seed give the same draws
    again = initial_models(spec, samples=50, seed=4)[1][0]
    assert again == posts[0]


# ---------------------------------------------------------------- degradation posteriors


def test_groups_pooling_and_levels():
    rng = np.random.default_rng(6)
    cfg = FleetOnly(samples=50, segment_min_increments=5, min_levels=4)
    core = Calibrator(cfg)
    events = histories(rng, segs=4, records=8, tamp_every=3)
    events += [
        trc("L3", "x0", "r0", T0, np.log([3, 2])),
        trc("L3", "x0", "r1", T0 + 60 * DAY_S, np.log([3, 2])),
    ]
    out = core.step(events)
    groups = {p.group: p for p in out if isinstance(p, DegradationPosterior)}
    # 8 records, tampings before records 3 and 6: 5 increments per segment, 2 levels
    assert set(groups) == {"net", "line.L1", "line.L2"} | {
        f"seg.{line}.s{s}" for line in ("L1", "L2") for s in range(4)
    }, "line.L3 has 1 increment: refused"
    assert core.stats["posteriors_refused"] == 1
    assert groups["net"].n_increments == 2 * 4 * 5 + 1 and groups["net"].n_levels == 16
    assert groups["line.L1"].n_increments == 20 and groups["line.L1"].n_levels == 8
    seg = groups["seg.L1.s0"]
    assert seg.n_increments == 5 and seg.n_levels == 8  # 2 own levels < 4: the line's
    assert seg.mu.shape == [50, 2] and seg.sigma.shape == [50, 2, 2]
    assert all(p.version == 1 for p in groups.values())
    assert groups["net"].t == max(e.t for e in events if isinstance(e, TrcRecord))
    mean_mu = groups["net"].mu.array().mean(axis=0)
    assert np.all(np.abs(mean_mu - MU) < 1e-3)
    # nothing new: nothing rebuilt; a new record on L1/s0: its groups get version 2
    assert core.step([]) == []
    last = max(
        e.t for e in events if isinstance(e, TrcRecord) and e.segment == "s0" and e.line == "L1"
    )
    new = trc("L1", "s0", "new", last + 60 * DAY_S, np.log([3.5, 2.5]))
    out = core.step([new, *waiting_index(0, t0=new.t)])  # event time follows it elsewhere
    assert sorted((p.group, p.version) for p in out) == [
        ("line.L1", 2),
        ("net", 2),
        ("seg.L1.s0", 2),
    ]


def test_levels_from_prior_when_no_tamping_and_deterministic_samples():
    rng = np.random.default_rng(7)
    events = histories(rng, lines=("L1",), segs=2, records=4, tamp_every=99)
    cfg = FleetOnly(samples=30, seed=11)
    (a,) = [m for m in Calibrator(cfg).step(events) if m.group == "net"]
    (b,) = [m for m in Calibrator(cfg).step(events) if m.group == "net"]
    assert a.n_levels == 0 and a.n_increments == 6
    assert a == b  # identical draws from (seed, group, version)
    (c,) = [m for m in Calibrator(FleetOnly(samples=30, seed=12)).step(events) if m.group == "net"]
    assert c.mu != a.mu
    assert group_rng(1, "net", 1).random() == group_rng(1, "net", 1).random()
    assert group_rng(1, "net", 1).random() != group_rng(1, "net", 2).random()


def test_tamping_interval_mid_rule_and_rebuild_on_maintenance():
    rng = np.random.default_rng(8)
    events = histories(rng, lines=("L1",), segs=3, records=6, tamp_every=99)
    core = Calibrator(FleetOnly(samples=20, min_increments=4, **EVERY_CHANGE))
    first = {m.group: m for m in core.step(events)}
    assert first["net"].n_increments == 15
    s0 = sorted((e for e in events if e.segment == "s0"), key=lambda e: e.t)
    # an interval whose middle falls between records 2 and 3 of s0: that increment is dropped
    ev = MaintenanceEvent(
        line="L1", segment="s0", event_id="m", t_start=s0[2].t + DAY_S, t_end=s0[3].t - DAY_S
    )
    out = {m.group: m for m in core.step([ev, ev])}
    assert out["net"].version == 2 and out["net"].n_increments == 14
    assert core.stats["maintenance_duplicates"] == 1


def test_a_withdrawn_detection_splits_no_increment_in_any_order_and_holds_when_found_again():
    rng = np.random.default_rng(8)
    events = histories(rng, lines=("L1",), segs=3, records=6, tamp_every=99)
    s0 = sorted((e for e in events if e.segment == "s0"), key=lambda e: e.t)
    found = MaintenanceEvent(
        line="L1", segment="s0", event_id="detected-1", t_start=s0[2].t + DAY_S,
        t_end=s0[3].t - DAY_S, detected=True, revision=1,
    )  # fmt: skip
    gone = msgspec.structs.replace(found, revision=2, withdrawn=True)
    again = msgspec.structs.replace(found, revision=3)

    def increments(*deliveries):
        """The network's increments in the newest posterior after ``deliveries``."""
        core = Calibrator(FleetOnly(samples=20, min_increments=4, **EVERY_CHANGE))
        newest = {}
        for batch in (events, *deliveries):
            newest.update({m.group: m for m in core.step(batch) if hasattr(m, "n_increments")})
        return newest["net"].n_increments

    whole = increments()
    assert increments([found]) == whole - 1
    assert increments([found], [gone]) == increments([gone], [found]) == whole
    assert increments([gone, found]) == increments([found, gone]) == whole
    assert increments([found], [gone], [again]) == increments([again], [gone], [found]) == whole - 1


# ---------------------------------------------------------------- persistence


@pytest.mark.parametrize("kind", ["memory", "sqlite"])
def test_restart_from_store_gives_identical_models(kind, tmp_path):
    def open_store():
        return MemoryStore() if kind == "memory" else SqliteStore(tmp_path / "c.sqlite")

    rng = np.random.default_rng(9)
    cfg = FleetOnly(min_pairs=30, refit_every=10, samples=40, seed=3)
    events = campaign(45, rng) + histories(rng) + [index("L1", "s0", T0 + 1e9, np.log([2, 1]))]
    store = open_store()
    core = Calibrator(cfg, store.load())
    for k in range(0, len(events), 7):  # several batches, several transactions
        core.step(events[k : k + 7])
        store.apply(core.drain_changes())
    more = campaign(25, rng, start=45) + [trc("L1", "s0", "late", T0 + 2e9, np.log([4, 3]))]
    if kind == "sqlite":
        store.close()
        store = open_store()
    restored = Calibrator(cfg, store.load())
    assert restored.models() == core.models()
    assert restored.pairs == core.pairs and restored.n_pending() == core.n_pending() == 1
    assert restored.stats == core.stats
    assert restored.step([]) == []  # nothing to redo after a restart
    # and both continue identically
    assert restored.step(more) == core.step(more) != []
    store.close()


# ---------------------------------------------------------------- publication rule


def day_batch(n_pairs, rng, day, *, start, t0=T0, **kw):
    """``campaign`` pairs from event day ``day`` after ``t0`` on (one pair a minute)."""
    return campaign(n_pairs, rng, start=start, t0=t0 + day * DAY_S - start * 60.0, **kw)


def waiting_index(day, t0=T0):
    """Events that only move event time: indices waiting for TRC records that never come, on
    as many segments as event time needs to agree (``event_time_quorum``, 3)."""
    return [
        index("L9", f"w{k}", t0 + day * DAY_S, np.log([2.0, 1.5]), run=f"none{day}")
        for k in range(3)
    ]


_day_batch, _waiting_index = day_batch, waiting_index


def test_refits_within_their_standard_errors_publish_no_version():
    rng = np.random.default_rng(21)
    core = Calibrator(FleetOnly(min_pairs=30, refit_every=10))
    (cal,) = core.step(day_batch(1000, rng, 0, start=0))  # first fit: nothing in force
    assert (cal.version, cal.n_pairs) == (1, 1000)
    for k in range(5):  # a refit a day, each on 10 more pairs of the same model
        assert core.step(day_batch(10, rng, 2 + k, start=1000 + 10 * k)) == []
    assert core.stats["fits_accepted"] == 6 and core.stats["changes_immaterial"] == 5
    assert core.calibration == cal  # still in force
    held = core.held["calibration"]
    assert (held.version, held.n_pairs) == (2, 1050)  # accumulated, not published
    # the held fit is the swap rule's reference: a faulty burst is judged against it and only
    # the burst is quarantined, not the good pairs since the version in force
    garbage = day_batch(10, rng, 8, start=2000, H=np.zeros((2, 2)), B=np.zeros(2), R=np.eye(2))
    assert core.step(garbage) == []
    assert "rejected against version 2 (held)" in core.rejections[-1]
    assert len(core.pairs) == 1050 and len(core.quarantined) == 10


def test_a_shift_beyond_the_standard_error_publishes_a_version():
    rng = np.random.default_rng(22)
    core = Calibrator(FleetOnly(min_pairs=30, refit_every=10))
    (cal,) = core.step(day_batch(1000, rng, 0, start=0))
    (cal2,) = core.step(day_batch(300, rng, 2, start=1000, B=B + [0.15, 0.0]))  # a biased unit
    assert (cal2.version, cal2.n_pairs) == (2, 1300) and core.held == {}
    assert cal2.b.array()[0] - cal.b.array()[0] > 0.02
    Z = np.array([p.z for p in core.pairs])
    Y = np.array([p.y for p in core.pairs])
    fit = fit_observation(Z, Y)
    assert calibration_change(fit, cal)[0] > 1.0  # the largest move (here R[0,0], inflated)
    assert abs(fit.b[0] - cal.b.array()[0]) > fit.se_b[0]  # and the bias itself


def test_two_material_changes_within_a_day_publish_once_then_when_event_time_passes():
    rng = np.random.default_rng(23)
    core = Calibrator(FleetOnly(min_pairs=30, refit_every=10, tolerance_days=None))
    (v1,) = core.step(day_batch(1000, rng, 0, start=0))
    (v2,) = core.step(day_batch(300, rng, 2, start=1000, B=B + [0.15, 0.0]))
    published = core.published_at["calibration"]
    # event time: the newest time three segments have reached (each pair has its own segment)
    assert published == core.now == sorted(p.t for p in core.pairs)[-3]
    # a second material change 0.3 day later: accepted, held by the rate limit
    assert core.step(day_batch(300, rng, 2.3, start=1300, B=B + [0.0, 0.15])) == []
    held = core.held["calibration"]
    assert held.version == 3 and held.n_pairs == 1600
    assert core.stats["publications_delayed"] == 1 and core.calibration == v2
    # event time moves on without any refit: still within the day, then past it
    assert core.step(waiting_index(3.1)) == []  # v2 came out at day 2.21 (its last pairs)
    (v3,) = core.step(waiting_index(3.3))
    assert v3 == held and core.held == {} and core.published_at["calibration"] == core.now
    assert core.stats["fits_accepted"] == 3 and core.stats["calibrations_published"] == 3
    assert [v1.version, v2.version, v3.version] == [1, 2, 3]


@pytest.mark.parametrize("kind", ["memory", "sqlite"])
def test_restart_keeps_the_version_in_force_and_its_publication_time(kind, tmp_path):
    def open_store():
        return MemoryStore() if kind == "memory" else SqliteStore(tmp_path / "c.sqlite")

    rng = np.random.default_rng(24)
    cfg = FleetOnly(min_pairs=30, refit_every=10, tolerance_days=None, samples=30)
    day_batch = functools.partial(_day_batch, t0=T0 + 1000 * DAY_S)  # after the histories
    waiting_index = functools.partial(_waiting_index, t0=T0 + 1000 * DAY_S)
    store = open_store()
    core = Calibrator(cfg, store.load())
    for events in (
        histories(rng) + day_batch(1000, rng, 0, start=0),
        day_batch(300, rng, 2, start=1000, B=B + [0.15, 0.0]),
        day_batch(300, rng, 2.3, start=1300, B=B + [0.0, 0.15]),  # held by the rate limit
    ):
        core.step(events)
        store.apply(core.drain_changes())
    assert set(core.held) == {"calibration"}
    if kind == "sqlite":
        store.close()
        store = open_store()
    restored = Calibrator(cfg, store.load())
    assert restored.models() == core.models() and restored.held == core.held
    assert restored.published_at == core.published_at and restored.now == core.now
    assert restored.step([]) == []
    # the held version comes out on both when event time passes the day, not before
    for day, n in ((3.1, 0), (3.3, 1)):
        out = core.step(waiting_index(day))
        assert restored.step(waiting_index(day)) == out and len(out) == n
        store.apply(restored.drain_changes())
    assert out[0].version == 3
    reopened = Calibrator(cfg, store.load())
    assert reopened.held == {} and reopened.published_at == core.published_at
    store.close()


def test_posterior_moves_within_its_sd_publish_no_version_a_shift_does():
    rng = np.random.default_rng(25)
    core = Calibrator(FleetOnly(samples=200, segment_min_increments=99))
    events = histories(rng, segs=6, records=8, tamp_every=99)
    first = {m.group: m for m in core.step(events)}
    assert set(first) == {"net", "line.L1", "line.L2"}
    last = {
        (e.line, e.segment): e
        for e in sorted(events, key=lambda e: e.t)
        if isinstance(e, TrcRecord)
    }
    t_new = max(e.t for e in last.values()) + 60 * DAY_S

    def next_record(line, seg, run, drift):
        rec = last[(line, seg)]
        dt = (t_new - rec.t) / DAY_S
        z = np.log([rec.top6_mm, rec.align10_mm]) + drift * dt
        return trc(line, seg, run, t_new, z)

    # one more increment of one segment at the usual drift: every group moves < 1 sd
    assert core.step([next_record("L1", "s0", "n1", MU)]) == []
    assert set(core.held) == {"net", "line.L1"} and core.stats["changes_immaterial"] == 2
    for g in ("net", "line.L1"):
        assert posterior_change(core.held[g], core.posteriors[g])[0] < 1.0
    # a day later, L2 degrading eight times faster: its line and the network move
    t_new += DAY_S
    out = core.step([next_record("L2", f"s{s}", "n2", 8 * MU) for s in range(6)])
    assert sorted((p.group, p.version) for p in out) == [("line.L2", 2), ("net", 2)]
    assert posterior_change(out[0], first["line.L2"])[0] > 1.0
    assert set(core.held) == {"line.L1"}  # still immaterial, still accumulated


def test_a_store_from_before_publication_times_opens(tmp_path):
    """A file whose models table has no published_at: the column is added, and its models
    count as published at an unknown time (the next version is not rate-limited)."""
    rng = np.random.default_rng(26)
    (old,) = Calibrator(FleetOnly(min_pairs=30)).step(campaign(30, rng))
    path = tmp_path / "old.sqlite"
    with sqlite3.connect(path) as db:
        db.execute(
            "CREATE TABLE models (key TEXT PRIMARY KEY, payload BLOB NOT NULL, "
            "fingerprint TEXT NOT NULL, prior INTEGER NOT NULL)"
        )
        db.execute("INSERT INTO models VALUES ('calibration', ?, '', 0)", (encode(old),))
    db.close()
    store = SqliteStore(path)
    core = Calibrator(FleetOnly(min_pairs=30, refit_every=10), store.load())
    assert core.models() == [old] and core.published_at == {"calibration": None}
    # a material change minutes later is published at once, then rate-limited
    (cal,) = core.step(campaign(300, rng, start=30, B=B + [0.3, 0.0]))
    assert cal.version == 2 and core.published_at == {"calibration": core.now}
    store.apply(core.drain_changes())
    store.close()
    store = SqliteStore(path)
    assert Calibrator(FleetOnly(), store.load()).published_at == core.published_at
    store.close()


# ---------------------------------------------------------------- robustness


def seven_records(line, seg, t0, mm, *, outlier_at=3, outlier_mm=99.0, rng=None):
    """Seven TRC records 70 days apart near ``mm``, one of them ``outlier_mm``."""
    rng = rng or np.random.default_rng(0)
    z = np.log(mm)
    out = []
    for k in range(7):
        v = np.exp(z) if k != outlier_at else np.array([outlier_mm, outlier_mm])
        out.append(trc(line, seg, f"x{k}", t0 + 70 * k * DAY_S, np.log(v)))
        z = z + MU * 70 + rng.multivariate_normal([0, 0], SIGMA * 70)
    return out


def moved_sd(new: DegradationPosterior, old: DegradationPosterior) -> float:
    """The largest move of the mean of mu or Sigma, in the old posterior's sd."""
    return max(
        float(np.max(np.abs(a_new.mean(0) - a_old.mean(0)) / a_old.std(0)))
        for a_new, a_old in (
            (new.mu.array(), old.mu.array()),
            (new.sigma.array(), old.sigma.array()),
        )
    )


@pytest.mark.parametrize("outlier_at", [3, 6])  # a spike; the newest record
def test_a_99_mm_record_does_not_move_the_network_posterior(outlier_at):
    rng = np.random.default_rng(31)
    cfg = FleetOnly(samples=200, segment_min_increments=99)
    core = Calibrator(cfg)
    events = histories(rng, segs=6, records=8, tamp_every=99)
    before = {m.group: m for m in core.step(events)}["net"]
    t0 = max(e.t for e in events) - 6 * 70 * DAY_S
    seven = seven_records("X", "unknown", t0, [3.0, 2.0], outlier_at=outlier_at)
    core.step(seven)
    net = core.held.get("net") or core.posteriors["net"]
    assert moved_sd(net, before) < cfg.max_move_sd
    assert net.sigma.array().mean(0)[0, 0] < 1e-3  # not 1.8e3 (ln mm)^2/day
    (q,) = core.drain_quarantined()
    assert (q.kind, q.line, q.segment, q.message) == ("trc", "X", "unknown", seven[outlier_at])
    assert "left out of the degradation posteriors" in q.reason and "ln mm" in q.reason
    assert core.stats["trc_quarantined"] == 1
    assert core.drain_quarantined() == []  # reported once
    # a later record does not report it again (but a newest outlier is taken back once a
    # record confirms the step: two agreeing records are a change, not an outlier)
    core.step([trc("X", "unknown", "x7", seven[-1].t + 70 * DAY_S, np.log([3.2, 2.1]))])
    assert core.drain_quarantined() == []


def test_the_incident_seven_records_on_one_segment_from_the_initial_models():
    """One outlier against the initial models: only the initial models and seven records of
    one segment, one of them 99 mm (the largest value the wire accepts is 100 mm)."""
    spec = read_json5(default_file("initial-models.json5"))
    cal0, posts = initial_models(spec, samples=200, seed=0)
    core = Calibrator(FleetOnly(samples=200))
    core.install_initial(cal0, posts)
    out = core.step(seven_records("X", "unknown", T0, [3.0, 2.0]))
    (q,) = core.drain_quarantined()
    assert q.message is not None and q.message.top6_mm == pytest.approx(99.0)
    assert "a spike" in q.reason
    for m in out:
        assert np.all(np.isfinite(m.sigma.array())) and m.sigma.array().mean(0)[0, 0] < 1e-3


def test_a_pooled_posterior_moved_by_one_segment_alone_is_held():
    rng = np.random.default_rng(32)
    cfg = FleetOnly(samples=200, segment_min_increments=99)
    core = Calibrator(cfg)
    events = histories(rng, lines=("L1",), segs=6, records=8, tamp_every=99)
    before = {m.group: m for m in core.step(events)}
    # one segment whose records all degrade 40x faster, steadily (no single record is odd)
    t0 = max(e.t for e in events) + DAY_S
    fast = [
        trc("L1", "s9", f"f{k}", t0 + 20 * k * DAY_S, np.log([2.0, 1.5]) + 0.3 * k)
        for k in range(8)
    ]
    assert core.step(fast) == []
    assert core.stats["posteriors_held_move"] >= 1
    assert "on the strength of segment L1/s9 alone" in core.rejections[-1]
    assert core.posteriors["net"] == before["net"] and "net" not in core.held
    (q, *_) = core.drain_quarantined()
    assert (q.line, q.segment) == ("L1", "s9") and "not published" in q.reason


def test_a_record_dated_2099_does_not_stall_publication():
    rng = np.random.default_rng(33)
    core = Calibrator(FleetOnly(min_pairs=30, refit_every=10, tolerance_days=None))
    (v1,) = core.step(day_batch(1000, rng, 0, start=0))
    now = core.now
    late = trc("L1", "c5", "late", 4_090_000_000.0, np.log([3.0, 2.0]))  # 2099-08
    late_index = index("L1", "c5", late.t + 5, np.log([2.5, 1.5]), run="late")
    assert core.step([late, late_index]) == []
    assert now <= core.now < now + DAY_S  # one segment cannot move event time
    # two days later a material change is published at once, the day after another one
    (v2,) = core.step(day_batch(300, rng, 2, start=1000, B=B + [0.15, 0.0]))
    assert v2.version == 2 and core.published_at["calibration"] < late.t
    assert core.step(day_batch(300, rng, 2.3, start=1300, B=B + [0.0, 0.15])) == []
    (v3,) = core.step(waiting_index(3.3))
    assert v3.version == 3
    # event time never came near 2099: the late record is left out of the posteriors
    assert core.now < T0 + 10 * DAY_S
    assert all(p.t < late.t for p in core.posteriors.values())
    reasons = [q.reason for q in core.drain_quarantined() if q.kind == "trc"]
    assert any("late" in r and "after event time" in r for r in reasons)


def test_a_wild_pair_the_swap_rule_lets_through_is_quarantined():
    rng = np.random.default_rng(34)
    core = Calibrator(FleetOnly(min_pairs=30, refit_every=10, **EVERY_CHANGE))
    core.step(campaign(200, rng))
    batch = campaign(10, rng, start=200)
    wild = batch[-1]
    batch[-1] = index(
        wild.line,
        wild.segment,
        wild.t,
        np.log([wild.top6_mm, wild.align10_mm]) + 2.0,
        run=wild.run_id,
    )
    (cal,) = core.step(batch)
    assert cal.n_pairs == 209 and core.stats["pairs_outliers"] == 1
    assert core.stats["fits_rejected"] == 0
    (q,) = core.drain_quarantined()
    assert (q.kind, q.segment, q.message) == ("index", wild.segment, None)
    assert "robust sd" in q.reason and "left out of the observation model" in q.reason
    assert [p.index_id for p in core.quarantined] == [f"L1/{wild.segment}/T1/u1/{wild.t!r}"]


def test_check_model_refuses_non_positive_definite_covariances():
    rng = np.random.default_rng(35)
    (cal,) = Calibrator(FleetOnly(min_pairs=30)).step(campaign(30, rng))
    assert check_model(cal) is None
    bad_r = msgspec.structs.replace(cal, R=NDArray.of(np.array([[1.0, 2.0], [2.0, 1.0]])))
    assert check_model(bad_r) == "R is not positive definite"
    (post,) = [
        m
        for m in Calibrator(FleetOnly(samples=20)).step(histories(rng, lines=("L1",)))
        if m.group == "net"
    ]
    assert check_model(post) is None
    sigma = post.sigma.array().copy()
    sigma[3] = [[1e-4, 2e-4], [2e-4, 1e-4]]  # symmetric, one eigenvalue < 0
    assert check_model(msgspec.structs.replace(post, sigma=NDArray.of(sigma))) == (
        "sigma is not positive definite"
    )
    # NaN and inf cannot even be built (NDArray refuses them): the core counts such a model
    # as invalid when it builds it (models_invalid) and never publishes it


@pytest.mark.parametrize("seed", range(12))
def test_no_nan_inf_or_indefinite_model_is_ever_published(seed):
    """Property: whatever outliers within the schema's bounds arrive (values in (0, 100] mm,
    times in [2000, 2100)), every model published is finite with SPD covariances."""
    rng = np.random.default_rng(100 + seed)
    core = Calibrator(FleetOnly(min_pairs=30, refit_every=10, samples=30))
    events = histories(rng, segs=3, records=6) + campaign(40, rng)
    for _ in range(25):
        line, seg = rng.choice(["L1", "L2", "X"]), f"s{rng.integers(0, 5)}"
        t = float(
            rng.choice([rng.uniform(946_684_800, 4_102_444_700), T0 + rng.uniform(0, 800) * DAY_S])
        )
        mm = np.exp(rng.uniform(np.log(1e-3), np.log(100.0), size=2))
        run = f"o{rng.integers(0, 10**9)}"
        events.append(trc(line, seg, run, t, np.log(mm)))
        if rng.random() < 0.5:
            y = np.log(np.exp(rng.uniform(np.log(1e-3), np.log(100.0), size=2)))
            events.append(index(line, seg, t + 1, y, run=run))
        if rng.random() < 0.2:
            events.append(
                MaintenanceEvent(
                    line=line, segment=seg, event_id=run, t_start=t - DAY_S, t_end=t - DAY_S
                )
            )
    rng.shuffle(events)
    published = []
    for k in range(0, len(events), 17):
        published += core.step(events[k : k + 17])
    published += core.step(waiting_index(0, t0=T0 + 900 * DAY_S))
    assert published
    for m in published:
        assert check_model(m) is None
        decode(encode(m), type(m))  # and within the wire limits


def test_service_network_setting_and_dead_letter_keys():
    from services.calibration import service

    network = default_file("demo-network.geojson")
    settings = service.settings_from({"network": str(network)})
    assert settings.network == network
    known = service.known_segments(settings.network)
    assert known is not None and len(known) == 295 and service.known_segments(None) is None
    q = Quarantine("trc", "L1", "s00042", "why")
    assert service.quarantine_key("tf", q) == "tf/trc/L1/s00042"
    assert service.quarantine_key("tf", Quarantine("index", "L1", "s1", "")) == "tf/index/L1/s1"


@pytest.mark.parametrize("make_store", [lambda _p: MemoryStore(), SqliteStore])
def test_replay_positions_are_stored_with_the_changes_and_loaded_back(tmp_path, make_store):
    from services.calibration.state import Changes

    store = make_store(tmp_path / "cal.sqlite")
    assert Changes(positions={"extraction/a": ("e1", 4)})  # positions alone are a change
    store.apply(Changes(positions={"extraction/a": ("e1", 4), "filtering/a": ("e2", 1)}))
    store.apply(Changes(positions={"extraction/a": ("e1", 9)}))
    assert store.load().positions == {"extraction/a": ("e1", 9), "filtering/a": ("e2", 1)}
    if isinstance(store, SqliteStore):
        store.close()
        assert SqliteStore(tmp_path / "cal.sqlite").load().positions["extraction/a"] == ("e1", 9)
