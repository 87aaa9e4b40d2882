"""Salvage a log cut short (``kill -9``, power loss) or damaged into a new, complete file: read
front to back with :class:`~mcap.stream_reader.StreamReader`, chunks whole and CRC-checked (a
damaged chunk costs only itself), until the first unreadable record; everything before goes to
a new file with a fresh summary, renamed when complete.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from mcap.records import Attachment, Channel, Chunk, Footer, McapRecord, Message, Metadata, Schema
from mcap.stream_reader import StreamReader, breakup_chunk
from mcap.writer import Writer

from dobhil.errors import LogFileError
from dobhil.files import atomic_path, check_output
from dobhil.recording.reader import check_library, check_mcap_head
from dobhil.recording.writer import CHUNK_SIZE, COMPRESSION, LIBRARY

ProgressFn = Callable[[int], None]


@dataclass(frozen=True)
class RecoveryReport:
    """What :func:`recover` salvaged."""

    source: str
    output: str
    counts: tuple[tuple[str, int], ...]
    start_ns: int
    end_ns: int
    complete: bool  # the source had its footer: nothing was cut
    skipped_chunks: int
    stopped_because: str

    @property
    def message_count(self) -> int:
        return sum(n for _, n in self.counts)

    @property
    def duration_s(self) -> float:
        return (self.end_ns - self.start_ns) / 1e9


@dataclass
class _Copier:
    """Copies records into ``writer``, schemas and channels renumbered."""

    writer: Writer
    progress: ProgressFn | None
    schemas: dict[int, Schema] = field(default_factory=dict)
    ids: dict[int, int] = field(default_factory=dict)  # schema id in the source -> in the copy
    channels: dict[int, tuple[int, str]] = field(default_factory=dict)
    counts: dict[str, int] = field(default_factory=dict)
    times: tuple[int, int] | None = None  # first, last log time
    skipped: int = 0
    complete: bool = False

    def copy(self, record: McapRecord) -> None:
        if isinstance(record, Chunk):
            try:
                records = breakup_chunk(record, validate_crc=True)
            except Exception:  # a damaged chunk: skip it, keep the rest
                self.skipped += 1
                return
            for inner in records:
                self.copy(inner)
        elif isinstance(record, Schema):
            self.schemas.setdefault(record.id, record)
        elif isinstance(record, Channel) and record.id not in self.channels:
            schema = self.schemas.get(record.schema_id)
            if schema is not None and record.schema_id not in self.ids:
                self.ids[record.schema_id] = self.writer.register_schema(schema.name, schema.encoding, schema.data)
            self.channels[record.id] = (self.writer.register_channel(
                record.topic, record.message_encoding, self.ids.get(record.schema_id, 0), record.metadata),
                record.topic)
        elif isinstance(record, Message) and record.channel_id in self.channels:
            channel, topic = self.channels[record.channel_id]
            self.writer.add_message(channel, record.log_time, record.data, record.publish_time, record.sequence)
            self.counts[topic] = self.counts.get(topic, 0) + 1
            first, last = self.times or (record.log_time, record.log_time)
            self.times = (min(first, record.log_time), max(last, record.log_time))
            if self.progress is not None:
                self.progress(1)
        elif isinstance(record, Metadata):
            self.writer.add_metadata(record.name, record.metadata)
        elif isinstance(record, Attachment):
            self.writer.add_attachment(record.create_time, record.log_time, record.name, record.media_type,
                                       record.data)
        elif isinstance(record, Footer):
            self.complete = True


def default_output(path: str | os.PathLike[str]) -> Path:
    """``run.mcap`` -> ``run.recovered.mcap``."""
    return Path(path).with_suffix(".recovered.mcap")


def recover(path: str | os.PathLike[str], out: str | os.PathLike[str] | None = None, *,
            progress: ProgressFn | None = None) -> RecoveryReport:
    """Every complete record of ``path`` to ``out`` (default ``*.recovered.mcap``)."""
    check_mcap_head(path)
    target = check_output(default_output(path) if out is None else out, inputs=[path], suffix=".mcap", what="output",
                          new=True)
    with atomic_path(target) as tmp, open(tmp, "wb") as sink, open(path, "rb") as source:
        writer = Writer(sink, chunk_size=CHUNK_SIZE, compression=COMPRESSION, enable_data_crcs=True)
        writer.start(profile="", library=f"{LIBRARY} recover")
        copier, pos, why = _Copier(writer, progress), 0, ""
        try:  # until the footer or the first unreadable record
            for record in StreamReader(source, emit_chunks=True, record_size_limit=os.fstat(source.fileno()).st_size
                                       ).records:
                if pos == 0:   # the header: another tool's MCAP is not made a dobhil log here
                    check_library(path, record)
                copier.copy(record)
                pos = source.tell()
        except LogFileError:
            raise
        except Exception as exc:  # the data ends or is damaged here
            why = f"cut short or damaged at byte {pos} ({type(exc).__name__})"
        if not copier.counts:   # an empty recording would only look like a recovered one
            raise LogFileError(f"{os.fspath(path)}: no complete message to recover "
                               f"({why or 'end of data'}); nothing written")
        writer.finish()
    first, last = copier.times or (0, 0)
    return RecoveryReport(source=os.fspath(path), output=os.fspath(target), counts=tuple(sorted(copier.counts.items())),
                          start_ns=first, end_ns=last, complete=copier.complete, skipped_chunks=copier.skipped,
                          stopped_because=why or ("footer reached" if copier.complete else "end of data"))


__all__ = ["RecoveryReport", "default_output", "recover"]
