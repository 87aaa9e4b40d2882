"""A python-can message as a dobhil ``/can/rx`` or ``/can/tx`` record, and back.

:mod:`dobhil.canio` uses :mod:`dobhil.recording` as it is -- the topic table, the frame
codec and (the writer plugin) :class:`~dobhil.recording.writer.LogWriter` -- so a frame
written by the plugins is byte for byte what ``dobhil run --log`` writes.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from typing import Final

import can

from dobhil.recording.axeslog import BUS_PREFIX
from dobhil.recording.encodings import Decoder
from dobhil.recording.schemas import TOPIC_SPECS, Topic, can_frame_message, decode

#: The two frame topics, received first.
FRAME_TOPICS: Final = (Topic.CAN_RX, Topic.CAN_TX)
#: Their names (``/can/rx``, ``/can/tx``).
FRAME_TOPIC_NAMES: Final = tuple(TOPIC_SPECS[t].name for t in FRAME_TOPICS)


def is_frame_topic(topic: str) -> bool:
    """A topic of CAN frames: ``/can/rx``, ``/can/tx``, or a bus' of a several-axis log
    (``/bus/<bus>/can/rx``, ``/bus/<bus>/can/tx``)."""
    return topic in FRAME_TOPIC_NAMES or (topic.startswith(BUS_PREFIX) and topic.endswith(FRAME_TOPIC_NAMES))


def topic_of(msg: can.Message) -> Topic:
    """``/can/rx`` for a received frame (python-can's ``is_rx``), else ``/can/tx``."""
    return Topic.CAN_RX if msg.is_rx else Topic.CAN_TX


def frame_message(data: bytes, log_time_ns: int, decoder: Decoder = decode) -> can.Message:
    """The python-can message of a recorded frame (bus time, else log time), its bytes read
    by ``decoder`` (its channel's encoding; JSON unless given)."""
    return can_frame_message(decoder(data), log_time_ns)


def frame_channels(metadata: Mapping[str, Mapping[str, str]], path: str | os.PathLike[str]) -> dict[str, str]:
    """Frame topic -> the channel its bus was opened on, from a log's metadata (the ``bus``
    record; a several-axis log's ``bus/<bus>``, its topics by
    :func:`dobhil.recording.axes.metadata_layout`: the topic's prefix is the bus name made a
    topic, ``/bus/socketcan_can0`` for ``socketcan:can0``). A sent frame is recorded with no
    channel (python-can sets none on a message it sends), so a reader or writer would put it
    on no channel or one of its own choosing -- candump ``vcan0``, ASC and BLF channel 1 --
    the sent frames of every bus of a several-bus run on one channel, apart from the frames
    received on the same bus. ``path`` names the log in an error."""
    from dobhil.recording.axes import metadata_layout
    out: dict[str, str] = {}
    for bus, prefix in metadata_layout(metadata, path).buses.items():
        record = metadata.get(f"bus/{bus}") or metadata.get("bus", {})
        channel = str(record.get("channel") or "")
        if channel:
            out.update(dict.fromkeys((prefix + name for name in FRAME_TOPIC_NAMES), channel))
    return out


__all__ = ["FRAME_TOPICS", "FRAME_TOPIC_NAMES", "Topic", "frame_channels", "frame_message", "is_frame_topic",
           "topic_of"]
