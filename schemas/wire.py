"""Wire format: MessagePack maps via msgspec, arrays as little-endian bytes, one error type."""

from __future__ import annotations

import math
from typing import Any, TypeVar

import msgspec
import numpy as np

# dtype codes on the wire: numpy's kind+size, always little-endian.
DTYPES = {"f4": "<f4", "f8": "<f8", "i2": "<i2", "i4": "<i4", "u1": "|u1"}
MAX_ARRAY_ELEMENTS = 4_000_000  # ~30 min of one 7-channel unit at 2000 Hz; larger is an error
ID_FORBIDDEN = set("/*$?# ")


class SchemaError(ValueError):
    """A payload or message that does not satisfy the wire contract; the message says why."""


def check(condition: bool, message: str) -> None:
    if not condition:
        raise SchemaError(message)


def check_finite(name: str, value: float | None, *, positive: bool = False) -> None:
    if value is None:
        return
    check(math.isfinite(value), f"{name}: must be finite, got {value!r}")
    if positive:
        check(value > 0, f"{name}: must be > 0, got {value!r}")


def check_id(name: str, value: str) -> None:
    """Ids become key-expression chunks: non-empty, no `/ * $ ? #` and no spaces."""
    check(bool(value), f"{name}: must be a non-empty string")
    bad = ID_FORBIDDEN.intersection(value)
    check(not bad, f"{name}: {value!r} contains forbidden characters {sorted(bad)}")


class NDArray(msgspec.Struct, frozen=True):
    """An n-dimensional array: raw little-endian bytes of ``dtype`` in C order of ``shape``."""

    dtype: str
    shape: list[int]
    data: bytes

    def __post_init__(self) -> None:
        check(self.dtype in DTYPES, f"dtype: {self.dtype!r} not one of {sorted(DTYPES)}")
        check(all(s >= 0 for s in self.shape), f"shape: negative extent in {self.shape}")
        size = math.prod(self.shape)
        check(size <= MAX_ARRAY_ELEMENTS, f"shape: {size} elements > {MAX_ARRAY_ELEMENTS}")
        itemsize = np.dtype(DTYPES[self.dtype]).itemsize
        check(
            len(self.data) == size * itemsize,
            f"data: {len(self.data)} bytes, shape {self.shape} of {self.dtype} needs "
            f"{size * itemsize}",
        )
        if self.dtype[0] == "f":
            check(bool(np.isfinite(self.array()).all()), "data: contains NaN or inf")

    def array(self) -> np.ndarray:
        """A read-only numpy view of the bytes."""
        return np.frombuffer(self.data, dtype=DTYPES[self.dtype]).reshape(self.shape)

    @classmethod
    def of(cls, values: Any, dtype: str = "f8") -> NDArray:
        a = np.ascontiguousarray(values, dtype=DTYPES[dtype])
        return cls(dtype=dtype, shape=list(a.shape), data=a.tobytes())


def check_array(name: str, value: NDArray, shape: tuple[int | None, ...], kinds: str = "f") -> None:
    """Check an array field's rank, extents (None = any) and dtype kind."""
    check(value.dtype[0] in kinds, f"{name}: dtype {value.dtype} not of kind {kinds!r}")
    check(
        len(value.shape) == len(shape)
        and all(want is None or want == got for want, got in zip(shape, value.shape, strict=True)),
        f"{name}: shape {value.shape} does not match {list(shape)}",
    )


_encoder = msgspec.msgpack.Encoder()
_decoders: dict[type, msgspec.msgpack.Decoder] = {}
T = TypeVar("T")


def encode(message: msgspec.Struct) -> bytes:
    """MessagePack bytes of a message (a map with the documented field names)."""
    return _encoder.encode(message)


def decode(payload: bytes | bytearray | memoryview, message_type: type[T]) -> T:
    """Decode and validate ``payload`` as ``message_type``; raise SchemaError saying why not."""
    decoder = _decoders.get(message_type)
    if decoder is None:
        decoder = _decoders[message_type] = msgspec.msgpack.Decoder(message_type)
    try:
        return decoder.decode(payload)
    except (msgspec.DecodeError, msgspec.ValidationError) as exc:
        raise SchemaError(f"{message_type.__name__}: {exc}") from None
