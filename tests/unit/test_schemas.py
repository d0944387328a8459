"""Wire contract: round trips, plain-msgpack payloads, one error type, README in step."""

from __future__ import annotations

import re
from pathlib import Path

import msgpack
import msgspec
import numpy as np
import pytest
import zenoh

import schemas
from schemas import (
    ACCEL_CHANNELS,
    ALL_MESSAGES,
    DAY_S,
    Alert,
    Calibration,
    DeadLetter,
    DegradationPosterior,
    GpsFix,
    InspectionPlan,
    MaintenanceEvent,
    MaintenancePlan,
    NDArray,
    OnboardIndex,
    PlannedTamping,
    PlanRow,
    PositionedChunk,
    RaisedAlerts,
    RawChunk,
    SchemaError,
    SegmentState,
    ServiceHealth,
    StackHealth,
    TrcRecord,
    TrcRunValue,
    ViewerSelect,
    decode,
    encode,
    keys,
)
from services.alerting.testing import plan_row

T0 = 1_767_225_600.0  # 2026-01-01T00:00:00Z


def f8(values) -> NDArray:
    return NDArray.of(values, "f8")


def examples() -> list[schemas.Message]:
    rng = np.random.default_rng(0)
    channels = [*ACCEL_CHANNELS, "supply_v"]
    samples = NDArray.of(rng.normal(size=(2000, 7)), "f4")
    knots = dict(
        knot_t=f8([T0, T0 + 0.5, T0 + 1.0]),
        knot_chainage_m=f8([100.0, 110.0, 120.0]),
        knot_speed_mps=f8([20.0, 20.0, 20.0]),
    )
    eye = np.eye(2)
    alert = Alert(
        line="L1",
        segment="s0001",
        t=T0,
        kind="predicted_exceedance",
        status="raised",
        indicator="top6",
        level="intervention",
        probability=0.4,
        horizon_days=90.0,
        message="Top6 may exceed 12 mm within 90 days",
    )
    return [
        RawChunk(
            train="T1", unit="b1", seq=3, t0=T0, rate_hz=2000, channels=channels, samples=samples
        ),
        GpsFix(train="T1", t=T0, lat_deg=-27.47, lon_deg=153.02, speed_mps=21.5, hdop=0.9),
        PositionedChunk(
            train="T1",
            unit="b1",
            seq=3,
            t0=T0,
            rate_hz=2000,
            channels=channels,
            samples=samples,
            line="L1",
            position_ok=True,
            **knots,
        ),
        OnboardIndex(
            line="L1",
            segment="s0001",
            train="T1",
            unit="b1",
            t=T0,
            top6_mm=3.2,
            align10_mm=2.1,
            speed_mps=20.0,
            coverage=1.0,
        ),
        TrcRecord(line="L1", segment="s0001", t=T0, top6_mm=4.0, align10_mm=3.0, run_id="r7"),
        MaintenanceEvent(line="L1", segment="s0001", event_id="m1", t_start=T0, t_end=T0 + 3600),
        Calibration(
            version=2,
            t=T0,
            indicators=["top6", "align10"],
            indices=["top6", "align10"],
            H=f8([[0.9, 0.05], [0.1, 0.7]]),
            b=f8([-0.1, 0.2]),
            R=f8([[0.04, 0.01], [0.01, 0.09]]),
            n_pairs=120,
            r2=f8([0.8, 0.5]),
        ),
        DegradationPosterior(
            group="class-typical",
            version=1,
            t=T0,
            indicators=["top6", "align10"],
            mu=f8(rng.normal(size=(5, 2)) * 1e-3),
            sigma=f8(np.broadcast_to(eye * 1e-4, (5, 2, 2))),
            z_plus=f8(np.ones((5, 2))),
            sigma_z_plus=f8(np.broadcast_to(eye * 0.01, (5, 2, 2))),
            n_increments=40,
            n_levels=6,
        ),
        SegmentState(
            line="L1",
            segment="s0001",
            t=T0,
            indicators=["top6", "align10"],
            mean=f8([1.2, 0.8]),
            cov=f8(eye * 0.01),
            ci_low_mm=f8([2.8, 1.8]),
            ci_high_mm=f8([4.1, 2.7]),
            width=0.01,
            limit_levels=["alert", "intervention"],
            limits_mm=f8([[8.0, 6.0], [12.0, 10.0]]),
            p_exceed=f8([[0.01, 0.0], [0.0, 0.0]]),
            horizons_days=f8([30, 90, 180]),
            forecast_mean=f8(np.ones((3, 2))),
            forecast_ci_low_mm=f8(np.ones((3, 2))),
            forecast_ci_high_mm=f8(np.full((3, 2), 4.0)),
            forecast_p_exceed=f8(np.zeros((3, 2, 2))),
            last_trc_t=T0 - DAY_S,
            n_updates=4,
            nis=1.3,
        ),
        alert,
        DeadLetter(
            service="ingestion",
            key="tf/raw/T1/b1",
            reason="bad",
            payload_head=b"\x00",
            received_at=T0,
        ),
        StackHealth(
            written_at=T0,
            processes=[ServiceHealth(name="filtering", state="running", alive=True, restarts=1)],
            stalled=["index arriving but no state published for 31 s"],
            counts={"index": 12, "state": 0},
            healthy=False,
        ),
        ViewerSelect(line="L1", segment="s0001"),
        RaisedAlerts(alerts=[alert]),
        InspectionPlan(t=T0, rows=[plan_row("L1", "s0001", 0.4, T0 + 30 * DAY_S)]),
        MaintenancePlan(
            t=T0,
            computed_at=T0 + DAY_S,
            horizon_weeks=2,
            eps=0.05,
            status="within_gap",
            objective=1.5e5,
            bound=1.49e5,
            gap=0.0067,
            solve_s=0.2,
            km_per_week=[1.0, 0.0],
            possessions=1,
            money=2.8e4,
            budget=None,
            segments=10,
            without_model=0,
            rows=[
                PlannedTamping(
                    line="L1",
                    segment="s0001",
                    week=0,
                    worksite=0,
                    length_km=0.2,
                    deadline_week=1,
                    p_reach_ial=0.01,
                    risk_met=True,
                    cost=4.0e3,
                    cost_untamped=9.0e3,
                )
            ],
            trc_lines=[TrcRunValue(line="L1", value=1.2e3, segments=10)],
        ),
    ]


def test_every_message_has_an_example():
    assert {type(m) for m in examples()} == set(ALL_MESSAGES)


@pytest.mark.parametrize("message", examples(), ids=lambda m: type(m).__name__)
def test_round_trip(message):
    assert decode(encode(message), type(message)) == message


def _plain(value):
    """The message as a plain msgpack map, the way another language would build it."""
    if isinstance(value, NDArray):
        return {"dtype": value.dtype, "shape": list(value.shape), "data": bytes(value.data)}
    if isinstance(value, msgspec.Struct):
        return {f: _plain(getattr(value, f)) for f in value.__struct_fields__}
    if isinstance(value, list):
        return [_plain(v) for v in value]
    return value


@pytest.mark.parametrize("message", examples(), ids=lambda m: type(m).__name__)
def test_plain_msgpack_map_decodes(message):
    payload = msgpack.packb(_plain(message), use_bin_type=True)
    assert decode(payload, type(message)) == message


def test_plain_msgpack_defaults_may_be_left_out():
    payload = msgpack.packb({"train": "T9", "t": T0, "lat_deg": 1.5, "lon_deg": 2.5})
    fix = decode(payload, GpsFix)
    assert fix.v == 1 and fix.fix_quality == 1 and fix.speed_mps is None


def _required_only(message) -> bytes:
    """A plain map of ``message`` without the fields that have a default (``v`` too), but
    those a valid message needs: a TrcRecord or an OnboardIndex measures one indicator at
    least."""
    required = {f.name for f in msgspec.structs.fields(message) if f.required}
    fields = {k: v for k, v in _plain(message).items() if k in required}
    if isinstance(message, TrcRecord | OnboardIndex):
        fields.update(top6_mm=message.top6_mm, indicators=["top6"])
    return msgpack.packb(fields)


@pytest.mark.parametrize("message", examples(), ids=lambda m: type(m).__name__)
def test_every_message_type_refuses_every_other_types_payload(message):
    """An OnboardIndex carrying a run_id has every field of a TrcRecord; no payload of
    one type, complete or with only its required fields, decodes as another type."""
    complete, minimal = encode(message), _required_only(message)
    assert decode(minimal, type(message)) is not None  # valid as its own type
    for other in ALL_MESSAGES:
        if other is type(message):
            continue
        for payload in (complete, minimal):
            with pytest.raises(SchemaError, match=f"^{other.__name__}: "):
                decode(payload, other)


def test_an_index_with_a_run_id_is_not_a_trc_record():
    index = next(m for m in examples() if isinstance(m, OnboardIndex))
    tagged = msgspec.structs.replace(index, run_id="r7")
    with pytest.raises(SchemaError, match="TrcRecord: Object contains unknown field `train`"):
        decode(encode(tagged), TrcRecord)


def test_arrays_are_little_endian_bytes():
    a = NDArray.of([[1.0, 2.0], [3.0, 4.0]], "f4")
    assert a.data == np.array([[1, 2], [3, 4]], "<f4").tobytes()
    assert a.array().dtype == np.dtype("<f4") and a.array().shape == (2, 2)


def _gps(**override) -> bytes:
    fields = {"v": 1, "train": "T1", "t": T0, "lat_deg": 1.0, "lon_deg": 2.0, **override}
    return msgpack.packb(fields)


def _index(**override) -> bytes:
    good = _plain(examples()[3])
    return msgpack.packb({**good, **override})


def _calibration(**override) -> bytes:
    good = _plain(examples()[6])
    return msgpack.packb({**good, **override})


def _with_first(payload: bytes, *pairs: bytes) -> bytes:
    """``payload`` (a msgpack map) with packed key/value ``pairs`` put in front."""
    n = len(msgpack.unpackb(payload))
    body = payload[1:] if payload[0] < 0x90 else payload[3:]
    return b"\xde" + (n + len(pairs) // 2).to_bytes(2, "big") + b"".join(pairs) + body


BAD_PAYLOADS = {
    "not msgpack": (b"\xc1\xc1", GpsFix, "malformed"),
    "not a map": (msgpack.packb([1, 2, 3]), GpsFix, "Expected `object`"),
    "missing field": (msgpack.packb({"train": "T1", "t": T0}), GpsFix, "lat_deg"),
    "wrong type": (_gps(t="yesterday"), GpsFix, "$.t"),
    "NaN": (_gps(lat_deg=float("nan")), GpsFix, "lat_deg: must be finite"),
    "inf": (_gps(t=float("inf")), GpsFix, "t: must be finite"),
    "unknown version": (_gps(v=7), GpsFix, "unknown schema version 7"),
    "out of range": (_gps(lat_deg=95.0), GpsFix, "lat_deg"),
    "empty id": (_gps(train=""), GpsFix, "train: must be a non-empty string"),
    "id with wildcard": (_gps(train="T*"), GpsFix, "forbidden characters"),
    "non-positive index": (_index(top6_mm=0.0), OnboardIndex, "top6_mm: must be > 0"),
    "coverage > 1": (_index(coverage=1.5), OnboardIndex, "coverage"),
    "unknown dtype": (
        _calibration(b={"dtype": "f16", "shape": [2], "data": b"\x00" * 32}),
        Calibration,
        "dtype",
    ),
    "data size mismatch": (
        _calibration(b={"dtype": "f8", "shape": [2], "data": b"\x00" * 8}),
        Calibration,
        "needs 16",
    ),
    "wrong shape": (
        _calibration(H={"dtype": "f8", "shape": [3, 2], "data": b"\x00" * 48}),
        Calibration,
        "H: shape",
    ),
    "NaN in array": (
        _calibration(b={"dtype": "f8", "shape": [2], "data": np.array([0, np.nan]).tobytes()}),
        Calibration,
        "NaN or inf",
    ),
    "huge array": (
        _calibration(b={"dtype": "u1", "shape": [10**9], "data": b""}),
        Calibration,
        "elements",
    ),
    "unknown alert kind": (
        msgpack.packb({**_plain(examples()[9]), "kind": "panic"}),
        Alert,
        "kind",
    ),
    # limits and plausibility
    "version beyond int64": (
        _calibration(version=2**63),
        Calibration,
        "version: 9223372036854775808",
    ),
    "version beyond 2^53": (_calibration(version=2**53 + 1), Calibration, "version"),
    "n_pairs beyond int64": (_calibration(n_pairs=2**64 - 1), Calibration, "n_pairs"),
    "index 1e308": (_index(top6_mm=1e308), OnboardIndex, "top6_mm: 1e+308 outside (0, 100]"),
    "index NaN": (_index(align10_mm=float("nan")), OnboardIndex, "align10_mm: must be finite"),
    "quality NaN": (_index(quality=float("nan")), OnboardIndex, "quality: must be finite"),
    "speed -inf": (_index(speed_mps=-float("inf")), OnboardIndex, "speed_mps: must be finite"),
    "align10 above 100 mm": (_index(align10_mm=100.5), OnboardIndex, "align10_mm"),
    "speed above 150 m/s": (_index(speed_mps=151.0), OnboardIndex, "speed_mps"),
    "time 0": (_index(t=0.0), OnboardIndex, "t: 0.0 outside"),
    "time -1e9": (_gps(t=-1e9), GpsFix, "t: -1000000000.0 outside"),
    "time in the year 3000": (_gps(t=32_503_680_000.0), GpsFix, "t: "),
    "time 2^63": (_gps(t=2**63), GpsFix, "t: "),
    "model time far": (_calibration(t=-(2.0**63)), Calibration, "t: "),
    "id with @": (_gps(train="@T1"), GpsFix, "train: '@T1' starts with '@'"),
    "id with slash": (_index(run_id="r/1"), OnboardIndex, "run_id"),
    "id with tab": (_gps(train="T\t1"), GpsFix, "whitespace or control"),
    "id with NUL": (_gps(train="T\x001"), GpsFix, "whitespace or control"),
    "id of 65 characters": (_gps(train="T" * 65), GpsFix, "train: 65 characters > 64"),
    "field name not UTF-8": (
        _with_first(_gps(), b"\xa2\xfd3", msgpack.packb(1)),
        GpsFix,
        "UTF-8",  # msgspec names it itself from 0.23, the decoder's wrapper before
    ),
    "string not UTF-8": (
        _with_first(_gps(), msgpack.packb("train"), b"\xa2\xfd3"),
        GpsFix,
        "UTF-8",
    ),
    "deep nesting": (
        _with_first(_gps(), msgpack.packb("deep"), b"\x91" * 3000 + b"\x90"),
        GpsFix,
        "'deep': nested deeper than 32 levels",
    ),
    "beyond the size limit": (
        msgpack.packb({**msgpack.unpackb(_gps()), "blob": b"\x00" * 5_000}),
        GpsFix,
        "payload of 5",
    ),
}


@pytest.mark.parametrize("case", BAD_PAYLOADS, ids=str)
def test_malformed_payload_raises_schema_error_saying_why(case):
    payload, message_type, says = BAD_PAYLOADS[case]
    with pytest.raises(SchemaError) as info:
        decode(payload, message_type)
    assert says in str(info.value)
    assert str(info.value).startswith(message_type.__name__)


def test_constructing_an_invalid_message_raises_the_same_error():
    with pytest.raises(SchemaError, match="t_end"):
        MaintenanceEvent(line="L1", segment="s1", event_id="e", t_start=T0, t_end=T0 - 1)


def test_a_withdrawal_outranks_the_detection_it_withdraws_and_a_later_one_outranks_it():
    found = MaintenanceEvent(
        line="L1", segment="s1", event_id="detected-1", t_start=T0, t_end=T0 + 60, detected=True
    )
    gone = msgspec.structs.replace(found, revision=1, withdrawn=True)
    again = msgspec.structs.replace(found, revision=2)
    assert found.rank < gone.rank < again.rank
    assert msgspec.structs.replace(found, withdrawn=True).rank > found.rank  # a tie: withdrawn
    assert decode(encode(gone), MaintenanceEvent) == gone
    with pytest.raises(SchemaError, match="withdrawn: only a detected tamping"):
        MaintenanceEvent(
            line="L1", segment="s1", event_id="e", t_start=T0, t_end=T0, withdrawn=True
        )


def test_an_unknown_field_is_refused_by_name():
    extra = _with_first(_gps(), msgpack.packb("extra"), b"\x91" * 30 + b"\x90")
    with pytest.raises(SchemaError, match="GpsFix: Object contains unknown field `extra`"):
        decode(extra, GpsFix)


def test_a_deep_unknown_field_beyond_the_scanned_items_is_refused_not_raised():
    # the nesting scan stops after NESTING_SCAN_ITEMS items; the decoder then refuses the
    # first unknown field before it descends into anything deep
    chunk = encode(examples()[0])
    many = msgpack.packb(list(range(20_000)))
    deep = b"\x91" * 5000 + b"\x90"
    payload = _with_first(chunk, msgpack.packb("many"), many, msgpack.packb("deep"), deep)
    assert len(payload) <= RawChunk.MAX_BYTES
    with pytest.raises(SchemaError, match="RawChunk: Object contains unknown field `many`"):
        decode(payload, RawChunk)


@pytest.mark.parametrize("message", examples(), ids=lambda m: type(m).__name__)
def test_every_example_is_within_its_size_limit(message):
    assert len(encode(message)) <= type(message).MAX_BYTES


def test_size_limits_fit_the_reference_unit_and_a_1000_sample_posterior():
    rng = np.random.default_rng(1)
    chunk = RawChunk(
        train="T1", unit="b1", seq=0, t0=T0, rate_hz=2000,
        channels=[*ACCEL_CHANNELS, "supply_v"], samples=NDArray.of(rng.normal(size=(2000, 7))),
    )  # fmt: skip
    assert 4 * len(encode(chunk)) <= RawChunk.MAX_BYTES  # 1 s in f8, four times over
    ns, eye = 1000, np.broadcast_to(np.eye(2), (1000, 2, 2))
    posterior = DegradationPosterior(
        group="net", version=1, t=T0, indicators=["top6", "align10"],
        mu=f8(np.zeros((ns, 2))), sigma=f8(eye), z_plus=f8(np.zeros((ns, 2))),
        sigma_z_plus=f8(eye), n_increments=10, n_levels=3,
    )  # fmt: skip
    assert 4 * len(encode(posterior)) <= DegradationPosterior.MAX_BYTES


def test_a_prior_model_may_have_time_zero():
    cal = decode(_calibration(t=0.0), Calibration)
    assert cal.t == 0.0


# --- keys --------------------------------------------------------------------------------


def test_each_key_has_its_documented_form():
    ns = "tf"
    assert keys.raw(ns, "T1", "b1") == "tf/raw/T1/b1"
    assert keys.gps(ns, "T1") == "tf/gps/T1"
    assert keys.accel(ns, "T1", "b1") == "tf/accel/T1/b1"
    assert keys.index(ns, "L1", "s1") == "tf/index/L1/s1"
    assert keys.trc(ns, "L1", "s1") == "tf/trc/L1/s1"
    assert keys.maintenance(ns, "L1", "s1") == "tf/maintenance/L1/s1"
    assert keys.calibration(ns) == "tf/model/calibration"
    assert keys.degradation(ns, "class-fast") == "tf/model/degradation/class-fast"
    assert keys.state(ns, "L1", "s1") == "tf/state/L1/s1"
    assert keys.alert(ns, "L1", "s1") == "tf/alert/L1/s1"
    assert keys.deadletter(ns, "ingestion") == "tf/deadletter/ingestion"
    assert keys.alive(ns, "filtering", "i0") == "tf/alive/filtering/i0"
    assert keys.q_state(ns, "L1", "s1") == "tf/q/state/L1/s1"
    assert keys.q_alerts(ns) == "tf/q/alerts"
    assert keys.q_plan(ns) == "tf/q/plan"
    assert keys.stack_health(ns) == "tf/health/stack"
    assert keys.viewer_select(ns) == "tf/viewer/select"
    assert str(keys.raw) == "{ns}/raw/{train}/{unit}"
    with pytest.raises(TypeError, match="takes 2 id"):
        keys.raw(ns, "T1")


def test_wildcards_include_their_concrete_keys():
    ke = zenoh.KeyExpr
    ns = "tf"
    pairs = [
        (keys.raw_all(ns), keys.raw(ns, "T1", "b1")),
        (keys.gps_all(ns), keys.gps(ns, "T1")),
        (keys.accel_all(ns), keys.accel(ns, "T1", "b1")),
        (keys.segment_keys(ns, "index"), keys.index(ns, "L1", "s1")),
        (keys.segment_keys(ns, "state", "L1/*"), keys.state(ns, "L1", "s1")),
        (keys.model_all(ns), keys.degradation(ns, "g")),
        (keys.model_all(ns), keys.calibration(ns)),
        (keys.deadletter_all(ns), keys.deadletter(ns, "x")),
        (keys.alive_all(ns), keys.alive(ns, "x", "y")),
        (keys.q_state_all(ns), keys.q_state(ns, "L1", "s1")),
    ]
    for wildcard, concrete in pairs:
        assert ke(wildcard).includes(ke(concrete)), (wildcard, concrete)
    assert not ke(keys.segment_keys(ns, "state", "L1/*")).intersects(ke(keys.state(ns, "L2", "s")))
    assert not ke(keys.raw_all("tf")).intersects(ke(keys.raw("tf2", "T1", "b1")))


@pytest.mark.parametrize(
    "bad", ["", "a/b", "a*", "$x", "q?", "#", "has space", "@x", "a\tb", "a\nb", "x" * 65]
)
def test_keys_refuse_unsafe_chunks(bad):
    with pytest.raises(ValueError):
        keys.index("tf", "L1", bad)


def test_parse_segment_key():
    assert keys.parse_segment_key("tf/index/L1/s1") == ("tf", "index", "L1", "s1")
    for bad in ("tf/index/L1", "tf/index/L1/s1/x", "tf/raw/L1/s1", "tf/index//s1"):
        with pytest.raises(SchemaError, match="is not of the form"):
            keys.parse_segment_key(bad)


# (builder, its arguments after ns, parser, what the parser returns)
PARSERS = [
    (keys.raw, ("T1", "b1"), keys.parse_raw, ("T1", "b1")),
    (keys.gps, ("T1",), keys.parse_gps, "T1"),
    (keys.accel, ("T1", "b1"), keys.parse_accel, ("T1", "b1")),
    *[
        (getattr(keys, kind), ("L1", "s1"), keys.parse_segment_key, ("tf", kind, "L1", "s1"))
        for kind in keys.SEGMENT_KINDS
    ],
    (keys.degradation, ("class-fast",), keys.parse_degradation, "class-fast"),
    (keys.deadletter, ("ingestion",), keys.parse_deadletter, "ingestion"),
    (keys.alive, ("filtering", "i0"), keys.parse_alive, ("filtering", "i0")),
    (keys.q_state, ("L1", "s1"), keys.parse_q_state, ("L1", "s1")),
]


@pytest.mark.parametrize(
    "builder, args, parse, ids", PARSERS, ids=lambda x: getattr(x, "__name__", None)
)
def test_parsers_reverse_their_builders_and_refuse_other_keys(builder, args, parse, ids):
    key = builder("tf", *args)
    assert parse(key) == ids
    others = [b("tf", *a) for b, a, p, _ in PARSERS if p is not parse]
    others += [key + "/x", key.rsplit("/", 1)[0], keys.calibration("tf")]
    for other in others:
        with pytest.raises(SchemaError):
            parse(other)


def test_kind_and_model_kind():
    assert keys.kind(keys.raw("tf", "T1", "b1")) == "raw"
    assert keys.kind(keys.q_state("tf", "L1", "s1")) == "q"
    assert keys.kind(keys.segment_keys("tf", "index", "L1/**")) == "index"
    assert keys.model_kind(keys.calibration("tf")) == "calibration"
    assert keys.model_kind(keys.degradation("tf", "g")) == "degradation"
    for bad in ("tf", "tf/"):
        with pytest.raises(SchemaError):
            keys.kind(bad)
    with pytest.raises(SchemaError):
        keys.model_kind(keys.state("tf", "L1", "s1"))


def test_selectors_narrow_the_queryable_and_the_subscriptions_alike():
    ke = zenoh.KeyExpr
    l1 = ke(keys.q_state_keys("tf", "L1/**"))
    assert keys.q_state_keys("tf") == keys.q_state_all("tf") == "tf/q/state/**"
    assert l1.includes(ke(keys.q_state("tf", "L1", "s1")))
    assert not l1.intersects(ke(keys.q_state("tf", "L2", "s1")))
    assert not l1.intersects(ke(keys.state("tf", "L1", "s1")))
    assert ke(keys.q_state_all("tf")).includes(l1)
    one_train = ke(keys.raw_of_train("tf", "T1"))
    assert one_train.includes(ke(keys.raw("tf", "T1", "b1")))
    assert not one_train.intersects(ke(keys.raw("tf", "T2", "b1")))
    assert ke(keys.raw_all("tf")).includes(one_train)


@pytest.mark.parametrize("kind", ["index", "trc", "maintenance", "state"])
def test_a_region_selector_splits_a_network_by_line_prefix(kind):
    # a national deployment (docs/operating.md#national-deployment, bench/scale.py): line
    # ids carry a region letter, and one selector per filtering instance takes a region's lines
    ke = zenoh.KeyExpr
    shards = {r: ke(keys.segment_keys("tf", kind, f"{r}$*/**")) for r in "ABCD"}
    queryables = {r: ke(keys.q_state_keys("tf", f"{r}$*/**")) for r in "ABCD"}
    for line in ("A001", "B017", "C200", "D042"):
        concrete = ke(getattr(keys, kind)("tf", line, "s0001"))
        owners = [r for r, k in shards.items() if k.includes(concrete)]
        assert owners == [line[0]]
        answering = [
            r for r, k in queryables.items() if k.includes(ke(keys.q_state("tf", line, "s1")))
        ]
        assert answering == [line[0]]


@pytest.mark.parametrize("message", examples(), ids=lambda m: type(m).__name__)
def test_every_message_has_its_key_and_refuses_another(message):
    key = keys.key_of("tf", message)
    keys.check_key(key, message)
    assert zenoh.KeyExpr(key).intersects(zenoh.KeyExpr(f"tf/{keys.kind(key)}/**"))
    moved = key.rsplit("/", 1)[0] + "/other"
    if moved != key:
        with pytest.raises(SchemaError, match=f"^{type(message).__name__}: key (says )?.*other"):
            keys.check_key(moved, message)
    for other in examples():
        if type(other) is not type(message) and not (
            isinstance(other, SegmentState) and isinstance(message, SegmentState)
        ):
            with pytest.raises(SchemaError, match=f"^{type(message).__name__}: key "):
                keys.check_key(keys.key_of("tf", other), message)


def test_a_state_is_checked_on_its_queryable_key_too():
    state = next(m for m in examples() if isinstance(m, SegmentState))
    keys.check_key(keys.q_state("tf", state.line, state.segment), state)
    with pytest.raises(SchemaError, match="SegmentState: key says L1/s9, message says L1/s0001"):
        keys.check_key(keys.q_state("tf", "L1", "s9"), state)


# --- the wire reference stays in step ------------------------------------------------------


def _readme_fields() -> dict[str, tuple[int, list[str]]]:
    """``{name: (version, fields)}`` of each ``### Name (vN)`` section (version 0 for a
    ``#### Part`` of a message, e.g. PlanRow); a section ends at the next heading."""
    text = (Path(schemas.__file__).parent / "README.md").read_text()
    documented = {}
    heading = r"^(?:### (\w+) \(v(\d+)\)|#### (\w+))\n(.*?)(?=^##|\Z)"
    for match in re.finditer(heading, text, re.M | re.S):
        name, version = match.group(1) or match.group(3), int(match.group(2) or 0)
        rows = re.findall(r"^\| (\w+) \|", match.group(4), re.M)
        documented[name] = (version, [r for r in rows if r != "field"])
    return documented


def test_wire_reference_documents_the_plan_rows():
    assert _readme_fields()["PlanRow"] == (0, list(PlanRow.__struct_fields__))


def test_wire_reference_documents_every_field_of_every_message():
    documented = _readme_fields()
    rows = {"PlanRow", "PlannedTamping", "TrcRunValue"}
    assert set(documented) - rows == {m.__name__ for m in ALL_MESSAGES}
    for message_type in ALL_MESSAGES:
        version, fields = documented[message_type.__name__]
        assert version == schemas.SCHEMA_VERSION
        assert fields == list(message_type.__struct_fields__), message_type.__name__


def test_nesting_just_beyond_the_limit_is_found_and_at_the_limit_is_not():
    """The scan's shortcut (too few container header bytes to be that deep) keeps the
    boundary: 33 nested non-empty containers in a value are refused, 32 are not."""
    from schemas.wire import MAX_NESTING, too_deep

    for depth, found in ((MAX_NESTING, None), (MAX_NESTING + 1, "'x'")):
        value = b"\x91" * depth + b"\x01"
        assert too_deep(_with_first(_gps(), msgpack.packb("x"), value)) == found


def test_an_id_refused_stays_refused_after_valid_ones_were_seen():
    for _ in range(2):  # the second time the valid ids come from the cache of checked ids
        assert decode(_gps(train="T1"), GpsFix).train == "T1"
        with pytest.raises(SchemaError, match="whitespace or control"):
            decode(_gps(train="T 1"), GpsFix)


@pytest.mark.parametrize("dtype", ["f4", "f8"])
@pytest.mark.parametrize("size", [1, 8, 127, 128, 129, 5000])  # around the small-array sum
def test_an_array_with_nan_or_inf_anywhere_is_refused_and_huge_finite_ones_are_not(dtype, size):
    rng = np.random.default_rng(size)
    huge = np.finfo(np.float32 if dtype == "f4" else np.float64).max
    assert NDArray.of(np.full(size, huge), dtype).shape == [size]  # the sum overflows: finite
    for bad in (np.nan, np.inf, -np.inf):
        values = rng.random(size)
        values[rng.integers(size)] = bad
        with pytest.raises(SchemaError, match="NaN or inf"):
            NDArray.of(values, dtype)
    mixed = np.full(size, huge)
    mixed[-1] = -np.inf if size > 1 else np.nan
    with pytest.raises(SchemaError, match="NaN or inf"):
        NDArray.of(mixed, dtype)


def test_decode_many_gives_what_decode_gives_or_none_where_decode_refuses_one():
    """A backlog's indices are decoded in one call: the same messages as one at a time,
    and None (decode then says which and why) as soon as one payload would be refused."""
    good = [
        OnboardIndex(line="L1", segment=f"s{k}", train="T1", unit="u1", t=T0 + k, top6_mm=1.0 + k,
                     align10_mm=0.5, speed_mps=30.0, coverage=1.0)
        for k in range(5)
    ]  # fmt: skip
    payloads = [encode(m) for m in good]
    assert schemas.decode_many(payloads, OnboardIndex) == [
        decode(p, OnboardIndex) for p in payloads
    ]
    assert schemas.decode_many([], OnboardIndex) == []
    out_of_range = msgpack.packb({**msgpack.unpackb(payloads[0]), "top6_mm": -1.0})
    bad = [
        payloads[1][:-3],  # truncated
        out_of_range,  # a check of the message's own
        msgpack.packb({**msgpack.unpackb(payloads[0]), "extra": 1}),  # unknown field
        b"\x91" * 40 + b"\x90",  # nested deeper than the limit
        bytes(OnboardIndex.MAX_BYTES + 1),  # too long
        bytearray(payloads[0]),  # not bytes: decode takes it, the batch leaves it to it
    ]
    for payload in bad:
        assert schemas.decode_many([*payloads, payload], OnboardIndex) is None
    with pytest.raises(SchemaError, match="top6_mm"):
        decode(out_of_range, OnboardIndex)


def test_a_trc_record_may_measure_some_indicators():
    """A level-only record is explicit; a plain map without ``indicators`` measures both."""
    both = {"line": "L1", "segment": "s1", "t": T0, "run_id": "r1"}
    record = decode(msgpack.packb({**both, "top6_mm": 2.0, "align10_mm": 1.5}), TrcRecord)
    assert record.indicators == ["top6", "align10"] and record.values_mm == (2.0, 1.5)
    level = decode(msgpack.packb({**both, "top6_mm": 2.0, "indicators": ["top6"]}), TrcRecord)
    assert level.values_mm == (2.0, None)
    assert decode(encode(level), TrcRecord) == level
    bad = [
        ({"top6_mm": 2.0}, "align10_mm: missing"),
        ({"top6_mm": 2.0, "align10_mm": 1.0, "indicators": ["top6"]}, "align10_mm: given"),
        ({"align10_mm": 1.0, "indicators": ["align10", "top6"]}, "indicators: "),
        ({"indicators": []}, "indicators: "),
        ({"top6_mm": 2.0, "indicators": ["top6", "top6"]}, "indicators: "),
    ]
    for fields, reason in bad:
        with pytest.raises(SchemaError, match=f"TrcRecord: {reason}"):
            decode(msgpack.packb({**both, **fields}), TrcRecord)


def test_an_index_may_measure_some_indicators():
    fields = {"line": "L1", "segment": "s1", "train": "T1", "unit": "u1", "t": T0,
              "speed_mps": 20.0, "coverage": 1.0}  # fmt: skip
    both = decode(msgpack.packb({**fields, "top6_mm": 2.0, "align10_mm": 1.5}), OnboardIndex)
    assert both.indicators == ["top6", "align10"]
    vertical = decode(msgpack.packb({**fields, "top6_mm": 2.0, "indicators": ["top6"]}),
                      OnboardIndex)  # fmt: skip
    assert vertical.values_mm == (2.0, None) and decode(encode(vertical), OnboardIndex) == vertical
    for extra, reason in (
        ({"top6_mm": 2.0}, "align10_mm: missing"),
        ({"top6_mm": 2.0, "indicators": ["top6"], "speed_mps": -1.0}, "speed_mps"),
        ({"top6_mm": 0.0, "indicators": ["top6"]}, "top6_mm"),
        ({"top6_mm": 2.0, "align10_mm": 1.0, "indicators": ["align10"]}, "top6_mm: given"),
    ):
        with pytest.raises(SchemaError, match=f"OnboardIndex: {reason}"):
            decode(msgpack.packb({**fields, **extra}), OnboardIndex)
