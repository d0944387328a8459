"""The checkpoint of a raw-chain stage: state and positions saved and loaded together."""

from __future__ import annotations

import pytest

from services.runtime.checkpoint import CheckpointBusy, CheckpointStore, dumps, fingerprint, loads


def test_state_and_positions_come_back_as_saved(tmp_path):
    store = CheckpointStore(tmp_path / "c.sqlite")
    assert store.load() is None
    store.save(b"one", "f1", {"gateway/a": ("e1", 7)})
    store.save(b"two", "f1", {"gateway/a": ("e1", 9), "gateway/b": ("e2", 3)})
    store.close()
    reopened = CheckpointStore(tmp_path / "c.sqlite")
    saved = reopened.load()
    reopened.close()
    assert (saved.state, saved.fingerprint) == (b"two", "f1")
    assert saved.positions == {"gateway/a": ("e1", 9), "gateway/b": ("e2", 3)}


def test_a_second_process_cannot_write_the_same_checkpoint(tmp_path):
    store = CheckpointStore(tmp_path / "c.sqlite")
    try:
        with pytest.raises(CheckpointBusy, match="held by another process"):
            CheckpointStore(tmp_path / "c.sqlite")
    finally:
        store.close()


def test_the_fingerprint_changes_with_the_network_and_the_configuration(tmp_path):
    network = tmp_path / "n.geojson"
    network.write_text('{"type": "FeatureCollection", "features": []}')
    base = fingerprint(network, {"a": 1})
    assert fingerprint(network, {"a": 2}) != base
    assert fingerprint(None, {"a": 1}) != base
    network.write_text('{"type": "FeatureCollection", "features": [ ]}')
    assert fingerprint(network, {"a": 1}) != base


def test_shared_objects_are_named_not_held():
    big = {"table": list(range(100_000))}
    state = {"rows": [1, 2, 3], "uses": big, "again": big}
    data = dumps(state, {"network": big})
    assert len(data) < 200  # the table is not in it
    other = {"table": [7]}
    back = loads(data, {"network": other})
    assert back["rows"] == [1, 2, 3]
    assert back["uses"] is other and back["again"] is other
