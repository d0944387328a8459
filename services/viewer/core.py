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

Entity paths (values in mm; ``{ind}`` is ``top6`` or ``align10``):

================================================  ==========================================
``{slot}/{ind}/g{n}/state``                       Scalars, one instance per series: estimate
                                                  (exp of the mixture mean of ln mm), 95 %
                                                  band low and high, then one per limit level
``{slot}/{ind}/g{n}/onboard``                     raw on-board index (points; not de-biased)
``{slot}/{ind}/g{n}/trc``                         TRC record (points)
``worst/ranking``                                 TextDocument: which segment each slot shows
``map/segments``                                  one line strip per segment of the network
                                                  (labelled ``{line}/{segment}``), coloured
                                                  by exceedance probability (green → red)
``map/tunnels``, ``map/stations``, ``map/lines``  static: tunnels (dark strips under the
                                                  segments), stations and line names
``map/legend``                                    static colour scale of the map
``map/trains``                                    last GPS fix of every train (fix_quality > 0)
``alerts``                                        TextLog: raised = WARN, cleared = INFO
``health``                                        TextDocument: services alive, restarts,
                                                  stalled flows
================================================  ==========================================

Map frame: local metres of :meth:`simulators.network.Network.to_xy` (x east, y north)
with y negated on logging, because Rerun's 2D view draws y downwards (rerun#1387): north
is up on screen.
"""

from __future__ import annotations

import heapq
import math
import re
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
import rerun as rr
import rerun.blueprint as rrb
from rerun.encodings import TimeRange

from schemas import (
    DAY_S,
    INDICATORS,
    Alert,
    GpsFix,
    Message,
    OnboardIndex,
    SegmentState,
    StackHealth,
    TrcRecord,
    ViewerSelect,
)
from schemas.keys import SegmentId
from track.network import Network

TIMELINE = "event_time"  # timestamp timeline of the messages' event time t (epoch s)
MAP_PATH = "map/segments"  # every segment of the network, one line strip each
RANKING_PATH = "worst/ranking"
HEALTH_PATH = "health"
SELECTED = "selected"
INTERVENTION = "intervention"  # the limit level the map colour and the worst ranking use
DEFAULT_WORST_N = 3
WORST_MARGIN = 0.25  # a segment replaces a plotted one if its p is higher by more than this
DEFAULT_PLOT_FLUSH_S = 30.0  # wall seconds between two writes of the slots' rows
DEFAULT_LIVE_FLUSH_S = 5.0  # wall seconds between two writes of map colours, alerts, trains
HISTORY_DAYS = 365  # event days of states and on-board indices kept per segment
PLOT_WINDOW_DAYS = 90.0  # event days before the time cursor that the plots show
STACK_REPORT_STALE_S = 5.0  # wall s without a StackHealth: `up` is taken as gone

UNKNOWN_RGB = (128, 128, 128)  # a segment without a state yet
_STOPS_P = np.array([0.0, 0.5, 1.0])
_STOPS_RGB = np.array([(40, 170, 60), (240, 200, 30), (220, 40, 40)], dtype=float)  # green→red
LEGEND_P = (0.0, 0.25, 0.5, 0.75, 1.0)


_BAND_RGBA = (80, 160, 255, 110)
_POINT_STYLE = {
    "onboard": {"colors": (255, 150, 40), "markers": "circle", "marker_sizes": 2.5},
    "trc": {"colors": (230, 80, 230), "markers": "diamond", "marker_sizes": 5.0},
}
_POINT_NAMES = {"onboard": "on-board", "trc": "TRC"}
_SECONDS = re.compile(r" (after|for) \d+ s$")  # "… after 12 s": changes every second
_LIMIT_RGB = {"alert": (255, 190, 0), "intervention": (230, 40, 40)}
# draw order on the map, bottom to top
_ORDER = {"tunnels": 10.0, "segments": 20.0, "stations": 30.0, "trains": 40.0, "labels": 50.0}


def exceedance_color(p: float | np.ndarray) -> np.ndarray:
    """RGB (uint8) of exceedance probabilities: green at 0, yellow at 0.5, red at 1.

    Values are clipped to [0, 1]; NaN (no state yet) is grey. Shape ``p.shape + (3,)``.
    """
    p = np.asarray(p, dtype=float)
    rgb = np.stack(
        [np.interp(np.clip(p, 0.0, 1.0), _STOPS_P, _STOPS_RGB[:, c]) for c in range(3)], -1
    )
    rgb[np.isnan(p)] = UNKNOWN_RGB
    return np.rint(rgb).astype(np.uint8)


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
    return None


def state_series(levels: Sequence[str]) -> list[str]:
    """Instance names of a ``…/state`` row: estimate, the band, then one per limit."""
    return ["estimate", "95% low", "95% high", *(f"{level} limit" for level in levels)]


def state_style(levels: Sequence[str], prefix: str = "") -> rr.SeriesLines:
    """One line style per instance of a ``…/state`` row (see :func:`state_series`), the
    names prefixed with ``prefix`` (the segment, shown when hovering a line)."""
    colors, widths, names = _state_style_lists(levels, prefix)
    return rr.SeriesLines(colors=colors, widths=widths, names=names)


def _state_style_lists(
    levels: Sequence[str], prefix: str
) -> tuple[list[tuple[int, ...]], list[float], list[str]]:
    colors = [(80, 160, 255, 255), _BAND_RGBA, _BAND_RGBA]
    colors += [(*_LIMIT_RGB.get(level, (200, 200, 200)), 255) for level in levels]
    widths = [2.0, 1.0, 1.0, *([1.5] * len(levels))]
    return colors, widths, [f"{prefix}{name}" for name in state_series(levels)]


def point_style(kind: str, prefix: str = "") -> rr.SeriesPoints:
    """The style of an ``onboard`` or ``trc`` entity."""
    return rr.SeriesPoints(**_POINT_STYLE[kind], names=f"{prefix}{_POINT_NAMES[kind]}")


def _style_columns(kind: str, levels: Sequence[str], prefix: str, rows: int) -> list[object]:
    """:func:`state_style` or :func:`point_style` as columns repeated on ``rows`` rows (a plot
    takes a row's style from that row: a style on the first row only would fall out of the
    plot's window once that row is older than the window)."""
    if kind == "state":
        colors, widths, names = _state_style_lists(levels, prefix)
        return list(
            rr.SeriesLines.columns(
                colors=colors * rows, widths=widths * rows, names=names * rows
            ).partition([len(names)] * rows)
        )
    spec = _POINT_STYLE[kind]
    return list(
        rr.SeriesPoints.columns(
            colors=[spec["colors"]] * rows,
            markers=[spec["markers"]] * rows,
            marker_sizes=[spec["marker_sizes"]] * rows,
            names=[f"{prefix}{_POINT_NAMES[kind]}"] * rows,
        )
    )


def slot_names(worst_n: int) -> list[str]:
    """The plot rows of the blueprint, top to bottom: ``worst/1`` … ``worst/N``, ``selected``."""
    return [*(f"worst/{rank}" for rank in range(1, worst_n + 1)), SELECTED]


def build_blueprint(worst_n: int, bounds: np.ndarray | None = None) -> rrb.Blueprint:
    """The map with the alert log, which segment each plot row shows, and the health board
    below it; on the right one plot row per worst rank and one for the selected segment (a
    plot per indicator). Sent once: the rows are slots the core fills.

    ``bounds``: ``[[x_min, y_min], [x_max, y_max]]`` of the map in logged coordinates, so
    that the map opens on the whole network and its legend.
    """
    map_view = rrb.Spatial2DView(
        origin="map",
        contents="$origin/**",
        name="Network: P(exceed intervention limit)",
        visual_bounds=None
        if bounds is None
        else rrb.VisualBounds2D(x_range=bounds[:, 0], y_range=bounds[:, 1]),
    )
    # an explicit window ending at the cursor: the plot's automatic x range is fitted to the
    # first rows it draws, which for a browser that connects late (newest first) are the
    # last few and so too narrow to show the rest when it arrives
    window = TimeRange(
        start=rrb.TimeRangeBoundary.cursor_relative(seconds=-PLOT_WINDOW_DAYS * DAY_S),
        end=rrb.TimeRangeBoundary.cursor_relative(seconds=DAY_S),
    )
    rows = [
        rrb.Horizontal(
            *(
                rrb.TimeSeriesView(
                    origin=f"{slot}/{indicator}",
                    contents="$origin/**",
                    name=f"{'selected' if slot == SELECTED else '#' + slot.split('/')[1]} "
                    f"{indicator} mm",
                    plot_legend=rrb.PlotLegend(visible=False),  # small plots: hover for names
                    axis_x=rrb.TimeAxis(view_range=window),
                )
                for indicator in INDICATORS
            )
        )
        for slot in slot_names(worst_n)
    ]
    left = rrb.Vertical(
        map_view,
        rrb.Horizontal(
            rrb.TextLogView(origin="alerts", name="Alerts"),
            rrb.TextDocumentView(origin=RANKING_PATH, name="Plotted segments"),
            rrb.TextDocumentView(origin=HEALTH_PATH, name="Health"),
            column_shares=[5, 3, 4],
        ),
        row_shares=[5, 2],
    )
    right = rrb.Vertical(*rows)
    return rrb.Blueprint(
        rrb.Horizontal(left, right, column_shares=[3, 2]),
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
        rrb.TimePanel(timeline=TIMELINE),
        auto_views=False,
        auto_layout=False,
    )


def health_markdown(
    stack: StackHealth | None,
    alive: Mapping[tuple[str, str], bool],
) -> str:
    """The health board: ``up``'s report (a table of its processes, stalled flows in bold)
    when ``stack`` is given, else the liveliness tokens seen (``alive``: (service,
    instance) → present now). Seconds are left out, so that the text changes only when the
    health does."""
    lines: list[str] = []
    if stack is not None:
        verdict = "healthy" if stack.healthy else "**not healthy**"
        lines += [
            f"**trackfusion up**: {verdict}",
            "",
            "| service | state | alive | restarts | last restart reason |",
            "|---|---|---|---|---|",
        ]
        for p in stack.processes:
            alive_text = "yes" if p.alive else "**no**"
            reason = _SECONDS.sub("", p.last_restart_reason)
            lines.append(f"| {p.name} | {p.state} | {alive_text} | {p.restarts} | {reason} |")
        for text in stack.stalled:
            lines += ["", f"**STALLED: {_SECONDS.sub('', text)}**"]
    else:
        lines += [
            "No report from `trackfusion up`: liveliness tokens seen",
            "",
            "| service | instance | alive |",
            "|---|---|---|",
        ]
        for (service, instance), present in sorted(alive.items()):
            lines.append(f"| {service} | {instance} | {'yes' if present else '**no**'} |")
        if not alive:
            lines += ["", "none yet"]
    return "\n".join(lines)


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
        self.worst_n = worst_n
        self.plot_flush_s = plot_flush_s
        self.live_flush_s = live_flush_s
        self.p_exceed: dict[SegmentId, float] = {}
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

    # --- setup ---------------------------------------------------------------------------

    def start(self, now: float) -> None:
        """Log the static map (segments, tunnels, stations, line names, legend) and send
        the one blueprint."""
        if self.network is not None:
            self._log_static_map(self.network)
        self.rec.send_blueprint(
            build_blueprint(self.worst_n, self._bounds), make_active=True, make_default=True
        )
        self.blueprints_sent += 1
        self._log_health()

    def _log_static_map(self, network: Network) -> None:
        lines = list(network.lines.values())
        xy = _screen(np.concatenate([ln.xy for ln in lines]))
        lo, hi = xy.min(axis=0), xy.max(axis=0)
        span = float((hi - lo).max())
        keys = [(line.id, seg.id) for line in lines for seg in line.segments]
        strips = [
            _screen(network.to_xy(line.segment_lonlat(seg)))
            for line in lines
            for seg in line.segments
        ]
        # one entity for the whole network: one chunk per colour change, not one per segment
        self.rec.log(
            MAP_PATH,
            rr.LineStrips2D(
                strips,
                radii=rr.Radius.ui_points(3.5),
                labels=[f"{line}/{segment}" for line, segment in keys],
                show_labels=False,
                draw_order=_ORDER["segments"],
            ),
            static=True,
        )
        self._map = _Map(
            keys,
            {key: i for i, key in enumerate(keys)},
            np.full((len(keys), 3), UNKNOWN_RGB, np.uint8),
        )
        tunnels, tunnel_labels = [], []
        stations, station_labels = [], []
        names, name_labels = [], []
        for line in lines:
            for a, b in line.tunnels:
                chainage = np.r_[
                    a, line.chainage_m[(line.chainage_m > a) & (line.chainage_m < b)], b
                ]
                tunnels.append(_screen(line.xy_at(chainage)))
                tunnel_labels.append(f"{line.id} tunnel {a / 1e3:.1f}–{b / 1e3:.1f} km")
            station_names = line.station_names or [""] * len(line.stations)
            for c, station_name in zip(line.stations, station_names, strict=True):
                stations.append(_screen(line.xy_at(c)))
                where = f"{line.id} km {c / 1e3:.1f}"
                station_labels.append(f"{station_name} ({where})" if station_name else where)
            # the line's name beyond both of its ends
            for end, inward in ((0.0, 1.0), (line.length_m, -1.0)):
                ahead = line.xy_at(np.clip(end + inward * 0.02 * span, 0, line.length_m))
                at = line.xy_at(end)
                direction = (at - ahead) / max(1e-9, float(np.hypot(*(at - ahead))))
                names.append(_screen(at + direction * 0.025 * span))
                name_labels.append(f"{line.id} {line.name}" if line.name else line.id)
        if tunnels:
            self.rec.log(
                "map/tunnels",
                rr.LineStrips2D(
                    tunnels,
                    radii=rr.Radius.ui_points(8.0),
                    colors=(35, 35, 45),
                    labels=tunnel_labels,
                    show_labels=False,
                    draw_order=_ORDER["tunnels"],
                ),
                static=True,
            )
        if stations:
            self.rec.log(
                "map/stations",
                rr.Points2D(
                    np.array(stations),
                    radii=rr.Radius.ui_points(4.0),
                    colors=(70, 70, 80),
                    labels=station_labels,
                    show_labels=False,  # on hover: names on the map would hide the colours
                    draw_order=_ORDER["stations"],
                ),
                static=True,
            )
        self.rec.log(
            "map/lines",
            rr.Points2D(
                np.array(names),
                radii=rr.Radius.ui_points(1.0),
                colors=(20, 20, 30),
                labels=name_labels,
                show_labels=True,
                draw_order=_ORDER["labels"],
            ),
            static=True,
        )
        # the colour scale below the network, at its left: small swatches, their labels in
        # a neutral colour beside them (coloured text would add to the colours of the map)
        step = 0.045 * span
        legend_at = (
            np.array([lo[0], hi[1] + 2 * step])
            + np.array([0.0, step]) * np.arange(len(LEGEND_P) + 1)[:, None]
        )
        labels = [f"p = {p:g}" for p in LEGEND_P] + ["no state yet"]
        colors = np.vstack([exceedance_color(np.array(LEGEND_P)), [UNKNOWN_RGB]])
        self.rec.log(
            "map/legend/colors",
            rr.Points2D(
                legend_at,
                radii=rr.Radius.ui_points(4.0),
                colors=colors,
                draw_order=_ORDER["labels"],
            ),
            static=True,
        )
        self.rec.log(
            "map/legend/labels",
            rr.Points2D(
                legend_at + [0.12 * span, -0.7 * step],  # a label is drawn below its point
                radii=rr.Radius.ui_points(0.5),
                colors=(20, 20, 30),
                labels=labels,
                show_labels=True,
                draw_order=_ORDER["labels"],
            ),
            static=True,
        )
        everything = np.vstack([xy, legend_at, np.array(names)])
        margin = 0.05 * span
        self._bounds = np.stack([everything.min(axis=0) - margin, everything.max(axis=0) + margin])

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
        values = np.array([[index.top6_mm], [index.align10_mm]])
        self._history_of((index.line, index.segment)).onboard.put(index.t, values)
        self._event_time(index.t)

    def _take_state(self, state: SegmentState) -> None:
        key = (state.line, state.segment)
        if state.t < self._newest_t.get(key, -math.inf):
            return  # a late state: its day's row is kept, the ranking keeps the newest
        self._newest_t[key] = state.t
        self.p_exceed[key] = p = segment_exceedance(state)
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
                        style = _style_columns(kind, levels, prefix, int(keep.sum()))
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
        lines = ["| row | segment | p |", "|---|---|---|"]
        for slot in self._slots:
            row = "selected" if slot.name == SELECTED else f"#{slot.name.split('/')[1]}"
            if slot.key is None:
                lines.append(f"| {row} | - | |")
                continue
            p = self.p_exceed.get(slot.key)
            lines.append(
                f"| {row} | {slot.key[0]}/{slot.key[1]} | {'-' if p is None else f'{p:.2f}'} |"
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
            xy = _screen(self.network.to_xy(np.array([[f.lon_deg, f.lat_deg] for f in fixes])))
            self.rec.set_time(TIMELINE, timestamp=max(f.t for f in fixes))
            self.rec.log(
                "map/trains",
                rr.Points2D(
                    xy,
                    radii=rr.Radius.ui_points(6.0),
                    colors=(0, 200, 255),
                    labels=[f.train for f in fixes],
                    show_labels=True,
                    draw_order=_ORDER["trains"],
                ),
            )
        self._fixes_new = False
        for alert in sorted(self._alerts, key=lambda a: a.t):
            self._log_alert(alert)
        self._alerts.clear()
        stale = self._stack_at is None or now - self._stack_at > STACK_REPORT_STALE_S
        self._log_health(None if stale else self._stack)

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
                f"{alert.line}/{alert.segment}",
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


def _screen(xy: np.ndarray) -> np.ndarray:
    """Local (x east, y north) metres to Rerun's y-down 2D frame: north up on screen."""
    return np.asarray(xy, dtype=float) * np.array([1.0, -1.0])
