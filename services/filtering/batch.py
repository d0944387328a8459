"""A batch of events folded together (:class:`BatchFold`): each on-board index that follows
its segment's log is queued, and the queued indices of all segments are folded in one
:func:`~services.filtering.fold.fold_many_counted`; anything else takes the one-event path
(:func:`~services.filtering.segment.step_segment`). The result is, bit for bit, that of
stepping the events one by one."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import NamedTuple

from schemas import MaintenanceEvent, OnboardIndex
from schemas.keys import SegmentId
from services.filtering.banks import CUSUM_THRESHOLD, BankRow, Scratch, as_filtered
from services.filtering.events import INDEX, Event, EventMessage, event_of, index_event
from services.filtering.fold import fold_many_counted
from services.filtering.histories import Checkpoint, Histories, SegmentHistory, evolve, rested
from services.filtering.models import Models
from services.filtering.segment import advance, detect

Entry = SegmentHistory | Checkpoint  # a segment as of the batch so far (Checkpoint: resting)


class _Queued(NamedTuple):
    """A segment's queued indices at their flush: what they fold from and with."""

    sid: SegmentId
    was: Entry  # the segment when its first index was queued (it has a state)
    group: str
    queue: list[tuple[int, Event]]  # (message position, index)
    log: list[Event]


def _last_order(hist: Entry | None):
    """The order key of the last event a segment's state folds; None: no state to extend."""
    if hist is None or hist.state is None:
        return None
    if isinstance(hist, Checkpoint):
        return hist.last_order
    return hist.log[-1].order if hist.log else None


class BatchFold:
    """Steps a batch of events over the segment histories without changing them: ``run``
    returns ``(reasons, changed, detected, withdrawn)``, the histories to swap in by the
    owner, the detected tampings added to the logs and those taken out of them, net over
    the batch (one found and withdrawn again within it is in neither).

    The usual event, an on-board index after the last event of its segment's log on a
    segment with a state (live, a backfill in time order), is appended and left pending;
    the pending indices of all segments are folded from their states at the end
    (several per segment: the logs differ in length). Anything else (a late index, a
    duplicate, a TRC record, a tamping, a segment without a state or a calibration for
    the index's unit) first folds its segment's pending indices, then takes the exact path
    of one message (:func:`advance`: a late event re-runs its segment's detection).
    Detection runs after each index one by one: the batched fold halts a segment at the
    first index whose CUSUM reaches ``CUSUM_THRESHOLD``, runs :func:`detect` there and
    steps the segment's later indices one by one. A resting segment is folded from its
    row of the bank into a free row, listed in ``taken`` (the owner's list), which it
    rests in after the swap.
    """

    def __init__(
        self,
        histories: Histories,
        models: Models,
        *,
        detect_maintenance: bool,
        scratch: Scratch,
        taken: list[tuple[SegmentId, BankRow]],
    ) -> None:
        self.histories, self.models = histories, models
        self.detect_maintenance = detect_maintenance
        self.halt = CUSUM_THRESHOLD if detect_maintenance else None
        self.scratch = scratch  # each state is copied out: the fold keeps no batch's arrays
        self.taken = taken
        # a segment's history after this batch's events so far; a resting one's (its log
        # not read) as a Checkpoint, its indices of this batch in ``tails``
        self.changed: dict[SegmentId, Entry] = {}
        self.tails: dict[SegmentId, list[Event]] = {}
        self.pending: dict[SegmentId, list[tuple[int, Event]]] = {}  # appended, not folded
        self.folds_from: dict[SegmentId, Entry] = {}  # base() of a pending one
        # per (segment, identity) of a detected tamping the batch touched: the one the log
        # held before the batch (None: none), and the one it holds now, with the position of
        # the message that put it there
        self.held_before: dict[tuple[SegmentId, tuple], MaintenanceEvent | None] = {}
        self.held_now: dict[tuple[SegmentId, tuple], tuple[int, MaintenanceEvent | None]] = {}
        self.group_of: dict[SegmentId, str | None] = {}  # the models do not change in a batch
        self.shape_of = {group: (p.ns, p.n) for group, p in models.params.items()}
        self.msgs: Sequence[EventMessage] = ()
        self.reasons: list[str] = []

    def run(self, msgs: Sequence[EventMessage]):
        """``(reasons, changed, detected, withdrawn)`` of stepping ``msgs`` one by one."""
        self.msgs, self.reasons = msgs, [""] * len(msgs)
        for i, msg in enumerate(msgs):
            sid = (msg.line, msg.segment)
            event = index_event(msg) if type(msg) is OnboardIndex else event_of(msg)
            if event.kind == INDEX and self._queue(i, sid, msg, event):
                continue
            if self.pending.get(sid):
                self.flush([sid])
            self._exact(i, sid, self._current(sid, msg), event)
        self.flush(list(self.pending))
        found = sorted(
            (i, msg)
            for key, (i, msg) in self.held_now.items()
            if msg is not None and msg != self.held_before[key]
        )
        withdrawn = [
            was
            for key, was in self.held_before.items()
            if was is not None and self.held_now[key][1] is None
        ]
        return self.reasons, self.changed, [msg for _, msg in found], withdrawn

    def _note(self, i: int, sid: SegmentId, found, withdrawn) -> None:
        """Message ``i`` took the detected tampings ``withdrawn`` out of ``sid``'s log and
        put ``found`` in it."""
        for msg, now in [*((m, None) for m in withdrawn), *((m, m) for m in found)]:
            key = (sid, ("maintenance", msg.event_id))
            if key not in self.held_before:
                self.held_before[key] = None if now is not None else msg
            self.held_now[key] = (i, now)

    def _queue(self, i: int, sid: SegmentId, msg: OnboardIndex, event: Event) -> bool:
        """Queue an index that follows its segment's log on a segment with a state, a
        posterior group and a calibration for its unit; False if it does not."""
        queued = self.pending.get(sid)
        if queued:
            last = queued[-1][1].order
        else:
            hist = self._base(sid)
            last = _last_order(hist)
        group = self.group_of.get(sid, False)
        if group is False:
            group = self.group_of[sid] = self.models.group_for(msg.line, msg.segment)
        if (
            last is None
            or not (event.t_s > last[0] or event.order > last)
            or group is None
            or self.models.observation_for(msg.train, msg.unit) is None
        ):
            return False
        if not queued:
            self.pending[sid] = queued = []
            self.folds_from[sid] = hist  # what _base(sid) stays until its flush
        queued.append((i, event))
        return True

    def _base(self, sid: SegmentId) -> Entry | None:
        """The segment as of this batch so far, a resting one without reading its log."""
        got = self.changed.get(sid)
        if got is not None:
            return got
        if self.histories.is_loaded(sid):
            return self.histories[sid]
        return self.histories.resting_entry(sid) if sid in self.histories else None

    def _current(self, sid: SegmentId, msg: EventMessage) -> SegmentHistory:
        """The segment with its log: a resting one's read from the store (where this
        batch's events are not yet) and this batch's indices appended."""
        got = self._base(sid)
        if got is None:
            return SegmentHistory(msg.line, msg.segment)
        if isinstance(got, Checkpoint):
            stored = self.histories.load(sid)
            log = stored.log + tuple(self.tails.get(sid, ()))
            state = as_filtered(got.state)
            got = evolve(stored, log=log, trc_t=got.trc_t, state=state, group=got.group)
        return got

    def _change(self, sid: SegmentId, hist: SegmentHistory) -> None:
        self.changed[sid] = hist
        self.tails.pop(sid, None)  # in its log now

    def _exact(self, i: int, sid: SegmentId, hist: SegmentHistory, event: Event) -> None:
        """Message ``i`` stepped alone, as :meth:`Tracker.step` does."""
        done = advance(hist, event, self.models, detecting=self.detect_maintenance)
        self.reasons[i] = done.reason
        if not done.reason:
            self._note(i, sid, done.found, done.withdrawn)
            self._change(sid, done.hist)

    def flush(self, sids: Sequence[SegmentId]) -> None:
        """Fold the pending indices of ``sids``, one fold per sample count and source
        (a resting segment's row of the bank, or a state of its own)."""
        jobs: dict[tuple[int, bool], list[_Queued]] = {}
        for sid in sids:
            queue = self.pending.pop(sid)
            item = _Queued(sid, self.folds_from.pop(sid), self.group_of[sid], queue,
                           [event for _, event in queue])  # fmt: skip
            ns, n = self.shape_of[item.group]
            state = item.was.state
            banked = isinstance(state, BankRow) and (state.banks.ns, state.banks.n) == (ns, n)
            jobs.setdefault((ns, banked), []).append(item)
        for (ns, banked), job in jobs.items():
            states, folded, cusums = self._fold(job, ns, banked)
            for item, own, count, cusum in zip(job, states, folded, cusums, strict=True):
                self._folded(item, own, count, cusum)

    def _fold(self, job: list[_Queued], ns: int, banked: bool):
        """``(states, folded, cusums)`` of one fold of the job's queued indices."""
        models = self.models
        states, folded = fold_many_counted(
            [item.was.state if banked else as_filtered(item.was.state) for item in job],
            [item.log for item in job],
            [models.params[item.group] for item in job],
            models,
            self.halt,
            scratch=self.scratch,
            into=self.histories.bank(ns, job[0].was.state.banks.n) if banked else None,
        )
        if banked and isinstance(states[0], BankRow):  # rows of the bank, all of them
            self.taken.extend((item.sid, own) for item, own in zip(job, states, strict=True))
            cusums = states[0].banks.cusum[[own.row for own in states]].tolist()
        else:  # (a model of another shape folds from copies: Filtered states)
            cusums = [math.nan if own is None else own.cusum for own in states]
        return states, folded, cusums

    def _folded(self, item: _Queued, own, count: int, cusum: float) -> None:
        """A segment's fold result in place; where the fold halted, :meth:`_halted`."""
        sid, was, log = item.sid, item.was, item.log
        tail = log if count == len(log) else log[:count]
        if isinstance(was, Checkpoint):  # it stays resting: the log is not read
            self.changed[sid] = rested(was, own, item.group, tail)
            got = self.tails.get(sid)
            if got is None:
                self.tails[sid] = list(tail)
            else:
                got.extend(tail)
        else:
            self.changed[sid] = evolve(was, log=was.log + tuple(tail), state=own, group=item.group)
        if count < len(log) or self.halt is not None and cusum >= self.halt:
            self._halted(sid, item.queue, count)

    def _halted(self, sid: SegmentId, queue: list[tuple[int, Event]], count: int) -> None:
        """A segment whose CUSUM reached the threshold at its ``count``-th queued index:
        :func:`detect` there, then its later indices one by one."""
        hist, found = detect(self._current(sid, self.msgs[queue[0][0]]), self.models)
        if found is not None:
            self._note(queue[count - 1][0], sid, (found,), ())
        self._change(sid, hist)
        for i, event in queue[count:]:
            self._exact(i, sid, self.changed[sid], event)
