"""One segment's history advanced by an event (:func:`add_event`, :func:`step_segment`,
:func:`advance`), replayed from its log (:func:`replay_many`), and searched for an
unreported tamping (:func:`detect`, :func:`redetect`)."""

from __future__ import annotations

import bisect
from collections.abc import Sequence
from dataclasses import replace
from typing import NamedTuple

import numpy as np

from schemas import DAY_S, MaintenanceEvent
from services.filtering.banks import CUSUM_THRESHOLD
from services.filtering.events import (
    INDEX,
    RESTART,
    TAMPING,
    Event,
    LogColumns,
    event_of,
    is_full_restart,
    outlives_restart,
    tamping_time,
)
from services.filtering.fold import fold_many, fold_many_counted
from services.filtering.histories import SegmentHistory
from services.filtering.models import Models
from services.filtering.state import Filtered

SUPERSEDE_DAYS = 30.0  # a reported tamping this close to a detected one replaces it
DERIVED = "a detected tamping is found in the segment's own log, not taken as an input"
WITHDRAWAL = "a withdrawal is filtering's own output, not taken as an input"


def publishable(log: Sequence[Event] | LogColumns, models: Models, started=False) -> bool:
    """False if the fold of ``log`` (from a started state if ``started``) needs an update
    without a calibration (neither the index's unit's nor the fleet's)."""
    if models.observation is not None:
        return True
    if isinstance(log, LogColumns):
        units = [models.observation_for(*u) is not None for u in log.unit_names]
        for kind, code in zip(log.kinds.tolist(), log.unit_codes.tolist(), strict=True):
            if kind != INDEX:
                started = True
            elif started and not units[code]:
                return False
        return True
    for event in log:
        if event.kind != INDEX:
            started = True
        elif started and models.observation_for_event(event) is None:
            return False
    return True


def _fold(hist: SegmentHistory, models: Models, events: Sequence[Event], start: Filtered | None):
    """Fold ``events`` from ``start``; (state, group) or (None, group) if not publishable."""
    group = models.group_for(hist.line, hist.segment)
    if group is None:
        return None, group
    if not publishable(events, models, started=start is not None):
        return None, group
    return fold_many([start], [events], [models.params[group]], models)[0], group


def replay_many(hists: Sequence[SegmentHistory], models: Models) -> list[SegmentHistory]:
    """The histories with their states recomputed from the start of their logs, in one pass.

    Segments of every posterior group go through one :func:`fold_many` per sample count
    ``Ns``; a segment without a group, or needing an update without a calibration, gets
    no state. Bit-identical to :func:`replay` of each history.
    """
    out = list(hists)
    jobs: dict[int, list[tuple[int, str]]] = {}
    for i, hist in enumerate(hists):
        group = models.group_for(hist.line, hist.segment)
        if group is None or not publishable(hist.log, models):
            out[i] = replace(hist, state=None, group=group)
        else:
            jobs.setdefault(models.params[group].ns, []).append((i, group))
    for job in jobs.values():
        states = fold_many(
            [None] * len(job),
            [hists[i].log for i, _ in job],
            [models.params[group] for _, group in job],
            models,
        )
        for (i, group), state in zip(job, states, strict=True):
            out[i] = replace(hists[i], state=state, group=group)
    return out


def replay_checked(
    hists: Sequence[SegmentHistory], models: Models
) -> tuple[list[SegmentHistory], list[int]]:
    """:func:`replay_many` for a model change with detection on: ``(histories, suspects)``.

    Whether a log's on-board data show an unreported tamping depends on the models, so a
    model change may find one or withdraw one. The replay folds each log halting where
    the CUSUM reaches :data:`CUSUM_THRESHOLD` (:func:`detect`'s condition); ``suspects``
    are the positions of the histories that halted, ended at the threshold, or hold a
    tamping (a detected one may go): their states here are not to be kept, the caller
    walks their logs again (:func:`redetected`). The others' states are those of
    :func:`replay_many`, bit for bit."""
    out = list(hists)
    suspects: list[int] = []
    jobs: dict[int, list[tuple[int, str]]] = {}
    for i, hist in enumerate(hists):
        group = models.group_for(hist.line, hist.segment)
        if _holds_tamping(hist.log):
            suspects.append(i)
        elif group is None or not publishable(hist.log, models):
            out[i] = replace(hist, state=None, group=group)
        else:
            jobs.setdefault(models.params[group].ns, []).append((i, group))
    for job in jobs.values():
        logs = [hists[i].log for i, _ in job]
        states, counts = fold_many_counted(
            [None] * len(job), logs, [models.params[group] for _, group in job], models,
            CUSUM_THRESHOLD,
        )  # fmt: skip
        for (i, group), state, count, log in zip(job, states, counts, logs, strict=True):
            if count < len(log) or (state is not None and state.cusum >= CUSUM_THRESHOLD):
                suspects.append(i)
            else:
                out[i] = replace(hists[i], state=state, group=group)
    return out, sorted(suspects)


def _holds_tamping(log: Sequence[Event] | LogColumns) -> bool:
    if isinstance(log, LogColumns):
        return bool((log.kinds == TAMPING).any())
    return any(e.kind == TAMPING for e in log)


def replay(hist: SegmentHistory, models: Models) -> SegmentHistory:
    """The history with its state recomputed from the start of its log."""
    return replay_many([hist], models)[0]


def add_event(hist: SegmentHistory, event: Event) -> tuple[SegmentHistory, str]:
    """Insert ``event`` into the log (state untouched): ``(hist, "")`` or ``(hist, reason)``.

    A tamping report that outranks the one held under its ``event_id`` (``MaintenanceEvent.rank``)
    replaces it. A reported tamping is accepted before the latest TRC record too, and a
    TRC record keeps those before it (:func:`outlives_restart`): there they change nothing
    of the state, and they keep every lower-ranked report of their ``event_id`` out
    whatever the order of arrival. Any other event before the latest TRC record is refused.
    """
    held = next((e for e in hist.log if e.identity == event.identity), None)
    log, trc_t = hist.log, hist.trc_t
    if event.kind == TAMPING and held is None:
        near = [
            e for e in log if e.kind == TAMPING and abs(e.t_s - event.t_s) <= SUPERSEDE_DAYS * DAY_S
        ]
        if event.message.detected:
            if any(not e.message.detected for e in near):
                return hist, "a reported tamping is within 30 days"
        else:  # a reported tamping replaces the detected ones near it
            log = tuple(e for e in log if not (e in near and e.message.detected))
    if held is not None:
        if event.kind != TAMPING or event.message.rank <= held.message.rank:
            return hist, "duplicate"
        log = tuple(e for e in log if e is not held)
    elif trc_t is not None and event.t_s < trc_t and not outlives_restart(event):
        return hist, "older than the latest TRC record"
    if is_full_restart(event):  # a restart forgets what precedes it, but for the reports
        log = tuple(e for e in log if e.t_s >= event.t_s or outlives_restart(e))
        trc_t = event.t_s if trc_t is None else max(trc_t, event.t_s)
    at = bisect.bisect([e.order for e in log], event.order)
    return replace(hist, log=(*log[:at], event, *log[at:]), trc_t=trc_t), ""


def step_segment(hist: SegmentHistory, event: Event, models: Models) -> tuple[SegmentHistory, str]:
    """Add one event to a segment and bring its state up to date: ``(hist, reason)``.

    ``reason`` is empty when the event was accepted, else why it was refused.
    """
    new, reason = add_event(hist, event)
    if reason:
        return hist, reason
    return _refolded(hist, new, event, models), ""


def _refolded(hist: SegmentHistory, new: SegmentHistory, event: Event, models: Models):
    """``new`` (``hist`` with ``event`` added) with its state: one more step of
    ``hist.state`` when ``event`` only extends the log (a TRC record, which restarts the
    state, also when it drops the events before it), else the replay of the log."""
    last = bool(new.log) and new.log[-1] is event
    extends = last and len(new.log) == len(hist.log) + 1
    if (extends and hist.state is not None) or (last and event.kind == RESTART):
        state, group = _fold(new, models, (event,), hist.state)
        return replace(new, state=state, group=group)
    return replay(new, models)


def is_detected(event: Event) -> bool:
    return event.kind == TAMPING and event.message.detected


def _detected_in(hist: SegmentHistory) -> dict:
    """The detected tampings of the log's window, by identity."""
    return {e.identity: e.message for e in hist.log if is_detected(e)}


class Advanced(NamedTuple):
    """One event's effect on a segment (:func:`advance`): the new history, why the event
    was refused (empty: accepted), the detected tampings it added to the log and those it
    took out of it (a report superseding them, or a detection the event invalidated)."""

    hist: SegmentHistory
    reason: str
    found: tuple[MaintenanceEvent, ...] = ()
    withdrawn: tuple[MaintenanceEvent, ...] = ()


def advance(hist: SegmentHistory, event: Event, models: Models, *, detecting: bool) -> Advanced:
    """One event into a segment, its state and (``detecting``) its detected tampings up to
    date.

    The detected tampings of a log are those that delivering its other events one at a
    time in canonical order would make (:func:`detect` after each): a function of the log,
    not of the order of arrival. An event after every event of the log is the next step of
    that walk; one that sorts before the log's end (a late event, a correction of a
    tamping) re-runs the walk from the log's start (:func:`redetect`), which withdraws the
    detections it invalidates. With ``detecting``, a detected tamping is not an input (the
    instance's own output coming back, or another instance's): refused with ``DERIVED``.
    A withdrawal (``MaintenanceEvent.withdrawn``) is never an input: ``WITHDRAWAL``.
    """
    if event.kind == TAMPING and event.message.withdrawn:
        return Advanced(hist, WITHDRAWAL)
    if detecting and is_detected(event):
        return Advanced(hist, DERIVED)
    new, reason = add_event(hist, event)
    if reason:
        return Advanced(hist, reason)
    held = any(e.identity == event.identity for e in hist.log)
    in_step = bool(new.log) and new.log[-1] is event and not held
    if not detecting or in_step:
        new = _refolded(hist, new, event, models)
        found = None
        if detecting:
            new, found = detect(new, models)
        withdrawn = ()
        if event.kind == TAMPING and len(new.log) < len(hist.log) + 1 + (found is not None):
            withdrawn = _changes(hist, new)[1]  # a report superseding detected ones
        return Advanced(new, "", () if found is None else (found,), withdrawn)
    new = redetect(new, models)
    return Advanced(new, "", *_changes(hist, new))


def redetected(hist: SegmentHistory, models: Models):
    """``(history, found, withdrawn)``: :func:`redetect` with ``models`` and the detected
    tampings that changed."""
    new = redetect(hist, models)
    return (new, *_changes(hist, new))


def _changes(old: SegmentHistory, new: SegmentHistory):
    """``(found, withdrawn)``: the detected tampings ``new``'s log has and ``old``'s does not
    (or holds otherwise), and those of ``old``'s log within ``new``'s window that ``new``'s
    does not hold as they were (a TRC record's pruning is no withdrawal)."""
    before, after = _detected_in(old), _detected_in(new)
    trc_t = new.trc_t
    found = tuple(m for k, m in after.items() if before.get(k) != m)
    withdrawn = tuple(
        m
        for k, m in before.items()
        if after.get(k) != m and (trc_t is None or tamping_time(m) >= trc_t)
    )
    return found, withdrawn


def redetect(hist: SegmentHistory, models: Models) -> SegmentHistory:
    """``hist`` with its detected tampings and state those of its log's other events
    delivered one at a time in canonical order, :func:`detect` after each (runs of indices
    are folded together, halting where the CUSUM reaches the threshold: the same bits)."""
    base = [e for e in hist.log if not is_detected(e)]
    group = models.group_for(hist.line, hist.segment)
    params = None if group is None else models.params[group]
    cur = SegmentHistory(hist.line, hist.segment, group=group)
    k = 0
    while k < len(base):
        event = base[k]
        if event.kind == INDEX and cur.state is None:  # nothing to update: state stays None
            cur = replace(cur, log=(*cur.log, event), group=group)
            k += 1
            continue
        end = k
        while (
            end < len(base)
            and base[end].kind == INDEX
            and models.observation_for_event(base[end]) is not None
        ):
            end += 1
        if end > k:
            run = tuple(base[k:end])
            (state,), (count,) = fold_many_counted(
                [cur.state], [run], [params], models, CUSUM_THRESHOLD
            )
            cur = replace(cur, log=cur.log + run[:count], state=state, group=group)
            k += count
        else:
            cur, reason = step_segment(cur, event, models)
            k += 1
            if reason:
                continue
        cur, _ = detect(cur, models)
    return replace(cur, trc_t=hist.trc_t)


def detect(hist: SegmentHistory, models: Models) -> tuple[SegmentHistory, MaintenanceEvent | None]:
    r"""A tamping that no feed reported, found in the segment's on-board indices.

    The fold keeps a one-sided CUSUM (Page's test) of the standardised amount by which each
    index reads below the mixture's prediction (:func:`low_score`):
    :math:`g_k = \max(0, g_{k-1} - \max(s_k, -c) - \kappa)`, reset to 0 by a TRC record or a
    tamping. A tamping lowers both indicators to about :math:`z^+` at once, so the indices
    after it read several standard deviations low and :math:`g` grows; degradation and noise
    do not. When :math:`g \ge h` the tamping lies in one of the intervals between the
    consecutive events since the CUSUM last was 0 (``cusum_t0``); for each the segment is
    re-run with a tamping there (Eq. 2: at the interval's middle), and the interval whose
    re-run gives the on-board data the highest marginal likelihood
    :math:`\log \frac{1}{N_s}\sum_j e^{\log w_j}` is reported as the detected
    maintenance ``[t_a, t_b]``. ``(hist, None)`` when nothing is detected, or when a
    reported tamping within ``SUPERSEDE_DAYS`` already explains the data.
    """
    state = hist.state
    if state is None or state.cusum < CUSUM_THRESHOLD or np.isnan(state.cusum_t1):
        return hist, None
    times = sorted({e.t_s for e in hist.log if e.t_s >= state.cusum_t0})
    best: tuple[float, SegmentHistory, MaintenanceEvent] | None = None
    for t_a, t_b in zip(times, times[1:], strict=False):
        msg = MaintenanceEvent(
            line=hist.line,
            segment=hist.segment,
            event_id=f"detected-{int(t_b)}",
            t_start=t_a,
            t_end=t_b,
            detected=True,
        )
        new, reason = step_segment(hist, event_of(msg), models)
        if reason or new.state is None:
            continue
        log_w = new.state.log_w
        evidence = float(log_w.max() + np.log(np.exp(log_w - log_w.max()).mean()))
        if best is None or evidence > best[0]:
            best = (evidence, new, msg)
    return (hist, None) if best is None else (best[1], best[2])
