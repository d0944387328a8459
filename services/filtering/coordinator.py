"""The batch coordinator: a :class:`~services.filtering.tracker.Tracker` whose accepted
inputs are committed to a :class:`~services.filtering.store.Store` before their states are
published (:class:`PersistentTracker`), restored from the store's checkpoints at start, and
checkpointed as it goes."""

from __future__ import annotations

import itertools
import logging
import time
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any

from schemas import (
    Calibration,
    DegradationPosterior,
    MaintenanceEvent,
    OnboardIndex,
    SchemaError,
    SegmentState,
    decode,
    encode,
    keys,
)
from schemas.keys import SegmentId
from services.filtering.columns import columns_after, log_columns, pack_columns, unpack_columns
from services.filtering.events import (
    KIND_NAMES,
    Event,
    EventMessage,
    LogColumns,
    ModelMessage,
    canonical_log,
    event_of,
    is_full_restart,
)
from services.filtering.histories import Checkpoint, SegmentHistory
from services.filtering.models import model_name, models_key
from services.filtering.payloads import decode_keyed, indices_of, stored_events
from services.filtering.state import pack_state, unpack_state
from services.filtering.store import Store, index_identity, order_json, order_of
from services.filtering.tracker import Step, Tracker
from track.segments import KnownSegments

log = logging.getLogger(__name__)
CHECKPOINT_S = 10.0  # worker time between two checkpoints of the changed segments
CHECKPOINT_SLICE = 64  # segments checkpointed per batch once a checkpoint is due
SLICE_EVENTS = 4096  # a batch's events per further slice
MAX_LOADED = 4096  # segment logs kept in memory (~1 KB an event; least recently used dropped)


@dataclass(frozen=True)
class BatchResult:
    """What a batch did: the newest changed state of each segment, and what was refused."""

    states: tuple[SegmentState, ...]
    rejected: tuple[tuple[str, str, bytes], ...]  # (key, reason, payload): dead letters
    accepted: int
    detected: tuple[MaintenanceEvent, ...] = ()  # tamping found in the data: to publish
    # with ``summarize=False``: the segments the batch's events changed (not in ``states``)
    changed: tuple[SegmentId, ...] = ()
    # detected tampings taken out of the logs (a report superseding them, or a late event
    # invalidating them): deleted from the store
    withdrawn: tuple[MaintenanceEvent, ...] = ()


class _Batch:
    """What a batch did so far (:meth:`PersistentTracker.handle_batch`)."""

    def __init__(self, rejected: list[tuple[str, str, bytes]]) -> None:
        self.states: dict[SegmentId, SegmentState] = {}  # the newest of each segment, last
        self.rejected = rejected  # (key, reason, payload): dead letters
        self.accepted = 0
        # per (segment, event_id) of a detected tamping the batch changed: the one the logs
        # held before the batch and the one they hold now (None: none)
        self._before: dict[tuple[SegmentId, str], MaintenanceEvent | None] = {}
        self._now: dict[tuple[SegmentId, str], MaintenanceEvent | None] = {}
        self.changed: list[SegmentId] = []

    def note(self, found: Iterable[MaintenanceEvent], withdrawn: Iterable[MaintenanceEvent]):
        """Detected tampings taken out of the logs, then those put in them, by one step."""
        for msg, now in [*((m, None) for m in withdrawn), *((m, m) for m in found)]:
            key = ((msg.line, msg.segment), msg.event_id)
            self._before.setdefault(key, None if now is not None else msg)
            self._now[key] = now

    def detected_changes(self) -> tuple[list[MaintenanceEvent], list[MaintenanceEvent]]:
        """``(found, withdrawn)`` net over the batch: one found and withdrawn again within
        it is in neither, one withdrawn and found again as it was is in neither."""
        found = [m for k, m in self._now.items() if m is not None and m != self._before[k]]
        withdrawn = [m for k, m in self._before.items() if m is not None and self._now[k] is None]
        return found, withdrawn

    def keep(self, new_states: Iterable[SegmentState]) -> None:
        for state in new_states:
            self.states.pop((state.line, state.segment), None)  # the newest, last
            self.states[(state.line, state.segment)] = state

    def result(self) -> BatchResult:
        found, withdrawn = self.detected_changes()
        return BatchResult(
            tuple(self.states.values()),
            tuple(self.rejected),
            self.accepted,
            tuple(found),
            tuple(self.changed),
            tuple(withdrawn),
        )


class PersistentTracker:
    """A :class:`Tracker` whose accepted inputs are committed to a :class:`Store` first.

    ``handle(key, payload)`` decodes, steps the tracker and, if the message was accepted,
    commits it before returning the states to publish. ``rebuild()`` replays the store.
    """

    def __init__(
        self,
        tracker: Tracker,
        store: Store,
        *,
        known: KnownSegments | None = None,
        ns: str = keys.DEFAULT_NS,
        checkpoint_s: float = CHECKPOINT_S,
        max_loaded: int = MAX_LOADED,
    ) -> None:
        self.tracker = tracker
        self.store = store
        self.ns = ns  # the key a detected tamping is stored under
        # the network's segments: an event on another is refused, so a sender cannot make
        # the service hold segment histories for ids that do not exist
        self.known = known
        if tracker.histories.loader is None:
            tracker.histories.loader = self.segment_log
        if tracker.histories.columns is None:
            tracker.histories.columns = self.segment_columns
        self.checkpoint_s = checkpoint_s
        self.max_loaded = max_loaded
        self.broken = False  # set by the owner when a batch failed: no checkpoint then
        self._summaries: dict[SegmentId, SegmentState] = {}  # newest, of dirty segments
        self._checkpointed = time.monotonic()
        self._due: list[SegmentId] | None = None  # a due checkpoint's segments left to write

    def handle(self, key: str, payload: bytes) -> Step:
        msg = decode_keyed(key, payload)
        if msg is None:
            return Step(False, "not a model this service uses")
        if self.known is not None and not isinstance(msg, Calibration | DegradationPosterior):
            self.known.check(msg)
        step = self.tracker.step(msg)
        if step.accepted:
            self._commit_detected(step.detected, step.withdrawn)
            self._commit(msg, str(key))
        return step

    def _commit_detected(
        self, found: Iterable[MaintenanceEvent], withdrawn: Iterable[MaintenanceEvent]
    ) -> None:
        """The detected tampings taken out of the logs deleted, those found stored (before
        the events that made them: a TRC record later in the batch prunes them)."""
        for msg in withdrawn:
            self.store.delete_tamping(msg.line, msg.segment, event_of(msg).identity)
        for msg in found:
            self._commit(msg, keys.maintenance(self.ns, msg.line, msg.segment))

    def handle_batch(
        self,
        items: Iterable[tuple[str, bytes]],
        *,
        summarize: bool = True,
        background: bool = False,
        positions: Sequence[tuple[str, str, int]] = (),
    ) -> BatchResult:
        """Several ``(key, payload)`` in one store transaction, with the delivery
        ``positions`` ``(producer, epoch, seq)`` they bring the store to.

        Model messages go first and are coalesced (:meth:`Tracker.update_models`): of
        several versions of one model only the newest is applied, each is validated, and
        the segments they affect are re-run once, in one batched pass. Then the
        events in the order given. Everything accepted is committed at the end, before the
        caller publishes the states; a payload that does not decode, or that the core
        refuses (a model that fails validation), is returned in ``rejected`` with the
        reason. A store error (``sqlite3.Error``) propagates: nothing of the batch is then
        persisted, and the caller must not go on with this tracker (nor after any other
        exception out of this method: the tracker may have moved on without the store).

        ``summarize=False``: the events' states are not summarised; ``changed`` lists the
        segments they changed, whose states :meth:`Tracker.states_of` gives when the
        caller publishes them (a model update's re-run states are in ``states`` still).
        The accepted rows go to the store grouped (:meth:`Store.add_events`), in order.

        ``background``: the transaction commits in the background
        (:meth:`Store.transaction`), with the checkpoint slice due after it: the call
        returns before its events are stored, and nothing of the batch may be published
        until :attr:`Store.committing` is False (or :meth:`Store.sync` returned). A commit
        that fails raises at the store's next access (the next batch): stop then, as after
        a store error here.
        """
        models, events, rejected = self._sorted_inputs(items)
        batch = _Batch(rejected)
        with self.store.transaction(background=background):
            self.store.put_positions(positions)
            if models:
                self._apply_models(models, batch)
            msgs = [msg for msg, _, _ in events]
            try:
                if summarize:
                    reasons, event_states, found, withdrawn = self.tracker.step_events(msgs)
                    changed: list[SegmentId] = []
                else:
                    reasons, changed, found, withdrawn = self.tracker.fold_events(msgs)
                    event_states = ()
            except Exception:  # one of them cannot be folded: find it, one at a time
                log.info("a batch of %d events failed; stepping them one by one", len(events))
                self._step_one_by_one(events, batch)
            else:
                self._commit_folded(events, reasons, found, withdrawn, batch)
                batch.changed = changed
                batch.keep(event_states)
            self._after_batch(batch.states.values(), models=bool(models), events=len(events))
        return batch.result()

    def _sorted_inputs(self, items: Iterable[tuple[str, bytes]]):
        """``(models, events, rejected)`` of a batch's ``(key, payload)``: the decoded
        model messages and events, each with its key and payload, and the dead letters
        ``(key, reason, payload)``; the indices decoded in one call (:func:`indices_of`)."""
        rejected: list[tuple[str, str, bytes]] = []
        models: list[tuple[ModelMessage, str, bytes]] = []
        events: list[tuple[EventMessage, str, bytes]] = []
        items = list(items)
        for (key, payload), index in zip(items, indices_of(items), strict=True):
            if index is not None:
                msg: EventMessage | ModelMessage | None = index
            else:
                try:
                    msg = decode_keyed(key, payload)
                except SchemaError as e:
                    rejected.append((key, str(e), payload))
                    continue
            if msg is None:
                continue
            if isinstance(msg, Calibration | DegradationPosterior):
                models.append((msg, key, payload))
                continue
            if self.known is not None:
                try:
                    self.known.check(msg)
                except SchemaError as e:
                    rejected.append((key, str(e), payload))
                    continue
            events.append((msg, key, payload))
        return models, events, rejected

    def _apply_models(self, models: list[tuple[ModelMessage, str, bytes]], batch: _Batch) -> None:
        """The batch's model messages, coalesced (:meth:`Tracker.update_models`), and the
        accepted ones committed."""
        origin = {id(msg): (key, payload) for msg, key, payload in models}
        update = self.tracker.update_models([msg for msg, _, _ in models])
        for msg, reason in update.refused:
            key, payload = origin[id(msg)]
            batch.rejected.append((key, reason, payload))
        self._commit_detected(update.detected, update.withdrawn)
        batch.note(update.detected, update.withdrawn)
        self._commit_many([(msg, origin[id(msg)][0]) for msg in update.accepted])
        batch.accepted += len(update.accepted)
        batch.keep(update.states)

    def _commit_folded(self, events, reasons: list[str], found, withdrawn, batch: _Batch):
        """Commit a folded batch's accepted events, after the changes of detected tampings
        it made (net over the batch)."""
        self._commit_detected(found, withdrawn)
        batch.note(found, withdrawn)
        taken = [
            (msg, key)
            for (msg, key, _payload), reason in zip(events, reasons, strict=True)
            if not reason
        ]
        batch.accepted += len(taken)
        self._commit_many(taken)

    def _step_one_by_one(self, events: list[tuple[EventMessage, str, bytes]], batch: _Batch):
        """Each event stepped and committed alone: the one the core refuses, or that
        raises, becomes a dead letter with the reason, and the batch goes on."""
        for msg, key, payload in events:
            try:
                step = self.tracker.step(msg)
            except ValueError as e:  # an event the core refuses
                batch.rejected.append((key, str(e), payload))
                continue
            except Exception as e:  # a bug: the letter says what, the batch goes on
                log.exception("error stepping %s", key)
                batch.rejected.append((key, f"{type(e).__name__}: {e}", payload))
                continue
            if step.accepted:
                batch.accepted += 1
                self._commit_detected(step.detected, step.withdrawn)
                self._commit(msg, key)
                batch.note(step.detected, step.withdrawn)
                batch.keep(step.states)

    def _commit(self, msg: EventMessage | ModelMessage, key: str) -> None:
        self._commit_many([(msg, key)])

    def _commit_many(self, items: Iterable[tuple[EventMessage | ModelMessage, str]]) -> None:
        """Write accepted messages in order: runs of event rows in one :meth:`Store.add_events`; a
        TRC record's prune runs after the rows before it, as one message at a time would."""
        rows: list[tuple[str, str, str, str, tuple[Any, ...] | str, float, bytes]] = []
        for msg, key in items:
            payload = encode(msg)  # not what was received: unknown fields are not kept
            if type(msg) is OnboardIndex:  # event_of's identity and time, without its logs
                identity = index_identity(msg.train, msg.unit, msg.t)
                rows.append((msg.line, msg.segment, "index", key, identity, msg.t, payload))
                continue
            match msg:
                case Calibration():
                    self.store.put_model(
                        name=model_name(msg),  # a unit's own model beside the fleet's
                        kind="calibration",
                        version=msg.version,
                        key=key,
                        payload=payload,
                    )
                case DegradationPosterior():
                    self.store.put_model(
                        name=f"degradation/{msg.group}",
                        kind="degradation",
                        version=msg.version,
                        key=key,
                        payload=payload,
                    )
                case _:
                    event = event_of(msg)
                    kind = KIND_NAMES[event.kind]
                    line, segment = msg.line, msg.segment
                    rows.append((line, segment, kind, key, event.identity, event.t_s, payload))
                    if is_full_restart(event):
                        self.store.add_events(rows)
                        rows = []
                        self.store.prune(line, segment, event.t_s)
        if rows:
            self.store.add_events(rows)

    def rebuild(self) -> list[SegmentState]:
        """:meth:`restore`, decoded: the publishable states of every segment."""
        return [decode(payload, SegmentState) for _sid, payload, _new in self.restore()]

    def restore(self) -> list[tuple[SegmentId, bytes, bool]]:
        """Bring the tracker back from the store: ``(segment, encoded SegmentState,
        unpublished)`` of every publishable segment; ``unpublished`` is False for a state
        restored from a checkpoint known to have been published (one older than the last
        checkpoint, or the last one after a clean stop), True otherwise (to publish again).

        Every stored model, then each segment's checkpoint (:meth:`Tracker.restore`): its
        state as stored and its stored SegmentState when nothing came after it; folded on
        over the events stored after it when they all sort after its last one; replayed
        from its whole log (read from the store) when one sorts before (a late event), when
        the models changed since, when it has no checkpoint, or when its row no longer
        decodes. The logs are not read otherwise (they load when a segment needs them).
        A stored row that no longer decodes (one the current schema's limits refuse) is
        skipped with a warning rather than stopping the service at every start.
        """
        models = [m for m in self._decoded(self.store.models()) if m is not None]
        summaries: dict[SegmentId, bytes] = {}
        published: set[SegmentId] = set()
        published_gen = self.store.published_gen()
        broken: list[SegmentId] = []

        def checkpoints() -> Iterator[Checkpoint]:
            """The stored checkpoints, one at a time (each state goes into the bank as it
            comes: a list of them would hold every state twice)."""
            rows = self.store.checkpoints()
            for line, segment, _seq, order, trc_t, grp, key, blob, summary, gen in rows:
                try:
                    state = None if blob is None else unpack_state(blob)
                    ckpt = Checkpoint(line, segment, trc_t, state, grp, order_of(order), key)
                except (ValueError, TypeError) as e:
                    log.warning(
                        "store: checkpoint of %s/%s no longer decodes (%s)", line, segment, e
                    )
                    broken.append((line, segment))
                    continue
                if summary is not None:
                    summaries[(line, segment)] = summary
                    if gen <= published_gen:
                        published.add((line, segment))
                yield ckpt

        tails: dict[SegmentId, list[Event]] = {}
        for line, segment, kind, key, payload in self.store.tails():
            for event in stored_events([(kind, key, payload)]):
                tails.setdefault((line, segment), []).append(event)
        # their logs: by the loader; read after the checkpoints, which add the broken ones
        replay = itertools.chain(broken, self.store.unchecked_segments())
        with self.store.transaction():  # the logs it caches as columns, in one commit
            kept, states = self.tracker.restore(models, checkpoints(), tails, replay)  # type: ignore[arg-type]
        out: list[tuple[SegmentId, bytes, bool]] = []
        unsummarised = []
        for sid in kept:
            if sid in summaries:
                out.append((sid, summaries[sid], sid not in published))
            else:
                unsummarised.append(self.tracker.histories.resting(sid))
        hists = [
            SegmentHistory(c.line, c.segment, (), c.trc_t, c.state, c.group) for c in unsummarised
        ]
        fresh = [s for s in (*states, *self.tracker.segment_states(hists)) if s is not None]
        for state in fresh:
            sid = (state.line, state.segment)
            self._summaries[sid] = state
            self.tracker.histories.dirty.add(sid)
            out.append((sid, encode(state), True))
        # what is restored has not been published again yet: not marked published
        self.checkpoint(published=False)
        return out

    def segment_log(self, line: str, segment: str) -> tuple[tuple[Event, ...], float | None]:
        """The segment's log from the store (:func:`canonical_log`): the tracker's loader."""
        return canonical_log(stored_events(self.store.segment_events(line, segment)))

    def segment_columns(self, line: str, segment: str) -> tuple[LogColumns, float | None] | None:
        """The segment's log from the store as :class:`LogColumns` (what :meth:`segment_log`
        gives, as columns): the tracker's column loader, for re-runs. None when a stored
        index does not pass :func:`stored_events`' checks or two events tie on time and
        kind (their order then needs the identities): the re-run reads the log as events.

        From the ``log_columns`` cache when it holds the segment: its row, with the events
        stored after it appended (:func:`columns_after`); otherwise, or when they cannot
        be appended, from the stored events, and the result is cached (with the newer
        events, so the next re-run reads one row again)."""
        store = self.store
        cached = store.cached_columns(line, segment)
        if cached is not None and (read := unpack_columns(cached[1])) is not None:
            newer = store.segment_events_after(line, segment, cached[0])
            tail = list(stored_events(row[1:] for row in newer))
            columns = columns_after(read[0], tail) if len(tail) == len(newer) else None
            if columns is not None:
                if newer:
                    seq = max(row[0] for row in newer)
                    store.put_cached_columns(line, segment, seq, pack_columns(columns, read[1]))
                return columns, read[1]
        seq = store.segment_last_seq(line, segment)
        read = log_columns(
            store.segment_index_payloads(line, segment),
            stored_events(store.segment_events(line, segment, indices=False)),
        )
        if read is not None:
            store.put_cached_columns(line, segment, seq, pack_columns(*read))
        return read

    def _after_batch(self, states: Iterable[SegmentState], *, models: bool, events: int) -> None:
        """At the end of a batch's transaction, after its events: note its states;
        checkpoint when due (every ``checkpoint_s`` of worker time, or after a model
        change), in the same transaction, then bound the loaded logs to ``max_loaded``
        (they are all stored once it commits, before any read of the store)."""
        self.note_states(states)
        if models:
            self.checkpoint()
        else:  # a slice per batch, so that the live worker never stalls on one big write
            self.checkpoint_if_due(slices=1 + events // SLICE_EVENTS)

    def checkpoint_if_due(self, slices: int = 1) -> int:
        """Between batches: the next ``slices`` slices (``CHECKPOINT_SLICE`` segments each)
        of the checkpoint when one is due (every ``checkpoint_s`` of worker time) or being
        written; how many segments it wrote (0: none due). An idle owner calls it until 0,
        so that what an instance holds when traffic stops is checkpointed without waiting
        for a batch. A batch writes a slice and one more per ``SLICE_EVENTS`` of its events,
        so that a backlog's big batches move a checkpoint on as fast as small ones."""
        if self._due is not None or time.monotonic() - self._checkpointed >= self.checkpoint_s:
            return self.checkpoint(limit=CHECKPOINT_SLICE * slices)
        return 0

    def note_states(self, states: Iterable[SegmentState]) -> None:
        """The newest SegmentStates summarised for segments changed since the checkpoint:
        the next checkpoint stores each with its state when they still match (else the
        restart summarises it again)."""
        for state in states:
            self._summaries[(state.line, state.segment)] = state

    def checkpoint(self, *, published: bool = True, limit: int | None = None) -> int:
        """Write the checkpoint of every segment changed since the last one (one
        transaction; the tracker must hold what the store holds, i.e. between batches);
        then drop the least recently used logs beyond ``max_loaded``. Returns how many.

        With ``limit``: the segments changed when the checkpoint fell due, at most ``limit``
        per call (each segment's row stands alone), the rest by the next calls; what changes
        meanwhile waits for the next period, which starts once they are all written.

        When the owner publishes a batch's states before it hands over the next batch, the
        previous checkpoint's states have been published when this one is written
        (:meth:`Store.put_checkpoints` marks them so). The service publishes changed
        segments later under a backlog, so it does not rely on the mark: it publishes
        every restored state again (the mark only feeds its log line)."""
        histories = self.tracker.histories
        if limit is None or self._due is None:
            self._due = [sid for sid in histories.dirty if sid in histories]
        write = self._due if limit is None else self._due[:limit]
        self._due = self._due[len(write) :]
        if write:
            with self.store.transaction():
                rows = (self._checkpoint_row(sid) for sid in write)
                self.store.put_checkpoints(rows, published=published)
        for sid in write:
            histories.dirty.discard(sid)
            self._summaries.pop(sid, None)
        if not self._due:
            self._due = None
            self._checkpointed = time.monotonic()
            gone = [sid for sid in histories.dirty if sid not in histories]  # no longer held
            histories.dirty.difference_update(gone)
            histories.trim(self.max_loaded)
        return len(write)

    def _checkpoint_row(self, sid: SegmentId) -> tuple[Any, ...]:
        rest = self.tracker.histories.resting(sid)
        state, summary = rest.state, self._summaries.get(sid)
        if (
            state is None
            or summary is None
            or not (
                summary.t == state.t_s
                and summary.n_updates == state.n_updates
                and summary.nis == state.nis
                and summary.posterior_group == rest.group
            )
        ):
            summary = None  # not known for this state: summarised again at restart
        return (
            *sid,
            order_json(rest.last_order),
            rest.trc_t,
            rest.group,
            models_key(self.tracker.models, *sid, rest.units),
            None if state is None else pack_state(state),
            None if summary is None else encode(summary),
        )

    def close(self) -> None:
        """At a clean stop: checkpoint what changed (not after a failed batch, when the
        tracker may hold what the store does not)."""
        if not self.broken:
            self.checkpoint()
            self.store.set_published()  # the worker published everything before it ended

    @staticmethod
    def _decoded(
        rows: Iterable[tuple[str, str, bytes]],
    ) -> Iterator[EventMessage | ModelMessage | None]:
        for _kind, key, payload in rows:
            try:
                yield decode_keyed(key, payload)
            except SchemaError as e:
                log.warning("store: skipping a stored %s that no longer decodes: %s", key, e)
