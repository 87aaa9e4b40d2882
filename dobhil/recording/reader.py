"""Validated reading of dobhil recordings.

:func:`open_log` checks a file before anything else reads it and turns every way
it can be unusable into one :class:`~dobhil.errors.LogFileError` line: missing,
empty, not MCAP (bad magic), truncated (no footer, e.g. after ``kill -9``). The
returned :class:`LogFile` uses the summary section (statistics, chunk indexes)
when the file has one and falls back to one linear scan when it has not.
"""

from __future__ import annotations

import io
import os
import struct
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from types import MappingProxyType
from typing import Any, Final

from mcap.exceptions import McapError
from mcap.reader import make_reader
from mcap.records import Footer
from mcap.stream_reader import StreamReader
from mcap.summary import Summary

from dobhil.errors import LogFileError
from dobhil.recording.filewriter import RECORDING_METADATA
from dobhil.recording.schemas import EventKind, Topic, decode, spec_for

MAGIC: Final = b"\x89MCAP0\r\n"
#: Opcode byte + length + three u64 fields + u32 crc, then the closing magic.
_FOOTER_TAIL: Final = 1 + 8 + 8 + 8 + 4 + len(MAGIC)


def _damage_errors() -> tuple[type[BaseException], ...]:
    """What mcap and its decompressors raise on damaged or cut data."""
    errors: list[type[BaseException]] = [McapError, struct.error, ValueError, EOFError, KeyError, RuntimeError]
    try:
        import zstandard
    except ImportError:
        return tuple(errors)
    return (*errors, zstandard.ZstdError)


#: Errors the mcap library and the decompressors raise on damaged data.
DAMAGE_ERRORS: Final = _damage_errors()
_DAMAGED: Final = DAMAGE_ERRORS

Message = tuple[str, int, dict[str, Any]]


@dataclass(frozen=True)
class ChannelInfo:
    """One channel of a recording and how many messages it holds."""

    topic: str
    schema_name: str
    message_encoding: str
    message_count: int


@dataclass(frozen=True)
class LogInfo:
    """What ``dobhil log info`` shows about a recording."""

    path: str
    channels: tuple[ChannelInfo, ...]
    message_count: int
    start_ns: int
    end_ns: int
    metadata: Mapping[str, Mapping[str, str]]
    attachments: tuple[str, ...]
    stop_reason: str | None
    dropped: int | None
    has_summary: bool

    @property
    def duration_s(self) -> float:
        """Time between the first and the last message."""
        return (self.end_ns - self.start_ns) / 1e9

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON-ready dict (``dobhil log info --json``)."""
        out = {f.name: getattr(self, f.name) for f in fields(self)}
        out["channels"] = [asdict(c) for c in self.channels]
        out["metadata"] = {k: dict(v) for k, v in self.metadata.items()}
        out["attachments"] = list(self.attachments)
        out["duration_s"] = self.duration_s
        return out


def _fail(path: str | os.PathLike[str], what: str) -> LogFileError:
    return LogFileError(f"{os.fspath(path)}: {what}")


def check_mcap_head(path: str | os.PathLike[str]) -> int:
    """Size of ``path`` after checking it exists, is not empty and starts like MCAP."""
    p = Path(path)
    if not p.exists():
        raise _fail(path, "no such file")
    if not p.is_file():
        raise _fail(path, "not a regular file")
    size = p.stat().st_size
    if size == 0:
        raise _fail(path, "empty file")
    with open(p, "rb") as f:
        if f.read(len(MAGIC)) != MAGIC:
            raise _fail(path, "not an MCAP file (bad magic)")
    return size


def _read_footer(path: str | os.PathLike[str], size: int) -> Footer:
    truncated = _fail(path, "truncated (no footer); try `dobhil log recover`")
    if size < len(MAGIC) + _FOOTER_TAIL:
        raise truncated
    with open(path, "rb") as f:
        f.seek(size - _FOOTER_TAIL)
        tail = f.read()
        if tail[-len(MAGIC):] != MAGIC:
            raise truncated
        try:
            record = next(StreamReader(io.BytesIO(tail), skip_magic=True).records)
        except _DAMAGED as exc:
            raise truncated from exc
    if not isinstance(record, Footer) or record.summary_start >= size:
        raise truncated
    return record


def _read_summary(path: str | os.PathLike[str], footer: Footer) -> Summary | None:
    if footer.summary_start == 0:
        return None
    try:
        with open(path, "rb") as f:
            return make_reader(f).get_summary()
    except _DAMAGED as exc:
        raise _fail(path, f"damaged summary ({exc}); try `dobhil log recover`") from exc


def open_log(path: str | os.PathLike[str]) -> LogFile:
    """A validated recording; LogFileError (one line) if it cannot be read."""
    size = check_mcap_head(path)
    footer = _read_footer(path, size)
    return LogFile(Path(path), _read_summary(path, footer))


class LogFile:
    """A validated MCAP recording; each method opens the file for its own use."""

    def __init__(self, path: Path, summary: Summary | None) -> None:
        self.path = path
        self._summary = summary

    @property
    def has_summary(self) -> bool:
        """Whether the file has a summary section (every clean dobhil recording has)."""
        return self._summary is not None

    def topics(self) -> tuple[str, ...]:
        """Topic names of every channel, in channel order."""
        return tuple(c.topic for c in self.channels())

    def channels(self) -> tuple[ChannelInfo, ...]:
        """Channels with their message counts."""
        if self._summary is None:
            return self._scan_channels()
        stats = self._summary.statistics
        counts = stats.channel_message_counts if stats is not None else {}
        return tuple(self._channel_info(c.id, counts.get(c.id, 0)) for c in self._summary.channels.values())

    def _channel_info(self, channel_id: int, count: int) -> ChannelInfo:
        assert self._summary is not None
        channel = self._summary.channels[channel_id]
        schema = self._summary.schemas.get(channel.schema_id)
        return ChannelInfo(channel.topic, schema.name if schema else "", channel.message_encoding, count)

    def _scan_channels(self) -> tuple[ChannelInfo, ...]:
        counts: dict[tuple[str, str, str], int] = {}
        with open(self.path, "rb") as f:
            for schema, channel, _ in self._guard(make_reader(f).iter_messages(log_time_order=False)):
                key = (channel.topic, schema.name if schema else "", channel.message_encoding)
                counts[key] = counts.get(key, 0) + 1
        return tuple(ChannelInfo(*key, count) for key, count in counts.items())

    def time_range(self) -> tuple[int, int]:
        """(first, last) message log time in ns; (0, 0) when there are no messages."""
        stats = self._summary.statistics if self._summary is not None else None
        if stats is not None:
            return stats.message_start_time, stats.message_end_time
        times = [t for _, t, _ in self.iter_messages()]
        return (min(times), max(times)) if times else (0, 0)

    def metadata(self) -> Mapping[str, Mapping[str, str]]:
        """Metadata records by name (config, versions, bus, run, recording)."""
        with open(self.path, "rb") as f:
            records = {m.name: MappingProxyType(dict(m.metadata)) for m in self._guard(make_reader(f).iter_metadata())}
        return MappingProxyType(records)

    def attachments(self) -> tuple[tuple[str, str, bytes], ...]:
        """Attachments as (name, media_type, data)."""
        with open(self.path, "rb") as f:
            return tuple((a.name, a.media_type, a.data) for a in self._guard(make_reader(f).iter_attachments()))

    def iter_messages(self, topics: Iterable[str | Topic] | None = None) -> Iterator[Message]:
        """(topic, log_time_ns, payload) in log-time order, optionally for some topics."""
        wanted = None if topics is None else [self._topic_name(t) for t in topics]
        with open(self.path, "rb") as f:
            for _, channel, message in self._guard(make_reader(f).iter_messages(topics=wanted)):
                yield channel.topic, message.log_time, decode(message.data)

    def _topic_name(self, topic: str | Topic) -> str:
        return spec_for(topic).name if isinstance(topic, Topic) else topic

    def require_topic(self, topic: str) -> None:
        """LogFileError naming the available topics if ``topic`` is not recorded."""
        available = self.topics()
        if topic not in available:
            listed = ", ".join(available) or "none"
            raise _fail(self.path, f"no topic {topic!r}; available: {listed}")

    def schema_properties(self, topic: str) -> tuple[str, ...]:
        """Property names of a topic's JSON schema, as stored in the file."""
        self.require_topic(topic)
        with open(self.path, "rb") as f:
            reader = make_reader(f)
            summary = self._summary or _scan_summary(reader)
        for channel in summary.channels.values():
            schema = summary.schemas.get(channel.schema_id)
            if channel.topic == topic and schema is not None and schema.data:
                return tuple(decode(schema.data).get("properties", {}))
        return ()

    def stop_reason(self) -> str | None:
        """Reason of the last ``/events`` record of kind stop, if any."""
        if "/events" not in self.topics():
            return None
        reasons = [p["reason"] for _, _, p in self.iter_messages(["/events"]) if p.get("kind") == _STOP]
        return reasons[-1] if reasons else None

    def info(self) -> LogInfo:
        """Channels, counts, time range, metadata, attachments and stop reason."""
        channels = self.channels()
        start, end = self.time_range()
        metadata = self.metadata()
        dropped = metadata.get(RECORDING_METADATA, {}).get("dropped")
        return LogInfo(
            path=os.fspath(self.path),
            channels=channels,
            message_count=sum(c.message_count for c in channels),
            start_ns=start,
            end_ns=end,
            metadata=metadata,
            attachments=tuple(name for name, _, _ in self.attachments()),
            stop_reason=self.stop_reason(),
            dropped=None if dropped is None else int(dropped),
            has_summary=self.has_summary,
        )

    def _guard(self, records: Iterator[Any]) -> Iterator[Any]:
        """Re-raise mcap's damage errors as one-line LogFileErrors."""
        try:
            yield from records
        except _DAMAGED as exc:
            raise _fail(self.path, f"damaged data ({exc}); try `dobhil log recover`") from exc


_STOP: Final = EventKind.STOP.name.lower()


def _scan_summary(reader: Any) -> Summary:
    """Schemas and channels of a file without summary, by reading its messages."""
    summary = Summary()
    for schema, channel, _ in reader.iter_messages(log_time_order=False):
        summary.channels[channel.id] = channel
        if schema is not None:
            summary.schemas[schema.id] = schema
    return summary


__all__ = ["ChannelInfo", "LogFile", "LogInfo", "MAGIC", "check_mcap_head", "open_log"]
