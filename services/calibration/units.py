"""Per-unit observation models: which units are due a fit of their own, and that fit. Pure.

Each on-board unit gets its own H, b, R (:func:`fit_unit_observation`), shrunk towards the
fleet's model (in force or held) by ``unit_shrink_pairs`` pseudo-pairs, once the unit has
``unit_min_pairs`` pairs and again every ``refit_every`` more. Its key is
``calibration/{train}/{unit}`` (:func:`~services.calibration.state.unit_key`); the
:class:`~services.calibration.calibrator.Calibrator` holds and publishes it by the same rule
as the fleet's. A unit's pairs include those quarantined from the fleet's fit: a unit that
reads the track differently from the fleet is what its own model is for.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from schemas import INDICATORS, ONBOARD_INDICES, Calibration, NDArray
from services.calibration.config import CalibratorConfig
from services.calibration.regression import ObservationFit, fit_unit_observation
from services.calibration.state import Pair


def units_due(
    pairs: Sequence[Pair], fit_at: Mapping[tuple[str, str], int], cfg: CalibratorConfig
) -> dict[tuple[str, str], list[Pair]]:
    """The units due a fit, with their pairs: ``unit_min_pairs`` or more, and ``refit_every``
    more than at their last fit (``fit_at``: a unit's pairs then)."""
    by_unit: dict[tuple[str, str], list[Pair]] = {}
    for p in pairs:
        by_unit.setdefault(p.unit, []).append(p)
    return {
        u: ps
        for u, ps in by_unit.items()
        if len(ps) >= cfg.unit_min_pairs
        and (u not in fit_at or len(ps) - fit_at[u] >= cfg.refit_every)
    }


def pair_design(pairs: Sequence[Pair]) -> np.ndarray:
    """:math:`X^T X / N` of every pair's ``[z, 1]``: the fleet's design the shrinkage uses."""
    X = np.hstack([np.array([p.z for p in pairs]), np.ones((len(pairs), 1))])
    return X.T @ X / len(X)


def unit_calibration(
    train: str,
    unit: str,
    pairs: Sequence[Pair],
    fleet: Calibration,
    design: np.ndarray,
    version: int,
    cfg: CalibratorConfig,
) -> tuple[ObservationFit, Calibration]:
    """A unit's own fit on its ``pairs``, shrunk towards ``fleet``, and its Calibration.

    Raises CalibrationError, SchemaError or ValueError when the fit or the message is refused.
    """
    fit = fit_unit_observation(
        np.array([p.z for p in pairs]),
        np.array([p.y for p in pairs]),
        H0=fleet.H.array(),
        b0=fleet.b.array(),
        R0=fleet.R.array(),
        design=design,
        shrink_pairs=cfg.unit_shrink_pairs,
    )
    cal = Calibration(
        version=version,
        t=max(p.t for p in pairs),
        indicators=list(INDICATORS),
        indices=list(ONBOARD_INDICES),
        H=NDArray.of(fit.H),
        b=NDArray.of(fit.b),
        R=NDArray.of(fit.R),
        n_pairs=len(pairs),
        r2=NDArray.of(fit.r2),
        train=train,
        unit=unit,
    )
    return fit, cal
