"""A segment's log as columns (:class:`~services.filtering.events.LogColumns`) built from
its stored rows, extended with newer events, and packed as the store's ``log_columns``
cache holds it."""

from __future__ import annotations

import math
import operator
import struct
from collections.abc import Iterable, Sequence

import msgspec
import numpy as np

from schemas import SCHEMA_VERSION, encode
from services.filtering.events import (
    INDEX,
    RESTART,
    Event,
    LogColumns,
    is_full_restart,
    outlives_restart,
)


class _FoldedIndex(msgspec.Struct, frozen=True, kw_only=True, gc=False):
    """What the fold reads of a stored OnboardIndex (its other fields are skipped)."""

    v: int = SCHEMA_VERSION
    train: str
    unit: str
    t: float
    top6_mm: float
    align10_mm: float


_STORED_INDICES = msgspec.msgpack.Decoder(list[_FoldedIndex])
_TOP6, _ALIGN10 = operator.attrgetter("top6_mm"), operator.attrgetter("align10_mm")
_TIME, _VERSION, _UNIT = (
    operator.attrgetter("t"),
    operator.attrgetter("v"),
    operator.attrgetter("train", "unit"),
)
_ARRAY32 = struct.Struct(">BI")  # a MessagePack array header: 0xdd, then the count


def log_columns(
    index_payloads: Sequence[bytes], others: Iterable[Event]
) -> tuple[LogColumns, float | None] | None:
    """``(log, trc_t)`` of :func:`canonical_log`, as :class:`LogColumns`, from a segment's
    stored index payloads and its other events (TRC records, tampings); None when an index
    does not pass :func:`stored_events`' checks (that path then skips it with a warning)
    or two events tie on (time, kind) (their canonical order then compares identities).

    The payloads are decoded in one call, as one MessagePack array of them, and the
    columns built without an Event per index: the same times and values (``math.log``, as
    :func:`~services.filtering.events.index_event`), so the fold gives the same bits.
    """
    try:
        msgs = _STORED_INDICES.decode(
            _ARRAY32.pack(0xDD, len(index_payloads)) + b"".join(index_payloads)
        )
    except (msgspec.DecodeError, msgspec.ValidationError):
        return None
    tops, aligns = list(map(_TOP6, msgs)), list(map(_ALIGN10, msgs))
    indices = np.array((tops, aligns))
    if set(map(_VERSION, msgs)) - {SCHEMA_VERSION} or not (
        (indices > 0.0).all() and (indices < math.inf).all()  # NaN fails both
    ):
        return None
    others = list(others)
    restarts = [e.t_s for e in others if is_full_restart(e)]
    trc_t = max(restarts) if restarts else None
    times = np.array(list(map(_TIME, msgs)), dtype=np.float64)
    if trc_t is not None:  # canonical_log keeps the events at or after the latest TRC record
        others = [e for e in others if e.t_s >= trc_t or outlives_restart(e)]
        kept = times >= trc_t
        if not kept.all():
            msgs, tops, aligns = (
                [x for x, keep in zip(column, kept.tolist(), strict=True) if keep]
                for column in (msgs, tops, aligns)
            )
            times = times[kept]
    n_index = len(msgs)
    units = list(map(_UNIT, msgs))
    names = {name: code for code, name in enumerate(dict.fromkeys(units))}
    codes = list(map(names.__getitem__, units))
    kinds = np.full(n_index + len(others), INDEX, dtype=np.int8)
    kinds[n_index:] = [e.kind for e in others]
    all_times = np.concatenate([times, [e.t_s for e in others]])
    values = np.zeros((len(kinds), 2))  # (Top6, Align10)
    values[:n_index, 0] = list(map(math.log, tops))
    values[:n_index, 1] = list(map(math.log, aligns))
    for k, e in enumerate(others, start=n_index):
        if e.value is not None:
            values[k] = e.value
    unit_codes = np.full(len(kinds), -1, dtype=np.int32)
    unit_codes[:n_index] = codes
    order = np.lexsort((kinds, all_times))  # by time, then kind
    kinds, all_times = kinds[order], all_times[order]
    if len(order) > 1 and ((all_times[1:] == all_times[:-1]) & (kinds[1:] == kinds[:-1])).any():
        return None
    last_order = None
    if len(order):
        last = int(order[-1])
        if last < n_index:
            m = msgs[last]
            last_order = (m.t, INDEX, ("index", m.train, m.unit, m.t))
        else:
            last_order = others[last - n_index].order
    columns = LogColumns(
        kinds, all_times, values[order], unit_codes[order], tuple(names), last_order
    )
    return columns, trc_t


class _ColumnsRow(msgspec.Struct, array_like=True, frozen=True, gc=False):
    """A :class:`LogColumns` and its ``trc_t`` as stored in ``log_columns``: the arrays as
    their exact little-endian bytes; ``layout`` names this layout (another is not read)."""

    layout: int
    trc_t: float | None
    last_order: tuple[float, int, tuple] | None
    unit_names: tuple[tuple[str, str], ...]
    kinds: bytes  # int8
    times: bytes  # <f8
    values: bytes  # <f8 (L, 2)
    unit_codes: bytes  # <i4


_COLUMNS_LAYOUT = 1
_COLUMNS_ROW = msgspec.msgpack.Decoder(_ColumnsRow)


def pack_columns(columns: LogColumns, trc_t: float | None) -> bytes:
    """A segment's log columns as the bytes the ``log_columns`` cache holds."""
    return encode(
        _ColumnsRow(
            _COLUMNS_LAYOUT,
            trc_t,
            columns.last_order,
            columns.unit_names,
            columns.kinds.astype(np.int8).tobytes(),
            columns.times.astype("<f8").tobytes(),
            columns.values.astype("<f8").tobytes(),
            columns.unit_codes.astype("<i4").tobytes(),
        )
    )


def unpack_columns(blob: bytes) -> tuple[LogColumns, float | None] | None:
    """:func:`pack_columns` back (read-only arrays over the bytes); None if the bytes are
    not one of this layout (the log is then read from its events)."""
    try:
        row = _COLUMNS_ROW.decode(blob)
        kinds = np.frombuffer(row.kinds, dtype=np.int8)
        times = np.frombuffer(row.times, dtype="<f8")
        values = np.frombuffer(row.values, dtype="<f8").reshape(-1, 2)
        codes = np.frombuffer(row.unit_codes, dtype="<i4")
    except (msgspec.DecodeError, msgspec.ValidationError, ValueError):
        return None
    if row.layout != _COLUMNS_LAYOUT or not (
        len(kinds) == len(times) == len(values) == len(codes)
        and (row.last_order is None) == (len(kinds) == 0)
        and (codes < len(row.unit_names)).all()
    ):
        return None
    last = row.last_order
    order = None if last is None else (last[0], last[1], tuple(last[2]))
    return LogColumns(kinds, times, values, codes, row.unit_names, order), row.trc_t


def columns_after(columns: LogColumns, tail: Sequence[Event]) -> LogColumns | None:
    """``columns`` with the segment's newer events ``tail`` (any order) appended: the
    columns :func:`log_columns` gives for the whole log, when every event of the tail is an
    index or a tamping that sorts after the log's last event (time, then kind; no two tied).
    None otherwise (a TRC record, which starts the log again, or a late event: the log is
    then read from its events)."""
    if not tail:
        return columns
    tail = sorted(tail, key=lambda e: e.order)
    keys = [(e.t_s, e.kind) for e in tail]
    if columns.last_order is not None:
        keys.insert(0, columns.last_order[:2])
    if any(e.kind == RESTART for e in tail) or any(map(operator.ge, keys, keys[1:])):
        return None
    names = {name: code for code, name in enumerate(columns.unit_names)}
    values = np.zeros((len(tail), 2))  # a tamping's: zeros
    unit_codes = np.full(len(tail), -1, dtype=np.int32)
    for k, e in enumerate(tail):
        if e.kind == INDEX:
            values[k] = e.value
            unit_codes[k] = names.setdefault((e.message.train, e.message.unit), len(names))
    return LogColumns(
        np.concatenate([columns.kinds, np.array([e.kind for e in tail], dtype=np.int8)]),
        np.concatenate([columns.times, [e.t_s for e in tail]]),
        np.concatenate([columns.values, values]),
        np.concatenate([columns.unit_codes, unit_codes]),
        tuple(names),
        tail[-1].order,
    )
