"""Correctness on simulated truth: the estimation pipeline against the truth.

Everything runs in-process on the pure cores (no Zenoh, no clock, deterministic for a seed),
in the simulator's fast mode (``fidelity="index"``) on the demo network (295 segments):

1. ``simulators.world.world_events`` → the :class:`~services.calibration.calibrator.Calibrator`
   core (TRC records, on-board indices, tampings). Its events are ingested one by one and its
   models flushed **once per simulated day** (at the first event of a new day; the service
   flushes once per queued batch), and the models that changed are given to the trackers.
   Both start from the deployed initial models (``services/defaults/initial-models.json5``, as
   ``services/defaults/stack.json5`` does).
2. Two :class:`~services.filtering.tracker.Tracker` cores: **fused** (TRC records, tampings,
   on-board indices, models) and **model alone** (the same minus every OnboardIndex). The
   SegmentStates of each go to an :class:`~services.alerting.core.AlertingCore` of its own
   (``services/defaults/alerting.json5`` defaults, ``services/defaults/limits.json5``);
   ``check_stale`` is called once per simulated day.
3. **TRC cut-off**: TRC records after ``--cutoff-days`` (default 120: the calibration
   campaign's first runs) are withheld from both trackers and the alerting, together with
   the OnboardIndex the TRC train itself produces on those runs (the run did not happen for
   the system). ``--calibrator-trc campaign`` (default) applies the same cut-off to the
   calibrator (it sees TRC records and the TRC train's indices up to the cut-off, in-service
   indices up to one pairing tolerance after it, and every tamping); ``all`` lets it see every
   TRC record of the year. Tampings always flow to everyone (a tamping restarts the filter
   from z+).

Figures (the truth is a :class:`simulators.truth.Truth` replica stepped alongside):

- **Coverage**: every ``--eval-every-days`` (default 1) at 00:00 of the simulation clock,
  after every event before that instant has been processed, each segment with a publishable
  state is predicted from its last event to that instant with the core's transition
  (``degradation.transition_unchecked``: ``z + mu dt``, ``P + Sigma dt`` per posterior
  sample, no tamping) and summarised with ``mixture.summarize`` with the state's mixture
  weights (``tracker.state_weights``, as published): the interval is the Gaussian
  mixture's **marginal equal-tailed 95 % credible interval in log space** (the 2.5 % and
  97.5 % quantiles of the exact mixture marginal), and it covers when it contains the true
  ``z_at(t)``. Counted per indicator over all (segment, time) points from day 30 on. The
  **effective sample size** ``1 / sum w_j^2`` of those weights is summarised over the same
  points (fused tracker; the model-alone tracker has no on-board data, so equal weights).
- **RMSE at 6 months**: for every segment, the evaluation instant nearest to
  ``--horizon-days`` (182.6) after its last TRC restart (within ±7 days), the mixture mean
  (log space) of fused and model-alone vs the true z; RMSE per indicator over segments, and
  the reduction ``1 - RMSE_fused / RMSE_alone``.
- **Crossings**: the truth's upward crossings of ln(intervention limit) (per line's speed
  class, ``services/limits.py``) by an indicator, found on the truth's daily grid with linear
  interpolation within a day (a tamping inside the day splits its path the way
  ``Truth.z_at`` does); crossings before day 30 are ignored. A crossing is **preceded** when,
  at the crossing instant, a ``predicted_exceedance`` or ``exceedance`` alert of the
  intervention level for that segment and indicator is raised (emitted at or before the
  crossing and not cleared in between). The lead time is the crossing time minus the time
  the pipeline emitted the raise (the world clock when it happened, which for a state
  re-run after a model update is later than the state's own time). A looser variant
  ("any such raise within the 90 days before") is reported alongside, and every missed
  crossing is printed.
- **False alarms**: raises of those alerts that the truth does not bear out within the
  predicted-exceedance horizon (``within_days``, 90): see :func:`_false_alarms`.

Sharding: segments are independent given the models, so ``--workers`` processes each run the
whole world stream and calibrator (cheap) and the trackers, alerting and evaluation of every
``workers``-th segment; the figures are computed on the union. ``--subsample N`` keeps only
every N-th segment (smoke tests).

Run: ``.venv/bin/python -m bench.correctness [--quick] [--json]``.
"""

from __future__ import annotations

import argparse
import json
import math
import multiprocessing
import sys
import time
from collections import defaultdict
from dataclasses import asdict, dataclass, replace
from datetime import UTC, datetime
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from schemas import DAY_S, INDICATORS, MaintenanceEvent, OnboardIndex, TrcRecord
from services.alerting.core import AlertingCore, Hysteresis
from services.alerting.service import load_alerting_config
from services.calibration.calibrator import Calibrator
from services.calibration.config import CalibratorConfig
from services.calibration.service import load_initial_models
from services.defaults import default_file, demo_network
from services.filtering.degradation import transition_unchecked
from services.filtering.events import TAMPING, tamping_time
from services.filtering.mixture import effective_sample_size, summarize
from services.filtering.summary import state_weights
from services.filtering.tracker import Tracker
from services.limits import load_limits
from simulators.fleet import MIXED
from simulators.truth import Truth, load_config
from simulators.world import WorldSpec, world_events

START_T = 1_767_225_600.0  # 2026-01-01T00:00Z
ROOT = Path(__file__).resolve().parents[1]
INITIAL_MODELS = default_file("initial-models.json5")
ALERTING_CONFIG = default_file("alerting.json5")
TRC_TRAIN = "TRC"
ALERT_KINDS = ("predicted_exceedance", "exceedance")
LEVEL = "intervention"
TRACKERS = ("fused", "alone")

TARGETS = {
    "coverage": (0.90, 0.98),
    "rmse_reduction": 0.30,
    "crossings_preceded": 0.95,
}


@dataclass(frozen=True)
class Settings:
    days: float = 365.0
    seed: int = 1
    trains: int = 2  # service passes per line per day
    samples: int = 200  # Ns
    cutoff_days: float = 120.0
    calibrator_trc: str = "campaign"  # "campaign" | "all"
    horizon_days: float = 182.625  # 6 months
    horizon_tol_days: float = 7.0
    eval_every_days: float = 1.0
    ignore_before_days: float = 30.0
    lookback_days: float = 90.0  # the loose "preceded" variant
    workers: int = 2
    subsample: int = 1
    segments: tuple[int, ...] = ()  # only these segment positions (diagnostics)
    predicted_raise: float | None = None  # override alerting.json5's predicted raise (study)
    unreported: float = 0.0  # share of tampings never reported (maintenance.unreported_fraction)
    late: float = 0.0  # share of reported tampings reported late (maintenance.late_fraction)
    fleet: str = "uniform"  # "uniform": one sensor model; "mixed": simulators.fleet.MIXED
    detect: bool = True  # the trackers look for unreported tampings (Tracker.detect_maintenance)
    unit_models: bool = True  # calibration fits each unit's own model (CalibratorConfig)


def world_config(st: Settings) -> dict:
    """The simulator config with the run's unkind-world options."""
    config = load_config()
    config["maintenance"].update(unreported_fraction=st.unreported, late_fraction=st.late)
    if st.fleet == "mixed":
        config["fleet"] = MIXED
    return config


# --- one shard ---------------------------------------------------------------------------


def _visible_to_trackers(msg, cutoff_t: float) -> bool:
    if isinstance(msg, TrcRecord):
        return msg.t <= cutoff_t
    if isinstance(msg, OnboardIndex) and msg.train == TRC_TRAIN:
        return msg.t <= cutoff_t
    return True


def _visible_to_calibrator(msg, cutoff_t: float, mode: str, tol_s: float) -> bool:
    if mode == "all" or isinstance(msg, MaintenanceEvent):
        return True
    if isinstance(msg, OnboardIndex) and msg.train != TRC_TRAIN:
        return msg.t <= cutoff_t + tol_s
    return msg.t <= cutoff_t


class _Crossings:
    """Upward crossings of ln(limit) by the truth, stepped one grid day at a time."""

    def __init__(self, truth: Truth, log_limits: np.ndarray, own: np.ndarray):
        self.truth, self.log_limits, self.own = truth, log_limits, own
        self.found: list[tuple[int, int, float]] = []  # (seg, indicator, t)
        self.tampings: list[tuple[int, float, float]] = []  # (seg, true t, reported at)

    def _scan(self, z0, z1, t0, t1, rows) -> None:
        lim = self.log_limits[rows]
        up = (z0 <= lim) & (z1 > lim)
        for r, i in zip(*np.nonzero(up), strict=True):
            f = (lim[r, i] - z0[r, i]) / (z1[r, i] - z0[r, i])
            t = t0[r] + f * (t1[r] - t0[r]) if np.ndim(t0) else t0 + f * (t1 - t0)
            self.found.append((int(rows[r]), int(i), float(t)))

    def advance_to(self, t: float) -> None:
        truth = self.truth
        while truth.t < t:
            z_prev, t_prev = truth.z.copy(), truth.t
            taps = truth.step()
            tamped = {tp.seg: tp for tp in taps}
            for tp in taps:  # reported at: inf if never
                reported = math.inf if tp.t_reported is None else tp.t_reported
                self.tampings.append((tp.seg, tp.t, reported))
            plain = np.array([s for s in self.own if s not in tamped], dtype=int)
            self._scan(z_prev[plain], truth.z[plain], t_prev, truth.t, plain)
            for s, tp in tamped.items():
                if s not in self.own_set:
                    continue
                row = np.array([s])
                self._scan(z_prev[row], tp.z_before[None], t_prev, tp.t, row)
                self._scan(tp.z_after[None], truth.z[row], tp.t, truth.t, row)

    @property
    def own_set(self) -> set[int]:
        if not hasattr(self, "_own_set"):
            self._own_set = set(self.own.tolist())
        return self._own_set


def _evaluate(tracker: Tracker, sids, t_e: float):
    """(rows, mean, lo, hi, trc_t, state_t, ess) of the publishable states of ``sids`` at ``t_e``.

    The mixture is weighted as the tracker publishes it (``tracker.state_weights``); ``ess``
    is the effective sample size of those weights.
    """
    rows, z, P, mu, sigma, trc_t, state_t, w = [], [], [], [], [], [], [], []
    for row, sid in sids:
        hist = tracker.histories.get(sid)
        if hist is None or hist.state is None or hist.group is None:
            continue
        params = tracker.models.params[hist.group]
        rows.append(row)
        z.append(hist.state.z)
        P.append(hist.state.P)
        mu.append(params.mu)
        sigma.append(params.sigma)
        trc_t.append(np.nan if hist.trc_t is None else hist.trc_t)
        state_t.append(hist.state.t_s)
        w.append(state_weights(hist.state))
    if not rows:
        return None
    params = SimpleNamespace(mu=np.stack(mu), sigma=np.stack(sigma))
    dt = (t_e - np.array(state_t)) / DAY_S
    zp, Pp = transition_unchecked(np.stack(z), np.stack(P), params, np.maximum(dt, 0.0))
    w = np.stack(w)
    s = summarize(zp, Pp, weights=w)
    ess = effective_sample_size(w)
    return np.array(rows), s.mean, s.ci_low, s.ci_high, np.array(trc_t), np.array(state_t), ess


def run_shard(settings: Settings, shard: int, n_shards: int) -> dict:
    """Run the pipeline on every ``n_shards``-th segment (from ``shard``); raw records."""
    st = settings
    network = demo_network()
    config = world_config(st)
    limits = load_limits()
    spec = WorldSpec(network, config, START_T, st.days, st.seed, st.trains, fidelity="index")
    keys = [(line.id, seg.id) for line, seg in network.segments()]
    stride = n_shards * st.subsample
    own = np.arange(shard * st.subsample, len(keys), stride)
    if st.segments:
        own = np.array([i for i in own if i in set(st.segments)], dtype=int)
    own_keys = {keys[i]: int(i) for i in own}
    sids = [(int(i), keys[i]) for i in own]
    level_i = limits.levels.index(LEVEL)
    log_limits = np.log(np.stack([limits.for_line(line)[level_i] for line, _ in keys]))
    cutoff_t = START_T + st.cutoff_days * DAY_S

    cal_config = CalibratorConfig(samples=st.samples, seed=st.seed, unit_models=st.unit_models)
    tol_s = (cal_config.tolerance_days or 0.0) * DAY_S
    calibrator = Calibrator(cal_config)
    cal0, posts0 = load_initial_models(INITIAL_MODELS, cal_config)
    first_models = calibrator.install_initial(cal0, posts0)
    alert_cfg = load_alerting_config(ALERTING_CONFIG)
    if st.predicted_raise is not None:  # clear at 0.6 x raise, the shipped thresholds' ratio
        clear = 0.6 * st.predicted_raise
        alert_cfg = replace(alert_cfg, predicted=Hysteresis(st.predicted_raise, clear))
    trackers = {
        name: Tracker(limits.for_line, limits.levels, detect_maintenance=st.detect)
        for name in TRACKERS
    }
    detections: list[tuple[int, float, float, float]] = []  # (seg, t_start, t_end, emitted)
    alerting = {name: AlertingCore(alert_cfg, limits) for name in TRACKERS}
    alerts: dict[str, list[tuple]] = {name: [] for name in TRACKERS}
    n_states = dict.fromkeys(TRACKERS, 0)
    truth = _Crossings(Truth(network, config, START_T, st.seed), log_limits, own)
    last_tamp_t = np.full(len(keys), np.nan)
    evals: dict[str, list] = {name: [] for name in TRACKERS}
    counts: dict[str, int] = defaultdict(int)
    published: list[tuple[float, str]] = []  # (event time, kind) of each model flushed
    timing = defaultdict(float)

    def feed(name: str, msg, now: float) -> None:
        step = trackers[name].step(msg)
        if name == "fused":
            for d in step.detected:
                detections.append((own_keys[(d.line, d.segment)], d.t_start, d.t_end, now))
        for state in step.states:
            n_states[name] += 1
            for a in alerting[name].on_state(state):
                alerts[name].append(
                    (a.line, a.segment, a.kind, a.indicator, a.level, a.status, now, a.t)
                )

    def publish_models(models, now: float) -> None:
        for m in models:
            counts[f"models_{type(m).__name__}"] += 1
            for name in TRACKERS:
                feed(name, m, now)

    def evaluate(t_e: float) -> None:
        t0 = time.perf_counter()
        truth.advance_to(t_e)
        for name in TRACKERS:
            got = _evaluate(trackers[name], sids, t_e)
            if got is None:
                continue
            rows, mean, lo, hi, trc_t, state_t, ess = got
            z_true = truth.truth.z_at(t_e, rows)
            evals[name].append((np.full(len(rows), t_e), rows, mean, lo, hi, z_true, trc_t, ess))
        timing["evaluate_s"] += time.perf_counter() - t0

    publish_models(first_models, START_T)
    next_eval = START_T + st.eval_every_days * DAY_S
    day = -1
    t_start = time.perf_counter()
    for t, msgs in world_events(spec):
        while next_eval <= t:
            evaluate(next_eval)
            next_eval += st.eval_every_days * DAY_S
        d = int((t - START_T) // DAY_S)
        if d != day:
            day = d
            t0 = time.perf_counter()
            models = calibrator.flush()
            published.extend((t, type(m).__name__) for m in models)
            timing["calibrator_s"] += time.perf_counter() - t0
            publish_models(models, t)
            for name in TRACKERS:
                for a in alerting[name].check_stale(t):
                    alerts[name].append(
                        (a.line, a.segment, a.kind, a.indicator, a.level, a.status, t, a.t)
                    )
        for msg in msgs:
            if _visible_to_calibrator(msg, cutoff_t, st.calibrator_trc, tol_s):
                t0 = time.perf_counter()
                calibrator.ingest(msg)
                timing["calibrator_s"] += time.perf_counter() - t0
            sid = (msg.line, msg.segment)
            if sid not in own_keys:
                continue
            if not _visible_to_trackers(msg, cutoff_t):
                counts["withheld_" + type(msg).__name__] += 1
                continue
            counts[type(msg).__name__] += 1
            if isinstance(msg, MaintenanceEvent):
                last_tamp_t[own_keys[sid]] = tamping_time(msg)
            if isinstance(msg, TrcRecord):
                for name in TRACKERS:
                    alerting[name].on_trc(msg)
            t0 = time.perf_counter()
            feed("fused", msg, t)
            timing["fused_s"] += time.perf_counter() - t0
            if not isinstance(msg, OnboardIndex):
                t0 = time.perf_counter()
                feed("alone", msg, t)
                timing["alone_s"] += time.perf_counter() - t0
    end = START_T + st.days * DAY_S
    while next_eval <= end:
        evaluate(next_eval)
        next_eval += st.eval_every_days * DAY_S
    truth.advance_to(end)
    timing["shard_s"] = time.perf_counter() - t_start

    def cat(name: str, k: int) -> np.ndarray:
        parts = [e[k] for e in evals[name]]
        return np.concatenate(parts) if parts else np.zeros((0, 2) if k in (2, 3, 4, 5) else 0)

    return {
        "evals": {
            name: {
                f: cat(name, k)
                for k, f in enumerate(("t", "seg", "mean", "lo", "hi", "z", "trc_t", "ess"))
            }
            for name in TRACKERS
        },
        "alerts": alerts,
        "crossings": truth.found,
        "tampings": [tp for tp in truth.tampings if tp[0] in truth.own_set],
        "detections": detections,
        "last_tamp_t": {int(i): float(last_tamp_t[i]) for i in own},
        "tamp_times": _tamp_times(trackers["fused"], own_keys),
        "keys": keys,
        "own": own.tolist(),
        "counts": dict(counts),
        "n_states": n_states,
        "timing": dict(timing),
        "calibration": _calibration_summary(calibrator),
        "published": published,
        "stale_alerts": {
            name: sum(1 for a in alerts[name] if a[2] == "stale" and a[5] == "raised")
            for name in TRACKERS
        },
    }


def _tamp_times(tracker: Tracker, own_keys: dict) -> dict[int, list[float]]:
    """Assumed tamping times of the events still in each segment history's log (diagnostics)."""
    out: dict[int, list[float]] = {}
    for sid, hist in tracker.histories.items():
        out[own_keys[sid]] = [e.t_s for e in hist.log if e.kind == TAMPING]
    return out


def _calibration_summary(cal: Calibrator) -> dict:
    c = cal.calibration
    out: dict = {"stats": dict(cal.stats)}
    if c is not None:
        out.update(
            version=c.version,
            n_pairs=c.n_pairs,
            H=c.H.array().round(4).tolist(),
            b=c.b.array().round(4).tolist(),
            R=c.R.array().round(5).tolist(),
            r2=c.r2.array().round(3).tolist(),
        )
    out["posteriors"] = {
        g: {"version": p.version, "n_increments": p.n_increments, "n_levels": p.n_levels}
        for g, p in cal.posteriors.items()
    }
    return out


# --- figures -----------------------------------------------------------------------------


def _merge(shards: list[dict]) -> dict:
    out = {"evals": {}, "alerts": {}}
    for name in TRACKERS:
        out["evals"][name] = {
            f: np.concatenate([s["evals"][name][f] for s in shards])
            for f in shards[0]["evals"][name]
        }
        out["alerts"][name] = [a for s in shards for a in s["alerts"][name]]
    for k in ("crossings", "tampings", "detections"):
        out[k] = [x for s in shards for x in s[k]]
    out["last_tamp_t"] = {k: v for s in shards for k, v in s["last_tamp_t"].items()}
    out["keys"] = shards[0]["keys"]
    out["own"] = sorted(i for s in shards for i in s["own"])
    out["calibration"] = shards[0]["calibration"]
    out["published"] = shards[0]["published"]  # every shard runs the same calibrator
    for k in ("counts", "n_states", "stale_alerts"):
        acc: dict = defaultdict(int)
        for s in shards:
            for kk, v in s[k].items():
                acc[kk] += v
        out[k] = dict(acc)
    out["timing"] = [s["timing"] for s in shards]
    return out


def _coverage(ev: dict, since_t: float, mask=None) -> list[float]:
    keep = ev["t"] >= since_t
    if mask is not None:
        keep &= mask
    inside = (ev["z"] >= ev["lo"]) & (ev["z"] <= ev["hi"])
    return [float(inside[keep, i].mean()) if keep.any() else math.nan for i in range(2)]


def _unreported_tamping_mask(ev: dict, tampings) -> np.ndarray:
    """True where the truth was tamped before ``t`` but the report came after ``t``."""
    bad = np.zeros(len(ev["t"]), dtype=bool)
    for seg, t_true, t_rep in tampings:
        if t_rep > t_true:
            bad |= (ev["seg"] == seg) & (ev["t"] > t_true) & (ev["t"] < t_rep)
    return bad


def _rmse_at_horizon(merged: dict, st: Settings) -> dict:
    f, a = merged["evals"]["fused"], merged["evals"]["alone"]
    target = st.horizon_days

    def pick(ev):
        age = (ev["t"] - ev["trc_t"]) / DAY_S
        ok = np.isfinite(age) & (np.abs(age - target) <= st.horizon_tol_days)
        best: dict[tuple[int, float], int] = {}
        for j in np.flatnonzero(ok):
            k = (int(ev["seg"][j]), float(ev["trc_t"][j]))
            if k not in best or abs(age[j] - target) < abs(age[best[k]] - target):
                best[k] = j
        return best

    bf, ba = pick(f), pick(a)
    common = sorted(set(bf) & set(ba))
    if not common:
        return {"n": 0}
    jf = np.array([bf[k] for k in common])
    ja = np.array([ba[k] for k in common])
    same_t = bool(np.all(f["t"][jf] == a["t"][ja]))
    ef = f["mean"][jf] - f["z"][jf]
    ea = a["mean"][ja] - a["z"][ja]
    tamped = np.array(
        [
            np.isfinite(merged["last_tamp_t"].get(seg, np.nan))
            and merged["last_tamp_t"][seg] > trc_t
            for seg, trc_t in common
        ]
    )

    def rm(e, m):
        return [float(np.sqrt(np.mean(e[m, i] ** 2))) if m.any() else math.nan for i in range(2)]

    all_ = np.ones(len(common), dtype=bool)
    rf, ra = rm(ef, all_), rm(ea, all_)
    return {
        "n": len(common),
        "n_tamped_since_trc": int(tamped.sum()),
        "same_times": same_t,
        "fused": rf,
        "alone": ra,
        "reduction": [1 - x / y if y > 0 else math.nan for x, y in zip(rf, ra, strict=True)],
        "bias_fused": [float(ef[:, i].mean()) for i in range(2)],
        "bias_alone": [float(ea[:, i].mean()) for i in range(2)],
        "untamped_fused": rm(ef, ~tamped),
        "untamped_alone": rm(ea, ~tamped),
        "coverage_at_horizon_fused": _coverage(_sub(f, jf), -math.inf),
        "coverage_at_horizon_alone": _coverage(_sub(a, ja), -math.inf),
    }


def _sub(ev: dict, j) -> dict:
    return {k: v[j] for k, v in ev.items()}


def _crossing_figures(merged: dict, alerts: list[tuple], st: Settings) -> dict:
    keys = merged["keys"]
    since = START_T + st.ignore_before_days * DAY_S
    episodes: dict[tuple, list[list[float]]] = defaultdict(list)  # (seg, ind) -> [[raise, clear]]
    for line, segment, kind, indicator, level, status, now, _t in alerts:
        if kind not in ALERT_KINDS or level != LEVEL:
            continue
        k = (line, segment, indicator, kind)
        if status == "raised":
            episodes[k].append([now, math.inf])
        elif episodes[k]:
            episodes[k][-1][1] = now
    n, strict, loose, leads, detail = 0, 0, 0, [], []
    by_line: dict[str, list[int]] = defaultdict(lambda: [0, 0])
    for seg, ind, t in merged["crossings"]:
        if t < since:
            continue
        line, segment = keys[seg]
        n += 1
        by_line[line][0] += 1
        active, recent = [], []
        for kind in ALERT_KINDS:
            for r, c in episodes.get((line, segment, INDICATORS[ind], kind), []):
                if r <= t < c or (r <= t and c == t):
                    active.append(r)
                if t - st.lookback_days * DAY_S <= r <= t:
                    recent.append(r)
        lead = (t - min(active)) / DAY_S if active else None
        if active:
            strict += 1
            by_line[line][1] += 1
            leads.append(lead)
        if recent:
            loose += 1
        later = [
            r
            for kind in ALERT_KINDS
            for r, _ in episodes.get((line, segment, INDICATORS[ind], kind), [])
            if r > t
        ]
        detail.append(
            {
                "line": line,
                "segment": segment,
                "indicator": INDICATORS[ind],
                "day": (t - START_T) / DAY_S,
                "lead_days": lead,
                "first_raise_after_days": (min(later) - t) / DAY_S if later else None,
            }
        )
    return {
        "n": n,
        "preceded": strict,
        "share": strict / n if n else math.nan,
        "share_loose": loose / n if n else math.nan,
        "median_lead_days": float(np.median(leads)) if leads else math.nan,
        "by_line": {k: {"crossings": v[0], "preceded": v[1]} for k, v in sorted(by_line.items())},
        "detail": sorted(detail, key=lambda d: (d["line"], d["segment"], d["day"])),
    }


def _ess_figures(ev: dict, since: float, ns: int) -> dict:
    """Effective sample size of the mixture weights over the evaluation points from ``since``."""
    ess = ev["ess"][ev["t"] >= since]
    if not ess.size:
        return {"n": 0}
    p1, p5, p50 = np.percentile(ess, [1, 5, 50])
    return {
        "n": int(ess.size),
        "ns": ns,
        "min": float(ess.min()),
        "p1": float(p1),
        "p5": float(p5),
        "median": float(p50),
        "mean": float(ess.mean()),
        "share_below_10": float((ess < 10).mean()),
        "share_below_2": float((ess < 2).mean()),
    }


def _false_alarms(merged: dict, alerts: list[tuple], st: Settings, within_days: float) -> dict:
    """Raises of intervention-level alerts the truth does not bear out within ``within_days``.

    A raise (``predicted_exceedance`` or ``exceedance``, intervention level, per indicator)
    emitted at ``r`` is **true** when the truth is above the intervention limit at some
    instant of ``[r, r + within_days]``: an upward crossing in that window, or the truth above
    the limit at an evaluation instant in ``[r - eval_every_days, r + within_days]`` (it was
    already above). Otherwise it is **false** if ``r + within_days`` is within the run, and
    **open** (not decidable) if the window runs past the end. ``false_tamped``: false raises
    whose segment the truth tamped within the window (maintenance came first; the simulator
    tamps ``delay_days`` after an alert-limit exceedance, below some lines' intervention
    limits).
    """
    keys = merged["keys"]
    seg_of = {k: i for i, k in enumerate(keys)}
    limits = load_limits()
    level_i = limits.levels.index(LEVEL)
    log_lim = {line: np.log(limits.for_line(line)[level_i]) for line, _ in keys}
    end = START_T + st.days * DAY_S
    h = within_days * DAY_S
    crossings: dict[tuple[int, int], list[float]] = defaultdict(list)
    for seg, ind, t in merged["crossings"]:
        crossings[(seg, ind)].append(t)
    tamped: dict[int, list[float]] = defaultdict(list)
    for seg, t_true, _t_reported in merged["tampings"]:
        tamped[seg].append(t_true)
    ev = merged["evals"]["fused"]
    above_t: dict[tuple[int, int], np.ndarray] = {}
    seg_lim = np.stack([log_lim[keys[int(g)][0]] for g in ev["seg"]]) if len(ev["seg"]) else None
    for i in range(len(INDICATORS)):
        if seg_lim is None:
            break
        hit = ev["z"][:, i] > seg_lim[:, i]
        for g in np.unique(ev["seg"][hit]):
            sel = hit & (ev["seg"] == g)
            above_t[(int(g), i)] = np.sort(ev["t"][sel])
    out: dict = {"within_days": within_days}
    for kind in ALERT_KINDS:
        n = true = false = open_ = false_tamped = 0
        false_segments: set[int] = set()
        for line, segment, k, indicator, level, status, now, _t in alerts:
            if k != kind or level != LEVEL or status != "raised" or now < START_T:
                continue
            n += 1
            g, i = seg_of[(line, segment)], INDICATORS.index(indicator)
            crossed = any(now <= c <= now + h for c in crossings.get((g, i), ()))
            at = above_t.get((g, i), np.zeros(0))
            above = bool(((at >= now - st.eval_every_days * DAY_S) & (at <= now + h)).any())
            if crossed or above:
                true += 1
            elif now + h > end:
                open_ += 1
            else:
                false += 1
                false_segments.add(g)
                false_tamped += any(now <= tp <= now + h for tp in tamped.get(g, ()))
        out[kind] = {
            "raised": n,
            "true": true,
            "false": false,
            "open": open_,
            "false_segments": len(false_segments),
            "false_tamped": false_tamped,
        }
    return out


def figures(merged: dict, st: Settings) -> dict:
    since = START_T + st.ignore_before_days * DAY_S
    out: dict = {"settings": asdict(st)}
    alert_cfg = load_alerting_config(ALERTING_CONFIG)
    for name in TRACKERS:
        ev = merged["evals"][name]
        bad = _unreported_tamping_mask(ev, merged["tampings"])
        keep = ev["t"] >= since
        out[f"coverage_{name}"] = _coverage(ev, since)
        out[f"coverage_{name}_known_tampings"] = _coverage(ev, since, ~bad)
        out[f"n_eval_{name}"] = int(keep.sum())
        out[f"n_eval_{name}_unreported_tamping"] = int((keep & bad).sum())
        after = keep & (ev["t"] > START_T + st.cutoff_days * DAY_S)
        out[f"coverage_{name}_after_cutoff"] = _coverage(ev, -math.inf, after)
        out[f"crossings_{name}"] = _crossing_figures(merged, merged["alerts"][name], st)
        out[f"false_alarms_{name}"] = _false_alarms(
            merged, merged["alerts"][name], st, alert_cfg.predicted_within_days
        )
        out[f"ess_{name}"] = _ess_figures(ev, since, st.samples)
    out["rmse"] = _rmse_at_horizon(merged, st)
    out["detection"] = _detection_figures(merged, st)
    out["calibration"] = merged["calibration"]
    out["counts"] = merged["counts"]
    out["versions_per_month"] = _versions_per_month(merged["published"])
    out["n_states"] = merged["n_states"]
    out["stale_alerts"] = merged["stale_alerts"]
    out["n_segments"] = len(merged["own"])
    out["n_tampings"] = len(merged["tampings"])
    out["timing"] = merged["timing"]
    return out


DETECT_TOL_S = DAY_S  # a detection matches a true tamping within a day of its interval


def _detection_figures(merged: dict, st: Settings) -> dict:
    """Detected maintenance against the truth's tampings of the evaluated segments.

    A detection ``[t_a, t_b]`` matches a true tamping of its segment at ``t`` when
    ``t_a - 1 d <= t <= t_b + 1 d``. Recall counts the tampings never reported (and,
    separately, those reported late) that happened at least 30 days before the end; the
    delay is from the true time to when the pipeline emitted the detection; a detection
    that matches no true tamping is false, counted per 1,000 segment-years.
    """
    end = START_T + st.days * DAY_S
    found = defaultdict(list)
    for seg, t_a, t_b, emitted in merged["detections"]:
        found[seg].append((t_a, t_b, emitted))
    true_t = defaultdict(list)
    for seg, t, _reported in merged["tampings"]:
        true_t[seg].append(t)

    def match(seg: int, t: float):
        hits = [e for a, b, e in found[seg] if a - DETECT_TOL_S <= t <= b + DETECT_TOL_S]
        return min(hits) if hits else None

    out: dict = {"n_detections": len(merged["detections"])}
    for label, pick in (
        ("unreported", lambda t, rep: math.isinf(rep)),
        ("late", lambda t, rep: math.isfinite(rep) and rep > t + DAY_S),
    ):
        cases = [
            (seg, t) for seg, t, rep in merged["tampings"] if pick(t, rep) and t < end - 30 * DAY_S
        ]
        delays = [(e - t) / DAY_S for seg, t in cases if (e := match(seg, t)) is not None]
        out[label] = {
            "n": len(cases),
            "detected": len(delays),
            "recall": len(delays) / len(cases) if cases else math.nan,
            "median_delay_days": float(np.median(delays)) if delays else math.nan,
            "p90_delay_days": float(np.percentile(delays, 90)) if delays else math.nan,
        }
    false = sum(
        1
        for seg, t_a, t_b, _ in merged["detections"]
        if not any(t_a - DETECT_TOL_S <= t <= t_b + DETECT_TOL_S for t in true_t[seg])
    )
    segment_years = len(merged["own"]) * st.days / 365.25
    out["false"] = false
    out["false_per_1000_segment_years"] = 1000 * false / segment_years if segment_years else 0
    return out


def _versions_per_month(published: list[tuple[float, str]]) -> dict[str, list[int]]:
    """Versions the calibrator published (after the initial models) per simulated calendar
    month: ``{"YYYY-MM": [Calibration, DegradationPosterior]}``."""
    out: dict[str, list[int]] = {}
    for t, kind in published:
        month = datetime.fromtimestamp(t, UTC).strftime("%Y-%m")
        out.setdefault(month, [0, 0])[kind != "Calibration"] += 1
    return dict(sorted(out.items()))


def checks(fig: dict) -> list[tuple[str, str, str, bool | None]]:
    """(figure, value, target, pass) rows of the table."""
    lo, hi = TARGETS["coverage"]
    rows = []
    for i, ind in enumerate(INDICATORS):
        c = fig["coverage_fused"][i]
        rows.append(
            (f"coverage 95% CI, fused, {ind}", f"{c:.3f}", f"{lo:.2f}-{hi:.2f}", lo <= c <= hi)
        )
    r = fig["rmse"]
    h = fig["settings"]["horizon_days"]
    for i, ind in enumerate(INDICATORS):
        if r.get("n"):
            red = r["reduction"][i]
            value = f"{r['fused'][i]:.4f} vs {r['alone'][i]:.4f} ({-100 * red:+.0f}%)"
            ok = red >= TARGETS["rmse_reduction"]
        else:
            value, ok = "no horizon reached", None
        rows.append(
            (
                f"RMSE ln at {h:g} d after TRC, fused vs alone, {ind}",
                value,
                f">= {100 * TARGETS['rmse_reduction']:.0f}% lower",
                ok,
            )
        )
    c = fig["crossings_fused"]
    if c["n"]:
        value = f"{c['preceded']}/{c['n']} = {c['share']:.3f}"
        ok = c["share"] >= TARGETS["crossings_preceded"]
    else:
        value, ok = "no crossings", None
    rows.append(
        ("intervention crossings preceded by an alert", value, ">= 0.95", ok),
    )
    rows.append(("median lead time (days)", f"{c['median_lead_days']:.1f}", "reported", None))
    return rows


def _table(fig: dict) -> str:
    rows = checks(fig)
    w = max(len(r[0]) for r in rows)
    v = max(len(r[1]) for r in rows)
    lines = [f"{'figure':<{w}}  {'value':<{v}}  {'target':<14}  result"]
    for name, value, target, ok in rows:
        res = "-" if ok is None else ("PASS" if ok else "FAIL")
        lines.append(f"{name:<{w}}  {value:<{v}}  {target:<14}  {res}")
    r = fig["rmse"]
    ca = fig["crossings_alone"]
    extra = [
        "",
        f"model alone: coverage {_fmt(fig['coverage_alone'])}, crossings preceded "
        f"{ca['preceded']}/{ca['n']}",
        "coverage without unreported tampings: fused "
        f"{_fmt(fig['coverage_fused_known_tampings'])}, alone "
        f"{_fmt(fig['coverage_alone_known_tampings'])}; after the TRC cut-off: fused "
        f"{_fmt(fig['coverage_fused_after_cutoff'])}, alone "
        f"{_fmt(fig['coverage_alone_after_cutoff'])}",
        f"crossings by line: {fig['crossings_fused']['by_line']}; "
        f"loose share (raise within 90 d before): {fig['crossings_fused']['share_loose']:.3f}",
    ]
    if r.get("n"):
        extra.append(
            f"RMSE horizon: {r['n']} segments ({r['n_tamped_since_trc']} tamped since the TRC "
            f"record); bias fused {_fmt(r['bias_fused'])}, alone {_fmt(r['bias_alone'])}; "
            f"coverage there fused {_fmt(r['coverage_at_horizon_fused'])}, alone "
            f"{_fmt(r['coverage_at_horizon_alone'])}"
        )
    e = fig["ess_fused"]
    if e.get("n"):
        extra.append(
            f"mixture weights (fused), effective sample size of Ns={e['ns']}: median "
            f"{e['median']:.1f}, p5 {e['p5']:.1f}, p1 {e['p1']:.1f}, min {e['min']:.2f}; "
            f"share < 10: {e['share_below_10']:.3f}, < 2: {e['share_below_2']:.3f}"
        )
    fa = fig["false_alarms_fused"]
    extra.append(
        f"intervention raises not followed by the truth above the limit within "
        f"{fa['within_days']:g} d (fused): "
        + "; ".join(
            f"{k} {v['false']} false / {v['raised']} raised ({v['true']} true, {v['open']} "
            f"open at the end; false: {v['false_segments']} segments, {v['false_tamped']} "
            f"tamped within the window)"
            for k, v in fa.items()
            if k != "within_days"
        )
    )
    missed = [d for d in fig["crossings_fused"]["detail"] if d["lead_days"] is None]
    for d in missed:
        after = d["first_raise_after_days"]
        extra.append(
            f"  missed crossing: {d['line']}/{d['segment']} {d['indicator']} day "
            f"{d['day']:.2f}, first raise " + ("never" if after is None else f"{after:.2f} d after")
        )
    vm = fig["versions_per_month"]
    extra.append(
        "model versions published per simulated month (Calibration / posteriors; the core is "
        "flushed once a day): "
        + ", ".join(f"{m} {c}/{p}" for m, (c, p) in vm.items())
        + f"; total {sum(c for c, _ in vm.values())}/{sum(p for _, p in vm.values())}"
    )
    s = fig["settings"]
    extra.append(
        f"size: {s['days']:g} days, {fig['n_segments']} segments, {s['trains']} passes/line/day, "
        f"Ns={s['samples']}, TRC cut-off day {s['cutoff_days']:g} (calibrator: "
        f"{s['calibrator_trc']}), {fig['n_tampings']} tampings, seed {s['seed']}"
    )
    d = fig["detection"]
    extra.append(
        f"units' own models {'on' if s['unit_models'] else 'off'}; "
        f"detected maintenance ({'on' if s['detect'] else 'off'}): {d['n_detections']} "
        f"detections, {d['false']} false ({d['false_per_1000_segment_years']:.1f} per 1,000 "
        "segment-years); "
        + "; ".join(
            f"{k} tampings {d[k]['detected']}/{d[k]['n']} detected, median delay "
            f"{d[k]['median_delay_days']:.1f} d (p90 {d[k]['p90_delay_days']:.1f})"
            for k in ("unreported", "late")
        )
    )
    extra.append(
        f"world: {s['unreported']:.0%} of tampings unreported, {s['late']:.0%} of the reported "
        f"late, {s['fleet']} fleet"
    )
    return "\n".join(lines + extra)


def _fmt(xs) -> str:
    return "[" + ", ".join(f"{x:.3f}" for x in xs) + "]"


def _run(st: Settings) -> list[dict]:
    n = max(1, st.workers)
    if n == 1:
        return [run_shard(st, 0, 1)]
    ctx = multiprocessing.get_context("spawn")
    with ctx.Pool(n) as pool:
        return pool.starmap(run_shard, [(st, k, n) for k in range(n)])


def run(st: Settings) -> dict:
    t0 = time.perf_counter()
    fig = figures(_merge(_run(st)), st)
    fig["wall_s"] = time.perf_counter() - t0
    return fig


def parse_args(argv=None) -> tuple[Settings, argparse.Namespace]:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--days", type=float, default=None, help="simulated days (365; quick 120)")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--trains-per-line-per-day", type=int, default=None, help="2 (quick 1)")
    p.add_argument("--samples", type=int, default=None, help="posterior samples Ns (200)")
    p.add_argument("--cutoff-days", type=float, default=None, help="TRC cut-off (120)")
    p.add_argument("--calibrator-trc", choices=("campaign", "all"), default="campaign")
    p.add_argument("--horizon-days", type=float, default=None, help="RMSE horizon (182.6)")
    p.add_argument("--eval-every-days", type=float, default=None, help="1 (quick 3)")
    p.add_argument("--workers", type=int, default=None, help="processes (2; quick 1)")
    p.add_argument("--subsample", type=int, default=None, help="every N-th segment (1)")
    p.add_argument("--segments", default="", help="only these positions, e.g. 130,131")
    p.add_argument(
        "--predicted-raise",
        type=float,
        default=None,
        help="predicted-exceedance raise threshold (clear at 0.6 x raise): sensitivity study",
    )
    p.add_argument("--unreported", type=float, default=0.0, help="tampings never reported")
    p.add_argument("--late", type=float, default=0.0, help="reported tampings reported late")
    p.add_argument("--fleet", choices=("uniform", "mixed"), default="uniform")
    p.add_argument("--no-detect", action="store_true", help="no detected maintenance")
    p.add_argument("--no-unit-models", action="store_true", help="one fleet-wide calibration")
    p.add_argument("--quick", action="store_true", help="smoke test: 120 days, small")
    p.add_argument("--json", action="store_true", help="print the figures as JSON")
    a = p.parse_args(argv)
    st = Settings()
    if a.quick:
        st = replace(
            st,
            days=120.0,
            trains=1,
            samples=50,
            cutoff_days=40.0,
            horizon_days=60.0,
            eval_every_days=3.0,
            workers=1,
            subsample=3,
        )
    given = {
        "days": a.days,
        "trains": a.trains_per_line_per_day,
        "samples": a.samples,
        "cutoff_days": a.cutoff_days,
        "horizon_days": a.horizon_days,
        "eval_every_days": a.eval_every_days,
        "predicted_raise": a.predicted_raise,
        "workers": a.workers,
        "subsample": a.subsample,
    }
    if a.segments:
        st = replace(st, segments=tuple(int(x) for x in a.segments.split(",")))
    st = replace(
        st,
        seed=a.seed,
        calibrator_trc=a.calibrator_trc,
        unreported=a.unreported,
        late=a.late,
        fleet=a.fleet,
        detect=not a.no_detect,
        unit_models=not a.no_unit_models,
        **{k: v for k, v in given.items() if v is not None},
    )
    return st, a


def _jsonable(x):
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_jsonable(v) for v in x]
    if isinstance(x, float) and not math.isfinite(x):
        return None
    if isinstance(x, np.generic):
        return _jsonable(x.item())
    return x


def main(argv=None) -> int:
    st, a = parse_args(argv)
    fig = run(st)
    if a.json:
        print(json.dumps(_jsonable(fig), indent=1))
    else:
        print(_table(fig))
        print(f"wall time {fig['wall_s']:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
