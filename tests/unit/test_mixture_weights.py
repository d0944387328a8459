"""Mixture weights from each segment's own on-board data (a departure from Eq. 13's 1/Ns).

w_j ∝ Π_k N(ν_jk; 0, S_jk) over the on-board updates since the last TRC restart: checked
against brute-force numpy/scipy, and through the filter bank and the tracker's fold.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import multivariate_normal, norm

from services.filtering.degradation import DegradationParams
from services.filtering.kalman import FilterBank, ObservationModel, update
from services.filtering.mixture import (
    effective_sample_size,
    forecast,
    summarize,
    weights_from_log,
)

H = np.array([[0.9, 0.05], [0.05, 0.75]])
B = np.array([-0.25, -0.35])
R = np.array([[0.01, 0.002], [0.002, 0.03]])


def random_weighted_mixture(rng, ns, n, n_point=0):
    A = rng.normal(size=(ns, n, n))
    P = 0.02 * (A @ np.swapaxes(A, -1, -2) + 0.1 * np.eye(n))
    P[:n_point] = 0.0
    w = rng.gamma(0.5, size=ns)
    return rng.normal(1.0, 0.3, (ns, n)), P, w / w.sum()


# --- weights_from_log, effective_sample_size ----------------------------------------------


def test_weights_from_log_normalise_in_log_space():
    log_w = np.array([-1e5, -1e5 + np.log(3.0), -1e5 - 800.0])  # exp() alone underflows
    w = weights_from_log(log_w)
    np.testing.assert_allclose(w, [0.25, 0.75, 0.0], atol=1e-15)
    np.testing.assert_array_equal(weights_from_log(log_w + 1234.5), w)  # shift invariant
    np.testing.assert_allclose(weights_from_log(np.zeros((3, 4))), 0.25)
    with pytest.raises(ValueError, match="^log_w:"):
        weights_from_log([0.0, np.nan])


def test_effective_sample_size():
    np.testing.assert_allclose(effective_sample_size(np.full(40, 1 / 40)), 40.0)
    np.testing.assert_allclose(effective_sample_size(np.eye(5)), np.ones(5))
    np.testing.assert_allclose(effective_sample_size([0.5, 0.5, 0.0]), 2.0)


# --- weighted summaries against brute force -----------------------------------------------


@pytest.mark.parametrize(("ns", "n", "n_point"), [(1, 2, 0), (6, 2, 0), (9, 3, 2), (5, 1, 1)])
def test_weighted_summary_matches_brute_force(ns, n, n_point):
    rng = np.random.default_rng(100 + ns * n)
    z, P, w = random_weighted_mixture(rng, ns, n, n_point)
    limits_mm = np.exp(rng.normal(1.2, 0.2, n))
    s = summarize(z, P, limits_mm, weights=w)

    mean = np.zeros(n)
    for j in range(ns):
        mean += w[j] * z[j]
    cov = np.zeros((n, n))
    for j in range(ns):
        d = z[j] - mean
        cov += w[j] * (P[j] + np.outer(d, d))
    np.testing.assert_allclose(s.mean, mean, rtol=1e-13, atol=1e-15)
    np.testing.assert_allclose(s.cov, cov, rtol=1e-12, atol=1e-15)

    def cdf(x, i):  # the weighted marginal CDF, component by component
        total = 0.0
        for j in range(ns):
            sd = np.sqrt(P[j, i, i])
            total += w[j] * (float(x >= z[j, i]) if sd == 0 else norm.cdf(x, z[j, i], sd))
        return total

    for i in range(n):
        assert abs(1 - cdf(np.log(limits_mm[i]), i) - s.p_exceed[i]) < 1e-12
        for q, bound in ((0.025, s.ci_low[i]), (0.975, s.ci_high[i])):
            # the infimum of {x: F(x) >= q}: F reaches q at the bound, not just below it
            assert cdf(bound + 1e-9, i) >= q - 1e-9
            assert cdf(bound - 1e-9, i) <= q + 1e-9


def test_weighted_summary_matches_monte_carlo():
    rng = np.random.default_rng(7)
    z, P, w = random_weighted_mixture(rng, 8, 2)
    size = 400_000
    j = rng.choice(len(w), size, p=w)
    x = z[j] + np.einsum("sij,sj->si", np.linalg.cholesky(P)[j], rng.standard_normal((size, 2)))
    s = summarize(z, P, weights=w)
    for q, bound in ((0.025, s.ci_low), (0.975, s.ci_high)):
        density = np.mean(np.abs(x - bound) < 0.01, axis=0) / 0.02
        se = np.sqrt(q * (1 - q) / size) / density
        assert (np.abs(np.quantile(x, q, axis=0) - bound) < 5 * se).all()


def test_equal_weights_reproduce_the_unweighted_summary():
    rng = np.random.default_rng(8)
    z, P, _ = random_weighted_mixture(rng, 7, 2, 2)
    plain = summarize(z, P, [3.0, 3.0])
    weighted = summarize(z, P, [3.0, 3.0], weights=np.full(7, 1 / 7))
    for field in ("mean", "cov", "ci_low", "ci_high", "width", "p_exceed"):
        np.testing.assert_allclose(getattr(weighted, field), getattr(plain, field), atol=1e-12)


def test_weighted_point_masses_give_the_weighted_empirical_quantile():
    z = np.array([[0.0], [1.0], [2.0], [3.0]])
    s = summarize(z, np.zeros((4, 1, 1)), weights=[0.01, 0.01, 0.9, 0.08], limits_mm=[np.e])
    np.testing.assert_allclose(s.ci_low, [2.0])  # cumulative 0.02 < 0.025 <= 0.92
    np.testing.assert_allclose(s.ci_high, [3.0])  # 0.92 < 0.975 <= 1
    np.testing.assert_allclose(s.p_exceed, [0.98])  # P(z > 1)
    np.testing.assert_allclose(s.mean, [0.01 + 1.8 + 0.24])


@pytest.mark.parametrize(
    "weights", [[0.5, 0.6], [-0.1, 1.1], [1.0, np.nan], [[0.5, 0.5, 0.0]], [[1.0], [0.0]]]
)
def test_bad_weights_raise_naming_weights(weights):
    with pytest.raises(ValueError, match=r"^weights:"):
        summarize(np.zeros((2, 2)), np.broadcast_to(np.eye(2), (2, 2, 2)), weights=weights)


# --- the log-likelihood of an update ------------------------------------------------------


@pytest.mark.parametrize("n", [2, 3])
def test_update_loglik_is_the_innovation_density(n):
    rng = np.random.default_rng(n)
    A = rng.normal(size=(4, 5, n, n))
    P = 0.01 * (A @ np.swapaxes(A, -1, -2))
    z = rng.normal(size=(4, 5, n))
    Hn = rng.normal(size=(2, n))
    y, b, Rn = rng.normal(size=(4, 2)), rng.normal(size=2), np.array([[0.05, 0.01], [0.01, 0.1]])
    z_post, P_post, nis, loglik = update(z, P, y, Hn, b, Rn, loglik=True)
    plain = update(z, P, y, Hn, b, Rn)
    for a, b_ in zip((z_post, P_post, nis), plain, strict=True):
        np.testing.assert_array_equal(a, b_)
    for k in range(4):
        for j in range(5):
            nu = y[k] - Hn @ z[k, j] - b
            S = Hn @ P[k, j] @ Hn.T + Rn
            expected = multivariate_normal(np.zeros(2), S).logpdf(nu)
            np.testing.assert_allclose(loglik[k, j], expected, rtol=1e-12)


# --- the filter bank and the tracker ------------------------------------------------------


def two_speed_posterior(ns=40):
    """Half the samples slow, half fast (in drift); everything else alike."""
    mu = np.where(np.arange(ns)[:, None] < ns // 2, [3e-4, 2e-4], [2.5e-3, 1.2e-3])
    sigma = np.broadcast_to(np.diag([3e-3, 2e-3]) ** 2, (ns, 2, 2))
    z_plus = np.broadcast_to(np.log([2.0, 1.8]), (ns, 2))
    return DegradationParams(mu, sigma, z_plus, np.broadcast_to(0.01 * np.eye(2), (ns, 2, 2)))


def test_fast_data_put_the_weight_on_fast_samples():
    params = two_speed_posterior()
    model = ObservationModel(H, B, R)
    rng = np.random.default_rng(11)
    bank = FilterBank(2, params)
    z0 = np.log([[3.0, 2.5], [3.0, 2.5]])
    bank.restart([0, 1], z0, 0.0)
    np.testing.assert_array_equal(bank.log_w, 0.0)
    true_mu = np.array([[2.5e-3, 1.2e-3], [3e-4, 2e-4]])  # segment 0 fast, segment 1 slow
    e, d = np.linalg.cholesky(R), np.linalg.cholesky(params.sigma[0])
    z = z0
    for day in range(1, 91):  # the Wiener model's path, observed daily
        z = z + true_mu + rng.standard_normal((2, 2)) @ d.T
        y = z @ H.T + B + rng.standard_normal((2, 2)) @ e.T
        bank.observe([0, 1], float(day), y, model)
    w = weights_from_log(bank.log_w)
    fast = np.arange(params.ns) >= params.ns // 2
    assert w[0, fast].sum() > 0.99 and w[1, ~fast].sum() > 0.99
    # and the weighted forecast drifts like the data, the equal-weight one does not
    ahead = forecast(bank.z, bank.P, params, [90.0], weights=w)
    equal = forecast(bank.z, bank.P, params, [90.0])
    truth = z + true_mu * 90
    assert (np.abs(ahead.mean[0] - truth) < np.abs(equal.mean[0] - truth)).all()
    # a TRC restart forgets the data; a tamping keeps them
    bank.predict_to([0], 95.0, tamping_age=[1.0])
    np.testing.assert_array_equal(weights_from_log(bank.log_w[0]), w[0])
    bank.restart([0], z0[:1], 100.0)
    np.testing.assert_array_equal(bank.log_w[0], 0.0)


def test_bank_log_weights_are_the_sum_of_update_logliks():
    params = two_speed_posterior(8)
    model = ObservationModel(H, B, R)
    bank = FilterBank(1, params)
    bank.restart([0], np.log([[3.0, 2.5]]), 0.0)
    z, P, t, total = bank.z[0].copy(), bank.P[0].copy(), 0.0, np.zeros(8)
    for day, y in ((3.0, [0.8, 0.5]), (10.0, [0.9, 0.6]), (12.0, [0.85, 0.4])):
        bank.observe([0], day, np.array([y]), model)
        z, P = z + params.mu * (day - t), P + params.sigma * (day - t)
        z, P, _, loglik = update(z, P, np.array(y), H, B, R, loglik=True)
        total, t = total + loglik, day
    np.testing.assert_allclose(bank.log_w[0], total, rtol=1e-12)
    other = FilterBank(1, params)
    other.set_state([0], *bank.get_state([0]))
    np.testing.assert_array_equal(other.log_w, bank.log_w)
    np.testing.assert_array_equal(bank.copy().log_w, bank.log_w)
    other.set_state([0], *bank.get_state([0])[:3])  # without log_w: equal weights
    np.testing.assert_array_equal(other.log_w, 0.0)
