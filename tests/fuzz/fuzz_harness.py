"""Running a service under fuzz: in a thread on its own namespace, valid traffic with bad
messages between it, end of input detected by markers, its results collected (see the
docstring of tests/fuzz/test_fuzz.py)."""

from __future__ import annotations

import contextlib
import os
import queue
import random
import sqlite3
from collections import Counter
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import msgpack
import pytest
import zenoh
from fuzz_inputs import Bad, Fuzzer
from fuzz_specs import RecordingCore, Spec
from support import ServiceThread

from schemas import (
    DeadLetter,
    SchemaError,
    decode,
    keys,
)
from services.runtime.config import RuntimeConfig
from services.runtime.delivery import ReliablePublisher
from services.viewer import service as viewer
from services.viewer.testing import rrd_contents

N_BAD = int(os.environ.get("TF_FUZZ_N", "10000"))  # bad messages per service
SEED = int(os.environ.get("TF_FUZZ_SEED", "7"))
BLOCK = zenoh.CongestionControl.BLOCK
PUT = zenoh.SampleKind.PUT
TIMEOUT_S = 10.0  # upper bound of one wait; normally milliseconds
WINDOW = 256  # bad messages in flight without their dead letter
MARKER = b"\xc1tf-fuzz-marker "  # 0xc1: a byte MessagePack never uses, so always refused


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
        self.exit_code: int | None = None
        self.markers = 0
        self.subscribers: list[zenoh.Subscriber] = []
        self.publishers: list[ReliablePublisher] = []  # the service's, flushed by `sync`
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
        alive = self.alive_events = queue.Queue()
        self.subscribers.append(
            self.session.liveliness().declare_subscriber(self.alive_key, alive.put)
        )
        spec = self.spec
        self._stop_recording = record_publishers(self.publishers)
        self.service = ServiceThread(
            spec.name, lambda stop: spec.main(self.conf, stop, self.tmp)
        ).start()
        try:
            sample = alive.get(timeout=TIMEOUT_S)
            assert sample.kind == PUT
        except (queue.Empty, AssertionError):
            self.__exit__()  # no block to end: stop it here
            raise AssertionError(f"{spec.name} did not come alive") from None
        return self

    def __exit__(self, *_exc: object) -> None:
        try:
            self.exit_code = self.service.stop(TIMEOUT_S)
        finally:
            self._stop_recording()
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
        """Until every worker has handled everything put so far, and its outputs are out.

        A reliable publisher puts from its own writer thread, after recording the message in
        its outbox, so a marker's letter can overtake an output queued before it: its
        publishers are flushed, then one more marker goes through. The service's outputs
        and letters leave one session on one priority, in order, and one callback here sees
        them in that order."""
        marker_keys = self.spec.marker_keys or [self.spec.inputs[0].key]
        for _ in range(2):  # twice: a batching worker publishes after a batch's letters
            for key in marker_keys:
                self.letters.until(self.marker(key))
        for publisher in self.publishers:
            assert publisher.flush(TIMEOUT_S), f"{publisher.producer}: outputs not put"
        for key in marker_keys:
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
        """The service runs and its liveliness token is at the router: the token's events
        since it came alive end in a PUT. A token dropped and declared again (a session that
        lost the router for a moment on a loaded machine) counts as alive; one gone for
        longer than TIMEOUT_S does not."""
        assert self.service.running, f"{self.spec.name} has stopped"
        present = True
        while True:
            try:
                sample = self.alive_events.get(timeout=0 if present else TIMEOUT_S)
            except queue.Empty:
                break
            present = sample.kind == PUT
        assert present, f"{self.spec.name}: liveliness token gone"


def record_publishers(into: list[ReliablePublisher]) -> Callable[[], None]:
    """Append every ReliablePublisher made from now on to ``into``; returns the undo."""
    init = ReliablePublisher.__init__

    def recording(self: ReliablePublisher, *args: Any, **kwargs: Any) -> None:
        init(self, *args, **kwargs)
        into.append(self)

    ReliablePublisher.__init__ = recording  # type: ignore[method-assign]

    def undo() -> None:
        ReliablePublisher.__init__ = init  # type: ignore[method-assign]

    return undo


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
    assert run.exit_code == 0, f"{spec.name}: exit {run.exit_code}"
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


def stored_bytes(run_dir: Path) -> tuple[int, int]:
    """(rows, payload bytes) in a filtering run's store."""
    with contextlib.closing(sqlite3.connect(run_dir / "filtering.sqlite")) as db:
        return db.execute(
            "SELECT COUNT(*) + (SELECT COUNT(*) FROM models),"
            " COALESCE(SUM(LENGTH(payload)), 0)"
            " + (SELECT COALESCE(SUM(LENGTH(payload)), 0) FROM models) FROM events"
        ).fetchone()
