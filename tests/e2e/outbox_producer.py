"""A producer process for the durable-delivery test: publishes a flood of models, TRC records
and on-board indices through its outbox (``ReliablePublisher``) in phases, then serves
replays until SIGTERM/SIGKILL.

Usage: ``python outbox_producer.py ENDPOINT NS OUTBOX_DIR SEGMENTS PASSES FIRST``. Phase 0 is
the models and the TRC records, phase k the k-th pass of indices; it publishes from phase
FIRST on (a producer started again on its outbox goes on where the killed one stopped),
prints ``phase K`` once phase K is recorded and put, and waits for SIGUSR1 before the next
one; after the last it serves its outbox until SIGTERM.
"""

from __future__ import annotations

import signal
import sys
import threading
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # the checkout's packages

import numpy as np  # noqa: E402
import zenoh  # noqa: E402

from schemas import Calibration, OnboardIndex, TrcRecord, encode, keys  # noqa: E402
from services.filtering.testing import example_models  # noqa: E402
from services.runtime.config import zenoh_config  # noqa: E402
from services.runtime.delivery import (  # noqa: E402
    DeliverySettings,
    OutboxSettings,
    ReliablePublisher,
)

T0 = 1_767_225_600.0
SAMPLES = 200


def flood(ns: str, segments: int, passes: int) -> list[list[tuple[str, object]]]:
    """The phases' ``(key, message)``: the models and one TRC record per segment, then a
    phase per pass of indices over every segment."""
    out: list[tuple[str, object]] = []
    phases = [out]
    for model in example_models(SAMPLES, seed=1):
        key = (
            keys.calibration(ns)
            if isinstance(model, Calibration)
            else keys.degradation(ns, model.group)
        )
        out.append((key, model))
    names = [f"s{i:05d}" for i in range(segments)]
    for segment in names:
        trc = TrcRecord(line="L1", segment=segment, t=T0, top6_mm=3.0, align10_mm=2.4, run_id="r0")
        out.append((keys.trc(ns, "L1", segment), trc))
    y = np.exp(np.random.default_rng(0).normal([0.8, 0.5], 0.1, (passes, segments, 2)))
    for k in range(passes):
        out = []
        phases.append(out)
        for i, segment in enumerate(names):
            index = OnboardIndex(
                line="L1", segment=segment, train="T1", unit="u1", t=T0 + 3600.0 * (k + 1),
                top6_mm=float(y[k, i, 0]), align10_mm=float(y[k, i, 1]), speed_mps=30.0,
                coverage=1.0,
            )  # fmt: skip
            out.append((keys.index(ns, "L1", segment), index))
    return phases


def main(endpoint: str, ns: str, outbox_dir: str, segments: str, passes: str, first: str) -> None:
    stop, go = threading.Event(), threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    signal.signal(signal.SIGUSR1, lambda *_: go.set())
    conf = {"mode": "client", "connect": {"endpoints": [endpoint]}}
    with zenoh.open(zenoh_config(conf)) as session:
        settings = DeliverySettings(replay_s=1.0, outbox=OutboxSettings(dir=outbox_dir))
        publisher = ReliablePublisher.open(session, ns, "extraction", "flood", settings)
        phases = flood(ns, int(segments), int(passes))
        for k in range(int(first), len(phases)):
            for key, message in phases[k]:
                publisher.put(key, encode(message))
            publisher.flush()
            print(f"phase {k}", flush=True)
            if k + 1 < len(phases):
                go.wait()
                go.clear()
        stop.wait()
        publisher.undeclare()


if __name__ == "__main__":
    main(*sys.argv[1:])
