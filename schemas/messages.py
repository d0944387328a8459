"""Every message of the key table (docs/architecture.md#key-expressions) as a versioned,
validated msgspec Struct.

Times are event times in UTC epoch seconds (float64) taken from the data; geometry is in
millimetres; the state ``mean``/``cov`` are in natural-log space z = [ln Top6_mm, ln Align10_mm].
Decoding runs ``__post_init__``, so a decoded message is a valid message.
"""

from __future__ import annotations

from typing import ClassVar, Literal

import msgspec

from schemas.wire import (
    _VALID_IDS,
    INT_MAX,
    T_MAX,
    T_MIN,
    NDArray,
    SchemaError,
    check,
    check_array,
    check_finite,
    check_id,
    check_int,
    check_range,
    check_time,
)

SCHEMA_VERSION = 1
INDICATORS = ("top6", "align10")  # state order, n = 2
ONBOARD_INDICES = ("top6", "align10")  # on-board index order, m = 2
ACCEL_CHANNELS = ("left_z", "left_y", "left_x", "right_z", "right_y", "right_x")
SUPPLY_CHANNEL = "supply_v"
DAY_S = 86_400.0  # seconds per day: degradation maths runs in days, epoch s / DAY_S
_ALL = list(INDICATORS)  # a message's default ``indicators``: every one

# Plausibility ranges (schemas/README.md, "Limits"): what a sender can be told at once.
INDEX_MAX_MM = 100.0  # Top6, Align10: (0, 100] mm; intervention limits are ~10 mm
SPEED_MAX_MPS = 150.0  # 540 km/h
RATE_MAX_HZ = 100_000.0
HDOP_MAX = 100.0
HORIZON_MAX_DAYS = 36_525.0  # 100 years
KIB = 1024


class Message(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """Base: the schema version ``v`` and its check.

    A field the type does not have is refused (``forbid_unknown_fields``): no message type's
    payload decodes as another's (an OnboardIndex carrying a ``run_id`` is not a TrcRecord),
    whatever key it came on. A new field therefore reaches receivers before senders send it
    (schemas/README.md, "Changing a message").
    """

    MAX_BYTES: ClassVar[int] = 4 * KIB  # payload size limit, checked before decoding
    IDS: ClassVar[tuple[str, ...]] = ()  # the fields that are key chunks, checked first

    v: int = SCHEMA_VERSION

    def __post_init__(self) -> None:
        if self.v != SCHEMA_VERSION:  # the message formatted only when it fails
            raise SchemaError(f"v: unknown schema version {self.v}")
        for name in self.IDS:
            check_id(name, getattr(self, name))


def _check_samples(msg: RawChunk | PositionedChunk) -> None:
    check_id("train", msg.train)
    check_id("unit", msg.unit)
    check_int("seq", msg.seq)
    check_time("t0", msg.t0)
    check_finite("rate_hz", msg.rate_hz, positive=True)
    check_range("rate_hz", msg.rate_hz, 0.0, RATE_MAX_HZ)
    check(len(msg.channels) > 0, "channels: empty")
    check(len(set(msg.channels)) == len(msg.channels), f"channels: duplicates in {msg.channels}")
    check_array("samples", msg.samples, (None, len(msg.channels)), kinds="fi")


class RawChunk(Message, frozen=True, kw_only=True):
    """About one second of bogie accelerometer samples from one on-board unit (gateway)."""

    # 1 s at 2000 Hz of the 7 channels in f8 is 112 kB: room for 4x that
    MAX_BYTES: ClassVar[int] = 512 * KIB
    train: str
    unit: str
    seq: int  # per (train, unit), +1 per chunk
    t0: float  # epoch s of the first sample
    rate_hz: float  # samples per second per channel (2000 on the reference unit)
    channels: list[str]  # column names, e.g. ACCEL_CHANNELS + (SUPPLY_CHANNEL,)
    samples: NDArray  # (n_samples, n_channels) f4/f8/i2; accelerations in g, supply in V

    def __post_init__(self) -> None:
        super().__post_init__()
        _check_samples(self)


class GpsFix(Message, frozen=True, kw_only=True):
    """One GPS fix of a train, 1 Hz."""

    IDS: ClassVar[tuple[str, ...]] = ("train",)
    train: str
    t: float  # epoch s
    lat_deg: float  # WGS84
    lon_deg: float  # WGS84
    speed_mps: float | None = None  # GPS ground speed
    fix_quality: int = 1  # 0 no fix, 1 GPS, 2 DGPS/RTK
    hdop: float | None = None

    def __post_init__(self) -> None:
        super().__post_init__()
        check_time("t", self.t)
        check_finite("lat_deg", self.lat_deg)
        check_finite("lon_deg", self.lon_deg)
        check(-90 <= self.lat_deg <= 90, f"lat_deg: {self.lat_deg} outside [-90, 90]")
        check(-180 <= self.lon_deg <= 180, f"lon_deg: {self.lon_deg} outside [-180, 180]")
        check_range("speed_mps", self.speed_mps, 0.0, SPEED_MAX_MPS)
        check_range("hdop", self.hdop, 0.0, HDOP_MAX)
        check(self.fix_quality in (0, 1, 2), f"fix_quality: {self.fix_quality} not 0, 1 or 2")


class PositionedChunk(Message, frozen=True, kw_only=True):
    """Cleaned samples of one unit with (t, line, chainage, speed) knots from map matching."""

    # a RawChunk's samples in f8 (up to 4x an i2 chunk at its limit) and the knots
    MAX_BYTES: ClassVar[int] = 4096 * KIB
    train: str
    unit: str
    seq: int
    t0: float
    rate_hz: float
    channels: list[str]
    samples: NDArray  # (n_samples, n_channels) f4/f8; accelerations in m/s^2, supply-corrected
    line: str
    knot_t: NDArray  # (k,) f8 epoch s, non-decreasing
    knot_chainage_m: NDArray  # (k,) f8 chainage along `line`
    knot_speed_mps: NDArray  # (k,) f8
    position_ok: bool  # False when the fix quality or map match is poor
    gap_before: bool = False  # samples are missing between the previous chunk and this one
    sensor_flags: list[str] = []  # health findings, e.g. "clipping", "flatline:left_z"

    def __post_init__(self) -> None:
        super().__post_init__()
        _check_samples(self)
        check_id("line", self.line)
        check_array("knot_t", self.knot_t, (None,))
        k = self.knot_t.shape[0]
        check(k >= 1, "knot_t: needs at least one knot")
        check_array("knot_chainage_m", self.knot_chainage_m, (k,))
        check_array("knot_speed_mps", self.knot_speed_mps, (k,))
        t = self.knot_t.array()
        check(bool((t[1:] >= t[:-1]).all()), "knot_t: must be non-decreasing")
        check_time("knot_t", float(t[0]))
        check_time("knot_t", float(t[-1]))
        v = self.knot_speed_mps.array()
        check(
            bool(((v >= 0) & (v <= SPEED_MAX_MPS)).all()),
            f"knot_speed_mps: values outside [0, {SPEED_MAX_MPS:g}]",
        )


class OnboardIndex(Message, frozen=True, kw_only=True):
    """On-board Top6 and Align10 indices of one train pass over one segment: both, or the
    ``indicators`` listed only (a unit with a vertical sensor only measures Top6)."""

    line: str
    segment: str
    train: str
    unit: str
    t: float  # epoch s at which the unit passed the segment's middle
    top6_mm: float | None = None  # > 0 when "top6" is listed, else None
    align10_mm: float | None = None  # > 0 when "align10" is listed, else None
    speed_mps: float  # mean speed over the segment
    coverage: float  # fraction of the segment's length with valid samples, [0, 1]
    quality: float = 1.0  # [0, 1], position and sensor health
    run_id: str = ""  # a TRC run id when the unit rode the TRC (calibration campaign)
    indicators: list[str] = msgspec.field(default_factory=lambda: list(INDICATORS))

    @property
    def values_mm(self) -> tuple[float | None, ...]:
        """The indices in state order (:data:`INDICATORS`), None for one not measured."""
        return (self.top6_mm, self.align10_mm)

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.top6_mm is None or self.align10_mm is None or self.indicators != _ALL:
            _check_measured(self)  # some indicators only: the values that are given
            standing_in = [1.0 if v is None else v for v in self.values_mm]  # checked above
            return self._check_fields(*standing_in)
        self._check_fields(self.top6_mm, self.align10_mm)

    def _check_fields(self, top6_mm: float, align10_mm: float) -> None:
        known = _VALID_IDS  # check_id's, inline: every index repeats ids that passed
        if not (
            self.line in known
            and self.segment in known
            and self.train in known
            and self.unit in known
        ):
            for name in ("line", "segment", "train", "unit"):
                check_id(name, getattr(self, name))
        if self.run_id:
            check_id("run_id", self.run_id)
        if (  # every number in range (so finite: NaN fails every comparison): done
            T_MIN <= self.t < T_MAX
            and 0.0 < top6_mm <= INDEX_MAX_MM
            and 0.0 < align10_mm <= INDEX_MAX_MM
            and 0.0 <= self.speed_mps <= SPEED_MAX_MPS
            and 0.0 <= self.coverage <= 1.0
            and 0.0 <= self.quality <= 1.0
        ):
            return
        check_time("t", self.t)  # which one is not, and why
        _check_index("top6_mm", top6_mm)
        _check_index("align10_mm", align10_mm)
        check_range("speed_mps", self.speed_mps, 0.0, SPEED_MAX_MPS)
        for name in ("coverage", "quality"):
            check_range(name, getattr(self, name), 0.0, 1.0)


def _check_index(name: str, value: float) -> None:
    check_finite(name, value, positive=True)
    check(value <= INDEX_MAX_MM, f"{name}: {value!r} outside (0, {INDEX_MAX_MM:g}] mm")


def _check_model_time(name: str, value: float) -> None:
    """A model's time: 0.0 for a prior (no data used yet), else an event time."""
    if value != 0.0:
        check_time(name, value)


class TrcRecord(Message, frozen=True, kw_only=True):
    """A Track Recording Car's measurement of one segment on one run: of every indicator,
    or of the ``indicators`` listed only (a car that records longitudinal level and not
    alignment). Exactly the listed indicators have a value."""

    IDS: ClassVar[tuple[str, ...]] = ("line", "segment", "run_id")
    line: str
    segment: str
    t: float  # epoch s
    top6_mm: float | None = None  # > 0 when "top6" is listed, else None
    align10_mm: float | None = None  # > 0 when "align10" is listed, else None
    run_id: str
    indicators: list[str] = msgspec.field(default_factory=lambda: list(INDICATORS))

    def __post_init__(self) -> None:
        super().__post_init__()
        check_time("t", self.t)
        _check_measured(self)

    @property
    def values_mm(self) -> tuple[float | None, ...]:
        """The values in state order (:data:`INDICATORS`), None for an indicator not measured."""
        return (self.top6_mm, self.align10_mm)


def _check_measured(msg: TrcRecord | OnboardIndex) -> None:
    """Exactly the ``indicators`` listed have a value, each in range."""
    _check_indicators(msg.indicators)
    for name, value in zip(INDICATORS, msg.values_mm, strict=True):
        if name in msg.indicators:
            check(value is not None, f"{name}_mm: missing, and {name} is in indicators")
            _check_index(f"{name}_mm", value)
        else:
            check(value is None, f"{name}_mm: given, and {name} is not in indicators")


def _check_indicators(indicators: list[str]) -> None:
    """A non-empty list of state indicators in state order, each once."""
    check(
        bool(indicators) and indicators == [i for i in INDICATORS if i in indicators],
        f"indicators: {indicators!r} is not a non-empty list of {list(INDICATORS)} in that order",
    )


class MaintenanceEvent(Message, frozen=True, kw_only=True):
    """Tamping of a segment at a known time (t_start == t_end) or within an interval."""

    IDS: ClassVar[tuple[str, ...]] = ("line", "segment", "event_id")
    line: str
    segment: str
    event_id: str
    kind: Literal["tamping"] = "tamping"
    t_start: float  # epoch s
    t_end: float  # epoch s, >= t_start
    revision: int = 0  # a correction of the same event_id carries a higher revision
    detected: bool = False  # found by filtering in the on-board data, not reported by a feed
    # a detected tamping filtering no longer finds: the detection of this event_id is void
    # unless one of a higher rank (a higher revision) holds it again
    withdrawn: bool = False

    def __post_init__(self) -> None:
        super().__post_init__()
        check_time("t_start", self.t_start)
        check_time("t_end", self.t_end)
        check_int("revision", self.revision)
        check(self.t_end >= self.t_start, f"t_end: {self.t_end} before t_start {self.t_start}")
        check(self.detected or not self.withdrawn, "withdrawn: only a detected tamping is")

    @property
    def rank(self) -> tuple[int, bool, float, float, float]:
        """Which of two reports of one ``event_id`` holds: the higher rank. A higher
        ``revision`` first (an explicit correction; filtering numbers its detections and
        withdrawals so), then a withdrawal over a detection, then the narrower interval (a
        known time is an interval of width 0, so it replaces an interval-only report), then
        the later ``(t_start, t_end)``. Equal ranks are the same report; the one held
        therefore does not depend on which arrived first, and a withdrawal held makes the
        ``event_id`` no tamping."""
        width = self.t_end - self.t_start
        return (self.revision, self.withdrawn, -width, self.t_start, self.t_end)


class Calibration(Message, frozen=True, kw_only=True):
    """Observation model y = H z + b + e, e ~ N(0, R) (paper Eq. 3-6) with diagnostics."""

    MAX_BYTES: ClassVar[int] = 16 * KIB
    version: int  # >= 1, increases with every accepted refit
    t: float  # event time of the newest pair used
    indicators: list[str]  # state names, n
    indices: list[str]  # on-board index names, m
    H: NDArray  # (m, n) f8
    b: NDArray  # (m,) f8
    R: NDArray  # (m, m) f8, symmetric positive definite
    n_pairs: int
    r2: NDArray  # (m,) f8, coefficient of determination per index
    # The on-board unit this model is of (its indices' train and unit ids); both empty: the
    # fleet's model, used for every unit without a model of its own.
    train: str = ""
    unit: str = ""

    def __post_init__(self) -> None:
        super().__post_init__()
        check_int("version", self.version, 1, INT_MAX)
        _check_model_time("t", self.t)
        check(bool(self.train) == bool(self.unit), "train/unit: both given or both empty")
        if self.train:
            check_id("train", self.train)
            check_id("unit", self.unit)
        n, m = len(self.indicators), len(self.indices)
        check(n > 0 and m > 0, "indicators/indices: must not be empty")
        check_array("H", self.H, (m, n))
        check_array("b", self.b, (m,))
        check_array("R", self.R, (m, m))
        check_array("r2", self.r2, (m,))
        check_int("n_pairs", self.n_pairs, 1, INT_MAX)


class DegradationPosterior(Message, frozen=True, kw_only=True):
    """Ns posterior samples of the degradation parameters of one group (paper Eq. 2, 13)."""

    # Ns = 1000 samples of n = 2 indicators are 96 kB: room for Ns = 5000, or n = 5 at 1000
    MAX_BYTES: ClassVar[int] = 512 * KIB
    IDS: ClassVar[tuple[str, ...]] = ("group",)
    group: str  # e.g. "class-fast", "line-L1", "L1.s0042"
    version: int
    t: float  # event time of the newest TRC record used
    indicators: list[str]
    mu: NDArray  # (Ns, n) f8, drift of z per day
    sigma: NDArray  # (Ns, n, n) f8, diffusion of z per day
    z_plus: NDArray  # (Ns, n) f8, mean z right after tamping
    sigma_z_plus: NDArray  # (Ns, n, n) f8
    n_increments: int  # TRC increments that did not span a tamping (of the indicator used, when
    # the group's records measured one indicator only)
    n_levels: int  # post-tamping levels

    def __post_init__(self) -> None:
        super().__post_init__()
        check_int("version", self.version, 1, INT_MAX)
        _check_model_time("t", self.t)
        check_int("n_increments", self.n_increments)
        check_int("n_levels", self.n_levels)
        n = len(self.indicators)
        check(n > 0, "indicators: must not be empty")
        check_array("mu", self.mu, (None, n))
        ns = self.mu.shape[0]
        check(ns > 0, "mu: needs at least one sample")
        check_array("sigma", self.sigma, (ns, n, n))
        check_array("z_plus", self.z_plus, (ns, n))
        check_array("sigma_z_plus", self.sigma_z_plus, (ns, n, n))


class SegmentState(Message, frozen=True, kw_only=True):
    """The filter's mixture summary of one segment after an event (paper Eq. 13-14)."""

    MAX_BYTES: ClassVar[int] = 64 * KIB
    line: str
    segment: str
    t: float  # event time of the state
    indicators: list[str]
    mean: NDArray  # (n,) f8, mixture mean of z (log mm)
    cov: NDArray  # (n, n) f8, total mixture covariance of z
    ci_low_mm: NDArray  # (n,) f8, 2.5% marginal quantile
    ci_high_mm: NDArray  # (n,) f8, 97.5% marginal quantile
    width: float  # W = |cov|^(1/n)
    limit_levels: list[str]  # L names, e.g. ["alert", "intervention"]
    limits_mm: NDArray  # (L, n) f8, the limits p_exceed refers to
    p_exceed: NDArray  # (L, n) f8, P(indicator > limit) now
    horizons_days: NDArray  # (h,) f8
    forecast_mean: NDArray  # (h, n) f8 log mm
    forecast_ci_low_mm: NDArray  # (h, n) f8
    forecast_ci_high_mm: NDArray  # (h, n) f8
    forecast_p_exceed: NDArray  # (h, L, n) f8
    last_trc_t: float | None = None  # epoch s of the restart, None before any TRC record
    n_updates: int = 0  # on-board updates since the last TRC record
    nis: float | None = None  # normalised innovation squared of the last update
    calibration_version: int = 0
    posterior_version: int = 0
    posterior_group: str = ""  # the DegradationPosterior group in use
    # the indicators the last TRC record measured (the others evolved from their own state);
    # empty before any TRC record
    last_trc_indicators: list[str] = []
    # (Ns,) f4: log w_j - max_j log w_j, the mixture weight of each sample j of the group's
    # posterior from the segment's own on-board data since its last TRC record (the filter's
    # departure from Eq. 13's equal weights); None: equal weights
    log_weights: NDArray | None = None

    def __post_init__(self) -> None:
        super().__post_init__()
        self.check_scalars()
        if self.log_weights is not None:
            check_array("log_weights", self.log_weights, (None,))
            lw = self.log_weights.array()
            check(lw.size > 0 and bool((lw <= 0).all()), "log_weights: must be <= 0, not empty")
        n, levels = len(self.indicators), len(self.limit_levels)
        check(n > 0, "indicators: must not be empty")
        for name in ("mean", "ci_low_mm", "ci_high_mm"):
            check_array(name, getattr(self, name), (n,))
        check_array("cov", self.cov, (n, n))
        check_array("limits_mm", self.limits_mm, (levels, n))
        check_array("p_exceed", self.p_exceed, (levels, n))
        check_array("horizons_days", self.horizons_days, (None,))
        h = self.horizons_days.shape[0]
        for name in ("forecast_mean", "forecast_ci_low_mm", "forecast_ci_high_mm"):
            check_array(name, getattr(self, name), (h, n))
        check_array("forecast_p_exceed", self.forecast_p_exceed, (h, levels, n))
        for name in ("p_exceed", "forecast_p_exceed"):
            p = getattr(self, name).array()
            check(bool(((p >= 0) & (p <= 1)).all()), f"{name}: probabilities outside [0, 1]")

    def check_scalars(self) -> None:
        """The checks of the fields that are not arrays (the ids, times, numbers): what a
        producer runs on a state copied from a checked one whose arrays it checked at once
        for a whole batch (``schemas.wire.unchecked_copy``)."""
        check_id("line", self.line)
        check_id("segment", self.segment)
        if self.posterior_group:
            check_id("posterior_group", self.posterior_group)
        check_time("t", self.t)
        check_finite("width", self.width)
        check(self.width >= 0, f"width: must be >= 0, got {self.width!r}")
        check_time("last_trc_t", self.last_trc_t)
        check_finite("nis", self.nis)
        check_int("n_updates", self.n_updates)
        check_int("calibration_version", self.calibration_version)
        check_int("posterior_version", self.posterior_version)
        if self.last_trc_indicators:
            _check_indicators(self.last_trc_indicators)


class Alert(Message, frozen=True, kw_only=True):
    """An alert raised or cleared for one segment."""

    MAX_BYTES: ClassVar[int] = 16 * KIB
    IDS: ClassVar[tuple[str, ...]] = ("line", "segment")
    line: str
    segment: str
    t: float  # event time
    kind: Literal[
        "exceedance", "predicted_exceedance", "sudden_change", "stale", "detected_maintenance"
    ]
    status: Literal["raised", "cleared"]
    indicator: str  # "top6", "align10" or "" when not about one indicator
    level: str = ""  # "alert" or "intervention" for exceedance kinds
    probability: float = 0.0  # [0, 1]
    horizon_days: float | None = None  # predicted_exceedance only
    message: str = ""
    speed_class: str = ""  # the speed class whose limit `level` is; "" for other kinds

    def __post_init__(self) -> None:
        super().__post_init__()
        check_time("t", self.t)
        check_range("probability", self.probability, 0.0, 1.0)
        check_range("horizon_days", self.horizon_days, 0.0, HORIZON_MAX_DAYS)


class DeadLetter(Message, frozen=True, kw_only=True):
    """A rejected payload: where it came from and why it was refused."""

    MAX_BYTES: ClassVar[int] = 64 * KIB
    IDS: ClassVar[tuple[str, ...]] = ("service",)
    service: str
    key: str
    reason: str
    payload_head: bytes  # first bytes of the payload (at most 256)
    received_at: float  # wall-clock epoch s of the rejection (the payload has no trusted time)

    def __post_init__(self) -> None:
        super().__post_init__()
        check(bool(self.reason), "reason: must not be empty")
        check_finite("received_at", self.received_at)


class ServiceHealth(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """One process of ``trackfusion up`` in a :class:`StackHealth` report."""

    name: str  # the stack file's process name
    state: str  # starting, running, stopping, waiting, exited, finished or failed
    alive: bool  # its liveliness token is present
    restarts: int
    last_restart_reason: str = ""
    pid: int | None = None
    uptime_s: float | None = None  # of the current run, wall s


class StackHealth(Message, frozen=True, kw_only=True):
    """What ``trackfusion up`` sees each second: its processes, stalled flows, counts."""

    MAX_BYTES: ClassVar[int] = 64 * KIB
    written_at: float  # wall-clock epoch s of the report (not an event time)
    processes: list[ServiceHealth]
    stalled: list[str]  # one sentence per stalled flow, e.g. "index arriving but no state …"
    counts: dict[str, int]  # messages seen on the bus since `up` started, per key kind
    healthy: bool
    viewer_url: str = ""

    def __post_init__(self) -> None:
        super().__post_init__()
        check_finite("written_at", self.written_at)
        for process in self.processes:
            check_id("process name", process.name)
            check_int("restarts", process.restarts)
        for kind, count in self.counts.items():
            check_id("counts key", kind)
            check_int(f"counts[{kind}]", count)


class ViewerSelect(Message, frozen=True, kw_only=True):
    """Pin one segment into the viewer's "selected segment" plots."""

    IDS: ClassVar[tuple[str, ...]] = ("line", "segment")
    line: str
    segment: str


class RaisedAlerts(Message, frozen=True, kw_only=True):
    """The reply of ``{ns}/q/alerts``: the raised alerts (their ``raised`` messages), by line,
    segment, kind, indicator and level; empty when nothing is raised."""

    MAX_BYTES: ClassVar[int] = 64 * KIB * KIB  # 100,000 segments with a few ~300-byte alerts each
    alerts: list[Alert]

    def __post_init__(self) -> None:
        super().__post_init__()
        for alert in self.alerts:
            check(alert.status == "raised", f"alerts: {alert.line}/{alert.segment} is cleared")


class PlanRow(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """One segment of an :class:`InspectionPlan`."""

    line: str
    segment: str
    probability: float  # P(exceeding `level` before next_trc_t), max over indicators
    indicator: str  # the indicator giving it
    level: str  # the limit level, e.g. "intervention"
    limit_mm: float  # that limit on this line
    next_trc_t: float  # epoch s, expected next TRC run of the line
    horizon_days: float  # next_trc_t - state_t, >= 0
    p_now: float  # P(indicator > limit) at state_t
    state_t: float  # event time of the state the row is computed from
    estimate_mm: float  # exp(mixture mean of ln mm): the median estimate
    ci_low_mm: float  # 95 % credible interval at state_t
    ci_high_mm: float
    speed_class: str = ""  # the line's speed class `limit_mm` belongs to

    def __post_init__(self) -> None:
        check_id("line", self.line)
        check_id("segment", self.segment)
        for name in ("probability", "p_now"):
            check_range(name, getattr(self, name), 0.0, 1.0)
        check_finite("limit_mm", self.limit_mm, positive=True)
        check_time("next_trc_t", self.next_trc_t)
        check_time("state_t", self.state_t)
        check_range("horizon_days", self.horizon_days, 0.0, HORIZON_MAX_DAYS)
        for name in ("estimate_mm", "ci_low_mm", "ci_high_mm"):
            check_finite(name, getattr(self, name))


class InspectionPlan(Message, frozen=True, kw_only=True):
    """The reply of ``{ns}/q/plan``: which segments the next TRC runs should inspect first."""

    MAX_BYTES: ClassVar[int] = 64 * KIB * KIB  # a row is ~300 bytes: 100,000 segments fit
    t: float | None  # newest event time the plan is computed at; None before any state
    rows: list[PlanRow]  # highest probability first (ties by line, segment)

    def __post_init__(self) -> None:
        super().__post_init__()
        check_time("t", self.t)


class PlannedTamping(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """One segment of a :class:`MaintenancePlan`: tamped in a week, or not tamped although
    its risk limit is not met (capacity, budget or the minimum interval prevent it)."""

    line: str
    segment: str
    week: int  # 0-based week of the horizon it is tamped in; -1: not tamped in the horizon
    worksite: int  # possession id: one per run of adjacent segments tamped in one week; -1
    length_km: float
    deadline_week: int  # last week whose tamping meets the risk limit; -1: none does;
    # horizon_weeks: the limit holds over the horizon without a tamping
    p_reach_ial: float  # P(reaching the immediate-action limit before the tamping, or before
    # the horizon's end when not tamped)
    risk_met: bool  # p_reach_ial <= the plan's eps
    cost: float  # expected cost of the segment under the plan
    cost_untamped: float  # expected cost of not tamping it in the horizon
    speed_class: str = ""  # the line's speed class (services/defaults/limits.json5)

    def __post_init__(self) -> None:
        check_id("line", self.line)
        check_id("segment", self.segment)
        check_int("week", self.week, -1, 1000)
        check_int("worksite", self.worksite, -1, INT_MAX)
        check_int("deadline_week", self.deadline_week, -1, 1000)
        check_finite("length_km", self.length_km, positive=True)
        check_range("p_reach_ial", self.p_reach_ial, 0.0, 1.0)
        check_finite("cost", self.cost)
        check_finite("cost_untamped", self.cost_untamped)


class TrcRunValue(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """One line of a :class:`MaintenancePlan`'s TRC ranking: what a run of it now is worth."""

    line: str
    value: float  # expected fall of the plan's cost from the run's information, >= 0
    segments: int  # segments of the line the value is summed over

    def __post_init__(self) -> None:
        check_id("line", self.line)
        check_finite("value", self.value)
        check(self.value >= 0, f"value: must be >= 0, got {self.value!r}")
        check_int("segments", self.segments)


class MaintenancePlan(Message, frozen=True, kw_only=True):
    """The tamping plan: published on ``{ns}/plan/maintenance`` after every re-plan and the
    reply of ``{ns}/q/plan/maintenance``."""

    MAX_BYTES: ClassVar[int] = 64 * KIB * KIB  # a row is ~200 bytes: 100,000 segments fit
    t: float | None  # epoch s of the start of week 0 (a Monday 00:00 UTC); None: no data yet
    computed_at: float | None  # the event time the plan was made at (newest state time)
    horizon_weeks: int
    eps: float  # the risk limit
    # "optimal", "within_gap" (cost within target_gap of the bound), "gap_above_target",
    # or "no_data" (no segment with a state and a model)
    status: Literal["optimal", "within_gap", "gap_above_target", "no_data"]
    objective: float  # expected cost of the plan over the horizon
    bound: float  # a lower bound of the optimum
    gap: float  # (objective - bound) / objective over the segments the optimisation decided
    solve_s: float  # wall time of the optimisation (not an event time)
    km_per_week: list[float]  # km tamped in each week
    possessions: int
    money: float  # tamping and possession money of the plan
    budget: float | None  # the budget it was made under; None: none
    segments: int  # segments planned (with a state and a degradation model)
    without_model: int  # segments with a state but no posterior of their group yet
    version: int = 0  # counts the plans a planner instance made
    rows: list[PlannedTamping]  # by week (not tamped last), line, segment
    trc_lines: list[TrcRunValue] = []  # lines by the value of a TRC run now, highest first

    def __post_init__(self) -> None:
        super().__post_init__()
        check_time("t", self.t)
        check_time("computed_at", self.computed_at)
        check_int("horizon_weeks", self.horizon_weeks, 1, 1000)
        check_range("eps", self.eps, 0.0, 1.0)
        for name in ("objective", "bound", "solve_s", "money"):
            check_finite(name, getattr(self, name))
        check(self.gap >= 0 and self.gap == self.gap, f"gap: must be >= 0, got {self.gap!r}")
        check_finite("budget", self.budget)
        check(
            len(self.km_per_week) in (0, self.horizon_weeks),
            f"km_per_week: {len(self.km_per_week)} values for {self.horizon_weeks} weeks",
        )
        for name in ("possessions", "segments", "without_model", "version"):
            check_int(name, getattr(self, name))
        for row in self.rows:
            check(row.week < self.horizon_weeks, f"rows: {row.segment} week {row.week} beyond")


ALL_MESSAGES: tuple[type[Message], ...] = (
    RawChunk,
    GpsFix,
    PositionedChunk,
    OnboardIndex,
    TrcRecord,
    MaintenanceEvent,
    Calibration,
    DegradationPosterior,
    SegmentState,
    Alert,
    DeadLetter,
    StackHealth,
    ViewerSelect,
    RaisedAlerts,
    InspectionPlan,
    MaintenancePlan,
)
