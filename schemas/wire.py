"""Wire format: MessagePack maps via msgspec, arrays as little-endian bytes, one error type."""

from __future__ import annotations

import math
import sys
from collections.abc import Sequence
from typing import Any, TypeVar

import msgspec
import numpy as np

# dtype codes on the wire: numpy's kind+size, always little-endian.
DTYPES = {"f4": "<f4", "f8": "<f8", "i2": "<i2", "i4": "<i4", "u1": "|u1"}
MAX_ARRAY_ELEMENTS = 4_000_000  # ~30 min of one 7-channel unit at 2000 Hz; larger is an error
ID_FORBIDDEN = set("/*$?#")  # key-expression syntax; whitespace and control characters too
ID_MAX_CHARS = 64
MAX_NESTING = 32  # containers inside containers; the deepest valid message has 3
NESTING_SCAN_ITEMS = 10_000  # items looked at for nesting before decoding (a valid message: <300)
# Plausibility windows shared by the messages (see schemas/README.md, "Limits").
T_MIN = 946_684_800.0  # 2000-01-01T00:00:00Z: event times are on or after it
T_MAX = 4_102_444_800.0  # 2100-01-01T00:00:00Z: and before it (a fixed window, not the clock)
INT_MAX = 2**53  # counters and versions: exact in a float64 and in SQLite's INTEGER
_ITEMSIZE = {code: np.dtype(dtype).itemsize for code, dtype in DTYPES.items()}


class SchemaError(ValueError):
    """A payload or message that does not satisfy the wire contract; the message says why."""


def check(condition: bool, message: str) -> None:
    if not condition:
        raise SchemaError(message)


def check_finite(name: str, value: float | None, *, positive: bool = False) -> None:
    if value is None:
        return
    # ``if not …: raise`` rather than ``check(…, f"…")``: the message is only formatted when
    # it is needed (these checks run for every field of every message decoded)
    if not math.isfinite(value):
        raise SchemaError(f"{name}: must be finite, got {value!r}")
    if positive and not value > 0:
        raise SchemaError(f"{name}: must be > 0, got {value!r}")


def check_range(name: str, value: float | None, low: float, high: float) -> None:
    """``low <= value <= high`` (and finite); None passes (an optional field left out)."""
    if value is None:
        return
    check_finite(name, value)
    if not low <= value <= high:
        raise SchemaError(f"{name}: {value!r} outside [{low:g}, {high:g}]")


def check_time(name: str, value: float | None) -> None:
    """An event time in [2000-01-01, 2100-01-01) UTC, epoch s."""
    if value is None:
        return
    check_finite(name, value)
    if not T_MIN <= value < T_MAX:
        raise SchemaError(
            f"{name}: {value!r} outside [{T_MIN:.0f}, {T_MAX:.0f}) (2000-01-01 to 2100-01-01 UTC)"
        )


def check_int(name: str, value: int, low: int = 0, high: int = INT_MAX) -> None:
    """An integer in [low, high] (by default a count: [0, 2^53])."""
    if not low <= value <= high:
        raise SchemaError(f"{name}: {_short(value)} outside [{low}, {_int_text(high)}]")


def _int_text(value: int) -> str:
    return "2^53" if value == INT_MAX else str(value)


def _short(value: object, limit: int = 60) -> str:
    text = repr(value)
    return text if len(text) <= limit else f"{text[: limit - 3]}..."


_VALID_IDS: set[str] = set()  # ids that passed check_id (a few thousand lines, segments, trains)
_VALID_IDS_MAX = 200_000  # forgotten beyond this many: a flood of new ids cannot grow it


def check_id(name: str, value: str) -> None:
    """Ids become key-expression chunks: 1 to 64 characters, no `/ * $ ? #`, no whitespace or
    control characters, no leading `@` (Zenoh's verbatim chunks, never delivered to ``**``).

    An id that passed once passes again without the checks (every event repeats its line,
    segment, train and unit ids; checking them each time is a large share of a backlog's decode)."""
    if value in _VALID_IDS:
        return
    if not value:
        raise SchemaError(f"{name}: must be a non-empty string")
    if len(value) > ID_MAX_CHARS:
        raise SchemaError(f"{name}: {len(value)} characters > {ID_MAX_CHARS}")
    bad = ID_FORBIDDEN.intersection(value)
    if bad:
        raise SchemaError(f"{name}: {value!r} contains forbidden characters {sorted(bad)}")
    if not (value.isprintable() and not any(c.isspace() for c in value)):
        raise SchemaError(f"{name}: {value!r} contains whitespace or control characters")
    if value.startswith("@"):
        raise SchemaError(f"{name}: {value!r} starts with '@' (a verbatim chunk)")
    if len(_VALID_IDS) >= _VALID_IDS_MAX:
        _VALID_IDS.clear()
    _VALID_IDS.add(value)


_SUM_FINITE_BYTES = 1024 if sys.byteorder == "little" else 0  # the wire is little-endian
_FORMATS = {"f4": "f", "f8": "d"}


def _all_finite(dtype: str, data: bytes) -> bool:
    """No NaN or inf in float ``data``. A small array is summed in Python first (2 us less
    than numpy's ufunc and reduction, for each of a state's 11 arrays): a finite sum means
    every element is finite (a NaN or inf anywhere makes the sum NaN or inf); otherwise, or
    for a large array, numpy looks at each element (a finite sum can overflow)."""
    if len(data) <= _SUM_FINITE_BYTES and math.isfinite(
        sum(memoryview(data).cast(_FORMATS[dtype]))
    ):
        return True
    return bool(np.isfinite(np.frombuffer(data, dtype=DTYPES[dtype])).all())


class NDArray(msgspec.Struct, frozen=True):
    """An n-dimensional array: raw little-endian bytes of ``dtype`` in C order of ``shape``."""

    dtype: str
    shape: list[int]
    data: bytes

    def __post_init__(self) -> None:
        if self.dtype not in DTYPES:
            raise SchemaError(f"dtype: {self.dtype!r} not one of {sorted(DTYPES)}")
        if len(self.shape) > 8:
            raise SchemaError(f"shape: {len(self.shape)} dimensions > 8")
        if self.shape and min(self.shape) < 0:
            raise SchemaError(f"shape: negative extent in {self.shape}")
        size = math.prod(self.shape)
        if size > MAX_ARRAY_ELEMENTS:
            raise SchemaError(f"shape: {size} elements > {MAX_ARRAY_ELEMENTS}")
        itemsize = _ITEMSIZE[self.dtype]
        if len(self.data) != size * itemsize:
            raise SchemaError(
                f"data: {len(self.data)} bytes, shape {self.shape} of {self.dtype} needs "
                f"{size * itemsize}"
            )
        if self.dtype[0] == "f" and not _all_finite(self.dtype, self.data):
            raise SchemaError("data: contains NaN or inf")

    def array(self) -> np.ndarray:
        """A read-only numpy view of the bytes."""
        return np.frombuffer(self.data, dtype=DTYPES[self.dtype]).reshape(self.shape)

    @classmethod
    def of(cls, values: Any, dtype: str = "f8") -> NDArray:
        a = np.ascontiguousarray(values, dtype=DTYPES[dtype])
        return cls(dtype=dtype, shape=list(a.shape), data=a.tobytes())


def check_array(name: str, value: NDArray, shape: tuple[int | None, ...], kinds: str = "f") -> None:
    """Check an array field's rank, extents (None = any) and dtype kind."""
    if value.dtype[0] not in kinds:
        raise SchemaError(f"{name}: dtype {value.dtype} not of kind {kinds!r}")
    if not (
        len(value.shape) == len(shape)
        and all(want is None or want == got for want, got in zip(shape, value.shape, strict=True))
    ):
        raise SchemaError(f"{name}: shape {value.shape} does not match {list(shape)}")


def unchecked_copy(message: T, **changes: Any) -> T:
    """A copy of ``message`` with ``changes``, without running its checks (``__post_init__``).

    Only for a producer of many messages of one shape that checks them otherwise: a copy of
    a message that was checked, whose array fields keep their dtype and shape and whose new
    values the producer checked as the message would (the filter's summaries:
    :func:`services.filtering.summary.summarize_states`). Anything else builds its
    messages the checked way.
    """
    out = message.__copy__()  # type: ignore[attr-defined]
    for name, value in changes.items():
        msgspec.structs.force_setattr(out, name, value)
    return out


_encoder = msgspec.msgpack.Encoder()
_decoders: dict[type, msgspec.msgpack.Decoder] = {}
T = TypeVar("T")


def encode(message: msgspec.Struct) -> bytes:
    """MessagePack bytes of a message (a map with the documented field names)."""
    return _encoder.encode(message)


def decode(payload: bytes | bytearray | memoryview, message_type: type[T]) -> T:
    """Decode and validate ``payload`` as ``message_type``; raise SchemaError saying why not.

    A payload longer than the type's ``MAX_BYTES`` is refused before it is parsed; so is one
    nested too deep for the decoder (an unknown field holding a list in a list in …).
    """
    name = message_type.__name__
    limit = getattr(message_type, "MAX_BYTES", None)
    if limit is not None and len(payload) > limit:
        raise SchemaError(f"{name}: payload of {len(payload)} bytes > the limit of {limit}")
    deep = too_deep(payload)
    if deep is not None:
        raise SchemaError(f"{name}: {deep}: nested deeper than {MAX_NESTING} levels")
    try:
        return _decoder(message_type).decode(payload)
    except (msgspec.DecodeError, msgspec.ValidationError) as exc:
        raise SchemaError(f"{name}: {exc}") from None
    except UnicodeDecodeError as exc:  # a string (a field name too: unknown ones are named)
        raise SchemaError(
            f"{name}: a string is not UTF-8: {exc.reason} at byte {exc.start}"
        ) from None
    except RecursionError:  # deep nesting beyond the items scanned
        raise SchemaError(f"{name}: nested too deep to decode") from None


def _decoder(message_type: type[T]) -> msgspec.msgpack.Decoder:
    decoder = _decoders.get(message_type)
    if decoder is None:
        decoder = _decoders[message_type] = msgspec.msgpack.Decoder(message_type)
    return decoder


def _shallow(buf: bytes, limit: int) -> bool:
    """Nesting deeper than ``limit`` needs more than ``limit`` container headers, each one
    byte of the ranges below; a payload with fewer such bytes (strings and numbers may
    hold some too) cannot be that deep: the usual message, decided in one C call."""
    return len(buf) - len(buf.translate(None, _CONTAINER_BYTES)) <= limit


def decode_many(payloads: Sequence[bytes], message_type: type[T]) -> list[T] | None:
    """:func:`decode` of every payload, each as ``message_type``, with the same checks,
    in one call (a backlog decodes thousands: one call per payload is a noticeable share of
    its time); None if any of them would raise (:func:`decode` of each then says which and
    why). Plain ``bytes`` only."""
    limit = getattr(message_type, "MAX_BYTES", None)
    decoder = _decoder(message_type)
    for payload in payloads:  # what decode refuses before it parses, C calls only
        if type(payload) is not bytes or (limit is not None and len(payload) > limit):
            return None
        if not _shallow(payload, MAX_NESTING):
            return None  # perhaps too deep: too_deep looks further
    try:
        return [decoder.decode(payload) for payload in payloads]
    except Exception:  # any decode error, or a check in __post_init__: decode says which
        return None


_FIXED = {  # MessagePack scalar type byte -> bytes that follow it
    0xC0: 0, 0xC2: 0, 0xC3: 0, 0xCA: 4, 0xCB: 8, 0xCC: 1, 0xCD: 2, 0xCE: 4, 0xCF: 8,
    0xD0: 1, 0xD1: 2, 0xD2: 4, 0xD3: 8, 0xD4: 2, 0xD5: 3, 0xD6: 5, 0xD7: 9, 0xD8: 17,
}  # fmt: skip
_SIZED = {  # type byte -> (length bytes, extra bytes): bin, str and ext
    0xC4: (1, 0), 0xC5: (2, 0), 0xC6: (4, 0), 0xD9: (1, 0), 0xDA: (2, 0), 0xDB: (4, 0),
    0xC7: (1, 1), 0xC8: (2, 1), 0xC9: (4, 1),
}  # fmt: skip
_COUNTED = {0xDC: (2, 1), 0xDD: (4, 1), 0xDE: (2, 2), 0xDF: (4, 2)}  # array/map: count bytes
_CONTAINER_BYTES = bytes([*range(0x80, 0xA0), *_COUNTED])  # a map's or array's header byte


def _item(buf: bytes, pos: int) -> tuple[int, int]:
    """``(position after the header, items it contains)`` of the MessagePack item at ``pos``
    (a scalar or string is skipped whole and contains 0 items)."""
    b = buf[pos]
    if b <= 0x7F or b >= 0xE0:
        return pos + 1, 0
    if b <= 0x8F:
        return pos + 1, 2 * (b - 0x80)
    if b <= 0x9F:
        return pos + 1, b - 0x90
    if b <= 0xBF:
        return pos + 1 + b - 0xA0, 0
    if b in _FIXED:
        return pos + 1 + _FIXED[b], 0
    if b in _SIZED:
        n, extra = _SIZED[b]
        return pos + 1 + n + extra + int.from_bytes(buf[pos + 1 : pos + 1 + n], "big"), 0
    if b in _COUNTED:
        n, per = _COUNTED[b]
        return pos + 1 + n, per * int.from_bytes(buf[pos + 1 : pos + 1 + n], "big")
    raise ValueError(f"byte {b:#x} at {pos}")


def too_deep(
    payload: bytes | bytearray | memoryview,
    limit: int = MAX_NESTING,
    max_items: int = NESTING_SCAN_ITEMS,
) -> str | None:
    """The top-level map key whose value nests deeper than ``limit`` containers, if any.

    Iterative (no recursion) and bounded: it looks at the first ``max_items`` items only
    (what lies beyond is left to the decoder, which refuses what it cannot recurse into).
    None when the payload is not a map or no value within the items looked at is that deep.
    """
    buf = payload if isinstance(payload, bytes) else bytes(payload)
    if _shallow(buf, limit):
        return None
    budget = max_items
    try:
        pos, items = _item(buf, 0)
        if not 0x80 <= buf[0] <= 0x8F and buf[0] not in (0xDE, 0xDF):
            return None
        for _ in range(items // 2):
            key_start = pos
            pos, _n = _item(buf, pos)
            key = repr(msgspec.msgpack.decode(buf[key_start:pos]))[:40]
            stack: list[int] = []
            remaining = 1
            while remaining or stack:
                if not remaining:
                    remaining = stack.pop()
                    continue
                remaining -= 1
                budget -= 1
                if budget < 0:
                    return None
                start = buf[pos]
                pos, n = _item(buf, pos)
                if n and (0x80 <= start <= 0x9F or start in _COUNTED):
                    stack.append(remaining)
                    if len(stack) > limit:
                        return key
                    remaining = n
    except (IndexError, ValueError, msgspec.DecodeError):
        return None
    return None
