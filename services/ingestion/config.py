"""Settings of the ingestion core (``services.ingestion`` section of the config file)."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, fields
from typing import Any


@dataclass(frozen=True)
class IngestionConfig:
    """Thresholds of the ingestion core (``services.ingestion`` section of the config file)."""

    rate_hz: float = 2000.0  # expected sample rate of a unit
    rate_overrides: Mapping[str, float] = field(default_factory=dict)  # "train/unit" -> Hz
    rate_tolerance: float = 0.01  # relative
    supply_nominal_v: float = 5.0  # ratiometric reference
    supply_min_v: float = 2.5  # outside [min, max]: implausible, the chunk is rejected
    supply_max_v: float = 7.5
    supply_flag_deviation: float = 0.05  # relative deviation of any sample -> flag "supply"
    clip_g: float = 15.9  # |a| at or above: clipped (full scale 16 g)
    flat_fraction: float = 0.05  # share of repeated consecutive values -> flatline/dropout
    t0_tolerance_s: float = 0.05  # t0 against seq
    reorder_chunks: int = 5  # reorder window, chunks ...
    reorder_s: float = 5.0  # ... or event time past the missing chunk's start
    max_hold_s: float = 10.0  # longest wait for the GPS knot after a chunk
    dead_reckon_s: float = 3.0  # trust dead reckoning / knot spacing up to this
    # A chunk whose last sample is at most this far past the train's last knot goes out at
    # once, its tail dead-reckoned from that knot; 0: every chunk waits for a knot at or
    # after its last sample (up to max_hold_s).
    extrapolate_s: float = 2.0
    extrapolate_accel_max_mps2: float = 1.5  # bound on the acceleration dead reckoning uses
    correction_s: float = 2.0  # a later fix's correction of a published position: spread
    correction_ok_m: float = 5.0  # larger: not spread but jumped, and marked poor for a while
    hdop_max: float = 5.0
    lateral_ok_m: float = 15.0  # a fix farther from its line is a poor match
    switch_lateral_m: float = 25.0  # "clearly off the current line"
    switch_fixes: int = 3  # consecutive fixes off the line before a switch
    acquire_m: float = 15.0  # a line "fits" within this lateral distance ...
    ambiguity_m: float = 10.0  # ... and this much closer than any other line
    reverse_m: float = 12.0  # backwards movement that means a reversal, not jitter
    fuse_gain: float = 0.3  # weight of the projection against the speed prediction
    fuse_gate_m: float = 20.0  # projections farther from the prediction are taken as is
    search_m: float = 300.0  # projection window around the predicted chainage
    # A fix this long after the train's previous fix (a gateway that was off or away: every
    # fix is sent, fix_quality 0 without GNSS) starts map matching over, not a continuation.
    reacquire_s: float = 60.0
    knot_keep_s: float = 60.0  # knots kept behind the train's event time
    # Time plausibility ("the train's clock", module docstring): event times outside
    # [valid_t_min, valid_t_max) are refused, and so are those more than future_s ahead of
    # the receiving machine's clock; a fix or chunk more than max_ahead_s ahead of the
    # train's last fix and more than max_ahead_s behind the receiving clock is refused as a
    # clock jump, and rebase_fixes consecutive fixes at the new time (each within
    # rebase_gap_s of the one before) re-base the train there.
    valid_t_min: float = 946_684_800.0  # 2000-01-01T00:00:00Z
    valid_t_max: float = 4_102_444_800.0  # 2100-01-01T00:00:00Z
    future_s: float = 60.0  # a time this far ahead of the receiving clock is in the future
    max_ahead_s: float = 300.0
    rebase_fixes: int = 5
    rebase_gap_s: float = 10.0
    # Units: the mean of a vertical channel over a chunk is gravity, +1 g; beyond this many g
    # the samples are not in g (m/s^2 reads 9.81, counts read hundreds or thousands).
    vertical_max_g: float = 2.5

    @classmethod
    def from_dict(cls, raw: Mapping[str, Any]) -> IngestionConfig:
        names = {f.name for f in fields(cls)}
        unknown = set(raw) - names
        if unknown:
            raise ValueError(
                f"unknown ingestion settings {sorted(unknown)}; known: {sorted(names)}"
            )
        return cls(**raw)

    def expected_rate(self, train: str, unit: str) -> float:
        return float(self.rate_overrides.get(f"{train}/{unit}", self.rate_hz))
