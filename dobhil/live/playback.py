"""``dobhil log serve``: a recording played to Foxglove at its recorded pace.

Channels are advertised exactly as recorded (topic, schema name, schema bytes) and
message payloads are passed on byte for byte, so a client sees what a live run
would have served. The file is read with mcap's public reader after dobhil's own
validation (:func:`dobhil.recording.reader.open_log`), which turns a missing,
empty, non-MCAP or truncated file into one :class:`~dobhil.errors.LogFileError` line.
"""

from __future__ import annotations

import math
import os
import struct
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import IO, Any, Final

from mcap.exceptions import McapError
from mcap.reader import McapReader, make_reader

from dobhil.errors import ConfigError, LogFileError
from dobhil.live.server import LiveChannel, LiveServer

_DAMAGED: Final = (McapError, struct.error, EOFError, ValueError, KeyError)
#: Shorter waits are not slept: the next message goes out at once (pace is kept on average).
_MIN_SLEEP_S: Final = 0.0005


@dataclass(frozen=True)
class RecordedChannel:
    """One channel of the recording as it will be advertised."""

    topic: str
    schema_name: str
    schema_data: bytes
    message_encoding: str = "json"
    schema_encoding: str = "jsonschema"

    def live(self) -> LiveChannel:
        """The channel as :class:`LiveServer` advertises it."""
        return LiveChannel(self.topic, self.schema_name, self.schema_data, self.message_encoding, self.schema_encoding)


#: (message encoding, schema encoding) the live view serves, as dobhil writes them
_SERVED: Final = {("json", "jsonschema"), ("json", ""), ("protobuf", "protobuf")}


@dataclass(frozen=True)
class PlaybackReport:
    """What one ``serve_recording`` call did."""

    passes: int
    published: int
    wall_s: float


#: Slowest and fastest playback: beyond these a recording would take years to play (and
#: ``time.sleep`` overflows), or every message would go out at once anyway.
MIN_SPEED: Final = 1e-3
MAX_SPEED: Final = 1e6
#: Shortest pass of ``--loop``: a recording whose messages share one log time (or span a
#: microsecond) played in no time, and the loop started over at once, about 1000 passes a
#: second each telling every client to reset. The next pass waits for the rest of this.
MIN_LOOP_PERIOD_S: Final = 0.5


def check_speed(speed: float) -> float:
    """``speed`` if it is a factor in [MIN_SPEED, MAX_SPEED], else one ConfigError line."""
    if not (math.isfinite(speed) and MIN_SPEED <= speed <= MAX_SPEED):
        raise ConfigError(f"--speed must be a positive finite factor of recorded pace (e.g. 1, 0.5, 10) "
                          f"from {MIN_SPEED:g} to {MAX_SPEED:g}, got {speed}")
    return speed


def _fail(path: str | os.PathLike[str], what: str) -> LogFileError:
    return LogFileError(f"{os.fspath(path)}: {what}")


def _guard(path: str | os.PathLike[str], records: Iterator[Any]) -> Iterator[Any]:
    try:
        yield from records
    except _DAMAGED as exc:
        raise _fail(path, f"damaged data ({exc}); try `dobhil log recover`") from exc


def _raw_channels(path: str | os.PathLike[str], reader: McapReader) -> list[tuple[Any, Any]]:
    """(schema, channel) records from the summary, or from one scan when there is none."""
    summary = reader.get_summary()
    if summary is not None:
        return [(summary.schemas.get(c.schema_id), c) for _, c in sorted(summary.channels.items())]
    found: dict[int, tuple[Any, Any]] = {}
    for schema, channel, _ in _guard(path, reader.iter_messages(log_time_order=False)):
        found.setdefault(channel.id, (schema, channel))
    return [found[k] for k in sorted(found)]


def recorded_channels(path: str | os.PathLike[str], f: IO[bytes]) -> tuple[RecordedChannel, ...]:
    """Channels of an open recording; LogFileError if one is neither JSON with a JSON schema
    nor protobuf with a protobuf schema."""
    out: dict[str, RecordedChannel] = {}
    for schema, channel in _raw_channels(path, make_reader(f)):
        encoding = schema.encoding if schema is not None else ""
        if (channel.message_encoding, encoding) not in _SERVED:
            raise _fail(
                path,
                f"channel {channel.topic!r} is {channel.message_encoding!r}/{encoding!r}; "
                "the live view serves json messages with jsonschema schemas and protobuf with protobuf",
            )
        name = schema.name if schema is not None else ""
        data = bytes(schema.data) if schema is not None else b""
        out.setdefault(channel.topic, RecordedChannel(channel.topic, name, data, channel.message_encoding,
                                                      encoding or "jsonschema"))
    if not out:
        raise _fail(path, "no channels to serve")
    return tuple(out.values())


def load_channels(path: str | os.PathLike[str], on_note: Callable[[str], None] | None = None
                  ) -> tuple[RecordedChannel, ...]:
    """Validate a recording and return its channels; one LogFileError line if unusable.
    Serving plays what was recorded and never applies the config, so a newer dobhil's log
    (a recorded config with keys this version does not know) is served, ``on_note`` given
    the note ``dobhil log info`` prints of it. A recording with channels but no message (an
    empty capture of ``can.Logger``, whose channels are registered up front) is refused
    here, before the server listens, not once a client has come to watch it."""
    from dobhil.recording.reader import open_log, unknown_keys_note

    log = open_log(path, describe=True)
    if log.unknown_config and on_note is not None:
        on_note(unknown_keys_note(log.unknown_config))
    with open(path, "rb") as f:
        channels = recorded_channels(path, f)
        f.seek(0)
        if next(_guard(path, make_reader(f).iter_messages(log_time_order=False)), None) is None:
            raise _fail(path, "no messages to serve")
        return channels


def _play_once(
    path: str | os.PathLike[str],
    f: IO[bytes],
    server: LiveServer,
    speed: float,
    clock: Callable[[], float],
    sleep: Callable[[float], None],
) -> int:
    """Publish every message once at ``speed`` times the recorded pace; the count."""
    f.seek(0)
    first: int | None = None
    start = clock()
    count = 0
    for _, channel, message in _guard(path, make_reader(f).iter_messages(log_time_order=True)):
        if first is None:
            first = message.log_time
        delay = start + (message.log_time - first) / 1e9 / speed - clock()
        if delay > _MIN_SLEEP_S:
            sleep(delay)
        server.publish(channel.topic, message.data, message.log_time)
        count += 1
    return count


def serve_recording(
    path: str | os.PathLike[str],
    server: LiveServer,
    *,
    speed: float = 1.0,
    loop: bool = False,
    wait_for_client: bool = True,
    settle_s: float = 0.5,
    on_ready: Callable[[tuple[RecordedChannel, ...]], None] | None = None,
    clock: Callable[[], float] = time.monotonic,
    sleep: Callable[[float], None] = time.sleep,
) -> PlaybackReport:
    """Advertise the recording's channels on ``server`` (those it does not have yet; give
    them to :class:`LiveServer` as ``channels`` so a client connected early is not refused
    them) and play its messages.

    With ``wait_for_client`` the playback starts when a client first subscribes
    (Foxglove subscribes when its panels load), ``settle_s`` after the first
    subscription so the client can subscribe the rest; ``on_ready`` is called once the
    channels are advertised, before waiting. With ``loop`` it starts over (telling
    clients to reset) until interrupted, a pass lasting :data:`MIN_LOOP_PERIOD_S` at least.
    """
    check_speed(speed)
    load_channels(path)
    with open(path, "rb") as f:
        channels = recorded_channels(path, f)
        for c in channels:
            if c.topic not in server.topics:  # those given to the server up front are advertised
                server.add_channel(c.topic, schema_name=c.schema_name, json_schema=c.schema_data,
                                   message_encoding=c.message_encoding, schema_encoding=c.schema_encoding)
        if on_ready is not None:
            on_ready(channels)
        if wait_for_client:
            server.wait_for_subscriber()
            sleep(settle_s)  # a client subscribes topic by topic (panel by panel): let it finish
        started = clock()
        passes = published = 0
        while True:
            if passes:
                server.new_session()
            began = clock()
            count = _play_once(path, f, server, speed, clock, sleep)
            if count == 0:
                raise _fail(path, "no messages to serve")
            passes += 1
            published += count
            if not loop:
                break
            rest = began + MIN_LOOP_PERIOD_S - clock()
            if rest > 0:
                sleep(rest)
    return PlaybackReport(passes, published, clock() - started)


__all__ = ["MIN_LOOP_PERIOD_S", "PlaybackReport",
           "RecordedChannel", "check_speed", "load_channels", "recorded_channels", "serve_recording"]
