"""A python-can bus between two processes: one end of a local socket pair.

:class:`PipeBus` joins the host and an emulated drive that runs in a process of its own
(:mod:`dobhil.emulator.process`). Written by hand because no well-kept library does it:
python-can's ``virtual`` bus is in-process only, ``socketcan``/``vcan`` needs a kernel
module (absent on CI machines and outside Linux), and python-can-remote or ``udp_multicast``
go through the network stack, a server and a thread. This is the smallest thing that
works: an ``AF_UNIX`` socket pair (``SOCK_SEQPACKET`` where there is one, so each frame
is one record), both ends non-blocking, waits in ``select`` -- no thread, and the
interpreter lock is released while waiting.

Each record is one byte of kind and a payload: a frame (its fields and the sender's
``time.time()`` stamp, which the receiver keeps as the frame's timestamp, like a bus
stamp at reception), or a line of text from the peer (its failure, or that it is
ready). An empty read means the peer's end is closed: the process is gone.
"""

from __future__ import annotations

import select
import socket
import struct
import time
from collections import deque
from collections.abc import Callable
from enum import IntEnum
from typing import Any

import can

__all__ = ["PipeBus", "RecordKind", "socket_pair"]

#: kind, stamp [s since the epoch], arbitration id, flags, DLC (then the data bytes)
_FRAME = struct.Struct("<BdIBB")
_RECORD_MAX = _FRAME.size + 64
#: the longest a send waits for room when no timeout is given [s]
SEND_WAIT_MAX = 0.05


class RecordKind(IntEnum):
    FRAME = 0
    READY = 1    # the peer is set up (text: what it is)
    FAILED = 2   # the peer failed (text: why, one line); it exits next


class _Flag(IntEnum):
    EXTENDED = 1
    REMOTE = 2
    ERROR = 4
    FD = 8
    BRS = 16
    ESI = 32


def socket_pair() -> tuple[socket.socket, socket.socket]:
    """Two connected ends; records keep their boundaries (SEQPACKET, else DGRAM: both
    reliable and ordered for AF_UNIX)."""
    kind = getattr(socket, "SOCK_SEQPACKET", socket.SOCK_DGRAM)
    try:
        a, b = socket.socketpair(socket.AF_UNIX, kind)
    except OSError:
        a, b = socket.socketpair(socket.AF_UNIX, socket.SOCK_DGRAM)
    for end in (a, b):
        end.setblocking(False)
    return a, b


def encode_frame(msg: can.Message) -> bytes:
    flags = ((_Flag.EXTENDED if msg.is_extended_id else 0) | (_Flag.REMOTE if msg.is_remote_frame else 0)
             | (_Flag.ERROR if msg.is_error_frame else 0) | (_Flag.FD if msg.is_fd else 0)
             | (_Flag.BRS if msg.bitrate_switch else 0) | (_Flag.ESI if msg.error_state_indicator else 0))
    return _FRAME.pack(RecordKind.FRAME, time.time(), msg.arbitration_id, flags, msg.dlc) + bytes(msg.data)


def decode_frame(record: bytes, channel: Any) -> can.Message:
    _, stamp, arbitration_id, flags, dlc = _FRAME.unpack_from(record)
    return can.Message(timestamp=stamp, arbitration_id=arbitration_id,
                       is_extended_id=bool(flags & _Flag.EXTENDED),
                       is_remote_frame=bool(flags & _Flag.REMOTE), is_error_frame=bool(flags & _Flag.ERROR),
                       is_fd=bool(flags & _Flag.FD), bitrate_switch=bool(flags & _Flag.BRS),
                       error_state_indicator=bool(flags & _Flag.ESI), dlc=dlc,
                       data=record[_FRAME.size:], channel=channel, is_rx=True, check=False)


def text_record(kind: RecordKind, text: str) -> bytes:
    return bytes([kind]) + " ".join(text.split()).encode("utf-8", "replace")[:_RECORD_MAX - 1]


class PipeBus(can.BusABC):
    """One end of a :func:`socket_pair` as a python-can bus.

    ``gone``: the text of the error raised when the peer's end is closed (called then, so
    it can name the peer's exit code). ``mirror``: a bus (a ``virtual`` one) that gets a
    copy of every frame sent or received, so in-process observers keep seeing the traffic.
    ``send_wait``: how long a send without a timeout waits for room. ``coalesce`` (the
    drive's end): a frame that finds the buffer full is not lost but held, the newest
    per arbitration id (as a CAN controller's transmit mailbox holds one frame per
    message), and goes out first once the reader has made room -- a host that stalled
    then reads the drive's newest heartbeat and estimates, not only the oldest frames of
    its stall; ``replaced`` counts the frames a newer one of the same id superseded.
    The socket is owned: :meth:`shutdown` closes it (the peer then reads the end).
    """

    def __init__(self, sock: socket.socket, channel: Any = None, *,
                 gone: Callable[[], str] = lambda: "the other end of the bus is closed",
                 mirror: can.BusABC | None = None, receive_own_messages: bool = False,
                 send_wait: float = SEND_WAIT_MAX, coalesce: bool = False, **kwargs: Any) -> None:
        self._sock = sock
        self._send_wait = send_wait
        self._held: dict[int, bytes] | None = {} if coalesce else None
        self.replaced = 0
        self._gone = gone
        self._mirror = mirror
        self._own: deque[can.Message] | None = deque() if receive_own_messages else None
        self.channel_info = f"pipe {channel}" if channel is not None else "pipe"
        self._channel = channel
        self.peer_text = ""   # the peer's READY text
        super().__init__(channel=channel, **kwargs)

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        """Send, waiting at most ``timeout`` s for room (None: at most ``send_wait``: a
        peer that stopped reading never hangs the sender)."""
        record = encode_frame(msg)
        held = self._held
        if held is not None and (held and not self._flush_held() or not self._try_send(record)):
            if held.pop(msg.arbitration_id, None) is not None:
                self.replaced += 1
            held[msg.arbitration_id] = record   # the newest of its id, last in line
            return
        if held is not None:
            self._copy(msg)
            return
        end = time.monotonic() + (self._send_wait if timeout is None else timeout)
        while True:
            try:
                self._sock.send(record)
                break
            except BlockingIOError:
                # the peer is not reading (stopped, or starved): never wait longer than asked
                remaining = end - time.monotonic()
                if remaining <= 0:
                    raise can.CanOperationError("pipe bus: the receiving end is not reading "
                                                "(its buffer is full)") from None
                select.select([], [self._sock], [], remaining)
            except OSError as exc:
                raise can.CanOperationError(f"{self._gone()} ({exc.strerror or exc})") from exc
        if self._own is not None:
            own = can.Message(timestamp=time.time(), arbitration_id=msg.arbitration_id,
                              is_extended_id=msg.is_extended_id, is_remote_frame=msg.is_remote_frame,
                              is_error_frame=msg.is_error_frame, is_fd=msg.is_fd, dlc=msg.dlc,
                              data=msg.data, channel=self._channel, is_rx=False, check=False)
            self._own.append(own)
        self._copy(msg)

    def _try_send(self, record: bytes) -> bool:
        try:
            self._sock.send(record)
        except BlockingIOError:
            return False
        except OSError as exc:
            raise can.CanOperationError(f"{self._gone()} ({exc.strerror or exc})") from exc
        return True

    def _flush_held(self) -> bool:
        """Send the held frames, oldest first, while there is room; True when all went."""
        held = self._held
        while held:
            key = next(iter(held))
            if not self._try_send(held[key]):
                return False
            del held[key]
        return True

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        if self._held:
            self._flush_held()
        if self._own:
            return self._own.popleft(), False
        end = None if timeout is None else time.monotonic() + timeout
        while True:
            record = self.read_record(end)
            if record is None:
                return None, False
            kind = record[0]
            if kind == RecordKind.FRAME:
                msg = decode_frame(record, self._channel)
                self._copy(msg)
                return msg, False
            text = record[1:].decode("utf-8", "replace")
            if kind == RecordKind.FAILED:
                raise can.CanOperationError(text)
            self.peer_text = text

    def read_record(self, end: float | None) -> bytes | None:
        """The next record, waiting until ``end`` (``time.monotonic``; None: for ever);
        None when none came. Raises CanOperationError when the peer's end is closed."""
        sock = self._sock
        while True:
            try:
                record = sock.recv(_RECORD_MAX)
            except BlockingIOError:
                remaining = None if end is None else end - time.monotonic()
                if remaining is not None and remaining <= 0:
                    return None
                select.select([sock], [], [], remaining)
                continue
            except OSError as exc:
                raise can.CanOperationError(f"{self._gone()} ({exc.strerror or exc})") from exc
            if not record:
                raise can.CanOperationError(self._gone())
            return record

    def wait_readable(self) -> None:
        """Block until a record (or the end of the stream) can be read; nothing is read."""
        select.select([self._sock], [], [])

    def send_text(self, kind: RecordKind, text: str) -> None:
        """A READY or FAILED line to the peer (best effort: the peer may be gone)."""
        try:
            self._sock.send(text_record(kind, text))
        except OSError:
            pass

    def _copy(self, msg: can.Message) -> None:
        if self._mirror is not None:
            try:
                self._mirror.send(msg)
            except can.CanError:   # an observer's copy: never the run's problem
                pass

    def shutdown(self) -> None:
        if self._is_shutdown:
            return
        super().shutdown()
        self._sock.close()
