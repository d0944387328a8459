"""Publishing the simulated world on Zenoh: a thin, paced loop over ``world_events``.

Fleet gateways are written in other languages, so RawChunk and GpsFix are packed with the
plain ``msgpack`` package as maps of the documented field names (schemas/README.md), the way
such a gateway would; the simulator's other feeds (TRC import, maintenance, fast-mode
indices) use the schemas' encoder. Pacing follows event time: ``speedup`` simulated seconds
per wall second (``inf``: as fast as the subscribers take it).
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable, Iterable, Iterator

import msgpack
import msgspec
import zenoh

from schemas import (
    GpsFix,
    MaintenanceEvent,
    Message,
    NDArray,
    OnboardIndex,
    RawChunk,
    TrcRecord,
    encode,
    keys,
)
from services.runtime.delivery import ReliablePublisher

log = logging.getLogger(__name__)


def plain_map(message: msgspec.Struct) -> dict:
    """The message as a plain map, arrays as {dtype, shape, data} (what a gateway builds)."""
    out = {}
    for name in message.__struct_fields__:
        value = getattr(message, name)
        if isinstance(value, NDArray):
            value = {"dtype": value.dtype, "shape": list(value.shape), "data": value.data}
        out[name] = value
    return out


def key_and_payload(ns: str, message: Message) -> tuple[str, bytes]:
    """The wire key of a simulated message and its MessagePack bytes."""
    match message:
        case RawChunk():
            return keys.raw(ns, message.train, message.unit), msgpack.packb(plain_map(message))
        case GpsFix():
            return keys.gps(ns, message.train), msgpack.packb(plain_map(message))
        case OnboardIndex():
            return keys.index(ns, message.line, message.segment), encode(message)
        case TrcRecord():
            return keys.trc(ns, message.line, message.segment), encode(message)
        case MaintenanceEvent():
            return keys.maintenance(ns, message.line, message.segment), encode(message)
    raise TypeError(f"the simulator does not publish {type(message).__name__}")


def paced(
    events: Iterable[tuple[float, list[Message]]],
    speedup: float,
    stop: threading.Event,
    clock: Callable[[], float] = time.monotonic,
) -> Iterator[tuple[float, list[Message]]]:
    """Yield events no earlier than their event time scaled by ``speedup`` allows.

    Waiting is ``stop.wait`` so that a stop request ends it at once.
    """
    start_wall, start_t = clock(), None
    for t, messages in events:
        if stop.is_set():
            return
        if start_t is None:
            start_t = t
        if math.isfinite(speedup):
            delay = (t - start_t) / speedup - (clock() - start_wall)
            if delay > 0 and stop.wait(delay):
                return
        yield t, messages


def publish(
    session,
    ns: str,
    events: Iterable[tuple[float, list[Message]]],
    *,
    reliable: ReliablePublisher | None = None,
    gateway: ReliablePublisher | None = None,
    speedup: float = math.inf,
    stop: threading.Event | None = None,
    on_batch: Callable[[float, list[Message]], None] | None = None,
) -> int:
    """Put every message of ``events`` on its key; returns how many were published.

    With ``reliable``, the event streams (OnboardIndex, TrcRecord, MaintenanceEvent) go
    through it (recorded for subscribers that return, see :mod:`services.runtime.delivery`).
    With ``gateway`` (producer ``gateway/{id}``), raw chunks and GPS fixes go through it, as
    a fleet gateway with an outbox sends them: ingestion reads them in order and none it
    acknowledged is lost; without, they are plain puts (at most once).
    """
    stop = stop or threading.Event()
    count = 0
    for t, messages in paced(events, speedup, stop):
        for message in messages:
            key, payload = key_and_payload(ns, message)
            raw = isinstance(message, RawChunk | GpsFix)
            if raw and gateway is not None:
                gateway.put(key, payload)
            elif reliable is not None and not raw:
                reliable.put(key, payload)
            else:
                # BLOCK: a simulated gateway waits for the network rather than dropping data.
                session.put(key, payload, congestion_control=zenoh.CongestionControl.BLOCK)
        count += len(messages)
        if on_batch:
            on_batch(t, messages)
    return count
