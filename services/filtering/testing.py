"""Test doubles that ship with the filtering service: plausible models to start it with."""

from __future__ import annotations

import numpy as np

from schemas import INDICATORS, Calibration, DegradationPosterior, NDArray

T0 = 1_767_225_600.0  # 2026-01-01T00:00:00Z


def example_models(
    samples: int, seed: int, *, z_plus_sd: float = 0.0, t: float = T0
) -> list[Calibration | DegradationPosterior]:
    """A Calibration (the study's H, b, R) and a ``net`` DegradationPosterior of ``samples``
    draws around the typical scenario (deploy/study.json5), both version 1."""
    rng = np.random.default_rng(seed)
    sd = np.array([1e-2, 7e-3]) * np.exp(0.3 * rng.standard_normal((samples, 1)))
    sigma = np.array([[1.0, 0.4], [0.4, 1.0]]) * sd[:, :, None] * sd[:, None]
    mu = rng.normal([7e-4, 4e-4], 2e-4, (samples, 2))
    z_plus = np.log([2.0, 1.8]) + (
        rng.normal(0.0, z_plus_sd, (samples, 2)) if z_plus_sd else np.zeros((samples, 2))
    )
    names = list(INDICATORS)
    return [
        Calibration(
            version=1,
            t=t,
            indicators=names,
            indices=names,
            H=NDArray.of([[0.9, 0.05], [0.05, 0.75]]),
            b=NDArray.of([-0.25, -0.35]),
            R=NDArray.of([[0.01, 0.002], [0.002, 0.03]]),
            n_pairs=40,
            r2=NDArray.of([0.8, 0.7]),
        ),
        DegradationPosterior(
            group="net",
            version=1,
            t=t,
            indicators=names,
            mu=NDArray.of(mu),
            sigma=NDArray.of(sigma),
            z_plus=NDArray.of(z_plus),
            sigma_z_plus=NDArray.of(np.broadcast_to(np.eye(2) * 0.01, (samples, 2, 2))),
            n_increments=20,
            n_levels=5,
        ),
    ]
