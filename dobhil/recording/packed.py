"""Records packed on the loop thread: a cycle record or a CAN frame record as one ``bytes``,
built by one precompiled :class:`struct.Struct` (Python's ``struct`` module, standard sizes,
little-endian), and :func:`unpacked`, the plain tuple of its named type again
(``schemas.CycleRecord``, ``schemas.FrameRecord``), in the writer process.

Why: the loop thread paid for each record twice, once building a tuple of 13 or 23 objects
and once pickling every one of them into the batch (a float: an opcode, 8 bytes, a memo
check; ``docs/recording.md``, "Who writes, who reads"). Packed, a record is one call and one
object, which the batch's pickle copies whole.

Only what a field's type holds exactly is packed: numbers into ``d`` (IEEE 754 double, what
the log stores), integers into ``q``, flags into ``?``, a frame's payload and a text or no
channel as bytes. A value that does not fit (``struct.error``, ``TypeError``,
``OverflowError``: ``None`` for a number, an integer beyond 64 bits, a channel that is
neither text nor ``None``) is the caller's to record as a plain tuple, as before: what
becomes of it in the writer does not change. Packed numbers come back as Python ``float``,
``int`` and ``bool`` of the same value (a numpy number's value kept bit for bit).

Layouts (``kind`` is the record's kind with its lane; its base tells the layout, a cycle's
length whether it carries the emulator's truth):

- cycle: ``<H q q d d q dddddd d d ? d q q q [dddd]`` -- the fields of ``CycleRecord`` in order;
- frame: ``<H q q ? ? ? ? ? ? q d H`` (kind, log time, id, the six flags, dlc, timestamp,
  payload length), then the payload, then the channel: ``<H`` length and UTF-8 text, or
  ``0xFFFF`` alone for ``None``.
"""

from __future__ import annotations

import struct
from typing import Any, Final

from dobhil.recording.schemas import CYCLE, LANE_MASK, Topic

#: A cycle record without the emulator's truth, and with it.
CYCLE_PLAIN: Final = struct.Struct("<Hqqddq6ddd?dqqq")
CYCLE_TRUTH: Final = struct.Struct("<Hqqddq6ddd?dqqq4d")
#: A frame record's fixed part: its fields but the payload and channel, then the payload's length.
FRAME_HEAD: Final = struct.Struct("<Hqq6?qdH")
_LENGTH: Final = struct.Struct("<H")
_NO_CHANNEL: Final = 0xFFFF
#: What a record that does not fit its layout raises while packed.
UNFIT: Final = (struct.error, TypeError, OverflowError)
#: Channels kept encoded (a bus has one or two; more are encoded each time).
_CHANNEL_CACHE: Final = 16
_FRAMES: Final = frozenset({int(Topic.CAN_RX), int(Topic.CAN_TX)})


def channel_bytes(channel: Any, cache: dict[Any, bytes]) -> bytes:
    """A frame's channel as packed (``cache``: channel -> its bytes, filled here); a channel
    that is neither text nor ``None`` raises ``TypeError`` (recorded as a tuple instead)."""
    if channel is None:
        data = _LENGTH.pack(_NO_CHANNEL)
    elif type(channel) is str:
        text = channel.encode("utf-8", "surrogatepass")
        if len(text) >= _NO_CHANNEL:
            raise OverflowError("channel name too long to pack")
        data = _LENGTH.pack(len(text)) + text
    else:
        raise TypeError(f"channel of type {type(channel).__name__} is not packed")
    if len(cache) < _CHANNEL_CACHE:
        cache[channel] = data
    return data


def pack_frame(kind: int, log_time_ns: int, msg: Any, data: Any, timestamp: float, channel: bytes) -> bytes:
    """A frame record packed (``data``: the payload to record, ``channel``: from
    :func:`channel_bytes`). The loop thread's hot paths inline this; tests use it."""
    return b"".join((FRAME_HEAD.pack(kind, log_time_ns, msg.arbitration_id, msg.is_extended_id,
                                     msg.is_remote_frame, msg.is_error_frame, msg.is_fd, msg.bitrate_switch,
                                     msg.error_state_indicator, msg.dlc, timestamp, len(data)), data, channel))


def unpacked(record: Any) -> tuple[Any, ...]:
    """The plain tuple of a record (a packed one unpacked; a tuple as it is)."""
    if type(record) is not bytes:
        return tuple(record)
    kind = _LENGTH.unpack_from(record)[0]
    base = kind & LANE_MASK
    if base == CYCLE:
        return (CYCLE_TRUTH if len(record) == CYCLE_TRUTH.size else CYCLE_PLAIN).unpack(record)
    if base not in _FRAMES:
        raise ValueError(f"packed record of kind {kind}: not a cycle or a frame")
    head = FRAME_HEAD.unpack_from(record)
    start = FRAME_HEAD.size
    end = start + head[-1]
    (length,) = _LENGTH.unpack_from(record, end)
    channel = None if length == _NO_CHANNEL else record[end + 2:end + 2 + length].decode("utf-8", "surrogatepass")
    if end + 2 + (0 if length == _NO_CHANNEL else length) != len(record):
        raise ValueError(f"packed frame record of {len(record)} bytes: its lengths say otherwise")
    return (*head[:10], record[start:end], head[10], channel)


def unpacked_batch(records: list[Any]) -> list[Any]:
    """A batch with every packed record unpacked (others kept as they are)."""
    return [unpacked(r) if type(r) is bytes else r for r in records]


__all__ = ["CYCLE_PLAIN", "CYCLE_TRUTH", "FRAME_HEAD", "UNFIT", "channel_bytes", "pack_frame", "unpacked",
           "unpacked_batch"]
