"""CAN frames between dobhil recordings and the log formats of other tools.

Both directions go through python-can's own ``can.io`` writers and readers, so
every format python-can knows stays readable by candump/SavvyCAN/CANalyzer:

- :func:`export_can` writes ``/can/rx`` and ``/can/tx`` (``is_rx=False``) in log-time
  order to candump (``.log``), Vector ASC (``.asc``) or Vector BLF (``.blf``).
- :func:`import_can` reads any log :class:`can.LogReader` understands and records it
  as ``/can/rx`` (``/can/tx`` for frames the reader marks ``is_rx=False``).
"""

from __future__ import annotations

import os
from collections.abc import Callable, Mapping
from enum import IntEnum
from pathlib import Path
from types import MappingProxyType
from typing import Any, Final

import can

from dobhil.errors import LogFileError
from dobhil.recording.reader import open_log
from dobhil.recording.recorder import Recorder, RecordMode
from dobhil.recording.schemas import Direction

ProgressFn = Callable[[int], None]

_CAN_TOPICS: Final = ("/can/rx", "/can/tx")


class CanLogFormat(IntEnum):
    """CAN log formats :func:`export_can` writes."""

    CANDUMP = 1
    ASC = 2
    BLF = 3


#: Format -> (file suffix, python-can writer class).
FORMATS: Final[Mapping[CanLogFormat, tuple[str, type[can.io.generic.MessageWriter]]]] = MappingProxyType(
    {
        CanLogFormat.CANDUMP: (".log", can.CanutilsLogWriter),
        CanLogFormat.ASC: (".asc", can.ASCWriter),
        CanLogFormat.BLF: (".blf", can.BLFWriter),
    }
)


def parse_format(name: str) -> CanLogFormat:
    """``"candump"`` -> :attr:`CanLogFormat.CANDUMP`; LogFileError if unknown."""
    try:
        return CanLogFormat[name.upper()]
    except KeyError:
        known = ", ".join(f.name.lower() for f in CanLogFormat)
        raise LogFileError(f"unknown CAN log format {name!r}; expected one of {known}") from None


def default_output(mcap_path: str | os.PathLike[str], fmt: CanLogFormat) -> Path:
    """``run.mcap`` -> ``run.log`` / ``run.asc`` / ``run.blf``."""
    return Path(mcap_path).with_suffix(FORMATS[fmt][0])


def payload_to_message(payload: Mapping[str, Any], log_time_ns: int) -> can.Message:
    """A python-can message from a ``/can/*`` payload (bus time, else log time)."""
    channel = payload.get("channel") or None
    return can.Message(
        timestamp=payload.get("timestamp") or log_time_ns / 1e9,
        arbitration_id=payload["arbitration_id"],
        is_extended_id=payload["is_extended_id"],
        is_remote_frame=payload["is_remote_frame"],
        is_error_frame=payload["is_error_frame"],
        is_fd=payload["is_fd"],
        bitrate_switch=payload.get("bitrate_switch", False),
        error_state_indicator=payload.get("error_state_indicator", False),
        dlc=payload["dlc"],
        data=bytes(payload["data"]),
        is_rx=payload["direction"] != "tx",
        channel=channel,
        check=False,
    )


def export_can(
    mcap_path: str | os.PathLike[str],
    out_path: str | os.PathLike[str],
    fmt: CanLogFormat,
    *,
    progress: ProgressFn | None = None,
) -> int:
    """Write the recording's CAN frames to ``out_path`` in ``fmt``; the frame count."""
    log = open_log(mcap_path)
    topics = [t for t in _CAN_TOPICS if t in log.topics()]
    if not topics:
        raise LogFileError(f"{os.fspath(mcap_path)}: no CAN frames (no /can/rx or /can/tx topic)")
    count = 0
    with _writer(out_path, fmt) as writer:
        for _, log_time_ns, payload in log.iter_messages(topics):
            msg = payload_to_message(payload, log_time_ns)
            if fmt is CanLogFormat.BLF:
                msg.channel = _blf_channel(msg.channel)
            writer.on_message_received(msg)
            count += 1
            if progress is not None:
                progress(1)
    return count


def _blf_channel(channel: Any) -> int | None:
    """BLF stores channels as small integers: a name that is not one becomes the default."""
    number = can.util.channel2int(channel)
    return number if number is not None and 0 <= number <= 0xFFFF else None


def _writer(out_path: str | os.PathLike[str], fmt: CanLogFormat) -> can.io.generic.MessageWriter:
    try:
        return FORMATS[fmt][1](out_path)
    except OSError as exc:
        raise LogFileError(f"{os.fspath(out_path)}: cannot create: {exc.strerror}") from exc


def _reader(canlog_path: str | os.PathLike[str]) -> Any:
    path = Path(canlog_path)
    if not path.is_file():
        raise LogFileError(f"{os.fspath(canlog_path)}: no such file")
    if path.stat().st_size == 0:
        raise LogFileError(f"{os.fspath(canlog_path)}: empty file")
    try:
        return can.LogReader(path)
    except ValueError as exc:
        raise LogFileError(f"{os.fspath(canlog_path)}: not a CAN log python-can reads ({exc})") from exc


def import_can(
    canlog_path: str | os.PathLike[str],
    out_mcap: str | os.PathLike[str],
    *,
    progress: ProgressFn | None = None,
) -> int:
    """Record every frame of a python-can readable log into a new MCAP; the frame count."""
    reader = _reader(canlog_path)
    name = Path(canlog_path).name
    metadata = {"import": {"source": name, "format": Path(canlog_path).suffix.lstrip(".").lower()}}
    count = 0
    with reader, Recorder(out_mcap, metadata=metadata, mode=RecordMode.BACKPRESSURE, fsync=False) as rec:
        try:
            for msg in reader:
                direction = Direction.RX if msg.is_rx else Direction.TX
                rec.write_frame(msg, direction, round((msg.timestamp or 0.0) * 1e9))
                count += 1
                if progress is not None:
                    progress(1)
        except (ValueError, IndexError, KeyError) as exc:
            raise LogFileError(f"{os.fspath(canlog_path)}: unreadable after {count} frames ({exc})") from exc
    return count


__all__ = ["FORMATS", "CanLogFormat", "default_output", "export_can", "import_can", "parse_format",
           "payload_to_message"]
