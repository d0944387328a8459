"""The fold: each segment's log applied to its state, many segments at once
(:func:`fold_many`), one vectorised step per event position (:func:`_fold_steps`) or, for
the system's 2 x 2 observation model, compiled runs of indices (:func:`_fold_runs`).
A segment's numbers never depend on the other segments of a call."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import NamedTuple

import numpy as np

from services.filtering.banks import (
    CUSUM_CLIP,
    CUSUM_DRIFT,
    BankRow,
    Banks,
    RestingBank,
    RowParams,
    Scratch,
    index_partial,
)
from services.filtering.degradation import DegradationParams
from services.filtering.events import INDEX, RESTART, TAMPING, Event, LogColumns
from services.filtering.kalman import ObservationModel
from services.filtering.kernel import index_runs
from services.filtering.models import Models
from services.filtering.state import Filtered

# In a fold's grid only: an index of some indices (its y NaN at the others), stepped with
# numpy (:func:`banks.index_partial`) outside the compiled runs, which stop at it.
PARTIAL_INDEX = 3


def fold_many(
    starts: Sequence[Filtered | None],
    logs: Sequence[Sequence[Event]],
    params: Sequence[DegradationParams],
    obs: ObservationModel | Models | None,
    scratch: Scratch | None = None,
) -> list[Filtered | None]:
    """Fold each ``logs[i]`` from ``starts[i]`` with ``params[i]``, all segments at once.

    One vectorised step per event position ``k``: the segments are ordered by decreasing
    log length, so those still holding a k-th event are a prefix, and split by the kind of
    that event (and an index's rows by the observation model of its unit). Bit-identical to
    folding each segment alone (see :class:`Banks`). Every ``params[i]`` must have the same
    ``(Ns, n)``; ``obs`` is one observation model for every index, or the :class:`Models`
    whose :meth:`~Models.observation_for` gives each index its unit's; there must be one
    for an index that follows a start (the caller checks it, see :func:`publishable`).
    Without ``scratch`` the states are views of the call's stacked arrays; with it they are
    copies, the fold having run in the scratch's reused buffer.
    """
    return fold_many_counted(starts, logs, params, obs, scratch=scratch)[0]


def fold_many_counted(
    starts,
    logs,
    params,
    obs,
    halt_cusum: float | None = None,
    copy=False,
    scratch=None,
    into: RestingBank | None = None,
):
    """:func:`fold_many`, and how many events of each log were folded: ``(states, folded)``.

    ``halt_cusum``: a segment stops after the first index that leaves its CUSUM at or above
    this (:func:`detect`'s condition), its state the one after that index, and ``folded[i]``
    says how many of its events that was. Every index's NIS is then computed (a halted
    row's last update is not known in advance); the bits do not change, since the NIS of a
    row is a sum over its own samples. ``copy``: each state owns its arrays
    (:meth:`Banks.states`); ``scratch`` (a :class:`Scratch`): the fold runs in its buffer
    and the states are copied out. ``into``: ``starts`` are all rows of that bank of
    resting states (:class:`BankRow`) and ``logs`` hold indices only; each is folded from
    its row into a free row of the bank (:func:`kernel.index_runs`' ``homes``), and the
    states are returned as those rows (:class:`BankRow`, taken: :meth:`Histories.settle`
    gives back the ones no segment keeps).
    """
    size = len(logs)
    if size == 0:
        return [], []
    ns, n = params[0].ns, params[0].n
    order = sorted(range(size), key=lambda i: -len(logs[i]))
    grid = _grid(logs, order, n, obs)
    runs = n == 2 and all(model.H.shape == (2, 2) for model in grid.observations)
    partial = bool((grid.kinds == PARTIAL_INDEX).any())
    if into is not None and (partial or not runs):  # (not indices of every kind) from copies
        starts, into = [start.state() for start in starts], None
    if into is not None:
        banks, homes = _into_free_rows(into, [starts[i] for i in order], grid.kinds)
    else:
        banks, homes = Banks([starts[i] for i in order], ns, n, scratch), None
    rows_params = RowParams([params[i] for i in order])
    lengths = np.array([len(logs[i]) for i in order])
    folded = lengths.copy()  # events folded per row (fewer if halted)
    fold = _fold_runs if runs else _fold_steps
    fold(banks, grid.kinds, grid.times, grid.values, grid.obs_ids, grid.observations,
         rows_params, lengths, folded, halt_cusum, homes)  # fmt: skip
    if homes is not None:
        states = [BankRow(banks, row) for row in homes[1].tolist()]
    else:
        states = banks.states(range(size), copy=copy or scratch is not None)
    out: list[Filtered | BankRow | None] = [None] * size
    counts = [0] * size
    for i, state, count in zip(order, states, folded.tolist(), strict=True):
        out[i] = state
        counts[i] = count
    return out, counts


class _Grid(NamedTuple):
    """A fold's logs, longest first, as padded ``(rows, depth)`` arrays: ``kinds`` (-1 past
    a log's end), ``times``, ``values`` (rows, depth, n), and ``obs_ids``: an index's
    observation model, its position in ``observations`` (-1: none, or not an index)."""

    kinds: np.ndarray
    times: np.ndarray
    values: np.ndarray
    obs_ids: np.ndarray
    observations: list[ObservationModel]


class _ObservationIds:
    """Numbers the observation models of a fold in the order they are first met."""

    def __init__(self, observations: list[ObservationModel]) -> None:
        self.observations = observations
        self._known: dict[int, int] = {}

    def __call__(self, model: ObservationModel | None) -> int:
        if model is None:
            return -1
        if id(model) not in self._known:
            self._known[id(model)] = len(self.observations)
            self.observations.append(model)
        return self._known[id(model)]


def _grid(logs, order: list[int], n: int, obs: ObservationModel | Models | None) -> _Grid:
    """The :class:`_Grid` of ``logs`` in ``order``; ``obs``: :func:`fold_many`'s."""
    # one model for every index (no unit has its own): no per-event look-up
    per_unit = obs if isinstance(obs, Models) and obs.unit_observations else None
    shared = obs.observation if isinstance(obs, Models) else obs
    size, depth = len(order), len(logs[order[0]])
    grid = _Grid(
        np.full((size, depth), -1, dtype=np.int8),
        np.zeros((size, depth)),
        np.zeros((size, depth, n)),
        np.full((size, depth), -1, dtype=np.int32),
        [],
    )
    model_id = _ObservationIds(grid.observations)
    # the Events of every row in one pass (a backlog folds ~1,000 rows of one index each),
    # LogColumns row by row
    at_row: list[int] = []
    at_k: list[int] = []
    events: list[Event] = []
    for row, i in enumerate(order):
        log = logs[i]
        if isinstance(log, LogColumns):
            _put_columns(grid, row, log, per_unit, model_id)
        else:
            at_row.extend([row] * len(log))
            at_k.extend(range(len(log)))
            events.extend(log)
    if events:
        _put_events(grid, at_row, at_k, events, per_unit, model_id)
    if per_unit is None and shared is not None:
        grid.observations.append(shared)
        grid.obs_ids[grid.kinds == INDEX] = 0
    grid.kinds[(grid.kinds == INDEX) & np.isnan(grid.values).any(axis=-1)] = PARTIAL_INDEX
    return grid


def _put_columns(grid: _Grid, row: int, log: LogColumns, per_unit: Models | None, model_id):
    """Row ``row`` of the grid from a log of columns."""
    grid.kinds[row, : len(log)] = log.kinds
    grid.times[row, : len(log)] = log.times
    grid.values[row, : len(log)] = log.values
    if per_unit is not None and log.unit_names:
        ids = np.array([model_id(per_unit.observation_for(*u)) for u in log.unit_names])
        at = np.flatnonzero(log.unit_codes >= 0)
        grid.obs_ids[row, at] = ids[log.unit_codes[at]]


def _put_events(grid: _Grid, at_row, at_k, events: list[Event], per_unit: Models | None, model_id):
    """Each of ``events`` at ``(at_row, at_k)`` of the grid, in one assignment per array."""
    zero = np.zeros(grid.values.shape[-1])
    grid.kinds[at_row, at_k] = [e.kind for e in events]
    grid.times[at_row, at_k] = [e.t_s for e in events]
    grid.values[at_row, at_k] = [zero if e.value is None else e.value for e in events]
    if per_unit is not None:
        for row, k, e in zip(at_row, at_k, events, strict=True):
            if e.kind == INDEX:
                grid.obs_ids[row, k] = model_id(per_unit.observation_for_event(e))


def _into_free_rows(into: RestingBank, starts: list[BankRow], kinds: np.ndarray):
    """``(banks, homes)`` of a fold from rows of ``into`` (``starts``, in fold order) into
    free rows of it, the scalars copied there first (the samples move with the fold)."""
    if not (kinds[kinds >= 0] == INDEX).all():
        raise ValueError("a fold from resting rows takes indices only")
    banks = into.banks
    srcs = np.array([start.row for start in starts], dtype=np.int64)
    ats = np.array(into.take(len(starts)), dtype=np.int64)
    for name in Banks.SCALARS:
        values_of = getattr(banks, name)
        values_of[ats] = values_of[srcs]
    return banks, (srcs, ats)


def _fold_steps(
    banks,
    kinds,
    times,
    values,
    obs_ids,
    observations,
    rows_params,
    lengths,
    folded,
    halt_cusum,
    homes=None,
):
    """:func:`fold_many_counted`'s fold one event position at a time over every row (any ``n``, any
    observation model: :meth:`Banks.index`); ``folded`` gets a halted row's count. The
    rows are ordered by decreasing log length."""
    if homes is not None:
        raise ValueError("a fold from resting rows (homes) is _fold_runs' only")
    depth = kinds.shape[1]
    # position of each row's last index: the NIS of a state is that of its last update
    last_index = depth - 1 - np.argmax(kinds[:, ::-1] == INDEX, axis=1)
    for k in range(depth):
        active = int(np.count_nonzero(lengths > k))
        kind = kinds[:active, k]
        for code in (RESTART, TAMPING, INDEX, PARTIAL_INDEX):
            rows = np.flatnonzero(kind == code)
            if code in (INDEX, PARTIAL_INDEX):
                rows = rows[banks.started[rows]]  # an index before any start is skipped
            if len(rows) == 0:
                continue
            if code == RESTART:
                banks.restart(rows, times[rows, k], values[rows, k], rows_params)
            elif code == TAMPING:
                banks.tamping(rows, times[rows, k], rows_params)
            else:
                ids = obs_ids[rows, k]
                assert (ids >= 0).all()
                for j in np.unique(ids):  # the rows whose index is read by model j
                    sub = rows if len(observations) == 1 else rows[ids == j]
                    last = None if halt_cusum is not None else last_index[sub] == k
                    at = (sub, times[sub, k], values[sub, k], rows_params, observations[j])
                    if code == PARTIAL_INDEX:
                        index_partial(banks, *at)
                    else:
                        banks.index(*at, last)
                    if halt_cusum is not None:
                        halted = sub[banks.cusum[sub] >= halt_cusum]
                        kinds[halted, k + 1 :] = -1  # nothing more is folded on these rows
                        folded[halted] = k + 1


def _fold_runs(
    banks, kinds, times, values, obs_ids, observations, params, lengths, folded, halt, homes=None
):
    """:func:`fold_many_counted`'s fold for ``n = m = 2`` (the system's case) as runs: the restarts
    and tampings at each row's position, vectorised over the rows (:meth:`Banks.restart`,
    :meth:`Banks.tamping`), then each row's indices up to its next other event, a row at
    a time (:func:`kernel.index_runs`), until every log is folded. The rows are independent,
    so the order across rows does not change a bit (:func:`_fold_steps` gives the same).
    ``homes``: index_runs' (indices only)."""
    if observations:
        Hs, bs, Rs = (np.stack([getattr(o, name) for o in observations]) for name in "HbR")
    else:  # no model: an index on a started row is then an error (reported below)
        Hs, bs, Rs = np.zeros((1, 2, 2)), np.zeros((1, 2)), np.zeros((1, 2, 2))
    pos = np.zeros(len(lengths), dtype=np.int64)  # each row's next event
    stop = lengths.astype(np.int64)  # a halted row's stops after the halting index
    missing = np.zeros(len(lengths), dtype=bool)
    while True:
        moved = True
        while moved:  # the restarts and tampings at the rows' positions
            live = np.flatnonzero(pos < stop)
            kind = kinds[live, pos[live]]
            moved = False
            for code in (RESTART, TAMPING, PARTIAL_INDEX):
                rows = live[kind == code]
                if len(rows):
                    at = pos[rows]
                    if code == RESTART:
                        banks.restart(rows, times[rows, at], values[rows, at], params)
                    elif code == TAMPING:
                        banks.tamping(rows, times[rows, at], params)
                    else:
                        _partial_indices(banks, rows, pos, stop, times, values, obs_ids,
                                         observations, params, folded, halt)  # fmt: skip
                    pos[rows] += 1
                    moved = True
        rows = np.flatnonzero(pos < stop)  # each at an index
        if len(rows) == 0:
            return
        index_runs(
            rows, banks.F, banks.t_s, pos, stop, kinds, times, values, obs_ids, Hs, bs, Rs,
            params.stack.mu, params.stack.sigma, params.row_group, banks.started, banks.nis,
            banks.n_updates, banks.cusum, banks.cusum_t0, banks.cusum_t1,
            (INDEX, CUSUM_DRIFT, CUSUM_CLIP, math.inf if halt is None else float(halt)),
            folded, missing, homes,
        )  # fmt: skip
        if missing.any():
            raise AssertionError("an index on a started state without an observation model")


def _partial_indices(banks, rows, pos, stop, times, values, obs_ids, observations, params,
                     folded, halt) -> None:  # fmt: skip
    """:func:`_fold_runs`' step of the indices of some indices at ``rows``' positions
    (:func:`banks.index_partial`); an index before any start is skipped, and a row whose
    CUSUM reaches ``halt`` stops after it, as in the compiled runs."""
    rows = rows[banks.started[rows]]
    at = pos[rows]
    ids = obs_ids[rows, at]
    if (ids < 0).any():
        raise AssertionError("an index on a started state without an observation model")
    for j in np.unique(ids):
        sub, k = rows[ids == j], at[ids == j]
        index_partial(banks, sub, times[sub, k], values[sub, k], params, observations[j])
        if halt is not None:
            halted = sub[banks.cusum[sub] >= halt]
            stop[halted] = folded[halted] = pos[halted] + 1


def apply_event(
    state: Filtered | None, event: Event, params: DegradationParams, obs: ObservationModel | None
) -> Filtered | None:
    r"""One step of the fold (paper Eq. 2, 7-12), vectorised over the ``Ns`` samples.

    An index also adds each sample's log-likelihood of it to the log weights,

    .. math::

        \log w_j \mathrel{+}= \log \mathcal N(\nu_j; 0, S_j), \qquad
        \nu_j = y - H \hat z^j_{k|k-1} - b, \quad S_j = H P^j_{k|k-1} H^T + R,

    which a TRC restart resets to 0 (equal weights).

    Returns None while nothing has started the state (an index before any start).
    ``obs`` must not be None for an index on a started state (the caller checks it).
    :func:`fold_many` with one segment and one event, so it gives the re-run's bits.
    """
    return fold_many([state], [(event,)], [params], obs)[0]
