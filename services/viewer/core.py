"""The viewer's pure core: TrackFusion messages in, Rerun log calls out.

No Zenoh, no clock, no sink: :class:`ViewerCore` logs to the ``rerun.RecordingStream`` it
is given, and the adapter (``service.py``) decides where that stream goes (native viewer,
web viewer, ``.rrd`` file) and passes wall time in where the rate limits need it.

Time: every temporal row is stamped on the timeline :data:`TIMELINE` (``"event_time"``),
a timestamp timeline holding each message's own event time ``t`` (UTC epoch seconds), so
late or replayed messages land where they belong.

One blueprint, sent once at start: a browser that connects late replays every blueprint
ever sent (about 0.8 s each on a software renderer), so the layout never changes. Its plot
rows are fixed **slots** (``worst/1`` … ``worst/N``, ``selected``) that the core fills: each
time a slot shows another segment, the segment's kept history goes to a new **generation**
of entities under the slot (``{slot}/{ind}/g{n}/…``, every row carrying its series style)
and the previous generation is hidden by a static ``visible_series = false`` (a time series
plot draws every row in its window whatever Clear says, so one entity cannot be re-used for
another segment).

Volume: the core keeps, per segment and event-day, the newest state and on-board index
(:data:`HISTORY_DAYS` days) and every TRC record, compactly; it writes the slots' new rows
every ``plot_flush_s`` wall seconds (one chunk per entity) and the map colours, trains,
alerts and health every ``live_flush_s``. Segments not in a slot are not written: an
operator pins one with ``trackfusion viewer select`` (services/viewer/README.md).

The planner's MaintenancePlan: the possessions of its first :data:`PLAN_WEEKS` weeks are
drawn on the map (``map/plan/tamping``) at the plan's event time, replaced by each newer plan.

Entity paths, styles, the blueprint and the static map: :mod:`services.viewer.scene`.
"""

from __future__ import annotations

import heapq
import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
import rerun as rr

from schemas import (
    DAY_S,
    INDICATORS,
    Alert,
    GpsFix,
    MaintenancePlan,
    Message,
    OnboardIndex,
    SegmentState,
    StackHealth,
    TrcRecord,
    ViewerSelect,
)
from schemas.keys import SegmentId
from services.viewer.scene import (
    DRAW_ORDER,
    HEALTH_PATH,
    MAP_PATH,
    RANKING_PATH,
    SELECTED,
    TIMELINE,
    UNKNOWN_RGB,
    build_blueprint,
    exceedance_color,
    health_markdown,
    log_static_map,
    plan_strips,
    screen_xy,
    slot_names,
    style_columns,
)
from track.network import Network

INTERVENTION = "intervention"  # the limit level the map colour and the worst ranking use
DEFAULT_WORST_N = 3
WORST_MARGIN = 0.25  # a segment replaces a plotted one if its p is higher by more than this
DEFAULT_PLOT_FLUSH_S = 30.0  # wall seconds between two writes of the slots' rows
DEFAULT_LIVE_FLUSH_S = 5.0  # wall seconds between two writes of map colours, alerts, trains
HISTORY_DAYS = 365  # event days of states and on-board indices kept per segment
STACK_REPORT_STALE_S = 5.0  # wall s without a StackHealth: `up` is taken as gone
PLAN_WEEKS = 8  # weeks of the plan, from its week 0, whose tampings the map shows


def segment_exceedance(state: SegmentState) -> float:
    """P(exceeding the intervention limit), max over indicators (the last level if the state
    has no ``intervention`` level; 0 without levels)."""
    p = state.p_exceed.array()
    if p.size == 0:
        return 0.0
    levels = state.limit_levels
    row = levels.index(INTERVENTION) if INTERVENTION in levels else len(levels) - 1
    return float(p[row].max())


def select_worst(p_exceed: Mapping[SegmentId, float], n: int) -> list[SegmentId]:
    """The ``n`` segments with the highest probability, highest first; ties by (line, segment)."""
    return [key for _, key in heapq.nsmallest(n, ((-p, key) for key, p in p_exceed.items()))]


def select_worst_sticky(
    p_exceed: Mapping[SegmentId, float],
    n: int,
    shown: Sequence[SegmentId],
    margin: float,
) -> list[SegmentId]:
    """Like :func:`select_worst`, but a segment already ``shown`` keeps its place unless
    one not shown has a probability more than ``min(margin, p / 2)`` above its ``p``:
    near-ties (many segments close to p = 1) do not swap the plots back and forth, while a
    plotted segment whose p fell (tamped: p = 0) gives way to any worse one. Highest
    first."""
    best = select_worst(p_exceed, n)
    kept = [key for key in shown if key in p_exceed][:n]
    for candidate in best:
        if candidate in kept:
            continue
        if len(kept) < n:
            kept.append(candidate)
            continue
        weakest = min(kept, key=lambda key: (p_exceed[key], key))
        p_weakest = p_exceed[weakest]
        if p_exceed[candidate] > p_weakest + min(margin, p_weakest / 2):
            kept[kept.index(weakest)] = candidate
    return sorted(kept, key=lambda key: (-p_exceed[key], key))


def planned_possessions(plan: MaintenancePlan, weeks: int) -> list[tuple[int, str, list[str]]]:
    """``(week, line, segment ids)`` of each possession tamped in the plan's first ``weeks``
    weeks, by week, line and first segment; the segments in the plan's order."""
    sites: dict[int, tuple[int, str, list[str]]] = {}
    for row in plan.rows:
        if 0 <= row.week < weeks:
            sites.setdefault(row.worksite, (row.week, row.line, []))[2].append(row.segment)
    return sorted(sites.values(), key=lambda site: (site[0], site[1], site[2][0]))


def message_version(msg: Message) -> float:
    """The event time that orders two messages of one :func:`coalesce_key`: a plan's
    ``computed_at``, else ``t``."""
    t = msg.computed_at if isinstance(msg, MaintenancePlan) else msg.t
    return -math.inf if t is None else t


def event_day(t: float) -> int:
    """The UTC day (days since the epoch) of an event time in epoch seconds."""
    return math.floor(t / DAY_S)


def coalesce_key(msg: Message) -> tuple[str, ...] | None:
    """What a newer message of the same key supersedes before it is written (the thinning
    rule of the series, the trains and the latest-only inputs); None for messages that are
    all kept (alerts, TRC records)."""
    match msg:
        case SegmentState() | OnboardIndex():
            kind = "state" if isinstance(msg, SegmentState) else "onboard"
            return (kind, msg.line, msg.segment, str(event_day(msg.t)))
        case GpsFix():
            return ("gps", msg.train)
        case StackHealth():
            return ("health",)
        case ViewerSelect():
            return ("select",)
        case MaintenancePlan():
            return ("plan",)
    return None


@dataclass
class _Map:
    keys: list[SegmentId]  # strip order: the network's lines, each in chainage order
    index: dict[SegmentId, int]  # segment -> strip
    colors: np.ndarray  # (k, 3) uint8, the current colours
    changed_t: float | None = None  # newest event time of a colour change not yet logged


class _Days:
    """The newest row per event-day of one kind of one segment, for the last
    :data:`HISTORY_DAYS` days: a ring of numpy rows indexed by day (a few tens of kB per
    segment, whatever the run length)."""

    def __init__(self, width: int) -> None:
        self.day = np.full(HISTORY_DAYS, -1, np.int64)
        self.t = np.full(HISTORY_DAYS, -np.inf)
        self.values = np.full((HISTORY_DAYS, len(INDICATORS), width), np.nan)
        self.levels: list[tuple[str, ...]] = [()] * HISTORY_DAYS

    def put(self, t: float, values: np.ndarray, levels: tuple[str, ...] = ()) -> None:
        day = event_day(t)
        i = day % HISTORY_DAYS
        if self.day[i] > day or (self.day[i] == day and self.t[i] > t):
            return  # older than the day held there, or than that day's newest
        self.day[i], self.t[i], self.levels[i] = day, t, levels
        self.values[i] = np.nan
        self.values[i, :, : values.shape[1]] = values

    def rows(self, after: float) -> list[tuple[float, tuple[str, ...], np.ndarray]]:
        """``(t, levels, values)`` newer than ``after``, oldest first; ``values`` has one
        row per indicator (NaN where the message lacked it)."""
        (index,) = np.nonzero((self.day >= 0) & (self.t > after))
        index = index[np.argsort(self.t[index])]
        return [(float(self.t[i]), self.levels[i], self.values[i]) for i in index]


MAX_LEVELS = 4  # limit levels a state row keeps (the demo has 2: alert, intervention)
_LEVELS: dict[tuple[str, ...], tuple[str, ...]] = {}  # one tuple per distinct level list


@dataclass
class _History:
    """What the core keeps of one segment: per event-day the newest state row and on-board
    index, and every TRC record of the last :data:`HISTORY_DAYS` days."""

    states: _Days = field(default_factory=lambda: _Days(3 + MAX_LEVELS))
    onboard: _Days = field(default_factory=lambda: _Days(1))
    trc: list[tuple[float, np.ndarray]] = field(default_factory=list)

    def rows(self, kind: str, after: float) -> list[tuple[float, tuple[str, ...], np.ndarray]]:
        """``(t, levels, values)`` of ``kind`` newer than ``after``, oldest first; a state's
        values are cut to its own levels."""
        if kind == "state":
            return [(t, lv, v[:, : 3 + len(lv)]) for t, lv, v in self.states.rows(after)]
        if kind == "onboard":
            return [(t, lv, v[:, 0]) for t, lv, v in self.onboard.rows(after)]
        return sorted(((t, (), v) for t, v in self.trc if t > after), key=lambda row: row[0])

    def add_trc(self, t: float, values: np.ndarray) -> None:
        self.trc.append((t, values))
        if len(self.trc) > 64:  # amortised: drop what is older than the kept days
            newest = max(t for t, _ in self.trc)
            self.trc = [(t, v) for t, v in self.trc if t > newest - HISTORY_DAYS * DAY_S]


@dataclass
class _Slot:
    """One plot row of the blueprint: the segment it shows and the generation of entities
    that holds that segment's rows."""

    name: str  # "worst/1" … or "selected"
    key: SegmentId | None = None
    generation: int = 0
    written: dict[str, float] = field(default_factory=dict)  # kind -> newest t written
    styled: dict[str, tuple[str, ...]] = field(default_factory=dict)  # entity -> levels

    def path(self, indicator: str, kind: str) -> str:
        return f"{self.name}/{indicator}/g{self.generation}/{kind}"


class ViewerCore:
    """Logs TrackFusion messages to ``rec``; one instance per recording, one thread.

    :meth:`take` buffers and thins (no Rerun call), :meth:`flush` writes what is due at
    wall time ``now``; :meth:`log_batch` does both and writes everything at once.

    Parameters
    ----------
    rec
        Where the log calls go.
    network
        The map; states, indices and TRC records of lines not in it are still kept and
        plotted.
    worst_n
        Plot rows of the worst segments (a row for the selected segment comes below).
    plot_flush_s, live_flush_s
        Wall seconds between two writes of the plots' rows, and of the map colours,
        alerts, trains and health.
    """

    def __init__(
        self,
        rec: rr.RecordingStream,
        network: Network | None = None,
        *,
        worst_n: int = DEFAULT_WORST_N,
        plot_flush_s: float = DEFAULT_PLOT_FLUSH_S,
        live_flush_s: float = DEFAULT_LIVE_FLUSH_S,
    ) -> None:
        if worst_n < 0:
            raise ValueError(f"worst_n: must be >= 0, got {worst_n}")
        if min(plot_flush_s, live_flush_s) < 0:
            raise ValueError("plot_flush_s, live_flush_s: must be >= 0")
        self.rec = rec
        self.network = network
        self.line_names = (
            {}
            if network is None
            else {line.id: line.name for line in network.lines.values() if line.name}
        )
        self.worst_n = worst_n
        self.plot_flush_s = plot_flush_s
        self.live_flush_s = live_flush_s
        self.p_exceed: dict[SegmentId, float] = {}
        self.last_trc: dict[SegmentId, tuple[str, ...]] = {}  # indicators the last TRC measured
        self.handled = 0  # messages taken (GPS fixes without a fix included)
        self.rows_written = 0  # rows of the plots' entities written
        self.blueprints_sent = 0
        self.generations = 0  # plot generations started (a slot showing another segment)
        self._newest_t: dict[SegmentId, float] = {}
        self._newest_event_t: float | None = None
        self._history: dict[SegmentId, _History] = {}
        self._slots = [_Slot(name) for name in slot_names(worst_n)]
        self._selected: SegmentId | None = None
        self._map: _Map | None = None
        self._map_start_t: float | None = None  # first state's event time on the map
        self._map_started = False
        self._bounds: np.ndarray | None = None
        self._ranking_text = ""
        # live buffers, emptied by flush
        self._alerts: list[Alert] = []
        self._fixes: dict[str, GpsFix] = {}  # newest fix per train
        self._fixes_new = False
        self._plots_due = True
        self._plot_at: float | None = None
        self._live_at: float | None = None
        # health: the newest report of `up` and when (wall, monotonic) it was taken
        self._stack: StackHealth | None = None
        self._stack_new = False
        self._stack_at: float | None = None
        self._alive: dict[tuple[str, str], bool] = {}
        self._health_text = ""
        self.plan: MaintenancePlan | None = None  # the newest plan taken
        self._plan_new = False

    # --- setup ---------------------------------------------------------------------------

    def start(self, now: float) -> None:
        """Log the static map (segments, tunnels, stations, line names, legend) and send
        the one blueprint."""
        if self.network is not None:
            keys, self._bounds = log_static_map(self.rec, self.network)
            self._map = _Map(
                keys,
                {key: i for i, key in enumerate(keys)},
                np.full((len(keys), 3), UNKNOWN_RGB, np.uint8),
            )
        self.rec.send_blueprint(
            build_blueprint(self.worst_n, self._bounds), make_active=True, make_default=True
        )
        self.blueprints_sent += 1
        self._log_health()

    # --- messages ------------------------------------------------------------------------

    def take(self, messages: Iterable[Message]) -> int:
        """Keep a batch (per segment and event-day the newest state and index), update the
        ranking, the map's current colours, the selection and the health. No Rerun call.
        Returns the count."""
        n = 0
        for msg in messages:
            n += 1
            match msg:
                case SegmentState():
                    self._keep_state(msg)
                    self._take_state(msg)
                case OnboardIndex():
                    self._keep_onboard(msg)
                case TrcRecord():
                    values = np.array([msg.top6_mm, msg.align10_mm], dtype=float)
                    self._history_of((msg.line, msg.segment)).add_trc(msg.t, values)
                    self._event_time(msg.t)
                case GpsFix():
                    newest = self._fixes.get(msg.train)
                    if msg.fix_quality > 0 and (newest is None or msg.t >= newest.t):
                        self._fixes[msg.train] = msg
                        self._fixes_new = True
                case Alert():
                    self._alerts.append(msg)
                case StackHealth():
                    if self._stack is None or msg.written_at >= self._stack.written_at:
                        self._stack, self._stack_new = msg, True
                case ViewerSelect():
                    self._selected = (msg.line, msg.segment)
                    self._plots_due = True
                case MaintenancePlan():
                    if self.plan is None or message_version(msg) >= message_version(self.plan):
                        self.plan, self._plan_new = msg, True
                case _:
                    raise TypeError(f"viewer: cannot log a {type(msg).__name__}")
        self.handled += n
        return n

    def set_alive(self, alive: Mapping[tuple[str, str], bool]) -> None:
        """The liveliness tokens seen: (service, instance) → present now."""
        self._alive = dict(alive)

    def log_batch(self, messages: Iterable[Message], now: float | None = None) -> int:
        """:meth:`take` then :meth:`flush` at ``now`` (everything when ``now`` is None)."""
        n = self.take(messages)
        self.flush(0.0 if now is None else now, force=now is None)
        return n

    def _history_of(self, key: SegmentId) -> _History:
        history = self._history.get(key)
        if history is None:
            history = self._history[key] = _History()
        return history

    def _event_time(self, t: float) -> None:
        if self._newest_event_t is None or t > self._newest_event_t:
            self._newest_event_t = t

    def _keep_state(self, state: SegmentState) -> None:
        levels = tuple(state.limit_levels[:MAX_LEVELS])
        levels = _LEVELS.setdefault(levels, levels)
        mean, low, high = state.mean.array(), state.ci_low_mm.array(), state.ci_high_mm.array()
        limits = state.limits_mm.array()[: len(levels)]
        values = np.full((len(INDICATORS), 3 + len(levels)), np.nan)
        for row, indicator in enumerate(INDICATORS):
            if indicator in state.indicators:
                i = state.indicators.index(indicator)
                values[row] = [math.exp(mean[i]), low[i], high[i], *limits[:, i]]
        self._history_of((state.line, state.segment)).states.put(state.t, values, levels)
        self._event_time(state.t)

    def _keep_onboard(self, index: OnboardIndex) -> None:
        values = np.array([[index.top6_mm], [index.align10_mm]], dtype=float)  # None: NaN
        self._history_of((index.line, index.segment)).onboard.put(index.t, values)
        self._event_time(index.t)

    def _take_state(self, state: SegmentState) -> None:
        key = (state.line, state.segment)
        if state.t < self._newest_t.get(key, -math.inf):
            return  # a late state: its day's row is kept, the ranking keeps the newest
        self._newest_t[key] = state.t
        self.p_exceed[key] = p = segment_exceedance(state)
        self.last_trc[key] = tuple(state.last_trc_indicators)
        i = self._map.index.get(key) if self._map is not None else None
        if self._map is None or i is None:
            return  # not on the map
        if self._map_start_t is None:
            self._map_start_t = state.t
        rgb = exceedance_color(p)
        if not np.array_equal(self._map.colors[i], rgb):
            self._map.colors[i] = rgb
            self._map.changed_t = max(self._map.changed_t or -math.inf, state.t)

    def flush(self, now: float, *, force: bool = False) -> None:
        """Write what is due at wall time ``now`` (monotonic s): the plots' rows each
        ``plot_flush_s`` (at once when a slot can be filled or a segment was selected), the
        map colours, trains, alerts and health each ``live_flush_s`` (``force``: all, now)."""

        def due(at: float | None, interval: float) -> bool:
            return force or at is None or now - at >= interval

        if self._stack_new:
            self._stack_at, self._stack_new = now, False
        if due(self._live_at, self.live_flush_s):
            self._live_at = now
            self._flush_live(now)
        if self._plots_due or self._slot_can_fill() or due(self._plot_at, self.plot_flush_s):
            self._plot_at = now
            self._plots_due = False
            self._flush_plots()

    # --- plots ---------------------------------------------------------------------------

    def worst(self) -> list[SegmentId]:
        """The segments to plot: :func:`select_worst_sticky` around the plotted ones."""
        shown = [slot.key for slot in self._slots[: self.worst_n] if slot.key is not None]
        return select_worst_sticky(self.p_exceed, self.worst_n, shown, WORST_MARGIN)

    def shown(self) -> dict[str, SegmentId | None]:
        """Slot → the segment it shows."""
        return {slot.name: slot.key for slot in self._slots}

    def segment_label(self, key: SegmentId) -> str:
        """A segment as operators know it: ``line name (line/segment)``, or ``line/segment``
        when the line has no name (the id is what `trackfusion viewer select` takes)."""
        name = self.line_names.get(key[0])
        ids = f"{key[0]}/{key[1]}"
        return f"{name} ({ids})" if name and name != key[0] else ids

    def _slot_can_fill(self) -> bool:
        empty = sum(slot.key is None for slot in self._slots[: self.worst_n])
        return empty > 0 and len(self.p_exceed) > self.worst_n - empty

    def _flush_plots(self) -> None:
        worst = self.worst()
        # a segment keeps its slot when it only moves in the ranking: no new generation
        by_key = {slot.key: slot for slot in self._slots[: self.worst_n] if slot.key}
        free = [slot for slot in self._slots[: self.worst_n] if slot.key not in worst]
        for key in worst:
            if key not in by_key:
                slot = free.pop(0)
                self._show(slot, key)
        self._show(self._slots[-1], self._selected)
        for slot in self._slots:
            if slot.key is not None:
                self._write_slot(slot)
        self._log_ranking()

    def _show(self, slot: _Slot, key: SegmentId | None) -> None:
        """Let ``slot`` show ``key``: hide the current generation, start a new one."""
        if slot.key == key:
            return
        if slot.key is not None:
            for path in slot.styled:
                hidden = (
                    rr.SeriesLines.from_fields(visible_series=[False])
                    if path.endswith("/state")
                    else rr.SeriesPoints.from_fields(visible_series=[False])
                )
                self.rec.log(path, hidden, static=True)
        slot.key = key
        slot.written, slot.styled = {}, {}
        if key is not None:
            self.generations += 1
            slot.generation = self.generations

    def _write_slot(self, slot: _Slot) -> None:
        assert slot.key is not None
        history = self._history.get(slot.key)
        if history is None:
            return
        prefix = f"{slot.key[0]}/{slot.key[1]} "
        for kind in ("state", "onboard", "trc"):
            rows = history.rows(kind, slot.written.get(kind, -math.inf))
            if not rows:
                continue
            slot.written[kind] = rows[-1][0]
            for levels in dict.fromkeys(levels for _, levels, _ in rows):
                same = [row for row in rows if row[1] == levels]
                t = np.array([row[0] for row in same])
                values = np.stack([row[2] for row in same])  # (rows, indicators[, series])
                for i, indicator in enumerate(INDICATORS):
                    path = slot.path(indicator, kind)
                    slot.styled[path] = levels
                    column = values[:, i]
                    keep = ~np.isnan(column).all(axis=-1) if column.ndim > 1 else ~np.isnan(column)
                    if keep.any():
                        style = style_columns(kind, levels, prefix, int(keep.sum()))
                        self._send(path, t[keep], column[keep], style)

    def _send(
        self, path: str, t: np.ndarray, values: np.ndarray, style: Iterable[object] = ()
    ) -> None:
        """Rows of scalars at event times ``t`` with their style on every row: one chunk
        (``values`` is (rows,) or (rows, instances)). The style goes with the rows, not as
        static data: the server keeps every static message for every browser that connects
        later, and a slot gets new entities each time it shows another segment."""
        self.rec.send_columns(
            path,
            indexes=[rr.TimeColumn(TIMELINE, timestamp=t)],
            columns=[*rr.Scalars.columns(scalars=values.astype(float)), *style],
        )
        self.rows_written += len(t)

    def _log_ranking(self) -> None:
        """Which segment each plot row shows, with its P(exceed intervention); temporal, at
        the newest event time, so it is written only when it changed."""
        if self._newest_event_t is None:
            return
        # the segment last: a line's name is long and the panel narrow
        lines = ["| row | p | last TRC measured | segment |", "|---|---|---|---|"]
        for slot in self._slots:
            row = "selected" if slot.name == SELECTED else f"#{slot.name.split('/')[1]}"
            if slot.key is None:
                lines.append(f"| {row} | | | - |")
                continue
            p = self.p_exceed.get(slot.key)
            measured = " ".join(self.last_trc.get(slot.key, ())) or "-"
            lines.append(
                f"| {row} | {'-' if p is None else f'{p:.2f}'} | {measured} "
                f"| {self.segment_label(slot.key)} |"
            )
        lines += [
            "",
            "p: P(exceed intervention limit)",
            "",
            "`trackfusion viewer select L1/s00042`",
        ]
        text = "\n".join(lines)
        if text != self._ranking_text:
            self._ranking_text = text
            self.rec.set_time(TIMELINE, timestamp=self._newest_event_t)
            self.rec.log(RANKING_PATH, rr.TextDocument(text, media_type="text/markdown"))

    # --- live: map colours, trains, alerts, health -----------------------------------------

    def _flush_live(self, now: float) -> None:
        if not self._map_started and self._map_start_t is not None:
            self._start_map_colors(self._map_start_t)
        if self._map is not None and self._map.changed_t is not None:
            self.rec.set_time(TIMELINE, timestamp=self._map.changed_t)
            self.rec.log(MAP_PATH, rr.LineStrips2D.from_fields(colors=self._map.colors))
            self._map.changed_t = None
        if self._fixes_new and self.network is not None:
            fixes = sorted(self._fixes.values(), key=lambda f: f.train)
            xy = screen_xy(self.network.to_xy(np.array([[f.lon_deg, f.lat_deg] for f in fixes])))
            self.rec.set_time(TIMELINE, timestamp=max(f.t for f in fixes))
            self.rec.log(
                "map/trains",
                rr.Points2D(
                    xy,
                    radii=rr.Radius.ui_points(6.0),
                    colors=(0, 200, 255),
                    labels=[f.train for f in fixes],
                    show_labels=True,
                    draw_order=DRAW_ORDER["trains"],
                ),
            )
        self._fixes_new = False
        if self._plan_new:
            self._log_plan()
        for alert in sorted(self._alerts, key=lambda a: a.t):
            self._log_alert(alert)
        self._alerts.clear()
        stale = self._stack_at is None or now - self._stack_at > STACK_REPORT_STALE_S
        self._log_health(None if stale else self._stack)

    def _log_plan(self) -> None:
        """The newest plan's possessions of the next :data:`PLAN_WEEKS` weeks at the plan's
        event time (a plan without data: nothing to draw)."""
        self._plan_new = False
        plan = self.plan
        if plan is None or plan.computed_at is None or plan.t is None or self.network is None:
            return
        self.rec.set_time(TIMELINE, timestamp=plan.computed_at)
        possessions = planned_possessions(plan, min(PLAN_WEEKS, plan.horizon_weeks))
        plan_strips(self.rec, self.network, possessions, PLAN_WEEKS, plan.t)

    def _log_health(self, stack: StackHealth | None = None) -> None:
        """The health board as a static document, re-logged only when its text changed
        (the server keeps every static message: a handful per restart or stall)."""
        text = health_markdown(stack, self._alive)
        if text != self._health_text:
            self._health_text = text
            self.rec.log(
                HEALTH_PATH, rr.TextDocument(text, media_type="text/markdown"), static=True
            )

    def _log_alert(self, alert: Alert) -> None:
        raised = alert.status == "raised"
        text = " ".join(
            part
            for part in (
                alert.status,
                alert.kind,
                self.segment_label((alert.line, alert.segment)),
                alert.indicator,
                alert.level,
                f"p={alert.probability:.2f}",
                f"in {alert.horizon_days:g} d" if alert.horizon_days is not None else "",
                f"- {alert.message}" if alert.message else "",
            )
            if part
        )
        self.rec.set_time(TIMELINE, timestamp=alert.t)
        self.rec.log(
            "alerts",
            rr.TextLog(text, level=rr.TextLogLevel.WARN if raised else rr.TextLogLevel.INFO),
        )

    def _start_map_colors(self, t: float) -> None:
        """Grey for every segment at the first state's event time (temporal colours can't
        start earlier: static colours would hide every later change)."""
        self._map_started = True
        if self._map is not None:
            self.rec.set_time(TIMELINE, timestamp=t)
            grey = np.full((len(self._map.keys), 3), UNKNOWN_RGB, np.uint8)
            self.rec.log(MAP_PATH, rr.LineStrips2D.from_fields(colors=grey))
