"""Events per second through one filtering instance over Zenoh, and publication latency.

One in-process router on loopback, the filtering service in a thread (its real ``main``,
SQLite store in a temporary directory), a publisher session sending OnboardIndex messages on
``SEGMENTS`` segments (models and a TRC record per segment set first), and a subscriber
session receiving the SegmentStates. Latency is from just before an index's ``put`` to the
arrival of its state at the subscriber (``time.perf_counter`` in this one process; the
state is matched to its index by ``(line, segment, t)``), so it is an upper bound of the
index-publication → state-publication latency that includes one more hop.

Two runs: *loaded* (all ``N_EVENTS`` sent as fast as the bus takes them; events/s and the
latency under that backlog) and *unloaded* (one index at a time; p50/p99). Baseline in the
same run: the pure tracker (:class:`services.filtering.tracker.Tracker`) on the same events
in-process, so the ratio is what Zenoh, decoding, SQLite commits and encoding cost.

Run: ``.venv/bin/python -m bench.filtering``.
"""

from __future__ import annotations

import socket
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
import zenoh

from schemas import (
    Calibration,
    DegradationPosterior,
    OnboardIndex,
    SegmentState,
    TrcRecord,
    decode,
    encode,
    keys,
)
from services.filtering import service
from services.filtering.store import PersistentTracker, Store
from services.filtering.testing import example_models
from services.filtering.tracker import Tracker
from services.limits import load_limits
from services.runtime.config import RuntimeConfig, zenoh_config
from services.runtime.service import ServiceRuntime

NS_SAMPLES, SEGMENTS, N_EVENTS, N_UNLOADED = 200, 200, 4000, 300
T0 = 1_767_225_600.0
WAIT_S = 120.0


def _models(rng: np.random.Generator) -> list[Calibration | DegradationPosterior]:
    return example_models(NS_SAMPLES, seed=int(rng.integers(2**31)))


def _trcs() -> list[TrcRecord]:
    return [
        TrcRecord(line="L1", segment=f"s{k:03d}", t=T0, top6_mm=3.0, align10_mm=2.4, run_id="r0")
        for k in range(SEGMENTS)
    ]


def _indices(rng: np.random.Generator, n: int, first_hour: int) -> list[OnboardIndex]:
    y = np.exp(rng.normal([0.8, 0.5], 0.1, (n, 2))).tolist()
    return [
        OnboardIndex(
            line="L1",
            segment=f"s{i % SEGMENTS:03d}",
            train="T1",
            unit="u1",
            t=T0 + (first_hour + i) * 3600.0,  # unique per event: the latency table's key
            top6_mm=y[i][0],
            align10_mm=y[i][1],
            speed_mps=30.0,
            coverage=1.0,
        )
        for i in range(n)
    ]


def _serve(conf, tmp: Path, stop: threading.Event, adapters: list) -> None:
    """The filtering service as ``service.main`` runs it, its adapter kept for its inbox."""
    limits = load_limits()
    store = Store(tmp / "bench.sqlite")
    try:
        with ServiceRuntime(service.SERVICE, conf, stop_event=stop) as rt:
            node = PersistentTracker(Tracker(limits.for_line, limits.levels), store)
            adapters.append(service.FilteringAdapter(rt, node, "**"))
            adapters[0].start()
            rt.run()
    finally:
        store.close()


def _percentiles_ms(latencies: list[float]) -> tuple[float, float]:
    p50, p99 = np.percentile(np.asarray(latencies) * 1e3, [50, 99])
    return float(p50), float(p99)


def bench_filtering_service() -> None:
    rng = np.random.default_rng(0)
    models, trcs = _models(rng), _trcs()
    loaded = _indices(rng, N_EVENTS, 1)
    unloaded = _indices(rng, N_UNLOADED, 1 + N_EVENTS)

    # Baseline: the pure tracker on the same events, in-process.
    limits = load_limits()
    tracker = Tracker(limits.for_line, limits.levels)
    for msg in (*models, *trcs):
        tracker.step(msg)
    started = time.perf_counter()
    for msg in loaded:
        tracker.step(msg)
    core_rate = len(loaded) / (time.perf_counter() - started)

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        endpoint = f"tcp/127.0.0.1:{s.getsockname()[1]}"
    ns = f"tfbench_{int(time.time())}"
    client = {"mode": "client", "connect": {"endpoints": [endpoint]}}
    conf = RuntimeConfig(ns=ns, instance="bench", zenoh=client)
    router_conf = {"mode": "router", "listen": {"endpoints": [endpoint]}, "scouting": {"delay": 0}}
    sent: dict[tuple[str, float], float] = {}  # (segment, t) -> perf_counter before put
    received: dict[tuple[str, float], float] = {}
    lock = threading.Lock()
    arrived = threading.Condition(lock)

    def on_state(sample: zenoh.Sample) -> None:
        now = time.perf_counter()
        state = decode(sample.payload.to_bytes(), SegmentState)
        with arrived:
            received.setdefault((state.segment, state.t), now)
            arrived.notify_all()

    def wait_for(wanted: list, timeout: float = WAIT_S) -> None:
        with arrived:
            ok = arrived.wait_for(lambda: all(k in received for k in wanted), timeout)
        if not ok:
            raise RuntimeError(f"states missing after {timeout} s")

    model_replies = [
        (keys.calibration(ns), encode(models[0])),
        (keys.degradation(ns, "net"), encode(models[1])),
    ]

    def on_model_query(query: zenoh.Query) -> None:
        for key, payload in model_replies:
            query.reply(key, payload)

    def put(session: zenoh.Session, msg) -> None:
        key = (
            keys.trc(ns, msg.line, msg.segment)
            if isinstance(msg, TrcRecord)
            else keys.index(ns, msg.line, msg.segment)
        )
        payload = encode(msg)
        sent[(msg.segment, msg.t)] = time.perf_counter()
        # BLOCK: a full queue on the way (router -> service) must slow us down, not drop.
        session.put(key, payload, congestion_control=zenoh.CongestionControl.BLOCK)

    stop = threading.Event()
    with (
        tempfile.TemporaryDirectory() as tmp,
        zenoh.open(zenoh_config(router_conf)) as _router,
        zenoh.open(zenoh_config(client)) as pub,
        zenoh.open(zenoh_config(client)) as sub_session,
    ):
        subscriber = sub_session.declare_subscriber(keys.segment_keys(ns, "state"), on_state)
        models_q = pub.declare_queryable(keys.model_all(ns), on_model_query)
        adapters: list[service.FilteringAdapter] = []
        thread = threading.Thread(target=_serve, args=(conf, Path(tmp), stop, adapters))
        thread.start()
        try:
            # Until the TRC states come back, the service may not be subscribed yet: resend.
            while True:
                for msg in trcs:
                    put(pub, msg)
                try:
                    wait_for([(trcs[0].segment, trcs[0].t)], timeout=1.0)
                    break
                except RuntimeError:
                    continue
            wait_for([(m.segment, m.t) for m in trcs])

            started = time.perf_counter()
            for msg in loaded:
                put(pub, msg)
            # under a backlog the service publishes the newest state of a segment per batch:
            # the loaded run ends with the state of each segment's last index
            newest = list({m.segment: m for m in loaded}.values())
            wait_for([(m.segment, m.t) for m in newest])
            with lock:
                last = max(received[(m.segment, m.t)] for m in newest)
            service_rate = len(loaded) / (last - started)
            lat_loaded = [received[(m.segment, m.t)] - sent[(m.segment, m.t)] for m in newest]
            inbox = adapters[0].inbox.stats()

            for msg in unloaded:
                put(pub, msg)
                wait_for([(msg.segment, msg.t)])
            lat_unloaded = [received[(m.segment, m.t)] - sent[(m.segment, m.t)] for m in unloaded]
        finally:
            stop.set()
            thread.join(10)
            models_q.undeclare()
            subscriber.undeclare()

    l50, l99 = _percentiles_ms(lat_loaded)
    u50, u99 = _percentiles_ms(lat_unloaded)
    print(
        f"filtering service over Zenoh, Ns = {NS_SAMPLES}, {SEGMENTS} segments, "
        f"{N_EVENTS} OnboardIndex:"
    )
    print(
        f"  {service_rate:,.0f} events/s through the service vs {core_rate:,.0f} events/s "
        f"pure tracker in-process: ratio {service_rate / core_rate:.2f}"
    )
    print(
        f"  latency index put -> newest state received, loaded: p50 {l50:.1f} ms, "
        f"p99 {l99:.1f} ms; longest Zenoh callback {inbox.max_put_s * 1e3:.2f} ms, "
        f"{inbox.spilled} spilled to disk"
    )
    print(f"  latency index put -> state received, unloaded: p50 {u50:.2f} ms, p99 {u99:.2f} ms")
    print(f"  (unloaded p99 against 1 / pure-tracker rate: {u99 / (1e3 / core_rate):.1f}x)")


if __name__ == "__main__":
    bench_filtering_service()
