"""Degradation transition, Kalman update and FilterBank against hand results and a dense loop."""

import numpy as np
import pytest

from services.filtering import kalman as kalman_module
from services.filtering.degradation import DegradationParams, mid_interval_age, transition
from services.filtering.kalman import (
    FilterBank,
    ObservationModel,
    _update_2x2,
    _update_general,
    predict,
    update,
)
from services.filtering.mixture import forecast


def random_spd(rng, shape, n, scale):
    A = rng.normal(size=shape + (n, n))
    return scale * (A @ np.swapaxes(A, -1, -2) / n + 0.1 * np.eye(n))


def random_params(rng, lead, ns, n):
    shape = lead + (ns,)
    return DegradationParams(
        mu=rng.normal(0.002, 0.001, shape + (n,)),
        sigma=random_spd(rng, shape, n, 1e-4),
        z_plus=rng.normal(1.0, 0.2, shape + (n,)),
        sigma_z_plus=random_spd(rng, shape, n, 0.01),
    )


def test_hand_worked_predict_update_2d():
    # Restart at z = [1, 2], P = 0; 5 days of drift [0.01, 0.02] and diffusion Sigma.
    params = DegradationParams(
        mu=[[0.01, 0.02]],
        sigma=[[[0.02, 0.01], [0.01, 0.04]]],
        z_plus=[[0.0, 0.0]],
        sigma_z_plus=[[[0.0, 0.0], [0.0, 0.0]]],
    )
    z, P = predict([[1.0, 2.0]], np.zeros((1, 2, 2)), params, 5.0)
    np.testing.assert_allclose(z, [[1.05, 2.10]], atol=1e-15)
    np.testing.assert_allclose(P, [[[0.1, 0.05], [0.05, 0.2]]], atol=1e-15)
    # With H = I and this R, S = P + R = diag(0.2, 0.4) and K = P S^-1 = [[.5, .125], [.25, .5]].
    # Innovation v = y - z - b = [0.2, 0.4]: z+ = z + K v = [1.20, 2.35],
    # P+ = P - K S K^T = diag(0.04375, 0.0875), NIS = 0.2^2 / 0.2 + 0.4^2 / 0.4 = 0.6.
    R = [[0.1, -0.05], [-0.05, 0.2]]
    z, P, nis = update(z, P, [1.35, 2.4], np.eye(2), [0.1, -0.1], R)
    np.testing.assert_allclose(z, [[1.20, 2.35]], atol=1e-14)
    np.testing.assert_allclose(P, [[[0.04375, 0.0], [0.0, 0.0875]]], atol=1e-14)
    np.testing.assert_allclose(nis, [0.6], atol=1e-14)


@pytest.mark.parametrize(
    ("z", "p", "h", "b", "r", "y"),
    [(1.0, 0.3, 1.0, 0.0, 0.1, 1.4), (2.0, 0.05, 0.7, -0.2, 0.02, 1.1), (0.5, 0.0, 2.0, 1, 0.3, 3)],
)
def test_scalar_update_matches_textbook(z, p, h, b, r, y):
    s = h * p * h + r
    k = p * h / s
    z_post, p_post, nis = update([[z]], [[[p]]], [y], [[h]], [b], [[r]])
    np.testing.assert_allclose(z_post[0, 0], z + k * (y - h * z - b), rtol=1e-14)
    np.testing.assert_allclose(p_post[0, 0, 0], p * r / s, rtol=1e-13, atol=1e-16)
    np.testing.assert_allclose(nis[0], (y - h * z - b) ** 2 / s, rtol=1e-14)


@pytest.mark.parametrize("n", [1, 2, 3])
def test_forecast_without_updates_grows_linearly(n):
    rng = np.random.default_rng(n)
    params = random_params(rng, (), 1, n)
    z, P = rng.normal(size=(1, n)), random_spd(rng, (1,), n, 0.01)
    horizons = np.array([0.0, 30.0, 90.0, 180.0])
    fc = forecast(z, P, params, horizons)
    for i, h in enumerate(horizons):
        assert np.array_equal(fc.mean[i], z[0] + params.mu[0] * h)
        assert np.array_equal(fc.cov[i], P[0] + params.sigma[0] * h)


@pytest.mark.parametrize("dt", [0.0, 7.0, 100.0])
def test_tamping_branches(dt):
    rng = np.random.default_rng(0)
    p = random_params(rng, (), 3, 2)
    z, P = rng.normal(size=(3, 3, 2)), random_spd(rng, (3, 3), 2, 0.01)
    age = np.array([np.nan, mid_interval_age(dt), 0.3 * dt])
    z_pred, P_pred = transition(z, P, p, np.full(3, dt), age)
    np.testing.assert_allclose(z_pred[0], z[0] + p.mu * dt, rtol=1e-15)
    np.testing.assert_allclose(P_pred[0], P[0] + p.sigma * dt, rtol=1e-15)
    for i, a in [(1, dt / 2), (2, 0.3 * dt)]:
        np.testing.assert_allclose(z_pred[i], p.z_plus + p.mu * a, rtol=1e-15)
        np.testing.assert_allclose(P_pred[i], p.sigma_z_plus + p.sigma * a, rtol=1e-15)


@pytest.mark.parametrize("lead", [(), (4,), (3, 5)])
def test_2x2_fast_path_equals_general(lead):
    rng = np.random.default_rng(len(lead))
    z, P = rng.normal(size=lead + (6, 2)), random_spd(rng, lead + (6,), 2, 0.05)
    y, H, b = rng.normal(size=lead + (2,)), rng.normal(size=(2, 2)), rng.normal(size=2)
    R = random_spd(rng, (), 2, 0.1)
    fast_and_general = zip(
        _update_2x2(z, P, y, H, b, R, True), _update_general(z, P, y, H, b, R, True), strict=True
    )
    for fast, general in fast_and_general:
        assert fast.shape == general.shape
        np.testing.assert_allclose(fast, general, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("lead", [(40,), (3,), (40,), (0,)])
def test_2x2_fast_path_large_batches_fresh_outputs(lead):
    """Scratch arrays are reused across calls: outputs must be fresh, P+ exactly symmetric."""
    rng = np.random.default_rng(sum(lead) + 7)
    z, P = rng.normal(size=lead + (200, 2)), random_spd(rng, lead + (200,), 2, 0.05)
    y, H, b = rng.normal(size=lead + (2,)), rng.normal(size=(2, 2)), rng.normal(size=2)
    R = random_spd(rng, (), 2, 0.1)
    first = _update_2x2(z, P, y, H, b, R, True)
    kept = [a.copy() for a in first]
    _update_2x2(z[..., ::-1, :], P[..., ::-1, :, :], -y, H, b, R, True)  # same sizes, other data
    for a, b_ in zip(first, kept, strict=True):
        np.testing.assert_array_equal(a, b_)
    np.testing.assert_array_equal(first[1], np.swapaxes(first[1], -1, -2))
    for fast, general in zip(first, _update_general(z, P, y, H, b, R, True), strict=True):
        np.testing.assert_allclose(fast, general, rtol=1e-12, atol=1e-12)


class DenseReference:
    """Independent per-sample loop: standard-form covariance update with an explicit inverse."""

    def __init__(self, S, params):
        self.p = {
            k: np.broadcast_to(getattr(params, k), (S,) + getattr(params, k).shape[-d:]).copy()
            for k, d in [("mu", 2), ("sigma", 3), ("z_plus", 2), ("sigma_z_plus", 3)]
        }
        self.z, self.P, self.t = [None] * S, [None] * S, [None] * S

    def restart(self, s, z, t):
        ns = self.p["mu"].shape[1]
        self.z[s] = [np.array(z, float) for _ in range(ns)]
        self.P[s] = [np.zeros((len(z), len(z))) for _ in range(ns)]
        self.t[s] = t

    def predict(self, s, t, mode, age):
        dt = t - self.t[s]
        for j in range(len(self.z[s])):
            mu, sig = self.p["mu"][s, j], self.p["sigma"][s, j]
            if mode == "none":
                self.z[s][j] = self.z[s][j] + mu * dt
                self.P[s][j] = self.P[s][j] + sig * dt
            else:
                a = dt / 2 if mode == "mid" else age
                self.z[s][j] = self.p["z_plus"][s, j] + mu * a
                self.P[s][j] = self.p["sigma_z_plus"][s, j] + sig * a
        self.t[s] = t

    def update(self, s, y, H, b, R):
        nis = []
        for j in range(len(self.z[s])):
            z, P = self.z[s][j], self.P[s][j]
            S = H @ P @ H.T + R
            S_inv = np.linalg.inv(S)
            K = P @ H.T @ S_inv
            v = y - H @ z - b
            self.z[s][j], self.P[s][j] = z + K @ v, P - K @ S @ K.T
            nis.append(v @ S_inv @ v)
        return np.array(nis)


@pytest.mark.parametrize(
    ("S", "ns", "n", "m", "per_segment"),
    [
        (1, 1, 2, 2, False),
        (4, 6, 2, 2, True),
        (3, 5, 3, 2, True),
        (3, 4, 2, 3, False),
        (2, 3, 1, 1, True),
        (5, 2, 3, 3, False),
    ],
)
def test_bank_matches_dense_reference(S, ns, n, m, per_segment):
    rng = np.random.default_rng(S * 100 + ns * 10 + n + m)
    params = random_params(rng, (S,) if per_segment else (), ns, n)
    H, b, R = rng.normal(size=(m, n)), rng.normal(size=m), random_spd(rng, (), m, 0.05)
    bank, ref = FilterBank(S, params), DenseReference(S, params)
    z0 = rng.normal(1.0, 0.3, (S, n))
    bank.restart(np.arange(S), z0, 0.0)
    for s in range(S):
        ref.restart(s, z0[s], 0.0)
    kinds = ["predict", "update", "update", "restart", "set_params"]
    for _ in range(60):
        idx = rng.choice(S, rng.integers(1, S + 1), replace=False)
        kind = kinds[rng.choice(5, p=[0.4, 0.35, 0.05, 0.1, 0.1])]
        if kind == "predict":
            t = bank.t[idx] + rng.exponential(10.0, len(idx)) * (rng.random(len(idx)) < 0.9)
            modes = rng.choice(["none", "none", "known", "mid"], len(idx))
            dt = t - bank.t[idx]
            age = np.where(modes == "known", rng.uniform(0, 1, len(idx)) * dt, np.nan)
            age = np.where(modes == "mid", mid_interval_age(dt), age)
            bank.predict_to(idx, t, age)
            for i, s in enumerate(idx):
                ref.predict(s, t[i], modes[i], age[i])
        elif kind == "update":
            y = rng.normal(0.5, 0.5, (len(idx), m))
            nis = bank.update(idx, y, ObservationModel(H, b, R))
            expected = [ref.update(s, y[i], H, b, R) for i, s in enumerate(idx)]
            np.testing.assert_allclose(nis, expected, rtol=1e-9, atol=1e-9)
        elif kind == "restart":
            z, t = rng.normal(1.0, 0.3, (len(idx), n)), bank.t[idx] + rng.uniform(0, 5, len(idx))
            bank.restart(idx, z, t)
            for i, s in enumerate(idx):
                ref.restart(s, z[i], t[i])
        else:
            new = random_params(rng, (len(idx),), ns, n)
            bank.set_params(idx, new)
            for key in ref.p:
                ref.p[key][idx] = getattr(new, key)
    np.testing.assert_allclose(bank.z, np.array(ref.z), rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(bank.P, np.array(ref.P), rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(bank.t, np.array(ref.t, float), rtol=0, atol=0)


def test_bank_snapshot_restore_and_unstarted_segments():
    rng = np.random.default_rng(7)
    params = random_params(rng, (), 4, 2)
    bank = FilterBank(3, params)
    with pytest.raises(ValueError, match="idx: segment without state"):
        bank.predict_to([0], 5.0)
    with pytest.raises(ValueError, match="idx: segment without state"):
        bank.update([0], [[1.0, 1.0]], ObservationModel(np.eye(2), np.zeros(2), np.eye(2)))
    bank.predict_to([0], 5.0, tamping_age=[2.0])  # a tamping resets even a stateless segment
    np.testing.assert_allclose(bank.z[0], params.z_plus + 2.0 * params.mu)
    bank.restart([1, 2], [[1.0, 2.0], [1.5, 2.5]], 3.0)
    snapshot, state = bank.copy(), bank.get_state([1])
    bank.predict_to([1, 2], 10.0)
    bank.update([1], [[1.0, 2.0]], ObservationModel(np.eye(2), np.zeros(2), 0.1 * np.eye(2)))
    bank.set_state([1], *state)
    for a, b in [(bank.z, snapshot.z), (bank.P, snapshot.P), (bank.t, snapshot.t)]:
        assert np.array_equal(a[:2], b[:2])
    assert bank.t[2] == 10.0 and snapshot.t[2] == 3.0


def _valid():
    rng = np.random.default_rng(1)
    return random_params(rng, (), 2, 2), rng.normal(size=(2, 2)), random_spd(rng, (2,), 2, 0.1)


def _params(**bad):
    p, _, _ = _valid()
    fields = {k: getattr(p, k) for k in ("mu", "sigma", "z_plus", "sigma_z_plus")}
    return DegradationParams(**(fields | bad))


def _bank():
    bank = FilterBank(2, _valid()[0])
    bank.restart([0, 1], np.ones((2, 2)), 10.0)
    return bank


NOT_PSD = [[[1.0, 2.0], [2.0, 1.0]]] * 2
ASYM = [[[1.0, 0.1], [0.0, 1.0]]] * 2
P_OK = _valid()[2]
Z_OK = _valid()[1]
H, B, R = np.eye(2), np.zeros(2), 0.1 * np.eye(2)


@pytest.mark.parametrize(
    ("name", "call"),
    [
        ("mu", lambda: _params(mu=[[np.nan, 0.0], [0.0, 0.0]])),
        ("sigma", lambda: _params(sigma=NOT_PSD)),
        ("sigma_z_plus", lambda: _params(sigma_z_plus=ASYM)),
        ("sigma_z_plus", lambda: _params(sigma_z_plus=np.ones((2, 3, 3)))),
        ("z_plus", lambda: _params(z_plus=np.ones((3, 2)))),
        ("z", lambda: transition([[np.inf, 0], [0, 0]], P_OK, _valid()[0], 1.0)),
        ("P", lambda: transition(Z_OK, NOT_PSD, _valid()[0], 1.0)),
        ("P", lambda: transition(Z_OK, np.ones((2, 3, 3)), _valid()[0], 1.0)),
        ("dt", lambda: transition(Z_OK, P_OK, _valid()[0], -1.0)),
        ("dt", lambda: transition(Z_OK, P_OK, _valid()[0], np.nan)),
        ("dt", lambda: transition(Z_OK, P_OK, _valid()[0], [1.0, 2.0, 3.0])),
        ("tamping_age", lambda: transition(Z_OK, P_OK, _valid()[0], 1.0, 2.0)),
        ("tamping_age", lambda: transition(Z_OK, P_OK, _valid()[0], 1.0, -0.5)),
        ("tamping_age", lambda: transition(Z_OK, P_OK, _valid()[0], 1.0, np.inf)),
        ("y", lambda: update(Z_OK, P_OK, [np.nan, 1.0], H, B, R)),
        ("y", lambda: update(Z_OK, P_OK, [1.0, 1.0, 1.0], H, B, R)),
        ("H", lambda: update(Z_OK, P_OK, [1.0, 1.0], np.eye(3), B, R)),
        ("b", lambda: update(Z_OK, P_OK, [1.0, 1.0], H, [0.0], R)),
        ("R", lambda: update(Z_OK, P_OK, [1.0, 1.0], H, B, np.zeros((2, 2)))),
        ("R", lambda: update(Z_OK, P_OK, [1.0, 1.0], H, B, ASYM[0])),
        ("P", lambda: update(Z_OK, NOT_PSD, [1.0, 1.0], H, B, R)),
        ("t", lambda: _bank().predict_to([0], 5.0)),
        ("t", lambda: _bank().restart([0], [[1.0, 1.0]], 5.0)),
        ("t", lambda: _bank().predict_to([0], np.nan)),
        ("idx", lambda: _bank().predict_to([0, 0], 12.0)),
        ("idx", lambda: _bank().predict_to([2], 12.0)),
        ("idx", lambda: _bank().predict_to([0.5], 12.0)),
        ("tamping_age", lambda: _bank().predict_to([0, 1], 12.0, [1.0, 3.0])),
        ("y", lambda: _bank().update([0], [[1.0, 1.0], [1.0, 1.0]], ObservationModel(H, B, R))),
        ("R", lambda: ObservationModel(H, B, np.zeros((2, 2)))),
        ("model", lambda: _bank().update([0], [[1.0, 1.0]], (H, B, R))),
        ("z_trc", lambda: _bank().restart([0], [[1.0, np.nan]], 12.0)),
        (
            "params",
            lambda: _bank().set_params([0], random_params(np.random.default_rng(), (), 3, 2)),
        ),
        ("params", lambda: FilterBank(3, random_params(np.random.default_rng(), (2,), 2, 2))),
    ],
)
def test_bad_input_raises_naming_argument(name, call):
    with pytest.raises(ValueError, match=rf"^{name}:"):
        call()


@pytest.mark.parametrize("block_filters", [1, 7, 8192])
def test_observe_equals_predict_then_update_in_any_block_size(monkeypatch, block_filters):
    monkeypatch.setattr(kalman_module, "BLOCK_FILTERS", block_filters)
    rng = np.random.default_rng(11)
    S, ns = 9, 5
    params = random_params(rng, (S,), ns, 2)
    model = ObservationModel(
        rng.normal(size=(2, 2)), rng.normal(size=2), random_spd(rng, (), 2, 0.1)
    )
    fused, stepwise = FilterBank(S, params), FilterBank(S, params)
    z0 = rng.normal(1.0, 0.3, (S, 2))
    for bank in (fused, stepwise):
        bank.restart(np.arange(S), z0, 0.0)
    for step in range(1, 6):
        idx = rng.choice(S, rng.integers(1, S + 1), replace=False)
        t = np.full(len(idx), 7.0 * step)
        age = np.where(rng.random(len(idx)) < 0.3, 1.0, np.nan)
        y = rng.normal(0.5, 0.2, (len(idx), 2))
        nis = fused.observe(idx, t, y, model, age)
        stepwise.predict_to(idx, t, age)
        np.testing.assert_allclose(nis, stepwise.update(idx, y, model), rtol=1e-12)
    np.testing.assert_allclose(fused.z, stepwise.z, rtol=1e-12)
    np.testing.assert_allclose(fused.P, stepwise.P, rtol=1e-12, atol=1e-15)
    np.testing.assert_array_equal(fused.t, stepwise.t)
