"""Writing small logs for tests through the one writer, :class:`LogWriter`."""

from __future__ import annotations

import functools
from collections.abc import Callable, Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import can

from dobhil.recording.schemas import EventKind, Topic, can_frame_record, event_record
from dobhil.recording.writer import LogWriter, RecordMode


def write_log(path: Path, records: Iterable[Sequence[Any]], *, metadata: Mapping[str, Mapping[str, Any]] | None = None,
              attachments: Sequence[tuple[str, str, bytes]] = (), stop: str | None = None,
              mode: RecordMode = RecordMode.BACKPRESSURE) -> Path:
    log = LogWriter(open(path, "wb"), metadata=metadata or {}, attachments=attachments, mode=mode, fsync=False)
    log.write(records)
    log.finish(stop)
    return path


def topic_counts(path: Path | str) -> dict[str, int]:
    """Topic -> messages a reader of ``path`` gets (either layout: a cycle message's topics
    counted as the topics layout would hold them; :meth:`LogFile.message_counts`)."""
    from dobhil.recording.reader import open_log
    return open_log(path).message_counts()


def frame(msg: can.Message, direction: Topic, t: int) -> tuple[Any, ...]:
    return can_frame_record(msg, direction, t)


def command(t: int, torque: float) -> tuple[Any, ...]:
    return (int(Topic.DRIVE_COMMAND), t, torque)


def feedback(t: int, position: float, velocity: float = 1.0, seq: int = 0, cycle: int = 0) -> tuple[Any, ...]:
    return (int(Topic.DRIVE_FEEDBACK), t, position, velocity, 8, -1, 0, seq, cycle)


def event(kind: EventKind, t: int, reason: str, detail: str = "") -> tuple[Any, ...]:
    return event_record(kind, t, reason, detail)


@functools.cache
def _decoder(message_encoding: str, schema_name: str, topic: str) -> Callable[[bytes], dict[str, Any]]:
    """One channel's decoder, built once: building it compiles the topic's unpacker, which
    costs far more than a message's decode (a rewritten log has tens of thousands)."""
    from dobhil.recording.reader import decoder_for
    from dobhil.recording.schemas import SPECS_BY_SCHEMA
    return decoder_for(message_encoding, SPECS_BY_SCHEMA.get(schema_name), "test", topic)


@functools.cache
def _packer(schema_name: str) -> Callable[[tuple[Any, ...]], bytes]:
    """A protobuf topic's packer, built once (as :func:`_decoder`)."""
    from dobhil.recording.encodings.protobuf import packer
    from dobhil.recording.schemas import SPECS_BY_SCHEMA
    return packer(SPECS_BY_SCHEMA[schema_name])


def decode_message(schema: Any, channel: Any, data: bytes) -> dict[str, Any]:
    """A recorded message's payload dict, read by its channel's encoding (mcap records)."""
    return _decoder(channel.message_encoding, schema.name, channel.topic)(data)


def encode_message(schema: Any, channel: Any, payload: dict[str, Any]) -> bytes:
    """``payload`` encoded as its channel's messages are (a test's edit of a recorded one):
    JSON as is, protobuf in the table's field order (None: NaN, as the writer records it;
    a list of integers: bytes)."""
    import json
    import math

    from dobhil.recording.schemas import SPECS_BY_SCHEMA
    if channel.message_encoding == "json":
        return json.dumps(payload).encode()
    values = (payload[k] for k in SPECS_BY_SCHEMA[schema.name].keys)
    return _packer(schema.name)(tuple(math.nan if v is None else bytes(v) if isinstance(v, list) else v
                                      for v in values))
