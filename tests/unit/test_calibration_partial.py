"""Calibration from TRC records of some indicators only (a level-only car): the posteriors'
exact update on what was measured, and pairs refused with their reason."""

from __future__ import annotations

import numpy as np

from schemas import DAY_S, INDICATORS, TrcRecord
from services.alerting.testing import make_index
from services.calibration.calibrator import Calibrator
from services.calibration.config import CalibratorConfig
from services.calibration.groups import GroupInput, build_posterior
from services.calibration.posterior import (
    group_rng,
    history_to_increments,
    partial_drift_posterior,
    sample_degradation_posterior,
    segment_increments,
)
from services.calibration.store import SqliteStore
from services.drift_diffusion import NIWPrior, posterior_drift_diffusion

T0 = 1_700_000_000.0
MU = np.array([1.0e-3, 5.0e-4])  # ln mm / day
SIGMA = np.array([[1.0e-4, 2.8e-5], [2.8e-5, 4.9e-5]])


def record(seg, run, t, z, indicators=("top6", "align10")):
    mm = dict(zip(("top6", "align10"), np.exp(z).tolist(), strict=True))
    return TrcRecord(
        line="L1",
        segment=seg,
        t=t,
        run_id=run,
        indicators=list(indicators),
        **{f"{k}_mm": v for k, v in mm.items() if k in indicators},
    )


def wiener(rng, dt):
    """Increments of the degradation over durations ``dt`` (days)."""
    return MU * dt[:, None] + np.array(
        [rng.multivariate_normal([0, 0], SIGMA * d) for d in dt]
    ).reshape(-1, 2)


def test_an_index_of_a_partial_record_is_not_paired_and_says_why():
    core = Calibrator(CalibratorConfig(tolerance_days=1.0, unit_models=False))
    level_only = record("s1", "r1", T0, np.log([2.0, 1.0]), ["top6"])
    assert core.ingest(level_only) is True
    assert core.stats["trc_partial"] == 1 and core.stats["trc"] == 1
    core.ingest(make_index(T0, line="L1", segment="s1", run_id="r1"))
    assert core.pairs == [] and core.stats["index_record_partial"] == 1
    (dead,) = core.drain_quarantined()
    assert dead.kind == "index" and "measured ['top6'] only" in dead.reason
    # by time, an index pairs with the nearest record of every indicator, not a partial one
    core.ingest(record("s1", "r2", T0 + 0.8 * DAY_S, np.log([2.0, 1.5])))
    core.ingest(record("s1", "r3", T0 + 0.2 * DAY_S, np.log([2.1, 1.0]), ["top6"]))
    core.ingest(make_index(T0 + 0.3 * DAY_S, line="L1", segment="s1"))
    (pair,) = core.pairs
    assert pair.run_id == "r2"


def test_segment_increments_of_complete_records_are_history_to_increments():
    rng = np.random.default_rng(3)
    t = np.cumsum(rng.uniform(30, 60, 9))
    z = np.cumsum(wiener(rng, np.r_[1.0, np.diff(t)]), axis=0)
    plain, same = history_to_increments(t, z, [t[4] - 3]), segment_increments(t, z, [t[4] - 3])
    for a, b in zip(same, plain, strict=True):
        assert np.array_equal(a, b)


def test_segment_increments_chain_each_indicator_over_the_records_that_measured_it():
    t = np.array([0.0, 10.0, 20.0, 30.0, 40.0, 50.0])
    z = np.array([[1, 2], [1.1, np.nan], [1.2, 2.2], [np.nan, 2.3], [1.4, 2.4], [1.5, 2.5]])
    inc = segment_increments(t, z, [45.0])  # a tamping between 40 and 50
    np.testing.assert_allclose(inc.dz, [[0.2, 0.2], [0.2, 0.2]])  # 0 -> 20 -> 40
    np.testing.assert_allclose(inc.dt, [20.0, 20.0])
    np.testing.assert_allclose(inc.level, [[1.5, 2.5]])
    (dz0, dt0), (dz1, dt1) = inc.chains
    np.testing.assert_allclose(dz0, [0.1, 0.1, 0.2])  # 0 -> 10 -> 20 -> 40
    np.testing.assert_allclose(dt0, [10.0, 10.0, 20.0])
    np.testing.assert_allclose(dz1, [0.2, 0.1, 0.1])  # 0 -> 20 -> 30 -> 40
    np.testing.assert_allclose(dt1, [20.0, 10.0, 10.0])
    assert inc.partial_with == (1, 1) and inc.partial_without == (1, 1)


def test_the_marginal_of_the_measured_indicator_is_its_one_dimensional_niw_update():
    rng = np.random.default_rng(5)
    dt = rng.uniform(20, 60, 15)
    dz = wiener(rng, dt)
    dt_j = rng.uniform(20, 60, 40)
    dz_j = wiener(rng, dt_j)[:, 0]
    prior = NIWPrior.default_drift(2)
    post = partial_drift_posterior(dz, dt, 0, dz_j, dt_j, prior, min_increments=4)
    # textbook Normal-Inverse-Gamma update of (mu_0, Sigma_00) written out here
    lam = prior.lambda0 + dt_j.sum()
    m = (prior.lambda0 * prior.m0[0] + dz_j.sum()) / lam
    psi = prior.Psi0[0, 0] + (dz_j**2 / dt_j).sum() + prior.lambda0 * prior.m0[0] ** 2 - lam * m**2
    marginal = post.marginal
    np.testing.assert_allclose([marginal.lam, marginal.m[0], marginal.nu], [lam, m, 3 + 40])
    np.testing.assert_allclose(marginal.Psi[0, 0], psi, rtol=1e-10)
    full = posterior_drift_diffusion(dz, dt, prior)
    np.testing.assert_allclose(post.complete.Psi, full.Psi)


def test_with_the_complete_increments_only_the_draws_follow_the_niw_posterior():
    """The factorised sampler against the joint NIW sampler: same distribution."""
    rng = np.random.default_rng(11)
    dt = rng.uniform(20, 60, 12)
    dz = wiener(rng, dt)
    full = posterior_drift_diffusion(dz, dt)
    ns = 200_000
    joint = full.sample(ns, 1)
    for j in (0, 1):
        factored = partial_drift_posterior(dz, dt, j, dz[:, j], dt, min_increments=4).sample(ns, 2)
        for a, b in zip(joint, factored, strict=True):
            a, b = a.reshape(ns, -1), b.reshape(ns, -1)
            for q in (0.1, 0.5, 0.9):  # quantiles agree within their sampling error
                qa, qb = np.quantile(a, q, axis=0), np.quantile(b, q, axis=0)
                spread = np.quantile(a, 0.75, axis=0) - np.quantile(a, 0.25, axis=0)
                assert np.all(np.abs(qa - qb) < 0.02 * spread), (j, q)
            corr_a = np.corrcoef(a.T)
            corr_b = np.corrcoef(b.T)
            np.testing.assert_allclose(corr_a, corr_b, atol=0.02)


def test_a_group_of_complete_records_draws_as_the_joint_update_bit_for_bit():
    rng = np.random.default_rng(7)
    dt = rng.uniform(20, 60, 30)
    dz = wiener(rng, dt)
    level = rng.normal([0.7, 0.6], 0.1, (8, 2))
    age = rng.uniform(0, 20, 8)
    cfg = CalibratorConfig(samples=50)
    g = GroupInput(dz, dt, level, age, "net", T0, (("L1", "s1"),))
    post = build_posterior("net", g, 3, cfg)
    s = sample_degradation_posterior(
        dz, dt, level, age, ns=50, rng=group_rng(cfg.seed, "net", 3),
        min_increments=cfg.min_increments, min_levels=cfg.min_levels,
    )  # fmt: skip
    for got, want in [(post.mu, s.mu), (post.sigma, s.sigma), (post.z_plus, s.z_plus)]:
        assert np.array_equal(got.array(), want)
    assert np.array_equal(post.sigma_z_plus.array(), s.sigma_z_plus)


def test_level_only_runs_give_the_level_drift_and_diffusion():
    """Every record after the first of each segment is level-only: the network posterior of
    top6's drift and diffusion converges to the truth; alignment's stays near its prior."""
    rng = np.random.default_rng(21)
    core = Calibrator(CalibratorConfig(samples=2000, unit_models=False, segment_min_increments=999))
    events = []
    for s in range(63):  # three alignment-only segments: left out, counted
        z = rng.normal([1.0, 0.8], 0.1)
        t = T0 + rng.uniform(0, 20) * DAY_S
        some = ["top6"] if s < 60 else ["align10"]
        for r in range(10):
            events.append(record(f"s{s}", f"r{r}", t, z, ["top6", "align10"] if r == 0 else some))
            dt = rng.uniform(56, 77)
            z = z + MU * dt + rng.multivariate_normal([0, 0], SIGMA * dt)
            t += dt * DAY_S
    out = {m.group: m for m in core.step(events)}
    net = out["net"]
    assert net.n_increments == 60 * 9 and core.stats["trc_partial"] == 63 * 9
    assert core.stats["trc_partial_left_out"] == 3 * 9
    mu, sigma = net.mu.array(), net.sigma.array()
    for value, truth in [(mu[:, 0], MU[0]), (sigma[:, 0, 0], SIGMA[0, 0])]:
        assert abs(value.mean() - truth) < 3 * value.std(), (value.mean(), truth)
        assert value.std() < 0.15 * truth  # informed by the data, not the prior
    assert sigma[:, 1, 1].std() > 10 * sigma[:, 0, 0].std()  # alignment: the prior's


def test_partial_records_come_back_from_the_store_with_the_same_posteriors(tmp_path):
    rng = np.random.default_rng(4)
    cfg = CalibratorConfig(samples=40, unit_models=False)
    events = []
    for s in range(8):
        z, t = rng.normal([1.0, 0.8], 0.1), T0 + s * DAY_S
        for r in range(6):
            events.append(record(f"s{s}", f"r{r}", t, z, ["top6"] if r % 2 else INDICATORS))
            dt = rng.uniform(56, 77)
            z, t = z + MU * dt + rng.multivariate_normal([0, 0], SIGMA * dt), t + dt * DAY_S
    store = SqliteStore(tmp_path / "c.sqlite")
    core = Calibrator(cfg, store.load())
    assert core.step(events) != []
    store.apply(core.drain_changes())
    store.close()
    store = SqliteStore(tmp_path / "c.sqlite")
    restored = Calibrator(cfg, store.load())
    assert restored.models() == core.models() and restored.step([]) == []
    store.close()
