"""Faults during a live run, with real processes: the router, calibration, two filtering
instances, alerting and the simulator (fast mode) publishing a 100-day world in about a
minute. While it publishes, in turn: SIGKILL filtering A and restart it, SIGKILL
calibration and restart it, SIGKILL alerting and restart it, SIGKILL the router and restart
it, cut filtering A's link (a proxy on loopback) and restore it. Nobody is told to
reconnect. At the end every filtering instance's states equal, byte for byte, those of an
uninterrupted run: the same world folded in this process with the final models.
"""

from __future__ import annotations

import json
import signal
import threading
from collections.abc import Callable

import zenoh
from support import accepts_connections, outbox_config, wait_for

from bench.chaos import (
    gateway_entries,
    raw_chain_indices,
    simulated_world,
    undisturbed_states,
)
from bench.linkproxy import LinkProxy
from schemas import (
    DAY_S,
    InspectionPlan,
    SegmentState,
    decode,
    encode,
    keys,
)
from schemas.keys import SegmentId
from services.defaults import default_file
from services.filtering.testing import states_by_instance
from services.runtime.config import zenoh_config
from services.runtime.delivery import ReliableSubscription
from simulators.network import generate_network

DAYS, TRAINS, SPEEDUP = 100, 2, 120_000.0  # ≈ 72 s of publishing
WAIT_S = 120.0


class Progress:
    """The distinct events of the world seen on the bus so far (a reliable subscriber of
    its own: it counts each event once however often it arrives)."""

    def __init__(self) -> None:
        self.seen: set[bytes] = set()
        self._cond = threading.Condition()

    def __call__(self, _kind: str, _key: str, payload: bytes) -> None:
        with self._cond:
            self.seen.add(payload)
            self._cond.notify_all()

    def reach(self, n: int, timeout: float = WAIT_S) -> None:
        with self._cond:
            assert self._cond.wait_for(lambda: len(self.seen) >= n, timeout), (
                f"only {len(self.seen)} of {n} events seen within {timeout} s"
            )


def models_of(session: zenoh.Session, ns: str) -> dict[str, bytes]:
    replies = session.get(keys.model_all(ns), timeout=10)
    return {str(r.ok.key_expr): r.ok.payload.to_bytes() for r in replies if r.ok}


def plan_state_times(session: zenoh.Session, ns: str) -> dict[SegmentId, float]:
    """{(line, segment): time of the state its row was computed from} of alerting's plan."""
    replies = [r for r in session.get(keys.q_plan(ns), timeout=10) if r.ok is not None]
    if not replies:
        return {}
    rows = decode(replies[0].ok.payload.to_bytes(), InspectionPlan).rows
    return {(row.line, row.segment): row.state_t for row in rows}


def test_every_fault_in_turn_leaves_the_uninterrupted_states(
    free_port, namespace, spawn, link_proxy: Callable[[int], LinkProxy], tmp_path
):
    ns = namespace
    network = tmp_path / "net.geojson"
    network.write_text(json.dumps(generate_network(1, 6.0, seed=3).to_geojson()))
    world = simulated_world(network, DAYS, 1, TRAINS)
    distinct = len({encode(m) for m in world})
    endpoint = f"tcp/127.0.0.1:{free_port}"
    wiring = ["--connect", endpoint, "--ns", ns]
    proxy = link_proxy(free_port)

    def router():
        process = spawn("router", "router", "--listen", endpoint, "--ns", ns)
        process.until(lambda: accepts_connections(free_port), WAIT_S, "the router listening")
        return process

    def service(name: str, *args: str, via: str = endpoint):
        return spawn(name, *args, "--instance", name, "--connect", via, "--ns", ns)

    def filtering(name: str, via: str = endpoint):
        db = str(tmp_path / f"{name}.sqlite")
        return service(name, "filtering", "--db", db, via=via)

    def calibration():
        db, initial = str(tmp_path / "cal.sqlite"), "services/defaults/initial-models.json5"
        return service("cal", "calibration", "--db", db, "--initial-models", initial)

    def alerting():
        return service("al", "alerting", "--db", str(tmp_path / "al.sqlite"))

    processes = {"router": router()}
    session = zenoh.open(zenoh_config({"mode": "client", "connect": {"endpoints": [endpoint]}}))
    progress = Progress()
    watched = [
        ReliableSubscription(
            session, ns,
            {kind: keys.segment_keys(ns, kind) for kind in ("index", "trc", "maintenance")},
            progress, lambda *mark: watched[0].confirm(*mark),
        )
    ]  # fmt: skip
    alive_now: set[str] = set()
    alive_changed = threading.Condition()

    def on_token(sample: zenoh.Sample) -> None:
        name = keys.parse_alive(str(sample.key_expr))[1]
        with alive_changed:
            if sample.kind == zenoh.SampleKind.PUT:
                alive_now.add(name)
            else:
                alive_now.discard(name)
            alive_changed.notify_all()

    tokens = session.liveliness().declare_subscriber(keys.alive_all(ns), on_token, history=True)

    def until_alive(*names: str, alive: bool = True) -> None:
        with alive_changed:
            assert alive_changed.wait_for(
                lambda: all((n in alive_now) == alive for n in names), WAIT_S
            ), f"{names} not {'up' if alive else 'gone'}; alive: {sorted(alive_now)}"

    try:
        processes |= {
            "cal": calibration(),
            "A": filtering("A", via=proxy.endpoint),
            "B": filtering("B"),
            "al": alerting(),
        }
        until_alive("cal", "A", "B", "al")
        simulate = spawn(
            "simulate",
            "simulate",
            "--network",
            str(network),
            "--days",
            str(DAYS),
            "--trains",
            str(TRAINS),
            "--speedup",
            str(SPEEDUP),
            "--linger",
            "600",
            *wiring,
        )
        restart = {"A": lambda: filtering("A", via=proxy.endpoint), "cal": calibration}
        restart["al"] = alerting
        step = distinct // 7
        for i, name in enumerate(("A", "cal", "al"), start=1):
            progress.reach(i * step)
            processes[name].signal(signal.SIGKILL)
            processes[name].wait(10)
            until_alive(name, alive=False)
            processes[name] = restart[name]()
            until_alive(name)

        progress.reach(4 * step)
        processes["router"].signal(signal.SIGKILL)
        processes["router"].wait(10)
        processes["router"] = router()  # same port: every client finds it again by itself
        until_alive("cal", "A", "B", "al")

        progress.reach(5 * step)
        connections = proxy.connections
        proxy.cut()
        progress.reach(6 * step)  # published while A is cut off
        proxy.restore()
        assert proxy.wait_connections(connections + 1, WAIT_S), "A did not reconnect"

        progress.reach(distinct)  # the test's own subscriber has seen the whole world
        reference: dict[str, bytes] = {}
        replies: dict[str, dict[str, bytes]] = {}

        def converged() -> bool:
            nonlocal reference, replies
            reference = undisturbed_states(ns, world, models_of(session, ns))
            replies = states_by_instance(session, ns)
            return len(replies) == 2 and all(states == reference for states in replies.values())

        def summary() -> str:
            equal = {
                zid: (len(s), sum(s.get(k) == v for k, v in reference.items()))
                for zid, s in replies.items()
            }
            return f"{len(reference)} reference states; per instance (states, equal): {equal}"

        wait_for(converged, WAIT_S, summary, poll_s=0.5)  # each poll folds the whole world
        assert len(reference) >= 25

        # alerting, restarted mid-run, holds the newest state of every segment
        newest = {
            (state.line, state.segment): state.t
            for state in (decode(p, SegmentState) for p in reference.values())
        }
        wait_for(
            lambda: plan_state_times(session, ns) == newest,
            WAIT_S,
            "alerting's plan at the newest state of every segment",
        )
        simulate.signal(signal.SIGTERM)
        assert simulate.wait(20) == 0, simulate.log()
        for name in ("A", "B", "cal", "al"):
            processes[name].signal(signal.SIGTERM)
            assert processes[name].wait(20) == 0, processes[name].log()
    finally:
        tokens.undeclare()
        for subscriber in watched:
            subscriber.undeclare()
        session.close()


def test_the_signal_chain_loses_nothing_when_its_services_are_killed(
    router, namespace, open_session, collector, liveliness_events, spawn, tmp_path
):
    """Raw data (2 trains, 15 simulated minutes at 60×) through a gateway with an outbox:
    SIGKILL ingestion, then extraction, then both, each restarted at once. Afterwards the
    distinct indices published are exactly those the two cores compute in one undisturbed
    pass over what the gateway recorded: a restarted stage resumes from its checkpoint and
    fetches what it missed from its producer's outbox, and the next stage drops what it
    sends twice (docs/operating.md#delivery-guarantees)."""
    session = open_session()
    indices = collector(lambda s: s.payload.to_bytes())
    session.declare_subscriber(keys.segment_keys(namespace, "index"), indices)
    alive = liveliness_events(session, keys.alive_all(namespace))
    wiring = ["--connect", router, "--ns", namespace]
    config = ("--config", str(outbox_config(tmp_path)))

    def start(name: str):
        return spawn(name, name, "--instance", name, *config, *wiring)

    def next_change(name: str):
        return alive.next_change(keys.alive(namespace, name, name), WAIT_S)

    processes = {name: start(name) for name in ("ingestion", "extraction")}
    for name in processes:
        assert next_change(name) == zenoh.SampleKind.PUT
    world = ["--fidelity", "raw", "--trains", "2", "--days", str(900 / DAY_S), "--seed", "11"]
    # the gateway serves its outbox after its last message, as a train's gateway keeps it
    # up: a stage that fell behind fetches from it what it did not take live
    linger = ("--linger", str(WAIT_S))
    simulate = spawn("simulate", "simulate", *world, "--speedup", "60", *linger, *config, *wiring)
    got = {indices.get(timeout=WAIT_S)}
    for names in (["ingestion"], ["extraction"], ["ingestion", "extraction"]):
        for name in names:
            processes[name].signal(signal.SIGKILL)
            processes[name].wait(10)
            assert next_change(name) == zenoh.SampleKind.DELETE
        for name in names:
            processes[name] = start(name)
            assert next_change(name) == zenoh.SampleKind.PUT
        got.add(indices.get(timeout=WAIT_S))  # indices flow again
    simulate.until(lambda: "published; lingering" in simulate.log(), WAIT_S, "the world")
    gateway = gateway_entries(tmp_path / "outbox-gateway-default.sqlite")
    expected = raw_chain_indices(gateway, default_file("demo-network.geojson"))
    assert len(expected) >= 20, "the scenario should index many passes"
    while not expected <= got:
        try:
            got.add(indices.get(timeout=WAIT_S))
        except AssertionError:
            raise AssertionError(
                f"{len(expected - got)} of {len(expected)} indices never published"
                f"{processes['ingestion'].log()[-2000:]}{processes['extraction'].log()[-2000:]}"
            ) from None
    assert got == expected
    for process in processes.values():
        process.signal(signal.SIGTERM)
        assert process.wait(10) == 0, process.log()
