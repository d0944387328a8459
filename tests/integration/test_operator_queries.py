"""Operator queries against a service that answers late: `--timeout` bounds the wait and
the message says what to do (a real router, the CLI as a real process)."""

from __future__ import annotations

import threading

import zenoh
from support import run_cli

from schemas import encode, keys
from services.alerting.testing import make_state
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
