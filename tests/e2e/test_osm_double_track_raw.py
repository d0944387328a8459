"""Raw-GPS trains on the two tracks of an imported double-track route, as real processes:
`trackfusion network import-osm --running left` → `trackfusion simulate --fidelity raw` →
`trackfusion ingestion` → `trackfusion extraction`. GPS cannot tell the tracks (8 m apart)
apart; their running direction does, so each train's on-board indices arrive on its own
track."""

from __future__ import annotations

import signal
from pathlib import Path

import numpy as np
from support import run_cli

from schemas import DAY_S, OnboardIndex, decode, keys
from services.defaults import load_network
from simulators.fleet import Fleet
from simulators.profile import LineProfile
from simulators.train import TrainSimulator
from simulators.truth import load_config

OSM = Path(__file__).parents[1] / "fixtures" / "osm" / "lakeside.geojson"
START = 1_767_225_600.0  # the simulator's default start, 2026-01-01T00:00:00Z
SECONDS = 240
SEED = 36  # both trains run their track's way at speed for two minutes of the four


def at_speed_s(network, train_id: str, line_id: str) -> int:
    """Seconds the simulator's train (built as simulators/world.py builds it) runs at speed
    in service and in the open: the scenario's precondition, not the result."""
    line = network.lines[line_id]
    profile = LineProfile(line.id, [(s.start_m, s.end_m) for s in line.segments], SEED)
    config = Fleet.from_config(load_config(), SEED).train_config(train_id)
    train = TrainSimulator(train_id, line, profile, SEED, start_t=START, config=config)
    t = START + np.arange(SECONDS)
    chainage, speed, _, _ = train.position(t)
    return int((train.in_service(t) & (speed > 10.0) & ~train.in_tunnel(chainage)).sum())


def test_raw_trains_on_double_track_give_indices_on_their_own_tracks(
    router, namespace, open_session, collector, signal_chain, spawn, tmp_path
):
    network_file = tmp_path / "network.geojson"
    imported = run_cli(
        "network", "import-osm", str(OSM), "--running", "left", "--out", str(network_file)
    )
    assert imported.returncode == 0, imported.stderr
    assert "tells them apart by their running direction" in imported.stdout
    network = load_network(str(network_file))
    # the simulator puts train i on line i: T000 on the westbound track, T001 eastbound
    assert list(network.lines)[:2] == ["650-t1", "650-t2"]
    assert [network.lines[i].running for i in ("650-t1", "650-t2")] == ["decreasing", "increasing"]
    assert at_speed_s(network, "T000", "650-t1") > 100
    assert at_speed_s(network, "T001", "650-t2") > 100

    session = open_session()
    indices = collector(lambda s: decode(s.payload.to_bytes(), OnboardIndex))
    session.declare_subscriber(keys.segment_keys(namespace, "index"), indices)
    wiring = ["--connect", router, "--ns", namespace, "--network", str(network_file)]
    ingestion, extraction = signal_chain(session, wiring)
    world = ["--fidelity", "raw", "--trains", "2", "--days", str(SECONDS / DAY_S)]
    simulate = spawn(
        "simulate", "simulate", *world, "--speedup", "60", "--seed", str(SEED), *wiring
    )
    assert simulate.wait(120) == 0, simulate.log()

    tracks = {"T000": "650-t1", "T001": "650-t2"}
    got: dict[str, set[str]] = {"T000": set(), "T001": set()}
    while not all(len(segments) >= 2 for segments in got.values()):
        try:
            index = indices.get(timeout=30)
        except AssertionError:
            for process in (ingestion, extraction):
                process.signal(signal.SIGTERM)  # they log their counters on the way out
                process.wait(10)
            raise AssertionError(
                f"indices so far {got}\n{ingestion.log()[-2000:]}{extraction.log()[-2000:]}"
            ) from None
        assert index.line == tracks[index.train], index  # never the other track
        assert (index.line, index.segment) in {(line.id, s.id) for line, s in network.segments()}
        got[index.train].add(index.segment)
