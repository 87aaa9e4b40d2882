"""``can.LogReader("run.mcap")``: python-can's log reader for dobhil recordings.

Yields the frames of ``/can/rx`` (``is_rx=True``) and ``/can/tx`` (``is_rx=False``), those
a log of the cycle layout holds in its ``/cycle`` messages (:mod:`dobhil.recording.cycles`)
included, in log-time order as :class:`can.Message` objects: bus timestamp in seconds, channel (a frame
recorded without one, as python-can sends a frame, that of its bus in the log's metadata, as
``dobhil log export --can`` writes it; one of digits as the number, as python-can's readers
give a numbered channel), identifier and every flag (extended, remote, error,
FD, BRS, ESI), DLC and data. Other topics are not CAN frames and are skipped. This is what
makes ``python -m can.logconvert run.mcap run.blf`` and ``python -m can.player run.mcap`` work.

A finished file is read through its chunk index, chunk and data CRCs checked: damaged
bytes are a ValueError naming the damage, never frames read silently. A file without a
summary (its writer was killed) is read front to back: every complete frame is yielded,
then a ValueError says the file is truncated and how to complete it.

A gzip stream (python-can opens ``x.mcap.gz`` with ``gzip.open``) is first copied,
decompressed, to an anonymous temporary file: python-can's ``.gz`` writer truncates its
output before any writer is called, so ``can.logconvert x.mcap.gz x.mcap.gz`` would
otherwise read an emptied input and leave nothing; with the copy it writes the input's
frames back (an interrupted conversion of a file onto itself keeps what was written). A
gzip stream cut short is copied up to its end and read like any truncated file.
"""

from __future__ import annotations

import gzip
import os
import tempfile
import zlib
from collections import Counter
from collections.abc import Iterator
from io import BufferedIOBase
from typing import IO, Any, BinaryIO, Final, cast

import can
from can.io.generic import BinaryIOMessageReader
from mcap.exceptions import McapError
from mcap.reader import make_reader
from mcap.records import Channel, Message, Metadata, Schema
from mcap.stream_reader import StreamReader

from dobhil.canio.frames import frame_channels, frame_message, is_frame_topic
from dobhil.errors import LogFileError, exception_line
from dobhil.recording.encodings import Decoder
from dobhil.recording.cycles import unfold
from dobhil.recording.layouts import cycle_lane
from dobhil.recording.reader import MAGIC, decoder_for
from dobhil.recording.schemas import SPECS_BY_SCHEMA, TOPIC_SPECS, Topic

#: (device, inode) of the files McapReaders of this process have open: the writer refuses
#: them (``can.logconvert run.mcap run.mcap`` would otherwise destroy its input).
_OPEN_INPUTS: Final[Counter[tuple[int, int]]] = Counter()


def is_open_input(path: str | os.PathLike[str]) -> bool:
    """Whether ``path`` is a file an McapReader of this process is reading."""
    try:
        st = os.stat(path)
    except OSError:
        return False
    return _OPEN_INPUTS[(st.st_dev, st.st_ino)] > 0


def _file_key(file: Any) -> tuple[int, int] | None:
    """(device, inode) of an open file; None for in-memory streams."""
    try:
        st = os.fstat(file.fileno())
    except (AttributeError, OSError, ValueError):   # io.UnsupportedOperation is both
        return None
    return st.st_dev, st.st_ino


#: Bytes decompressed per read when copying a gzip input (a truncated stream loses at most
#: the read that hits its end).
_COPY_CHUNK: Final = 1 << 16


def _decompressed_copy(stream: gzip.GzipFile) -> BinaryIO:
    """The whole stream in an anonymous temporary file (gone when closed); ``stream``
    is closed. Also spares the indexed read gzip's slow seeks."""
    copy = cast(BinaryIO, tempfile.TemporaryFile())
    try:
        while True:
            try:
                chunk = stream.read(_COPY_CHUNK)
            except (EOFError, OSError, zlib.error):
                # a truncated or damaged gzip stream (a logger killed): what came before is
                # copied, and reading the copy yields its frames, then says it is truncated
                break
            if not chunk:
                break
            copy.write(chunk)
        copy.seek(0)
    except BaseException:
        copy.close()
        raise
    finally:
        stream.close()
    return copy


#: topic number -> name of the frame topics a cycle message holds
_FRAME_TOPICS: Final = {int(t): TOPIC_SPECS[t].name for t in (Topic.CAN_RX, Topic.CAN_TX)}


class McapReader(BinaryIOMessageReader):
    """Reads the CAN frames of an MCAP file (path or seekable binary file object)."""

    def __init__(self, file: str | os.PathLike[str] | BinaryIO | BufferedIOBase, **kwargs: Any) -> None:
        if kwargs:
            raise ValueError(f"MCAP reader: unknown option(s) {', '.join(sorted(kwargs))}; it takes none")
        self.name = os.fspath(file) if isinstance(file, (str, os.PathLike)) else str(getattr(file, "name", "MCAP"))
        self._decoders: dict[int, Decoder] = {}
        self._cycle_frames: Decoder | None = None   # the frames a cycle message holds (made once)
        self._bus_channels: dict[str, str] = {}
        super().__init__(file, mode="rb")
        try:
            head = self.file.read(len(MAGIC))
            self.file.seek(0)
        except BaseException:
            self.file.close()
            raise
        if head != MAGIC:
            self.file.close()
            raise ValueError(f"{self.name}: not an MCAP file (bad magic)")
        self.frames_read = 0
        self._key = _file_key(self.file)
        if self._key is not None:
            _OPEN_INPUTS[self._key] += 1
        self._recover = f"`dobhil log recover {self.name}`"
        if isinstance(self.file, gzip.GzipFile):
            # dobhil log recover reads MCAP, not gzip: decompress what there is first
            self._recover = f"`zcat {self.name} > x.mcap` then `dobhil log recover x.mcap`"
            try:
                self.file = _decompressed_copy(self.file)
            except BaseException:
                self.stop()
                raise

    def stop(self) -> None:
        if self._key is not None:
            _OPEN_INPUTS[self._key] -= 1
            self._key = None
        super().stop()

    def __iter__(self) -> Iterator[can.Message]:
        try:
            for topic, log_time, data, decoder in self._records():
                msg = frame_message(data, log_time, decoder)
                if msg.channel is None:
                    msg.channel = self._bus_channels.get(topic)
                if isinstance(msg.channel, str) and msg.channel.isascii() and msg.channel.isdigit():
                    # a number (Kvaser, Vector, IXXAT number their channels) is recorded as
                    # text (the schema's channel is a string): read back as the number, as
                    # python-can's own readers give it (can/io/canutils.py: a channel of
                    # digits is an int; ASC and BLF store numbers only)
                    msg.channel = int(msg.channel)
                self.frames_read += 1
                yield msg
        except (KeyError, TypeError) as exc:
            raise ValueError(f"{self.name}: /can/* message {self.frames_read + 1} is not a dobhil CAN frame "
                             f"(missing {exc})") from exc
        finally:
            self.stop()

    def _decoder(self, schema: Any, channel: Any) -> Decoder:
        """The decoder of a frame channel (its encoding, its schema), made once."""
        found = self._decoders.get(channel.id)
        if found is None:
            spec = SPECS_BY_SCHEMA.get(schema.name) if schema is not None else None
            found = self._decoders[channel.id] = decoder_for(channel.message_encoding, spec, self.name, channel.topic)
        return found

    def _unfolded(self, prefix: str, log_time: int, data: bytes) -> Iterator[tuple[str, int, bytes, Decoder]]:
        """The frames a cycle message of lane ``prefix`` holds, as :meth:`_records` gives frames."""
        for number, at, part in unfold(data, log_time):
            if number in _FRAME_TOPICS:
                name = prefix + _FRAME_TOPICS[number]
                if self._cycle_frames is None:   # both frame topics' messages are dobhil.CanFrame
                    self._cycle_frames = decoder_for("protobuf", SPECS_BY_SCHEMA["dobhil.CanFrame"], self.name, name)
                yield name, at, part, self._cycle_frames

    def _take_metadata(self, records: dict[str, dict[str, str]]) -> None:
        """The channel of each frame topic's bus, from the log's metadata records (as ``dobhil
        log export --can`` gives a sent frame, :func:`dobhil.canio.frames.frame_channels`)."""
        try:
            self._bus_channels = frame_channels(records, self.name)
        except LogFileError:   # a layout it cannot read: the frames as recorded
            self._bus_channels = {}

    def _records(self) -> Iterator[tuple[str, int, bytes, Decoder]]:
        """(topic, log time, data) of each frame message, chunk and data CRCs checked; indexed
        when there is a summary."""
        reader = make_reader(cast(IO[bytes], self.file), validate_crcs=True)
        try:
            summary = reader.get_summary()
        except Exception:  # no footer: a writer killed before stop()
            summary = None
        if summary is None or not summary.chunk_indexes:
            yield from self._scan()
            return
        topics = {c.topic for c in summary.channels.values()}
        cycles = {c.topic: lane for c in summary.channels.values()
                  if (lane := cycle_lane(summary.schemas.get(c.schema_id), c)) is not None}
        frames = [t for t in topics if is_frame_topic(t)]
        if not frames and not cycles:
            listed = ", ".join(sorted(topics)) or "none"
            raise ValueError(f"{self.name}: no CAN frames (no /can/rx or /can/tx topic; topics: {listed})")
        try:
            self._take_metadata({m.name: m.metadata for m in reader.iter_metadata()})
            for schema, channel, message in reader.iter_messages(topics=[*frames, *cycles], log_time_order=True):
                if channel.topic in cycles:
                    yield from self._unfolded(cycles[channel.topic], message.log_time, message.data)
                else:
                    yield channel.topic, message.log_time, message.data, self._decoder(schema, channel)
        except Exception as exc:  # a CRC, zstd or lz4 error: the bytes are wrong
            raise ValueError(f"{self.name}: damaged after {self.frames_read} frames ({exception_line(exc)}); "
                             f"{self._recover} saves the intact chunks") from exc

    def _scan(self) -> Iterator[tuple[str, int, bytes, Decoder]]:
        """Front to back, for a file without chunk index; file order is the writer's order.
        The metadata records (written before the first message, dobhil/recording/writer.py)
        are taken as they come, as NonSeekingReader.iter_messages skips them."""
        self.file.seek(0)
        schemas: dict[int, Schema] = {}
        channels: dict[int, Channel] = {}
        metadata: dict[str, dict[str, str]] = {}
        try:
            for record in StreamReader(cast(IO[bytes], self.file), validate_crcs=True).records:
                if isinstance(record, Metadata):
                    metadata[record.name] = record.metadata
                    self._take_metadata(metadata)
                elif isinstance(record, Schema):
                    schemas[record.id] = record
                elif isinstance(record, Channel):
                    channels[record.id] = record
                elif isinstance(record, Message):
                    channel = channels.get(record.channel_id)
                    if channel is None:
                        raise McapError(f"no channel record found with id {record.channel_id}")
                    if is_frame_topic(channel.topic):
                        yield (channel.topic, record.log_time, record.data,
                               self._decoder(schemas.get(channel.schema_id), channel))
                    elif (lane := cycle_lane(schemas.get(channel.schema_id), channel)) is not None:
                        yield from self._unfolded(lane, record.log_time, record.data)
        except Exception as exc:
            raise ValueError(f"{self.name}: truncated or damaged after {self.frames_read} frames ({exc}); "
                             f"{self._recover} writes a complete copy") from exc


__all__ = ["McapReader", "is_open_input"]
