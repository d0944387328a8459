"""`make soak`: what `make run` starts, left running, watched like an operator would.

Runs ``trackfusion up`` on a copy of ``services/defaults/stack.json5`` — the same processes and
flags (fast-mode world at 15,000×, four raw trains, the web viewer), moved to a free router port,
its own namespace, state directory and viewer ports so that it can run beside another
stack — for ``--minutes`` (30 by default), and watches it from outside:

- **alive**: ``up``'s ``health.json`` every 5 s: every process running and holding its
  liveliness token, and how often ``up`` restarted one;
- **state keeps flowing**: a client of the router counts ``index/**`` and ``state/**``; the
  longest time without any state while indices kept arriving (the "went deaf" symptom);
- **answers**: every minute ``q/state/**`` is asked (as ``trackfusion export states``
  does): how many segments answered, and how long the answer took;
- **memory**: VmRSS of every process every ``--sample-s``; growth from the first sample
  after ``--warmup-minutes`` to the last;
- **the viewer in a browser** (where Debian's chromium is installed): at each ``--open``
  minute a fresh headless Chromium opens the web viewer and the time to the coloured map is
  taken (:func:`tests.browser.first_picture`);
- **wrong input**: at minute ``--hostile`` (half the run by default) the bad messages of
  :mod:`bench.hostile` are put on the stack's bus; each must get a dead letter with its
  reason on ``{ns}/deadletter/**`` within a minute, and no process may stop.

The run passes when every process stayed alive (no restart), no state gap while indices
flowed exceeded 30 s, every q/state answer covered the segments tracked, the viewer stayed
within 500 MB, no process grew by more than 20 % over the second half of the run (memory
bounded once the demo's caches and TRC cycles have filled), and each browser drew the map
within 15 s, and every bad message got its dead letter. A summary table is printed, and
``--json FILE`` writes it; the exit code is 1 when a check failed.

    python -m bench.demo_soak --minutes 30 --open 2,10,20,29 --hostile 15
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
import uuid
from datetime import datetime
from pathlib import Path

import zenoh

from bench.hostile import DeadLetters, Hostile, answered, hostile_messages, unanswered
from schemas import DAY_S, keys
from services.defaults import default_file
from services.runtime.config import users_env, zenoh_config
from simulators.run import DEFAULT_START

REPO = Path(__file__).resolve().parents[1]
STATE_GAP_LIMIT_S = 30.0
VIEWER_RSS_LIMIT_MB = 500.0
GROWTH_LIMIT = 0.2
FIRST_PICTURE_LIMIT_S = 15.0
HOSTILE_LINE = "L1"  # a line of the demo network
HOSTILE_T = datetime.fromisoformat(DEFAULT_START).timestamp() + 30 * DAY_S  # in the demo's year


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def start_up(stack: Path, out: Path) -> subprocess.Popen:
    """`trackfusion up --stack stack` in its own process group, its output in
    ``out/up.log``."""
    with (out / "up.log").open("wb") as log:
        return subprocess.Popen(
            [sys.executable, "-m", "services.cli", "up", "--stack", str(stack)],
            cwd=REPO,
            stdout=log,
            stderr=subprocess.STDOUT,
            start_new_session=True,
            env=users_env(),  # not this bench process's reserved rx threads
        )


def stack_copy(
    out: Path, *, endpoint: str, ns: str, web_port: int, grpc_port: int, viewer_args: str = ""
) -> Path:
    """``services/defaults/stack.json5`` with its endpoint, namespace, state files and viewer moved
    (and ``viewer_args`` added to the viewer's arguments)."""
    text = default_file("stack.json5").read_text()
    text = text.replace('"var/', f'"{out}/').replace('state_dir: "var"', f'state_dir: "{out}"')
    text = re.sub(r'ns: "\w+"', f'ns: "{ns}"', text, count=1)
    text = re.sub(r"tcp/127\.0\.0\.1:\d+", endpoint, text, count=1)
    viewer = re.search(r'\{ name: "viewer".*?args: \[(.*?)\]', text, flags=re.S)
    if viewer is None:
        raise SystemExit(
            "services/defaults/stack.json5: no viewer entry; update bench/demo_soak.py"
        )
    args = viewer.group(1) + f', "--web", "--web-port", "{web_port}", "--grpc-port", "{grpc_port}"'
    args += "".join(f', "{arg}"' for arg in viewer_args.split())
    text = text[: viewer.start(1)] + args + text[viewer.end(1) :]
    path = out / "stack.json5"
    path.write_text(text)
    return path


def rss_mb(pid: int) -> float | None:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    except OSError:
        return None
    return None


class Flows:
    """Index and state arrivals (wall clock), and the longest state silence while indices
    kept coming; fed by Zenoh callbacks (a lock, counters, nothing else)."""

    def __init__(self) -> None:
        self.started = time.monotonic()
        self.lock = threading.Lock()
        self.index = self.state = 0
        self.last_state = self.last_index = None
        self.longest_gap_s = 0.0  # no state while indices arrived
        self.gaps: list[tuple[float, float]] = []  # (start, length) of gaps > 5 s

    def on_index(self, _sample: zenoh.Sample) -> None:
        now = time.monotonic()
        with self.lock:
            self.index += 1
            self.last_index = now
            if self.last_state is not None:
                self.longest_gap_s = max(self.longest_gap_s, now - self.last_state)

    def on_state(self, _sample: zenoh.Sample) -> None:
        now = time.monotonic()
        with self.lock:
            if self.last_state is not None and now - self.last_state > 5.0:
                self.gaps.append((self.last_state - self.started, now - self.last_state))
            self.state += 1
            self.last_state = now


def run(args: argparse.Namespace) -> dict:
    out = Path(args.out or tempfile.mkdtemp(prefix="demo-soak-"))
    out.mkdir(parents=True, exist_ok=True)
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    ns = f"soak{uuid.uuid4().hex[:8]}"
    stack = stack_copy(out, endpoint=endpoint, ns=ns, web_port=free_port(), grpc_port=free_port())
    up = start_up(stack, out)
    print(f"demo soak: {args.minutes:g} min, ns {ns}, router {endpoint}, files in {out}")
    flows = Flows()
    health_path = out / "health.json"
    samples: list[dict] = []
    answers: list[dict] = []
    pictures: list[dict] = []
    letters = DeadLetters()
    hostile: list[Hostile] = []
    hostile_at = args.minutes / 2 if args.hostile is None else args.hostile
    not_alive: dict[str, float] = {}  # process -> seconds seen not alive (after start-up)
    restarts: dict[str, int] = {}
    opens = sorted(float(m) for m in args.open.split(",") if m) if args.open else []
    browser = shutil.which("chromium") is not None
    started = time.monotonic()
    end = started + args.minutes * 60
    try:
        conf = zenoh_config({"mode": "client", "connect": {"endpoints": [endpoint]}})
        deadline = time.monotonic() + 60
        while True:
            try:
                session = zenoh.open(conf)
                break
            except zenoh.ZError:
                if time.monotonic() > deadline:
                    raise SystemExit(
                        f"no router at {endpoint} after 60 s; see {out}/up.log"
                    ) from None
                time.sleep(0.5)  # the router is starting: retry, no result to wait for
        with session:
            subs = [
                session.declare_subscriber(keys.segment_keys(ns, "index"), flows.on_index),
                session.declare_subscriber(keys.segment_keys(ns, "state"), flows.on_state),
                session.declare_subscriber(keys.deadletter_all(ns), letters.on_sample),
            ]
            next_sample = next_query = time.monotonic() + 30
            while (now := time.monotonic()) < end and up.poll() is None:
                minute = (now - started) / 60
                health = read_json(health_path)
                if health and minute > 1.0:  # after start-up
                    for name, proc in health.get("processes", {}).items():
                        restarts[name] = proc.get("restarts", 0)
                        if not proc.get("alive") and proc.get("state") != "finished":
                            not_alive[name] = not_alive.get(name, 0.0) + 5.0
                if now >= next_sample and health:
                    next_sample = now + args.sample_s
                    rss = {
                        name: rss_mb(p["pid"])
                        for name, p in health.get("processes", {}).items()
                        if p.get("pid")
                    }
                    samples.append({"minute": round(minute, 2), "rss_mb": rss})
                    print(
                        f"{minute:5.1f} min  "
                        + "  ".join(f"{k} {v:.0f}" for k, v in rss.items() if v is not None)
                        + f"  MB; index {flows.index} state {flows.state}",
                        flush=True,
                    )
                if now >= next_query:
                    next_query = now + 60
                    answers.append(ask_states(session, ns, minute, health))
                if not hostile and hostile_at >= 0 and minute >= hostile_at:
                    hostile = hostile_messages(ns, HOSTILE_LINE, HOSTILE_T)
                    for message in hostile:
                        session.put(message.key, message.payload)
                    print(f"{minute:5.1f} min  put {len(hostile)} bad messages", flush=True)
                if opens and browser and minute >= opens[0]:
                    opens.pop(0)
                    pictures.append(open_viewer(health, out, minute))
                time.sleep(5.0)  # the watch period: a sampling clock, not a wait for a result
            for sub in subs:
                sub.undeclare()
    finally:
        if up.poll() is None:
            os.killpg(up.pid, signal.SIGINT)
            try:
                up.wait(30)
            except subprocess.TimeoutExpired:
                os.killpg(up.pid, signal.SIGKILL)
                up.wait()
    wrong_input = {
        "put": [m.what for m in hostile],
        "unanswered": unanswered(hostile, letters.snapshot()),
        "dead_letters": [
            f"{d.service}: {d.key}: {d.reason[:160]}"
            for m in hostile
            for d in answered(m, letters.snapshot())
        ],
    }
    return summarize(
        args, out, flows, samples, answers, pictures, not_alive, restarts, up, wrong_input
    )


def read_json(path: Path) -> dict | None:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


def ask_states(session: zenoh.Session, ns: str, minute: float, health: dict | None) -> dict:
    t0 = time.monotonic()
    replies = session.get(
        keys.q_state_all(ns), timeout=20, congestion_control=zenoh.CongestionControl.BLOCK
    )
    n = sum(1 for r in replies if r.ok is not None)
    tracked = (health or {}).get("segments", 0)
    return {"minute": round(minute, 2), "answered": n, "tracked": tracked,
            "seconds": round(time.monotonic() - t0, 2)}  # fmt: skip


def open_viewer(health: dict | None, out: Path, minute: float) -> dict:
    from tests.browser import first_picture

    url = (health or {}).get("viewer_url", "")
    if not url:
        return {"minute": round(minute, 2), "error": "no viewer URL in health.json"}
    workdir = out / f"browser-{minute:.0f}"
    picture = first_picture(url, workdir, wanted=("green", "blue", "limit"), timeout_s=120)
    for at, png in picture.shots[::10]:  # what the operator saw, every 5 s
        (workdir / f"shot-{at:05.1f}s.png").write_bytes(png)
    if picture.png:
        (workdir / "last.png").write_bytes(picture.png)
    return {"minute": round(minute, 2), "started_s": picture.started_s,
            "map_s": picture.seen_s.get("green"), "plots_s": picture.drawn_s,
            "hues_s": {hue: round(s, 1) for hue, s in picture.seen_s.items()},
            "missing": picture.missing}  # fmt: skip


def summarize(
    args, out, flows, samples, answers, pictures, not_alive, restarts, up, wrong_input
) -> dict:
    # bounded: what a process still grows over the second half of the run (after the
    # warm-up), when the demo's caches and TRC cycles have filled
    warm = [s for s in samples if s["minute"] >= max(args.warmup_minutes, args.minutes / 2)]
    growth, peak = {}, {}
    if warm:
        for name in warm[-1]["rss_mb"]:
            first, last = warm[0]["rss_mb"].get(name), warm[-1]["rss_mb"].get(name)
            if first and last:
                growth[name] = last / first - 1
            values = [s["rss_mb"].get(name) for s in samples if s["rss_mb"].get(name)]
            peak[name] = max(values) if values else None
    checks = {
        "every process alive, none restarted": not not_alive and not any(restarts.values()),
        f"no state gap over {STATE_GAP_LIMIT_S:.0f} s while indices flowed": (
            flows.longest_gap_s <= STATE_GAP_LIMIT_S and flows.state > 0
        ),
        "q/state answered for every tracked segment": any(a["tracked"] for a in answers)
        and all(a["answered"] >= a["tracked"] for a in answers),
        f"viewer ≤ {VIEWER_RSS_LIMIT_MB:.0f} MB": (peak.get("viewer") or 0) <= VIEWER_RSS_LIMIT_MB,
        f"no process grew over {GROWTH_LIMIT:.0%} in the second half": all(
            g <= GROWTH_LIMIT for g in growth.values()
        ),
    }
    if wrong_input["put"]:
        checks["every bad message got a dead letter"] = not wrong_input["unanswered"]
    if pictures:
        checks[f"coloured map within {FIRST_PICTURE_LIMIT_S:.0f} s"] = all(
            p.get("map_s") is not None and p["map_s"] <= FIRST_PICTURE_LIMIT_S for p in pictures
        )
        checks[f"plots with estimates and limits within {FIRST_PICTURE_LIMIT_S:.0f} s"] = all(
            p.get("plots_s") is not None and p["plots_s"] <= FIRST_PICTURE_LIMIT_S for p in pictures
        )
    return {
        "minutes": args.minutes,
        "files": str(out),
        "up_exit": up.returncode,
        "not_alive_s": not_alive,
        "restarts": restarts,
        "index": flows.index,
        "state": flows.state,
        "longest_state_gap_while_indices_s": round(flows.longest_gap_s, 1),
        "state_gaps_over_5s": [
            {"minute": round(at / 60, 2), "seconds": round(g, 1)} for at, g in flows.gaps
        ],
        "q_state": answers,
        "rss_peak_mb": {k: round(v, 0) for k, v in peak.items() if v},
        "rss_growth_second_half": {k: round(v, 3) for k, v in growth.items()},
        "browser": pictures,
        "wrong_input": wrong_input,
        "checks": checks,
    }


def table(summary: dict) -> str:
    lines = [f"demo soak, {summary['minutes']:g} min (files: {summary['files']})"]
    gap = summary["longest_state_gap_while_indices_s"]
    lines.append(f"  indices {summary['index']}, states {summary['state']}, longest state gap")
    lines.append(f"  while indices flowed {gap} s")
    lines.append(f"  restarts {summary['restarts']}, not alive {summary['not_alive_s']}")
    lines.append(f"  RSS peak MB {summary['rss_peak_mb']}")
    lines.append(f"  RSS growth in the second half {summary['rss_growth_second_half']}")
    if summary["state_gaps_over_5s"]:
        lines.append(f"  state gaps over 5 s: {summary['state_gaps_over_5s']}")
    if summary["q_state"]:
        worst = max(summary["q_state"], key=lambda a: a["seconds"])
        lines.append(f"  q/state: {len(summary['q_state'])} asks, slowest {worst}")
    for p in summary["browser"]:
        lines.append(f"  browser at {p['minute']} min: {p}")
    wrong = summary["wrong_input"]
    if wrong["put"]:
        counts = f"{len(wrong['put'])} bad messages, {len(wrong['dead_letters'])} dead letters"
        lines.append(f"  wrong input: {counts}, unanswered {wrong['unanswered']}")
        lines.extend(f"    {letter}" for letter in wrong["dead_letters"])
    for name, ok in summary["checks"].items():
        lines.append(f"  {'PASS' if ok else 'FAIL'}  {name}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m bench.demo_soak", description=__doc__.split("\n")[0]
    )
    p.add_argument("--minutes", type=float, default=30.0)
    p.add_argument("--open", default="2,10,20,29", help="minutes at which a browser opens")
    p.add_argument("--sample-s", type=float, default=30.0, help="RSS sampling period")
    p.add_argument("--warmup-minutes", type=float, default=5.0)
    p.add_argument("--out", help="directory for the stack's files (default: a new temp dir)")
    p.add_argument("--json", metavar="FILE", help="also write the summary here")
    p.add_argument(
        "--hostile",
        type=float,
        metavar="MINUTE",
        help="when to put the bad messages of bench/hostile.py (default: half the run; <0: never)",
    )
    args = p.parse_args(argv)
    summary = run(args)
    print(table(summary))
    if args.json:
        Path(args.json).write_text(json.dumps(summary, indent=2))
    return 0 if all(summary["checks"].values()) else 1


if __name__ == "__main__":
    sys.exit(main())
