"""The calibration service in-process on a real router: data in, models out, late joiners,
dead letters, restart from its SQLite file."""

from __future__ import annotations

from collections.abc import Callable

import msgpack
import numpy as np
import pytest
import zenoh
from support import ServiceThread

from schemas import (
    DAY_S,
    Calibration,
    DeadLetter,
    DegradationPosterior,
    MaintenanceEvent,
    TrcRecord,
    decode,
    encode,
    keys,
)
from services.calibration import service
from services.calibration.config import CalibratorConfig
from services.calibration.store import SqliteStore

BLOCK = zenoh.CongestionControl.BLOCK  # a fast burst of puts is otherwise dropped
T0 = 1_735_689_600.0  # 2025-01-01
H = np.array([[0.90, 0.05], [0.05, 0.75]])
B = np.array([-0.25, -0.35])
R = np.array([[0.010, 0.002], [0.002, 0.030]])
MU = np.array([1.0e-3, 5.0e-4])  # ln mm / day
SIGMA = np.array([[1.0e-4, 2.8e-5], [2.8e-5, 4.9e-5]])
LINES, SEGMENTS, RUNS = ("L1", "L2", "L3"), 10, 6


def generate(seed: int = 42):
    """TRC runs every ~60 days over every segment with the on-board unit riding the TRC (same
    run_id), a tamping before the 4th run of each segment: (key, payload) in event order."""
    rng = np.random.default_rng(seed)
    out: list[tuple[float, str, bytes]] = []
    for line in LINES:
        for s in range(SEGMENTS):
            seg = f"s{s:02d}"
            z = rng.normal([1.1, 0.9], [0.35, 0.3])
            t = T0 + rng.uniform(0, 5) * DAY_S
            for run in range(RUNS):
                if run == 3:
                    tm = t - 12 * DAY_S
                    ev = MaintenanceEvent(
                        line=line, segment=seg, event_id=f"tamp{run}", t_start=tm, t_end=tm
                    )
                    out.append((tm, keys.maintenance("NS", line, seg), encode(ev)))
                    z = rng.normal([0.7, 0.6], 0.15) + MU * 12
                top, align = (float(v) for v in np.exp(z))
                rec = TrcRecord(
                    line=line, segment=seg, t=t, top6_mm=top, align10_mm=align, run_id=f"R{run}"
                )
                out.append((t, keys.trc("NS", line, seg), encode(rec)))
                y = H @ z + B + rng.multivariate_normal([0, 0], R)
                index = {  # as a gateway in another language would pack it
                    "v": 1,
                    "line": line,
                    "segment": seg,
                    "train": "TRC1",
                    "unit": "bogie1",
                    "t": t + 2.0,
                    "top6_mm": float(np.exp(y[0])),
                    "align10_mm": float(np.exp(y[1])),
                    "speed_mps": 20.0,
                    "coverage": 1.0,
                    "run_id": f"R{run}",
                }
                out.append((t + 2.0, keys.index("NS", line, seg), msgpack.packb(index)))
                dt = rng.uniform(56, 77)
                z = z + MU * dt + rng.multivariate_normal([0, 0], SIGMA * dt)
                t += dt * DAY_S
    out.sort(key=lambda e: e[0])
    return [(k, p) for _, k, p in out]


@pytest.fixture
def run_service(service_config, service_thread) -> Callable[[service.Settings], ServiceThread]:
    """``run_service(settings)``: the service in a thread, returned once its token is alive
    (subscriptions and queryable declared); ``.stop()`` gives its exit code."""

    def start(settings: service.Settings) -> ServiceThread:
        return service_thread(
            "calibration",
            lambda stop: service.main(
                service_config, settings, stop_event=stop, handle_signals=False
            ),
            alive=keys.alive(service_config.ns, "calibration", "test"),
        )

    return start


def decode_model(sample: zenoh.Sample):
    kind = Calibration if str(sample.key_expr).endswith("/calibration") else DegradationPosterior
    return decode(sample.payload.to_bytes(), kind)


def late_join(session: zenoh.Session, ns: str) -> dict[str, bytes]:
    replies = session.get(keys.model_all(ns), timeout=5)
    return {str(r.ok.key_expr): r.ok.payload.to_bytes() for r in replies if r.ok is not None}


def test_models_from_data_late_joiners_dead_letters_and_restart(
    service_config, run_service, open_session, collector, tmp_path
):
    ns = service_config.ns
    settings = service.Settings(
        # every accepted change published at once (the publication rule has its unit tests):
        # the test waits for the fit on all pairs and the posterior on all increments
        core=CalibratorConfig(
            min_pairs=30,
            refit_every=20,
            samples=50,
            seed=7,
            material_se=0.0,
            min_publish_interval_days=0.0,
        ),
        db=tmp_path / "calibration.sqlite",
    )
    client = open_session()
    models = collector(decode_model)
    letters = collector(lambda s: decode(s.payload.to_bytes(), DeadLetter))
    client.declare_subscriber(keys.model_all(ns), models)
    client.declare_subscriber(keys.deadletter_all(ns), letters)
    running = run_service(settings)

    events = generate()
    for key, payload in events:
        client.put(key.replace("NS/", f"{ns}/", 1), payload, congestion_control=BLOCK)
    client.put(keys.trc(ns, "L1", "bad"), b"\x93not a map")

    # the robustness rules may dead-letter a TRC record first (which one depends on where
    # the batches fell): wait for the bad message's own letter
    while (letter := letters.get()).key != keys.trc(ns, "L1", "bad"):
        assert "not published" in letter.reason, letter
    assert letter.service == "calibration" and "TrcRecord" in letter.reason

    n_pairs = len(LINES) * SEGMENTS * RUNS
    n_increments = len(LINES) * SEGMENTS * (RUNS - 2)  # one spans the tamping
    latest: dict[str, Calibration | DegradationPosterior] = {}  # by key: units have theirs
    while not (
        isinstance(cal := latest.get(keys.calibration(ns)), Calibration)
        and cal.n_pairs > n_pairs - settings.core.refit_every  # the last refit
        and getattr(latest.get(keys.degradation(ns, "net")), "n_increments", 0) == n_increments
    ):
        model = models.get()
        latest[keys.key_of(ns, model)] = model

    cal = latest[keys.calibration(ns)]
    np.testing.assert_allclose(cal.H.array(), H, atol=0.15)
    np.testing.assert_allclose(cal.b.array(), B, atol=0.2)
    np.testing.assert_allclose(cal.R.array(), R, atol=0.01)
    net = latest[keys.degradation(ns, "net")]
    assert net.n_levels == len(LINES) * SEGMENTS and net.mu.shape == [50, 2]
    assert np.all(np.abs(net.mu.array().mean(axis=0) - MU) < 5e-4)

    # a late joiner gets the latest of every model, each on its own key
    replies = late_join(open_session(), ns)
    assert replies[keys.calibration(ns)] == encode(cal)
    assert replies[keys.degradation(ns, "net")] == encode(net)
    assert {k.rsplit("/", 1)[1] for k in replies} >= {"calibration", "net", "line.L1"}
    assert running.stop() == 0

    # restart on the same file: the same models, versions and samples as the stopped service
    # last published (a unit's refit may have come after the late join above)
    store = SqliteStore(settings.db)
    stored = {keys.key_of(ns, e.message): encode(e.message) for e in store.load().models}
    store.close()
    assert stored.keys() == replies.keys()
    run_service(settings)
    assert late_join(open_session(), ns) == stored
