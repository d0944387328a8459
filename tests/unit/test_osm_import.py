"""The OpenStreetMap import (track/osm.py): each rule on hand-made extracts, and the file it
writes read back by every reader of a network file."""

from __future__ import annotations

import copy
import json
import uuid
from pathlib import Path

import numpy as np
import pytest
import rerun as rr

from services.calibration.service import known_segments as calibration_segments
from services.cli import main as cli_main
from services.defaults import load_network
from services.filtering.service import known_segments as filtering_segments
from services.filtering.service import read_network
from services.tools.network_map import network_map
from services.viewer.core import ViewerCore
from services.viewer.testing import rrd_printout
from track.network import Line, Network, check_id, lonlat_to_xy
from track.osm import import_osm, parse_maxspeed, running_of_pair, slug, to_geojson
from track.segments import SegmentTable

FIXTURES = Path(__file__).parents[1] / "fixtures" / "osm"
LAKESIDE = FIXTURES / "lakeside.geojson"
OVERPASS = FIXTURES / "overpass.json"


def lakeside() -> dict:
    return json.loads(LAKESIDE.read_text())


def osm_feature(doc: dict, osm_id: str) -> dict:
    """The fixture's feature of an OSM id, whichever way its id is written."""
    number = osm_id.split("/")[1]
    for f in doc["features"]:
        p = f["properties"]
        if p.get("@id") == osm_id or p.get("id") == osm_id or p.get("osm_id") == number:
            return f
    raise KeyError(osm_id)


def chainage_of(line: Line, lonlat) -> float:
    """Chainage of a point's projection on the line (independent of how it was joined)."""
    chainage, _ = line.project(lonlat_to_xy(np.asarray(lonlat, float), line.origin_lonlat))
    return float(chainage)


def way_length_m(doc: dict, osm_id: str, origin) -> float:
    xy = lonlat_to_xy(np.asarray(osm_feature(doc, osm_id)["geometry"]["coordinates"]), origin)
    return float(np.hypot(*np.diff(xy, axis=0).T).sum())


@pytest.fixture(scope="module")
def imported():
    return import_osm(lakeside())


def test_a_double_track_route_gives_one_line_per_track_and_the_branch_its_own(imported):
    network, extra, report = imported
    assert set(network.lines) == {"650-t1", "650-t2", "651"}
    assert extra["650-t1"]["osm_ways"] == ["way/101", "way/102", "way/103", "way/104", "way/105"]
    assert extra["650-t2"]["osm_ways"] == ["way/201", "way/202", "way/203", "way/204"]
    assert extra["651"]["osm_ways"] == ["way/301", "way/302"]
    assert [extra[i]["track_ref"] for i in ("650-t1", "650-t2", "651")] == ["1", "2", ""]
    names = {line.id: line.name for line in network.lines.values()}
    assert names == {
        "650-t1": "Lakeside Line, track 1",
        "650-t2": "Lakeside Line, track 2",
        "651": "Valley Branch",
    }
    assert [line.id for line in report.lines] == sorted(network.lines)


def test_reversed_ways_are_turned_so_the_line_runs_on_without_doubling_back(imported):
    network, extra, _ = imported
    doc = lakeside()
    for line in network.lines.values():
        ways = sum(way_length_m(doc, w, network.origin_lonlat) for w in extra[line.id]["osm_ways"])
        assert line.length_m == pytest.approx(ways, rel=1e-9)  # each way once, end to end
        steps = np.hypot(*np.diff(line.xy, axis=0).T)
        assert steps.max() < 101.0  # the fixture's vertex spacing: no jump between ways
        assert line.lonlat[-1, 0] > line.lonlat[0, 0]  # west to east
    # both tracks share their chainage direction: a station is at about the same chainage
    t1, t2 = network.lines["650-t1"], network.lines["650-t2"]
    assert abs(t1.stations[0] - t2.stations[0]) < 5.0


def test_the_branch_starts_at_the_junction_with_the_main_line(imported):
    network, _, _ = imported
    junction = osm_feature(lakeside(), "way/105")["geometry"]["coordinates"][0]
    branch = network.lines["651"]
    assert np.allclose(branch.lonlat[0], junction)
    assert chainage_of(network.lines["650-t1"], junction) == pytest.approx(
        way_length_m(lakeside(), "way/101", network.origin_lonlat)
        + sum(way_length_m(lakeside(), w, network.origin_lonlat) for w in ("way/102", "way/103"))
        + way_length_m(lakeside(), "way/104", network.origin_lonlat),
        abs=0.01,
    )


def test_where_more_ways_of_a_route_meet_the_walk_goes_on_straight_ahead():
    def way(n, coords):
        return {
            "type": "Feature",
            "properties": {"@id": f"way/{n}", "railway": "rail", "ref": "X 1"},
            "geometry": {"type": "LineString", "coordinates": coords},
        }

    a, b = [8.30, 47.05], [8.31, 47.05]
    doc = {
        "type": "FeatureCollection",
        "features": [
            way(1, [a, b]),
            way(2, [b, [8.315, 47.055]]),  # turns off by 45 degrees
            way(3, [[8.32, 47.05], b]),  # straight on, drawn backwards
        ],
    }
    network, extra, _ = import_osm(doc)
    assert extra["X-1"]["osm_ways"] == ["way/1", "way/3"]
    assert extra["X-1-2"]["osm_ways"] == ["way/2"]
    # a hairpin (back the way it came) is no way on: a train cannot turn so
    doc["features"] = [way(1, [a, b]), way(4, [b, [8.30, 47.0502]])]
    network, extra, _ = import_osm(doc)
    assert sorted(extra[i]["osm_ways"] for i in network.lines) == [["way/1"], ["way/4"]]


def test_what_is_left_out_is_reported_with_its_reason(imported):
    _, _, report = imported
    dropped = {reason.split(" (")[0]: ids for reason, ids in report.dropped.items()}
    assert dropped == {
        "service=siding": ["way/401"],
        "service=yard": ["way/402", "way/403"],
        "railway=tram": ["way/501"],
        "railway=platform": ["way/502"],
        "railway=abandoned": ["way/503"],
        "shorter than 100 m after joining": ["way/504"],
        "station farther than 150 m from every line": ["node/6"],
        "stop_position of another mode than train": ["node/7"],
    }
    text = report.text()
    assert "made 3 lines" in text and "service=yard" in text and "way/402 way/403" in text


def test_keep_service_keeps_yards_and_sidings_as_lines_of_their_own():
    network, extra, report = import_osm(lakeside(), keep_service=True)
    assert {"way401", "way402", "way403"} <= set(network.lines)
    assert not any(reason.startswith("service=") for reason in report.dropped)
    assert extra["650-t1"]["osm_ways"][0] == "way/101"  # the siding does not join the main line


def test_tunnels_and_bridges_are_the_chainage_ranges_of_their_ways(imported):
    network, extra, _ = imported
    doc = lakeside()
    for line_id, tunnel_way, bridge_way in (
        ("650-t1", "way/102", "way/103"),
        ("650-t2", "way/202", "way/203"),
    ):
        line = network.lines[line_id]
        ends = osm_feature(doc, tunnel_way)["geometry"]["coordinates"]
        expected = sorted(chainage_of(line, p) for p in (ends[0], ends[-1]))
        ((start, end),) = line.tunnels
        assert (start, end) == pytest.approx(expected, abs=0.1)
        bridge = osm_feature(doc, bridge_way)["geometry"]["coordinates"]
        expected = sorted(chainage_of(line, p) for p in (bridge[0], bridge[-1]))
        assert extra[line_id]["bridges"] == [pytest.approx(expected, abs=0.1)]
    assert network.lines["651"].tunnels == []


def test_stations_snap_to_every_line_near_them_once_with_their_names(imported):
    network, _, _ = imported
    doc = lakeside()
    station = {
        f["properties"]["name"]: f["geometry"]["coordinates"]
        for f in doc["features"]
        if f["properties"].get("railway") in ("station", "halt")
    }
    for line_id in ("650-t1", "650-t2"):
        line = network.lines[line_id]
        # Westbrook's station node and its stop position are one station
        assert line.station_names == ["Westbrook", "Lakeside Halt", "Eastfield"]
        for name, c in zip(line.station_names, line.stations, strict=True):
            assert c == pytest.approx(chainage_of(line, station[name]), abs=0.1)
    assert network.lines["651"].station_names == ["Valley"]
    narrow = import_osm(lakeside(), station_snap_m=10.0)[0]  # Valley is ~12 m off its line
    assert narrow.lines["651"].stations == []


@pytest.mark.parametrize(
    ("tag", "kmh"),
    [
        ("100", 100.0),
        ("100 km/h", 100.0),
        ("80kmh", 80.0),
        ("60 mph", 96.56064),
        ("80;100", 80.0),
        ("none", None),
        ("signals", None),
        ("DE:rural", None),
        ("", None),
        (None, None),
    ],
)
def test_maxspeed_tags(tag, kmh):
    got = parse_maxspeed(tag)
    assert got == (None if kmh is None else pytest.approx(kmh / 3.6))


def test_line_speed_is_the_length_weighted_median_of_the_known_maxspeeds(imported):
    network, extra, report = imported
    doc = lakeside()
    for line_id in ("650-t1", "650-t2", "651"):
        known = []
        for w in extra[line_id]["osm_ways"]:
            f = osm_feature(doc, w)
            tags = f["properties"].get("tags") or f["properties"]
            if "other_tags" in tags:
                tags = dict(t.split('"=>"') for t in tags["other_tags"].strip('"').split('","'))
            s = parse_maxspeed(tags.get("maxspeed"))
            if s is not None:
                known.append((s, way_length_m(doc, w, network.origin_lonlat)))
        known.sort()
        total = sum(length for _, length in known)
        cumulative = np.cumsum([length for _, length in known])
        median = known[int(np.searchsorted(cumulative, total / 2))][0]
        assert network.lines[line_id].line_speed_mps == pytest.approx(median, abs=1e-3)
    assert network.lines["650-t1"].line_speed_mps == pytest.approx(100 / 3.6, abs=1e-3)
    no_speed = copy.deepcopy(lakeside())
    for f in no_speed["features"]:
        for props in (f["properties"], f["properties"].get("tags") or {}):
            props.pop("maxspeed", None)
        f["properties"].pop("other_tags", None)
    network, _, report = import_osm(no_speed, default_speed_mps=30.0)
    assert {line.line_speed_mps for line in network.lines.values()} == {30.0}
    assert sum("no maxspeed" in w for w in report.warnings) == 3


def test_ids_are_safe_unique_and_the_same_for_the_same_input(imported):
    network, _, _ = imported
    for line_id in network.lines:
        assert check_id("id", line_id) == line_id
    again = import_osm(lakeside())
    assert json.dumps(to_geojson(again[0], again[1])) == json.dumps(
        to_geojson(imported[0], imported[1])
    )
    assert slug("Zürich – Chur / Nord #2") == "Zurich-Chur-Nord-2"


def test_an_extract_beyond_the_local_plane_is_warned_about():
    far = {
        "type": "FeatureCollection",
        "features": [
            {
                "type": "Feature",
                "properties": {"@id": f"way/{n}", "railway": "rail", "name": f"L{n}"},
                "geometry": {
                    "type": "LineString",
                    "coordinates": [[lon, 47.0], [lon + 0.01, 47.0]],
                },
            }
            for n, lon in ((1, 5.0), (2, 11.0))  # ~450 km apart
        ],
    }
    _, _, report = import_osm(far)
    assert any("within about 200 km" in w for w in report.warnings)
    assert not [w for w in import_osm(lakeside())[2].warnings if "200 km" in w]


def test_tracks_too_close_for_gps_map_matching_are_warned_about(imported):
    _, _, report = imported
    (close,) = [w for w in report.warnings if "cannot tell them apart" in w]
    assert close.startswith("lines 650-t1 and 650-t2 run within 10 m")
    assert "over 6.0 km" in close  # the tracks are 8 m apart all along
    assert "not positioned: pass --running left|right" in close
    _, _, told = import_osm(lakeside(), running="left")
    (close,) = [w for w in told.warnings if "cannot tell them apart" in w]
    assert "tells them apart by their running direction" in close
    assert "not positioned" not in close


def test_tracks_of_one_route_share_it_and_the_branch_is_its_own_route(imported):
    network, _, _ = imported
    routes = {line.id: line.route for line in network.lines.values()}
    assert routes == {"650-t1": "650", "650-t2": "650", "651": ""}
    assert network.lines["651"].route_id == "651"
    # no side given: no guess, every track runs both ways
    assert {line.running for line in network.lines.values()} == {"both"}


@pytest.mark.parametrize("side", ["left", "right"])
def test_running_is_the_direction_of_the_side_trains_keep_to(side):
    network, _, _ = import_osm(lakeside(), running=side)
    t1, t2 = network.lines["650-t1"], network.lines["650-t2"]
    # where t2 lies, seen from t1, independently of the import: the sign of its lateral
    _, lateral = t1.project(t2.xy_at(np.linspace(0.0, t2.length_m, 31)))
    t2_left = bool(np.median(lateral) > 0)
    assert t2_left  # the fixture draws track 2 north of track 1, both running east
    # a train running towards increasing chainage (east) keeps to `side`
    eastbound = t2 if (side == "left") == t2_left else t1
    westbound = t1 if eastbound is t2 else t2
    assert (eastbound.running, westbound.running) == ("increasing", "decreasing")
    assert network.lines["651"].running == "both"  # a single track


def test_running_is_left_unset_for_tracks_not_side_by_side_or_opposed():
    origin = (8.3, 47.05)
    a = Line("a", [[8.30, 47.05], [8.32, 47.05]], origin)
    beside = Line("b", [[8.30, 47.05007], [8.32, 47.05007]], origin)  # 8 m north
    far = Line("c", [[8.30, 47.06], [8.32, 47.06]], origin)  # 1.1 km north
    turned = Line("d", [[8.32, 47.05007], [8.30, 47.05007]], origin)  # drawn westwards
    assert running_of_pair(a, beside, "left") == ("decreasing", "increasing")
    assert running_of_pair(a, beside, "right") == ("increasing", "decreasing")
    assert running_of_pair(a, far, "left") is None
    assert running_of_pair(a, turned, "left") is None
    with pytest.raises(ValueError, match="left or right"):
        import_osm(lakeside(), running="middle")


def test_overpass_json_joins_by_node_ids():
    network, extra, report = import_osm(json.loads(OVERPASS.read_text()))
    (line,) = network.lines.values()
    assert line.id == "Harbour-Line" and line.name == "Harbour Line"
    assert extra[line.id]["osm_ways"] == ["way/7001", "way/7002"]
    assert report.dropped["service=crossover (yards and sidings: --keep-service to keep them)"]
    assert report.dropped["element relation"] == ["relation/9"]
    first = way_length_m(
        {"features": [{"properties": {"@id": "way/1"}, "geometry": {"coordinates": [
            [153.0200, -27.4700], [153.0260, -27.4712], [153.0320, -27.4725]]}}]},
        "way/1",
        network.origin_lonlat,
    )  # fmt: skip
    assert line.tunnels == [pytest.approx((first, line.length_m), abs=0.1)]
    assert line.station_names == ["Quay Street"]
    assert line.length_m - first > first  # 60 km/h over the longer half: the median
    assert line.line_speed_mps == pytest.approx(60 / 3.6, abs=1e-3)


@pytest.mark.parametrize(
    ("doc", "message"),
    [
        ({"type": "Topology"}, "expected a GeoJSON FeatureCollection"),
        ({"type": "FeatureCollection", "features": {}}, '"features" must be a list'),
        ({"type": "FeatureCollection", "features": [{"type": "Feature"}]}, "feature 0"),
        (
            {
                "type": "FeatureCollection",
                "features": [
                    {
                        "type": "Feature",
                        "properties": {"@id": "way/5", "railway": "rail"},
                        "geometry": {"type": "LineString", "coordinates": [[8.3, "x"]]},
                    }
                ],
            },
            "feature 0 (way/5): coordinates",
        ),
        (
            {"elements": [{"type": "way", "id": 3, "tags": {"railway": "rail"}}]},
            'element 0 (way/3): needs "geometry"',
        ),
        ({"type": "FeatureCollection", "features": []}, "no railway=rail way"),
    ],
)
def test_bad_input_says_what_is_wrong_and_where(doc, message):
    with pytest.raises(ValueError, match=message.replace("(", r"\(").replace(")", r"\)")):
        import_osm(doc)


def test_the_written_file_reads_back_in_every_reader(imported, tmp_path):
    network, extra, _ = imported
    path = tmp_path / "network.geojson"
    path.write_text(json.dumps(to_geojson(network, extra)))
    back = load_network(str(path))
    assert list(back.lines) == list(network.lines)
    for line_id, line in network.lines.items():
        got = back.lines[line_id]
        assert np.allclose(got.lonlat, line.lonlat)
        assert [s.id for s in got.segments] == [s.id for s in line.segments]
        assert got.tunnels == line.tunnels
        assert got.stations == line.stations and got.station_names == line.station_names
        assert got.name == line.name and got.line_speed_mps == line.line_speed_mps
        assert (got.route, got.running) == (line.route, line.running)
    assert Network.from_geojson(path).origin_lonlat == network.origin_lonlat
    ids = {(line.id, seg.id) for line, seg in network.segments()}
    assert calibration_segments(path).ids == ids
    assert filtering_segments(read_network(path), path).ids == ids
    assert SegmentTable.from_geojson(path).n_segments == network.n_segments
    stations = network_map(str(path)).stations
    assert {s.label for s in stations} == {"Westbrook", "Lakeside Halt", "Eastfield", "Valley"}


def test_the_command_writes_the_file_and_prints_the_report(tmp_path, capsys):
    out = tmp_path / "network.geojson"
    code = cli_main(["network", "import-osm", str(LAKESIDE), "--out", str(out)])
    printed = capsys.readouterr().out
    assert code == 0 and "made 3 lines" in printed and "dropped 9" in printed
    assert set(load_network(str(out)).lines) == {"650-t1", "650-t2", "651"}
    code = cli_main(
        ["network", "import-osm", str(LAKESIDE), "--out", str(out), "--segment-length", "500"]
    )
    assert code == 0
    network = load_network(str(out))  # what the services read: cut as written
    assert network.segment_length_m == 500.0
    assert SegmentTable.from_geojson(out).n_segments == network.n_segments < 71 / 2
    code = cli_main(
        ["network", "import-osm", str(LAKESIDE), "--out", str(out), "--running", "left"]
    )
    assert code == 0
    running = {line.id: line.running for line in load_network(str(out)).lines.values()}
    assert running == {"650-t1": "decreasing", "650-t2": "increasing", "651": "both"}


def test_a_bad_file_exits_2_with_one_line_naming_it(tmp_path, capsys):
    bad = tmp_path / "bad.geojson"
    bad.write_text(
        json.dumps(
            {
                "type": "FeatureCollection",
                "features": [
                    {"type": "Feature", "properties": {"@id": "way/9"}, "geometry": {"a": 1}}
                ],
            }
        )
    )
    code = cli_main(["network", "import-osm", str(bad), "--out", str(tmp_path / "n.geojson")])
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1
    assert str(bad) in err and "feature 0 (way/9)" in err
    code = cli_main(["network", "import-osm", str(tmp_path / "missing.geojson"), "--out", "x"])
    assert code == 2 and "missing.geojson" in capsys.readouterr().err


def test_the_viewer_map_shows_the_imported_names(imported, tmp_path):
    network, _, _ = imported
    path = tmp_path / "map.rrd"
    rec = rr.RecordingStream("TrackFusion", recording_id=uuid.uuid4())
    rec.save(path)
    ViewerCore(rec, network, worst_n=1).start(now=0.0)
    rec.flush()
    rec.disconnect()
    printed = rrd_printout(path)  # long cells are cut: the first labels of each
    first = network.lines["650-t1"]
    assert (
        f"[{first.id} Lakeside Line, track 1, {first.id} Lakeside Line, track 1, 650-t2" in printed
    )
    assert f"[Westbrook ({first.id} km {first.stations[0] / 1e3:.1f}), Lakeside Halt" in printed


def test_degenerate_ways_are_dropped_not_fatal():
    def way(n, coords):
        return {
            "type": "Feature",
            "properties": {"@id": f"way/{n}", "railway": "rail", "name": "Spur"},
            "geometry": {"type": "LineString", "coordinates": coords},
        }

    doc = {
        "type": "FeatureCollection",
        "features": [
            way(1, [[8.3, 47.0]]),  # one point
            way(2, [[8.5, 47.0], [8.5, 47.0]]),  # zero length
            way(3, [[8.4, 47.0], [8.4, 47.0], [8.41, 47.0]]),  # a repeated first vertex
        ],
    }
    network, extra, report = import_osm(doc, min_length_m=0.0)
    assert report.dropped["a way of fewer than 2 points"] == ["way/1"]
    assert report.dropped["zero length"] == ["way/2"]
    assert [extra[i]["osm_ways"] for i in network.lines] == [["way/3"]]


@pytest.mark.parametrize(
    ("feature_id", "props", "expected"),
    [
        ("w123", {}, "way/123"),  # osmium export --add-unique-id=type_id
        (None, {"@type": "way", "@id": 123}, "way/123"),  # osmium export -a type,id
        (None, {"@id": "way/123"}, "way/123"),  # overpass-turbo
        (None, {"id": "way/123"}, "way/123"),  # osmtogeojson, tags nested
        (None, {"osm_id": "123"}, "way/123"),  # ogr2ogr
        (None, {}, "feature0"),
    ],
)
def test_the_osm_id_is_read_as_each_exporter_writes_it(feature_id, props, expected):
    feature = {
        "type": "Feature",
        "properties": {"railway": "tram", **props},
        "geometry": {"type": "LineString", "coordinates": [[8.3, 47.0], [8.31, 47.0]]},
    }
    if feature_id is not None:
        feature["id"] = feature_id
    rail = {
        "type": "Feature",
        "properties": {"railway": "rail", "@id": "way/1"},
        "geometry": {"type": "LineString", "coordinates": [[8.4, 47.0], [8.41, 47.0]]},
    }
    _, _, report = import_osm({"type": "FeatureCollection", "features": [feature, rail]})
    assert report.dropped["railway=tram"] == [expected]


def test_untagged_open_line_joins_the_numbered_tracks_of_a_station():
    """Double track without ``railway:track_ref`` between stations, tracks 1, 2 and a loop
    3 tagged in the station: one line per track through the station, the loop its own."""
    k = 1 / (111_195 * np.cos(np.radians(47.0)))

    def way(n, xy, track=None):
        tags = {"railway": "rail", "ref": "R"} | ({"railway:track_ref": track} if track else {})
        coords = [[8.3 + x * k, 47.0 + y / 111_195] for x, y in xy]
        return {
            "type": "Feature",
            "properties": {"@id": f"way/{n}", **tags},
            "geometry": {"type": "LineString", "coordinates": coords},
        }

    doc = {
        "type": "FeatureCollection",
        "features": [
            way(1, [(0, 0), (1000, 0)]),
            way(2, [(0, 4.5), (1000, 4.5)]),
            way(3, [(1000, 0), (1600, 0)], "1"),
            way(4, [(1600, 4.5), (1000, 4.5)], "2"),
            way(5, [(1000, 0), (1050, -5), (1550, -5), (1600, 0)], "3"),
            way(6, [(3000, 0), (1600, 0)]),
            way(7, [(1600, 4.5), (3000, 4.5)]),
        ],
    }
    network, extra, _ = import_osm(doc)
    assert {i: extra[i]["osm_ways"] for i in network.lines} == {
        "R-t1": ["way/1", "way/3", "way/6"],
        "R-t2": ["way/2", "way/4", "way/7"],
        "R-t3": ["way/5"],
    }
    assert network.lines["R-t1"].length_m == pytest.approx(3000.0, rel=1e-3)


def test_other_railway_values_are_kept_when_asked():
    doc = lakeside()
    for f in doc["features"]:
        tags = f["properties"].get("tags") or f["properties"]
        if tags.get("ref") == "651":
            tags["railway"] = "narrow_gauge"
    network, _, report = import_osm(doc)
    assert "651" not in network.lines and report.dropped["railway=narrow_gauge"]
    network, _, report = import_osm(doc, railway_values=("rail", "narrow_gauge"))
    assert "651" in network.lines and "railway=narrow_gauge" not in report.dropped


def test_the_readme_shows_what_the_command_prints(tmp_path, monkeypatch, capsys):
    readme = (Path(__file__).parents[2] / "README.md").read_text()
    start = readme.index("read 18 ways and 7 points\n")
    shown = readme[start : readme.index("```", start)]
    monkeypatch.chdir(tmp_path)
    command = ["network", "import-osm", str(LAKESIDE), "--running", "left"]
    assert cli_main([*command, "--out", "network.geojson"]) == 0
    assert capsys.readouterr().out == shown


def test_a_line_is_named_after_most_of_its_length():
    doc = lakeside()
    first = osm_feature(doc, "way/101")  # the first 1.5 km of 6 km
    first["properties"]["name"] = "Westbrook Viaduct"
    network, _, _ = import_osm(doc)
    assert network.lines["650-t1"].name == "Lakeside Line, track 1"
    assert network.lines["650-t1"].id == "650-t1"  # joined by ref all the same


RIVIERA = FIXTURES / "riviera.json"


def test_lines_without_name_or_ref_are_named_by_their_relations_or_stations():
    """Ways with no name nor ref (ids stay ``way{n}[-t{track}]``): a route=railway
    relation names its line; otherwise the first and last station along it do."""
    doc = json.loads(RIVIERA.read_text())
    network, _, report = import_osm(doc, running="left")
    names = {line.id: line.name for line in network.lines.values()}
    assert names == {
        "way1024952344-t1": "Alassio – Albenga, track 1",
        "way1024952346-t2": "Alassio – Albenga, track 2",
        "way1100000001": "Albenga–Garessio",
    }
    assert "Alassio – Albenga, track 2" in report.text()
    again, _, _ = import_osm(json.loads(RIVIERA.read_text()), running="left")
    assert {i: line.name for i, line in again.lines.items()} == names  # same ids, same names
    assert "element relation" not in report.dropped  # relations are read, not dropped


def test_a_railway_relation_beats_the_ways_name_which_beats_a_train_relation():
    doc = json.loads(RIVIERA.read_text())
    branch = next(e for e in doc["elements"] if e.get("id") == 1100000001)
    branch["tags"]["name"] = "Branch"
    network, _, _ = import_osm(doc)
    assert network.lines["Branch"].name == "Albenga–Garessio"
    for e in doc["elements"]:
        if e.get("id") == 5501:
            e["tags"]["route"] = "disused"
    network, _, _ = import_osm(doc)
    assert network.lines["Branch"].name == "Branch"
    del branch["tags"]["name"]
    network, _, _ = import_osm(doc)
    assert network.lines["way1100000001"].name == "Regionale Savona – Ventimiglia"


def test_overpass_turbo_geojson_lists_relations_in_its_features():
    doc = {
        "type": "FeatureCollection",
        "features": [
            {
                "type": "Feature",
                "properties": {
                    "@id": "way/77",
                    "railway": "rail",
                    "@relations": [
                        {"role": "", "rel": 5, "reltags": {"route": "railway", "ref": "R5"}}
                    ],
                },
                "geometry": {"type": "LineString", "coordinates": [[8.0, 44.0], [8.01, 44.0]]},
            }
        ],
    }
    network, _, _ = import_osm(doc)
    assert network.lines["way77"].name == "R5"
