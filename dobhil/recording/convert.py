"""Logs to and from other formats, outputs checked first and written under a temporary name.

- :func:`export_csv`: ``log_time_ns``, then one column per property of the schema stored
  in the file; lists space-separated, booleans ``true``/``false``, ``null`` empty.
- :func:`export_can` / :func:`import_can`: ``/can/rx`` and ``/can/tx`` to and from any log
  python-can writes or reads (candump, ASC, BLF), through python-can's own classes.
"""

from __future__ import annotations

import csv
import os
from collections.abc import Callable, Mapping
from enum import IntEnum
from pathlib import Path
from types import MappingProxyType
from typing import Any, Final

import can

from dobhil.errors import LogFileError
from dobhil.files import atomic_path, check_output, input_problem
from dobhil.recording.reader import open_log
from dobhil.recording.schemas import Direction, can_frame_message, can_frame_record
from dobhil.recording.writer import LogWriter

ProgressFn = Callable[[int], None]
_CAN_TOPICS: Final = ("/can/rx", "/can/tx")


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


def default_csv_output(mcap_path: str | os.PathLike[str], topic: str) -> Path:
    """``run.mcap`` + ``/drive/feedback`` -> ``run.drive_feedback.csv``."""
    return Path(mcap_path).with_suffix(f".{topic.strip('/').replace('/', '_') or 'topic'}.csv")


def cell(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    return "" if value is None else " ".join(map(cell, value)) if isinstance(value, list) else str(value)


def export_csv(mcap_path: str | os.PathLike[str], topic: str, out: str | os.PathLike[str], *,
               progress: ProgressFn | None = None) -> int:
    """``topic`` of the recording to ``out`` as CSV; the row count."""
    check_output(out, inputs=[mcap_path], what="output")
    with open_log(mcap_path) as log, atomic_path(out) as tmp, open(tmp, "w", newline="", encoding="utf-8") as sink:
        columns, writer = log.schema_properties(topic), csv.writer(sink)
        writer.writerow(["log_time_ns", *columns])
        return _each(log.iter_messages([topic]), progress,
                     lambda t, p: writer.writerow([str(t), *(cell(p.get(c)) for c in columns)]))


def export_can(mcap_path: str | os.PathLike[str], out: str | os.PathLike[str], fmt: CanLogFormat, *,
               progress: ProgressFn | None = None) -> int:
    """The recording's CAN frames to ``out`` in ``fmt``; the frame count."""
    check_output(out, inputs=[mcap_path], what="output", suffix=FORMATS[fmt][0])
    with open_log(mcap_path) as log:
        topics = [t for t in _CAN_TOPICS if t in log.topics()]
        if not topics:
            raise LogFileError(f"{os.fspath(mcap_path)}: no CAN frames (no /can/rx or /can/tx topic)")
        with atomic_path(out) as tmp, FORMATS[fmt][1](tmp) as writer:
            def write(t: int, payload: Any) -> None:
                msg = can_frame_message(payload, t)
                if fmt is CanLogFormat.BLF:  # BLF stores channels as small integers
                    number = can.util.channel2int(msg.channel)
                    msg.channel = number if number is not None and 0 <= number <= 0xFFFF else None
                writer.on_message_received(msg)
            return _each(log.iter_messages(topics), progress, write)


def _each(messages: Any, progress: ProgressFn | None, write: Callable[[int, Any], Any]) -> int:
    count = 0
    for count, (_, t, payload) in enumerate(messages, 1):
        write(t, payload)
        if progress is not None:
            progress(1)
    return count


def _can_reader(path: Path) -> Any:
    problem = input_problem(path)
    if problem is not None:
        raise LogFileError(f"{path}: {problem}; expected a CAN log file python-can reads (.asc, .blf, .log, .trc, ...)")
    if path.stat().st_size == 0:
        raise LogFileError(f"{path}: empty file")
    try:
        return can.LogReader(path)
    except Exception as exc:  # python-can readers raise what their parsers raise
        raise LogFileError(f"{path}: not a CAN log python-can reads ({type(exc).__name__}: {exc})") from exc


def import_can(canlog: str | os.PathLike[str], out: str | os.PathLike[str], *,
               progress: ProgressFn | None = None) -> int:
    """Every frame of a python-can readable log into a new MCAP; the frame count."""
    source = Path(canlog)
    check_output(out, inputs=[source], suffix=".mcap", what="output")
    count, meta = 0, {"import": {"source": source.name, "format": source.suffix.lstrip(".").lower()}}
    with _can_reader(source) as reader, atomic_path(out) as tmp:
        log = LogWriter(open(tmp, "wb"), metadata=meta, fsync=False)
        try:
            for count, msg in enumerate(reader, 1):
                log.write([can_frame_record(msg, Direction.RX if msg.is_rx else Direction.TX,
                                            round((msg.timestamp or 0.0) * 1e9))])
                if progress is not None:
                    progress(1)
        except Exception as exc:  # whatever a damaged log makes the reader raise
            log.close()
            raise LogFileError(f"{source}: unreadable after {count} frames ({type(exc).__name__}: {exc})") from exc
        if count == 0:
            log.close()
            raise LogFileError(f"{source}: no CAN frames found (is it a {source.suffix or 'CAN'} log?)")
        log.finish(None)
    return count


__all__ = ["FORMATS", "CanLogFormat", "cell", "default_can_output", "default_csv_output", "export_can",
           "export_csv", "import_can", "parse_format"]
