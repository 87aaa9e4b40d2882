"""The writer process of a recorded run and the pipe to it (``docs/recording.md``: diagram,
guarantees). Batches arrive pickled, one ``os.write`` each: ``LOSSY`` never blocks (no room:
refused; taken in part: finished first), ``BACKPRESSURE`` waits -- in slices, so a stop
request ends the wait, and never for a writer still for ``STALL_TIMEOUT`` s (killed: a
recorder failure), as the log's end never does either. The process ignores the stop
signals (SIGINT, SIGTERM, SIGHUP, SIGQUIT), writes through :class:`LogWriter`, hands each chunk to the OS every
``write_interval`` and fsyncs every ``flush_interval``, finishes the file on ``STOP`` or
when the parent dies, and sends one status.
"""

from __future__ import annotations

import io
import os
import pickle
import select
import signal
import struct
import subprocess
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from enum import IntEnum
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any, Final, NamedTuple, cast

from dobhil import forkserver
from dobhil.errors import RecorderError, exception_line
from dobhil.recording.codes import ProtocolCodes
from dobhil.recording.encodings import DEFAULT_ENCODING, encoding as find_encoding
from dobhil.recording.packed import unpacked_batch
from dobhil.recording.layouts import DEFAULT_LAYOUT, LAYOUTS
from dobhil.recording.writer import Lane, LiveView, LogWriter, RecordMode

#: Seconds ``close`` waits for the writer process to finish the file, at most, however busy it is.
JOIN_TIMEOUT: Final = 60.0
#: Seconds the writer may show no sign of life -- nothing taken from its pipe, and (Linux,
#: ``/proc/PID/schedstat``) neither run nor waited for a CPU -- while a hand-over or the log's
#: end waits for it: then it is given up and killed (a stopped process, or one blocked on a
#: disk that no longer answers: an NFS mount gone, a dying USB stick). A healthy writer is
#: never that still: it reads the pipe every ``POLL`` between chunks; between two reads it
#: encodes at most the pipe's 1 MiB (~3,600 cycles at ~51 us each: ~0.2 s of CPU, during which
#: it runs), hands a chunk to the OS and fsyncs once a second (a second of records, ~0.2 MB:
#: milliseconds on a local disk, up to about a second on a slow SD card or USB stick: the
#: only time it is still). A writer starved by a busy machine is waiting for a CPU, which
#: counts as life. Five seconds is several times that slowest fsync, and short enough that
#: the end of a run (its stop line, the warning of a drive that may still be enabled) is not
#: held longer than someone waits before reaching for ``kill -9``.
STALL_TIMEOUT: Final = 5.0
#: Seconds between looks at a waiting hand-over (its progress, its ``cancel``): a stop request
#: (SIGINT) ends the wait within this (``dobhil.drives.waits.WAIT_SLICE``, the loop's waits').
WAIT_SLICE: Final = 0.02
#: ``stop_reason`` of a file finished because the parent went away without closing it.
PARENT_EXITED: Final = "parent exited"
#: Bytes of pipe asked for (Linux, F_SETPIPE_SZ): ~3.5 s of a 1 kHz run (~290 bytes a cycle with
#: its two frames, packed) before real time drops.
PIPE_SIZE: Final = 1 << 20
#: Seconds the writer sleeps when the pipe is empty.
POLL: Final = 0.002
#: Seconds between chunks handed to the OS: what a SIGKILL of run and writer loses at most
#: of what the writer has read (an unfinished chunk lives in the writer's memory only).
#: Chunks also end at ``CHUNK_SIZE``, about 0.2 s of a 1 kHz run: 0.05 s costs ~1 % in size
#: in the topics layout (MCAP's message index outweighs the data) and ~12 % in the cycle
#: layout, whose chunks compress on their own (docs/recording.md, Encoding): kept, for safety.
WRITE_INTERVAL: Final = 0.05
_LENGTH: Final = struct.Struct("<I")
_NO_LENGTH: Final = bytes(_LENGTH.size)
_INT: Final = struct.Struct("i")
_BOOT: Final = "import sys; sys.path.insert(0, sys.argv[1]); from dobhil.recording.process import main; main()"


class Control(IntEnum):
    """First element (``kind``) of a control message (an :class:`Open` or a :class:`Stop`),
    sent alone in its batch among the records; told from a record by its type, as a record's
    kind grows with its lane."""

    OPEN = 100  # an Open
    STOP = 102  # a Stop


class Status(IntEnum):
    DONE = 0  # the file is finished: Reply.written, Reply.dropped
    FAILED = 1  # Reply.reason, one line
    READY = 2  # the file is open (and the live view listens: Reply.port)


class Open(NamedTuple):
    """Control message: open the file."""

    kind: int  # Control.OPEN
    mode: int  # RecordMode
    sync_interval: float  # fsync every (s)
    write_interval: float  # chunk to the OS every (s)
    fsync: bool
    metadata: dict[str, dict[str, str]]
    attachments: list[tuple[str, str, bytes]]
    live: LiveView | None
    codes: ProtocolCodes | None = None  # names the drive's codes on /drive/feedback
    lanes: tuple[Lane, ...] = ()  # the topic prefix and codes per lane (LogWriter); () one lane
    encoding: str = DEFAULT_ENCODING  # of the messages (dobhil.recording.encodings)
    layout: str = DEFAULT_LAYOUT  # a message per topic or per cycle (dobhil.recording.cycles)


class Stop(NamedTuple):
    """Control message: finish the file."""

    kind: int  # Control.STOP
    stop_reason: str | None
    detail: str


class Reply(NamedTuple):
    """The writer's status messages to the parent."""

    status: int  # Status
    port: int | None = None
    reason: str = ""
    written: int = 0
    dropped: int = 0


def encode(records: Sequence[tuple[Any, ...]]) -> bytes:
    """Records framed for the pipe: length, then the pickled list (tuples, and the loop's
    cycles and frames packed into ``bytes``: :mod:`dobhil.recording.packed`). Pickled: as fast
    as ``marshal`` here, and exact for numpy numbers in a tuple (which ``marshal`` turns into
    bytes); only this process's own child unpickles it."""
    out = io.BytesIO(_NO_LENGTH)
    out.seek(_LENGTH.size)
    pickler = pickle.Pickler(out, protocol=5)
    pickler.fast = True  # no memo: a batch is flat, no object in it is pickled twice
    pickler.dump(list(records))
    out.seek(0)
    out.write(_LENGTH.pack(out.getbuffer().nbytes - _LENGTH.size))
    return out.getvalue()


def unpack(data: bytes) -> tuple[list[list[tuple[Any, ...]]], int]:
    """The batches (record lists, packed records unpacked: plain tuples) wholly in ``data``,
    and where the first incomplete one starts. A control message always travels alone in its
    batch."""
    out: list[list[tuple[Any, ...]]] = []
    pos, end, length = 0, len(data), _LENGTH.unpack_from
    while pos + 4 <= end and (stop := pos + 4 + length(data, pos)[0]) <= end:
        out.append(unpacked_batch(pickle.loads(data[pos + 4:stop])))
        pos = stop
    return out, pos


class WriterProcess:
    """A writer process recording to ``path``; the file is created here (a bad path raises)."""

    def __init__(self, path: str | os.PathLike[str], *, flush_interval: float = 1.0, fsync: bool = True,
                 write_interval: float = WRITE_INTERVAL, encoding: str = DEFAULT_ENCODING,
                 layout: str = DEFAULT_LAYOUT) -> None:
        self.path = Path(path)
        self.encoding = find_encoding(encoding).name  # an unknown one refused here, not in the child
        if layout not in LAYOUTS:
            raise ValueError(f"unknown log layout {layout!r}; expected one of {', '.join(LAYOUTS)}")
        self.layout = layout
        self.mode = RecordMode.BACKPRESSURE
        self.opened = self._closed = False
        self.dropped = self.written = 0
        self.live_port: int | None = None
        self._interval, self._fsync = (flush_interval, write_interval), fsync
        self._tail = b""  # the part of a batch the pipe has not taken yet: goes first
        self._failure: str | None = None
        #: asked while a hand-over waits for the writer (returns why to stop waiting, or ""):
        #: the run's stop request, so a SIGINT is not held up by a writer that takes nothing
        self.cancel: Callable[[], str] | None = None
        with open(self.path, "xb"):  # the caller checked the path: this only fails on a race
            pass
        self._proc, self._fd, self._status = _spawn(self.path)
        self.pid = self._proc.pid

    def open(self, metadata: Mapping[str, Mapping[str, Any]], attachments: Sequence[tuple[str, str, bytes]],
             mode: RecordMode, live: LiveView | None = None, early: Sequence[tuple[Any, ...]] = (),
             codes: ProtocolCodes | None = None, lanes: Sequence[Lane] = ()) -> None:
        """Header, metadata, attachments, the mode, the live view (if any); waits
        until the writer is ready (its start-up never competes with the loop); then the
        ``early`` records (taken before the log was open). ``codes`` names the drive's own
        state and error codes in the messages (None: numbers only); ``lanes`` the topic
        prefix and codes of each lane of a several-axis log (:class:`LogWriter`)."""
        self.mode = RecordMode(mode)
        meta = {str(n): {str(k): str(v) for k, v in r.items()} for n, r in metadata.items()}
        files = [(str(n), str(m), bytes(d)) for n, m, d in attachments]
        self._send(encode([Open(Control.OPEN, int(self.mode), *self._interval, self._fsync, meta, files, live,
                                codes, tuple(Lane(*lane) for lane in lanes), self.encoding, self.layout)]), None)
        message: Reply | None = _read_status(self._status, JOIN_TIMEOUT)
        if message is None or message.status != Status.READY:
            self._closed = True
            self._join()
            self._failure = message.reason if message is not None else "the writer process did not start"
            raise RecorderError(f"{self.path}: {self._failure}")
        self.live_port = message.port
        self._send(self.encode(early), None)
        self.opened = True

    def write(self, data: bytes) -> bool:
        """Hand encoded records over; False if dropped (``LOSSY`` and the pipe full). Raises
        :class:`RecorderError` once the writer has failed."""
        if self._failure is not None:
            raise self._fail(self._failure)
        if self.mode is not RecordMode.LOSSY:
            self._send(data, self.cancel)   # a stop request ends the wait: the rest goes first next time
            return True
        try:
            if self._tail:
                self._tail = self._tail[os.write(self._fd, self._tail):]
                if self._tail:
                    return False
            self._tail = data[os.write(self._fd, data):]
            return True
        except BlockingIOError:
            return False
        except OSError:
            raise self._fail(self._ended_early()) from None

    def queued(self) -> int:
        """Bytes handed over the writer has not read yet (a batch's unsent part included);
        where the OS cannot tell (not Linux or a BSD), the unsent part only."""
        return _waiting(self._fd) + len(self._tail)

    def encode(self, records: Sequence[tuple[Any, ...]]) -> bytes:
        """:func:`encode`; a record that cannot be pickled is refused (:meth:`refuse`)."""
        try:
            return encode(records)
        except (pickle.PicklingError, TypeError, ValueError, AttributeError) as exc:
            raise self.refuse(f"cannot encode a record: {exception_line(exc)}") from None

    def close(self, stop_reason: str | None = None, detail: str = "", rest: Sequence[tuple[Any, ...]] = (),
              cancel: Callable[[], str] | None = None) -> None:
        """The ``rest`` of the records, none dropped; stop event (if a reason is given),
        summary, footer; waits for the process (never opened: the empty file is removed).
        The wait is bounded: a writer still for ``STALL_TIMEOUT`` s, or not done within
        ``JOIN_TIMEOUT`` s, or ``cancel`` saying why (a second SIGINT), is killed and the file
        left unfinished (:meth:`unfinished`). Raises :class:`RecorderError` if the writer
        failed. Idempotent."""
        if not self._closed:
            try:
                if self.opened and self._failure is None:
                    self._stop(self.encode(rest), stop_reason, detail, cancel)
            except RecorderError:
                pass  # refused (the file finished recorder_failed): raised below
            self._closed = True
            self._join(cancel)
            if not self.opened and self.path.exists() and self.path.stat().st_size == 0:
                self.path.unlink()
        if self._failure is not None:
            raise self._fail(self._failure)

    def refuse(self, why: str) -> RecorderError:
        """A record that cannot be encoded (a bug, not the disk): the file is finished with
        stop reason ``recorder_failed``; this and every later hand-over raise."""
        if self._failure is None and self.opened:
            self._stop(b"", "recorder_failed", why, self.cancel)
        return self._fail(why)

    def _fail(self, why: str) -> RecorderError:
        self._failure = self._failure or why
        return RecorderError(f"{self.path}: recorder failed: {self._failure}")

    def unfinished(self, why: str) -> str:
        """The failure of a writer given up while it had the file to finish: killed, so
        the file has no footer (``docs/recording.md``: recover)."""
        return (f"{why}: killed, the log is not finished (`dobhil log recover {self.path}` salvages "
                "what reached the disk)")

    def _stop(self, data: bytes, stop_reason: str | None, detail: str,
              cancel: Callable[[], str] | None = None) -> None:
        try:
            why = self._send(data + encode([Stop(Control.STOP, stop_reason, detail)]), cancel)
            if why:
                self._kill(self.unfinished(f"stopped waiting for the writer process ({why})"))
        except (RecorderError, OSError):
            pass  # the failure is noted; close raises it

    def _send(self, data: bytes, cancel: Callable[[], str] | None) -> str:
        """The rest of a batch begun first, then ``data``, waiting while the pipe is full.
        Returns "" once all is in the pipe, or why ``cancel`` ended the wait (the rest kept to
        go first). A writer still for ``STALL_TIMEOUT`` s is killed: raises
        :class:`RecorderError`."""
        view = memoryview(self._tail + data if self._tail else data)
        watch: _Watch | None = None
        try:
            while view:
                try:
                    view = view[os.write(self._fd, view):]
                    continue
                except BlockingIOError:
                    pass
                # the pipe is full: wait for room a slice at a time, asking cancel and
                # watching the writer between slices
                why = cancel() if cancel is not None else ""
                if why:
                    self._tail = bytes(view)
                    return why
                watch = watch or _Watch(self.pid, self._fd)
                select.select([], [self._fd], [], WAIT_SLICE)
                if watch.still(len(view)):
                    raise self._kill(self.unfinished(f"the writer process took nothing for {STALL_TIMEOUT:g} s "
                                                     "(stopped, or stuck on a disk that does not answer)"))
        except OSError:
            raise self._fail(self._ended_early()) from None
        self._tail = b""
        return ""

    def _kill(self, why: str) -> RecorderError:
        """Give the writer up: killed at once (SIGKILL ends a stopped process too), ``why``
        the failure."""
        self._proc.kill()
        try:
            self._proc.wait(JOIN_TIMEOUT)
        except subprocess.TimeoutExpired:
            pass   # the kernel has not reaped it yet; nothing more to do here
        return self._fail(why)

    def _ended_early(self) -> str:
        self._wait()
        status = _read_status(self._status)
        if status is not None and status.status == Status.FAILED:
            return status.reason
        return f"writer process ended early (exit code {self._proc.poll()})"

    def _join(self, cancel: Callable[[], str] | None = None) -> None:
        if self._fd >= 0:
            os.close(self._fd)
            self._fd = -1
        why = self._finish_wait(cancel)
        if why:
            self._failure = self._failure or self.unfinished(why)
        status = _read_status(self._status)
        self._status.close()
        if status is not None and status.status == Status.DONE:
            self.written = status.written
        elif self._failure is None:
            self._failure = status.reason if status is not None else f"writer exit code {self._proc.returncode}"

    def _finish_wait(self, cancel: Callable[[], str] | None) -> str:
        """Wait for the process to finish the file and exit: "" when it did, else why it was
        given up and killed (still for ``STALL_TIMEOUT`` s, not done in ``JOIN_TIMEOUT`` s,
        or ``cancel``)."""
        watch, end = _Watch(self.pid, -1), time.monotonic() + JOIN_TIMEOUT
        while True:
            try:
                self._proc.wait(WAIT_SLICE)
                return ""
            except subprocess.TimeoutExpired:
                pass
            why = cancel() if cancel is not None else ""
            if why:
                why = f"stopped waiting for the writer process ({why})"
            elif watch.still(0):
                why = f"the writer process did nothing for {STALL_TIMEOUT:g} s (stopped, or stuck on a disk " \
                      "that does not answer)"
            elif time.monotonic() >= end:
                why = f"writer process did not finish within {JOIN_TIMEOUT:g} s"
            if why:
                self._proc.kill()
                self._wait()
                return why

    def _wait(self) -> bool:
        """Wait for the process (killed after ``JOIN_TIMEOUT``); False if it had to be."""
        try:
            self._proc.wait(JOIN_TIMEOUT)
            return True
        except subprocess.TimeoutExpired:
            self._proc.kill()
            self._proc.wait()
            return False


class _Watch:
    """Whether a writer has been still for ``STALL_TIMEOUT`` s: it took nothing from the pipe
    ``fd`` (-1: not watched) -- the bytes to send did not shrink, nor the bytes waiting in the
    pipe -- and its scheduler statistics (Linux ``/proc/PID/schedstat``: time on a CPU and time
    waiting for one) did not move. Where the OS tells neither, a writer is never still by this
    (only ``JOIN_TIMEOUT`` bounds the wait)."""

    def __init__(self, pid: int, fd: int) -> None:
        self.pid, self.fd = pid, fd
        self.mark: tuple[int, int, str] | None = None
        self.since = time.monotonic()

    def still(self, unsent: int) -> bool:
        now = (unsent, _waiting(self.fd) if self.fd >= 0 else 0, _schedstat(self.pid))
        if now != self.mark:
            self.mark, self.since = now, time.monotonic()
            return False
        return now[1:] != (0, "") and time.monotonic() - self.since >= STALL_TIMEOUT


def _schedstat(pid: int) -> str:
    """Process ``pid``'s time on a CPU and waiting for one (Linux ``/proc/PID/schedstat``,
    its first two fields), "" where the kernel does not say."""
    try:
        with open(f"/proc/{pid}/schedstat") as f:
            return " ".join(f.read().split()[:2])
    except OSError:
        return ""


def _spawn(path: Path) -> tuple[subprocess.Popen[bytes] | forkserver.Child, int, Connection]:
    data_r, data_w = os.pipe()
    status_r, status_w = os.pipe()
    try:
        import fcntl
        fcntl.fcntl(data_w, fcntl.F_SETPIPE_SZ, PIPE_SIZE)
    except (ImportError, AttributeError, OSError):
        pass  # not Linux, or above /proc/sys/fs/pipe-max-size: the default 64 KiB
    # never blocks: LOSSY drops what has no room, BACKPRESSURE waits in slices (_send)
    os.set_blocking(data_w, False)
    # the stop signals blocked while the child starts (it inherits the mask and ignores
    # them before unblocking): a terminal's Ctrl-C never kills the writer before it can finish
    old = signal.pthread_sigmask(signal.SIG_BLOCK, forkserver.STOP_SIGNALS)
    proc: subprocess.Popen[bytes] | forkserver.Child
    try:
        if forkserver.available():
            # forked from a process that imported the writer's code once (dobhil/forkserver.py:
            # the imports are most of a short run's writer CPU); the mask goes with the call
            proc = forkserver.server(_PRELOAD).start(f"{__name__}:forked_main", (os.fspath(path),),
                                                     (data_r, status_w))
        else:
            argv = [sys.executable, "-c", _BOOT, forkserver.ROOT, str(data_r), str(status_w),
                    os.fspath(path)]
            proc = subprocess.Popen(argv, pass_fds=(data_r, status_w), stdin=subprocess.DEVNULL,
                                    stdout=subprocess.DEVNULL)
    except OSError as exc:
        os.close(data_w)
        os.close(status_r)
        path.unlink()
        raise RecorderError(f"{path}: cannot start the writer process: {exc}") from exc
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)
        os.close(data_r)
        os.close(status_w)
    return proc, data_w, Connection(status_r, writable=False)


def _waiting(fd: int) -> int:
    """Bytes in the pipe ``fd`` (FIONREAD: Linux and the BSDs; else 0)."""
    try:
        from fcntl import ioctl
        from termios import FIONREAD
        return int(_INT.unpack(ioctl(fd, FIONREAD, b"\0\0\0\0"))[0])
    except (ImportError, OSError, ValueError):
        return 0


def _read_status(conn: Connection, timeout: float = 0.0) -> Reply | None:
    try:
        return pickle.loads(conn.recv_bytes()) if conn.poll(timeout) else None
    except (EOFError, OSError, ValueError):
        return None


# -- the child ---------------------------------------------------------------------------


def _open(path: str, status: Connection, o: Open) -> LogWriter:
    for codes in (o.codes, *(lane.codes for lane in o.lanes)):
        if codes is not None:
            codes.prepare()
    log = LogWriter(open(path, "wb"), metadata=o.metadata, attachments=o.attachments, mode=RecordMode(o.mode),
                    fsync=o.fsync, codes=o.codes, lanes=o.lanes, encoding=o.encoding, layout=o.layout)
    live = o.live
    port = None
    if live is not None:
        server = live.serve(host=live.host, port=live.port, channels=log.output_channels())
        log.add_output(server, announced=True)
        port = server.port
    status.send_bytes(pickle.dumps(Reply(int(Status.READY), port=port)))
    return log


def _file_id(path: str) -> tuple[int, int] | None:
    """(device, inode) of the file at ``path``; None when there is none."""
    try:
        st = os.stat(path)
    except OSError:
        return None
    return st.st_dev, st.st_ino


def _serve(fd: int, status: Connection, path: str) -> Reply:
    """Read (polling: no write of the loop's wakes this process), write, hand chunks to the
    OS and fsync on time."""
    log: Any = None  # a LogWriter once OPEN (always the first message) came
    pending, (sync_every, write_every), next_sync, next_write = b"", (1.0, WRITE_INTERVAL), 0.0, 0.0
    os.set_blocking(fd, False)
    reserved = _file_id(path)   # the empty file the parent created for the log (WriterProcess)
    try:
        while True:
            try:
                chunk = os.read(fd, PIPE_SIZE)
            except BlockingIOError:
                time.sleep(POLL)
                chunk = None
            if chunk == b"":  # the parent went away without closing the log
                if log is None:   # closed before a run started
                    if reserved is not None and _file_id(path) == reserved and os.path.getsize(path) == 0:
                        # the parent gone before it opened the log (a run killed while it starts):
                        # its empty file removed, as its close() does, or the next run given
                        # the same --log would refuse it as a recording that exists
                        os.unlink(path)
                    return Reply(int(Status.DONE))
                log.finish(PARENT_EXITED, "the recording process ended without closing the log")
                return Reply(int(Status.DONE), written=log.written, dropped=log.dropped)
            batches, used = unpack(pending + chunk) if chunk else ([], 0)
            pending = (pending + chunk)[used:] if chunk else pending
            for batch in batches:
                # a control message travels alone, and is no record (whose kind may be any number)
                control = len(batch) == 1 and isinstance(batch[0], (Open, Stop))
                kind = batch[0][0] if control else 0
                if not control:
                    log.write(batch)
                elif kind == Control.OPEN:
                    o = cast(Open, batch[0])
                    log = _open(path, status, o)
                    sync_every, write_every = o.sync_interval, o.write_interval
                    next_write, next_sync = time.monotonic() + write_every, time.monotonic() + sync_every
                elif kind == Control.STOP:
                    stop = cast(Stop, batch[0])
                    log.finish(stop.stop_reason, stop.detail)
                    return Reply(int(Status.DONE), written=log.written, dropped=log.dropped)
            if log is not None and (now := time.monotonic()) >= next_write:
                sync = now >= next_sync
                log.flush(sync)
                next_write = now + write_every
                next_sync = now + sync_every if sync else next_sync
    except BaseException as exc:  # a record the encoder refuses: the file finished, if the disk lets it
        if log is not None:
            try:
                log.finish("recorder_failed", exception_line(exc))
            except BaseException:
                log.close()
        raise


def warm_child() -> None:
    """What a writer imports before it writes, done once in the fork server: the default
    encoding's module (imported by name when a log opens)."""
    find_encoding(DEFAULT_ENCODING)


#: the fork server's preload for writer processes
_PRELOAD: Final = (f"{__name__}:warm_child",)


def forked_main(data_fd: int, status_fd: int, path: str) -> None:
    """:func:`main` in a child of the fork server (its descriptors handed to it)."""
    main([str(data_fd), str(status_fd), path])


def main(argv: Sequence[str] | None = None) -> None:
    """``DATA_FD STATUS_FD PATH``: serve, send one status, exit."""
    for sig in forkserver.STOP_SIGNALS:
        signal.signal(sig, signal.SIG_IGN)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, forkserver.STOP_SIGNALS)
    data_fd, status_fd, path = (argv or sys.argv[2:])[:3]
    status_conn = Connection(int(status_fd), readable=False)
    code = 0
    try:
        status = _serve(int(data_fd), status_conn, path)
    except BaseException as exc:  # one line for the parent, whatever it was
        status, code = Reply(int(Status.FAILED), reason=exception_line(exc)), 1
    try:
        status_conn.send_bytes(pickle.dumps(status))
    except OSError:
        pass  # the parent is gone: nobody to tell
    sys.exit(code)


__all__ = ["JOIN_TIMEOUT", "PARENT_EXITED", "PIPE_SIZE", "WRITE_INTERVAL", "WriterProcess", "encode", "main", "unpack"]
