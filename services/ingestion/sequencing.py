"""Sequencing of one (train, unit)'s chunks. Pure.

**Sequencing** per (train, unit) (:func:`step_unit`): ``t0`` must agree with ``seq``
(``t0 ≈ t0_ref + (seq - seq_ref) * chunk duration`` within ``t0_tolerance_s``);
duplicates (same seq) are dropped and counted, not dead-lettered (re-delivery is normal
and harmless; the first copy wins); chunks are reordered within a window of
``reorder_chunks`` chunks or ``reorder_s`` of event time; when the window passes a missing
seq, the next chunk carries ``gap_before``. A chunk arriving after its slot was declared
missing is rejected as ``late``. A seq that jumps backwards while ``t0`` moves forwards
is a restarted gateway counter: the unit starts over with ``gap_before``.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field

from services.ingestion.config import IngestionConfig
from services.ingestion.health import Inspected, UnitHealth, account


@dataclass
class UnitState:
    """Reorder buffer and sequence bookkeeping of one (train, unit)."""

    health: UnitHealth = field(default_factory=UnitHealth)
    next_seq: int | None = None  # next seq to release; None before the first release
    last_t0: float = 0.0  # of the last released chunk
    last_duration: float = 0.0
    ref: tuple[int, float, float] | None = None  # (seq, t0, duration) of the highest seq
    buffer: dict[int, Inspected] = field(default_factory=dict)
    gap_pending: bool = False
    lost: deque[int] = field(default_factory=lambda: deque(maxlen=256))  # declared missing


def step_unit(
    state: UnitState, item: Inspected, cfg: IngestionConfig
) -> tuple[UnitState, list[tuple[Inspected, bool]], str | None]:
    """Sequence one inspected chunk: ``(state, released [(chunk, gap_before)], rejection)``."""
    chunk = item.raw
    seq, h = chunk.seq, state.health
    released: list[tuple[Inspected, bool]] = []
    if state.ref is not None:
        ref_seq, ref_t0, ref_dur = state.ref
        expected = ref_t0 + (seq - ref_seq) * ref_dur
        if abs(chunk.t0 - expected) > cfg.t0_tolerance_s:
            if seq < ref_seq and chunk.t0 > ref_t0 + ref_dur - cfg.t0_tolerance_s:
                # the gateway's counter restarted: finish the old run, start a new one
                released += release_unit(state, cfg, force=True)
                state.next_seq, state.ref, state.gap_pending = seq, None, True
                state.lost.clear()
                h.restarts += 1
            else:
                h.rejected += 1
                return (
                    state,
                    released,
                    f"t0: {chunk.t0:.3f} inconsistent with seq {seq} "
                    f"(expected {expected:.3f} ± {cfg.t0_tolerance_s:g} s from seq {ref_seq})",
                )
    if seq in state.buffer or (
        state.next_seq is not None and seq < state.next_seq and seq not in state.lost
    ):
        h.duplicates += 1
        return state, released, None
    if state.next_seq is not None and seq < state.next_seq:
        h.late += 1
        h.rejected += 1
        return state, released, f"late: seq {seq} arrived after its gap was reported"
    state.buffer[seq] = item
    if state.ref is None or seq > state.ref[0]:
        state.ref = (seq, chunk.t0, item.duration_s)
    account(h, item)
    released += release_unit(state, cfg)
    return state, released, None


def release_unit(
    state: UnitState, cfg: IngestionConfig, *, now: float | None = None, force: bool = False
) -> list[tuple[Inspected, bool]]:
    """Release what the reorder window allows (everything with ``force``)."""
    out: list[tuple[Inspected, bool]] = []
    buffer = state.buffer
    while buffer:
        nxt = state.next_seq
        if nxt is None and 0 in buffer:
            nxt = state.next_seq = 0  # a counter starts at 0: nothing can come before it
        if nxt is not None and nxt in buffer:
            item = buffer.pop(nxt)
            out.append((item, state.gap_pending))
            state.gap_pending = False
            state.next_seq = nxt + 1
            state.last_t0, state.last_duration = item.raw.t0, item.duration_s
            continue
        oldest = min(buffer)
        newest_t0 = max(state.ref[1] if state.ref else -math.inf, now or -math.inf)
        waiting_since = (
            buffer[oldest].raw.t0 if nxt is None else state.last_t0 + state.last_duration
        )
        window_passed = (
            len(buffer) >= cfg.reorder_chunks or newest_t0 - waiting_since >= cfg.reorder_s
        )
        if not (force or window_passed):
            break
        if nxt is not None:
            state.lost.extend(range(nxt, oldest))
            state.health.missing += oldest - nxt
            state.gap_pending = True
        state.next_seq = oldest
    return out
