"""Key expressions of DESIGN's key table: the only place they are spelled out.

Every builder checks its id chunks, so a key never carries `/ * $ ? #` by accident.
Wildcard variants (``*_all``) are for subscribers.
"""

from __future__ import annotations

from schemas.wire import check_id

DEFAULT_NS = "tf"


def _key(ns: str, *chunks: str) -> str:
    check_id("ns", ns)
    for chunk in chunks:
        check_id("key chunk", chunk)
    return "/".join((ns, *chunks))


def raw(ns: str, train: str, unit: str) -> str:
    return _key(ns, "raw", train, unit)


def raw_all(ns: str) -> str:
    return f"{_key(ns, 'raw')}/**"


def gps(ns: str, train: str) -> str:
    return _key(ns, "gps", train)


def gps_all(ns: str) -> str:
    return f"{_key(ns, 'gps')}/*"


def accel(ns: str, train: str, unit: str) -> str:
    return _key(ns, "accel", train, unit)


def accel_all(ns: str) -> str:
    return f"{_key(ns, 'accel')}/**"


def index(ns: str, line: str, segment: str) -> str:
    return _key(ns, "index", line, segment)


def trc(ns: str, line: str, segment: str) -> str:
    return _key(ns, "trc", line, segment)


def maintenance(ns: str, line: str, segment: str) -> str:
    return _key(ns, "maintenance", line, segment)


def state(ns: str, line: str, segment: str) -> str:
    return _key(ns, "state", line, segment)


def alert(ns: str, line: str, segment: str) -> str:
    return _key(ns, "alert", line, segment)


def segment_keys(ns: str, kind: str, selector: str = "**") -> str:
    """Subscriber key for a per-segment kind (index, trc, maintenance, state, alert).

    ``selector`` narrows to part of the network, e.g. ``"L1/**"`` for one line.
    """
    if kind not in {"index", "trc", "maintenance", "state", "alert"}:
        raise ValueError(f"kind: {kind!r} is not a per-segment key kind")
    return f"{_key(ns, kind)}/{selector}"


def calibration(ns: str) -> str:
    return _key(ns, "model", "calibration")


def degradation(ns: str, group: str) -> str:
    return _key(ns, "model", "degradation", group)


def model_all(ns: str) -> str:
    return f"{_key(ns, 'model')}/**"


def deadletter(ns: str, service: str) -> str:
    return _key(ns, "deadletter", service)


def deadletter_all(ns: str) -> str:
    return f"{_key(ns, 'deadletter')}/**"


def alive(ns: str, service: str, instance: str) -> str:
    return _key(ns, "alive", service, instance)


def alive_all(ns: str) -> str:
    return f"{_key(ns, 'alive')}/**"


def q_state(ns: str, line: str, segment: str) -> str:
    return _key(ns, "q", "state", line, segment)


def q_state_all(ns: str) -> str:
    return f"{_key(ns, 'q', 'state')}/**"


def q_alerts(ns: str) -> str:
    return _key(ns, "q", "alerts")


def q_plan(ns: str) -> str:
    return _key(ns, "q", "plan")


def parse_segment_key(key: str) -> tuple[str, str, str, str]:
    """Split ``{ns}/{kind}/{line}/{segment}`` into its four chunks; ValueError otherwise."""
    parts = str(key).split("/")
    if len(parts) != 4:
        raise ValueError(f"key: {key!r} is not of the form ns/kind/line/segment")
    ns, kind, line, segment = parts
    return ns, kind, line, segment
