"""The fast path of run logging: raw records from the loop thread, JSON and MCAP in the writer thread.

The control loop must not pay for logging, so the loop thread only appends plain
tuples (:class:`RawKind` first) to a shared list (:class:`Batcher`); the recorder's
writer thread turns a batch of them into messages:

- :func:`encode_raw` expands one raw record into ``(Topic, log_time_ns, json_bytes)``
  messages with precomputed ``%``-templates. Floats go through ``%r`` (``repr``),
  which round-trips exactly, so replay reads back the very same doubles; a message
  holding ``nan``/``inf`` is re-encoded through :func:`~dobhil.recording.schemas.encode`
  (non-finite numbers become ``null``).
- :class:`FastWriter` is :class:`mcap.writer.Writer` with a batched ``add_messages``
  that writes message records straight into the chunk buffer (one ``struct.pack``
  each) instead of building record objects; the file is the same MCAP.
"""

from __future__ import annotations

import struct
from collections.abc import Callable, Iterable, Iterator, Sequence
from enum import IntEnum
from itertools import chain
from typing import Any, Final

from mcap._chunk_builder import ChunkBuilder
from mcap.data_stream import RecordBuilder
from mcap.records import MessageIndex
from mcap.writer import Writer

from dobhil.recording.schemas import Topic, encode


class RawKind(IntEnum):
    """First element of a raw record tuple."""

    FRAME_RX = 1      # (kind, t_ns, can.Message, data)
    FRAME_TX = 2      # (kind, t_ns, can.Message, data)
    CYCLE = 3         # (kind, t_ns, k, Feedback, ControlOutput, period_error, exec_time, overrun, DriveStatus, truth|None)
    FEEDBACK = 4      # (kind, t_ns, position, velocity, axis_state, axis_error, seq, cycle)


Encoded = tuple[Topic, int, bytes]

_BOOL: Final = ("false", "true")
_BYTE: Final = tuple(str(b) for b in range(256))
_FEEDBACK: Final = '{"position":%r,"velocity":%r,"axis_state":%d,"axis_error":%d,"seq":%d,"cycle":%d}'
_COMMAND: Final = '{"torque":%r}'
_CONTROLLER: Final = ('{"tau_ref":%r,"tau_int_hat":%r,"tau_dis_hat":%r,"tau_per":%r,'
                      '"u_unsat":%r,"u_sat":%r,"cycle":%d}')
_LOOP: Final = '{"cycle":%d,"period_error":%r,"exec_time":%r,"overrun":%s}'
_TRUTH: Final = '{"q":%r,"dq":%r,"tau_motor":%r,"tau_int":%r}'


def _checked(topic: Topic, text: str) -> bytes:
    """JSON bytes of a template result; non-finite numbers re-encoded as null."""
    data = text.encode()
    if b"nan" in data or b"inf" in data:
        return encode(_plain_dict(data))
    return data


def _plain_dict(data: bytes) -> dict[str, Any]:
    """The template's JSON with Python's nan/inf spellings read back (json accepts them)."""
    import json
    return json.loads(data.replace(b"nan", b"NaN").replace(b"inf", b"Infinity"))


class FrameEncoder:
    """CAN frame JSON with the constant part per (id, flags, dlc, channel) cached."""

    def __init__(self) -> None:
        self._heads: dict[tuple[Any, ...], str] = {}

    def __call__(self, topic: Topic, t_ns: int, msg: Any, data: bytes | bytearray) -> bytes:
        direction = "rx" if topic is Topic.CAN_RX else "tx"
        key = (msg.arbitration_id, msg.is_extended_id, msg.is_remote_frame, msg.is_error_frame,
               msg.is_fd, msg.bitrate_switch, msg.error_state_indicator, msg.dlc, msg.channel, direction)
        head = self._heads.get(key)
        if head is None:
            head = self._heads[key] = _frame_head(key)
        stamp = msg.timestamp or t_ns / 1e9
        body = (f'{{"timestamp":{stamp!r},{head[0]},"data":[{",".join([_BYTE[b] for b in data])}],'
                f'"data_hex":"{bytes(data).hex()}",{head[1]}}}')
        return body.encode()


def _frame_head(key: tuple[Any, ...]) -> tuple[str, str]:
    arb, ext, rtr, err, fd, brs, esi, dlc, channel, direction = key
    flags = (f'"arbitration_id":{arb},"is_extended_id":{_BOOL[bool(ext)]},'
             f'"is_remote_frame":{_BOOL[bool(rtr)]},"is_error_frame":{_BOOL[bool(err)]},'
             f'"is_fd":{_BOOL[bool(fd)]},"bitrate_switch":{_BOOL[bool(brs)]},'
             f'"error_state_indicator":{_BOOL[bool(esi)]},"dlc":{dlc}')
    import json
    tail = f'"direction":"{direction}","channel":{json.dumps("" if channel is None else str(channel))}'
    return flags, tail


def encode_raw(records: Iterable[tuple[Any, ...]], frames: FrameEncoder) -> Iterator[Encoded]:
    """The messages of a batch of raw records, in order."""
    for rec in records:
        kind = rec[0]
        if kind == RawKind.CYCLE:
            yield from _cycle_messages(rec)
        elif kind == RawKind.FRAME_RX:
            yield Topic.CAN_RX, rec[1], frames(Topic.CAN_RX, rec[1], rec[2], rec[3])
        elif kind == RawKind.FRAME_TX:
            yield Topic.CAN_TX, rec[1], frames(Topic.CAN_TX, rec[1], rec[2], rec[3])
        elif kind == RawKind.FEEDBACK:
            yield Topic.DRIVE_FEEDBACK, rec[1], _checked(Topic.DRIVE_FEEDBACK, _FEEDBACK % rec[2:])


def _cycle_messages(rec: tuple[Any, ...]) -> Iterator[Encoded]:
    _, t, k, fb, out, period_error, exec_time, overrun, status, truth = rec
    yield Topic.DRIVE_FEEDBACK, t, _checked(
        Topic.DRIVE_FEEDBACK, _FEEDBACK % (fb.position, fb.velocity, status.state, status.error_code, fb.seq, k))
    yield Topic.CONTROLLER, t, _checked(Topic.CONTROLLER, _CONTROLLER % (*out, k))
    yield Topic.DRIVE_COMMAND, t, _checked(Topic.DRIVE_COMMAND, _COMMAND % (out[5],))
    yield Topic.LOOP, t, _checked(Topic.LOOP, _LOOP % (k, period_error, exec_time, _BOOL[bool(overrun)]))
    if truth is not None:
        yield Topic.EMULATOR_TRUTH, t, _checked(Topic.EMULATOR_TRUTH, _TRUTH % truth)


def _cycle_messages_orjson(rec: tuple[Any, ...]) -> Iterator[Encoded]:
    """:func:`_cycle_messages` through orjson (exact shortest floats, NaN as null)."""
    _, t, k, fb, out, period_error, exec_time, overrun, status, truth = rec
    dumps = _orjson_dumps
    yield Topic.DRIVE_FEEDBACK, t, dumps({"position": fb.position, "velocity": fb.velocity,
                                          "axis_state": int(status.state), "axis_error": status.error_code,
                                          "seq": fb.seq, "cycle": k})
    yield Topic.CONTROLLER, t, dumps({"tau_ref": out[0], "tau_int_hat": out[1], "tau_dis_hat": out[2],
                                      "tau_per": out[3], "u_unsat": out[4], "u_sat": out[5], "cycle": k})
    yield Topic.DRIVE_COMMAND, t, dumps({"torque": out[5]})
    yield Topic.LOOP, t, dumps({"cycle": k, "period_error": period_error, "exec_time": exec_time,
                                "overrun": bool(overrun)})
    if truth is not None:
        yield Topic.EMULATOR_TRUTH, t, dumps({"q": truth[0], "dq": truth[1], "tau_motor": truth[2],
                                              "tau_int": truth[3]})


try:  # optional: about twice as fast as the templates
    from orjson import dumps as _orjson_dumps
except ImportError:  # pragma: no cover - depends on the environment
    _orjson_dumps = None
else:
    _cycle_messages = _cycle_messages_orjson  # noqa: F811


def messages_per_record(rec: Sequence[Any]) -> int:
    """How many messages a raw record becomes (for queue accounting)."""
    if rec[0] == RawKind.CYCLE:
        return 4 if rec[9] is None else 5
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


__all__ = ["Batcher", "FastWriter", "FrameEncoder", "RawKind", "encode_raw", "messages_per_record"]
