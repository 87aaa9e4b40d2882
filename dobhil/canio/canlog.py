"""CAN logs in python-can's formats to and from dobhil recordings: ``dobhil log export
--can`` (a checked recording's ``/can/rx`` and ``/can/tx`` through python-can's writers) and
``dobhil log import`` (any log python-can reads, through :class:`LogWriter`, the same frame
records as ``can.Logger("x.mcap")``); outputs checked first and written under a temporary name.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable, Mapping
from enum import IntEnum
from pathlib import Path
from types import MappingProxyType
from typing import Any, Final

import can

from dobhil.canio.frames import is_frame_topic, topic_of
from dobhil.errors import LogFileError, exception_line
from dobhil.files import atomic_path, check_output, input_problem
from dobhil.recording.reader import open_log
from dobhil.recording.schemas import can_frame_message, can_frame_record
from dobhil.recording.writer import LogWriter

ProgressFn = Callable[[int], None]


class CanLogFormat(IntEnum):
    CANDUMP = 1
    ASC = 2
    BLF = 3


#: Format -> (file suffix, python-can writer class).
FORMATS: Final[Mapping[CanLogFormat, tuple[str, type[can.io.generic.MessageWriter]]]] = MappingProxyType({
    CanLogFormat.CANDUMP: (".log", can.CanutilsLogWriter), CanLogFormat.ASC: (".asc", can.ASCWriter),
    CanLogFormat.BLF: (".blf", can.BLFWriter)})


def parse_format(name: str) -> CanLogFormat:
    try:
        return CanLogFormat[name.upper()]
    except KeyError:
        known = ", ".join(f.name.lower() for f in CanLogFormat)
        raise LogFileError(f"unknown CAN log format {name!r}; expected one of {known}") from None


def default_can_output(mcap_path: str | os.PathLike[str], fmt: CanLogFormat) -> Path:
    """``run.mcap`` -> ``run.log`` / ``run.asc`` / ``run.blf``."""
    return Path(mcap_path).with_suffix(FORMATS[fmt][0])


def export_can(mcap_path: str | os.PathLike[str], out: str | os.PathLike[str], fmt: CanLogFormat, *,
               progress: ProgressFn | None = None) -> int:
    """The recording's CAN frames to ``out`` in ``fmt`` (every bus' of a several-axis log, in
    the order recorded, each frame with the channel its bus gave it); the frame count."""
    check_output(out, inputs=[mcap_path], what="output", suffix=FORMATS[fmt][0])
    with open_log(mcap_path) as log:
        topics = [t for t in log.topics() if is_frame_topic(t)]
        if not topics:
            raise LogFileError(f"{os.fspath(mcap_path)}: no CAN frames (no /can/rx or /can/tx topic)")
        with atomic_path(out) as tmp, FORMATS[fmt][1](tmp) as writer:
            count = 0
            if isinstance(writer, can.ASCWriter):
                _start_at_earliest(writer, log, topics)
            for _, t, payload in log.iter_messages(topics):
                msg = can_frame_message(payload, t)
                if fmt is CanLogFormat.BLF:  # BLF stores channels as small integers
                    number = can.util.channel2int(msg.channel)
                    msg.channel = number if number is not None and 0 <= number <= 0xFFFF else None
                writer.on_message_received(msg)
                count += 1
                if progress is not None:
                    progress(1)
            return count


def _start_at_earliest(writer: can.ASCWriter, log: Any, topics: list[str]) -> None:
    """ASC times are relative to the first line written, and python-can writes a frame
    older than that as an absolute time (which reads back as another date). Frames are
    exported in log-time order, where a received frame may be older than a command sent
    before it was read: so the file starts at the earliest frame (one event line)."""
    earliest = min((p.get("timestamp") or t / 1e9 for _, t, p in log.iter_messages(topics)), default=None)
    if earliest is not None:
        writer.log_event("dobhil log export", asc_start(earliest))


def asc_start(earliest: float) -> float:
    """A start time for an ASC file, at or before ``earliest``, that python-can reads back
    as it wrote it. Workaround: python-can's ASCWriter writes the header's milliseconds
    without leading zeros (``12:00:07.46`` for 46 ms) and its reader takes them as a
    fraction (0.46 s), so a start in the first 100 ms of a second would read back up to
    0.9 s late. A whole millisecond (the header holds no more) from 100 to 999 reads back
    exactly: the nearest one at or before ``earliest``."""
    ms = math.floor(earliest * 1000)
    if ms % 1000 < 100:
        ms -= ms % 1000 + 1   # the last millisecond of the second before
    return ms / 1000


def _can_reader(path: Path) -> Any:
    problem = input_problem(path)
    if problem is not None:
        raise LogFileError(f"{path}: {problem}; expected a CAN log file python-can reads (.asc, .blf, .log, .trc, ...)")
    if path.stat().st_size == 0:
        raise LogFileError(f"{path}: empty file")
    # ASC: absolute times (its Begin Triggerblock date plus each line's offset), as every
    # other format gives; python-can's default for ASC is times from 0, i.e. 1970
    absolute = {"relative_timestamp": False} if path.suffix.lower() == ".asc" else {}
    try:
        return can.LogReader(path, **absolute)
    except Exception as exc:  # python-can readers raise what their parsers raise
        raise LogFileError(f"{path}: not a CAN log python-can reads ({exception_line(exc)})") from exc


def import_can(canlog: str | os.PathLike[str], out: str | os.PathLike[str], *,
               progress: ProgressFn | None = None) -> int:
    """Every frame of a python-can readable log into a new MCAP; the frame count."""
    source = Path(canlog)
    check_output(out, inputs=[source], suffix=".mcap", what="output", new=True)
    count, meta = 0, {"import": {"source": source.name, "format": source.suffix.lstrip(".").lower()}}
    with _can_reader(source) as reader, atomic_path(out) as tmp:
        log = LogWriter(open(tmp, "wb"), metadata=meta, fsync=False)
        try:
            for msg in reader:
                log.write([can_frame_record(msg, topic_of(msg),
                                            round((msg.timestamp or 0.0) * 1e9))])
                count += 1
                if progress is not None:
                    progress(1)
        except Exception as exc:  # whatever a damaged log makes the reader raise
            log.close()
            raise LogFileError(f"{source}: unreadable after {count} frames ({exception_line(exc)})") from exc
        if count == 0:
            log.close()
            raise LogFileError(f"{source}: no CAN frames found (is it a {source.suffix or 'CAN'} log?)")
        log.finish(None)
    return count


__all__ = ["FORMATS", "CanLogFormat", "default_can_output", "export_can", "import_can", "parse_format"]
