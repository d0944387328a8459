"""Without ``--db`` and ``--instance`` every service with a store opens one stable file,
``./var/{service}-default.sqlite``, so a restart finds what the previous run stored (a
file named after hostname-pid would start every restart on an empty store)."""

from __future__ import annotations

import dataclasses
import threading
from collections.abc import Callable
from pathlib import Path

import pytest

from services.alerting import service as alerting
from services.calibration import service as calibration
from services.calibration.store import SqliteStore
from services.defaults import default_file
from services.filtering import service as filtering
from services.runtime.config import RuntimeConfig


def _run_calibration(conf: RuntimeConfig, stop: threading.Event, **options: object) -> int:
    settings = calibration.settings_from(
        conf.options("calibration", calibration.OPTIONS), db=None, **options
    )
    return calibration.main(conf, settings, stop_event=stop, handle_signals=False)


MAINS: dict[str, Callable[..., int]] = {
    "calibration": _run_calibration,
    "filtering": lambda conf, stop: filtering.main(conf, stop=stop, handle_signals=False),
    "alerting": lambda conf, stop: alerting.main(conf, stop=stop, handle_signals=False),
}


def _stopped() -> threading.Event:
    stop = threading.Event()
    stop.set()  # announce, then leave at once
    return stop


def _files(tmp_path: Path) -> list[str]:
    return sorted(p.name for p in (tmp_path / "var").glob("*.sqlite"))


@pytest.mark.parametrize("service", sorted(MAINS))
def test_a_service_without_db_or_instance_reopens_one_file(
    service, service_config, tmp_path, monkeypatch
):
    monkeypatch.chdir(tmp_path)
    conf = dataclasses.replace(service_config, instance=None)
    for _ in range(2):  # a start and a restart (another pid)
        assert MAINS[service](conf, _stopped()) == 0
    assert _files(tmp_path) == [f"{service}-default.sqlite"]


def test_calibration_restarted_without_db_has_the_models_it_stored(
    service_config, tmp_path, monkeypatch
):
    monkeypatch.chdir(tmp_path)
    conf = dataclasses.replace(service_config, instance=None)
    initial = default_file("initial-models.json5")
    assert _run_calibration(conf, _stopped(), initial_models=initial) == 0
    assert _run_calibration(conf, _stopped()) == 0  # no initial models this time
    store = SqliteStore(tmp_path / "var" / "calibration-default.sqlite")
    try:
        assert store.load().models, "the restart's store holds no model"
    finally:
        store.close()
    assert _files(tmp_path) == ["calibration-default.sqlite"]
