"""Mixture summaries (Eq. 13-14) against Monte Carlo sampling and exact special cases."""

import numpy as np
import pytest
from scipy.stats import norm

from services.filtering.degradation import DegradationParams
from services.filtering.mixture import credibility_width, forecast, summarize

N_MC = 400_000


def sample_mixture(rng, z, P, size):
    """Draws of the equal-weight mixture; zero-variance components give their mean exactly."""
    j = rng.integers(0, z.shape[0], size)
    w, V = np.linalg.eigh(P)
    root = V * np.sqrt(np.clip(w, 0, None))[:, None, :]  # test-side only: P is PSD by build
    return z[j] + np.einsum("sij,sj->si", root[j], rng.standard_normal((size, z.shape[1])))


def random_mixture(rng, ns, n, n_point):
    A = rng.normal(size=(ns, n, n))
    P = 0.02 * (A @ np.swapaxes(A, -1, -2) + 0.1 * np.eye(n))
    P[:n_point] = 0.0  # point masses, as right after a TRC restart
    return rng.normal(1.0, 0.3, (ns, n)), P


@pytest.mark.parametrize(("ns", "n", "n_point"), [(1, 2, 0), (5, 2, 0), (8, 3, 3), (6, 1, 2)])
def test_summary_matches_monte_carlo(ns, n, n_point):
    rng = np.random.default_rng(ns * 10 + n)
    z, P = random_mixture(rng, ns, n, n_point)
    x = sample_mixture(rng, z, P, N_MC)
    limits_mm = np.exp(np.quantile(x, 0.8, axis=0))
    s = summarize(z, P, limits_mm)

    np.testing.assert_allclose(s.mean, z.mean(0), rtol=1e-14)
    dev = x - x.mean(0)
    products = dev[:, :, None] * dev[:, None, :]
    se = products.std(0) / np.sqrt(N_MC)
    assert (np.abs(s.cov - products.mean(0)) < 5 * se + 1e-12).all()

    for q, bound in [(0.025, s.ci_low), (0.975, s.ci_high)]:
        # Sample-quantile error: sqrt(q (1 - q) / N) / density, the density from the sample.
        h = 0.01
        density = np.mean(np.abs(x - bound) < h, axis=0) / (2 * h)
        se_q = np.sqrt(q * (1 - q) / N_MC) / density
        assert (np.abs(np.quantile(x, q, axis=0) - bound) < 5 * se_q).all()
    np.testing.assert_allclose(s.ci_low_mm, np.exp(s.ci_low))
    mc_exceed = (x > np.log(limits_mm)).mean(0)
    se_p = np.sqrt(mc_exceed * (1 - mc_exceed) / N_MC)
    assert (np.abs(s.p_exceed - mc_exceed) < 5 * se_p).all()


@pytest.mark.parametrize("level", [0.9, 0.95, 0.99])
def test_single_component_interval_is_gaussian(level):
    z, P = np.array([[1.0, 2.0]]), np.array([[[0.04, 0.01], [0.01, 0.09]]])
    s = summarize(z, P, limits_mm=np.exp([1.2, 1.5]), level=level)
    k = norm.ppf(0.5 + level / 2)
    np.testing.assert_allclose(s.ci_low, [1.0 - 0.2 * k, 2.0 - 0.3 * k], atol=1e-10)
    np.testing.assert_allclose(s.ci_high, [1.0 + 0.2 * k, 2.0 + 0.3 * k], atol=1e-10)
    np.testing.assert_allclose(s.p_exceed, norm.sf([0.2 / 0.2, -0.5 / 0.3]), rtol=1e-12)
    np.testing.assert_allclose(s.width, np.sqrt(0.04 * 0.09 - 0.01**2), rtol=1e-12)


def test_point_masses_are_exact_steps():
    z = np.array([[0.0, 5.0], [1.0, 5.0], [2.0, 5.0], [3.0, 5.0]])
    s = summarize(z, np.zeros((4, 2, 2)), limits_mm=np.exp([1.5, 5.0]))
    # Quantiles of the discrete uniform on {0,1,2,3} and of a single atom at 5.
    np.testing.assert_allclose(s.ci_low, [0.0, 5.0], atol=1e-10)
    np.testing.assert_allclose(s.ci_high, [3.0, 5.0], atol=1e-10)
    np.testing.assert_allclose(s.p_exceed, [0.5, 0.0])
    np.testing.assert_allclose(s.cov, [[1.25, 0.0], [0.0, 0.0]], atol=1e-15)
    assert s.width == 0.0


def test_batched_summary_equals_per_batch():
    rng = np.random.default_rng(3)
    zs, Ps = zip(*(random_mixture(rng, 5, 2, i % 3) for i in range(6)), strict=True)
    z, P = np.array(zs).reshape(2, 3, 5, 2), np.array(Ps).reshape(2, 3, 5, 2, 2)
    batched = summarize(z, P, limits_mm=[3.0, 2.5])
    for a in range(2):
        for b in range(3):
            single = summarize(z[a, b], P[a, b], limits_mm=[3.0, 2.5])
            for field in ("mean", "cov", "ci_low", "ci_high", "width", "p_exceed"):
                np.testing.assert_allclose(
                    getattr(batched, field)[a, b], getattr(single, field), atol=1e-12
                )


@pytest.mark.parametrize("weighted", [False, True])
def test_summary_bits_do_not_depend_on_the_batch_or_the_cores(weighted):
    # 400 mixtures x 2 marginals x 2 levels: the compiled quantile runs on all cores
    # (kernel.PARALLEL_QUANTILES); every number must be the one of that mixture alone.
    rng = np.random.default_rng(11)
    zs, Ps = zip(*(random_mixture(rng, 50, 2, i % 4) for i in range(400)), strict=True)
    z, P = np.array(zs), np.array(Ps)
    w = rng.random((400, 50)) if weighted else None
    if w is not None:
        w /= w.sum(-1, keepdims=True)
    batched = summarize(z, P, limits_mm=[3.0, 2.5], weights=w)
    for i in range(0, 400, 37):
        one = summarize(z[i], P[i], limits_mm=[3.0, 2.5], weights=None if w is None else w[i])
        for field in ("ci_low", "ci_high", "p_exceed"):
            np.testing.assert_array_equal(getattr(batched, field)[i], getattr(one, field))
        # the quantiles solve F(x) = q for the exact mixture CDF (scipy's normal CDF here)
        wi = np.full(50, 1 / 50) if w is None else w[i]
        sd = np.sqrt(np.diagonal(P[i], axis1=-2, axis2=-1))
        for q, bound in ((0.025, one.ci_low), (0.975, one.ci_high)):
            for k in range(2):
                live = sd[:, k] > 0
                cdf = (
                    wi
                    * np.where(
                        live,
                        norm.cdf(bound[k], z[i, :, k], np.where(live, sd[:, k], 1)),
                        bound[k] >= z[i, :, k],
                    )
                ).sum()
                step = 1e-9
                below = (
                    wi
                    * np.where(
                        live,
                        norm.cdf(bound[k] - step, z[i, :, k], np.where(live, sd[:, k], 1)),
                        bound[k] - step >= z[i, :, k],
                    )
                ).sum()
                assert below <= q + 1e-12 and cdf >= q - 1e-9


@pytest.mark.parametrize(("diag", "w"), [([4.0, 9.0], 6.0), ([1.0, 8.0, 27.0], 6.0), ([0.5], 0.5)])
def test_credibility_width_of_diagonal(diag, w):
    P = np.diag(diag)
    np.testing.assert_allclose(credibility_width(P), w, rtol=1e-12)
    np.testing.assert_allclose(credibility_width(np.stack([P, 2 * P])), [w, 2 * w], rtol=1e-12)


def random_params(rng: np.random.Generator, S: int, ns: int) -> DegradationParams:
    """Per-segment parameters of ``S`` segments x ``ns`` samples, random drifts."""
    return DegradationParams(
        mu=rng.normal(0.002, 0.001, (S, ns, 2)),
        sigma=np.broadcast_to(1e-4 * np.eye(2), (S, ns, 2, 2)),
        z_plus=np.ones((S, ns, 2)),
        sigma_z_plus=np.broadcast_to(0.01 * np.eye(2), (S, ns, 2, 2)),
    )


def test_forecast_per_segment_params_has_horizon_axis():
    rng = np.random.default_rng(5)
    S, ns = 3, 4
    params = random_params(rng, S, ns)
    z, P = rng.normal(1, 0.2, (S, ns, 2)), np.zeros((S, ns, 2, 2))
    fc = forecast(z, P, params, [30.0, 90.0, 180.0], limits_mm=[4.0, 4.0])
    assert fc.mean.shape == (3, S, 2) and fc.cov.shape == (3, S, 2, 2) and fc.width.shape == (3, S)
    np.testing.assert_allclose(fc.mean[1], (z + 90 * params.mu).mean(1), rtol=1e-14)
    assert (np.diff(fc.width, axis=0) > 0).all()


Z, P = np.zeros((2, 2)), np.broadcast_to(np.eye(2), (2, 2, 2))
PARAMS = DegradationParams(np.zeros((2, 2)), P, np.zeros((2, 2)), P)


@pytest.mark.parametrize(
    ("name", "call"),
    [
        ("z", lambda: summarize([[np.nan, 0.0], [0.0, 0.0]], P)),
        ("P", lambda: summarize(Z, -P)),
        ("P", lambda: summarize(Z, np.ones((3, 2, 2)))),
        ("limits_mm", lambda: summarize(Z, P, limits_mm=[1.0, -1.0])),
        ("limits_mm", lambda: summarize(Z, P, limits_mm=[1.0, 2.0, 3.0])),
        ("level", lambda: summarize(Z, P, level=1.5)),
        ("P", lambda: credibility_width(np.ones((2, 3)))),
        ("P", lambda: credibility_width([[np.inf, 0.0], [0.0, 1.0]])),
        ("horizons_days", lambda: forecast(Z, P, PARAMS, [-1.0])),
        ("horizons_days", lambda: forecast(Z, P, PARAMS, [np.nan])),
        ("params", lambda: forecast(np.zeros((3, 2)), np.zeros((3, 2, 2)), PARAMS, [1.0])),
    ],
)
def test_bad_input_raises_naming_argument(name, call):
    with pytest.raises(ValueError, match=rf"^{name}:"):
        call()


def test_weighted_forecast_and_batches():
    rng = np.random.default_rng(9)
    S, ns = 3, 5
    params = random_params(rng, S, ns)
    z, P = rng.normal(1, 0.2, (S, ns, 2)), np.zeros((S, ns, 2, 2))
    w = rng.dirichlet(np.ones(ns), S)
    fc = forecast(z, P, params, [30.0, 90.0], limits_mm=[4.0, 4.0], weights=w)
    np.testing.assert_allclose(fc.mean[1], np.einsum("sj,sji->si", w, z + 90 * params.mu))
    for seg in range(S):
        one = summarize(
            z[seg] + 30 * params.mu[seg], 30 * params.sigma[seg], [4.0, 4.0], weights=w[seg]
        )
        np.testing.assert_allclose(fc.ci_high[0, seg], one.ci_high, atol=1e-12)
        np.testing.assert_allclose(fc.p_exceed[0, seg], one.p_exceed, atol=1e-14)
