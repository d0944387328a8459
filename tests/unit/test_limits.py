"""services.limits: which speed class applies to a line, and the loader's checks."""

from __future__ import annotations

import json

import numpy as np
import pytest

from services.defaults import demo_network
from services.limits import (
    DEFAULT_LIMITS_FILE,
    load_limits,
    network_line_speeds,
    speed_band,
)
from services.runtime.config import read_json5


def test_default_file_names_the_demo_lines_and_has_every_table():
    limits = load_limits()
    assert limits.levels == ("alert", "intervention")
    assert {ln: limits.speed_class(ln) for ln in ("L1", "L2", "L3")} == {
        "L1": "80<v<=120",
        "L2": "120<v<=160",
        "L3": "v<=80",
    }
    assert set(limits.immediate_action) == set(limits.speed_classes)
    for line in ("L1", "L2", "L3"):
        table, ial = limits.for_line(line), limits.immediate_action_for_line(line)
        assert table.shape == (2, 2) and (ial >= table[-1]).all()


@pytest.mark.parametrize(
    ("name", "band"),
    [("v<=80", (0.0, 80.0)), ("80<v<=120", (80.0, 120.0)), ("160 < v <= 230", (160.0, 230.0))],
)
def test_speed_band_of_a_class_name(name, band):
    assert speed_band(name) == band


@pytest.mark.parametrize("name", ["fast", "v<80", "120<v<=80", "v<=", "80<v"])
def test_a_class_name_without_a_band_is_refused(name):
    with pytest.raises(ValueError, match="speed class"):
        speed_band(name)


@pytest.mark.parametrize(
    ("kmh", "name"),
    [(40.0, "v<=80"), (80.0, "v<=80"), (80.1, "80<v<=120"), (160.0, "120<v<=160"),
     (200.0, "160<v<=230"), (300.0, "160<v<=230")],
)  # fmt: skip
def test_class_for_speed_takes_the_band_holding_it(kmh, name):
    assert load_limits().class_for_speed(kmh) == name


def test_the_file_names_first_then_the_network_speed_then_the_default():
    limits = load_limits(line_speeds_kmh={"L1": 200.0, "X1": 140.0})
    assert limits.speed_class("L1") == "80<v<=120"  # named in the file: the speed is ignored
    assert limits.speed_class("X1") == "120<v<=160"  # from its line speed
    assert limits.speed_class("X2") == "80<v<=120"  # neither: the default class
    assert limits.describe("L1") == "speed class 80<v<=120"
    assert limits.describe("X1") == "speed class 120<v<=160 (line speed 140 km/h)"
    assert limits.describe("X2") == "speed class 80<v<=120 (default)"
    np.testing.assert_array_equal(limits.for_line("X1"), limits.speed_classes["120<v<=160"])


def test_network_line_speeds_are_its_lines_speeds_in_kmh():
    network = demo_network()
    speeds = network_line_speeds(network)
    assert set(speeds) == set(network.lines)
    for line in network.lines.values():
        assert speeds[line.id] == pytest.approx(line.line_speed_mps * 3.6)


def _write(tmp_path, **changes):
    raw = read_json5(DEFAULT_LIMITS_FILE) | changes
    path = tmp_path / "limits.json5"
    path.write_text(json.dumps(raw))
    return path


def test_loader_refuses_a_class_without_a_band_and_an_ial_below_the_il(tmp_path):
    raw_classes = load_limits().speed_classes
    classes = {n: {"alert": t[0].tolist(), "intervention": t[1].tolist()} for n, t in
               raw_classes.items()}  # fmt: skip
    bad_name = {**classes, "express": classes["v<=80"]}
    with pytest.raises(ValueError, match="'express' is not"):
        load_limits(_write(tmp_path, speed_classes=bad_name))
    low_ial = {n: [1.0, 1.0] for n in classes}
    with pytest.raises(ValueError, match="immediate_action"):
        load_limits(_write(tmp_path, immediate_action=low_ial))
