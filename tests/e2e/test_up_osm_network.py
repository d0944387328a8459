"""An OpenStreetMap extract to a running system: `trackfusion network import-osm` writes the
network file, `trackfusion up --network FILE` runs a stack on it, and the segment states of
the imported lines (both tracks of the double-track route and the branch) arrive."""

from __future__ import annotations

import json
import signal
from pathlib import Path

from support import run_cli

from schemas import SegmentState, decode, keys
from services.defaults import load_network
from tests.e2e.stacks import estimation_on

OSM = Path(__file__).parents[1] / "fixtures" / "osm" / "lakeside.geojson"
START_S = 60.0  # upper bound for a process to start or a first state on two loaded cores


def test_up_runs_the_stack_on_an_imported_network(
    up, namespace, collector, liveliness_events, tmp_path
):
    network_file = tmp_path / "network.geojson"
    imported = run_cli("network", "import-osm", str(OSM), "--out", str(network_file))
    assert imported.returncode == 0, imported.stderr
    assert "made 3 lines" in imported.stdout
    network = load_network(str(network_file))
    assert any(line.tunnels for line in network.lines.values())
    assert all(line.stations for line in network.lines.values())

    state_dir = tmp_path / "var"
    stack = up(
        [
            *estimation_on("{network}", state_dir),
            {"name": "ingestion", "args": ["--instance", "ingestion", "--network", "{network}"]},
            {"name": "extraction", "args": ["--instance", "extraction", "--network", "{network}"]},
            {"name": "simulator", "command": "simulate",
             "args": ["--fidelity", "index", "--days", "20", "--trains", "2",
                      "--speedup", "200000", "--no-progress", "--instance", "simulator",
                      "--network", "{network}"]},
        ],
        "--network",
        str(network_file),
    )  # fmt: skip
    with stack.client() as s:  # waits for the router of `up`
        alive = liveliness_events(s, keys.alive_all(namespace))
        services: set[str] = set()
        while not {"calibration", "filtering", "ingestion", "extraction"} <= services:
            _, key = alive.get(timeout=START_S)
            services.add(keys.parse_alive(key)[0])
        states = collector(lambda sample: decode(sample.payload.to_bytes(), SegmentState))
        s.declare_subscriber(keys.segment_keys(namespace, "state"), states)
        seen: dict[str, set[str]] = {line: set() for line in network.lines}
        while not all(seen.values()):
            state = states.get(timeout=START_S)
            assert state.line in network.lines, state.line  # nothing of the demo network
            seen[state.line].add(state.segment)
        known = {(line.id, seg.id) for line, seg in network.segments()}
        assert {(line, seg) for line, segs in seen.items() for seg in segs} <= known

    stack.process.signal(signal.SIGINT)
    assert stack.process.wait(20) == 0, stack.process.log()
    health = json.loads((state_dir / "health.json").read_text())
    assert all(p["restarts"] == 0 for p in health["processes"].values()), health
    # extraction found the imported segment bounds, not the demo network's
    extraction_log = (state_dir / "extraction.log").read_text()
    assert f"{len(network.lines)} lines, {network.n_segments} segments" in extraction_log
