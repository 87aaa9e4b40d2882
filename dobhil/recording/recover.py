"""Salvage a recording cut short (``kill -9``, power loss) into a new, valid MCAP file.

The damaged file is read front to back with :class:`mcap.stream_reader.StreamReader`
(chunks emitted whole, so one damaged chunk costs only that chunk). Reading stops
at the first record that cannot be read, normally the end of the data; every
complete schema, channel, message, metadata record and attachment before it is
written to a new file, which gets a fresh summary and index.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import BinaryIO, Final

from mcap.records import Attachment, Channel, Chunk, Footer, McapRecord, Message, Metadata, Schema
from mcap.stream_reader import StreamReader, breakup_chunk
from mcap.writer import Writer

from dobhil import __version__
from dobhil.errors import LogFileError
from dobhil.recording.reader import DAMAGE_ERRORS, check_mcap_head
from dobhil.recording.filewriter import CHUNK_SIZE, chunk_compression

ProgressFn = Callable[[int], None]

#: Errors that mean "the data ends or is damaged here".
_DAMAGED: Final[tuple[type[BaseException], ...]] = (*DAMAGE_ERRORS, MemoryError)
#: Largest record a recovery will try to read (a damaged length field must not allocate GiBs).
_RECORD_LIMIT: Final = 1 << 30


@dataclass(frozen=True)
class RecoveryReport:
    """What :func:`recover` salvaged."""

    source: str
    output: str
    counts: tuple[tuple[str, int], ...]
    start_ns: int
    end_ns: int
    metadata: int
    attachments: int
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
    """Copies records into ``writer``, renumbering schemas and channels."""

    writer: Writer
    progress: ProgressFn | None
    schemas: dict[int, int] = field(default_factory=dict)
    channels: dict[int, int] = field(default_factory=dict)
    topics: dict[int, str] = field(default_factory=dict)
    pending_schemas: dict[int, Schema] = field(default_factory=dict)
    counts: dict[str, int] = field(default_factory=dict)
    start_ns: int | None = None
    end_ns: int = 0
    metadata: int = 0
    attachments: int = 0
    skipped_chunks: int = 0
    complete: bool = False

    def copy(self, record: McapRecord) -> None:
        if isinstance(record, Chunk):
            self._copy_chunk(record)
        elif isinstance(record, Schema):
            self.pending_schemas.setdefault(record.id, record)
        elif isinstance(record, Channel):
            self._channel(record)
        elif isinstance(record, Message):
            self._message(record)
        elif isinstance(record, Metadata):
            self.writer.add_metadata(record.name, record.metadata)
            self.metadata += 1
        elif isinstance(record, Attachment):
            self._attachment(record)
        elif isinstance(record, Footer):
            self.complete = True

    def _copy_chunk(self, chunk: Chunk) -> None:
        try:
            records = breakup_chunk(chunk, validate_crc=True)
        except _DAMAGED:
            self.skipped_chunks += 1
            return
        for record in records:
            self.copy(record)

    def _schema(self, schema_id: int) -> int:
        if schema_id == 0:
            return 0
        if schema_id not in self.schemas:
            schema = self.pending_schemas.get(schema_id)
            if schema is None:
                return 0
            self.schemas[schema_id] = self.writer.register_schema(schema.name, schema.encoding, schema.data)
        return self.schemas[schema_id]

    def _channel(self, channel: Channel) -> None:
        if channel.id in self.channels:
            return
        schema_id = self._schema(channel.schema_id)
        self.channels[channel.id] = self.writer.register_channel(
            channel.topic, channel.message_encoding, schema_id, channel.metadata
        )
        self.topics[channel.id] = channel.topic

    def _message(self, message: Message) -> None:
        channel_id = self.channels.get(message.channel_id)
        if channel_id is None:
            return  # its channel record was lost: nothing can decode it
        self.writer.add_message(channel_id, message.log_time, message.data, message.publish_time, message.sequence)
        topic = self.topics[message.channel_id]
        self.counts[topic] = self.counts.get(topic, 0) + 1
        self.start_ns = message.log_time if self.start_ns is None else min(self.start_ns, message.log_time)
        self.end_ns = max(self.end_ns, message.log_time)
        if self.progress is not None:
            self.progress(1)

    def _attachment(self, a: Attachment) -> None:
        self.writer.add_attachment(a.create_time, a.log_time, a.name, a.media_type, a.data)
        self.attachments += 1


def default_output(path: str | os.PathLike[str]) -> Path:
    """``run.mcap`` -> ``run.recovered.mcap``."""
    return Path(path).with_suffix(".recovered.mcap")


def _records(stream: BinaryIO) -> Iterator[McapRecord]:
    return StreamReader(stream, emit_chunks=True, record_size_limit=_RECORD_LIMIT).records


def _copy_all(source: BinaryIO, copier: _Copier) -> str:
    """Copy until the footer or the first unreadable record; say why it stopped."""
    try:
        for record in _records(source):
            copier.copy(record)
    except _DAMAGED as exc:
        return f"cut short or damaged at byte {source.tell()} ({type(exc).__name__})"
    return "footer reached" if copier.complete else "end of data"


def recover(
    path: str | os.PathLike[str],
    out: str | os.PathLike[str] | None = None,
    *,
    progress: ProgressFn | None = None,
) -> RecoveryReport:
    """Write every complete record of ``path`` to ``out`` (default ``*.recovered.mcap``)."""
    check_mcap_head(path)
    target = default_output(path) if out is None else Path(out)
    if target.resolve() == Path(path).resolve():
        raise LogFileError(f"{os.fspath(path)}: recovering onto the input file is refused; give -o OUT")
    try:
        sink = open(target, "wb")
    except OSError as exc:
        raise LogFileError(f"{os.fspath(target)}: cannot create: {exc.strerror}") from exc
    with sink, open(path, "rb") as source:
        writer = Writer(sink, chunk_size=CHUNK_SIZE, compression=chunk_compression())
        writer.start(profile="", library=f"dobhil/{__version__} recover")
        copier = _Copier(writer, progress)
        why = _copy_all(source, copier)
        writer.finish()
    return _report(path, target, copier, why)


def _report(path: str | os.PathLike[str], target: Path, c: _Copier, why: str) -> RecoveryReport:
    return RecoveryReport(
        source=os.fspath(path),
        output=os.fspath(target),
        counts=tuple(sorted(c.counts.items())),
        start_ns=c.start_ns or 0,
        end_ns=c.end_ns,
        metadata=c.metadata,
        attachments=c.attachments,
        complete=c.complete,
        skipped_chunks=c.skipped_chunks,
        stopped_because=why,
    )


__all__ = ["RecoveryReport", "default_output", "recover"]
