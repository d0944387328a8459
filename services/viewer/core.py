"""The viewer's pure core: TrackFusion messages in, Rerun log calls out.

No Zenoh, no clock, no sink: :class:`ViewerCore` logs to the ``rerun.RecordingStream`` it
is given, and the adapter (``service.py``) decides where that stream goes (native viewer,
web viewer, ``.rrd`` file) and passes wall time in where the rate limits need it.

Time: every temporal row is stamped on the timeline :data:`TIMELINE` (``"event_time"``),
a timestamp timeline holding each message's own event time ``t`` (UTC epoch seconds), so
late or replayed messages land where they belong.

Volume: what a viewer holds, and what a browser that connects late must take in before it
draws, is what is logged; so superseded messages are thinned and rows are batched into few
chunks (:meth:`ViewerCore.take` only updates buffers and the ranking; :meth:`ViewerCore.flush`
writes what is due; services/viewer/README.md has the figures):

* series (states, on-board indices): per segment and **event-day**, the newest message of
  that day is buffered; the plotted segments' buffers are written every ``plot_flush_s``
  wall seconds, every segment's every ``series_flush_s``, one ``send_columns`` chunk per
  entity. So a plot gets at most one row per event-day per write. On-board indices of a
  segment never plotted are kept (90 days) and written when it is first plotted; TRC
  records (a few per segment and year) are all written.
* live (map colours, alerts, trains): every ``live_flush_s`` wall seconds; the network's
  colours are re-logged (one row) only when one changed, all trains' latest positions go in one
  row; every alert is written.
* static series styles only for the segments ever plotted (static data reaches a browser
  before anything else).

Entity paths (values in mm; ``{ind}`` is ``top6`` or ``align10``):

================================================  ==========================================
``segments/{line}/{segment}/{ind}/state``         Scalars, one instance per series: estimate
                                                  (exp of the mixture mean of ln mm), 95 %
                                                  band low and high, then one per limit level
``segments/{line}/{segment}/{ind}/onboard``       raw on-board index (points; not de-biased)
``segments/{line}/{segment}/{ind}/trc``           TRC record (points)
``map/segments``                                  one line strip per segment of the network
                                                  (labelled ``{line}/{segment}``), coloured
                                                  by exceedance probability (green → red)
``map/trains``                                    last GPS fix of every train (fix_quality > 0)
``alerts``                                        TextLog: raised = WARN, cleared = INFO
================================================  ==========================================

Map frame: local metres of :meth:`simulators.network.Network.to_xy` (x east, y north)
with y negated on logging, because Rerun's 2D view draws y downwards (rerun#1387): north
is up on screen. Strip geometry and labels are static; only the colours are temporal, so
the map is drawn before the first state and a colour change re-logs one colour array.
"""

from __future__ import annotations

import heapq
import math
from collections import defaultdict
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import rerun as rr
import rerun.blueprint as rrb
from rerun.encodings import TimeRange

from schemas import INDICATORS, Alert, GpsFix, Message, OnboardIndex, SegmentState, TrcRecord
from simulators.network import Network

TIMELINE = "event_time"  # timestamp timeline of the messages' event time t (epoch s)
MAP_PATH = "map/segments"  # every segment of the network, one line strip each
INTERVENTION = "intervention"  # the limit level the map colour and the worst ranking use
DAY_S = 86_400.0
DEFAULT_WORST_N = 3
# Rerun's gRPC server keeps every blueprint ever sent (~100 KB each) and replays them all
# to each browser that connects: re-send rarely.
DEFAULT_BLUEPRINT_INTERVAL_S = 60.0  # wall seconds between two blueprint re-sends, at least
DEFAULT_SERIES_FLUSH_S = 300.0  # wall seconds between two writes of the other segments' rows
WORST_MARGIN = 0.25  # a segment replaces a plotted one if its p is higher by more than this
DEFAULT_PLOT_FLUSH_S = 10.0  # wall seconds between two writes of the plotted segments' rows
DEFAULT_LIVE_FLUSH_S = 3.0  # wall seconds between two writes of map colours, alerts, trains
ONBOARD_KEPT_DAYS = 90  # event days of on-board points kept for a segment not plotted yet
PLOT_WINDOW_DAYS = 90.0  # event days before the time cursor that the plots show

UNKNOWN_RGB = (128, 128, 128)  # a segment without a state yet
_STOPS_P = np.array([0.0, 0.5, 1.0])
_STOPS_RGB = np.array([(40, 170, 60), (240, 200, 30), (220, 40, 40)], dtype=float)  # green→red

SegmentKey = tuple[str, str]  # (line, segment)

_BAND_RGBA = (80, 160, 255, 110)
_POINTS: dict[str, rr.AsComponents] = {
    "onboard": rr.SeriesPoints(
        colors=(255, 150, 40), markers="circle", marker_sizes=2.5, names="on-board"
    ),
    "trc": rr.SeriesPoints(colors=(230, 80, 230), markers="diamond", marker_sizes=5.0, names="TRC"),
}
_LIMIT_RGB = {"alert": (255, 190, 0), "intervention": (230, 40, 40)}


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


def select_worst(p_exceed: Mapping[SegmentKey, float], n: int) -> list[SegmentKey]:
    """The ``n`` segments with the highest probability, highest first; ties by (line, segment)."""
    return [key for _, key in heapq.nsmallest(n, ((-p, key) for key, p in p_exceed.items()))]


def select_worst_sticky(
    p_exceed: Mapping[SegmentKey, float],
    n: int,
    shown: Sequence[SegmentKey],
    margin: float,
) -> list[SegmentKey]:
    """Like :func:`select_worst`, but a segment already ``shown`` keeps its place unless
    one not shown has a probability more than ``margin`` above it: near-ties (many segments
    close to p = 1) do not swap the plots back and forth. Highest first."""
    best = select_worst(p_exceed, n)
    kept = [key for key in shown if key in p_exceed][:n]
    for candidate in best:
        if candidate in kept:
            continue
        if len(kept) < n:
            kept.append(candidate)
            continue
        weakest = min(kept, key=lambda key: (p_exceed[key], key))
        if p_exceed[candidate] > p_exceed[weakest] + margin:
            kept[kept.index(weakest)] = candidate
    return sorted(kept, key=lambda key: (-p_exceed[key], key))


def event_day(t: float) -> int:
    """The UTC day (days since the epoch) of an event time in epoch seconds."""
    return math.floor(t / DAY_S)


def coalesce_key(msg: Message) -> tuple[str, ...] | None:
    """What a newer message of the same key supersedes before it is written (the thinning
    rule of the series and the trains); None for messages that are all kept (alerts, TRC)."""
    match msg:
        case SegmentState() | OnboardIndex():
            kind = "state" if isinstance(msg, SegmentState) else "onboard"
            return (kind, msg.line, msg.segment, str(event_day(msg.t)))
        case GpsFix():
            return ("gps", msg.train)
    return None


def state_series(levels: Sequence[str]) -> list[str]:
    """Instance names of a ``…/{ind}/state`` row: estimate, the band, then one per limit."""
    return ["estimate", "95% low", "95% high", *(f"{level} limit" for level in levels)]


def state_style(levels: Sequence[str]) -> rr.SeriesLines:
    """One line style per instance of a ``…/{ind}/state`` row (see :func:`state_series`)."""
    colors = [(80, 160, 255), _BAND_RGBA, _BAND_RGBA]
    colors += [_LIMIT_RGB.get(level, (200, 200, 200)) for level in levels]
    widths = [2.0, 1.0, 1.0, *([1.5] * len(levels))]
    return rr.SeriesLines(colors=colors, widths=widths, names=state_series(levels))


def build_blueprint(
    worst: Sequence[tuple[str, str, float]], bounds: np.ndarray | None = None
) -> rrb.Blueprint:
    """The map, the worst segments' plots beside it (one row per segment, one plot per
    indicator, titled with P(exceed intervention)), the alert log below.

    ``bounds``: ``[[x_min, y_min], [x_max, y_max]]`` of the map in logged coordinates, so
    that the map opens on the whole network.
    """
    map_view = rrb.Spatial2DView(
        origin="map",
        contents="$origin/**",
        name="Network: P(exceed intervention)",
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
                    origin=f"segments/{line}/{segment}/{indicator}",
                    contents="$origin/**",
                    name=f"{line}/{segment} {indicator} mm (p={p:.2f})",
                    plot_legend=rrb.PlotLegend(visible=False),  # small plots: hover for names
                    axis_x=rrb.TimeAxis(view_range=window),
                )
                for indicator in INDICATORS
            )
        )
        for line, segment, p in worst
    ]
    top: rrb.Container = (
        rrb.Horizontal(map_view, rrb.Vertical(*rows, name="Worst segments"), column_shares=[3, 2])
        if rows
        else rrb.Horizontal(map_view)
    )
    return rrb.Blueprint(
        rrb.Vertical(top, rrb.TextLogView(origin="alerts", name="Alerts"), row_shares=[3, 1]),
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
        rrb.TimePanel(timeline=TIMELINE),
        auto_views=False,
        auto_layout=False,
    )


@dataclass
class _Map:
    keys: list[SegmentKey]  # strip order: the network's lines, each in chainage order
    index: dict[SegmentKey, int]  # segment -> strip
    colors: np.ndarray  # (k, 3) uint8, the current colours
    changed_t: float | None = None  # newest event time of a colour change not yet logged


class ViewerCore:
    """Logs TrackFusion messages to ``rec``; one instance per recording, one thread.

    :meth:`take` buffers and thins (no Rerun call), :meth:`flush` writes what is due at
    wall time ``now``; :meth:`log_batch` does both and writes everything at once.

    Parameters
    ----------
    rec
        Where the log calls go.
    network
        The map; states, indices and TRC records of lines not in it still get their plots.
    worst_n
        Segments shown beside the map.
    blueprint_interval_s
        Minimum wall time between two blueprint sends (see :meth:`maybe_send_blueprint`).
    series_flush_s, plot_flush_s, live_flush_s
        Wall seconds between two writes of every segment's rows, of the plotted segments'
        rows, of the map colours, alerts and trains.
    """

    def __init__(
        self,
        rec: rr.RecordingStream,
        network: Network | None = None,
        *,
        worst_n: int = DEFAULT_WORST_N,
        blueprint_interval_s: float = DEFAULT_BLUEPRINT_INTERVAL_S,
        series_flush_s: float = DEFAULT_SERIES_FLUSH_S,
        plot_flush_s: float = DEFAULT_PLOT_FLUSH_S,
        live_flush_s: float = DEFAULT_LIVE_FLUSH_S,
    ) -> None:
        if worst_n < 0:
            raise ValueError(f"worst_n: must be >= 0, got {worst_n}")
        if min(series_flush_s, plot_flush_s, live_flush_s) < 0:
            raise ValueError("series_flush_s, plot_flush_s, live_flush_s: must be >= 0")
        self.rec = rec
        self.network = network
        self.worst_n = worst_n
        self.blueprint_interval_s = blueprint_interval_s
        self.series_flush_s = series_flush_s
        self.plot_flush_s = plot_flush_s
        self.live_flush_s = live_flush_s
        self.p_exceed: dict[SegmentKey, float] = {}
        self.handled = 0  # messages taken (GPS fixes without a fix included)
        self.rows_written = 0  # rows of the plots' entities written (thinning's result)
        self.blueprints_sent = 0
        self._newest_t: dict[SegmentKey, float] = {}
        # Series styles are static, and every static chunk goes to each browser that
        # connects before any data: only the segments ever plotted get them.
        self._styled: dict[str, tuple[str, ...]] = {}  # entity -> styled limit levels
        self._levels: dict[str, tuple[str, ...]] = {}  # state entity -> its limit levels
        self._plotted: set[SegmentKey] = set()  # segments that were ever in a blueprint
        self._map: _Map | None = None
        self._map_start_t: float | None = None  # first state's event time on the map
        self._map_started = False
        self._blueprint_keys: list[SegmentKey] | None = None
        self._blueprint_at: float | None = None
        self._bounds: np.ndarray | None = None
        # buffers, emptied by flush
        self._series: dict[tuple[str, ...], SegmentState | OnboardIndex] = {}
        self._trc: list[TrcRecord] = []
        self._alerts: list[Alert] = []
        self._fixes: dict[str, GpsFix] = {}  # newest fix per train
        self._fixes_new = False
        self._series_at: float | None = None
        self._plot_at: float | None = None
        self._live_at: float | None = None
        # on-board points of segments not plotted: written when a segment is first plotted
        self._onboard_kept: dict[SegmentKey, dict[int, OnboardIndex]] = defaultdict(dict)

    # --- setup ---------------------------------------------------------------------------

    def start(self, now: float) -> None:
        """Log the static map geometry and send the first blueprint (map and alerts)."""
        if self.network is not None:
            xy = _screen(np.concatenate([ln.xy for ln in self.network.lines.values()]))
            margin = 0.05 * (xy.max(axis=0) - xy.min(axis=0)).max()
            self._bounds = np.stack([xy.min(axis=0) - margin, xy.max(axis=0) + margin])
            lines = list(self.network.lines.values())
            keys = [(line.id, seg.id) for line in lines for seg in line.segments]
            strips = [
                _screen(self.network.to_xy(line.segment_lonlat(seg)))
                for line in lines
                for seg in line.segments
            ]
            # one entity for the whole network: one chunk per colour change, not one per line
            self.rec.log(
                MAP_PATH,
                rr.LineStrips2D(
                    strips,
                    radii=rr.Radius.ui_points(3.5),
                    labels=[f"{line}/{segment}" for line, segment in keys],
                    show_labels=False,
                ),
                static=True,
            )
            self._map = _Map(
                keys,
                {key: i for i, key in enumerate(keys)},
                np.full((len(keys), 3), UNKNOWN_RGB, np.uint8),
            )
        self.maybe_send_blueprint(now, force=True)

    # --- messages ------------------------------------------------------------------------

    def take(self, messages: Iterable[Message]) -> int:
        """Buffer a batch, keeping per :func:`coalesce_key` only the newest message; update
        the ranking and the map's current colours. No Rerun call. Returns the count."""
        n = 0
        for msg in messages:
            n += 1
            match msg:
                case SegmentState() | OnboardIndex():
                    self._buffer_series(msg)
                    if isinstance(msg, SegmentState):
                        self._take_state(msg)
                case TrcRecord():
                    self._trc.append(msg)
                case GpsFix():
                    newest = self._fixes.get(msg.train)
                    if msg.fix_quality > 0 and (newest is None or msg.t >= newest.t):
                        self._fixes[msg.train] = msg
                        self._fixes_new = True
                case Alert():
                    self._alerts.append(msg)
                case _:
                    raise TypeError(f"viewer: cannot log a {type(msg).__name__}")
        self.handled += n
        return n

    def log_batch(self, messages: Iterable[Message], now: float | None = None) -> int:
        """:meth:`take` then :meth:`flush` at ``now`` (everything when ``now`` is None)."""
        n = self.take(messages)
        self.flush(0.0 if now is None else now, force=now is None)
        return n

    def _buffer_series(self, msg: SegmentState | OnboardIndex) -> None:
        key = coalesce_key(msg)
        assert key is not None
        held = self._series.get(key)
        if held is None or msg.t >= held.t:
            self._series[key] = msg

    def _take_state(self, state: SegmentState) -> None:
        key = (state.line, state.segment)
        if state.t < self._newest_t.get(key, -math.inf):
            return  # a late state: its day's row is written, the ranking keeps the newest
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
        """Write what is due at wall time ``now``: every segment's rows each
        ``series_flush_s``, the plotted segments' rows each ``plot_flush_s``, the map
        colours, trains and alerts each ``live_flush_s`` (``force``: all, now)."""

        def due(at: float | None, interval: float) -> bool:
            return force or at is None or now - at >= interval

        series = due(self._series_at, self.series_flush_s)
        plots = series or due(self._plot_at, self.plot_flush_s)
        if plots or due(self._live_at, self.live_flush_s):
            self._live_at = now
            self._flush_live()
        if series:
            self._series_at = self._plot_at = now
            self._flush_series()
        elif plots:
            self._plot_at = now
            self._flush_series(set(self._blueprint_keys or ()))

    # --- series --------------------------------------------------------------------------

    def _flush_series(self, only: set[SegmentKey] | None = None) -> None:
        """Write the buffered rows (of the ``only`` segments, if given)."""
        states: dict[SegmentKey, list[SegmentState]] = defaultdict(list)
        points: dict[tuple[SegmentKey, str], list[OnboardIndex | TrcRecord]] = defaultdict(list)
        if only is None:
            taken, self._series = self._series, {}
            trcs, self._trc = self._trc, []
        else:
            taken = {k: m for k, m in self._series.items() if (m.line, m.segment) in only}
            for k in taken:
                del self._series[k]
            trcs = [m for m in self._trc if (m.line, m.segment) in only]
            self._trc = [m for m in self._trc if (m.line, m.segment) not in only]
        for msg in taken.values():
            key = (msg.line, msg.segment)
            if isinstance(msg, SegmentState):
                states[key].append(msg)
            elif key in self._plotted:
                points[(key, "onboard")].append(msg)
            else:  # kept for when the segment is plotted: half the chunks of the history
                kept = self._onboard_kept[key]
                day = event_day(msg.t)
                if day not in kept or kept[day].t <= msg.t:
                    kept[day] = msg
                for old in sorted(kept)[:-ONBOARD_KEPT_DAYS]:
                    del kept[old]
        for trc in trcs:
            points[((trc.line, trc.segment), "trc")].append(trc)
        for key, batch in states.items():
            self._log_states(key, sorted(batch, key=lambda s: s.t))
        for (key, kind), batch in points.items():
            self._log_points(key, kind, sorted(batch, key=lambda m: m.t))

    def _log_states(self, key: SegmentKey, states: list[SegmentState]) -> None:
        line, segment = key
        base = f"segments/{line}/{segment}"
        for levels in dict.fromkeys(tuple(s.limit_levels) for s in states):
            same = [s for s in states if tuple(s.limit_levels) == levels]
            for i, indicator in enumerate(same[-1].indicators):
                rows = [s for s in same if i < len(s.indicators) and s.indicators[i] == indicator]
                path = f"{base}/{indicator}/state"
                self._levels[path] = levels
                if key in self._plotted and self._styled.get(path) != levels:
                    self.rec.log(path, state_style(levels), static=True)
                    self._styled[path] = levels
                values = np.array(
                    [
                        [
                            math.exp(s.mean.array()[i]),
                            s.ci_low_mm.array()[i],
                            s.ci_high_mm.array()[i],
                            *s.limits_mm.array()[:, i],
                        ]
                        for s in rows
                    ]
                )
                self._send(path, np.array([s.t for s in rows]), values)

    def _log_points(self, key: SegmentKey, kind: str, msgs: list[OnboardIndex | TrcRecord]) -> None:
        t = np.array([m.t for m in msgs])
        base = f"segments/{key[0]}/{key[1]}"
        for indicator in INDICATORS:
            path = f"{base}/{indicator}/{kind}"
            if key in self._plotted and path not in self._styled:
                self.rec.log(path, _POINTS[kind], static=True)
                self._styled[path] = ()
            self._send(path, t, np.array([getattr(m, f"{indicator}_mm") for m in msgs]))

    def _send(self, path: str, t: np.ndarray, values: np.ndarray) -> None:
        """Rows of scalars at event times ``t``: one chunk (``values`` is (rows,) or
        (rows, instances))."""
        self.rec.send_columns(
            path,
            indexes=[rr.TimeColumn(TIMELINE, timestamp=t)],
            columns=rr.Scalars.columns(scalars=values.astype(float)),
        )
        self.rows_written += len(t)

    # --- live: map colours, trains, alerts ------------------------------------------------

    def _flush_live(self) -> None:
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
                ),
            )
        self._fixes_new = False
        for alert in sorted(self._alerts, key=lambda a: a.t):
            self._log_alert(alert)
        self._alerts.clear()

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

    # --- blueprint -----------------------------------------------------------------------

    def _style(self, keys: Iterable[SegmentKey]) -> None:
        """The static series styles of newly plotted segments' entities."""
        for key in keys:
            if key in self._plotted:
                continue
            self._plotted.add(key)
            base = f"segments/{key[0]}/{key[1]}"
            for indicator in INDICATORS:
                path = f"{base}/{indicator}/state"
                levels = self._levels.get(path)
                if levels is not None:
                    self.rec.log(path, state_style(levels), static=True)
                    self._styled[path] = levels
                for kind, style in _POINTS.items():
                    self.rec.log(f"{base}/{indicator}/{kind}", style, static=True)
                    self._styled[f"{base}/{indicator}/{kind}"] = ()
            kept = self._onboard_kept.pop(key, {})
            if kept:
                self._log_points(key, "onboard", sorted(kept.values(), key=lambda m: m.t))

    def worst(self) -> list[SegmentKey]:
        """The segments to plot: :func:`select_worst_sticky` around the plotted ones."""
        return select_worst_sticky(
            self.p_exceed, self.worst_n, self._blueprint_keys or [], WORST_MARGIN
        )

    def maybe_send_blueprint(self, now: float, *, force: bool = False) -> bool:
        """Send the blueprint if the worst set changed and ``blueprint_interval_s`` of wall
        time ``now`` (monotonic seconds) passed since the last send, or at once if it fills
        the plots for the first time (``worst_n`` segments known); ``force``: if it changed
        (or was never sent), now. True if sent.

        Rerun's gRPC server keeps every blueprint and a browser that connects replays them
        all before any data (about 15 s for 7 of them on SwiftShader): send few."""
        worst = self.worst()
        first_full = len(worst) == self.worst_n and len(self._blueprint_keys or ()) < len(worst)
        if (
            not force
            and not first_full
            and self._blueprint_at is not None
            and now - self._blueprint_at < self.blueprint_interval_s
        ):
            return False
        if self._blueprint_keys is not None and set(worst) == set(self._blueprint_keys):
            return False
        self.rec.send_blueprint(
            build_blueprint([(*key, self.p_exceed[key]) for key in worst], self._bounds),
            make_active=True,
            make_default=True,
        )
        self._blueprint_keys = worst
        self._blueprint_at = now
        self._style(worst)
        self.blueprints_sent += 1
        return True


def _screen(xy: np.ndarray) -> np.ndarray:
    """Local (x east, y north) metres to Rerun's y-down 2D frame: north up on screen."""
    return np.asarray(xy, dtype=float) * np.array([1.0, -1.0])
