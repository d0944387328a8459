"""`trackfusion up` supervises its children: a killed child is started again, a child whose
liveliness token is gone (a hung process) is stopped and started again, a simulator that
has finished its world is left alone, and a stalled flow is flagged; all of it shows in
``{state_dir}/health.json``. Small stacks with short thresholds (the stack file's
``supervision`` section) keep these tests quick."""

from __future__ import annotations

import contextlib
import os
import signal
from collections.abc import Callable

import pytest
import zenoh

from schemas import StackHealth, decode, keys

START_S = 60.0  # upper bound for processes to start on two loaded cores
POLL_S = 0.2


def alive(name: str) -> Callable[[dict], bool]:
    return lambda h: h["processes"][name]["alive"]


def test_a_killed_child_is_started_again_and_its_token_comes_back(up, liveliness_events, collector):
    stack = up([{"name": "ingestion", "args": ["--instance", "ingestion"]}])
    first = stack.until(alive("ingestion"))["processes"]["ingestion"]
    with stack.client() as session:
        events = liveliness_events(session, keys.alive(stack.ns, "ingestion", "ingestion"))
        assert events.get(START_S)[0] == zenoh.SampleKind.PUT
        os.kill(first["pid"], signal.SIGKILL)
        assert events.get(START_S)[0] == zenoh.SampleKind.DELETE
        assert events.get(START_S)[0] == zenoh.SampleKind.PUT  # the new process's

    health = stack.until(
        lambda h: alive("ingestion")(h) and h["processes"]["ingestion"]["restarts"]
    )
    now = health["processes"]["ingestion"]
    assert now["pid"] != first["pid"] and now["restarts"] == 1
    assert now["last_exit"] == -signal.SIGKILL and "SIGKILL" in now["last_restart_reason"]
    child_log = (stack.state_dir / "ingestion.log").read_text()
    assert "restarted by up: exited with SIGKILL" in child_log
    assert "ingestion: restart 1 (exited with SIGKILL" in stack.process.log_path.read_text()
    # the same report on the bus, for the viewer's health board
    with stack.client() as session:
        reports = collector(lambda sample: decode(sample.payload.to_bytes(), StackHealth))
        subscriber = session.declare_subscriber(keys.stack_health(stack.ns), reports)
        report = reports.get(START_S)
        subscriber.undeclare()
    (ingestion,) = report.processes
    assert (ingestion.name, ingestion.alive, ingestion.restarts) == ("ingestion", True, 1)
    assert "SIGKILL" in ingestion.last_restart_reason and report.healthy


def test_a_child_whose_token_is_gone_is_stopped_and_started_again(up, liveliness_events):
    """SIGSTOP: the process runs but answers nothing; its token goes when the router's
    lease on it expires (10 s), and `up` acts ``token_missing_s`` later."""
    stack = up(
        [{"name": "ingestion", "args": []}],  # no --instance: the token is {hostname}-{pid}
        token_missing_s=2,
        stop_grace_s=3,
    )
    first = stack.until(alive("ingestion"))["processes"]["ingestion"]
    os.kill(first["pid"], signal.SIGSTOP)
    try:
        gone = stack.until(lambda h: not h["processes"]["ingestion"]["alive"], timeout=30)
        assert gone["processes"]["ingestion"]["pid"] == first["pid"]
        health = stack.until(
            lambda h: alive("ingestion")(h) and h["processes"]["ingestion"]["restarts"]
        )
    finally:
        with contextlib.suppress(ProcessLookupError):  # if `up` has not: it would stay deaf
            os.kill(first["pid"], signal.SIGCONT)
    now = health["processes"]["ingestion"]
    assert now["pid"] != first["pid"] and now["restarts"] == 1
    assert now["last_restart_reason"].startswith("liveliness token missing for")
    with pytest.raises(ProcessLookupError):
        os.kill(first["pid"], 0)  # the hung process is gone, not left behind
    assert (
        "restarted by up: liveliness token missing"
        in (stack.state_dir / "ingestion.log").read_text()
    )


def test_a_finished_simulator_is_left_alone_and_a_failing_one_is_restarted(up):
    simulate = ["--fidelity", "index", "--trains", "1", "--speedup", "inf", "--no-progress"]
    stack = up(
        [
            {"name": "world", "command": "simulate", "args": [*simulate, "--days", "0.05"]},
            {
                "name": "broken",
                "command": "simulate",
                "args": [*simulate, "--network", "/nonexistent/network.geojson"],
            },
        ],
        backoff_initial_s=0.5,
    )
    finished = stack.until(lambda h: h["processes"]["world"]["state"] == "finished", timeout=90)
    # Three more seconds (six times the restart delay) and the broken one's second restart.
    then = finished["up"]["uptime_s"] + 3
    health = stack.until(
        lambda h: h["up"]["uptime_s"] >= then and h["processes"]["broken"]["restarts"] >= 2,
        timeout=90,
    )
    world, broken = health["processes"]["world"], health["processes"]["broken"]
    assert world["state"] == "finished" and world["last_exit"] == 0, world
    assert world["restarts"] == 0 and not world["running"]
    assert broken["last_exit"] == 2 and broken["restart"] == "on-failure"  # a bad --network
    assert not health["healthy"]  # broken does not hold its token
    assert "restarted by up" not in (stack.state_dir / "world.log").read_text()


def test_indices_without_states_are_flagged_stalled(up):
    stack = up([], stalled_state_s=1.5)
    stack.until(lambda h: h["up"]["running"])
    index_key = keys.index(stack.ns, "L1", "s00001")
    with stack.client() as session:
        publisher = session.declare_publisher(index_key)

        def stalled(h: dict) -> bool:
            publisher.put(b"index")  # the flow keeps coming while nothing comes out of it
            return bool(h["stalled"])

        health = stack.until(stalled, timeout=30)
        assert health["stalled"][0].startswith("index arriving but no state published for")
        assert [f["stalled"] for f in health["flows"]] == [True, False]
        assert not health["healthy"]

        def board_says_stalled() -> bool:
            publisher.put(b"index")
            return (
                "STALLED: index arriving but no state published"
                in stack.process.log_path.read_text()
            )

        # the board is printed every 5 s when not a terminal
        stack.process.until(board_says_stalled, 30, "the board showing the stall", poll_s=POLL_S)

        session.put(keys.state(stack.ns, "L1", "s00001"), b"state")
        health = stack.until(lambda h: not h["stalled"], timeout=10)
        assert health["flows"][0]["waiting_s"] is None
        publisher.undeclare()
