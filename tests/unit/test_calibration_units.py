"""Per-unit observation models: each on-board unit's H, b, R, shrunk towards the
fleet's model while it has few pairs."""

from __future__ import annotations

import msgspec
import numpy as np

from schemas import DAY_S, Calibration, keys
from services.calibration.calibrator import Calibrator
from services.calibration.config import CalibratorConfig
from services.calibration.regression import (
    _fit_unit_rows,
    fit_observation,
    fit_unit_observation,
)
from services.calibration.state import unit_key
from services.calibration.store import SqliteStore
from tests.unit.test_calibration_service_core import T0, B, H, R, campaign, index, trc

ONE_AT_A_TIME = {"material_se": 0.0, "min_publish_interval_days": 0.0}


def unit_pairs(rng, n, b_shift, *, train, unit="u1", start=0, line="L1"):
    """A TRC record and, 2 h later, an index of ``train``'s unit reading ``b + b_shift``."""
    events = []
    for k in range(start, start + n):
        z = rng.normal([1.1, 0.9], [0.35, 0.3])
        y = H @ z + B + np.asarray(b_shift) + rng.multivariate_normal([0, 0], R)
        t = T0 + DAY_S + k * 600.0
        events += [
            trc(line, f"u{k}", f"run-u{k}", t, z),
            index(line, f"u{k}", t + 7200.0, y, train=train, unit=unit),
        ]
    return events


def design_of(Z):
    X = np.hstack([Z, np.ones((len(Z), 1))])
    return X.T @ X / len(X)


def test_a_unit_fit_moves_from_the_fleets_model_to_its_own_least_squares_with_pairs():
    rng = np.random.default_rng(0)
    shift = np.array([0.15, -0.1])
    Z = rng.normal([1.1, 0.9], [0.35, 0.3], (2000, 2))
    Y = Z @ H.T + B + shift + rng.multivariate_normal([0, 0], R, len(Z))
    D = design_of(Z)
    fits = {
        n: fit_unit_observation(Z[:n], Y[:n], H0=H, b0=B, R0=R, design=D, shrink_pairs=20)
        for n in (1, 3, 20, 2000)
    }
    # one pair: near the fleet; 20 pairs: about halfway; 2,000: the unit's own fit
    assert np.abs(fits[1].b - B).max() < 0.05
    assert 0.3 < np.mean((fits[20].b - B) / shift) < 0.8
    ols = fit_observation(Z, Y)
    np.testing.assert_allclose(fits[2000].b, ols.b, atol=0.01)
    np.testing.assert_allclose(fits[2000].H, ols.H, atol=0.01)
    np.testing.assert_allclose(fits[2000].R, R, rtol=0.1, atol=0.002)
    assert (fits[2000].se_b < fits[20].se_b).all()
    # pairs from one point of z (one segment, one run): still a finite, fleet-like slope
    same = fit_unit_observation(
        np.repeat(Z[:1], 8, 0), Y[:8], H0=H, b0=B, R0=R, design=D, shrink_pairs=20
    )
    assert np.isfinite(same.H).all() and np.abs(same.H - H).max() < 0.2


def test_each_unit_gets_its_own_model_and_the_fleets_stays():
    rng = np.random.default_rng(1)
    core = Calibrator(CalibratorConfig(min_pairs=30, refit_every=10, **ONE_AT_A_TIME))
    events = campaign(40, rng)  # the TRC's own unit: the fleet's model
    events += unit_pairs(rng, 60, [0.2, -0.15], train="TA")
    events += unit_pairs(rng, 60, [-0.1, 0.1], train="TB", start=100)
    out = core.step(events)
    units = core.unit_calibrations
    assert {("TA", "u1"), ("TB", "u1")} <= set(units)
    fleet = core.calibration
    assert fleet is not None and not fleet.train
    for train in ("TA", "TB"):
        cal = units[(train, "u1")]
        assert cal.n_pairs == 60 and keys.key_of("tf", cal) == f"tf/model/calibration/{train}/u1"
        # the unit's own indices: no bias left under its model, a bias under the fleet's
        pairs = [p for p in core.pairs + core.quarantined if p.unit == (train, "u1")]
        Z, Y = np.array([p.z for p in pairs]), np.array([p.y for p in pairs])

        def bias(model: Calibration, Z=Z, Y=Y) -> np.ndarray:
            return (Y - Z @ model.H.array().T - model.b.array()).mean(axis=0)

        assert np.abs(bias(cal)).max() < 0.04
        assert np.abs(bias(fleet)).max() > 0.1
    assert any(isinstance(m, Calibration) and m.train == "TA" for m in out)
    # the models in force list the fleet's first, then the units'
    models = core.models()
    assert models[0] == fleet and {m.train for m in models[1:4]} == {"T1", "TA", "TB"}


def test_unit_models_survive_a_restart(tmp_path):
    rng = np.random.default_rng(2)
    store = SqliteStore(tmp_path / "cal.sqlite")
    core = Calibrator(CalibratorConfig(min_pairs=30, **ONE_AT_A_TIME), store.load())
    core.step(campaign(40, rng) + unit_pairs(rng, 30, [0.2, 0.0], train="TA"))
    store.apply(core.drain_changes())
    again = Calibrator(CalibratorConfig(min_pairs=30, **ONE_AT_A_TIME), SqliteStore(
        tmp_path / "cal.sqlite"
    ).load())  # fmt: skip
    assert again.unit_calibrations == core.unit_calibrations
    assert unit_key("TA", "u1") in again.published_at
    # and it goes on as if never stopped: the same next events publish the same models
    more = unit_pairs(rng, 3, [0.2, 0.0], train="TA", start=300)
    assert again.step(more) == core.step(more)


def test_a_tamping_correction_replaces_the_report_in_calibration_whatever_the_order(tmp_path):
    from schemas import MaintenanceEvent

    report = MaintenanceEvent(
        line="L1", segment="s0", event_id="m1", t_start=T0, t_end=T0 + 10 * 86_400.0
    )
    fixed = MaintenanceEvent(
        line="L1", segment="s0", event_id="m1", t_start=T0 + 2 * 86_400.0,
        t_end=T0 + 2 * 86_400.0,
    )  # fmt: skip
    assert fixed.rank > report.rank
    for order in ([report, fixed], [fixed, report]):
        store = SqliteStore(tmp_path / f"cal-{order[0] is report}.sqlite")
        core = Calibrator(CalibratorConfig(), store.load())
        core.step(order)
        store.apply(core.drain_changes())
        assert core._maint[("L1", "s0")] == {"L1/s0/m1": fixed}
        again = Calibrator(CalibratorConfig(), SqliteStore(store.path).load())
        assert again._maint[("L1", "s0")] == {"L1/s0/m1": fixed}


def test_a_unit_measuring_one_index_fits_its_row_and_keeps_the_fleets_other():
    """Pairs with Align10 missing (NaN): Top6's row of H, b from them, against a per-row
    derivation straight from the formula; Align10's row, and R's elements of it, the
    fleet's."""
    rng = np.random.default_rng(3)
    Z = rng.normal([1.1, 0.9], [0.35, 0.3], (200, 2))
    Y = Z @ H.T + B + [0.2, 0.0] + rng.multivariate_normal([0, 0], R, len(Z))
    D, k = design_of(Z), 20.0
    vertical = Y.copy()
    vertical[:, 1] = np.nan
    fit = fit_unit_observation(Z, vertical, H0=H, b0=B, R0=R, design=D, shrink_pairs=k)
    X = np.hstack([Z, np.ones((len(Z), 1))])
    theta0 = np.hstack([H, B[:, None]])
    want = np.linalg.solve(X.T @ X + k * D, X.T @ Y[:, 0] + k * D @ theta0[0])
    np.testing.assert_allclose(np.r_[fit.H[0], fit.b[0]], want, rtol=1e-10)
    np.testing.assert_allclose(fit.H[1], H[1]) and np.testing.assert_allclose(fit.b[1], B[1])
    e = Y[:, 0] - X @ want
    np.testing.assert_allclose(fit.R[0, 0], (e @ e + k * R[0, 0]) / (len(Z) + k), rtol=1e-12)
    np.testing.assert_allclose([fit.R[0, 1], fit.R[1, 1]], [R[0, 1], R[1, 1]])
    assert 0.15 < fit.b[0] - B[0] < 0.25  # the unit's own bias, learnt from its pairs
    full = fit_unit_observation(Z, Y, H0=H, b0=B, R0=R, design=D, shrink_pairs=k)
    rows = _fit_unit_rows(Z, Y, H, B, R, D, k)  # the row by row form, nothing missing
    for name in ("H", "b", "R", "r2", "se_H", "se_b"):
        np.testing.assert_allclose(getattr(rows, name), getattr(full, name), rtol=1e-9)


def test_a_vertical_only_unit_gets_its_model_from_its_pairs_and_keeps_it(tmp_path):
    rng = np.random.default_rng(4)
    core = Calibrator(CalibratorConfig(min_pairs=30, refit_every=10, **ONE_AT_A_TIME))
    events = campaign(40, rng)
    for msg in unit_pairs(rng, 40, [0.2, 0.0], train="TV"):
        if msg.__class__.__name__ == "OnboardIndex":
            msg = msgspec.structs.replace(msg, align10_mm=None, indicators=["top6"])
        events.append(msg)
    store = SqliteStore(tmp_path / "cal.sqlite")
    core.step(events)
    store.apply(core.drain_changes())
    cal = core.unit_calibrations[("TV", "u1")]
    fleet = core.calibration
    assert cal.n_pairs == 40 and core.stats["pairs_partial"] == 40
    assert cal.b.array()[0] - fleet.b.array()[0] > 0.1  # its Top6 bias, its own
    np.testing.assert_allclose(cal.H.array()[1], fleet.H.array()[1])  # Align10: the fleet's
    assert all(p.unit != ("TV", "u1") for p in core.pairs)  # not in the fleet's fit
    again = Calibrator(core.config, state=store.load())
    assert [p.index_id for p in again._partial_pairs] == [p.index_id for p in core._partial_pairs]
    assert np.isnan(again._partial_pairs[0].y[1])
    assert again.ingest(events[-1]) is False  # a paired index is known after a restart
    store.close()


def test_a_restart_after_any_batch_publishes_what_the_undisturbed_run_publishes(tmp_path):
    """Fleet, units, posteriors and tampings in batches; stopped after batch k and restarted
    on its store, the core publishes, batch by batch, the same models as if never stopped."""
    from tests.unit.test_calibration_service_core import histories

    rng = np.random.default_rng(4)
    events = campaign(35, rng) + histories(rng, segs=3, records=6)
    events += unit_pairs(rng, 25, [0.2, -0.1], train="TA") + campaign(30, rng, start=35)
    events += unit_pairs(rng, 25, [0.2, -0.1], train="TA", start=100)
    batches = [events[k : k + 9] for k in range(0, len(events), 9)]
    cfg = CalibratorConfig(min_pairs=30, refit_every=10, samples=30, seed=5, **ONE_AT_A_TIME)
    undisturbed = Calibrator(cfg)
    published = [undisturbed.step(b) for b in batches]
    assert sum(map(len, published)) > 10
    for cut in rng.choice(np.arange(1, len(batches)), size=4, replace=False):
        store = SqliteStore(tmp_path / f"cut{cut}.sqlite")
        core = Calibrator(cfg, store.load())
        for b in batches[:cut]:
            core.step(b)
            store.apply(core.drain_changes())
        store.close()
        store = SqliteStore(tmp_path / f"cut{cut}.sqlite")
        again = Calibrator(cfg, store.load())
        assert [again.step(b) for b in batches[cut:]] == published[cut:], f"cut after {cut}"
        store.close()
