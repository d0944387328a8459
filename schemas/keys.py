"""Key expressions: each key's form is written once here, as a :class:`KeyForm`; its builder,
its wildcard and its parser all come from that one definition, and nothing else in the
system spells a key out or takes one apart.

A key is ``{ns}/{fixed chunks}/{id chunks}``, e.g. ``tf/raw/{train}/{unit}``. A form is
called to build a key (``raw(ns, train, unit)``) and checks its id chunks, so a key never
carries `/ * $ ? #` by accident. Wildcards (``*_all``, ``*_keys`` with a selector) are for
subscribers and queryables. Each ``parse_*`` reverses its builder and raises
:class:`~schemas.wire.SchemaError` (a ``ValueError``) for a key of another form;
:func:`check_key` says whether a message's ids are its key's.
"""

from __future__ import annotations

from dataclasses import dataclass

from schemas import messages
from schemas.wire import SchemaError, check_id

DEFAULT_NS = "tf"
SegmentId = tuple[str, str]  # (line, segment): a segment's ids, as its keys carry them
SEGMENT = ("line", "segment")  # the id chunks of a per-segment key


def _key(ns: str, *chunks: str) -> str:
    check_id("ns", ns)
    for chunk in chunks:
        check_id("key chunk", chunk)
    return "/".join((ns, *chunks))


@dataclass(frozen=True)
class KeyForm:
    """The keys ``{ns}/{head...}/{ids...}``: fixed chunks, then one chunk per id name."""

    head: tuple[str, ...]
    ids: tuple[str, ...] = ()

    def __call__(self, ns: str, *ids: str) -> str:
        """The key of these ids."""
        if len(ids) != len(self.ids):
            raise TypeError(f"{self}: takes {len(self.ids)} id(s), got {len(ids)}")
        return _key(ns, *self.head, *ids)

    def keys(self, ns: str, selector: str = "**") -> str:
        """The wildcard of this form's keys, narrowed by ``selector`` (e.g. ``"L1/**"``)."""
        return f"{_key(ns, *self.head)}/{selector}"

    def parse(self, key: str) -> tuple[str, ...]:
        """The id chunks of ``key``; SchemaError when it is not of this form."""
        parts = str(key).split("/")
        n = 1 + len(self.head)
        if len(parts) != n + len(self.ids) or tuple(parts[1:n]) != self.head or not all(parts):
            raise SchemaError(f"key: {key!r} is not of the form {self}")
        return tuple(parts[n:])

    def parse_id(self, key: str) -> str:
        """The one id chunk of ``key`` (a form with a single id)."""
        (one,) = self.parse(key)
        return one

    def __str__(self) -> str:
        return "/".join(("{ns}", *self.head, *(f"{{{name}}}" for name in self.ids)))


raw = KeyForm(("raw",), ("train", "unit"))
gps = KeyForm(("gps",), ("train",))
accel = KeyForm(("accel",), ("train", "unit"))
index = KeyForm(("index",), SEGMENT)
trc = KeyForm(("trc",), SEGMENT)
maintenance = KeyForm(("maintenance",), SEGMENT)
state = KeyForm(("state",), SEGMENT)
alert = KeyForm(("alert",), SEGMENT)
calibration = KeyForm(("model", "calibration"))
unit_calibration = KeyForm(("model", "calibration"), ("train", "unit"))  # a unit's own model
degradation = KeyForm(("model", "degradation"), ("group",))
deadletter = KeyForm(("deadletter",), ("service",))
alive = KeyForm(("alive",), ("service", "instance"))
q_state = KeyForm(("q", "state"), SEGMENT)
q_alerts = KeyForm(("q", "alerts"))
q_plan = KeyForm(("q", "plan"))
maintenance_plan = KeyForm(("plan", "maintenance"))  # the planner's MaintenancePlan
# The planner's queryable: the MaintenancePlan (``?weeks=N;budget=X`` plans anew).
q_maintenance_plan = KeyForm(("q", "plan", "maintenance"))
stack_health = KeyForm(("health", "stack"))  # `trackfusion up`'s StackHealth, once a second
viewer_select = KeyForm(("viewer", "select"))  # the segment a viewer pins into its plots

SEGMENT_KEYS = {form.head[0]: form for form in (index, trc, maintenance, state, alert)}
SEGMENT_KINDS = tuple(SEGMENT_KEYS)  # {ns}/{kind}/{line}/{segment}

parse_raw = raw.parse
parse_gps = gps.parse_id
parse_accel = accel.parse
parse_degradation = degradation.parse_id
parse_deadletter = deadletter.parse_id
parse_alive = alive.parse
parse_q_state = q_state.parse


# --- wildcards -------------------------------------------------------------------------------


def raw_all(ns: str) -> str:
    return raw.keys(ns)


def raw_of_train(ns: str, train: str) -> str:
    """The raw keys of every unit of one train."""
    check_id("train", train)
    return raw.keys(ns, f"{train}/**")


def gps_all(ns: str) -> str:
    return gps.keys(ns, "*")


def accel_all(ns: str) -> str:
    return accel.keys(ns)


def segment_keys(ns: str, kind: str, selector: str = "**") -> str:
    """Subscriber key for a per-segment kind (index, trc, maintenance, state, alert).

    ``selector`` narrows to part of the network, e.g. ``"L1/**"`` for one line.
    """
    if kind not in SEGMENT_KEYS:
        raise ValueError(f"kind: {kind!r} is not a per-segment key kind")
    return SEGMENT_KEYS[kind].keys(ns, selector)


def model_all(ns: str) -> str:
    return f"{_key(ns, 'model')}/**"


def deadletter_all(ns: str) -> str:
    return deadletter.keys(ns)


def alive_all(ns: str) -> str:
    return alive.keys(ns)


def q_state_keys(ns: str, selector: str = "**") -> str:
    """Queryable key of the states of part of the network (``selector`` as in
    :func:`segment_keys`, e.g. ``"L1/**"``)."""
    return q_state.keys(ns, selector)


def q_state_all(ns: str) -> str:
    return q_state.keys(ns)


# --- taking keys apart --------------------------------------------------------------------


def kind(key: str) -> str:
    """The kind chunk (the second) of a key or key expression: ``raw``, ``index``, ``model``,
    ``q`` …"""
    parts = str(key).split("/")
    if len(parts) < 2 or not parts[1]:
        raise SchemaError(f"key: {key!r} has no kind chunk ({{ns}}/{{kind}}/...)")
    return parts[1]


def parse_segment_key(key: str) -> tuple[str, str, str, str]:
    """``(ns, kind, line, segment)`` of ``{ns}/{kind}/{line}/{segment}``, ``kind`` one of
    :data:`SEGMENT_KINDS`."""
    parts = str(key).split("/")
    if len(parts) != 4 or parts[1] not in SEGMENT_KEYS or not all(parts):
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


# --- a message and its key -----------------------------------------------------------------

# Each message type's key; its id chunks are the message's fields of the same names.
_MESSAGE_KEYS: dict[type[messages.Message], KeyForm] = {
    messages.RawChunk: raw,
    messages.GpsFix: gps,
    messages.PositionedChunk: accel,
    messages.OnboardIndex: index,
    messages.TrcRecord: trc,
    messages.MaintenanceEvent: maintenance,
    messages.Calibration: calibration,
    messages.DegradationPosterior: degradation,
    messages.SegmentState: state,
    messages.Alert: alert,
    messages.DeadLetter: deadletter,
    messages.StackHealth: stack_health,
    messages.ViewerSelect: viewer_select,
    messages.RaisedAlerts: q_alerts,  # replies of the alerting queryables
    messages.InspectionPlan: q_plan,
    messages.MaintenancePlan: maintenance_plan,
}
_ALSO = {  # also the reply of a queryable
    messages.SegmentState: (q_state,),
    messages.MaintenancePlan: (q_maintenance_plan,),
}


def _form_of(message: messages.Message) -> KeyForm:
    if isinstance(message, messages.Calibration) and message.train:
        return unit_calibration
    return _MESSAGE_KEYS[type(message)]


def key_of(ns: str, message: messages.Message) -> str:
    """The key ``message`` is published on: its kind and its own ids."""
    form = _form_of(message)
    return form(ns, *(getattr(message, name) for name in form.ids))


def check_key(key: str, message: messages.Message) -> None:
    """Refuse a message whose key is not its kind's or carries other ids than the message.

    The namespace chunk is not compared (the subscription chose it). A SegmentState may
    also come on ``{ns}/q/state/{line}/{segment}``. Raises SchemaError with the reason, e.g.
    ``OnboardIndex: key says L1/s2, message says L1/s1``, so an adapter makes a dead letter.
    """
    message_type = type(message)
    name = message_type.__name__
    form = _form_of(message)
    parts = str(key).split("/")
    for candidate in (form, *_ALSO.get(message_type, ())):
        head = candidate.head
        if tuple(parts[1 : 1 + len(head)]) == head:
            got = parts[1 + len(head) :]
            if len(got) == len(candidate.ids):
                want = [str(getattr(message, field)) for field in candidate.ids]
                if got != want:
                    raise SchemaError(
                        f"{name}: key says {'/'.join(got)}, message says {'/'.join(want)}"
                    )
                return
    raise SchemaError(f"{name}: key {key} is not of the form {form}")
