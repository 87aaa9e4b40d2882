"""The writer process of run logging: batches of raw records in through a pipe, one MCAP file out.

Why a process: encoding ~7 JSON messages per control cycle, chunking and compressing
them costs about as much as the control cycle itself. In a thread that work holds the
GIL the control loop needs, so in lockstep the two costs add up and in real time it
delays cycles. In its own interpreter it runs on another core and the loop thread only
appends tuples and, every batch, pays one ``marshal.dumps`` and one pipe write
(:class:`~dobhil.recording.writerproc.WriterProcess`, the parent side).

The process is a fresh interpreter (``python -S -E -c``, see
:mod:`~dobhil.recording.writerproc`), never a fork of the possibly threaded parent; it
imports only this module, :mod:`~dobhil.recording.filewriter` and what they need (no
python-can, no numpy), to be ready soon after the log is opened. It inherits three file
descriptors: the read end of the data pipe, the write end of the status pipe and the
log file, which the parent created (so a bad path fails in the parent, at once).

Wire format: :mod:`multiprocessing.connection` framing (a ``!i`` byte count, then the
bytes; ``-1`` and a ``!Q`` count for more than 2 GiB), so the parent sends with
``Connection.send_bytes``. Each message is :mod:`marshal` data:

- a ``list`` of raw records (:mod:`~dobhil.recording.fastlog`): encoded and written;
- a :class:`Control` tuple: ``OPEN`` first (metadata, attachments, mode, flushing),
  ``LOSS`` after records the parent dropped (real time), ``STOP`` last.

The process ignores SIGINT and SIGTERM (a Ctrl-C reaches the whole process group; the
parent handles it and closes the log). It ends the chunk, flushes and fsyncs the file
every ``flush_interval``. On ``STOP`` it writes the stop event and the summary; on end
of file (the parent died without closing, e.g. SIGKILL) it writes everything already
in the pipe and finishes the file with ``stop_reason`` :data:`PARENT_EXITED`. Then it
writes one :class:`Status` message and exits. A failure (disk full, ...) becomes a
one-line ``FAILED`` status; the parent raises it as :class:`~dobhil.errors.LogFileError`.
"""

from __future__ import annotations

import marshal
import os
import select
import signal
import stat
import struct
import sys
import time
from collections.abc import Sequence
from enum import IntEnum
from typing import Any, BinaryIO, Final

from dobhil.recording.filewriter import LogFileWriter, RecordMode


class Control(IntEnum):
    """First element of a control message (a tuple; record batches are lists)."""

    OPEN = 100  # (OPEN, mode, flush_interval, fsync, metadata, attachments)
    LOSS = 101  # (LOSS, log_time_ns, count, total): records the parent dropped (LOSSY)
    STOP = 102  # (STOP, stop_reason | None, detail, dropped_total)


class Status(IntEnum):
    """First element of the one message the writer process sends back."""

    DONE = 0  # (DONE, written, dropped)
    FAILED = 1  # (FAILED, one-line reason)


#: ``stop_reason`` of a file finished because the parent went away without closing it.
PARENT_EXITED: Final = "parent exited"
_HEADER: Final = struct.Struct("!i")
_BIG: Final = struct.Struct("!Q")
_READ_SIZE: Final = 1 << 20


class FrameReader:
    """Messages framed as :mod:`multiprocessing.connection` frames them, read from a pipe.

    One ``os.read`` takes everything the pipe holds (up to 1 MiB), so a backlog of
    batches costs one system call, not two per message.
    """

    def __init__(self, fd: int) -> None:
        self._fd = fd
        self._buf = bytearray()
        self._eof = False
        self._poll = select.poll()
        self._poll.register(fd, select.POLLIN)

    def read(self, timeout: float) -> list[bytes]:
        """The complete messages available, waiting at most ``timeout`` s for the first;
        EOFError once the writer end is closed and nothing is left."""
        out = self._split()
        if out:
            return out
        if self._eof:
            raise EOFError
        if not self._poll.poll(max(0, int(timeout * 1000))):
            return []
        chunk = os.read(self._fd, _READ_SIZE)
        if not chunk:
            self._eof = True
            if self._buf:
                raise EOFError  # a partial message: the writer died mid-send
        self._buf += chunk
        return self._split() if chunk else self.read(0)

    def _split(self) -> list[bytes]:
        buf, pos, out = self._buf, 0, []
        while len(buf) - pos >= _HEADER.size:
            (n,) = _HEADER.unpack_from(buf, pos)
            start = pos + _HEADER.size
            if n == -1:
                if len(buf) - start < _BIG.size:
                    break
                (n,) = _BIG.unpack_from(buf, start)
                start += _BIG.size
            if len(buf) - start < n:
                break
            out.append(bytes(buf[start:start + n]))
            pos = start + n
        if pos:
            del buf[:pos]
        return out


class _Writer:
    """The writer process's state: the reader, the file, and (once opened) the MCAP writer."""

    def __init__(self, reader: FrameReader, file: BinaryIO, path: str) -> None:
        self.reader = reader
        self.file = file
        self.path = path
        self.log: LogFileWriter | None = None
        self.interval = 1.0

    def serve(self) -> tuple[int, ...]:
        """Run until STOP or end of file; the :class:`Status` message to send back."""
        messages = self._open()
        if messages is None:
            self._discard()
            return (int(Status.DONE), 0, 0)
        log = self.log
        assert log is not None
        next_flush = time.monotonic() + self.interval
        while True:
            for data in messages:
                stop = self._handle(marshal.loads(data))
                if stop is not None:
                    self._finish(*stop)
                    return (int(Status.DONE), log.written, log.dropped)
                if time.monotonic() >= next_flush:  # a long backlog still flushes every interval
                    log.flush()
                    next_flush = time.monotonic() + self.interval
            if time.monotonic() >= next_flush:
                log.flush()
                next_flush = time.monotonic() + self.interval
            try:
                messages = self.reader.read(max(0.0, next_flush - time.monotonic()))
            except EOFError:
                self._finish(PARENT_EXITED, "the recording process ended without closing the log", log.dropped)
                return (int(Status.DONE), log.written, log.dropped)

    def _open(self) -> list[bytes] | None:
        """Wait for OPEN and write the header; the messages read after it, None if the log
        was closed before OPEN (the run never started)."""
        messages: list[bytes] = []
        while not messages:
            try:
                messages = self.reader.read(3600.0)
            except EOFError:
                return None
        first = marshal.loads(messages[0])
        if first[0] != Control.OPEN:
            return None
        _, mode, self.interval, fsync, metadata, attachments = first
        self.log = LogFileWriter(self.file, metadata=metadata, attachments=attachments,
                                 mode=RecordMode(mode), fsync=fsync)
        return messages[1:]

    def _handle(self, message: Any) -> tuple[str | None, str, int] | None:
        """Write a batch or apply a control message; the STOP arguments when it is one."""
        log = self.log
        assert log is not None
        if type(message) is list:
            log.write_records(message)
            return None
        kind = message[0]
        if kind == Control.LOSS:
            _, t, count, total = message
            log.loss(count, total, t)
            return None
        if kind == Control.STOP:
            _, reason, detail, dropped = message
            return reason, detail, dropped
        raise ValueError(f"unexpected control message {kind!r}")

    def _finish(self, reason: str | None, detail: str, dropped: int) -> None:
        log = self.log
        assert log is not None
        log.dropped = dropped
        if reason is not None:
            log.stop_event(reason, detail, log.last_log_ns or time.time_ns())
        log.finish(reason)

    def _discard(self) -> None:
        """Closed before OPEN (the run never started): remove the empty file the parent created."""
        st = os.fstat(self.file.fileno())
        self.file.close()
        try:
            same = os.stat(self.path)
        except OSError:
            return
        if stat.S_ISREG(st.st_mode) and st.st_size == 0 and (same.st_dev, same.st_ino) == (st.st_dev, st.st_ino):
            os.unlink(self.path)


def _ignore_signals() -> None:
    """SIGINT/SIGTERM are the parent's to handle; they were blocked from before the exec
    (see ``WriterProcess``), so ignoring them first and unblocking second loses no race."""
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, signal.SIG_IGN)
    if hasattr(signal, "pthread_sigmask"):
        signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT, signal.SIGTERM})


def _send_status(fd: int, status: Sequence[Any]) -> None:
    data = marshal.dumps(tuple(status))
    try:
        os.write(fd, _HEADER.pack(len(data)) + data)
    except OSError:
        pass  # the parent is gone; nobody to tell


def _one_line(exc: BaseException) -> str:
    text = " ".join(str(exc).split()) or type(exc).__name__
    return f"{type(exc).__name__}: {text}"


def main(argv: Sequence[str]) -> None:
    """Entry point: ``DATA_FD STATUS_FD FILE_FD PATH``; never returns (``os._exit``: the
    file is closed and nothing else needs tearing down, which keeps ``close()`` short)."""
    _ignore_signals()
    data_fd, status_fd, file_fd = (int(a) for a in argv[:3])
    file = os.fdopen(file_fd, "wb")
    code = 0
    try:
        status: tuple[Any, ...] = _Writer(FrameReader(data_fd), file, argv[3]).serve()
    except BaseException as exc:
        status, code = (int(Status.FAILED), _one_line(exc)), 1
        try:
            file.close()
        except OSError:
            pass
    _send_status(status_fd, status)
    sys.stderr.flush()
    os._exit(code)


__all__ = ["PARENT_EXITED", "Control", "FrameReader", "Status", "main"]
