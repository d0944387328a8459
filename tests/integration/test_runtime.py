"""services.runtime on real Zenoh sessions through an in-process router on loopback."""

from __future__ import annotations

import argparse
from pathlib import Path

import pytest
import zenoh

from schemas import DeadLetter, decode, encode, keys
from services.runtime.config import (
    DEFAULT_ENDPOINT,
    ROUTER_CONFIG,
    SERVICE_CONFIG,
    add_zenoh_arguments,
    config_from_args,
    endpoints,
    load_config,
    zenoh_config,
)
from services.runtime.deadletter_publisher import PAYLOAD_HEAD_BYTES
from services.runtime.service import ServiceRuntime, run_service
from services.tools import deadletter_printer

PUT, DELETE = zenoh.SampleKind.PUT, zenoh.SampleKind.DELETE


def test_pubsub_across_two_clients(open_session, namespace, until_matched, collector):
    alice, bob = open_session(), open_session()
    received = collector(lambda s: (str(s.key_expr), s.payload.to_bytes()))
    bob.declare_subscriber(f"{namespace}/x/**", received)
    publisher = alice.declare_publisher(f"{namespace}/x/1")
    until_matched(publisher)

    publisher.put(b"hello")

    assert received.get() == (f"{namespace}/x/1", b"hello")
    publisher.undeclare()


def test_liveliness_token_visible_then_gone_after_stop(
    open_session, service_config, liveliness_events
):
    observer = open_session()
    key = keys.alive(service_config.ns, "probe", "test")
    events = liveliness_events(observer, keys.alive_all(service_config.ns))

    with ServiceRuntime("probe", service_config) as rt:
        assert rt.alive_key == key
        rt.announce()
        assert events.get() == (PUT, key)
        # Asked from a session without a liveliness subscriber: in about one run in 25 the
        # subscriber's own session answered this query with nothing (zenoh 1.10.2).
        replies = open_session().liveliness().get(key, timeout=5)
        assert [str(r.ok.key_expr) for r in replies if r.ok is not None] == [key]

    assert events.get() == (DELETE, key)


def test_run_service_returns_0_on_stop(
    open_session, service_config, liveliness_events, service_thread
):
    events = liveliness_events(open_session(), keys.alive_all(service_config.ns))
    setup_done: list[ServiceRuntime] = []
    probe = service_thread(
        "probe",
        lambda stop: run_service("probe", service_config, setup_done.append, stop_event=stop),
    )
    kind, key = events.get()
    assert kind == PUT and key.endswith("/alive/probe/test")
    assert setup_done and setup_done[0].session is not None
    assert probe.stop() == 0
    assert events.get() == (DELETE, key)


def test_dead_letter_arrives_with_reason_and_counts(
    open_session, service_config, until_matched, collector
):
    observer = open_session()
    letters = collector(lambda s: (str(s.key_expr), decode(s.payload.to_bytes(), DeadLetter)))
    observer.declare_subscriber(keys.deadletter_all(service_config.ns), letters)

    with ServiceRuntime("probe", service_config) as rt:
        until_matched(rt.deadletters.publisher)
        payload = bytes(range(256)) * 2
        rt.deadletters.reject(f"{rt.ns}/raw/t1/u1", "v: unknown schema version 9", payload)
        rt.deadletters.reject(f"{rt.ns}/raw/t1/u1", "v: unknown schema version 9", b"x")
        rt.deadletters.reject(f"{rt.ns}/gps/t1", "not msgpack", None)

        key, first = letters.get()
        assert key == keys.deadletter(rt.ns, "probe")
        assert first.service == "probe"
        assert first.key == f"{rt.ns}/raw/t1/u1"
        assert first.reason == "v: unknown schema version 9"
        assert first.payload_head == payload[:PAYLOAD_HEAD_BYTES]
        assert first.received_at > 1.6e9  # wall clock of the rejection
        assert letters.get()[1].payload_head == b"x"
        assert letters.get()[1].reason == "not msgpack"
        assert rt.deadletters.counts == {"v: unknown schema version 9": 2, "not msgpack": 1}
        assert rt.deadletters.total == 3


def test_subscribe_worker_dead_letters_bad_input_and_keeps_going(
    open_session, service_config, until_matched, collector
):
    observer = open_session()
    letters = collector(lambda s: decode(s.payload.to_bytes(), DeadLetter))
    observer.declare_subscriber(keys.deadletter_all(service_config.ns), letters)
    good = collector()

    def on_item(_kind: str, _key: str, payload: bytes) -> None:
        if payload == b"boom":
            raise ZeroDivisionError("boom")
        good(decode(payload, DeadLetter))  # SchemaError on garbage

    with ServiceRuntime("probe", service_config) as rt:
        rt.subscribe_in_order({"in": f"{rt.ns}/in/**"}, on_item)
        publisher = observer.declare_publisher(f"{rt.ns}/in/a")
        until_matched(publisher)
        until_matched(rt.deadletters.publisher)

        publisher.put(b"\xc1garbage")
        publisher.put(b"boom")
        ok = DeadLetter(service="x", key="k", reason="r", payload_head=b"", received_at=0.0)
        publisher.put(encode(ok))

        schema_letter = letters.get()
        assert schema_letter.key == f"{rt.ns}/in/a"
        assert schema_letter.reason.startswith("DeadLetter:")
        assert schema_letter.payload_head == b"\xc1garbage"
        assert letters.get().reason == "ZeroDivisionError: boom"
        assert good.get() == ok  # the worker survived both
        assert rt.deadletters.total == 2
        publisher.undeclare()


def test_deadletters_service_prints_one_line_per_letter(
    open_session, service_config, until_matched, liveliness_events, collector, service_thread
):
    class Lines:
        def __init__(self) -> None:
            self.lines = collector()

        def write(self, text: str) -> None:
            for line in text.splitlines():
                self.lines(line)

        def flush(self) -> None:
            pass

    out = Lines()
    observer = open_session()
    events = liveliness_events(observer, keys.alive(service_config.ns, "deadletters", "test"))
    printer = service_thread(
        "deadletters", lambda stop: deadletter_printer.main(service_config, out, stop=stop)
    )
    assert events.get()[0] == PUT
    publisher = observer.declare_publisher(keys.deadletter(service_config.ns, "ingestion"))
    until_matched(publisher)
    letter = DeadLetter(
        service="ingestion",
        key=f"{service_config.ns}/raw/t1/u1",
        reason="GpsFix: Expected `float`,\n got `str`",
        payload_head=b"\x81",
        received_at=1.0,
    )
    publisher.put(encode(letter))
    publisher.put(b"not a dead letter")  # logged, not printed, not dead-lettered again
    publisher.put(encode(letter))
    line = out.lines.get()
    assert line.split(" ", 2) == [
        "ingestion",
        f"{service_config.ns}/raw/t1/u1",
        "GpsFix: Expected `float`, got `str`",
    ]
    assert out.lines.get() == line
    publisher.undeclare()
    assert printer.stop() == 0
    assert events.get()[0] == DELETE


# --- configuration ---------------------------------------------------------------------------


def _parse(argv: list[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    add_zenoh_arguments(parser)
    return parser.parse_args(argv)


def test_defaults_are_client_of_local_router_without_multicast():
    conf = load_config()
    assert (conf.ns, conf.instance, conf.mode) == ("tf", None, "client")
    assert endpoints(conf, "connect") == [DEFAULT_ENDPOINT]
    assert conf.zenoh_config().get_json("scouting/multicast/enabled") == "false"


def test_file_then_flags_overlay(tmp_path: Path):
    path = tmp_path / "svc.json5"
    path.write_text(
        """// a comment, trailing commas, unquoted keys: JSON5
        {
          ns: "site_a", instance: "filtering-1",
          mode: "peer",
          connect: { endpoints: ["tcp/10.0.0.1:7447", "tcp/10.0.0.2:7447"], },
          scouting: { multicast: { enabled: true } },  // forced off anyway
          services: { filtering: { db: "state.sqlite" } },
        }"""
    )
    conf = config_from_args(_parse(["--config", str(path)]))
    assert (conf.ns, conf.instance, conf.mode) == ("site_a", "filtering-1", "peer")
    assert endpoints(conf, "connect") == ["tcp/10.0.0.1:7447", "tcp/10.0.0.2:7447"]
    assert conf.options("filtering", ("db",)) == {"db": "state.sqlite"}
    assert conf.options("calibration", ("db",)) == {}
    assert conf.zenoh_config().get_json("scouting/multicast/enabled") == "false"

    argv = ["--config", str(path), "--ns", "site_b", "--mode", "client"]
    argv += ["--connect", "tcp/127.0.0.1:9001", "--connect", "tcp/127.0.0.1:9002"]
    argv += ["--listen", "tcp/127.0.0.1:9003", "--instance", "i2"]
    conf = config_from_args(_parse(argv))
    assert (conf.ns, conf.instance, conf.mode) == ("site_b", "i2", "client")
    assert endpoints(conf, "connect") == ["tcp/127.0.0.1:9001", "tcp/127.0.0.1:9002"]
    assert endpoints(conf, "listen") == ["tcp/127.0.0.1:9003"]
    assert conf.options("filtering", ("db",)) == {"db": "state.sqlite"}  # flags leave the rest


def test_deploy_files_load():
    service = load_config(SERVICE_CONFIG)
    assert (service.ns, service.mode) == ("tf", "client")
    assert endpoints(service, "connect") == [DEFAULT_ENDPOINT]
    router = load_config(ROUTER_CONFIG, listen=["tcp/127.0.0.1:9999"])
    assert router.mode == "router"
    assert endpoints(router, "listen") == ["tcp/127.0.0.1:9999"]
    assert load_config(ROUTER_CONFIG).zenoh == {
        "mode": "router",
        "listen": {"endpoints": [DEFAULT_ENDPOINT]},
        "scouting": {"multicast": {"enabled": False}},
    }


@pytest.mark.parametrize(
    ("text", "message"),
    [
        (None, r"config file .*bad.json5: cannot read: No such file"),
        ("{ns: 'tf',\n,}", r"bad.json5:2: not valid JSON5: Unexpected"),
        ("[1, 2]", "must hold a JSON5 object"),
        ("{modee: 'client'}", "invalid Zenoh settings.*modee"),
        ("{mode: 'server'}", "mode must be one of client, peer, router"),
        ("{ns: 'a/b'}", "ns 'a/b' contains forbidden characters"),
        ("{instance: ''}", "instance must be a non-empty string"),
        ("{connect: 'tcp/127.0.0.1:7447'}", "'connect' must be an object"),
        ("{services: {filtering: 3}}", "'services' must be an object of objects"),
        ("{services: {filtring: {}}}", "unknown section 'filtring'.*known sections: calib"),
    ],
)
def test_invalid_config_file_says_what_to_fix(tmp_path: Path, text: str | None, message: str):
    path = tmp_path / "bad.json5"
    if text is not None:
        path.write_text(text)
    with pytest.raises(ValueError, match=message) as excinfo:
        config_from_args(_parse(["--config", str(path)]))
    assert str(path) in str(excinfo.value)


def test_zenoh_config_from_plain_settings_forces_multicast_off():
    conf = zenoh_config({"mode": "router", "scouting": {"multicast": {"enabled": True}}})
    assert conf.get_json("scouting/multicast/enabled") == "false"
    assert conf.get_json("listen/endpoints") == f'["{DEFAULT_ENDPOINT}"]'


def test_a_service_without_instance_or_db_finds_its_file_again_after_a_restart():
    """The state file is named after the configured instance id, never the process's
    hostname-pid id (which would start every restart on an empty store)."""
    from services.runtime.config import default_db, default_instance

    assert default_db("calibration", None) == Path("var/calibration-default.sqlite")
    assert default_db("filtering", "f1") == Path("var/filtering-f1.sqlite")
    assert default_instance() not in str(default_db("alerting", None))
