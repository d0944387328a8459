"""`trackfusion alerting`: the thin adapter around :mod:`services.alerting.core`.

Subscribes ``{ns}/state/**`` (SegmentState), ``{ns}/trc/**`` (TrcRecord, to learn each
line's TRC schedule) and ``{ns}/maintenance/**`` (MaintenanceEvent: detected tampings and
the reports that confirm them); the subscriptions feed the runtime's inbox drained by ONE
worker, so the core sees one ordered stream and needs no lock of its own (the queryables take the
adapter's lock to read it). Alerts go out with ``session.put`` on ``{ns}/alert/{line}/{segment}``;
``{ns}/q/alerts`` and ``{ns}/q/plan`` answer from the core with a RaisedAlerts and an
InspectionPlan (schemas/README.md). At start it also asks ``{ns}/q/state/**`` for every
segment's newest state and queues the replies like publications (also the states filtering's
outbox no longer retains; a repeated state changes nothing).
The raised set, the segments' last states and the TRC runs persist in SQLite
(``./var/alerting-{instance}.sqlite`` by default).
"""

from __future__ import annotations

import argparse
import logging
import threading
from pathlib import Path

import zenoh

from schemas import (
    Alert,
    InspectionPlan,
    MaintenanceEvent,
    RaisedAlerts,
    SegmentState,
    TrcRecord,
    decode,
    encode,
    keys,
)
from services.alerting.core import AlertingConfig, AlertingCore
from services.alerting.store import AlertStore
from services.defaults import add_network_argument, default_file, load_network, network_name
from services.limits import (
    DEFAULT_LIMITS_FILE,
    add_limits_argument,
    load_limits,
    network_line_speeds,
)
from services.runtime.config import (
    RuntimeConfig,
    add_db_argument,
    add_zenoh_arguments,
    default_db,
    read_json5,
)
from services.runtime.service import ServiceRuntime, run_command
from track.segments import KnownSegments

log = logging.getLogger(__name__)

SERVICE = "alerting"
DEFAULT_ALERTING_FILE = default_file("alerting.json5")
STATE_QUERY_TIMEOUT_S = 10.0  # the start-up q/state query (ends sooner when all reply)


def load_alerting_config(path: str | Path = DEFAULT_ALERTING_FILE) -> AlertingConfig:
    """Read ``services/defaults/alerting.json5`` (or ``path``); ValueError says what to fix."""
    raw = read_json5(path)
    try:
        return AlertingConfig.from_dict(raw)
    except ValueError as exc:
        raise ValueError(f"alerting config {path}: {exc}") from None


_TYPES = {"state": SegmentState, "trc": TrcRecord, "maintenance": MaintenanceEvent}


class AlertingAdapter:
    """Decode → core → encode → put, persisted; one instance per running service."""

    def __init__(
        self,
        rt: ServiceRuntime,
        core: AlertingCore,
        store: AlertStore,
        known: KnownSegments | None = None,
    ) -> None:
        self.rt = rt
        self.core = core
        self.store = store
        # the network's segments: a message on another is a dead letter, so a sender
        # cannot raise alerts on, or grow the memory with, segments that do not exist
        self.known = known
        self.lock = threading.Lock()  # the worker writes the core, queryables read it
        self.published = 0

    # --- subscriptions: one queue, one worker ------------------------------------------------

    def start(self) -> None:
        ns = self.rt.ns
        subscriptions = {
            "state": keys.segment_keys(ns, "state"),
            "trc": keys.segment_keys(ns, "trc"),
            "maintenance": keys.segment_keys(ns, "maintenance"),
        }
        inbox = self.rt.subscribe_in_order(subscriptions, self.handle, reliable=True)
        self.rt.declare_queryable(keys.q_alerts(ns), self.on_query_alerts)
        self.rt.declare_queryable(keys.q_plan(ns), self.on_query_plan)
        # After subscribing (nothing newer is missed): the newest state of every segment
        # from filtering's q/state, queued like publications. A segment whose states
        # filtering's outbox no longer retains has no replay, and would otherwise be judged
        # only at its next change.
        asked = 0
        for key, payload in self.rt.ask(keys.q_state_all(ns), STATE_QUERY_TIMEOUT_S):
            try:
                line, segment = keys.parse_q_state(key)
            except ValueError as exc:
                log.warning("q/state: %s", exc)
                continue
            inbox.put("state", keys.state(ns, line, segment), payload)
            asked += 1
        log.info("alerting: %d segment states from q/state at start", asked)

    def handle(self, kind: str, key: str, payload: bytes) -> list[Alert]:
        """One message through the core; publishes and persists what it changes."""
        message_type = _TYPES[kind]
        message = decode(payload, message_type)
        keys.check_key(key, message)
        if self.known is not None:
            self.known.check(message)
        with self.lock:
            run = None
            memory = None
            detection = None
            match message:
                case SegmentState():
                    alerts = self.core.on_state(message)
                    memory = self.core.segments[(message.line, message.segment)]
                case TrcRecord():
                    alerts = []
                    if self.core.on_trc(message):
                        run = (message.line, message.run_id, message.t)
                case MaintenanceEvent():
                    alerts = self.core.on_maintenance(message)
                    where = (message.line, message.segment)
                    if self.core.detections.get(where, {}).get(message.event_id) is message:
                        detection = message  # held now: persisted
            if self.core.newest_t is not None:
                alerts += self.core.check_stale(self.core.newest_t)
        # publish, then persist: a kill in between repeats an alert rather than losing it
        for alert in alerts:
            self.rt.session.put(keys.alert(self.rt.ns, alert.line, alert.segment), encode(alert))
            log.info("%s %s %s/%s: %s", alert.status, alert.kind, alert.line, alert.segment,
                     alert.message)  # fmt: skip
        self.published += len(alerts)
        self.store.save(alerts, memory, run, detection)
        return alerts

    # --- queryables (callbacks: short, read under the lock) ------------------------------------

    def on_query_alerts(self, query: zenoh.Query) -> None:
        line = query.parameters.get("line")
        with self.lock:
            alerts = self.core.raised_alerts(line)
        query.reply(keys.q_alerts(self.rt.ns), encode(RaisedAlerts(alerts=alerts)))

    def on_query_plan(self, query: zenoh.Query) -> None:
        line = query.parameters.get("line")
        limit = query.parameters.get("limit")
        try:
            top = int(limit) if limit is not None else None
            if top is not None and top < 0:
                raise ValueError(limit)
        except ValueError:
            query.reply_err(f"limit: not a non-negative integer: {limit!r}".encode())
            return
        with self.lock:
            rows = self.core.plan(line=line)
            t = self.core.newest_t
        plan = InspectionPlan(t=t, rows=rows[:top])
        query.reply(keys.q_plan(self.rt.ns), encode(plan))


def main(
    conf: RuntimeConfig,
    *,
    alerting_config: str | Path | None = None,
    limits: str | Path | None = None,
    network: str | Path | None = None,
    db: str | Path | None = None,
    stop: threading.Event | None = None,
    handle_signals: bool = True,
) -> int:
    """Run the alerting service until ``stop`` is set or SIGINT/SIGTERM; 0. ``network``: the
    network file whose line speeds choose the speed class of lines the limits file does not
    name (``services.limits``)."""
    loaded = load_network(network) if network is not None else None
    speeds = network_line_speeds(loaded) if loaded is not None else None
    known = KnownSegments.of(loaded, network_name(network)) if loaded is not None else None
    core = AlertingCore(
        load_alerting_config(alerting_config or DEFAULT_ALERTING_FILE),
        load_limits(limits or DEFAULT_LIMITS_FILE, speeds),
    )
    db_path = Path(db) if db is not None else default_db(SERVICE, conf.instance)
    store = AlertStore(db_path)
    try:
        core.restore(*store.load())
        log.info(
            "%s: %d raised alerts, %d segments restored from %s",
            SERVICE,
            len(core.raised),
            len(core.segments),
            db_path,
        )
        with ServiceRuntime(SERVICE, conf, handle_signals=handle_signals, stop_event=stop) as rt:
            AlertingAdapter(rt, core, store, known).start()
            return rt.run()
    finally:
        store.close()


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """``trackfusion alerting``."""
    parser.description = (
        "Subscribe to {ns}/state/** and {ns}/trc/**, publish Alerts on "
        "{ns}/alert/{line}/{segment}, answer {ns}/q/alerts and {ns}/q/plan."
    )
    parser.add_argument(
        "--config-alerting",
        metavar="FILE",
        type=Path,
        default=DEFAULT_ALERTING_FILE,
        help="alerting thresholds, JSON5 (default: %(default)s)",
    )
    add_limits_argument(parser, "alert and intervention limits per line, JSON5")
    add_network_argument(
        parser,
        "its line speeds choose the speed class of lines the limits do not name",
        default="the limits file's default class",
    )
    add_db_argument(parser, SERVICE, "the raised alerts")
    add_zenoh_arguments(parser)


def run(args: argparse.Namespace) -> int:
    return run_command(
        args,
        main,
        alerting_config=args.config_alerting,
        limits=args.limits,
        network=args.network,
        db=args.db,
    )
