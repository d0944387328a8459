"""The viewer's pure core: TrackFusion messages in, Rerun log calls out.

No Zenoh, no clock, no sink: :class:`ViewerCore` logs to the ``rerun.RecordingStream`` it
is given, and the adapter (``service.py``) decides where that stream goes (native viewer,
web viewer, ``.rrd`` file) and passes wall time in where the blueprint's rate limit needs it.

Time: every temporal row is stamped on the timeline :data:`TIMELINE` (``"event_time"``),
a timestamp timeline holding each message's own event time ``t`` (UTC epoch seconds), so
late or replayed messages land where they belong. Rerun also adds ``log_time``/``log_tick``
to rows logged with ``log``; batches sent with ``send_columns`` carry only ``event_time``.

Entity paths (values in mm; ``{ind}`` is ``top6`` or ``align10``):

================================================  ==========================================
``segments/{line}/{segment}/{ind}/estimate``      exp of the state's mixture mean of ln mm
``segments/{line}/{segment}/{ind}/ci_low``        2.5 % marginal quantile (95 % band, low)
``segments/{line}/{segment}/{ind}/ci_high``       97.5 % marginal quantile (band, high)
``segments/{line}/{segment}/{ind}/limit_{level}`` the limits the state refers to
``segments/{line}/{segment}/{ind}/onboard``       raw on-board index (points; not de-biased)
``segments/{line}/{segment}/{ind}/trc``           TRC record (points)
``map/segments/{line}``                           one line strip per segment, coloured by
                                                  exceedance probability (green → red)
``map/trains/{train}``                            last GPS fix of a train (fix_quality > 0)
``alerts``                                        TextLog: raised = WARN, cleared = INFO
================================================  ==========================================

Map frame: local metres of :meth:`simulators.network.Network.to_xy` (x east, y north)
with y negated on logging, because Rerun's 2D view draws y downwards (rerun#1387): north
is up on screen. Strip geometry and labels are static; only the colours are temporal, so
the map is drawn before the first state and a colour change re-logs one array per line.
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

from schemas import INDICATORS, Alert, GpsFix, Message, OnboardIndex, SegmentState, TrcRecord
from simulators.network import Network

TIMELINE = "event_time"  # timestamp timeline of the messages' event time t (epoch s)
INTERVENTION = "intervention"  # the limit level the map colour and the worst ranking use
DEFAULT_WORST_N = 3
DEFAULT_BLUEPRINT_INTERVAL_S = 5.0  # wall seconds between two blueprint re-sends, at least

UNKNOWN_RGB = (128, 128, 128)  # a segment without a state yet
_STOPS_P = np.array([0.0, 0.5, 1.0])
_STOPS_RGB = np.array([(40, 170, 60), (240, 200, 30), (220, 40, 40)], dtype=float)  # green→red

SegmentKey = tuple[str, str]  # (line, segment)

_STYLES: dict[str, rr.AsComponents] = {
    "estimate": rr.SeriesLines(colors=(80, 160, 255), widths=2.0, names="estimate"),
    "ci_low": rr.SeriesLines(colors=(80, 160, 255, 110), widths=1.0, names="95% low"),
    "ci_high": rr.SeriesLines(colors=(80, 160, 255, 110), widths=1.0, names="95% high"),
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
    rows = [
        rrb.Horizontal(
            *(
                rrb.TimeSeriesView(
                    origin=f"segments/{line}/{segment}/{indicator}",
                    contents="$origin/**",
                    name=f"{line}/{segment} {indicator} mm (p={p:.2f})",
                    plot_legend=rrb.PlotLegend(visible=False),  # small plots: hover for names
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
class _MapLine:
    keys: list[SegmentKey]  # strip order
    index: dict[str, int]  # segment id -> strip
    colors: np.ndarray  # (k, 3) uint8, what was logged last


class ViewerCore:
    """Logs TrackFusion messages to ``rec``; one instance per recording, one thread.

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
    """

    def __init__(
        self,
        rec: rr.RecordingStream,
        network: Network | None = None,
        *,
        worst_n: int = DEFAULT_WORST_N,
        blueprint_interval_s: float = DEFAULT_BLUEPRINT_INTERVAL_S,
    ) -> None:
        if worst_n < 0:
            raise ValueError(f"worst_n: must be >= 0, got {worst_n}")
        self.rec = rec
        self.network = network
        self.worst_n = worst_n
        self.blueprint_interval_s = blueprint_interval_s
        self.p_exceed: dict[SegmentKey, float] = {}
        self.handled = 0  # messages taken (GPS fixes without a fix included)
        self.blueprints_sent = 0
        self._styled: set[str] = set()
        self._lines: dict[str, _MapLine] = {}
        self._map_started = False
        self._blueprint_keys: list[SegmentKey] | None = None
        self._blueprint_at: float | None = None
        self._bounds: np.ndarray | None = None

    # --- setup ---------------------------------------------------------------------------

    def start(self, now: float) -> None:
        """Log the static map geometry and send the first blueprint (map and alerts)."""
        if self.network is not None:
            xy = _screen(np.concatenate([ln.xy for ln in self.network.lines.values()]))
            margin = 0.05 * (xy.max(axis=0) - xy.min(axis=0)).max()
            self._bounds = np.stack([xy.min(axis=0) - margin, xy.max(axis=0) + margin])
            for line in self.network.lines.values():
                keys = [(line.id, seg.id) for seg in line.segments]
                strips = [
                    _screen(self.network.to_xy(line.segment_lonlat(s))) for s in line.segments
                ]
                self.rec.log(
                    f"map/segments/{line.id}",
                    rr.LineStrips2D(
                        strips,
                        radii=rr.Radius.ui_points(3.5),
                        labels=[f"{line.id}/{seg.id}" for seg in line.segments],
                        show_labels=False,
                    ),
                    static=True,
                )
                self._lines[line.id] = _MapLine(
                    keys,
                    {seg.id: i for i, seg in enumerate(line.segments)},
                    np.zeros((len(keys), 3), np.uint8),
                )
        self.maybe_send_blueprint(now, force=True)

    # --- messages ------------------------------------------------------------------------

    def log_batch(self, messages: Iterable[Message]) -> int:
        """Log a batch: series grouped per entity (``send_columns`` when several rows),
        map colours re-logged once per line whose colours changed. Returns the count."""
        states: dict[SegmentKey, list[SegmentState]] = defaultdict(list)
        points: dict[tuple[SegmentKey, str], list[OnboardIndex | TrcRecord]] = defaultdict(list)
        fixes: dict[str, GpsFix] = {}
        alerts: list[Alert] = []
        n = 0
        for msg in messages:
            n += 1
            match msg:
                case SegmentState():
                    states[(msg.line, msg.segment)].append(msg)
                case OnboardIndex():
                    points[((msg.line, msg.segment), "onboard")].append(msg)
                case TrcRecord():
                    points[((msg.line, msg.segment), "trc")].append(msg)
                case GpsFix():
                    newest = fixes.get(msg.train)
                    if msg.fix_quality > 0 and (newest is None or msg.t >= newest.t):
                        fixes[msg.train] = msg
                case Alert():
                    alerts.append(msg)
                case _:
                    raise TypeError(f"viewer: cannot log a {type(msg).__name__}")
        if n == 0:
            return 0
        times = list(_times(states, points, fixes, alerts))
        if times and not self._map_started:
            self._start_map_colors(min(times))
        for key, batch in states.items():
            self._log_states(key, sorted(batch, key=lambda s: s.t))
        for (key, kind), batch in points.items():
            self._log_points(key, kind, sorted(batch, key=lambda m: m.t))
        for fix in fixes.values():
            self._log_fix(fix)
        for alert in sorted(alerts, key=lambda a: a.t):
            self._log_alert(alert)
        self._update_map(states)
        self.handled += n
        return n

    def _log_states(self, key: SegmentKey, states: list[SegmentState]) -> None:
        line, segment = key
        t = np.array([s.t for s in states])
        base = f"segments/{line}/{segment}"
        for i, indicator in enumerate(states[-1].indicators):
            path = f"{base}/{indicator}"
            if not all(i < len(s.indicators) and s.indicators[i] == indicator for s in states):
                continue  # a state with another indicator order: skip rather than mix series
            self._series(
                f"{path}/estimate", "estimate", t, [math.exp(s.mean.array()[i]) for s in states]
            )
            self._series(f"{path}/ci_low", "ci_low", t, [s.ci_low_mm.array()[i] for s in states])
            self._series(f"{path}/ci_high", "ci_high", t, [s.ci_high_mm.array()[i] for s in states])
            for j, level in enumerate(states[-1].limit_levels):
                same = [s for s in states if j < len(s.limit_levels) and s.limit_levels[j] == level]
                self._series(
                    f"{path}/limit_{level}",
                    f"limit_{level}",
                    np.array([s.t for s in same]),
                    [s.limits_mm.array()[j, i] for s in same],
                )
        self.p_exceed[key] = segment_exceedance(states[-1])

    def _log_points(self, key: SegmentKey, kind: str, msgs: list[OnboardIndex | TrcRecord]) -> None:
        t = np.array([m.t for m in msgs])
        base = f"segments/{key[0]}/{key[1]}"
        for indicator in INDICATORS:
            values = [getattr(m, f"{indicator}_mm") for m in msgs]
            self._series(f"{base}/{indicator}/{kind}", kind, t, values)

    def _series(self, path: str, style: str, t: np.ndarray, values: Sequence[float]) -> None:
        """Scalars at event times: one row with ``set_time`` + ``log``, more with a batch."""
        if len(t) == 0:
            return
        if path not in self._styled:
            self.rec.log(path, _style(style), static=True)
            self._styled.add(path)
        if len(t) == 1:
            self.rec.set_time(TIMELINE, timestamp=float(t[0]))
            self.rec.log(path, rr.Scalars(float(values[0])))
        else:
            self.rec.send_columns(
                path,
                indexes=[rr.TimeColumn(TIMELINE, timestamp=t)],
                columns=rr.Scalars.columns(scalars=np.asarray(values, dtype=float)),
            )

    def _log_fix(self, fix: GpsFix) -> None:
        if self.network is None:
            return
        xy = _screen(self.network.to_xy([fix.lon_deg, fix.lat_deg]))
        self.rec.set_time(TIMELINE, timestamp=fix.t)
        self.rec.log(
            f"map/trains/{fix.train}",
            rr.Points2D(
                [xy], radii=rr.Radius.ui_points(6.0), colors=(0, 200, 255), labels=fix.train
            ),
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

    # --- map -----------------------------------------------------------------------------

    def _start_map_colors(self, t: float) -> None:
        """Grey for every segment at the first event time seen (temporal colours can't start
        earlier: static colours would hide every later change)."""
        self._map_started = True
        self.rec.set_time(TIMELINE, timestamp=t)
        for line_id, line in self._lines.items():
            line.colors[:] = UNKNOWN_RGB
            self.rec.log(f"map/segments/{line_id}", rr.LineStrips2D.from_fields(colors=line.colors))

    def _update_map(self, states: Mapping[SegmentKey, list[SegmentState]]) -> None:
        newest: dict[str, float] = {}
        for (line_id, segment), batch in states.items():
            line = self._lines.get(line_id)
            i = line.index.get(segment) if line is not None else None
            if line is None or i is None:
                continue  # not on the map
            rgb = exceedance_color(self.p_exceed[(line_id, segment)])
            if not np.array_equal(line.colors[i], rgb):
                line.colors[i] = rgb
                newest[line_id] = max(newest.get(line_id, -math.inf), max(s.t for s in batch))
        for line_id, t in newest.items():
            self.rec.set_time(TIMELINE, timestamp=t)
            self.rec.log(
                f"map/segments/{line_id}",
                rr.LineStrips2D.from_fields(colors=self._lines[line_id].colors),
            )

    # --- blueprint -----------------------------------------------------------------------

    def worst(self) -> list[SegmentKey]:
        return select_worst(self.p_exceed, self.worst_n)

    def maybe_send_blueprint(self, now: float, *, force: bool = False) -> bool:
        """Send the blueprint if the worst set changed and ``blueprint_interval_s`` of wall
        time ``now`` (monotonic seconds) passed since the last send; ``force``: if it changed
        (or was never sent), now. True if sent."""
        if (
            not force
            and self._blueprint_at is not None
            and now - self._blueprint_at < self.blueprint_interval_s
        ):
            return False
        worst = self.worst()
        if self._blueprint_keys is not None and set(worst) == set(self._blueprint_keys):
            return False
        self.rec.send_blueprint(
            build_blueprint([(*key, self.p_exceed[key]) for key in worst], self._bounds),
            make_active=True,
            make_default=True,
        )
        self._blueprint_keys = worst
        self._blueprint_at = now
        self.blueprints_sent += 1
        return True


def _style(name: str) -> rr.AsComponents:
    if name in _STYLES:
        return _STYLES[name]
    level = name.removeprefix("limit_")
    return rr.SeriesLines(
        colors=_LIMIT_RGB.get(level, (200, 200, 200)), widths=1.5, names=f"{level} limit"
    )


def _screen(xy: np.ndarray) -> np.ndarray:
    """Local (x east, y north) metres to Rerun's y-down 2D frame: north up on screen."""
    return np.asarray(xy, dtype=float) * np.array([1.0, -1.0])


def _times(states, points, fixes, alerts) -> Iterable[float]:
    for batch in (*states.values(), *points.values()):
        yield from (m.t for m in batch)
    yield from (f.t for f in fixes.values())
    yield from (a.t for a in alerts)
