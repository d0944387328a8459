"""Scale-out as real processes through a real router: one filtering instance owns the whole
network (``--selector '**'``), two more split it by key expression (``L1/**`` and
``L2/**``; a selector is ONE key-expression suffix, so each split instance owns one line of
a two-line network). A fast-mode simulator run feeds all three at once; when every instance
is drained, the union of the split instances' states equals the single instance's, byte
for byte, and the split instances' key sets are disjoint.
"""

from __future__ import annotations

import signal

import zenoh
from support import wait_for

from schemas import SegmentState, decode, keys
from services.filtering.testing import LastEvents, states_by_instance

WAIT_S = 45.0  # the whole run takes ~15 s on a loaded 2-core machine
DAYS = 70
SELECTORS = {"all": "**", "L1": "L1/**", "L2": "L2/**"}


def lines_of(states: dict[str, bytes]) -> frozenset[str]:
    return frozenset(keys.parse_q_state(key)[0] for key in states)


def settled(
    session: zenoh.Session, ns: str, last: LastEvents
) -> tuple[dict[str, bytes], dict[str, dict[str, bytes]]]:
    """Wait until the three instances are drained (each state at the newest event of its
    segment) and the split instances' union equals the single instance's states (the
    models have settled everywhere); returns (single, {line: split instance's states})."""
    status = "no replies"
    found: tuple[dict[str, bytes], dict[str, dict[str, bytes]]] | None = None

    def poll() -> bool:
        nonlocal status, found
        seen = last.snapshot()
        replies = list(states_by_instance(session, ns).values())
        whole = [s for s in replies if lines_of(s) == {"L1", "L2"}]
        split = {next(iter(lines_of(s))): s for s in replies if len(lines_of(s)) == 1}
        behind = sum(
            decode(payload, SegmentState).t != seen.get(keys.parse_q_state(key))
            for states in replies
            for key, payload in states.items()
        )
        status = (
            f"{len(replies)} repliers with {[len(s) for s in replies]} states, "
            f"{behind} behind the newest event, {len(seen)} segments seen on the bus"
        )
        if len(replies) == 3 and len(whole) == 1 and set(split) == {"L1", "L2"} and not behind:
            union = {**split["L1"], **split["L2"]}
            if union == whole[0] and len(whole[0]) == len(seen):
                found = whole[0], split
                return True
            status += f"; union differs from the single instance on {len(union)} keys"
        return False

    wait_for(poll, WAIT_S, lambda: f"not settled: {status}", poll_s=0.25)
    assert found is not None
    return found


def test_split_instances_equal_one_instance(namespace, fast_mode_world, spawn, tmp_path):
    network, wiring, session, last, alive = fast_mode_world(2, 3.0, seed=5)
    filtering = {
        name: spawn(
            f"filtering-{name}",
            "filtering",
            "--selector",
            selector,
            "--db",
            str(tmp_path / f"filtering-{name}.sqlite"),
            "--instance",
            f"f{name}",
            *wiring,
        )
        for name, selector in SELECTORS.items()
    }
    alive.until_alive(
        keys.alive(namespace, "calibration", "cal"),
        *(keys.alive(namespace, "filtering", f"f{name}") for name in filtering),
        timeout=30,
    )

    world = ["--network", str(network), "--days", str(DAYS), "--trains", "2", "--seed", "2"]
    simulate = spawn(
        "simulate",
        "simulate",
        "--fidelity",
        "index",
        *world,
        "--speedup",
        "inf",
        "--no-progress",
        *wiring,
    )
    assert simulate.wait(60) == 0, simulate.log()

    whole, split = settled(session, namespace, last)
    assert not set(split["L1"]) & set(split["L2"])  # each segment has exactly one owner
    assert all(lines_of(s) == {line} for line, s in split.items())
    assert {**split["L1"], **split["L2"]} == whole  # byte for byte
    assert len(whole) >= 25  # both 3 km lines have states (15 segments of 200 m each)
    states = [decode(p, SegmentState) for p in whole.values()]
    assert all(s.calibration_version >= 1 for s in states)
    for process in filtering.values():
        process.signal(signal.SIGTERM)
        assert process.wait(10) == 0, process.log()
