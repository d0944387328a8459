"""`trackfusion gateway check` against a real in-process router: a good simulated gateway is
clean (exit 0), a bad one (m/s², a clock jump) is reported rule by rule (exit 1), silence is
exit 2."""

from __future__ import annotations

import io
import threading

import msgspec
import numpy as np
import zenoh
from support import TIMEOUT_S

from schemas import DAY_S, GpsFix, NDArray, RawChunk, keys
from services.defaults import demo_network
from services.ingestion.health import G_MPS2
from services.tools import gateway_check
from simulators.gateway import key_and_payload
from simulators.profile import LineProfile
from simulators.train import TrainSimulator

T0 = 1_767_225_600.0


def gateway_messages(train: str, seconds: int) -> list[RawChunk | GpsFix]:
    line = demo_network().lines["L3"]
    profile = LineProfile("L3", [(s.start_m, s.end_m) for s in line.segments], 1)
    sim = TrainSimulator(train, line, profile, 1, start_t=T0, phase_s=300.0)
    out: list[RawChunk | GpsFix] = []
    for k in range(seconds):
        chunk = sim.raw_chunk(k)[0]
        out += [chunk, *sim.gps_fixes(chunk.t0, chunk.t0 + 1.0)]
    return out


def run_check(
    service_config, open_session, until_matched, service_thread, train, messages
) -> tuple[int, str]:
    """Start the check, publish ``messages`` as a gateway does, stop once all were seen."""
    out, seen = io.StringIO(), threading.Event()

    def on_message(check: gateway_check.GatewayCheck) -> None:
        if check.messages >= len(messages):
            seen.set()

    check = service_thread(
        "gateway-check",
        lambda stop: gateway_check.main(
            service_config, train, out=out, stop=stop, handle_signals=False, on_message=on_message
        ),
    )
    session = open_session()
    ns = service_config.ns
    publishers = {
        # BLOCK, as a gateway sends (simulators/gateway.py): nothing dropped
        key: session.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK)
        for key in {key_and_payload(ns, m)[0] for m in messages}
    }
    for publisher in publishers.values():
        until_matched(publisher)
    for message in messages:
        key, payload = key_and_payload(ns, message)
        publishers[key].put(payload)
    assert seen.wait(TIMEOUT_S), out.getvalue()
    code = check.stop()
    assert code is not None
    return code, out.getvalue()


def test_a_good_gateway_is_clean(service_config, open_session, until_matched, service_thread):
    messages = gateway_messages("T5", 6)
    code, report = run_check(
        service_config, open_session, until_matched, service_thread, "T5", messages
    )
    assert code == 0, report
    assert "no deviation from the gateway contract" in report
    assert f"{keys.raw(service_config.ns, 'T5', 'u0')}: 6" in report
    assert "sample rate measured 2000.0 Hz" in report


def test_a_bad_gateway_is_reported_rule_by_rule(
    service_config, open_session, until_matched, service_thread
):
    messages = gateway_messages("T6", 6)
    bad: list[RawChunk | GpsFix] = []
    for m in messages:
        if isinstance(m, RawChunk) and m.seq == 3:  # this chunk in m/s²
            a = m.samples.array().astype(np.float32)
            a[:, :6] *= G_MPS2
            m = msgspec.structs.replace(m, samples=NDArray.of(a, "f4"))
        if isinstance(m, GpsFix) and m.t == T0 + 4:  # a clock jump of a day
            m = msgspec.structs.replace(m, t=m.t + DAY_S)
        bad.append(m)
    code, report = run_check(service_config, open_session, until_matched, service_thread, "T6", bad)
    assert code == 1, report
    assert "[RawChunk samples] ×1: RawChunk: samples: vertical mean 9.8" in report
    assert "[GpsFix t] ×1: GpsFix: t: " in report and "clock jump" in report


def test_nothing_arriving_is_exit_2(service_config):
    out = io.StringIO()
    code = gateway_check.main(service_config, "T9", 0.2, out=out, handle_signals=False)
    assert code == 2 and "nothing arrived" in out.getvalue()
