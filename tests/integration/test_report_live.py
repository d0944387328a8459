"""`trackfusion report` against a real router, with queryables standing in for filtering
(`q/state/**`), alerting (`q/alerts`, `q/plan`) and the planner (`q/plan/maintenance`), and
with the real alerting service."""

from __future__ import annotations

import io
from pathlib import Path

import pytest
import zenoh
from support import run_cli

from schemas import (
    DAY_S,
    Alert,
    InspectionPlan,
    MaintenancePlan,
    PlannedTamping,
    RaisedAlerts,
    decode,
    encode,
    keys,
)
from services.alerting import service as alerting
from services.alerting.testing import T0, make_state, p_top6, plan_row
from services.tools import report

STATES = [
    make_state(T0, line="L1", segment="s00001", p_exceed=p_top6(1, 0.3)),
    make_state(T0, line="L1", segment="s00002", p_exceed=p_top6(1, 0.95)),
    make_state(T0, line="L2", segment="s00001", p_exceed=p_top6(1, 0.6)),
]
ALERT = Alert(line="L1", segment="s00002", t=T0, kind="exceedance", status="raised",
              indicator="top6", level="intervention", probability=0.95,
              message="Top6 likely above intervention limit 8.0 mm")  # fmt: skip


def filtering_stand_in(session: zenoh.Session, ns: str) -> zenoh.Queryable:
    """Answers `q/state/**` like filtering: one reply per state whose key the query asks."""

    def answer(query: zenoh.Query) -> None:
        for state in STATES:
            key = keys.q_state(ns, state.line, state.segment)
            if query.key_expr.intersects(zenoh.KeyExpr(key)):
                query.reply(key, encode(state))

    return session.declare_queryable(keys.q_state_all(ns), answer)


def alerting_stand_in(session: zenoh.Session, ns: str, asked: list[str]):
    """Answers `q/alerts` and `q/plan` like alerting; ``asked`` gets each query's parameters."""

    def alerts(query: zenoh.Query) -> None:
        asked.append(f"alerts?{query.parameters}")
        query.reply(keys.q_alerts(ns), encode(RaisedAlerts(alerts=[ALERT])))

    def plan(query: zenoh.Query) -> None:
        asked.append(f"plan?{query.parameters}")
        row = plan_row("L1", "s00002", 0.97, T0 + 40 * DAY_S)
        query.reply(keys.q_plan(ns), encode(InspectionPlan(t=T0, rows=[row])))

    return [
        session.declare_queryable(keys.q_alerts(ns), alerts),
        session.declare_queryable(keys.q_plan(ns), plan),
    ]


def planner_stand_in(session: zenoh.Session, ns: str) -> zenoh.Queryable:
    """Answers `q/plan/maintenance` like the planner: L1/s00002 tamped in week 3."""
    row = PlannedTamping(
        line="L1", segment="s00002", week=3, worksite=0, length_km=0.2, deadline_week=5,
        p_reach_ial=0.01, risk_met=True, cost=1.0, cost_untamped=2.0,
    )  # fmt: skip
    plan = MaintenancePlan(
        t=T0, computed_at=T0, horizon_weeks=26, eps=0.05, status="optimal", objective=1.0,
        bound=1.0, gap=0.0, solve_s=0.1, km_per_week=[0.0] * 3 + [0.2] + [0.0] * 22,
        possessions=1, money=1.0, budget=None, segments=3, without_model=0, rows=[row],
    )  # fmt: skip
    return session.declare_queryable(
        keys.q_maintenance_plan(ns),
        lambda query: query.reply(keys.q_maintenance_plan(ns), encode(plan)),
    )


def test_report_of_one_line_from_the_running_system(open_session, service_config, tmp_path):
    ns, asked = service_config.ns, []
    services = open_session()
    filtering_stand_in(services, ns)
    alerting_stand_in(services, ns, asked)
    planner_stand_in(services, ns)
    out_path, out = tmp_path / "report.html", io.StringIO()

    assert report.main(service_config, out_path=out_path, line="L1", timeout=5, out=out) == 0

    html = out_path.read_text()
    assert "wrote" in out.getvalue() and "2 segments" in out.getvalue()
    assert sorted(asked) == ["alerts?line=L1", "plan?line=L1"]
    segments = [s for s in ("L1/s00001", "L1/s00002", "L2/s00001") if f"{s}: P(exceed)" in html]
    assert segments == ["L1/s00001", "L1/s00002"]  # L2 was not asked for
    assert html.index("<td>s00002</td>") < html.index("<td>s00001</td>")  # 0.95 before 0.3
    assert "Top6 likely above intervention limit 8.0 mm" in html  # the open alert
    assert "2026-02-10" in html  # next TRC from the plan
    assert "missing" not in html
    worksites = html[html.index('<table class="worksites">') :].split("</table>")[0]
    assert "<td>s00002 – s00002</td>" in worksites  # the planner's tamping, week 3


def test_report_without_alerting_is_written_with_a_note(open_session, service_config, tmp_path):
    filtering_stand_in(open_session(), service_config.ns)
    out_path, out = tmp_path / "report.html", io.StringIO()

    assert report.main(service_config, out_path=out_path, timeout=5, out=out) == 0

    html = out_path.read_text()
    assert "Alerts and plan missing: the alerting service did not answer" in html
    assert "Alerts and plan missing" in out.getvalue()
    assert "Tamping plan missing: no planning service answered" in html
    assert all(f"{s.line}/{s.segment}: P(exceed)" in html for s in STATES)


def test_report_without_filtering_exits_1_saying_what_to_check(
    open_session, service_config, router, tmp_path
):
    alerting_stand_in(open_session(), service_config.ns, [])
    out_path = tmp_path / "report.html"
    with pytest.raises(SystemExit, match=r"filtering service running \(`trackfusion status`\)"):
        report.main(service_config, out_path=out_path, timeout=5, out=io.StringIO())
    # the command itself: exit code 1, the message on stderr, no file
    done = run_cli(
        "report", "--out", str(out_path), "--line", "L1",
        "--connect", router, "--ns", service_config.ns, "--timeout", "5", timeout=60,
    )  # fmt: skip
    assert done.returncode == 1, done.stderr
    assert "no segment state for line L1" in done.stderr and "trackfusion status" in done.stderr
    assert not Path(out_path).exists()


def test_report_with_the_real_alerting_service(
    open_session, service_config, service_thread, collector, until_matched, tmp_path
):
    ns = service_config.ns
    client = open_session()
    filtering_stand_in(client, ns)
    raised = collector(lambda s: decode(s.payload.to_bytes(), Alert))
    client.declare_subscriber(keys.segment_keys(ns, "alert"), raised)
    service = service_thread(
        "alerting",
        lambda stop: alerting.main(
            service_config, db=tmp_path / "a.sqlite", stop=stop, handle_signals=False
        ),
        alive=keys.alive(ns, alerting.SERVICE, "test"),
    )
    for state in STATES:  # what filtering would have published
        publisher = client.declare_publisher(keys.state(ns, state.line, state.segment))
        until_matched(publisher)
        publisher.put(encode(state))
    # once L1/s00002's alert is out, alerting has it in its plan too
    while (alert := raised.get()).segment != "s00002" or alert.line != "L1":
        pass  # L2 has other limits in the default limits: its state may raise or not
    out_path = tmp_path / "report.html"
    assert report.main(service_config, out_path=out_path, line="L1", timeout=5) == 0
    assert service.stop() == 0
    html = out_path.read_text()
    assert "Alerts and plan missing" not in html
    assert "Top6 likely above intervention limit 8.0 mm (p=0.95)" in html
    row = html[html.index("<td>s00002</td>") :].split("</tr>")[0]
    assert "2026-03-12" in row  # next TRC: the last-TRC stand-in + 70 days (alerting README)
