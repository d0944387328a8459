"""Per-segment live filtering as a pure function of events (no Zenoh, no clock, no I/O).

Each segment keeps the log of the events that can still change its state and, when the
models allow, the filter bank of its ``Ns`` posterior samples (paper Eq. 7-13). The state is
always the fold of :func:`apply_event` over the log in canonical order with the current
models, so the order in which events arrive, duplicates, and when the models arrive do not
change it:

- **Canonical order** of a log: ``(t, kind priority, identity)`` with the priority
  ``tamping < restart < index`` for equal times (a TRC record at a tamping's time is the
  exact measurement after it, so it wins); identities are ``(run_id, t)`` for a TRC
  record, ``event_id`` for a tamping and ``(train, unit, t)`` for an on-board index. A second
  event with an identity already in the log is a duplicate and is ignored, except that a
  tamping report replaces the one held under its ``event_id`` when it ranks higher
  (``MaintenanceEvent.rank``: higher ``revision``, then the narrower interval, then the later
  time), so that a correction wins whatever the order of arrival.
- **Log window**: every event at or after the segment's latest TRC record (every event while
  there is none), and the reported tampings before it. A TRC record drops the other events
  before it; such an event older than the latest TRC record cannot change the state and is
  refused (``accepted`` False, reason given). A reported tamping before the record changes
  nothing of the state either (the record restarts it) but stays, so that the highest
  ranked report of each ``event_id`` holds whatever the order of arrival
  (``events.outlives_restart``).
- **Incremental or replay**: an event after the last one of the log is applied to the
  current state; a late one is inserted and the log replayed from its start. Both run the
  same fold, so they give bit-identical arrays.
- **Events** (time in the maths is days, ``t_s / DAY_S``):

  * ``TrcRecord``: restart, ``z = ln [top6_mm, align10_mm]`` in every sample, ``P = 0``.
    A record of some indicators only observes those exactly (``Banks.restart_partial``),
    keeps the log before it, and does not start a segment without state.
  * ``MaintenanceEvent`` (tamping): at ``t_start`` if ``t_start == t_end``, else at the
    middle of the *reported* interval ``(t_start + t_end) / 2``. The paper (Eq. 2) assumes
    the middle of the filter interval ``(t_{k-1}, t_k]`` in which a tamping is known to
    have happened; a maintenance report's interval is that knowledge, narrowed, so its
    middle is Eq. 2's rule on the report. It does not depend on the other events of the
    log (an on-board index inside the reported interval does not move it). The filter
    predicts to that time with ``tamping_age = 0``, i.e. resets to ``(z+, Sigma_z+)`` of
    each sample; the next event then degrades from there (Eq. 7-8 with the tamping age).
    A tamping also starts a state on a segment without any TRC record yet.
  * ``OnboardIndex``: predict to ``t`` and update with ``y = ln [top6_mm, align10_mm]``
    (Eq. 9-12, Joseph form), and add each sample's log-likelihood of ``y`` to its log
    weight (below). An index of some indices only updates with its rows of H, b, R
    (``banks.index_partial``).

- **Mixture weights** (a departure from Eq. 13's equal weights ``1 / Ns``): the posterior
  samples ``j`` are the segment's line (or network) pooled degradation posterior, so a
  segment degrading faster than its pool would be forecast with the pool's drift. Each
  state therefore carries ``log_w[j] = sum_k log N(nu_jk; 0, S_jk)`` over its on-board
  updates since the last TRC restart (innovation ``nu``, innovation covariance ``S`` of
  sample ``j``; the Kalman prediction error decomposition of the likelihood of the
  segment's own data), and the summaries weight sample ``j`` by
  ``w_j ∝ exp(log_w[j])`` (``mixture.weights_from_log``): Bayes' rule on the equally
  likely samples. A TRC restart resets ``log_w`` to 0 (equal weights), a tamping keeps it
  (the data still speak for the segment's parameters), a tamping that starts a state
  starts it at 0. ``log_w`` is part of the fold, so it is as deterministic as ``z, P``
  and is rebuilt by the same replay (nothing extra is stored).

- **Not publishable yet** (events are kept, no state is output): no TRC record or tamping
  to start from, no degradation posterior for the segment, or an on-board index in the log
  while there is no calibration. Indices before the first start of a segment without a
  TRC record are kept in the log but skipped by the fold (there is nothing to update).
- **Models**: one Calibration (``H, b, R``) and DegradationPosteriors per group. A segment
  uses the most specific group available: ``seg.{line}.{segment}``, then ``line.{line}``,
  then ``net``. A model with a version not newer than the one held is ignored; a model is
  checked completely (:func:`parse_model`) before it may replace the one held, and a
  refused one leaves the models and segment histories as they were. A new calibration re-runs every
  segment, a new posterior the segments that now use its group; several models at once
  (:meth:`Tracker.update_models`) re-run the union of their segments once.
- **Batched re-run**: a re-run (model change, restart) folds all its segments together
  (:func:`fold_many`: one vectorised step per event position over the segments still
  holding an event there, split by kind) and summarises them together
  (:func:`summarize_states`). A segment's numbers never depend on the other segments of a
  call, so the re-run, a replay of one segment and the live one-event step give the same
  bits.
- ``nis`` is the mean over samples of the per-sample NIS of the last update since the start
  of the state (a tamping keeps it; a TRC restart clears it to None), weighted by the
  mixture weights before that update (the predictive distribution the index is checked
  against); ``n_updates`` counts the updates since the last TRC record (or since the
  tamping that started the state).
- **Logs held lazily** (:class:`Histories`): a segment's log can rest outside memory (in
  the store) while its state stays; it is read back through a loader the first time it
  is needed (a late event, a duplicate check, detection, a re-run). A re-run of every
  segment goes through them in chunks (``RERUN_CHUNK``), so it holds one chunk of logs.

:class:`Tracker` keeps the segment histories (:class:`Histories`) and the models; its
:meth:`step` returns a :class:`Step` (accepted or not, why, and the SegmentStates to publish), its
:meth:`~Tracker.update_models` a :class:`ModelUpdate`.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from schemas import (
    Calibration,
    DegradationPosterior,
    MaintenanceEvent,
    SegmentState,
)
from schemas.keys import SegmentId
from services.filtering.banks import BankRow, Scratch
from services.filtering.batch import BatchFold
from services.filtering.events import (
    Event,
    EventMessage,
    ModelMessage,
    event_of,
)
from services.filtering.fold import fold_many
from services.filtering.histories import (
    Checkpoint,
    Histories,
    LogLoader,
    SegmentHistory,
    checkpoint_of,
    rested,
    summarised,
)
from services.filtering.models import (
    Models,
    held_version,
    key_units,
    model_name,
    models_key,
    parse_model,
    with_parsed,
)
from services.filtering.segment import (
    add_event,
    advance,
    publishable,
    redetected,
    replay_checked,
    replay_many,
)
from services.filtering.summary import summarize_states

HORIZONS_DAYS = (30.0, 90.0, 180.0)
SUMMARY_SEGMENTS = 32  # segments per batched summary: 512 quantile searches, spread over the cores
RERUN_CHUNK = 2048  # segments re-run together: one chunk of logs in memory at a time


@dataclass(frozen=True)
class Step:
    """What one message did: accepted (else ``reason``), the states to publish, the
    tampings it made :func:`detect` find (to be stored and published like a report), and
    the detected tampings it took out of the log (:func:`advance`: to delete from the
    store)."""

    accepted: bool
    reason: str = ""
    states: tuple[SegmentState, ...] = ()
    detected: tuple[MaintenanceEvent, ...] = ()
    withdrawn: tuple[MaintenanceEvent, ...] = ()


@dataclass(frozen=True)
class ModelUpdate:
    """What :meth:`Tracker.update_models` did with each model message, and the new states.

    ``accepted``: applied (the newest version per model name); ``ignored``: not newer than
    the one held or superseded by a newer one in the same update, with why; ``refused``:
    invalid (the reason names the field) or its re-run failed; ``states``: the re-run
    segments' publishable states; ``detected``, ``withdrawn``: the detected tampings the
    re-run found or took out (stored and published as a fold's are).
    """

    accepted: list[ModelMessage] = field(default_factory=list)
    ignored: list[tuple[ModelMessage, str]] = field(default_factory=list)
    refused: list[tuple[ModelMessage, str]] = field(default_factory=list)
    states: tuple[SegmentState, ...] = ()
    detected: tuple[MaintenanceEvent, ...] = ()  # tampings the new models find in the data
    withdrawn: tuple[MaintenanceEvent, ...] = ()  # detected ones the new models do not


class Tracker:
    """Every segment's :class:`SegmentHistory` (dict by ``(line, segment)``) and the models.

    Parameters
    ----------
    limits_mm
        ``limits_mm(line) -> (L, n)`` mm, e.g. ``services.limits.Limits.for_line``.
    limit_levels
        The ``L`` level names, e.g. ``Limits.levels``.
    horizons_days
        Forecast horizons.
    detect_maintenance
        Look for unreported tampings in the on-board data after each index (:func:`detect`).
    """

    def __init__(
        self,
        limits_mm,
        limit_levels: Iterable[str],
        horizons_days: Iterable[float] = HORIZONS_DAYS,
        *,
        detect_maintenance: bool = True,
        loader: LogLoader | None = None,
    ) -> None:
        self.detect_maintenance = detect_maintenance  # :func:`detect` after each index
        self.histories = Histories(loader)
        self.models = Models()
        self._scratch = Scratch()  # the stacked states of the live and backlog folds
        # the rows of the bank a batch's fold took for resting segments, until the swap
        self._taken: list[tuple[SegmentId, BankRow]] = []
        self._limits_mm = limits_mm
        self.limit_levels = list(limit_levels)
        self.horizons_days = np.asarray(tuple(horizons_days), dtype=np.float64)

    def step(self, msg: EventMessage | ModelMessage) -> Step:
        """Apply one decoded message; the returned states are the segments it changed.

        A model is :meth:`update_models` of that one message; an invalid one raises
        ValueError with the reason (the service turns it into a dead letter).
        """
        if isinstance(msg, Calibration | DegradationPosterior):
            update = self.update_models([msg])
            if update.refused:
                raise ValueError(update.refused[0][1])
            if update.ignored:
                return Step(False, update.ignored[0][1])
            return Step(True, "", update.states)
        event = event_of(msg)
        sid = (msg.line, msg.segment)
        hist = self.histories.get(sid) or SegmentHistory(msg.line, msg.segment)
        done = advance(hist, event, self.models, detecting=self.detect_maintenance)
        if done.reason:
            return Step(False, done.reason)
        out = self.segment_state(done.hist)  # before the swap: if it raises, nothing changed
        self.histories[sid] = done.hist
        return Step(True, "", () if out is None else (out,), done.found, done.withdrawn)

    def step_events(self, msgs: Sequence[EventMessage]) -> tuple[list[str], tuple, list, list]:
        """Fold several events and summarise each changed segment once, in batches.

        Returns ``(reasons, states, detected, withdrawn)``: per message ``""`` if accepted,
        else why not; the newest SegmentState of each changed, publishable segment; the
        tampings :func:`detect` found on the way and the detected tampings taken out of the
        logs (net over the batch: :class:`BatchFold`). The histories are the same as after
        stepping the messages one by one, bit for bit (:meth:`fold_events`), and so are the
        final states (:meth:`segment_states` is :meth:`segment_state` in batches); only the
        intermediate states of a segment are not summarised. If anything raises, nothing is changed.
        """
        try:
            reasons, changed, detected, withdrawn = self._fold_events(msgs)
            states = self.segment_states([summarised(h) for h in changed.values()])
        except BaseException:  # before the swap: nothing changed
            self._settle()
            raise
        self._swap(changed)
        self._settle()
        return reasons, tuple(state for state in states if state is not None), detected, withdrawn

    def fold_events(self, msgs: Sequence[EventMessage]) -> tuple[list[str], list, list, list]:
        """:meth:`step_events` without the summaries: ``(reasons, changed, detected,
        withdrawn)``, with the ids of the segments whose history changed (their states:
        :meth:`states_of`)."""
        try:
            reasons, changed, detected, withdrawn = self._fold_events(msgs)
        except BaseException:  # nothing changed
            self._settle()
            raise
        self._swap(changed)
        self._settle()
        return reasons, list(changed), detected, withdrawn

    def _settle(self) -> None:
        """Give back the rows the last batch's fold took and no segment rests in."""
        taken, self._taken = self._taken, []
        self.histories.settle(taken)

    def states_of(self, sids: Iterable[SegmentId]) -> list[SegmentState]:
        """The publishable SegmentStates of the segments ``sids`` (in batches; a resting
        segment's log is not read)."""
        known = [sid for sid in sids if sid in self.histories]
        resting = iter(
            self.histories.resting_many([s for s in known if not self.histories.is_loaded(s)])
        )
        hists = [
            summarised(self.histories.load(sid) if self.histories.is_loaded(sid) else next(resting))
            for sid in known
        ]
        return [state for state in self.segment_states(hists) if state is not None]

    def _fold_events(self, msgs: Sequence[EventMessage]):
        """``(reasons, changed, detected, withdrawn)`` of stepping ``msgs`` one by one,
        nothing swapped (:class:`BatchFold`: bit for bit :meth:`step` per message)."""
        batch = BatchFold(
            self.histories,
            self.models,
            detect_maintenance=self.detect_maintenance,
            scratch=self._scratch,
            taken=self._taken,
        )
        return batch.run(msgs)

    def update_models(self, msgs: Sequence[ModelMessage]) -> ModelUpdate:
        """Apply several model messages at once, re-running each affected segment once.

        Keeps the newest version per model name (``calibration``,
        ``degradation/{group}``) among the valid messages newer than the one held, checks
        each completely (:func:`parse_model`) before anything is replaced, then re-runs the
        union of the segments they affect in one batched pass (:func:`replay_many`). The
        swap is atomic: if the re-run fails, the models and histories stay as they were and
        the messages are refused with the reason (one by one if there were several, so
        that a good one still applies). Same final states as stepping the messages one by
        one, in any order.
        """
        models, newest, ignored, refused = self._newest_models(msgs)
        if not newest:
            return ModelUpdate([], ignored, refused)
        calibrated = any(isinstance(m, Calibration) and not m.train for m in newest.values())
        units = {
            (m.train, m.unit) for m in newest.values() if isinstance(m, Calibration) and m.train
        }
        groups = {msg.group for msg in newest.values() if isinstance(msg, DegradationPosterior)}
        affected = [
            sid
            for sid in self.histories
            if calibrated
            or models.group_for(*sid) in groups
            or (units and not units.isdisjoint(self.histories.units(sid)))
        ]
        accepted = [msg for msg in msgs if newest.get(model_name(msg)) is msg]
        try:
            hists, states, found, withdrawn = self._rerun(
                models, affected, detect=self.detect_maintenance
            )
        except (ValueError, ArithmeticError) as exc:
            if len(accepted) == 1:
                refused.append((accepted[0], f"re-run with this model failed: {exc}"))
                return ModelUpdate([], ignored, refused)
            one_by_one = [self.update_models([msg]) for msg in accepted]
            return ModelUpdate(
                [m for u in one_by_one for m in u.accepted],
                ignored + [m for u in one_by_one for m in u.ignored],
                refused + [m for u in one_by_one for m in u.refused],
                tuple(state for u in one_by_one for state in u.states),
                tuple(m for u in one_by_one for m in u.detected),
                tuple(m for u in one_by_one for m in u.withdrawn),
            )
        self.models = models
        self._swap(hists)
        return ModelUpdate(accepted, ignored, refused, states, found, withdrawn)

    def _newest_models(self, msgs: Iterable[ModelMessage]):
        """``(models, newest, ignored, refused)``: the held models with the newest valid
        message per name applied (``newest`` by name), and the messages left out, with why."""
        ignored: list[tuple[ModelMessage, str]] = []
        refused: list[tuple[ModelMessage, str]] = []
        newest: dict[str, tuple[ModelMessage, Any]] = {}
        for msg in msgs:
            name = model_name(msg)
            held = held_version(self.models, msg)
            if held is not None and msg.version <= held:
                ignored.append((msg, "version not newer than the one held"))
                continue
            try:
                parsed = parse_model(msg)
            except ValueError as exc:
                refused.append((msg, str(exc)))
                continue
            previous = newest.get(name)
            if previous is not None:
                if msg.version <= previous[0].version:
                    why = f"superseded by version {previous[0].version} in the same update"
                    ignored.append((msg, why))
                    continue
                why = f"superseded by version {msg.version} in the same update"
                ignored.append((previous[0], why))
            newest[name] = (msg, parsed)
        models = self.models
        for msg, parsed in newest.values():
            models = with_parsed(models, msg, parsed)
        return models, {name: msg for name, (msg, _) in newest.items()}, ignored, refused

    def load(self, models: Iterable[ModelMessage], events: Iterable[EventMessage]) -> list:
        """Rebuild from stored models and events (any order): the publishable states.

        A stored model that is no longer valid is skipped (:meth:`update_models` says why),
        so that it cannot stop a restart.
        """
        for msg in events:
            sid = (msg.line, msg.segment)
            hist = self.histories.get(sid) or SegmentHistory(msg.line, msg.segment)
            self.histories[sid] = add_event(hist, event_of(msg))[0]
        models_in, *_ = self._newest_models(models)
        hists, states, *_ = self._rerun(models_in, list(self.histories))
        self.models = models_in
        self._swap(hists)
        return list(states)

    def restore(
        self,
        models: Iterable[ModelMessage],
        checkpoints: Iterable[Checkpoint],
        tails: Mapping[SegmentId, Sequence[Event]],
        replay: Iterable[SegmentId] = (),
    ) -> tuple[list[SegmentId], list[SegmentState]]:
        """Restart from checkpoints: ``(kept, states)``.

        ``checkpoints``: each segment's last checkpoint (read once, in order: a stream
        keeps one state at a time besides the bank); ``tails``: per segment, the stored
        events its checkpoint does not cover; ``replay``: segments without a usable
        checkpoint (replayed from the log start, read through the loader; read after
        ``checkpoints``). A checkpoint
        folded with other models than the current ones (:func:`models_key` over the units
        its key names: a calibration of a unit its log does not read leaves it valid), or
        one written without its log's units, or followed
        by an event that sorts before its last one (a late event), is replayed from the
        log start too; one followed by newer events only is folded on over them (one
        :func:`fold_many` for all), which is the fold of the whole log, bit for bit.
        ``kept`` are the segments restored unchanged (their stored SegmentState still
        holds), ``states`` the SegmentStates of the others. The restored segments rest
        (their logs load when needed).
        """
        self.models, *_ = self._newest_models(models)
        full: set[SegmentId] = set()
        kept: list[SegmentId] = []
        on: list[tuple[SegmentId, Checkpoint, tuple[Event, ...]]] = []
        for ckpt in checkpoints:
            sid = (ckpt.line, ckpt.segment)
            units = key_units(ckpt.models_key)  # the units of its log, as written
            ckpt = replace(ckpt, units=units)
            self.histories.rest(sid, ckpt)
            tail = sorted(tails.get(sid, ()), key=lambda e: e.order)
            if (
                units is None
                or ckpt.models_key != models_key(self.models, *sid, units)
                or (tail and ckpt.last_order is not None and tail[0].order <= ckpt.last_order)
            ):
                full.add(sid)
            elif tail:
                on.append((sid, ckpt, tuple(tail)))
            else:
                kept.append(sid)
        full.update(replay)  # after the checkpoints: a stream of them may add to it
        for sid in full:
            if sid not in self.histories:  # no (usable) checkpoint: all from its log
                self.histories.rest(sid, Checkpoint(*sid, None, None, None, None), dirty=True)
        rested = self._fold_on(on)
        hists, states, *_ = self._rerun(self.models, sorted(full))
        self._swap(hists)
        for sid in hists:
            self.histories.dirty.add(sid)
        return kept, [*self._swap_states(rested), *states]

    def _fold_on(self, on: Sequence[tuple[SegmentId, Checkpoint, tuple[Event, ...]]]):
        """Fold each checkpoint on over its newer events (:meth:`restore`)."""
        out: dict[SegmentId, Checkpoint] = {}
        jobs: dict[int, list[int]] = {}
        for i, (sid, ckpt, tail) in enumerate(on):
            group = self.models.group_for(*sid)
            start = ckpt.state
            if group is None or not publishable(tail, self.models, started=start is not None):
                out[sid] = rested(ckpt, None, group, tail)
            else:
                jobs.setdefault(self.models.params[group].ns, []).append(i)
        for job in jobs.values():
            states = fold_many(
                [on[i][1].state for i in job],
                [on[i][2] for i in job],
                [self.models.params[self.models.group_for(*on[i][0])] for i in job],
                self.models,
            )
            for i, state in zip(job, states, strict=True):
                sid, ckpt, tail = on[i]
                out[sid] = rested(ckpt, state, self.models.group_for(*sid), tail)
        return out

    def _swap_states(self, rested: Mapping[SegmentId, Checkpoint]) -> list[SegmentState]:
        for sid, ckpt in rested.items():
            self.histories.rest(sid, ckpt, dirty=True)
        hists = [summarised(c) for c in rested.values()]
        return [s for s in self.segment_states(hists) if s is not None]

    def _swap(self, hists: Mapping[SegmentId, SegmentHistory | Checkpoint]) -> None:
        """Put re-run results in place: a history, or a resting state (log not kept)."""
        for sid, hist in hists.items():
            if isinstance(hist, Checkpoint):
                self.histories.rest(sid, hist, dirty=True)
            else:
                self.histories[sid] = hist

    def _rerun(self, models: Models, sids: Sequence[SegmentId], *, detect: bool = False):
        """Re-run ``sids`` with ``models``; nothing is changed in place. Returns the
        histories, their publishable states, and the detected tampings found and taken out.

        With ``detect`` (a model change while detecting), a segment whose replay could
        change a detection (:func:`~services.filtering.segment.replay_checked`) has its log
        walked again with :func:`~services.filtering.segment.redetect`, as the canonical
        delivery of its events would with these models. Without (a restart from the store,
        whose logs hold the detections made), the logs are replayed as they are.

        In chunks of ``RERUN_CHUNK`` segments (one batched :func:`replay_many` and
        summary each): a segment whose log was not loaded is read for its chunk only (as
        columns when the store gives them: :meth:`Histories.load_columns`) and comes back
        resting (a :class:`Checkpoint`), so a re-run of every segment holds one chunk of
        logs at a time.
        """
        out: dict[SegmentId, SegmentHistory | Checkpoint] = {}
        states: list[SegmentState] = []
        found: list[MaintenanceEvent] = []
        withdrawn: list[MaintenanceEvent] = []
        for first in range(0, len(sids), RERUN_CHUNK):
            chunk = sids[first : first + RERUN_CHUNK]
            logs = [self.histories.load_columns(sid) for sid in chunk]
            if detect:
                hists, suspects = replay_checked(logs, models)
                for j in suspects:
                    hists[j], new, gone = redetected(self.histories.load(chunk[j]), models)
                    found.extend(new)
                    withdrawn.extend(gone)
            else:
                hists = replay_many(logs, models)
            states.extend(s for s in self.segment_states(hists, models) if s is not None)
            for sid, hist in zip(chunk, hists, strict=True):
                if self.histories.is_loaded(sid):
                    out[sid] = hist
                else:
                    out[sid] = checkpoint_of(hist)
        return out, tuple(states), tuple(found), tuple(withdrawn)

    def segment_states(
        self, hists: Sequence[SegmentHistory], models: Models | None = None
    ) -> list[SegmentState | None]:
        """The SegmentState messages of histories (None if not publishable), in batches."""
        models = self.models if models is None else models
        out: list[SegmentState | None] = [None] * len(hists)
        jobs: dict[int, list[int]] = {}
        for i, hist in enumerate(hists):
            if hist.state is not None and hist.group is not None:
                jobs.setdefault(hist.state.z.shape[0], []).append(i)
        limits: dict[str, np.ndarray] = {}
        for job in jobs.values():
            for first in range(0, len(job), SUMMARY_SEGMENTS):
                chunk = job[first : first + SUMMARY_SEGMENTS]
                for line in {hists[i].line for i in chunk} - limits.keys():
                    limits[line] = np.asarray(self._limits_mm(line), dtype=np.float64)
                states = summarize_states(
                    [hists[i] for i in chunk],
                    [models.params[hists[i].group] for i in chunk],
                    [limits[hists[i].line] for i in chunk],
                    self.limit_levels,
                    self.horizons_days,
                    calibration_version=(models.calibration.version if models.calibration else 0),
                    posterior_versions=[models.posteriors[hists[i].group].version for i in chunk],
                )
                for i, state in zip(chunk, states, strict=True):
                    out[i] = state
        return out

    def segment_state(self, hist: SegmentHistory) -> SegmentState | None:
        """The SegmentState message of a history (None if not publishable)."""
        return self.segment_states([hist])[0]

    def state_of(self, line: str, segment: str) -> SegmentState | None:
        hist = self.histories.get((line, segment))
        return None if hist is None else self.segment_state(hist)
