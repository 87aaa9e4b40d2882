"""The writer process of a recorded run: batches of records in through a pipe, one MCAP file out.

A process, not a thread: encoding and writing ~7 messages per cycle would hold the GIL the
loop needs. The loop thread puts a batch (a list) on a bounded queue (at most
:data:`QUEUE_BATCHES`); a sender thread prepares it (``prepare``: flattening references),
``marshal``-s it and writes it to a pipe. ``BACKPRESSURE`` waits for room; ``LOSSY`` drops
and counts (events kept for the next batch; the running drop total rides on every batch,
and the child writes each increase as ``/events`` ``kind=loss``). The child is a fresh
interpreter (``subprocess``: no fork of a threaded parent), ignores SIGINT/SIGTERM (blocked
before the exec), flushes and fsyncs every ``flush_interval``, finishes the file on
``STOP`` or, if the parent died, on end of file (:data:`PARENT_EXITED`), and reports one
status. A failure (disk full) is raised as :class:`~dobhil.errors.RecorderError` at the
next hand-over.
"""

from __future__ import annotations

import marshal
import os
import queue
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from enum import IntEnum
from multiprocessing import Pipe
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any, Final

import dobhil
from dobhil.errors import RecorderError
from dobhil.recording.schemas import Topic, message_count
from dobhil.recording.writer import LogWriter, RecordMode

#: Batches that may wait in the parent (bounded memory: ~256 records each).
QUEUE_BATCHES: Final = 64
#: Records the sender flattens and sends at a time (~50 us of GIL).
SLICE: Final = 32
#: Seconds ``close`` waits for the writer process to finish the file.
JOIN_TIMEOUT: Final = 60.0
#: ``stop_reason`` of a file finished because the parent went away without closing it.
PARENT_EXITED: Final = "parent exited"
_EVENTS: Final = int(Topic.EVENTS)
_BOOT: Final = "import sys; sys.path.insert(0, sys.argv[1]); from dobhil.recording.process import main; main()"
Records = list[tuple[Any, ...]]


class Control(IntEnum):
    """First element of a message to the child; ``dropped`` is the running total of
    messages the parent dropped, ``at`` the log time of the last one."""

    OPEN = 100  # (OPEN, mode, flush_interval, fsync, metadata, attachments, live)
    BATCH = 101  # (BATCH, dropped, at, records)
    STOP = 102  # (STOP, dropped, at, stop_reason | None, detail)


class Status(IntEnum):
    DONE = 0  # (DONE, written, dropped)
    FAILED = 1  # (FAILED, one-line reason)
    READY = 2  # (READY, live view port | None): the file is open (and the live view listens)


class WriterProcess:
    """A writer process recording to ``path``; the file is created here (a bad path raises)."""

    def __init__(self, path: str | os.PathLike[str], *, flush_interval: float = 1.0, fsync: bool = True,
                 prepare: Callable[[Records], Records] = list) -> None:
        self.path = Path(path)
        self.mode = RecordMode.BACKPRESSURE
        self.dropped = self.written = 0
        self.live_port: int | None = None
        self._prepare, self._interval, self._fsync = prepare, flush_interval, fsync
        self._loss = (0, 0)  # (dropped, log time of the last dropped): one object, read by the sender
        self._carry: Records = []
        self._failure: str | None = None
        self._closed = False
        self._queue: queue.Queue[bytes | Records | None] = queue.Queue(QUEUE_BATCHES)
        with open(self.path, "xb"):  # the caller checked the path: this only fails on a race
            pass
        self._proc, self._conn, self._status = _spawn(self.path)
        self._sender = threading.Thread(target=self._send_all, name="dobhil-log-sender", daemon=True)
        self._sender.start()

    @property
    def pid(self) -> int:
        return self._proc.pid

    def open(self, metadata: Mapping[str, Mapping[str, Any]], attachments: Sequence[tuple[str, str, bytes]],
             mode: RecordMode, live: tuple[str, int] | None = None) -> None:
        """Header, metadata, attachments, the mode, and the live view's address (if any)."""
        self.mode = RecordMode(mode)
        meta = {str(n): {str(k): str(v) for k, v in r.items()} for n, r in metadata.items()}
        files = [(str(n), str(m), bytes(d)) for n, m, d in attachments]
        self._put(marshal.dumps((int(Control.OPEN), int(self.mode), self._interval, self._fsync, meta, files,
                                 live)), force=True)
        self.live_port = self._wait_ready()

    def _wait_ready(self) -> int | None:
        """Wait until the writer has started (imports, file, live view: all before the run, so
        its start-up never competes with the loop: measured, it caused most of the overruns a
        logged real-time run had more than an unlogged one); the live view's port, if any."""
        message = marshal.loads(self._status.recv_bytes()) if self._status.poll(JOIN_TIMEOUT) else None
        if message is not None and message[0] == Status.READY:
            return message[1]
        self._closed = True
        self._join()
        self._failure = str(message[1]) if message is not None else "the writer process did not start"
        raise RecorderError(f"{self.path}: {self._failure}")

    def send(self, records: Records, *, force: bool = False) -> bool:
        """Hand a batch over; False if dropped (LOSSY and the writer lags; never with ``force``).
        Raises :class:`RecorderError` once the writer has failed."""
        self._raise_failure()
        if self._carry:
            records, self._carry = self._carry + records, []
        if not records or self._put(records, force=force):
            return True
        self._raise_failure()
        records = self._prepare(records)
        self._carry = [r for r in records if r[0] == _EVENTS]  # events are never dropped
        self.dropped += sum(message_count(r) for r in records if r[0] != _EVENTS)
        self._loss = (self.dropped, records[-1][1])
        return False

    def close(self, stop_reason: str | None = None, detail: str = "") -> None:
        """Stop event (if a reason is given), summary, footer; waits for the process.
        Raises :class:`RecorderError` if the writer failed. Idempotent."""
        if not self._closed:
            self._closed = True
            if self._carry:
                self.send([], force=True)
            self._put(marshal.dumps((int(Control.STOP), *self._loss, stop_reason, detail)), force=True)
            self._join()
        self._raise_failure()

    def abandon(self) -> None:
        """Close without a run (nothing was opened): the empty file is removed."""
        self._closed = True
        self._join()
        if self.path.exists() and self.path.stat().st_size == 0:
            self.path.unlink()

    # -- internals ---------------------------------------------------------------

    def _raise_failure(self) -> None:
        if self._failure is not None:
            raise RecorderError(f"{self.path}: recorder failed: {self._failure}")

    def _put(self, item: bytes | Records, *, force: bool) -> bool:
        if self.mode is RecordMode.LOSSY and not force:
            try:
                self._queue.put_nowait(item)
            except queue.Full:
                return False
            return True
        while self._failure is None:
            try:
                self._queue.put(item, timeout=0.2)
                return True
            except queue.Full:
                continue
        return False

    def _send_all(self) -> None:
        """The sender thread: queue to pipe until the sentinel, a broken pipe or a record it
        cannot encode (the writer is then told to stop: the file stays readable). A batch
        goes over in slices of :data:`SLICE` records: the GIL is released (``send_bytes``)
        between two, so a waking loop thread waits for one slice at most, never a batch."""
        while (item := self._queue.get()) is not None:
            for i in range(0, len(item), SLICE) if not isinstance(item, bytes) else (0,):
                try:
                    data = item if isinstance(item, bytes) else _batch(self._loss, self._prepare(item[i:i + SLICE]))
                except Exception as exc:  # a bug, not the disk: still one line at the next hand-over
                    self._failure = f"cannot encode a record: {type(exc).__name__}: {exc}"
                    data = marshal.dumps((int(Control.STOP), *self._loss, "recorder_failed", self._failure))
                try:
                    self._conn.send_bytes(data)
                except OSError:
                    self._failure = self._ended_early()
                    return
                if self._failure is not None:
                    return

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
        while self._sender.is_alive():
            try:
                self._queue.put(None, timeout=0.2)
                break
            except queue.Full:
                continue
        self._sender.join()
        self._conn.close()
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


def _spawn(path: Path) -> tuple[subprocess.Popen[bytes], Connection, Connection]:
    data_r, data_w = Pipe(duplex=False)
    status_r, status_w = Pipe(duplex=False)
    fds = (data_r.fileno(), status_w.fileno())
    root = str(Path(dobhil.__file__).resolve().parent.parent)
    argv = [sys.executable, "-c", _BOOT, root, *map(str, fds), os.fspath(path)]
    try:
        with _signals_blocked():
            proc = subprocess.Popen(argv, pass_fds=fds, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL)
    except OSError as exc:
        path.unlink()
        raise RecorderError(f"{path}: cannot start the writer process: {exc}") from exc
    finally:
        data_r.close()
        status_w.close()
    return proc, data_w, status_r


@contextmanager
def _signals_blocked() -> Iterator[None]:
    """SIGINT/SIGTERM blocked in this thread; a child started meanwhile inherits the mask."""
    old = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT, signal.SIGTERM})
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)


def _batch(loss: tuple[int, int], records: Records) -> bytes:
    """The BATCH message; values marshal refuses (numpy ints, enums) made plain."""
    try:
        return marshal.dumps((int(Control.BATCH), *loss, records))
    except ValueError:
        return marshal.dumps((int(Control.BATCH), *loss, [tuple(map(_plain, r)) for r in records]))


def _plain(value: Any) -> Any:
    if isinstance(value, (bool, str, bytes)) or value is None:
        return value
    return int(value) if hasattr(value, "__index__") else float(value)


def _read_status(conn: Connection) -> Sequence[Any] | None:
    try:
        return marshal.loads(conn.recv_bytes()) if conn.poll(0) else None
    except (EOFError, OSError, ValueError):
        return None


# -- the child ---------------------------------------------------------------------------


def _serve(conn: Connection, status: Connection, path: str) -> tuple[Any, ...]:
    try:
        first = marshal.loads(conn.recv_bytes())
    except EOFError:
        return (int(Status.DONE), 0, 0)  # closed before a run started
    _, mode, interval, fsync, metadata, attachments, live = first
    log = LogWriter(open(path, "wb"), metadata=metadata, attachments=attachments, mode=RecordMode(mode),
                    fsync=fsync)
    try:
        port = None
        if live is not None:
            from dobhil.live import LiveServer  # optional extra [live]
            server = LiveServer(host=live[0], port=live[1])
            log.add_output(server)
            port = server.port
        status.send_bytes(marshal.dumps((int(Status.READY), port)))
        return _write_until_stop(conn, log, interval)
    except BaseException:
        log.close()
        raise


def _write_until_stop(conn: Connection, log: LogWriter, interval: float) -> tuple[Any, ...]:
    next_flush = time.monotonic() + interval
    while True:
        if conn.poll(max(0.0, next_flush - time.monotonic())):
            try:
                kind, dropped, at, *rest = marshal.loads(conn.recv_bytes())
            except EOFError:
                log.finish(PARENT_EXITED, "the recording process ended without closing the log")
                return (int(Status.DONE), log.written, log.dropped)
            if dropped > log.dropped:
                log.loss(dropped - log.dropped, dropped, at)
            if kind == Control.BATCH:
                log.write(rest[0])
            else:
                log.finish(*rest)
                return (int(Status.DONE), log.written, log.dropped)
        if time.monotonic() >= next_flush:
            log.flush()
            next_flush = time.monotonic() + interval


def main(argv: Sequence[str] | None = None) -> None:
    """``DATA_FD STATUS_FD PATH``: serve, send one status, exit."""
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, signal.SIG_IGN)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT, signal.SIGTERM})
    data_fd, status_fd, path = (argv or sys.argv[2:])[:3]
    status_conn = Connection(int(status_fd), readable=False)
    code = 0
    try:
        status = _serve(Connection(int(data_fd), writable=False), status_conn, path)
    except BaseException as exc:  # one line for the parent, whatever it was
        status, code = (int(Status.FAILED), f"{type(exc).__name__}: {' '.join(str(exc).split())}"), 1
    try:
        status_conn.send_bytes(marshal.dumps(status))
    except OSError:
        pass  # the parent is gone: nobody to tell
    sys.exit(code)


__all__ = ["JOIN_TIMEOUT", "PARENT_EXITED", "QUEUE_BATCHES", "WriterProcess", "main"]
