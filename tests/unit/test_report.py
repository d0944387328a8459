"""Pure parts of `trackfusion report`: fixture states → one self-contained HTML document."""

from __future__ import annotations

import json
import re

import pytest

from schemas import DAY_S, Alert, InspectionPlan, MaintenancePlan, PlannedTamping, TrcRunValue
from services.alerting.testing import T0, forecast_top6, make_state, p_top6, plan_row
from services.limits import load_limits
from services.tools.network_map import NetworkMap, Station, network_map
from services.tools.report import (
    BINS,
    DEADLINE,
    GRID_H,
    GRID_LEFT,
    GRID_TOP,
    NO_STATE,
    PLANNED,
    WEEK_PX,
    ReportData,
    colour,
    p_forecast,
    p_now,
    ranked,
    render,
)

EVIL = 's<b>&"1"'  # ids are key chunks: `<`, `&` and quotes are allowed in them


def a_network() -> NetworkMap:
    """Three segments in a row on line L1, 0.002° (≈ 200 m) each, and one station."""
    polylines = {
        ("L1", seg): [(153.0 + 0.002 * k, -27.5), (153.0 + 0.002 * (k + 1), -27.5)]
        for k, seg in enumerate(("s1", "s2", EVIL))
    }
    chainage = {key: (200.0 * k, 200.0 * (k + 1)) for k, key in enumerate(polylines)}
    return NetworkMap(polylines, chainage, [Station("L1", 153.0, -27.5, "Roma <St>")])


def some_states():
    return [
        make_state(T0, segment="s1", p_exceed=p_top6(1, 0.2), last_trc_t=T0 - 30 * DAY_S),
        make_state(
            T0 + DAY_S,
            segment="s2",
            p_exceed=p_top6(1, 0.9),
            forecast=forecast_top6(0.92, 0.95, 0.99),
        ),
        make_state(T0, segment=EVIL, p_exceed=p_top6(1, 0.05)),
    ]


def a_report(**kw) -> str:
    data = {"states": some_states(), "network": a_network(), "made_at": T0 + 5 * DAY_S} | kw
    return render(ReportData(**data))


def an_alert(**kw) -> Alert:
    fields = {"line": "L1", "segment": "s2", "t": T0, "kind": "exceedance", "status": "raised"}
    fields |= {"indicator": "top6", "level": "intervention", "probability": 0.9}
    return Alert(**(fields | kw))


@pytest.mark.parametrize(
    ("p", "expected"),
    [(0.0, BINS[0][1]), (0.099, BINS[0][1]), (0.1, BINS[1][1]), (0.35, BINS[2][1]),
     (0.5, BINS[3][1]), (0.8, BINS[4][1]), (1.0, BINS[4][1]), (None, NO_STATE)],
)  # fmt: skip
def test_colour_per_probability_bin(p, expected):
    assert colour(p) == expected


def test_probabilities_are_the_intervention_level_max_over_indicators():
    state = make_state(p_exceed=[[0.9, 0.8], [0.2, 0.4]], forecast=forecast_top6(0.5, 0.6, 0.7))
    assert p_now(state) == pytest.approx(0.4)  # align10 at intervention, not top6 at alert
    assert p_forecast(state) == pytest.approx({30.0: 0.5, 90.0: 0.6, 180.0: 0.7})


def test_segments_are_ranked_by_p_exceed_then_id():
    states = some_states() + [make_state(segment="s0", p_exceed=p_top6(1, 0.2))]
    assert [s.segment for s in ranked(states)] == ["s2", "s0", "s1", EVIL]
    html = a_report()
    rows = re.findall(r"<tr><td class=\"n\">(\d+)</td><td>L1</td><td>([^<]*)</td>", html)
    assert rows == [("1", "s2"), ("2", "s1"), ("3", "s&lt;b&gt;&amp;&quot;1&quot;")]


def test_map_draws_each_segment_in_the_colour_of_its_probability():
    html = a_report()
    svg = html[html.index('<svg id="map"') : html.index("</svg>")]
    strokes = re.findall(r'<polyline points="[^"]+" fill="none" stroke="(#\w+)"', svg)
    assert sorted(strokes) == sorted([colour(0.2), colour(0.9), colour(0.05)])
    assert "Roma &lt;St&gt;" in svg  # station label, escaped
    # a segment of the network without a state is grey; the legend has every bin
    html = a_report(states=some_states()[:2])
    assert f'stroke="{NO_STATE}"' in html
    assert all(f"background:{c}" in html for _, c, _ in BINS)


def test_ids_and_messages_are_escaped():
    html = a_report(alerts=[an_alert(segment=EVIL, message="<script>alert(1)</script> & co")])
    assert EVIL not in html and "<b>&" not in html and "<script>" not in html
    assert "&lt;script&gt;alert(1)&lt;/script&gt; &amp; co" in html
    assert "L1/s&lt;b&gt;&amp;&quot;1&quot;" in html  # the map tooltip and the alert row


def test_the_file_is_self_contained():
    html = a_report(alerts=[an_alert()], plan=InspectionPlan(t=T0, rows=[]))
    assert html.startswith("<!DOCTYPE html>")
    for external in ("http://", "https://", "src=", "<script", "<link", "url(", "@import"):
        assert external not in html, external
    assert html.count("<svg") == 1 + 2 * 3  # the map, two fans per segment


def test_table_has_estimates_intervals_forecasts_last_and_next_trc():
    plan = InspectionPlan(t=T0, rows=[plan_row("L1", "s2", 0.97, T0 + 40 * DAY_S)])
    html = a_report(alerts=[], plan=plan)
    row = re.search(r"<tr><td class=\"n\">1</td>.*?</tr>", html).group(0)
    assert "0.2 – 0.4" in row  # chainage, km
    assert "4.00 [3.29, 4.87]" in row and "3.00 [2.47, 3.65]" in row  # median [95 %] mm
    assert [c for c in re.findall(r">(\d\.\d\d)</td>", row)] == ["0.90", "0.92", "0.95", "0.99",
                                                                "0.97"]  # fmt: skip
    assert "2026-02-10" in row  # next TRC from the plan
    first = re.search(r"<tr><td class=\"n\">2</td>.*?</tr>", html).group(0)
    assert "2025-12-02" in first  # last TRC record
    assert "No alert raised." in html
    assert "Made 2026-01-06T00:00:00 UTC (wall clock)" in html
    assert "Newest state: 2026-01-02T00:00 UTC (event time)" in html


def test_fans_of_the_worst_n_with_limits():
    html = a_report(worst_n=1)
    fans = html[html.index('<div class="fans">') :]
    assert fans.count('<div class="fan">') == 1 and "L1/s2: P(exceed) 0.90" in fans
    assert "intervention 8" in fans and "alert 6" in fans  # limits_mm, top6
    assert "intervention 7" in fans and "alert 5" in fans  # align10


def test_missing_alerting_is_said_not_fatal():
    note = "Alerts and plan missing: the alerting service did not answer"
    html = a_report(alerts=None, plan=None, missing=note)
    assert note in html and "Alerts missing" in html
    assert html.count('<tr><td class="n">') == 3  # the segments are still there


def test_demo_network_map_has_every_segment_and_stations():
    demo = network_map(None)
    assert len(demo.polylines) == 295 and set(demo.chainage_m) == set(demo.polylines)
    assert demo.chainage_m[("L1", "s00001")] == (200.0, 400.0)
    assert any(s.label == "L1 km 3.5" for s in demo.stations)


def test_station_names_from_the_network_file_and_a_bad_file(tmp_path):
    line = {"type": "Feature", "geometry": {"type": "LineString",
            "coordinates": [[153.0, -27.5], [153.01, -27.5]]},
            "properties": {"id": "X", "stations": [0.0, 900.0],
                           "station_names": ["Central", "Park"]}}  # fmt: skip
    path = tmp_path / "net.geojson"
    path.write_text(json.dumps({"type": "FeatureCollection", "features": [line]}))
    assert [s.label for s in network_map(str(path)).stations] == ["Central", "Park"]
    path.write_text("{")
    with pytest.raises(ValueError, match="--network"):
        network_map(str(path))


def test_a_last_trc_record_of_one_indicator_is_said():
    import msgspec

    level_only = msgspec.structs.replace(
        make_state(T0, segment="s1", last_trc_t=T0 - DAY_S), last_trc_indicators=["top6"]
    )
    html = render(ReportData(states=[level_only], network=a_network(), made_at=T0))
    row = re.search(r"<tr><td class=\"n\">1</td>.*?</tr>", html).group(0)
    assert "2025-12-31<br><small>top6 only</small>" in row
    both = msgspec.structs.replace(level_only, last_trc_indicators=["top6", "align10"])
    html = render(ReportData(states=[both], network=a_network(), made_at=T0))
    assert "only</small>" not in html


def test_lines_are_shown_with_the_names_operators_use():
    network = a_network()
    named = NetworkMap(network.polylines, network.chainage_m, network.stations,
                       {"L1": "Alassio – Albenga, track 2"})  # fmt: skip
    html = render(ReportData(states=some_states(), network=named, made_at=T0))
    assert "1 line(s) (L1 (Alassio – Albenga, track 2))" in html
    row = re.search(r"<tr><td class=\"n\">1</td>.*?</tr>", html).group(0)
    assert "<td>L1 (Alassio – Albenga, track 2)</td>" in row


def tamping(line: str, segment: str, week: int, worksite: int, deadline: int, p: float):
    return PlannedTamping(
        line=line, segment=segment, week=week, worksite=worksite, length_km=0.2,
        deadline_week=deadline, p_reach_ial=p, risk_met=p <= 0.05, cost=1.0, cost_untamped=2.0,
    )  # fmt: skip


def a_tamping_plan() -> MaintenancePlan:
    """s1 and s2 of L1 tamped in week 2 in one possession (s2's deadline week 3), the third
    segment not tamped with its risk limit not met, and a row of line L2."""
    return MaintenancePlan(
        t=T0, computed_at=T0 - DAY_S, horizon_weeks=26, eps=0.05, status="optimal",
        objective=5.0e4, bound=5.0e4, gap=0.0, solve_s=0.1,
        km_per_week=[0.0, 0.0, 0.4] + [0.0] * 23 , possessions=2, money=3.0e4, budget=None,
        segments=40, without_model=0,
        rows=[
            tamping("L1", "s1", 2, 0, 26, 0.01),
            tamping("L1", "s2", 2, 0, 3, 0.02),
            tamping("L2", "s9", 5, 1, 6, 0.01),
            tamping("L1", EVIL, -1, -1, -1, 0.3),
        ],
        trc_lines=[TrcRunValue(line="L1", value=1234.0, segments=3),
                   TrcRunValue(line="L2", value=10.0, segments=1)],
    )  # fmt: skip


def _rects(svg: str, fill: str) -> list[tuple[float, float, float, float]]:
    """(x, y, width, height) of the rects of one fill in an SVG text."""
    found = re.findall(
        r'<rect x="([\d.]+)" y="([\d.]+)" width="([\d.]+)" height="([\d.]+)" fill="'
        + re.escape(fill)
        + '"',
        svg,
    )
    return [tuple(map(float, row)) for row in found]


def test_the_tamping_plan_is_a_weeks_by_chainage_grid_per_line():
    html = a_report(tamping=a_tamping_plan(), lines=("L1",))
    section = html[html.index('<h2 id="tamping">') :]
    assert "26 weeks from 2026-01-01" in section and "≤ 0.05" in section
    svg = section[section.index('<svg class="plan"') : section.index("</svg>")]
    cell = GRID_H / 3  # three 200 m segments over the grid's height
    planned = _rects(svg, PLANNED)
    x2 = GRID_LEFT + 2 * WEEK_PX + 1
    assert planned == [(x2, GRID_TOP, WEEK_PX - 2, cell), (x2, GRID_TOP + cell, WEEK_PX - 2, cell)]
    # one possession around both cells; s2's deadline at the end of week 3; s1's is beyond
    # the horizon and the third segment has none
    possession = re.findall(r'<rect x="([\d.]+)" y="([\d.]+)" width="(\d+)" height="([\d.]+)" '
                            r'fill="none"', svg)  # fmt: skip
    assert [tuple(map(float, r)) for r in possession] == [
        (GRID_LEFT + 2 * WEEK_PX, GRID_TOP - 1, WEEK_PX, 2 * cell + 2)
    ]
    deadlines = [r for r in _rects(svg, DEADLINE) if r[2] == 3]
    assert deadlines == [(GRID_LEFT + 4 * WEEK_PX - 2, GRID_TOP + cell, 3, cell)]
    unmet = [r for r in _rects(svg, DEADLINE) if r[2] == 26 * WEEK_PX]
    assert unmet == [(GRID_LEFT, GRID_TOP + 2 * cell, 26 * WEEK_PX, cell)]
    assert "s&lt;b&gt;" in svg and "s<b>" not in svg
    # the possession's row: week, Monday, segments, chainage, km, earliest deadline
    row = re.search(r'<table class="worksites">.*?</table>', section).group(0)
    assert "<td>2026-01-15</td><td>s1 – s2</td><td>0.0 – 0.4</td>" in row and "w3" in row
    assert "Risk limit not met on 1 segments" in section
    runs = re.search(r'<table class="trc-runs">.*?</table>', section).group(0)
    assert '<td>L1</td><td class="n">1,234</td>' in runs
    assert "L2" not in section  # --line L1: the other line's tampings and runs left out


def test_a_missing_planner_is_said_in_one_line_and_the_rest_rendered():
    note = "Tamping plan missing: no planning service answered on ns/q/plan/maintenance"
    html = a_report(tamping=None, tamping_missing=note)
    assert html.count(note) == 1 and '<svg class="plan"' not in html
    assert html.count('<tr><td class="n">') == 3 and '<svg id="map"' in html


def test_a_trc_run_worth_nothing_is_not_recommended():
    import msgspec

    plan = msgspec.structs.replace(
        a_tamping_plan(), trc_lines=[TrcRunValue(line="L1", value=0.0, segments=3)]
    )
    html = a_report(tamping=plan)
    assert 'class="trc-runs"' not in html and "No TRC run recommended" in html


def test_the_names_of_two_tracks_starting_together_do_not_overlap():
    one = a_network()
    polylines = one.polylines | {("L2", seg): pts for (_, seg), pts in one.polylines.items()}
    both = NetworkMap(polylines, {}, [], {"L1": "track 1", "L2": "track 2"})
    html = render(ReportData(states=some_states(), network=both, made_at=T0))
    names = re.findall(r'<text x="([\d.]+)" y="([\d.]+)"[^>]*>(L\d \(track \d\))</text>', html)
    (x1, y1, first), (x2, y2, second) = names
    assert (first, second) == ("L1 (track 1)", "L2 (track 2)")
    assert x1 == x2 and float(y2) - float(y1) == 16


def test_each_line_shows_its_speed_class_and_its_al_il_ial():
    limits = load_limits(line_speeds_kmh={"L9": 150.0})
    states = [*some_states(), make_state(T0, line="L9", segment="s1")]
    html = a_report(states=states, limits=limits)
    table = re.search(r'<table id="limits">.*?</table>', html).group(0)
    assert "<th>Top6 AL mm</th><th>Top6 IL mm</th><th>Top6 IAL mm</th>" in table
    cells = '<td class="n">{:g}</td>' * 6
    assert (
        "<tr><td>L1</td><td>80&lt;v&lt;=120</td>" + cells.format(6, 8, 11, 5, 7, 9.5) + "</tr>"
    ) in table
    assert (
        "<tr><td>L9</td><td>120&lt;v&lt;=160 (line speed 150 km/h)</td>"
        + cells.format(5, 6.5, 9, 4, 5.5, 7.5)
        + "</tr>"
    ) in table


def test_the_alert_table_says_the_speed_class():
    stale = an_alert(kind="stale", indicator="", level="")
    html = a_report(alerts=[an_alert(speed_class="80<v<=120"), stale])
    table = re.search(r'<table id="alerts">.*?</table>', html).group(0)
    assert "<th>speed class</th>" in table
    assert "<td>intervention</td><td>80&lt;v&lt;=120</td>" in table
    assert "<td>stale</td><td></td><td></td><td>–</td>" in table
