"""Alert and intervention limits per line, read from ``services/defaults/limits.json5``.

One deploy-time config read by the services that need it (filtering computes exceedance
probabilities against the limits; alerting raises alerts on them). Limits are in mm on the
indicators of ``schemas.INDICATORS``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from services.defaults import default_file
from services.runtime.config import read_json5

DEFAULT_LIMITS_FILE = default_file("limits.json5")


@dataclass(frozen=True)
class Limits:
    """Limits of every line: ``for_line(line)`` gives ``(L, n)`` mm in ``levels`` order."""

    levels: tuple[str, ...]
    speed_classes: dict[str, np.ndarray]  # speed class -> (L, n) mm
    default_speed_class: str
    lines: dict[str, str]  # line -> speed class

    def for_line(self, line: str) -> np.ndarray:
        return self.speed_classes[self.lines.get(line, self.default_speed_class)]

    def speed_class(self, line: str) -> str:
        return self.lines.get(line, self.default_speed_class)


def load_limits(path: str | Path = DEFAULT_LIMITS_FILE) -> Limits:
    """Read and check a limits file; ValueError says what to fix."""
    raw = read_json5(path)
    try:
        levels = tuple(raw["levels"])
        classes = {
            name: np.array([values[level] for level in levels], dtype=float)
            for name, values in raw["speed_classes"].items()
        }
        default = raw["default_speed_class"]
        lines = dict(raw.get("lines", {}))
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise ValueError(f"{path}: not a valid limits file ({type(exc).__name__}: {exc})") from None
    for name, table in classes.items():
        if table.ndim != 2 or not np.isfinite(table).all() or (table <= 0).any():
            raise ValueError(f"{path}: speed class {name!r}: limits must be positive numbers")
        if (np.diff(table, axis=0) < 0).any():
            raise ValueError(f"{path}: speed class {name!r}: levels must not decrease")
    unknown = {default, *lines.values()} - set(classes)
    if unknown:
        raise ValueError(f"{path}: unknown speed class(es) {sorted(unknown)}")
    return Limits(levels, classes, default, lines)


def load_immediate_action(path: str | Path, limits: Limits) -> dict[str, np.ndarray]:
    """The ``immediate_action`` limits (mm, one per indicator) of every speed class of a
    limits file, each at or above the class's highest level; ValueError says what to fix."""
    raw = read_json5(path)
    try:
        raw = raw["immediate_action"]
        table = {name: np.asarray(raw[name], dtype=float) for name in limits.speed_classes}
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise ValueError(
            f"{path}: no immediate_action limits for every speed class ({type(exc).__name__}: "
            f"{exc})"
        ) from None
    for name, ial in table.items():
        below = limits.speed_classes[name][-1]
        if ial.shape != below.shape or not np.isfinite(ial).all() or (ial < below).any():
            raise ValueError(
                f"{path}: immediate_action {name!r}: need {below.size} limits at or above "
                f"{limits.levels[-1]} {below.tolist()}, got {ial.tolist()}"
            )
    return table
