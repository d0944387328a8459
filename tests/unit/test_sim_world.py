"""The merged simulator stream: deterministic bytes, every message decodes, both fidelities."""

from __future__ import annotations

import hashlib

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
from simulators.gateway import key_and_payload
from simulators.truth import load_config
from simulators.world import WorldSpec, world_events
from track.network import demo_network

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
