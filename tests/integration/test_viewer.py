"""The viewer service in-process on a real router, writing ``--rrd``: what is published
lands in the recording under the documented entity paths, bad payloads become dead letters."""

from __future__ import annotations

import threading
from pathlib import Path

import zenoh

from schemas import Alert, DeadLetter, GpsFix, OnboardIndex, TrcRecord, decode, encode, keys
from services.alerting.testing import T0, make_state, p_top6
from services.viewer import service as viewer
from services.viewer.testing import blueprint_views, rrd_contents, verify_rrd
from simulators.network import DEMO_NETWORK, demo_network

PUT = zenoh.SampleKind.PUT
TIMEOUT_S = 5.0
DAY_S = 86_400.0


class Logged:
    """``on_logged`` callback: wait until the viewer has taken ``n`` messages."""

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self.total = 0

    def __call__(self, total: int) -> None:
        with self._cond:
            self.total = total
            self._cond.notify_all()

    def wait_for(self, n: int, timeout: float = TIMEOUT_S) -> None:
        with self._cond:
            ok = self._cond.wait_for(lambda: self.total >= n, timeout)
        assert ok, f"viewer logged {self.total} messages, expected {n}"


def test_viewer_records_published_messages(
    open_session, service_config, liveliness_events, collector, until_matched, tmp_path: Path
):
    ns = service_config.ns
    rrd = tmp_path / "viewer.rrd"
    line = demo_network().lines["L2"]
    seg, hot = line.segments[1].id, line.segments[7].id
    lon, lat = map(float, line.lonlat_at(line.segments[1].mid_m))
    client = open_session()
    dead = collector(lambda s: decode(s.payload.to_bytes(), DeadLetter))
    client.declare_subscriber(keys.deadletter(ns, viewer.SERVICE), dead)
    alive = liveliness_events(client, keys.alive(ns, viewer.SERVICE, "test"))

    logged, stop, result = Logged(), threading.Event(), []
    thread = threading.Thread(
        target=lambda: result.append(
            viewer.main(
                service_config,
                DEMO_NETWORK,
                viewer.Sink("rrd", path=rrd),
                stop=stop,
                handle_signals=False,
                on_logged=logged,
            )
        ),
        name="viewer-under-test",
    )
    thread.start()
    try:
        assert alive.get() == (PUT, keys.alive(ns, viewer.SERVICE, "test"))
        messages = {
            keys.state(ns, "L2", seg): [
                make_state(T0 + k * DAY_S, line="L2", segment=seg, p_exceed=p_top6(1, 0.1 * k))
                for k in range(3)
            ],
            keys.state(ns, "L2", hot): [
                make_state(T0, line="L2", segment=hot, p_exceed=p_top6(1, 0.95))
            ],
            keys.index(ns, "L2", seg): [
                OnboardIndex(
                    line="L2",
                    segment=seg,
                    train="T7",
                    unit="u1",
                    t=T0 + 0.5 * DAY_S,
                    top6_mm=4.4,
                    align10_mm=3.2,
                    speed_mps=22.0,
                    coverage=0.9,
                )  # fmt: skip
            ],
            keys.trc(ns, "L2", seg): [
                TrcRecord(line="L2", segment=seg, t=T0, top6_mm=4.0, align10_mm=3.0, run_id="r1")
            ],
            keys.alert(ns, "L2", hot): [
                Alert(
                    line="L2",
                    segment=hot,
                    t=T0 + 60,
                    kind="exceedance",
                    status=status,
                    indicator="top6",
                    level="intervention",
                    probability=0.95,
                )  # fmt: skip
                for status in ("raised", "cleared")
            ],
            keys.gps(ns, "T7"): [GpsFix(train="T7", t=T0 + 5, lat_deg=lat, lon_deg=lon)],
        }
        publishers = {key: client.declare_publisher(key) for key in messages}
        for publisher in publishers.values():
            until_matched(publisher)
        publishers[keys.trc(ns, "L2", seg)].put(b"\x81\xa1v\x01")  # a map without the fields
        for key, batch in messages.items():
            for message in batch:
                publishers[key].put(encode(message))

        letter = dead.get()
        assert letter.key == keys.trc(ns, "L2", seg) and "TrcRecord" in letter.reason
        logged.wait_for(sum(map(len, messages.values())))
    finally:
        stop.set()
        thread.join(TIMEOUT_S)
    assert not thread.is_alive() and result == [0]

    verify_rrd(rrd)
    contents = rrd_contents(rrd)
    for indicator in ("top6", "align10"):
        base = f"segments/L2/{seg}/{indicator}"
        assert contents[f"{base}/state"]["Scalars:scalars"] == 3  # 3 days, written at stop
        assert contents[f"{base}/onboard"]["Scalars:scalars"] == 1
        assert contents[f"{base}/trc"]["Scalars:scalars"] == 1
    assert contents["map/segments"]["LineStrips2D:strips"] == 1  # the network, static
    assert contents["map/segments"]["LineStrips2D:colors"] >= 2  # grey, then coloured
    assert contents["map/trains"]["Points2D:positions"] == 1
    assert contents["alerts"]["TextLog:text"] == 2
    # the blueprint: the initial one and the final one with the worst segments' plots
    views = blueprint_views(rrd)
    assert {("2D", "map"), ("TextLog", "alerts")} <= views
    assert {
        ("TimeSeries", f"segments/L2/{hot}/top6"),
        ("TimeSeries", f"segments/L2/{seg}/align10"),
    } <= views
