"""``can.Logger("x.mcap")``: python-can's log writer for MCAP, with dobhil's topics.

Every frame goes to ``/can/rx`` (python-can's ``is_rx``) or ``/can/tx`` with the JSON
schema of a dobhil recording, so ``dobhil log info``, ``can.LogReader`` and Foxglove
read the file like one ``dobhil run --log`` wrote. Both channels are registered at the
start: an empty capture is still a CAN log. Log time is the frame's timestamp (the
wall clock for a frame without one).

The file is finished (summary, footer) by :meth:`McapWriter.stop`, which python-can's
``can.logger`` calls on Ctrl-C and ``can.logconvert`` at the end. Until then the chunk
in progress is written out every ``flush_interval`` seconds, so a killed logger loses
at most that much and ``dobhil log recover`` completes the file.

Keyword arguments (on python-can's command lines ``--compression=lz4``, ``--flush-interval=0.5``):
``compression`` (``zstd``, ``lz4`` or ``none``; default zstd), ``chunk_size`` (bytes) and ``flush_interval`` (seconds).

Errors are what python-can's own writers raise: an output that cannot be opened (a
missing folder: FileNotFoundError, as ``can.ASCWriter`` and ``can.BLFWriter`` raise) is
the OSError of ``open``. An output that is a file this process reads as input
(``can.logconvert run.mcap run.mcap``) is refused before it is opened, the input left
intact (python-can's writers would truncate it: its ``.asc`` and ``.log`` inputs end up
empty), with :class:`OutputIsInputError`, an OSError as well. python-can's programs
(``can.logconvert``, ``can.logger``) show a traceback for any writer error, for their own
formats too; its last line is the one-line reason.
"""

from __future__ import annotations

import os
import signal
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from datetime import datetime, timezone
from io import BufferedIOBase
from pathlib import Path
from typing import Any, BinaryIO, Final, cast

import can
from can.io.generic import BinaryIOMessageWriter
from mcap.exceptions import UnsupportedCompressionError
from mcap.writer import CompressionType

from dobhil import __version__
from dobhil.canio.mcap_reader import is_open_input
from dobhil.canio.frames import FRAME_TOPICS, topic_of
from dobhil.recording.schemas import can_frame_record
from dobhil.recording.writer import CHUNK_SIZE, LogWriter

#: Name of the metadata record written at the start (and ``.stop`` at the end).
METADATA: Final = "python-can"
_DEFERRED: Final = {signal.SIGINT, signal.SIGTERM}
_COMPRESSION: Final = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}


def program_name(argv0: str | None = None) -> str:
    """What is writing: ``can.logger`` for ``python -m can.logger``, else the script's name."""
    path = Path(sys.argv[0] if argv0 is None else argv0)
    can_dir = Path(can.__file__).resolve().parent
    try:
        inside = path.resolve().parent == can_dir
    except OSError:
        inside = False
    return f"can.{path.stem}" if inside else (path.name or "python")


def _positive(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and value > 0


@contextmanager
def _signals_deferred() -> Iterator[None]:
    """SIGINT/SIGTERM handled only after one frame is written and counted: a Ctrl-C (how
    ``can.logger`` is stopped) must not raise inside ``add_message`` (a frame in the
    chunk but not counted, or a record half built). Blocking the signal is not enough:
    the process's other threads (an interface's own, like the ``dobhil`` bus's emulator)
    still take it and the main thread raises at its next bytecode. So the Python handlers
    are swapped for one that notes the signal, and the noted ones run right after. Only the
    main thread runs Python signal handlers: elsewhere there is nothing to defer."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    noted: list[int] = []
    saved: dict[int, Any] = {s: h for s in _DEFERRED if callable(h := signal.getsignal(s))}
    for sig in saved:
        signal.signal(sig, lambda signum, _frame: noted.append(signum))
    try:
        yield
    finally:
        for sig, handler in saved.items():
            signal.signal(sig, handler)
        for signum in noted:
            saved[signum](signum, None)


class OutputIsInputError(OSError, ValueError):
    """The output is a file this process is reading as input: refused, nothing written.

    An OSError, as python-can's writers raise for an output they cannot open, and a
    ValueError, as this writer's other refusals (and as it was before)."""


def _utc_now() -> str:
    return datetime.now(timezone.utc).isoformat(timespec="milliseconds")


class McapWriter(BinaryIOMessageWriter):
    """Writes CAN frames to an MCAP file (path or binary file object, owned either way)
    through recording's :class:`~dobhil.recording.writer.LogWriter`: one writer of dobhil logs."""

    def __init__(self, file: str | os.PathLike[str] | BinaryIO | BufferedIOBase, append: bool = False, *,
                 compression: str | None = None, chunk_size: int = CHUNK_SIZE, flush_interval: float = 1.0,
                 **kwargs: Any) -> None:
        if kwargs:
            raise ValueError(f"MCAP writer: unknown option(s) {', '.join(sorted(kwargs))}; "
                             f"allowed: compression, chunk_size, flush_interval")
        if append:
            raise ValueError("MCAP writer: cannot append to an MCAP file (it ends with a summary); "
                             "write a new file")
        compression = None if compression is None else str(compression).lower()
        if compression is not None and compression not in _COMPRESSION:
            raise ValueError(f"MCAP writer: compression {compression!r}; allowed: {', '.join(_COMPRESSION)}")
        if not _positive(chunk_size) or not _positive(flush_interval):
            raise ValueError(f"MCAP writer: chunk_size and flush_interval must be > 0, "
                             f"got {chunk_size!r}, {flush_interval!r}")
        if isinstance(file, (str, os.PathLike)) and is_open_input(file):
            raise OutputIsInputError(f"MCAP writer: {os.fspath(file)} is being read as input; "
                                     f"write to another file (the input is left as it was)")
        super().__init__(file, mode="wb")
        self._lock = threading.Lock()
        self._interval = float(flush_interval)
        self._next_flush = time.monotonic() + self._interval
        self._counts = {topic: 0 for topic in FRAME_TOPICS}
        self._stopped = False
        metadata = {METADATA: {"writer": f"{__name__}.{type(self).__name__}", "program": program_name(),
                               "dobhil": __version__, "python-can": can.__version__, "started": _utc_now()}}
        try:
            self._log = LogWriter(cast(BinaryIO, self.file), metadata=metadata, fsync=False,
                                  library=f"dobhil/{__version__} (python-can {can.__version__})",
                                  compression=_COMPRESSION[compression or "zstd"],
                                  chunk_size=int(chunk_size))
        except UnsupportedCompressionError:
            self.file.close()
            raise ValueError(f"MCAP writer: compression {compression!r} is not installed") from None
        except BaseException:
            self.file.close()
            raise
        self._log.register(*FRAME_TOPICS)  # an empty capture is still a CAN log
        self._log.flush()

    @property
    def frames_written(self) -> int:
        """Frames written so far (both topics)."""
        return sum(self._counts.values())

    def on_message_received(self, msg: can.Message) -> None:
        topic = topic_of(msg)
        stamp = msg.timestamp
        record = can_frame_record(msg, topic, max(0, round(stamp * 1e9)) if stamp else time.time_ns())
        with self._lock, _signals_deferred():
            if self._stopped:
                raise ValueError("MCAP writer: message after stop()")
            self._log.write((record,))
            self._counts[topic] += 1
            if time.monotonic() >= self._next_flush:
                self._log.flush()
                self._next_flush = time.monotonic() + self._interval

    def stop(self) -> None:
        """Write the summary and footer and close the file (again: no-op)."""
        with self._lock:
            if self._stopped:
                return
            self._stopped = True
            try:
                rx, tx = (self._counts[t] for t in FRAME_TOPICS)
                self._log.finish(None, metadata={f"{METADATA}.stop": {
                    "frames": str(rx + tx), "rx": str(rx), "tx": str(tx), "stopped": _utc_now()}})
            finally:
                super().stop()


__all__ = ["METADATA", "McapWriter", "OutputIsInputError", "program_name"]
