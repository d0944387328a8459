"""What the end-to-end tests share: a `trackfusion up` stack of their own, a fast-mode world
with calibration running, the signal chain as processes."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Any, NamedTuple

import json5
import pytest
import zenoh
from support import outbox_config

from schemas import keys
from services.filtering.testing import EVENT_TYPES, LastEvents
from services.runtime.config import zenoh_config
from simulators.network import generate_network

START_S = 60.0  # upper bound for processes to start on two loaded cores
POLL_S = 0.2


class Up:
    """A running `trackfusion up` on a stack of its own, and its health file."""

    def __init__(self, process, state_dir: Path, endpoint: str, ns: str) -> None:
        self.process, self.state_dir, self.endpoint, self.ns = process, state_dir, endpoint, ns

    def health(self) -> dict[str, Any] | None:
        try:
            return json.loads((self.state_dir / "health.json").read_text())
        except FileNotFoundError:
            return None

    def until(self, condition: Callable[[dict[str, Any]], bool], timeout: float = START_S) -> dict:
        """Poll the health file until ``condition`` holds; its last content otherwise fails."""
        health = None

        def met() -> dict | None:
            nonlocal health
            health = self.health()
            return health if health is not None and condition(health) else None

        return self.process.until(met, timeout, lambda: f"health: {health}", poll_s=POLL_S)

    def client(self) -> zenoh.Session:
        conf = {"mode": "client", "connect": {"endpoints": [self.endpoint], "timeout_ms": 60000}}
        return zenoh.open(zenoh_config(conf))


@pytest.fixture
def up(free_port, namespace, spawn, tmp_path) -> Callable[..., Up]:
    """``up(processes, *args, **supervision)``: `trackfusion up` (with ``args``) on a stack
    file of those processes, its state in ``tmp_path / "var"``."""

    def start(processes: list[dict], *args: str, **supervision: float) -> Up:
        endpoint = f"tcp/127.0.0.1:{free_port}"
        state_dir = tmp_path / "var"
        stack = {
            "ns": namespace,
            "router": {"listen": endpoint},
            "state_dir": str(state_dir),
            "supervision": supervision,
            "processes": processes,
        }
        stack_file = tmp_path / "stack.json5"
        stack_file.write_text(json5.dumps(stack))
        process = spawn("up", "up", "--stack", str(stack_file), "--log-level", "info", *args)
        return Up(process, state_dir, endpoint, namespace)

    return start


class FastModeWorld(NamedTuple):
    """A generated network file, the test's session hearing every event (``last``) and the
    services' liveliness tokens (``alive``), and calibration running on the initial models."""

    network: Path
    wiring: list[str]  # the flags that put a process on the test's router and namespace
    session: zenoh.Session
    last: LastEvents
    alive: Any


@pytest.fixture
def fast_mode_world(
    router, namespace, open_session, liveliness_events, spawn, tmp_path
) -> Callable[..., FastModeWorld]:
    """``fast_mode_world(lines, length_km, seed)``: see :class:`FastModeWorld`."""

    def start(lines: int, length_km: float, seed: int) -> FastModeWorld:
        network = tmp_path / "net.geojson"
        network.write_text(json.dumps(generate_network(lines, length_km, seed=seed).to_geojson()))
        wiring = ["--connect", router, "--ns", namespace]
        session = open_session()
        last = LastEvents()
        for kind in EVENT_TYPES:
            session.declare_subscriber(keys.segment_keys(namespace, kind), last)
        alive = liveliness_events(session, keys.alive_all(namespace))
        initial = "services/defaults/initial-models.json5"
        db = str(tmp_path / "calibration.sqlite")
        spawn("calibration", "calibration", "--db", db, "--initial-models", initial,
              "--instance", "cal", *wiring)  # fmt: skip
        return FastModeWorld(network, wiring, session, last, alive)

    return start


@pytest.fixture
def signal_chain(namespace, liveliness_events, spawn, tmp_path) -> Callable[..., tuple]:
    """``signal_chain(session, wiring)``: ingestion and extraction processes, once both are
    alive."""

    def start(session: zenoh.Session, wiring: list[str]) -> tuple:
        alive = liveliness_events(session, keys.alive_all(namespace))
        ingestion = spawn("ingestion", "ingestion", "--instance", "ing", *wiring)
        outboxes = ("--config", str(outbox_config(tmp_path)))
        extraction = spawn("extraction", "extraction", "--instance", "ext", *outboxes, *wiring)
        alive.until_alive(
            keys.alive(namespace, "ingestion", "ing"),
            keys.alive(namespace, "extraction", "ext"),
            timeout=START_S,
        )
        return ingestion, extraction

    return start
