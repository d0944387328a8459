"""Real processes: a flood of valid indices, faster than one filtering instance folds them.

What makes a filtering instance go deaf
(docs/architecture.md#no-callback-blocks-a-session): Zenoh callbacks that block on a full
queue while the worker is busy stop the session reading its link, the router closes the
link, and what was queued on it is lost without a trace; the instance comes back with its
token withdrawn and re-declared (or not at all). Behind a blocking queue this test loses
about three quarters of the flood (7,713 of 30,000 indices folded) and sees the token
withdrawn 8 s in; with the inbox every index is folded and the token stays.
"""

from __future__ import annotations

import time

import numpy as np
import zenoh

from schemas import Calibration, OnboardIndex, TrcRecord, encode, keys
from services.filtering.testing import example_models
from services.runtime.config import zenoh_config
from tests.e2e.stacks import FoldProgress

READY_S = 30.0
SEGMENTS, PASSES = 1000, 30  # 30,000 indices: a service that drops under load loses most
FOLD_S = 600.0  # an upper bound on a loaded 2-core machine (unloaded: about a minute)
T0 = 1_767_225_600.0
BLOCK = zenoh.CongestionControl.BLOCK


def test_a_flood_is_folded_whole_and_the_instance_stays_alive(
    stack, spawn, tmp_path, free_port, namespace, liveliness_events
):
    endpoint = f"tcp/127.0.0.1:{free_port}"
    spawn("router", "router", "--listen", endpoint)
    settings = {"connect": {"endpoints": [endpoint], "timeout_ms": int(READY_S * 1000)}}
    session = stack.enter_context(zenoh.open(zenoh_config(settings)))
    alive_key = keys.alive(namespace, "filtering", "flood")
    alive = liveliness_events(session, alive_key)
    progress = FoldProgress(SEGMENTS, PASSES)
    subscriber = session.declare_subscriber(keys.segment_keys(namespace, "state"), progress)
    stack.callback(subscriber.undeclare)
    filtering = spawn(
        "filtering",
        *("filtering", "--connect", endpoint, "--ns", namespace, "--instance", "flood"),
        *("--db", str(tmp_path / "filtering.sqlite")),
    )
    assert alive.get(READY_S) == (zenoh.SampleKind.PUT, alive_key), filtering.log()

    for model in example_models(200, seed=1):
        key = (
            keys.calibration(namespace)
            if isinstance(model, Calibration)
            else keys.degradation(namespace, model.group)
        )
        session.put(key, encode(model), congestion_control=BLOCK)
    segments = [f"s{i:05d}" for i in range(SEGMENTS)]
    for segment in segments:
        trc = TrcRecord(line="L1", segment=segment, t=T0, top6_mm=3.0, align10_mm=2.4, run_id="r0")
        session.put(keys.trc(namespace, "L1", segment), encode(trc), congestion_control=BLOCK)
    y = np.exp(np.random.default_rng(0).normal([0.8, 0.5], 0.1, (PASSES, SEGMENTS, 2)))
    for k in range(PASSES):  # as fast as the client can put them
        for i, segment in enumerate(segments):
            index = OnboardIndex(
                line="L1",
                segment=segment,
                train="T1",
                unit="u1",
                t=T0 + 3600.0 * (k + 1),
                top6_mm=float(y[k, i, 0]),
                align10_mm=float(y[k, i, 1]),
                speed_mps=30.0,
                coverage=1.0,
            )
            session.put(
                keys.index(namespace, "L1", segment), encode(index), congestion_control=BLOCK
            )

    deadline = time.monotonic() + FOLD_S
    while not progress.done.wait(1.0) and time.monotonic() < deadline:
        # a withdrawn token is the loss itself: fail at once, not at the deadline
        assert alive.empty(), f"the token was withdrawn during the flood{filtering.log()}"
    short = progress.short()
    assert alive.empty(), f"the token was withdrawn during the flood{filtering.log()}"
    assert progress.done.is_set(), (
        f"{len(progress.folded)} segments with a state, {len(short)} short of {PASSES} updates "
        f"(e.g. {dict(list(short.items())[:5])}){filtering.log()}"
    )
