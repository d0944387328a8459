"""Trains on routes: a deterministic speed profile, bogie units and a 1 Hz GPS.

A route is a line run end to end, a turn-back dwell, the line back, another turn-back,
repeated; the train reverses without turning (end B leads on the way back). The speed
profile over distance is the fastest one under a speed limit with bounded acceleration
and braking (a forward and a backward pass, both closed-form cumulative minima):

.. math::

    v_f^2(x) = \\min_{y \\le x} \\left[v_{lim}^2(y) + 2 a (x - y)\\right], \\qquad
    v^2(x) = \\min_{y \\ge x} \\left[v_f^2(y) + 2 b (y - x)\\right]

where ``v_lim`` is the cruise speed, 0 at stations, ``crawl_mps`` over the last
``crawl_m`` before a stop (station approach) and ``restriction_mps`` over a temporary
speed restriction of the line. Time follows from ``dt = 2 dx / (v_i + v_{i+1})``, with
a dwell at each stop. ``position(t)`` interpolates this precomputed cycle: no loop over
samples.

``line`` is duck-typed: ``.length_m``, ``.stations`` (chainages; both ends are always
stops), ``.line_speed_mps`` (optional, default 30), ``.lonlat_at(chainage) -> (lon, lat)``,
``.tunnels`` (list of ``(start, end)`` chainages) and ``.running`` (optional, default
``"both"``). On a track of double track that runs one way (``"increasing"`` or
``"decreasing"``) the train is in service only on the legs in that direction
(:meth:`TrainSimulator.in_service`): the way back runs on the other track, which this
simulator does not model, so its gateway sends nothing then.
"""

from __future__ import annotations

import math
import zlib
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from schemas import ACCEL_CHANNELS, SUPPLY_CHANNEL, NDArray
from schemas.messages import GpsFix, RawChunk
from simulators.bogie import BogiePhysics, BogieUnit, Kinematics
from simulators.profile import LineProfile, line_rng

RAW_CHANNELS = [*ACCEL_CHANNELS, SUPPLY_CHANNEL]  # the columns of a RawChunk's samples

_ROUTE_TAG, _GPS_TAG, _TSR_TAG = 0x524F5554, 0x47505321, 0x54535221
EARTH_RADIUS_M = 6_371_000.0


@dataclass(frozen=True)
class TrainConfig:
    """Operation and GPS constants of a train (services/defaults/simulator.json5 may override)."""

    accel_mps2: float = 0.8
    brake_mps2: float = 1.0
    dwell_s: tuple[float, float] = (30.0, 60.0)
    cruise_factor: tuple[float, float] = (0.9, 1.0)  # of the line speed, drawn per train
    default_line_speed_mps: float = 30.0
    crawl_m: float = 80.0  # station approach at crawl speed
    crawl_mps: float = 4.0
    restriction_m: float = 300.0  # one temporary speed restriction per line
    restriction_mps: float = 4.0
    grid_m: float = 1.0  # distance step of the precomputed profile
    unit_spacing_m: float = 20.0  # unit k sits k * spacing behind unit 0 (end A)
    chunk_s: float = 1.0
    gps_sigma_m: float = 2.0  # white error per axis
    gps_bias_m: float = 1.5  # slowly wandering error per axis
    gps_outage_prob: float = 0.002  # a fix lost in the open
    portal_m: float = 100.0  # degraded fixes near tunnel portals
    speed_sigma_mps: float = 0.1
    physics: BogiePhysics = field(default_factory=BogiePhysics)


def speed_profile(x: np.ndarray, vlim: np.ndarray, accel: float, brake: float) -> np.ndarray:
    """Fastest speed over the grid ``x`` under ``vlim`` with bounded acceleration/braking."""
    fwd = np.minimum.accumulate(vlim**2 - 2 * accel * x) + 2 * accel * x
    bwd = np.minimum.accumulate((fwd + 2 * brake * x)[::-1])[::-1] - 2 * brake * x
    return np.sqrt(np.maximum(bwd, 0.0))


MIN_STOP_SPACING_M = 200.0


def _stops(stations, length: float) -> np.ndarray:
    """Termini plus the stations at least MIN_STOP_SPACING_M from the previous stop and the
    far terminus: two stops a metre apart would leave no room to start and stop between."""
    kept = [0.0]
    for s in np.unique(np.asarray(stations, float)):
        if s - kept[-1] >= MIN_STOP_SPACING_M and length - s >= MIN_STOP_SPACING_M:
            kept.append(float(s))
    return np.array([*kept, length])


class TrainSimulator:
    """One train on a line with ``units`` bogie units.

    Parameters
    ----------
    train_id : str
        Stable id; seeds everything of this train.
    line : object
        Duck-typed line (see the module docstring).
    profile : LineProfile
        The line's irregularity profile (shared by all trains of the line).
    seed : int
        World seed.
    units : int
        Number of on-board units (``unit_spacing_m`` apart along the train).
    start_t : float
        Epoch s of chunk 0.
    phase_s : float or None
        Where in its route cycle the train is at ``start_t``; None draws one from the seed.
    config : TrainConfig
        Constants.
    sensors : sequence of (gain, mount_rad), optional
        Each unit's sensor (:class:`~simulators.bogie.BogieUnit`); default exact ones.
    """

    def __init__(
        self,
        train_id: str,
        line,
        profile: LineProfile,
        seed: int,
        units: int = 1,
        start_t: float = 0.0,
        phase_s: float | None = None,
        config: TrainConfig | None = None,
        sensors: Sequence[tuple[float, float]] | None = None,
    ) -> None:
        self.train_id, self.line, self.profile, self.seed = train_id, line, profile, seed
        self.start_t, self.cfg = float(start_t), config or TrainConfig()
        self._key = [seed, zlib.crc32(train_id.encode())]
        rng = np.random.default_rng([*self._key, _ROUTE_TAG])
        self._build_cycle(rng)
        self.phase_s = float(rng.uniform(0.0, self.cycle_s) if phase_s is None else phase_s)
        ph = self.cfg.physics
        self.fs_hz, self.n_chunk = ph.fs_hz, round(self.cfg.chunk_s * ph.fs_hz)
        sensors = sensors or [(1.0, 0.0)] * units  # (gain, mounting tilt rad) per unit
        self.units = [
            BogieUnit(profile, ph, seed, train_id, u, gain=sensors[u][0], mount_rad=sensors[u][1])
            for u in range(units)
        ]
        self._next = [-1] * units
        self._tunnels = np.asarray(getattr(line, "tunnels", []) or [], dtype=float).reshape(-1, 2)
        running = getattr(line, "running", "both")
        self.running_dir = {"increasing": 1, "decreasing": -1}.get(running, 0)  # 0: both
        g = np.random.default_rng([*self._key, _GPS_TAG])
        self._gps_w, self._gps_phase = (
            2 * np.pi / g.uniform(60, 600, (2, 2)),
            g.uniform(0, 7, (2, 2)),
        )

    # -- the route ------------------------------------------------------------------

    def _build_cycle(self, rng: np.random.Generator) -> None:
        cfg, length = self.cfg, float(self.line.length_m)
        dx = cfg.grid_m
        x = np.linspace(0.0, length, max(2, round(length / dx) + 1))
        stations = _stops(self.line.stations, length)
        line_speed = getattr(self.line, "line_speed_mps", None) or cfg.default_line_speed_mps
        cruise = line_speed * rng.uniform(*cfg.cruise_factor)
        # One temporary speed restriction per line, away from stations when possible.
        tsr = line_rng(self.seed, self.profile.line_id, _TSR_TAG).uniform(0.0, 1.0, 8)
        lo = tsr * (length - cfg.restriction_m)
        ok = np.abs(lo[:, None] + cfg.restriction_m / 2 - stations[None]).min(axis=1) > 500.0
        tsr0 = lo[ok][0] if ok.any() else None
        knots, t_end, odo_end = [], 0.0, 0.0
        for direction in (+1, -1):
            # Work in travel coordinates u (0 at the departure terminus), then map back.
            u = x
            st = np.sort(length - stations) if direction < 0 else stations
            vlim = np.full(u.size, cruise)
            if tsr0 is not None:
                r0 = tsr0 if direction > 0 else length - tsr0 - cfg.restriction_m
                vlim[(u >= r0) & (u <= r0 + cfg.restriction_m)] = cfg.restriction_mps
            ahead = st[np.searchsorted(st, u, side="left").clip(max=st.size - 1)] - u
            vlim[(ahead > 0) & (ahead <= cfg.crawl_m)] = np.minimum(cruise, cfg.crawl_mps)
            stop_idx = np.unique(np.searchsorted(u, st).clip(max=u.size - 1))
            vlim[stop_idx] = 0.0
            v = speed_profile(u, vlim, cfg.accel_mps2, cfg.brake_mps2)
            dt = np.diff(u) * 2.0 / np.maximum(v[:-1] + v[1:], 1e-9)
            t = np.r_[0.0, np.cumsum(dt)]
            # A dwell at every stop but the departure: the stop's knot appears twice, at the
            # arrival and at the departure, and everything after it is shifted by the dwell.
            dwell_at = stop_idx[stop_idx > 0]
            dw = np.zeros(u.size + 1)
            dw[dwell_at] = rng.uniform(*cfg.dwell_s, dwell_at.size)
            t = t + np.cumsum(np.r_[0.0, dw[:-1]])[: u.size]
            idx = np.sort(np.r_[np.arange(u.size), dwell_at])
            tt = t[idx]
            second = np.r_[False, idx[1:] == idx[:-1]]
            tt[second] += dw[idx[second]]
            chain = u[idx] if direction > 0 else length - u[idx]
            knots.append(
                (t_end + tt, chain, v[idx], np.full(idx.size, direction), odo_end + u[idx])
            )
            t_end, odo_end = t_end + tt[-1], odo_end + length
        self._t, self._x, self._v, self._dir, self._odo = (
            np.concatenate(k) for k in zip(*knots, strict=True)
        )
        self.cycle_s, self.cycle_m = t_end, odo_end

    def position(self, t):
        """``(chainage_m, speed_mps, accel_mps2, direction)`` of unit 0 at epoch times ``t``."""
        k = self.kinematics(np.asarray(t, dtype=np.float64))
        return k.chainage_m, k.speed_mps, k.accel_mps2, k.direction

    def kinematics(self, t: np.ndarray, unit: int = 0) -> Kinematics:
        """Kinematics of a unit's bogie at epoch times ``t`` (vectorised)."""
        rel = t - self.start_t + self.phase_s
        cycles = np.floor(rel / self.cycle_s)
        tau = rel - cycles * self.cycle_s
        i = np.clip(np.searchsorted(self._t, tau, side="right") - 1, 0, self._t.size - 2)
        span = np.maximum(self._t[i + 1] - self._t[i], 1e-12)  # the terminus knot is doubled
        f = (tau - self._t[i]) / span
        x = self._x[i] + f * (self._x[i + 1] - self._x[i])
        v = self._v[i] + f * (self._v[i + 1] - self._v[i])
        a = (self._v[i + 1] - self._v[i]) / span
        d = self._dir[i]
        odo = cycles * self.cycle_m + self._odo[i] + f * (self._odo[i + 1] - self._odo[i])
        return Kinematics(t, x - d * unit * self.cfg.unit_spacing_m, v, a, d, odo)

    def in_service(self, t) -> np.ndarray:
        """Whether the train runs on this line at epoch times ``t``: always, unless the
        line runs one way only and unit 0 is on a leg the other way."""
        direction = self.kinematics(np.asarray(t, dtype=np.float64)).direction
        return (self.running_dir == 0) | (direction == self.running_dir)

    # -- outputs --------------------------------------------------------------------

    def chunk(self, seq: int, unit: int = 0) -> tuple[float, np.ndarray, bool]:
        """Chunk ``seq`` of a unit: ``(t0, samples (n, 7) float32, dropped)``.

        Chunk ``seq`` starts at ``start_t + seq * chunk_s``. Consecutive calls continue
        the unit's filter state; any other ``seq`` restarts it in steady state.
        """
        if seq < 0:
            raise ValueError(f"seq: must be >= 0, got {seq}")
        bogie = self.units[unit]
        if seq != self._next[unit]:
            bogie.reset()
        self._next[unit] = seq + 1
        t0 = self.start_t + seq * self.cfg.chunk_s
        t = t0 + np.arange(self.n_chunk) / self.fs_hz
        samples, dropped = bogie.chunk(seq, self.kinematics(t, unit))
        return t0, samples, dropped

    def raw_chunk(self, seq: int, unit: int = 0) -> tuple[RawChunk, bool]:
        """Chunk ``seq`` of a unit as its gateway sends it, and whether it was lost
        (``dropped``: a gateway skips it; tests may keep it)."""
        t0, samples, dropped = self.chunk(seq, unit)
        chunk = RawChunk(
            train=self.train_id,
            unit=f"u{unit}",
            seq=seq,
            t0=t0,
            rate_hz=self.fs_hz,
            channels=RAW_CHANNELS,
            samples=NDArray.of(samples, "f4"),
        )
        return chunk, dropped

    def in_tunnel(self, chainage) -> np.ndarray:
        """Whether each chainage lies in a tunnel."""
        c = np.asarray(chainage, dtype=float)[..., None]
        tun = self._tunnels
        return ((c >= tun[:, 0]) & (c <= tun[:, 1])).any(axis=-1)

    def gps_fixes(self, t0: float, t1: float) -> list[GpsFix]:
        """The 1 Hz fixes at whole epoch seconds in ``[t0, t1)``.

        Error: a slowly wandering bias (two sinusoids per axis, ``gps_bias_m``) plus white
        noise (``gps_sigma_m``) east and north, converted to degrees with a local
        spherical projection. In a tunnel, and on rare outages, the receiver has no fix:
        the fix is still sent (1 Hz heartbeat) with ``fix_quality = 0``, lat/lon 0.0 and no
        speed or hdop; consumers must ignore its position. Within ``portal_m`` of a portal
        the error is three times larger and hdop 3-5.
        """
        cfg = self.cfg
        ts = np.arange(math.ceil(t0), t1, 1.0)
        if ts.size == 0:
            return []
        s, v, _, _ = self.position(ts)
        fixes = []
        tun = self._tunnels
        near = (
            np.abs(s[:, None, None] - tun[None]).min(axis=(1, 2)) < cfg.portal_m
            if tun.size
            else np.zeros(ts.size, bool)
        )
        bias = cfg.gps_bias_m * np.sin(ts[:, None, None] * self._gps_w + self._gps_phase).mean(
            axis=2
        )
        inside = self.in_tunnel(s)
        for k, tk in enumerate(ts):  # 1 Hz: one Python step per fix is cheap
            rng = np.random.default_rng([*self._key, _GPS_TAG, int(tk)])
            err = rng.normal(0.0, cfg.gps_sigma_m, 2) + bias[k]
            hdop = rng.uniform(0.7, 1.3)
            lost = rng.random() < cfg.gps_outage_prob
            if inside[k] or lost:
                fixes.append(
                    GpsFix(
                        train=self.train_id, t=float(tk), lat_deg=0.0, lon_deg=0.0, fix_quality=0
                    )
                )
                continue
            if near[k]:
                err, hdop = 3.0 * err, rng.uniform(3.0, 5.0)
            lon, lat = (float(c) for c in self.line.lonlat_at(float(s[k])))
            lat2 = lat + math.degrees(err[1] / EARTH_RADIUS_M)
            lon2 = lon + math.degrees(err[0] / (EARTH_RADIUS_M * math.cos(math.radians(lat))))
            speed = max(0.0, float(v[k]) + rng.normal(0.0, cfg.speed_sigma_mps))
            fixes.append(
                GpsFix(
                    train=self.train_id,
                    t=float(tk),
                    lat_deg=lat2,
                    lon_deg=lon2,
                    speed_mps=speed,
                    fix_quality=1,
                    hdop=float(hdop),
                )
            )
        return fixes
