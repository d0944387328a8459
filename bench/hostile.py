"""Wrong input fed to a running stack, as a careless or hostile sender would: for the soak.

:func:`hostile_messages` builds one payload per kind of mistake the services must refuse
with a dead letter (never a crash, never a changed model): bytes that are not MessagePack,
a map missing required fields, a tamping on a segment the network lacks, a payload whose
segment disagrees with its key, an index with a negative value, a unit calibration whose
R is not positive definite, and one published on another unit's key. :class:`DeadLetters`
collects what the services answer on ``{ns}/deadletter/**``, and :func:`unanswered` says
which bad message got no dead letter at all.

``python -m bench.demo_soak --hostile 8`` feeds them at minute 8 of the soak and checks
that each got its dead letter and that every process stayed alive.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

import msgpack
import zenoh

from schemas import Calibration, DeadLetter, MaintenanceEvent, NDArray, decode, encode, keys

IDENTITY = [[1.0, 0.0], [0.0, 1.0]]


@dataclass(frozen=True)
class Hostile:
    """One bad message: what is wrong with it, its key and its payload."""

    what: str
    key: str
    payload: bytes


def _calibration(t: float, train: str, unit: str, R: list[list[float]]) -> Calibration:
    return Calibration(
        version=1,
        t=t,
        indicators=["top6", "align10"],
        indices=["top6", "align10"],
        H=NDArray.of(IDENTITY),
        b=NDArray.of([0.0, 0.0]),
        R=NDArray.of(R),
        n_pairs=5,
        r2=NDArray.of([0.5, 0.5]),
        train=train,
        unit=unit,
    )


def hostile_messages(ns: str, line: str, t: float) -> list[Hostile]:
    """The bad messages for a stack whose network has ``line`` (with segments s00001–3)."""
    a, b, c = "s00001", "s00002", "s00003"
    negative = {"v": 1, "line": line, "segment": a, "train": "TX", "unit": "u1", "t": t,
                "top6_mm": -1.0, "align10_mm": 1.0, "speed_mps": 20.0, "coverage": 1.0}  # fmt: skip
    return [
        Hostile("not MessagePack", keys.index(ns, line, a), b"\xc1garbage"),
        Hostile("a raw chunk not MessagePack", keys.raw(ns, "T000", "u0"), b"\xc1garbage"),
        Hostile(
            "a positioned chunk missing fields",
            keys.accel(ns, "T000", "u0"),
            msgpack.packb({"v": 1, "train": "T000", "unit": "u0"}),
        ),
        Hostile(
            "a map missing fields", keys.index(ns, line, a), msgpack.packb({"v": 1, "line": line})
        ),
        Hostile("a negative index", keys.index(ns, line, a), msgpack.packb(negative)),
        Hostile(
            "a tamping on a segment the network lacks",
            keys.maintenance(ns, "NOLINE", "s00000"),
            encode(
                MaintenanceEvent(line="NOLINE", segment="s00000", event_id="x", t_start=t, t_end=t)
            ),
        ),  # fmt: skip
        Hostile(
            "a payload disagreeing with its key",
            keys.maintenance(ns, line, b),
            encode(MaintenanceEvent(line=line, segment=c, event_id="y", t_start=t, t_end=t)),
        ),
        Hostile(
            "a unit calibration with R not positive definite",
            keys.unit_calibration(ns, "TX", "u1"),
            encode(_calibration(t, "TX", "u1", [[-1.0, 0.0], [0.0, 1.0]])),
        ),
        Hostile(
            "a unit calibration on another unit's key",
            keys.unit_calibration(ns, "TY", "u1"),
            encode(_calibration(t, "TX", "u1", [[0.01, 0.0], [0.0, 0.01]])),
        ),
    ]


class DeadLetters:
    """The dead letters of a namespace, as they arrive (a Zenoh callback: lock, list)."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.letters: list[DeadLetter] = []

    def on_sample(self, sample: zenoh.Sample) -> None:
        letter = decode(sample.payload.to_bytes(), DeadLetter)
        with self.lock:
            self.letters.append(letter)

    def snapshot(self) -> list[DeadLetter]:
        with self.lock:
            return list(self.letters)


def answered(message: Hostile, letters: list[DeadLetter]) -> list[DeadLetter]:
    """The dead letters about ``message``: same key, same first bytes of the payload."""
    head = message.payload[:32]
    return [d for d in letters if d.key == message.key and d.payload_head[:32] == head]


def unanswered(messages: list[Hostile], letters: list[DeadLetter]) -> list[str]:
    """What is wrong with each message that got no dead letter."""
    return [m.what for m in messages if not answered(m, letters)]
