"""The planner's forecasts against Monte Carlo simulation of the degradation mixture."""

from __future__ import annotations

import numpy as np
import pytest

from services.planning.risk import Posterior, above_any, above_any_after_tamping, first_passage

N_PATHS = 20_000
DT = 0.5  # days per simulated step: a discrete path misses crossings between steps


def posterior(seed: int) -> Posterior:
    rng = np.random.default_rng(seed)
    s = 8
    return Posterior(
        mu=np.array([7e-4, 4e-4]) * np.exp(0.3 * rng.standard_normal((s, 2))),
        var=np.array([1e-4, 4.9e-5]) * np.exp(0.2 * rng.standard_normal((s, 2))),
        z_plus=np.log([2.0, 1.8]) + 0.02 * rng.standard_normal((s, 2)),
        var_plus=np.full((s, 2), 0.08**2),
    )


def simulate(m, v, post: Posterior, days: float, log_limit, seed: int):
    """Paths of the mixture: (ever above by each step, above at each step) per indicator."""
    rng = np.random.default_rng(seed)
    j = rng.integers(0, post.mu.shape[0], N_PATHS)
    z = m + np.sqrt(v) * rng.standard_normal((N_PATHS, 2))
    steps = int(round(days / DT))
    ever = np.zeros((steps + 1, N_PATHS, 2), bool)
    now = np.zeros((steps + 1, N_PATHS, 2), bool)
    ever[0] = now[0] = z > log_limit
    for k in range(1, steps + 1):
        z = z + post.mu[j] * DT + np.sqrt(post.var[j] * DT) * rng.standard_normal((N_PATHS, 2))
        now[k] = z > log_limit
        ever[k] = ever[k - 1] | now[k]
    return ever, now


@pytest.mark.parametrize(
    ("seed", "mean_mm", "sd"),
    [(0, (7.0, 5.0), 0.05), (1, (8.5, 6.0), 0.1), (2, (6.0, 6.5), 0.02), (3, (9.0, 8.0), 0.15)],
)
def test_first_passage_and_marginals_match_monte_carlo(seed, mean_mm, sd):
    post = posterior(seed)
    m = np.log(np.array([mean_mm]))
    v = np.full((1, 2), sd**2)
    log_limit = np.log(np.array([[11.0, 9.5]]))
    days = np.array([[7.0, 28.0, 91.0, 182.0]])
    fp = first_passage(m, v, post, days, log_limit)[0]  # the default 5 nodes
    marginal = above_any(m, v, post, days, log_limit)[0]
    ever, now = simulate(m[0], v[0], post, 182.0, log_limit[0], seed)
    at = (days[0] / DT).astype(int)
    mc_each = ever[at].mean(axis=1)  # (T, 2): P(indicator reached its limit by then)
    mc_any = ever[at].any(axis=2).mean(axis=1)
    mc_now = now[at].any(axis=2).mean(axis=1)
    se = np.sqrt(np.maximum(mc_any * (1 - mc_any), 1e-4) / N_PATHS)
    # the union bound: at least the probability of any, at most the sum of each
    assert (fp >= mc_any - 4 * se - 0.004).all()
    assert (fp <= mc_each.sum(axis=1) + 4 * se + 0.01).all()
    assert marginal == pytest.approx(mc_now, abs=4 * float(se.max()) + 0.003)
    assert (np.diff(fp) >= -1e-12).all()


def test_after_tamping_matches_monte_carlo():
    post = posterior(5)
    rng = np.random.default_rng(5)
    j = rng.integers(0, post.mu.shape[0], N_PATHS)
    age = np.array([30.0, 180.0, 720.0])
    log_limit = np.log([3.0, 2.6])
    p = above_any_after_tamping(post, age, log_limit).mean(axis=0)  # equal weights
    z0 = post.z_plus[j] + np.sqrt(post.var_plus[j]) * rng.standard_normal((N_PATHS, 2))
    for a, expected in zip(age, p, strict=True):
        z = z0 + post.mu[j] * a + np.sqrt(post.var[j] * a) * rng.standard_normal((N_PATHS, 2))
        assert (z > log_limit).any(axis=1).mean() == pytest.approx(expected, abs=0.01)


def test_a_level_already_above_the_limit_has_reached_it():
    post = posterior(0)
    fp = first_passage(np.log([[12.0, 3.0]]), np.full((1, 2), 1e-6), post, np.array([[1.0]]),
                       np.log([[11.0, 9.5]]))  # fmt: skip
    assert fp[0, 0] == pytest.approx(1.0)


def test_a_segments_weights_forecast_with_the_samples_they_favour():
    """Weights all on one sample: the forecast of that sample alone; weights from log
    weights over a thinned posterior: the kept samples' weights, normalised."""
    post = posterior(5)
    m = np.log(np.array([[8.0, 6.0], [8.0, 6.0]]))
    v = np.full((2, 2), 0.05**2)
    log_limit = np.log(np.array([[11.0, 9.5]] * 2))
    days = np.array([[28.0, 91.0]] * 2)
    k = int(np.argmax(post.mu[:, 0]))  # the fastest sample
    w = np.zeros((2, post.mu.shape[0]))
    w[0, k] = 1.0
    w[1] = 1.0 / post.mu.shape[0]
    alone = Posterior(post.mu[k : k + 1], post.var[k : k + 1], post.z_plus[k : k + 1],
                      post.var_plus[k : k + 1])  # fmt: skip
    fp = first_passage(m, v, post, days, log_limit, w=w)
    np.testing.assert_allclose(fp[0], first_passage(m[:1], v[:1], alone, days[:1],
                                                    log_limit[:1])[0], rtol=1e-12)  # fmt: skip
    np.testing.assert_allclose(fp[1], first_passage(m[1:], v[1:], post, days[1:],
                                                    log_limit[1:])[0], rtol=1e-12)  # fmt: skip
    assert fp[0, -1] > fp[1, -1]  # the fastest sample reaches the limit sooner
    marginal = above_any(m, v, post, days, log_limit, w=w)
    np.testing.assert_allclose(marginal[0], above_any(m[:1], v[:1], alone, days[:1],
                                                      log_limit[:1])[0], rtol=1e-12)  # fmt: skip

    thinned = Posterior.from_samples(
        np.repeat(post.mu, 3, 0), np.repeat(np.eye(2)[None] * 1e-4, 24, 0),
        np.repeat(post.z_plus, 3, 0), np.repeat(np.eye(2)[None] * 1e-2, 24, 0), 8,
    )  # fmt: skip
    assert (thinned.source_samples, thinned.step) == (24, 3)
    log_w = -np.arange(24.0)
    kept = np.exp(-np.arange(0.0, 24.0, 3.0))
    np.testing.assert_allclose(thinned.weights(log_w), kept / kept.sum())
    np.testing.assert_allclose(thinned.weights(None), np.full(8, 1 / 8))
    np.testing.assert_allclose(thinned.weights(log_w[:10]), np.full(8, 1 / 8))  # other posterior
