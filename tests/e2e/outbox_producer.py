"""A producer process for the durable-delivery test: publishes a flood of models, TRC records
and on-board indices through its outbox (``ReliablePublisher``), then serves replays until
SIGTERM/SIGKILL. Started again on the same outbox, it publishes the same flood again (the
numbering continues; the consumers drop the repeats).

Usage: ``python outbox_producer.py ENDPOINT NS OUTBOX_DIR SEGMENTS PASSES``; prints ``half``
once half the flood is recorded, ``published`` once all of it is.
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


def flood(ns: str, segments: int, passes: int) -> list[tuple[str, object]]:
    """``(key, message)``: the models, one TRC record per segment, then ``passes`` indices
    per segment, pass after pass."""
    out: list[tuple[str, object]] = []
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
        for i, segment in enumerate(names):
            index = OnboardIndex(
                line="L1", segment=segment, train="T1", unit="u1", t=T0 + 3600.0 * (k + 1),
                top6_mm=float(y[k, i, 0]), align10_mm=float(y[k, i, 1]), speed_mps=30.0,
                coverage=1.0,
            )  # fmt: skip
            out.append((keys.index(ns, "L1", segment), index))
    return out


def main(endpoint: str, ns: str, outbox_dir: str, segments: str, passes: str) -> None:
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    conf = {"mode": "client", "connect": {"endpoints": [endpoint]}}
    with zenoh.open(zenoh_config(conf)) as session:
        settings = DeliverySettings(replay_s=1.0, outbox=OutboxSettings(dir=outbox_dir))
        publisher = ReliablePublisher.open(session, ns, "extraction", "flood", settings)
        messages = flood(ns, int(segments), int(passes))
        for i, (key, message) in enumerate(messages):
            publisher.put(key, encode(message))
            if i == len(messages) // 2:
                publisher.flush()
                print("half", flush=True)
        publisher.flush()
        print("published", flush=True)
        stop.wait()
        publisher.undeclare()


if __name__ == "__main__":
    main(*sys.argv[1:])
