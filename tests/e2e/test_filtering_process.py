"""Real processes: `trackfusion router` and `trackfusion filtering`; SIGKILL the filtering
process mid-run (before any checkpoint, then between committed events and the next
checkpoint), stop it cleanly (checkpoints), restart it on the same --db each time: the
final states equal an uninterrupted run."""

from __future__ import annotations

import queue
import signal
import sqlite3

import numpy as np
import zenoh

from schemas import (
    DAY_S,
    Calibration,
    DegradationPosterior,
    MaintenanceEvent,
    SegmentState,
    TrcRecord,
    encode,
    keys,
)
from services.filtering.testing import example_models, onboard_index, sample_state
from services.filtering.tracker import Tracker
from services.limits import load_limits
from services.runtime.config import zenoh_config

READY_S = 20.0  # interpreter start + imports on a loaded machine
WAIT_S = 20.0
T0 = 1_767_225_600.0
NS = 50
SEGMENTS = ("s1", "s2", "s3")


def models() -> list[Calibration | DegradationPosterior]:
    return example_models(NS, seed=7, z_plus_sd=0.05)


def history() -> tuple[list, list]:
    """Two phases of events on three L1 segments; phase 2 has a late index and duplicates."""
    rng = np.random.default_rng(8)
    before, after = [], []
    for seg in SEGMENTS:
        before.append(
            TrcRecord(line="L1", segment=seg, t=T0, top6_mm=3.0, align10_mm=2.4, run_id="r0")
        )
        for day in range(3, 60, 5):
            top6, align10 = np.exp(rng.normal([0.8, 0.5], 0.1)).tolist()
            msg = onboard_index("L1", seg, T0 + day * DAY_S, top6, align10, train=f"T{day % 3}")
            (before if day < 30 else after).append(msg)
        after.append(
            MaintenanceEvent(
                line="L1",
                segment=seg,
                event_id=f"tamp-{seg}",
                t_start=T0 + 40 * DAY_S,
                t_end=T0 + 44 * DAY_S,
            )
        )
    late = after.pop(len(after) // 2)  # arrives after later events of its segment
    return before, [*after, late, before[2], after[0]]  # plus two duplicates


def test_sigkill_and_restart_give_the_uninterrupted_states(
    stack, spawn, tmp_path, free_port, namespace, until_matched, liveliness_events
):
    endpoint = f"tcp/127.0.0.1:{free_port}"
    spawn("router", "router", "--listen", endpoint)
    filtering_args = (
        *("filtering", "--connect", endpoint, "--ns", namespace, "--instance", "e2e"),
        *("--db", str(tmp_path / "filtering.sqlite")),
    )
    settings = {"connect": {"endpoints": [endpoint], "timeout_ms": int(READY_S * 1000)}}
    session = stack.enter_context(zenoh.open(zenoh_config(settings)))

    # The test stands in for the calibration service: the latest models on a queryable.
    model_msgs = models()
    latest = [(keys.key_of(namespace, m), encode(m)) for m in model_msgs]

    def on_query(query: zenoh.Query) -> None:
        for key, payload in latest:
            if query.key_expr.intersects(zenoh.KeyExpr(key)):
                query.reply(key, payload)

    stack.callback(session.declare_queryable(keys.model_all(namespace), on_query).undeclare)
    states: queue.Queue[SegmentState] = queue.Queue()
    subscriber = session.declare_subscriber(
        keys.segment_keys(namespace, "state"),
        lambda s: states.put(sample_state(s)),
    )
    stack.callback(subscriber.undeclare)
    alive_key = keys.alive(namespace, "filtering", "e2e")
    alive = liveliness_events(session, alive_key)

    before, after = history()
    reference = Tracker(*_limits())
    for msg in model_msgs:
        reference.step(msg)

    def send_and_wait(messages, proc) -> None:
        """Publish, then wait until every segment's latest state is the reference's."""
        for msg in messages:
            reference.step(msg)
        want = {seg: encode(reference.state_of("L1", seg)) for seg in SEGMENTS}
        publishers: dict[str, zenoh.Publisher] = {}
        for msg in messages:
            key = keys.key_of(namespace, msg)
            if key not in publishers:
                publishers[key] = session.declare_publisher(key)
                until_matched(publishers[key], READY_S)
            publishers[key].put(encode(msg))
        for publisher in publishers.values():
            publisher.undeclare()
        got: dict[str, bytes] = {}
        while got != want:
            try:
                state = states.get(timeout=WAIT_S)
            except queue.Empty:
                raise AssertionError(f"states never matched{proc.log()}") from None
            got[state.segment] = encode(state)

    first = spawn("filtering", *filtering_args)
    assert alive.get(READY_S) == (zenoh.SampleKind.PUT, alive_key), first.log()
    send_and_wait(before, first)

    first.signal(signal.SIGKILL)  # mid-run: no chance to close anything
    assert first.wait(5) == -signal.SIGKILL
    assert alive.get(WAIT_S) == (zenoh.SampleKind.DELETE, alive_key)

    # replayed from the events (no checkpoint yet); a clean stop then checkpoints
    second = spawn("filtering", *filtering_args)
    assert alive.get(READY_S) == (zenoh.SampleKind.PUT, alive_key), second.log()
    split = len(after) // 2
    send_and_wait(after[:split], second)
    second.signal(signal.SIGTERM)
    assert second.wait(5) == 0, second.log()
    assert alive.get(WAIT_S) == (zenoh.SampleKind.DELETE, alive_key)
    with sqlite3.connect(tmp_path / "filtering.sqlite") as db:
        assert db.execute("SELECT COUNT(*) FROM checkpoints").fetchone()[0] == len(SEGMENTS)

    # from the checkpoints; the rest (a late index, duplicates) is committed, then SIGKILL
    # before the next checkpoint (CHECKPOINT_S): the restart folds on over those events
    third = spawn("filtering", *filtering_args)
    assert alive.get(READY_S) == (zenoh.SampleKind.PUT, alive_key), third.log()
    send_and_wait(after[split:], third)
    third.signal(signal.SIGKILL)
    assert third.wait(5) == -signal.SIGKILL
    assert alive.get(WAIT_S) == (zenoh.SampleKind.DELETE, alive_key)

    fourth = spawn("filtering", *filtering_args)
    assert alive.get(READY_S) == (zenoh.SampleKind.PUT, alive_key), fourth.log()
    replies = session.get(keys.q_state_all(namespace), timeout=5)
    queried = {str(r.ok.key_expr): r.ok.payload.to_bytes() for r in replies if r.ok is not None}
    assert queried == {
        keys.q_state(namespace, "L1", seg): encode(reference.state_of("L1", seg))
        for seg in SEGMENTS
    }
    fourth.signal(signal.SIGTERM)
    assert fourth.wait(5) == 0, fourth.log()


def _limits():
    limits = load_limits()
    return limits.for_line, limits.levels
