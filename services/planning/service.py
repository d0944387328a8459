"""`trackfusion planning`: the thin adapter around :mod:`services.planning.core`.

Subscribes ``{ns}/state/**`` (SegmentState), ``{ns}/model/**`` (DegradationPosterior on
``model/degradation/{group}``; calibrations are not the planner's) and
``{ns}/maintenance/**`` (a tamping starts the minimum interval); all feed ONE inbox drained by
ONE worker, which only updates the core. A second thread, the planner, makes the plan when
something changed, from a snapshot of the core's inputs taken under the lock (the worker goes
on folding states while it plans): once nothing new arrived for ``replan.quiet_s``, and at most
``replan.max_wait_s`` after the first change, one plan at a time, so a flood of states gives a
few plans, never a storm. Each plan goes out on ``{ns}/plan/maintenance`` (cached for late
joiners) and answers ``{ns}/q/plan/maintenance``; a query with ``weeks`` or ``budget`` is
planned anew by the planner thread, which replies. At start it asks ``{ns}/q/state/**`` and
``{ns}/model/**`` for what was published before it ran, and rebuilds its inputs from them;
the one thing no message holds any more, each segment's evidence from its closed TRC
intervals, it keeps in its SQLite file (``--db``, :mod:`services.planning.evidence_store`), written
before every plan and when it stops.
"""

from __future__ import annotations

import argparse
import logging
import math
import queue
import sqlite3
import threading
import time
from pathlib import Path

import zenoh

from schemas import (
    DegradationPosterior,
    MaintenanceEvent,
    MaintenancePlan,
    PlannedTamping,
    SchemaError,
    SegmentState,
    TrcRunValue,
    decode,
    encode,
    keys,
)
from services.defaults import default_file, load_network, network_name
from services.limits import (
    DEFAULT_LIMITS_FILE,
    add_limits_argument,
    load_immediate_action,
    load_limits,
    network_line_speeds,
)
from services.planning.core import Plan, PlanningConfig, PlanningCore, SegmentRef
from services.planning.evidence_store import EvidenceStore
from services.runtime.config import (
    RuntimeConfig,
    add_zenoh_arguments,
    config_from_args,
    default_db,
    read_json5,
)
from services.runtime.event_time import NewestTimes
from services.runtime.service import ServiceRuntime, configure_logging
from track.segments import KnownSegments

log = logging.getLogger(__name__)

SERVICE = "planning"
DEFAULT_PLANNING_FILE = default_file("planning.json5")
START_QUERY_TIMEOUT_S = 10.0  # the start-up q/state and model queries
TRC_VALUE_MAX_SEGMENTS = 20_000  # the TRC ranking costs 9 forecasts a segment: not beyond
QUORUM = 3  # segments whose newest state times must agree on "now" (one far-future outlier
# cannot move the plan's weeks)


def load_planning_config(path: str | Path = DEFAULT_PLANNING_FILE) -> PlanningConfig:
    """Read ``services/defaults/planning.json5`` (or ``path``); ValueError says what to fix."""
    try:
        return PlanningConfig.from_dict(read_json5(path))
    except (OSError, ValueError) as exc:
        raise ValueError(f"planning config {path}: {exc}") from None


def network_segments(network) -> list[SegmentRef]:
    """The segments of a network, lines in chainage order."""
    return [SegmentRef(line.id, seg.id, seg.length_m) for line, seg in network.segments()]


def to_message(
    plan: Plan | None,
    *,
    computed_at: float | None,
    eps: float,
    budget: float | None,
    horizon_weeks: int,
    version: int,
    trc_lines: list[tuple[str, float, int]] = (),
) -> MaintenancePlan:
    """The wire form of a plan (``plan`` None: ``no_data``) and the TRC ranking."""
    if plan is None:
        return MaintenancePlan(
            t=None, computed_at=computed_at, horizon_weeks=horizon_weeks, eps=eps,
            status="no_data", objective=0.0, bound=0.0, gap=0.0, solve_s=0.0, km_per_week=[],
            possessions=0, money=0.0, budget=budget, segments=0, without_model=0,
            version=version, rows=[],
        )  # fmt: skip
    rows = [PlannedTamping(**vars(r)) for r in plan.rows]  # the same fields, by name
    return MaintenancePlan(
        t=plan.t,
        computed_at=computed_at,
        horizon_weeks=plan.horizon_weeks,
        eps=eps,
        status=plan.status if plan.segments else "no_data",
        objective=plan.objective,
        bound=plan.bound,
        gap=plan.gap,
        solve_s=plan.seconds,
        km_per_week=plan.km_per_week,
        possessions=plan.possessions,
        money=plan.money,
        budget=budget,
        segments=plan.segments,
        without_model=plan.without_model,
        version=version,
        rows=rows,
        trc_lines=[TrcRunValue(line=ln, value=v, segments=n) for ln, v, n in trc_lines],
    )


def plan_parameters(parameters) -> tuple[int | None, float | None]:
    """``weeks`` and ``budget`` of a query's parameters; ValueError saying which is bad."""
    weeks = parameters.get("weeks")
    budget = parameters.get("budget")
    try:
        w = int(weeks) if weeks is not None else None
        if w is not None and not 1 <= w <= 104:
            raise ValueError
    except ValueError:
        raise ValueError(f"weeks: not a whole number of weeks from 1 to 104: {weeks!r}") from None
    try:
        b = float(budget) if budget is not None else None
        if b is not None and not (math.isfinite(b) and b >= 0):
            raise ValueError
    except ValueError:
        raise ValueError(f"budget: not a number >= 0: {budget!r}") from None
    return w, b


class PlanningAdapter:
    """Decode → core (worker); plan → encode → put (planner thread); queryable."""

    def __init__(
        self, rt: ServiceRuntime, core: PlanningCore, store: EvidenceStore, network: str
    ) -> None:
        self.rt = rt
        self.core = core
        self.store = store
        self.known = KnownSegments(core.index, network)  # states of others are refused
        self.lock = threading.Lock()  # the worker writes the core, the planner snapshots it
        self.changed = threading.Condition(self.lock)
        self.first_change: float | None = None  # monotonic s of the first unplanned change
        self.last_change = 0.0
        self.plans = 0
        self.latest: bytes = encode(self._message(None, None))
        self.requests: queue.Queue[tuple[zenoh.Query, int | None, float | None]] = queue.Queue()
        self.times = NewestTimes(QUORUM)

    def _message(self, plan: Plan | None, now_t: float | None, budget=None, weeks=None, trc=()):
        cfg = self.core.config
        return to_message(
            plan,
            computed_at=now_t,
            eps=cfg.eps,
            budget=budget if budget is not None else cfg.budget,
            horizon_weeks=weeks or cfg.horizon_weeks,
            version=self.plans,
            trc_lines=list(trc),
        )

    def start(self) -> None:
        ns = self.rt.ns
        saved = self.store.load()
        self.core.restore_evidence(saved)
        if saved:
            log.info("evidence of %d segments from %s", len(saved), self.store.path)
        self.out = self.rt.reliable_publisher()
        subscriptions = {
            "state": keys.segment_keys(ns, "state"),
            "model": keys.model_all(ns),
            "maintenance": keys.segment_keys(ns, "maintenance"),
        }
        inbox = self.rt.subscribe_in_order(subscriptions, self.handle, reliable=True)
        self.rt.declare_queryable(keys.q_maintenance_plan(ns), self.on_query)
        for selector, kind, as_key in (
            (keys.model_all(ns), "model", lambda k: k),
            (keys.q_state_all(ns), "state", lambda k: keys.state(ns, *keys.parse_q_state(k))),
        ):
            for key, payload in self.rt.ask(selector, START_QUERY_TIMEOUT_S):
                try:
                    inbox.put(kind, as_key(key), payload)
                except SchemaError as exc:
                    log.warning("%s: %s", selector, exc)
        self.rt.spawn(self._planner, name="planning:planner")

    # --- the worker: inputs into the core ------------------------------------------------

    def handle(self, kind: str, key: str, payload: bytes) -> None:
        if kind == "model":
            if keys.model_kind(key) != "degradation":
                return  # calibrations: not the planner's
            message = decode(payload, DegradationPosterior)
        else:
            message = decode(payload, SegmentState if kind == "state" else MaintenanceEvent)
        keys.check_key(key, message)
        if kind != "model":
            self.known.check(message)
        with self.lock:
            match message:
                case SegmentState():
                    changed = self.core.on_state(message)
                    if changed:
                        self.times.note((message.line, message.segment), message.t)
                case DegradationPosterior():
                    changed = self.core.on_posterior(message)
                case MaintenanceEvent():
                    changed = self.core.on_maintenance(message)
            if changed:
                now = time.monotonic()
                self.first_change = self.first_change or now
                self.last_change = now
                self.changed.notify()

    @property
    def now_t(self) -> float | None:
        """The newest state time ``QUORUM`` segments agree on (the newest of fewer)."""
        return self.times.kth(min(QUORUM, len(self.times)))

    # --- the planner thread ----------------------------------------------------------------

    def _due(self) -> float | None:
        """Seconds until a re-plan is due (0: now); None when nothing changed."""
        if self.first_change is None:
            return None
        cfg = self.core.config
        now = time.monotonic()
        return max(
            0.0,
            min(
                self.last_change + cfg.replan_quiet_s - now,
                self.first_change + cfg.replan_max_wait_s - now,
            ),
        )

    def _planner(self) -> None:
        while not self.rt.stopping:
            try:
                query, weeks, budget = self.requests.get_nowait()
            except queue.Empty:
                pass
            else:
                self._answer(query, weeks, budget)
                continue
            with self.lock:
                due = self._due()
                if due is None or due > 0:
                    self.changed.wait(min(due if due is not None else 0.5, 0.5))
                    continue
                self.first_change = None
                now_t = self.now_t
                evidence = self.core.take_changed_evidence()
                inputs = None if now_t is None else self.core.snapshot()
            self.save_evidence(evidence)
            if inputs is None:
                continue
            # planned outside the lock: the worker goes on folding states into the core
            started = time.perf_counter()
            plan = inputs.plan(now_t)
            trc = []
            if plan.segments <= TRC_VALUE_MAX_SEGMENTS:
                trc = inputs.trc_value(now_t)
            self.plans += 1
            message = self._message(plan, now_t, trc=trc)
            payload = encode(message)
            self.latest = payload
            self.out.put(keys.maintenance_plan(self.rt.ns), payload)
            log.info(
                "plan %d: %d segments, %d tamped in %d possessions, %.1f km, gap %.3g %% (%s), "
                "%.2f s",
                self.plans, plan.segments, sum(r.week >= 0 for r in plan.rows), plan.possessions,
                sum(plan.km_per_week), 100 * plan.gap, plan.status,
                time.perf_counter() - started,
            )  # fmt: skip

    def save_evidence(self, evidence=None) -> None:
        """Persist the evidence that changed (taken from the core when ``evidence`` is None).
        A failed write puts it back, to be written with the next plan."""
        if evidence is None:
            with self.lock:
                evidence = self.core.take_changed_evidence()
        try:
            self.store.save(evidence)
        except sqlite3.Error as exc:
            log.error("evidence %s: not written (%s); retried with the next plan",
                      self.store.path, exc)  # fmt: skip
            with self.lock:
                self.core.evidence_changed.update(
                    self.core.index[(line, segment)] for line, segment, _ in evidence
                )

    def _answer(self, query: zenoh.Query, weeks: int | None, budget: float | None) -> None:
        try:
            with self.lock:
                now_t = self.now_t
                inputs = self.core.snapshot()
            plan = None if now_t is None else inputs.plan(now_t, weeks=weeks, budget=budget)
            payload = encode(self._message(plan, now_t, budget, weeks))
            query.reply(keys.q_maintenance_plan(self.rt.ns), payload)
        except Exception as exc:  # the question fails, not the planner
            log.exception("planning: answering %s", query.selector)
            query.reply_err(f"{type(exc).__name__}: {exc}".encode())
        finally:
            query.drop()

    # --- queryable (callback: short) -------------------------------------------------------

    def on_query(self, query: zenoh.Query) -> None:
        try:
            weeks, budget = plan_parameters(query.parameters)
        except ValueError as exc:
            query.reply_err(str(exc).encode())
            return
        if weeks is None and budget is None:
            query.reply(keys.q_maintenance_plan(self.rt.ns), self.latest)
            return
        self.requests.put((query, weeks, budget))  # the planner replies
        with self.lock:
            self.changed.notify()


def main(
    conf: RuntimeConfig,
    *,
    planning_config: str | Path | None = None,
    limits: str | Path | None = None,
    network: str | Path | None = None,
    db: str | Path | None = None,
    stop: threading.Event | None = None,
    handle_signals: bool = True,
) -> int:
    """Run the planner until ``stop`` is set or SIGINT/SIGTERM; 0. ``db``: the evidence file
    (default ``./var/planning-{instance}.sqlite``)."""
    limits_path = limits or DEFAULT_LIMITS_FILE
    loaded = load_network(network)
    table = load_limits(limits_path, network_line_speeds(loaded))
    core = PlanningCore(
        load_planning_config(planning_config or DEFAULT_PLANNING_FILE),
        table,
        load_immediate_action(limits_path, table),
        network_segments(loaded),
    )
    store = EvidenceStore(db or default_db(SERVICE, conf.instance))
    try:
        with ServiceRuntime(SERVICE, conf, handle_signals=handle_signals, stop_event=stop) as rt:
            adapter = PlanningAdapter(rt, core, store, network_name(network))
            adapter.start()
            code = rt.run()
        adapter.save_evidence()  # the workers are stopped: what changed since the last plan
        return code
    finally:
        store.close()


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """``trackfusion planning``."""
    parser.description = (
        "Subscribe to {ns}/state/**, {ns}/model/** and {ns}/maintenance/**; publish the "
        "tamping plan on {ns}/plan/maintenance and answer {ns}/q/plan/maintenance."
    )
    parser.add_argument(
        "--config-planning",
        metavar="FILE",
        type=Path,
        default=DEFAULT_PLANNING_FILE,
        help="costs, capacity, risk limit, horizon, JSON5 (default: %(default)s)",
    )
    add_limits_argument(parser, "intervention and immediate-action limits per line, JSON5")
    parser.add_argument(
        "--network", metavar="FILE.geojson", help="segments and their order (default: the demo)"
    )
    parser.add_argument(
        "--db",
        metavar="FILE",
        type=Path,
        help="SQLite file of each segment's on-board evidence from its closed TRC intervals "
        "(default: ./var/planning-{instance}.sqlite)",
    )
    add_zenoh_arguments(parser)


def run(args: argparse.Namespace) -> int:
    configure_logging(args.log_level)
    return main(
        config_from_args(args),
        planning_config=args.config_planning,
        limits=args.limits,
        network=args.network,
        db=args.db,
    )
