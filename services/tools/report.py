"""`trackfusion report`: one self-contained HTML file for a maintenance planner.

The map of the line(s) coloured by P(exceeding the intervention limit), the segments ranked
by it with their estimates, 95 % intervals, forecasts and next TRC run, forecast fans of the
worst segments, the open alerts, and the planner's tamping plan (per line a weeks × chainage
grid of the planned tampings, their possessions and deadlines, then the TRC runs the plan
recommends). Inline CSS and SVG only: no script, no external
resource, so it renders offline from a mail attachment.

Pure part: :func:`render` (``ReportData`` → HTML text) and its helpers, tested without
Zenoh. Thin part: :func:`main` asks the running system like :mod:`services.tools.operator` does.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from dataclasses import dataclass
from datetime import UTC, datetime
from html import escape
from pathlib import Path
from typing import TextIO

from schemas import (
    DAY_S,
    Alert,
    InspectionPlan,
    MaintenancePlan,
    RaisedAlerts,
    SchemaError,
    SegmentState,
    decode,
    keys,
)
from services.defaults import add_network_argument
from services.limits import DEFAULT_LIMITS_FILE, Limits, add_limits_argument, load_limits
from services.runtime.config import RuntimeConfig, config_from_args
from services.tools import maintenance_plan, operator
from services.tools.network_map import NetworkMap, network_map

INTERVENTION = "intervention"
WORST_N = 6
DEFAULT_OUT = "report.html"  # `--out`
# P(exceed) bins of the map and the table: (upper bound, colour, label). The edges follow
# the alerting defaults: predicted exceedance raises at 0.3, exceedance at 0.5.
BINS: tuple[tuple[float, str, str], ...] = (
    (0.1, "#1a9850", "below 0.1"),
    (0.3, "#91cf60", "0.1 – 0.3"),
    (0.5, "#f6d32d", "0.3 – 0.5"),
    (0.8, "#f46d43", "0.5 – 0.8"),
    (math.inf, "#d73027", "0.8 and above"),
)
NO_STATE = "#b0b0b0"  # a segment of the network without a state
MAP_W, MAP_H_MAX = 800, 560  # px


# --- data -----------------------------------------------------------------------------------


@dataclass(frozen=True)
class ReportData:
    """Everything one report shows. ``alerts``/``plan`` are None when alerting did not
    answer; ``missing`` then says why. ``tamping`` is None when the planner did not
    answer; ``tamping_missing`` then says why."""

    states: list[SegmentState]
    network: NetworkMap
    made_at: float  # wall clock, epoch s
    alerts: list[Alert] | None = None
    plan: InspectionPlan | None = None
    missing: str = ""
    lines: tuple[str, ...] = ()  # the lines asked for; () = all
    worst_n: int = WORST_N
    tamping: MaintenancePlan | None = None
    tamping_missing: str = ""
    limits: Limits | None = None  # the limits file, with the network's line speeds


def level_index(state: SegmentState, level: str = INTERVENTION) -> int:
    """Index of ``level`` in the state's limit levels; the last (strictest) if absent."""
    levels = state.limit_levels
    return levels.index(level) if level in levels else len(levels) - 1


def p_now(state: SegmentState) -> float:
    """P(exceeding the intervention limit) now, max over indicators."""
    return float(state.p_exceed.array()[level_index(state)].max())


def p_forecast(state: SegmentState) -> dict[float, float]:
    """{horizon days: P(exceeding the intervention limit) then, max over indicators}."""
    p = state.forecast_p_exceed.array()[:, level_index(state), :].max(axis=1)
    return {float(h): float(v) for h, v in zip(state.horizons_days.array(), p, strict=True)}


def colour(p: float | None) -> str:
    """The map and table colour of a probability (None: no state)."""
    if p is None or math.isnan(p):
        return NO_STATE
    return next(c for upper, c, _ in BINS if p < upper)


def ranked(states: list[SegmentState]) -> list[SegmentState]:
    """Highest P(exceed) first; ties by line and segment."""
    return sorted(states, key=lambda s: (-p_now(s), s.line, s.segment))


def iso(t: float | None, spec: str = "minutes") -> str:
    if t is None:
        return "–"
    return datetime.fromtimestamp(t, UTC).isoformat(timespec=spec).replace("+00:00", " UTC")


def day(t: float | None) -> str:
    return "–" if t is None else datetime.fromtimestamp(t, UTC).strftime("%Y-%m-%d")


# --- rendering ------------------------------------------------------------------------------

CSS = """
body{font:14px/1.4 system-ui,-apple-system,"Segoe UI",Roboto,sans-serif;margin:16px;color:#222}
h1{font-size:20px;margin:0 0 4px}h2{font-size:16px;margin:20px 0 6px}
.meta{color:#555;margin:0 0 6px}.note{background:#fff4ce;border:1px solid #e0c060;padding:6px}
table{border-collapse:collapse;font-size:12px}th,td{border:1px solid #ccc;padding:2px 6px}
th{background:#eee;text-align:left}td.n{text-align:right;font-variant-numeric:tabular-nums}
td.p{text-align:right;font-weight:600}.legend span{display:inline-block;margin-right:12px}
.legend i{display:inline-block;width:14px;height:10px;margin-right:4px;vertical-align:middle}
.fans{display:flex;flex-wrap:wrap;gap:12px}.fan{border:1px solid #ddd;padding:4px}
.fan h3{font-size:13px;margin:0 0 2px}svg text{font-family:inherit}
"""


def render(data: ReportData) -> str:
    """The whole HTML document."""
    states = ranked(data.states)
    title = "TrackFusion track geometry report"
    if data.lines:
        title += " — " + ", ".join(data.lines)
    parts = [
        "<!DOCTYPE html>",
        '<html lang="en"><head><meta charset="utf-8">',
        f"<title>{escape(title)}</title><style>{CSS}</style></head><body>",
        _header(data, states, title),
        '<h2 id="map-title">Map: P(exceeding the intervention limit) now</h2>',
        _map(data, states),
        _legend(),
    ]
    if data.limits is not None:
        parts += ['<h2 id="limits">Limits by line</h2>', _limits(data, data.limits)]
    if data.missing:
        parts.append(f'<p class="note">{escape(data.missing)}</p>')
    parts += [
        "<h2>Segments, highest P(exceed) first</h2>",
        _table(data, states),
        f"<h2>Forecast fans of the {min(data.worst_n, len(states))} worst segments</h2>",
        _fans(states[: data.worst_n]),
        "<h2>Open alerts</h2>",
        _alerts(data),
        '<h2 id="tamping">Tamping plan</h2>',
        _tamping(data),
        "</body></html>",
    ]
    return "\n".join(parts) + "\n"


def _header(data: ReportData, states: list[SegmentState], title: str) -> str:
    newest = max((s.t for s in states), default=None)
    high = sum(p_now(s) >= 0.5 for s in states)
    lines = sorted({s.line for s in states})
    return (
        f"<h1>{escape(title)}</h1>"
        f'<p class="meta">Made {escape(iso(data.made_at, "seconds"))} (wall clock). '
        f"Newest state: {escape(iso(newest))} (event time). "
        f"{len(states)} segments on {len(lines)} line(s) "
        f"({escape(', '.join(map(data.network.label, lines)))}); "
        f"{high} with P(exceed) ≥ 0.5.</p>"
        "<p>Each 200 m segment's track geometry is estimated from the last Track Recording "
        "Car (TRC) record and the on-board indices of in-service trains since then. Top6 and "
        "Align10 are in mm; the estimate is the median and [low, high] the 95 % credible "
        "interval: the true value lies in it with probability 0.95. <b>P(exceed)</b> is the "
        "probability that the segment's worse indicator is above its intervention limit now; "
        'the "in … d" columns are the same probability at the forecast horizons if nothing '
        "is done until then. "
        "The fans show how the interval widens with the forecast against the alert and "
        "intervention limits. Next TRC is the expected next run of the line's recording "
        "car; alerts are those raised now.</p>"
    )


def _project(points: list[tuple[float, float]], lat0: float) -> list[tuple[float, float]]:
    k = math.cos(math.radians(lat0))
    return [(lon * k, -lat) for lon, lat in points]


def _map(data: ReportData, states: list[SegmentState]) -> str:
    wanted = set(data.lines)
    by_key = {(s.line, s.segment): s for s in states}
    polylines = {
        key: pts
        for key, pts in data.network.polylines.items()
        if (not wanted or key[0] in wanted) and len(pts) >= 2
    }
    stations = [s for s in data.network.stations if not wanted or s.line in wanted]
    if not polylines:
        return '<p class="note">No geometry for these segments in the network file.</p>'
    lat0 = sum(p[1] for pts in polylines.values() for p in pts) / sum(
        len(pts) for pts in polylines.values()
    )
    projected = {key: _project(pts, lat0) for key, pts in polylines.items()}
    xs = [x for pts in projected.values() for x, _ in pts]
    ys = [y for pts in projected.values() for _, y in pts]
    x0, y0 = min(xs), min(ys)
    span = max(max(xs) - x0, (max(ys) - y0) * MAP_W / MAP_H_MAX, 1e-9)
    pad = 30
    scale = (MAP_W - 2 * pad) / span
    height = round((max(ys) - y0) * scale + 2 * pad)

    def xy(x: float, y: float) -> str:
        return f"{pad + (x - x0) * scale:.1f},{pad + (y - y0) * scale:.1f}"

    out = [
        f'<svg id="map" width="{MAP_W}" height="{height}" '
        f'viewBox="0 0 {MAP_W} {height}" role="img" aria-label="map" '
        'style="background:#fafafa;border:1px solid #ccc">'
    ]
    # segments without a state first, so that coloured ones are drawn over them
    order = sorted(projected, key=lambda k: (k in by_key, p_now(by_key[k]) if k in by_key else 0))
    for key in order:
        state = by_key.get(key)
        p = p_now(state) if state is not None else None
        tip = f"{key[0]}/{key[1]}: " + ("no state" if p is None else f"P(exceed) {p:.2f}")
        points = " ".join(xy(*pt) for pt in projected[key])
        out.append(
            f'<polyline points="{points}" fill="none" stroke="{colour(p)}" stroke-width="5" '
            f'stroke-linecap="round"><title>{escape(tip)}</title></polyline>'
        )
    placed: list[tuple[float, float]] = []
    for line in sorted({k[0] for k in projected}):
        first = min((k for k in projected if k[0] == line), key=lambda k: k[1])
        x, y = map(float, xy(*projected[first][0]).split(","))
        y -= 8
        # the tracks of a double-track line start a few metres apart: one name below the other
        while any(abs(x - px) < 40 and abs(y - py) < 14 for px, py in placed):
            y += 16
        placed.append((x, y))
        # a line starting in the right half is named leftwards, so that its name stays inside
        anchor = ' text-anchor="end"' if x > MAP_W / 2 else ""
        out.append(
            f'<text x="{x:.1f}" y="{y:.1f}"{anchor} font-size="13" font-weight="bold" '
            f'fill="#222">{escape(data.network.label(line))}</text>'
        )
    for st in stations:
        x, y = xy(*_project([(st.lon, st.lat)], lat0)[0]).split(",")
        out.append(
            f'<circle cx="{x}" cy="{y}" r="3.5" fill="#fff" stroke="#222" stroke-width="1.5"/>'
            f'<text x="{float(x) + 6:.1f}" y="{float(y) + 4:.1f}" font-size="10" '
            f'fill="#333">{escape(st.label)}</text>'
        )
    out.append("</svg>")
    return "".join(out)


def _legend() -> str:
    items = [f'<span><i style="background:{c}"></i>{escape(label)}</span>' for _, c, label in BINS]
    items.append(f'<span><i style="background:{NO_STATE}"></i>no state</span>')
    return (
        '<p class="legend">P(exceeding the intervention limit), max over Top6 and Align10: '
        + "".join(items)
        + "</p>"
    )


def _limits(data: ReportData, limits: Limits) -> str:
    """Per line: its speed class, where the class comes from, and the AL, IL and IAL of Top6
    and Align10 of that class."""
    lines = sorted({s.line for s in data.states} | set(data.lines))
    names = ["AL", "IL"] if limits.levels == ("alert", "intervention") else list(limits.levels)
    head = ["line", "speed class"] + [
        f"{indicator} {level} mm"
        for indicator in ("Top6", "Align10")
        for level in (*names, *(["IAL"] if limits.immediate_action else []))
    ]
    out = [
        "<p>EN 13848-5 levels per line speed class: AL (alert), IL (intervention), IAL "
        "(immediate action). A line's class is the one the limits file names for it, else "
        "the class holding its line speed in the network file, else the file's default.</p>",
        '<table id="limits"><thead><tr>',
        *(f"<th>{escape(h)}</th>" for h in head),
        "</tr></thead><tbody>",
    ]
    for line in lines:
        table, ial = limits.for_line(line), limits.immediate_action_for_line(line)
        values = [
            v
            for i in range(table.shape[1])
            for v in [*table[:, i], *([ial[i]] if ial is not None else [])]
        ]
        band = limits.describe(line).removeprefix("speed class ")
        out.append(
            f"<tr><td>{escape(data.network.label(line))}</td><td>{escape(band)}</td>"
            + "".join(f'<td class="n">{v:g}</td>' for v in values)
            + "</tr>"
        )
    out.append("</tbody></table>")
    return "".join(out)


def _mm(state: SegmentState, i: int) -> str:
    median = math.exp(state.mean.array()[i])
    low, high = state.ci_low_mm.array()[i], state.ci_high_mm.array()[i]
    return f"{median:.2f} [{low:.2f}, {high:.2f}]"


def _table(data: ReportData, states: list[SegmentState]) -> str:
    horizons = sorted({h for s in states for h in p_forecast(s)})
    plan_rows = {(r.line, r.segment): r for r in (data.plan.rows if data.plan else [])}
    head = ["#", "line", "segment", "chainage (km)"]
    head += ["Top6 mm [95 %]", "Align10 mm [95 %]", "P(exceed) now"]
    head += [f"in {h:g} d" for h in horizons]
    head += ["last TRC", "next TRC", "P before next TRC"]
    rows = ['<table id="segments"><thead><tr>']
    rows += [f"<th>{escape(h)}</th>" for h in head]
    rows.append("</tr></thead><tbody>")
    for rank, s in enumerate(states, 1):
        key = (s.line, s.segment)
        chain = data.network.chainage_m.get(key)
        chain_text = "–" if chain is None else f"{chain[0] / 1e3:.1f} – {chain[1] / 1e3:.1f}"
        cells = [f'<td class="n">{rank}</td>', f"<td>{escape(data.network.label(s.line))}</td>"]
        cells.append(f"<td>{escape(s.segment)}</td><td>{chain_text}</td>")
        for name in ("top6", "align10"):
            text = _mm(s, s.indicators.index(name)) if name in s.indicators else "–"
            cells.append(f'<td class="n">{text}</td>')
        cells.append(_p_cell(p_now(s)))
        forecast = p_forecast(s)
        cells += [_p_cell(forecast.get(h)) for h in horizons]
        plan = plan_rows.get(key)
        cells.append(f"<td>{day(s.last_trc_t)}{_measured(s)}</td>")
        if plan is None:
            cells.append("<td>–</td><td>–</td>")
        else:
            cells.append(f"<td>{day(plan.next_trc_t)}</td>")
            cells.append(_p_cell(plan.probability))
        rows.append("<tr>" + "".join(cells) + "</tr>")
    rows.append("</tbody></table>")
    return "".join(rows)


def _measured(state: SegmentState) -> str:
    """What the last TRC record measured, when it was not every indicator."""
    names = state.last_trc_indicators
    if not names or len(names) == len(state.indicators):
        return ""
    return f"<br><small>{escape(' '.join(names))} only</small>"


def _p_cell(p: float | None) -> str:
    if p is None:
        return "<td>–</td>"
    text = "#fff" if p >= 0.5 or p < 0.1 else "#222"
    return f'<td class="p" style="background:{colour(p)};color:{text}">{p:.2f}</td>'


def _fans(states: list[SegmentState]) -> str:
    if not states:
        return "<p>No segment.</p>"
    out = []
    for s in states:
        title = f"{s.line}/{s.segment}: P(exceed) {p_now(s):.2f} at {iso(s.t)}"
        out.append(f'<div class="fan"><h3>{escape(title)}</h3>')
        out += [_fan(s, i) for i in range(len(s.indicators))]
        out.append("</div>")
    return '<div class="fans">' + "".join(out) + "</div>"


def _fan(s: SegmentState, i: int) -> str:
    """One indicator's estimate now and forecasts at the horizons: the 95 % band, the
    median, and the alert and intervention limits."""
    w, h, left, right, top, bottom = 330, 170, 42, 92, 10, 28
    days = [0.0] + [float(d) for d in s.horizons_days.array()]
    median = [math.exp(s.mean.array()[i])] + [math.exp(v) for v in s.forecast_mean.array()[:, i]]
    low = [float(s.ci_low_mm.array()[i])] + [float(v) for v in s.forecast_ci_low_mm.array()[:, i]]
    high = [float(s.ci_high_mm.array()[i])]
    high += [float(v) for v in s.forecast_ci_high_mm.array()[:, i]]
    limits = [(lvl, float(s.limits_mm.array()[k, i])) for k, lvl in enumerate(s.limit_levels)]
    y_max = max(high + [v for _, v in limits]) * 1.1
    x_max = max(days) or 1.0

    def px(d: float) -> float:
        return left + d / x_max * (w - left - right)

    def py(mm: float) -> float:
        return top + (1 - mm / y_max) * (h - top - bottom)

    band = [f"{px(d):.1f},{py(v):.1f}" for d, v in zip(days, high, strict=True)]
    band += [f"{px(d):.1f},{py(v):.1f}" for d, v in reversed(list(zip(days, low, strict=True)))]
    line = " ".join(f"{px(d):.1f},{py(v):.1f}" for d, v in zip(days, median, strict=True))
    name = s.indicators[i]
    out = [
        f'<svg width="{w}" height="{h}" '
        f'viewBox="0 0 {w} {h}" role="img" aria-label="{escape(name)} forecast">',
        f'<line x1="{left}" y1="{py(0):.1f}" x2="{w - right}" y2="{py(0):.1f}" stroke="#888"/>',
        f'<line x1="{left}" y1="{top}" x2="{left}" y2="{py(0):.1f}" stroke="#888"/>',
        f'<polygon points="{" ".join(band)}" fill="#9cc3ec" fill-opacity="0.7"/>',
        f'<polyline points="{line}" fill="none" stroke="#1f5fb4" stroke-width="2"/>',
    ]
    for d, v, lo, hi in zip(days, median, low, high, strict=True):
        tip = f"{'now' if d == 0 else f'in {d:g} d'}: {v:.2f} mm [{lo:.2f}, {hi:.2f}]"
        out.append(
            f'<circle cx="{px(d):.1f}" cy="{py(v):.1f}" r="3" fill="#1f5fb4">'
            f"<title>{escape(tip)}</title></circle>"
        )
    for lvl, v in limits:
        stroke = "#d73027" if lvl == INTERVENTION else "#e08a00"
        out.append(
            f'<line x1="{left}" y1="{py(v):.1f}" x2="{w - right}" y2="{py(v):.1f}" '
            f'stroke="{stroke}" stroke-dasharray="5,3"/>'
            f'<text x="{w - right + 3}" y="{py(v) + 4:.1f}" font-size="10" fill="{stroke}">'
            f"{escape(lvl)} {v:g}</text>"
        )
    for d in days:
        out.append(
            f'<text x="{px(d):.1f}" y="{h - 12}" font-size="10" text-anchor="middle">'
            f"{'now' if d == 0 else f'{d:g} d'}</text>"
        )
    for frac in (0.0, 0.5, 1.0):
        v = y_max / 1.1 * frac
        out.append(
            f'<text x="{left - 4}" y="{py(v) + 3:.1f}" font-size="10" text-anchor="end">'
            f"{v:.1f}</text>"
        )
    out.append(
        f'<text x="{left + 4}" y="{top + 10}" font-size="11" font-weight="bold">'
        f"{escape(name)} (mm)</text></svg>"
    )
    return "".join(out)


def _alerts(data: ReportData) -> str:
    if data.alerts is None:
        return '<p class="note">Alerts missing: the alerting service did not answer.</p>'
    if not data.alerts:
        return "<p>No alert raised.</p>"
    rows = ['<table id="alerts"><thead><tr>']
    head = ("time", "segment", "kind", "indicator", "level", "speed class", "p", "message")
    rows += [f"<th>{h}</th>" for h in head]
    rows.append("</tr></thead><tbody>")
    for a in sorted(data.alerts, key=lambda a: (-a.probability, a.line, a.segment, a.kind)):
        band = a.speed_class or "–"
        cells = [iso(a.t), f"{a.line}/{a.segment}", a.kind, a.indicator, a.level, band]
        rows.append(
            "<tr>"
            + "".join(f"<td>{escape(c)}</td>" for c in cells)
            + f'<td class="n">{a.probability:.2f}</td><td>{escape(a.message)}</td></tr>'
        )
    rows.append("</tbody></table>")
    return "".join(rows)


# --- the tamping plan -----------------------------------------------------------------------

PLANNED = "#1f78b4"  # a segment tamped that week
POSSESSION = "#222"  # the outline of a possession: adjacent segments tamped in one week
DEADLINE = "#d73027"  # the last week a tamping meets the risk limit
WEEK_PX, GRID_H, GRID_LEFT, GRID_TOP = 26, 180, 64, 22  # px


def _tamping(data: ReportData) -> str:
    plan = data.tamping
    if plan is None:
        return f'<p class="note">{escape(data.tamping_missing)}</p>'
    if plan.status == "no_data" or plan.t is None:
        return "<p>No plan yet: no segment has both a state and a degradation model.</p>"
    wanted = set(data.lines)
    rows = [r for r in plan.rows if not wanted or r.line in wanted]
    budget = "no budget" if plan.budget is None else f"budget {plan.budget:,.0f}"
    out = [
        f"<p>{plan.horizon_weeks} weeks from {day(plan.t)} (Monday of week 0), made from the "
        f"states up to {escape(iso(plan.computed_at))}: {plan.segments} segments planned, "
        f"{sum(plan.km_per_week):.1f} km tamped in "
        f"{maintenance_plan.counted(plan.possessions, 'possession')}, money "
        f"{plan.money:,.0f} ({budget}), expected cost {plan.objective:,.0f} "
        f"({escape(plan.status.replace('_', ' '))}, {100 * plan.gap:.2f} % above the bound). "
        f"Risk limit: P(reaching the immediate-action limit before the tamping) ≤ "
        f"{plan.eps:g}; a segment's deadline is the last week whose tamping meets it.</p>",
        '<p class="legend">'
        f'<span><i style="background:{PLANNED}"></i>tamped that week</span>'
        f'<span><i style="border:2px solid {POSSESSION};height:6px"></i>possession</span>'
        f'<span><i style="background:{DEADLINE};width:3px"></i>deadline</span>'
        f'<span><i style="background:{DEADLINE};opacity:0.25"></i>risk limit not met</span>'
        "</p>",
    ]
    planned = sorted({r.line for r in rows})
    if not planned:
        out.append("<p>No tamping planned and every risk limit met over the horizon.</p>")
    for line in planned:
        line_rows = [r for r in rows if r.line == line]
        out.append(f"<h3>{escape(data.network.label(line))}</h3>")
        out.append(_tamping_grid(plan, line, line_rows, data.network))
        out.append(_worksites(plan, line_rows, data.network))
    out.append(_trc_runs(plan, wanted, data.network))
    return "".join(out)


def _line_extent(network: NetworkMap, line: str, rows) -> tuple[float, float]:
    """Chainage range (m) of a line: its segments in the network, else the planned ones."""
    spans = [c for (ln, _), c in network.chainage_m.items() if ln == line]
    spans = spans or [
        network.chainage_m[(r.line, r.segment)]
        for r in rows
        if (r.line, r.segment) in network.chainage_m
    ]
    if not spans:
        return 0.0, 1.0
    return min(a for a, _ in spans), max(b for _, b in spans)


def _tamping_grid(plan: MaintenancePlan, line: str, rows, network: NetworkMap) -> str:
    """Weeks across, chainage down: each planned tamping a filled cell, each possession an
    outline around its cells, each deadline a red bar at the end of its week, each segment
    whose risk limit the plan does not meet a pale red row."""
    weeks = plan.horizon_weeks
    lo, hi = _line_extent(network, line, rows)
    w = GRID_LEFT + weeks * WEEK_PX + 10
    h = GRID_TOP + GRID_H + 10

    def x(week: float) -> float:
        return GRID_LEFT + week * WEEK_PX

    def y(chainage_m: float) -> float:
        return GRID_TOP + (chainage_m - lo) / max(hi - lo, 1e-9) * GRID_H

    out = [
        f'<svg class="plan" width="{w}" height="{h}" viewBox="0 0 {w} {h}" role="img" '
        f'aria-label="{escape(line)} tamping plan" '
        'style="background:#fafafa;border:1px solid #ccc">'
    ]
    for week in range(weeks + 1):
        out.append(
            f'<line x1="{x(week):.1f}" y1="{GRID_TOP}" x2="{x(week):.1f}" y2="{GRID_TOP + GRID_H}" '
            'stroke="#e4e4e4"/>'
        )
    for week in range(0, weeks, 4):
        out.append(
            f'<text x="{x(week) + 2:.1f}" y="{GRID_TOP - 10}" font-size="10">w{week}</text>'
            f'<text x="{x(week) + 2:.1f}" y="{GRID_TOP - 1}" font-size="9" fill="#555">'
            f"{day(plan.t + week * 7 * DAY_S)[5:]}</text>"
        )
    for frac in (0.0, 0.5, 1.0):
        c = lo + frac * (hi - lo)
        out.append(
            f'<text x="{GRID_LEFT - 4}" y="{y(c) + 3:.1f}" font-size="10" text-anchor="end">'
            f"{c / 1e3:.1f} km</text>"
        )
    sites: dict[int, list] = {}
    for r in rows:
        span = network.chainage_m.get((r.line, r.segment))
        if span is None:
            continue
        top, bottom = y(span[0]), y(span[1])
        tip = (
            f"{r.line}/{r.segment} {span[0] / 1e3:.1f}–{span[1] / 1e3:.1f} km: "
            + (f"tamped week {r.week}" if r.week >= 0 else "not tamped")
            + f", deadline {'none' if r.deadline_week < 0 else 'w' + str(r.deadline_week)}"
            + f", P(IAL first) {r.p_reach_ial:.3f}"
        )
        if not r.risk_met:
            out.append(
                f'<rect x="{x(0):.1f}" y="{top:.1f}" width="{weeks * WEEK_PX}" '
                f'height="{max(bottom - top, 1):.1f}" fill="{DEADLINE}" fill-opacity="0.25">'
                f"<title>{escape(tip)}</title></rect>"
            )
        if r.week >= 0:
            sites.setdefault(r.worksite, []).append((r, span))
            out.append(
                f'<rect x="{x(r.week) + 1:.1f}" y="{top:.1f}" width="{WEEK_PX - 2}" '
                f'height="{max(bottom - top, 1):.1f}" fill="{PLANNED}">'
                f"<title>{escape(tip)}</title></rect>"
            )
        if 0 <= r.deadline_week < weeks:
            out.append(
                f'<rect x="{x(r.deadline_week + 1) - 2:.1f}" y="{top:.1f}" width="3" '
                f'height="{max(bottom - top, 1):.1f}" fill="{DEADLINE}">'
                f"<title>{escape(tip)}</title></rect>"
            )
    for site in sites.values():
        week = site[0][0].week
        top = y(min(span[0] for _, span in site))
        bottom = y(max(span[1] for _, span in site))
        out.append(
            f'<rect x="{x(week):.1f}" y="{top - 1:.1f}" width="{WEEK_PX}" '
            f'height="{bottom - top + 2:.1f}" fill="none" stroke="{POSSESSION}" '
            'stroke-width="1.5"/>'
        )
    out.append("</svg>")
    return "".join(out)


def _worksites(plan: MaintenancePlan, rows, network: NetworkMap) -> str:
    """One table row per possession: its week, where, how long, its earliest deadline."""
    sites: dict[int, list] = {}
    for r in rows:
        if r.week >= 0:
            sites.setdefault(r.worksite, []).append(r)
    unmet = [r for r in rows if not r.risk_met]
    if not sites:
        unmet_segments = maintenance_plan.counted(len(unmet), "segment")
        return f"<p>No tamping planned; risk limit not met on {unmet_segments}.</p>"
    head = ("week", "starts", "segments", "chainage (km)", "km", "deadline", "max P(IAL first)")
    out = ['<table class="worksites"><thead><tr>']
    out += [f"<th>{h}</th>" for h in head]
    out.append("</tr></thead><tbody>")
    for site in sorted(sites.values(), key=lambda s: (s[0].week, s[0].segment)):
        site.sort(key=lambda r: r.segment)
        spans = [network.chainage_m.get((r.line, r.segment)) for r in site]
        known = [s for s in spans if s is not None]
        where = (
            "–"
            if not known
            else f"{min(a for a, _ in known) / 1e3:.1f} – {max(b for _, b in known) / 1e3:.1f}"
        )
        deadline = min(r.deadline_week for r in site)
        deadline_text = (
            "–" if deadline >= plan.horizon_weeks else ("none" if deadline < 0 else f"w{deadline}")
        )
        cells = [
            f'<td class="n">w{site[0].week}</td>',
            f"<td>{day(plan.t + site[0].week * 7 * DAY_S)}</td>",
            f"<td>{escape(site[0].segment)} – {escape(site[-1].segment)}</td>",
            f"<td>{where}</td>",
            f'<td class="n">{sum(r.length_km for r in site):.1f}</td>',
            f"<td>{deadline_text}</td>",
            f'<td class="n">{max(r.p_reach_ial for r in site):.3f}</td>',
        ]
        out.append("<tr>" + "".join(cells) + "</tr>")
    out.append("</tbody></table>")
    if unmet:
        out.append(f"<p>Risk limit not met on {len(unmet)} segments (pale red in the grid).</p>")
    return "".join(out)


def _trc_runs(plan: MaintenancePlan, wanted: set[str], network: NetworkMap) -> str:
    """The lines whose TRC run now is worth most to the plan (value of information); a run
    worth nothing is not recommended."""
    runs = [v for v in plan.trc_lines if v.value > 0 and (not wanted or v.line in wanted)]
    if not runs:
        return "<p>No TRC run recommended: no run would lower the plan's expected cost.</p>"
    out = [
        "<h3>TRC runs the plan recommends</h3>",
        "<p>Lines by the value of a recording-car run now: the expected fall of the plan's "
        "cost from the uncertainty the run removes.</p>",
        '<table class="trc-runs"><thead><tr><th>#</th><th>line</th><th>value</th>'
        "<th>segments</th></tr></thead><tbody>",
    ]
    for rank, v in enumerate(runs, 1):
        out.append(
            f'<tr><td class="n">{rank}</td><td>{escape(network.label(v.line))}</td>'
            f'<td class="n">{v.value:,.0f}</td><td class="n">{v.segments}</td></tr>'
        )
    out.append("</tbody></table>")
    return "".join(out)


# --- the running system ---------------------------------------------------------------------


def _ask_alerting(session, ns: str, line: str | None, timeout: float):
    """(alerts, plan, missing note): both None with a note when alerting does not answer."""
    params = f"?line={line}" if line else ""
    try:
        replies = list(operator.ask(session, keys.q_alerts(ns) + params, timeout))
        plan_replies = list(operator.ask(session, keys.q_plan(ns) + params, timeout))
    except SystemExit as exc:  # ask's message for an incomplete or failed answer
        return None, None, f"Alerts and plan missing: {exc}"
    if not replies or not plan_replies:
        return (
            None,
            None,
            (
                "Alerts and plan missing: the alerting service did not answer "
                "(is it running? `trackfusion status`)."
            ),
        )
    try:
        alerts = decode(replies[0][1], RaisedAlerts).alerts
        plan = decode(plan_replies[0][1], InspectionPlan)
    except SchemaError as exc:
        return None, None, f"Alerts and plan missing: the alerting service's answer: {exc}"
    return alerts, plan, ""


def _ask_planner(session, ns: str, timeout: float) -> tuple[MaintenancePlan | None, str]:
    """(the plan, "") by the query of `trackfusion plan maintenance`; (None, why not) when
    the planning service does not answer."""
    selector = maintenance_plan.selector(ns, None, None)
    try:
        replies = list(operator.ask(session, selector, timeout))
    except SystemExit as exc:
        return None, f"Tamping plan missing: {exc}"
    if not replies:
        return None, (
            f"Tamping plan missing: no planning service answered on {selector} "
            "(is it running? `trackfusion status`)."
        )
    try:
        return decode(replies[0][1], MaintenancePlan), ""
    except SchemaError as exc:
        return None, f"Tamping plan missing: the planning service's answer: {exc}"


def main(
    conf: RuntimeConfig,
    *,
    out_path: str | Path = DEFAULT_OUT,
    line: str | None = None,
    network_path: str | None = None,
    worst_n: int = WORST_N,
    limits_path: str | Path = DEFAULT_LIMITS_FILE,
    timeout: float = operator.QUERY_TIMEOUT_S,
    out: TextIO = sys.stdout,
) -> int:
    """Ask the running system and write the report; SystemExit (1) without any state.
    ``limits_path``: the limits file the services apply (the report shows each line's)."""
    network = network_map(network_path)
    limits = load_limits(limits_path, network.line_speeds_kmh)
    with operator.open_session(conf) as session:
        states = operator.query_states(session, conf.ns, f"{line}/**" if line else "**", timeout)
        if not states:
            what = f"line {line}" if line else f"namespace {conf.ns!r}"
            raise SystemExit(
                f"report: no segment state for {what} on {keys.q_state_all(conf.ns)}. Is the "
                "filtering service running (`trackfusion status`)? It answers only for "
                "segments with a TRC record and a model; check the line id too."
            )
        alerts, plan, missing = _ask_alerting(session, conf.ns, line, timeout)
        tamping, tamping_missing = _ask_planner(session, conf.ns, timeout)
    data = ReportData(
        states=states,
        network=network,
        made_at=time.time(),
        alerts=alerts,
        plan=plan,
        missing=missing,
        lines=(line,) if line else (),
        worst_n=worst_n,
        tamping=tamping,
        tamping_missing=tamping_missing,
        limits=limits,
    )
    Path(out_path).write_text(render(data), encoding="utf-8")
    note = "".join(f" ({text})" for text in (missing, tamping_missing) if text)
    print(f"wrote {out_path}: {len(states)} segments{note}", file=out)
    return 0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """``trackfusion report``."""
    parser.description = (
        "Map, ranked segments, forecast fans, open alerts and the tamping plan in one HTML "
        "file (inline CSS and SVG, no external resource)."
    )
    parser.add_argument("--line", help="one line (default: all lines)")
    parser.add_argument("--out", default=DEFAULT_OUT, metavar="FILE.html", help="(%(default)s)")
    add_network_argument(parser, "the geometry and the line speeds")
    add_limits_argument(parser, "the limits file the services apply")
    parser.add_argument(
        "--worst", type=int, default=WORST_N, metavar="N", help="fans drawn (%(default)s)"
    )
    operator.add_query_arguments(parser)


def run(args: argparse.Namespace) -> int:
    return main(
        config_from_args(args),
        out_path=args.out,
        line=args.line,
        network_path=args.network,
        worst_n=args.worst,
        limits_path=args.limits,
        timeout=args.timeout,
    )
