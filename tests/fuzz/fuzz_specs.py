"""The services under fuzz: how each one runs in a thread, its input keys with a valid
template of each, the valid traffic it gets and where its results are (the harness is
tests/fuzz/fuzz_harness.py, the test tests/fuzz/test_fuzz.py)."""

from __future__ import annotations

import dataclasses
import math
import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import msgpack
import msgspec
import numpy as np

from schemas import (
    DAY_S,
    Alert,
    Calibration,
    DegradationPosterior,
    GpsFix,
    MaintenanceEvent,
    Message,
    NDArray,
    OnboardIndex,
    PositionedChunk,
    RawChunk,
    SegmentState,
    TrcRecord,
    encode,
    keys,
)
from schemas.wire import DTYPES
from services.alerting import service as alerting
from services.alerting.testing import make_state, p_top6
from services.calibration import service as calibration
from services.calibration.config import CalibratorConfig
from services.defaults import DEMO_NETWORK, demo_network
from services.extraction import service as extraction
from services.filtering import service as filtering
from services.filtering.testing import example_models
from services.ingestion import service as ingestion
from services.ingestion.core import IngestionCore
from services.runtime.config import RuntimeConfig
from services.viewer import service as viewer
from services.viewer.core import ViewerCore
from simulators.gateway import key_and_payload
from simulators.profile import LineProfile
from simulators.train import RAW_CHANNELS, TrainSimulator

T0 = 1_767_225_600.0  # 2026-01-01
EXTRA = "fuzzchunk"  # an unexpected key chunk


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


def plain_array(values: Any, dtype: str = "f8") -> dict[str, Any]:
    """An array field as a gateway packs it (``NDArray.of`` would refuse some of these)."""
    a = np.ascontiguousarray(values, dtype=DTYPES[dtype])
    return {"dtype": dtype, "shape": list(a.shape), "data": a.tobytes()}


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
