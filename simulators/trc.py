"""Track Recording Car runs: a TrcRecord per segment every 8-11 weeks per line.

The schedule follows the paper's Table 1 (``trc`` section of ``services/defaults/simulator.json5``):
each line's first run starts ``first_run_days`` after the simulation start, the next ones
follow after gaps drawn uniformly from ``interval_weeks``, independently per line. A run
records the whole line in chainage order at ``speed_mps``; it passes a segment's middle
at ``run start + mid chainage / speed`` and records

.. math::

    [\\text{Top6}, \\text{Align10}] = \\exp(z(t) + \\varepsilon), \\qquad
    \\varepsilon \\sim N(0, \\operatorname{diag}(\\text{noise\\_sd}^2)),

with z(t) the true state at that instant.

The paper's calibration campaign: on its first ``onboard_runs`` runs per line the TRC
carries an on-board unit. In ``index`` fidelity the same pass then also yields an
OnboardIndex (train ``TRC``, unit ``onboard_unit``, the run's ``run_id``) drawn from the
index sensor model; in ``raw`` fidelity the train physics produce those signals from
:func:`trc_schedule` instead.
"""

from __future__ import annotations

import heapq
from collections.abc import Iterator, Mapping
from dataclasses import dataclass

import numpy as np

from schemas import DAY_S, Message, OnboardIndex, TrcRecord
from simulators.index_model import IndexSensorModel
from simulators.network import stable_rng
from simulators.truth import Truth, config_pair
from track.network import Network

TRC_TRAIN = "TRC"


@dataclass(frozen=True)
class TrcConfig:
    """The ``trc`` section of the simulator config."""

    interval_weeks: tuple[float, float]
    first_run_days: tuple[float, float]
    speed_mps: float
    noise_sd: np.ndarray  # (2,) log space
    onboard_runs: int
    onboard_unit: str

    @classmethod
    def from_config(cls, config: Mapping) -> TrcConfig:
        sec = config["trc"]
        cfg = cls(
            interval_weeks=config_pair(sec, "interval_weeks", "trc"),
            first_run_days=config_pair(sec, "first_run_days", "trc"),
            speed_mps=float(sec["speed_mps"]),
            noise_sd=np.asarray(sec["noise_sd"], dtype=np.float64),
            onboard_runs=int(sec.get("onboard_runs", 0)),
            onboard_unit=str(sec.get("onboard_unit", "onboard")),
        )
        if cfg.interval_weeks[0] <= 0 or not cfg.speed_mps > 0:
            raise ValueError("trc.interval_weeks and trc.speed_mps must be > 0")
        if cfg.noise_sd.shape != (2,) or (cfg.noise_sd < 0).any():
            raise ValueError("trc.noise_sd: expected 2 standard deviations >= 0")
        return cfg


@dataclass(frozen=True)
class TrcRun:
    """One TRC run over one line."""

    line: str
    k: int  # run number on this line, 0-based
    run_id: str
    t_start: float  # epoch s at chainage 0
    speed_mps: float
    onboard: bool  # the TRC carries an on-board unit on this run


def trc_schedule(
    network: Network, config: Mapping, start_t: float, days: float, seed: int
) -> list[TrcRun]:
    """All runs starting within ``days`` of ``start_t``, sorted by start time."""
    cfg = TrcConfig.from_config(config)
    end = start_t + days * DAY_S
    runs = []
    for line in network.lines.values():
        rng = stable_rng(seed, "trc-schedule", line.id)
        t, k = start_t + rng.uniform(*cfg.first_run_days) * DAY_S, 0
        while t < end:
            run_id = f"{TRC_TRAIN}-{line.id}-{k:03d}"
            runs.append(TrcRun(line.id, k, run_id, t, cfg.speed_mps, k < cfg.onboard_runs))
            t += rng.uniform(*cfg.interval_weeks) * 7 * DAY_S
            k += 1
    return sorted(runs, key=lambda r: (r.t_start, r.line))


def _run_messages(
    run: TrcRun,
    network: Network,
    truth: Truth,
    cfg: TrcConfig,
    model: IndexSensorModel | None,
    seed: int,
) -> list[tuple[float, list[Message]]]:
    line = network.lines[run.line]
    sl = truth.line_slices[run.line]
    t = run.t_start + np.array([s.mid_m for s in line.segments]) / run.speed_mps
    truth.advance_to(t[-1])
    z = truth.z_at(t, np.arange(sl.start, sl.stop))
    noise = stable_rng(seed, "trc-noise", run.line, run.k).standard_normal(z.shape)
    trc_mm = np.exp(z + noise * cfg.noise_sd)
    onboard_mm = None
    if model is not None and run.onboard:
        onboard_mm = model.indices(z, stable_rng(seed, "trc-onboard", run.line, run.k))
    out = []
    for j, seg in enumerate(line.segments):
        tj = float(t[j])
        msgs: list[Message] = [
            TrcRecord(
                line=run.line,
                segment=seg.id,
                t=tj,
                top6_mm=float(trc_mm[j, 0]),
                align10_mm=float(trc_mm[j, 1]),
                run_id=run.run_id,
            )
        ]
        if onboard_mm is not None:
            msgs.append(
                OnboardIndex(
                    line=run.line,
                    segment=seg.id,
                    train=TRC_TRAIN,
                    unit=cfg.onboard_unit,
                    t=tj,
                    top6_mm=float(onboard_mm[j, 0]),
                    align10_mm=float(onboard_mm[j, 1]),
                    speed_mps=run.speed_mps,
                    coverage=1.0,
                    quality=1.0,
                    run_id=run.run_id,
                )
            )
        out.append((tj, msgs))
    return out


def trc_events(
    network: Network,
    config: Mapping,
    start_t: float,
    days: float,
    seed: int,
    *,
    fidelity: str = "index",
    truth: Truth | None = None,
    model: IndexSensorModel | None = None,
) -> Iterator[tuple[float, list[Message]]]:
    """TRC records (and the campaign's on-board indices) as ``(t, [messages])`` in time order.

    One item per segment pass: ``[TrcRecord]``, plus the OnboardIndex of the same instant
    on campaign runs in ``index`` fidelity. ``truth`` (default: a new Truth of the same
    seed) is advanced by this generator; do not share it with another generator.
    """
    if fidelity not in ("index", "raw"):
        raise ValueError(f"fidelity: expected 'index' or 'raw', got {fidelity!r}")
    cfg = TrcConfig.from_config(config)
    truth = truth if truth is not None else Truth(network, config, start_t, seed)
    if fidelity == "raw":  # the train physics produce the campaign's on-board signals
        model = None
    elif model is None:
        model = IndexSensorModel.from_config(config)
    pending: list[tuple[float, int, list[Message]]] = []
    n = 0
    for run in trc_schedule(network, config, start_t, days, seed):
        # Later runs start after run.t_start: what is due before it is final.
        while pending and pending[0][0] < run.t_start:
            t, _, msgs = heapq.heappop(pending)
            yield t, msgs
        for t, msgs in _run_messages(run, network, truth, cfg, model, seed):
            heapq.heappush(pending, (t, n, msgs))
            n += 1
    while pending:
        t, _, msgs = heapq.heappop(pending)
        yield t, msgs
