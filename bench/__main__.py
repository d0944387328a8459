"""`make bench`: each figure with a ratio against a baseline measured in the same process.

Workloads (targets: docs/performance.md):

1. replay: Ns = 200 posterior samples, 52 weekly on-board events on 500 segments, through
   ``FilterBank`` (all segments of a week in one call). Baseline: filterpy ``KalmanFilter``
   objects, one per (segment, sample), on identical events; measured on a subset of the
   segments (a full filterpy replay would take minutes) and compared as sample-updates/s.
2. single event: one on-board event (predict + update) on one segment, Ns = 200, repeated;
   p50/p99 latency. Baseline: the filterpy loop over the 200 samples of that segment.
3. the frequency study at its default size (1,000 paths x 52 weeks x 5 intervals x 3
   scenarios), against its 20 s target.
4. the simulator's raw-signal generation, in trains simulated in real time per core
   (``bench/simulator.py``), against its target of 200.
5. ingestion and extraction: raw samples per second per core through each core, per-chunk
   latency (``bench/ingestion.py``, ``bench/extraction.py``); target >= 12 M through both.
6. the filtering service over Zenoh: events per second and index-to-state latency, the
   service as its own process as deployed, then in a thread of the bench's process
   (``bench/filtering.py``).
7. at-least-once delivery: messages per second through the producer's outbox against plain
   puts, what a consumer away while 300 keys were published replays on its return, and
   raw chunks in order from a gateway's outbox against plain puts, with a consumer that
   resumes at its position (``bench/delivery.py``; ``--keys 100000`` for a national
   instance's size).
8. the filtering core's model-change re-run: events replayed per second, summaries included,
   against the filter bank alone and the one-segment-at-a-time re-run (``bench/rerun.py``).
9. model versions calibration publishes per simulated month of the demo world, with the
   publication rule against without it (``bench/calibration_versions.py``).
10. one filtering instance with a backlog, in process: ``handle_batch`` on SQLite against the
    fold alone on the same batches, then the publication of the dirty states; once on fresh
    segments, once on 10,000 segments of 121 stored events after a restart (every segment
    resting: ``--history 60``), ten batches of 65,536 (``bench/backlog.py``).
11. filtering restart and model change on a store of 2,000 segments x 60 days (first start
    without checkpoints, restart from them, after SIGKILL; a new calibration), against
    ``fold_many`` alone (``bench/restart.py``; ``--segments 100000`` for a national
    instance's size).
12. the compiled index step alone, ns per sample-update on one core and on all, against the
    numpy filter bank on the same shapes (``bench/kernel.py``).
13. the maintenance plan of 100,000 segments x 26 weeks, 4 km a week a region: the first
    plan against its 60 s target, the same with the regions one at a time, a re-plan after
    one segment's change, and HiGHS's MILP over every (segment, week) of 500 segments of
    one region as the baseline (``bench/planning_scale.py``, about 4 minutes).

Not run here (minutes each, real processes): ``make scale`` (``bench/scale.py``, a national
deployment: two routers, four filtering shards, 10,000 to 100,000 segments);
``make soak``; ``python -m bench.planning`` (the planner in closed loop on a simulated year
against the threshold rule, a fixed cycle, point forecasts and an oracle).
"""

from __future__ import annotations

import time

import numpy as np
from filterpy.kalman import KalmanFilter

from services.filtering import study
from services.filtering.degradation import DegradationParams
from services.filtering.kalman import FilterBank, ObservationModel
from services.filtering.mixture import summarize

NS, SEGMENTS, WEEKS = 200, 500, 52
BASELINE_SEGMENTS = 4
H = np.array([[0.9, 0.05], [0.05, 0.75]])
B = np.array([-0.25, -0.35])
R = np.array([[0.01, 0.002], [0.002, 0.03]])
MODEL = ObservationModel(H, B, R)


def make_params(rng: np.random.Generator, segments: int) -> DegradationParams:
    mu = rng.normal([7e-4, 4e-4], 2e-4, (segments, NS, 2))
    sd = np.array([1e-2, 7e-3]) * np.exp(0.3 * rng.standard_normal((segments, NS, 1)))
    corr = np.array([[1.0, 0.4], [0.4, 1.0]])
    sigma = corr * sd[..., :, None] * sd[..., None, :]
    z_plus = np.broadcast_to(np.log([2.0, 1.8]), (segments, NS, 2))
    sigma_z_plus = np.broadcast_to(np.eye(2) * 0.01, (segments, NS, 2, 2))
    return DegradationParams(mu, sigma, z_plus, sigma_z_plus)


def make_events(rng: np.random.Generator, segments: int):
    z0 = np.log(rng.uniform(2.0, 4.0, (segments, 2)))
    t = 7.0 * np.arange(1, WEEKS + 1)
    y = (z0 @ H.T + B)[:, None, :] + rng.normal(0, 0.1, (segments, WEEKS, 2))
    return z0, t, y


def filterpy_filters(params: DegradationParams, z0: np.ndarray, segment: int) -> list:
    filters = []
    for j in range(NS):
        kf = KalmanFilter(dim_x=2, dim_z=2, dim_u=2)
        kf.x = z0[segment].reshape(2, 1).copy()
        kf.P = np.zeros((2, 2))
        kf.F = np.eye(2)
        kf.B = np.eye(2)
        kf.H = H
        kf.R = R
        filters.append((kf, params.mu[segment, j], params.sigma[segment, j]))
    return filters


def filterpy_event(filters: list, dt: float, y: np.ndarray) -> None:
    """One event for one segment: predict (drift as control input) and update every sample."""
    yb = (y - B).reshape(2, 1)
    for kf, mu, sigma in filters:
        kf.predict(u=(mu * dt).reshape(2, 1), Q=sigma * dt)
        kf.update(yb)


def bench_replay(rng: np.random.Generator) -> None:
    params = make_params(rng, SEGMENTS)
    z0, t, y = make_events(rng, SEGMENTS)
    everyone = np.arange(SEGMENTS)

    def replay() -> FilterBank:
        bank = FilterBank(SEGMENTS, params)
        bank.restart(everyone, z0, 0.0)
        for week in range(WEEKS):
            bank.observe(everyone, t[week], y[:, week], MODEL)
        return bank

    replay()  # warm-up
    start = time.perf_counter()
    bank = replay()
    bank_s = time.perf_counter() - start
    bank_rate = SEGMENTS * NS * WEEKS / bank_s

    start = time.perf_counter()
    for segment in range(BASELINE_SEGMENTS):
        filters = filterpy_filters(params, z0, segment)
        previous = 0.0
        for week in range(WEEKS):
            filterpy_event(filters, t[week] - previous, y[segment, week])
            previous = t[week]
    base_s = time.perf_counter() - start
    base_rate = BASELINE_SEGMENTS * NS * WEEKS / base_s

    # Same numbers: the last baseline segment against the bank.
    kf, _, _ = filters[-1]
    agree = np.allclose(kf.x.ravel(), bank.z[BASELINE_SEGMENTS - 1, -1], atol=1e-9) and np.allclose(
        kf.P, bank.P[BASELINE_SEGMENTS - 1, -1], atol=1e-12
    )
    print(
        f"replay  Ns={NS}, {WEEKS} weekly events x {SEGMENTS} segments: "
        f"bank {bank_s:.3f} s = {bank_rate / 1e6:.2f} M sample-updates/s; "
        f"filterpy loop {base_rate / 1e3:.1f} k sample-updates/s "
        f"(measured on {BASELINE_SEGMENTS} segments); ratio {bank_rate / base_rate:.0f}x "
        f"(target >= 300x); same numbers: {agree}"
    )


def bench_single_event(rng: np.random.Generator, repeats: int = 3000) -> None:
    params = make_params(rng, SEGMENTS)
    z0, t, y = make_events(rng, SEGMENTS)
    bank = FilterBank(SEGMENTS, params)
    bank.restart(np.arange(SEGMENTS), z0, 0.0)
    one = np.array([7])
    latencies = np.empty(repeats)
    for i in range(repeats):
        start = time.perf_counter()
        bank.observe(one, 0.01 * (i + 1), y[7:8, i % WEEKS], MODEL)
        latencies[i] = time.perf_counter() - start
    summary_latencies = np.empty(repeats // 3)
    for i in range(len(summary_latencies)):
        start = time.perf_counter()
        summarize(bank.z[7], bank.P[7], limits_mm=np.array([12.0, 10.0]))
        summary_latencies[i] = time.perf_counter() - start

    filters = filterpy_filters(params, z0, 7)
    base = np.empty(200)
    for i in range(len(base)):
        start = time.perf_counter()
        filterpy_event(filters, 0.01, y[7, i % WEEKS])
        base[i] = time.perf_counter() - start
    p50, p99 = np.percentile(latencies[100:], [50, 99]) * 1e3  # after warm-up
    base_p50 = np.median(base) * 1e3
    s50, s99 = np.percentile(summary_latencies[20:], [50, 99]) * 1e3
    print(
        f"single event  Ns={NS}, one segment, FilterBank.observe (predict + update): "
        f"p50 {p50:.3f} ms, p99 {p99:.3f} ms (target p99 < 1 ms); filterpy loop p50 "
        f"{base_p50:.2f} ms; ratio {base_p50 / p50:.0f}x (target >= 50x)"
    )
    print(f"  mixture summary of that segment (Eq. 13-14): p50 {s50:.3f} ms, p99 {s99:.3f} ms")


def bench_study() -> None:
    config = study.load_study_config()
    start = time.perf_counter()
    study.run_study(config)
    elapsed = time.perf_counter() - start
    work = config.paths * config.weeks * len(config.intervals_weeks) * len(config.scenarios)
    print(
        f"frequency study  {config.paths} paths x {config.weeks} weeks x "
        f"{len(config.intervals_weeks)} intervals x {len(config.scenarios)} scenarios, "
        f"Ns={config.posterior_samples}: {elapsed:.1f} s (target < 20 s, ratio to target "
        f"{elapsed / 20:.2f}); {work * config.posterior_samples / elapsed / 1e6:.2f} M "
        "sample-steps/s"
    )


def main() -> None:
    from bench.backlog import bench_backlog
    from bench.calibration_versions import main as bench_calibration_versions
    from bench.delivery import bench_delivery
    from bench.extraction import bench_extraction
    from bench.filtering import bench_filtering_service
    from bench.ingestion import bench_ingestion
    from bench.kernel import bench_kernel
    from bench.planning_scale import main as bench_planning_scale
    from bench.rerun import bench_rerun
    from bench.restart import bench_restart
    from bench.simulator import bench_raw_generation

    rng = np.random.default_rng(1)
    bench_replay(rng)
    bench_single_event(rng)
    bench_kernel()
    bench_rerun()
    bench_backlog()
    bench_backlog(10_000, 655_360, history=60)  # the backlog target's figure: ten batches of 65,536
    bench_study()
    bench_raw_generation()
    bench_ingestion()
    bench_extraction()
    bench_filtering_service(own_process=True)
    bench_filtering_service(own_process=False)
    bench_delivery()
    bench_calibration_versions([])
    bench_restart()
    bench_planning_scale(["--capacity", "4"])


if __name__ == "__main__":
    main()
