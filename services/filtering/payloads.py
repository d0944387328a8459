"""Decoding of keyed payloads (a sample's key and bytes) into messages, and of stored event
rows into the filter's events."""

from __future__ import annotations

import logging
import math
from collections.abc import Iterable, Iterator, Sequence
from typing import Any

import msgspec

from schemas import (
    SCHEMA_VERSION,
    Calibration,
    DegradationPosterior,
    MaintenanceEvent,
    OnboardIndex,
    SchemaError,
    TrcRecord,
    decode,
    decode_many,
    keys,
)
from services.filtering.events import Event, EventMessage, ModelMessage, event_of, index_event

log = logging.getLogger(__name__)


# The message type of each event kind (the kind chunk of its key).
EVENT_TYPES = {"index": OnboardIndex, "trc": TrcRecord, "maintenance": MaintenanceEvent}
_MODEL_TYPES = {"calibration": Calibration, "degradation": DegradationPosterior}


def decode_keyed(key: str, payload: bytes) -> EventMessage | ModelMessage | None:
    """Decode a payload by the kind chunk of its key; None for a model kind we do not use.

    Raises SchemaError when the payload is malformed or disagrees with its key.
    """
    kind = keys.kind(key)
    message_type: type[EventMessage | ModelMessage]
    if kind in EVENT_TYPES:
        message_type = EVENT_TYPES[kind]
    elif kind != "model":
        raise SchemaError(f"key {key}: not an index, trc, maintenance or model key")
    elif keys.model_kind(key) in _MODEL_TYPES:
        message_type = _MODEL_TYPES[keys.model_kind(key)]
    else:
        return None
    message = decode(payload, message_type)
    keys.check_key(key, message)
    return message


def indices_of(items: Sequence[tuple[str, bytes]]) -> list[OnboardIndex | None]:
    """Each item's OnboardIndex as :func:`decode_keyed` gives it, for the items on index
    keys, decoded in one call (:func:`schemas.decode_many`); None for the others, and for
    all of them when one does not decode or disagrees with its key (:func:`decode_keyed`
    then says why, one by one)."""
    out: list[OnboardIndex | None] = [None] * len(items)
    at = [i for i, (key, _payload) in enumerate(items) if key.split("/", 2)[1:2] == ["index"]]
    msgs = decode_many([items[i][1] for i in at], OnboardIndex)
    if msgs is None:
        return out
    for i, msg in zip(at, msgs, strict=True):
        if items[i][0].partition("/")[2] != f"index/{msg.line}/{msg.segment}":
            return [None] * len(items)  # keys.check_key's form: {ns}/index/{line}/{segment}
        out[i] = msg
    return out


def _unchecked(message_type: type) -> type:
    """A Struct with the fields (names, types, defaults) of ``message_type`` and none of its
    checks (``__post_init__``): what a stored row of it decodes into."""
    fields: list[tuple[Any, ...]] = []
    for f in msgspec.structs.fields(message_type):
        if f.default is not msgspec.NODEFAULT:
            fields.append((f.name, f.type, f.default))
        elif f.default_factory is not msgspec.NODEFAULT:
            fields.append((f.name, f.type, msgspec.field(default_factory=f.default_factory)))
        else:
            fields.append((f.name, f.type))
    return msgspec.defstruct(
        f"Stored{message_type.__name__}",
        fields,
        kw_only=True,
        frozen=True,
        forbid_unknown_fields=True,
    )


StoredIndex = _unchecked(OnboardIndex)
_STORED = {kind: msgspec.msgpack.Decoder(t) for kind, t in EVENT_TYPES.items()}
_STORED_INDEX = msgspec.msgpack.Decoder(StoredIndex)


def stored_events(rows: Iterable[tuple[str, str, bytes]]) -> Iterator[Event]:
    """The core's events of stored ``(kind, key, payload)`` rows.

    The rows are the service's own re-encoding of messages it validated and whose key it
    checked, so they skip what guards the wire (size limit, nesting scan, key check): a
    re-run decodes every stored event, and those checks cost more than the fold. An index
    (nearly every row) is decoded into :data:`StoredIndex`, the same fields without the
    message's checks (nearly half of a re-run's decoding), and only what the fold
    needs is checked again: the schema version and positive finite indices (one may be
    left out: a unit measuring some indices only). TRC records
    and tampings run their checks. A row failing a check is skipped with a warning.
    """
    for kind, key, payload in rows:
        try:
            if kind == "index":
                msg = _STORED_INDEX.decode(payload)
                top, align = msg.top6_mm, msg.align10_mm
                if msg.v != SCHEMA_VERSION or not (
                    (0.0 < top < math.inf if top is not None else align is not None)
                    and (align is None or 0.0 < align < math.inf)
                ):
                    raise SchemaError(f"v {msg.v}, indices {top}, {align}")
                yield index_event(msg)
                continue
            msg = _STORED[kind].decode(payload)
        except (KeyError, msgspec.DecodeError, msgspec.ValidationError, SchemaError) as e:
            log.warning("store: skipping a stored %s that no longer decodes: %s", key, e)
            continue
        yield event_of(msg)
