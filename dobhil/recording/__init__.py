"""MCAP recording of dobhil runs, and the tools that read, repair and convert recordings.

- :mod:`~dobhil.recording.schemas`     the one table of topics and their JSON schemas
- :mod:`~dobhil.recording.sink`        :class:`RunLog`: recording one run (tap, cycle sink, events)
- :mod:`~dobhil.recording.writerproc`  the writer process run logging hands raw records to
- :mod:`~dobhil.recording.recorder`    :class:`Recorder`, a writer thread per file
- :mod:`~dobhil.recording.filewriter`  the MCAP file both writers write through
- :mod:`~dobhil.recording.reader`      :func:`open_log`, validated reading and ``info``
- :mod:`~dobhil.recording.recover`     salvage a file cut short (``kill -9``)
- :mod:`~dobhil.recording.canlog`      CAN frames to/from candump, ASC and BLF via python-can
- :mod:`~dobhil.recording.export`      one topic to CSV

The channels and encodings are documented in ``docs/recording.md``.

The names below are imported on first use (PEP 562), so the writer process, which
imports :mod:`dobhil.recording.writerchild`, starts without python-can and the readers.
"""

from __future__ import annotations

from importlib import import_module
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from dobhil.recording.reader import LogFile, LogInfo, open_log
    from dobhil.recording.recorder import CanRecordListener, Recorder, RecordMode, record_can_bus
    from dobhil.recording.schemas import TOPIC_SPECS, Direction, EventKind, Topic, TopicSpec

_EXPORTS: dict[str, str] = {
    "LogFile": "reader", "LogInfo": "reader", "open_log": "reader",
    "CanRecordListener": "recorder", "Recorder": "recorder", "RecordMode": "recorder",
    "record_can_bus": "recorder",
    "TOPIC_SPECS": "schemas", "Direction": "schemas", "EventKind": "schemas", "Topic": "schemas",
    "TopicSpec": "schemas",
}


def __getattr__(name: str) -> Any:
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return getattr(import_module(f"{__name__}.{module}"), name)


__all__ = [
    "TOPIC_SPECS",
    "CanRecordListener",
    "Direction",
    "EventKind",
    "LogFile",
    "LogInfo",
    "RecordMode",
    "Recorder",
    "Topic",
    "TopicSpec",
    "open_log",
    "record_can_bus",
]
