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
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from schemas import GpsFix
from services.ingestion.config import IngestionConfig

if TYPE_CHECKING:
    from services.ingestion.core import TrainState


@dataclass(frozen=True)
class Knot:
    t: float
    line: str
    chainage_m: float
    speed_mps: float
    ok: bool


@dataclass(frozen=True)
class _LineGeometry:
    id: str
    length_m: float
    a: np.ndarray  # (pieces, 2) start points
    d: np.ndarray  # (pieces, 2) piece vectors
    dd: np.ndarray  # (pieces,) squared lengths
    chainage_m: np.ndarray  # (pieces + 1,)

    @classmethod
    def of(cls, line: Any) -> _LineGeometry:
        xy = np.asarray(line.xy, dtype=np.float64)
        d = np.diff(xy, axis=0)
        return cls(line.id, float(line.length_m), xy[:-1], d, (d * d).sum(axis=1), line.chainage_m)

    def project(self, p: np.ndarray, lo: float = -math.inf, hi: float = math.inf):
        """``(chainage, lateral)`` of the nearest point of the pieces overlapping [lo, hi].

        Lateral is signed, positive left of increasing chainage (as ``Line.project``).
        """
        c = self.chainage_m
        i0 = 0 if lo == -math.inf else max(0, int(np.searchsorted(c, lo, side="right")) - 1)
        i1 = len(self.a) if hi == math.inf else max(i0 + 1, int(np.searchsorted(c, hi)))
        a, d, dd = self.a[i0:i1], self.d[i0:i1], self.dd[i0:i1]
        q = p - a
        f = np.clip((q * d).sum(axis=1) / dd, 0.0, 1.0)
        r = q - f[:, None] * d
        dist2 = (r * r).sum(axis=1)
        j = int(dist2.argmin())
        cross = d[j, 0] * q[j, 1] - d[j, 1] * q[j, 0]
        chain = float(c[i0 + j] + f[j] * math.sqrt(dd[j]))
        return chain, math.copysign(math.sqrt(float(dist2[j])), cross)


class Positioner:
    """Map matching on a network (lines with ``id``, ``xy``, ``chainage_m``, ``length_m``)."""

    def __init__(self, network: Any, cfg: IngestionConfig) -> None:
        self.cfg = cfg
        self.to_xy = network.to_xy
        self.lines = {line_id: _LineGeometry.of(line) for line_id, line in network.lines.items()}

    def best_line(self, p: np.ndarray, exclude: str | None = None) -> tuple[str, float] | None:
        """The line that clearly fits ``p`` and its chainage, or None (none or ambiguous)."""
        cfg = self.cfg
        fits = sorted(
            (abs(lat), line_id, chain)
            for line_id, g in self.lines.items()
            if line_id != exclude
            for chain, lat in [g.project(p)]
        )
        if not fits or fits[0][0] > cfg.acquire_m:
            return None
        if len(fits) > 1 and fits[1][0] - fits[0][0] < cfg.ambiguity_m:
            return None
        return fits[0][1], fits[0][2]

    def knot(self, st: TrainState, fix: GpsFix) -> Knot | None:
        """A knot for one fix (matched or dead-reckoned), updating the matching state."""
        cfg = self.cfg
        last = st.knots[-1] if st.knots else None
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
            last = None
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
                    g, last = self.lines[st.line], None
                    chain, lat = g.project(p)
                    off = False
        else:
            st.off_count = 0
        chain = self._smooth(st, last, fix, self._monotone(st, chain), chain)
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
