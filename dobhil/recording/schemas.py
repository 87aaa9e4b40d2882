"""The one table of recorded topics (:data:`TOPIC_SPECS`): each topic's fields, JSON schema and
encoder; ``docs/recording.md`` lists them (a test checks it). Records are flat tuples laid out
by named types: :class:`CycleRecord`, :class:`FrameRecord`, :class:`EventRecord` and one per
other topic (``(Topic, log_time_ns, *the topic's fields)``), all starting ``kind, log_time_ns``;
:data:`VIEWS` gives the messages of each. The loop thread builds them in their type's field
order, cycles and frames packed into bytes (:mod:`dobhil.recording.packed`), the others as plain
tuples (a NamedTuple instance costs it 0.17 us more per record and pickles 5-11x slower); whoever
reads one (unpacked) names it first (:func:`named`) and reads fields by name.
"""

from __future__ import annotations

import json
from collections import namedtuple
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from functools import cached_property
from enum import IntEnum
from operator import itemgetter
from types import MappingProxyType
from typing import Any, Final, NamedTuple

import orjson

from dobhil.errors import LogFileError
from dobhil.recording.codes import ProtocolCodes

SCHEMA_ENCODING: Final = "jsonschema"
MESSAGE_ENCODING: Final = "json"
#: First element of a cycle record (topic records start with their Topic).
CYCLE: Final = 0
#: A record's kind is ``base + LANE_STRIDE * lane``: ``base`` is CYCLE or a Topic, ``lane``
#: the topic prefix its messages go under (0: none, the single-axis topics; a several-axis
#: log gives each axis and each bus a lane, :mod:`dobhil.recording.axeslog`). Topics and
#: CYCLE are below it, so ``kind & LANE_MASK`` is the base.
LANE_STRIDE: Final = 16
LANE_MASK: Final = LANE_STRIDE - 1


class Topic(IntEnum):
    """Every topic dobhil records."""

    CAN_RX = 1
    CAN_TX = 2
    DRIVE_FEEDBACK = 3
    DRIVE_COMMAND = 4
    CONTROLLER = 5
    LOOP = 6
    EMULATOR_TRUTH = 7
    EVENTS = 8


class FieldKind(IntEnum):
    NUMBER = 1
    INTEGER = 2
    BOOLEAN = 3
    STRING = 4
    BYTES = 5  # a list of integers 0..255


class EventKind(IntEnum):
    """Kinds of ``/events`` records; the JSON carries the lower-case name."""

    ENABLE = 1
    DISABLE = 2
    STOP = 3
    FAULT = 4
    WATCHDOG = 5
    LOSS = 6
    INFO = 7


_JSON_TYPE: Final[dict[FieldKind, dict[str, Any]]] = {
    FieldKind.NUMBER: {"type": ["number", "null"]}, FieldKind.INTEGER: {"type": "integer"},
    FieldKind.BOOLEAN: {"type": "boolean"}, FieldKind.STRING: {"type": "string"},
    FieldKind.BYTES: {"type": "array", "items": {"type": "integer", "minimum": 0, "maximum": 255}}}


@dataclass(frozen=True)
class Field:
    """One property of a payload: name, JSON type, meaning (with its unit), allowed values."""

    name: str
    kind: FieldKind
    description: str
    choices: tuple[str, ...] = ()

    def json_schema(self) -> dict[str, Any]:
        return {**_JSON_TYPE[self.kind], "description": self.description,
                **({"enum": list(self.choices)} if self.choices else {})}


Encoder = Callable[[Sequence[Any]], bytes]


@dataclass(frozen=True)
class TopicSpec:
    """One channel: topic, names, fields in canonical order, encoder (values -> JSON bytes;
    None: the values are the fields, in order; NaN and infinity become ``null``) and the
    record values it takes (``sources``; empty: the fields)."""

    topic: Topic
    name: str
    schema_name: str
    description: str
    fields: tuple[Field, ...]
    encoder: Encoder | None = None
    sources: tuple[str, ...] = ()

    @cached_property
    def keys(self) -> tuple[str, ...]:
        return tuple(f.name for f in self.fields)

    @cached_property
    def inputs(self) -> tuple[str, ...]:
        """The names of the values the encoder takes, in order."""
        return self.sources or self.keys

    def json_schema(self) -> dict[str, Any]:
        return {"$schema": "https://json-schema.org/draft/2020-12/schema", "title": self.schema_name,
                "description": self.description, "type": "object",
                "properties": {f.name: f.json_schema() for f in self.fields}, "required": list(self.keys)}

    def schema_bytes(self) -> bytes:
        return json.dumps(self.json_schema(), indent=1).encode()

    @cached_property
    def encode(self) -> Encoder:
        keys, dumps, numpy = self.keys, orjson.dumps, orjson.OPT_SERIALIZE_NUMPY
        return self.encoder or (lambda values: dumps(dict(zip(keys, values)), option=numpy))


def _fields(kind: FieldKind, *pairs: str) -> tuple[Field, ...]:
    """Fields of one kind from ``name, description, name, description, ...``."""
    return tuple(Field(n, kind, d) for n, d in zip(pairs[::2], pairs[1::2]))


_N, _I, _B = FieldKind.NUMBER, FieldKind.INTEGER, FieldKind.BOOLEAN


_CAN_FIELDS: Final = (
    *_fields(_N, "timestamp", "bus timestamp of the frame [s]"), *_fields(_I, "arbitration_id", "CAN identifier"),
    *_fields(_B, "is_extended_id", "29-bit identifier", "is_remote_frame", "remote transmission request",
             "is_error_frame", "error frame", "is_fd", "CAN FD frame", "bitrate_switch", "CAN FD bit rate switch",
             "error_state_indicator", "CAN FD error state indicator"),
    *_fields(_I, "dlc", "data length in bytes"), Field("data", FieldKind.BYTES, "payload bytes"),
    Field("data_hex", FieldKind.STRING, "payload as lower-case hex"),
    Field("direction", FieldKind.STRING, "direction seen by dobhil", ("rx", "tx")),
    Field("channel", FieldKind.STRING, "bus channel name ('' when unknown)"),
)


class FrameRecord(NamedTuple):
    """A CAN frame on ``/can/rx`` or ``/can/tx``: the python-can message's attributes."""

    kind: int  # Topic.CAN_RX or Topic.CAN_TX
    log_time_ns: int
    arbitration_id: int
    is_extended_id: bool
    is_remote_frame: bool
    is_error_frame: bool
    is_fd: bool
    bitrate_switch: bool
    error_state_indicator: bool
    dlc: int
    data: bytes  # bytes or a bytearray python-can handed out (not refilled)
    timestamp: float
    channel: Any


class EventRecord(NamedTuple):
    """An ``/events`` record."""

    kind: int  # Topic.EVENTS
    log_time_ns: int
    event: int  # EventKind (the payload's ``kind``)
    reason: str
    detail: str
    lost: int  # messages lost (EventKind.LOSS), else 0: the payload's ``count``


class CycleRecord(NamedTuple):
    """One control cycle, the loop thread's record: ``/drive/feedback``, ``/controller``,
    ``/drive/command``, ``/loop`` and ``/emulator/truth``. A run without an emulator ends the
    record at ``protocol_error`` (no truth fields: its length says so, see :func:`message_count`).
    ``drive_state`` is dobhil's :class:`~dobhil.drives.base.DriveState`; ``protocol_state`` and
    ``protocol_error`` are the drive's own codes (``DriveStatus.protocol_state``, ``error_code``)."""

    kind: int  # CYCLE
    log_time_ns: int
    cycle: int
    position: float
    velocity: float
    seq: int
    tau_ref: float
    tau_int_hat: float
    tau_dis_hat: float
    tau_per: float
    u_unsat: float
    u_sat: float
    period_error: float
    exec_time: float
    overrun: bool
    sample_latency: float  # the drive's sample (SYNC) -> its feedback received [s]; NaN: unknown
    drive_state: int
    protocol_state: int
    protocol_error: int
    q: float
    dq: float
    tau_motor: float
    tau_int: float


#: The python-can message attributes a CAN frame record holds, in order.
FRAME_ATTRIBUTES: Final = FrameRecord._fields[2:]


def can_frame_record(msg: Any, topic: Topic, log_time_ns: int) -> FrameRecord:
    """The record of a python-can message on ``/can/rx`` or ``/can/tx`` (the data copied)."""
    record = FrameRecord(int(topic), log_time_ns, *(getattr(msg, a) for a in FRAME_ATTRIBUTES))
    return record._replace(data=bytes(record.data or b""))


def can_frame_payload(values: Sequence[Any], topic: Topic) -> dict[str, Any]:
    """The ``/can/*`` payload of a frame record's values (after topic and log time)."""
    arb, ext, rtr, err, fd, brs, esi, dlc, data, stamp, channel = values
    data = bytes(data)
    return {"timestamp": float(stamp or 0.0), "arbitration_id": arb, "is_extended_id": bool(ext),
            "is_remote_frame": bool(rtr), "is_error_frame": bool(err), "is_fd": bool(fd), "bitrate_switch": bool(brs),
            "error_state_indicator": bool(esi), "dlc": dlc, "data": list(data), "data_hex": data.hex(),
            "direction": "rx" if topic == Topic.CAN_RX else "tx", "channel": "" if channel is None else str(channel)}


#: The ``/can/*`` fields a python-can message is made of (:func:`can_frame_message_of`), in
#: the order it takes them.
CAN_MESSAGE_FIELDS: Final = ("timestamp", "arbitration_id", "is_extended_id", "is_remote_frame", "is_error_frame",
                             "is_fd", "bitrate_switch", "error_state_indicator", "dlc", "data", "direction", "channel")
#: Their values in a message of a log written before they were recorded.
CAN_MESSAGE_DEFAULTS: Final[Mapping[str, Any]] = MappingProxyType(
    {"timestamp": None, "bitrate_switch": False, "error_state_indicator": False, "channel": None})
_can_fields = itemgetter(*CAN_MESSAGE_FIELDS)


def can_frame_message(payload: Mapping[str, Any], log_time_ns: int) -> Any:
    """The python-can message of a ``/can/*`` payload (bus timestamp, else the log time)."""
    try:
        values = _can_fields(payload)
    except KeyError:   # an older log's frame
        values = tuple(payload[k] if k in payload else CAN_MESSAGE_DEFAULTS[k] for k in CAN_MESSAGE_FIELDS)
    return can_frame_message_of(values, log_time_ns)


def can_frame_message_of(values: Sequence[Any], log_time_ns: int) -> Any:
    """The python-can message of a ``/can/*`` message's :data:`CAN_MESSAGE_FIELDS` values."""
    import can
    stamp, arb, ext, rtr, err, fd, brs, esi, dlc, data, direction, channel = values
    return can.Message(timestamp=stamp or log_time_ns / 1e9, arbitration_id=arb, is_extended_id=ext,
                       is_remote_frame=rtr, is_error_frame=err, is_fd=fd, bitrate_switch=brs,
                       error_state_indicator=esi, dlc=dlc, data=bytes(data), is_rx=direction != "tx",
                       channel=channel or None, check=False)


def _frame_encoder(topic: Topic) -> Encoder:
    return lambda values: orjson.dumps(can_frame_payload(values, topic))


Fields = Callable[[Sequence[Any]], tuple[Any, ...]]


def can_frame_fields(topic: Topic) -> Fields:
    """A frame record's values -> the ``/can/*`` fields in the table's order (what
    :func:`can_frame_payload` holds: a test checks they agree)."""
    direction = "rx" if topic == Topic.CAN_RX else "tx"

    def fields(values: Sequence[Any]) -> tuple[Any, ...]:
        arb, ext, rtr, err, fd, brs, esi, dlc, data, stamp, channel = values
        data = bytes(data)
        return (float(stamp or 0.0), arb, bool(ext), bool(rtr), bool(err), bool(fd), bool(brs), bool(esi), dlc,
                data, data.hex(), direction, "" if channel is None else str(channel))
    return fields


#: ``/drive/feedback.drive_state`` by dobhil's ``DriveState`` code (``dobhil.drives.base``; a
#: test checks they match). Names, not the codes: a drive's own state codes differ (a drive's
#: 1 may be its idle state, dobhil's 1 is enabled), and a number in Foxglove reads as the drive's.
DRIVE_STATE_NAMES: Final = ("disabled", "enabled", "fault")


def drive_state_name(code: int) -> str:
    """The recorded name of a ``DriveState`` code (``code N`` for one this table lacks)."""
    return DRIVE_STATE_NAMES[code] if 0 <= code < len(DRIVE_STATE_NAMES) else f"code {code}"


def feedback_fields(codes: ProtocolCodes) -> Fields:
    """``/drive/feedback``'s record values -> its fields in the table's order, the drive's
    codes named by ``codes`` (what :func:`feedback_encoder` holds: a test checks they agree)."""
    def fields(values: Sequence[Any]) -> tuple[Any, ...]:
        position, velocity, state, protocol_state, error, seq, cycle = values
        return (position, velocity, drive_state_name(int(state)), protocol_state,
                codes.state_name(int(protocol_state)), error, codes.error_text(int(error)), seq, cycle)
    return fields


def feedback_encoder(codes: ProtocolCodes) -> Encoder:
    """``/drive/feedback`` with the drive's codes named by ``codes`` (the run's protocol)."""
    def encode(values: Sequence[Any]) -> bytes:
        position, velocity, state, protocol_state, error, seq, cycle = values
        return orjson.dumps({"position": position, "velocity": velocity, "drive_state": drive_state_name(int(state)),
                             "protocol_state": protocol_state,
                             "protocol_state_name": codes.state_name(int(protocol_state)),
                             "protocol_error": error, "protocol_error_text": codes.error_text(int(error)),
                             "seq": seq, "cycle": cycle}, option=orjson.OPT_SERIALIZE_NUMPY)
    return encode


def feedback_state(payload: Mapping[str, Any]) -> tuple[str, int, int]:
    """(drive state name, protocol state, protocol error) of a ``/drive/feedback`` payload of
    any dobhil version: ``drive_state`` by name or (older logs) ``axis_state`` as dobhil's
    code, ``axis_error`` for ``protocol_error``, the protocol state not recorded (-1) before
    ``protocol_state`` was."""
    state = payload.get("drive_state")
    name = state if isinstance(state, str) else drive_state_name(int(payload.get("axis_state", -1)))
    error = payload.get("protocol_error", payload.get("axis_error", 0))
    return name, int(payload.get("protocol_state", -1)), int(error or 0)


def event_fields(values: Sequence[Any]) -> tuple[Any, ...]:
    """An event record's values -> the ``/events`` fields (the kind by its lower-case name)."""
    kind, reason, detail, count = values
    return EventKind(kind).name.lower(), reason, detail, count


def _event_encoder(values: Sequence[Any]) -> bytes:
    kind, reason, detail, count = values
    return orjson.dumps({"kind": EventKind(kind).name.lower(), "reason": reason, "detail": detail, "count": count})


# -- the table -------------------------------------------------------------------

_SPECS: Final = (
    TopicSpec(Topic.CAN_RX, "/can/rx", "dobhil.CanFrame", "CAN frame received", _CAN_FIELDS,
              _frame_encoder(Topic.CAN_RX)),
    TopicSpec(Topic.CAN_TX, "/can/tx", "dobhil.CanFrame", "CAN frame sent", _CAN_FIELDS,
              _frame_encoder(Topic.CAN_TX)),
    TopicSpec(Topic.DRIVE_FEEDBACK, "/drive/feedback", "dobhil.DriveFeedback", "drive feedback decoded from the bus",
              _fields(_N, "position", "motor-side position [rad]", "velocity", "motor-side velocity [rad/s]")
              + (Field("drive_state", FieldKind.STRING, "dobhil's drive state (not the drive's own state code): "
                       + ", ".join(DRIVE_STATE_NAMES)),)
              + _fields(_I, "protocol_state", "the drive's own state code as its protocol reports it "
                        "(-1: not reported)")
              + _fields(FieldKind.STRING, "protocol_state_name", "protocol_state in the protocol's words")
              + _fields(_I, "protocol_error", "the drive's own error code as its protocol reports it (0: none)")
              + _fields(FieldKind.STRING, "protocol_error_text", "protocol_error in the protocol's words")
              + _fields(_I, "seq", "motion frames received from the drive so far (Feedback.seq)",
                        "cycle", "control cycle that used this feedback (-1: controller.initialize)"),
              feedback_encoder(ProtocolCodes()),
              ("position", "velocity", "drive_state", "protocol_state", "protocol_error", "seq", "cycle")),
    TopicSpec(Topic.DRIVE_COMMAND, "/drive/command", "dobhil.DriveCommand", "torque command sent to the drive",
              _fields(_N, "torque", "commanded motor torque [N m]")),
    TopicSpec(Topic.CONTROLLER, "/controller", "dobhil.Controller", "controller internals of one cycle",
              _fields(_N, "tau_ref", "torque reference [N m]",
                      "tau_int_hat", "estimated interaction torque (RTOb) [N m]",
                      "tau_dis_hat", "estimated disturbance torque (DOb) [N m]", "tau_per", "performance torque [N m]",
                      "u_unsat", "control output before saturation [N m]",
                      "u_sat", "control output after saturation [N m]") + _fields(_I, "cycle", "control cycle index")),
    TopicSpec(Topic.LOOP, "/loop", "dobhil.Loop", "timing of one control cycle",
              _fields(_I, "cycle", "control cycle index")
              + _fields(_N, "period_error", "actual minus nominal period [s]",
                        "exec_time", "time spent computing the cycle [s]")
              + _fields(_B, "overrun", "the cycle missed its deadline")
              + _fields(_N, "sample_latency", "the drive's sample instant (its SYNC) to its feedback received, "
                        "bus stamps [s]; null when unknown (a protocol that does not tell it, lockstep; absent "
                        "in logs before it)")),
    TopicSpec(Topic.EMULATOR_TRUTH, "/emulator/truth", "dobhil.EmulatorTruth", "ground truth of the plant emulator",
              _fields(_N, "q", "position [rad]", "dq", "velocity [rad/s]", "tau_motor", "motor torque applied [N m]",
                      "tau_int", "interaction torque applied [N m]")),
    TopicSpec(Topic.EVENTS, "/events", "dobhil.Event", "state changes, faults and recorder notes",
              (Field("kind", FieldKind.STRING, "event kind", tuple(k.name.lower() for k in EventKind)),
               *_fields(FieldKind.STRING, "reason", "one-line reason", "detail", "free-form detail"),
               *_fields(_I, "count", "records lost (kind=loss), else 0")), _event_encoder),
)

#: Topic -> spec: the one table of channels.
TOPIC_SPECS: Final[Mapping[Topic, TopicSpec]] = MappingProxyType({s.topic: s for s in _SPECS})
#: Schema name ("dobhil.CanFrame") -> spec (the two frame topics share theirs).
SPECS_BY_SCHEMA: Final[Mapping[str, TopicSpec]] = MappingProxyType({s.schema_name: s for s in _SPECS})
#: Topic name ("/can/rx") -> spec.
SPECS_BY_NAME: Final[Mapping[str, TopicSpec]] = MappingProxyType({s.name: s for s in _SPECS})


def spec_for(topic: str | int) -> TopicSpec:
    """The spec of a topic given by name or number; LogFileError if unknown."""
    spec = SPECS_BY_NAME.get(topic) if isinstance(topic, str) else TOPIC_SPECS.get(Topic(topic))
    if spec is None:
        raise LogFileError(f"unknown topic {topic!r}; expected one of {', '.join(SPECS_BY_NAME)}")
    return spec


#: Values of a cycle record after (CYCLE, log_time_ns); the truth values are optional.
CYCLE_FIELDS: Final = CycleRecord._fields[2:]
#: /drive/command.torque is the saturated output
_ALIASES: Final = {"torque": "u_sat"}
View = tuple[Topic, Encoder, int]


def _view(spec: TopicSpec, in_cycle: bool, encode: Encoder) -> View:
    """(topic, record -> JSON, shortest record holding its values) of a message in a cycle
    record or in a record of its own."""
    if not in_cycle:
        return spec.topic, lambda r: encode(r[2:]), 0
    idx = [2 + CYCLE_FIELDS.index(_ALIASES.get(k, k)) for k in spec.inputs]
    if len(idx) == 1:
        return spec.topic, lambda r, i=idx[0]: encode((r[i],)), idx[0] + 1
    get = itemgetter(*idx)
    return spec.topic, lambda r: encode(get(r)), max(idx) + 1


def field_values(spec: TopicSpec, codes: ProtocolCodes | None = None) -> Fields | None:
    """A topic's record values -> its fields in the table's order (None: the values are the
    fields); the drive's codes on ``/drive/feedback`` named by ``codes`` (None: numbers)."""
    if spec.topic in (Topic.CAN_RX, Topic.CAN_TX):
        return can_frame_fields(spec.topic)
    if spec.topic == Topic.DRIVE_FEEDBACK:
        return feedback_fields(codes or ProtocolCodes())
    return event_fields if spec.topic == Topic.EVENTS else None


def views(codes: ProtocolCodes | None = None, encoding: Any = None) -> Mapping[int, tuple[View, ...]]:
    """Record kind (CYCLE or a Topic) -> the views of each message the record becomes, in
    ``encoding`` (a :class:`~dobhil.recording.encodings.Encoding`; None: JSON), the drive's
    codes on ``/drive/feedback`` named by ``codes`` (None: as numbers)."""
    if encoding is not None:
        encoders = {t: encoding.encoder(s, codes) for t, s in TOPIC_SPECS.items()}
    else:   # the table's own JSON encoders (what encodings.json_messages hands out)
        encoders = {t: s.encode for t, s in TOPIC_SPECS.items()}
        if codes is not None:
            encoders[Topic.DRIVE_FEEDBACK] = feedback_encoder(codes)
    in_cycle = (Topic.DRIVE_FEEDBACK, Topic.CONTROLLER, Topic.DRIVE_COMMAND, Topic.LOOP, Topic.EMULATOR_TRUTH)
    return MappingProxyType({CYCLE: tuple(_view(TOPIC_SPECS[t], True, encoders[t]) for t in in_cycle),
                             **{int(t): (_view(s, False, encoders[t]),) for t, s in TOPIC_SPECS.items()}})


#: :func:`views` without protocol names (what a record becomes and its shortest length).
VIEWS: Final = views()


def _topic_record(spec: TopicSpec) -> type[tuple[Any, ...]]:
    """The record type of a topic's own record: ``kind, log_time_ns`` and its fields."""
    name = spec.schema_name.rpartition(".")[2] + "Record"
    return namedtuple(name, ("kind", "log_time_ns", *spec.inputs), module=__name__)


#: Record kind (CYCLE or a Topic) -> its named type.
RECORD_TYPES: Final[Mapping[int, Any]] = MappingProxyType({
    CYCLE: CycleRecord, int(Topic.CAN_RX): FrameRecord, int(Topic.CAN_TX): FrameRecord,
    int(Topic.EVENTS): EventRecord,
    **{int(t): _topic_record(s) for t, s in TOPIC_SPECS.items()
       if t not in (Topic.CAN_RX, Topic.CAN_TX, Topic.EVENTS)}})
_new = tuple.__new__


def named(record: Sequence[Any]) -> Any:
    """``record`` as its named type (a copy; no check of its values): its fields by name
    (``kind`` keeps its lane)."""
    return _new(RECORD_TYPES[record[0] & LANE_MASK], record)


def message_count(record: Sequence[Any]) -> int:
    """How many messages a record becomes (loss accounting)."""
    return sum(len(record) >= needs for _, _, needs in VIEWS[record[0] & LANE_MASK])


def lane_kind(base: int, lane: int) -> int:
    """The record kind of ``base`` (CYCLE or a Topic) in ``lane``."""
    return int(base) + LANE_STRIDE * lane


def event_record(kind: EventKind, log_time_ns: int, reason: str, detail: str = "", count: int = 0) -> EventRecord:
    return EventRecord(int(Topic.EVENTS), log_time_ns, int(kind), reason, detail, count)


def decode(data: bytes) -> dict[str, Any]:
    """The payload dict of a recorded JSON message."""
    return orjson.loads(data)


__all__ = ["CAN_MESSAGE_DEFAULTS", "CAN_MESSAGE_FIELDS",
           "CYCLE", "CYCLE_FIELDS", "DRIVE_STATE_NAMES", "FRAME_ATTRIBUTES", "LANE_MASK", "LANE_STRIDE",
           "MESSAGE_ENCODING", "RECORD_TYPES",
           "SCHEMA_ENCODING", "SPECS_BY_NAME", "SPECS_BY_SCHEMA", "TOPIC_SPECS", "VIEWS", "CycleRecord", "EventKind",
           "EventRecord",
           "Field", "FieldKind", "FrameRecord", "Topic", "TopicSpec", "can_frame_message",
           "can_frame_message_of", "can_frame_payload",
           "can_frame_fields", "can_frame_record", "decode", "event_fields", "feedback_encoder", "feedback_fields",
           "field_values", "drive_state_name", "event_record", "feedback_state", "lane_kind",
           "message_count", "named",
           "spec_for", "views"]
