"""The viewer core: colour map, worst-segment selection, the one blueprint and its plot
slots, the health board, and what it writes to a recording (read back with the ``rerun``
CLI)."""

from __future__ import annotations

import uuid
from collections.abc import Iterator
from pathlib import Path

import msgspec
import numpy as np
import pytest
import rerun as rr

from schemas import (
    DAY_S,
    GpsFix,
    ServiceHealth,
    StackHealth,
    TrcRecord,
    ViewerSelect,
)
from services.alerting.testing import T0, make_alert, make_index, make_state, p_top6
from services.defaults import demo_network
from services.viewer.core import (
    PLAN_WEEKS,
    ViewerCore,
    coalesce_key,
    message_version,
    planned_possessions,
    segment_exceedance,
    select_worst,
    select_worst_sticky,
)
from services.viewer.scene import UNKNOWN_RGB, build_blueprint, exceedance_color, health_markdown
from services.viewer.testing import make_plan, rrd_contents, rrd_printout, verify_rrd
from track.network import Line, Network


@pytest.mark.parametrize(
    ("p", "rgb"),
    [
        (0.0, (40, 170, 60)),
        (0.5, (240, 200, 30)),
        (1.0, (220, 40, 40)),
        (0.25, (140, 185, 45)),
        (-1.0, (40, 170, 60)),
        (2.0, (220, 40, 40)),
        (float("nan"), UNKNOWN_RGB),
    ],
)
def test_exceedance_color_green_yellow_red(p, rgb):
    assert tuple(exceedance_color(p)) == rgb


def test_exceedance_color_is_vectorised_and_reddens_monotonically():
    p = np.linspace(0, 1, 21)
    rgb = exceedance_color(p).astype(int)
    assert rgb.shape == (21, 3) and rgb.dtype == int
    green_to_yellow, yellow_to_red = rgb[:11], rgb[10:]
    assert (np.diff(green_to_yellow[:, 0]) >= 0).all()  # red rises first
    assert (np.diff(yellow_to_red[:, 1]) <= 0).all()  # then green falls


def test_segment_exceedance_uses_intervention_level_max_over_indicators():
    p = np.array([[0.9, 0.8], [0.2, 0.35]])  # alert row high, intervention row lower
    assert segment_exceedance(make_state(p_exceed=p)) == pytest.approx(0.35)
    assert segment_exceedance(make_state(p_exceed=p_top6(0, 0.9))) == 0.0


def test_select_worst_highest_first_ties_by_key():
    p = {("L1", "s2"): 0.5, ("L1", "s1"): 0.5, ("L2", "s0"): 0.9, ("L3", "s9"): 0.1}
    assert select_worst(p, 3) == [("L2", "s0"), ("L1", "s1"), ("L1", "s2")]
    assert select_worst(p, 10)[-1] == ("L3", "s9")
    assert select_worst(p, 0) == [] and select_worst({}, 3) == []


def test_one_blueprint_map_logs_and_a_fixed_row_per_slot():
    blueprint = build_blueprint(2)
    (root,) = [blueprint.root_container]
    left, right = root.contents
    map_view, below = left.contents
    alerts, ranking, health = below.contents
    assert map_view.origin == "map" and alerts.origin == "alerts" and health.origin == "health"
    assert ranking.origin == "worst/ranking"
    rows = right.contents
    assert [[v.origin for v in row.contents] for row in rows] == [
        ["worst/1/top6", "worst/1/align10"],
        ["worst/2/top6", "worst/2/align10"],
        ["selected/top6", "selected/align10"],
    ]


@pytest.fixture
def recording(tmp_path: Path) -> Iterator[tuple[rr.RecordingStream, Path]]:
    path = tmp_path / "core.rrd"
    rec = rr.RecordingStream("TrackFusion", recording_id=uuid.uuid4())
    rec.save(path)
    try:
        yield rec, path
    finally:
        rec.disconnect()


def test_slots_keep_their_segment_and_a_new_one_gets_a_new_generation(recording):
    rec, _ = recording
    core = ViewerCore(rec, None, worst_n=2, plot_flush_s=5.0, live_flush_s=1.0)
    core.start(now=0.0)
    assert core.blueprints_sent == 1
    core.take([make_state(T0, segment="s1", p_exceed=p_top6(1, 0.7))])
    core.flush(0.0)
    assert core.shown() == {"worst/1": ("L1", "s1"), "worst/2": None, "selected": None}
    core.take([make_state(T0, segment="s2", p_exceed=p_top6(1, 0.2))])
    core.flush(0.5)  # a slot can be filled: at once, not after plot_flush_s
    assert core.shown()["worst/2"] == ("L1", "s2") and core.generations == 2
    core.take([make_state(T0 + DAY_S, segment="s3", p_exceed=p_top6(1, 0.28))])  # < 0.2 + 0.1
    core.flush(10.0)
    assert set(core.shown().values()) == {("L1", "s1"), ("L1", "s2"), None}
    core.take([make_state(T0 + DAY_S, segment="s3", p_exceed=p_top6(1, 0.9))])  # > 0.2 + 0.25
    core.flush(12.0)  # not due: plot_flush_s
    assert core.shown()["worst/2"] == ("L1", "s2")
    core.flush(15.0)
    assert core.shown() == {"worst/1": ("L1", "s1"), "worst/2": ("L1", "s3"), "selected": None}
    assert core.generations == 3  # s1 stayed where it was
    core.take([ViewerSelect(line="L1", segment="s2")])
    core.flush(15.5)  # a selection is answered at once
    assert core.shown()["selected"] == ("L1", "s2") and core.generations == 4
    assert core.blueprints_sent == 1


def test_a_slot_that_changes_segment_hides_the_previous_generation(recording):
    rec, path = recording
    core = ViewerCore(rec, None, worst_n=1)
    core.start(now=0.0)
    old = [make_state(T0 + k * DAY_S, segment="old", p_exceed=p_top6(1, 0.3)) for k in range(3)]
    core.log_batch(old)
    new = [make_state(T0 + k * DAY_S, segment="new", p_exceed=p_top6(1, 0.9)) for k in range(5)]
    core.log_batch(new)
    core.log_batch([make_state(T0 + 5 * DAY_S, segment="new", p_exceed=p_top6(1, 0.9))])
    rec.flush()
    rec.disconnect()
    contents = rrd_contents(path)
    for indicator in ("top6", "align10"):
        # the first generation: its 3 rows, its style, then hidden
        assert contents[f"worst/1/{indicator}/g1/state"]["Scalars:scalars"] == 3
        assert contents[f"worst/1/{indicator}/g1/state"]["SeriesLines:visible_series"] == 1
        # the second: the new segment's whole history at once, then its next row
        assert contents[f"worst/1/{indicator}/g2/state"]["Scalars:scalars"] == 6
        assert "SeriesLines:visible_series" not in contents[f"worst/1/{indicator}/g2/state"]
    assert contents["worst/ranking"]["TextDocument:text"] == 2


def test_health_board_from_up_or_from_liveliness_tokens():
    stack = StackHealth(
        written_at=T0,
        processes=[
            ServiceHealth(name="filtering", state="running", alive=True, restarts=0),
            ServiceHealth(
                name="alerting",
                state="waiting",
                alive=False,
                restarts=2,
                last_restart_reason="exited with 1 after 12 s",
            ),
        ],
        stalled=["index arriving but no state published for 31 s"],
        counts={},
        healthy=False,
    )
    text = health_markdown(stack, {})
    assert "| alerting | waiting | **no** | 2 | exited with 1 |" in text
    assert "| filtering | running | yes | 0 |  |" in text
    assert "**STALLED: index arriving but no state published**" in text  # no seconds
    tokens = health_markdown(None, {("filtering", "f0"): True, ("alerting", "a0"): False})
    assert "| alerting | a0 | **no** |" in tokens and "| filtering | f0 | yes |" in tokens
    assert "none yet" in health_markdown(None, {})


def test_health_is_logged_when_it_changes_and_up_goes_stale(recording):
    rec, path = recording
    core = ViewerCore(rec, None, live_flush_s=1.0)
    core.start(now=0.0)  # "none yet"
    core.set_alive({("filtering", "f0"): True})
    core.flush(1.0)
    core.flush(2.0)  # the same text: not logged again
    report = StackHealth(written_at=T0, processes=[], stalled=[], counts={}, healthy=True)
    core.take([report])
    core.flush(3.0)
    assert "trackfusion up" in core._health_text
    core.flush(4.0 + 5.0)  # no report for more than 5 s: the tokens again
    assert "liveliness tokens" in core._health_text
    rec.flush()
    rec.disconnect()
    assert rrd_contents(path)["health"]["TextDocument:text"] == 4


def test_core_writes_series_map_trains_and_alerts(recording):
    rec, path = recording
    network = demo_network()
    line = network.lines["L1"]
    seg = line.segments[3].id
    core = ViewerCore(rec, network, worst_n=2)
    core.start(now=0.0)
    lon, lat = line.lonlat_at(450.0)
    states = [
        make_state(T0 + k * DAY_S, segment=seg, p_exceed=p_top6(1, 0.6), mean_mm=(4 + k, 3))
        for k in range(3)
    ]
    batch = [
        *states,  # three rows of one segment: one send_columns per series
        make_index(T0 + 0.5 * DAY_S, segment=seg),
        TrcRecord(line="L1", segment=seg, t=T0, top6_mm=4.1, align10_mm=3.1, run_id="r1"),
        GpsFix(train="T1", t=T0 + 10, lat_deg=lat, lon_deg=lon),
        GpsFix(train="T2", t=T0 + 10, lat_deg=lat, lon_deg=lon, fix_quality=0),  # skipped
        make_alert(T0 + DAY_S, segment=seg, probability=0.6),
    ]
    assert core.log_batch(batch) == len(batch)
    assert core.shown()["worst/1"] == ("L1", seg)
    # the same colour again: the colours are not re-logged; a newer state is one more row
    core.log_batch([make_state(T0 + 4 * DAY_S, segment=seg, p_exceed=p_top6(1, 0.6))])
    rec.flush()
    rec.disconnect()

    verify_rrd(path)
    contents = rrd_contents(path)
    base = "worst/1/{}/g1"
    for indicator in ("top6", "align10"):
        # estimate, band, limits: one row per state (days 0, 1, 2 and 4), each with its style
        # (not static: the server would keep every generation's for each late browser)
        assert contents[f"{base.format(indicator)}/state"]["Scalars:scalars"] == 4
        assert contents[f"{base.format(indicator)}/state"]["SeriesLines:colors"] == 4
        for series in ("onboard", "trc"):
            assert contents[f"{base.format(indicator)}/{series}"]["Scalars:scalars"] == 1
            assert contents[f"{base.format(indicator)}/{series}"]["SeriesPoints:markers"] == 1
    assert not any(entity.startswith("segments/") for entity in contents)  # only the slots
    assert contents["map/segments"]["LineStrips2D:strips"] == 1  # static geometry, all lines
    assert contents["map/segments"]["LineStrips2D:colors"] == 2  # grey, then one change
    assert contents["map/trains"]["Points2D:positions"] == 1  # T1 only: T2 had no fix
    assert contents["alerts"]["TextLog:level"] == 1
    # what an operator reads on the map: tunnels, stations, line names, the colour scale
    n_tunnels = sum(len(ln.tunnels) for ln in network.lines.values())
    assert contents["map/tunnels"]["LineStrips2D:strips"] == 1 and n_tunnels == 2
    assert contents["map/stations"]["Points2D:labels"] == 1
    assert contents["map/lines"]["Points2D:labels"] == 1
    assert contents["map/legend/colors"]["Points2D:colors"] == 1
    assert contents["map/legend/labels"]["Points2D:labels"] == 1


def test_history_thinned_to_the_newest_per_segment_and_event_day(recording):
    rec, path = recording
    core = ViewerCore(rec, None, worst_n=1, plot_flush_s=10.0, live_flush_s=1.0)
    core.start(now=0.0)
    hour = 3600.0
    day0 = [make_state(T0 + k * hour, p_exceed=p_top6(1, 0.1 * k)) for k in range(4)]
    day1 = make_state(T0 + DAY_S, p_exceed=p_top6(1, 0.5))
    core.take([day0[3], day0[0], day1, day0[2], day0[1]])  # order of arrival does not matter
    core.flush(0.0)  # the first flush writes at once: one row for day 0 (its last), one for day 1
    assert core.rows_written == 2 * 2  # two rows, two indicators
    core.take([make_state(T0 + DAY_S + 5 * hour, p_exceed=p_top6(1, 0.6))])
    assert core.p_exceed[("L1", "s1")] == pytest.approx(0.6)
    core.flush(5.0)  # not due yet
    assert core.rows_written == 4
    core.take([make_state(T0 + DAY_S + 6 * hour, p_exceed=p_top6(1, 0.7))])
    core.flush(10.0)  # day 1's newest
    assert core.rows_written == 4 + 2
    rec.flush()
    rec.disconnect()
    assert rrd_contents(path)["worst/1/top6/g1/state"]["Scalars:scalars"] == 3


def test_the_inbox_keeps_the_newest_state_of_a_segment_and_day_and_every_alert(recording):
    from services.viewer.service import ViewerAdapter

    rec, _ = recording
    inbox = ViewerAdapter(None, ViewerCore(rec, demo_network(), worst_n=2)).inbox  # type: ignore[arg-type]
    states = [make_state(T0 + k * 60.0, segment="s1") for k in range(3)]
    for state in (states[0], states[2], states[1]):  # s1, day 0: only the newest stays
        inbox.put(state)
    other_day = make_state(T0 + DAY_S, segment="s1")
    alerts = [make_alert(T0 + k, level="alert") for k in range(2)]
    for message in (other_day, *alerts):
        inbox.put(message)
    assert inbox.take(timeout=0) == [states[2], other_day, *alerts]
    assert inbox.superseded == 2 and inbox.dropped == 0


def test_select_worst_sticky_keeps_plotted_segments_through_near_ties():
    p = {("L1", "a"): 0.99, ("L1", "b"): 0.98, ("L1", "c"): 1.0, ("L1", "d"): 0.5}
    shown = [("L1", "a"), ("L1", "b")]
    assert select_worst_sticky(p, 2, shown, margin=0.05) == shown  # c is only 0.02 above b
    p[("L1", "c")] = 1.0
    p[("L1", "b")] = 0.9
    assert select_worst_sticky(p, 2, shown, margin=0.05) == [("L1", "c"), ("L1", "a")]
    assert select_worst_sticky(p, 3, [], margin=0.05) == select_worst(p, 3)
    assert select_worst_sticky(p, 1, [("L9", "gone")], margin=0.05) == [("L1", "c")]
    # a plotted segment that was tamped (p = 0) gives way to any worse one
    tamped = {("L1", "a"): 0.0, ("L1", "b"): 0.9, ("L1", "d"): 0.1}
    assert select_worst_sticky(tamped, 2, [("L1", "a"), ("L1", "b")], margin=0.25) == [
        ("L1", "b"),
        ("L1", "d"),
    ]
    # and one at p = 0.3 to one above 0.45 only
    lower = {("L1", "a"): 0.3, ("L1", "d"): 0.44}
    assert select_worst_sticky(lower, 1, [("L1", "a")], margin=0.25) == [("L1", "a")]
    lower[("L1", "d")] = 0.46
    assert select_worst_sticky(lower, 1, [("L1", "a")], margin=0.25) == [("L1", "d")]


def test_messages_on_segments_the_map_lacks_are_refused(recording):
    from schemas import SchemaError, encode
    from services.viewer.service import ViewerAdapter
    from track.segments import KnownSegments

    rec, _ = recording
    network = demo_network()
    known = KnownSegments.of(network, "demo")
    adapter = ViewerAdapter(None, ViewerCore(rec, network, worst_n=2), known=known)  # type: ignore[arg-type]

    class Sample:  # what the decoder reads of a zenoh.Sample
        def __init__(self, key: str, payload: bytes) -> None:
            self.key_expr, self.payload, self._payload = key, self, payload

        def to_bytes(self) -> bytes:
            return self._payload

    known = make_state(T0, line="L1", segment="s00001")
    unknown = make_state(T0, line="L1", segment="s99999")
    on_state = adapter._decoder("state", type(known))
    for state in (known, unknown):
        sample = Sample(f"tf/state/{state.line}/{state.segment}", encode(state))
        if state is known:
            on_state(sample)  # type: ignore[arg-type]
        else:
            with pytest.raises(SchemaError, match="L1/s99999 is not in the network demo"):
                on_state(sample)  # type: ignore[arg-type]
    assert len(adapter.inbox.take(timeout=0)) == 1


@pytest.mark.parametrize("text", ["L1", "L1/", "/s1", "L1/s1/x", "L 1/s1", "L1/s*"])
def test_viewer_select_refuses_what_is_not_line_slash_segment(text):
    from services.viewer.service import parse_segment

    with pytest.raises(ValueError):
        parse_segment(text)


def test_viewer_select_takes_line_slash_segment():
    from services.viewer.service import parse_segment

    assert parse_segment("L1/s00042") == ("L1", "s00042")


def test_the_ranking_says_what_each_segments_last_trc_record_measured(recording):
    rec, _ = recording
    core = ViewerCore(rec, None, worst_n=2, plot_flush_s=5.0, live_flush_s=1.0)
    core.start(now=0.0)
    level_only = msgspec.structs.replace(
        make_state(T0, segment="s1", p_exceed=p_top6(1, 0.7), last_trc_t=T0 - DAY_S),
        last_trc_indicators=["top6"],
    )
    core.take([level_only, make_state(T0, segment="s2", p_exceed=p_top6(1, 0.2))])
    core.flush(0.0)
    rows = core._ranking_text.splitlines()
    assert "| #1 | 0.70 | top6 | L1/s1 |" in rows and "| #2 | 0.20 | - | L1/s2 |" in rows


def test_the_ranking_and_alerts_name_lines_as_operators_do(recording):
    rec, _ = recording
    lonlat = [(8.0, 44.0), (8.05, 44.0)]
    network = Network(
        {
            "way7-t2": Line("way7-t2", lonlat, lonlat[0], name="Sanremo – Albenga, track 2"),
            "L9": Line("L9", lonlat, lonlat[0]),
        },
        200.0,
        lonlat[0],
    )
    core = ViewerCore(rec, network, worst_n=2, plot_flush_s=5.0, live_flush_s=1.0)
    core.start(now=0.0)
    core.take(
        [
            make_state(T0, line="way7-t2", segment="s00001", p_exceed=p_top6(1, 0.7)),
            make_state(T0, line="L9", segment="s00002", p_exceed=p_top6(1, 0.2)),
        ]
    )
    core.flush(0.0)
    rows = core._ranking_text.splitlines()
    assert "| #1 | 0.70 | - | Sanremo – Albenga, track 2 (way7-t2/s00001) |" in rows
    assert "| #2 | 0.20 | - | L9/s00002 |" in rows
    assert (
        core.segment_label(("way7-t2", "s00003")) == "Sanremo – Albenga, track 2 (way7-t2/s00003)"
    )


PLAN_ROWS = [
    ("L1", "s00002", 0, 0),
    ("L2", "s00010", 3, 1),
    ("L1", "s00003", 0, 0),
    ("L1", "s00050", 12, 2),  # beyond the weeks the map shows
    ("L1", "s00060", -1, -1),  # not tamped
]


def test_planned_possessions_of_the_next_weeks_by_week():
    assert planned_possessions(make_plan(T0, PLAN_ROWS, T0), PLAN_WEEKS) == [
        (0, "L1", ["s00002", "s00003"]),
        (3, "L2", ["s00010"]),
    ]
    assert planned_possessions(make_plan(T0, PLAN_ROWS, T0), 13)[-1] == (12, "L1", ["s00050"])


def test_the_map_shows_the_newest_plans_tampings_labelled_with_their_week(recording):
    rec, path = recording
    core = ViewerCore(rec, demo_network(), worst_n=1)
    core.start(now=0.0)
    core.log_batch([make_plan(T0 + DAY_S, PLAN_ROWS, T0)])
    core.log_batch([make_plan(T0, [("L3", "s00001", 1, 0)], T0)])  # older: not drawn
    assert core.plan is not None and core.plan.computed_at == T0 + DAY_S
    core.log_batch([make_plan(T0 + 2 * DAY_S, [], T0)])  # a newer plan tamping nothing: cleared
    rec.flush()
    rec.disconnect()
    verify_rrd(path)
    assert rrd_contents(path)["map/plan/tamping"]["LineStrips2D:strips"] == 2
    printed = rrd_printout(path)
    assert "tamp w0 01-01" in printed and "tamp w3 01-22" in printed
    assert "tamp w1" not in printed and "tamp w12" not in printed


def test_the_inbox_keeps_the_newest_plan():
    from services.viewer.service import ViewerAdapter

    inbox = ViewerAdapter(None, ViewerCore(None, None)).inbox  # type: ignore[arg-type]
    newest, older = make_plan(T0 + DAY_S, PLAN_ROWS, T0), make_plan(T0, [], T0)
    inbox.put(newest)
    inbox.put(older)  # late: kept out
    assert coalesce_key(newest) == ("plan",) and message_version(newest) == T0 + DAY_S
    assert inbox.take(timeout=0) == [newest]
