"""The planner in-process on a real router: a posterior and states in, a plan published and
answered, a plan for another horizon on request, bad parameters, bad payloads and segments
not in the network refused."""

from __future__ import annotations

import threading
from pathlib import Path

import numpy as np
import pytest
import zenoh

from schemas import DeadLetter, MaintenancePlan, decode, encode, keys
from services.planning import service as planning
from services.planning.core import PlanningCore
from services.planning.testing import T0, make_posterior, make_state

TIMEOUT_S = 10.0
FIRST_PLAN_S = 180.0
SEGMENTS = [f"s{k:05d}" for k in range(12)]  # the first segments of the demo network's L1


@pytest.fixture
def config_file(tmp_path: Path) -> Path:
    path = tmp_path / "planning.json5"
    path.write_text("{ replan: { quiet_s: 0.2, max_wait_s: 1.0 } }")
    return path


def query(session: zenoh.Session, selector: str) -> list[zenoh.Reply]:
    return list(session.get(selector, timeout=TIMEOUT_S))


def test_states_and_a_model_give_a_published_plan_that_the_queryable_answers(
    open_session, service_config, service_thread, collector, until_matched, config_file, tmp_path
):
    ns = service_config.ns
    client = open_session()
    plans = collector(lambda s: decode(s.payload.to_bytes(), MaintenancePlan))
    client.declare_subscriber(keys.maintenance_plan(ns), plans)
    letters = collector(lambda s: decode(s.payload.to_bytes(), DeadLetter))
    client.declare_subscriber(keys.deadletter(ns, planning.SERVICE), letters)
    service_thread(
        "planning",
        lambda stop: planning.main(
            service_config,
            planning_config=config_file,
            db=tmp_path / "p.sqlite",
            stop=stop,
            handle_signals=False,
        ),
        alive=keys.alive(ns, planning.SERVICE, "test"),
    )
    (before,) = query(client, keys.q_maintenance_plan(ns))
    assert decode(before.ok.payload.to_bytes(), MaintenancePlan).status == "no_data"

    model_pub = client.declare_publisher(keys.degradation(ns, "net"))
    until_matched(model_pub)
    model_pub.put(encode(make_posterior()))
    state_pub = client.declare_publisher(keys.segment_keys(ns, "state", "L1/**"))
    for k, segment in enumerate(SEGMENTS):
        worn = (10.0, 8.5) if 2 <= k < 8 else (3.0, 2.5)  # six worn segments in a row
        client.put(keys.state(ns, "L1", segment), encode(make_state("L1", segment, T0,
                                                                    mean_mm=worn)))  # fmt: skip
    client.put(keys.state(ns, "L1", "s00000"), b"not msgpack")
    assert letters.get().reason
    client.put(keys.state(ns, "NOLINE", "s00000"),
               encode(make_state("NOLINE", "s00000", T0, mean_mm=(30.0, 30.0))))  # fmt: skip
    assert "NOLINE/s00000 is not in the network demo" in letters.get().reason

    # On a fresh checkout the first plan compiles the planner's kernels (numba): the wait
    # bounds a stalled service, it times nothing.
    plan = plans.get(timeout=FIRST_PLAN_S)
    while plan.segments < len(SEGMENTS):  # a plan made before every state arrived
        plan = plans.get(timeout=FIRST_PLAN_S)
    assert plan.status in ("optimal", "within_gap") and plan.gap <= 0.01
    assert plan.t is not None and plan.t <= T0 < plan.t + 7 * 86400.0
    tamped = {r.segment for r in plan.rows if r.week >= 0}
    assert {f"s{k:05d}" for k in range(2, 8)} <= tamped
    assert plan.possessions >= 1 and sum(plan.km_per_week) > 0
    assert [v.line for v in plan.trc_lines] == ["L1"] and plan.trc_lines[0].value >= 0

    (reply,) = query(client, keys.q_maintenance_plan(ns))
    assert decode(reply.ok.payload.to_bytes(), MaintenancePlan) == plan
    (reply,) = query(client, keys.q_maintenance_plan(ns) + "?weeks=4;budget=0")
    short = decode(reply.ok.payload.to_bytes(), MaintenancePlan)
    assert short.horizon_weeks == 4 and short.budget == 0.0 and len(short.km_per_week) == 4
    assert short.money == 0.0 and all(not r.risk_met for r in short.rows)
    (bad,) = query(client, keys.q_maintenance_plan(ns) + "?weeks=x")
    assert bad.err is not None and b"weeks" in bad.err.payload.to_bytes()
    state_pub.undeclare()
    model_pub.undeclare()


def test_states_keep_being_taken_while_a_plan_is_made(
    open_session, service_config, service_thread, collector, until_matched, config_file,
    monkeypatch, tmp_path,
):  # fmt: skip
    # the first plan is held until the test lets it go; a state put meanwhile must be folded
    # into the core before then, and the next plan has it
    planning_now, release, folded = threading.Event(), threading.Event(), threading.Event()
    plan, on_state = PlanningCore.plan, PlanningCore.on_state

    def held_plan(core, *args, **kwargs):
        if not planning_now.is_set():
            planning_now.set()
            assert release.wait(FIRST_PLAN_S), "the test did not let the plan go"
        return plan(core, *args, **kwargs)

    def noting_on_state(core, state):
        changed = on_state(core, state)
        if state.segment == SEGMENTS[5]:
            folded.set()
        return changed

    monkeypatch.setattr(PlanningCore, "plan", held_plan)
    monkeypatch.setattr(PlanningCore, "on_state", noting_on_state)
    ns = service_config.ns
    client = open_session()
    plans = collector(lambda s: decode(s.payload.to_bytes(), MaintenancePlan))
    client.declare_subscriber(keys.maintenance_plan(ns), plans)
    service_thread(
        "planning",
        lambda stop: planning.main(
            service_config,
            planning_config=config_file,
            db=tmp_path / "p.sqlite",
            stop=stop,
            handle_signals=False,
        ),
        alive=keys.alive(ns, planning.SERVICE, "test"),
    )
    model_pub = client.declare_publisher(keys.degradation(ns, "net"))
    until_matched(model_pub)
    model_pub.put(encode(make_posterior()))
    client.put(keys.state(ns, "L1", SEGMENTS[2]), encode(make_state("L1", SEGMENTS[2], T0)))
    assert planning_now.wait(TIMEOUT_S), "no plan started"
    late = make_state("L1", SEGMENTS[5], T0, mean_mm=(10.0, 8.5))
    client.put(keys.state(ns, "L1", SEGMENTS[5]), encode(late))
    try:
        assert folded.wait(TIMEOUT_S), "a state waited for the plan to end"
    finally:
        release.set()
    got = plans.get(timeout=FIRST_PLAN_S)
    while got.segments < 2:  # the held plan had the first state only
        got = plans.get(timeout=FIRST_PLAN_S)
    assert any(r.segment == SEGMENTS[5] for r in got.rows)
    model_pub.undeclare()


def test_a_restarted_planner_keeps_the_evidence_of_closed_trc_intervals(
    open_session, service_config, service_thread, collector, until_matched, config_file,
    tmp_path,
):  # fmt: skip
    """A segment's on-board data favoured fast drifts before its last TRC record: its plan
    row is the same after a restart that is given only the states of now (what ``q/state``
    holds), because the planner kept that evidence in its file."""
    import msgspec

    from schemas import NDArray
    from services.planning.evidence_store import EvidenceStore

    ns = service_config.ns
    db = tmp_path / "planning.sqlite"
    client = open_session()
    posterior = make_posterior(mu_spread=0.8)
    mu = posterior.mu.array()[:, 0]
    fast = NDArray.of(np.where(mu >= np.quantile(mu, 0.9), 0.0, -30.0).astype(np.float32), "f4")
    before = msgspec.structs.replace(
        make_state("L1", SEGMENTS[0], T0 - 40 * 86400.0, mean_mm=(8.0, 4.6)),
        last_trc_t=T0 - 120 * 86400.0, log_weights=fast,
    )  # fmt: skip
    now = [
        msgspec.structs.replace(
            make_state("L1", segment, T0, mean_mm=(8.5, 5.0)), last_trc_t=T0 - 30 * 86400.0
        )  # fmt: skip
        for segment in SEGMENTS[:2]
    ]

    def run_planner(states):
        plans = collector(lambda s: decode(s.payload.to_bytes(), MaintenancePlan))
        subscriber = client.declare_subscriber(keys.maintenance_plan(ns), plans)
        service = service_thread(
            "planning",
            lambda stop: planning.main(
                service_config,
                planning_config=config_file,
                db=db,
                stop=stop,
                handle_signals=False,
            ),  # fmt: skip
            alive=keys.alive(ns, planning.SERVICE, "test"),
        )
        model_pub = client.declare_publisher(keys.degradation(ns, "net"))
        until_matched(model_pub)
        model_pub.put(encode(posterior))
        for state in states:
            client.put(keys.state(ns, state.line, state.segment), encode(state))
        plan = plans.get(timeout=FIRST_PLAN_S)
        while plan.segments < 2:  # a plan made before both states arrived
            plan = plans.get(timeout=FIRST_PLAN_S)
        model_pub.undeclare()
        subscriber.undeclare()
        assert service.stop() == 0
        return {r.segment: r for r in plan.rows}

    first = run_planner([before, *now])
    assert first[SEGMENTS[0]].deadline_week < first[SEGMENTS[1]].deadline_week
    store = EvidenceStore(db)
    saved = store.load()
    store.close()
    assert [(line, segment) for line, segment, _ in saved] == [("L1", SEGMENTS[0])]
    assert run_planner(now) == first
