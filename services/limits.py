"""Alert, intervention and immediate-action limits per line speed band, read from
``services/defaults/limits.json5``.

One deploy-time config read by every service that applies a limit (filtering computes
exceedance probabilities against the limits; alerting raises alerts on them; the planner's
risk limit is the immediate-action limit) and by the commands that show them (the report,
``trackfusion state``). Limits are in mm on the indicators of ``schemas.INDICATORS``.

Which speed class applies to a line is :meth:`Limits.speed_class`, the one rule all of them
use: the class the file's ``lines`` names for the line; else, when the service was given a
network, the class whose band holds the line's speed (``line_speed_mps`` of the network file,
from OpenStreetMap ``maxspeed`` for an imported network); else ``default_speed_class``.
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from services.defaults import default_file
from services.runtime.config import read_json5

DEFAULT_LIMITS_FILE = default_file("limits.json5")

# A speed class name: its band of line speed in km/h, "v<=80" or "80<v<=120".
_BAND = re.compile(r"^(?:(\d+(?:\.\d+)?)<)?v<=(\d+(?:\.\d+)?)$")


def add_limits_argument(parser, what: str) -> None:
    """``--limits FILE``: the limits file, read with :func:`load_limits`; ``what`` says what
    the command takes from it."""
    parser.add_argument(
        "--limits",
        metavar="FILE",
        type=Path,
        default=DEFAULT_LIMITS_FILE,
        help=f"{what} (default: %(default)s)",
    )


def speed_band(name: str) -> tuple[float, float]:
    """``(low, high]`` km/h of a speed class name (``"v<=80"``: (0, 80]); ValueError when the
    name is not of that form."""
    match = _BAND.match(name.replace(" ", ""))
    if match is None:
        raise ValueError(f"speed class {name!r} is not 'v<=HIGH' or 'LOW<v<=HIGH' (km/h)")
    low, high = float(match.group(1) or 0.0), float(match.group(2))
    if not low < high:
        raise ValueError(f"speed class {name!r}: empty band")
    return low, high


def network_line_speeds(network) -> dict[str, float]:
    """Line id -> line speed in km/h of a ``track.network.Network``."""
    return {line.id: line.line_speed_mps * 3.6 for line in network.lines.values()}


@dataclass(frozen=True)
class Limits:
    """Limits of every line: ``for_line(line)`` gives ``(L, n)`` mm in ``levels`` order."""

    levels: tuple[str, ...]
    speed_classes: dict[str, np.ndarray]  # speed class -> (L, n) mm
    default_speed_class: str
    lines: dict[str, str]  # line -> speed class, as the file names them
    immediate_action: dict[str, np.ndarray] = field(default_factory=dict)  # class -> (n,) mm
    line_speeds_kmh: dict[str, float] = field(default_factory=dict)  # line -> network speed

    def __post_init__(self) -> None:
        # (upper bound km/h, class) slowest first, read once from the class names
        bands = sorted((speed_band(name)[1], name) for name in self.speed_classes)
        object.__setattr__(self, "_bands", bands)

    def speed_class(self, line: str) -> str:
        """The speed class of ``line``: named in the file, else from the network's line speed,
        else the default (module docstring)."""
        named = self.lines.get(line)
        if named is not None:
            return named
        speed = self.line_speeds_kmh.get(line)
        if speed is None or not math.isfinite(speed):
            return self.default_speed_class
        return self.class_for_speed(speed)

    def class_for_speed(self, speed_kmh: float) -> str:
        """The class whose band holds ``speed_kmh``; the fastest class above every band."""
        bands = self._bands
        return next((name for high, name in bands if speed_kmh <= high), bands[-1][1])

    def for_line(self, line: str) -> np.ndarray:
        return self.speed_classes[self.speed_class(line)]

    def immediate_action_for_line(self, line: str) -> np.ndarray | None:
        """``(n,)`` mm, None when the file has no ``immediate_action`` table."""
        return self.immediate_action.get(self.speed_class(line))

    def describe(self, line: str) -> str:
        """``"speed class 80<v<=120"`` and where it comes from when not named in the file."""
        name = self.speed_class(line)
        if line in self.lines:
            return f"speed class {name}"
        speed = self.line_speeds_kmh.get(line)
        if speed is not None and math.isfinite(speed):
            return f"speed class {name} (line speed {speed:.0f} km/h)"
        return f"speed class {name} (default)"


def load_limits(
    path: str | Path = DEFAULT_LIMITS_FILE, line_speeds_kmh: Mapping[str, float] | None = None
) -> Limits:
    """Read and check a limits file, with the network's line speeds if given; ValueError
    says what to fix."""
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
    if not classes:
        raise ValueError(f"{path}: no speed class")
    for name, table in classes.items():
        try:
            speed_band(name)
        except ValueError as exc:
            raise ValueError(f"{path}: {exc}") from None
        if table.ndim != 2 or not np.isfinite(table).all() or (table <= 0).any():
            raise ValueError(f"{path}: speed class {name!r}: limits must be positive numbers")
        if (np.diff(table, axis=0) < 0).any():
            raise ValueError(f"{path}: speed class {name!r}: levels must not decrease")
    unknown = {default, *lines.values()} - set(classes)
    if unknown:
        raise ValueError(f"{path}: unknown speed class(es) {sorted(unknown)}")
    limits = Limits(levels, classes, default, lines, line_speeds_kmh=dict(line_speeds_kmh or {}))
    if "immediate_action" in raw:
        limits = replace(limits, immediate_action=load_immediate_action(path, limits))
    return limits


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
