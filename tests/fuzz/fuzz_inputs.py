"""Bad messages for a service's inputs: seeded mutations of a valid template (random
bytes, wrong types and shapes, missing fields, NaN and inf, huge arrays, unknown versions,
wrong keys, out-of-range values, truncations, …), each one refusable by the schema."""

from __future__ import annotations

import math
import os
import random
from dataclasses import dataclass
from typing import Any

import msgpack
import msgspec
import numpy as np
from fuzz_specs import Input, plain

from schemas import (
    NDArray,
    SchemaError,
    decode,
    encode,
)


@dataclass(frozen=True)
class Bad:
    kind: str
    key: str
    payload: bytes
    detail: str = ""  # what was changed, for failure messages


KINDS = (
    "random_bytes",
    "not_a_map",
    "wrong_type",
    "missing_field",
    "nan_inf",
    "nan_in_array",
    "huge_array",
    "unknown_version",
    "wrong_key",
    "wrong_message_type",
    "out_of_range",
    "truncated",
    "extra_key_prefix",
    "deep_nesting",
    "big_int",
    "huge_float",
    "far_time",
    "bad_id",
    "huge_unknown",
    "oversize",
)
TIME_FIELDS = ("t", "t0", "t_start", "t_end", "last_trc_t")
ID_FIELDS = ("train", "unit", "line", "segment", "run_id", "event_id", "group", "posterior_group")
FAR_TIMES = (0.0, -1e9, 32_503_680_000.0, 2.0**63, -(2.0**63), 2**63 - 1, -(2**63))  # 3000 AD
BIG_INTS = (2**63, 2**64 - 1, 2**63 - 1, -(2**63), 2**53 + 1)  # MessagePack stops at 64 bits
HUGE_FLOATS = (1e308, -1e308, 1.7976931348623157e308)  # near the largest float, and it
BAD_IDS = ("@x", "@", "a/b", "L1/s1", "a b", "a\tb", "a\nb", "a\x00b", "x" * 65, "a*", "$a")
HUGE_BYTES = 5_000_000  # an unknown field of 5 MB
HUGE_BUDGET = 6  # payloads of megabytes per run: they cost the 2-core CI seconds each
if os.environ.get("TF_FUZZ_KINDS"):  # a comma-separated subset, e.g. to bisect a failure
    KINDS = tuple(os.environ["TF_FUZZ_KINDS"].split(","))


class Fuzzer:
    """Seeded bad messages for a service's inputs, each checked to be refusable."""

    def __init__(self, inputs: list[Input], seed: int) -> None:
        self.inputs = inputs
        self.rng = random.Random(seed)
        self.np_rng = np.random.default_rng(seed)
        self.last_valid: dict[str, bytes] = {}  # per input key: the last valid payload sent
        self.huge_left = HUGE_BUDGET

    def next(self) -> Bad:
        while True:
            inp = self.rng.choice(self.inputs)
            kind = self.rng.choice(KINDS)
            self.detail = ""
            made = getattr(self, f"_{kind}")(inp)
            if made is not None:
                key, payload = made
                return Bad(kind, key, payload, self.detail)

    # each returns (key, payload) or None when the kind does not apply to the input

    def _random_bytes(self, inp: Input) -> tuple[str, bytes] | None:
        n = self.rng.choice((0, 1, 2, 8, 64, 300))
        return inp.key, self.rng.randbytes(n) if n else b""

    def _not_a_map(self, inp: Input) -> tuple[str, bytes] | None:
        values = list(plain(inp.template).values())
        choice = self.rng.choice([values, "a string", 42, None, 3.5, [1, 2, 3], b"\x00\x01", True])
        return inp.key, msgpack.packb(choice)

    def _fields(self, inp: Input) -> dict[str, msgspec.structs.FieldInfo]:
        return {f.encode_name: f for f in msgspec.structs.fields(type(inp.template))}

    def _wrong_type(self, inp: Input) -> tuple[str, bytes] | None:
        m = plain(inp.template)
        name = self.rng.choice(list(m))
        m[name] = self.rng.choice(wrong_values(m[name], optional=self._optional(inp, name)))
        self.detail = f"{name}={m[name]!r:.40}"
        return inp.key, msgpack.packb(front(m, name))

    def _optional(self, inp: Input, name: str) -> bool:
        info = self._fields(inp)[name]
        return "None" in repr(info.type)

    def _missing_field(self, inp: Input) -> tuple[str, bytes] | None:
        m = plain(inp.template)
        required = [f.encode_name for f in self._fields(inp).values() if f.required]
        for name in self.rng.sample(required, k=self.rng.randint(1, len(required))):
            del m[name]
        return inp.key, msgpack.packb(m)

    def _nan_inf(self, inp: Input) -> tuple[str, bytes] | None:
        m = plain(inp.template)
        floats = [k for k, v in m.items() if isinstance(v, float) or self._is_float(inp, k)]
        if not floats:
            return None
        name = self.rng.choice(floats)
        m[name] = self.rng.choice((math.nan, math.inf, -math.inf))
        self.detail = f"{name}={m[name]}"
        return inp.key, msgpack.packb(front(m, name))

    def _is_float(self, inp: Input, name: str) -> bool:
        return "float" in repr(self._fields(inp)[name].type)

    def _arrays(self, m: dict[str, Any]) -> list[str]:
        return [k for k, v in m.items() if isinstance(v, dict) and {"dtype", "shape"} <= set(v)]

    def _nan_in_array(self, inp: Input) -> tuple[str, bytes] | None:
        m = plain(inp.template)
        names = [k for k in self._arrays(m) if math.prod(m[k]["shape"]) > 0]
        if not names:
            return None
        name = self.rng.choice(names)
        a = NDArray(**m[name]).array().astype(self.rng.choice(("<f4", "<f8")))
        a.flat[self.rng.randrange(a.size)] = self.rng.choice((math.nan, math.inf, -math.inf))
        m[name] = {"dtype": a.dtype.str[1:], "shape": list(a.shape), "data": a.tobytes()}
        self.detail = f"{name} with NaN or inf"
        return inp.key, msgpack.packb(front(m, name))

    def _huge_array(self, inp: Input) -> tuple[str, bytes] | None:
        m = plain(inp.template)
        names = self._arrays(m)
        if not names:  # no array field: a huge list where a scalar belongs
            name = self.rng.choice(list(m))
            m[name] = [1.0] * (100_000 if self.rng.random() < 0.01 else 1_000)
            self.detail = f"{name}=[1.0] * {len(m[name])}"
            return inp.key, msgpack.packb(front(m, name))
        name = self.rng.choice(names)
        arr = m[name]
        variant = self.rng.randrange(5)
        if variant == 0:  # declared shape far too large, little data
            arr["shape"] = [10**7, *arr["shape"][1:]] if arr["shape"] else [10**7]
        elif variant == 1:  # declared shape that overflows any index type
            arr["shape"] = [2**62, 2**62]
        elif variant == 2:  # data length disagreeing with the shape
            arr["data"] = arr["data"][:-1] if arr["data"] else b"\x00"
        elif variant == 3:  # negative extent
            arr["shape"] = [-1, *arr["shape"][1:]]
        else:  # an unknown dtype
            arr["dtype"] = self.rng.choice(("f16", "c8", "<f8", "", "object"))
        self.detail = f"{name}: {arr['dtype']} {arr['shape']} {len(arr['data'])} bytes"
        return inp.key, msgpack.packb(front(m, name))

    def _unknown_version(self, inp: Input) -> tuple[str, bytes] | None:
        m = plain(inp.template)
        m["v"] = self.rng.choice((0, 2, 3, 99, -1, 2**40))
        return inp.key, msgpack.packb(m)

    def _wrong_key(self, inp: Input) -> tuple[str, bytes] | None:
        return self.rng.choice(inp.wrong_keys), encode(inp.template)

    def _wrong_message_type(self, inp: Input) -> tuple[str, bytes] | None:
        # a payload of another type that decodes as this one (its fields are a superset):
        # nothing on the wire tells them apart, so it is not sent (see the report)
        return _if_refused(inp, encode(self.rng.choice(inp.others)))

    def _out_of_range(self, inp: Input) -> tuple[str, bytes] | None:
        m = plain(inp.template)
        patch = self.rng.choice(inp.out_of_range)
        m.update(patch)
        self.detail = f"{patch!r:.80}"
        return inp.key, msgpack.packb(front(m, *patch))

    def _refused(self, inp: Input, m: dict[str, Any], *first: str) -> tuple[str, bytes] | None:
        """``m`` packed on the input's key if its type refuses it, else None (not sent)."""
        return _if_refused(inp, msgpack.packb(front(m, *first)))

    def _deep_nesting(self, inp: Input) -> tuple[str, bytes] | None:
        # an unknown field holding a list in a list in ... (msgpack's packer refuses to
        # nest this deep, so the map is written by hand, the deep field first)
        m = plain(inp.template)
        depth = self.rng.choice((33, 100, 1_000, 3_000, 10_000))
        self.detail = f"extra field nested {depth} deep"
        body = b"".join(msgpack.packb(k) + msgpack.packb(v) for k, v in m.items())
        deep = msgpack.packb("fuzz_deep") + b"\x91" * depth + b"\x90"
        return inp.key, map_header(len(m) + 1) + deep + body

    def _big_int(self, inp: Input) -> tuple[str, bytes] | None:
        # integers beyond int64 and beyond SQLite's INTEGER, in integer or float fields
        m = plain(inp.template)
        names = [k for k, v in m.items() if isinstance(v, int | float) and not isinstance(v, bool)]
        self.rng.shuffle(names)
        return self._first_refused(inp, m, names, self.rng.choice(BIG_INTS))

    def _huge_float(self, inp: Input) -> tuple[str, bytes] | None:
        m = plain(inp.template)
        names = [k for k, v in m.items() if isinstance(v, float) or self._is_float(inp, k)]
        self.rng.shuffle(names)
        return self._first_refused(inp, m, names, self.rng.choice(HUGE_FLOATS))

    def _first_refused(
        self, inp: Input, m: dict[str, Any], names: list[str], value
    ) -> tuple[str, bytes] | None:
        """``m`` with the first of ``names`` set to ``value`` whose type refuses it."""
        for name in names:
            made = self._refused(inp, m | {name: value}, name)
            if made is not None:
                self.detail = f"{name}={value}"
                return made
        return None

    def _far_time(self, inp: Input) -> tuple[str, bytes] | None:
        m = plain(inp.template)
        names = [k for k in TIME_FIELDS if k in m]
        if not names:
            return None
        name, value = self.rng.choice(names), self.rng.choice(FAR_TIMES)
        if name == "t_start":  # keep t_end >= t_start out of the way: both move
            m["t_end"] = value
        self.detail = f"{name}={value}"
        return self._refused(inp, m | {name: value}, name)  # a model's t = 0 is a prior

    def _bad_id(self, inp: Input) -> tuple[str, bytes] | None:
        m = plain(inp.template)
        names = [k for k in ID_FIELDS if k in m]
        if not names:
            return None
        name, value = self.rng.choice(names), self.rng.choice(BAD_IDS)
        self.detail = f"{name}={value!r}"
        return self._refused(inp, m | {name: value}, name)

    def _huge_unknown(self, inp: Input) -> tuple[str, bytes] | None:
        # an unknown field of 5 MB: beyond every message's size limit
        if self.huge_left <= 0:
            return None
        self.huge_left -= 1
        m = plain(inp.template)
        m["fuzz_blob"] = self.rng.choice((b"\x00" * HUGE_BYTES, "x" * HUGE_BYTES))
        self.detail = f"unknown field of {HUGE_BYTES} bytes"
        return inp.key, msgpack.packb(m)

    def _oversize(self, inp: Input) -> tuple[str, bytes] | None:
        # a valid message padded by an unknown field to just beyond its type's size limit
        limit = type(inp.template).MAX_BYTES
        if limit > 1_000_000:
            if self.huge_left <= 0:
                return None
            self.huge_left -= 1
        m = plain(inp.template)
        size = len(msgpack.packb(m))
        pad = limit - size + self.rng.randint(1, 100)
        m["fuzz_pad"] = b"\x00" * pad
        self.detail = f"{len(msgpack.packb(m))} bytes > {limit}"
        return inp.key, msgpack.packb(m)

    def _truncated(self, inp: Input) -> tuple[str, bytes] | None:
        payload = encode(inp.template)
        return inp.key, payload[: self.rng.randrange(1, len(payload))]

    def _extra_key_prefix(self, inp: Input) -> tuple[str, bytes] | None:
        # a valid message already sent, again, on its key with an extra leading chunk
        if inp.prefix_key is None or inp.key not in self.last_valid:
            return None
        return inp.prefix_key, self.last_valid[inp.key]


def front(m: dict[str, Any], *names: str) -> dict[str, Any]:
    """``m`` with ``names`` first: the mutation lands in the dead letter's 256-byte head."""
    return {n: m[n] for n in names if n in m} | m


def map_header(n: int) -> bytes:
    """The MessagePack header of a map of ``n`` pairs."""
    return bytes([0x80 | n]) if n < 16 else b"\xde" + n.to_bytes(2, "big")


def wrong_values(value: Any, *, optional: bool) -> list[Any]:
    """Values of another type than ``value`` that a strict decoder must refuse."""
    if isinstance(value, bool):
        return ["true", 2.5, [True]]
    if isinstance(value, int):
        return ["1", 1.5, [1], {"n": 1}]
    if isinstance(value, float):
        return ["1.0", [1.0], {"x": 1.0}, b"\x00"] + ([] if optional else [None])
    if isinstance(value, str):
        return [5, 1.5, ["a"], {"a": 1}, None]
    if isinstance(value, list):
        return ["abc", 7, {"a": 1}, [1, 2]]
    if isinstance(value, dict):
        return [[1, 2, 3], "array", {"dtype": "f8"}, {"dtype": 8, "shape": [1], "data": b""}]
    if value is None:
        return ["x", [1.0], {"a": 1}]
    return [None]


def _if_refused(inp: Input, payload: bytes) -> tuple[str, bytes] | None:
    """``payload`` on the input's key if the input's type refuses it, else None (not sent)."""
    try:
        decode(payload, type(inp.template))
    except SchemaError:
        return inp.key, payload
    return None
