"""Test doubles of the wire contract, shared by the services' own ``testing`` modules."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from schemas.messages import INDICATORS, NDArray, SegmentState

T0 = 1_767_225_600.0  # 2026-01-01T00:00:00Z, a Thursday
LEVELS = ("alert", "intervention")
LIMITS_MM = np.array([[6.0, 5.0], [8.0, 7.0]])  # (L, n): alert, intervention x top6, align10


def f8(values) -> NDArray:
    return NDArray.of(np.asarray(values, float), "f8")


def lognormal_state(
    line: str,
    segment: str,
    t: float,
    *,
    mean_mm: Sequence[float],
    sd_log: Sequence[float],
    horizons: Sequence[float],
    levels: Sequence[str] = LEVELS,
    limits_mm=LIMITS_MM,
    p_exceed=None,
    forecast_p_exceed=None,
    **fields: Any,
) -> SegmentState:
    """A SegmentState whose summary is independent log-normals (median ``mean_mm``, log sd
    ``sd_log``) with a flat forecast at ``horizons`` and the limits ``limits_mm`` (L, n) of
    ``levels``; ``p_exceed`` (L, n) and
    ``forecast_p_exceed`` (h, L, n) are zeros unless given; ``fields`` sets the rest."""
    n, h, levels_n = len(INDICATORS), len(horizons), len(levels)
    mean = np.log(np.asarray(mean_mm, float))
    sd = np.asarray(sd_log, float)
    low, high = np.exp(mean - 1.96 * sd), np.exp(mean + 1.96 * sd)
    p_now = np.zeros((levels_n, n)) if p_exceed is None else p_exceed
    p_ahead = np.zeros((h, levels_n, n)) if forecast_p_exceed is None else forecast_p_exceed
    return SegmentState(
        line=line,
        segment=segment,
        t=t,
        indicators=list(INDICATORS),
        mean=f8(mean),
        cov=f8(np.diag(sd**2)),
        ci_low_mm=f8(low),
        ci_high_mm=f8(high),
        width=float(np.prod(sd**2) ** (1 / n)),
        limit_levels=list(levels),
        limits_mm=f8(limits_mm),
        p_exceed=f8(p_now),
        horizons_days=f8(horizons),
        forecast_mean=f8(np.tile(mean, (h, 1))),
        forecast_ci_low_mm=f8(np.tile(low, (h, 1))),
        forecast_ci_high_mm=f8(np.tile(high, (h, 1))),
        forecast_p_exceed=f8(p_ahead),
        **fields,
    )
