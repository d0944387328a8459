"""The models the filter reads: the calibrations (observation models) and the degradation
posteriors by group, each checked completely before it may replace the one held."""

from __future__ import annotations

import json
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field, replace

import numpy as np

from schemas import (
    INDICATORS,
    ONBOARD_INDICES,
    Calibration,
    DegradationPosterior,
)
from services.filtering.degradation import DegradationParams
from services.filtering.events import Event, ModelMessage
from services.filtering.kalman import ObservationModel


@dataclass(frozen=True)
class Models:
    """The latest calibration and degradation posteriors (by group), as the core uses them."""

    calibration: Calibration | None = None
    observation: ObservationModel | None = None
    posteriors: Mapping[str, DegradationPosterior] = field(default_factory=dict)
    params: Mapping[str, DegradationParams] = field(default_factory=dict)
    # the units' own calibrations, by (train, unit); a unit without one uses the fleet's
    unit_calibrations: Mapping[tuple[str, str], Calibration] = field(default_factory=dict)
    unit_observations: Mapping[tuple[str, str], ObservationModel] = field(default_factory=dict)

    def observation_for(self, train: str, unit: str) -> ObservationModel | None:
        """The model an index of ``(train, unit)`` is read with: its own, else the fleet's."""
        return self.unit_observations.get((train, unit), self.observation)

    def observation_for_event(self, event: Event) -> ObservationModel | None:
        msg = event.message
        return self.observation_for(msg.train, msg.unit)

    def group_for(self, line: str, segment: str) -> str | None:
        """The most specific posterior group available for the segment, or None."""
        for group in (f"seg.{line}.{segment}", f"line.{line}", "net"):
            if group in self.params:
                return group
        return None


def model_name(msg: ModelMessage) -> str:
    """The name a model is versioned under: ``calibration`` or ``degradation/{group}``."""
    match msg:
        case Calibration():
            return f"calibration/{msg.train}/{msg.unit}" if msg.train else "calibration"
        case DegradationPosterior():
            return f"degradation/{msg.group}"
    raise TypeError(f"not a model: {type(msg).__name__}")


def _field(kind: str, name: str, value, shape: tuple[int | None, ...]) -> np.ndarray:
    """A model field as float64 of ``shape`` (None: any extent >= 1), or ValueError naming it."""
    try:
        arr = np.asarray(value.array(), dtype=np.float64)
    except (AttributeError, TypeError, ValueError) as exc:
        raise ValueError(f"{kind}.{name}: not a numeric array ({exc})") from None
    if arr.ndim != len(shape) or any(
        got < 1 if want is None else got != want for want, got in zip(shape, arr.shape, strict=True)
    ):
        want_s = ", ".join("Ns" if w is None else str(w) for w in shape)
        raise ValueError(f"{kind}.{name}: shape {arr.shape}, expected ({want_s})")
    if not np.isfinite(arr).all():
        raise ValueError(f"{kind}.{name}: contains NaN or inf")
    return arr


def parse_model(msg: ModelMessage) -> ObservationModel | DegradationParams:
    """The core's form of a model message, checked completely; ValueError naming the field.

    Everything the fold and the summaries use is checked here, before a model may replace
    the one held: the state and index names and order, every array's exact shape, finite
    values, ``R`` symmetric positive definite (right after a TRC restart ``S = R``), the
    posterior covariances ``Sigma`` and ``Sigma_z+`` symmetric positive semi-definite, and
    a version >= 1.
    """
    kind = type(msg).__name__
    if not isinstance(msg, Calibration | DegradationPosterior):
        raise TypeError(f"not a model: {kind}")
    if not isinstance(msg.version, int) or msg.version < 1:
        raise ValueError(f"{kind}.version: {msg.version!r}, expected an integer >= 1")
    if tuple(msg.indicators) != INDICATORS:
        raise ValueError(f"{kind}.indicators: {list(msg.indicators)} != {list(INDICATORS)}")
    n = len(INDICATORS)
    if isinstance(msg, Calibration):
        if tuple(msg.indices) != ONBOARD_INDICES:
            raise ValueError(f"{kind}.indices: {list(msg.indices)} != {list(ONBOARD_INDICES)}")
        m = len(ONBOARD_INDICES)
        H = _field(kind, "H", msg.H, (m, n))
        b = _field(kind, "b", msg.b, (m,))
        R = _field(kind, "R", msg.R, (m, m))
        try:
            return ObservationModel(H, b, R)
        except ValueError as exc:  # "R: not positive definite" and the like
            raise ValueError(f"{kind}.{exc}") from None
    mu = _field(kind, "mu", msg.mu, (None, n))
    ns = mu.shape[0]
    arrays = {
        "mu": mu,
        "sigma": _field(kind, "sigma", msg.sigma, (ns, n, n)),
        "z_plus": _field(kind, "z_plus", msg.z_plus, (ns, n)),
        "sigma_z_plus": _field(kind, "sigma_z_plus", msg.sigma_z_plus, (ns, n, n)),
    }
    try:
        return DegradationParams(**arrays)
    except ValueError as exc:  # "sigma: not positive semi-definite" and the like
        raise ValueError(f"{kind}.{exc}") from None


def with_parsed(models: Models, msg: ModelMessage, parsed) -> Models:
    if isinstance(msg, Calibration) and msg.train:
        unit = (msg.train, msg.unit)
        return replace(
            models,
            unit_calibrations={**models.unit_calibrations, unit: msg},
            unit_observations={**models.unit_observations, unit: parsed},
        )
    if isinstance(msg, Calibration):
        return replace(models, calibration=msg, observation=parsed)
    return replace(
        models,
        posteriors={**models.posteriors, msg.group: msg},
        params={**models.params, msg.group: parsed},
    )


def held_version(models: Models, msg: ModelMessage) -> int | None:
    """The version of the model held under ``msg``'s name, None if none is held."""
    if isinstance(msg, Calibration):
        held = (
            models.unit_calibrations.get((msg.train, msg.unit)) if msg.train else models.calibration
        )
    else:
        held = models.posteriors.get(msg.group)
    return None if held is None else held.version


def with_model(models: Models, msg: ModelMessage) -> Models | None:
    """``models`` with ``msg`` in it, None if not newer than the one held; ValueError if invalid."""
    held = held_version(models, msg)
    if held is not None and msg.version <= held:
        return None
    return with_parsed(models, msg, parse_model(msg))


def models_key(
    models: Models, line: str, segment: str, units: Iterable[tuple[str, str]] | None = None
) -> str:
    """The versions of the models a segment's fold uses: the fleet calibration, the
    calibration of each of the log's ``units`` (0: the unit has none of its own; None:
    every unit calibration held, when the log's units are not known), its posterior group
    and that group's version. Two folds of one log with equal keys are the same bits."""
    group = models.group_for(line, segment)
    if units is None:
        versions = sorted([*unit, cal.version] for unit, cal in models.unit_calibrations.items())
    else:
        held = models.unit_calibrations
        versions = sorted([*unit, held[unit].version if unit in held else 0] for unit in units)
    return json.dumps(
        {
            "calibration": models.calibration.version if models.calibration else 0,
            "units": versions,
            "known_units": units is not None,
            "group": group,
            "posterior": models.posteriors[group].version if group is not None else 0,
        }
    )


def key_units(key: str) -> frozenset[tuple[str, str]] | None:
    """The log's units a :func:`models_key` was written for (None: not known, or a key
    without them: it matches no current key, so its segment replays)."""
    try:
        parsed = json.loads(key)
    except ValueError:
        return None
    if not isinstance(parsed, dict) or parsed.get("known_units") is not True:
        return None
    return frozenset((train, unit) for train, unit, _version in parsed["units"])
