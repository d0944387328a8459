"""Bad-input fuzzing of every subscribing service, in-process on a real router (issue 7, item 1).

For each service: a clean run of a fixed sequence of valid traffic, then a run of the same
valid traffic interleaved with ``TF_FUZZ_N`` bad messages (default 10,000) on the service's
input keys: random bytes, valid MessagePack of the wrong types or shapes, missing fields,
NaN and inf in floats and arrays, huge declared arrays, unknown versions, keys disagreeing
with the payload or with unexpected chunks, out-of-range values and truncated payloads. It
checks that

- the service is still alive at the end (its worker thread runs, its liveliness token is
  there) and stops cleanly with exit code 0;
- every bad message produced exactly one dead letter with a non-empty reason on
  ``{ns}/deadletter/{service}`` (counted by key, so a kind of bad input that is silently
  accepted or dropped shows up by name in the failure);
- the results of the valid traffic (published outputs, in order, and the queryables'
  answers) are byte-identical to the clean run's.

End of input is detected with *markers*: a payload of one never-used MessagePack byte
(0xc1) and a counter, which every service refuses; each service handles its inputs in one
worker thread, in order, so once a marker's dead letter is back everything put before it
has been handled. The clean run uses the same markers at the same places (they come after
the valid message they follow, so they cannot change its result); they are counted among
the fuzz run's bad messages.

Each valid message is followed by a marker on its own key, and the next valid message waits
for that marker's letter. This makes the clean run reproducible: zenoh-python runs each
subscriber's callback on its own thread, so messages on keys of *different* subscriptions
of one service can be handled in another order than they were put (seen: 153 inversions in
2,000 puts over four subscriptions), and the calibration core refits per batch the worker
takes from its queue. Bad messages are still interleaved freely between the valid ones.
Bad messages are sent with at most ``WINDOW`` of them
unanswered by a dead letter (flow control: the viewer's subscriptions are ring buffers that
drop the oldest when it falls behind, by design, and dead letters are put with Zenoh's
default congestion control). No sleeps: every wait is a queue read with a timeout.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import os
import queue
import random
import sqlite3
import threading
from collections import Counter
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import msgpack
import msgspec
import numpy as np
import pytest
import zenoh

from schemas import (
    Alert,
    Calibration,
    DeadLetter,
    DegradationPosterior,
    GpsFix,
    MaintenanceEvent,
    Message,
    NDArray,
    OnboardIndex,
    PositionedChunk,
    RawChunk,
    SchemaError,
    SegmentState,
    TrcRecord,
    decode,
    encode,
    keys,
)
from schemas.wire import DTYPES
from services.alerting import service as alerting
from services.alerting.core import DAY_S
from services.alerting.testing import make_state, p_top6
from services.calibration import service as calibration
from services.calibration.calibrator import CalibratorConfig
from services.extraction import service as extraction
from services.filtering import service as filtering
from services.filtering.testing import example_models
from services.ingestion import service as ingestion
from services.ingestion.core import IngestionCore
from services.runtime.config import RuntimeConfig
from services.viewer import service as viewer
from services.viewer.core import ViewerCore
from services.viewer.testing import rrd_contents
from simulators.gateway import key_and_payload
from simulators.network import DEMO_NETWORK, demo_network
from simulators.profile import LineProfile
from simulators.train import RAW_CHANNELS, TrainSimulator

N_BAD = int(os.environ.get("TF_FUZZ_N", "10000"))  # bad messages per service
SEED = int(os.environ.get("TF_FUZZ_SEED", "7"))
BLOCK = zenoh.CongestionControl.BLOCK
PUT = zenoh.SampleKind.PUT
TIMEOUT_S = 10.0  # upper bound of one wait; normally milliseconds
WINDOW = 256  # bad messages in flight without their dead letter
MARKER = b"\xc1tf-fuzz-marker "  # 0xc1: a byte MessagePack never uses, so always refused
T0 = 1_767_225_600.0  # 2026-01-01
EXTRA = "fuzzchunk"  # an unexpected key chunk


# --- inputs, valid traffic and the services --------------------------------------------------


@dataclass
class Input:
    """One input key of a service: a valid template of its message, the wrong keys for it,
    and out-of-range field values the service must refuse."""

    key: str  # where the template belongs
    template: Message  # a valid message for ``key`` (the base of the mutations)
    wrong_keys: list[str]  # keys the service receives on which the template is wrong
    out_of_range: list[dict[str, Any]]  # field patches (of the plain map) to refuse
    prefix_key: str | None = None  # the key with an extra leading id chunk, if subscribed
    others: list[Message] = field(default_factory=list)  # valid messages of other types


@dataclass
class Spec:
    """A service under test: how to run it, its inputs, valid traffic and results."""

    name: str
    main: Callable[[RuntimeConfig, threading.Event, Path], int]
    inputs: list[Input]
    valid: list[tuple[str, bytes]]  # (key, payload) in publishing order
    outputs: list[str]  # key expressions of its outputs
    queries: list[str] = field(default_factory=list)  # answers compared at the end
    marker_keys: list[str] = field(default_factory=list)  # one per worker; default inputs[0]


def plain(message: Message) -> dict[str, Any]:
    """The message as the plain map a gateway in another language would pack."""
    return msgpack.unpackb(encode(message))


def simulated(seconds: int, phase_s: float = 300.0) -> list[RawChunk | GpsFix]:
    """RawChunks (bogie physics) and GPS fixes of train T7 on L3, in publishing order."""
    line = demo_network().lines["L3"]
    profile = LineProfile("L3", [(s.start_m, s.end_m) for s in line.segments], 1)
    sim = TrainSimulator("T7", line, profile, 1, start_t=T0, phase_s=phase_s)
    messages: list[RawChunk | GpsFix] = []
    for k in range(seconds):
        chunk = sim.raw_chunk(k)[0]
        messages += [chunk, *sim.gps_fixes(chunk.t0, chunk.t0 + 1.0)]
    return messages


def ingestion_spec(ns: str) -> Spec:
    messages = simulated(8)
    chunk = next(m for m in messages if isinstance(m, RawChunk))
    fix = next(m for m in messages if isinstance(m, GpsFix))
    small = NDArray.of(np.hstack([np.zeros((4, 6)), np.full((4, 1), 5.0)]), "f4")
    raw_t = msgspec.structs.replace(chunk, seq=3, t0=chunk.t0 + 3.0, samples=small)
    return Spec(
        name=ingestion.SERVICE,
        main=lambda conf, stop, _tmp: ingestion.main(conf, stop=stop, handle_signals=False),
        inputs=[
            Input(
                key=keys.raw(ns, "T7", "u0"),
                template=raw_t,
                wrong_keys=[
                    keys.raw(ns, "T7", "u1"),
                    keys.raw(ns, "T8", "u0"),
                    f"{keys.raw(ns, 'T7', 'u0')}/{EXTRA}",
                    f"{ns}/raw/T7",
                    f"{ns}/raw",
                ],
                out_of_range=[
                    {"seq": -1},
                    {"rate_hz": 0.0},
                    {"rate_hz": -2000.0},
                    {"rate_hz": 500.0},  # refused by the core: not the unit's rate
                    {"channels": []},
                    {"channels": ["left_z"] * 7},  # duplicates
                    {"channels": [*RAW_CHANNELS[:6], "volts"]},  # no supply_v: the core refuses
                    {"train": ""},
                    {"unit": "u 0"},
                    {"train": "T*"},
                    {"samples": plain_array(np.full((4, 7), 1.0), "f4")},  # supply 1 V
                    {"samples": plain_array(np.full((1, 7), 5.0), "f4")},  # one row
                    {"samples": plain_array(np.full((4, 7), 5.0), "u1")},  # unsigned
                ],
                prefix_key=f"{ns}/raw/{EXTRA}/T7/u0",
                others=[fix],
            ),
            Input(
                key=keys.gps(ns, "T7"),
                template=fix,
                wrong_keys=[keys.gps(ns, "T8"), f"{ns}/gps/{EXTRA}"],
                out_of_range=[
                    {"lat_deg": 95.0},
                    {"lat_deg": -90.5},
                    {"lon_deg": 181.0},
                    {"fix_quality": 3},
                    {"fix_quality": -1},
                    {"train": ""},
                    {"speed_mps": math.inf},
                    {"hdop": math.nan},
                ],
                others=[raw_t],
            ),
        ],
        valid=[key_and_payload(ns, m) for m in messages],
        outputs=[keys.accel_all(ns)],
    )


def extraction_spec(ns: str) -> Spec:
    core = IngestionCore(demo_network())
    chunks = [o for o in core.run(simulated(40), flush=False) if isinstance(o, PositionedChunk)]
    first = chunks[0]
    k = first.knot_t.shape[0]
    assert k >= 2  # so that reversed knot times are out of order
    small = msgspec.structs.replace(
        first,
        seq=5000,
        samples=NDArray.of(np.zeros((4, 6)), "f4"),
    )
    return Spec(
        name=extraction.SERVICE,
        main=lambda conf, stop, _tmp: extraction.main(conf, stop=stop, handle_signals=False),
        inputs=[
            Input(
                key=keys.accel(ns, "T7", "u0"),
                template=small,
                wrong_keys=[
                    keys.accel(ns, "T7", "u1"),
                    keys.accel(ns, "T9", "u0"),
                    f"{keys.accel(ns, 'T7', 'u0')}/{EXTRA}",
                    f"{ns}/accel/T7",
                ],
                out_of_range=[
                    {"seq": -1},
                    {"rate_hz": 0.0},
                    {"rate_hz": 1000.0},  # refused by the core: not the expected rate
                    {"channels": ["left_z"] * 6},
                    {"channels": ["a", "b", "c", "d", "e", "f"]},  # the core refuses
                    {"line": ""},
                    {"line": "L3/x"},
                    {"knot_t": plain_array(np.arange(k, dtype=float)[::-1] + T0)},
                    {"knot_chainage_m": plain_array(np.zeros(k + 1))},
                    {"knot_speed_mps": plain_array(np.zeros((k, 1)))},
                ],
                prefix_key=f"{ns}/accel/{EXTRA}/T7/u0",
                others=[GpsFix(train="T7", t=T0, lat_deg=-27.4, lon_deg=153.0)],
            )
        ],
        valid=[(keys.accel(ns, c.train, c.unit), encode(c)) for c in chunks],
        outputs=[keys.segment_keys(ns, "index")],
    )


def calibration_events() -> list[TrcRecord | OnboardIndex | MaintenanceEvent]:
    """TRC runs every ~60 days with the on-board unit riding the TRC (same run_id), a
    tamping before the 4th run of each segment, in event order."""
    rng = np.random.default_rng(42)
    H, B = np.array([[0.90, 0.05], [0.05, 0.75]]), np.array([-0.25, -0.35])
    R = np.array([[0.010, 0.002], [0.002, 0.030]])
    mu, sigma = np.array([1.0e-3, 5.0e-4]), np.array([[1.0e-4, 2.8e-5], [2.8e-5, 4.9e-5]])
    out: list[tuple[float, TrcRecord | OnboardIndex | MaintenanceEvent]] = []
    for line in ("L1", "L2"):
        for s in range(6):
            seg = f"s{s:02d}"
            z = rng.normal([1.1, 0.9], [0.35, 0.3])
            t = T0 + rng.uniform(0, 5) * DAY_S
            for run in range(5):
                if run == 3:
                    tm = t - 12 * DAY_S
                    out.append(
                        (tm, MaintenanceEvent(line=line, segment=seg, event_id=f"tamp{run}",
                                              t_start=tm, t_end=tm))
                    )  # fmt: skip
                    z = rng.normal([0.7, 0.6], 0.15) + mu * 12
                top, align = (float(v) for v in np.exp(z))
                out.append(
                    (t, TrcRecord(line=line, segment=seg, t=t, top6_mm=top, align10_mm=align,
                                  run_id=f"R{run}"))
                )  # fmt: skip
                y = H @ z + B + rng.multivariate_normal([0, 0], R)
                out.append(
                    (t + 2.0, OnboardIndex(line=line, segment=seg, train="TRC1", unit="bogie1",
                                           t=t + 2.0, top6_mm=float(np.exp(y[0])),
                                           align10_mm=float(np.exp(y[1])), speed_mps=20.0,
                                           coverage=1.0, run_id=f"R{run}"))
                )  # fmt: skip
                dt = rng.uniform(56, 77)
                z = z + mu * dt + rng.multivariate_normal([0, 0], sigma * dt)
                t += dt * DAY_S
    out.sort(key=lambda e: e[0])
    return [m for _, m in out]


def event_key(ns: str, message: TrcRecord | OnboardIndex | MaintenanceEvent) -> str:
    kind = {TrcRecord: "trc", OnboardIndex: "index", MaintenanceEvent: "maintenance"}
    return f"{ns}/{kind[type(message)]}/{message.line}/{message.segment}"


def segment_inputs(
    ns: str, templates: list[Message], extra_ranges: dict[type, list[dict[str, Any]]]
) -> list[Input]:
    """Inputs of per-segment keys (index, trc, maintenance, state, alert)."""
    kinds = {
        OnboardIndex: "index",
        TrcRecord: "trc",
        MaintenanceEvent: "maintenance",
        SegmentState: "state",
        Alert: "alert",
    }
    ranges: dict[type, list[dict[str, Any]]] = {
        OnboardIndex: [
            {"top6_mm": -1.0},
            {"top6_mm": 0.0},
            {"align10_mm": -0.5},
            {"coverage": 1.5},
            {"coverage": -0.1},
            {"quality": 2.0},
            {"speed_mps": -3.0},
            {"train": ""},
            {"segment": "s#1"},
        ],
        TrcRecord: [
            {"top6_mm": -2.0},
            {"align10_mm": 0.0},
            {"run_id": ""},
            {"run_id": "r 1"},
            {"line": "L$"},
        ],
        MaintenanceEvent: [
            {"t_end": T0 - DAY_S},  # before t_start
            {"kind": "grinding"},
            {"event_id": ""},
        ],
        SegmentState: [
            {"indicators": []},
            {"cov": plain_array(np.eye(3))},
            {"forecast_p_exceed": plain_array(np.zeros((2, 2, 2)))},
            {"width": math.inf},
            {"limit_levels": ["alert"]},  # 1 level, limits_mm has 2 rows
        ],
        Alert: [
            {"probability": 1.5},
            {"probability": -0.1},
            {"kind": "meteor"},
            {"status": "pending"},
        ],
    }
    for kind, patches in extra_ranges.items():
        ranges[kind] = ranges[kind] + patches
    inputs = []
    for template in templates:
        kind = kinds[type(template)]
        line, seg = template.line, template.segment  # type: ignore[attr-defined]
        key = f"{ns}/{kind}/{line}/{seg}"
        inputs.append(
            Input(
                key=key,
                template=template,
                wrong_keys=[
                    f"{ns}/{kind}/{line}/s_other",
                    f"{ns}/{kind}/L_other/{seg}",
                    f"{key}/{EXTRA}",
                    f"{ns}/{kind}/{line}",
                    f"{ns}/{kind}",
                ],
                out_of_range=ranges[type(template)],
                prefix_key=f"{ns}/{kind}/{EXTRA}/{line}/{seg}",
                others=[t for t in templates if type(t) is not type(template)],
            )
        )
    return inputs


def calibration_spec(ns: str) -> Spec:
    events = calibration_events()
    templates = [
        next(e for e in events if isinstance(e, cls))
        for cls in (TrcRecord, OnboardIndex, MaintenanceEvent)
    ]
    settings = calibration.Settings(
        core=CalibratorConfig(min_pairs=20, refit_every=10, samples=50, seed=7)
    )

    def main(conf: RuntimeConfig, stop: threading.Event, tmp: Path) -> int:
        run = dataclasses.replace(settings, db=tmp / "calibration.sqlite")
        return calibration.main(conf, run, stop_event=stop, handle_signals=False)

    return Spec(
        name=calibration.SERVICE,
        main=main,
        inputs=segment_inputs(ns, templates, {}),
        valid=[(event_key(ns, e), encode(e)) for e in events],
        outputs=[keys.model_all(ns)],
        queries=[keys.model_all(ns)],
    )


def filtering_spec(ns: str) -> Spec:
    cal, post = example_models(30, seed=0)
    events: list[Message] = []
    for seg in ("s1", "s2"):
        events.append(TrcRecord(line="L1", segment=seg, t=T0, top6_mm=3.0, align10_mm=2.5,
                                run_id="r1"))  # fmt: skip
        for k, (top6, align10) in enumerate([(2.4, 1.7), (2.6, 1.6), (2.5, 1.9), (3.1, 2.2)]):
            events.append(
                OnboardIndex(line="L1", segment=seg, train="T1", unit="u1",
                             t=T0 + (k + 1) * 7 * DAY_S, top6_mm=top6, align10_mm=align10,
                             speed_mps=30.0, coverage=1.0)
            )  # fmt: skip
        events.append(
            MaintenanceEvent(line="L1", segment=seg, event_id="m1", t_start=T0 + 30 * DAY_S,
                             t_end=T0 + 32 * DAY_S)
        )  # fmt: skip
    events.append(OnboardIndex(line="L1", segment="s1", train="T2", unit="u1",
                               t=T0 + 40 * DAY_S, top6_mm=2.2, align10_mm=1.5, speed_mps=25.0,
                               coverage=0.9))  # fmt: skip
    cal2 = msgspec.structs.replace(cal, version=2, b=NDArray.of([-0.2, -0.3]))
    templates = [events[0], events[1], events[5]]
    inputs = segment_inputs(ns, templates, {})
    bad_r = plain_array([[-1.0, 0.0], [0.0, -1.0]])
    bad_cov = plain_array(np.broadcast_to(-np.eye(2), (30, 2, 2)))
    inputs += [
        Input(
            key=keys.calibration(ns),
            template=cal,
            wrong_keys=[keys.degradation(ns, "net"), keys.trc(ns, "L1", "s1")],
            out_of_range=[
                {"version": 0},
                {"n_pairs": 0},
                {"H": plain_array(np.ones((3, 2)))},
                # newer versions the core must refuse (not positive definite, wrong names)
                {"version": 1000, "R": bad_r},
                {"version": 1000, "indicators": ["a", "b"]},
            ],
            others=[post, events[0]],
        ),
        Input(
            key=keys.degradation(ns, "net"),
            template=post,
            wrong_keys=[
                keys.degradation(ns, "line.L1"),
                f"{keys.degradation(ns, 'net')}/{EXTRA}",
                f"{ns}/model/degradation",
                keys.calibration(ns),
            ],
            out_of_range=[
                {"version": 0},
                {"group": "n et"},
                {"sigma": plain_array(np.zeros((29, 2, 2)))},
                {"version": 1000, "sigma": bad_cov},  # not positive semi-definite
            ],
            others=[cal, events[1]],
        ),
    ]
    messages: list[Message] = [cal, post, *events[:8], cal2, *events[8:]]

    def key_of(m: Message) -> str:
        if isinstance(m, Calibration):
            return keys.calibration(ns)
        if isinstance(m, DegradationPosterior):
            return keys.degradation(ns, m.group)
        return event_key(ns, m)  # type: ignore[arg-type]

    def main(conf: RuntimeConfig, stop: threading.Event, tmp: Path) -> int:
        db = tmp / "filtering.sqlite"
        return filtering.main(conf, db=db, stop=stop, handle_signals=False)

    return Spec(
        name=filtering.SERVICE,
        main=main,
        inputs=inputs,
        valid=[(key_of(m), encode(m)) for m in messages],
        outputs=[keys.segment_keys(ns, "state")],
        queries=[keys.q_state_all(ns)],
    )


def state_probability_ranges() -> list[dict[str, Any]]:
    """Probabilities outside [0, 1] in a SegmentState."""
    return [
        {"p_exceed": plain_array([[1.5, 0.0], [0.0, 0.0]])},
        {"forecast_p_exceed": plain_array(np.full((3, 2, 2), -0.5))},
    ]


def alerting_spec(ns: str) -> Spec:
    trc = [
        TrcRecord(line="L1", segment="s1", t=T0 + k * 60 * DAY_S, top6_mm=3.0, align10_mm=2.0,
                  run_id=f"r{k}")
        for k in range(3)
    ]  # fmt: skip
    states = [
        make_state(T0 + DAY_S, p_exceed=p_top6(1, 0.72)),
        make_state(T0 + 2 * DAY_S, p_exceed=p_top6(1, 0.8), nis=40.0),
        make_state(T0 + 3 * DAY_S, p_exceed=p_top6(1, 0.1)),
        make_state(T0 + 4 * DAY_S, segment="s2", p_exceed=p_top6(0, 0.9)),
        make_state(T0 + 5 * DAY_S, segment="s2", p_exceed=p_top6(0, 0.95)),
        make_state(T0 + 200 * DAY_S, segment="s3"),  # s1 and s2 stale
        make_state(T0 + 201 * DAY_S, p_exceed=p_top6(0, 0.3)),
    ]
    messages: list[Message] = [trc[0], *states[:3], trc[1], *states[3:6], trc[2], *states[6:]]
    inputs = segment_inputs(ns, [states[0], trc[0]], {SegmentState: state_probability_ranges()})

    def key_of(m: Message) -> str:
        kind = "trc" if isinstance(m, TrcRecord) else "state"
        return f"{ns}/{kind}/{m.line}/{m.segment}"  # type: ignore[attr-defined]

    def main(conf: RuntimeConfig, stop: threading.Event, tmp: Path) -> int:
        db = tmp / "alerting.sqlite"
        return alerting.main(conf, db=db, stop=stop, handle_signals=False)

    return Spec(
        name=alerting.SERVICE,
        main=main,
        inputs=inputs,
        valid=[(key_of(m), encode(m)) for m in messages],
        outputs=[keys.segment_keys(ns, "alert")],
        queries=[keys.q_alerts(ns), keys.q_plan(ns)],
    )


class RecordingCore(ViewerCore):
    """The viewer's core, also keeping every message it logged (encoded)."""

    logged: list[bytes]

    def take(self, messages):  # type: ignore[no-untyped-def]
        messages = list(messages)
        RecordingCore.logged.extend(encode(m) for m in messages)
        return super().take(messages)


def viewer_spec(ns: str) -> Spec:
    line = demo_network().lines["L2"]
    seg, hot = line.segments[1].id, line.segments[7].id
    lon, lat = map(float, line.lonlat_at(line.segments[1].mid_m))
    states = [
        make_state(T0 + k * DAY_S, line="L2", segment=seg, p_exceed=p_top6(1, 0.1 * k))
        for k in range(3)
    ]
    hot_state = make_state(T0, line="L2", segment=hot, p_exceed=p_top6(1, 0.95))
    index = OnboardIndex(line="L2", segment=seg, train="T7", unit="u1", t=T0 + 0.5 * DAY_S,
                         top6_mm=4.4, align10_mm=3.2, speed_mps=22.0, coverage=0.9)  # fmt: skip
    trc = TrcRecord(line="L2", segment=seg, t=T0, top6_mm=4.0, align10_mm=3.0, run_id="r1")
    alerts = [
        Alert(line="L2", segment=hot, t=T0 + 60, kind="exceedance", status=status,
              indicator="top6", level="intervention", probability=0.95)
        for status in ("raised", "cleared")
    ]  # fmt: skip
    fixes = [GpsFix(train="T7", t=T0 + 5 + k, lat_deg=lat, lon_deg=lon) for k in range(3)]
    messages: list[Message] = [states[0], trc, fixes[0], index, hot_state, alerts[0], fixes[1],
                               states[1], alerts[1], states[2], fixes[2]]  # fmt: skip
    inputs = segment_inputs(
        ns, [states[0], index, trc, alerts[0]], {SegmentState: state_probability_ranges()}
    )
    inputs.append(
        Input(
            key=keys.gps(ns, "T7"),
            template=fixes[0],
            wrong_keys=[keys.gps(ns, "T8"), f"{ns}/gps/{EXTRA}"],
            out_of_range=[{"lat_deg": 95.0}, {"lon_deg": -181.0}, {"fix_quality": 7}],
            others=[trc],
        )
    )

    def key_of(m: Message) -> str:
        if isinstance(m, GpsFix):
            return keys.gps(ns, m.train)
        kind = {SegmentState: "state", OnboardIndex: "index", TrcRecord: "trc", Alert: "alert"}
        return f"{ns}/{kind[type(m)]}/{m.line}/{m.segment}"  # type: ignore[attr-defined]

    def main(conf: RuntimeConfig, stop: threading.Event, tmp: Path) -> int:
        sink = viewer.Sink("rrd", path=tmp / "viewer.rrd")
        return viewer.main(conf, DEMO_NETWORK, sink, stop=stop, handle_signals=False)

    return Spec(
        name=viewer.SERVICE,
        main=main,
        inputs=inputs,
        valid=[(key_of(m), encode(m)) for m in messages],
        outputs=[],  # the viewer publishes nothing: its results are the logged messages
        # one subscription worker per kind: a marker on each says that worker is through
        marker_keys=[i.key for i in inputs],
    )


SPECS: dict[str, Callable[[str], Spec]] = {
    "ingestion": ingestion_spec,
    "extraction": extraction_spec,
    "calibration": calibration_spec,
    "filtering": filtering_spec,
    "alerting": alerting_spec,
    "viewer": viewer_spec,
}


# --- bad messages ------------------------------------------------------------------------------


def plain_array(values: Any, dtype: str = "f8") -> dict[str, Any]:
    """An array field as a gateway packs it (``NDArray.of`` would refuse some of these)."""
    a = np.ascontiguousarray(values, dtype=DTYPES[dtype])
    return {"dtype": dtype, "shape": list(a.shape), "data": a.tobytes()}


@dataclass(frozen=True)
class Bad:
    kind: str
    key: str
    payload: bytes
    detail: str = ""  # what was changed, for failure messages


KINDS = (
    "random_bytes",
    "not_a_map",
    "wrong_type",
    "missing_field",
    "nan_inf",
    "nan_in_array",
    "huge_array",
    "unknown_version",
    "wrong_key",
    "wrong_message_type",
    "out_of_range",
    "truncated",
    "extra_key_prefix",
    "deep_nesting",
    "big_int",
    "huge_float",
    "far_time",
    "bad_id",
    "huge_unknown",
    "oversize",
)
TIME_FIELDS = ("t", "t0", "t_start", "t_end", "last_trc_t")
ID_FIELDS = ("train", "unit", "line", "segment", "run_id", "event_id", "group", "posterior_group")
FAR_TIMES = (0.0, -1e9, 32_503_680_000.0, 2.0**63, -(2.0**63), 2**63 - 1, -(2**63))  # 3000 AD
BIG_INTS = (2**63, 2**64 - 1, 2**63 - 1, -(2**63), 2**53 + 1)  # MessagePack stops at 64 bits
BAD_IDS = ("@x", "@", "a/b", "L1/s1", "a b", "a\tb", "a\nb", "a\x00b", "x" * 65, "a*", "$a")
HUGE_BYTES = 5_000_000  # an unknown field of 5 MB
HUGE_BUDGET = 6  # payloads of megabytes per run: they cost the 2-core CI seconds each
if os.environ.get("TF_FUZZ_KINDS"):  # a comma-separated subset, e.g. to bisect a failure
    KINDS = tuple(os.environ["TF_FUZZ_KINDS"].split(","))


class Fuzzer:
    """Seeded bad messages for a service's inputs, each checked to be refusable."""

    def __init__(self, inputs: list[Input], seed: int) -> None:
        self.inputs = inputs
        self.rng = random.Random(seed)
        self.np_rng = np.random.default_rng(seed)
        self.last_valid: dict[str, bytes] = {}  # per input key: the last valid payload sent
        self.huge_left = HUGE_BUDGET

    def next(self) -> Bad:
        while True:
            inp = self.rng.choice(self.inputs)
            kind = self.rng.choice(KINDS)
            self.detail = ""
            made = getattr(self, f"_{kind}")(inp)
            if made is not None:
                key, payload = made
                return Bad(kind, key, payload, self.detail)

    # each returns (key, payload) or None when the kind does not apply to the input

    def _random_bytes(self, inp: Input) -> tuple[str, bytes] | None:
        n = self.rng.choice((0, 1, 2, 8, 64, 300))
        return inp.key, self.rng.randbytes(n) if n else b""

    def _not_a_map(self, inp: Input) -> tuple[str, bytes] | None:
        values = list(plain(inp.template).values())
        choice = self.rng.choice([values, "a string", 42, None, 3.5, [1, 2, 3], b"\x00\x01", True])
        return inp.key, msgpack.packb(choice)

    def _fields(self, inp: Input) -> dict[str, msgspec.structs.FieldInfo]:
        return {f.encode_name: f for f in msgspec.structs.fields(type(inp.template))}

    def _wrong_type(self, inp: Input) -> tuple[str, bytes] | None:
        m = plain(inp.template)
        name = self.rng.choice(list(m))
        m[name] = self.rng.choice(wrong_values(m[name], optional=self._optional(inp, name)))
        self.detail = f"{name}={m[name]!r:.40}"
        return inp.key, msgpack.packb(front(m, name))

    def _optional(self, inp: Input, name: str) -> bool:
        info = self._fields(inp)[name]
        return "None" in repr(info.type)

    def _missing_field(self, inp: Input) -> tuple[str, bytes] | None:
        m = plain(inp.template)
        required = [f.encode_name for f in self._fields(inp).values() if f.required]
        for name in self.rng.sample(required, k=self.rng.randint(1, len(required))):
            del m[name]
        return inp.key, msgpack.packb(m)

    def _nan_inf(self, inp: Input) -> tuple[str, bytes] | None:
        m = plain(inp.template)
        floats = [k for k, v in m.items() if isinstance(v, float) or self._is_float(inp, k)]
        if not floats:
            return None
        name = self.rng.choice(floats)
        m[name] = self.rng.choice((math.nan, math.inf, -math.inf))
        self.detail = f"{name}={m[name]}"
        return inp.key, msgpack.packb(front(m, name))

    def _is_float(self, inp: Input, name: str) -> bool:
        return "float" in repr(self._fields(inp)[name].type)

    def _arrays(self, m: dict[str, Any]) -> list[str]:
        return [k for k, v in m.items() if isinstance(v, dict) and {"dtype", "shape"} <= set(v)]

    def _nan_in_array(self, inp: Input) -> tuple[str, bytes] | None:
        m = plain(inp.template)
        names = [k for k in self._arrays(m) if math.prod(m[k]["shape"]) > 0]
        if not names:
            return None
        name = self.rng.choice(names)
        a = NDArray(**m[name]).array().astype(self.rng.choice(("<f4", "<f8")))
        a.flat[self.rng.randrange(a.size)] = self.rng.choice((math.nan, math.inf, -math.inf))
        m[name] = {"dtype": a.dtype.str[1:], "shape": list(a.shape), "data": a.tobytes()}
        self.detail = f"{name} with NaN or inf"
        return inp.key, msgpack.packb(front(m, name))

    def _huge_array(self, inp: Input) -> tuple[str, bytes] | None:
        m = plain(inp.template)
        names = self._arrays(m)
        if not names:  # no array field: a huge list where a scalar belongs
            name = self.rng.choice(list(m))
            m[name] = [1.0] * (100_000 if self.rng.random() < 0.01 else 1_000)
            self.detail = f"{name}=[1.0] * {len(m[name])}"
            return inp.key, msgpack.packb(front(m, name))
        name = self.rng.choice(names)
        arr = m[name]
        variant = self.rng.randrange(5)
        if variant == 0:  # declared shape far too large, little data
            arr["shape"] = [10**7, *arr["shape"][1:]] if arr["shape"] else [10**7]
        elif variant == 1:  # declared shape that overflows any index type
            arr["shape"] = [2**62, 2**62]
        elif variant == 2:  # data length disagreeing with the shape
            arr["data"] = arr["data"][:-1] if arr["data"] else b"\x00"
        elif variant == 3:  # negative extent
            arr["shape"] = [-1, *arr["shape"][1:]]
        else:  # an unknown dtype
            arr["dtype"] = self.rng.choice(("f16", "c8", "<f8", "", "object"))
        self.detail = f"{name}: {arr['dtype']} {arr['shape']} {len(arr['data'])} bytes"
        return inp.key, msgpack.packb(front(m, name))

    def _unknown_version(self, inp: Input) -> tuple[str, bytes] | None:
        m = plain(inp.template)
        m["v"] = self.rng.choice((0, 2, 3, 99, -1, 2**40))
        return inp.key, msgpack.packb(m)

    def _wrong_key(self, inp: Input) -> tuple[str, bytes] | None:
        return self.rng.choice(inp.wrong_keys), encode(inp.template)

    def _wrong_message_type(self, inp: Input) -> tuple[str, bytes] | None:
        payload = encode(self.rng.choice(inp.others))
        try:
            decode(payload, type(inp.template))
        except SchemaError:
            return inp.key, payload
        # a payload of another type that decodes as this one (its fields are a superset):
        # nothing on the wire tells them apart, so it is not sent (see the report)
        return None

    def _out_of_range(self, inp: Input) -> tuple[str, bytes] | None:
        m = plain(inp.template)
        patch = self.rng.choice(inp.out_of_range)
        m.update(patch)
        self.detail = f"{patch!r:.80}"
        return inp.key, msgpack.packb(front(m, *patch))

    def _refused(self, inp: Input, m: dict[str, Any], *first: str) -> tuple[str, bytes] | None:
        """``m`` packed on the input's key if its type refuses it, else None (not sent)."""
        payload = msgpack.packb(front(m, *first))
        try:
            decode(payload, type(inp.template))
        except SchemaError:
            return inp.key, payload
        return None

    def _deep_nesting(self, inp: Input) -> tuple[str, bytes] | None:
        # an unknown field holding a list in a list in ... (msgpack's packer refuses to
        # nest this deep, so the map is written by hand, the deep field first)
        m = plain(inp.template)
        depth = self.rng.choice((33, 100, 1_000, 3_000, 10_000))
        self.detail = f"extra field nested {depth} deep"
        body = b"".join(msgpack.packb(k) + msgpack.packb(v) for k, v in m.items())
        deep = msgpack.packb("fuzz_deep") + b"\x91" * depth + b"\x90"
        return inp.key, map_header(len(m) + 1) + deep + body

    def _big_int(self, inp: Input) -> tuple[str, bytes] | None:
        # integers beyond int64 and beyond SQLite's INTEGER, in integer or float fields
        m = plain(inp.template)
        names = [k for k, v in m.items() if isinstance(v, int | float) and not isinstance(v, bool)]
        self.rng.shuffle(names)
        value = self.rng.choice(BIG_INTS)
        for name in names:
            made = self._refused(inp, m | {name: value}, name)
            if made is not None:
                self.detail = f"{name}={value}"
                return made
        return None

    def _huge_float(self, inp: Input) -> tuple[str, bytes] | None:
        m = plain(inp.template)
        names = [k for k, v in m.items() if isinstance(v, float) or self._is_float(inp, k)]
        self.rng.shuffle(names)
        value = self.rng.choice((1e308, -1e308, 1.7976931348623157e308))
        for name in names:
            made = self._refused(inp, m | {name: value}, name)
            if made is not None:
                self.detail = f"{name}={value}"
                return made
        return None

    def _far_time(self, inp: Input) -> tuple[str, bytes] | None:
        m = plain(inp.template)
        names = [k for k in TIME_FIELDS if k in m]
        if not names:
            return None
        name, value = self.rng.choice(names), self.rng.choice(FAR_TIMES)
        if name == "t_start":  # keep t_end >= t_start out of the way: both move
            m["t_end"] = value
        self.detail = f"{name}={value}"
        return self._refused(inp, m | {name: value}, name)  # a model's t = 0 is a prior

    def _bad_id(self, inp: Input) -> tuple[str, bytes] | None:
        m = plain(inp.template)
        names = [k for k in ID_FIELDS if k in m]
        if not names:
            return None
        name, value = self.rng.choice(names), self.rng.choice(BAD_IDS)
        self.detail = f"{name}={value!r}"
        return self._refused(inp, m | {name: value}, name)

    def _huge_unknown(self, inp: Input) -> tuple[str, bytes] | None:
        # an unknown field of 5 MB: beyond every message's size limit
        if self.huge_left <= 0:
            return None
        self.huge_left -= 1
        m = plain(inp.template)
        m["fuzz_blob"] = self.rng.choice((b"\x00" * HUGE_BYTES, "x" * HUGE_BYTES))
        self.detail = f"unknown field of {HUGE_BYTES} bytes"
        return inp.key, msgpack.packb(m)

    def _oversize(self, inp: Input) -> tuple[str, bytes] | None:
        # a valid message padded by an unknown field to just beyond its type's size limit
        limit = type(inp.template).MAX_BYTES
        if limit > 1_000_000:
            if self.huge_left <= 0:
                return None
            self.huge_left -= 1
        m = plain(inp.template)
        size = len(msgpack.packb(m))
        pad = limit - size + self.rng.randint(1, 100)
        m["fuzz_pad"] = b"\x00" * pad
        self.detail = f"{len(msgpack.packb(m))} bytes > {limit}"
        return inp.key, msgpack.packb(m)

    def _truncated(self, inp: Input) -> tuple[str, bytes] | None:
        payload = encode(inp.template)
        return inp.key, payload[: self.rng.randrange(1, len(payload))]

    def _extra_key_prefix(self, inp: Input) -> tuple[str, bytes] | None:
        # a valid message already sent, again, on its key with an extra leading chunk
        if inp.prefix_key is None or inp.key not in self.last_valid:
            return None
        return inp.prefix_key, self.last_valid[inp.key]


def front(m: dict[str, Any], *names: str) -> dict[str, Any]:
    """``m`` with ``names`` first: the mutation lands in the dead letter's 256-byte head."""
    return {n: m[n] for n in names if n in m} | m


def map_header(n: int) -> bytes:
    """The MessagePack header of a map of ``n`` pairs."""
    return bytes([0x80 | n]) if n < 16 else b"\xde" + n.to_bytes(2, "big")


def wrong_values(value: Any, *, optional: bool) -> list[Any]:
    """Values of another type than ``value`` that a strict decoder must refuse."""
    if isinstance(value, bool):
        return ["true", 2.5, [True]]
    if isinstance(value, int):
        return ["1", 1.5, [1], {"n": 1}]
    if isinstance(value, float):
        return ["1.0", [1.0], {"x": 1.0}, b"\x00"] + ([] if optional else [None])
    if isinstance(value, str):
        return [5, 1.5, ["a"], {"a": 1}, None]
    if isinstance(value, list):
        return ["abc", 7, {"a": 1}, [1, 2]]
    if isinstance(value, dict):
        return [[1, 2, 3], "array", {"dtype": "f8"}, {"dtype": 8, "shape": [1], "data": b""}]
    if value is None:
        return ["x", [1.0], {"a": 1}]
    return [None]


# --- running a service -------------------------------------------------------------------------


class Letters:
    """Dead letters of the service, read with a timeout; markers recognised by their head."""

    def __init__(self) -> None:
        self.queue: queue.Queue[DeadLetter] = queue.Queue()
        self.received: list[DeadLetter] = []

    def __call__(self, sample: zenoh.Sample) -> None:
        self.queue.put(decode(sample.payload.to_bytes(), DeadLetter))

    def take(self, timeout: float = TIMEOUT_S) -> DeadLetter:
        try:
            letter = self.queue.get(timeout=timeout)
        except queue.Empty:
            raise AssertionError(
                f"no dead letter within {timeout} s ({len(self.received)} so far)"
            ) from None
        self.received.append(letter)
        return letter

    def until(self, head: bytes) -> None:
        while self.take().payload_head != head:
            pass


@dataclass
class Result:
    outputs: list[tuple[str, bytes]]  # (key without the namespace, payload), in order
    answers: dict[str, dict[str, bytes]]  # query -> {key without the namespace: payload}
    letters: list[DeadLetter]
    logged: list[bytes]  # viewer only: the messages it logged
    rrd: dict[str, dict[str, int]]  # viewer only: data rows per entity


class Run:
    """One service in a thread on its own namespace, a client session publishing to it."""

    def __init__(self, spec: Spec, conf: RuntimeConfig, session: zenoh.Session, tmp: Path) -> None:
        self.spec, self.conf, self.session, self.tmp = spec, conf, session, tmp
        self.ns = conf.ns
        self.outputs: queue.Queue[tuple[str, bytes]] = queue.Queue()
        self.letters = Letters()
        self.stop = threading.Event()
        self.exit: list[int] = []
        self.markers = 0
        self.subscribers: list[zenoh.Subscriber] = []
        self._letters_key = zenoh.KeyExpr(keys.deadletter(self.ns, spec.name))
        self._outputs = [zenoh.KeyExpr(key) for key in spec.outputs]

    def __enter__(self) -> Run:
        # ONE subscriber for outputs and dead letters: a service puts an output before the
        # letter of the marker behind it, and one callback sees them in that order (separate
        # subscribers run on separate threads: under load an output could still be on its
        # way when `sync` saw the last marker's letter).
        self.subscribers.append(
            self.session.declare_subscriber(
                f"{self.ns}/**", self._on_sample, allowed_origin=zenoh.Locality.REMOTE
            )
        )
        alive = queue.Queue()
        self.subscribers.append(
            self.session.liveliness().declare_subscriber(self.alive_key, alive.put)
        )
        self.thread = threading.Thread(
            target=lambda: self.exit.append(self.spec.main(self.conf, self.stop, self.tmp)),
            name=f"{self.spec.name}-under-test",
        )
        self.thread.start()
        try:
            sample = alive.get(timeout=TIMEOUT_S)
        except queue.Empty:
            raise AssertionError(f"{self.spec.name} did not come alive") from None
        assert sample.kind == PUT
        return self

    def __exit__(self, *_exc: object) -> None:
        self.stop.set()
        self.thread.join(TIMEOUT_S)
        for subscriber in self.subscribers:
            subscriber.undeclare()

    @property
    def alive_key(self) -> str:
        return keys.alive(self.ns, self.spec.name, "test")

    def _on_sample(self, sample: zenoh.Sample) -> None:
        if sample.key_expr == self._letters_key:
            self.letters(sample)
        elif any(sample.key_expr.intersects(output) for output in self._outputs):
            self.outputs.put((str(sample.key_expr), sample.payload.to_bytes()))

    def put(self, key: str, payload: bytes) -> None:
        self.session.put(key, payload, congestion_control=BLOCK)

    def marker(self, key: str) -> bytes:
        """Put a marker on ``key``; its payload (= its dead letter's head)."""
        self.markers += 1
        payload = MARKER + str(self.markers).encode()
        self.put(key, payload)
        return payload

    def until_matched(self, keys_: set[str]) -> None:
        """Until the router routes each key to the service: a put right after the service
        declared its subscribers may reach the router first and go nowhere."""
        for key in sorted(keys_):
            publisher = self.session.declare_publisher(key)
            matched: queue.Queue[bool] = queue.Queue()
            listener = publisher.declare_matching_listener(
                lambda status, q=matched: q.put(status.matching)
            )
            try:
                if not publisher.matching_status.matching:
                    while not matched.get(timeout=TIMEOUT_S):
                        pass
            finally:
                listener.undeclare()
                publisher.undeclare()

    def sync(self) -> None:
        """Until every worker has handled everything put so far, and its outputs are out."""
        for _ in range(2):  # twice: a batching worker publishes after a batch's letters
            for key in self.spec.marker_keys or [self.spec.inputs[0].key]:
                self.letters.until(self.marker(key))

    def drive(self, bad: Iterator[Bad] | None, n_bad: int) -> list[Bad]:
        """Publish the valid traffic with ``n_bad`` bad messages spread between it."""
        spec, rng = self.spec, random.Random(SEED)
        self.until_matched({k for k, _ in spec.valid} | {i.key for i in spec.inputs})
        slots = Counter(rng.randrange(len(spec.valid) + 1) for _ in range(n_bad))
        sent: list[Bad] = []

        def send_bad(count: int) -> None:
            for _ in range(count):
                assert bad is not None
                while len(sent) + self.markers - len(self.letters.received) >= WINDOW:
                    try:
                        self.letters.take()
                    except AssertionError as e:
                        lost = unlettered(sent, self.letters.received, self.ns)
                        raise AssertionError(
                            f"{spec.name}: {e}; without a letter: {lost}"
                        ) from None
                item = next(bad)
                sent.append(item)
                self.put(item.key, item.payload)

        for i, (key, payload) in enumerate(spec.valid):
            send_bad(slots[i])
            self.put(key, payload)
            if isinstance(bad, FuzzIterator):
                bad.fuzzer.last_valid[key] = payload
            self.letters.until(self.marker(key))  # handled before the next valid message
        send_bad(slots[len(spec.valid)])
        self.sync()
        return sent

    def result(self) -> Result:
        outputs = []
        while True:
            try:
                key, payload = self.outputs.get_nowait()
            except queue.Empty:
                break
            outputs.append((strip(self.ns, key), payload))
        answers = {}
        for selector in self.spec.queries:
            replies = self.session.get(selector, timeout=TIMEOUT_S)
            answers[strip(self.ns, selector)] = {
                strip(self.ns, str(r.ok.key_expr)): r.ok.payload.to_bytes()
                for r in replies
                if r.ok is not None
            }
        return Result(outputs, answers, list(self.letters.received), [], {})

    def assert_alive(self) -> None:
        assert self.thread.is_alive(), f"{self.spec.name} has stopped"
        tokens: list[str] = []
        for _ in range(12):  # an unanswered query on a loaded 2-core machine is not a dead token
            tokens = [
                str(r.ok.key_expr)
                for r in self.session.liveliness().get(self.alive_key, timeout=TIMEOUT_S)
                if r.ok is not None
            ]
            if tokens:
                break
        assert tokens == [self.alive_key], f"{self.spec.name}: liveliness token gone"


class FuzzIterator:
    def __init__(self, fuzzer: Fuzzer) -> None:
        self.fuzzer = fuzzer

    def __iter__(self) -> FuzzIterator:
        return self

    def __next__(self) -> Bad:
        return self.fuzzer.next()


def strip(ns: str, key: str) -> str:
    return key.removeprefix(f"{ns}/")


def check_refusable(spec: Spec, bad: Bad, ns: str) -> None:
    """Self-check of the generator: the payload does not decode, or its key is wrong, or it is
    one of the out-of-range cases only the service's core refuses."""
    if bad.kind in ("wrong_key", "extra_key_prefix", "out_of_range"):
        return
    inp = next(i for i in spec.inputs if i.key == bad.key)
    with pytest.raises(SchemaError):
        decode(bad.payload, type(inp.template))


def run_service(
    spec: Spec,
    conf: RuntimeConfig,
    session: zenoh.Session,
    tmp: Path,
    n_bad: int,
) -> tuple[Result, list[Bad]]:
    tmp.mkdir()
    RecordingCore.logged = []
    fuzzer = Fuzzer(spec.inputs, SEED)
    with Run(spec, conf, session, tmp) as run:
        sent = run.drive(FuzzIterator(fuzzer) if n_bad else None, n_bad)
        result = run.result()
        run.assert_alive()
        markers = run.markers
    assert run.exit == [0] and not run.thread.is_alive(), f"{spec.name}: exit {run.exit}"
    for bad in sent[:2000]:
        check_refusable(spec, bad, conf.ns)
    result.logged = list(RecordingCore.logged)
    if spec.name == viewer.SERVICE:
        contents = rrd_contents(tmp / "viewer.rrd")
        result.rrd = {k: v for k, v in contents.items() if k.startswith(("segments/", "alerts"))}
    # markers are bad messages too: their letters are part of the accounting
    sent += [Bad("marker", "", b"")] * markers
    return result, sent


def unlettered(sent: list[Bad], letters: list[DeadLetter], ns: str) -> dict[str, Any]:
    """For a failure message: the bad messages whose payload head no dead letter of their
    key carries, by kind and detail (letters of refusals by a core that re-encodes the
    message carry another head: those are counted apart, per key)."""
    heads = Counter((strip(ns, letter.key), letter.payload_head) for letter in letters)
    missing: Counter[str] = Counter()
    for bad in sent:
        if bad.kind == "marker":
            continue
        head = (strip(ns, bad.key), bad.payload[:256])
        if heads[head]:
            heads[head] -= 1
        else:
            missing[f"{bad.kind} on {head[0]}: {bad.detail or head[1][:40]!r}"] += 1
    unknown = Counter(
        k for (k, h), n in heads.items() if not h.startswith(MARKER) for _ in range(n)
    )
    return {"no letter": dict(missing.most_common(12)), "letters of other heads": dict(unknown)}


def first_difference(clean: list[tuple[str, bytes]], fuzz: list[tuple[str, bytes]]) -> str:
    """Where two output sequences part, with the differing fields of the decoded messages."""
    for i, (a, b) in enumerate(zip(clean, fuzz, strict=False)):
        if a != b:
            ma, mb = msgpack.unpackb(a[1]), msgpack.unpackb(b[1])
            fields = {
                k: (ma.get(k), mb.get(k)) for k in set(ma) | set(mb) if ma.get(k) != mb.get(k)
            }
            return f"output {i} on {a[0]} / {b[0]}: clean vs fuzz {fields}"[:3000]
    return (
        f"{len(clean)} outputs in the clean run, {len(fuzz)} in the fuzz run; extra: "
        + (repr(clean[len(fuzz) :] or fuzz[len(clean) :])[:2000])
    )


# --- the test ----------------------------------------------------------------------------------


@pytest.fixture
def viewer_records(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(viewer, "ViewerCore", RecordingCore)


@pytest.mark.parametrize("name", list(SPECS))
def test_bad_input_is_dead_lettered_and_changes_nothing(
    name: str,
    router: str,
    namespace: str,
    open_session: Callable[..., zenoh.Session],
    tmp_path: Path,
    viewer_records: None,
):
    session = open_session()

    def conf(suffix: str) -> RuntimeConfig:
        return RuntimeConfig(
            ns=f"{namespace}{suffix}",
            instance="test",
            zenoh={"mode": "client", "connect": {"endpoints": [router]}},
        )

    clean_spec = SPECS[name](f"{namespace}c")
    clean, clean_sent = run_service(clean_spec, conf("c"), session, tmp_path / "clean", 0)
    fuzz_spec = SPECS[name](f"{namespace}f")
    n_bad = max(0, N_BAD - len(clean_sent))  # the markers count among the bad messages
    fuzz, sent = run_service(fuzz_spec, conf("f"), session, tmp_path / "fuzz", n_bad)

    # every bad message (markers included) has exactly one dead letter with a reason
    assert all(letter.reason.strip() for letter in fuzz.letters)
    assert all(letter.service == name for letter in fuzz.letters)
    ns = f"{namespace}f"
    by_key_sent = Counter(strip(ns, b.key) for b in sent if b.kind != "marker")
    by_key_got = Counter(
        strip(ns, letter.key)
        for letter in fuzz.letters
        if not letter.payload_head.startswith(MARKER)
    )
    assert by_key_got == by_key_sent, (
        f"{name}: {len(fuzz.letters)} dead letters for {len(sent)} bad messages; "
        f"without a letter: {unlettered(sent, fuzz.letters, ns)}"
    )
    assert len(fuzz.letters) == len(sent) == max(N_BAD, len(clean_sent))

    # the valid traffic's results are those of the clean run, byte for byte
    difference = first_difference(clean.outputs, fuzz.outputs)
    assert fuzz.outputs == clean.outputs, f"{name}: outputs differ from the clean run: {difference}"
    assert fuzz.answers == clean.answers, f"{name}: queryable answers differ from the clean run"
    if name == viewer.SERVICE:
        # A display is latest-only: its inbox replaces a held message by a newer one of the
        # same segment and day (and GPS fix of the same train) when they come faster than it
        # draws, so how many of the earlier ones it logged depends on timing. What must
        # hold: it logged only valid messages, the newest of each key in both runs, and the
        # same entities.
        valid = {payload for _, payload in clean_spec.valid}
        newest = set(dict(clean_spec.valid).values())
        for run in (clean, fuzz):
            assert set(run.logged) <= valid, f"{name}: logged a message it was not sent"
            assert newest <= set(run.logged), f"{name}: the newest of a key was not logged"
        assert fuzz.rrd.keys() == clean.rrd.keys() and clean.rrd
    else:
        assert fuzz.logged == clean.logged, f"{name}: logged messages differ from the clean run"
        assert clean.outputs, f"{name}: the valid traffic gave no output to compare"
    if name == filtering.SERVICE:  # unknown fields are not stored: the same bytes as clean
        assert stored_bytes(tmp_path / "fuzz") == stored_bytes(tmp_path / "clean")


def stored_bytes(run_dir: Path) -> tuple[int, int]:
    """(rows, payload bytes) in a filtering run's store."""
    with contextlib.closing(sqlite3.connect(run_dir / "filtering.sqlite")) as db:
        return db.execute(
            "SELECT COUNT(*) + (SELECT COUNT(*) FROM models),"
            " COALESCE(SUM(LENGTH(payload)), 0)"
            " + (SELECT COALESCE(SUM(LENGTH(payload)), 0) FROM models) FROM events"
        ).fetchone()
