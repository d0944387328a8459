"""The supervision rules of `trackfusion up` on their own: restart policies, backoff, the
token watch and stalled flows, with a stand-in process and the clock as an argument."""

from __future__ import annotations

import signal
from pathlib import Path

import json5
import pytest

from schemas import Alert, encode
from services.defaults import DEMO_NETWORK
from services.tools.stack import (
    TRAIN_SEEN_S,
    Child,
    Flow,
    ProcessSpec,
    Stack,
    StatusBoard,
    Supervision,
    backoff_s,
    load_stack,
    network_segments,
)


class FakeProcess:
    """What :class:`Child` uses of a ``subprocess.Popen``."""

    def __init__(self, pid: int = 4242) -> None:
        self.pid = pid
        self.returncode: int | None = None
        self.signals: list[int] = []

    def poll(self) -> int | None:
        return self.returncode

    def send_signal(self, signum: int) -> None:
        self.signals.append(signum)


def running_child(tmp_path: Path, restart: str = "always", **supervision: float) -> Child:
    spec = ProcessSpec("svc", "ingestion", ("--instance", "svc"), restart)
    stack = Stack("ns", "tcp/127.0.0.1:1", tmp_path, (spec,), Supervision(**supervision))
    child = Child(stack, spec, env={})
    child.popen = FakeProcess()  # type: ignore[assignment]
    child.started_at = 0.0
    return child


def test_backoff_doubles_up_to_the_cap():
    settings = Supervision()
    assert [backoff_s(n, settings) for n in range(8)] == [1, 2, 4, 8, 16, 32, 60, 60]
    assert backoff_s(10_000, settings) == 60


def test_stack_file_defaults_and_errors(tmp_path):
    path = tmp_path / "stack.json5"
    stack = {
        "router": {"listen": "tcp/127.0.0.1:1"},
        "processes": [
            {"name": "filtering"},
            {"name": "world", "command": "simulate"},
            {"name": "once", "command": "simulate", "restart": "never"},
        ],
    }
    path.write_text(json5.dumps(stack))
    loaded = load_stack(path)
    assert [p.restart for p in loaded.processes] == ["always", "on-failure", "never"]
    assert loaded.supervision == Supervision()
    assert (Supervision().token_missing_s, Supervision().stalled_state_s) == (15, 30)

    for broken in (
        {**stack, "processes": [{"name": "x", "restart": "sometimes"}]},
        {**stack, "supervision": {"token_missing": 1}},  # a misspelt setting
        {**stack, "supervision": {"token_missing_s": 0}},
    ):
        path.write_text(json5.dumps(broken))
        with pytest.raises(ValueError, match="not a valid stack file"):
            load_stack(path)


@pytest.mark.parametrize(
    ("restart", "code", "restarted"),
    [
        ("always", 0, True),
        ("always", 1, True),
        ("always", -9, True),
        ("on-failure", 0, False),
        ("on-failure", 2, True),
        ("on-failure", -9, True),
        ("never", 1, False),
    ],
)
def test_an_exit_is_restarted_per_policy(tmp_path, restart, code, restarted):
    child = running_child(tmp_path, restart)
    child.popen.returncode = code
    child.step(10.0, alive=set())
    assert child.last_exit == code
    assert (child.next_start is not None) == restarted
    assert child.finished == (not restarted)
    if restarted:
        assert child.next_start == 11.0  # the first delay


def test_quick_failures_back_off_and_a_long_run_resets_it(tmp_path):
    child = running_child(tmp_path, backoff_reset_s=100)
    delays = []
    for run in range(4):
        child.popen = FakeProcess()
        child.started_at, child.next_start = run * 1000.0, None
        child.popen.returncode = 1
        ended = child.started_at + 5  # a quick failure
        child.step(ended, alive=set())
        delays.append(child.next_start - ended)
    assert delays == [1, 2, 4, 8]
    child.popen, child.started_at, child.next_start = FakeProcess(), 9000.0, None
    child.popen.returncode = 1
    child.step(9200.0, alive=set())  # ran 200 s >= backoff_reset_s
    assert child.next_start - 9200.0 == 1


def test_a_token_gone_too_long_stops_the_process_then_restarts_it(tmp_path):
    child = running_child(tmp_path, token_missing_s=15, stop_grace_s=5)
    child.step(0.0, alive=set())  # not seen yet: starting, nothing happens however long
    child.step(100.0, alive=set())
    assert child.popen.signals == []
    child.step(101.0, alive={"svc"})
    child.step(102.0, alive=set())  # gone
    child.step(117.0, alive=set())  # 15 s: not more than 15
    assert child.popen.signals == []
    child.step(117.5, alive=set())
    assert child.popen.signals == [signal.SIGTERM, signal.SIGCONT]
    assert child.reason == "liveliness token missing for 16 s"
    child.popen.returncode = 0  # it obeyed; a clean exit, restarted all the same
    child.step(118.0, alive=set())
    assert child.next_start == 119.0 and not child.finished


def test_a_token_back_in_time_is_no_restart(tmp_path):
    child = running_child(tmp_path, token_missing_s=15)
    child.step(1.0, alive={"svc"})
    child.step(2.0, alive=set())
    child.step(10.0, alive={"svc"})  # a reconnect
    child.step(30.0, alive={"svc"})
    assert child.popen.signals == [] and child.token_missing_since is None


def test_never_is_not_stopped_for_a_missing_token(tmp_path):
    child = running_child(tmp_path, "never", token_missing_s=1)
    child.step(1.0, alive={"svc"})
    child.step(2.0, alive=set())
    child.step(60.0, alive=set())
    assert child.popen.signals == []


def test_a_flow_is_stalled_when_input_comes_and_output_does_not():
    flow = Flow("index", "state", after_s=30)
    flow.update(0.0, source_arrived=True, result_arrived=False)
    assert not flow.stalled(0.0)  # just started: give it the window
    for t in range(1, 30):
        flow.update(float(t), source_arrived=True, result_arrived=False)
    assert not flow.stalled(29.0)
    flow.update(30.0, source_arrived=True, result_arrived=False)
    assert flow.stalled(30.0)
    assert flow.text(30.0) == "index arriving but no state published for 30 s"
    flow.update(31.0, source_arrived=True, result_arrived=True)
    assert not flow.stalled(31.0)


def test_a_flow_that_stopped_arriving_is_not_stalled():
    flow = Flow("gps", "index", after_s=60)
    flow.update(0.0, source_arrived=True, result_arrived=False)
    assert flow.stalled(60.0)
    assert not flow.stalled(61.0)  # nothing arriving: nothing stuck
    flow.update(62.0, source_arrived=False, result_arrived=False)
    assert "no index made for" in flow.text(62.0)


def test_health_of_a_child_through_its_runs(tmp_path, monkeypatch):
    started: list[FakeProcess] = []
    monkeypatch.setattr(
        "services.tools.stack.subprocess.Popen",
        lambda *a, **kw: started.append(FakeProcess(43)) or started[-1],
    )
    child = running_child(tmp_path, "on-failure")
    assert child.health(1.0, alive=set())["state"] == "starting"
    child.step(1.0, alive={"svc"})
    health = child.health(3.0, alive={"svc"})
    assert (health["state"], health["alive"], health["uptime_s"]) == ("running", True, 3.0)
    child.popen.returncode = -signal.SIGKILL
    child.step(4.0, alive=set())
    health = child.health(4.5, alive=set())
    assert (health["state"], health["running"], health["next_start_in_s"]) == (
        "waiting",
        False,
        0.5,
    )
    assert health["last_restart_reason"] == "exited with SIGKILL after 4 s"
    child.step(5.0, alive=set())
    assert child.popen is started[0] and child.restarts == 1
    assert "restarted by up: exited with SIGKILL after 4 s" in (tmp_path / "svc.log").read_text()
    child.popen.returncode = 0
    child.step(6.0, alive=set())
    health = child.health(6.0, alive=set())
    assert (health["state"], health["last_exit"], health["uptime_s"]) == ("finished", 0, None)


class FakeSample:
    """What :meth:`StatusBoard.on_sample` reads of a ``zenoh.Sample``."""

    def __init__(self, key: str, payload: bytes = b"") -> None:
        self.key_expr, self._payload = key, payload
        self.payload = self

    def to_bytes(self) -> bytes:
        return self._payload


def test_the_board_counts_only_the_segments_of_its_network():
    board = StatusBoard(frozenset({"L1/s1", "L1/s2"}))
    for key in ("ns/state/L1/s1", "ns/state/L1/s9", "ns/state/NOLINE/s1", "ns/state/L1/s2"):
        board.on_sample(FakeSample(key))  # type: ignore[arg-type]
    assert board.totals() == (0, 2, 0)
    assert board.snapshot()["state"] == 4  # every message still counts in the rates


def test_a_train_counts_until_its_last_fix_is_older_than_the_window():
    now = [0.0]
    board = StatusBoard(clock=lambda: now[0])
    board.on_sample(FakeSample("ns/gps/T1"))  # type: ignore[arg-type]
    now[0] = 200.0
    board.on_sample(FakeSample("ns/gps/T2"))  # type: ignore[arg-type]
    assert board.totals()[0] == 2
    now[0] = TRAIN_SEEN_S + 1.0  # T1 silent for longer than the window: forgotten
    assert board.totals()[0] == 1 and set(board.trains) == {"T2"}
    board.on_sample(FakeSample("ns/gps/T1"))  # type: ignore[arg-type]
    assert board.totals()[0] == 2


def test_the_stack_names_the_network_its_processes_use(tmp_path):
    assert load_stack().network == str(DEMO_NETWORK)
    assert network_segments(load_stack().network) >= {"L1/s00001", "L2/s00003"}
    other = tmp_path / "net.geojson"
    assert load_stack(network=other).network == str(other.absolute())
    bare = tmp_path / "stack.json5"
    bare.write_text('{router: {listen: "tcp/127.0.0.1:7447"}, processes: [{name: "viewer"}]}')
    assert load_stack(bare).network is None and network_segments(None) is None
    with pytest.raises(ValueError, match="--network"):
        network_segments(str(other))  # no such file: what to fix


def test_the_board_counts_in_callbacks_and_decodes_alerts_later():
    board = StatusBoard()

    def alert(status: str) -> FakeSample:
        message = Alert(
            line="L1", segment="s1", t=1.767e9, kind="stale", status=status, indicator=""
        )
        return FakeSample("ns/alert/L1/s1", encode(message))

    for sample in (
        FakeSample("ns/state/L1/s1"),
        FakeSample("ns/state/L1/s2"),
        FakeSample("ns/gps/T7"),
        alert("raised"),
        FakeSample("ns/alert/L1/s2", b"not an alert"),
    ):
        board.on_sample(sample)  # type: ignore[arg-type]
    assert board.totals() == (1, 2, 0)  # alerts wait for the main loop
    board.take_alerts()
    assert board.totals() == (1, 2, 1)
    board.on_sample(alert("cleared"))  # type: ignore[arg-type]
    board.take_alerts()
    assert board.totals() == (1, 2, 0)
    assert board.snapshot() == {"state": 2, "gps": 1, "alert": 3}
