"""Real processes: kills during a flood on more keys than any per-key cache could hold,
then every segment's final state compared with an undisturbed fold of the same messages.

The producer (``outbox_producer.py``) publishes models, a TRC record and two on-board
indices for each of 3,000 segments through its outbox. During the flood it is SIGKILLed
and started again on its outbox (it publishes everything again: repeats), and filtering is
SIGKILLed twice and started again on its store. Whatever a process missed while it was
down reaches it by the replay, so every segment ends on the state the filtering core
computes from the same messages in one undisturbed pass, byte for byte.
"""

from __future__ import annotations

import signal
import sys
import threading
from pathlib import Path

import zenoh
from outbox_producer import flood

from schemas import SegmentState, decode, encode, keys
from services.filtering.tracker import Tracker
from services.limits import load_limits
from services.runtime.config import zenoh_config

READY_S = 60.0
SEGMENTS, PASSES = 3000, 2  # 9,000 events on 3,000 keys of each kind
FOLD_S = 150.0
PRODUCER = Path(__file__).with_name("outbox_producer.py")


def undisturbed(ns: str) -> dict[str, bytes]:
    """``{segment: encoded final state}`` of the flood folded in order by one tracker."""
    limits = load_limits()
    tracker = Tracker(limits.for_line, limits.levels)
    final: dict[str, bytes] = {}
    for _key, message in flood(ns, SEGMENTS, PASSES):
        for state in tracker.step(message).states:
            final[state.segment] = encode(state)
    return final


def test_kills_during_a_flood_change_no_final_state(
    stack, spawn, tmp_path, free_port, namespace, liveliness_events
):
    endpoint = f"tcp/127.0.0.1:{free_port}"
    spawn("router", "router", "--listen", endpoint)
    settings = {"connect": {"endpoints": [endpoint], "timeout_ms": int(READY_S * 1000)}}
    session = stack.enter_context(zenoh.open(zenoh_config(settings)))
    alive_key = keys.alive(namespace, "filtering", "durable")
    alive = liveliness_events(session, alive_key)
    config = tmp_path / "filtering.json5"
    config.write_text("{services: {delivery: {replay_s: 1}}}")
    folded: dict[str, int] = {}  # segment -> n_updates of its newest state
    lock = threading.Lock()
    reached = {n: threading.Event() for n in (SEGMENTS // 3, 2 * SEGMENTS // 3)}
    done = threading.Event()

    def on_state(sample: zenoh.Sample) -> None:
        state = decode(sample.payload.to_bytes(), SegmentState)
        with lock:
            folded[state.segment] = max(folded.get(state.segment, 0), state.n_updates)
            with_states = len(folded)
            if with_states == SEGMENTS and min(folded.values()) == PASSES:
                done.set()
        for n, event in reached.items():
            if with_states >= n:
                event.set()

    subscriber = session.declare_subscriber(keys.segment_keys(namespace, "state"), on_state)
    stack.callback(subscriber.undeclare)

    def start_filtering():
        process = spawn(
            "filtering",
            *("filtering", "--connect", endpoint, "--ns", namespace, "--instance", "durable"),
            *("--db", str(tmp_path / "filtering.sqlite"), "--config", str(config)),
        )
        assert alive.get(READY_S) == (zenoh.SampleKind.PUT, alive_key), process.log()
        return process

    def start_producer():
        argv = [sys.executable, str(PRODUCER), endpoint, namespace, str(tmp_path / "outbox")]
        return spawn("producer", argv=[*argv, str(SEGMENTS), str(PASSES)])

    filtering = start_filtering()
    producer = start_producer()
    assert producer.line(READY_S) == "half", producer.log()
    producer.signal(signal.SIGKILL)  # half the flood recorded, part of it put
    producer.wait(READY_S)
    producer = start_producer()  # on its outbox: the same flood again, numbered on
    for event in reached.values():
        assert event.wait(FOLD_S), f"{len(folded)} segments with a state{filtering.log()}"
        filtering.signal(signal.SIGKILL)  # mid-flood: what it folded since its commit is lost
        filtering.wait(READY_S)
        assert alive.get(READY_S) == (zenoh.SampleKind.DELETE, alive_key)
        filtering = start_filtering()
    assert done.wait(FOLD_S), (
        f"{len(folded)} segments with a state, "
        f"{sum(n < PASSES for n in folded.values())} short of {PASSES} updates{filtering.log()}"
    )
    replies = session.get(keys.q_state_all(namespace), timeout=10)
    got = {
        keys.parse_q_state(str(r.ok.key_expr))[1]: r.ok.payload.to_bytes()
        for r in replies
        if r.ok is not None
    }
    want = undisturbed(namespace)
    differ = sorted(s for s in want if got.get(s) != want[s])
    assert not differ, f"{len(differ)} of {SEGMENTS} states differ, e.g. {differ[:5]}"
    assert producer.running, producer.log()
