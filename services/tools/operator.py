"""Questions an engineer asks the running system: `trackfusion status|state|alerts|plan|
export`. Each opens a short-lived Zenoh session, asks, prints, and closes. The parser of
`trackfusion import-trc FILE.csv` is here too; the command itself, with its ``--profile``
form, is :mod:`services.tools.trc_import`.

Pure parts (CSV parsing, formatting, GeoJSON building) are plain functions, tested without
Zenoh; the thin part is ``main_*``, asking through :mod:`services.tools.query`.
"""

from __future__ import annotations

import argparse
import csv
import io
import json
import math
import sys
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import TextIO

import numpy as np
import zenoh

from schemas import (
    INDICATORS,
    Alert,
    InspectionPlan,
    MaintenancePlan,
    RaisedAlerts,
    SchemaError,
    SegmentState,
    TrcRecord,
    decode,
    keys,
)
from schemas.keys import SegmentId
from services.defaults import add_network_argument
from services.limits import (
    DEFAULT_LIMITS_FILE,
    Limits,
    add_limits_argument,
    load_limits,
    network_line_speeds,
)
from services.runtime.config import RuntimeConfig, add_zenoh_arguments, config_from_args
from services.tools import maintenance_plan
from services.tools.query import QUERY_TIMEOUT_S, ask, open_session

PLAN_ROWS = 20  # `plan --limit`
TRC_COLUMNS = ("line", "segment", "t", "run_id")  # and one value column at least
TRC_VALUE_COLUMNS = ("top6_mm", "align10_mm")  # in state order (INDICATORS)


# --- status ---------------------------------------------------------------------------------


def main_status(
    conf: RuntimeConfig, timeout: float = QUERY_TIMEOUT_S, out: TextIO = sys.stdout
) -> int:
    """Every live service instance (liveliness tokens under ``{ns}/alive/**``)."""
    with open_session(conf) as session:
        tokens = [
            str(reply.ok.key_expr)
            for reply in session.liveliness().get(keys.alive_all(conf.ns), timeout=timeout)
            if reply.ok is not None
        ]
    alive = sorted(_alive_ids(tokens))
    if not alive:
        print(f"no service alive in namespace {conf.ns!r}", file=out)
        return 1
    print(f"{'service':14} instance", file=out)
    for service, instance in alive:
        print(f"{service:14} {instance}", file=out)
    return 0


def _alive_ids(tokens: Iterable[str]) -> Iterator[tuple[str, str]]:
    """``(service, instance)`` of each token of a service (others under alive/** are skipped)."""
    for token in tokens:
        try:
            yield keys.parse_alive(token)
        except SchemaError:
            continue


# --- state ----------------------------------------------------------------------------------


def format_state(state: SegmentState, line_name: str = "", limits: Limits | None = None) -> str:
    """A segment's state as an engineer reads it: estimate, 95 % interval, risk, forecasts;
    ``line_name``: the line's name in the network file, shown after its id; ``limits``: the
    limits file, whose speed class of the line and immediate-action limits are shown."""
    measured = " ".join(state.last_trc_indicators)
    last = _iso(state.last_trc_t) + (f", measured {measured}" if measured else "")
    named = f" ({line_name})" if line_name and line_name != state.line else ""
    lines = [f"{state.line}/{state.segment}{named} at {_iso(state.t)} (last TRC {last})"]
    mean_mm = [math.exp(v) for v in state.mean.array()]
    low, high = state.ci_low_mm.array(), state.ci_high_mm.array()
    p = state.p_exceed.array()
    levels = state.limit_levels
    for i, name in enumerate(state.indicators):
        risk = ", ".join(
            f"P(>{state.limits_mm.array()[k, i]:.1f} mm {level})={p[k, i]:.2f}"
            for k, level in enumerate(levels)
        )
        lines.append(f"  {name:8} {mean_mm[i]:6.2f} mm  95% [{low[i]:.2f}, {high[i]:.2f}]  {risk}")
    if limits is not None:
        lines.append("  " + _limits_line(state, limits))
    fp = state.forecast_p_exceed.array()
    for h, days in enumerate(state.horizons_days.array()):
        parts = [
            f"{name} [{state.forecast_ci_low_mm.array()[h, i]:.2f}, "
            f"{state.forecast_ci_high_mm.array()[h, i]:.2f}] P(>{levels[-1]})={fp[h, -1, i]:.2f}"
            for i, name in enumerate(state.indicators)
        ]
        lines.append(f"  in {days:4.0f} d: " + "; ".join(parts))
    lines.append(
        f"  W={state.width:.3g}  updates since TRC={state.n_updates}  "
        f"models: calibration v{state.calibration_version}, "
        f"posterior {state.posterior_group or '-'} v{state.posterior_version}"
    )
    return "\n".join(lines)


def _limits_line(state: SegmentState, limits: Limits) -> str:
    """The speed class of the state's line, its immediate-action limits, and whether the
    state's limits are that class's."""
    text = f"limits of {limits.describe(state.line)}"
    ial = limits.immediate_action_for_line(state.line)
    names = [n for n in state.indicators if n in INDICATORS]
    if ial is not None:
        text += "; immediate action " + ", ".join(
            f"{n} {ial[INDICATORS.index(n)]:.1f} mm" for n in names
        )
    table = limits.for_line(state.line)
    ours = [
        table[limits.levels.index(level), INDICATORS.index(n)]
        for level in state.limit_levels
        if level in limits.levels
        for n in names
    ]
    theirs = [
        state.limits_mm.array()[k, state.indicators.index(n)]
        for k, level in enumerate(state.limit_levels)
        if level in limits.levels
        for n in names
    ]
    if not np.allclose(ours, theirs):
        text += "; the state's limits above are not this class's (another limits file)"
    return text


def query_states(
    session: zenoh.Session, ns: str, selector: str = "**", timeout: float = QUERY_TIMEOUT_S
) -> list[SegmentState]:
    replies = ask(session, keys.q_state_keys(ns, selector), timeout)
    return [decode(payload, SegmentState) for _, payload in replies]


def main_state(
    conf: RuntimeConfig,
    segment: str,
    timeout: float = QUERY_TIMEOUT_S,
    out: TextIO = sys.stdout,
    network_path: str | None = None,
    limits_path: str | Path = DEFAULT_LIMITS_FILE,
) -> int:
    """`trackfusion state LINE/SEGMENT` (or `LINE/**` for a whole line); the lines' names
    and speeds from the network file ``network_path`` (the demo network without one), the
    speed classes from the limits file ``limits_path``."""
    from services.defaults import load_network

    network = load_network(network_path)
    names = {line.id: line.name for line in network.lines.values()}
    limits = load_limits(limits_path, network_line_speeds(network))
    if segment.count("/") != 1:
        raise SystemExit(f"state: {segment!r} is not LINE/SEGMENT (e.g. L1/s00042)")
    with open_session(conf) as session:
        states = query_states(session, conf.ns, segment, timeout)
    if not states:
        print(f"no state for {segment} (unknown segment, or no TRC record and model yet)", file=out)
        return 1
    for state in sorted(states, key=lambda s: (s.line, s.segment)):
        print(format_state(state, names.get(state.line, ""), limits), file=out)
    return 0


# --- alerts and plan ------------------------------------------------------------------------


def query_alerts(session: zenoh.Session, ns: str, timeout: float = QUERY_TIMEOUT_S) -> list[Alert]:
    alerts = []
    for _, payload in ask(session, keys.q_alerts(ns), timeout):
        alerts += decode(payload, RaisedAlerts).alerts
    return alerts


def main_alerts(
    conf: RuntimeConfig, timeout: float = QUERY_TIMEOUT_S, out: TextIO = sys.stdout
) -> int:
    with open_session(conf) as session:
        alerts = query_alerts(session, conf.ns, timeout)
    if not alerts:
        print("no alert raised", file=out)
        return 0
    for a in sorted(alerts, key=lambda a: (-a.probability, a.line, a.segment)):
        print(
            f"{_iso(a.t)}  {a.line}/{a.segment:8} {a.kind:20} {a.indicator:8} "
            f"{a.level:12} p={a.probability:.2f}  {a.message}",
            file=out,
        )
    return 0


def format_trc_ranking(plan: MaintenancePlan, limit: int = PLAN_ROWS) -> str:
    """The planner's ranking of recording-car runs: lines by the value of information of a
    run now (the expected fall of the plan's cost from the uncertainty the run removes)."""
    made = _iso(plan.computed_at)
    lines = [
        f"TRC runs ranked by the planner's value of information (plan made from the states up "
        f"to {made}): the expected fall of the tamping plan's cost from the uncertainty a run "
        "removes",
        f"{'rank':>4} {'line':16} {'value':>12} {'segments':>8}",
    ]
    for rank, run in enumerate(plan.trc_lines[:limit], 1):
        lines.append(f"{rank:4d} {run.line:16} {run.value:12,.0f} {run.segments:8d}")
    if not any(run.value > 0 for run in plan.trc_lines):
        lines.append("no run would lower the plan's expected cost now")
    return "\n".join(lines)


def format_alerting_ranking(plan: InspectionPlan, why: str, limit: int = PLAN_ROWS) -> str:
    """Alerting's ranking of segments, used when the planner gives none (``why``): by the
    probability of exceeding the intervention limit before the line's next TRC run."""
    lines = [
        f"Segments ranked by P(exceeding the intervention limit before the line's next TRC "
        f"run), alerting's ranking: {why}",
        f"{'rank':>4} {'segment':16} {'P(exceed)':>9} {'indicator':9} {'limit':>7} "
        f"{'speed class':11} next TRC",
    ]
    for rank, row in enumerate(plan.rows[:limit], 1):
        lines.append(
            f"{rank:4d} {row.line + '/' + row.segment:16} {row.probability:9.3f} "
            f"{row.indicator:9} {row.limit_mm:4.1f} mm {row.speed_class or '-':11} "
            f"{_iso(row.next_trc_t)}"
        )
    return "\n".join(lines)


def why_no_trc_ranking(plan: MaintenancePlan | None) -> str:
    """Why the planner's plan gives no TRC ranking; "" when it gives one."""
    if plan is None:
        return "no planning service answered"
    if plan.status == "no_data":
        return "the planner has no plan yet"
    if not plan.trc_lines:
        return "the planner ranks no TRC run (a network above its value-of-information size)"
    return ""


def main_plan(
    conf: RuntimeConfig,
    limit: int = PLAN_ROWS,
    timeout: float = QUERY_TIMEOUT_S,
    out: TextIO = sys.stdout,
) -> int:
    """`trackfusion plan inspection`: where to send the recording car. The planner's ranking
    of TRC runs by value of information when a planner answers with one; else alerting's
    ranking of segments by P(exceeding before the next TRC run), saying why."""
    with open_session(conf) as session:
        tamping = maintenance_plan.ask_plan(session, conf.ns, timeout)
        why = why_no_trc_ranking(tamping)
        if not why:
            print(format_trc_ranking(tamping, limit), file=out)
            return 0
        replies = list(ask(session, keys.q_plan(conf.ns), timeout))
    if not replies:
        raise SystemExit(f"plan: {why}, and no answer from the alerting service (is it running?)")
    print(format_alerting_ranking(decode(replies[0][1], InspectionPlan), why, limit), file=out)
    return 0


# --- import-trc -----------------------------------------------------------------------------


@dataclass(frozen=True)
class RowError:
    line_no: int
    reason: str


def parse_time(text: str) -> float:
    """Epoch seconds from a number or an ISO 8601 date-time (UTC when no zone is given)."""
    text = text.strip()
    try:
        return float(text)
    except ValueError:
        pass
    try:
        value = datetime.fromisoformat(text.replace("Z", "+00:00"))
    except ValueError:
        raise ValueError(
            f"t: {text!r} is neither epoch seconds nor an ISO 8601 time (e.g. 2026-01-05T08:30:00Z)"
        ) from None
    if value.tzinfo is None:
        value = value.replace(tzinfo=UTC)
    return value.timestamp()


def parse_trc_csv(text: TextIO) -> Iterator[TrcRecord | RowError]:
    """TrcRecords of a TRC export, or a RowError (with its file line number) per bad row.

    Columns: line, segment, t (epoch s or ISO 8601), run_id, and top6_mm, align10_mm or
    both (a level-only or alignment-only export). An empty value cell: the record did not
    measure that indicator; a row must measure one at least.
    """
    reader = csv.DictReader(text)
    header = set(reader.fieldnames or ())
    missing = set(TRC_COLUMNS) - header
    values = [c for c in TRC_VALUE_COLUMNS if c in header]
    if missing or not values:
        need = f"{list(TRC_COLUMNS)} and one or both of {list(TRC_VALUE_COLUMNS)}"
        lacks = sorted(missing) if missing else list(TRC_VALUE_COLUMNS)
        yield RowError(1, f"header lacks column(s) {lacks}; need {need}")
        return
    for row in reader:
        line_no = reader.line_num
        try:
            measured = {c: _number(c, row[c]) for c in values if (row[c] or "").strip()}
            if not measured:
                raise ValueError(f"no value in {values}")
            yield TrcRecord(
                line=row["line"].strip(),
                segment=row["segment"].strip(),
                t=parse_time(row["t"]),
                run_id=row["run_id"].strip(),
                indicators=[
                    i for i, c in zip(INDICATORS, TRC_VALUE_COLUMNS, strict=True) if c in measured
                ],
                **measured,
            )
        except (SchemaError, ValueError, TypeError, AttributeError) as exc:
            yield RowError(line_no, str(exc))


def _number(column: str, cell: str) -> float:
    try:
        return float(cell)
    except ValueError:
        raise ValueError(f"{column}: {cell.strip()!r} is not a number (mm)") from None


# --- export ---------------------------------------------------------------------------------

STATE_COLUMNS = [
    "line",
    "segment",
    "t",
    "last_trc_t",
    "last_trc_indicators",
    "n_updates",
    "width",
] + [
    f"{name}_{what}"
    for name in INDICATORS
    for what in ("mm", "ci_low_mm", "ci_high_mm", "p_exceed_intervention")
]
ALERT_COLUMNS = [
    "line", "segment", "t", "kind", "status", "indicator", "level", "speed_class", "probability",
]  # fmt: skip


def state_row(state: SegmentState) -> dict:
    row = {
        "line": state.line,
        "segment": state.segment,
        "t": _iso(state.t),
        "last_trc_t": _iso(state.last_trc_t),
        "last_trc_indicators": " ".join(state.last_trc_indicators),
        "n_updates": state.n_updates,
        "width": state.width,
    }
    p = state.p_exceed.array()[-1]
    for i, name in enumerate(state.indicators):
        row[f"{name}_mm"] = round(math.exp(state.mean.array()[i]), 3)
        row[f"{name}_ci_low_mm"] = round(float(state.ci_low_mm.array()[i]), 3)
        row[f"{name}_ci_high_mm"] = round(float(state.ci_high_mm.array()[i]), 3)
        row[f"{name}_p_exceed_intervention"] = round(float(p[i]), 4)
    return row


def alert_row(alert: Alert) -> dict:
    row = {name: getattr(alert, name) for name in ALERT_COLUMNS}
    row["t"] = _iso(alert.t)
    return row


def to_csv(rows: Iterable[dict], columns: list[str]) -> str:
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=columns, extrasaction="ignore")
    writer.writeheader()
    writer.writerows(rows)
    return buffer.getvalue()


def to_geojson(rows: Iterable[dict], geometry: dict[SegmentId, list]) -> dict:
    """A FeatureCollection: each row as the properties of its segment's LineString."""
    return {
        "type": "FeatureCollection",
        "features": [
            {
                "type": "Feature",
                "geometry": {
                    "type": "LineString",
                    "coordinates": geometry[(r["line"], r["segment"])],
                },
                "properties": r,
            }
            for r in rows
            if (r["line"], r["segment"]) in geometry
        ],
    }


def segment_geometry(network_path: str | None) -> dict[SegmentId, list]:
    from services.defaults import load_network

    network = load_network(network_path)
    return {
        (line.id, seg.id): line.segment_lonlat(seg).tolist()
        for line in network.lines.values()
        for seg in line.segments
    }


def main_export(
    conf: RuntimeConfig,
    what: str,
    fmt: str,
    network_path: str | None = None,
    timeout: float = QUERY_TIMEOUT_S,
    out: TextIO = sys.stdout,
) -> int:
    with open_session(conf) as session:
        if what == "states":
            states = query_states(session, conf.ns, timeout=timeout)
            rows, columns = [state_row(s) for s in states], STATE_COLUMNS
        else:
            alerts = query_alerts(session, conf.ns, timeout)
            rows, columns = [alert_row(a) for a in alerts], ALERT_COLUMNS
    rows.sort(key=lambda r: (r["line"], r["segment"]))
    if fmt == "csv":
        out.write(to_csv(rows, columns))
    else:
        json.dump(to_geojson(rows, segment_geometry(network_path)), out)
        out.write("\n")
    return 0


def _iso(t: float | None) -> str:
    if t is None:
        return "-"
    return datetime.fromtimestamp(t, UTC).isoformat(timespec="minutes")


# --- command lines ----------------------------------------------------------------------------


def seconds(text: str) -> float:
    """A positive, finite number of seconds (``--timeout``)."""
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not value > 0 or value == math.inf:
        raise argparse.ArgumentTypeError(f"{text!r} is not a positive number of seconds")
    return value


def add_query_arguments(parser: argparse.ArgumentParser, *, timeout: bool = True) -> None:
    """What every question to the running system takes: the Zenoh flags and ``--timeout``."""
    add_zenoh_arguments(parser, mode=False)
    if timeout:
        parser.add_argument(
            "--timeout",
            type=seconds,
            default=QUERY_TIMEOUT_S,
            metavar="S",
            help="seconds to wait for the whole answer (default: %(default)g)",
        )


status_add_arguments = alerts_add_arguments = add_query_arguments


def status_run(args: argparse.Namespace) -> int:
    return main_status(config_from_args(args), args.timeout)


def state_add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "segment", metavar="LINE/SEGMENT", help="e.g. L1/s00042, or L1/** for a line"
    )
    add_network_argument(parser, "the lines' names and speeds")
    add_limits_argument(parser, "the limits file the services apply: the lines' speed classes")
    add_query_arguments(parser)


def state_run(args: argparse.Namespace) -> int:
    return main_state(
        config_from_args(args),
        args.segment,
        args.timeout,
        network_path=args.network,
        limits_path=args.limits,
    )


def alerts_run(args: argparse.Namespace) -> int:
    return main_alerts(config_from_args(args), args.timeout)


def plan_add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "what",
        nargs="?",
        choices=["inspection", "maintenance"],
        default="inspection",
        help="inspection (the default): where to send the recording car, the planner's "
        "ranking of TRC runs by value of information, or alerting's ranking of segments "
        "without a planner; maintenance: the tamping plan (planning)",
    )
    parser.add_argument(
        "--limit", type=int, default=PLAN_ROWS, help="inspection rows to show (default %(default)s)"
    )
    parser.add_argument("--weeks", type=int, help="maintenance: plan this many weeks instead")
    parser.add_argument("--budget", type=float, help="maintenance: plan under this budget")
    output = parser.add_mutually_exclusive_group()
    output.add_argument("--json", action="store_const", const="json", dest="format")
    output.add_argument("--csv", action="store_const", const="csv", dest="format")
    add_query_arguments(parser)


def plan_run(args: argparse.Namespace) -> int:
    if args.what == "maintenance":
        return maintenance_plan.main(
            config_from_args(args),
            weeks=args.weeks,
            budget=args.budget,
            fmt=args.format or "table",
            timeout=args.timeout,
        )
    if args.weeks is not None or args.budget is not None or args.format is not None:
        raise ValueError("--weeks, --budget, --json and --csv are for `plan maintenance`")
    return main_plan(config_from_args(args), args.limit, args.timeout)


def export_add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("what", choices=["states", "alerts"])
    parser.add_argument("--format", choices=["csv", "geojson"], default="csv")
    add_network_argument(parser, "the geometry")
    add_query_arguments(parser)


def export_run(args: argparse.Namespace) -> int:
    return main_export(config_from_args(args), args.what, args.format, args.network, args.timeout)
