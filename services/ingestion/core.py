"""Ingestion core: RawChunk + GpsFix in, PositionedChunk + rejections out. Pure.

No Zenoh, no clock, no I/O: time is the data's event time, bounded by the receiving
machine's clock that the adapter passes in. The adapter (``services/ingestion/service.py``)
feeds one ordered stream of decoded messages through :meth:`IngestionCore.step` and
publishes what comes out; tests do the same with lists.

The chain, per message:

1. **Validation** beyond the schema, **health and correction** (:mod:`.health`,
   :func:`~services.ingestion.health.inspect_chunk`): a failure is a :class:`Rejection` with
   a reason.

   **The train's clock.** Event time is the gateway's, so one wrong time must not become
   "now", and what senders say must not define the future: the receiving machine's clock
   does. The adapter passes its clock at each message (``received_t``, epoch s); the core
   keeps none. A fix's ``t`` and a chunk's ``t0`` outside ``[valid_t_min, valid_t_max)``
   (2000..2100) are refused, and so is one more than ``future_s`` (60 s) ahead of
   ``received_t``, always (no re-base). A fix or chunk more than ``max_ahead_s`` (300 s)
   ahead of the train's last accepted fix is refused as a clock jump unless it is within
   ``max_ahead_s`` of ``received_t`` (a live train back from an outage or a depot night;
   without ``received_t``, as when recorded data is replayed, it is refused), as is a fix
   more than ``max_ahead_s`` behind the train's last fix: neither moves the train's event
   time, its reorder windows or its knot horizon. Other trains' times never enter: a burst
   of old-dated messages from many trains changes nothing for a live one. A train whose
   gateway clock really moved is **re-based**: ``rebase_fixes`` (5) consecutive refused
   fixes, each 0 < Δt <= ``rebase_gap_s`` (10 s) after the one before, make the last of
   them the train's new timeline (what is held is released first; the units' sequencing
   starts over with ``gap_before``; a warning is logged; :attr:`TrainStats.rebases`). One
   fix on the train's timeline ends a run of refused fixes, so a single outlier, or
   outliers among good fixes, never re-base anything.
2. **Sequencing** per (train, unit) (:mod:`.sequencing`): reorder, duplicates, gaps.
3. **Positioning** per train (:func:`step_train`): every fix with ``fix_quality > 0`` is
   projected onto the network lines and becomes a knot ``(t, line, chainage, speed, ok)``;
   fixes without a position (tunnels) become dead-reckoned knots (last speed, direction of
   travel), trusted for ``dead_reckon_s`` after the last good fix. A chunk goes out as soon
   as its samples can be positioned: between knots by interpolation and, past the last
   knot, by dead reckoning from it (its speed and the acceleration between the last two
   knots, stopping at 0) when its last sample is at most ``extrapolate_s`` (2 s) past that
   knot and the train's direction is known (or it stands still). GPS is 1 Hz and a gateway
   sends a ~1 s chunk at its end, so the fix after a chunk's last sample is usually not
   there yet; waiting for it would cost about a second per chunk, longer through outages. A
   chunk farther from the last knot (an outage without heartbeat fixes, a train starting
   off) is held until a knot at or after its last sample exists (at most ``max_hold_s`` of
   the train's event time), as with ``extrapolate_s = 0`` every chunk is.

   The knots a chunk goes out with are the **published trajectory** (:mod:`.trajectory`):
   what went out is never revised. Fixes become knots by **map matching** (:mod:`.matching`).

``position_ok`` is False when a bracketing knot is missing, any knot of the chunk is poor
(no fix and dead reckoning longer than ``dead_reckon_s`` after the last good fix, or past
the last knot longer than ``extrapolate_s``; hdop above ``hdop_max``; lateral offset above
``lateral_ok_m``; off the line while a switch is pending; within ``correction_s`` after a
correction larger than ``correction_ok_m``), knots are more than ``dead_reckon_s`` apart, or
the chunk straddles a line change (rare: the chunk then keeps only the knots on the new
line). :class:`TrainStats` counts the chunks ``extrapolated`` (a dead-reckoned tail) and
``held`` (waited for a knot) and the largest correction.

A chunk of a train that has never been matched to any line cannot be positioned: after
``max_hold_s`` it is rejected with reason ``unpositioned`` (a dead letter, so it is counted
and visible, never silently lost).
"""

from __future__ import annotations

import logging
from bisect import bisect_left, bisect_right
from collections.abc import Iterable
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from schemas import GpsFix, NDArray, PositionedChunk, RawChunk
from services.ingestion.config import IngestionConfig
from services.ingestion.health import (
    Inspected,
    UnitHealth,
    inspect_chunk,
    time_range_reason,
)
from services.ingestion.matching import Positioner
from services.ingestion.sequencing import UnitState, release_unit, step_unit
from services.ingestion.train import TrainState, TrainStats
from services.ingestion.trajectory import can_extrapolate, publish_trajectory

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Rejection:
    """A message the core refuses; the adapter publishes it as a dead letter."""

    reason: str
    message: RawChunk | GpsFix


Output = PositionedChunk | Rejection


def step_train(
    st: TrainState,
    event: GpsFix | tuple[Inspected, bool] | None,
    pos: Positioner,
    *,
    final: bool = False,
) -> tuple[TrainState, list[Output]]:
    """One fix or one released chunk for a train; ``(state, outputs)``.

    ``event`` None with ``final`` releases every held chunk (end of the stream).
    """
    out: list[Output] = []
    cfg = pos.cfg
    if isinstance(event, GpsFix):
        fix = event
        if st.last_fix_t is not None and fix.t <= st.last_fix_t:
            if fix.t == st.last_fix_t:
                st.stats.duplicates += 1
                return st, out
            return st, [
                Rejection(f"GpsFix: t {fix.t:.3f} before the previous fix {st.last_fix_t:.3f}", fix)
            ]
        st.last_fix_t = fix.t
        st.now = max(st.now, fix.t)
        st.stats.fixes += 1
        knot = pos.knot(st, fix)
        if knot is not None:
            st.knots.append(knot)
            st.knot_t.append(knot.t)
            if knot.ok:
                st.stats.matched += 1
            else:
                st.stats.poor += 1
    elif event is not None:
        item = event[0]
        st.now = max(st.now, item.t_last)
        st.pending.append(event)
    keep: list[tuple[Inspected, bool]] = []
    for entry in st.pending:
        item, gap = entry
        if st.pub_t and st.pub_t[-1] >= item.t_last:
            pass  # published already (for another unit of the train)
        elif st.knot_t and st.knot_t[-1] >= item.t_last:
            publish_trajectory(st, pos, item.t_last)
        elif can_extrapolate(st, pos, item.t_last):
            publish_trajectory(st, pos, item.t_last, extrapolate=True)
            st.stats.extrapolated += 1
        elif final or st.now - item.t_last > cfg.max_hold_s:
            publish_trajectory(st, pos, item.t_last)  # as far as the knots go: not bracketed
        else:
            keep.append(entry)
            continue
        out.append(_positioned(st, item, gap, cfg))
    if event is not None and not isinstance(event, GpsFix) and keep and keep[-1] is event:
        st.stats.held += 1
    st.pending = keep
    horizon = st.now - cfg.knot_keep_s
    drop = bisect_left(st.knot_t, horizon) - 1  # keep one knot before the horizon
    if drop > 0:
        del st.knots[:drop], st.knot_t[:drop]
    drop = bisect_left(st.pub_t, horizon) - 1
    if drop > 0:
        del st.pub[:drop], st.pub_t[:drop]
    return st, out


def _positioned(st: TrainState, item: Inspected, gap_before: bool, cfg: IngestionConfig) -> Output:
    raw = item.raw
    if not st.pub:
        st.stats.unpositioned += 1
        return Rejection(
            f"unpositioned: no map-matched GPS position of train {raw.train} around "
            f"t0 {raw.t0:.3f}",
            raw,
        )
    kt = st.pub_t
    i0 = bisect_right(kt, raw.t0) - 1
    i1 = bisect_left(kt, item.t_last)
    bracketed = i0 >= 0 and i1 < len(kt)
    knots = st.pub[max(i0, 0) : min(i1, len(kt) - 1) + 1]
    line = knots[-1].line
    single_line = all(k.line == line for k in knots)
    if not single_line:
        knots = [k for k in knots if k.line == line]
    t = np.array([k.t for k in knots])
    gaps_ok = len(t) < 2 or float(np.diff(t).max()) <= cfg.dead_reckon_s
    ok = bracketed and single_line and gaps_ok and all(k.ok for k in knots)
    return PositionedChunk(
        train=raw.train,
        unit=raw.unit,
        seq=raw.seq,
        t0=raw.t0,
        rate_hz=raw.rate_hz,
        channels=item.channels,
        samples=NDArray(dtype="f4", shape=list(item.samples.shape), data=item.samples.tobytes()),
        line=line,
        knot_t=NDArray.of(t),
        knot_chainage_m=NDArray.of([k.chainage_m for k in knots]),
        knot_speed_mps=NDArray.of([k.speed_mps for k in knots]),
        position_ok=ok,
        gap_before=gap_before,
        sensor_flags=list(item.flags),
    )


# --- the whole core --------------------------------------------------------------------------


class IngestionCore:
    """Per-unit sequencing and health, per-train positioning; one ordered event stream.

    Parameters
    ----------
    network : simulators.network.Network (or alike)
        Lines with ``id``, ``xy``, ``chainage_m``, ``length_m`` and ``to_xy(lonlat)``.
    config : IngestionConfig
    """

    def __init__(self, network: Any, config: IngestionConfig | None = None) -> None:
        self.cfg = config or IngestionConfig()
        self.positioner = Positioner(network, self.cfg)
        self.units: dict[tuple[str, str], UnitState] = {}
        self.trains: dict[str, TrainState] = {}

    def step(self, event: RawChunk | GpsFix, received_t: float | None = None) -> list[Output]:
        """One decoded message in arrival order; what it releases comes out.

        ``received_t``: the receiving machine's clock (epoch s) when the message arrived,
        the bound on future times (module docstring); None: no bound (recorded data)."""
        match event:
            case RawChunk():
                return self._on_chunk(event, received_t)
            case GpsFix():
                return self._on_fix(event, received_t)
        raise TypeError(f"ingestion takes RawChunk or GpsFix, not {type(event).__name__}")

    def run(
        self,
        events: Iterable[RawChunk | GpsFix],
        *,
        flush: bool = True,
        received_t: float | None = None,
    ) -> list[Output]:
        """Every event through :meth:`step` (then :meth:`flush`): lists in, lists out."""
        out: list[Output] = []
        for event in events:
            out += self.step(event, received_t)
        if flush:
            out += self.flush()
        return out

    def flush(self) -> list[Output]:
        """End of the stream: release every buffered and held chunk (gaps flagged)."""
        out: list[Output] = []
        for st in self.trains.values():
            for unit in st.units:
                for released in release_unit(unit, self.cfg, force=True):
                    out += self._to_train(st, released)
            out += self._count(step_train(st, None, self.positioner, final=True)[1])
        return out

    def health(self, train: str, unit: str) -> UnitHealth:
        """A copy of the counters of one unit (zeros for a unit never seen)."""
        h = self.units.get((train, unit))
        if h is None:
            return UnitHealth()
        h = h.health
        return replace(
            h, flatline_chunks=dict(h.flatline_chunks), dropout_chunks=dict(h.dropout_chunks)
        )

    def train_stats(self, train: str) -> TrainStats:
        st = self.trains.get(train)
        return replace(st.stats) if st else TrainStats()

    # --- internals ----------------------------------------------------------------------

    def _train(self, train: str) -> TrainState:
        st = self.trains.get(train)
        if st is None:
            st = self.trains[train] = TrainState()
        return st

    def _ahead(self, st: TrainState, name: str, t: float, received_t: float | None):
        """``(reason, future)``: why ``t`` is too far ahead (None: it is not), and whether it
        is ahead of the receiving machine's clock (never re-bases)."""
        cfg, last = self.cfg, st.last_fix_t
        if received_t is not None and t - received_t > cfg.future_s:
            return (
                f"{name}: {t:.3f} is {t - received_t:.0f} s ahead of the receiving clock "
                f"{received_t:.3f} (more than {cfg.future_s:g} s): refused as a clock jump"
            ), True
        if last is None or t - last <= cfg.max_ahead_s:
            return None, False
        if received_t is not None and received_t - t <= cfg.max_ahead_s:
            return None, False  # live again after an outage or a depot night
        return (
            f"{name}: {t:.3f} is {t - last:.0f} s ahead of the train's last fix {last:.3f} "
            f"(more than {cfg.max_ahead_s:g} s): refused as a clock jump"
        ), False

    def _clock_check(self, fix: GpsFix, st: TrainState, received_t: float | None):
        """``(reason, rebase)``: why a fix is off the train's timeline (None: on it) and
        whether the train re-bases to it now (the rule in the module docstring)."""
        cfg, last, t = self.cfg, st.last_fix_t, fix.t
        reason, future = self._ahead(st, "t", t, received_t)
        if future:
            return reason, False
        if reason is None and last is not None and last - t > cfg.max_ahead_s:
            reason = (
                f"t: {t:.3f} is {last - t:.0f} s behind the train's last fix {last:.3f} "
                f"(more than {cfg.max_ahead_s:g} s): refused as a clock jump"
            )
        if reason is None:
            st.suspects.clear()
            return None, False
        run = st.suspects
        if run and 0 < t - run[-1] <= cfg.rebase_gap_s:
            run.append(t)
        else:
            run[:] = [t]
        if len(run) >= cfg.rebase_fixes:
            return None, True
        return (
            f"{reason} ({cfg.rebase_fixes - len(run)} more consecutive fixes at the new "
            "time re-base the train there)",
            False,
        )

    def _rebase(self, st: TrainState, fix: GpsFix) -> list[Output]:
        """Start the train's timeline over at ``fix``: what is held goes out first."""
        out: list[Output] = []
        for unit in st.units:
            for released in release_unit(unit, self.cfg, force=True):
                out += self._to_train(st, released)
        out += self._count(step_train(st, None, self.positioner, final=True)[1])
        log.warning(
            "train %s: clock re-based from %s to %s (%d consecutive fixes at the new time)",
            fix.train,
            "none" if st.last_fix_t is None else f"{st.last_fix_t:.3f}",
            f"{fix.t:.3f}",
            len(st.suspects),
        )
        for unit in st.units:  # sequencing starts over too: t0 against seq at the new time
            unit.next_seq, unit.ref, unit.gap_pending = None, None, True
            unit.lost.clear()
        fresh = TrainState(stats=st.stats, units=st.units)
        fresh.stats.rebases += 1
        self.trains[fix.train] = fresh
        return out

    def _on_chunk(self, chunk: RawChunk, received_t: float | None) -> list[Output]:
        key = (chunk.train, chunk.unit)
        st = self._train(chunk.train)
        unit = self.units.get(key)
        if unit is None:
            unit = self.units[key] = UnitState()
            st.units.append(unit)
        inspected = inspect_chunk(chunk, self.cfg)
        if isinstance(inspected, str):
            unit.health.rejected += 1
            return [Rejection(f"RawChunk: {inspected}", chunk)]
        jump, _ = self._ahead(st, "t0", chunk.t0, received_t)
        if jump is not None:
            unit.health.rejected += 1
            st.stats.clock_jumps += 1
            return [Rejection(f"RawChunk: {jump}", chunk)]
        unit, released, reason = step_unit(unit, inspected, self.cfg)
        out: list[Output] = [] if reason is None else [Rejection(f"RawChunk: {reason}", chunk)]
        if reason is None:
            st.now = max(st.now, inspected.t_last)  # the train's event time moves on
        for r in released:
            out += self._to_train(st, r)
        if not released:  # held chunks of the train may have timed out
            out += self._count(step_train(st, None, self.positioner)[1])
        return out

    def _on_fix(self, fix: GpsFix, received_t: float | None) -> list[Output]:
        st = self._train(fix.train)
        out: list[Output] = []
        bad = time_range_reason("t", fix.t, self.cfg)
        if bad is not None:
            return [Rejection(f"GpsFix: {bad}", fix)]
        reason, rebase = self._clock_check(fix, st, received_t)
        if reason is not None:
            st.stats.clock_jumps += 1
            return [Rejection(f"GpsFix: {reason}", fix)]
        if rebase:
            out += self._rebase(st, fix)
            st = self.trains[fix.train]
        # the fix's time also closes the reorder windows of the train's units
        for unit in st.units:
            if unit.buffer:
                for released in release_unit(unit, self.cfg, now=fix.t):
                    out += self._to_train(st, released)
        out += self._count(step_train(st, fix, self.positioner)[1])
        return out

    def _to_train(self, st: TrainState, released: tuple[Inspected, bool]) -> list[Output]:
        return self._count(step_train(st, released, self.positioner)[1])

    def _count(self, outputs: list[Output]) -> list[Output]:
        for o in outputs:
            if isinstance(o, PositionedChunk):
                self.units[(o.train, o.unit)].health.published += 1
        return outputs
