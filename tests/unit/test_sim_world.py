"""The merged simulator stream: deterministic bytes, every message decodes, both fidelities."""

from __future__ import annotations

import hashlib

import numpy as np
import pytest

from schemas import (
    DAY_S,
    GpsFix,
    MaintenanceEvent,
    OnboardIndex,
    RawChunk,
    TrcRecord,
    decode,
    keys,
)
from services.defaults import demo_network
from simulators.gateway import key_and_payload
from simulators.truth import load_config
from simulators.world import WorldSpec, world_events

START = 1_767_225_600.0  # 2026-01-01T00:00:00Z
KINDS = {
    "raw": RawChunk,
    "gps": GpsFix,
    "index": OnboardIndex,
    "trc": TrcRecord,
    "maintenance": MaintenanceEvent,
}


def _spec(fidelity: str, seed: int = 3) -> WorldSpec:
    # small worlds that still hold every kind: 20 days see TRC runs and tampings (seed 3)
    days = 20.0 if fidelity == "index" else 8 / DAY_S
    trains = 1 if fidelity == "index" else 3
    return WorldSpec(demo_network(), load_config(), START, days, seed, trains, fidelity)


def _published(spec: WorldSpec) -> list[tuple[float, str, bytes]]:
    return [
        (t, *key_and_payload("tf", message))
        for t, messages in world_events(spec)
        for message in messages
    ]


def _digest(published) -> str:
    h = hashlib.sha256()
    for t, key, payload in published:
        h.update(f"{t!r} {key} ".encode() + payload)
    return h.hexdigest()


@pytest.mark.parametrize("fidelity", ["index", "raw"])
def test_same_seed_same_bytes_other_seed_other_bytes(fidelity):
    first = _published(_spec(fidelity))
    assert first, "the world published nothing"
    assert _digest(first) == _digest(_published(_spec(fidelity)))
    assert _digest(first) != _digest(_published(_spec(fidelity, seed=4)))


@pytest.mark.parametrize("fidelity", ["index", "raw"])
def test_every_published_message_decodes_on_its_key(fidelity):
    published = _published(_spec(fidelity))
    seen = set()
    times = [t for t, _, _ in published]
    assert times == sorted(times), "events are not in time order"
    for _, key, payload in published:
        kind = keys.kind(key)
        message = decode(payload, KINDS[kind])  # raises SchemaError if the payload is bad
        seen.add(kind)
        assert key == keys.key_of("tf", message)
    expected = {"index", "trc", "maintenance"} if fidelity == "index" else {"raw", "gps"}
    assert expected <= seen, seen


def test_raw_chunks_follow_each_other_per_unit():
    chunks = [
        decode(payload, RawChunk)
        for _, key, payload in _published(_spec("raw"))
        if keys.kind(key) == "raw"
    ]
    by_unit: dict[tuple[str, str], list[RawChunk]] = {}
    for chunk in chunks:
        by_unit.setdefault((chunk.train, chunk.unit), []).append(chunk)
    assert len(by_unit) == 3
    for series in by_unit.values():
        seqs = [c.seq for c in series]
        assert seqs == sorted(seqs) and len(set(seqs)) == len(seqs)
        for c in series:
            assert c.samples.shape == [2000, 7] and c.rate_hz == 2000.0
            assert c.t0 == pytest.approx(START + c.seq)


def test_bad_world_spec_is_refused():
    with pytest.raises(ValueError, match="fidelity"):
        WorldSpec(demo_network(), load_config(), START, 1.0, 1, 1, "video")


def _lakeside(running: str | None):
    import json
    from pathlib import Path

    from track.osm import import_osm

    path = Path(__file__).parents[1] / "fixtures" / "osm" / "lakeside.geojson"
    return import_osm(json.loads(path.read_text()), running=running)[0]


def test_raw_trains_on_a_one_way_track_send_only_while_running_its_way():
    """On the double track imported with left-hand running 650-t1 runs west (decreasing
    chainage), 650-t2 east; trains T000, T001 run on them, T002 on the single-track
    branch, both ways."""
    from simulators.world import raw_train_events

    network = _lakeside("left")
    spec = WorldSpec(network, load_config(), START, 1500 / DAY_S, 3, 3, "raw")
    fixes: dict[str, list[float]] = {"T000": [], "T001": [], "T002": []}
    for _, messages in raw_train_events(spec):
        for m in messages:
            if isinstance(m, GpsFix) and m.fix_quality and m.hdop < 2:  # not near a portal
                lon_lat = [m.lon_deg, m.lat_deg]
                fixes[m.train].append(network.to_xy(lon_lat))
    lines = {"T000": "650-t1", "T001": "650-t2", "T002": "651"}
    for train, xy in fixes.items():
        chain = network.lines[lines[train]].project(np.array(xy))[0]
        step = np.diff(chain)
        moving = np.abs(step) > 8.0  # beyond GPS noise, and no silence jump (> 1 km)
        trip = moving & (np.abs(step) < 1_000.0)
        signs = set(np.sign(step[trip]).astype(int).tolist())
        running = network.lines[lines[train]].running
        want = {"increasing": {1}, "decreasing": {-1}, "both": {-1, 1}}[running]
        assert signs == want, (train, running, signs)
    # the silences: the one-way trains send fewer fixes than the branch's train
    assert len(fixes["T000"]) < 1400 and len(fixes["T001"]) < 1400


def test_index_passes_on_a_one_way_track_all_run_its_way():
    from simulators.truth import Truth
    from simulators.world import index_pass_events

    network = _lakeside("left")
    config = load_config()
    truth = Truth(network, config, START, 3)
    order: dict[tuple[str, str], list[float]] = {}
    for _, messages in index_pass_events(network, truth, 4, 1.0, 3, config=config):
        for m in messages:
            line = network.lines[m.line]
            mid = next(s.mid_m for s in line.segments if s.id == m.segment)
            order.setdefault((m.line, m.train), []).append(mid)
    for (line_id, train), mids in order.items():
        step = np.sign(np.diff(mids))
        running = network.lines[line_id].running
        if running == "increasing":
            assert (step > 0).all(), train
        elif running == "decreasing":
            assert (step < 0).all(), train
    branch = [np.sign(np.diff(m))[0] for (line_id, _), m in order.items() if line_id == "651"]
    assert set(branch) == {-1.0, 1.0}  # both ways on single track
