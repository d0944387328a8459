"""Real inputs end to end: an OpenStreetMap extract whose ways have no name nor ref
(`network import-osm`), `trackfusion up --network` with the simulated fleet on it, then two
runs of a car that records longitudinal level only (`import-trc --profile`), 34 days apart,
the second aligned to the first; `trackfusion state` and `trackfusion report` say which
indicators the last record measured and call the line by its name."""

from __future__ import annotations

import signal
from pathlib import Path

from support import run_cli

from bench import walkthrough_pictures
from bench.walkthrough_pictures import level_only_export
from schemas import SegmentState, decode, keys
from services.tools.operator import parse_time
from tests.e2e.stacks import estimation_on

OSM = Path(__file__).parents[1] / "fixtures" / "osm" / "riviera.json"
LINE = walkthrough_pictures.LINE  # track 1 of the coast line: no name, no ref on its ways
NAME = "Alassio – Albenga, track 1"  # its first and last stations, and the track
RUNS = (("r1", "2026-01-22T09:00:00Z", 0.0), ("r2", "2026-02-25T09:00:00Z", 4.0))
COVERED = [f"s{k:05d}" for k in range(1, 15)]  # what 100-3100 m covers of 16 segments
START_S = 60.0  # upper bound for a process to start or a state to arrive on two loaded cores


def test_a_level_only_car_on_an_imported_network(up, namespace, collector, tmp_path):
    network_file = tmp_path / "network.geojson"
    imported = run_cli("network", "import-osm", str(OSM), "--out", str(network_file))
    assert imported.returncode == 0, imported.stderr
    assert f"{LINE:<20} {NAME}" in imported.stdout

    state_dir = tmp_path / "var"
    stack = up(
        [
            *estimation_on("{network}", state_dir),
            {"name": "simulator", "command": "simulate",
             "args": ["--fidelity", "index", "--days", "20", "--trains", "2",
                      "--start", "2026-01-01", "--speedup", "200000", "--no-progress",
                      "--instance", "simulator", "--network", "{network}"]},
        ],
        "--network",
        str(network_file),
    )  # fmt: skip
    wiring = ("--connect", stack.endpoint, "--ns", namespace)
    with stack.client() as s:  # waits for the router of `up`
        states = collector(lambda sample: decode(sample.payload.to_bytes(), SegmentState))
        s.declare_subscriber(keys.segment_keys(namespace, "state"), states)
        started: set[str] = set()  # the simulated TRC runs started every segment
        while not set(COVERED) <= started:
            state = states.get(timeout=START_S)
            if state.line == LINE:
                started.add(state.segment)
        archive = ("--archive", str(tmp_path / "profiles.sqlite"))
        reports = []
        for k, (run_id, t, offset_m) in enumerate(RUNS):
            export = tmp_path / f"{run_id}.csv"
            export.write_text(level_only_export(network_file, offset_m, seed=k))
            result = run_cli(
                "import-trc", "--profile", str(export), "--line", LINE, "--run-id", run_id,
                "--t", t, "--network", str(network_file), *archive, *wiring, timeout=120,
            )  # fmt: skip
            assert result.returncode == 0, result.stderr
            reports.append(result.stdout)
        assert "top6: the smaller of level_left_mm and level_right_mm" in reports[0]
        assert "align10: not measured, the file has no alignment column" in reports[0]
        assert "no earlier run of this stretch" in reports[0]
        assert "alignment to run r1" in reports[1] and f"{len(COVERED)} with a record" in reports[1]
        assert reports[0].startswith(f"run r1 on line {LINE} ({NAME}): ")
        used = [row.split() for row in reports[1].splitlines() if row.endswith("  used")]
        assert used and all(abs(float(row[1]) - 4.0) < 0.1 for row in used), reports[1]

        t2 = parse_time(RUNS[1][1])
        restarted: set[str] = set()  # every covered segment restarted on Top6 by r2
        while restarted != set(COVERED):
            state = states.get(timeout=START_S)
            if state.line == LINE and state.last_trc_t == t2:
                assert state.last_trc_indicators == ["top6"], state
                restarted.add(state.segment)

        shown = run_cli("state", f"{LINE}/s00005", "--network", str(network_file), *wiring)
        assert shown.returncode == 0, shown.stderr
        assert f"{LINE}/s00005 ({NAME})" in shown.stdout
        assert "measured top6)" in shown.stdout
        out = tmp_path / "report.html"
        report = run_cli("report", "--line", LINE, "--out", str(out),
                         "--network", str(network_file), *wiring)  # fmt: skip
        assert report.returncode == 0, report.stderr
        html = out.read_text()
        assert f"{LINE} ({NAME})" in html and "top6 only" in html

    stack.process.signal(signal.SIGINT)
    assert stack.process.wait(20) == 0, stack.process.log()
