"""The viewer under `make run`: memory and time to the first picture in a late browser.

Runs ``trackfusion up`` on a copy of ``services/defaults/stack.json5`` with its own router endpoint,
namespace, state directory and viewer ports (so it runs beside another stack), samples the
viewer's VmRSS every ``--sample`` seconds, and at each ``--open`` minute opens the web
viewer in a fresh headless Chromium (``tests/browser.py``) and times the first screenshot
with the coloured map (green strips: grey before the first states), with the plots'
estimate lines (blue) and with their intervention limits (red).

    python -m bench.viewer_soak --minutes 11 --open 5,10 --out /tmp/viewer-soak
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import sys
import time
from pathlib import Path

from bench.demo_soak import free_port, rss_mb, stack_copy, start_up
from tests.browser import first_picture, hue_pixels


def viewer_pid(ns: str) -> int | None:
    """The viewer child of this stack (by its command line: ``viewer … --ns {ns}``)."""
    for proc in Path("/proc").iterdir():
        if not proc.name.isdigit():
            continue
        try:
            argv = (proc / "cmdline").read_bytes().split(b"\0")
        except OSError:
            continue
        if b"services.cli" in argv and b"viewer" in argv and ns.encode() in argv:
            return int(proc.name)
    return None


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--minutes", type=float, default=11.0)
    parser.add_argument("--open", default="5,10", help="minutes at which a browser opens")
    parser.add_argument("--sample", type=float, default=30.0, help="RSS period, seconds")
    parser.add_argument("--browser-timeout", type=float, default=120.0)
    parser.add_argument("--out", type=Path, default=Path("/tmp/viewer-soak"))
    parser.add_argument("--viewer-args", default="", help="more viewer flags, e.g. '--worst 2'")
    args = parser.parse_args(argv)
    out = args.out.resolve()
    out.mkdir(parents=True, exist_ok=True)
    ns = f"tfsoak{os.getpid()}"
    web_port, grpc_port = free_port(), free_port()
    stack = stack_copy(
        out,
        endpoint=f"tcp/127.0.0.1:{free_port()}",
        ns=ns,
        web_port=web_port,
        grpc_port=grpc_port,
        viewer_args=args.viewer_args,
    )
    opens = sorted(float(m) for m in args.open.split(",") if m)
    up = start_up(stack, out)
    t0 = time.monotonic()
    samples: list[tuple[float, float | None]] = []
    pictures: list[dict] = []
    url = f"http://127.0.0.1:{web_port}/?url=rerun%2Bhttp%3A%2F%2F127.0.0.1%3A{grpc_port}%2Fproxy"
    pid = None
    next_sample = 0.0
    try:
        while (elapsed := time.monotonic() - t0) < args.minutes * 60:
            pid = pid or viewer_pid(ns)
            if elapsed >= next_sample and pid is not None:
                samples.append((round(elapsed), rss_mb(pid)))
                print(f"{elapsed:6.0f} s  viewer RSS {samples[-1][1]} MB", flush=True)
                next_sample += args.sample
            if opens and elapsed >= opens[0] * 60:
                minute = opens.pop(0)
                picture = first_picture(
                    url,
                    out / f"browser-{minute:g}",
                    wanted=("green", "blue", "limit"),
                    timeout_s=args.browser_timeout,
                )
                if picture.png:
                    (out / f"viewer-{minute:g}min.png").write_bytes(picture.png)
                pictures.append(
                    {
                        "minute": minute,
                        "started_s": picture.started_s,
                        "map_s": picture.seen_s.get("green"),  # coloured (grey before)
                        "plots_s": picture.seen_s.get("blue"),
                        "limits_s": picture.seen_s.get("limit"),  # intervention limit (red)
                        "all_s": picture.drawn_s,
                        "missing": picture.missing,
                        "pixels": hue_pixels(picture.png) if picture.png else {},
                        "rss_mb_after": rss_mb(pid) if pid else None,
                    }
                )
                print(json.dumps(pictures[-1]), flush=True)
                continue
            time.sleep(1.0)  # a sampling loop: the clock is what it waits for
    finally:
        os.killpg(up.pid, signal.SIGINT)
        up.wait(60)
    rss = [mb for _, mb in samples if mb is not None]
    report = {"samples": samples, "pictures": pictures, "max_rss_mb": max(rss, default=None)}
    (out / "report.json").write_text(json.dumps(report, indent=1))
    print(json.dumps({"max_rss_mb": report["max_rss_mb"], "pictures": pictures}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
