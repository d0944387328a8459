"""deploy/ and services/defaults/: the compose file and the default stack file run the same
processes with the same settings; every config file there parses."""

from __future__ import annotations

import configparser
from pathlib import Path

import pytest
import yaml

from services.defaults import default_file
from services.runtime.config import read_json5
from services.tools.stack import load_stack

DEPLOY = Path(__file__).resolve().parents[2] / "deploy"
DEFAULTS = default_file("stack.json5").parent
WIRING = {"--connect", "--ns"}  # the stack adds these itself


def normalised(args) -> tuple[str, ...]:
    """Arguments without the wiring flags, state files reduced to their names, config files
    to where they are (compose's relative to the image's source tree, the checkout here)."""
    out, skip = [], False
    for arg in map(str, args):
        if skip:
            skip = False
            continue
        if arg in WIRING:
            skip = True
            continue
        if arg.endswith(".sqlite"):
            arg = Path(arg).name
        elif arg.endswith((".json5", ".geojson")):
            arg = str((DEPLOY.parent / arg).resolve())
        out.append(arg)
    return tuple(out)


def test_the_default_stack_names_packaged_files_that_exist(tmp_path, monkeypatch):
    """``{defaults}/…`` becomes the packaged file wherever ``up`` runs; state stays there."""
    monkeypatch.chdir(tmp_path)
    stack = load_stack(DEFAULTS / "stack.json5")
    assert stack.state_dir == tmp_path / "var"
    files = [a for p in stack.processes for a in p.args if a.endswith((".json5", ".geojson"))]
    assert files and all(Path(f).is_absolute() and Path(f).is_file() for f in files), files
    assert all(Path(f).parent == DEFAULTS for f in files)


def test_compose_and_stack_run_the_same_processes():
    stack = load_stack(DEFAULTS / "stack.json5")
    compose = yaml.safe_load((DEPLOY / "compose.yaml").read_text())["services"]
    assert "router" in compose
    in_compose = {
        name: (svc["command"][0], normalised(svc["command"][1:]))
        for name, svc in compose.items()
        if name != "router"
    }
    in_stack = {p.name: (p.command, normalised(p.args)) for p in stack.processes}
    assert in_compose == in_stack


def test_compose_router_uses_the_router_config():
    router = yaml.safe_load((DEPLOY / "compose.yaml").read_text())["services"]["router"]
    assert router["image"].startswith("eclipse/zenoh:")
    assert any("router.json5" in volume for volume in router["volumes"])


@pytest.mark.parametrize(
    "path", sorted([*DEPLOY.glob("*.json5"), *DEFAULTS.glob("*.json5")]), ids=lambda p: p.name
)
def test_every_config_file_parses(path):
    read_json5(path)  # raises unless the file holds a JSON5 object


def test_systemd_units_run_trackfusion():
    for unit in (DEPLOY / "systemd").glob("*.service"):
        text = unit.read_text()
        assert "ExecStart=/opt/trackfusion/.venv/bin/trackfusion" in text, unit.name


def unit(name: str) -> configparser.ConfigParser:
    """A systemd unit file's sections and keys (case kept; a repeated key: the last)."""
    parser = configparser.ConfigParser(strict=False, interpolation=None)
    parser.optionxform = str  # type: ignore[method-assign]
    parser.read_string((DEPLOY / "systemd" / name).read_text())
    return parser


def test_service_unit_is_supervised_by_systemd():
    """READY and WATCHDOG come from the runtime (services/runtime/systemd.py); a silent
    watchdog or a failure restarts it with a delay; a crash loop is bounded."""
    service = unit("trackfusion@.service")["Service"]
    assert service["Type"] == "notify"
    assert service["NotifyAccess"] == "main"
    assert 10 <= int(service["WatchdogSec"].removesuffix("s")) <= 300
    assert service["Restart"] in {"always", "on-failure"}
    assert float(service["RestartSec"]) > 0
    limits = unit("trackfusion@.service")["Unit"]
    assert int(limits["StartLimitIntervalSec"]) > 0 and int(limits["StartLimitBurst"]) > 1


def test_router_unit_always_restarts():
    router = unit("trackfusion-router.service")
    assert router["Service"]["Restart"] == "always"
    assert float(router["Service"]["RestartSec"]) > 0
