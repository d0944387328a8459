"""The written report in a real browser: headless Chromium (Debian's ``chromium``, driven
over the DevTools pipe by tests/browser.py) opens the file offline and draws the map in the
colours of P(exceed)."""

from __future__ import annotations

import time
from pathlib import Path

import pytest
from browser import CHROMIUM, MIN_PIXELS, DevTools, hue_pixels

from services.alerting.testing import T0, make_state, p_top6
from services.tools import report
from services.tools.network_map import network_map

pytestmark = pytest.mark.skipif(
    not CHROMIUM.exists(), reason="no /usr/bin/chromium (apt-get install -y chromium)"
)

# resolves once the page has loaded (at once if it has): the page's own event, no polling
LOADED = """new Promise(done => document.readyState === "complete" ? done(location.href)
    : addEventListener("load", () => done(location.href)))"""


def screenshot_of_the_map(browser: DevTools, path: Path) -> bytes:
    """Open ``path`` and screenshot with the whole map where hue_pixels counts (the left
    58 % between 5 % and 55 % of the height) and the legend below it."""
    browser.open(path.as_uri())
    loaded = browser.call(
        "Runtime.evaluate", {"expression": LOADED, "awaitPromise": True, "returnByValue": True}
    )
    assert loaded["result"]["value"] == path.as_uri()
    top = browser.evaluate(
        """(() => { const map = document.getElementById("map").getBoundingClientRect();
        scrollTo(0, map.bottom + scrollY - 0.55 * innerHeight);
        return document.getElementById("map").getBoundingClientRect().top / innerHeight; })()"""
    )
    assert top > 0.05, f"the map does not fit the counted rows (top at {top:.2f})"
    return browser.screenshot()


def test_chromium_draws_the_map_in_the_colours_of_p_exceed(tmp_path: Path):
    network = network_map(None)
    l1 = sorted(seg for line, seg in network.polylines if line == "L1")

    def write(name: str, p_of) -> Path:
        states = [
            make_state(T0, segment=seg, p_exceed=p_top6(1, p_of(k / (len(l1) - 1))))
            for k, seg in enumerate(l1)
        ]
        path = tmp_path / name
        path.write_text(report.render(report.ReportData(states, network, time.time())))
        return path

    graded = write("graded.html", lambda x: x)  # green at chainage 0 to red at the end
    calm = write("calm.html", lambda x: 0.02)
    size = (1400, 1300)  # tall enough for the map in the counted rows
    with DevTools(tmp_path / "profile", tmp_path / "chromium.log", size=size) as browser:
        png = screenshot_of_the_map(browser, graded)
        (tmp_path / "graded.png").write_bytes(png)  # to look at when it fails
        pixels = hue_pixels(png)
        calm_pixels = hue_pixels(screenshot_of_the_map(browser, calm))
    print(f"map pixels: graded {pixels}, calm {calm_pixels}")
    assert all(pixels[hue] >= MIN_PIXELS[hue] for hue in ("green", "yellow", "red")), pixels
    assert calm_pixels["green"] >= MIN_PIXELS["green"], calm_pixels
    assert all(calm_pixels[hue] < MIN_PIXELS[hue] for hue in ("yellow", "red")), calm_pixels
