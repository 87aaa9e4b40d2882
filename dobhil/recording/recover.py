"""Salvage a log cut short (``kill -9``, power loss) or damaged into a new, complete file.

The file is read front to back, record by record, each parsed by the ``mcap`` package's record
classes and chunks CRC-checked. A record that does not read or check is skipped, and reading
goes on at the next record that does (:func:`_resync`): damage costs only the bytes it hit,
not everything after them. The schemas and channels come from wherever they can still be read:
the data (the first chunk holds them) or the summary section, which repeats them in a finished
file (read only when its CRC matches). A channel whose definition is lost everywhere has
messages that cannot be decoded: they are counted, not copied. The copy says what it lost in
its ``recover`` metadata record (:data:`RECOVER_METADATA`: the gaps' log times), so a reader
(``dobhil replay --verify``) can tell a missing stretch from a changed one; it is written
under a temporary name, renamed when complete.
"""

from __future__ import annotations

import json
import mmap
import os
import zlib
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace
from io import BytesIO
from pathlib import Path
from typing import Any, Final

from mcap.data_stream import ReadDataStream
from mcap.opcode import Opcode
from mcap.reader import make_reader
from mcap.records import (Attachment, AttachmentIndex, Channel, Chunk, ChunkIndex, DataEnd, Footer, Header,
                          McapRecord, Message, MessageIndex, Metadata, MetadataIndex, Schema, Statistics,
                          SummaryOffset)
from mcap.stream_reader import breakup_chunk
from mcap.writer import Writer

from dobhil.errors import LogFileError
from dobhil.files import atomic_path, check_output
from dobhil.recording import cycles
from dobhil.recording.layouts import cycle_lane
from dobhil.recording.reader import MAGIC, RECOVER_METADATA, check_library, check_mcap_head, summary_intact
from dobhil.recording.schemas import TOPIC_SPECS
from dobhil.recording.writer import CHUNK_SIZE, COMPRESSION, LIBRARY

ProgressFn = Callable[[int], None]

#: Opcode -> reader of the record's body (the ``mcap`` package's record classes).
_READERS: Final[Mapping[int, Callable[[ReadDataStream], McapRecord]]] = {
    Opcode.HEADER: Header.read, Opcode.FOOTER: Footer.read, Opcode.SCHEMA: Schema.read,
    Opcode.CHANNEL: Channel.read, Opcode.CHUNK: Chunk.read, Opcode.MESSAGE_INDEX: MessageIndex.read,
    Opcode.CHUNK_INDEX: ChunkIndex.read, Opcode.ATTACHMENT: Attachment.read,
    Opcode.ATTACHMENT_INDEX: AttachmentIndex.read, Opcode.STATISTICS: Statistics.read,
    Opcode.METADATA: Metadata.read, Opcode.METADATA_INDEX: MetadataIndex.read,
    Opcode.SUMMARY_OFFSET: SummaryOffset.read, Opcode.DATA_END: DataEnd.read,
}
_HEAD: Final = 1 + 8            # a record's opcode and length
_FOOTER_SIZE: Final = _HEAD + 8 + 8 + 4


def _frame(data: Any, pos: int) -> tuple[int, int] | None:
    """(opcode, body length) of the record at ``pos`` when it could be one: a known opcode and
    a length that ends inside the file; None otherwise.

    The MCAP spec's framing (https://mcap.dev/spec: an opcode byte, a little-endian uint64
    length, the body) read by hand: the ``mcap`` package's :class:`~mcap.stream_reader.StreamReader`
    reads a stream from its start and stops at the first bad record, and has no way to start
    again at a chosen byte, which skipping a damaged record needs."""
    if pos + _HEAD > len(data) or data[pos] not in _READERS:
        return None
    length = int.from_bytes(data[pos + 1:pos + _HEAD], "little")
    return (data[pos], length) if pos + _HEAD + length <= len(data) else None


def _attachment_crc(body: bytes) -> int:
    """An Attachment's crc: its body's last 4 bytes, of every byte before them (the MCAP spec;
    the ``mcap`` package's :class:`~mcap.records.Attachment` reads past it)."""
    return int.from_bytes(body[-4:], "little")


def _parse(data: Any, pos: int, crcs: bool = True) -> tuple[McapRecord, int] | None:
    """The record at ``pos`` and the byte after it, when it reads exactly its length and (with
    ``crcs``) a chunk's or attachment's CRC matches; None otherwise."""
    framed = _frame(data, pos)
    if framed is None:
        return None
    opcode, length = framed
    body = bytes(data[pos + _HEAD:pos + _HEAD + length])
    stream = ReadDataStream(BytesIO(body))
    try:
        record = Message.read(stream, length) if opcode == Opcode.MESSAGE else _READERS[opcode](stream)
        if stream.count != length:
            return None
        if crcs and isinstance(record, Chunk) and record.uncompressed_crc:
            breakup_chunk(record, validate_crc=True)
        if crcs and isinstance(record, Attachment) and _attachment_crc(body) not in (0, zlib.crc32(body[:-4])):
            return None
    except Exception:   # mcap, zstd and struct errors alike: the bytes are not this record
        return None
    return record, pos + _HEAD + length


def _closing(data: Any, pos: int) -> bool:
    """True when the file's closing magic, and nothing else, is at ``pos``."""
    return pos == len(data) - len(MAGIC) and bytes(data[pos:]) == MAGIC


def _checks(data: Any, pos: int) -> bool:
    """True when a record that reads and checks starts at ``pos``: a chunk or attachment
    whose CRC matches, or another record followed by one that could be a record (or by the
    file's closing magic), so that no byte run that happens to parse is taken for one."""
    parsed = _parse(data, pos)
    if parsed is None:
        return False
    record, end = parsed
    if (isinstance(record, Chunk) and record.uncompressed_crc) or (
            isinstance(record, Attachment) and _attachment_crc(bytes(data[end - 4:end]))):
        return True   # its CRC matched
    return _closing(data, end) or _frame(data, end) is not None


def _resync(data: Any, start: int) -> int | None:
    """The first byte at or after ``start`` where a record that reads and checks begins."""
    for pos in range(start, len(data) - _HEAD + 1):
        if data[pos] in _READERS and _checks(data, pos):
            return pos
    return None


@dataclass(frozen=True)
class Skipped:
    """Bytes of the source that could not be read (a damaged chunk or record, or a run of
    bytes between two readable records), what they held when known."""

    offset: int
    length: int
    what: str                     # "a damaged chunk", "a damaged Metadata record", "unreadable bytes"
    chunks: int = 0               # chunks lost (by the summary's chunk index when the bytes are not framed)
    messages: int | None = None   # messages lost (by the message indexes), None when not known
    start_ns: int | None = None   # log times the lost chunks held, None when not known
    end_ns: int | None = None
    after_ns: int | None = None   # the last log time copied before it and the first after (None: none)
    before_ns: int | None = None

    def line(self, stamp: Callable[[int], str] = str) -> str:
        held = [f"{self.length} bytes"]
        if self.chunks and self.what != "a damaged chunk":
            held.append(f"{self.chunks} chunks")
        if self.messages is not None:
            held.append(f"{self.messages} messages")
        text = f"skipped {self.what} at byte {self.offset} ({', '.join(held)})"
        if self.start_ns is not None and self.end_ns is not None:
            return f"{text}: log time {stamp(self.start_ns)} .. {stamp(self.end_ns)} lost"
        if self.after_ns is not None or self.before_ns is not None:
            after = "the start" if self.after_ns is None else stamp(self.after_ns)
            before = "the end" if self.before_ns is None else stamp(self.before_ns)
            return f"{text}: lost what was logged between {after} and {before}"
        return text


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
    skipped: tuple[Skipped, ...] = ()
    #: (channel id, messages) of channels whose definition was lost everywhere: not copied
    undefined: tuple[tuple[int, int], ...] = ()

    @property
    def message_count(self) -> int:
        return sum(n for _, n in self.counts)

    @property
    def duration_s(self) -> float:
        return (self.end_ns - self.start_ns) / 1e9

    def problems(self, stamp: Callable[[int], str] = str) -> list[str]:
        """One line per problem: each skipped stretch, each channel whose messages were lost
        with its definition."""
        lines = [s.line(stamp) for s in self.skipped]
        lines += [f"lost {n} messages of channel {cid}: its channel record was in damaged bytes and is repeated "
                  "nowhere readable" for cid, n in self.undefined]
        return lines


@dataclass
class _Copier:
    """Copies records into ``writer``, schemas and channels renumbered; a channel not defined
    by the data so far taken from ``known`` (the summary's)."""

    writer: Writer
    progress: ProgressFn | None
    known_schemas: Mapping[int, Schema]
    known_channels: Mapping[int, Channel]
    schemas: dict[int, Schema] = field(default_factory=dict)
    ids: dict[int, int] = field(default_factory=dict)  # schema id in the source -> in the copy
    channels: dict[int, tuple[int, str]] = field(default_factory=dict)
    counts: dict[str, int] = field(default_factory=dict)
    undefined: dict[int, int] = field(default_factory=dict)
    times: tuple[int, int] | None = None  # first, last log time
    last_ns: int | None = None            # the last log time copied
    skipped: list[Skipped] = field(default_factory=list)
    open_gaps: list[int] = field(default_factory=list)   # skipped entries waiting for the next log time
    counting: int | None = None           # the skipped chunk the message indexes that follow count for
    complete: bool = False
    earlier: list[list[int | None]] = field(default_factory=list)   # gaps of a source recovered before
    #: a cycle channel's id in the source -> its lane's prefix (``/axis/left``; "" for one axis)
    cycle_lanes: dict[int, str] = field(default_factory=dict)
    #: topic -> messages the copied cycle messages hold (what the writer's lost summary counted)
    folded: dict[str, int] = field(default_factory=dict)

    def skip(self, entry: Skipped) -> None:
        self.skipped.append(replace(entry, after_ns=self.last_ns))
        self.open_gaps.append(len(self.skipped) - 1)
        self.counting = len(self.skipped) - 1 if entry.what == "a damaged chunk" else None

    def copy(self, record: McapRecord, offset: int, length: int) -> None:
        if isinstance(record, MessageIndex):
            if self.counting is not None:   # the index of a skipped chunk counts what it held
                entry = self.skipped[self.counting]
                self.skipped[self.counting] = replace(entry, messages=(entry.messages or 0) + len(record.records))
            return
        self.counting = None
        if isinstance(record, Chunk):
            try:
                records = breakup_chunk(record, validate_crc=True)
            except Exception:  # a damaged chunk: skip it, keep the rest
                self.skip(Skipped(offset, length, "a damaged chunk", 1, None, record.message_start_time,
                                  record.message_end_time))
                return
            for inner in records:
                self.copy(inner, offset, length)
        elif isinstance(record, Schema):
            self.schemas.setdefault(record.id, record)
        elif isinstance(record, Channel) and record.id not in self.channels:
            self._define(record)
        elif isinstance(record, Message):
            self._message(record)
        elif isinstance(record, Metadata) and record.name == RECOVER_METADATA:   # the source's own gaps: kept
            try:
                self.earlier += json.loads(record.metadata.get("gaps", "[]"))
            except ValueError:
                pass
        elif isinstance(record, Metadata):
            self.writer.add_metadata(record.name, record.metadata)
        elif isinstance(record, Attachment):
            self.writer.add_attachment(record.create_time, record.log_time, record.name, record.media_type,
                                       record.data)
        elif isinstance(record, Footer):
            self.complete = True

    def _define(self, channel: Channel) -> None:
        schema = self.schemas.get(channel.schema_id) or self.known_schemas.get(channel.schema_id)
        if schema is not None and channel.schema_id not in self.ids:
            self.ids[channel.schema_id] = self.writer.register_schema(schema.name, schema.encoding, schema.data)
        self.channels[channel.id] = (self.writer.register_channel(
            channel.topic, channel.message_encoding, self.ids.get(channel.schema_id, 0), channel.metadata),
            channel.topic)
        lane = cycle_lane(schema, channel)
        if lane is not None:
            self.cycle_lanes[channel.id] = lane

    def _message(self, message: Message) -> None:
        if message.channel_id not in self.channels:
            known = self.known_channels.get(message.channel_id)
            if known is None:
                self.undefined[message.channel_id] = self.undefined.get(message.channel_id, 0) + 1
                return
            self._define(known)
        channel, topic = self.channels[message.channel_id]
        self.writer.add_message(channel, message.log_time, message.data, message.publish_time, message.sequence)
        self.counts[topic] = self.counts.get(topic, 0) + 1
        lane = self.cycle_lanes.get(message.channel_id)
        if lane is not None:
            self._fold(lane, message.data)
        first, last = self.times or (message.log_time, message.log_time)
        self.times = (min(first, message.log_time), max(last, message.log_time))
        self.last_ns = message.log_time
        for i in self.open_gaps:
            self.skipped[i] = replace(self.skipped[i], before_ns=message.log_time)
        self.open_gaps.clear()
        if self.progress is not None:
            self.progress(1)

    def _fold(self, lane: str, data: bytes) -> None:
        """Count what a cycle message holds (as the writer's summary did, lost with the end);
        a message that is no cycle is copied as it is and left to the reader to refuse."""
        try:
            held = cycles.held(data)
        except ValueError:
            return
        for topic, n in held.items():
            name = lane + TOPIC_SPECS[topic].name
            self.folded[name] = self.folded.get(name, 0) + n

    def gaps(self) -> list[list[int | None]]:
        """[after, before] log times of each skipped stretch that held messages (or may have),
        with the gaps of a source recovered before, in log time order (None first: before any message)."""
        gaps = self.earlier + [[s.after_ns, s.before_ns] for s in self.skipped if s.messages != 0]
        return sorted(gaps, key=lambda g: -1 if g[0] is None else g[0])


@dataclass(frozen=True)
class _Summary:
    """What a finished file's summary section repeats, when its CRC matches."""

    schemas: Mapping[int, Schema] = field(default_factory=dict)
    channels: Mapping[int, Channel] = field(default_factory=dict)
    chunks: tuple[ChunkIndex, ...] = ()


def _summary(f: Any, data: Any) -> _Summary:
    """The schemas, channels and chunk index of the summary section (read by the ``mcap``
    package's reader) when the file ends in a footer and the summary's CRC matches; none otherwise."""
    footer_at = len(data) - len(MAGIC) - _FOOTER_SIZE
    parsed = _parse(data, footer_at) if footer_at > len(MAGIC) and bytes(data[-len(MAGIC):]) == MAGIC else None
    if parsed is None or not isinstance(parsed[0], Footer) or not summary_intact(f, footer_at, parsed[0]):
        return _Summary()
    try:
        summary = make_reader(f).get_summary()
    except Exception:   # a summary that does not read is no help: the data's own records are used
        return _Summary()
    if summary is None:
        return _Summary()
    return _Summary(dict(summary.schemas), dict(summary.channels), tuple(summary.chunk_indexes))


def _unframed(offset: int, end: int, summary: _Summary) -> Skipped:
    """Bytes between two readable records: the chunks the summary's index places there."""
    lost = [c for c in summary.chunks if offset <= c.chunk_start_offset < end]
    if not lost:   # no chunk there by a summary that lists them all; without one, not known
        return Skipped(offset, end - offset, "unreadable bytes", messages=0 if summary.chunks else None)
    return Skipped(offset, end - offset, "unreadable bytes", len(lost), None,
                   min(c.message_start_time for c in lost), max(c.message_end_time for c in lost))


def _framed(offset: int, length: int, opcode: int) -> Skipped:
    """One record whose framing holds but whose body does not read: a chunk (its messages,
    not known), a message, or a record that holds no message."""
    if opcode == Opcode.CHUNK:
        return Skipped(offset, length, "a damaged chunk", 1)
    name = Opcode(opcode).name.title().replace("_", "")
    return Skipped(offset, length, f"a damaged {name} record", messages=None if opcode == Opcode.MESSAGE else 0)


def default_output(path: str | os.PathLike[str]) -> Path:
    """``run.mcap`` -> ``run.recovered.mcap``."""
    return Path(path).with_suffix(".recovered.mcap")


def recover(path: str | os.PathLike[str], out: str | os.PathLike[str] | None = None, *,
            progress: ProgressFn | None = None) -> RecoveryReport:
    """Every readable record of ``path`` to ``out`` (default ``*.recovered.mcap``), damaged
    records and chunks skipped, what was skipped in the report and in the copy's
    :data:`RECOVER_METADATA` record."""
    size = check_mcap_head(path)
    target = check_output(default_output(path) if out is None else out, inputs=[path], suffix=".mcap", what="output",
                          new=True)
    with open(path, "rb") as source, mmap.mmap(source.fileno(), size, access=mmap.ACCESS_READ) as data:
        summary = _summary(source, data)
        header = _parse(data, len(MAGIC))
        if header is not None:   # another tool's MCAP is not made a dobhil log here
            check_library(path, header[0])
        with atomic_path(target) as tmp, open(tmp, "wb") as sink:
            writer = Writer(sink, chunk_size=CHUNK_SIZE, compression=COMPRESSION, enable_data_crcs=True)
            writer.start(profile="", library=f"{LIBRARY} recover")
            copier = _Copier(writer, progress, summary.schemas, summary.channels)
            why = _copy(data, copier, summary)
            if not copier.counts:   # an empty recording would only look like a recovered one
                undefined = (f"; {sum(copier.undefined.values())} messages of {len(copier.undefined)} channels "
                             "whose channel records were in damaged bytes" if copier.undefined else "")
                raise LogFileError(f"{os.fspath(path)}: no complete message to recover "
                                   f"({why or 'end of data'}{undefined}); nothing written")
            writer.add_metadata(RECOVER_METADATA, {
                "source": os.path.basename(os.fspath(path)), "messages": str(sum(copier.counts.values())),
                "skipped": json.dumps([[s.offset, s.length, s.what] for s in copier.skipped]),
                "gaps": json.dumps(copier.gaps()), "undefined": str(sum(copier.undefined.values())),
                "stopped": why or ("footer reached" if copier.complete else "end of data"),
                **({"folded": json.dumps(copier.folded, separators=(",", ":"))} if copier.folded else {})})
            writer.finish()
    first, last = copier.times or (0, 0)
    return RecoveryReport(source=os.fspath(path), output=os.fspath(target), counts=tuple(sorted(copier.counts.items())),
                          start_ns=first, end_ns=last, complete=copier.complete,
                          skipped_chunks=sum(s.chunks for s in copier.skipped),
                          stopped_because=why or ("footer reached" if copier.complete else "end of data"),
                          skipped=tuple(copier.skipped), undefined=tuple(sorted(copier.undefined.items())))


def _copy(data: Any, copier: _Copier, summary: _Summary) -> str:
    """Every record of the data section to ``copier``, a record that does not read skipped to
    the next that does; why it stopped ("" at the footer or the end of the data)."""
    pos, end = len(MAGIC), len(data)
    while pos < end:
        parsed = _parse(data, pos, crcs=False)   # a chunk's CRC is the copier's: it skips that chunk alone
        if parsed is None:
            if _closing(data, pos):   # a file's closing magic without the footer before it
                return ""
            framed = _frame(data, pos)
            # the record's own end first (only its body is damaged), else the next record that checks
            after = pos + _HEAD + framed[1] if framed is not None and _checks(data, pos + _HEAD + framed[1]) else None
            resume = after if after is not None else _resync(data, pos + 1)
            if resume is None:   # nothing readable after it: the file was cut here (or damaged to its end)
                return f"cut short or damaged at byte {pos}"
            if after is not None and framed is not None:
                copier.skip(_framed(pos, resume - pos, framed[0]))
            else:
                copier.skip(_unframed(pos, resume, summary))
            pos = resume
            continue
        record, after_record = parsed
        copier.copy(record, pos, after_record - pos)
        if isinstance(record, (DataEnd, Footer)):   # the summary section follows: read above, not data
            footer = _parse(data, end - len(MAGIC) - _FOOTER_SIZE)
            copier.complete = footer is not None and isinstance(footer[0], Footer)
            return ""
        pos = after_record
    return ""


__all__ = ["RECOVER_METADATA", "RecoveryReport", "Skipped", "default_output", "recover"]
