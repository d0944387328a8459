"""The state ingestion keeps per train: its knots (fixes on a line), its published trajectory,
the chunks waiting for knots, and its counters. Map matching (:mod:`.matching`), the
published trajectory (:mod:`.trajectory`) and the core (:mod:`.core`) all work on it."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from services.ingestion.health import Inspected
from services.ingestion.sequencing import UnitState


@dataclass(frozen=True)
class Knot:
    """A train at time ``t`` on ``line`` at ``chainage_m``, moving at ``speed_mps``; ``ok`` is
    False for a poor position (dead-reckoned too long, a poor fix, off the line)."""

    t: float
    line: str
    chainage_m: float
    speed_mps: float
    ok: bool


@dataclass
class TrainStats:
    """Positioning counters of one train."""

    fixes: int = 0
    no_fix: int = 0  # fix_quality 0
    matched: int = 0  # knots from a good match
    poor: int = 0  # knots marked not ok
    switches: int = 0  # line changes
    duplicates: int = 0
    unpositioned: int = 0
    extrapolated: int = 0  # chunks whose tail was dead-reckoned past the last knot
    held: int = 0  # chunks that had to wait for a knot (none close enough before them)
    max_correction_m: float = 0.0  # largest later correction of a dead-reckoned position
    clock_jumps: int = 0  # fixes and chunks refused as ahead of (or far behind) the clock
    rebases: int = 0  # times the train's clock was re-based to a new timeline


@dataclass
class TrainState:
    """Map-matching state and the chunks of one train waiting for their knots."""

    stats: TrainStats = field(default_factory=TrainStats)
    line: str | None = None
    direction: int = 0  # +1 / -1 along the chainage, 0 not known yet
    extreme_m: float = 0.0  # farthest chainage reached in ``direction`` (or the start)
    off_count: int = 0
    # on a route of close tracks: the track was chosen by the running direction (until then
    # the train is not positioned on either)
    track_known: bool = False
    matched_fix_t: float | None = None  # the previous fix map matching saw
    last_fix_t: float | None = None
    last_good_t: float | None = None
    now: float = -math.inf  # newest event time of the train
    knots: list[Knot] = field(default_factory=list)  # from the fixes (map matching)
    knot_t: list[float] = field(default_factory=list)
    # the published trajectory: what PositionedChunks carried, never changed afterwards
    pub: list[Knot] = field(default_factory=list)
    pub_t: list[float] = field(default_factory=list)
    # corrections of the published trajectory being spread: (from t, offset m, until t)
    corrections: list[tuple[float, float, float]] = field(default_factory=list)
    poor_until: float = -math.inf  # published knots before this follow a large correction
    pending: list[tuple[Inspected, bool]] = field(default_factory=list)
    units: list[UnitState] = field(default_factory=list)  # the train's units, for windows
    # times of the current run of consecutive fixes refused as a clock jump (a re-base
    # candidate); cleared by a fix on the train's timeline
    suspects: list[float] = field(default_factory=list)
