"""Test doubles of the alerting core: SegmentStates built from given probabilities, the
alerts and on-board indices beside them, and plan rows for the consumers of ``q/plan``."""

from __future__ import annotations

import numpy as np

from schemas import DAY_S, INDICATORS, Alert, OnboardIndex, PlanRow, SegmentState
from schemas.testing import LEVELS, LIMITS_MM, T0, lognormal_state
from services.limits import Limits

HORIZONS = (30.0, 90.0, 180.0)


def make_limits() -> Limits:
    """One speed class for every line, with :data:`LIMITS_MM`."""
    return Limits(LEVELS, {"80<v<=120": LIMITS_MM}, "80<v<=120", {})


def make_state(
    t: float = T0,
    *,
    line: str = "L1",
    segment: str = "s1",
    p_exceed=None,
    forecast=None,
    nis: float | None = None,
    limits_mm=LIMITS_MM,
    mean_mm=(4.0, 3.0),
    sd_log=(0.1, 0.1),
    last_trc_t: float | None = None,
) -> SegmentState:
    """A SegmentState with the given (L, n) ``p_exceed`` and (h, L, n) ``forecast`` at
    :data:`HORIZONS` (zeros by default); the rest is a consistent log-normal summary
    with a flat forecast."""
    return lognormal_state(
        line,
        segment,
        t,
        mean_mm=mean_mm,
        sd_log=sd_log,
        levels=LEVELS,
        limits_mm=limits_mm,
        horizons=HORIZONS,
        p_exceed=p_exceed,
        forecast_p_exceed=forecast,
        last_trc_t=last_trc_t,
        nis=nis,
    )


def make_alert(
    t: float = T0,
    *,
    line: str = "L1",
    segment: str = "s1",
    status: str = "raised",
    level: str = "intervention",
    probability: float = 0.9,
) -> Alert:
    """An exceedance Alert of Top6."""
    return Alert(
        line=line, segment=segment, t=t, kind="exceedance", status=status,
        indicator="top6", level=level, probability=probability,
    )  # fmt: skip


def make_index(t: float = T0, *, line: str = "L1", segment: str = "s1", **kw) -> OnboardIndex:
    """An OnboardIndex of train T1, unit u1 (``kw`` overrides its other fields)."""
    fields = dict(train="T1", unit="u1", top6_mm=5.0, align10_mm=3.5, speed_mps=20.0, coverage=1.0)
    return OnboardIndex(line=line, segment=segment, t=t, **{**fields, **kw})


def p_top6(level: int, p: float) -> np.ndarray:
    """(L, n) exceedance probabilities: ``p`` for Top6 at level index ``level``, else 0."""
    out = np.zeros((len(LEVELS), len(INDICATORS)))
    out[level, 0] = p
    return out


def forecast_top6(p30: float, p90: float, p180: float) -> np.ndarray:
    """(h, L, n) forecasts: Top6 above the intervention limit at 30/90/180 days."""
    out = np.zeros((len(HORIZONS), len(LEVELS), len(INDICATORS)))
    out[:, 1, 0] = (p30, p90, p180)
    return out


def plan_row(line: str, segment: str, probability: float, next_trc_t: float, **kw) -> PlanRow:
    """A row of the TRC inspection plan for a Top6 intervention limit of 8 mm; ``kw``
    overrides the other fields."""
    fields = dict(
        indicator="top6",
        level="intervention",
        limit_mm=8.0,
        horizon_days=max(next_trc_t - T0, 0.0) / DAY_S,
        p_now=probability / 2,
        state_t=T0,
        estimate_mm=5.0,
        ci_low_mm=4.0,
        ci_high_mm=6.5,
    )
    return PlanRow(
        line=line, segment=segment, probability=probability, next_trc_t=next_trc_t,
        **{**fields, **kw},
    )  # fmt: skip
