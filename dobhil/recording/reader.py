"""Reading a dobhil log: :class:`LogFile`, checked before anything uses it. One pass with the
``mcap`` package's public :class:`~mcap.stream_reader.StreamReader` (data and chunk CRCs)
tells apart, one :class:`~dobhil.errors.LogFileError` line each: complete; cut short; damaged
at byte N; not a dobhil log (written by X); invalid metadata. Messages are then read chunk by
chunk at the offsets found, CRC-checked again, sliced with ``struct`` (the ``mcap`` reader's
object per record made replay spend most of its time reading).
"""

from __future__ import annotations

import json
import os
import struct
import zlib
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from contextvars import ContextVar
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from types import MappingProxyType
from typing import Any, BinaryIO, Final

from mcap.records import (Attachment, Channel, Chunk, DataEnd, Footer, Header, MessageIndex, Metadata, Schema,
                          Statistics)
from mcap.stream_reader import StreamReader, get_chunk_data_stream

from dobhil import __version__
from dobhil.errors import LogFileError, exception_line
from dobhil.files import input_problem
from dobhil.recording.encodings import Decoder, Encoding, RowDecoder, encoding
from dobhil.recording.layouts import cycle_lane
from dobhil.recording.schemas import SPECS_BY_SCHEMA, EventKind, Topic
from dobhil.recording.writer import RECORDING_METADATA

MAGIC: Final = b"\x89MCAP0\r\n"
#: Name of the metadata record a recovered log gets (dobhil/recording/recover.py): what it
#: lost and where, and what its cycle messages hold.
RECOVER_METADATA: Final = "recover"
_RECORD: Final = struct.Struct("<BQ")            # opcode, length
_MESSAGE: Final = struct.Struct("<HIQQ")         # channel, sequence, log time, publish time
_OP_MESSAGE: Final = 0x05
#: Numbers in metadata the tools use as numbers: (record, key) -> type.
_NUMERIC: Final = {("recording", "dropped"): int, ("recording", "written"): int, ("bus", "bitrate"): float,
                   ("bus", "data_bitrate"): float,
                   ("run", "torque_limit"): float, ("run", "period"): float, ("run", "duration"): float}
_STOP: Final = EventKind.STOP.name.lower()
_FRAME_NUMBERS: Final = (int(Topic.CAN_RX), int(Topic.CAN_TX))

@dataclass(frozen=True)
class ChannelInfo:
    topic: str
    schema_name: str
    message_encoding: str
    message_count: int


@dataclass(frozen=True)
class LogInfo:
    """What ``dobhil log info`` shows."""

    path: str
    channels: tuple[ChannelInfo, ...]
    message_count: int
    start_ns: int
    end_ns: int
    metadata: Mapping[str, Mapping[str, str]]
    attachments: tuple[str, ...]
    stop_reason: str | None
    dropped: int | None
    encoding: str = ""  # the channels' message encodings, e.g. "protobuf" ("json": before 0.2)
    layout: str = "topics"  # or "cycle": a message per control cycle (dobhil/recording/cycles.py)
    #: config record -> its keys this version does not know (:attr:`LogFile.unknown_config`)
    unknown_config_keys: Mapping[str, tuple[str, ...]] = field(default_factory=dict)
    #: topic -> messages the cycle messages hold of it (the cycle layout; the writer's count,
    #: or recover's, :meth:`LogFile.message_counts`)
    folded: Mapping[str, int] = field(default_factory=dict)

    @property
    def duration_s(self) -> float:
        return (self.end_ns - self.start_ns) / 1e9

    def to_dict(self) -> dict[str, Any]:
        return {**{f.name: getattr(self, f.name) for f in fields(self)}, "channels": [asdict(c) for c in self.channels],
                "metadata": {k: dict(v) for k, v in self.metadata.items()}, "duration_s": self.duration_s,
                "unknown_config_keys": {k: list(v) for k, v in self.unknown_config_keys.items()},
                "folded": dict(self.folded)}


def _fail(path: str | os.PathLike[str], what: str) -> LogFileError:
    return LogFileError(f"{os.fspath(path)}: {what}")


def check_mcap_head(path: str | os.PathLike[str]) -> int:
    """Size of ``path`` after checking it exists, is a non-empty file and starts like MCAP."""
    p = Path(path)
    problem = input_problem(p)  # no such file, a directory, a FIFO, a loop of links, ...
    if problem is not None:
        raise _fail(path, problem)
    size = p.stat().st_size
    if size == 0:
        raise _fail(path, "empty file")
    with open(p, "rb") as f:
        if f.read(len(MAGIC)) != MAGIC:
            raise _fail(path, "not an MCAP file (bad magic)")
    return size


def _records(f: BinaryIO, path: str | os.PathLike[str]) -> Iterator[tuple[int, Any]]:
    """(offset, record) to the footer, CRCs checked (each chunk's too); damage named by its byte."""
    records = StreamReader(f, emit_chunks=True, validate_crcs=True,
                           record_size_limit=os.fstat(f.fileno()).st_size).records
    while True:
        pos = f.tell()
        try:
            record = next(records)
            if isinstance(record, Chunk):
                get_chunk_data_stream(record, validate_crc=True)
        except StopIteration:
            return
        except Exception as exc:  # mcap, zstd, lz4 and struct errors alike: the bytes are wrong
            found = _uncovered_damage(f) if isinstance(getattr(exc, "record", None), DataEnd) else None
            at, why = found or (pos, exception_line(exc))
            raise _fail(path, f"damaged at byte {at} ({why}); "
                              "`dobhil log recover` saves the intact chunks") from exc
        yield pos, record
        if isinstance(record, Footer):
            return


def _uncovered_damage(f: BinaryIO) -> tuple[int, str] | None:
    """(byte, what) of the first record the data section's CRC caught that no CRC of its own
    covers: a message index whose entries are not its chunk's messages, or a chunk whose
    header's times are not its messages'; None when none disagrees (the damage is in a record
    nothing repeats: metadata, or the DataEnd record itself). The DataEnd record's CRC covers
    the whole data section, so where it fails names only the end of the damage's section."""
    here = f.tell()
    f.seek(0)
    try:
        expected: dict[int, list[tuple[int, int]]] = {}
        records = StreamReader(f, emit_chunks=True).records
        while True:
            pos = f.tell()
            record = next(records)
            if isinstance(record, Chunk):
                data = get_chunk_data_stream(record, validate_crc=True)[0].read(record.uncompressed_size)
                expected = _message_index(data)
                times = [t for entries in expected.values() for t, _ in entries]
                if times and (min(times), max(times)) != (record.message_start_time, record.message_end_time):
                    return pos, "the chunk's message times are not its messages'; the data section's CRC does not match"
            elif isinstance(record, MessageIndex) and sorted(record.records) != expected.get(record.channel_id, []):
                return pos, (f"the message index of channel {record.channel_id} does not match its chunk; "
                             "the data section's CRC does not match")
            elif isinstance(record, DataEnd):
                return None
    except Exception:   # the damage elsewhere (a record that no longer reads): the caller's byte stands
        return None
    finally:
        f.seek(here)


def _message_index(records: bytes) -> dict[int, list[tuple[int, int]]]:
    """Channel -> sorted (log time, offset) of its messages in a chunk's records: its message
    index as the MCAP spec defines it (offset: of the Message record in the uncompressed records)."""
    out: dict[int, list[tuple[int, int]]] = {}
    pos, end = 0, len(records)
    while pos < end:
        opcode, length = _RECORD.unpack_from(records, pos)
        if opcode == _OP_MESSAGE:
            channel, _, log_time, _ = _MESSAGE.unpack_from(records, pos + 9)
            out.setdefault(channel, []).append((log_time, pos))
        pos += 9 + length
    for entries in out.values():
        entries.sort()
    return out


#: bytes of a Footer record the summary's CRC covers: opcode, length, summary_start, summary_offset_start
_FOOTER_COVERED: Final = 1 + 8 + 8 + 8


def summary_intact(f: BinaryIO, footer_at: int, footer: Footer) -> bool:
    """False when the summary section's CRC (the MCAP spec's footer ``summary_crc``: every byte
    from the summary's start through the footer's ``summary_offset_start``; 0: not computed)
    does not match. The mcap reader does not check it."""
    if footer.summary_start == 0 or footer.summary_crc == 0:
        return True
    here = f.tell()
    f.seek(footer.summary_start)
    covered = f.read(footer_at + _FOOTER_COVERED - footer.summary_start)
    f.seek(here)
    return zlib.crc32(covered) == footer.summary_crc


def _check_summary(f: BinaryIO, path: str | os.PathLike[str], footer_at: int, footer: Footer) -> None:
    """The summary section checked by its CRC (:func:`summary_intact`): the summary is what
    ``dobhil log info`` counts messages with and where the channels' names come from: a
    flipped bit there would print false figures. Damage is named at the summary's first byte."""
    if not summary_intact(f, footer_at, footer):
        raise _fail(path, f"damaged at byte {footer.summary_start} (the summary section's CRC does not match); "
                          "`dobhil log recover` saves the intact chunks")


def check_library(path: str | os.PathLike[str], header: Any) -> None:
    """LogFileError unless ``header`` is a dobhil log's (its library ``dobhil/...``): another
    tool's MCAP has none of the topics, schemas and metadata the commands read."""
    if not isinstance(header, Header) or not header.library.startswith("dobhil/"):
        library = getattr(header, "library", "") or "an unnamed writer"
        raise _fail(path, f"not a dobhil log (written by {library!r})")


def unknown_config_keys(record: Mapping[str, str] | None) -> tuple[str, ...]:
    """The keys of a recorded config (a ``config`` or ``axis/<name>/config`` record) that this
    version's config schema (:func:`dobhil.config.key_fields`) does not know: a log of a newer
    dobhil, whose run used keys this one cannot apply."""
    if not record:
        return ()
    from dobhil.config import key_fields
    known = key_fields()
    return tuple(k for k in record if k not in known)


def unknown_keys_problem(what: str, keys: Sequence[str], library: str) -> str:
    """The line a command that needs the config refuses a log with: ``what`` (``its recorded
    config``) has ``keys`` this version does not know; ``library``: the log's writer."""
    return (f"{what} has keys dobhil {__version__} does not know: {', '.join(keys)} (the log was written by "
            f"{library or 'an unnamed writer'}); `dobhil log info`, `log export` and `log serve` still read it")


def unknown_keys_note(unknown: Mapping[str, Sequence[str]]) -> str:
    """One line for the commands that read such a log without its config (``log info``,
    ``log export``, ``log serve``): the recorded config's keys this version does not know, by
    config record (``config``; ``axis/<name>/config`` of a several-axis log), and that the
    commands that need the config refuse the log."""
    where = "; ".join(("" if name == "config" else f"axis {name.split('/')[1]}: ") + ", ".join(keys)
                      for name, keys in unknown.items())
    return (f"the recorded config has keys dobhil {__version__} does not know ({where}); commands that need "
            "the config (replay, report, identify, compare) refuse this log")


def recorded_config(path: str | os.PathLike[str], record: Mapping[str, str], axis: str | None = None) -> Any:
    """The :class:`~dobhil.config.Config` a recorded config record holds (``axis``: that axis'
    of a several-axis log); LogFileError naming a value the config schema refuses (a crafted
    or damaged log: a value out of range would make replay and report compute nonsense)."""
    from dobhil.config import build_config
    of = "" if axis is None else f" of axis {axis}"
    try:
        return build_config({k: json.loads(v) for k, v in record.items()},
                            source=f"{os.fspath(path)}{'' if axis is None else f' axis {axis}'} config")
    except (ValueError, TypeError) as exc:
        raise _fail(path, f"invalid recorded config{of}: {exception_line(exc, named=False)}") from None


def axis_config_records(metadata: Mapping[str, Mapping[str, str]]) -> dict[str, Mapping[str, str]]:
    """Axis name -> its recorded config of a several-axis log (``axis/<name>/config`` over the
    run's ``config``, as :class:`dobhil.recording.axes.AxisLog` reads it); {}: a single-axis log."""
    run = metadata.get("config", {})
    return {name.split("/")[1]: {**run, **record} for name, record in metadata.items()
            if name.startswith("axis/") and name.endswith("/config") and name.count("/") == 2}


def _validate_metadata(path: str | os.PathLike[str], metadata: Mapping[str, Mapping[str, str]],
                       library: str = "", *, describe: bool = False) -> Any:
    """The recorded :class:`~dobhil.config.Config` (None without one); LogFileError naming a bad
    value or the keys this version does not know (``describe``: None for those, the file
    described without its config). Each axis' config of a several-axis log is checked the
    same way, but an axis whose config has keys this version does not know is left to
    :class:`dobhil.recording.axes.AxisLog`, which refuses that axis alone (the other axes
    stay readable)."""
    for (name, key), kind in _NUMERIC.items():
        value = metadata.get(name, {}).get(key)
        if value is not None:
            try:
                kind(value)
            except ValueError:
                raise _fail(path, f"metadata {name}.{key} = {value!r} is not a number") from None
    for axis, axis_record in axis_config_records(metadata).items():
        if not unknown_config_keys(axis_record):
            recorded_config(path, axis_record, axis)
    record = metadata.get("config")
    if not record:
        return None
    unknown = unknown_config_keys(record)
    if unknown:
        if describe:
            return None
        raise _fail(path, unknown_keys_problem("its recorded config", unknown, library))
    return recorded_config(path, record)


class LogFile:
    """A complete, checked dobhil log, opened and checked at once; nothing is held open
    between reads. ``describe``: a recorded config with keys this version does not know
    (:attr:`unknown_config`) is no refusal, ``config`` is then None: the commands that read
    what was recorded without applying the config (``dobhil log info``, ``log export``, ``log
    serve``) open a newer dobhil's log so and say :func:`unknown_keys_note`; every command
    that needs the config opens without it and so refuses such a log in one line."""

    def __init__(self, path: str | os.PathLike[str], *, describe: bool = False) -> None:
        size = check_mcap_head(path)
        self.path, self.library = Path(path), ""
        self.schemas: dict[int, Schema] = {}
        self.channel_records: dict[int, Channel] = {}
        self.metadata: dict[str, Mapping[str, str]] = {}
        self.attachments: list[tuple[str, str, bytes]] = []
        self.chunks: list[tuple[int, int]] = []  # (offset, uncompressed size)
        self.statistics: Statistics | None = None
        self._decoders: dict[int, Decoder] = {}
        with open(path, "rb") as f:
            f.seek(max(0, size - len(MAGIC)))
            if f.read() != MAGIC or size < 2 * len(MAGIC) + 9:
                f.seek(len(MAGIC))
                try:
                    check_library(path, next(StreamReader(f, skip_magic=True).records))
                except LogFileError:
                    raise
                except Exception:
                    pass  # not even a header: cut short is all we know
                raise _fail(path, "cut short (no footer): run `dobhil log recover` on it")
            f.seek(0)
            for pos, record in _records(f, path):
                if isinstance(record, Header):
                    self.library = record.library
                    check_library(path, record)
                elif isinstance(record, Schema):
                    self.schemas[record.id] = record
                elif isinstance(record, Channel):
                    self.channel_records[record.id] = record
                elif isinstance(record, Metadata):
                    self.metadata[record.name] = MappingProxyType(dict(record.metadata))
                elif isinstance(record, Attachment):
                    self.attachments.append((record.name, record.media_type, record.data))
                elif isinstance(record, Chunk):
                    self.chunks.append((pos, record.uncompressed_size))
                elif isinstance(record, Statistics):
                    self.statistics = record
                elif isinstance(record, Footer):
                    _check_summary(f, path, pos, record)
        #: record name (``config``, ``axis/<name>/config``) -> its keys this version does not know
        self.unknown_config: dict[str, tuple[str, ...]] = {
            name: keys for name, record in self.metadata.items()
            if (name == "config" or name.startswith("axis/") and name.endswith("/config"))
            and (keys := unknown_config_keys(record))}
        #: cycle channel (the cycle layout, dobhil/recording/cycles.py) -> topic number -> the
        #: channel its messages are read as: a channel of the file on that topic, else one of
        #: :attr:`folded_channels`, which only this reader knows of
        self.cycle_channels: dict[int, dict[int, int]] = {}
        self.folded_channels: set[int] = set()
        held = self._folded_counts()
        for cid, channel in list(self.channel_records.items()):
            schema = self.schemas.get(channel.schema_id)
            lane = cycle_lane(schema, channel)
            if lane is not None:
                self.cycle_channels[cid] = self._unfolded(lane, held)
        self.config: Any = _validate_metadata(path, self.metadata, self.library, describe=describe)

    def _folded_counts(self) -> dict[str, int] | None:
        """Topic -> messages the writer put in cycle messages (its ``recording`` summary's
        ``folded``, or in a recovered file the count ``recover`` made of what it copied);
        None when the file has neither."""
        for record in (RECORDING_METADATA, RECOVER_METADATA):
            try:
                folded = json.loads(self.metadata.get(record, {})["folded"])
                break
            except (KeyError, ValueError):
                continue
        else:
            return None
        if not isinstance(folded, dict):
            return None
        return {str(k): v for k, v in folded.items() if isinstance(v, int) and v > 0}

    def _unfolded(self, prefix: str, held: Mapping[str, int] | None) -> dict[int, int]:
        """Topic number -> channel of each topic a cycle channel under ``prefix`` holds (made
        up, with its protobuf schema, when the file has none on that topic): those the writer
        counted in ``held`` (None: not known, every topic a cycle message can hold)."""
        from dobhil.recording.cycles import FOLDED
        from dobhil.recording.encodings.protobuf import file_descriptor_set
        from dobhil.recording.schemas import TOPIC_SPECS
        out: dict[int, int] = {}
        by_topic = {c.topic: cid for cid, c in self.channel_records.items()}
        for topic in FOLDED:
            spec, name = TOPIC_SPECS[topic], prefix + TOPIC_SPECS[topic].name
            if held is not None and name not in held:
                continue
            cid = by_topic.get(name)
            if cid is None:
                cid = max(self.channel_records, default=0) + 1
                sid = max(self.schemas, default=0) + 1
                self.schemas[sid] = Schema(id=sid, name=spec.schema_name, encoding="protobuf",
                                           data=file_descriptor_set(spec))
                self.channel_records[cid] = Channel(id=cid, topic=name, message_encoding="protobuf", metadata={},
                                                    schema_id=sid)
                self.folded_channels.add(cid)
            out[int(topic)] = cid
        return out

    def __enter__(self) -> LogFile:  # nothing is held open between reads: ``with`` only reads well
        return self

    def __exit__(self, *exc: object) -> None:
        pass

    def channels(self) -> tuple[ChannelInfo, ...]:
        """The channels of the file (a cycle channel's topics are not channels of their own)."""
        counts = self.statistics.channel_message_counts if self.statistics is not None else {}
        return tuple(ChannelInfo(c.topic, getattr(self.schemas.get(c.schema_id), "name", ""), c.message_encoding,
                                 counts.get(c.id, 0)) for c in self.channel_records.values()
                     if c.id not in self.folded_channels)

    def message_counts(self) -> dict[str, int]:
        """Topic -> messages a reader gets of it: the file's statistics, and for the topics
        cycle messages hold the writer's count of what it put in them (its ``recording``
        summary's ``folded``; in a recovered file, recover's count of what it copied; in a
        file with neither, :meth:`_guessed_folded`)."""
        topics = set(self.topics())
        out = {c.topic: c.message_count for c in self.channels() if c.topic in topics}
        if not self.cycle_channels:
            return out
        folded = self._folded_counts()
        if folded is None:   # no count (a file recovered before recover counted them): a guess
            folded = self._guessed_folded()
        for topic, count in folded.items():
            out[topic] = out.get(topic, 0) + count
        return out

    def _guessed_folded(self) -> dict[str, int]:
        """Topic -> messages its cycle messages hold, when the writer's count is lost: each
        signal topic once per cycle message (its frames not counted)."""
        statistics = self.statistics.channel_message_counts if self.statistics is not None else {}
        out: dict[str, int] = {}
        for cycle, held in self.cycle_channels.items():
            for number, cid in held.items():
                if number not in _FRAME_NUMBERS:   # how many frames each cycle held is not known
                    topic = self.channel_records[cid].topic
                    out[topic] = out.get(topic, 0) + statistics.get(cycle, 0)
        return out

    @property
    def layout(self) -> str:
        """``cycle`` when the file holds cycle messages (dobhil/recording/cycles.py), else ``topics``."""
        return "cycle" if self.cycle_channels else "topics"

    def topics(self) -> tuple[str, ...]:
        """Every topic a reader gets messages of (a cycle channel's own topic is not one: its
        messages are read as the topics they hold)."""
        return tuple(c.topic for cid, c in self.channel_records.items() if cid not in self.cycle_channels)

    def require_topic(self, topic: str) -> None:
        if topic not in self.topics():
            axes = _axis_names(self.metadata)
            if axes:   # a several-axis log (dobhil.recording.axeslog): say so, not 40 topics
                # the example a topic of the axis (/axis/NAME alone names no topic: one of its own)
                under = topic if not topic.startswith("/axis/") and topic != "/" else "/controller"
                raise _fail(self.path, f"no topic {topic!r}: a log of several axes ({', '.join(axes)}), each "
                                       f"axis' topics under /axis/<name> (e.g. /axis/{axes[0]}{under})")
            raise _fail(self.path, f"no topic {topic!r}; available: {', '.join(self.topics()) or 'none'}")

    def encodings(self) -> tuple[str, ...]:
        """The message encodings of its channels, each once."""
        return tuple(dict.fromkeys(c.message_encoding for c in self.channel_records.values()
                                   if c.id not in self.folded_channels))

    def schema_properties(self, topic: str) -> tuple[str, ...]:
        """Field names of a topic's schema as stored in the file (a JSON schema's properties,
        a protobuf message's fields)."""
        self.require_topic(topic)
        channel = next(c for c in self.channel_records.values() if c.topic == topic)
        schema = self.schemas.get(channel.schema_id)
        try:
            return encoding(channel.message_encoding).schema_fields(schema.data, schema.name) if schema else ()
        except (ValueError, KeyError, TypeError) as exc:
            raise _fail(self.path, f"the schema of {topic} is not a {channel.message_encoding} schema "
                                   f"({exception_line(exc)})") from None

    def decoder(self, channel_id: int) -> Decoder:
        """Message bytes -> payload dict for a channel, by its message encoding and schema."""
        found = self._decoders.get(channel_id)
        if found is None:
            channel = self.channel_records[channel_id]
            schema = self.schemas.get(channel.schema_id)
            spec = SPECS_BY_SCHEMA.get(schema.name) if schema is not None else None
            found = self._decoders[channel_id] = decoder_for(channel.message_encoding, spec, self.path, channel.topic)
        return found

    def iter_payloads(self, topics: Iterable[str] | None = None) -> Iterator[tuple[str, int, bytes]]:
        """(topic, log_time_ns, message bytes) in file order (the order written); each chunk read
        by its offset and CRC-checked again (the file may have changed)."""
        for _, topic, t, data in self._iter_raw(topics):
            yield topic, t, data

    def _iter_raw(self, topics: Iterable[str] | None = None) -> Iterator[tuple[int, str, int, bytes]]:
        """(channel id, topic, log_time_ns, message bytes) in file order; a cycle message's
        messages each as its own, in the order written."""
        chosen = None if topics is None else set(topics)
        wanted = {cid: c.topic for cid, c in self.channel_records.items()
                  if (chosen is None or c.topic in chosen) and cid not in self.cycle_channels}
        folded = {cycle: {number: (cid, wanted[cid]) for number, cid in held.items() if cid in wanted}
                  for cycle, held in self.cycle_channels.items()}
        folded = {cycle: held for cycle, held in folded.items() if held}
        with open(self.path, "rb") as f:
            for offset, size in self.chunks:
                try:
                    f.seek(offset)
                    chunk = next(StreamReader(f, skip_magic=True, emit_chunks=True).records)
                    if not isinstance(chunk, Chunk):
                        raise ValueError(f"expected a chunk, found {type(chunk).__name__}")
                    data = get_chunk_data_stream(chunk, validate_crc=True)[0].read(size)
                except Exception as exc:
                    raise _fail(self.path, f"damaged at byte {offset} ({exception_line(exc)})") from exc
                if folded:
                    yield from self._unfold(_chunk_messages(data, {**wanted, **dict.fromkeys(folded, "")}), folded)
                else:
                    yield from _chunk_messages(data, wanted)

    def _unfold(self, raw: Iterator[tuple[int, str, int, bytes]], folded: Mapping[int, Mapping[int, tuple[int, str]]]
                ) -> Iterator[tuple[int, str, int, bytes]]:
        """``raw`` with each message of a channel in ``folded`` (a cycle channel: topic number
        -> the channel and topic its messages are read as) split into the messages it holds."""
        from dobhil.recording.cycles import unfold
        for cid, topic, t, data in raw:
            held = folded.get(cid)
            if held is None:
                yield cid, topic, t, data
                continue
            try:
                for number, at, part in unfold(data, t):
                    target = held.get(number)
                    if target is not None:
                        yield target[0], target[1], at, part
            except ValueError as exc:
                raise _fail(self.path, f"a {self.channel_records[cid].topic} message at log time {t} is not "
                                       f"a dobhil.Cycle message ({exc})") from None

    def iter_messages(self, topics: Iterable[str] | None = None) -> Iterator[tuple[str, int, dict[str, Any]]]:
        """(topic, log_time_ns, payload dict) in file order, whatever the encoding (the same
        dict: numbers that are not finite as None, bytes as a list of integers)."""
        return self._decoded(topics, lambda cid, _topic: self.decoder(cid))

    def iter_rows(self, fields: Mapping[str, Sequence[str]], defaults: Mapping[str, Any] | None = None
                  ) -> Iterator[tuple[str, int, tuple[Any, ...]]]:
        """(topic, log_time_ns, the values of the fields ``fields[topic]``, in that order) of
        the topics in ``fields``, in file order: the values :meth:`iter_messages`' dicts hold
        (but bytes as bytes), without the dicts (an encoding that reads the fields straight
        from the bytes builds none). A field a message lacks takes its value in ``defaults`` (an older log's
        message), else KeyError (an encoding with defaults of its own, protobuf, gives those)."""
        return self._decoded(fields, lambda cid, topic: self.row_decoder(cid, fields[topic], defaults or {}))

    def _decoded(self, topics: Iterable[str] | None, make: Callable[[int, str], Callable[[bytes], Any]]
                 ) -> Iterator[tuple[str, int, Any]]:
        """(topic, log_time_ns, what ``make(channel id, topic)``'s decoder gives) of each message
        of ``topics`` in file order, one decoder per channel; a message it cannot read fails the
        log in one line naming the topic, the time and the encoding."""
        decoders: dict[int, Callable[[bytes], Any]] = {}
        for cid, topic, t, data in self._iter_raw(topics):
            decode = decoders.get(cid) or decoders.setdefault(cid, make(cid, topic))
            try:
                value = decode(data)
            except (ValueError, TypeError, struct.error) as exc:
                raise _fail(self.path, f"a {topic} message at log time {t} is not valid "
                                       f"{self.channel_records[cid].message_encoding} ({exc})") from None
            yield topic, t, value

    def row_decoder(self, channel_id: int, names: Sequence[str], defaults: Mapping[str, Any]) -> RowDecoder:
        """Message bytes -> the values of the fields ``names`` for a channel (:meth:`iter_rows`)."""
        channel = self.channel_records[channel_id]
        found, spec = self._encoding(channel)
        return found.row_decoder(spec, names, defaults)

    def _encoding(self, channel: Channel) -> tuple[Encoding, Any]:
        """A channel's encoding and its topic's spec (None: a schema dobhil does not know)."""
        schema = self.schemas.get(channel.schema_id)
        spec = SPECS_BY_SCHEMA.get(schema.name) if schema is not None else None
        return encoding_for(channel.message_encoding, spec, self.path, channel.topic), spec

    def stop_reason(self) -> str | None:
        if "/events" not in self.topics():
            return None
        reasons = [p.get("reason") for _, _, p in self.iter_messages(["/events"]) if p.get("kind") == _STOP]
        return reasons[-1] if reasons else None

    def info(self) -> LogInfo:
        channels, stats = self.channels(), self.statistics
        dropped = self.metadata.get(RECORDING_METADATA, {}).get("dropped")
        return LogInfo(os.fspath(self.path), channels, sum(c.message_count for c in channels),
                       stats.message_start_time if stats else 0, stats.message_end_time if stats else 0,
                       MappingProxyType(self.metadata), tuple(a for a, _, _ in self.attachments), self.stop_reason(),
                       None if dropped is None else int(dropped), ", ".join(self.encodings()),
                       self.layout, dict(self.unknown_config), self._held_counts(channels))

    def _held_counts(self, channels: Sequence[ChannelInfo]) -> dict[str, int]:
        """Topic -> messages the cycle messages hold of it: what a reader counts beyond the
        file's own channels."""
        own = {c.topic: c.message_count for c in channels}
        return {t: n - own.get(t, 0) for t, n in self.message_counts().items() if n > own.get(t, 0)}


def _axis_names(metadata: Mapping[str, Mapping[str, str]]) -> list[str]:
    """The axes a several-axis log's ``axes`` metadata names ([]: none, or not readable)."""
    try:
        names = json.loads(metadata.get("axes", {}).get("names", "[]"))
    except ValueError:
        return []
    return [str(n) for n in names] if isinstance(names, list) else []


def encoding_for(message_encoding: str, spec: Any, path: str | os.PathLike[str], topic: str) -> Encoding:
    """The encoding of a channel (``spec``: its topic's, None when the schema is not
    dobhil's); LogFileError naming what is not readable."""
    try:
        found = encoding(message_encoding)
    except LogFileError as exc:
        raise _fail(path, f"channel {topic}: {exc}") from None
    if spec is None and found.name != "json":   # JSON reads without a schema; others need dobhil's
        raise _fail(path, f"channel {topic}: a {message_encoding} schema dobhil does not know")
    return found


def decoder_for(message_encoding: str, spec: Any, path: str | os.PathLike[str], topic: str) -> Decoder:
    """The decoder of a channel (``spec``: its topic's, None when the schema is not dobhil's);
    LogFileError naming what is not readable."""
    return encoding_for(message_encoding, spec, path, topic).decoder(spec)


def _chunk_messages(records: bytes, wanted: Mapping[int, str]) -> Iterator[tuple[int, str, int, bytes]]:
    head, msg_head = _RECORD.unpack_from, _MESSAGE.unpack_from
    pos, end = 0, len(records)
    while pos < end:
        opcode, length = head(records, pos)
        body = pos + 9
        if opcode == _OP_MESSAGE:
            channel, _, log_time, _ = msg_head(records, body)
            topic = wanted.get(channel)
            if topic is not None:
                yield channel, topic, log_time, records[body + 22:body + length]
        pos = body + length


#: the logs opened within :func:`opened_once`: (path, describe) -> ((size, mtime), the log)
_OPENED: ContextVar[dict[tuple[str, bool], tuple[tuple[int, int], LogFile]] | None] = ContextVar(
    "dobhil_opened_logs", default=None)


@contextmanager
def opened_once() -> Iterator[None]:
    """Within it, :func:`open_log` of a path it opened before (the file unchanged: its size
    and modification time) gives that :class:`LogFile` again. Opening reads and checks the
    whole file (20-50 ms a 10 s run), and a command whose steps each take a path -- ``dobhil
    identify``: its method, its axes, its data, its drive's firmware, ``--validate``'s log --
    would otherwise read the same log several times over. A LogFile holds nothing open and is
    not changed by its reads, so one serves them all."""
    token = _OPENED.set({})
    try:
        yield
    finally:
        _OPENED.reset(token)


def open_log(path: str | os.PathLike[str], *, describe: bool = False) -> LogFile:
    """:class:`LogFile` of ``path``; within :func:`opened_once`, the one opened there before."""
    opened = _OPENED.get()
    if opened is None:
        return LogFile(path, describe=describe)
    try:
        st = os.stat(path)
    except OSError:   # LogFile says what is wrong with it, in one line
        return LogFile(path, describe=describe)
    key, stamp = (os.fspath(path), describe), (st.st_size, st.st_mtime_ns)
    seen = opened.get(key)
    if seen is not None and seen[0] == stamp:
        return seen[1]
    log = LogFile(path, describe=describe)
    opened[key] = (stamp, log)
    return log


__all__ = ["MAGIC", "RECOVER_METADATA", "ChannelInfo", "LogFile", "LogInfo", "axis_config_records", "check_library",
           "check_mcap_head", "decoder_for", "encoding_for", "open_log", "opened_once", "recorded_config",
           "summary_intact", "unknown_config_keys", "unknown_keys_note", "unknown_keys_problem"]
