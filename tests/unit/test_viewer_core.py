"""The viewer core: colour map, worst-segment selection, blueprint rate limit, and what it
writes to a recording (read back with the ``rerun`` CLI)."""

from __future__ import annotations

import uuid
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import rerun as rr

from schemas import Alert, GpsFix, OnboardIndex, TrcRecord
from services.alerting.testing import T0, make_state, p_top6
from services.viewer.core import (
    UNKNOWN_RGB,
    ViewerCore,
    build_blueprint,
    exceedance_color,
    segment_exceedance,
    select_worst,
)
from services.viewer.testing import rrd_contents, verify_rrd
from simulators.network import demo_network

DAY_S = 86_400.0


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


def test_blueprint_has_map_one_row_per_worst_segment_and_alert_log():
    blueprint = build_blueprint([("L1", "s00001", 0.8), ("L2", "s00005", 0.4)])
    top, alerts = blueprint.root_container.contents  # Vertical(top, alerts)
    map_view, worst = top.contents
    assert map_view.origin == "map" and alerts.origin == "alerts"
    assert [[v.origin for v in row.contents] for row in worst.contents] == [
        ["segments/L1/s00001/top6", "segments/L1/s00001/align10"],
        ["segments/L2/s00005/top6", "segments/L2/s00005/align10"],
    ]
    (only_map,) = build_blueprint([]).root_container.contents[0].contents
    assert only_map.origin == "map"


@pytest.fixture
def recording(tmp_path: Path) -> Iterator[tuple[rr.RecordingStream, Path]]:
    path = tmp_path / "core.rrd"
    rec = rr.RecordingStream("TrackFusion", recording_id=uuid.uuid4())
    rec.save(path)
    try:
        yield rec, path
    finally:
        rec.disconnect()


def test_blueprint_resent_only_when_worst_set_changes_and_interval_passed(recording):
    rec, _ = recording
    core = ViewerCore(rec, None, worst_n=1, blueprint_interval_s=5.0)
    core.start(now=0.0)
    assert core.blueprints_sent == 1  # the map and the alert log, no segment yet
    core.log_batch([make_state(T0, segment="s1", p_exceed=p_top6(1, 0.7))])
    assert not core.maybe_send_blueprint(1.0)  # too soon
    assert core.maybe_send_blueprint(6.0) and core.worst() == [("L1", "s1")]
    core.log_batch([make_state(T0, segment="s2", p_exceed=p_top6(1, 0.2))])
    assert not core.maybe_send_blueprint(20.0)  # same worst set: nothing to send
    core.log_batch([make_state(T0 + DAY_S, segment="s2", p_exceed=p_top6(1, 0.9))])
    assert not core.maybe_send_blueprint(7.0)
    assert core.maybe_send_blueprint(7.0, force=True) and core.worst() == [("L1", "s2")]
    assert core.blueprints_sent == 3


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
        OnboardIndex(
            line="L1",
            segment=seg,
            train="T1",
            unit="u1",
            t=T0 + 0.5 * DAY_S,
            top6_mm=5.0,
            align10_mm=3.5,
            speed_mps=20.0,
            coverage=1.0,
        ),  # fmt: skip
        TrcRecord(line="L1", segment=seg, t=T0, top6_mm=4.1, align10_mm=3.1, run_id="r1"),
        GpsFix(train="T1", t=T0 + 10, lat_deg=lat, lon_deg=lon),
        GpsFix(train="T2", t=T0 + 10, lat_deg=lat, lon_deg=lon, fix_quality=0),  # skipped
        Alert(
            line="L1",
            segment=seg,
            t=T0 + DAY_S,
            kind="exceedance",
            status="raised",
            indicator="top6",
            level="intervention",
            probability=0.6,
        ),  # fmt: skip
    ]
    assert core.log_batch(batch) == len(batch)
    # the same colour again: the line's colours are not re-logged
    core.log_batch([make_state(T0 + 4 * DAY_S, segment=seg, p_exceed=p_top6(1, 0.6))])
    rec.flush()
    rec.disconnect()

    verify_rrd(path)
    contents = rrd_contents(path)
    base = f"segments/L1/{seg}"
    for indicator in ("top6", "align10"):
        for series in ("estimate", "ci_low", "ci_high", "limit_alert", "limit_intervention"):
            assert contents[f"{base}/{indicator}/{series}"]["Scalars:scalars"] == 4
            assert contents[f"{base}/{indicator}/{series}"]["SeriesLines:colors"] == 1  # static
        for series in ("onboard", "trc"):
            assert contents[f"{base}/{indicator}/{series}"]["Scalars:scalars"] == 1
            assert contents[f"{base}/{indicator}/{series}"]["SeriesPoints:markers"] == 1
    assert contents["map/segments/L1"]["LineStrips2D:strips"] == 1  # static geometry
    assert contents["map/segments/L1"]["LineStrips2D:colors"] == 2  # grey, then one change
    assert contents["map/segments/L2"]["LineStrips2D:colors"] == 1  # grey only
    assert contents["map/trains/T1"]["Points2D:positions"] == 1
    assert "map/trains/T2" not in contents
    assert contents["alerts"]["TextLog:level"] == 1
