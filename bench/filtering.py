"""Events per second through one filtering instance over Zenoh, and publication latency.

One in-process router on loopback, the filtering service in a thread (its real ``main``,
SQLite store in a temporary directory), a publisher session sending OnboardIndex messages on
``SEGMENTS`` segments (models and a TRC record per segment set first), and a subscriber
session receiving the SegmentStates. Latency is from just before an index's ``put`` to the
arrival of its state at the subscriber (``time.perf_counter`` in this one process; the
state is matched to its index by ``(line, segment, t)``), so it is an upper bound of the
index-publication → state-publication latency that includes one more hop.

Three runs:

- *backlog*: all ``N_EVENTS`` put as fast as the bus takes them (BLOCK). Events/s folded and
  committed (the service's SQLite file, read by a second connection until it holds them
  all), and the time until every segment's newest state has arrived (under a backlog the
  service publishes dirty segments with a share of its time, all of them once the backlog
  is gone: :mod:`services.filtering.service`).
- *live*: ``LIVE_RATE`` indices/s paced for ``LIVE_S`` seconds (each put at its slot, the
  publisher catching up if late); latency p50/p99/max of each index's own state, and how
  many states were coalesced into a later one (not received).
- *unloaded*: one index at a time; p50/p99.

Baseline in the same run: the pure tracker (:class:`services.filtering.tracker.Tracker`) on
the same backlog in-process, batches of ``service.BATCH`` through ``step_events``
(summaries included), so the ratio is what Zenoh, decoding, SQLite commits, encoding and
the publication rule change.

Run: ``.venv/bin/python -m bench.filtering [--process]``; ``--process``: the service as its
own process (``trackfusion filtering``, as deployed), the rest in this one.
"""

from __future__ import annotations

import socket
import sqlite3
import subprocess
import sys
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
    TrcRecord,
    encode,
    keys,
)
from services.filtering import service
from services.filtering.coordinator import PersistentTracker
from services.filtering.store import Store
from services.filtering.testing import example_models, onboard_index, sample_state
from services.filtering.tracker import Tracker
from services.limits import load_limits
from services.runtime.config import RuntimeConfig, zenoh_config
from services.runtime.service import ServiceRuntime

NS_SAMPLES, SEGMENTS, N_EVENTS, N_UNLOADED = 200, 2000, 20_000, 200
LIVE_RATE, LIVE_S = 1000.0, 30.0  # indices/s, seconds
T0 = 1_767_225_600.0
WAIT_S = 120.0


def _models(rng: np.random.Generator) -> list[Calibration | DegradationPosterior]:
    return example_models(NS_SAMPLES, seed=int(rng.integers(2**31)))


def _trcs() -> list[TrcRecord]:
    return [
        TrcRecord(line="L1", segment=f"s{k:05d}", t=T0, top6_mm=3.0, align10_mm=2.4, run_id="r0")
        for k in range(SEGMENTS)
    ]


def _indices(rng: np.random.Generator, n: int, first_hour: int) -> list[OnboardIndex]:
    y = np.exp(rng.normal([0.8, 0.5], 0.1, (n, 2))).tolist()
    # t: unique per event, the latency table's key
    return [
        onboard_index("L1", f"s{i % SEGMENTS:05d}", T0 + (first_hour + i) * 3600.0, *y[i])
        for i in range(n)
    ]


def _serve(conf, tmp: Path, stop: threading.Event, adapters: list) -> None:
    """The filtering service as ``service.main`` runs it, its adapter kept for its inbox."""
    limits = load_limits()
    store = Store(tmp / "bench.sqlite")
    try:
        with ServiceRuntime(service.SERVICE, conf, stop_event=stop) as rt:
            node = PersistentTracker(Tracker(limits.for_line, limits.levels), store)
            adapters.append(service.FilteringAdapter(rt, node, "**", freeze_gc=True))
            adapters[0].start()
            rt.run()
    finally:
        store.close()


def _percentiles_ms(latencies: list[float]) -> tuple[float, float]:
    p50, p99 = np.percentile(np.asarray(latencies) * 1e3, [50, 99])
    return float(p50), float(p99)


def _spawn(endpoint: str, ns: str, tmp: Path) -> subprocess.Popen:
    """The filtering service as its own process (``trackfusion filtering``), as deployed."""
    return subprocess.Popen(
        [sys.executable, "-m", "services.cli", "filtering", "--connect", endpoint, "--ns", ns]
        + ["--instance", "bench", "--db", str(tmp / "bench.sqlite"), "--log-level", "warning"],
        stdout=subprocess.DEVNULL,
        stderr=open(tmp / "filtering.log", "wb"),  # noqa: SIM115 (closed with the process)
    )


def bench_filtering_service(own_process: bool = False) -> None:
    """``own_process``: the service runs as its own process (as deployed; the router, the
    publisher and the subscriber stay in this one); else in a thread of this process."""
    rng = np.random.default_rng(0)
    models, trcs = _models(rng), _trcs()
    loaded = _indices(rng, N_EVENTS, 1)
    unloaded = _indices(rng, N_UNLOADED, 1 + N_EVENTS)

    live = _indices(rng, int(LIVE_RATE * LIVE_S), 1 + N_EVENTS + N_UNLOADED)

    # Baseline: the pure tracker on the same events, in-process, in the service's batches.
    limits = load_limits()
    tracker = Tracker(limits.for_line, limits.levels)
    tracker.update_models(models)
    tracker.step_events(trcs)
    tracker.step_events(loaded[:300])  # warm-up (numba's compiled kernels load on first use)
    started = time.perf_counter()
    for i in range(300, len(loaded), service.BATCH):
        tracker.step_events(loaded[i : i + service.BATCH])
    core_rate = (len(loaded) - 300) / (time.perf_counter() - started)
    del tracker

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
        state = sample_state(sample)
        with arrived:
            received.setdefault((state.segment, state.t), now)
            arrived.notify_all()

    def wait_for(wanted: list, timeout: float = WAIT_S) -> None:
        with arrived:
            ok = arrived.wait_for(lambda: all(k in received for k in wanted), timeout)
        if not ok:
            raise RuntimeError(f"states missing after {timeout} s")

    model_replies = [(keys.key_of(ns, model), encode(model)) for model in models]

    def on_model_query(query: zenoh.Query) -> None:
        for key, payload in model_replies:
            query.reply(key, payload)

    def put(session: zenoh.Session, msg) -> None:
        key, payload = keys.key_of(ns, msg), encode(msg)
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
        process = _spawn(endpoint, ns, Path(tmp)) if own_process else None
        if process is None:
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

            reader = sqlite3.connect(Path(tmp) / "bench.sqlite")  # the service's file
            stored_before = reader.execute("SELECT COUNT(*) FROM events").fetchone()[0]
            started = time.perf_counter()
            for msg in loaded:
                put(pub, msg)
            put_s = time.perf_counter() - started
            stored_at = None
            while stored_at is None:  # committed = folded (one transaction per batch)
                count = reader.execute("SELECT COUNT(*) FROM events").fetchone()[0]
                if count >= stored_before + len(loaded):
                    stored_at = time.perf_counter()
                elif time.perf_counter() - started > WAIT_S:
                    raise RuntimeError(f"{count - stored_before} of {len(loaded)} stored")
                else:
                    time.sleep(0.01)  # a bench's poll, not a test's wait
            reader.close()
            fold_rate = len(loaded) / (stored_at - started)
            # the backlog run ends with the state of each segment's last index
            newest = list({m.segment: m for m in loaded}.values())
            wait_for([(m.segment, m.t) for m in newest])
            with lock:
                last = max(received[(m.segment, m.t)] for m in newest)
            service_rate = len(loaded) / (last - started)
            inbox = adapters[0].inbox.stats() if adapters else None

            for msg in unloaded:
                put(pub, msg)
                wait_for([(msg.segment, msg.t)])
            lat_unloaded = [received[(m.segment, m.t)] - sent[(m.segment, m.t)] for m in unloaded]

            live_started = time.perf_counter()
            for i, msg in enumerate(live):
                slot = live_started + i / LIVE_RATE
                ahead = slot - time.perf_counter()
                if ahead > 0:
                    time.sleep(ahead)  # pacing the publisher
                put(pub, msg)
            live_put_s = time.perf_counter() - live_started
            newest_live = list({m.segment: m for m in live}.values())
            wait_for([(m.segment, m.t) for m in newest_live])
            with lock:
                got = [m for m in live if (m.segment, m.t) in received]
                lat_live = [received[(m.segment, m.t)] - sent[(m.segment, m.t)] for m in got]
        finally:
            stop.set()
            if process is None:
                thread.join(10)
            else:
                process.terminate()
                process.wait(10)
            models_q.undeclare()
            subscriber.undeclare()

    u50, u99 = _percentiles_ms(lat_unloaded)
    v50, v99 = _percentiles_ms(lat_live)
    callbacks = (
        "the service's own process"
        if inbox is None
        else f"longest Zenoh callback {inbox.max_put_s * 1e3:.2f} ms, "
        f"{inbox.spilled} spilled to disk"
    )
    print(
        f"filtering service over Zenoh ({'its own process' if own_process else 'a thread'}), "
        f"Ns = {NS_SAMPLES}, {SEGMENTS:,} segments, "
        f"a backlog of {N_EVENTS:,} OnboardIndex (put in {put_s:.1f} s):"
    )
    print(
        f"  {fold_rate:,.0f} events/s folded and committed; every newest state received after "
        f"{last - started:.1f} s ({service_rate:,.0f} events/s); pure tracker in-process "
        f"(step_events, batches of {service.BATCH}, summaries included) {core_rate:,.0f} "
        f"events/s: ratio {fold_rate / core_rate:.2f} (folded), {service_rate / core_rate:.2f} "
        f"(published); {callbacks}"
    )
    print(
        f"  live, {LIVE_RATE:,.0f} indices/s for {live_put_s:.1f} s: latency index put -> its "
        f"state received p50 {v50:.1f} ms, p99 {v99:.1f} ms, max {max(lat_live) * 1e3:.0f} ms "
        f"(target p99 < 50 ms); {len(live) - len(got)} of {len(live):,} states coalesced "
        "into a newer one"
    )
    print(f"  one index at a time: latency p50 {u50:.2f} ms, p99 {u99:.2f} ms")


if __name__ == "__main__":
    bench_filtering_service(own_process="--process" in sys.argv)
