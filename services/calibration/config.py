"""Settings of the calibration core (``services.calibration`` section of the config file)."""

from __future__ import annotations

from dataclasses import dataclass

from schemas import INDICATORS
from services.drift_diffusion import NIWPrior

_N = len(INDICATORS)


@dataclass(frozen=True)
class CalibratorConfig:
    """Settings of :class:`~services.calibration.calibrator.Calibrator` (each module's
    docstring says what the ones it uses rule)."""

    min_pairs: int = 30  # pairs before the first fit
    refit_every: int = 10  # new pairs between fit attempts
    tolerance_days: float | None = 1.0  # time pairing of indices without run_id; None: off
    index_window_days: float = 30.0  # an unpaired index waits this long (segment's TRC time)
    max_pending_per_segment: int = 500  # unpaired indices kept per segment (newest by t)
    min_quality: float = 0.5  # indices below are not used for calibration
    min_coverage: float = 0.5
    max_r2_drop: float = 0.10  # swap rule 1
    max_loglik_drop: float = 0.25  # swap rule 2, nats per pair
    segment_min_increments: int = 6  # k: a segment gets its own posterior group
    min_increments: int = _N + 2  # pooled groups (line, net)
    min_levels: int = _N + 2  # post-tamping levels for (z+, Σz+) from data
    max_level_age_days: float | None = 120.0  # older post-tamping levels are not used
    samples: int = 200  # Ns
    seed: int = 0
    material_se: float = 1.0  # publication rule: a change is material beyond this many SEs
    min_publish_interval_days: float = 1.0  # event time between two versions of one model
    # robustness (robust.py)
    max_rate_per_day: float = 1.0 / 30.0  # hard bound on |dz|/dt between records, ln mm/day
    max_jump: float = 0.5  # ... plus this much, ln mm (diffusion and TRC noise over short dt)
    robust_k: float = 8.0  # outliers: beyond this many robust sd (1.4826 MAD)
    robust_min_count: int = 20  # samples before a median/MAD reference is used
    max_move_sd: float = 8.0  # a pooled posterior moved beyond this (sd of the one in force)
    event_time_quorum: int = 3  # event time: the newest time this many segments have reached
    max_ahead_days: float = 180.0  # TRC records later than event time + this: left out for now
    # per-unit observation models (units.py): shrunk towards the fleet's by this many pairs
    unit_models: bool = True
    unit_min_pairs: int = 5  # a unit's pairs before its first own model
    unit_shrink_pairs: float = 20.0
    drift_prior: NIWPrior | None = None  # None: NIWPrior.default_drift
    level_prior: NIWPrior | None = None  # None: NIWPrior.default_level

    def __post_init__(self) -> None:
        if self.min_pairs < 1 or self.refit_every < 1:
            raise ValueError(
                f"min_pairs and refit_every must be >= 1, got {self.min_pairs}, {self.refit_every}"
            )
        if self.tolerance_days is not None and not self.tolerance_days >= 0:
            raise ValueError(f"tolerance_days: must be >= 0 or None, got {self.tolerance_days}")
        if not self.index_window_days >= 0:
            raise ValueError(f"index_window_days: must be >= 0, got {self.index_window_days}")
        if self.samples < 1:
            raise ValueError(f"samples: must be >= 1, got {self.samples}")
        if self.seed < 0:
            raise ValueError(f"seed: must be >= 0, got {self.seed}")
        if self.segment_min_increments < 1 or self.min_increments < 1 or self.min_levels < 1:
            raise ValueError("segment_min_increments, min_increments, min_levels must be >= 1")
        if not (
            self.max_rate_per_day > 0
            and self.max_jump >= 0
            and self.robust_k > 0
            and self.max_move_sd > 0
            and self.max_ahead_days >= 0
        ):
            raise ValueError(
                "max_rate_per_day, robust_k, max_move_sd must be > 0, max_jump and "
                "max_ahead_days >= 0"
            )
        if self.event_time_quorum < 1 or self.robust_min_count < 3:
            raise ValueError("event_time_quorum must be >= 1 and robust_min_count >= 3")
        if not self.material_se >= 0 or not self.min_publish_interval_days >= 0:
            raise ValueError(
                "material_se and min_publish_interval_days: must be >= 0, got "
                f"{self.material_se}, {self.min_publish_interval_days}"
            )
