"""A real browser: headless Chromium (Debian's ``chromium``) opens the web viewer served by
the viewer service while it holds data, and a screenshot shows the rendered viewer.

Chromium's ``--screenshot`` captures at the page's load event, before the viewer's Wasm
has started (``--virtual-time-budget`` does not wait for it either), so the test drives
Chromium over the DevTools protocol on ``--remote-debugging-pipe`` (fd 3 in, fd 4 out,
NUL-separated JSON; no extra package): navigate, wait until the page's ``window._handle``
exists (the viewer's own "app started" hook), give it frames to draw, capture. Rendering
is WebGL on SwiftShader (``renderer=webgl`` in the URL); services/viewer/README.md has
what was tried.
"""

from __future__ import annotations

import base64
import io
import json
import os
import signal
import socket
import subprocess
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from schemas import Alert, GpsFix, encode, keys
from services.alerting.testing import T0, make_state, p_top6
from services.viewer import service as viewer
from simulators.network import DEMO_NETWORK, demo_network

CHROMIUM = Path("/usr/bin/chromium")
TIMEOUT_S = 5.0
# Upper bounds only (each loop ends as soon as its condition holds: ~20 s in all unloaded).
# SwiftShader renders on the CPU: with three busy processes beside the suite, 30 s to draw
# was once not enough.
START_S = 120.0  # Wasm download + compile + first frame on 2 shared cores
DRAW_S = 120.0  # then until the streamed recording is drawn
DAY_S = 86_400.0

pytestmark = pytest.mark.skipif(
    not CHROMIUM.exists(), reason="no /usr/bin/chromium (apt-get install -y chromium)"
)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class DevTools:
    """Headless Chromium driven over ``--remote-debugging-pipe``."""

    def __init__(self, profile: Path, log: Path) -> None:
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
                    "--disable-quic",
                    "--no-first-run",
                    "--disable-background-networking",
                    "--disable-component-update",
                    "--disable-sync",
                    f"--user-data-dir={profile}",
                    "--window-size=1400,900",
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

    def call(self, method: str, params: dict[str, Any] | None = None) -> dict[str, Any]:
        self._id += 1
        message: dict[str, Any] = {"id": self._id, "method": method, "params": params or {}}
        if self.session is not None:
            message["sessionId"] = self.session
        os.write(self._to_chrome, json.dumps(message).encode() + b"\0")
        while True:  # skip events until our answer
            while b"\0" not in self._buffer:
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
        try:
            self.session = None
            self.call("Browser.close")
            self.proc.wait(TIMEOUT_S)
        except (OSError, EOFError, RuntimeError, subprocess.TimeoutExpired):
            os.killpg(self.proc.pid, signal.SIGKILL)
            self.proc.wait(TIMEOUT_S)
        finally:
            os.close(self._to_chrome)
            os.close(self._from_chrome)


def test_headless_chromium_renders_the_web_viewer(
    open_session, service_config, liveliness_events, tmp_path: Path
):
    ns = service_config.ns
    line = demo_network().lines["L1"]
    segments = [s.id for s in line.segments[-40:]]  # 8 km of line, green to red
    lon, lat = map(float, line.lonlat_at(line.segments[5].mid_m))
    client = open_session()
    alive = liveliness_events(client, keys.alive(ns, viewer.SERVICE, "test"))
    sink = viewer.Sink("web", web_port=_free_port(), grpc_port=_free_port())
    out = io.StringIO()
    logged = threading.Event()
    expected = len(segments) * 2 + 2
    stop, result = threading.Event(), []
    thread = threading.Thread(
        target=lambda: result.append(
            viewer.main(
                service_config,
                DEMO_NETWORK,
                sink,
                stop=stop,
                handle_signals=False,
                blueprint_interval_s=0.0,  # the worst segments' plots at once
                on_logged=lambda total: total >= expected and logged.set(),
                out=out,
            )
        ),
        name="viewer-web-under-test",
    )
    thread.start()
    browser = None
    try:
        assert alive.get()[1] == keys.alive(ns, viewer.SERVICE, "test")
        url = out.getvalue().strip()
        assert url.startswith(f"http://127.0.0.1:{sink.web_port}/?url=rerun%2Bhttp")
        for i, segment in enumerate(segments):
            for k in range(2):
                p = p_top6(1, min(1.0, i / len(segments) + 0.1 * k))
                state = make_state(T0 + k * DAY_S, segment=segment, p_exceed=p)
                client.put(keys.state(ns, "L1", segment), encode(state))
        client.put(keys.gps(ns, "T1"), encode(GpsFix(train="T1", t=T0, lat_deg=lat, lon_deg=lon)))
        alert = Alert(
            line="L1",
            segment=segments[-1],
            t=T0 + DAY_S,
            kind="exceedance",
            status="raised",
            indicator="top6",
            level="intervention",
            probability=1.0,
        )
        client.put(keys.alert(ns, "L1", segments[-1]), encode(alert))
        assert logged.wait(TIMEOUT_S), "the viewer did not log the published messages"

        browser = DevTools(tmp_path / "profile", tmp_path / "chromium.log")
        browser.open(f"{url}&renderer=webgl")
        deadline = time.monotonic() + START_S
        state = ""
        while time.monotonic() < deadline:  # polling a page: no event to wait on from here
            state = browser.evaluate(
                "window._handle ? 'started' : (document.body ? document.body.innerText : '')"
            )
            if state == "started":
                break
            time.sleep(0.5)
        assert state == "started", f"web viewer did not start: {state!r}"
        assert browser.evaluate("window._handle.has_panicked()") is False
        deadline = time.monotonic() + DRAW_S
        while True:  # the recording streams in over gRPC: screenshot until the map is coloured
            png = browser.screenshot()
            missing = missing_colors(png)
            if not missing or time.monotonic() > deadline:
                break
            time.sleep(1.0)
        assert browser.evaluate("window._handle.has_panicked()") is False
    finally:
        if browser is not None:
            browser.close()
        stop.set()
        thread.join(TIMEOUT_S)
    assert not thread.is_alive() and result == [0]

    (tmp_path / "viewer.png").write_bytes(png)
    assert not missing, f"no {missing} map pixels on the screenshot {tmp_path / 'viewer.png'}"


def missing_colors(png: bytes) -> list[str]:
    """Hues of the map's exceedance colours (green, red) with fewer than 100 pixels.

    Strips are drawn with an outline and blended, so hues are matched, not exact RGB.
    """
    from PIL import Image  # matplotlib's dependency

    rgb = np.asarray(Image.open(io.BytesIO(png)).convert("RGB")).astype(int)
    r, g, b = rgb[..., 0], rgb[..., 1], rgb[..., 2]
    hues = {"green": (g > r + 30) & (g > b + 30), "red": (r > g + 60) & (r > b + 60)}
    return [name for name, mask in hues.items() if mask.sum() < 100]
