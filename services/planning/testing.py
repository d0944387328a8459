"""Test doubles of the planning core: posteriors and states from a few numbers, and a random
network of segments at random ages since their last tamping (tests and benchmarks)."""

from __future__ import annotations

import numpy as np

from schemas import DAY_S, INDICATORS, DegradationPosterior, SegmentState
from schemas.testing import LEVELS, LIMITS_MM, T0, f8, lognormal_state
from services.limits import Limits
from services.planning.core import SegmentRef

IAL_MM = np.array([11.0, 9.5])
# the simulator's "typical" class (services/defaults/simulator.json5), per day, log mm
MU = np.array([7.0e-4, 4.0e-4])
SIGMA_SD = np.array([1.0e-2, 7.0e-3])
Z_PLUS_MM = np.array([2.0, 1.8])
Z_PLUS_SD = np.array([0.08, 0.08])


def make_limits() -> tuple[Limits, dict[str, np.ndarray]]:
    """One speed class for every line: :data:`LIMITS_MM` and the IAL :data:`IAL_MM`."""
    return Limits(LEVELS, {"80<v<=120": LIMITS_MM}, "80<v<=120", {}), {"80<v<=120": IAL_MM}


def make_posterior(
    group: str = "net",
    ns: int = 64,
    *,
    seed: int = 0,
    mu=MU,
    sigma_sd=SIGMA_SD,
    mu_spread: float = 0.2,
    z_plus_mm=Z_PLUS_MM,
    z_plus_sd=Z_PLUS_SD,
    version: int = 1,
) -> DegradationPosterior:
    """``ns`` samples: drift ``mu`` x LogNormal(0, mu_spread), the rest fixed (correlation 0.4
    for Sigma, 0.3 for Sigma_z+)."""
    rng = np.random.default_rng(seed)
    n = len(INDICATORS)
    mu_s = np.asarray(mu) * np.exp(mu_spread * rng.standard_normal((ns, n)))
    sd = np.asarray(sigma_sd, float)
    sigma = np.array([[1.0, 0.4], [0.4, 1.0]]) * np.outer(sd, sd)
    zsd = np.asarray(z_plus_sd, float)
    szp = np.array([[1.0, 0.3], [0.3, 1.0]]) * np.outer(zsd, zsd)
    return DegradationPosterior(
        group=group,
        version=version,
        t=T0,
        indicators=list(INDICATORS),
        mu=f8(mu_s),
        sigma=f8(np.repeat(sigma[None], ns, 0)),
        z_plus=f8(np.repeat(np.log(z_plus_mm)[None], ns, 0)),
        sigma_z_plus=f8(np.repeat(szp[None], ns, 0)),
        n_increments=10,
        n_levels=10,
    )


def make_state(
    line: str = "L1",
    segment: str = "s1",
    t: float = T0,
    *,
    mean_mm=(4.0, 3.0),
    sd_log=(0.05, 0.05),
    group: str = "net",
) -> SegmentState:
    """A SegmentState with the given log-normal summary (its probabilities are not used)."""
    return lognormal_state(
        line,
        segment,
        t,
        mean_mm=mean_mm,
        sd_log=sd_log,
        horizons=(30.0,),
        posterior_group=group,
        posterior_version=1,
    )


def random_network(
    n_lines: int,
    segments_per_line: int,
    *,
    seed: int = 0,
    segment_m: float = 200.0,
    max_age: float = 1.2,
) -> tuple[list[SegmentRef], list[SegmentState]]:
    """Lines of adjacent segments, each at a random age since its last tamping (uniform up to
    the expected time to the intervention limit x ``max_age``) with drift x LogNormal(0, 0.4);
    the states at :data:`T0` with a log-space sd of 0.05."""
    rng = np.random.default_rng(seed)
    width = len(str(segments_per_line - 1))
    refs, states = [], []
    log_il = np.log(LIMITS_MM[1])
    for line_no in range(n_lines):
        line = f"L{line_no + 1}"
        mu = MU * np.exp(0.4 * rng.standard_normal((segments_per_line, 2)))
        t_limit = ((log_il - np.log(Z_PLUS_MM)) / mu).min(axis=1)
        age = rng.uniform(0, max_age, segments_per_line) * t_limit
        z = np.log(Z_PLUS_MM) + Z_PLUS_SD * rng.standard_normal((segments_per_line, 2))
        z += mu * age[:, None] + SIGMA_SD * np.sqrt(age)[:, None] * rng.standard_normal(
            (segments_per_line, 2)
        )
        for k in range(segments_per_line):
            segment = f"s{k:0{width}d}"
            refs.append(SegmentRef(line, segment, segment_m))
            states.append(make_state(line, segment, T0, mean_mm=np.exp(z[k])))
    return refs, states


__all__ = ["DAY_S", "T0", "make_limits", "make_posterior", "make_state", "random_network"]
