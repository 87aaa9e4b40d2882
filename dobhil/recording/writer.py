"""One MCAP file being written, through the public :class:`mcap.writer.Writer`: every dobhil
log (a run's, ``dobhil log import``'s, python-can's ``can.Logger("x.mcap")``'s) is written by
:class:`LogWriter`: header, metadata, attachments, a channel per topic on its first message,
records encoded by the table, flush (and fsync), the ``recording`` summary on finish, every
message to a second output (the live view) too. No python-can, no numpy: it starts fast.
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from enum import IntEnum
from typing import Any, BinaryIO, Final, NamedTuple, Protocol

from mcap.writer import CompressionType, Writer

from dobhil import __version__
from dobhil.recording.codes import ProtocolCodes
from dobhil.recording.encodings import DEFAULT_ENCODING, Encoding, encoding
from dobhil.recording.layouts import CYCLE_SCHEMA, CYCLE_TOPIC, DEFAULT_LAYOUT, LAYOUTS
from dobhil.recording.schemas import (CYCLE, LANE_MASK, LANE_STRIDE, TOPIC_SPECS, EventKind, Topic, event_record,
                                      lane_kind, named, views)

#: Chunks end at this size or at every flush, whichever comes first.
CHUNK_SIZE: Final = 256 * 1024
#: Chunk compression (``zstandard`` is a dependency of ``mcap``).
COMPRESSION: Final = CompressionType.ZSTD
#: Name of the metadata record written on close.
RECORDING_METADATA: Final = "recording"
#: Header ``library`` of every file dobhil writes (the reader checks it).
LIBRARY: Final = f"dobhil/{__version__}"


class RecordMode(IntEnum):
    """What the sender does when the writer lags."""

    BACKPRESSURE = 1  # wait for room, lose nothing (lockstep)
    LOSSY = 2  # never wait; drop and count (real time)


class Output(Protocol):
    """A second output of every message (the live view)."""

    def add_channel(self, topic: str, *, schema_name: str, json_schema: dict[str, Any] | bytes,
                    message_encoding: str = "json", schema_encoding: str = "jsonschema") -> None: ...
    def publish(self, topic: str, payload: bytes, log_time_ns: int) -> None: ...
    def close(self) -> None: ...
    @property
    def dropped(self) -> int: ...


class LiveOutput(Output, Protocol):
    """An :class:`Output` listening on a port: the live view."""

    @property
    def port(self) -> int: ...


@dataclass(frozen=True)
class LiveView:
    """The live view a writer process serves: ``serve(host=host, port=port, channels=...)`` makes
    its output, given the log's :meth:`LogWriter.output_channels` to advertise before it listens.

    The caller names ``serve`` (``dobhil.live.LiveServer``): the live view is above the
    recording, which so never imports it. It crosses to the writer process pickled, ``serve``
    by reference (a class or function at module level), imported there when unpickled."""

    serve: Callable[..., LiveOutput]
    host: str
    port: int


_EVENTS, _LOSS = int(Topic.EVENTS), int(EventKind.LOSS)
_FRAME_KINDS: Final = frozenset((int(Topic.CAN_RX), int(Topic.CAN_TX)))
_encoding = encoding
class Lane(NamedTuple):
    """One lane of a log (a record's lane is in its kind:
    :data:`~dobhil.recording.schemas.LANE_STRIDE`): the prefix of its topics ("" for the
    single-axis topics, "/axis/left" for an axis'), the codes naming its drive's states
    (None: numbers) and the topics it has (empty: every topic of the table)."""

    prefix: str
    codes: ProtocolCodes | None = None
    topics: tuple[Topic, ...] = ()

    def names(self) -> tuple[tuple[str, Topic], ...]:
        """(topic name, topic) of each of its topics."""
        return tuple((self.prefix + TOPIC_SPECS[t].name, t) for t in (self.topics or tuple(TOPIC_SPECS)))


#: (topic name, topic, encoder, shortest record holding its values) of a message of a record
_LaneView = tuple[str, Topic, Callable[[Any], bytes], int]


def lane_views(lanes: Sequence[Lane], encoding: Encoding | None = None) -> dict[int, tuple[_LaneView, ...]]:
    """Record kind (base and lane) -> the messages it becomes in ``encoding`` (None: JSON),
    under the lane's prefix (a record a lane has no topic for has no kind here: the writer
    refuses it)."""
    out: dict[int, tuple[_LaneView, ...]] = {}
    for lane, (prefix, codes, topics) in enumerate(lanes):
        for base, views_of in views(codes, encoding).items():
            mine = tuple((prefix + TOPIC_SPECS[topic].name, topic, encode, needs)
                         for topic, encode, needs in views_of if not topics or topic in topics)
            if mine:
                out[lane_kind(base, lane)] = mine
    return out


class LogWriter:
    """Writes records to ``file`` (owned: closed by :meth:`finish` or :meth:`close`), each
    message in ``encoding`` (a name of :data:`~dobhil.recording.encodings.ENCODINGS`), laid
    out as ``layout`` (:data:`~dobhil.recording.cycles.LAYOUTS`: a message per topic, or one
    per control cycle, :mod:`dobhil.recording.cycles`, protobuf only); the other outputs (the
    live view) get JSON, a message per topic. Not thread-safe: one thread (or process) writes."""

    def __init__(self, file: BinaryIO, *, metadata: Mapping[str, Mapping[str, Any]],
                 attachments: Iterable[Sequence[Any]] = (), mode: RecordMode = RecordMode.BACKPRESSURE,
                 fsync: bool = True, library: str = LIBRARY, compression: CompressionType = COMPRESSION,
                 chunk_size: int = CHUNK_SIZE, codes: ProtocolCodes | None = None,
                 lanes: Sequence[Lane] = (), encoding: str = DEFAULT_ENCODING,
                 layout: str = DEFAULT_LAYOUT) -> None:
        if layout not in LAYOUTS:
            raise ValueError(f"unknown log layout {layout!r}; expected one of {', '.join(LAYOUTS)}")
        self.file = file
        #: the topic prefix and codes of each lane (:data:`Lane`); one lane without prefix,
        #: its drive's codes named by ``codes``, unless given
        self.lanes: tuple[Lane, ...] = tuple(Lane(*lane) for lane in lanes) or (Lane("", codes),)
        self.encoding: Encoding = _encoding(encoding)
        if layout == "cycle" and self.encoding.name != "protobuf":
            raise ValueError(f"the cycle layout is protobuf's; not {self.encoding.name}")
        self.layout = layout
        if layout == "cycle":   # imported when asked, as an encoding is
            from dobhil.recording import cycles
            self._cycles = cycles
        self._views = lane_views(self.lanes, self.encoding)
        #: the cycle message being filled (cycle layout): its lane, log time and fields
        self._cycle: tuple[int, int, list[bytes]] | None = None
        #: topic -> messages written inside cycle messages (the summary's ``folded``)
        self.folded: dict[str, int] = {}
        self._live_views: dict[int, tuple[_LaneView, ...]] = {}  # JSON, once an output is added
        self.mode = RecordMode(mode)
        self.fsync = fsync
        self.written = self.dropped = self.last_log_ns = 0
        self._outputs: list[Output] = []
        self._channels: dict[str, int] = {}  # topic name -> channel, registered on its first message
        self._schemas: dict[str, int] = {}
        self._mcap = Writer(file, chunk_size=chunk_size, compression=compression, enable_data_crcs=True)
        self._mcap.start(profile="", library=library)
        for name, record in metadata.items():
            self._mcap.add_metadata(name, {str(k): str(v) for k, v in record.items()})
        now = time.time_ns()
        for name, media_type, data in attachments:
            self._mcap.add_attachment(create_time=now, log_time=now, name=name, media_type=media_type, data=data)
        file.flush()

    def register(self, *topics: Topic) -> None:
        """Channels for ``topics`` (of the first lane) now (they are registered on first use otherwise)."""
        prefix = self.lanes[0][0]
        for topic in topics:
            if prefix + TOPIC_SPECS[topic].name not in self._channels:
                self._register(prefix + TOPIC_SPECS[topic].name, topic)

    def output_channels(self) -> tuple[tuple[str, str, dict[str, Any] | bytes, str, str], ...]:
        """(topic, schema name, schema, message encoding, schema encoding) of each channel an
        output is told of: every topic of the table under each lane's prefix, in JSON, and in
        the cycle layout each lane's cycle channel as the file has it (protobuf): an output
        gets the cycle messages the file gets, and the records no cycle holds as JSON."""
        out: list[tuple[str, str, dict[str, Any] | bytes, str, str]] = []
        if self.layout == "cycle":
            # the lanes whose cycle records have messages: those :meth:`_write_cycles` folds
            out += [(lane.prefix + CYCLE_TOPIC, CYCLE_SCHEMA, self._cycles.cycle_schema(), "protobuf", "protobuf")
                    for i, lane in enumerate(self.lanes) if lane_kind(CYCLE, i) in self._views]
        out += [(name, TOPIC_SPECS[topic].schema_name, TOPIC_SPECS[topic].json_schema(), "json", "jsonschema")
                for lane in self.lanes for name, topic in lane.names()]
        return tuple(out)

    def add_output(self, output: Output, *, announced: bool = False) -> None:
        """Send every message to ``output`` as well, its channels (:meth:`output_channels`)
        announced now unless ``announced`` (given to it when it was made: a live view
        advertises them before it listens, so no client connected early is refused one)."""
        if not announced:
            for name, schema_name, schema, message_encoding, schema_encoding in self.output_channels():
                output.add_channel(name, schema_name=schema_name, json_schema=schema,
                                   message_encoding=message_encoding, schema_encoding=schema_encoding)
        self._outputs.append(output)
        self._live_views = self._live_views or lane_views(self.lanes)

    def write(self, records: Iterable[Sequence[Any]]) -> None:
        """Encode and write records (flat tuples of the topic table, named here), in order."""
        if self.layout == "cycle":
            self._write_cycles(records)
        else:
            self._write_topics(records)

    def _write_topics(self, records: Iterable[Sequence[Any]]) -> None:
        """:meth:`write` in the topics layout: each record's messages, one per topic."""
        add, channels, outputs = self._mcap.add_message, self._channels, self._outputs
        written, last = self.written, self.last_log_ns
        views_of = self._views
        for record in map(named, records):
            t, n = record.log_time_ns, len(record)
            if record.kind & LANE_MASK == _EVENTS and record.event == _LOSS:  # the sender's count of its drops
                self.dropped += record.lost
            for name, topic, encode, needs in views_of[record.kind]:
                if n >= needs:
                    add(channels.get(name) or self._register(name, topic), t, encode(record), t)
                    written += 1
            if outputs:
                self._publish(record, n)
            last = max(last, t)
        self.written, self.last_log_ns = written, last

    def _write_cycles(self, records: Iterable[Sequence[Any]]) -> None:
        """:meth:`write` in the cycle layout: a cycle record's messages, and the frames of its
        lane that follow it, become fields of one message (written when the next record that
        is neither comes, or at :meth:`flush`); everything else goes to :meth:`_write_topics`.
        ``written`` counts the messages folded, as the topics layout would."""
        views_of, cycles, folded = self._views, self._cycles, self.folded
        for record in map(named, records):
            kind, t, n = record.kind, record.log_time_ns, len(record)
            base, lane = kind & LANE_MASK, kind // LANE_STRIDE
            pending = self._cycle
            if base == CYCLE:
                self._end_cycle()
                parts = []
                for name, topic, encode, needs in views_of[kind]:
                    if n >= needs:
                        parts.append(cycles.signal_part(topic, encode(record)))
                        folded[name] = folded.get(name, 0) + 1
                self._cycle = (lane, t, parts)
                self.written += len(parts)
            elif base in _FRAME_KINDS and pending is not None and pending[0] == lane:
                (name, topic, encode, _), = views_of[kind]
                pending[2].append(cycles.frame_part(topic, encode(record), t - pending[1]))
                folded[name] = folded.get(name, 0) + 1
                self.written += 1
            else:
                self._end_cycle()
                self._write_topics((record,))   # its messages, the live view's, the last log time
                continue
            self.last_log_ns = max(self.last_log_ns, t)   # outputs get the cycle message (_end_cycle)

    def _end_cycle(self) -> None:
        """Write the cycle message being filled, if any (cycle layout)."""
        if self._cycle is None:
            return
        lane, t, parts = self._cycle
        self._cycle = None
        name = self.lanes[lane].prefix + CYCLE_TOPIC
        channel = self._channels.get(name)
        if channel is None:
            schema = self._schemas.get(CYCLE_SCHEMA)
            if schema is None:
                schema = self._schemas[CYCLE_SCHEMA] = self._mcap.register_schema(CYCLE_SCHEMA, "protobuf",
                                                                                 self._cycles.cycle_schema())
            channel = self._channels[name] = self._mcap.register_channel(name, "protobuf", schema)
        data = b"".join(parts)
        self._mcap.add_message(channel, t, data, t)
        for out in self._outputs:   # the file's bytes: no second encoding for the live view
            out.publish(name, data, t)

    def _publish(self, record: Any, n: int) -> None:
        """``record``'s messages, in JSON, to every other output."""
        for name, _, encode, needs in self._live_views[record.kind]:
            if n >= needs:
                data = encode(record)
                for out in self._outputs:
                    out.publish(name, data, record.log_time_ns)

    def flush(self, sync: bool = True) -> None:
        """End the chunk and hand it to the OS (a killed process then loses nothing older);
        with ``sync`` (and ``fsync``) also fsync (a power loss then loses nothing older)."""
        self._end_cycle()
        self._mcap.flush()  # flushes the file object too
        if sync and self.fsync:
            os.fsync(self.file.fileno())

    def finish(self, stop_reason: str | None, detail: str = "",
               metadata: Mapping[str, Mapping[str, str]] | None = None) -> None:
        """Stop event (if a reason is given), more ``metadata``, the summary, footer; close the file."""
        for name, record in (metadata or {}).items():
            self._mcap.add_metadata(name, dict(record))
        if stop_reason is not None:
            self.write([event_record(EventKind.STOP, self.last_log_ns or time.time_ns(), stop_reason, detail)])
        self._end_cycle()
        summary = {"mode": self.mode.name.lower(), "written": str(self.written), "dropped": str(self.dropped),
                   "stop_reason": stop_reason or ""}
        if self.folded:   # what a reader counts each topic's messages with (the statistics count /cycle's)
            summary["folded"] = json.dumps(self.folded, separators=(",", ":"))
        if self._outputs:
            summary["live_dropped"] = str(sum(out.dropped for out in self._outputs))
        self._mcap.add_metadata(RECORDING_METADATA, summary)
        self._mcap.finish()
        self.flush()
        self.close()

    def close(self) -> None:
        """Close the file (and the other outputs) without finishing it."""
        for out in self._outputs:
            out.close()
        self._outputs.clear()
        try:
            self.file.close()
        except OSError:
            pass

    def _register(self, name: str, topic: Topic) -> int:
        """The channel ``name`` of ``topic``'s schema (one schema per topic of the table,
        shared by every lane's channel of it)."""
        spec = TOPIC_SPECS[topic]
        schema = self._schemas.get(spec.schema_name)
        if schema is None:
            schema = self._schemas[spec.schema_name] = self._mcap.register_schema(
                spec.schema_name, self.encoding.schema_encoding, self.encoding.schema(spec))
        channel = self._channels[name] = self._mcap.register_channel(name, self.encoding.name, schema)
        return channel  # > 0: the writer numbers channels from 1


__all__ = ["CHUNK_SIZE", "COMPRESSION", "LIBRARY", "RECORDING_METADATA", "Lane", "LiveOutput", "LiveView",
           "LogWriter", "Output", "RecordMode", "lane_views"]
