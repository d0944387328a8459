"""Headless Chromium (Debian's ``chromium``) driven over the DevTools pipe: open the web
viewer, wait until it draws the coloured network map, take a screenshot.

Chromium's ``--screenshot`` captures at the page's load event, before the viewer's Wasm has
started, so Chromium runs with ``--remote-debugging-pipe`` (fd 3 in, fd 4 out, NUL-separated
JSON; stdlib only): navigate, wait until the page's ``window._handle`` exists (the viewer's
"app started" hook), then screenshot until the map's exceedance colours are on it.
Rendering is WebGL on SwiftShader (``renderer=webgl`` is appended to the URL);
services/viewer/README.md, "Headless browser check". Used by tests/e2e/test_viewer_browser.py and
``python -m bench.viewer_soak``; ``python tests/browser.py URL OUT.png`` times one opening.
"""

from __future__ import annotations

import argparse
import base64
import io
import json
import os
import select
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

CHROMIUM = Path("/usr/bin/chromium")
CLOSE_TIMEOUT_S = 5.0
# a hue counts as on screen from this many pixels: the map's colour legend alone has up to
# ~100 of green, yellow and red; "blue" counts in the plot row that has the fewest, and a
# few days of estimate (line and band) in a row's 90-day window are ~70 of it
MIN_PIXELS = {"green": 200, "yellow": 200, "red": 200, "blue": 40, "limit": 100}
PLOT_ROWS = 4  # the viewer's default layout: the three worst segments, then the selected one


class DevTools:
    """Headless Chromium driven over ``--remote-debugging-pipe``; a fresh profile in
    ``profile``, Chromium's stderr in ``log``. Use as a context manager (or ``close``)."""

    def __init__(self, profile: Path, log: Path, *, size: tuple[int, int] = (1400, 900)) -> None:
        to_chrome_r, self._to_chrome = os.pipe()
        self._from_chrome, from_chrome_w = os.pipe()

        def fds_3_and_4() -> None:  # in the child: the pipe ends Chromium expects
            a, b = os.dup(to_chrome_r), os.dup(from_chrome_w)
            os.dup2(a, 3)
            os.dup2(b, 4)

        with log.open("wb") as err:
            self.proc = subprocess.Popen(
                [
                    str(CHROMIUM),
                    "--headless",
                    "--no-sandbox",
                    "--disable-gpu",
                    "--disable-quic",
                    "--no-first-run",
                    "--disable-background-networking",
                    "--disable-component-update",
                    "--disable-sync",
                    "--disable-crash-reporter",
                    "--disable-breakpad",
                    f"--user-data-dir={profile}",
                    f"--window-size={size[0]},{size[1]}",
                    "--use-angle=swiftshader",
                    "--enable-unsafe-swiftshader",
                    "--remote-debugging-pipe",
                    "about:blank",
                ],  # fmt: skip
                preexec_fn=fds_3_and_4,
                close_fds=False,
                stdin=subprocess.DEVNULL,
                stdout=subprocess.DEVNULL,
                stderr=err,
                start_new_session=True,
            )
        os.close(to_chrome_r)
        os.close(from_chrome_w)
        self._buffer = b""
        self._id = 0
        self.session: str | None = None

    def __enter__(self) -> DevTools:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def call(
        self, method: str, params: dict[str, Any] | None = None, *, timeout_s: float = 30.0
    ) -> dict[str, Any]:
        """Send one command and return its result; TimeoutError after ``timeout_s`` (a page
        whose main thread is busy, e.g. the viewer ingesting data, answers late)."""
        deadline = time.monotonic() + timeout_s
        self._id += 1
        message: dict[str, Any] = {"id": self._id, "method": method, "params": params or {}}
        if self.session is not None:
            message["sessionId"] = self.session
        os.write(self._to_chrome, json.dumps(message).encode() + b"\0")
        while True:  # skip events until our answer
            while b"\0" not in self._buffer:
                left = deadline - time.monotonic()
                if left <= 0 or not select.select([self._from_chrome], [], [], left)[0]:
                    raise TimeoutError(f"{method}: no answer from chromium in {timeout_s} s")
                chunk = os.read(self._from_chrome, 1 << 16)
                if not chunk:
                    raise EOFError("chromium closed the DevTools pipe")
                self._buffer += chunk
            raw, self._buffer = self._buffer.split(b"\0", 1)
            reply = json.loads(raw)
            if reply.get("id") == self._id:
                if "error" in reply:
                    raise RuntimeError(f"{method}: {reply['error']}")
                return reply["result"]

    def open(self, url: str) -> None:
        target = self.call("Target.createTarget", {"url": "about:blank"})["targetId"]
        attach = {"targetId": target, "flatten": True}
        self.session = self.call("Target.attachToTarget", attach)["sessionId"]
        self.call("Page.enable")
        self.call("Page.navigate", {"url": url})

    def evaluate(self, expression: str) -> Any:
        result = self.call("Runtime.evaluate", {"expression": expression, "returnByValue": True})
        return result["result"].get("value")

    def screenshot(self) -> bytes:
        return base64.b64decode(self.call("Page.captureScreenshot", {"format": "png"})["data"])

    def close(self) -> None:
        if self.proc.poll() is not None and self._to_chrome < 0:
            return
        try:
            self.session = None
            self.call("Browser.close", timeout_s=CLOSE_TIMEOUT_S)
            self.proc.wait(CLOSE_TIMEOUT_S)
        except (OSError, EOFError, RuntimeError, TimeoutError, subprocess.TimeoutExpired):
            os.killpg(self.proc.pid, signal.SIGKILL)
            self.proc.wait(CLOSE_TIMEOUT_S)
        finally:
            os.close(self._to_chrome)
            os.close(self._from_chrome)
            self._to_chrome = self._from_chrome = -1


def hue_pixels(png: bytes) -> dict[str, int]:
    """Pixels of the map's exceedance hues (green, yellow, red) in the map's part of the
    screenshot (left 58 %, below the top bar, above the alert log), of the plots'
    intervention-limit red (``limit``) in the plots' part (the right 38 %, from the top bar
    to the time panel) and of the estimate blue in the plot row of the worst segments that
    has the fewest (``blue``: every worst row shows its estimate, however short its history
    still is). Strips are drawn with an outline and blended, so hues are matched, not exact
    RGB."""
    from PIL import Image  # matplotlib's dependency

    rgb = np.asarray(Image.open(io.BytesIO(png)).convert("RGB")).astype(int)
    h, w = rgb.shape[:2]
    rows = slice(int(0.05 * h), int(0.55 * h))  # below the top bar ("Software rasterizer")
    map_part = rgb[rows, : int(0.58 * w)]
    plots = rgb[int(0.045 * h) : int(0.81 * h), int(0.62 * w) :]

    def hues(part: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return part[..., 0], part[..., 1], part[..., 2]

    r, g, b = hues(map_part)
    pr, pg, pb = hues(plots)
    # the estimate (80, 160, 255); the trains' (0, 200, 255) are on the map, not here
    blue = (pb > pg + 60) & (pg > pr + 40) & (pr > 30)
    row_h = len(blue) // PLOT_ROWS
    masks = {
        "green": (g > r + 30) & (g > b + 30),
        "yellow": (r > 180) & (g > 150) & (b < 90) & (abs(r - g) < 60),
        "red": (r > g + 60) & (r > b + 60),
        # the plots' intervention limit (230, 40, 40), not the orange of a notification
        "limit": (pr > pg + 120) & (pr > pb + 120) & (abs(pg - pb) < 40),
    }
    pixels = {name: int(mask.sum()) for name, mask in masks.items()}
    pixels["blue"] = min(int(blue[k * row_h : (k + 1) * row_h].sum()) for k in range(PLOT_ROWS - 1))
    return pixels


def missing_colors(png: bytes, wanted: tuple[str, ...] = ("green", "red")) -> list[str]:
    """The ``wanted`` hues with fewer than their :data:`MIN_PIXELS` on the screenshot."""
    pixels = hue_pixels(png)
    return [name for name in wanted if pixels[name] < MIN_PIXELS[name]]


@dataclass
class Picture:
    """One opening of the viewer: seconds from navigation to the app's start and to the first
    screenshot with every wanted hue (None if it never came), the last screenshot."""

    started_s: float | None = None
    drawn_s: float | None = None
    png: bytes = b""
    panicked: bool = False
    missing: list[str] = field(default_factory=list)
    page_text: str = ""
    seen_s: dict[str, float] = field(default_factory=dict)  # hue -> first screenshot with it
    shots: list[tuple[float, bytes]] = field(default_factory=list)  # (seconds, png) each one


def first_picture(
    url: str,
    workdir: Path,
    *,
    wanted: tuple[str, ...] = ("green",),
    timeout_s: float = 120.0,
    poll_s: float = 0.5,
) -> Picture:
    """Open ``url`` (``&renderer=webgl`` appended) in a fresh headless Chromium profile under
    ``workdir`` and screenshot until every ``wanted`` hue is drawn or ``timeout_s`` passes.

    Polling is the only way to see a page from outside; each loop ends at its condition.
    Chromium is closed before returning.
    """
    workdir.mkdir(parents=True, exist_ok=True)
    picture = Picture(missing=list(wanted))
    profile = Path(tempfile.mkdtemp(prefix="profile-", dir=workdir))
    with DevTools(profile, workdir / "chromium.log") as browser:
        t0 = time.monotonic()
        deadline = t0 + timeout_s

        def ask(method: str, params: dict[str, Any] | None = None) -> dict[str, Any] | None:
            """The answer, or None if the page is too busy to give it before the deadline."""
            try:
                return browser.call(method, params, timeout_s=max(0.1, deadline - time.monotonic()))
            except TimeoutError:
                return None

        def evaluate(expression: str) -> Any:
            reply = ask("Runtime.evaluate", {"expression": expression, "returnByValue": True})
            return None if reply is None else reply["result"].get("value")

        browser.open(f"{url}&renderer=webgl")
        while time.monotonic() < deadline:
            state = evaluate(
                "window._handle ? 'started' : (document.body ? document.body.innerText : '')"
            )
            if state == "started":
                picture.started_s = time.monotonic() - t0
                break
            picture.page_text = str(state)
            time.sleep(poll_s)
        while picture.started_s is not None and time.monotonic() < deadline:
            shot = ask("Page.captureScreenshot", {"format": "png"})
            if shot is not None:
                picture.png = base64.b64decode(shot["data"])
                picture.shots.append((time.monotonic() - t0, picture.png))
                picture.missing = missing_colors(picture.png, wanted)
                for hue in wanted:
                    if hue not in picture.missing:
                        picture.seen_s.setdefault(hue, time.monotonic() - t0)
                if not picture.missing:
                    picture.drawn_s = time.monotonic() - t0
                    break
            time.sleep(poll_s)
        if picture.started_s is not None:
            picture.panicked = bool(evaluate("window._handle.has_panicked()"))
    return picture


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("url", help="the web viewer's URL (as the viewer prints it)")
    parser.add_argument("png", type=Path, help="where the last screenshot goes")
    parser.add_argument("--timeout", type=float, default=120.0, help="seconds (%(default)s)")
    parser.add_argument("--want", default="green", help="hues, comma-separated (%(default)s)")
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="viewer-browser-") as tmp:
        picture = first_picture(
            args.url, Path(tmp), wanted=tuple(args.want.split(",")), timeout_s=args.timeout
        )
    if picture.png:
        args.png.write_bytes(picture.png)
    report = {
        "started_s": picture.started_s,
        "drawn_s": picture.drawn_s,
        "missing": picture.missing,
        "panicked": picture.panicked,
        "pixels": hue_pixels(picture.png) if picture.png else {},
        "page_text": picture.page_text[:200],
    }
    print(json.dumps(report))
    return 0 if picture.drawn_s is not None else 1


if __name__ == "__main__":
    sys.exit(main())
