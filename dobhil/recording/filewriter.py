"""The writing side of a recording: one MCAP file, its channels, flushes and summary.

:class:`LogFileWriter` is what both writers run: the thread of
:class:`~dobhil.recording.recorder.Recorder` and the writer process of run logging
(:mod:`~dobhil.recording.writerchild`). It owns the :class:`~dobhil.recording.fastlog.FastWriter`,
registers a channel when its first message comes, encodes raw records
(:func:`~dobhil.recording.fastlog.encode_raw`), ends the chunk and flushes (and
fsyncs) the file on request, and finishes it with the ``recording`` metadata record.

This module imports neither python-can nor anything the loop needs, so the writer
process starts quickly.
"""

from __future__ import annotations

import os
import time
from collections.abc import Iterable, Mapping, Sequence
from enum import IntEnum
from typing import Any, BinaryIO, Final

from mcap.writer import CompressionType

from dobhil import __version__
from dobhil.recording.fastlog import FastWriter, FrameEncoder, encode_raw, event_payload, loss_payload
from dobhil.recording.schemas import (
    MESSAGE_ENCODING,
    SCHEMA_ENCODING,
    TOPIC_SPECS,
    EventKind,
    Topic,
    TopicSpec,
    encode,
)

#: Chunks end at this size or every ``flush_interval``, whichever comes first.
CHUNK_SIZE: Final = 256 * 1024
#: Name of the metadata record written on close.
RECORDING_METADATA: Final = "recording"


class RecordMode(IntEnum):
    """What a writer does when the consumer lags."""

    BACKPRESSURE = 1  # wait for room, lose nothing (lockstep)
    LOSSY = 2  # never wait; drop and count (real time)


def chunk_compression() -> CompressionType:
    """zstd if importable, else lz4, else none."""
    for module, kind in (("zstandard", CompressionType.ZSTD), ("lz4.frame", CompressionType.LZ4)):
        try:
            __import__(module)
        except ImportError:
            continue
        return kind
    return CompressionType.NONE


class LogFileWriter:
    """One MCAP file being written: header, metadata and attachments at construction.

    Not thread-safe: exactly one thread (or process) writes. ``file`` is owned (closed
    by :meth:`finish` or :meth:`close`).
    """

    def __init__(self, file: BinaryIO, *, metadata: Mapping[str, Mapping[str, Any]],
                 attachments: Iterable[Sequence[Any]] = (), mode: RecordMode, fsync: bool = True) -> None:
        self.file = file
        self.mode = RecordMode(mode)
        self.fsync = fsync
        self.written = 0
        self.dropped = 0
        self.last_log_ns = 0
        self._channels: dict[Topic, int] = {}
        self._schemas: dict[str, int] = {}
        self._frames = FrameEncoder()
        self._writer = FastWriter(file, chunk_size=CHUNK_SIZE, compression=chunk_compression())
        self._writer.start(profile="", library=f"dobhil/{__version__}")
        for name, record in metadata.items():
            self._writer.add_metadata(name, {str(k): str(v) for k, v in record.items()})
        now = time.time_ns()
        for name, media_type, data in attachments:
            self._writer.add_attachment(create_time=now, log_time=now, name=name, media_type=media_type, data=data)
        file.flush()

    def write_message(self, topic: Topic, log_time_ns: int, data: bytes) -> None:
        """Write one encoded message."""
        channel = self._channels.get(topic)
        if channel is None:
            channel = self._register(TOPIC_SPECS[topic])
        self._writer.add_message(channel, log_time_ns, data, log_time_ns)
        self.written += 1

    def write_records(self, records: Sequence[Sequence[Any]]) -> None:
        """Encode and write raw records (:mod:`~dobhil.recording.fastlog`), in order."""
        if not records:
            return
        channels = self._channels
        out = []
        for topic, t, data in encode_raw(records, self._frames):
            channel = channels.get(topic)
            if channel is None:
                channel = self._register(TOPIC_SPECS[topic])
            out.append((channel, t, data))
        self._writer.add_messages(out)
        self.written += len(out)
        self.last_log_ns = max(self.last_log_ns, records[-1][1])

    def loss(self, count: int, total: int, log_time_ns: int) -> None:
        """The ``/events`` ``kind=loss`` record of ``count`` records dropped."""
        self.dropped = total
        self.last_log_ns = max(self.last_log_ns, log_time_ns)
        self.write_message(Topic.EVENTS, log_time_ns, encode(loss_payload(count, total)))

    def flush(self) -> None:
        """End the current chunk, flush and (if asked) fsync: a crash loses nothing older."""
        self._writer.flush()
        self.file.flush()
        if self.fsync:
            os.fsync(self.file.fileno())

    def stop_event(self, reason: str, detail: str, log_time_ns: int) -> None:
        """The last ``/events`` record, ``kind=stop``."""
        self.write_message(Topic.EVENTS, log_time_ns, encode(event_payload(EventKind.STOP, reason, detail)))

    def finish(self, stop_reason: str | None) -> None:
        """Summary metadata, footer; flush, fsync and close the file."""
        self._writer.add_metadata(RECORDING_METADATA, self.summary(stop_reason))
        self._writer.finish()
        self.file.flush()
        if self.fsync:
            os.fsync(self.file.fileno())
        self.file.close()

    def close(self) -> None:
        """Close the file without finishing it (after a failure)."""
        try:
            self.file.close()
        except OSError:
            pass

    def summary(self, stop_reason: str | None) -> dict[str, str]:
        """The ``recording`` metadata record."""
        return {"mode": self.mode.name.lower(), "written": str(self.written), "dropped": str(self.dropped),
                "stop_reason": stop_reason or ""}

    def _register(self, spec: TopicSpec) -> int:
        schema = self._schemas.get(spec.schema_name)
        if schema is None:
            schema = self._writer.register_schema(spec.schema_name, SCHEMA_ENCODING, spec.schema_bytes())
            self._schemas[spec.schema_name] = schema
        channel = self._writer.register_channel(spec.name, MESSAGE_ENCODING, schema)
        self._channels[spec.topic] = channel
        return channel


__all__ = ["CHUNK_SIZE", "RECORDING_METADATA", "LogFileWriter", "RecordMode", "chunk_compression"]
