"""The compiled index step of the filter (``services/filtering/kernel.py``) alone.

Workload: ``SEGMENTS`` segments at Ns = 200, each stepped by ``STEPS`` on-board indices, one
call per step over every segment (``kernel.index_step``'s own loops: on the calling thread,
then spread over the cores as a re-run or a backlog does). Figure: nanoseconds per
sample-update (one sample of one segment predicted, scored, updated and weighted), best of
5 repetitions. Baseline in the same run: the numpy filter bank (``FilterBank.observe``,
the same maths without the weights and the CUSUM score) on the same shapes. Both states
are compared at the end (same filter: equal to 1e-9).

Run: ``.venv/bin/python -m bench.kernel``.
"""

from __future__ import annotations

import functools
import time

import numpy as np

from services.filtering import kernel
from services.filtering.degradation import DegradationParams
from services.filtering.kalman import FilterBank, ObservationModel
from services.filtering.state import state_layout, state_views

NS, SEGMENTS, STEPS, REPEATS = 200, 2000, 20, 5
DAY_S = 86_400.0


def bench_kernel() -> None:
    rng = np.random.default_rng(4)
    mu = rng.normal([7e-4, 4e-4], 2e-4, (NS, 2))
    sd = np.array([1e-2, 7e-3]) * np.exp(0.3 * rng.standard_normal((NS, 1)))
    sigma = np.array([[1.0, 0.4], [0.4, 1.0]]) * sd[:, :, None] * sd[:, None, :]
    params = DegradationParams(
        np.broadcast_to(mu, (SEGMENTS, NS, 2)),
        np.broadcast_to(sigma, (SEGMENTS, NS, 2, 2)),
        np.broadcast_to(np.log([2.0, 1.8]), (SEGMENTS, NS, 2)),
        np.broadcast_to(np.eye(2) * 0.01, (SEGMENTS, NS, 2, 2)),
    )
    H, b = np.array([[0.9, 0.05], [0.05, 0.75]]), np.array([-0.25, -0.35])
    R = np.array([[0.01, 0.002], [0.002, 0.03]])
    z0 = np.log(rng.uniform(2.0, 4.0, (SEGMENTS, 2)))
    y = (z0 @ H.T + b)[:, None, :] + rng.normal(0, 0.1, (SEGMENTS, STEPS, 2))
    rows = np.arange(SEGMENTS)
    group = np.zeros(SEGMENTS, dtype=np.int64)
    everyone_nis = np.ones(SEGMENTS, dtype=bool)

    def compiled(step) -> tuple[float, np.ndarray]:
        best = np.inf
        for _ in range(REPEATS):
            F = np.zeros((SEGMENTS, state_layout(NS, 2)[2]))  # z, P, log_w of each row
            z = state_views(F, NS, 2)[0]
            z[:] = z0[:, None, :]
            t_s = np.zeros(SEGMENTS)
            nis, score = np.zeros(SEGMENTS), np.zeros(SEGMENTS)
            started = time.perf_counter()
            for k in range(STEPS):
                t = np.full(SEGMENTS, 7.0 * (k + 1) * DAY_S)
                step(F, t_s, rows, t, y[:, k], mu[None], sigma[None], group,
                     H, b, R, everyone_nis, nis, score)  # fmt: skip
            best = min(best, time.perf_counter() - started)
        return best / (SEGMENTS * STEPS * NS) * 1e9, z

    def numpy_bank() -> tuple[float, np.ndarray]:
        best, model = np.inf, ObservationModel(H, b, R)
        for _ in range(REPEATS):
            bank = FilterBank(SEGMENTS, params)
            bank.restart(rows, z0, 0.0)
            started = time.perf_counter()
            for k in range(STEPS):
                bank.observe(rows, 7.0 * (k + 1), y[:, k], model)
            best = min(best, time.perf_counter() - started)
        return best / (SEGMENTS * STEPS * NS) * 1e9, bank.z

    serial = functools.partial(kernel.index_step, parallel=False)
    compiled(serial)  # compile or load the cache
    serial_ns, z_serial = compiled(serial)
    parallel_ns, z_parallel = compiled(functools.partial(kernel.index_step, parallel=True))
    bank_ns, z_bank = numpy_bank()
    same = np.array_equal(z_serial, z_parallel) and np.allclose(z_serial, z_bank, atol=1e-9)
    print(
        f"compiled index step  Ns={NS}, {SEGMENTS} segments x {STEPS} indices (best of"
        f" {REPEATS}): {serial_ns:.1f} ns a sample-update on one core, {parallel_ns:.1f} ns"
        f" over all cores; the numpy filter bank on the same shapes {bank_ns:.1f} ns"
        f" (ratio {bank_ns / serial_ns:.1f}x one core, {bank_ns / parallel_ns:.1f}x all);"
        f" serial and parallel the same bits, the bank's numbers: {same}"
    )


if __name__ == "__main__":
    bench_kernel()
