"""`trackfusion up` with a small stack file, and every operator command against it; Ctrl-C
(SIGINT) stops the whole stack with exit code 0."""

from __future__ import annotations

import csv
import io
import json
import signal

from support import run_cli

from schemas import keys


def test_up_runs_the_stack_and_answers_every_command(
    up, namespace, collector, liveliness_events, tmp_path
):
    state_dir = tmp_path / "var"
    stack = up(
        [
            {
                "name": "calibration",
                "args": [
                    "--db", str(state_dir / "cal.sqlite"), "--instance", "calibration",
                    "--initial-models", "{defaults}/initial-models.json5",
                ],
            },
            {"name": "filtering", "args": ["--db", str(state_dir / "f.sqlite")]},
            {"name": "alerting", "args": ["--db", str(state_dir / "a.sqlite")]},
            {
                "name": "simulator",
                "command": "simulate",
                "args": ["--fidelity", "index", "--days", "30", "--trains", "1",
                         "--speedup", "200000", "--no-progress"],
            },
        ],
    )  # fmt: skip
    with stack.client() as s:  # waits for the router of `up`
        alive = liveliness_events(s, keys.alive_all(namespace))
        services = set()
        while not {"calibration", "filtering", "alerting"} <= services:
            kind, key = alive.get(timeout=60)
            services.add(keys.parse_alive(key)[0])
        states = collector()
        s.declare_subscriber(keys.segment_keys(namespace, "state"), states)
        first = states.get(timeout=60)  # a TRC run and the initial models make states
        _, _, line, segment = keys.parse_segment_key(str(first.key_expr))

        # The simulator outruns filtering on purpose: a query waits behind the queued events
        # (under load, more than the default 10 s), so the commands get a longer bound.
        wiring = ("--connect", stack.endpoint, "--ns", namespace, "--timeout", "60")
        status = run_cli("status", *wiring)
        assert status.returncode == 0 and "filtering" in status.stdout, status.stderr
        state = run_cli("state", f"{line}/{segment}", *wiring)
        assert state.returncode == 0 and f"{line}/{segment}" in state.stdout, state.stderr
        assert "95% [" in state.stdout and "in  180 d" in state.stdout
        assert run_cli("state", "nonsense", *wiring).returncode != 0
        alerts = run_cli("alerts", *wiring)
        assert alerts.returncode == 0, alerts.stderr
        plan = run_cli("plan", "--limit", "3", *wiring)
        assert plan.returncode == 0 and "rank" in plan.stdout, plan.stderr
        exported = run_cli("export", "states", "--format", "csv", *wiring)
        rows = list(csv.DictReader(io.StringIO(exported.stdout)))
        assert exported.returncode == 0 and rows and float(rows[0]["top6_mm"]) > 0
        geo = run_cli("export", "states", "--format", "geojson", *wiring)
        features = json.loads(geo.stdout)["features"]
        assert features and features[0]["geometry"]["type"] == "LineString"
        geo_alerts = run_cli("export", "alerts", "--format", "geojson", *wiring)
        assert json.loads(geo_alerts.stdout)["type"] == "FeatureCollection"

    stack.process.signal(signal.SIGINT)
    assert stack.process.wait(20) == 0, stack.process.log()
    assert "stack stopped" in stack.process.log_path.read_text()
    for name in ("calibration", "filtering", "alerting", "simulator"):
        assert (state_dir / f"{name}.log").exists()
    health = json.loads((state_dir / "health.json").read_text())  # the last one, on stopping
    assert not health["up"]["running"]
    assert set(health["processes"]) == {"calibration", "filtering", "alerting", "simulator"}
    assert all(p["restarts"] == 0 for p in health["processes"].values()), health
