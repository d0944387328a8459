"""Map matching on a double-track route (services/ingestion/matching.py): GPS cannot tell
the two tracks of the imported OpenStreetMap fixture apart (8 m), their running direction
does. Trains on each track in each direction, a reversal, and what stays as it was."""

from __future__ import annotations

import json
from functools import cache
from pathlib import Path

import numpy as np
import pytest

from schemas import GpsFix, RawChunk
from services.ingestion.config import IngestionConfig
from services.ingestion.core import IngestionCore
from simulators.profile import LineProfile
from simulators.train import TrainSimulator
from tests.unit.test_ingestion_core import T0, chunk, positioned, rejections, train_on
from track.network import Network
from track.osm import import_osm

LAKESIDE = Path(__file__).parents[1] / "fixtures" / "osm" / "lakeside.geojson"


@cache
def lakeside(running: str | None = "left") -> Network:
    """The fixture imported with left-hand running (it is in Switzerland): 650-t2, north of
    650-t1, runs east (increasing chainage), 650-t1 west."""
    return import_osm(json.loads(LAKESIDE.read_text()), running=running)[0]


def test_the_fixture_tracks_are_closer_than_gps_can_tell_apart():
    network = lakeside()
    t1, t2 = network.lines["650-t1"], network.lines["650-t2"]
    _, lateral = t1.project(t2.xy_at(np.linspace(0.0, t2.length_m, 61)))
    assert (np.abs(lateral) < IngestionConfig().ambiguity_m).all()
    assert (t1.route, t2.route) == ("650", "650")
    assert (t1.running, t2.running) == ("decreasing", "increasing")


@pytest.mark.parametrize(
    ("track", "direction", "at_m"),
    [
        ("650-t2", 1, 400.0),  # eastbound on the eastbound track
        ("650-t1", -1, 5_600.0),  # westbound on the westbound track
    ],
)
def test_a_train_on_either_track_is_positioned_on_it_all_along(track, direction, at_m):
    network = lakeside()
    sim, events = train_on(track, 150, at_m=at_m, direction=direction, on=network)
    out = IngestionCore(network).run(events)
    chunks = positioned(out)
    assert {c.line for c in chunks} == {track}
    # only the first seconds, before the train has moved reverse_m, are not positioned
    refused = rejections(out)
    assert all(r.reason.startswith("unpositioned") for r in refused)
    assert len(refused) <= 3 and len(chunks) >= 147
    t = np.concatenate([c.knot_t.array() for c in chunks])
    chain = np.concatenate([c.knot_chainage_m.array() for c in chunks])
    truth = sim.position(t)[0]
    assert abs(truth[-1] - truth[0]) > 1_500  # it covers kilometres
    outside = ~sim.in_tunnel(truth)
    err = np.abs(chain - truth)[outside]
    assert np.median(err) < 3.0 and err.max() < 15.0


def test_the_track_is_chosen_by_direction_not_by_gps():
    """A train running east on the westbound track (wrong-line running) is put on the
    eastbound track: GPS cannot see the difference, the rule is the running direction."""
    network = lakeside()
    _, events = train_on("650-t1", 60, at_m=400.0, direction=1, on=network)
    assert {c.line for c in positioned(IngestionCore(network).run(events))} == {"650-t2"}


def test_a_reversal_at_the_terminus_moves_the_train_to_the_track_running_back():
    network = lakeside()
    line = network.lines["650-t2"]
    _, events = train_on("650-t2", 400, at_m=line.length_m - 1_500.0, direction=1, on=network)
    core = IngestionCore(network)
    chunks = positioned(core.run(events))
    lines = [c.line for c in chunks]
    assert lines[0] == "650-t2" and lines[-1] == "650-t1"
    first_back = lines.index("650-t1")
    assert set(lines[first_back:]) == {"650-t1"}  # and stays there
    assert core.train_stats("T1").switches == 1


def test_without_running_the_tracks_stay_unpositioned():
    network = lakeside(None)
    _, events = train_on("650-t2", 40, at_m=400.0, direction=1, on=network)
    out = IngestionCore(network).run(events)
    assert positioned(out) == []
    assert len(rejections(out)) == 40
    assert all(r.reason.startswith("unpositioned") for r in rejections(out))


def test_the_single_track_branch_is_positioned_from_the_first_fix():
    network = lakeside()
    _, events = train_on("651", 60, at_m=300.0, direction=1, on=network)
    out = IngestionCore(network).run(events)
    assert rejections(out) == []
    assert {c.line for c in positioned(out)} == {"651"}


def test_a_simulated_one_way_train_is_on_its_track_every_trip():
    """The simulator's train on the eastbound track sends nothing on its way back (that
    runs on the other track): after each silence map matching starts over at the west end
    and takes the eastbound track again, never the westbound one."""
    network = lakeside()
    line = network.lines["650-t2"]
    profile = LineProfile(line.id, [(s.start_m, s.end_m) for s in line.segments], 1)
    sim = TrainSimulator("T1", line, profile, 1, start_t=T0, phase_s=0.0)
    seconds = int(1.6 * sim.cycle_s)
    t = T0 + np.arange(seconds)
    sent = sim.in_service(t)
    assert (sim.position(t)[3][sent] == 1).all() and not sent.all()
    events: list[RawChunk | GpsFix] = []
    for k in np.flatnonzero(sent):
        events.append(chunk(int(k)))
        events += sim.gps_fixes(T0 + k, T0 + k + 1)
    # live, the receiving clock shows the silence is no clock jump; replayed without it,
    # the train's own clock would be doubted (max_ahead_s), which is not what is tested here
    cfg = IngestionConfig(max_ahead_s=1e9)
    out = IngestionCore(network, cfg).run(events)
    chunks = positioned(out)
    assert {c.line for c in chunks} == {"650-t2"}
    assert all(r.reason.startswith("unpositioned") for r in rejections(out))
    second_trip = [c for c in chunks if c.t0 > T0 + sim.cycle_s]
    assert len(second_trip) > 60  # positioned again after the silence
    chain = np.concatenate([c.knot_chainage_m.array() for c in second_trip])
    truth = sim.position(np.concatenate([c.knot_t.array() for c in second_trip]))[0]
    assert np.median(np.abs(chain - truth)) < 3.0


def test_the_piece_grid_finds_the_nearest_piece_within_its_reach():
    """Projecting on the pieces the grid lists near a point gives the whole-line answer for
    every point within ``reach_m`` of the line, and lists nothing far from it."""
    from services.ingestion.matching import _LineGeometry, _PieceGrid

    line = lakeside().lines["650-t1"]
    g = _LineGeometry.of(line)
    grid = _PieceGrid(g)
    rng = np.random.default_rng(5)
    chain = rng.uniform(0.0, line.length_m, 2_000)
    heading = line.heading_at(chain)
    normal = np.stack([-np.sin(heading), np.cos(heading)], -1)
    offset = rng.uniform(-grid.reach_m, grid.reach_m, 2_000)
    points = line.xy_at(chain) + offset[:, None] * normal
    for p in points:
        pieces = grid.near(p)
        assert pieces is not None
        assert np.allclose(g._project(p, pieces), g.project(p), atol=1e-9)
    assert grid.near(line.xy_at(np.array(1_000.0)) + np.array([0.0, 1_000.0])) is None
