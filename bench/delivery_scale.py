"""What the delivery machinery costs at national size: a process holding N advanced publishers
(one per concrete key, ``ReliablePublisher``), the router routing their liveliness tokens and a
recovering subscriber seeing them, for N = 1k, 10k, 30k, 100k keys.

For each N, real processes on loopback: a router (``trackfusion router``), a subscriber
(``declare_reliable_subscriber`` on ``{ns}/state/**``) and a publisher that puts one 200-byte
message on each of N keys ``{ns}/state/L{i//500}/s{i%500}`` (declaring what it declares), then
stays idle, then puts ``--rounds`` more messages per key. Printed per process: RSS after the
declarations, CPU while idle (``--idle-s``) and CPU per message under puts. ``--bound B`` gives
the publisher ``DeliverySettings(max_publishers=B)`` (default: N, one publisher per key);
``--plain`` plain ``session.put`` (the baseline).

Run: ``.venv/bin/python -m bench.delivery_scale --keys 1000,10000``.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

PAYLOAD = b"x" * 200  # a SegmentState is a few hundred bytes
NS = "dscale"
KEYS_PER_LINE = 500
TICK_S = os.sysconf("SC_CLK_TCK")


def key_of(i: int) -> str:
    return f"{NS}/state/L{i // KEYS_PER_LINE:04d}/s{i % KEYS_PER_LINE:04d}"


def rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def cpu_s(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / TICK_S


def _client(endpoint: str):
    import zenoh

    from services.runtime.config import zenoh_config

    return zenoh.open(
        zenoh_config(
            {
                "mode": "client",
                "connect": {"endpoints": [endpoint]},
                "scouting": {"multicast": {"enabled": False}},
            }
        )
    )


def role_publisher(endpoint: str, n: int, bound: int | None, plain: bool) -> None:
    """Reads commands on stdin (``declare``, ``put R``, ``quit``), answers one JSON line each."""
    import zenoh

    from services.runtime.delivery import DeliverySettings, ReliablePublisher

    with _client(endpoint) as session:
        settings = DeliverySettings(cache_samples=16, max_publishers=bound or n)
        reliable = ReliablePublisher(session, settings)

        def put(key: str) -> None:
            if plain:
                session.put(key, PAYLOAD, congestion_control=zenoh.CongestionControl.BLOCK)
            else:
                reliable.put(key, PAYLOAD)

        try:
            for line in sys.stdin:
                cmd = line.split()
                started = time.perf_counter()
                if cmd[0] == "declare":
                    for i in range(n):
                        put(key_of(i))
                elif cmd[0] == "put":
                    for _ in range(int(cmd[1])):
                        for i in range(n):
                            put(key_of(i))
                else:
                    break
                print(
                    json.dumps(
                        {"s": time.perf_counter() - started, "plain_puts": reliable.plain_puts}
                    ),
                    flush=True,
                )
        finally:
            reliable.undeclare()


def role_subscriber(endpoint: str) -> None:
    """Counts samples; ``count`` on stdin prints the count so far."""
    from services.runtime.delivery import declare_reliable_subscriber

    count = 0
    lock = threading.Lock()

    def on_sample(_sample) -> None:
        nonlocal count
        with lock:
            count += 1

    with _client(endpoint) as session:
        sub = declare_reliable_subscriber(session, f"{NS}/state/**", on_sample)
        try:
            print(json.dumps({"ready": True}), flush=True)
            for line in sys.stdin:
                if line.strip() != "count":
                    break
                with lock:
                    print(json.dumps({"count": count}), flush=True)
        finally:
            sub.undeclare()


class Proc:
    """A child process driven over stdin/stdout; killed at exit whatever happens."""

    def __init__(self, argv: list[str]) -> None:
        self.p = subprocess.Popen(
            argv,
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=sys.stderr,
            text=True,
            start_new_session=True,
        )

    def ask(self, command: str) -> dict:
        assert self.p.stdin is not None and self.p.stdout is not None
        self.p.stdin.write(command + "\n")
        self.p.stdin.flush()
        line = self.p.stdout.readline()
        if not line:
            raise RuntimeError(f"{self.p.args} ended with {self.p.wait()}")
        return json.loads(line)

    def stop(self) -> None:
        if self.p.poll() is None:
            try:
                assert self.p.stdin is not None
                self.p.stdin.write("quit\n")
                self.p.stdin.flush()
                self.p.wait(30)
            except (OSError, subprocess.TimeoutExpired):
                os.killpg(self.p.pid, 9)
                self.p.wait()


def measure(n: int, args: argparse.Namespace) -> dict:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        endpoint = f"tcp/127.0.0.1:{s.getsockname()[1]}"
    me = [sys.executable, "-m", "bench.delivery_scale"]
    procs: list[Proc] = []
    try:
        router = Proc([sys.executable, "-m", "services.cli", "router", "--listen", endpoint])
        procs.append(router)
        time.sleep(1.0)  # bench, not test: the router has no readiness line on stdout
        sub = Proc([*me, "--role", "sub", "--endpoint", endpoint])
        procs.append(sub)
        sub.p.stdout.readline()  # ready
        extra = ["--bound", str(args.bound)] if args.bound else []
        extra += ["--plain"] if args.plain else []
        pub = Proc([*me, "--role", "pub", "--endpoint", endpoint, "--n", str(n), *extra])
        procs.append(pub)
        pids = {"pub": pub.p.pid, "router": router.p.pid, "sub": sub.p.pid}
        declare_s = pub.ask("declare")["s"]
        deadline = time.monotonic() + 120
        while sub.ask("count")["count"] < n and time.monotonic() < deadline:
            time.sleep(0.2)
        time.sleep(2.0)  # let the liveliness tokens settle
        cpu0 = {k: cpu_s(p) for k, p in pids.items()}
        time.sleep(args.idle_s)
        idle = {k: (cpu_s(p) - cpu0[k]) / args.idle_s for k, p in pids.items()}
        rss = {k: rss_mb(p) for k, p in pids.items()}
        cpu1 = {k: cpu_s(p) for k, p in pids.items()}
        before = sub.ask("count")["count"]
        put_s = pub.ask(f"put {args.rounds}")["s"]
        sent = n * args.rounds
        deadline = time.monotonic() + 120
        while sub.ask("count")["count"] < before + sent and time.monotonic() < deadline:
            time.sleep(0.2)
        received = sub.ask("count")["count"] - before
        busy = {k: (cpu_s(p) - cpu1[k]) / sent * 1e6 for k, p in pids.items()}
        rss_after = {k: rss_mb(p) for k, p in pids.items()}
        return {
            "keys": n,
            "declare_s": round(declare_s, 2),
            "rss_mb": {k: round(v, 1) for k, v in rss.items()},
            "rss_after_puts_mb": {k: round(v, 1) for k, v in rss_after.items()},
            "idle_cpu_pct": {k: round(100 * v, 1) for k, v in idle.items()},
            "put_rate_per_s": round(sent / put_s),
            "cpu_us_per_msg": {k: round(v, 1) for k, v in busy.items()},
            "received": f"{received}/{sent}",
        }
    finally:
        for proc in reversed(procs):
            proc.stop()


def main(args: argparse.Namespace) -> None:
    def on_term(signum, _frame) -> None:  # so that ``finally`` stops the children
        raise KeyboardInterrupt(signal.Signals(signum).name)

    signal.signal(signal.SIGTERM, on_term)
    mode = "plain put" if args.plain else f"bound {args.bound}" if args.bound else "one per key"
    rows = []
    for n in args.keys:
        row = measure(n, args)
        rows.append(row)
        print(f"[{mode}] {json.dumps(row)}", flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps({"mode": mode, "rows": rows}, indent=1))


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--role", choices=("main", "pub", "sub"), default="main")
    parser.add_argument("--endpoint")
    parser.add_argument("--n", type=int)
    parser.add_argument("--keys", type=lambda s: [int(x) for x in s.split(",")], default=[1000])
    parser.add_argument("--bound", type=int)
    parser.add_argument("--plain", action="store_true")
    parser.add_argument("--idle-s", type=float, default=10.0)
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--json")
    a = parser.parse_args()
    if a.role == "pub":
        role_publisher(a.endpoint, a.n, a.bound, a.plain)
    elif a.role == "sub":
        role_subscriber(a.endpoint)
    else:
        main(a)
