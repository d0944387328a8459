"""Initial models: version 1 of the Calibration and the degradation posteriors, drawn from a
prior specification (``initial-models.json5``) until data gives better ones."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from schemas import INDICATORS, ONBOARD_INDICES, Calibration, DegradationPosterior, NDArray
from services.calibration.posterior import group_rng, sample_prior
from services.drift_diffusion import NIWPrior

_N = len(INDICATORS)


def prior_from_spec(spec: Mapping[str, Any], what: str, weight: str, cov: str) -> NIWPrior:
    """NIW prior from ``{mean, <weight>, <cov> (prior mean of the covariance), dof}``."""
    try:
        dof = float(spec["dof"])
        cov_mean = np.asarray(spec[cov], dtype=np.float64)
        n = cov_mean.shape[0]
        if not dof > n + 1:
            raise ValueError(f"{what}.dof: must be > n + 1 = {n + 1} (finite mean), got {dof}")
        return NIWPrior(
            m0=np.asarray(spec["mean"], dtype=np.float64),
            lambda0=float(spec[weight]),
            Psi0=cov_mean * (dof - n - 1),  # so that E[Σ] = Psi0 / (nu0 - n - 1) = cov_mean
            nu0=dof,
        )
    except KeyError as e:
        raise ValueError(f"{what}: missing {e.args[0]!r}") from None


def initial_models(
    spec: Mapping[str, Any], *, samples: int, seed: int
) -> tuple[Calibration | None, list[DegradationPosterior]]:
    """Version-1 models from a prior specification (``services/defaults/initial-models.json5``).

    ``spec["calibration"]``: ``H``, ``b``, ``R``, optionally ``r2`` (default 0) and ``n_pairs``
    (default 1: the schema needs > 0; the pairs behind a prior model are not ours). ``t`` is 0.
    ``spec["degradation"]``: ``{group: {drift: {...}, level: {...}}}`` where ``drift`` is
    ``{mean (ln mm/day), weight_days, sigma (prior mean of Σ, ln mm²/day), dof}`` and
    ``level`` is ``{mean (ln mm), weight_levels, cov (prior mean of Σz+), dof}``; the
    ``samples`` draws come from these Normal-Inverse-Wishart priors, seeded by
    ``(seed, group, 1)``. Raises ValueError naming what is wrong.
    """
    calibration = None
    if (cal := spec.get("calibration")) is not None:
        try:
            H, b, R = (np.asarray(cal[k], dtype=np.float64) for k in ("H", "b", "R"))
        except KeyError as e:
            raise ValueError(f"calibration: missing {e.args[0]!r}") from None
        m = len(ONBOARD_INDICES)
        if H.shape != (m, _N) or b.shape != (m,) or R.shape != (m, m):
            raise ValueError(
                f"calibration: H {H.shape}, b {b.shape}, R {R.shape}; need ({m}, {_N}), "
                f"({m},), ({m}, {m})"
            )
        if not np.allclose(R, R.T) or np.linalg.eigvalsh(R)[0] <= 0:
            raise ValueError("calibration.R: must be symmetric positive definite")
        calibration = Calibration(
            version=1,
            t=0.0,
            indicators=list(INDICATORS),
            indices=list(ONBOARD_INDICES),
            H=NDArray.of(H),
            b=NDArray.of(b),
            R=NDArray.of(R),
            n_pairs=int(cal.get("n_pairs", 1)),
            r2=NDArray.of(cal.get("r2", np.zeros(m))),
        )
    posteriors = []
    for group, gspec in sorted(dict(spec.get("degradation") or {}).items()):
        drift = prior_from_spec(gspec.get("drift", {}), f"{group}.drift", "weight_days", "sigma")
        level = prior_from_spec(gspec.get("level", {}), f"{group}.level", "weight_levels", "cov")
        rng = group_rng(seed, group, 1)
        mu, sigma = sample_prior(drift, samples, rng)
        z_plus, sigma_z_plus = sample_prior(level, samples, rng)
        posteriors.append(
            DegradationPosterior(
                group=group,
                version=1,
                t=0.0,
                indicators=list(INDICATORS),
                mu=NDArray.of(mu),
                sigma=NDArray.of(sigma),
                z_plus=NDArray.of(z_plus),
                sigma_z_plus=NDArray.of(sigma_z_plus),
                n_increments=0,
                n_levels=0,
            )
        )
    return calibration, posteriors
