"""A python-can message as a dobhil ``/can/rx`` or ``/can/tx`` record, and back.

The one place :mod:`dobhil.canio` depends on :mod:`dobhil.recording`: the topic table
(names, schemas, encodings) and the frame codec of a recording, used as they are, so a
frame written by the plugins is byte for byte what ``dobhil run --log`` writes.
"""

from __future__ import annotations

from typing import Final

import can

from dobhil.recording.schemas import (MESSAGE_ENCODING, SCHEMA_ENCODING, TOPIC_SPECS, Direction, Topic,
                                      can_frame_message, can_frame_record, decode)

#: The two frame topics, received first.
FRAME_TOPICS: Final = (Topic.CAN_RX, Topic.CAN_TX)
#: Their names (``/can/rx``, ``/can/tx``).
FRAME_TOPIC_NAMES: Final = tuple(TOPIC_SPECS[t].name for t in FRAME_TOPICS)


def topic_of(msg: can.Message) -> Topic:
    """``/can/rx`` for a received frame (python-can's ``is_rx``), else ``/can/tx``."""
    return Topic.CAN_RX if msg.is_rx else Topic.CAN_TX


def frame_json(msg: can.Message) -> bytes:
    """The JSON message of a frame on :func:`topic_of` its direction."""
    topic = topic_of(msg)
    record = can_frame_record(msg, Direction.RX if msg.is_rx else Direction.TX, 0)
    return TOPIC_SPECS[topic].encode(record[2:])


def frame_message(data: bytes, log_time_ns: int) -> can.Message:
    """The python-can message of a recorded frame (bus time, else log time)."""
    return can_frame_message(decode(data), log_time_ns)


def channel_spec(topic: Topic) -> tuple[str, str, bytes, str, str]:
    """(topic name, schema name, schema bytes, schema encoding, message encoding) of a frame topic."""
    spec = TOPIC_SPECS[topic]
    return spec.name, spec.schema_name, spec.schema_bytes(), SCHEMA_ENCODING, MESSAGE_ENCODING


__all__ = ["FRAME_TOPICS", "FRAME_TOPIC_NAMES", "Topic", "channel_spec", "frame_json", "frame_message", "topic_of"]
