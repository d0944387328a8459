"""`trackfusion plan maintenance` and `plan inspection`: the question each asks and how
it prints the answer."""

from __future__ import annotations

import csv
import io
import json

import msgspec

from schemas import DAY_S, InspectionPlan, MaintenancePlan, TrcRunValue, decode, encode
from services.alerting.testing import plan_row
from services.cli import build_parser
from services.planning.core import PlanningConfig, PlanningCore, SegmentRef
from services.planning.service import to_message
from services.planning.testing import T0, make_limits, make_posterior, make_state
from services.tools.maintenance_plan import counted, format_plan, selector, to_csv, to_json
from services.tools.operator import (
    format_alerting_ranking,
    format_trc_ranking,
    why_no_trc_ranking,
)


def plan_message(overdue: tuple[float, float] | None = None) -> MaintenancePlan:
    limits, ial = make_limits()
    refs = [SegmentRef("L1", f"s{k:02d}", 200.0) for k in range(12)]
    core = PlanningCore(PlanningConfig(), limits, ial, refs)
    core.on_posterior(make_posterior())
    for k in range(12):
        worn = (9.0, 7.6) if 3 <= k < 6 else (2.2, 2.0)
        if overdue is not None and k == 9:
            worn = overdue
        core.on_state(make_state("L1", f"s{k:02d}", T0, mean_mm=worn))
    message = to_message(core.plan(T0), computed_at=T0, eps=0.05, budget=None, horizon_weeks=26,
                         version=1)  # fmt: skip
    return decode(encode(message), MaintenancePlan)


def test_the_command_line_asks_for_weeks_and_budget():
    args = build_parser().parse_args(["plan", "maintenance", "--weeks", "8", "--budget", "1e5",
                                      "--csv"])  # fmt: skip
    assert (args.what, args.weeks, args.budget, args.format) == ("maintenance", 8, 1e5, "csv")
    assert build_parser().parse_args(["plan"]).what == "inspection"
    assert selector("tf", 8, 1e5) == "tf/q/plan/maintenance?weeks=8;budget=100000"
    assert selector("tf", None, None) == "tf/q/plan/maintenance"


def test_the_table_csv_and_json_show_the_worksite():
    plan = plan_message()
    text = format_plan(plan)
    sites = counted(plan.possessions, "possession")
    assert "L1/s" in text and f"in {sites};" in text and "gap" in text
    rows = list(csv.DictReader(io.StringIO(to_csv(plan))))
    tamped = [r for r in rows if int(r["week"]) >= 0]
    assert {r["segment"] for r in tamped} >= {"s03", "s04", "s05"}
    assert all(r["week_start"] for r in tamped)
    assert {r["speed_class"] for r in rows} == {"80<v<=120"} and "80<v<=120" in text
    assert json.loads(to_json(plan))["possessions"] == plan.possessions


def test_no_plan_yet_says_why():
    empty = to_message(None, computed_at=None, eps=0.05, budget=None, horizon_weeks=26, version=0)
    assert "no plan yet" in format_plan(empty)


def test_a_segment_past_its_deadline_at_week_zero_is_printed_overdue():
    text = format_plan(plan_message(overdue=(10.6, 9.0)))
    assert "L1/s09: P(IAL first)" in text and "tamped week 0, overdue at week 0" in text


def test_plan_inspection_ranks_trc_runs_by_the_planners_value_of_information():
    runs = [TrcRunValue(line="L2", value=5400.0, segments=40),
            TrcRunValue(line="L1", value=120.0, segments=12)]  # fmt: skip
    plan = msgspec.structs.replace(plan_message(), trc_lines=runs)
    assert why_no_trc_ranking(plan) == ""
    text = format_trc_ranking(plan, limit=1).splitlines()
    assert text[0].startswith("TRC runs ranked by the planner's value of information")
    assert text[2].split() == ["1", "L2", "5,400", "40"] and len(text) == 3


def test_plan_inspection_falls_back_to_alerting_and_says_why():
    assert why_no_trc_ranking(None) == "no planning service answered"
    empty = to_message(None, computed_at=None, eps=0.05, budget=None, horizon_weeks=26, version=0)
    assert why_no_trc_ranking(empty) == "the planner has no plan yet"
    assert "ranks no TRC run" in why_no_trc_ranking(plan_message())  # trc_lines empty
    rows = [plan_row("L1", "s2", 0.8, T0 + 30 * DAY_S, speed_class="80<v<=120")]
    text = format_alerting_ranking(InspectionPlan(t=T0, rows=rows), "no planning service answered")
    head, _, row = text.splitlines()
    assert "alerting's ranking: no planning service answered" in head
    assert row.split()[:7] == ["1", "L1/s2", "0.800", "top6", "8.0", "mm", "80<v<=120"]


def test_one_possession_is_singular():
    assert tuple(counted(n, "possession") for n in (0, 1, 2)) == (
        "0 possessions", "1 possession", "2 possessions",
    )  # fmt: skip
