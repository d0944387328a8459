"""Key expressions of DESIGN's key table: the only place they are spelled out or taken apart.

Every builder checks its id chunks, so a key never carries `/ * $ ? #` by accident.
Wildcard variants (``*_all``, ``*_keys`` with a selector) are for subscribers and queryables.
Each ``parse_*`` reverses its builder and raises :class:`~schemas.wire.SchemaError` (a
``ValueError``) for a key of another form; :func:`check_key` says whether a message's ids are
its key's.
"""

from __future__ import annotations

from schemas.messages import (
    Alert,
    Calibration,
    DeadLetter,
    DegradationPosterior,
    GpsFix,
    InspectionPlan,
    MaintenanceEvent,
    MaintenancePlan,
    Message,
    OnboardIndex,
    PositionedChunk,
    RaisedAlerts,
    RawChunk,
    SegmentState,
    StackHealth,
    TrcRecord,
    ViewerSelect,
)
from schemas.wire import SchemaError, check_id

DEFAULT_NS = "tf"
SegmentId = tuple[str, str]  # (line, segment): a segment's ids, as its keys carry them


def _key(ns: str, *chunks: str) -> str:
    check_id("ns", ns)
    for chunk in chunks:
        check_id("key chunk", chunk)
    return "/".join((ns, *chunks))


def raw(ns: str, train: str, unit: str) -> str:
    return _key(ns, "raw", train, unit)


def raw_all(ns: str) -> str:
    return f"{_key(ns, 'raw')}/**"


def raw_of_train(ns: str, train: str) -> str:
    """The raw keys of every unit of one train."""
    return f"{_key(ns, 'raw', train)}/**"


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


SEGMENT_KINDS = ("index", "trc", "maintenance", "state", "alert")  # {ns}/{kind}/{line}/{segment}


def segment_keys(ns: str, kind: str, selector: str = "**") -> str:
    """Subscriber key for a per-segment kind (index, trc, maintenance, state, alert).

    ``selector`` narrows to part of the network, e.g. ``"L1/**"`` for one line.
    """
    if kind not in SEGMENT_KINDS:
        raise ValueError(f"kind: {kind!r} is not a per-segment key kind")
    return f"{_key(ns, kind)}/{selector}"


def calibration(ns: str) -> str:
    return _key(ns, "model", "calibration")


def unit_calibration(ns: str, train: str, unit: str) -> str:
    """The calibration of one on-board unit (a Calibration with ``train``, ``unit``)."""
    return _key(ns, "model", "calibration", train, unit)


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


def q_state_keys(ns: str, selector: str = "**") -> str:
    """Queryable key of the states of part of the network (``selector`` as in
    :func:`segment_keys`, e.g. ``"L1/**"``)."""
    return f"{_key(ns, 'q', 'state')}/{selector}"


def q_state_all(ns: str) -> str:
    return q_state_keys(ns)


def q_alerts(ns: str) -> str:
    return _key(ns, "q", "alerts")


def q_plan(ns: str) -> str:
    return _key(ns, "q", "plan")


def maintenance_plan(ns: str) -> str:
    """The planner's MaintenancePlan, published after every re-plan."""
    return _key(ns, "plan", "maintenance")


def q_maintenance_plan(ns: str) -> str:
    """The planner's queryable: the MaintenancePlan (``?weeks=N;budget=X`` plans anew)."""
    return _key(ns, "q", "plan", "maintenance")


def stack_health(ns: str) -> str:
    """``trackfusion up``'s StackHealth report, once a second."""
    return _key(ns, "health", "stack")


def viewer_select(ns: str) -> str:
    """ViewerSelect: the segment a running viewer pins into its "selected" plots."""
    return _key(ns, "viewer", "select")


# --- taking keys apart --------------------------------------------------------------------


def kind(key: str) -> str:
    """The kind chunk (the second) of a key or key expression: ``raw``, ``index``, ``model``,
    ``q`` …"""
    parts = str(key).split("/")
    if len(parts) < 2 or not parts[1]:
        raise SchemaError(f"key: {key!r} has no kind chunk ({{ns}}/{{kind}}/...)")
    return parts[1]


def _ids(key: str, head: tuple[str, ...], names: tuple[str, ...]) -> list[str]:
    """The id chunks of ``{ns}/{head...}/{names...}``; SchemaError for another form."""
    parts = str(key).split("/")
    if (
        len(parts) != 1 + len(head) + len(names)
        or tuple(parts[1 : 1 + len(head)]) != head
        or not all(parts)
    ):
        form = "/".join(("{ns}", *head, *(f"{{{n}}}" for n in names)))
        raise SchemaError(f"key: {key!r} is not of the form {form}")
    return parts[1 + len(head) :]


def parse_raw(key: str) -> tuple[str, str]:
    """``(train, unit)`` of ``{ns}/raw/{train}/{unit}``."""
    train, unit = _ids(key, ("raw",), ("train", "unit"))
    return train, unit


def parse_gps(key: str) -> str:
    """``train`` of ``{ns}/gps/{train}``."""
    return _ids(key, ("gps",), ("train",))[0]


def parse_accel(key: str) -> tuple[str, str]:
    """``(train, unit)`` of ``{ns}/accel/{train}/{unit}``."""
    train, unit = _ids(key, ("accel",), ("train", "unit"))
    return train, unit


def parse_segment_key(key: str) -> tuple[str, str, str, str]:
    """``(ns, kind, line, segment)`` of ``{ns}/{kind}/{line}/{segment}``, ``kind`` one of
    :data:`SEGMENT_KINDS`."""
    parts = str(key).split("/")
    if len(parts) != 4 or parts[1] not in SEGMENT_KINDS or not all(parts):
        raise SchemaError(
            f"key: {key!r} is not of the form {{ns}}/{{kind}}/{{line}}/{{segment}} "
            f"with kind one of {', '.join(SEGMENT_KINDS)}"
        )
    ns, kind_, line, segment = parts
    return ns, kind_, line, segment


def model_kind(key: str) -> str:
    """The model chunk of ``{ns}/model/{model}/...``: ``calibration``, ``degradation`` or one
    this version does not know."""
    parts = str(key).split("/")
    if len(parts) < 3 or parts[1] != "model" or not parts[2]:
        raise SchemaError(f"key: {key!r} is not of the form {{ns}}/model/{{model}}/...")
    return parts[2]


def parse_degradation(key: str) -> str:
    """``group`` of ``{ns}/model/degradation/{group}``."""
    return _ids(key, ("model", "degradation"), ("group",))[0]


def parse_deadletter(key: str) -> str:
    """``service`` of ``{ns}/deadletter/{service}``."""
    return _ids(key, ("deadletter",), ("service",))[0]


def parse_alive(key: str) -> tuple[str, str]:
    """``(service, instance)`` of ``{ns}/alive/{service}/{instance}``."""
    service, instance = _ids(key, ("alive",), ("service", "instance"))
    return service, instance


def parse_q_state(key: str) -> SegmentId:
    """``(line, segment)`` of ``{ns}/q/state/{line}/{segment}``."""
    line, segment = _ids(key, ("q", "state"), ("line", "segment"))
    return line, segment


# --- a message and its key -----------------------------------------------------------------

# Each message type: the fixed chunks of its key after {ns}, and the fields its ids come from.
_MESSAGE_KEYS: dict[type[Message], tuple[tuple[str, ...], tuple[str, ...]]] = {
    RawChunk: (("raw",), ("train", "unit")),
    GpsFix: (("gps",), ("train",)),
    PositionedChunk: (("accel",), ("train", "unit")),
    OnboardIndex: (("index",), ("line", "segment")),
    TrcRecord: (("trc",), ("line", "segment")),
    MaintenanceEvent: (("maintenance",), ("line", "segment")),
    Calibration: (("model", "calibration"), ()),
    DegradationPosterior: (("model", "degradation"), ("group",)),
    SegmentState: (("state",), ("line", "segment")),
    Alert: (("alert",), ("line", "segment")),
    DeadLetter: (("deadletter",), ("service",)),
    StackHealth: (("health", "stack"), ()),
    ViewerSelect: (("viewer", "select"), ()),
    RaisedAlerts: (("q", "alerts"), ()),  # replies of the alerting queryables
    InspectionPlan: (("q", "plan"), ()),
    MaintenancePlan: (("plan", "maintenance"), ()),
}
_ALSO = {  # also the reply of a queryable
    SegmentState: (("q", "state"),),
    MaintenancePlan: (("q", "plan", "maintenance"),),
}


def _key_form(message: Message) -> tuple[tuple[str, ...], tuple[str, ...]]:
    head, fields = _MESSAGE_KEYS[type(message)]
    if isinstance(message, Calibration) and message.train:  # a unit's own model
        fields = ("train", "unit")
    return head, fields


def key_of(ns: str, message: Message) -> str:
    """The key ``message`` is published on: its kind and its own ids."""
    head, fields = _key_form(message)
    return _key(ns, *head, *(getattr(message, f) for f in fields))


def check_key(key: str, message: Message) -> None:
    """Refuse a message whose key is not its kind's or carries other ids than the message.

    The namespace chunk is not compared (the subscription chose it). A SegmentState may
    also come on ``{ns}/q/state/{line}/{segment}``. Raises SchemaError with the reason, e.g.
    ``OnboardIndex: key says L1/s2, message says L1/s1``, so an adapter makes a dead letter.
    """
    message_type = type(message)
    name = message_type.__name__
    head, fields = _key_form(message)
    parts = str(key).split("/")
    for kind_chunks in (head, *_ALSO.get(message_type, ())):
        if tuple(parts[1 : 1 + len(kind_chunks)]) == kind_chunks:
            got = parts[1 + len(kind_chunks) :]
            if len(got) == len(fields):
                want = [str(getattr(message, f)) for f in fields]
                if got != want:
                    raise SchemaError(
                        f"{name}: key says {'/'.join(got)}, message says {'/'.join(want)}"
                    )
                return
    form = "/".join(("{ns}", *head, *(f"{{{f}}}" for f in fields)))
    raise SchemaError(f"{name}: key {key} is not of the form {form}")
