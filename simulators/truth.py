"""The true degradation of every segment: the same Wiener model with tamping as the filter.

Each segment belongs to a degradation class (fast, typical, slow;
``services/defaults/simulator.json5``, section ``truth``) and draws its own drift and
diffusion around the class values. Its state
``z = [ln Top6_mm, ln Align10_mm]`` follows the multivariate Wiener model of the paper's
Eq. 1 on a fixed grid of ``step_days`` (default one day):

.. math::

    z_k = z_{k-1} + \\mu\\,\\Delta t + L\\,\\sqrt{\\Delta t}\\,\\varepsilon_k, \\qquad
    L L^T = \\Sigma, \\quad \\varepsilon_k \\sim N(0, I).

A tamping at :math:`t_m \\in (t_{k-1}, t_k]` resets the state to
:math:`z^+ \\sim N(z^+_{class}, \\Sigma_{z^+})` and the segment then degrades for
:math:`a = t_k - t_m`: :math:`z_k = z^+ + \\mu a + L \\sqrt{a}\\,\\varepsilon_k`, which is
exactly the filter's transition with a known tamping age (``degradation.transition``).
Each tamping increments the segment's ``epoch``, the counter of its irregularity profile
shape (a fresh profile after tamping).

Tamping happens (``maintenance`` section) ``delay_days`` after a grid day on which Top6 or
Align10 exceeds its limit, and on a fixed schedule per track section (every
``scheduled_period_days``, random phase per section), whichever comes first. A share
``interval_fraction`` of the MaintenanceEvents is reported only as an interval containing
the true time, published at the interval's end. Maintenance records are not always kept:
a share ``unreported_fraction`` of the tampings is never reported (the ground truth still
has them), and a share ``late_fraction`` of the reported ones is published
``late_days`` after it would have been (the report itself is unchanged). Both are drawn
per tamping from keys of their own, so turning them on changes no other draw.

Between grid points :meth:`Truth.z_at` interpolates linearly (across a tamping: the
untamped path up to :math:`t_m`, then from :math:`z^+` at :math:`t_m`), so the truth at
any instant is deterministic and does not depend on who asks when.

Initial state: every segment starts at a random age since its last tamping, uniform in
``[0, min(expected days to reach the limit, days since its section's last scheduled
tamping, max_initial_age_days)]``, so that a network starts in a steady-state-like mix of
fresh and worn track.

Randomness is keyed by stable ids (:func:`simulators.network.stable_rng`): per line for the
initial state and the daily increments, per (line, segment, epoch) for tamping draws.
Results therefore do not depend on iteration order, and adding a line changes no other.
"""

from __future__ import annotations

import copy
import heapq
import math
from collections import deque
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from schemas import DAY_S, MaintenanceEvent
from services.defaults import default_file
from services.runtime.config import read_json5
from simulators.network import stable_rng
from track.network import Network

DEFAULT_CONFIG = default_file("simulator.json5")


def load_config(path: str | Path | None = None) -> dict:
    """The simulator config (JSON5) as a dict; every module parses its own section."""
    return read_json5(path or DEFAULT_CONFIG)


def _cov(sd, corr: float, name: str) -> np.ndarray:
    sd = np.asarray(sd, dtype=np.float64)
    if sd.shape != (2,) or (sd < 0).any() or not -1 < corr < 1:
        raise ValueError(f"{name}: needs 2 standard deviations >= 0 and -1 < corr < 1")
    return np.array([[1.0, corr], [corr, 1.0]]) * np.outer(sd, sd)


def config_pair(cfg: Mapping, key: str, section: str, positive: bool = True) -> tuple[float, float]:
    """``cfg[key]`` as ``(low, high)``; ValueError naming ``section.key`` if malformed."""
    try:
        lo, hi = (float(v) for v in cfg[key])
    except (KeyError, TypeError, ValueError):
        raise ValueError(f"{section}.{key}: expected [low, high]") from None
    if not (lo <= hi and (lo >= 0 or not positive)):
        raise ValueError(f"{section}.{key}: expected 0 <= low <= high, got [{lo}, {hi}]")
    return lo, hi


@dataclass(frozen=True)
class DegradationClass:
    """True class parameters (per day, log mm)."""

    name: str
    mu: np.ndarray  # (2,)
    sigma: np.ndarray  # (2, 2)
    z_plus: np.ndarray  # (2,) ln mm
    sigma_z_plus: np.ndarray  # (2, 2)


@dataclass(frozen=True)
class TruthConfig:
    """The ``truth`` and ``maintenance`` sections of the simulator config."""

    classes: dict[str, DegradationClass]
    mix: dict[str, float]
    line_mix: dict[str, dict[str, float]]
    mu_spread: float
    sigma_spread: float
    step_days: float
    max_initial_age_days: float
    limits_mm: np.ndarray  # (2,)
    line_limits_mm: dict[str, np.ndarray]
    delay_days: tuple[float, float]
    scheduled_period_days: float  # 0: none
    section_segments: int
    interval_fraction: float
    interval_days: tuple[float, float]
    unreported_fraction: float = 0.0
    late_fraction: float = 0.0
    late_days: tuple[float, float] = (3.0, 21.0)

    @classmethod
    def from_config(cls, config: Mapping) -> TruthConfig:
        """Parse and check; a ValueError names the offending entry."""
        if isinstance(config, TruthConfig):
            return config
        try:
            t, m = config["truth"], config["maintenance"]
        except KeyError as exc:
            raise ValueError(f"simulator config: missing section {exc}") from None
        classes = {}
        for name, c in t["classes"].items():
            mu = np.asarray(c["mu"], dtype=np.float64)
            if mu.shape != (2,):
                raise ValueError(f"truth.classes.{name}.mu: expected 2 values")
            classes[name] = DegradationClass(
                name,
                mu,
                _cov(c["sigma_sd"], c["corr"], f"truth.classes.{name}"),
                np.log(np.asarray(c["z_plus_mm"], dtype=np.float64)),
                _cov(c["z_plus_sd"], c["z_plus_corr"], f"truth.classes.{name}.z_plus"),
            )

        def mix(raw: Mapping, where: str) -> dict[str, float]:
            unknown = set(raw) - set(classes)
            w = np.array([float(raw.get(k, 0.0)) for k in classes])
            if unknown or (w < 0).any() or w.sum() <= 0:
                raise ValueError(f"{where}: shares >= 0 of classes {list(classes)}, got {raw}")
            return dict(zip(classes, w / w.sum(), strict=True))

        limits = np.asarray(m["limits_mm"], dtype=np.float64)
        line_limits = {k: np.asarray(v, float) for k, v in (m.get("line_limits_mm") or {}).items()}
        for name, lim in [("limits_mm", limits)] + list(line_limits.items()):
            if lim.shape != (2,) or (lim <= 0).any():
                raise ValueError(f"maintenance.{name}: expected 2 limits > 0 mm")
        cfg = cls(
            classes=classes,
            mix=mix(t["mix"], "truth.mix"),
            line_mix={k: mix(v, f"truth.line_mix.{k}") for k, v in t.get("line_mix", {}).items()},
            mu_spread=float(t.get("mu_spread", 0.0)),
            sigma_spread=float(t.get("sigma_spread", 0.0)),
            step_days=float(t.get("step_days", 1.0)),
            max_initial_age_days=float(t.get("max_initial_age_days", 3650.0)),
            limits_mm=limits,
            line_limits_mm=line_limits,
            delay_days=config_pair(m, "delay_days", "maintenance"),
            scheduled_period_days=float(m.get("scheduled_period_days", 0.0)),
            section_segments=int(m.get("section_segments", 25)),
            interval_fraction=float(m.get("interval_fraction", 0.0)),
            interval_days=config_pair(m, "interval_days", "maintenance"),
            unreported_fraction=float(m.get("unreported_fraction", 0.0)),
            late_fraction=float(m.get("late_fraction", 0.0)),
            late_days=config_pair(m, "late_days", "maintenance")
            if "late_days" in m
            else (3.0, 21.0),
        )
        if not cfg.step_days > 0 or cfg.section_segments < 1 or cfg.scheduled_period_days < 0:
            raise ValueError("truth.step_days > 0, section_segments >= 1, period >= 0 required")
        if not 0 <= cfg.interval_fraction <= 1 or cfg.mu_spread < 0 or cfg.sigma_spread < 0:
            raise ValueError("interval_fraction in [0, 1], mu_spread and sigma_spread >= 0")
        for name in ("unreported_fraction", "late_fraction"):
            if not 0 <= getattr(cfg, name) <= 1:
                raise ValueError(f"maintenance.{name}: a share in [0, 1]")
        return cfg


@dataclass(frozen=True)
class Tamping:
    """One true tamping of one segment."""

    seg: int  # position in the network's segment order
    line: str
    segment: str
    t: float  # true time, epoch s
    t_start: float  # reported interval (t_start == t_end == t when the time is known)
    t_end: float
    epoch: int  # the segment's profile epoch after this tamping
    cause: str  # "limit" or "scheduled"
    z_before: np.ndarray  # (2,) state just before
    z_after: np.ndarray  # (2,) state just after (the drawn z+)
    report: str = "on_time"  # "on_time", "late" or "never" (no MaintenanceEvent published)
    t_reported: float | None = None  # when the MaintenanceEvent is published; None: never

    @property
    def event_id(self) -> str:
        return f"tamp-{self.line}-{self.segment}-{self.epoch}"

    def message(self) -> MaintenanceEvent:
        return MaintenanceEvent(
            line=self.line,
            segment=self.segment,
            event_id=self.event_id,
            t_start=self.t_start,
            t_end=self.t_end,
        )


@dataclass(frozen=True)
class _Step:
    t_prev: float
    t: float
    z_prev: np.ndarray  # (S, 2)
    z: np.ndarray  # (S, 2)
    tamped: dict[int, tuple[float, np.ndarray, np.ndarray]]  # seg -> (t_m, z_pre, z_post)


class Truth:
    """The true state of all segments of a network, stepped on a fixed time grid.

    Parameters
    ----------
    network : Network
    config : Mapping or TruthConfig
        The simulator config (:func:`load_config`).
    start_t : float
        Epoch s of the initial state.
    seed : int
    keep_steps : int or None
        Grid steps kept for :meth:`z_at` (queries may lag the newest step by this much);
        default: at least two days' worth.

    Attributes
    ----------
    keys : list of (line, segment)
        Segment order of every per-segment array (the network's order).
    t : float
        Epoch s of the current state ``z`` (S, 2); ``epoch`` (S,) counts tampings.
    klass : ndarray of int, (S,)
        Index into ``class_names``.
    mu, sigma, z_plus, sigma_z_plus : ndarray
        True per-segment parameters, (S, 2), (S, 2, 2), (S, 2), (S, 2, 2).
    """

    def __init__(self, network: Network, config, start_t: float, seed: int, keep_steps: int = 2):
        cfg = self.config = TruthConfig.from_config(config)
        self.seed, self.start_t = int(seed), float(start_t)
        self.step_s = cfg.step_days * DAY_S
        self.keys = [(line.id, seg.id) for line, seg in network.segments()]
        self.segment_index = np.array([seg.index for _, seg in network.segments()])
        self.line_slices: dict[str, slice] = {}
        lo = 0
        for line in network.lines.values():
            self.line_slices[line.id] = slice(lo, lo + len(line.segments))
            lo += len(line.segments)
        self.class_names = tuple(cfg.classes)
        classes = list(cfg.classes.values())
        period = cfg.scheduled_period_days
        parts = []
        for line_id, sl in self.line_slices.items():
            n = sl.stop - sl.start
            rng = stable_rng(seed, "truth-init", line_id)
            shares = np.array(list(cfg.line_mix.get(line_id, cfg.mix).values()))
            cum = np.cumsum(shares)
            klass = np.minimum(np.searchsorted(cum, rng.random(n) * cum[-1], "right"), len(cum) - 1)
            n_sections = (n - 1) // cfg.section_segments + 1
            phase = rng.uniform(0, period, n_sections)[np.arange(n) // cfg.section_segments]
            parts.append(
                dict(
                    klass=klass,
                    mu_f=np.exp(cfg.mu_spread * rng.standard_normal((n, 2))),
                    sigma_f=np.exp(cfg.sigma_spread * rng.standard_normal(n)),
                    zp=rng.standard_normal((n, 2)),
                    age_u=rng.random(n),
                    w=rng.standard_normal((n, 2)),
                    phase=phase,
                    limits=np.log(cfg.line_limits_mm.get(line_id, cfg.limits_mm)) * np.ones((n, 1)),
                )
            )
        p = {k: np.concatenate([d[k] for d in parts]) for k in parts[0]}
        self.klass = p["klass"]
        self.mu = np.stack([c.mu for c in classes])[self.klass] * p["mu_f"]
        self.sigma = np.stack([c.sigma for c in classes])[self.klass] * p["sigma_f"][:, None, None]
        self.z_plus = np.stack([c.z_plus for c in classes])[self.klass]
        self.sigma_z_plus = np.stack([c.sigma_z_plus for c in classes])[self.klass]
        self.log_limits = p["limits"]
        self._chol = np.linalg.cholesky(self.sigma)
        self._chol_zp = np.linalg.cholesky(self.sigma_z_plus)
        # Age since the last tamping: not beyond the expected crossing of a limit nor the
        # section's last scheduled tamping (phase = days until the next one).
        with np.errstate(divide="ignore"):
            t_lim = np.where(self.mu > 0, (self.log_limits - self.z_plus) / self.mu, np.inf)
        a_max = np.minimum(t_lim.min(axis=1), period - p["phase"] if period > 0 else np.inf)
        age = p["age_u"] * np.clip(a_max, 0.0, cfg.max_initial_age_days)
        self.z = (
            self.z_plus
            + _matvec(self._chol_zp, p["zp"])
            + self.mu * age[:, None]
            + np.sqrt(age)[:, None] * _matvec(self._chol, p["w"])
        )
        self.epoch = np.zeros(len(self.keys), dtype=np.int64)
        self.t = self.start_t
        self.tamping_due = np.full(
            len(self.keys), np.inf
        )  # when each segment is tamped (inf: none due)
        self._next_sched = np.where(period > 0, self.start_t + p["phase"] * DAY_S, np.inf)
        self._gens = {
            line_id: stable_rng(seed, "truth-increments", line_id) for line_id in self.line_slices
        }
        keep = keep_steps or max(2, math.ceil(2.0 / cfg.step_days))
        self._history: deque[_Step] = deque(maxlen=max(1, keep) + 1)
        self._history.append(_Step(self.t, self.t, self.z, self.z, {}))
        self._schedule_crossings()

    @property
    def n_segments(self) -> int:
        return len(self.keys)

    def copy(self) -> Truth:
        """An independent replica that will follow exactly the same path."""
        return copy.deepcopy(self)

    def _event_rng(self, kind: str, i: int) -> np.random.Generator:
        return stable_rng(self.seed, kind, self.keys[i][0], self.segment_index[i], self.epoch[i])

    def _report(self, i: int, t_end: float) -> tuple[str, float | None]:
        """Whether and when segment ``i``'s tamping (epoch already counted) is reported."""
        cfg = self.config
        if not (cfg.unreported_fraction or cfg.late_fraction):
            return "on_time", t_end
        rng = self._event_rng("report", i)
        if rng.random() < cfg.unreported_fraction:
            return "never", None
        if rng.random() < cfg.late_fraction:
            return "late", t_end + rng.uniform(*cfg.late_days) * DAY_S
        return "on_time", t_end

    def _schedule_crossings(self) -> None:
        """Schedule a tamping for segments over a limit with none pending."""
        lo, hi = self.config.delay_days
        for i in np.flatnonzero(
            (self.z > self.log_limits).any(axis=1) & np.isinf(self.tamping_due)
        ):
            self.tamping_due[i] = self.t + self._event_rng("delay", i).uniform(lo, hi) * DAY_S

    def step(self) -> list[Tamping]:
        """Advance one grid step; returns the tampings inside it, in time order."""
        cfg, t_prev, t_new = self.config, self.t, self.t + self.step_s
        dt = cfg.step_days
        # One fixed-size draw per line and step: a line's path never depends on the others.
        e = np.concatenate(
            [
                self._gens[k].standard_normal((s.stop - s.start, 2))
                for k, s in self.line_slices.items()
            ]
        )
        w = _matvec(self._chol, e)
        z_new = self.z + self.mu * dt + math.sqrt(dt) * w
        due_t = np.minimum(self.tamping_due, self._next_sched)
        tamped, out = {}, []
        for i in np.flatnonzero(due_t <= t_new):
            t_m = max(float(due_t[i]), t_prev)
            cause = "limit" if self.tamping_due[i] <= self._next_sched[i] else "scheduled"
            self.epoch[i] += 1
            rng = self._event_rng("tamping", i)
            zp = self.z_plus[i] + self._chol_zp[i] @ rng.standard_normal(2)
            z_pre = self.z[i] + (t_m - t_prev) / self.step_s * (z_new[i] - self.z[i])
            age = (t_new - t_m) / DAY_S
            z_new[i] = zp + self.mu[i] * age + math.sqrt(age) * w[i]
            t_start = t_end = t_m
            if rng.random() < cfg.interval_fraction:
                span = rng.uniform(*cfg.interval_days) * DAY_S
                t_start = t_m - rng.random() * span
                t_end = t_start + span
            self.tamping_due[i] = np.inf
            while self._next_sched[i] <= t_new:
                self._next_sched[i] += cfg.scheduled_period_days * DAY_S
            tamped[int(i)] = (t_m, z_pre, zp)
            line, seg = self.keys[i]
            report, t_reported = self._report(int(i), t_end)
            out.append(
                Tamping(
                    *(int(i), line, seg, t_m, t_start, t_end, int(self.epoch[i]), cause),
                    *(z_pre, zp, report, t_reported),
                )
            )
        self.z, self.t = z_new, t_new
        self._history.append(_Step(t_prev, t_new, self._history[-1].z, z_new, tamped))
        self._schedule_crossings()
        return sorted(out, key=lambda tp: (tp.t, tp.seg))

    def advance_to(self, t: float) -> list[Tamping]:
        """Step until the current grid time reaches ``t``; returns the tampings on the way."""
        out = []
        while self.t < t:
            out.extend(self.step())
        return out

    def z_at(self, t, idx=None) -> np.ndarray:
        """The true state at times ``t`` (epoch s) of segments ``idx`` (default: all).

        ``t`` and ``idx`` broadcast; the result has their shape + (2,). Times must lie in
        the retained window ``(t - keep_steps * step, t]`` of the grid (or equal the start).
        """
        if idx is None:
            idx = np.arange(self.n_segments)
        t, idx = np.broadcast_arrays(np.asarray(t, dtype=np.float64), np.asarray(idx))
        shape, t, idx = t.shape, t.ravel(), idx.ravel()
        out = np.full((t.size, 2), np.nan)
        for st in self._history:
            rows = np.flatnonzero(((t > st.t_prev) & (t <= st.t)) | (t == st.t))
            if not rows.size:
                continue
            span = st.t - st.t_prev
            f = (t[rows] - st.t_prev) / span if span > 0 else np.ones(rows.size)
            i = idx[rows]
            out[rows] = st.z_prev[i] + f[:, None] * (st.z[i] - st.z_prev[i])
            for j in rows[np.isin(i, list(st.tamped))] if st.tamped else ():
                s = idx[j]
                t_m, z_pre, z_post = st.tamped[int(s)]
                if t[j] < t_m:  # on the untamped path
                    out[j] = st.z_prev[s] + (t[j] - st.t_prev) / (t_m - st.t_prev) * (
                        z_pre - st.z_prev[s]
                    )
                else:
                    g = (t[j] - t_m) / (st.t - t_m) if st.t > t_m else 1.0
                    out[j] = z_post + g * (st.z[s] - z_post)
        if np.isnan(out).any():
            raise ValueError(
                f"z_at: times outside the retained window "
                f"[{self._history[0].t_prev}, {self.t}] (advance_to first, or keep more steps)"
            )
        return out.reshape(shape + (2,))


def _matvec(A: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Row-wise ``A[s] @ x[s]`` for 2 x 2 matrices (faster than einsum at this size)."""
    return np.stack(
        [A[:, 0, 0] * x[:, 0] + A[:, 0, 1] * x[:, 1], A[:, 1, 0] * x[:, 0] + A[:, 1, 1] * x[:, 1]],
        axis=-1,
    )


def truth_events(
    network: Network,
    config,
    start_t: float,
    days: float,
    seed: int,
    *,
    truth: Truth | None = None,
    on_step: Callable[[Truth, list[Tamping]], None] | None = None,
) -> Iterator[tuple[float, list[MaintenanceEvent]]]:
    """Tamping MaintenanceEvents of ``days`` from ``start_t``, as ``(t, [events])`` in order.

    ``t`` is when the event is reported: the tamping time, or the interval's end for an
    interval-only report, plus the delay of a late report; an unreported tamping gives
    nothing (reports due after the simulated period are dropped).
    ``on_step(truth, tampings)`` is called with the initial state and after every grid
    step (the ground-truth hook). Pass ``truth`` to use a replica built elsewhere; it is
    advanced by this generator.
    """
    truth = truth if truth is not None else Truth(network, config, start_t, seed)
    end = start_t + days * DAY_S
    if on_step:
        on_step(truth, [])
    queue: list[tuple[float, int, MaintenanceEvent]] = []
    n = 0
    while truth.t < end:
        taps = truth.step()
        if on_step:
            on_step(truth, taps)
        for tp in taps:
            if tp.t_reported is not None:
                heapq.heappush(queue, (tp.t_reported, n, tp.message()))
                n += 1
        # Every later tamping happens after truth.t, so reports up to it are final.
        while queue and queue[0][0] <= min(truth.t, end):
            t = queue[0][0]
            batch = []
            while queue and queue[0][0] == t:
                batch.append(heapq.heappop(queue)[2])
            yield t, batch
