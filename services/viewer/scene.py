"""What the viewer draws and where: entity paths, colours, series styles, the one blueprint,
the static map and its legend, and the health board. :mod:`services.viewer.core` decides
when to write what.

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
``map/plan/tamping``                              the planner's tampings of the next weeks:
                                                  one blue halo per possession under the
                                                  segments, darker the sooner, labelled
                                                  with its week and Monday
``map/trains``                                    last GPS fix of every train (fix_quality > 0)
``alerts``                                        TextLog: raised = WARN, cleared = INFO
``health``                                        TextDocument: services alive, restarts,
                                                  stalled flows
================================================  ==========================================

Map frame: local metres of :meth:`track.network.Network.to_xy` (x east, y north) with y
negated on logging (:func:`screen_xy`), because Rerun's 2D view draws y downwards
(rerun#1387): north is up on screen.
"""

from __future__ import annotations

import re
from collections.abc import Mapping, Sequence

import numpy as np
import rerun as rr
import rerun.blueprint as rrb
from rerun.encodings import TimeRange

from schemas import DAY_S, INDICATORS, StackHealth
from schemas.keys import SegmentId
from track.network import Line, Network

TIMELINE = "event_time"  # timestamp timeline of the messages' event time t (epoch s)
MAP_PATH = "map/segments"  # every segment of the network, one line strip each
PLAN_PATH = "map/plan/tamping"  # the planned tampings of the next weeks, one strip a possession
RANKING_PATH = "worst/ranking"
HEALTH_PATH = "health"
SELECTED = "selected"
PLOT_WINDOW_DAYS = 90.0  # event days before the time cursor that the plots show
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
DRAW_ORDER = {
    "tunnels": 10.0,
    "plan": 15.0,
    "segments": 20.0,
    "stations": 30.0,
    "trains": 40.0,
    "labels": 50.0,
}
_PLAN_SOON_RGB = np.array([20, 70, 230.0])  # a possession of week 0
_PLAN_LATE_RGB = np.array([150, 200, 255.0])  # one of the last week the map shows


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


def style_columns(kind: str, levels: Sequence[str], prefix: str, rows: int) -> list[object]:
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
            column_shares=[3, 5, 3],  # the plotted segments: long line names
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


def plan_color(week: int, weeks: int) -> tuple[int, int, int]:
    """RGB of a possession in ``week`` of the ``weeks`` the map shows: darker the sooner."""
    f = week / max(weeks - 1, 1)
    rgb = np.rint(_PLAN_SOON_RGB + f * (_PLAN_LATE_RGB - _PLAN_SOON_RGB)).astype(int)
    return int(rgb[0]), int(rgb[1]), int(rgb[2])


def plan_strips(
    rec: rr.RecordingStream,
    network: Network,
    possessions: Sequence[tuple[int, str, list[str]]],
    weeks: int,
    week0_t: float,
) -> int:
    """Log the possessions (``(week, line, segment ids)``, adjacent segments of one line) as
    halos under the segments at the current time, each labelled ``tamp w{week} {MM-DD}``;
    none: an empty layer. How many strips were logged."""
    from datetime import UTC, datetime

    strips, colors, labels = [], [], []
    for week, line_id, segment_ids in possessions:
        line = network.lines.get(line_id)
        if line is None:
            continue
        by_id = {seg.id: seg for seg in line.segments}
        segs = sorted((by_id[s] for s in segment_ids if s in by_id), key=lambda g: g.index)
        if not segs:
            continue
        chainage = line.chainage_m
        inside = chainage[(chainage > segs[0].start_m) & (chainage < segs[-1].end_m)]
        at = np.r_[segs[0].start_m, inside, segs[-1].end_m]
        strips.append(screen_xy(line.xy_at(at)))
        colors.append(plan_color(week, weeks))
        monday = datetime.fromtimestamp(week0_t + week * 7 * DAY_S, UTC).strftime("%m-%d")
        labels.append(f"tamp w{week} {monday}")
    rec.log(
        PLAN_PATH,
        rr.LineStrips2D(
            strips,
            radii=rr.Radius.ui_points(7.0),
            colors=colors,
            labels=labels,
            show_labels=True,
            draw_order=DRAW_ORDER["plan"],
        ),
    )
    return len(strips)


def screen_xy(xy: np.ndarray) -> np.ndarray:
    """Local (x east, y north) metres to Rerun's y-down 2D frame: north up on screen."""
    return np.asarray(xy, dtype=float) * np.array([1.0, -1.0])


def log_static_map(rec: rr.RecordingStream, network: Network) -> tuple[list[SegmentId], np.ndarray]:
    """Log the network (segments, tunnels, stations, line names) and the colour legend as
    static entities; the segments in the order of :data:`MAP_PATH`'s strips, and the map's
    bounds ``[[x_min, y_min], [x_max, y_max]]`` in logged coordinates."""
    lines = list(network.lines.values())
    xy = screen_xy(np.concatenate([ln.xy for ln in lines]))
    lo, hi = xy.min(axis=0), xy.max(axis=0)
    span = float((hi - lo).max())
    keys = [(line.id, seg.id) for line in lines for seg in line.segments]
    strips = [
        screen_xy(network.to_xy(line.segment_lonlat(seg)))
        for line in lines
        for seg in line.segments
    ]
    # one entity for the whole network: one chunk per colour change, not one per segment
    rec.log(
        MAP_PATH,
        rr.LineStrips2D(
            strips,
            radii=rr.Radius.ui_points(3.5),
            labels=[f"{line}/{segment}" for line, segment in keys],
            show_labels=False,
            draw_order=DRAW_ORDER["segments"],
        ),
        static=True,
    )
    names = _log_features(rec, lines, span)
    legend_at = _log_legend(rec, np.array([lo[0], hi[1]]), span)
    everything = np.vstack([xy, legend_at, names])
    margin = 0.05 * span
    return keys, np.stack([everything.min(axis=0) - margin, everything.max(axis=0) + margin])


def _log_features(rec: rr.RecordingStream, lines: list[Line], span: float) -> np.ndarray:
    """Log the tunnels, stations and line names; where the names are."""
    tunnels, tunnel_labels = [], []
    stations, station_labels = [], []
    names, name_labels = [], []
    for line in lines:
        for a, b in line.tunnels:
            chainage = np.r_[a, line.chainage_m[(line.chainage_m > a) & (line.chainage_m < b)], b]
            tunnels.append(screen_xy(line.xy_at(chainage)))
            tunnel_labels.append(f"{line.id} tunnel {a / 1e3:.1f}–{b / 1e3:.1f} km")
        station_names = line.station_names or [""] * len(line.stations)
        for c, station_name in zip(line.stations, station_names, strict=True):
            stations.append(screen_xy(line.xy_at(c)))
            where = f"{line.id} km {c / 1e3:.1f}"
            station_labels.append(f"{station_name} ({where})" if station_name else where)
        # the line's name beyond both of its ends
        for end, inward in ((0.0, 1.0), (line.length_m, -1.0)):
            ahead = line.xy_at(np.clip(end + inward * 0.02 * span, 0, line.length_m))
            at = line.xy_at(end)
            direction = (at - ahead) / max(1e-9, float(np.hypot(*(at - ahead))))
            where = screen_xy(at + direction * 0.025 * span)
            # the tracks of a double-track line end a few metres apart: their names one
            # below the other, not on top of each other
            while any(np.hypot(*(where - other)) < 0.02 * span for other in names):
                where = where + np.array([0.0, 0.035 * span])
            names.append(where)
            name_labels.append(f"{line.id} {line.name}" if line.name else line.id)
    if tunnels:
        rec.log(
            "map/tunnels",
            rr.LineStrips2D(
                tunnels,
                radii=rr.Radius.ui_points(8.0),
                colors=(35, 35, 45),
                labels=tunnel_labels,
                show_labels=False,
                draw_order=DRAW_ORDER["tunnels"],
            ),
            static=True,
        )
    if stations:
        rec.log(
            "map/stations",
            rr.Points2D(
                np.array(stations),
                radii=rr.Radius.ui_points(4.0),
                colors=(70, 70, 80),
                labels=station_labels,
                show_labels=False,  # on hover: names on the map would hide the colours
                draw_order=DRAW_ORDER["stations"],
            ),
            static=True,
        )
    rec.log("map/lines", _labels(np.array(names), name_labels, 1.0), static=True)
    return np.array(names)


def _log_legend(rec: rr.RecordingStream, corner: np.ndarray, span: float) -> np.ndarray:
    """Log the colour scale below the network's lower left ``corner``: small swatches, their
    labels in a neutral colour beside them (coloured text would add to the colours of the
    map); where the swatches are."""
    step = 0.045 * span
    legend_at = (
        corner
        + np.array([0.0, 2 * step])
        + np.array([0.0, step]) * np.arange(len(LEGEND_P) + 1)[:, None]
    )
    labels = [f"p = {p:g}" for p in LEGEND_P] + ["no state yet"]
    colors = np.vstack([exceedance_color(np.array(LEGEND_P)), [UNKNOWN_RGB]])
    rec.log(
        "map/legend/colors",
        rr.Points2D(
            legend_at,
            radii=rr.Radius.ui_points(4.0),
            colors=colors,
            draw_order=DRAW_ORDER["labels"],
        ),
        static=True,
    )
    # a label is drawn below its point
    rec.log(
        "map/legend/labels",
        _labels(legend_at + [0.12 * span, -0.7 * step], labels, 0.5),
        static=True,
    )
    return legend_at


def _labels(at: np.ndarray, labels: list[str], radius: float) -> rr.Points2D:
    """Text shown on the map at ``at``, in a neutral colour."""
    return rr.Points2D(
        at,
        radii=rr.Radius.ui_points(radius),
        colors=(20, 20, 30),
        labels=labels,
        show_labels=True,
        draw_order=DRAW_ORDER["labels"],
    )
