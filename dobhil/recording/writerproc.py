"""The parent side of run logging's writer process: raw record batches to a pipe.

:class:`WriterProcess` starts the writer process (:mod:`~dobhil.recording.writerchild`)
when it is created -- by :class:`~dobhil.recording.sink.RunLog`, before the session and
the loop -- and hands it batches of flat raw records (:mod:`~dobhil.recording.fastlog`).
The calling thread (the control loop) pays one ``marshal.dumps`` (plain tuples of
floats, ints and bytes: several times cheaper than pickle) and one
``Connection.send_bytes`` per batch; all encoding, MCAP writing, compression and
flushing happen in the other process, on another core, outside the GIL.

Modes (:class:`~dobhil.recording.filewriter.RecordMode`), set by :meth:`WriterProcess.open`:

- ``BACKPRESSURE`` (lockstep): ``send`` blocks while the pipe is full, so nothing is
  lost and at most the pipe's capacity (1 MiB where Linux allows, ~40 batches) is in
  flight.
- ``LOSSY`` (real time): ``send`` never blocks. A batch that does not fit in the pipe
  (``FIONREAD`` says how much is unread) is dropped and its messages counted; its
  ``/events`` records are kept for the next batch. The next batch sent is preceded by a
  ``LOSS`` message: the writer records an ``/events`` ``kind=loss`` with the count; the
  total is the summary's ``dropped``.

Start: a fresh interpreter (``sys.executable -S -E -c``) through :mod:`subprocess`, with
the parent's ``sys.path``; the spawn start method in effect. Not a fork: the parent may
have threads (the real-time emulator). Not :mod:`multiprocessing`'s own spawn either:
that re-imports the parent's ``__main__`` script in the child (e.g. ``tools/bench.py``
with numpy and the analysis), which would add a large, variable start-up time to every
run. SIGINT and SIGTERM are blocked around the start, so the child cannot be
interrupted before it ignores them. The child gets only its three descriptors; it ends
on ``STOP`` (:meth:`WriterProcess.close`, which always waits for it) or on end of file
when this process dies.
"""

from __future__ import annotations

import marshal
import os
import signal
import subprocess
import sys
from collections.abc import Iterable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from multiprocessing import Pipe
from multiprocessing.connection import Connection
from numbers import Integral, Real
from pathlib import Path
from typing import Any, BinaryIO, Final

import dobhil
from dobhil.errors import LogFileError
from dobhil.recording.fastlog import RawKind, messages_per_record
from dobhil.recording.filewriter import RecordMode
from dobhil.recording.writerchild import Control, Status

#: Pipe capacity asked for (Linux ``F_SETPIPE_SZ``; the default is 64 KiB).
PIPE_SIZE: Final = 1 << 20
#: LOSSY: room kept free in the pipe beyond the batch (frame header, partly used pages).
_SLACK: Final = 16 * 1024
#: Seconds ``close`` waits for the writer process to finish the file.
JOIN_TIMEOUT: Final = 60.0
_EVENT: Final = int(RawKind.EVENT)
_PLAIN: Final = (int, float, bool, str, bytes, type(None))
_BOOT: Final = ("import sys; sys.path[:] = sys.argv[1].split({sep!r}); "
                "from dobhil.recording.writerchild import main; main(sys.argv[2:])")


class WriterProcess:
    """A writer process recording to ``path`` (created here: a bad path raises at once)."""

    def __init__(self, path: str | os.PathLike[str], *, flush_interval: float = 1.0, fsync: bool = True) -> None:
        if flush_interval <= 0:
            raise LogFileError(f"flush_interval must be > 0, got {flush_interval}")
        self.path = Path(path)
        self.mode: RecordMode | None = None
        self.dropped = 0
        self.written = 0
        self._interval = flush_interval
        self._fsync = fsync
        self._reported = 0
        self._last_drop_ns = 0
        self._carry: list[tuple[Any, ...]] = []
        self._failure: str | None = None
        self._closed = False
        file = _create(self.path)
        try:
            self._proc, self._conn, self._status = _spawn(file, self.path)
        finally:
            file.close()
        self._capacity = _grow_pipe(self._conn.fileno())

    # -- the caller's side -------------------------------------------------------

    @property
    def pid(self) -> int:
        """Process id of the writer process."""
        return self._proc.pid

    def open(self, metadata: Mapping[str, Mapping[str, Any]], attachments: Iterable[tuple[str, str, bytes]],
             mode: RecordMode) -> None:
        """Header, metadata and attachments; the mode for what follows. Does not wait."""
        self.mode = RecordMode(mode)
        meta = {str(name): {str(k): str(v) for k, v in record.items()} for name, record in metadata.items()}
        files = [(str(n), str(m), bytes(d)) for n, m, d in attachments]
        self._send(marshal.dumps((int(Control.OPEN), int(self.mode), self._interval, self._fsync, meta, files)))

    def send(self, records: list[tuple[Any, ...]], *, force: bool = False) -> bool:
        """Hand a batch over; False if it was dropped (LOSSY, pipe full; never with ``force``)."""
        self._check()
        if self._carry:
            records, self._carry = self._carry + records, []
        if not records:
            return True
        data = _dumps(records)
        if self.mode is RecordMode.LOSSY and not force and not self._room(len(data)):
            self._drop(records)
            return False
        if self.dropped != self._reported:
            self._send_loss()
        self._send(data)
        return True

    def close(self, stop_reason: str | None = None, detail: str = "") -> None:
        """Stop event (if a reason is given), summary, footer; waits for the process.
        Raises :class:`LogFileError` if the writer failed. Idempotent."""
        if self._closed:
            self._raise_failure()
            return
        try:
            if self._failure is None:
                self._stop(stop_reason, detail)
        except LogFileError:
            pass  # the failure is raised below, after the process is joined
        finally:
            self._join()
        self._raise_failure()

    # -- internals -----------------------------------------------------------------

    def _stop(self, stop_reason: str | None, detail: str) -> None:
        if self.mode is not None:
            if self._carry:
                self.send([], force=True)
            if self.dropped != self._reported:
                self._send_loss()
        self._send(marshal.dumps((int(Control.STOP), stop_reason, detail, self.dropped)))

    def _room(self, size: int) -> bool:
        """Whether ``size`` bytes surely fit in the pipe now, so the write cannot block.

        The pipe holds pages, not bytes: a write leaves at most its last page partly
        used, so unread bytes can occupy up to twice their size (for writes of at
        least a page; smaller ones fill the last page). Hence the factor 2."""
        return 2 * _unread(self._conn.fileno()) + size + _SLACK <= self._capacity

    def _drop(self, records: list[tuple[Any, ...]]) -> None:
        """Count a dropped batch's messages; keep its events (never dropped) for the next one."""
        self._carry = [r for r in records if r[0] == _EVENT]
        self.dropped += sum(messages_per_record(r) for r in records if r[0] != _EVENT)
        self._last_drop_ns = records[-1][1]
        if self._proc.poll() is not None:  # not lagging but gone: say why
            self._fail()

    def _send_loss(self) -> None:
        count = self.dropped - self._reported
        self._reported = self.dropped
        self._send(marshal.dumps((int(Control.LOSS), self._last_drop_ns, count, self.dropped)))

    def _send(self, data: bytes) -> None:
        try:
            self._conn.send_bytes(data)
        except OSError:  # BrokenPipeError: the writer process is gone
            self._fail()

    def _check(self) -> None:
        if self._failure is not None:
            self._raise_failure()
        if self._closed:
            raise LogFileError(f"{self.path}: recorder is closed")

    def _fail(self) -> None:
        """The writer process ended early: collect its reason and raise it."""
        self._join()
        if self._failure is None:
            self._failure = "writer process ended early"
        self._raise_failure()

    def _join(self) -> None:
        """Close our end of the data pipe, wait for the process, read its status (once)."""
        if self._closed:
            return
        self._closed = True
        self._conn.close()
        try:
            code = self._proc.wait(JOIN_TIMEOUT)
        except subprocess.TimeoutExpired:
            self._proc.kill()
            code = self._proc.wait()
            self._failure = self._failure or f"writer process did not finish within {JOIN_TIMEOUT:g} s"
        status = _read_status(self._status)
        self._status.close()
        if status is not None and status[0] == Status.DONE:
            self.written = status[1]
        elif status is not None and self._failure is None:
            self._failure = str(status[1])
        elif self._failure is None:
            self._failure = f"writer process exited with code {code}"

    def _raise_failure(self) -> None:
        if self._failure is not None:
            raise LogFileError(f"{self.path}: recorder failed: {self._failure}")


def _create(path: Path) -> BinaryIO:
    try:
        return open(path, "wb")
    except OSError as exc:
        raise LogFileError(f"{path}: cannot create: {exc.strerror}") from exc


def _spawn(file: BinaryIO, path: Path) -> tuple[subprocess.Popen[bytes], Connection, Connection]:
    """Start the writer process with the read end of the data pipe, the write end of
    the status pipe and ``file``; our copies of its ends are closed."""
    data_r, data_w = Pipe(duplex=False)
    status_r, status_w = Pipe(duplex=False)
    fds = (data_r.fileno(), status_w.fileno(), file.fileno())
    argv = [sys.executable, "-S", "-E", "-c", _BOOT.format(sep=os.pathsep), os.pathsep.join(_child_path()),
            *map(str, fds), os.fspath(path)]
    try:
        with _signals_blocked():
            proc = subprocess.Popen(argv, pass_fds=fds, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL)
    except OSError as exc:
        for conn in (data_r, data_w, status_r, status_w):
            conn.close()
        raise LogFileError(f"{path}: cannot start the writer process: {exc}") from exc
    data_r.close()
    status_w.close()
    return proc, data_w, status_r


def _child_path() -> list[str]:
    """This ``sys.path``, the directory holding the ``dobhil`` package first (``-S``: no site)."""
    root = str(Path(dobhil.__file__).resolve().parent.parent)
    return [root, *(p for p in sys.path if p and p != root)]


@contextmanager
def _signals_blocked() -> Iterator[None]:
    """Block SIGINT/SIGTERM in this thread; a child started meanwhile inherits the mask."""
    if not hasattr(signal, "pthread_sigmask"):
        yield
        return
    old = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT, signal.SIGTERM})
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)


def _grow_pipe(fd: int) -> int:
    """Ask for a :data:`PIPE_SIZE` pipe; its capacity in bytes."""
    try:
        import fcntl
        try:
            return int(fcntl.fcntl(fd, fcntl.F_SETPIPE_SZ, PIPE_SIZE))
        except OSError:
            return int(fcntl.fcntl(fd, fcntl.F_GETPIPE_SZ))
    except (ImportError, AttributeError, OSError):
        return 1 << 16


def _unread(fd: int) -> int:
    """Bytes written to the pipe and not read yet."""
    try:
        import fcntl
        import termios
        buf = bytearray(4)
        fcntl.ioctl(fd, termios.FIONREAD, buf)
        return int.from_bytes(buf, sys.byteorder, signed=True)
    except (ImportError, OSError):
        return 0


def _dumps(records: list[tuple[Any, ...]]) -> bytes:
    """``marshal`` data of a batch; values marshal refuses (numpy ints, enums, ...)
    are converted to plain ones, at a cost paid only then."""
    try:
        return marshal.dumps(records)
    except ValueError:
        return marshal.dumps([tuple(_plain(v) for v in rec) for rec in records])


def _plain(value: Any) -> Any:
    if type(value) in _PLAIN:
        return value
    if isinstance(value, (bytes, bytearray, memoryview)):
        return bytes(value)
    if isinstance(value, Integral):
        return int(value)
    if isinstance(value, Real):
        return float(value)
    return str(value)


def _read_status(conn: Connection) -> Sequence[Any] | None:
    try:
        if conn.poll(0):
            return marshal.loads(conn.recv_bytes())
    except (EOFError, OSError, ValueError):
        return None
    return None


__all__ = ["JOIN_TIMEOUT", "PIPE_SIZE", "WriterProcess"]
