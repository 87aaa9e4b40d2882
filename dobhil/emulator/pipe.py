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
stamp at reception), a line of text from the peer (its failure, or that it is
ready), or a periodic send's start, change or stop. An empty read means the peer's end
is closed: the process is gone.

Periodic send (python-can's ``send_periodic``) on the host's end with a ticking peer
(``periodic_peer``, the emulator process): the task goes to the peer as a record, and
the peer sends the frames on its own clock -- outside the host's interpreter, as the
kernel's broadcast manager does on SocketCAN (:func:`dobhil.drives.periodic.native_periodic`
says so). The peer keeps its tasks in a :class:`PeriodicTable` and asks it, at the start of
each of its ticks, which frames are due; it echoes each to the host (as SocketCAN loops
broadcast-manager frames back to the other sockets) and hands it to the emulated drive.
"""

from __future__ import annotations

import math
import select
import socket
import struct
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from enum import IntEnum
from typing import Any

import can
from can.broadcastmanager import (CyclicSendTaskABC, LimitedDurationCyclicSendTaskABC,
                                  ModifiableCyclicTaskABC, RestartableCyclicTaskABC)

__all__ = ["PeriodicTable", "PipeBus", "PipePeriodicTask", "RecordKind", "socket_pair"]

#: kind, stamp [s since the epoch], arbitration id, flags, DLC (then the data bytes)
_FRAME = struct.Struct("<BdIBB")
#: the longest line of text a record carries
_TEXT_MAX = _FRAME.size + 64
#: kind, task id, period [s], duration [s] (NaN: none), frame count (then per frame: its
#: record's length in one byte and the record)
_PERIODIC = struct.Struct("<BIddB")
#: kind, task id
_PERIODIC_STOP = struct.Struct("<BI")
#: frames one periodic task may cycle through (python-can sends them one per period)
PERIODIC_FRAMES_MAX = 16
_RECORD_MAX = _PERIODIC.size + PERIODIC_FRAMES_MAX * (1 + _TEXT_MAX)
#: the longest a send waits for room when no timeout is given [s]
SEND_WAIT_MAX = 0.05


class RecordKind(IntEnum):
    FRAME = 0
    READY = 1    # the peer is set up (text: what it is)
    FAILED = 2   # the peer failed (text: why, one line); it exits next
    PERIODIC_START = 3    # the peer sends these frames every period from now on
    PERIODIC_MODIFY = 4   # ... these frames instead, keeping its timing
    PERIODIC_STOP = 5     # ... no more


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


_PERIODIC_KINDS = frozenset({RecordKind.PERIODIC_START, RecordKind.PERIODIC_MODIFY, RecordKind.PERIODIC_STOP})


def text_record(kind: RecordKind, text: str) -> bytes:
    return bytes([kind]) + " ".join(text.split()).encode("utf-8", "replace")[:_TEXT_MAX - 1]


def periodic_record(kind: RecordKind, task_id: int, messages: Sequence[can.Message] = (),
                    period: float = math.nan, duration: float | None = None) -> bytes:
    """A periodic task's start or change (its frames, period, duration) or stop."""
    if kind == RecordKind.PERIODIC_STOP:
        return _PERIODIC_STOP.pack(kind, task_id)
    frames = [encode_frame(msg) for msg in messages]
    return (_PERIODIC.pack(kind, task_id, period, math.nan if duration is None else duration, len(frames))
            + b"".join(bytes([len(f)]) + f for f in frames))


@dataclass
class _PeerTask:
    frames: tuple[can.Message, ...]
    period: float
    start: float           # peer clock [s] when it started
    end: float             # the last instant a frame may go out (inf: none)
    sent: int = 0          # frames sent so far: the next is due at start + (sent + 1) * period


class PeriodicTable:
    """The peer's side of periodic send: the tasks the host started, and which frames
    are due at an instant of the peer's clock (``clock``, set by the peer: its drive's
    time; a task started now sends its first frame one period from now).

    Frame ``k`` (k = 1, 2, ...) of a task is due at ``start + k * period`` (no sum of
    periods, no drift) and goes out at the first :meth:`due` at or after it: exact
    when the period is a whole number of the peer's ticks, else up to a tick late."""

    def __init__(self, clock: Callable[[], float] = lambda: 0.0) -> None:
        self.clock = clock
        self._tasks: dict[int, _PeerTask] = {}

    def __len__(self) -> int:
        return len(self._tasks)

    def record(self, record: bytes, channel: Any = None) -> None:
        """Apply a PERIODIC_* record from the host."""
        kind = record[0]
        if kind == RecordKind.PERIODIC_STOP:
            self._tasks.pop(_PERIODIC_STOP.unpack_from(record)[1], None)
            return
        _, task_id, period, duration, count = _PERIODIC.unpack_from(record)
        frames, at = [], _PERIODIC.size
        for _ in range(count):
            size = record[at]
            frames.append(decode_frame(record[at + 1:at + 1 + size], channel))
            at += 1 + size
        if not (frames and math.isfinite(period) and period > 0):
            return   # the host's end checked these: nothing to send
        task = self._tasks.get(task_id)
        if kind == RecordKind.PERIODIC_MODIFY and task is not None:
            task.frames = tuple(frames)
            return
        now = self.clock()
        end = now + duration if math.isfinite(duration) else math.inf
        self._tasks[task_id] = _PeerTask(tuple(frames), period, now, end)

    def due(self, now: float) -> list[can.Message]:
        """The frames due by ``now`` (peer clock), in task order; ended tasks are dropped."""
        if not self._tasks:
            return []
        out: list[can.Message] = []
        for task_id in sorted(self._tasks):
            task = self._tasks[task_id]
            slack = 1e-6 * task.period   # the peer's clock is a sum of ticks: rounding
            while True:
                at = task.start + (task.sent + 1) * task.period
                if at > now + slack:
                    break
                if at > task.end + slack:
                    del self._tasks[task_id]
                    break
                out.append(task.frames[task.sent % len(task.frames)])
                task.sent += 1
        return out


class PipePeriodicTask(LimitedDurationCyclicSendTaskABC, ModifiableCyclicTaskABC, RestartableCyclicTaskABC):
    """A periodic send the host's :class:`PipeBus` handed to its peer (python-can's task
    interface): :meth:`start` (again) from now, :meth:`stop`, :meth:`modify_data`."""

    def __init__(self, bus: PipeBus, task_id: int, messages: Sequence[can.Message] | can.Message,
                 period: float, duration: float | None = None, autostart: bool = True) -> None:
        super().__init__(messages, period, duration)
        if len(self.messages) > PERIODIC_FRAMES_MAX:
            raise ValueError(f"send_periodic: at most {PERIODIC_FRAMES_MAX} frames per task, "
                             f"got {len(self.messages)}")
        self._bus = bus
        self.task_id = task_id
        if autostart:
            self.start()

    def start(self) -> None:
        self._bus.send_record(periodic_record(RecordKind.PERIODIC_START, self.task_id, self.messages,
                                              self.period, self.duration))

    def modify_data(self, messages: Sequence[can.Message] | can.Message) -> None:
        super().modify_data(messages)
        self._bus.send_record(periodic_record(RecordKind.PERIODIC_MODIFY, self.task_id, self.messages,
                                              self.period, self.duration))

    def stop(self) -> None:
        """Best effort: a peer that is gone sends nothing anyway."""
        try:
            self._bus.send_record(periodic_record(RecordKind.PERIODIC_STOP, self.task_id))
        except can.CanError:
            pass


class PipeBus(can.BusABC):
    """One end of a :func:`socket_pair` as a python-can bus.

    ``gone``: the text of the error raised when the peer's end is closed (called then, so
    it can name the peer's exit code). ``mirror``: a bus (a ``virtual`` one) that gets a
    copy of every frame sent or received, so in-process observers keep seeing the traffic.
    ``send_wait``: how long a send without a timeout waits for room. ``coalesce`` (the
    drive's end): a frame that finds the buffer full is not lost but held, the newest
    per arbitration id (as a CAN controller's transmit mailbox holds one frame per
    message), and goes out first once the reader has made room -- a host that stalled
    then reads the drive's newest status and feedback frames, not only the oldest frames of
    its stall; ``replaced`` counts the frames a newer one of the same id superseded.
    ``periodic_peer`` (the host's end of an emulator process): the peer sends periodic
    frames itself (:attr:`native_periodic`); otherwise python-can's thread does, here.
    ``serve_periodic`` (the peer's end): keep the tasks the host starts in
    :attr:`periodic` (a :class:`PeriodicTable`), for the peer to send.
    The socket is owned: :meth:`shutdown` closes it (the peer then reads the end).
    """

    #: send_periodic runs outside this process (dobhil.drives.periodic): the peer sends
    native_periodic: bool

    def __init__(self, sock: socket.socket, channel: Any = None, *,
                 gone: Callable[[], str] = lambda: "the other end of the bus is closed",
                 mirror: can.BusABC | None = None, receive_own_messages: bool = False,
                 send_wait: float = SEND_WAIT_MAX, coalesce: bool = False,
                 periodic_peer: bool = False, serve_periodic: bool = False, **kwargs: Any) -> None:
        self.native_periodic = periodic_peer
        self.periodic = PeriodicTable() if serve_periodic else None
        self._next_task = 0
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
        # the records carry the FD and BRS flags and up to 64 data bytes: a CAN FD link
        self._can_protocol = can.CanProtocol.CAN_FD

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
        self.send_record(record, timeout)
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
            if kind in _PERIODIC_KINDS:
                if self.periodic is not None:
                    self.periodic.record(record, self._channel)
                continue
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

    def send_record(self, record: bytes, timeout: float | None = None) -> None:
        """A record to the peer (a frame's, or a periodic task's), waiting at most
        ``timeout`` s for room (None: ``send_wait``); CanOperationError when it cannot go."""
        end = time.monotonic() + (self._send_wait if timeout is None else timeout)
        while True:
            try:
                self._sock.send(record)
                return
            except BlockingIOError:
                # the peer is not reading (stopped, or starved): never wait longer than asked
                remaining = end - time.monotonic()
                if remaining <= 0:
                    raise can.CanOperationError("pipe bus: the receiving end is not reading "
                                                "(its buffer is full)") from None
                select.select([], [self._sock], [], remaining)
            except OSError as exc:
                raise can.CanOperationError(f"{self._gone()} ({exc.strerror or exc})") from exc

    def _send_periodic_internal(
        self, msgs: Sequence[can.Message] | can.Message, period: float, duration: float | None = None,
        autostart: bool = True, modifier_callback: Callable[[can.Message], None] | None = None,
    ) -> CyclicSendTaskABC:
        """The peer sends it (``periodic_peer``); python-can's thread does otherwise, and
        for a ``modifier_callback`` (it runs in this process: SocketCAN falls back so too)."""
        if not self.native_periodic or modifier_callback is not None:
            return super()._send_periodic_internal(msgs, period, duration, autostart, modifier_callback)
        if not (math.isfinite(period) and period > 0):
            raise ValueError(f"send_periodic period {period!r}: expected a finite number of seconds > 0")
        if duration is not None and not duration >= 0:
            raise ValueError(f"send_periodic duration {duration!r}: expected a number of seconds >= 0")
        self._next_task += 1
        return PipePeriodicTask(self, self._next_task, msgs, period, duration, autostart)

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
