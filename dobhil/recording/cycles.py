"""The ``cycle`` log layout: one MCAP message per control cycle.

MCAP indexes every message with 16 bytes (log time, offset) outside the compressed chunk,
and Foxglove's indexed reader needs that index (``typescript/core/src/ChunkCursor.ts`` in
github.com/foxglove/mcap refuses a chunk with messages and none). A cycle recorded as the
default ``topics`` layout is seven messages (five signal topics and two CAN frames): 112
of its ~190 bytes are index. The ``cycle`` layout writes the cycle's signal messages and
the CAN frames recorded after it (until the next cycle) as one protobuf message on
``/cycle`` (under the lane's prefix in a several-axis log), schema ``dobhil.Cycle``:

    message CycleFrame { sint64 log_time_offset_ns = 1; CanFrame frame = 2; }
    message Cycle {
      repeated CycleFrame rx = 1;  repeated CycleFrame tx = 2;
      DriveFeedback drive_feedback = 3;  DriveCommand drive_command = 4;
      Controller controller = 5;  Loop loop = 6;  EmulatorTruth emulator_truth = 7;
    }

Field numbers are the topics' numbers (:class:`~dobhil.recording.schemas.Topic`); each
sub-message is exactly the bytes the ``topics`` layout writes as that topic's message, and
a frame keeps its own log time as an offset from the cycle's. Foxglove decodes it from the
schema in the file (plot ``/cycle.loop.period_error``); dobhil's reader
(:class:`~dobhil.recording.reader.LogFile`) and python-can's reader
(:mod:`dobhil.canio.mcap_reader`) split it back (:func:`unfold`) into the per-topic
messages, in the order and with the log times they were recorded with, so replay, report,
identify and export read either layout alike. Frames outside a cycle (before the loop,
after it, or after the writer ended a chunk) keep their own ``/can/rx`` and ``/can/tx``
messages. A third of the bytes per cycle of the JSON logs dobhil wrote before 0.2
(``docs/recording.md``), at the price of the per-signal topics in Foxglove.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from functools import lru_cache
from typing import Final

from dobhil.recording.encodings.protobuf import (ProtoType, Wire, descriptor_proto, fields_on_wire, read_varint,
                                                 tag, varint)
from dobhil.recording.layouts import CYCLE_SCHEMA, CYCLE_TOPIC
from dobhil.recording.schemas import TOPIC_SPECS, Topic
#: The topics a cycle message holds, by field number (= the topic's number).
FOLDED: Final = (Topic.CAN_RX, Topic.CAN_TX, Topic.DRIVE_FEEDBACK, Topic.DRIVE_COMMAND, Topic.CONTROLLER,
                 Topic.LOOP, Topic.EMULATOR_TRUTH)
_FRAMES: Final = (Topic.CAN_RX, Topic.CAN_TX)
_TOPIC: Final = {int(t): t for t in FOLDED}
_LABEL_OPTIONAL, _LABEL_REPEATED = 1, 3
_SINT64: Final = 18
_TAGS: Final = {t: tag(int(t), Wire.LEN) for t in FOLDED}
_OFFSET_TAG: Final = tag(1, Wire.VARINT)
_FRAME_TAG: Final = tag(2, Wire.LEN)


def _ld(tag_bytes: bytes, data: bytes) -> bytes:
    return tag_bytes + varint(len(data)) + data


def _field(number: int, name: str, type_: int, label: int = _LABEL_OPTIONAL, type_name: str = "") -> bytes:
    """A ``FieldDescriptorProto``: name (1), number (3), label (4), type (5), type_name (6)."""
    out = (_ld(tag(1, Wire.LEN), name.encode()) + tag(3, Wire.VARINT) + varint(number)
           + tag(4, Wire.VARINT) + varint(label) + tag(5, Wire.VARINT) + varint(type_))
    return out + (_ld(tag(6, Wire.LEN), type_name.encode()) if type_name else b"")


def _message(name: str, fields: Sequence[bytes]) -> bytes:
    return _ld(tag(1, Wire.LEN), name.encode()) + b"".join(_ld(tag(2, Wire.LEN), f) for f in fields)


def _short(topic: Topic) -> str:
    return TOPIC_SPECS[topic].schema_name.rpartition(".")[2]


def field_name(topic: Topic) -> str:
    """The field of a cycle message that holds ``topic``'s messages (``/drive/feedback`` -> ``drive_feedback``)."""
    return {Topic.CAN_RX: "rx", Topic.CAN_TX: "tx"}.get(topic) or TOPIC_SPECS[topic].name.strip("/").replace("/", "_")


@lru_cache(maxsize=1)
def cycle_schema() -> bytes:
    """The serialized ``FileDescriptorSet`` of ``dobhil.Cycle``: one file holding it, the
    message of each topic it folds (as :func:`~dobhil.recording.encodings.protobuf.
    file_descriptor_set` describes them) and ``CycleFrame``."""
    inner = {_short(t): descriptor_proto(TOPIC_SPECS[t]) for t in FOLDED}   # the frames share CanFrame
    frame = _message("CycleFrame", [_field(1, "log_time_offset_ns", _SINT64),
                                    _field(2, "frame", ProtoType.MESSAGE, type_name=".dobhil.CanFrame")])
    cycle = _message("Cycle", [
        _field(int(t), field_name(t), ProtoType.MESSAGE,
               _LABEL_REPEATED if t in _FRAMES else _LABEL_OPTIONAL,
               ".dobhil.CycleFrame" if t in _FRAMES else f".dobhil.{_short(t)}") for t in FOLDED])
    messages = b"".join(_ld(tag(4, Wire.LEN), m) for m in (*inner.values(), frame, cycle))
    file = (_ld(tag(1, Wire.LEN), b"dobhil/Cycle.proto") + _ld(tag(2, Wire.LEN), b"dobhil") + messages
            + _ld(tag(12, Wire.LEN), b"proto3"))
    return _ld(tag(1, Wire.LEN), file)


def signal_part(topic: Topic, data: bytes) -> bytes:
    """A signal topic's message as its field of a cycle message."""
    return _ld(_TAGS[topic], data)


def frame_part(topic: Topic, data: bytes, offset_ns: int) -> bytes:
    """A CAN frame's message, ``offset_ns`` after the cycle's log time, as its field."""
    zigzag = (offset_ns << 1) ^ (offset_ns >> 63)
    return _ld(_TAGS[topic], _OFFSET_TAG + varint(zigzag) + _ld(_FRAME_TAG, data))


def _varint(data: bytes, pos: int) -> tuple[int, int]:
    """The varint at ``pos`` and the position after it (one byte, the common case, first)."""
    if pos < len(data) and data[pos] < 0x80:
        return data[pos], pos + 1
    return read_varint(data, pos)


def _frame(entry: bytes) -> tuple[int, bytes]:
    """(log time offset, frame bytes) of a ``CycleFrame``; fields it does not know skipped."""
    offset, frame = 0, None
    for n, w, v in fields_on_wire(entry):
        if n == 1 and w == Wire.VARINT:
            offset = (v >> 1) ^ -(v & 1)
        elif n == 2 and w == Wire.LEN:
            frame = v
    if frame is None:
        raise ValueError("an rx or tx entry of dobhil.Cycle holds no frame")
    return offset, frame


def unfold(data: bytes, log_time_ns: int) -> Iterator[tuple[Topic, int, bytes]]:
    """(topic, log time, message bytes) of each message a cycle message holds, in the order
    written; ValueError when it is not one. Read field by field here rather than with
    :func:`~dobhil.recording.encodings.protobuf.fields_on_wire`, whose generator per field
    made a replay of a cycle log twice as slow as of the same run in the topics layout."""
    pos, end = 0, len(data)
    while pos < end:
        key, pos = _varint(data, pos)
        number, wire = key >> 3, key & 7
        topic = _TOPIC.get(number)
        if topic is None or wire != Wire.LEN:
            raise ValueError(f"field {number} (wire type {wire}) is not a field of dobhil.Cycle")
        size, pos = _varint(data, pos)
        stop = pos + size
        if stop > end:
            raise ValueError(f"field {number} runs past the end of the message")
        if topic not in _FRAMES:
            yield topic, log_time_ns, data[pos:stop]
        else:
            if stop - pos >= 2 and data[pos] == 0x08:   # the writer's own layout: offset, then the frame
                v, at = _varint(data, pos + 1)
                if at < stop and data[at] == 0x12:
                    n, at = _varint(data, at + 1)
                    if at + n == stop:
                        yield topic, log_time_ns + ((v >> 1) ^ -(v & 1)), data[at:stop]
                        pos = stop
                        continue
            offset, frame = _frame(data[pos:stop])
            yield topic, log_time_ns + offset, frame
        pos = stop


def held(data: bytes) -> dict[Topic, int]:
    """Topic -> messages a cycle message holds (its frames each counted); ValueError when it
    is not one (:func:`unfold`)."""
    out: dict[Topic, int] = {}
    for topic, _, _ in unfold(data, 0):
        out[topic] = out.get(topic, 0) + 1
    return out


__all__ = ["CYCLE_SCHEMA", "CYCLE_TOPIC", "FOLDED", "cycle_schema", "field_name", "frame_part", "held",
           "signal_part", "unfold"]
