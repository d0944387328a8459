"""Map matching: a GPS fix to a knot ``(t, line, chainage, speed, ok)`` on the network. Pure.

Map matching keeps **continuity**: a train stays on its line while the fixes are within
``switch_lateral_m`` of it; only ``switch_fixes`` consecutive fixes farther away, with
another line clearly fitting (within ``acquire_m``, ``ambiguity_m`` closer than any other),
move it. Acquisition needs the same clear fit. Two lines 30 m apart (the demo's L1/L3) are
therefore never confused by a few metres of GPS error. Chainage is projected on a window of
the current line around the predicted position (no jumps to another part of a curving
line) and kept monotone in the direction of travel: a backwards step smaller than
``reverse_m`` (GPS jitter at a standstill) holds the previous chainage; a larger one is a
reversal (a terminus).

**Tracks of one route.** GPS cannot tell the tracks of a double-track route apart (a few
metres), but the direction of running can: each track normally carries one direction
(``Line.running``). Lines sharing a ``route`` whose nearest points to a fix lie within
``ambiguity_m`` of each other are one candidate for acquisition and switching; among them
the train takes the track whose ``running`` is its direction of travel along the route,
learnt from its chainage as above, and keeps it while it keeps that direction. A reversal
moves it to a close track that runs the new way, if there is one. Until the direction is
known (the first fixes, a standstill), or when no single track runs that way, the train is
not positioned (its chunks are refused as ``unpositioned``). A fix more than
``reacquire_s`` after the previous one (a gateway that was off) starts matching over.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from schemas import GpsFix
from services.ingestion.config import IngestionConfig
from services.ingestion.train import Knot, TrainState


@dataclass(frozen=True)
class _LineGeometry:
    id: str
    length_m: float
    route: str  # Line.route_id
    running: str  # Line.running
    a: np.ndarray  # (pieces, 2) start points
    d: np.ndarray  # (pieces, 2) piece vectors
    dd: np.ndarray  # (pieces,) squared lengths
    chainage_m: np.ndarray  # (pieces + 1,)

    @classmethod
    def of(cls, line: Any) -> _LineGeometry:
        xy = np.asarray(line.xy, dtype=np.float64)
        d = np.diff(xy, axis=0)
        route = getattr(line, "route", "") or line.id
        running = getattr(line, "running", "both")
        c = line.chainage_m
        return cls(
            line.id, float(line.length_m), route, running, xy[:-1], d, (d * d).sum(axis=1), c
        )

    def _piece(self, chain: float) -> int:
        return min(
            max(int(np.searchsorted(self.chainage_m, chain, side="right")) - 1, 0), len(self.a) - 1
        )

    def point_at(self, chain: float) -> np.ndarray:
        """Local x, y of a chainage on the line."""
        j = self._piece(chain)
        f = (chain - self.chainage_m[j]) / math.sqrt(self.dd[j])
        return self.a[j] + min(max(f, 0.0), 1.0) * self.d[j]

    def heading_at(self, chain: float) -> np.ndarray:
        """Unit vector of increasing chainage at a chainage."""
        j = self._piece(chain)
        return self.d[j] / math.sqrt(self.dd[j])

    def runs(self, direction: int) -> bool:
        """Whether ``running`` names ``direction`` (+1/-1 chainage) explicitly."""
        return self.running == ("increasing" if direction > 0 else "decreasing")

    def project(self, p: np.ndarray, lo: float = -math.inf, hi: float = math.inf):
        """``(chainage, lateral)`` of the nearest point of the pieces overlapping [lo, hi].

        Lateral is signed, positive left of increasing chainage (as ``Line.project``).
        """
        c = self.chainage_m
        i0 = 0 if lo == -math.inf else max(0, int(np.searchsorted(c, lo, side="right")) - 1)
        i1 = len(self.a) if hi == math.inf else max(i0 + 1, int(np.searchsorted(c, hi)))
        return self._project(p, slice(i0, i1))

    def _project(self, p: np.ndarray, pieces: slice | np.ndarray) -> tuple[float, float]:
        a, d, dd = self.a[pieces], self.d[pieces], self.dd[pieces]
        q = p - a
        f = np.clip((q * d).sum(axis=1) / dd, 0.0, 1.0)
        r = q - f[:, None] * d
        dist2 = (r * r).sum(axis=1)
        j = int(dist2.argmin())
        cross = d[j, 0] * q[j, 1] - d[j, 1] * q[j, 0]
        i = (pieces.start or 0) + j if isinstance(pieces, slice) else int(pieces[j])
        chain = float(self.chainage_m[i] + f[j] * math.sqrt(dd[j]))
        return chain, math.copysign(math.sqrt(float(dist2[j])), cross)


class _PieceGrid:
    """The pieces of a line near each cell of a square grid, to project a point on the
    pieces near it only (a track's other tracks are looked up at every fix: projecting on
    all the pieces of a 300 km line would cost ~2 ms a fix).

    Pieces are sampled every ``cell_m / 2`` and each sample registered in its cell and the
    8 around it. A point of a piece is within ``cell_m / 4`` of a sample, so every piece
    within ``cell_m * 3 / 4`` of a point is registered in the point's cell: :meth:`near`
    is exact within ``reach_m``.
    """

    def __init__(self, g: _LineGeometry, cell_m: float = 100.0) -> None:
        self.cell_m, self.reach_m = cell_m, 0.75 * cell_m
        n = np.maximum(1, np.ceil(np.sqrt(g.dd) / (cell_m / 2)).astype(np.int64)) + 1
        piece = np.repeat(np.arange(len(g.a)), n)  # n samples of each piece, ends included
        first = np.repeat(np.cumsum(n) - n, n)
        f = (np.arange(len(piece)) - first) / np.repeat(n - 1, n)
        cell = np.floor((g.a[piece] + f[:, None] * g.d[piece]) / cell_m).astype(np.int64)
        ring = np.array([(dx, dy) for dx in (-1, 0, 1) for dy in (-1, 0, 1)])
        cell = (cell[:, None, :] + ring[None]).reshape(-1, 2)
        rows = np.c_[cell, np.repeat(piece, len(ring))]
        rows = rows[np.lexsort((rows[:, 2], rows[:, 1], rows[:, 0]))]  # by cell, then piece
        rows = rows[np.r_[True, (np.diff(rows, axis=0) != 0).any(axis=1)]]  # once each
        starts = np.r_[0, np.flatnonzero((np.diff(rows[:, :2], axis=0) != 0).any(axis=1)) + 1]
        self.cells = {
            (int(rows[i, 0]), int(rows[i, 1])): rows[i:j, 2]
            for i, j in zip(starts, np.r_[starts[1:], len(rows)], strict=True)
        }

    def near(self, p: np.ndarray) -> np.ndarray | None:
        """Indices of the pieces that may lie within ``reach_m`` of ``p`` (None: none)."""
        return self.cells.get((int(p[0] // self.cell_m), int(p[1] // self.cell_m)))


class Positioner:
    """Map matching on a network (lines with ``id``, ``xy``, ``chainage_m``, ``length_m``)."""

    def __init__(self, network: Any, cfg: IngestionConfig) -> None:
        self.cfg = cfg
        self.to_xy = network.to_xy
        self.lines = {line_id: _LineGeometry.of(line) for line_id, line in network.lines.items()}
        routes: dict[str, list[str]] = {}
        for line_id, g in self.lines.items():
            routes.setdefault(g.route, []).append(line_id)
        # the other tracks of each line's route (none for a line that is its own route)
        self.siblings = {
            line_id: [other for other in routes[g.route] if other != line_id]
            for line_id, g in self.lines.items()
        }
        self.grids = {
            line_id: _PieceGrid(self.lines[line_id])
            for line_id, others in self.siblings.items()
            if others
        }

    def best_line(self, p: np.ndarray, exclude: str | None = None) -> tuple[str, float] | None:
        """The line that clearly fits ``p`` and its chainage, or None (none or ambiguous).

        Tracks of the best line's route close to it at ``p`` (:meth:`close_tracks`) are not
        rivals: they are one candidate, told apart later by the running direction.
        """
        cfg = self.cfg
        fits = sorted(
            (abs(lat), line_id, chain)
            for line_id, g in self.lines.items()
            if line_id != exclude
            for chain, lat in [g.project(p)]
        )
        if not fits or fits[0][0] > cfg.acquire_m:
            return None
        best, chain = fits[0][1], fits[0][2]
        same = {line_id for line_id, _ in self.close_tracks(best, chain, p)}
        rivals = [f for f in fits[1:] if f[1] not in same]
        if rivals and rivals[0][0] - fits[0][0] < cfg.ambiguity_m:
            return None
        return best, chain

    def close_tracks(self, line_id: str, chain: float, p: np.ndarray) -> list[tuple[str, int]]:
        """The other tracks of ``line_id``'s route whose nearest point to ``p`` is within
        ``ambiguity_m`` of ``line_id``'s (at ``chain``), each with the sense of its chainage
        relative to ``line_id``'s there (+1 the same way, -1 drawn the other way)."""
        if not self.siblings[line_id]:
            return []
        g = self.lines[line_id]
        q, h = g.point_at(chain), g.heading_at(chain)
        # a close track's nearest point lies within this of p
        within = float(np.hypot(*(q - p))) + self.cfg.ambiguity_m
        out = []
        for other in self.siblings[line_id]:
            o, grid = self.lines[other], self.grids[other]
            if within <= grid.reach_m:
                pieces = grid.near(p)
                if pieces is None:
                    continue  # no piece of it near p
                c, _ = o._project(p, pieces)
            else:  # far off the line: every piece
                c, _ = o.project(p)
            if float(np.hypot(*(o.point_at(c) - q))) <= self.cfg.ambiguity_m:
                out.append((other, 1 if float(o.heading_at(c) @ h) >= 0 else -1))
        return out

    def _track(self, st: TrainState, chain: float, p: np.ndarray) -> tuple[str, int] | None:
        """The track the train is on among the close tracks of its route, with its
        direction on it; None while it cannot be told (direction unknown, or no single
        track running that way)."""
        close = self.close_tracks(st.line, chain, p)
        if not close:
            st.track_known = True  # no close track: the line is told by GPS alone
            return st.line, st.direction
        if st.direction == 0:
            return None
        if st.track_known and self.lines[st.line].runs(st.direction):
            return st.line, st.direction
        here = [(st.line, st.direction)] + [(o, s * st.direction) for o, s in close]
        runners = [(o, d) for o, d in here if self.lines[o].runs(d)]
        if len(runners) == 1:
            st.track_known = True
            return runners[0]
        if st.track_known:  # no other track runs the new way: wrong-line running, stay
            return st.line, st.direction
        return None

    def knot(self, st: TrainState, fix: GpsFix) -> Knot | None:
        """A knot for one fix (matched or dead-reckoned), updating the matching state."""
        cfg = self.cfg
        last = st.knots[-1] if st.knots else None
        silent = st.matched_fix_t is not None and fix.t - st.matched_fix_t > cfg.reacquire_s
        st.matched_fix_t = fix.t
        if silent:  # the gateway was off: wherever the train is now, start over
            st.line, st.direction, st.track_known, last = None, 0, False, None
        if fix.fix_quality == 0:
            st.stats.no_fix += 1
            if st.line is None or last is None or last.line != st.line:
                return None
            g = self.lines[st.line]
            dt = fix.t - last.t
            chain = min(max(last.chainage_m + st.direction * last.speed_mps * dt, 0.0), g.length_m)
            ok = st.last_good_t is not None and fix.t - st.last_good_t <= cfg.dead_reckon_s
            return Knot(fix.t, st.line, chain, last.speed_mps, ok)
        p = self.to_xy(np.array([fix.lon_deg, fix.lat_deg]))
        if st.line is None:
            found = self.best_line(p)
            if found is None:
                return None
            st.line, st.direction, st.extreme_m, st.off_count = found[0], 0, found[1], 0
            st.track_known, last = False, None
        g = self.lines[st.line]
        if last is not None and last.line == st.line:
            reach = cfg.search_m + last.speed_mps * (fix.t - last.t) * 1.5
            chain, lat = g.project(p, last.chainage_m - reach, last.chainage_m + reach)
            if abs(lat) > cfg.switch_lateral_m:  # lost the thread (long outage): whole line
                chain, lat = g.project(p)
        else:
            chain, lat = g.project(p)
        off = abs(lat) > cfg.switch_lateral_m
        if off:
            st.off_count += 1
            if st.off_count >= cfg.switch_fixes:
                found = self.best_line(p, exclude=st.line)
                if found is not None:
                    st.stats.switches += 1
                    st.line, st.direction, st.extreme_m, st.off_count = found[0], 0, found[1], 0
                    st.track_known, g, last = False, self.lines[st.line], None
                    chain, lat = g.project(p)
                    off = False
        else:
            st.off_count = 0
        measured = chain
        chain = self._smooth(st, last, fix, self._monotone(st, chain), chain)
        track = self._track(st, measured, p)
        if track is None:
            return None
        if track[0] != st.line:  # the close track running this way
            st.stats.switches += 1
            st.line, st.direction, st.off_count = track[0], track[1], 0
            g, last = self.lines[st.line], None
            chain, lat = g.project(p)
            st.extreme_m = chain
        if fix.speed_mps is not None:
            speed = fix.speed_mps
        elif last is not None and last.line == st.line and fix.t > last.t:
            speed = abs(chain - last.chainage_m) / (fix.t - last.t)
        else:
            speed = 0.0
        ok = (
            not off
            and abs(lat) <= cfg.lateral_ok_m
            and (fix.hdop is None or fix.hdop <= cfg.hdop_max)
        )
        if ok:
            st.last_good_t = fix.t
        return Knot(fix.t, st.line, chain, speed, ok)

    def _smooth(
        self, st: TrainState, last: Knot | None, fix: GpsFix, held: float, measured: float
    ) -> float:
        r"""Blend the projection with the chainage predicted from the fix speeds.

        .. math::

            \hat c = c_{k-1} + d\,\tfrac{v_{k-1} + v_k}{2}\,\Delta t, \qquad
            c_k = \hat c + g\,(c_{meas} - \hat c)

        GPS speed is far less noisy than GPS position, so this cuts the white position
        noise (to about ``sqrt(g / (2 - g))`` of it) and keeps a standing train still. Off
        the gate (after an outage, a reversal being detected) the projection is used as is.
        """
        cfg = self.cfg
        if (
            last is None
            or last.line != st.line
            or st.direction == 0
            or fix.speed_mps is None
            or fix.t - last.t > cfg.dead_reckon_s
        ):
            return held
        dt = fix.t - last.t
        pred = last.chainage_m + st.direction * 0.5 * (last.speed_mps + fix.speed_mps) * dt
        if abs(measured - pred) > cfg.fuse_gate_m:
            return held
        fused = pred + cfg.fuse_gain * (measured - pred)
        if st.direction * (fused - last.chainage_m) < 0:  # never backwards
            return last.chainage_m
        return fused

    def _monotone(self, st: TrainState, chain: float) -> float:
        """Chainage kept monotone in the direction of travel (GPS jitter at a standstill)."""
        reverse = self.cfg.reverse_m
        if st.direction == 0:
            if abs(chain - st.extreme_m) > reverse:
                st.direction = 1 if chain > st.extreme_m else -1
                st.extreme_m = chain
            return chain
        ahead = st.direction * (chain - st.extreme_m)
        if ahead >= 0:
            st.extreme_m = chain
            return chain
        if -ahead > reverse:  # a reversal (terminus): follow it
            st.direction, st.extreme_m = -st.direction, chain
            return chain
        return st.extreme_m
