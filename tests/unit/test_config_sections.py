"""Every ``services.{name}`` section goes through one loader that refuses a key nobody reads,
naming the file, the section, the key and the keys it knows; the command line turns that
into exit code 2 and one line on stderr. Nothing here opens a Zenoh session: the section is
read before anything else."""

from __future__ import annotations

import re
from pathlib import Path

import json5
import pytest

from services import cli
from services.calibration import service as calibration
from services.filtering import service as filtering
from services.ingestion import service as ingestion
from services.runtime.config import SECTIONS, load_config
from services.runtime.delivery import DeliverySettings
from services.runtime.service import ServiceRuntime
from services.tools import gateway_check


def config_file(tmp_path: Path, section: str, options: dict) -> Path:
    path = tmp_path / "service.json5"
    path.write_text(json5.dumps({"services": {section: options}}))
    return path


def refused(path: Path, section: str, key: str, known: str) -> str:
    """The message: file, section and key, then the keys that section knows."""
    return re.escape(
        f"config file {path}: services.{section}: unknown key {key!r}; known keys: {known}"
    )


# How each reader of a section is started; each must refuse before it opens anything.
READERS = {
    "filtering": lambda conf: filtering.main(conf),
    "calibration": lambda conf: calibration.main(conf),
    "ingestion": lambda conf: ingestion.main(conf),
    "delivery": lambda conf: ServiceRuntime("filtering", conf),
}
KNOWN = {
    "filtering": "db, limits, network, selector",
    "calibration": ", ".join(sorted(calibration.OPTIONS)),
    "ingestion": None,  # IngestionConfig's fields, checked below
    "delivery": "outbox, raw_outbox, replay_s, replay_timeout_s",
}


def test_every_section_has_a_reader_here():
    assert set(READERS) == set(SECTIONS)


@pytest.mark.parametrize("section", sorted(READERS))
def test_unknown_key_in_a_section_is_refused_naming_file_section_key_and_known_keys(
    tmp_path, section
):
    path = config_file(tmp_path, section, {"no_such_key": 1})
    with pytest.raises(ValueError) as refusal:
        READERS[section](load_config(path))
    message = str(refusal.value)
    assert message.startswith(f"config file {path}: services.{section}: unknown key ")
    assert "'no_such_key'; known keys: " in message
    if KNOWN[section] is not None:
        assert re.fullmatch(refused(path, section, "no_such_key", KNOWN[section]), message)


def test_ingestion_lists_its_thresholds_as_known_keys(tmp_path):
    path = config_file(tmp_path, "ingestion", {"extrapolate_sec": 2})
    with pytest.raises(ValueError, match="known keys: .*extrapolate_s"):
        ingestion.main(load_config(path))


def test_gateway_check_reads_the_ingestion_section_the_same_way(tmp_path):
    path = config_file(tmp_path, "ingestion", {"no_such_key": 1})
    with pytest.raises(ValueError, match=r"services\.ingestion: unknown key 'no_such_key'"):
        gateway_check.main(load_config(path), "T1", 0.0)


@pytest.mark.parametrize("section", ["alerting", "extraction", "viewer", "simulate"])
def test_a_section_of_a_service_that_takes_no_settings_is_refused(tmp_path, section):
    path = config_file(tmp_path, section, {"no_such_key": 1})
    expected = (
        f"config file {path}: services: unknown section {section!r} (that service takes no "
        f"settings from the file, or the name is misspelt); known sections: "
        f"{', '.join(SECTIONS)}"
    )
    with pytest.raises(ValueError, match=re.escape(expected)):
        load_config(path)


def test_known_keys_pass_through_unchanged(tmp_path):
    path = config_file(tmp_path, "filtering", {"selector": "L1/**"})
    assert load_config(path).options("filtering", filtering.OPTIONS) == {"selector": "L1/**"}


@pytest.mark.parametrize(
    ("argv", "section"), [(["filtering"], "filtering"), (["gateway", "check"], "ingestion")]
)
def test_the_command_line_exits_2_with_one_line_saying_what_to_fix(tmp_path, capsys, argv, section):
    path = config_file(tmp_path, section, {"no_such_key": 1})
    extra = ["--train", "T1", "--seconds", "0"] if argv[0] == "gateway" else []
    assert cli.main([*argv, *extra, "--config", str(path), "--log-level", "warning"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1
    assert err.startswith(f"trackfusion {' '.join(argv)}: config file {path}: services.{section}")


def test_a_bad_section_of_a_service_without_settings_exits_2(tmp_path, capsys):
    path = config_file(tmp_path, "alerting", {"raise_at": 0.5})
    assert cli.main(["alerting", "--config", str(path)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "unknown section 'alerting'" in err


@pytest.mark.parametrize("argv", [["viewer", "--rrd", "x.rrd"], ["ingestion"], ["report"]])
def test_a_bad_network_file_exits_2_naming_the_file(tmp_path, capsys, argv):
    path = tmp_path / "net.geojson"
    path.write_text('{"type": "FeatureCollection", "features": []}')
    assert cli.main([*argv, "--network", str(path), "--log-level", "warning"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and str(path) in err and "no LineString" in err


@pytest.mark.parametrize("bad", [0, -1, 2.5, "many"])
def test_delivery_outbox_max_bytes_must_be_a_positive_integer(bad):
    with pytest.raises(ValueError, match=r"services\.delivery\.outbox\.max_bytes must be"):
        DeliverySettings.from_options({"outbox": {"max_bytes": bad}})
    assert DeliverySettings.from_options({"outbox": {"max_bytes": 5}}).outbox.max_bytes == 5


@pytest.mark.parametrize("command", ["planning", "filtering"])
def test_a_state_file_that_cannot_be_opened_exits_74_naming_it(tmp_path, capsys, command):
    blocker = tmp_path / "not-a-directory"
    blocker.write_text("")
    db = blocker / "state.sqlite"
    argv = [command, "--db", str(db), "--connect", "tcp/127.0.0.1:1", "--log-level", "warning"]
    assert cli.main(argv) == cli.EXIT_IO
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith(f"trackfusion {command}: ")
    assert str(blocker) in err
