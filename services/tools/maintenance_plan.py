"""`trackfusion plan maintenance`: the tamping plan of the running planner, as a table, JSON
or CSV. Pure formatting functions, and a thin ``main`` that queries
``{ns}/q/plan/maintenance``."""

from __future__ import annotations

import csv
import io
import json
import sys
from datetime import UTC, datetime
from typing import TextIO

import msgspec

from schemas import DAY_S, MaintenancePlan, decode, keys
from services.runtime.config import RuntimeConfig
from services.tools.query import ask, open_session

CSV_COLUMNS = [
    "line", "segment", "week", "week_start", "worksite", "length_km", "deadline_week",
    "p_reach_ial", "risk_met", "cost", "cost_untamped", "speed_class",
]  # fmt: skip


def _day(t: float) -> str:
    return datetime.fromtimestamp(t, UTC).strftime("%Y-%m-%d")


def selector(ns: str, weeks: int | None, budget: float | None) -> str:
    params = [f"weeks={weeks}"] if weeks is not None else []
    params += [f"budget={budget:g}"] if budget is not None else []
    return keys.q_maintenance_plan(ns) + ("?" + ";".join(params) if params else "")


def to_csv(plan: MaintenancePlan) -> str:
    out = io.StringIO()
    writer = csv.DictWriter(out, fieldnames=CSV_COLUMNS)
    writer.writeheader()
    for row in plan.rows:
        values = msgspec.structs.asdict(row)
        start = plan.t + row.week * 7 * DAY_S if plan.t is not None and row.week >= 0 else None
        values["week_start"] = _day(start) if start is not None else ""
        writer.writerow(values)
    return out.getvalue()


def to_json(plan: MaintenancePlan) -> str:
    return json.dumps(msgspec.to_builtins(plan), indent=1)


def counted(n: int, noun: str) -> str:
    """'1 possession', '2 possessions': ``n`` and ``noun``, plural unless one."""
    return f"{n} {noun}{'s' * (n != 1)}"


def format_plan(plan: MaintenancePlan) -> str:
    """A planner's reading: how good the plan is, the weeks, the worksites, the unmet risks."""
    if plan.status == "no_data" or plan.t is None:
        return "no plan yet: no segment has both a state and a degradation model"
    budget = "none" if plan.budget is None else f"{plan.budget:,.0f}"
    lines = [
        f"Tamping plan, {plan.horizon_weeks} weeks from {_day(plan.t)} (data up to "
        f"{_day(plan.computed_at or plan.t)}), {plan.segments} segments",
        f"  expected cost {plan.objective:,.0f}; bound {plan.bound:,.0f}; gap "
        f"{100 * plan.gap:.2f} % ({plan.status}); solved in {plan.solve_s:.1f} s",
        f"  {sum(plan.km_per_week):.1f} km in {counted(plan.possessions, 'possession')}; money "
        f"{plan.money:,.0f} (budget {budget}); risk limit P(IAL before tamping) <= {plan.eps:g}",
    ]
    sites: dict[int, list] = {}
    for row in plan.rows:
        if row.week >= 0:
            sites.setdefault(row.worksite, []).append(row)
    lines.append(
        f"{'week':>4} {'starts':10} {'worksite':24} {'speed class':11} {'km':>5} "
        f"{'deadline':>8} max P(IAL)"
    )
    for rows in sorted(sites.values(), key=lambda r: (r[0].week, r[0].line, r[0].segment)):
        first, last = rows[0], rows[-1]
        deadline = min(r.deadline_week for r in rows)
        lines.append(
            f"{first.week:4d} {_day(plan.t + first.week * 7 * DAY_S):10} "
            f"{first.line + '/' + first.segment + '-' + last.segment:24} "
            f"{first.speed_class or '-':11} {sum(r.length_km for r in rows):5.1f} "
            f"{'-' if deadline >= plan.horizon_weeks else deadline:>8} "
            f"{max(r.p_reach_ial for r in rows):.3f}"
        )
    if plan.trc_lines:
        lines.append("next TRC runs by value of information (expected fall of the plan's cost):")
        for value in plan.trc_lines[:5]:
            lines.append(f"  {value.line:12} {value.value:12,.0f}  ({value.segments} segments)")
    unmet = [r for r in plan.rows if not r.risk_met]
    if unmet:
        lines.append(f"risk limit not met on {counted(len(unmet), 'segment')}:")
        for r in unmet[:20]:
            when = "not tamped" if r.week < 0 else f"tamped week {r.week}"
            if r.deadline_week < 0:
                when += ", overdue at week 0"
            lines.append(
                f"  {r.line}/{r.segment}: P(IAL first) {r.p_reach_ial:.2f}, {when}"
                + (f" (speed class {r.speed_class})" if r.speed_class else "")
            )
    return "\n".join(lines)


def ask_plan(
    session, ns: str, timeout: float, weeks: int | None = None, budget: float | None = None
) -> MaintenancePlan | None:
    """The running planner's plan (made for ``weeks`` and ``budget`` when given); None when
    no planning service answers."""
    replies = list(ask(session, selector(ns, weeks, budget), timeout))
    return decode(replies[0][1], MaintenancePlan) if replies else None


def main(
    conf: RuntimeConfig,
    *,
    weeks: int | None,
    budget: float | None,
    fmt: str,
    timeout: float,
    out: TextIO = sys.stdout,
) -> int:
    with open_session(conf) as session:
        plan = ask_plan(session, conf.ns, timeout, weeks, budget)
    if plan is None:
        raise SystemExit("plan maintenance: no answer from the planning service (is it running?)")
    text = {"json": to_json, "csv": to_csv}.get(fmt, format_plan)(plan)
    out.write(text if text.endswith("\n") else text + "\n")
    return 0
