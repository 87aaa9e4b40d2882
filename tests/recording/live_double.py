"""A live view for the writer process's tests: what it is served goes to a file (``host``
names it), so a test sees what the writer process sent it, without the [live] extra. At
module level: a :class:`~dobhil.recording.writer.LiveView` carries it by reference."""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any


class FileOutput:
    """An ``Output`` listening on ``port`` (it only says so) that writes one line a call."""

    def __init__(self, *, host: str, port: int, channels: Iterable[tuple[Any, ...]] = ()) -> None:
        self.port, self.dropped = port, 0
        self._file = open(host, "a")
        for topic, schema_name, *_ in channels:  # advertised before it listens
            self._file.write(f"channel {topic} {schema_name}\n")
        self._file.write("listening\n")

    def add_channel(self, topic: str, *, schema_name: str, json_schema: dict[str, Any] | bytes,
                    message_encoding: str = "json", schema_encoding: str = "jsonschema") -> None:
        self._file.write(f"channel {topic} {schema_name}\n")

    def publish(self, topic: str, payload: bytes, log_time_ns: int) -> None:
        self._file.write(f"{topic} {log_time_ns}\n")

    def close(self) -> None:
        self._file.write("closed\n")
        self._file.close()
