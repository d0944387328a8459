"""The viewer service in-process on a real router, writing ``--rrd``: what is published
lands in the recording under the documented entity paths, bad payloads become dead letters,
``viewer select`` pins a segment and the health board shows liveliness tokens, then what
``trackfusion up`` reports."""

from __future__ import annotations

import re
import threading
from pathlib import Path

import zenoh

from schemas import (
    DAY_S,
    DeadLetter,
    GpsFix,
    ServiceHealth,
    StackHealth,
    TrcRecord,
    decode,
    encode,
    keys,
)
from services.alerting.testing import T0, make_alert, make_index, make_state, p_top6
from services.defaults import DEMO_NETWORK, demo_network
from services.viewer import service as viewer
from services.viewer.testing import (
    blueprint_views,
    make_plan,
    rrd_contents,
    rrd_printout,
    verify_rrd,
)

PUT = zenoh.SampleKind.PUT
TIMEOUT_S = 5.0


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


def start_viewer(
    service_config, rrd: Path
) -> tuple[threading.Thread, threading.Event, list, Logged]:
    """``viewer.main`` on the demo network in a thread, recording to ``rrd``: the thread,
    its stop event, the list its exit code lands in, and its ``on_logged`` counter."""
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
    return thread, stop, result, logged


def rows(contents: dict, pattern: str, column: str = "Scalars:scalars") -> int:
    """How many values of ``column`` the recording's entities matching ``pattern`` hold."""
    return sum(
        columns.get(column, 0)
        for entity, columns in contents.items()
        if re.fullmatch(pattern, entity)
    )


def test_viewer_records_published_messages(
    open_session, service_config, liveliness_events, collector, until_matched, tmp_path: Path
):
    ns = service_config.ns
    rrd = tmp_path / "viewer.rrd"
    line = demo_network().lines["L2"]
    seg, hot, picked = line.segments[1].id, line.segments[7].id, line.segments[20].id
    lon, lat = map(float, line.lonlat_at(line.segments[1].mid_m))
    client = open_session()
    dead = collector(lambda s: decode(s.payload.to_bytes(), DeadLetter))
    client.declare_subscriber(keys.deadletter(ns, viewer.SERVICE), dead)
    alive = liveliness_events(client, keys.alive(ns, viewer.SERVICE, "test"))

    thread, stop, result, logged = start_viewer(service_config, rrd)
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
            keys.state(ns, "L2", picked): [
                make_state(T0 + k * DAY_S, line="L2", segment=picked, p_exceed=p_top6(1, 0.0))
                for k in range(2)
            ],
            keys.index(ns, "L2", seg): [
                make_index(
                    T0 + 0.5 * DAY_S,
                    line="L2",
                    segment=seg,
                    train="T7",
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
                make_alert(T0 + 60, line="L2", segment=hot, status=status, probability=0.95)
                for status in ("raised", "cleared")
            ],
            keys.gps(ns, "T7"): [GpsFix(train="T7", t=T0 + 5, lat_deg=lat, lon_deg=lon)],
            keys.maintenance_plan(ns): [make_plan(T0, [("L2", hot, 2, 0)], T0)],
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
        n = sum(map(len, messages.values()))
        logged.wait_for(n)
        # what an operator types to see another segment: answered by the running viewer
        assert viewer.main_select(service_config, f"L2/{picked}") == 0
        logged.wait_for(n + 1)
        # what `trackfusion up` publishes each second
        report = StackHealth(
            written_at=T0,
            processes=[ServiceHealth(name="filtering", state="waiting", alive=False, restarts=2)],
            stalled=[],
            counts={"state": 6},
            healthy=False,
        )
        client.put(keys.stack_health(ns), encode(report))
        logged.wait_for(n + 2)
    finally:
        stop.set()
        thread.join(TIMEOUT_S)
    assert not thread.is_alive() and result == [0]

    verify_rrd(rrd)
    contents = rrd_contents(rrd)

    for indicator in ("top6", "align10"):
        # three segments, three worst rows: seg's 3 days, hot's one, picked's 2
        assert rows(contents, rf"worst/\d/{indicator}/g\d+/state") == 3 + 1 + 2
        assert rows(contents, rf"worst/\d/{indicator}/g\d+/onboard") == 1
        assert rows(contents, rf"worst/\d/{indicator}/g\d+/trc") == 1
        assert (
            rows(contents, rf"selected/{indicator}/g\d+/state") == 2
        )  # the selected segment's history
    assert contents["map/segments"]["LineStrips2D:strips"] == 1  # the network, static
    assert contents["map/segments"]["LineStrips2D:colors"] >= 2  # grey, then coloured
    assert contents["map/trains"]["Points2D:positions"] == 1
    assert contents["alerts"]["TextLog:text"] == 2
    assert contents["map/plan/tamping"]["LineStrips2D:strips"] == 1  # the planner's plan
    printout = rrd_printout(rrd)
    assert f"L2/{picked}" in printout  # in the plotted-segments table
    assert "tamp w2 01-15" in printout  # the planned tamping's label on the map
    assert "No report from `trackfusion up`" in printout  # first the liveliness tokens
    assert "**trackfusion up**: **not healthy**" in printout  # then up's report
    # the one blueprint: map, alert log, health, the slots' plots
    views = blueprint_views(rrd)
    assert {("2D", "map"), ("TextLog", "alerts"), ("TextDocument", "health")} <= views
    assert {
        ("TimeSeries", "worst/1/top6"),
        ("TimeSeries", "worst/3/align10"),
        ("TimeSeries", "selected/top6"),
    } <= views


def test_viewer_select_without_a_viewer_says_so(service_config, capsys):
    assert viewer.main_select(service_config, "L1/s00001", timeout_s=0.5) == 1
    assert "no viewer listens" in capsys.readouterr().err


def test_viewer_takes_every_segments_newest_state_from_q_state_at_start(
    open_session, service_config, collector, tmp_path: Path
):
    """The map is coloured at once: at start the viewer asks filtering's q/state for every
    segment's newest state (a segment that seldom changes would stay grey until its next
    state); a reply on a segment the network lacks is a dead letter."""
    ns = service_config.ns
    seg = demo_network().lines["L2"].segments[3].id
    client = open_session()
    dead = collector(lambda s: decode(s.payload.to_bytes(), DeadLetter))
    client.declare_subscriber(keys.deadletter(ns, viewer.SERVICE), dead)

    def answer(query: zenoh.Query) -> None:
        state = make_state(T0, line="L2", segment=seg, p_exceed=p_top6(1, 0.9))
        query.reply(keys.q_state(ns, "L2", seg), encode(state))
        nowhere = make_state(T0, line="L9", segment="s1", p_exceed=p_top6(1, 0.9))
        query.reply(keys.q_state(ns, "L9", "s1"), encode(nowhere))

    queryable = client.declare_queryable(keys.q_state_all(ns), answer)
    rrd = tmp_path / "viewer.rrd"
    thread, stop, result, logged = start_viewer(service_config, rrd)
    try:
        logged.wait_for(1)
        letter = dead.get()
        assert letter.key == keys.q_state(ns, "L9", "s1") and "not in" in letter.reason
    finally:
        stop.set()
        thread.join(TIMEOUT_S)
        queryable.undeclare()
    assert not thread.is_alive() and result == [0]
    assert rows(rrd_contents(rrd), r"worst/\d/top6/g\d+/state") == 1
