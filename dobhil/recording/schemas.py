"""The recorded channels: one table of topics, their JSON schemas and a cheap encoder.

Every channel uses message encoding ``json`` with schema encoding ``jsonschema``,
so Foxglove opens a recording without plugins. The table :data:`TOPIC_SPECS` is
the single source of truth; ``docs/recording.md`` describes the same table.

Encoding is on the hot path of the control loop, so :func:`encode` is one call to
a prebuilt compact :class:`json.JSONEncoder`; only payloads it rejects (NaN or
infinity, numpy integers) take a slower path that writes non-finite numbers as
``null`` and numpy scalars as plain numbers.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from enum import IntEnum
from types import MappingProxyType
from typing import Any, Final

from dobhil.errors import LogFileError

#: Schema encoding and message encoding of every dobhil channel.
SCHEMA_ENCODING: Final = "jsonschema"
MESSAGE_ENCODING: Final = "json"


class Topic(IntEnum):
    """Every topic dobhil records; :data:`TOPIC_SPECS` maps each to its schema."""

    CAN_RX = 1
    CAN_TX = 2
    DRIVE_FEEDBACK = 3
    DRIVE_COMMAND = 4
    CONTROLLER = 5
    LOOP = 6
    EMULATOR_TRUTH = 7
    EVENTS = 8


class FieldKind(IntEnum):
    """JSON type of one payload field."""

    NUMBER = 1
    INTEGER = 2
    BOOLEAN = 3
    STRING = 4
    BYTES = 5  # a list of integers 0..255


class Direction(IntEnum):
    """Direction of a CAN frame as seen by dobhil."""

    RX = 1
    TX = 2


class EventKind(IntEnum):
    """Kinds of ``/events`` records; the JSON carries the lower-case name."""

    ENABLE = 1
    DISABLE = 2
    STOP = 3
    FAULT = 4
    WATCHDOG = 5
    LOSS = 6
    INFO = 7


_KIND_JSON: Final[Mapping[FieldKind, Mapping[str, Any]]] = MappingProxyType(
    {
        FieldKind.NUMBER: {"type": "number"},
        FieldKind.INTEGER: {"type": "integer"},
        FieldKind.BOOLEAN: {"type": "boolean"},
        FieldKind.STRING: {"type": "string"},
        FieldKind.BYTES: {"type": "array", "items": {"type": "integer", "minimum": 0, "maximum": 255}},
    }
)


@dataclass(frozen=True)
class Field:
    """One property of a payload: name, JSON type, unit and meaning."""

    name: str
    kind: FieldKind
    description: str
    unit: str = ""
    choices: tuple[str, ...] = ()

    def json_schema(self) -> dict[str, Any]:
        """The JSON-schema property of this field."""
        prop: dict[str, Any] = {**_KIND_JSON[self.kind]}
        unit = f" [{self.unit}]" if self.unit else ""
        prop["description"] = f"{self.description}{unit}"
        if self.choices:
            prop["enum"] = list(self.choices)
        return prop


@dataclass(frozen=True)
class TopicSpec:
    """One channel: topic name, schema name, fields in their canonical order."""

    topic: Topic
    name: str
    schema_name: str
    description: str
    fields: tuple[Field, ...]

    @property
    def keys(self) -> tuple[str, ...]:
        """Field names in canonical order (the CSV column order)."""
        return tuple(f.name for f in self.fields)

    def json_schema(self) -> dict[str, Any]:
        """The channel's JSON schema: ``title``, ``type: object``, ``properties``."""
        return {
            "$schema": "https://json-schema.org/draft/2020-12/schema",
            "title": self.schema_name,
            "description": self.description,
            "type": "object",
            "properties": {f.name: f.json_schema() for f in self.fields},
            "required": list(self.keys),
        }

    def schema_bytes(self) -> bytes:
        """The JSON schema as stored in the MCAP schema record."""
        return json.dumps(self.json_schema(), indent=1).encode()

    def from_values(self, values: Sequence[Any]) -> dict[str, Any]:
        """A payload dict from values given in canonical field order."""
        if len(values) != len(self.fields):
            raise LogFileError(
                f"{self.name}: expected {len(self.fields)} values {self.keys}, got {len(values)}"
            )
        return dict(zip(self.keys, values))


def _num(name: str, unit: str, description: str) -> Field:
    return Field(name, FieldKind.NUMBER, description, unit)


def _int(name: str, description: str) -> Field:
    return Field(name, FieldKind.INTEGER, description)


def _bool(name: str, description: str) -> Field:
    return Field(name, FieldKind.BOOLEAN, description)


def _str(name: str, description: str, choices: tuple[str, ...] = ()) -> Field:
    return Field(name, FieldKind.STRING, description, choices=choices)


_CAN_FIELDS: Final = (
    _num("timestamp", "s", "bus timestamp of the frame"),
    _int("arbitration_id", "CAN identifier"),
    _bool("is_extended_id", "29-bit identifier"),
    _bool("is_remote_frame", "remote transmission request"),
    _bool("is_error_frame", "error frame"),
    _bool("is_fd", "CAN FD frame"),
    _bool("bitrate_switch", "CAN FD bit rate switch"),
    _bool("error_state_indicator", "CAN FD error state indicator"),
    _int("dlc", "data length in bytes"),
    Field("data", FieldKind.BYTES, "payload bytes"),
    _str("data_hex", "payload as lower-case hex"),
    _str("direction", "direction seen by dobhil", ("rx", "tx")),
    _str("channel", "bus channel name ('' when unknown)"),
)

_SPECS: Final = (
    TopicSpec(Topic.CAN_RX, "/can/rx", "dobhil.CanFrame", "CAN frame received", _CAN_FIELDS),
    TopicSpec(Topic.CAN_TX, "/can/tx", "dobhil.CanFrame", "CAN frame sent", _CAN_FIELDS),
    TopicSpec(
        Topic.DRIVE_FEEDBACK,
        "/drive/feedback",
        "dobhil.DriveFeedback",
        "drive feedback decoded from the bus",
        (
            _num("position", "rad", "motor-side position"),
            _num("velocity", "rad/s", "motor-side velocity"),
            _int("axis_state", "drive state code"),
            _int("axis_error", "drive error code (0: none)"),
            _int("seq", "motion frames received from the drive so far (Feedback.seq)"),
            _int("cycle", "control cycle that used this feedback (-1: controller.initialize)"),
        ),
    ),
    TopicSpec(
        Topic.DRIVE_COMMAND,
        "/drive/command",
        "dobhil.DriveCommand",
        "torque command sent to the drive",
        (_num("torque", "N m", "commanded motor torque"),),
    ),
    TopicSpec(
        Topic.CONTROLLER,
        "/controller",
        "dobhil.Controller",
        "controller internals of one cycle",
        (
            _num("tau_ref", "N m", "torque reference"),
            _num("tau_int_hat", "N m", "estimated interaction torque (RTOb)"),
            _num("tau_dis_hat", "N m", "estimated disturbance torque (DOb)"),
            _num("tau_per", "N m", "performance torque"),
            _num("u_unsat", "N m", "control output before saturation"),
            _num("u_sat", "N m", "control output after saturation"),
            _int("cycle", "control cycle index"),
        ),
    ),
    TopicSpec(
        Topic.LOOP,
        "/loop",
        "dobhil.Loop",
        "timing of one control cycle",
        (
            _int("cycle", "control cycle index"),
            _num("period_error", "s", "actual minus nominal period"),
            _num("exec_time", "s", "time spent computing the cycle"),
            _bool("overrun", "the cycle missed its deadline"),
        ),
    ),
    TopicSpec(
        Topic.EMULATOR_TRUTH,
        "/emulator/truth",
        "dobhil.EmulatorTruth",
        "ground truth of the plant emulator",
        (
            _num("q", "rad", "position"),
            _num("dq", "rad/s", "velocity"),
            _num("tau_motor", "N m", "motor torque applied"),
            _num("tau_int", "N m", "interaction torque applied"),
        ),
    ),
    TopicSpec(
        Topic.EVENTS,
        "/events",
        "dobhil.Event",
        "state changes, faults and recorder notes",
        (
            _str("kind", "event kind", tuple(k.name.lower() for k in EventKind)),
            _str("reason", "one-line reason"),
            _str("detail", "free-form detail"),
            _int("count", "records lost (kind=loss), else 0"),
        ),
    ),
)

#: Topic -> spec, the one table of channels.
TOPIC_SPECS: Final[Mapping[Topic, TopicSpec]] = MappingProxyType({s.topic: s for s in _SPECS})
#: Topic name ("/can/rx") -> spec.
SPECS_BY_NAME: Final[Mapping[str, TopicSpec]] = MappingProxyType({s.name: s for s in _SPECS})


def spec_for(topic: str | Topic) -> TopicSpec:
    """The spec of a topic given by name or enum; LogFileError if unknown."""
    spec = TOPIC_SPECS.get(topic) if isinstance(topic, Topic) else SPECS_BY_NAME.get(topic)
    if spec is None:
        raise LogFileError(f"unknown topic {topic!r}; expected one of {', '.join(SPECS_BY_NAME)}")
    return spec


def _plain(value: Any) -> Any:
    """``default`` hook of the encoder: numpy scalars and arrays to Python values."""
    for attr in ("tolist", "item"):
        method = getattr(value, attr, None)
        if method is not None:
            return method()
    if isinstance(value, (bytes, bytearray, memoryview)):
        return list(value)
    raise TypeError(f"cannot record {type(value).__name__} as JSON")


def _finite(value: Any) -> Any:
    """Non-finite floats (also inside lists) replaced by None."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, (list, tuple)):
        return [_finite(v) for v in value]
    return value


_STRICT = json.JSONEncoder(separators=(",", ":"), check_circular=False, allow_nan=False, default=_plain)


def encode(payload: Mapping[str, Any]) -> bytes:
    """Compact JSON of a payload; NaN and infinity become ``null``."""
    try:
        return _STRICT.encode(payload).encode()
    except ValueError:
        plain = json.loads(json.dumps(payload, default=_plain))
        return _STRICT.encode({k: _finite(v) for k, v in plain.items()}).encode()


def decode(data: bytes) -> dict[str, Any]:
    """The payload dict of a recorded JSON message."""
    return json.loads(data)


__all__ = [
    "MESSAGE_ENCODING",
    "SCHEMA_ENCODING",
    "SPECS_BY_NAME",
    "TOPIC_SPECS",
    "Direction",
    "EventKind",
    "Field",
    "FieldKind",
    "Topic",
    "TopicSpec",
    "decode",
    "encode",
    "spec_for",
]
