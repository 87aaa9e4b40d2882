"""The writer process of a recorded run, and the packed records it is handed through a pipe.

No thread of the loop's process touches the log. The loop thread packs each record with
``struct`` into a :class:`Batch` of at most ``PIPE_BUF`` bytes and writes a full one to
the pipe with one ``os.write`` after a cycle's command went out (~3 us: the writer polls,
so no write wakes it). A write of at most ``PIPE_BUF`` bytes is atomic: in real time
(``LOSSY``, a non-blocking pipe) a batch goes whole or is dropped and counted at once,
its non-frame records (events) kept for the next one, the running total carried over as
a loss record the child writes as ``/events`` ``kind=loss``; in lockstep
(``BACKPRESSURE``) the write waits. The kernel orders the bytes on any processor.
(The sender thread this replaces flattened and marshalled batches, holding the GIL the
loop thread then waited for.)

The child is a fresh interpreter (``subprocess``: no fork of a threaded parent), ignores
SIGINT/SIGTERM (blocked before the exec), unpacks, writes through :class:`LogWriter`,
flushes and fsyncs every ``flush_interval``, finishes the file on ``STOP`` or, if the
parent died, on end of file (:data:`PARENT_EXITED`), and reports one status. Its failure
(disk full) is a :class:`~dobhil.errors.RecorderError` at the loop's next cycle.
"""

from __future__ import annotations

import marshal
import os
import select
import signal
import struct
import subprocess
import sys
import time
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from enum import IntEnum
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any, Final

import dobhil
from dobhil.errors import RecorderError
from dobhil.recording.schemas import CYCLE, Topic, frame_flags, message_count
from dobhil.recording.writer import LogWriter, RecordMode

#: Seconds ``close`` waits for the writer process to finish the file.
JOIN_TIMEOUT: Final = 60.0
#: ``stop_reason`` of a file finished because the parent went away without closing it.
PARENT_EXITED: Final = "parent exited"
#: Bytes of pipe asked for (Linux, F_SETPIPE_SZ): ~4 s of a 1 kHz run before real time drops.
PIPE_SIZE: Final = 1 << 20
#: A batch is written by one ``os.write`` (atomic up to PIPE_BUF), a loss record included.
BATCH_BYTES: Final = select.PIPE_BUF - 64
#: Seconds the writer sleeps when the pipe is empty.
POLL: Final = 0.002
#: Characters kept of each text of a marshalled record (events): it must fit a batch.
TEXT_LIMIT: Final = 600
_CYCLE_ROOM: Final = 640  # left after a cycle for the next cycle's frames: no write inside a bus call
_BOOT: Final = "import sys; sys.path.insert(0, sys.argv[1]); from dobhil.recording.process import main; main()"


class Kind(IntEnum):
    """First byte of a packed record; the 4-byte length of the rest follows."""

    CYCLE = 1  # _CYCLE below
    CYCLE_TRUTH = 2  # _CYCLE_TRUTH
    RX = 3  # _FRAME, then the data
    TX = 4
    MARSHAL = 5  # a flat record of the topic table (events, ...) or a Control message: never dropped


class Control(IntEnum):
    """First element of a marshalled control message."""

    OPEN = 100  # (OPEN, mode, flush_interval, fsync, metadata, attachments, live)
    LOSS = 101  # (LOSS, dropped so far, log time of the last dropped)
    STOP = 102  # (STOP, stop_reason | None, detail)
    CHANNEL = 103  # (CHANNEL, number, name): the bus channel name of frames with that number


class Status(IntEnum):
    DONE = 0  # (DONE, written, dropped)
    FAILED = 1  # (FAILED, one-line reason)
    READY = 2  # (READY, live view port | None): the file is open (and the live view listens)


_HEAD: Final = struct.Struct("<BI")
# kind, length, log time, then schemas.CYCLE_FIELDS in order: cycle, position, velocity, seq,
# the 6 ControlOutput values, period error, exec time, overrun, axis state, axis error [, truth]
_CYCLE: Final = struct.Struct("<BIqqddq6dd d?qq")
_CYCLE_TRUTH: Final = struct.Struct(_CYCLE.format + "4d")
# kind, length, log time, arbitration id, flags, dlc, bus timestamp, channel number
_FRAME: Final = struct.Struct("<BIqIBBdB")
#: Messages a packed cycle or frame becomes (marshalled records are never dropped: not counted).
_MESSAGES: Final = {Kind.CYCLE: message_count((CYCLE,) + (0,) * 16), Kind.RX: 1, Kind.TX: 1,
                    Kind.CYCLE_TRUTH: message_count((CYCLE,) + (0,) * 20)}
_TOPIC: Final = {Kind.RX: int(Topic.CAN_RX), Kind.TX: int(Topic.CAN_TX)}


class Batch:
    """The loop side: records packed into one buffer, handed to ``writer`` when full.
    Until the writer is open, full batches wait in memory (:attr:`early`)."""

    def __init__(self, writer: WriterProcess) -> None:
        self.writer = writer
        self.buf = bytearray(BATCH_BYTES)
        self.pos = 0
        self.received: list[tuple[int, Any]] = []  # (log time, frame): packed after the command went out
        self.kept: list[bytes] = []  # the marshalled records in buf: carried over a dropped batch
        self.early: list[bytes] = []
        self._channels: dict[Any, int] = {}

    def cycle(self, t: int, k: int, fb: Any, out: Sequence[float], period_error: float, exec_time: float,
              overrun: bool, status: Any, truth: tuple[float, ...] | None) -> None:
        """A cycle record; a full batch is written now, after the command went out. The one
        place a writer failure is raised on the loop thread."""
        if self.received:
            self.pack_received()
        if self.pos > BATCH_BYTES - _CYCLE_TRUTH.size:
            self.flush()
        pos = self.pos
        s = _CYCLE if truth is None else _CYCLE_TRUTH
        try:
            s.pack_into(self.buf, pos, 1 if truth is None else 2, s.size - 5, t, k, fb.position, fb.velocity, fb.seq,
                        *out, period_error, exec_time, overrun, status.state, status.error_code, *(truth or ()))
        except (struct.error, TypeError) as exc:  # a bug, not the disk: one line, the loop stops
            raise self.writer.refuse(f"cannot encode a record: {type(exc).__name__}: {exc}") from None
        self.pos = pos = pos + s.size
        if pos > BATCH_BYTES - _CYCLE_ROOM:
            self.flush()

    def frame(self, kind: int, t: int, msg: Any) -> None:
        """A frame as it is now (a sender may refill a preallocated message later)."""
        data = msg.data or b""
        n = len(data)
        if n > 64:
            data, n = data[:64], 64
        if self.pos + 28 + n > BATCH_BYTES and not self._made_room():
            return
        try:
            channel = self._channels[msg.channel]
        except (KeyError, TypeError):
            channel = self._channel(msg.channel)
        pos = self.pos
        try:
            _FRAME.pack_into(self.buf, pos, kind, 23 + n, t, msg.arbitration_id & 0xFFFFFFFF, frame_flags(msg),
                             msg.dlc & 0xFF, msg.timestamp or 0.0, channel)
        except (struct.error, TypeError) as exc:  # never raised into a bus call: the next hand-over tells
            self.writer.refuse(f"cannot encode a CAN frame: {type(exc).__name__}: {exc}")
            return
        if n:
            self.buf[pos + 28:pos + 28 + n] = data
        self.pos = pos + 28 + n

    def receive(self, t: int, msg: Any) -> None:
        """A received frame: only a reference now (python-can hands out a new message per
        receive), packed by the next cycle, once its command is out."""
        self.received.append((t, msg))
        if len(self.received) > 64:  # no cycle for a while (enable, preflight)
            self.pack_received()

    def pack_received(self) -> None:
        received, self.received = self.received, []
        for t, msg in received:
            self.frame(Kind.RX, t, msg)

    def record(self, record: Sequence[Any]) -> None:
        """A flat record of the topic table (an event): after the frames received before it;
        never dropped."""
        if self.received:
            self.pack_received()
        data = _packed(record)
        self._keep(data if len(data) <= BATCH_BYTES // 4 else
                   _packed([v[:TEXT_LIMIT] if isinstance(v, str) else v for v in record]))

    def flush(self) -> None:
        """Hand the batch over; dropped (the writer lags), its kept records start the next."""
        view = memoryview(self.buf)[:self.pos]
        if not self.writer.opened:
            self.early.append(bytes(view))
        elif not self.writer.write(view):
            self.writer.count_dropped(*_dropped(bytes(view)))
            kept = b"".join(self.kept)
            if len(kept) > BATCH_BYTES // 2:  # a writer stuck for good: memory stays bounded
                self.writer.count_dropped(len(self.kept), 0)
                kept, self.kept = b"", []
                self._channels.clear()  # their names go again
            self.buf[:len(kept)] = kept
            self.pos = len(kept)
            return
        self.pos = 0
        self.kept.clear()

    def take(self) -> bytes:
        """Everything not yet handed over (early batches first); the batch is empty after."""
        self.pack_received()
        out = b"".join(self.early) + bytes(self.buf[:self.pos])
        self.early.clear()
        self.pos = 0
        self.kept.clear()
        return out

    def _channel(self, channel: Any) -> int:
        number = len(self._channels) % 256
        self._keep(_packed((Control.CHANNEL, number, "" if channel is None else str(channel)[:TEXT_LIMIT])))
        if channel.__hash__ is not None:
            self._channels[channel] = number
        return number

    def _keep(self, data: bytes) -> None:
        """A marshalled record, kept if its batch is dropped."""
        if self.pos + len(data) > BATCH_BYTES and not self._made_room():
            return
        self.buf[self.pos:self.pos + len(data)] = data
        self.pos += len(data)
        self.kept.append(data)

    def _made_room(self) -> bool:
        """Flush for a frame or an event: a failed writer is told by the next cycle (the loop
        stops ``recorder_failed``) or by the end, never from inside a bus call."""
        try:
            self.flush()
        except RecorderError:
            return False
        return True


def _dropped(data: bytes) -> tuple[int, int]:
    """(messages, log time of the last) of the cycles and frames in packed ``data``."""
    messages = last = pos = 0
    while pos < len(data):
        kind, size = _HEAD.unpack_from(data, pos)
        if kind != Kind.MARSHAL:
            messages += _MESSAGES[Kind(kind)]
            last = struct.unpack_from("<q", data, pos + 5)[0]
        pos += 5 + size
    return messages, last


class WriterProcess:
    """A writer process recording to ``path``; the file is created here (a bad path raises)."""

    def __init__(self, path: str | os.PathLike[str], *, flush_interval: float = 1.0, fsync: bool = True) -> None:
        self.path = Path(path)
        self.mode = RecordMode.BACKPRESSURE
        self.opened = False
        self.dropped = self.written = 0
        self.live_port: int | None = None
        self._interval, self._fsync = flush_interval, fsync
        self._loss = b""  # the loss record still to go over (it rides on the next batch)
        self._last_drop = 0
        self._failure: str | None = None
        self._closed = False
        with open(self.path, "xb"):  # the caller checked the path: this only fails on a race
            pass
        self._proc, self._fd, self._status = _spawn(self.path)

    @property
    def pid(self) -> int:
        return self._proc.pid

    def open(self, metadata: Mapping[str, Mapping[str, Any]], attachments: Sequence[tuple[str, str, bytes]],
             mode: RecordMode, live: tuple[str, int] | None = None, early: bytes = b"") -> None:
        """Header, metadata, attachments, the mode, the live view's address (if any), then the
        ``early`` records (packed before the log was open)."""
        self.mode = RecordMode(mode)
        meta = {str(n): {str(k): str(v) for k, v in r.items()} for n, r in metadata.items()}
        files = [(str(n), str(m), bytes(d)) for n, m, d in attachments]
        self._send(_packed((Control.OPEN, int(self.mode), self._interval, self._fsync, meta, files, live)) + early)
        self.live_port = self._wait_ready()
        os.set_blocking(self._fd, self.mode is not RecordMode.LOSSY)
        self.opened = True

    def write(self, data: bytes | memoryview) -> bool:
        """Hand packed records over; False if dropped (``LOSSY`` and the pipe full). Raises
        :class:`RecorderError` once the writer has failed."""
        if self._failure is not None:
            raise self._fail(self._failure)
        try:
            if self.mode is not RecordMode.LOSSY:
                _write_all(self._fd, self._loss + bytes(data) if self._loss else data)
            else:  # whole or nothing: at most PIPE_BUF bytes
                os.write(self._fd, self._loss + bytes(data) if self._loss else data)
        except BlockingIOError:
            return False
        except OSError:
            raise self._fail(self._ended_early()) from None
        self._loss = b""
        return True

    def count_dropped(self, messages: int, last_time: int) -> None:
        self.dropped += messages
        self._last_drop = max(self._last_drop, last_time)
        self._loss = _packed((Control.LOSS, self.dropped, self._last_drop))

    def close(self, stop_reason: str | None = None, detail: str = "", rest: bytes = b"") -> None:
        """The ``rest`` of the records, none dropped; stop event (if a reason is given),
        summary, footer; waits for the process. Raises :class:`RecorderError` if the writer
        failed. Idempotent."""
        if not self._closed:
            self._closed = True
            if self._failure is None:
                self._stop(rest + _packed((Control.STOP, stop_reason, detail)))
            self._join()
        if self._failure is not None:
            raise self._fail(self._failure)

    def abandon(self) -> None:
        """Close without a run (nothing was opened): the empty file is removed."""
        self._closed = True
        self._join()
        if self.path.exists() and self.path.stat().st_size == 0:
            self.path.unlink()

    def refuse(self, why: str) -> RecorderError:
        """A record that cannot be encoded (a bug, not the disk): the file is finished with
        stop reason ``recorder_failed``; this and every later hand-over raise."""
        if self._failure is None and self.opened:
            self._stop(_packed((Control.STOP, "recorder_failed", why)))
        return self._fail(why)

    # -- internals ---------------------------------------------------------------

    def _fail(self, why: str) -> RecorderError:
        self._failure = self._failure or why
        return RecorderError(f"{self.path}: recorder failed: {self._failure}")

    def _stop(self, data: bytes) -> None:
        try:
            os.set_blocking(self._fd, True)
            self._send(self._loss + data)
        except (RecorderError, OSError):
            pass  # the failure is noted; close raises it

    def _send(self, data: bytes) -> None:
        try:
            _write_all(self._fd, data)
        except OSError:
            raise self._fail(self._ended_early()) from None

    def _wait_ready(self) -> int | None:
        """Wait until the writer has started (imports, file, live view: all before the run, so
        its start-up never competes with the loop); the live view's port. RecorderError if not."""
        message = marshal.loads(self._status.recv_bytes()) if self._status.poll(JOIN_TIMEOUT) else None
        if message is not None and message[0] == Status.READY:
            return message[1]
        self._closed = True
        self._join()
        self._failure = str(message[1]) if message is not None else "the writer process did not start"
        raise RecorderError(f"{self.path}: {self._failure}")

    def _ended_early(self) -> str:
        try:
            self._proc.wait(JOIN_TIMEOUT)
        except subprocess.TimeoutExpired:
            self._proc.kill()
        status = _read_status(self._status)
        if status is not None and status[0] == Status.FAILED:
            return str(status[1])
        return f"writer process ended early (exit code {self._proc.poll()})"

    def _join(self) -> None:
        if self._fd >= 0:
            os.close(self._fd)
            self._fd = -1
        try:
            self._proc.wait(JOIN_TIMEOUT)
        except subprocess.TimeoutExpired:
            self._proc.kill()
            self._proc.wait()
            self._failure = self._failure or f"writer process did not finish within {JOIN_TIMEOUT:g} s"
        status = _read_status(self._status)
        self._status.close()
        if status is not None and status[0] == Status.DONE:
            self.written = status[1]
        elif self._failure is None:
            self._failure = str(status[1]) if status is not None else f"writer exit code {self._proc.returncode}"


def _packed(record: Sequence[Any]) -> bytes:
    """A MARSHAL record; values marshal refuses (numpy numbers, enums) made plain."""
    try:
        data = marshal.dumps(tuple(record))
    except ValueError:
        data = marshal.dumps(tuple(v if isinstance(v, (str, bytes, tuple, list, dict)) or v is None else
                                   int(v) if hasattr(v, "__index__") else float(v) for v in record))
    return _HEAD.pack(Kind.MARSHAL, len(data)) + data


def _write_all(fd: int, data: bytes | memoryview) -> None:
    view = memoryview(data)
    while view:
        view = view[os.write(fd, view):]


def _spawn(path: Path) -> tuple[subprocess.Popen[bytes], int, Connection]:
    data_r, data_w = os.pipe()
    status_r, status_w = os.pipe()
    try:
        import fcntl
        fcntl.fcntl(data_w, fcntl.F_SETPIPE_SZ, PIPE_SIZE)
    except (ImportError, AttributeError, OSError):
        pass  # not Linux, or above /proc/sys/fs/pipe-max-size: the default 64 KiB
    root = str(Path(dobhil.__file__).resolve().parent.parent)
    argv = [sys.executable, "-c", _BOOT, root, str(data_r), str(status_w), os.fspath(path)]
    try:
        with _signals_blocked():
            proc = subprocess.Popen(argv, pass_fds=(data_r, status_w), stdin=subprocess.DEVNULL,
                                    stdout=subprocess.DEVNULL)
    except OSError as exc:
        os.close(data_w)
        os.close(status_r)
        path.unlink()
        raise RecorderError(f"{path}: cannot start the writer process: {exc}") from exc
    finally:
        os.close(data_r)
        os.close(status_w)
    return proc, data_w, Connection(status_r, writable=False)


@contextmanager
def _signals_blocked() -> Iterator[None]:
    """SIGINT/SIGTERM blocked in this thread; a child started meanwhile inherits the mask."""
    old = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT, signal.SIGTERM})
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)


def _read_status(conn: Connection) -> Sequence[Any] | None:
    try:
        return marshal.loads(conn.recv_bytes()) if conn.poll(0) else None
    except (EOFError, OSError, ValueError):
        return None


# -- the child ---------------------------------------------------------------------------


def unpack(data: bytes, channels: dict[int, str] | None = None) -> tuple[list[tuple[Any, ...]], int]:
    """The flat records and control messages of the whole packed records in ``data``, and
    where the first incomplete one starts; ``channels`` (number -> name) is kept up to date."""
    out: list[tuple[Any, ...]] = []
    names = {} if channels is None else channels
    pos, end = 0, len(data)
    cycle, truth, frame, head = _CYCLE.unpack_from, _CYCLE_TRUTH.unpack_from, _FRAME.unpack_from, _HEAD.unpack_from
    while pos + 5 <= end:
        kind, size = head(data, pos)
        stop = pos + 5 + size
        if stop > end:
            break
        if kind == Kind.CYCLE:
            out.append((CYCLE, *cycle(data, pos)[2:]))
        elif kind == Kind.CYCLE_TRUTH:
            out.append((CYCLE, *truth(data, pos)[2:]))
        elif kind == Kind.MARSHAL:
            record = marshal.loads(data[pos + 5:stop])
            if record[0] == Control.CHANNEL:
                names[record[1]] = record[2]
            else:
                out.append(record)
        else:
            _, _, t, arb, flags, dlc, stamp, channel = frame(data, pos)
            out.append((_TOPIC[Kind(kind)], t, arb, flags, dlc, data[pos + 28:stop], stamp, names.get(channel, "")))
        pos = stop
    return out, pos


class _Child:
    """The writer process: the log once opened, written as the records come."""

    def __init__(self, path: str, status: Connection) -> None:
        self.path, self.status = path, status
        self.log: LogWriter | None = None
        self.interval = 1.0
        self.channels: dict[int, str] = {}

    def handle(self, records: list[tuple[Any, ...]]) -> bool:
        """Write the records, obeying control messages; True once stopped."""
        start = 0
        for i, r in enumerate(records):
            if r[0] < Control.OPEN:
                continue
            if start < i:
                self.opened.write(records[start:i])
            start = i + 1
            if r[0] == Control.OPEN:
                self.open(*r[1:])
            elif r[0] == Control.LOSS and r[1] > self.opened.dropped:
                self.opened.loss(r[1] - self.opened.dropped, r[1], r[2])
            elif r[0] == Control.STOP:
                self.opened.finish(r[1], r[2])
                return True
        if start < len(records):
            self.opened.write(records[start:])
        return False

    def open(self, mode: int, interval: float, fsync: bool, metadata: Any, attachments: Any, live: Any) -> None:
        self.interval = interval
        self.log = LogWriter(open(self.path, "wb"), metadata=metadata, attachments=attachments,
                             mode=RecordMode(mode), fsync=fsync)
        port = None
        if live is not None:
            from dobhil.live import LiveServer  # optional extra [live]
            server = LiveServer(host=live[0], port=live[1])
            self.log.add_output(server)
            port = server.port
        self.status.send_bytes(marshal.dumps((int(Status.READY), port)))

    @property
    def opened(self) -> LogWriter:
        if self.log is None:
            raise RecorderError("records before the log was opened")
        return self.log


def _serve(fd: int, status: Connection, path: str) -> tuple[Any, ...]:
    """Read (polling: no write of the loop's wakes this process), write, flush on time."""
    child, pending = _Child(path, status), b""
    os.set_blocking(fd, False)
    next_flush = time.monotonic() + child.interval
    try:
        while True:
            try:
                chunk = os.read(fd, PIPE_SIZE)
            except BlockingIOError:
                time.sleep(POLL)
            else:
                if not chunk:  # the parent went away without closing the log
                    if child.log is None:
                        return (int(Status.DONE), 0, 0)  # closed before a run started
                    child.log.finish(PARENT_EXITED, "the recording process ended without closing the log")
                    break
                records, used = unpack(pending + chunk, child.channels)
                pending = (pending + chunk)[used:]
                if child.handle(records):
                    break
            if child.log is not None and time.monotonic() >= next_flush:
                child.log.flush()
                next_flush = time.monotonic() + child.interval
    except BaseException:
        if child.log is not None:
            child.log.close()
        raise
    return (int(Status.DONE), child.opened.written, child.opened.dropped)


def main(argv: Sequence[str] | None = None) -> None:
    """``DATA_FD STATUS_FD PATH``: serve, send one status, exit."""
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, signal.SIG_IGN)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT, signal.SIGTERM})
    data_fd, status_fd, path = (argv or sys.argv[2:])[:3]
    status_conn = Connection(int(status_fd), readable=False)
    code = 0
    try:
        status = _serve(int(data_fd), status_conn, path)
    except BaseException as exc:  # one line for the parent, whatever it was
        status, code = (int(Status.FAILED), f"{type(exc).__name__}: {' '.join(str(exc).split())}"), 1
    try:
        status_conn.send_bytes(marshal.dumps(status))
    except OSError:
        pass  # the parent is gone: nobody to tell
    sys.exit(code)


__all__ = ["BATCH_BYTES", "JOIN_TIMEOUT", "PARENT_EXITED", "PIPE_SIZE", "Batch", "Kind", "WriterProcess", "main",
           "unpack"]
