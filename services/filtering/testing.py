"""Test doubles that ship with the filtering service: plausible models to start it with,
on-board indices to feed it, and probes of running instances (the newest events on the bus,
every instance's states)."""

from __future__ import annotations

import threading

import numpy as np
import zenoh

from schemas import (
    INDICATORS,
    Calibration,
    DegradationPosterior,
    NDArray,
    OnboardIndex,
    SegmentState,
    decode,
    keys,
)
from schemas.keys import SegmentId
from services.filtering.events import event_of
from services.filtering.payloads import EVENT_TYPES

T0 = 1_767_225_600.0  # 2026-01-01T00:00:00Z


def example_models(
    samples: int, seed: int, *, z_plus_sd: float = 0.0, t: float = T0
) -> list[Calibration | DegradationPosterior]:
    """A Calibration (the study's H, b, R) and a ``net`` DegradationPosterior of ``samples``
    draws around the typical scenario (services/defaults/study.json5), both version 1."""
    names = list(INDICATORS)
    return [
        Calibration(
            version=1,
            t=t,
            indicators=names,
            indices=names,
            H=NDArray.of([[0.9, 0.05], [0.05, 0.75]]),
            b=NDArray.of([-0.25, -0.35]),
            R=NDArray.of([[0.01, 0.002], [0.002, 0.03]]),
            n_pairs=40,
            r2=NDArray.of([0.8, 0.7]),
        ),
        example_posterior(samples, seed, z_plus_sd=z_plus_sd, t=t),
    ]


def example_posterior(
    samples: int,
    seed: int,
    *,
    group: str = "net",
    version: int = 1,
    z_plus_sd: float = 0.0,
    t: float = T0,
    n_increments: int = 20,
    n_levels: int = 5,
) -> DegradationPosterior:
    """A DegradationPosterior of ``samples`` draws around the typical scenario: drifts of
    0.07 %/day and 0.04 %/day, post-tamping levels of 2.0 and 1.8 mm (``z_plus_sd``: the
    spread of those levels between draws)."""
    rng = np.random.default_rng(seed)
    sd = np.array([1e-2, 7e-3]) * np.exp(0.3 * rng.standard_normal((samples, 1)))
    sigma = np.array([[1.0, 0.4], [0.4, 1.0]]) * sd[:, :, None] * sd[:, None]
    mu = rng.normal([7e-4, 4e-4], 2e-4, (samples, 2))
    z_plus = np.log([2.0, 1.8]) + (
        rng.normal(0.0, z_plus_sd, (samples, 2)) if z_plus_sd else np.zeros((samples, 2))
    )
    return DegradationPosterior(
        group=group,
        version=version,
        t=t,
        indicators=list(INDICATORS),
        mu=NDArray.of(mu),
        sigma=NDArray.of(sigma),
        z_plus=NDArray.of(z_plus),
        sigma_z_plus=NDArray.of(np.broadcast_to(np.eye(2) * 0.01, (samples, 2, 2))),
        n_increments=n_increments,
        n_levels=n_levels,
    )


def onboard_index(
    line: str, segment: str, t: float, top6_mm: float, align10_mm: float, train: str = "T1"
) -> OnboardIndex:
    """An index of ``train``'s unit ``u1`` over the whole segment (coverage 1) at 30 m/s."""
    return OnboardIndex(
        line=line,
        segment=segment,
        train=train,
        unit="u1",
        t=t,
        top6_mm=top6_mm,
        align10_mm=align10_mm,
        speed_mps=30.0,
        coverage=1.0,
    )


def sample_state(sample: zenoh.Sample) -> SegmentState:
    """The SegmentState a sample of ``{ns}/state/**`` carries."""
    return decode(sample.payload.to_bytes(), SegmentState)


class LastEvents:
    """A subscriber callback keeping the newest event time per segment seen on the bus:
    a drained filtering instance shows exactly these times in its states."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.t: dict[SegmentId, float] = {}

    def __call__(self, sample: zenoh.Sample) -> None:
        kind = keys.kind(sample.key_expr)
        event = event_of(decode(sample.payload.to_bytes(), EVENT_TYPES[kind]))
        sid = (event.message.line, event.message.segment)
        with self.lock:
            self.t[sid] = max(self.t.get(sid, event.t_s), event.t_s)

    def snapshot(self) -> dict[SegmentId, float]:
        with self.lock:
            return dict(self.t)


def states_by_instance(session: zenoh.Session, ns: str) -> dict[str, dict[str, bytes]]:
    """``{replier zid: {q/state key: payload}}`` of every filtering instance that answers."""
    out: dict[str, dict[str, bytes]] = {}
    # No consolidation: by default Zenoh keeps one reply per key, and several instances answer.
    none = zenoh.ConsolidationMode.NONE
    block = zenoh.CongestionControl.BLOCK
    for reply in session.get(
        keys.q_state_all(ns), timeout=10.0, consolidation=none, congestion_control=block
    ):
        if reply.ok is not None:
            out.setdefault(str(reply.replier_id.zid), {})[str(reply.ok.key_expr)] = (
                reply.ok.payload.to_bytes()
            )
    return out
