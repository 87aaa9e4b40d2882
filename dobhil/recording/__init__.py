"""MCAP recording of dobhil runs, and the tools that read, repair and convert recordings.

- :mod:`~dobhil.recording.schemas`  the one table of topics and their JSON schemas
- :mod:`~dobhil.recording.recorder` :class:`Recorder`, a writer thread per file
- :mod:`~dobhil.recording.reader`   :func:`open_log`, validated reading and ``info``
- :mod:`~dobhil.recording.recover`  salvage a file cut short (``kill -9``)
- :mod:`~dobhil.recording.canlog`   CAN frames to/from candump, ASC and BLF via python-can
- :mod:`~dobhil.recording.export`   one topic to CSV

The channels and encodings are documented in ``docs/recording.md``.
"""

from __future__ import annotations

from dobhil.recording.reader import LogFile, LogInfo, open_log
from dobhil.recording.recorder import CanRecordListener, Recorder, RecordMode, record_can_bus
from dobhil.recording.schemas import TOPIC_SPECS, Direction, EventKind, Topic, TopicSpec

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
