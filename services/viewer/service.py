"""`trackfusion viewer`: the thin adapter around :mod:`services.viewer.core`.

Subscribes ``{ns}/state/**``, ``{ns}/index/**``, ``{ns}/trc/**``, ``{ns}/alert/**``,
``{ns}/gps/*``, ``{ns}/health/stack``, ``{ns}/viewer/select`` and the planner's
``{ns}/plan/maintenance`` latest-only (``ServiceRuntime.subscribe``: a Zenoh
``RingChannel`` each: when the viewer falls behind, the oldest samples are dropped and the
pipeline never waits for it). The runtime's per-subscription workers decode (errors become
dead letters) and hand them to one bounded inbox
(:class:`~services.runtime.inbox.LatestInbox`) in which a newer state or index of a
segment and event-day, a newer fix of a train, or a newer plan, replaces the held one
(alerts and TRC records queue); ONE worker thread takes everything held at once, hands it
to the core and lets the core write what is due, so only that thread touches the
recording. A slow browser makes Rerun's log calls wait; the inbox then coalesces and the
Zenoh callbacks still never wait. The liveliness tokens (``{ns}/alive/**``) go to a set
the worker hands to the core for the health board.

:func:`main_select` is ``trackfusion viewer select LINE/SEGMENT``: it publishes a
ViewerSelect that a running viewer answers by plotting that segment in its "selected" row.

Sinks (:class:`Sink`): ``rrd`` writes a recording file, ``web`` serves the gRPC log
stream and the web viewer and prints the viewer's URL on stdout, ``spawn`` starts the
native viewer. :func:`default_sink` picks spawn with a display, else web.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
import threading
import time
import uuid
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Literal, TextIO
from urllib.parse import quote

import rerun as rr
import zenoh

from schemas import (
    Alert,
    GpsFix,
    MaintenancePlan,
    Message,
    OnboardIndex,
    SchemaError,
    SegmentState,
    StackHealth,
    TrcRecord,
    ViewerSelect,
    decode,
    encode,
    keys,
)
from services.defaults import add_network_argument, load_network, network_name
from services.runtime.config import (
    RuntimeConfig,
    add_zenoh_arguments,
    config_from_args,
    zenoh_config,
)
from services.runtime.inbox import LatestInbox
from services.runtime.service import ServiceRuntime, configure_logging
from services.viewer.core import (
    DEFAULT_LIVE_FLUSH_S,
    DEFAULT_PLOT_FLUSH_S,
    DEFAULT_WORST_N,
    ViewerCore,
    coalesce_key,
    message_version,
)
from track.segments import KnownSegments

log = logging.getLogger(__name__)

SERVICE = "viewer"
APP_ID = "TrackFusion"
INBOX_CAPACITY = 8192  # keys (and, apart, alerts + TRC records) waiting for the worker
SUBSCRIPTION_CAPACITY = 1024  # per RingChannel
# What Rerun's gRPC server keeps for browsers that connect later (it drops the oldest
# temporal data beyond it; static data and blueprints are kept). A connecting browser is
# first sent a copy of it, so the process may hold about twice this.
SERVER_MEMORY_LIMIT = "32MiB"
DEFAULT_WEB_PORT = 9090
DEFAULT_GRPC_PORT = 9876


@dataclass(frozen=True)
class Sink:
    """Where the recording goes: ``rrd`` (``path``), ``web`` or ``spawn``."""

    kind: Literal["rrd", "web", "spawn"]
    path: Path | None = None
    web_port: int = DEFAULT_WEB_PORT
    grpc_port: int = DEFAULT_GRPC_PORT

    def __post_init__(self) -> None:
        if self.kind not in ("rrd", "web", "spawn"):
            raise ValueError(f"sink: unknown kind {self.kind!r}")
        if (self.kind == "rrd") != (self.path is not None):
            raise ValueError("sink: a path is needed for, and only for, kind 'rrd'")


def default_sink(env: Mapping[str, str], **ports: int) -> Sink:
    """The native viewer where there is a display (``DISPLAY``/``WAYLAND_DISPLAY``), else web."""
    has_display = bool(env.get("DISPLAY") or env.get("WAYLAND_DISPLAY"))
    return Sink("spawn" if has_display else "web", **ports)


def web_viewer_url(grpc_url: str, web_port: int, host: str = "127.0.0.1") -> str:
    """The address that opens the web viewer connected to ``grpc_url``."""
    return f"http://{host}:{web_port}/?url={quote(grpc_url, safe='')}"


def open_sink(rec: rr.RecordingStream, sink: Sink, out: TextIO) -> str | None:
    """Attach ``sink`` to ``rec``; for ``web`` print the viewer's URL on ``out`` and return it."""
    match sink.kind:
        case "rrd":
            assert sink.path is not None
            sink.path.parent.mkdir(parents=True, exist_ok=True)
            rec.save(sink.path)
            log.info("%s: recording to %s", SERVICE, sink.path)
        case "web":
            # newest first: a browser that connects late draws the current state at once and
            # fills the history in backwards
            grpc_url = rec.serve_grpc(
                grpc_port=sink.grpc_port,
                server_memory_limit=SERVER_MEMORY_LIMIT,
                newest_first=True,
            )
            rr.serve_web_viewer(web_port=sink.web_port, open_browser=False, connect_to=grpc_url)
            url = web_viewer_url(grpc_url, sink.web_port)
            print(url, file=out, flush=True)  # the command's output: where to point a browser
            log.info("%s: web viewer at %s (log stream %s)", SERVICE, url, grpc_url)
            return url
        case "spawn":
            rerun_binary = Path(sys.executable).parent / "rerun"  # the venv's, not PATH's
            rr.spawn(
                port=sink.grpc_port,
                recording=rec,
                executable_path=str(rerun_binary) if rerun_binary.is_file() else None,
            )
    return None


_SUBSCRIPTIONS: dict[str, type[Message]] = {
    "state": SegmentState,
    "index": OnboardIndex,
    "trc": TrcRecord,
    "alert": Alert,
    "gps": GpsFix,
    "health": StackHealth,
    "select": ViewerSelect,
    "plan": MaintenancePlan,
}
SELECT_TIMEOUT_S = 5.0  # `viewer select`: how long to wait for a running viewer to listen
STATE_QUERY_TIMEOUT_S = 10.0  # the start-up q/state query (ends sooner when all reply)


class ViewerAdapter:
    """Subscriptions → inbox → one worker → :class:`ViewerCore`."""

    def __init__(
        self,
        rt: ServiceRuntime,
        core: ViewerCore,
        *,
        known: KnownSegments | None = None,
        on_logged: Callable[[int], None] | None = None,
    ) -> None:
        self.rt = rt
        self.core = core
        # what the map draws: a message on a segment it does not have is a dead letter, so
        # a sender cannot grow the viewer's per-segment memory with ids that do not exist
        self.known = known
        # the viewer writes only the newest state, index, fix of a key (coalesce_key) anyway
        self.inbox: LatestInbox[Message] = LatestInbox(
            INBOX_CAPACITY, key=coalesce_key, version=message_version
        )
        self._on_logged = on_logged
        self._worker: threading.Thread | None = None
        self._alive_lock = threading.Lock()
        self._alive: dict[tuple[str, str], bool] = {}  # (service, instance) -> token present

    def start(self) -> None:
        ns = self.rt.ns
        special = {
            "gps": keys.gps_all(ns),
            "health": keys.stack_health(ns),
            "select": keys.viewer_select(ns),
            "plan": keys.maintenance_plan(ns),
        }
        for kind, message_type in _SUBSCRIPTIONS.items():
            key = special.get(kind) or keys.segment_keys(ns, kind)
            self.rt.subscribe(
                key,
                self._decoder(kind, message_type),
                capacity=SUBSCRIPTION_CAPACITY,
            )
        self.rt.undeclare_at_close(
            self.rt.session.liveliness().declare_subscriber(
                keys.alive_all(ns), self._on_alive, history=True
            )
        )
        self._worker = self.rt.spawn(self._work, name=f"{SERVICE}:rerun")
        self.rt.spawn(self._ask_states, name=f"{SERVICE}:q-state")

    def _ask_states(self) -> None:
        """Once at start, after subscribing: the newest state of every segment from
        filtering's ``q/state``, taken like publications, so that the map is coloured at
        once rather than segment by segment as states change (a segment changing rarely,
        would stay grey until then). A reply that
        does not decode or disagrees with its key is a dead letter."""
        ns = self.rt.ns
        for key, payload in self.rt.ask(keys.q_state_all(ns), STATE_QUERY_TIMEOUT_S):
            if self.rt.stopping:
                return
            try:
                line, segment = keys.parse_q_state(key)
                self._accept("state", SegmentState, keys.state(ns, line, segment), payload)
            except SchemaError as exc:
                self.rt.deadletters.reject(key, str(exc), payload)
        # then the planner's current plan: it publishes only when it plans anew
        for key, payload in self.rt.ask(keys.q_maintenance_plan(ns), STATE_QUERY_TIMEOUT_S):
            if self.rt.stopping:
                return
            try:
                self._accept("plan", MaintenancePlan, keys.maintenance_plan(ns), payload)
            except SchemaError as exc:
                self.rt.deadletters.reject(key, str(exc), payload)

    def _accept(self, kind: str, message_type: type[Message], key: str, payload: bytes) -> None:
        """Decode and check one message and queue it for the recording; SchemaError says
        why not."""
        message = decode(payload, message_type)
        keys.check_key(key, message)
        if self.known is not None and kind not in ("gps", "health", "plan"):
            self.known.check(message)
        self.inbox.put(message)

    def _decoder(self, kind: str, message_type: type[Message]) -> Callable[[zenoh.Sample], None]:
        def on_sample(sample: zenoh.Sample) -> None:
            # runs in the runtime's worker for this subscription; SchemaError -> dead letter
            self._accept(kind, message_type, str(sample.key_expr), sample.payload.to_bytes())

        return on_sample

    def _on_alive(self, sample: zenoh.Sample) -> None:
        """A liveliness token appeared or went (Zenoh's callback: only a set update)."""
        try:
            service, instance = keys.parse_alive(str(sample.key_expr))
        except ValueError:
            return  # not a service token
        with self._alive_lock:
            self._alive[(service, instance)] = sample.kind == zenoh.SampleKind.PUT

    def _work(self) -> None:
        core = self.core
        while True:
            # the timeout lets due writes and a pending blueprint go out when messages stop
            batch = self.inbox.take(timeout=max(0.05, min(core.live_flush_s, 1.0)))
            if batch is None:
                break
            now = time.monotonic()
            with self._alive_lock:
                alive = dict(self._alive)
            try:
                core.set_alive(alive)
                core.take(batch)
                core.flush(now)
            except Exception:  # a bad batch must not end the viewer
                log.exception("%s: logging a batch of %d failed", SERVICE, len(batch))
                core.handled += len(batch)
            if batch and self._on_logged is not None:
                self._on_logged(core.handled)
        core.flush(time.monotonic(), force=True)

    def finish(self) -> None:
        """Log what is queued, then end the worker (before the recording is closed)."""
        self.inbox.close()
        if self._worker is not None:
            self._worker.join()
        if self.inbox.dropped:
            log.warning("%s: dropped %d messages (viewer behind)", SERVICE, self.inbox.dropped)
        log.info(
            "%s: %d messages superseded before logging, %d plot rows written, %d plot generations",
            SERVICE,
            self.inbox.superseded,
            self.core.rows_written,
            self.core.generations,
        )


def main(
    conf: RuntimeConfig,
    network_path: str | Path | None,
    sink: Sink,
    *,
    worst_n: int = DEFAULT_WORST_N,
    plot_flush_s: float = DEFAULT_PLOT_FLUSH_S,
    live_flush_s: float = DEFAULT_LIVE_FLUSH_S,
    stop: threading.Event | None = None,
    handle_signals: bool = True,
    on_logged: Callable[[int], None] | None = None,
    out: TextIO | None = None,
) -> int:
    """Run the viewer until ``stop`` is set or SIGINT/SIGTERM; 0.

    ``on_logged(total)`` is called by the logging worker after every batch (tests wait on
    it); the recording is flushed and its sink closed before returning.
    """
    network = load_network(network_path)  # ValueError: the CLI exits 2 with the reason
    rec = rr.RecordingStream(APP_ID, recording_id=uuid.uuid4())
    try:
        open_sink(rec, sink, out if out is not None else sys.stdout)
        core = ViewerCore(
            rec,
            network,
            worst_n=worst_n,
            plot_flush_s=plot_flush_s,
            live_flush_s=live_flush_s,
        )
        core.start(time.monotonic())
        with ServiceRuntime(SERVICE, conf, handle_signals=handle_signals, stop_event=stop) as rt:
            known = KnownSegments.of(network, network_name(network_path))
            adapter = ViewerAdapter(rt, core, known=known, on_logged=on_logged)
            adapter.start()
            try:
                return rt.run()
            finally:
                adapter.finish()
                log.info("%s: %d messages logged", SERVICE, core.handled)
    finally:
        rec.flush(timeout_sec=10.0)
        rec.disconnect()  # closes the file (with its footer), the gRPC server or connection


def parse_segment(text: str) -> tuple[str, str]:
    """``LINE/SEGMENT`` (e.g. ``L1/s00042``) → ``(line, segment)``; ValueError otherwise."""
    line, _, segment = text.partition("/")
    if not line or not segment or "/" in segment:
        raise ValueError(f"segment: expected LINE/SEGMENT (e.g. L1/s00042), got {text!r}")
    ViewerSelect(line=line, segment=segment)  # the id checks (SchemaError is a ValueError)
    return line, segment


def main_select(conf: RuntimeConfig, segment: str, timeout_s: float = SELECT_TIMEOUT_S) -> int:
    """``trackfusion viewer select LINE/SEGMENT``: publish a ViewerSelect once a viewer
    listens; 0, or 1 if no viewer subscribed within ``timeout_s``."""
    line, seg = parse_segment(segment)
    with zenoh.open(zenoh_config(conf)) as session:
        publisher = session.declare_publisher(keys.viewer_select(conf.ns))
        matched = threading.Event()
        listener = publisher.declare_matching_listener(
            lambda status: status.matching and matched.set()
        )
        try:
            # the router knows a viewer's subscription: the put reaches it
            if not publisher.matching_status.matching and not matched.wait(timeout_s):
                print(f"viewer select: no viewer listens in namespace {conf.ns}", file=sys.stderr)
                return 1
            publisher.put(encode(ViewerSelect(line=line, segment=seg)))
        finally:
            listener.undeclare()
            publisher.undeclare()
    print(f"viewer: plotting {line}/{seg} in the selected row")
    return 0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """``trackfusion viewer [select LINE/SEGMENT]``."""
    parser.description = (
        "Subscribe to {ns}/state/**, index/**, trc/**, alert/**, gps/* and plan/maintenance "
        "(dropping the oldest when behind) and log them to Rerun on the event_time timeline. "
        "Default sink: the native viewer when DISPLAY/WAYLAND_DISPLAY is set, else the web "
        "viewer (its URL is printed on stdout)."
    )
    add_network_argument(parser, "the map")
    sink = parser.add_mutually_exclusive_group()
    sink.add_argument(
        "--rrd", metavar="FILE", type=Path, help="save the recording to FILE (headless)"
    )
    sink.add_argument(
        "--web", action="store_true", help="serve the web viewer and print its URL on stdout"
    )
    sink.add_argument("--spawn", action="store_true", help="start the native viewer")
    parser.add_argument(
        "--web-port", type=int, default=DEFAULT_WEB_PORT, help="web viewer HTTP port (%(default)s)"
    )
    parser.add_argument(
        "--grpc-port",
        type=int,
        default=DEFAULT_GRPC_PORT,
        help="Rerun gRPC log stream port (%(default)s)",
    )
    parser.add_argument(
        "--worst",
        type=int,
        default=DEFAULT_WORST_N,
        help="worst segments plotted beside the map (%(default)s)",
    )
    parser.add_argument(
        "action",
        nargs="?",
        choices=["select"],
        help="select LINE/SEGMENT: plot that segment in the running viewer's selected row",
    )
    parser.add_argument("segment", nargs="?", metavar="LINE/SEGMENT", help="e.g. L1/s00042")
    add_zenoh_arguments(parser)


def run(args: argparse.Namespace) -> int:
    configure_logging(args.log_level)
    if args.action == "select":  # a tool: tell the running viewer, then exit
        if args.segment is None:
            raise SystemExit("viewer select: which segment? e.g. viewer select L1/s00042")
        try:
            return main_select(config_from_args(args), args.segment)
        except ValueError as exc:
            raise SystemExit(f"viewer select: {exc}") from None
    ports = {"web_port": args.web_port, "grpc_port": args.grpc_port}
    if args.rrd is not None:
        sink = Sink("rrd", path=args.rrd, **ports)
    elif args.web:
        sink = Sink("web", **ports)
    elif args.spawn:
        sink = Sink("spawn", **ports)
    else:  # the environment is read here, at the edge, and passed down
        sink = default_sink(os.environ, **ports)
    return main(config_from_args(args), args.network, sink, worst_n=args.worst)
