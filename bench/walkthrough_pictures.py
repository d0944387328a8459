"""The pictures of the real-network walk-through in docs/operating.md, made by running it.

``python -m bench.walkthrough_pictures [--out docs/img]`` (``make pictures``):

1. ``trackfusion network import-osm`` of ``tests/fixtures/osm/riviera.json`` (the extract
   ``tests/e2e/test_real_exports.py`` uses: ways without name nor ref);
2. ``trackfusion up --network`` with calibration, filtering, alerting, the planner, the
   viewer (web) and the simulated fleet in fast mode for 20 days;
3. two runs of a level-only recording car on track 1 (``import-trc --profile``), 34 days
   apart, the second aligned to the first;
4. once every segment of the run was restarted by the second run and the planner has a
   plan of that time: ``trackfusion report`` of track 1 and of the network, and the web
   viewer with track 1's segment ``s00005`` selected, screenshot by headless Chromium.

Writes ``walkthrough-report.png`` (the top of track 1's report: its name, its map, the
"top6 only" of the last TRC column), ``walkthrough-plan.png`` (the network's report's
tamping plan) and ``walkthrough-viewer.png``, each reduced to 256 colours to stay small.
About 3-5 minutes on two cores; the stack's logs stay in ``--workdir`` (a temporary
directory by default).
"""

from __future__ import annotations

import argparse
import io
import json
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import zenoh

from bench.demo_soak import REPO, free_port
from schemas import MaintenancePlan, SegmentState, decode, keys
from services.defaults import load_network
from services.runtime.config import users_env, zenoh_config
from services.tools.operator import parse_time
from services.viewer.service import web_viewer_url
from simulators.profile import LineProfile
from tests.browser import DevTools, first_picture

OSM = REPO / "tests" / "fixtures" / "osm" / "riviera.json"
LINE = "way1024952344-t1"  # track 1 of the coast line: no name, no ref on its ways
SELECTED = "s00005"  # the segment the viewer's selected row plots
RUNS = (("r1", "2026-01-22T09:00:00Z", 0.0), ("r2", "2026-02-25T09:00:00Z", 4.0))
RUN_M = (100.0, 3100.0)  # true chainage the car records
NS = "walk"
WAIT_S = 300.0  # upper bound for each step of the stack on two loaded cores
SIZE = (1400, 900)  # browser window, px


def cli(*args: str, timeout: float = 120.0) -> str:
    """Run ``trackfusion ARGS`` and return its stdout; SystemExit with its stderr on failure."""
    done = subprocess.run(
        [sys.executable, "-m", "services.cli", *args],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=timeout,
        env=users_env(),
        check=False,
    )
    if done.returncode != 0:
        raise SystemExit(f"trackfusion {' '.join(args)}: exit {done.returncode}\n{done.stderr}")
    return done.stdout


def level_only_export(network_file: Path, offset_m: float, seed: int) -> str:
    """A run of :data:`LINE` over :data:`RUN_M` recorded ``offset_m`` short, with the level of
    both rails and no alignment column, as a level-only car exports it."""
    line = load_network(str(network_file)).lines[LINE]
    bounds = np.stack([line.segment_starts_m, line.segment_ends_m], -1)
    track = LineProfile(LINE, bounds, seed=3)
    n = len(bounds)
    z = np.stack([np.random.default_rng(3).normal(np.log(1.6), 0.4, n), np.zeros(n)], -1)
    track.update(z, np.zeros(n, dtype=np.int64))
    rng = np.random.default_rng(seed)
    true_m = np.arange(*RUN_M, 0.25)
    level = track.sample(true_m)[:2] + rng.normal(0.0, 0.15, (2, true_m.size))
    rows = np.stack([true_m - offset_m, *level], -1)
    lines = ["# level-only export", "chainage_m,level_left_mm,level_right_mm"]
    lines += [f"{x:.3f},{a:.2f},{b:.2f}" for x, a, b in rows]
    return "\n".join(lines) + "\n"


def stack_file(work: Path, endpoint: str, web_port: int, grpc_port: int) -> Path:
    state = work / "var"

    def service(name: str, *args: str) -> dict:
        return {"name": name, "command": name, "args": ["--instance", name, *args]}

    processes = [
        service("calibration", "--db", str(state / "cal.sqlite"), "--initial-models",
                "{defaults}/initial-models.json5", "--network", "{network}"),
        service("filtering", "--db", str(state / "f.sqlite"), "--network", "{network}"),
        service("alerting", "--db", str(state / "a.sqlite")),
        service("planning", "--db", str(state / "p.sqlite"), "--network", "{network}"),
        service("viewer", "--network", "{network}", "--web", "--web-port", str(web_port),
                "--grpc-port", str(grpc_port)),
        {"name": "simulator", "command": "simulate", "restart": "on-failure",
         "args": ["--fidelity", "index", "--days", "20", "--trains", "2", "--start",
                  "2026-01-01", "--speedup", "200000", "--no-progress", "--instance",
                  "simulator", "--network", "{network}"]},
    ]  # fmt: skip
    stack = {
        "ns": NS,
        "router": {"listen": endpoint},
        "state_dir": str(state),
        "processes": processes,
    }
    path = work / "stack.json"
    path.write_text(json.dumps(stack, indent=1))
    return path


def states_until(done, what: str) -> None:
    """Wait until ``done()`` holds over the states received so far (polled: they arrive on
    Zenoh's thread)."""
    deadline = time.monotonic() + WAIT_S
    while not done():
        if time.monotonic() > deadline:
            raise SystemExit(f"walk-through: {what} not within {WAIT_S:g} s")
        time.sleep(0.5)


def newest_plan(session: zenoh.Session, since_t: float) -> MaintenancePlan:
    """The planner's plan once it was made from the states up to ``since_t`` or later."""
    deadline = time.monotonic() + WAIT_S
    while time.monotonic() < deadline:
        for reply in session.get(keys.q_maintenance_plan(NS), timeout=10.0):
            if reply.ok is not None:
                plan = decode(reply.ok.payload.to_bytes(), MaintenancePlan)
                if plan.computed_at is not None and plan.computed_at >= since_t:
                    return plan
        time.sleep(2.0)
    raise SystemExit(
        f"walk-through: no plan made from the states of the second run in {WAIT_S:g} s"
    )


def small_png(png: bytes, path: Path) -> None:
    """Save ``png`` with 256 colours (the pictures are flat colours and text)."""
    from PIL import Image

    image = Image.open(io.BytesIO(png)).convert("RGB")
    image.quantize(colors=256, method=Image.Quantize.MEDIANCUT).save(path, optimize=True)
    print(f"wrote {path} ({path.stat().st_size // 1024} kB)")


def report_pictures(line_report: Path, report: Path, work: Path, out: Path) -> None:
    """The top of the line's report, and the tamping plan section of the network's, in a
    browser window of :data:`SIZE`."""

    def load(browser: DevTools, path: Path) -> None:
        browser.open(path.as_uri())
        deadline = time.monotonic() + 60.0
        while browser.evaluate("document.readyState") != "complete":
            if time.monotonic() > deadline:
                raise SystemExit(f"walk-through: {path} did not load in Chromium")
            time.sleep(0.2)

    for path, picture, scroll_to in (
        (line_report, "walkthrough-report.png", None),
        (report, "walkthrough-plan.png", "tamping"),
    ):
        profile = work / f"profile-{path.stem}"
        with DevTools(profile, work / f"chromium-{path.stem}.log", size=SIZE) as browser:
            load(browser, path)
            if scroll_to is not None:
                browser.evaluate(f"document.getElementById('{scroll_to}').scrollIntoView()")
            small_png(browser.screenshot(), out / picture)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=REPO / "docs" / "img")
    parser.add_argument("--workdir", type=Path, help="stack state and logs (default: a temp dir)")
    args = parser.parse_args(argv)
    work = (args.workdir or Path(tempfile.mkdtemp(prefix="walkthrough-"))).resolve()
    work.mkdir(parents=True, exist_ok=True)
    out = args.out.resolve()
    out.mkdir(parents=True, exist_ok=True)
    network = work / "network.geojson"
    print(cli("network", "import-osm", str(OSM), "--running", "left", "--out", str(network)))

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    web_port, grpc_port = free_port(), free_port()
    stack = stack_file(work, endpoint, web_port, grpc_port)
    with (work / "up.log").open("wb") as log:
        up = subprocess.Popen(
            [sys.executable, "-m", "services.cli", "up", "--stack", str(stack),
             "--network", str(network)],
            cwd=REPO, stdout=log, stderr=subprocess.STDOUT, start_new_session=True,
            env=users_env(),
        )  # fmt: skip
    wiring = ("--connect", endpoint, "--ns", NS)
    try:
        conf = zenoh_config({"mode": "client", "connect": {"endpoints": [endpoint]}})
        deadline = time.monotonic() + 60.0
        while True:
            try:
                session = zenoh.open(conf)
                break
            except zenoh.ZError:
                if time.monotonic() > deadline or up.poll() is not None:
                    raise SystemExit(f"walk-through: no router; see {work / 'up.log'}") from None
                time.sleep(0.5)
        with session:
            states: list[SegmentState] = []
            session.declare_subscriber(
                keys.segment_keys(NS, "state"),
                lambda sample: states.append(decode(sample.payload.to_bytes(), SegmentState)),
            )
            line = load_network(str(network)).lines[LINE]
            # the segments both runs cover whole (import-trc skips the others)
            covered = {s.id for s in line.segments if RUN_M[0] <= s.start_m and s.end_m <= RUN_M[1]}
            states_until(
                lambda: covered <= {s.segment for s in states if s.line == LINE},
                "a state of every segment of the run from the simulated TRC runs",
            )
            archive = ("--archive", str(work / "profiles.sqlite"))
            for k, (run_id, t, offset_m) in enumerate(RUNS):
                export = work / f"{run_id}.csv"
                export.write_text(level_only_export(network, offset_m, seed=k))
                print(
                    cli("import-trc", "--profile", str(export), "--line", LINE, "--run-id",
                        run_id, "--t", t, "--network", str(network), *archive, *wiring)
                )  # fmt: skip
            t2 = parse_time(RUNS[1][1])
            states_until(
                lambda: (
                    covered <= {s.segment for s in states if s.line == LINE and s.last_trc_t == t2}
                ),
                "the second run's restart of every segment it covered",
            )
            plan = newest_plan(session, t2)
            print(f"plan: {sum(r.week >= 0 for r in plan.rows)} tampings, {plan.status}")
            print(cli("state", f"{LINE}/{SELECTED}", "--network", str(network), *wiring))
            line_report, report = work / "report-line.html", work / "report.html"
            print(cli("report", "--line", LINE, "--out", str(line_report), "--network",
                      str(network), *wiring))  # fmt: skip
            print(cli("report", "--out", str(report), "--network", str(network), *wiring))
            report_pictures(line_report, report, work, out)
            print(cli("viewer", "select", f"{LINE}/{SELECTED}", *wiring))
            url = web_viewer_url(f"rerun+http://127.0.0.1:{grpc_port}/proxy", web_port)
            picture = first_picture(url, work / "browser", wanted=("green", "blue"))
            if picture.missing:
                raise SystemExit(f"walk-through: the viewer drew no {picture.missing} in time")
            small_png(picture.png, out / "walkthrough-viewer.png")
    finally:
        up.send_signal(signal.SIGINT)
        try:
            up.wait(30.0)
        except subprocess.TimeoutExpired:
            up.kill()
            up.wait()
    print(f"stack logs: {work}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
