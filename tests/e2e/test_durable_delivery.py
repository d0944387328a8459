"""Real processes: kills during a flood on more keys than any per-key cache could hold,
then every segment's final state compared with an undisturbed fold of the same messages.

The producer (``outbox_producer.py``) publishes, through its outbox, models and a TRC
record for each of 3,000 segments (phase 0), then two passes of on-board indices (phases 1
and 2). Filtering is SIGKILLed right after phase 0 went out (mid-fold); phase 1 is
published while it is down; the producer is then SIGKILLed too, and started again on its
outbox for phase 2 only; filtering, started again on its store, gets phase 1 from the
outbox of a producer that did not publish it, and is SIGKILLed once more during phase 2.
Every segment must end on the state the filtering core computes from the same messages in
one undisturbed pass, byte for byte.
"""

from __future__ import annotations

import signal
import sys
from pathlib import Path

import zenoh
from outbox_producer import flood

from schemas import encode, keys
from services.filtering.tracker import Tracker
from services.limits import load_limits
from services.runtime.config import zenoh_config
from tests.e2e.stacks import FoldProgress

READY_S = 60.0
SEGMENTS, PASSES = 3000, 2  # 9,000 events on 3,000 keys of each kind
FOLD_S = 150.0
PRODUCER = Path(__file__).with_name("outbox_producer.py")


def undisturbed(ns: str) -> dict[str, bytes]:
    """``{segment: encoded final state}`` of the flood folded in order by one tracker."""
    limits = load_limits()
    tracker = Tracker(limits.for_line, limits.levels)
    final: dict[str, bytes] = {}
    for _key, message in (m for phase in flood(ns, SEGMENTS, PASSES) for m in phase):
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
    progress = FoldProgress(SEGMENTS, PASSES)
    subscriber = session.declare_subscriber(keys.segment_keys(namespace, "state"), progress)
    stack.callback(subscriber.undeclare)

    def start_filtering():
        process = spawn(
            "filtering",
            *("filtering", "--connect", endpoint, "--ns", namespace, "--instance", "durable"),
            *("--db", str(tmp_path / "filtering.sqlite"), "--config", str(config)),
        )
        assert alive.get(READY_S) == (zenoh.SampleKind.PUT, alive_key), process.log()
        return process

    def kill_filtering(process) -> None:
        process.signal(signal.SIGKILL)
        process.wait(READY_S)
        assert alive.get(READY_S) == (zenoh.SampleKind.DELETE, alive_key)

    def start_producer(first: int):
        argv = [sys.executable, str(PRODUCER), endpoint, namespace, str(tmp_path / "outbox")]
        return spawn("producer", argv=[*argv, str(SEGMENTS), str(PASSES), str(first)])

    filtering = start_filtering()
    producer = start_producer(0)
    assert producer.line(READY_S) == "phase 0", producer.log()
    kill_filtering(filtering)  # mid-fold: what it had not committed is lost with it
    producer.signal(signal.SIGUSR1)
    assert producer.line(READY_S) == "phase 1", producer.log()  # nobody listening
    producer.signal(signal.SIGKILL)
    producer.wait(READY_S)
    filtering = start_filtering()
    producer = start_producer(2)  # on its outbox: phases 0 and 1 only there
    assert producer.line(READY_S) == "phase 2", producer.log()
    assert progress.indexed.wait(FOLD_S), filtering.log()
    kill_filtering(filtering)
    filtering = start_filtering()
    assert progress.done.wait(FOLD_S), (
        f"{len(progress.folded)} segments with a state, "
        f"{len(progress.short())} short of {PASSES} updates{filtering.log()}"
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
