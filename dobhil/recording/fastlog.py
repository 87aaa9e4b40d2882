"""The fast path of run logging: flat records from the loop thread, JSON and MCAP in the writer.

The control loop must not pay for logging, so the loop thread only appends flat
tuples of plain values (:class:`RawKind` first; floats, ints, bools, str, bytes,
None -- no objects) to a shared list (:class:`Batcher`). Plain values are what
:mod:`marshal` serialises fastest, so a batch crosses to the writer *process*
(:mod:`~dobhil.recording.writerproc`) for the price of one ``marshal.dumps``; the
thread :class:`~dobhil.recording.recorder.Recorder` takes the same records.
The writer turns a batch into messages:

- :func:`encode_raw` expands one record into ``(Topic, log_time_ns, json_bytes)``
  messages (orjson for the cycle records, a ``%``-template for the initial feedback). Floats are
  written in their shortest exact form (``repr``), so replay reads back the very same
  doubles; non-finite numbers become ``null``.
- :class:`FastWriter` is :class:`mcap.writer.Writer` with a batched ``add_messages``
  that writes message records straight into the chunk buffer (one ``struct.pack``
  each) instead of building record objects; the file is the same MCAP.
"""

from __future__ import annotations

import json
import struct
from collections.abc import Callable, Iterable, Iterator, Sequence
from enum import IntEnum
from itertools import chain
from typing import Any, Final

import orjson

from mcap._chunk_builder import ChunkBuilder
from mcap.data_stream import RecordBuilder
from mcap.records import MessageIndex
from mcap.writer import Writer

from dobhil.recording.schemas import EventKind, Topic, encode


class RawKind(IntEnum):
    """First element of a raw record tuple; the rest is plain values, laid out as commented."""

    FRAME_RX = 1   # (kind, t_ns, arbitration_id, flags, dlc, data, timestamp, channel)
    FRAME_TX = 2   # same as FRAME_RX
    CYCLE = 3      # (kind, t_ns, k, position, velocity, seq, tau_ref, tau_int_hat, tau_dis_hat, tau_per,
    #                 u_unsat, u, period_error, exec_time, overrun, axis_state, axis_error[, q, dq, tau_motor, tau_int])
    FEEDBACK = 4   # (kind, t_ns, position, velocity, axis_state, axis_error, seq, cycle)
    EVENT = 5      # (kind, t_ns, EventKind, reason, detail)
    LOSS = 6       # (kind, t_ns, count, total): records dropped before this one (LOSSY)


class FrameFlag(IntEnum):
    """Bits of a frame record's ``flags``: the booleans of a python-can message."""

    EXTENDED_ID = 1
    REMOTE_FRAME = 2
    ERROR_FRAME = 4
    FD = 8
    BITRATE_SWITCH = 16
    ERROR_STATE_INDICATOR = 32


#: Length of a CYCLE record without and with the emulator truth.
CYCLE_LEN: Final = 17
CYCLE_TRUTH_LEN: Final = 21

Encoded = tuple[Topic, int, bytes]

_BOOL: Final = ("false", "true")
_BYTE: Final = tuple(str(b) for b in range(256))
_FEEDBACK: Final = '{"position":%r,"velocity":%r,"axis_state":%d,"axis_error":%d,"seq":%d,"cycle":%d}'


def frame_flags(msg: Any) -> int:
    """The :class:`FrameFlag` bits of a python-can message."""
    return (msg.is_extended_id | msg.is_remote_frame << 1 | msg.is_error_frame << 2 | msg.is_fd << 3
            | msg.bitrate_switch << 4 | msg.error_state_indicator << 5)


def event_payload(kind: EventKind, reason: str, detail: str = "", count: int = 0) -> dict[str, Any]:
    """The ``/events`` payload."""
    return {"kind": kind.name.lower(), "reason": reason, "detail": detail, "count": count}


def loss_payload(count: int, total: int) -> dict[str, Any]:
    """The ``/events`` ``kind=loss`` payload for ``count`` records dropped (``total`` so far)."""
    return event_payload(EventKind.LOSS, f"{count} records dropped (queue full)", f"total {total}", count)


def _checked(text: str) -> bytes:
    """JSON bytes of a template result; non-finite numbers re-encoded as null."""
    data = text.encode()
    if b"nan" in data or b"inf" in data:
        return encode(_plain_dict(data))
    return data


def _plain_dict(data: bytes) -> dict[str, Any]:
    """The template's JSON with Python's nan/inf spellings read back (json accepts them)."""
    return json.loads(data.replace(b"nan", b"NaN").replace(b"inf", b"Infinity"))


class FrameEncoder:
    """CAN frame JSON with the constant part per (id, flags, dlc, channel, direction) cached."""

    def __init__(self) -> None:
        self._heads: dict[tuple[Any, ...], tuple[str, str]] = {}

    def __call__(self, rec: Sequence[Any]) -> bytes:
        _, t_ns, arb, flags, dlc, data, stamp, channel = rec
        key = (arb, flags, dlc, channel, rec[0])
        head = self._heads.get(key)
        if head is None:
            head = self._heads[key] = _frame_head(arb, flags, dlc, channel, rec[0] == RawKind.FRAME_RX)
        stamp = stamp or t_ns / 1e9
        body = (f'{{"timestamp":{stamp!r},{head[0]},"data":[{",".join([_BYTE[b] for b in data])}],'
                f'"data_hex":"{bytes(data).hex()}",{head[1]}}}')
        return body.encode()


def _frame_head(arb: int, flags: int, dlc: int, channel: Any, rx: bool) -> tuple[str, str]:
    bits = [_BOOL[bool(flags & f)] for f in FrameFlag]
    head = (f'"arbitration_id":{arb},"is_extended_id":{bits[0]},"is_remote_frame":{bits[1]},'
            f'"is_error_frame":{bits[2]},"is_fd":{bits[3]},"bitrate_switch":{bits[4]},'
            f'"error_state_indicator":{bits[5]},"dlc":{dlc}')
    tail = f'"direction":"{"rx" if rx else "tx"}","channel":{json.dumps("" if channel is None else str(channel))}'
    return head, tail


def encode_raw(records: Iterable[Sequence[Any]], frames: FrameEncoder) -> Iterator[Encoded]:
    """The messages of a batch of raw records, in order."""
    for rec in records:
        kind = rec[0]
        if kind == RawKind.CYCLE:
            yield from _cycle_messages(rec)
        elif kind == RawKind.FRAME_RX:
            yield Topic.CAN_RX, rec[1], frames(rec)
        elif kind == RawKind.FRAME_TX:
            yield Topic.CAN_TX, rec[1], frames(rec)
        elif kind == RawKind.FEEDBACK:
            yield Topic.DRIVE_FEEDBACK, rec[1], _checked(_FEEDBACK % tuple(rec[2:]))
        elif kind == RawKind.EVENT:
            yield Topic.EVENTS, rec[1], encode(event_payload(EventKind(rec[2]), rec[3], rec[4]))
        elif kind == RawKind.LOSS:
            yield Topic.EVENTS, rec[1], encode(loss_payload(rec[2], rec[3]))


def _cycle_messages(rec: Sequence[Any]) -> Iterator[Encoded]:
    """The messages of one cycle record, through orjson (exact shortest floats, NaN as null;
    about twice as fast as string templates, which matters: this runs every cycle)."""
    dumps = orjson.dumps
    t, k = rec[1], rec[2]
    yield Topic.DRIVE_FEEDBACK, t, dumps({"position": rec[3], "velocity": rec[4], "axis_state": rec[15],
                                          "axis_error": rec[16], "seq": rec[5], "cycle": k})
    yield Topic.CONTROLLER, t, dumps({"tau_ref": rec[6], "tau_int_hat": rec[7], "tau_dis_hat": rec[8],
                                      "tau_per": rec[9], "u_unsat": rec[10], "u_sat": rec[11], "cycle": k})
    yield Topic.DRIVE_COMMAND, t, dumps({"torque": rec[11]})
    yield Topic.LOOP, t, dumps({"cycle": k, "period_error": rec[12], "exec_time": rec[13],
                                "overrun": bool(rec[14])})
    if len(rec) > CYCLE_LEN:
        yield Topic.EMULATOR_TRUTH, t, dumps({"q": rec[17], "dq": rec[18], "tau_motor": rec[19],
                                              "tau_int": rec[20]})


def messages_per_record(rec: Sequence[Any]) -> int:
    """How many messages a raw record becomes (for loss and queue accounting)."""
    if rec[0] == RawKind.CYCLE:
        return 4 if len(rec) <= CYCLE_LEN else 5
    return 1


class Batcher:
    """The shared list raw records are appended to; handed to ``sink`` every ``size`` records.

    Producers (the bus tap and the cycle sink) append to :attr:`buffer` directly
    (``list.append`` is the cheapest thing the loop thread can do) and call
    :meth:`maybe_flush` once per cycle.
    """

    def __init__(self, sink: Callable[[list[tuple[Any, ...]]], object], size: int = 256) -> None:
        self.buffer: list[tuple[Any, ...]] = []
        self._sink = sink
        self._size = size

    def maybe_flush(self) -> None:
        if len(self.buffer) >= self._size:
            self.flush()

    def flush(self) -> None:
        buf = self.buffer
        if buf:
            batch = buf.copy()
            buf.clear()
            self._sink(batch)


class _FastIndex(MessageIndex):
    """A message index written with one ``struct.pack``."""

    def write(self, stream: RecordBuilder) -> None:
        n = len(self.records)
        stream.write(struct.pack(f"<BQHI{2 * n}Q", 0x07, 6 + 16 * n, self.channel_id, 16 * n,
                                 *chain.from_iterable(self.records)))


class FastWriter(Writer):
    """:class:`mcap.writer.Writer` plus :meth:`add_messages` (same file format)."""

    _PACK: Final = struct.Struct("<BQHIQQ").pack

    def add_messages(self, messages: Iterable[tuple[int, int, bytes]]) -> None:
        """Add ``(channel_id, log_time_ns, data)`` messages (publish time = log time)."""
        builder: ChunkBuilder | None = self._Writer__chunk_builder  # type: ignore[attr-defined]
        if builder is None:
            for channel, t, data in messages:
                self.add_message(channel, t, data, t)
            return
        stats = self._Writer__statistics  # type: ignore[attr-defined]
        counts = stats.channel_message_counts
        limit = self._Writer__chunk_size  # type: ignore[attr-defined]
        pack = self._PACK
        for channel, t, data in messages:
            if stats.message_count == 0 or t < stats.message_start_time:
                stats.message_start_time = t
            if t > stats.message_end_time:
                stats.message_end_time = t
            counts[channel] += 1
            stats.message_count += 1
            buf = builder.record_writer._buffer
            offset = buf.tell()
            if builder.num_messages == 0 or t < builder.message_start_time:
                builder.message_start_time = t
            if t > builder.message_end_time:
                builder.message_end_time = t
            index = builder.message_indices.get(channel)
            if index is None:
                index = builder.message_indices[channel] = _FastIndex(channel_id=channel, records=[])
            index.records.append((t, offset))
            builder.num_messages += 1
            buf.write(pack(0x05, 22 + len(data), channel, 0, t, t))
            buf.write(data)
            if offset > limit:
                self._Writer__finalize_chunk()  # type: ignore[attr-defined]


__all__ = ["CYCLE_LEN", "CYCLE_TRUTH_LEN", "Batcher", "FastWriter", "FrameEncoder", "FrameFlag", "RawKind",
           "encode_raw", "event_payload", "frame_flags", "loss_payload", "messages_per_record"]
