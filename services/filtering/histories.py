"""Segment histories: a segment's log and state (:class:`SegmentHistory`), its state
without the log (:class:`Checkpoint`), and every segment's, its log loaded lazily
(:class:`Histories`)."""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable, Iterable, Iterator, MutableMapping, Sequence
from dataclasses import dataclass
from typing import Any, TypeVar

from schemas.keys import SegmentId
from services.filtering.banks import BankRow, Banks, RestingBank, as_filtered
from services.filtering.events import Event, Log, LogColumns, is_full_restart, log_units
from services.filtering.state import Filtered


@dataclass(frozen=True)
class SegmentHistory:
    """One segment's history: its event log (canonical order), the filter state folded from
    it, the posterior group it used."""

    line: str
    segment: str
    log: Log = ()  # columns only inside a re-run of a resting segment (Histories.load_columns)
    trc_t: float | None = None  # epoch s of the latest TRC record: the log's lower bound
    state: Filtered | None = None
    group: str | None = None  # posterior group of ``state``


@dataclass(frozen=True)
class Checkpoint:
    """A segment's fold without its log: what a checkpoint stores and a restart restores.

    ``last_order`` is the canonical order key of the log's last event (None: empty log);
    an event stored later with a smaller key is a late one, and the segment must then be
    replayed from its log's start. ``models_key`` (:func:`models_key`) names the model
    versions ``state`` was folded with.
    """

    line: str
    segment: str
    trc_t: float | None
    state: Filtered | None
    group: str | None
    last_order: tuple[float, int, tuple[Any, ...]] | None
    models_key: str = ""
    # the (train, unit) of every index in the log ``state`` folds (or more); None: unknown
    units: frozenset[tuple[str, str]] | None = None


def checkpoint_of(hist: SegmentHistory) -> Checkpoint:
    """``hist`` without its log: its state, where its log ends and whose indices it read."""
    if isinstance(hist.log, LogColumns):
        last_order = hist.log.last_order
    else:
        last_order = hist.log[-1].order if hist.log else None
    return Checkpoint(
        hist.line,
        hist.segment,
        hist.trc_t,
        hist.state,
        hist.group,
        last_order,
        units=log_units(hist.log),
    )


LogLoader = Callable[[str, str], tuple[tuple[Event, ...], float | None]]
ColumnLoader = Callable[[str, str], tuple[LogColumns, float | None] | None]


class Histories(MutableMapping[SegmentId, SegmentHistory]):
    """The segment histories by ``(line, segment)``: a dict whose logs load lazily.

    A segment is either *loaded* (a :class:`SegmentHistory` with its log) or *resting*
    (a :class:`Checkpoint`: its state without the log, e.g. restored from a checkpoint or
    evicted by :meth:`trim`). Reading a resting segment (``[sid]``, ``get``) asks
    ``loader(line, segment) -> (log, trc_t)`` for its log in canonical order (the store
    supplies it; the core does no I/O) and keeps it loaded. Iteration and ``len`` cover
    every known segment; ``items()``/``values()`` load every log, so the core iterates the
    keys and uses :meth:`resting` where the state alone is enough. Every assignment marks
    the segment ``dirty`` (its checkpoint is out of date) until the owner clears it.
    ``columns(line, segment) -> (LogColumns, trc_t) | None``, when given, reads a resting
    log as columns for a re-run (:meth:`load_columns`; None: read it as events).

    A resting segment's state is a row of the bank of its sample count
    (:class:`RestingBank`), not a :class:`Filtered` of its own: :meth:`resting` reads it
    out (a copy); only the tracker's fold sees the row (:meth:`resting_entry`), folds from
    it into a free row, and hands that back with the segment's new Checkpoint at the swap
    (:meth:`rest` keeps it there and frees the old row; :meth:`settle` frees the rows a
    failed or superseded fold took).
    """

    def __init__(self, loader: LogLoader | None = None) -> None:
        self.loader = loader
        self.columns: ColumnLoader | None = None
        self._loaded: OrderedDict[SegmentId, SegmentHistory] = OrderedDict()
        # a resting segment's Checkpoint, its state (if any) a BankRow of ``_banks``
        self._resting: dict[SegmentId, Checkpoint] = {}
        self._banks: dict[tuple[int, int], RestingBank] = {}  # by (Ns, n)
        self.dirty: set[SegmentId] = set()

    def _release(self, rest: Checkpoint | None) -> None:
        """``rest``'s row (if it has one) back to its bank, once it no longer rests."""
        if rest is not None and isinstance(rest.state, BankRow):
            self._free(rest.state)

    def _free(self, row: BankRow) -> None:
        self._banks[(row.banks.ns, row.banks.n)].free.append(row.row)

    def bank(self, ns: int, n: int) -> RestingBank:
        """The bank of the resting states of ``(ns, n)``."""
        bank = self._banks.get((ns, n))
        if bank is None:
            self._banks[(ns, n)] = bank = RestingBank(ns, n)
        return bank

    def __getitem__(self, sid: SegmentId) -> SegmentHistory:
        hist = self._loaded.get(sid)
        if hist is not None:
            self._loaded.move_to_end(sid)
            return hist
        hist = self.load(sid)
        self._release(self._resting.pop(sid))
        self._loaded[sid] = hist
        return hist

    def load(self, sid: SegmentId) -> SegmentHistory:
        """The segment's history with its log, without keeping a resting one's log loaded."""
        hist = self._loaded.get(sid)
        if hist is not None:
            return hist
        rest = self._resting[sid]  # KeyError: unknown segment
        if self.loader is None:
            raise LookupError(f"segment {sid}: log not loaded and no loader")
        log, trc_t = self.loader(rest.line, rest.segment)
        return SegmentHistory(
            rest.line, rest.segment, log, trc_t, as_filtered(rest.state), rest.group
        )

    def load_columns(self, sid: SegmentId) -> SegmentHistory:
        """:meth:`load`, with a resting segment's log as :class:`LogColumns` when the
        column loader gives it, and then without its state, which a re-run recomputes from
        the log (a re-run's read, not kept: never assign the result)."""
        rest = self._resting.get(sid)
        if rest is None or self.columns is None:
            return self.load(sid)
        read = self.columns(rest.line, rest.segment)
        if read is None:
            return self.load(sid)
        log, trc_t = read
        return SegmentHistory(rest.line, rest.segment, log, trc_t, None, rest.group)

    def __setitem__(self, sid: SegmentId, hist: SegmentHistory) -> None:
        self._release(self._resting.pop(sid, None))
        self._loaded[sid] = hist
        self._loaded.move_to_end(sid)
        self.dirty.add(sid)

    def __delitem__(self, sid: SegmentId) -> None:
        if self._loaded.pop(sid, None) is None:
            self._release(self._resting.pop(sid))
        self.dirty.discard(sid)

    def __contains__(self, sid: object) -> bool:
        return sid in self._loaded or sid in self._resting

    def __iter__(self) -> Iterator[SegmentId]:
        yield from list(self._loaded)
        yield from list(self._resting)

    def __len__(self) -> int:
        return len(self._loaded) + len(self._resting)

    def rest(self, sid: SegmentId, checkpoint: Checkpoint, *, dirty: bool = False) -> None:
        """Hold ``sid`` as its state alone (its log is then read again when needed): the
        state is copied into the segment's row of the bank (its own row again if it has
        one of that shape), or, a row of the bank already (a backlog's fold), kept there."""
        self._loaded.pop(sid, None)
        old = self._resting.get(sid)
        state = checkpoint.state
        if state is None:
            self._release(old)
        elif isinstance(state, BankRow):
            if old is not None and old.state != state:
                self._release(old)
        else:
            row = self._row_for(old, *state.z.shape)
            row.banks.put(row.row, state)
            checkpoint = evolve(checkpoint, state=row)
        self._resting[sid] = checkpoint
        if dirty:
            self.dirty.add(sid)

    def _row_for(self, old: Checkpoint | None, ns: int, n: int) -> BankRow:
        """The row a resting segment's state of ``(ns, n)`` goes in: its own (``old``'s)
        if of that shape, else a free one."""
        if old is not None and isinstance(old.state, BankRow):
            if (old.state.banks.ns, old.state.banks.n) == (ns, n):
                return old.state
            self._release(old)
        bank = self.bank(ns, n)
        return BankRow(bank.banks, bank.take(1)[0])

    def settle(self, taken: Iterable[tuple[SegmentId, BankRow]]) -> None:
        """Free each row of ``taken`` (``(segment, row)``: rows a fold took for segments)
        that its segment does not rest in (after the swap, or after a failed batch)."""
        for sid, row in taken:
            rest = self._resting.get(sid)
            if rest is None or rest.state != row:
                self._free(row)

    def resting(self, sid: SegmentId) -> Checkpoint:
        """The segment's state without loading its log (``models_key`` left empty)."""
        rest = self._resting.get(sid)
        if rest is not None:
            if isinstance(rest.state, BankRow):
                return evolve(rest, state=rest.state.state())
            return rest
        return checkpoint_of(self._loaded[sid])

    def resting_many(self, sids: Sequence[SegmentId]) -> list[Checkpoint]:
        """:meth:`resting` of each of ``sids``, the states read out of each bank in one
        pass (:meth:`Banks.states`)."""
        out = [self.resting_entry(sid) for sid in sids]
        blocks: dict[int, tuple[Banks, list[int]]] = {}
        for k, rest in enumerate(out):
            if isinstance(rest.state, BankRow):
                blocks.setdefault(id(rest.state.banks), (rest.state.banks, []))[1].append(k)
        for banks, ks in blocks.values():
            states = banks.states([out[k].state.row for k in ks], copy=True)
            for k, state in zip(ks, states, strict=True):
                out[k] = evolve(out[k], state=state)
        return out

    def resting_entry(self, sid: SegmentId) -> Checkpoint:
        """:meth:`resting`, a resting segment's state left as its :class:`BankRow` (what
        the fold folds from; never kept, nor given out)."""
        rest = self._resting.get(sid)
        return rest if rest is not None else checkpoint_of(self._loaded[sid])

    def units(self, sid: SegmentId) -> frozenset[tuple[str, str]]:
        """The ``(train, unit)`` whose indices the segment's log holds (or a superset),
        reading the log only when a resting segment does not know them."""
        hist = self._loaded.get(sid)
        if hist is not None:
            return log_units(hist.log)
        units = self._resting[sid].units
        return log_units(self.load(sid).log) if units is None else units

    def is_loaded(self, sid: SegmentId) -> bool:
        return sid in self._loaded

    @property
    def n_loaded(self) -> int:
        return len(self._loaded)

    def trim(self, max_loaded: int) -> int:
        """Drop the logs of the least recently used segments beyond ``max_loaded`` (their
        states stay); only call it when the loader returns those logs (stored); returns
        how many were dropped."""
        dropped = 0
        while len(self._loaded) > max_loaded:
            sid = next(iter(self._loaded))
            self.rest(sid, checkpoint_of(self._loaded[sid]))
            dropped += 1
        return dropped


def rested(ckpt: Checkpoint, state, group, tail: Sequence[Event]) -> Checkpoint:
    """``ckpt`` folded on over ``tail`` (in canonical order, after its last event)."""
    trc_t = ckpt.trc_t
    for event in tail:
        if is_full_restart(event) and (trc_t is None or event.t_s > trc_t):
            trc_t = event.t_s
    units = ckpt.units
    if units is not None:  # a superset is safe
        read = log_units(tail)
        if not read <= units:
            units = units | read
    changes = {"trc_t": trc_t, "state": state, "group": group, "units": units}
    changes["last_order"] = tail[-1].order
    return replaced(ckpt, changes)  # a backlog's per segment: evolve without its check


def summarised(hist: SegmentHistory | Checkpoint) -> SegmentHistory:
    """What a summary reads of a segment (its log is not): a resting one without its log."""
    if isinstance(hist, SegmentHistory):
        return hist
    state = as_filtered(hist.state)
    return SegmentHistory(hist.line, hist.segment, (), hist.trc_t, state, hist.group)


_Frozen = TypeVar("_Frozen", "SegmentHistory", "Checkpoint")


def evolve(hist: _Frozen, **changes: Any) -> _Frozen:
    """``dataclasses.replace(hist, **changes)`` of a SegmentHistory or a Checkpoint, without
    its per-call field introspection (a backlog makes one per segment and batch): every
    field, whatever they are, copied, then changed."""
    cls = type(hist)
    if not changes.keys() <= cls.__dataclass_fields__.keys():
        raise TypeError(f"{cls.__name__} has no field {set(changes) - set(vars(hist))}")
    return replaced(hist, changes)


def replaced(hist: _Frozen, changes: dict[str, Any]) -> _Frozen:
    """:func:`evolve` without the check that ``changes`` names fields of ``hist``."""
    new = object.__new__(type(hist))
    new.__dict__.update(hist.__dict__)
    new.__dict__.update(changes)
    return new
