"""Operator queries against a service that answers late: `--timeout` bounds the wait and
the message says what to do (a real router, the CLI as a real process)."""

from __future__ import annotations

import threading

import zenoh
from support import run_cli

from schemas import DAY_S, InspectionPlan, MaintenancePlan, TrcRunValue, encode, keys
from services.alerting.testing import T0, make_state, plan_row
from services.cli import build_parser
from services.tools.operator import QUERY_TIMEOUT_S


def test_an_answer_later_than_the_timeout_says_what_to_do(open_session, router, namespace):
    released = threading.Event()  # the busy service answers once the asker has given up
    state = encode(make_state())

    def busy(query: zenoh.Query) -> None:
        released.wait(30)
        query.reply(keys.q_state(namespace, "L1", "s1"), state)

    session = open_session()
    queryable = session.declare_queryable(keys.q_state_all(namespace), busy)
    try:
        late = run_cli("state", "L1/s1", "--timeout", "0.5", "--connect", router,
                           "--ns", namespace)  # fmt: skip
    finally:
        released.set()
    assert late.returncode != 0
    assert "no complete answer within 0.5 s" in late.stderr and "--timeout" in late.stderr

    # the same question with a timeout longer than the delay gets the state
    released.clear()
    threading.Timer(1.0, released.set).start()
    patient = run_cli("state", "L1/s1", "--timeout", "20", "--connect", router,
                          "--ns", namespace)  # fmt: skip
    assert patient.returncode == 0 and "L1/s1" in patient.stdout, patient.stderr
    queryable.undeclare()


def test_timeout_flag_default_and_bad_values():
    parser = build_parser()
    for command in (["status"], ["state", "L1/s1"], ["alerts"], ["plan"], ["export", "states"]):
        assert parser.parse_args(command).timeout == QUERY_TIMEOUT_S
    for bad in ("0", "-1", "nan", "inf", "soon"):
        refused = run_cli("alerts", "--timeout", bad)
        assert refused.returncode == 2 and "positive number of seconds" in refused.stderr


def test_plan_inspection_is_the_planners_trc_ranking_else_alerting_s(
    open_session, router, namespace
):
    session = open_session()
    wiring = ("--connect", router, "--ns", namespace)
    row = plan_row("L1", "s2", 0.8, T0 + 30 * DAY_S, speed_class="80<v<=120")
    alerting = session.declare_queryable(
        keys.q_plan(namespace),
        lambda q: q.reply(keys.q_plan(namespace), encode(InspectionPlan(t=T0, rows=[row]))),
    )
    without = run_cli("plan", *wiring)
    assert without.returncode == 0, without.stderr
    assert "alerting's ranking: no planning service answered" in without.stdout
    assert "L1/s2" in without.stdout and "80<v<=120" in without.stdout

    plan = MaintenancePlan(
        t=T0, computed_at=T0, horizon_weeks=26, eps=0.05, status="optimal", objective=1.0,
        bound=1.0, gap=0.0, solve_s=0.1, km_per_week=[0.0] * 26, possessions=0, money=0.0,
        budget=None, segments=3, without_model=0, rows=[],
        trc_lines=[TrcRunValue(line="L2", value=900.0, segments=3)],
    )  # fmt: skip
    key = keys.q_maintenance_plan(namespace)
    planner = session.declare_queryable(key, lambda q: q.reply(key, encode(plan)))
    with_planner = run_cli("plan", "inspection", *wiring)
    assert with_planner.returncode == 0, with_planner.stderr
    assert "ranked by the planner's value of information" in with_planner.stdout
    assert with_planner.stdout.splitlines()[2].split() == ["1", "L2", "900", "3"]
    planner.undeclare()
    alerting.undeclare()
