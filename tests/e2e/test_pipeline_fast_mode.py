"""The live pipeline as real processes through a real router: simulator (fast mode) →
calibration → filtering → alerting. One filtering instance is SIGKILLed between two halves
of the simulated world and restarted on its SQLite file; a second instance runs
uninterrupted beside it. At the end both answer exactly the same states, byte for byte.
"""

from __future__ import annotations

import signal

import zenoh
from support import wait_for

from schemas import InspectionPlan, SegmentState, decode, keys
from services.filtering.testing import LastEvents, states_by_instance

WAIT_S = 90.0  # a loaded 2-core machine replays the whole half-world within this
DAYS, HALF = 100, 50


def disagreement(replies: dict[str, dict[str, bytes]], last: LastEvents) -> str:
    """What differs between the instances' states (for the failure message)."""
    seen = last.snapshot()
    lines = []
    for zid, states in replies.items():
        behind = [
            k
            for k, p in states.items()
            if decode(p, SegmentState).t != seen.get(keys.parse_q_state(k))
        ]
        lines.append(f"{zid}: {len(states)} states, {len(behind)} behind the newest event")
    if len(replies) == 2:
        a, b = replies.values()
        for key in sorted(set(a) & set(b)):
            if a[key] != b[key]:
                sa, sb = decode(a[key], SegmentState), decode(b[key], SegmentState)
                fields = [f for f in sa.__struct_fields__ if getattr(sa, f) != getattr(sb, f)]
                lines.append(f"{key} differs in {fields}")
                break
    return "; ".join(lines)


def drained(
    session, ns: str, last: LastEvents, instances: int, *, agree: bool
) -> dict[str, dict[str, bytes]]:
    """Wait until every instance's states are at the newest event of their segment (and,
    with ``agree``, the instances answer the same states: the models have settled too)."""
    replies: dict[str, dict[str, bytes]] = {}

    def poll() -> bool:
        nonlocal replies
        seen = last.snapshot()
        replies = states_by_instance(session, ns)
        caught_up = len(replies) == instances and all(
            len(states) > 0
            and all(
                decode(payload, SegmentState).t == seen.get(keys.parse_q_state(key))
                for key, payload in states.items()
            )
            for states in replies.values()
        )
        return caught_up and (
            not agree or len({frozenset(s.items()) for s in replies.values()}) == 1
        )

    wait_for(poll, WAIT_S, lambda: f"no agreement: {disagreement(replies, last)}", poll_s=0.25)
    return replies


def test_pipeline_survives_a_filtering_kill(namespace, fast_mode_world, spawn, tmp_path):
    network, wiring, session, last, alive = fast_mode_world(1, 6.0, seed=3)

    def start_filtering(name: str):
        db = str(tmp_path / f"{name}.sqlite")
        return spawn(name, "filtering", "--db", db, "--instance", name, *wiring)

    spawn("alerting", "alerting", "--db", str(tmp_path / "al.sqlite"), "--instance", "al", *wiring)
    killed, reference = start_filtering("A"), start_filtering("B")
    token_a = keys.alive(namespace, "filtering", "A")
    alive.until_alive(
        keys.alive(namespace, "calibration", "cal"),
        keys.alive(namespace, "alerting", "al"),
        token_a,
        keys.alive(namespace, "filtering", "B"),
        timeout=30,
    )

    def simulate(*days: str) -> None:
        world = ["--network", str(network), "--days", str(DAYS), "--trains", "2"]
        process = spawn("simulate", "simulate", *world, "--speedup", "inf", *days, *wiring)
        assert process.wait(120) == 0, process.log()

    simulate("--to-day", str(HALF))
    drained(session, namespace, last, instances=2, agree=False)  # A has committed it all

    killed.signal(signal.SIGKILL)
    killed.wait(10)
    assert alive.next_change(token_a, 30) == zenoh.SampleKind.DELETE  # token gone
    restarted = start_filtering("A")
    assert alive.next_change(token_a, 30) == zenoh.SampleKind.PUT

    simulate("--from-day", str(HALF))
    final = drained(session, namespace, last, instances=2, agree=True)
    a, b = final.values()
    assert a == b  # drained(agree=True) waited for it: the restarted A equals the reference B
    assert len(a) >= 25  # every segment of the 6 km line has a state
    states = [decode(p, SegmentState) for p in a.values()]
    assert all(s.calibration_version >= 1 for s in states)  # the fitted models are in use
    assert any(s.n_updates > 0 for s in states)  # on-board indices folded, not only TRC runs

    plan = [r for r in session.get(keys.q_plan(namespace), timeout=10) if r.ok is not None]
    assert plan and decode(plan[0].ok.payload.to_bytes(), InspectionPlan).rows
    for process in (restarted, reference):
        process.signal(signal.SIGTERM)
        assert process.wait(10) == 0, process.log()
