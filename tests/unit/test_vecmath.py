"""The filter's vectorisable exp, log and normal CDF (services/filtering/vecmath.py) against
the C library's and scipy's, over the ranges the filter uses them on."""

from __future__ import annotations

import math

import numba
import numpy as np
import scipy.special

from services.filtering.vecmath import exp_nonpositive, log_normal, ndtr


@numba.njit(fastmath={"contract"}, error_model="numpy")
def _exp_all(x, out):
    for i in range(x.shape[0]):
        out[i] = exp_nonpositive(x[i])


@numba.njit(fastmath={"contract"}, error_model="numpy")
def _log_all(x, out):
    for i in range(x.shape[0]):
        out[i] = log_normal(x[i])


def _ulps(got: np.ndarray, want: np.ndarray) -> np.ndarray:
    """|got - want| in units of the last place of ``want`` (0 where equal)."""
    diff = np.abs(got - want)
    return np.where(diff == 0, 0.0, diff / np.spacing(np.abs(want)))


def test_exp_within_one_ulp_of_libm_down_to_underflow():
    rng = np.random.default_rng(3)
    edges = [0.0, -0.0, -1e-300, -1e-17, -0.5 * math.log(2), -math.log(2), -708.39, -708.4,
             -744.4, -745.1, -745.2, -800.0, -np.inf]  # fmt: skip
    x = np.concatenate([-np.abs(rng.standard_cauchy(200_000)) * 5, -rng.random(50_000), edges])
    got = np.empty_like(x)
    _exp_all(x, got)
    want = np.array([math.exp(v) for v in x])
    assert _ulps(got, want).max() <= 1.0
    assert (got[x < -745.2] == 0.0).all()  # below the smallest subnormal, as libm
    assert got[np.nonzero(x == 0.0)[0]].tolist() == [1.0, 1.0]


def test_log_within_one_ulp_of_libm_on_normal_numbers():
    rng = np.random.default_rng(4)
    below_one, above_one = np.nextafter(1.0, 0.0), np.nextafter(1.0, 2.0)
    tiny, huge = 2.2250738585072014e-308, 1.7976931348623157e308  # the normal range's ends
    edges = [1.0, 2.0, 0.5, math.sqrt(0.5), math.sqrt(2.0), below_one, above_one, tiny, huge]
    x = np.concatenate(
        [np.exp(rng.normal(size=200_000) * 40), 1 + rng.normal(size=50_000) * 1e-6, edges]
    )
    got = np.empty_like(x)
    _log_all(x, got)
    want = np.array([math.log(v) for v in x])
    assert _ulps(got, want).max() <= 1.0
    assert got[-9] == 0.0  # log 1 exactly


@numba.njit(fastmath={"contract"}, error_model="numpy")
def _ndtr_all(x, out):
    for i in range(x.shape[0]):
        out[i] = ndtr(x[i])


def test_normal_cdf_close_to_scipy_everywhere_and_in_the_lower_tail():
    rng = np.random.default_rng(5)
    x = np.concatenate([rng.normal(size=300_000) * 4, np.linspace(-38.0, 38.0, 76_001)])
    got = np.empty_like(x)
    _ndtr_all(x, got)
    want = scipy.special.ndtr(x)
    assert np.abs(got - want).max() <= 4e-16
    tail = (x < 0) & (want > 0)  # relative, down to 1e-300 and below
    assert (np.abs(got[tail] - want[tail]) / want[tail]).max() <= 2e-13
    edges = np.array([-np.inf, 0.0, np.inf])
    _ndtr_all(edges, out := np.empty(3))
    assert out.tolist() == [0.0, 0.5, 1.0]
