"""`trackfusion filtering`: the live filter bank per segment on Zenoh (thin adapter).

Subscribes ``{ns}/index/{selector}``, ``{ns}/trc/{selector}``, ``{ns}/maintenance/{selector}``
and ``{ns}/model/**``; at start asks ``{ns}/model/**`` for the latest models (the calibration
service's late-joiner queryable) and queues the replies like publications before it declares
itself ready. Every sample goes into the runtime's inbox (which never blocks Zenoh, see
:mod:`services.runtime.inbox`), read by one worker thread, so the tracker is single-threaded.
The worker takes what is queued (up to ``BATCH`` messages; one when the instance keeps up)
and hands it to :meth:`PersistentTracker.handle_batch`: decode (a malformed payload or one
disagreeing with its key → dead letter with the reason), model updates of the batch first
and coalesced (only the newest version of each model counts, the affected segments re-run
once), then the events in arrival order, all accepted inputs committed to SQLite in one
transaction → ``put`` the newest SegmentState of the changed segments on
``{ns}/state/{line}/{segment}``.

Publication rule (a SegmentState summary costs far more than folding an event, so a
backlog cannot summarise every changed segment per batch):

- a batch's events are committed before any state that depends on them is summarised or
  published (the summary is taken after the transaction, from the tracker); a batch of
  ``BACKLOG`` or more messages commits in the background while the next one folds
  (:meth:`Store.transaction`), and the segments it changed wait until that commit is done;
- the segments a batch changed are marked *dirty* (kept in the order they first became
  dirty); a segment changed again while dirty keeps its place and is published once, with
  its newest state;
- **no backlog** (fewer than ``BACKLOG`` messages queued after the batch: live, a few
  arrived meanwhile): every dirty segment is summarised and published at once;
- **backlog** (``BACKLOG`` or more queued): the oldest dirty segments are published, in chunks of
  ``SUMMARY_CHUNK``, while the time spent publishing stays within ``PUBLISH_SHARE`` of the
  time the batch took (at least one chunk per batch), so the backlog drains at nearly the
  fold's speed; the rest wait, and all are published as soon as the backlog is gone;
- at a stop the dirty segments are published for up to ``STOP_PUBLISH_S``; what is left
  is republished at the next start (every rebuilt state is).

A segment's intermediate states are therefore not all published, but its final published
state is the one of its last event, bit for bit as when stepping one message at a time.
Model updates publish their re-run states at once. The queryable
``{ns}/q/state/{selector}`` answers each matching segment's latest *published* state on
``{ns}/q/state/{line}/{segment}``.

At start the tracker is restored from the store's checkpoints and the events after them
(:meth:`PersistentTracker.restore`, see :mod:`services.filtering.coordinator`); every restored
state answers ``q/state`` at once, and is published again in the background, before any
newer one (a state committed but not yet published when the process died is then not
lost; a repeated state is harmless).
Event time only: the wall clock is never used for a state.

Detected tampings: each batch's net changes to the logs' detected tampings are published on
``{ns}/maintenance/{line}/{segment}`` once committed, through the same cached publisher: a
detection taken out of a log first, as the message it was with ``withdrawn`` true, then each
one found. Both carry a ``revision`` (:class:`Revisions`) higher than any this instance
published before, so a consumer that keeps the highest-ranked message per ``event_id``
(``MaintenanceEvent.rank``) ends on filtering's last verdict whatever the order of delivery.

Options (``services.filtering`` in the config file, overridden by the flags): ``selector``
(default ``**``), ``db`` (default ``./var/filtering-{instance}.sqlite`` with the configured
instance id, ``default`` without one, so a restarted process finds its file), ``limits``,
``network`` (a network GeoJSON file: events on segments it does not have are dead-lettered,
so a sender cannot make the instance hold segment histories for ids that do not exist, and
its line speeds choose the speed class of lines the limits file does not name; default:
none, every segment accepted).
"""

from __future__ import annotations

import argparse
import gc
import itertools
import logging
import sqlite3
import threading
import time
from contextlib import ExitStack
from pathlib import Path

import msgpack
import msgspec

from schemas import MaintenanceEvent, SegmentState, encode, keys
from schemas.keys import SegmentId
from services.defaults import add_network_argument, network_name
from services.filtering.coordinator import PersistentTracker
from services.filtering.store import Store
from services.filtering.tracker import Tracker
from services.limits import DEFAULT_LIMITS_FILE, load_limits, network_line_speeds
from services.runtime import systemd
from services.runtime.config import (
    RuntimeConfig,
    add_db_argument,
    add_zenoh_arguments,
    default_db,
    flag_values,
)
from services.runtime.delivery import MARK
from services.runtime.inbox import Inbox
from services.runtime.latest import LatestValues
from services.runtime.service import ServiceRuntime, run_command
from track.network import Network
from track.segments import KnownSegments

log = logging.getLogger(__name__)

SERVICE = "filtering"
# Queued messages handled in one store transaction when there is a backlog: the larger the
# batch, the more events a segment's per-batch work (reading its state, one fold, one
# commit) is shared by.
BATCH = 65_536
EXIT_STORE_FAILED = 74  # EX_IOERR
EXIT_SOFTWARE = 70  # EX_SOFTWARE: a bug escaped a batch
DEFAULT_SELECTOR = "**"  # the whole network
OPTIONS = ("db", "limits", "network", "selector")  # services.filtering, flags of the same names
MODEL_QUERY_TIMEOUT_S = (
    10.0  # the start-up query for the latest models (ends sooner when all reply)
)
BACKLOG = 64  # queued messages from which the inbox counts as a backlog (publication rule)
PUBLISH_SHARE = 0.25  # under a backlog: publishing time per batch, a share of the batch's time
SUMMARY_CHUNK = 8  # dirty segments summarised together (Tracker.segment_states' batch)
FREEZE_S = 5.0  # worker time between two moves of what survived into the GC's permanent generation
STOP_PUBLISH_S = 0.4  # at a stop: dirty segments published for at most this long (the
# worker drains for up to DRAIN_S = 1.5 s first and is joined within JOIN_TIMEOUT_S = 2 s)
MIGRATE_S_PER_EVENT = 25e-6  # start time allowed per stored event for a store's migration


def main(
    conf: RuntimeConfig,
    *,
    selector: str | None = None,
    db: str | Path | None = None,
    limits: str | Path | None = None,
    network: str | Path | None = None,
    stop: threading.Event | None = None,
    handle_signals: bool = True,
    freeze_gc: bool = False,
) -> int:
    """Run one filtering instance until ``stop`` is set or SIGINT/SIGTERM; returns 0.
    ``freeze_gc``: the process is this instance's own (``trackfusion filtering``), see
    :meth:`FilteringAdapter._freeze`."""
    options = conf.options(SERVICE, OPTIONS)
    selector = selector or options.get("selector") or DEFAULT_SELECTOR
    network = network or options.get("network")
    loaded = read_network(network)
    limits_table = load_limits(
        limits or options.get("limits") or DEFAULT_LIMITS_FILE,
        network_line_speeds(loaded) if loaded is not None else None,
    )
    db = db or options.get("db") or default_db(SERVICE, conf.instance)
    with ExitStack() as stack:
        store = Store(db, migrating=extend_start_timeout)
        stack.callback(store.close)  # after the runtime has joined the worker
        tracker = Tracker(limits_table.for_line, limits_table.levels)
        node = PersistentTracker(tracker, store, ns=conf.ns, known=known_segments(loaded, network))
        stack.callback(node.close)  # checkpoint at a clean stop, once the worker is joined
        rt = stack.enter_context(
            ServiceRuntime(SERVICE, conf, handle_signals=handle_signals, stop_event=stop)
        )
        FilteringAdapter(rt, node, selector, freeze_gc=freeze_gc).start()
        log.info("filtering %s: selector %s, store %s", rt.instance, selector, store.path)
        return rt.run()
    return 0  # unreachable; for type checkers


def read_network(network: str | Path | None) -> Network | None:
    """The network file ``network``, None without one; ValueError saying what to fix."""
    if network is None:
        return None
    try:
        return Network.from_geojson(Path(network))
    except (OSError, ValueError) as exc:
        raise ValueError(f"network {network}: {exc}") from None


def known_segments(network: Network | None, path: str | Path) -> KnownSegments | None:
    """The segments of the network read from the file ``path``, None without one."""
    return None if network is None else KnownSegments.of(network, network_name(path))


class Revisions:
    """The ``revision`` of each detection and withdrawal published: the wall clock in
    microseconds, strictly increasing within the process. A later verdict on an ``event_id``
    (withdrawn, found again) therefore outranks every earlier one, across restarts too as
    long as the host's clock does not step back by more than the restart took. The revision
    says which message is newer, nothing of the tamping (its times are event time); the
    stored detection keeps revision 0."""

    def __init__(self) -> None:
        self._last = 0

    def stamp(self, msg: MaintenanceEvent, *, withdrawn: bool) -> MaintenanceEvent:
        self._last = max(self._last + 1, time.time_ns() // 1000)
        return msgspec.structs.replace(msg, revision=self._last, withdrawn=withdrawn)


class FilteringAdapter:
    """Zenoh plumbing around a :class:`PersistentTracker`: inbox, worker, puts, queryable."""

    def __init__(
        self, rt: ServiceRuntime, node: PersistentTracker, selector: str, *, freeze_gc=False
    ) -> None:
        self.rt = rt
        self.node = node
        self.selector = selector
        self.latest = LatestValues()  # q/state key -> the segment's newest state
        self._republished = threading.Event()  # the restored states went out (start())
        self._republished.set()
        # changed, not yet published, oldest first: the batch that last changed each
        self.dirty: dict[SegmentId, int] = {}
        self._batches = 0  # handed to the store; the last one may be committing still
        self.inbox: Inbox | None = None
        self.freeze_gc = freeze_gc  # only where the process is this service's own
        self._frozen_at = 0.0
        self.revisions = Revisions()

    def start(self) -> None:
        ns = self.rt.ns
        self.states_out = self.rt.reliable_publisher(beside=self.node.store.path)
        restored = self.node.restore()
        for (line, segment), payload, _unpublished in restored:
            self.latest.put(keys.q_state(ns, line, segment), payload)
        log.info(
            "restored %d states, %d of them possibly never published",
            len(restored),
            sum(new for *_, new in restored),
        )
        # published again in the background: a first put on each key declares its cached
        # publisher (milliseconds each), which must not hold up readiness; the worker
        # waits for it before its first batch, so no newer state goes out before it
        self._republished.clear()
        self.rt.spawn(self._republish, restored, name="filtering-republish")
        subscriptions = {
            kind: keys.segment_keys(ns, kind, self.selector)
            for kind in ("index", "trc", "maintenance")
        }
        subscriptions["model"] = keys.model_all(ns)
        self.inbox = self.rt.subscribe_batches(
            subscriptions,
            self._handle_batch,
            max_batch=BATCH,
            reliable=True,
            positions=self.node.store.positions(),  # the replay resumes where the store is
            on_idle=self._idle,
            on_end=self._at_end,
        )
        self.rt.declare_queryable(keys.q_state_keys(ns, self.selector), self.latest.on_query)
        # After subscribing, so a model published meanwhile is not missed either; and
        # before the liveliness token (ready), so the latest models are queued ahead of
        # any event a producer sends once it sees this instance ready.
        for key, payload in self.rt.ask(keys.model_all(ns), MODEL_QUERY_TIMEOUT_S):
            self.inbox.put("model", key, payload)

    # --- the worker ---------------------------------------------------------------------

    def _republish(self, restored: list[tuple[tuple[str, str], bytes, bool]]) -> None:
        """Publish the restored states again (a state committed but not yet published
        when the process died is then not lost; a repeated one is harmless)."""
        try:
            for (line, segment), payload, _unpublished in restored:
                if self.rt.stopping:
                    return
                self.states_out.put(keys.state(self.rt.ns, line, segment), payload)
        finally:
            self._republished.set()

    def _handle_batch(self, batch: list[tuple[str, str, bytes]]) -> None:
        """What is queued, in one store transaction; then the dirty segments are published
        (all of them without a backlog, a share of the time with one: see the module)."""
        self._republished.wait()  # the restored states go out first
        started = time.perf_counter()
        try:
            positions = [
                (producer, *msgpack.unpackb(position))
                for kind, producer, position in batch
                if kind == MARK
            ]
            done = self.node.handle_batch(
                ((key, payload) for kind, key, payload in batch if kind != MARK),
                summarize=False,
                background=len(batch) >= BACKLOG,  # commits while the next batch folds
                positions=positions,  # stored with the events the replays brought
            )
            self._batches += 1
            backlog = self.inbox is not None and len(self.inbox) >= BACKLOG
            if done.states or done.detected or done.withdrawn or not backlog:
                self.node.store.sync()  # what is published next is committed
        except Exception as e:
            self._store_failed(e)
            return
        for key, reason, payload in done.rejected:
            self.rt.deadletters.reject(key, reason, payload)
        for state in done.states:  # a model update's re-run
            self._publish(state)
        for sid in done.changed:
            self.dirty[sid] = self._batches  # a dirty one keeps its place: oldest first
        if backlog:
            self._publish_dirty(PUBLISH_SHARE * (time.perf_counter() - started))
        else:
            self._publish_dirty(None)
        self._freeze()
        self._publish_detected(done.withdrawn, done.detected)

    def _publish_detected(self, withdrawn, found) -> None:
        """The batch's detected tampings taken out of the logs (deleted with the batch),
        then those found (stored with it), for alerting, calibration and planning: the
        withdrawals first, so a detection of the same ``event_id`` found anew outranks
        its withdrawal."""
        for gone in withdrawn:
            key = keys.maintenance(self.rt.ns, gone.line, gone.segment)
            self.states_out.put(key, encode(self.revisions.stamp(gone, withdrawn=True)))
            log.info(
                "withdrew the detected tamping %s on %s/%s: %s",
                gone.event_id,
                gone.line,
                gone.segment,
                "the segment's events no longer show it",
            )
        for new in found:
            key = keys.maintenance(self.rt.ns, new.line, new.segment)
            self.states_out.put(key, encode(self.revisions.stamp(new, withdrawn=False)))
            log.info(
                "detected an unreported tamping on %s/%s in [%s, %s]",
                new.line,
                new.segment,
                new.t_start,
                new.t_end,
            )

    def _store_failed(self, e: Exception) -> None:
        """The store failed (disk full, file removed; now or in a batch's commit in the
        background), or a bug escaped the transaction (its writes are rolled back): either
        way what the tracker holds is no longer what is persisted; stop so that a restart
        rebuilds it from the store."""
        log.exception("filtering: a batch failed in the store transaction; stopping")
        self.node.broken = True  # no checkpoint of what the store may not hold
        self.rt.exit_code = EXIT_STORE_FAILED if isinstance(e, sqlite3.Error) else EXIT_SOFTWARE
        self.rt.stop()

    def _freeze(self) -> None:
        """Every ``FREEZE_S``: collect the young generations, then move every surviving
        object into the garbage collector's permanent generation (``gc.freeze``).

        The tracker holds a few hundred thousand long-lived objects (the segments' logs
        and states); a full collection walks them all, a pause that grows with the network,
        and CPython runs one every few seconds of live traffic: the live latency's worst
        spikes. Frozen objects are skipped by every collection;
        acyclic ones are still freed by reference counting when dropped (the logs, states
        and messages here hold no reference cycles), so only a cycle alive at a freeze
        that dies later would stay, which this worker does not make. In between, the
        automatic collections are off (``gc.disable`` at the first call): they would walk
        every young object a batch makes (states, checkpoints, events, ~10 a message); the
        young ones are collected here instead, after a batch or when idle (so that what
        the other threads make is collected too). Only with ``freeze_gc`` (the service's
        own process, not a test or a host that embeds it)."""
        if not self.freeze_gc:
            return
        gc.disable()
        now = time.monotonic()
        if now - self._frozen_at >= FREEZE_S:
            gc.collect(1)
            gc.freeze()
            self._frozen_at = now

    def _idle(self) -> None:
        """Nothing arrived for a second: write the due checkpoint's slices while nothing is
        queued, so that an instance whose traffic stopped has its checkpoints current (a
        kill then replays nothing); a slice per batch otherwise waits for the next batch.
        The young objects are collected when due (:meth:`_freeze`)."""
        self._freeze()
        if self.node.broken:
            return
        try:
            self.node.store.sync()  # the last batch's commit, if it ran in the background
            self._publish_dirty(None)  # what waited for it
            while self.node.checkpoint_if_due() and not (
                self.inbox is not None and len(self.inbox)
            ):
                pass
        except sqlite3.Error as e:
            self._store_failed(e)

    def _publish_dirty(self, budget_s: float | None) -> None:
        """Summarise and publish the oldest dirty segments, ``SUMMARY_CHUNK`` at a time, for
        ``budget_s`` (at least one chunk), or all of them (None). An error in a summary is a
        bug: logged, the segments stay dirty (their events are committed), the worker goes on.

        While the last batch commits in the background, the segments it changed wait (they
        keep their place); all of them are published by the next call once it is done."""
        started = time.perf_counter()
        committed = self._batches - 1 if self.node.store.committing else self._batches
        while self.dirty:
            chunk = list(
                itertools.islice(
                    (sid for sid, batch in self.dirty.items() if batch <= committed),
                    SUMMARY_CHUNK,
                )
            )
            if not chunk:
                return
            try:
                states = self.node.tracker.states_of(chunk)
            except Exception:
                log.exception("filtering: summarising %d segments failed", len(chunk))
                return
            for sid in chunk:
                del self.dirty[sid]
            self.node.note_states(states)  # the next checkpoint stores them with the state
            for state in states:
                self._publish(state)
            if budget_s is not None and time.perf_counter() - started >= budget_s:
                return

    def _at_end(self) -> None:
        """The inbox is drained at a stop: publish what is dirty, within ``STOP_PUBLISH_S``
        (the rest is republished at the next start)."""
        try:
            self.node.store.sync()  # the last batch's commit, if it ran in the background
        except Exception as e:
            self._store_failed(e)
            return
        try:
            self._publish_dirty(STOP_PUBLISH_S)
        except Exception:  # a put after the session went: the rebuild republishes them
            log.exception("filtering: publishing at the stop failed")
        if self.dirty:
            log.info("filtering: %d changed segments left to the next start", len(self.dirty))

    def _publish(self, state: SegmentState) -> None:
        payload = encode(state)
        self.latest.put(keys.q_state(self.rt.ns, state.line, state.segment), payload)
        # cached per segment (alerting restarted gets what it missed); BLOCK: a slow
        # consumer slows the worker down rather than losing states
        self.states_out.put(keys.state(self.rt.ns, state.line, state.segment), payload)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """``trackfusion filtering``: the flags override the config file's ``services.filtering``."""
    parser.description = "Filter every segment under --selector; state persisted in SQLite."
    parser.add_argument(
        "--selector",
        metavar="KEYEXPR_SUFFIX",
        help="the part of the network this instance owns, e.g. 'L1/**' "
        f"(default: {DEFAULT_SELECTOR})",
    )
    add_network_argument(
        parser,
        "refuse events on segments this network does not have; its line speeds choose the "
        "speed class of lines the limits file does not name",
        default="accept any",
    )
    add_db_argument(parser, SERVICE, "the accepted events and models")
    parser.add_argument(
        "--limits", metavar="FILE", help=f"limits file (default: {DEFAULT_LIMITS_FILE})"
    )
    add_zenoh_arguments(parser)


def extend_start_timeout(events: int) -> None:
    """The store is migrated at open (:meth:`Store._migrate_events`), before the instance
    can be ready: ask systemd (``TimeoutStartSec``) for that long, with margin
    (``MIGRATE_S_PER_EVENT``), from now."""
    usec = int((60.0 + events * MIGRATE_S_PER_EVENT) * 1e6)
    systemd.notify(f"EXTEND_TIMEOUT_USEC={usec}")


def run(args: argparse.Namespace) -> int:
    # freeze_gc: the process is this service's alone
    return run_command(args, main, **flag_values(args, OPTIONS), freeze_gc=True)
