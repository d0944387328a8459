"""The simulator's network: GeoJSON in and out, segment cut, chainage geometry, generator."""

from __future__ import annotations

import json

import numpy as np
import pytest

from schemas import keys
from schemas.wire import check_id
from services.defaults import demo_network
from simulators.network import generate_network
from track.network import Network, cut_segments


@pytest.fixture(scope="module")
def demo() -> Network:
    return demo_network()


def _same(a: Network, b: Network) -> None:
    assert list(a.lines) == list(b.lines)
    assert a.origin_lonlat == b.origin_lonlat and a.segment_length_m == b.segment_length_m
    for la, lb in zip(a.lines.values(), b.lines.values(), strict=True):
        np.testing.assert_array_equal(la.lonlat, lb.lonlat)
        assert la.segments == lb.segments
        assert (la.tunnels, la.stations, la.line_speed_mps) == (
            lb.tunnels,
            lb.stations,
            lb.line_speed_mps,
        )


@pytest.mark.parametrize("include_segments", [True, False])
def test_geojson_round_trip(demo, tmp_path, include_segments):
    gj = demo.to_geojson(include_segments=include_segments)
    assert len(gj["features"]) == 3 + include_segments * demo.n_segments
    _same(demo, Network.from_geojson(gj))
    path = tmp_path / "net.geojson"
    path.write_text(json.dumps(gj))
    _same(demo, Network.from_geojson(path))
    _same(demo, Network.from_geojson(str(path)))
    _same(demo, Network.from_geojson(json.dumps(gj)))


def test_segment_features_follow_the_line(demo):
    segs = [f for f in demo.to_geojson()["features"] if f["properties"]["kind"] == "segment"]
    line = demo.lines["L2"]
    f = next(f for f in segs if f["properties"]["line"] == "L2" and f["properties"]["index"] == 7)
    ll = np.array(f["geometry"]["coordinates"])
    np.testing.assert_allclose(ll[[0, -1]], line.lonlat_at([1400.0, 1600.0]), atol=1e-9)
    c, lateral = line.project(demo.to_xy(ll))
    np.testing.assert_allclose(lateral, 0, atol=1e-6)
    assert (np.diff(c) > 0).all()


@pytest.mark.parametrize(
    ("length", "seg", "n", "last"),
    [(1000.0, 200.0, 5, 200.0), (1099.0, 200.0, 5, 299.0), (1100.0, 200.0, 6, 100.0),
     (150.0, 200.0, 1, 150.0), (1000.0, 50.0, 20, 50.0)],
)  # fmt: skip
def test_cut_segments(length, seg, n, last):
    s = cut_segments("L1", length, seg)
    assert len(s) == n and s[-1].length_m == pytest.approx(last)
    assert s[0].start_m == 0 and s[-1].end_m == length
    assert all(a.end_m == b.start_m for a, b in zip(s, s[1:], strict=False))
    assert [x.index for x in s] == list(range(n))


def test_demo_segments_cover_lines_with_unique_safe_ids(demo):
    for line in demo.lines.values():
        lengths = np.array([s.length_m for s in line.segments])
        assert ((lengths >= 100) & (lengths < 300)).all()
        assert lengths.sum() == pytest.approx(line.length_m)
        ids = [s.id for s in line.segments]
        assert len(set(ids)) == len(ids)
        for s in line.segments:
            check_id("segment", s.id)
            assert keys.index("tf", line.id, s.id).endswith(f"/{line.id}/{s.id}")
    assert demo.n_segments == sum(1 for _ in demo.segments())


def test_chainage_geometry(demo):
    rng = np.random.default_rng(0)
    for line in demo.lines.values():
        c = np.r_[0.0, rng.uniform(0, line.length_m, 500), line.length_m]
        got, lateral = line.project(line.xy_at(c))
        np.testing.assert_allclose(got, c, atol=1e-6)
        np.testing.assert_allclose(lateral, 0, atol=1e-6)
        # Points 5 m to the left of piece middles project back with lateral +5 m.
        mid = 0.5 * (line.chainage_m[:-1] + line.chainage_m[1:])
        h = line.heading_at(mid)
        off = line.xy_at(mid) + 5.0 * np.stack([-np.sin(h), np.cos(h)], -1)
        got, lateral = line.project(off)
        np.testing.assert_allclose(got, mid, atol=1e-6)
        np.testing.assert_allclose(lateral, 5.0, atol=1e-6)
        np.testing.assert_allclose(demo.to_xy(line.lonlat_at(c)), line.xy_at(c), atol=1e-6)
        np.testing.assert_allclose(demo.to_lonlat(demo.to_xy(line.lonlat)), line.lonlat)
        idx = line.segment_index_at([-1.0, 0.0, 199.9, 200.0, line.length_m, line.length_m + 1])
        assert idx.tolist() == [-1, 0, 0, 1, len(line.segments) - 1, -1]


def test_demo_network_is_plausible(demo):
    assert len(demo.lines) == 3
    assert 55e3 < sum(line.length_m for line in demo.lines.values()) < 65e3
    assert sum(len(line.tunnels) for line in demo.lines.values()) >= 2
    lon, lat = np.concatenate([line.lonlat for line in demo.lines.values()]).mean(axis=0)
    assert abs(lon - 153.0) < 0.5 and abs(lat + 27.5) < 0.5  # around Brisbane
    for line in demo.lines.values():
        turn = np.ptp(np.unwrap(line.heading_at(line.chainage_m[:-1])))
        assert turn > np.radians(30)  # curved, not straight
        assert np.diff(line.stations).max() < 5e3
    # L3 runs a few tens of metres beside L1 for kilometres: map matching must hold on.
    _, lateral = demo.lines["L1"].project(demo.lines["L3"].xy)
    beside = (np.abs(lateral) > 20) & (np.abs(lateral) < 50)
    assert np.diff(demo.lines["L3"].chainage_m)[beside[:-1]].sum() > 3e3


@pytest.mark.parametrize(
    ("obj", "match"),
    [
        ({"type": "Feature"}, "FeatureCollection"),
        ({"type": "FeatureCollection"}, "features"),
        ({"type": "FeatureCollection", "features": []}, "no LineString"),
        (
            {"type": "FeatureCollection", "features": [
                {"type": "Feature", "geometry": {"type": "Point", "coordinates": [153, -27]},
                 "properties": {"id": "L1"}}]},
            "LineString",
        ),
        (
            {"type": "FeatureCollection", "features": [
                {"type": "Feature", "geometry": {"type": "LineString",
                 "coordinates": [[153, -27], [153.1, -27]]}, "properties": {}}]},
            "id",
        ),
        (
            {"type": "FeatureCollection", "features": [
                {"type": "Feature", "geometry": {"type": "LineString",
                 "coordinates": [[153, -27]]}, "properties": {"id": "L1"}}]},
            "at least 2",
        ),
        (
            {"type": "FeatureCollection", "features": [
                {"type": "Feature", "geometry": {"type": "LineString",
                 "coordinates": [[153, -27], [153.1, -27]]}, "properties": {"id": "L/1"}}]},
            "without",
        ),
        (
            {"type": "FeatureCollection", "features": [
                {"type": "Feature", "geometry": {"type": "LineString",
                 "coordinates": [[-27, 153], [-27, 153.1]]}, "properties": {"id": "L1"}}]},
            r"\[lon, lat\]",
        ),
        (
            {"type": "FeatureCollection", "features": [
                {"type": "Feature", "geometry": {"type": "LineString",
                 "coordinates": [[153, -27], [153.1, -27]]},
                 "properties": {"id": "L1", "tunnels": [[0, 1e6]]}}]},
            "tunnel",
        ),
        ("{not json", "JSON"),
    ],
)  # fmt: skip
def test_bad_geojson_says_what_to_fix(obj, match):
    with pytest.raises(ValueError, match=match):
        Network.from_geojson(obj)


def test_duplicate_line_ids_are_refused(demo):
    gj = demo.to_geojson(include_segments=False)
    gj["features"][1]["properties"]["id"] = "L1"
    with pytest.raises(ValueError, match="unique"):
        Network.from_geojson(gj)


def test_generate_large_network():
    net = generate_network(40, 50, seed=7)
    assert net.n_segments >= 10_000 and len(net.lines) == 40
    assert len({line.id for line in net.lines.values()}) == 40
    again = generate_network(40, 50, seed=7)
    np.testing.assert_array_equal(net.lines["L17"].lonlat, again.lines["L17"].lonlat)
    other = generate_network(40, 50, seed=8)
    assert not np.allclose(net.lines["L17"].lonlat, other.lines["L17"].lonlat)
    extent = np.ptp(np.concatenate([line.xy for line in net.lines.values()]), axis=0)
    assert (extent < 400e3).all()
    line = net.lines["L01"]
    c = np.linspace(0, line.length_m, 300)
    np.testing.assert_allclose(line.project(line.xy_at(c))[0], c, atol=1e-6)
    _same(net, Network.from_geojson(net.to_geojson(include_segments=False)))


def test_route_and_running_are_read_written_and_checked(demo):
    gj = demo.to_geojson(include_segments=False)
    assert all("route" not in f["properties"] for f in gj["features"])  # defaults not written
    gj["features"][0]["properties"] |= {"route": "R1", "running": "increasing"}
    gj["features"][2]["properties"] |= {"route": "R1", "running": "decreasing"}
    network = Network.from_geojson(gj)
    got = {line.id: (line.route_id, line.running) for line in network.lines.values()}
    assert got == {
        "L1": ("R1", "increasing"),
        "L2": ("L2", "both"),
        "L3": ("R1", "decreasing"),
    }
    back = Network.from_geojson(network.to_geojson())
    assert {i: (x.route, x.running) for i, x in back.lines.items()} == {
        "L1": ("R1", "increasing"),
        "L2": ("", "both"),
        "L3": ("R1", "decreasing"),
    }
    gj["features"][1]["properties"]["running"] = "up"
    with pytest.raises(ValueError, match=r"feature 1 \(id 'L2'\): line L2: running must be"):
        Network.from_geojson(gj)
    gj["features"][1]["properties"] |= {"running": "both", "route": "R/2"}
    with pytest.raises(ValueError, match="route"):
        Network.from_geojson(gj)
