"""A log in the other layout (``dobhil log convert FILE --layout topics|cycle``): the same
messages, in the same order with the same log times and bytes, as a message per topic or
folded into cycle messages (:mod:`dobhil.recording.cycles`). A cycle log goes to tools that
read topics by name without dobhil; a topics log shrinks to about a third.

Folding works on the messages, not on the loop's records: a run of messages of one lane
(one topic prefix) makes a cycle message when its signal messages share their log time and
each signal topic comes once, the frames of that lane after them joined with their own log
times. Unfolding reads what any grouping wrote back in its order, so a copy reads as its
source (``tests/recording/test_relayout.py``) even where its grouping is not the writer's
(a run's initial feedback, which the writer keeps apart, may open a cycle message here).
Metadata and attachments are copied; the ``recording`` summary's per-topic counts of what
cycle messages hold (``folded``) are those of the copy. Written under a temporary name,
renamed when complete; the source must be a complete log (`dobhil log recover` first).
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from mcap.writer import Writer

from dobhil.errors import LogFileError
from dobhil.files import atomic_path, check_output
from dobhil.recording.cycles import FOLDED, cycle_schema, frame_part, signal_part
from dobhil.recording.layouts import CYCLE_SCHEMA, CYCLE_TOPIC, LAYOUTS
from dobhil.recording.reader import LogFile, open_log
from dobhil.recording.schemas import TOPIC_SPECS, Topic
from dobhil.recording.writer import CHUNK_SIZE, COMPRESSION, LIBRARY, RECORDING_METADATA

ProgressFn = Callable[[int], None]
_FRAMES = (Topic.CAN_RX, Topic.CAN_TX)
#: topic name (after its lane's prefix) -> the topic, of each topic a cycle message holds
_HELD = {TOPIC_SPECS[t].name: t for t in FOLDED}


@dataclass(frozen=True)
class Relayout:
    """What :func:`relayout` wrote: the copy, its layout, messages read and MCAP messages written."""

    output: str
    layout: str
    messages: int
    written: int


def default_output(path: str | os.PathLike[str], layout: str) -> Path:
    """``run.mcap`` + ``cycle`` -> ``run.cycle.mcap``."""
    return Path(path).with_suffix(f".{layout}.mcap")


def _split(topic: str) -> tuple[str, Topic | None]:
    """(lane prefix, topic) of a topic name a cycle message can hold, else (``topic``, None)."""
    for name, held in _HELD.items():
        if topic.endswith(name):
            return topic[:-len(name)], held
    return topic, None


class _Out:
    """The copy's MCAP writer: a channel per topic, registered on its first message with the
    source's schema of it."""

    def __init__(self, writer: Writer, log: LogFile) -> None:
        self.writer, self.log = writer, log
        self.channels: dict[str, int] = {}
        self.schemas: dict[tuple[str, bytes], int] = {}
        self.written = 0
        self.folded: dict[str, int] = {}

    def channel(self, topic: str, schema_name: str, encoding: str, data: bytes, message_encoding: str) -> int:
        found = self.channels.get(topic)
        if found is None:
            key = (schema_name, data)
            sid = self.schemas.get(key)
            if sid is None:
                sid = self.schemas[key] = self.writer.register_schema(schema_name, encoding, data)
            found = self.channels[topic] = self.writer.register_channel(topic, message_encoding, sid)
        return found

    def add(self, topic: str, t: int, data: bytes, source_channel: int) -> None:
        cid = self.channels.get(topic)
        if cid is None:   # the source's schema of it, looked up once per topic
            channel = self.log.channel_records[source_channel]
            schema = self.log.schemas.get(channel.schema_id)
            cid = self.channel(topic, schema.name if schema else "", schema.encoding if schema else "",
                               bytes(schema.data) if schema else b"", channel.message_encoding)
        self.writer.add_message(cid, log_time=t, data=data, publish_time=t)
        self.written += 1

    def add_cycle(self, prefix: str, t: int, parts: list[bytes]) -> None:
        cid = self.channel(prefix + CYCLE_TOPIC, CYCLE_SCHEMA, "protobuf", cycle_schema(), "protobuf")
        self.writer.add_message(cid, log_time=t, data=b"".join(parts), publish_time=t)
        self.written += 1


class _Folder:
    """Messages in file order into :class:`_Out`, folded into cycle messages (module docstring)."""

    def __init__(self, out: _Out) -> None:
        self.out = out
        self.prefix, self.t, self.framed = "", 0, False
        self.parts: list[bytes] = []
        self.seen: set[Topic] = set()
        self.topics: list[str] = []

    def message(self, cid: int, topic: str, t: int, data: bytes, foldable: bool) -> None:
        prefix, held = _split(topic) if foldable else (topic, None)
        if held is not None and self.parts and prefix == self.prefix:
            if held in _FRAMES:
                self._take(topic, frame_part(held, data, t - self.t))
                self.framed = True
                return
            if held not in self.seen and t == self.t and not self.framed:
                self.seen.add(held)
                self._take(topic, signal_part(held, data))
                return
        self.end()
        if held is not None and held not in _FRAMES:
            self.prefix, self.t, self.seen = prefix, t, {held}
            self._take(topic, signal_part(held, data))
        else:
            self.out.add(topic, t, data, cid)

    def _take(self, topic: str, part: bytes) -> None:
        self.parts.append(part)
        self.topics.append(topic)

    def end(self) -> None:
        """Write the cycle message being filled, if any."""
        if self.parts:
            self.out.add_cycle(self.prefix, self.t, self.parts)
            for topic in self.topics:
                self.out.folded[topic] = self.out.folded.get(topic, 0) + 1
        self.parts, self.topics, self.seen, self.framed = [], [], set(), False


def relayout(path: str | os.PathLike[str], layout: str, out: str | os.PathLike[str] | None = None, *,
             progress: ProgressFn | None = None) -> Relayout:
    """``path`` copied to ``out`` (default :func:`default_output`) in ``layout``; LogFileError
    (one line) when it is in that layout already or is no complete dobhil log."""
    if layout not in LAYOUTS:
        raise LogFileError(f"unknown layout {layout!r}; expected one of {', '.join(LAYOUTS)}")
    log = open_log(path, describe=True)   # a copy applies no config: a newer dobhil's log converts too
    if log.layout == layout:
        raise LogFileError(f"{os.fspath(path)}: already in the {layout} layout; nothing written")
    if layout == "cycle" and "protobuf" not in log.encodings():
        raise LogFileError(f"{os.fspath(path)}: the cycle layout holds protobuf messages; this log's are "
                           f"{', '.join(log.encodings()) or 'none'} (dobhil logs before 0.2 are JSON)")
    target = check_output(default_output(path, layout) if out is None else out, inputs=[path], suffix=".mcap",
                          what="output", new=True)
    # topic -> the channel a reader reads it from (a cycle log's topics: the reader's own)
    channel_of = {c.topic: cid for cid, c in log.channel_records.items() if cid not in log.cycle_channels}
    count = 0
    with atomic_path(target) as tmp, open(tmp, "wb") as sink:
        writer = Writer(sink, chunk_size=CHUNK_SIZE, compression=COMPRESSION, enable_data_crcs=True)
        writer.start(profile="", library=f"{LIBRARY} convert")
        start = log.statistics.message_start_time if log.statistics is not None else 0
        for name, media_type, data in log.attachments:
            writer.add_attachment(create_time=start, log_time=start, name=name, media_type=media_type, data=data)
        copy = _Out(writer, log)
        folder = _Folder(copy) if layout == "cycle" else None
        for topic, t, data in log.iter_payloads():
            cid = channel_of[topic]
            if folder is None:
                copy.add(topic, t, data, cid)
            else:   # a cycle message holds protobuf messages only
                folder.message(cid, topic, t, data, log.channel_records[cid].message_encoding == "protobuf")
            count += 1
            if progress is not None:
                progress(1)
        if folder is not None:
            folder.end()
        for name, record in log.metadata.items():
            copied = dict(record)
            if name == RECORDING_METADATA:
                copied.pop("folded", None)
                if copy.folded:
                    copied["folded"] = json.dumps(copy.folded, separators=(",", ":"))
            writer.add_metadata(name, copied)
        writer.finish()
    return Relayout(os.fspath(target), layout, count, copy.written)


__all__ = ["Relayout", "default_output", "relayout"]
