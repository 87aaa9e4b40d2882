"""JSON messages with JSON schemas (``json`` / ``jsonschema``): what dobhil wrote before
protobuf, kept to read those logs and to measure against (``tools/bench.py``
``log_bytes_per_cycle_vs_json``). Encoded by the table's own orjson encoders
(:attr:`~dobhil.recording.schemas.TopicSpec.encode`); NaN and infinity become ``null``."""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Final

import orjson

from dobhil.recording.codes import ProtocolCodes
from dobhil.recording.encodings.base import Decoder, Encoder, RowDecoder, as_bytes, bytes_at, row_getter
from dobhil.recording.schemas import Topic, TopicSpec, feedback_encoder


@dataclass(frozen=True)
class JsonEncoding:
    name: str = "json"
    schema_encoding: str = "jsonschema"

    def schema(self, spec: TopicSpec) -> bytes:
        return spec.schema_bytes()

    def encoder(self, spec: TopicSpec, codes: ProtocolCodes | None) -> Encoder:
        if spec.topic == Topic.DRIVE_FEEDBACK and codes is not None:
            return feedback_encoder(codes)
        return spec.encode

    def decoder(self, spec: TopicSpec | None) -> Decoder:
        loads: Decoder = orjson.loads
        return loads

    def row_decoder(self, spec: TopicSpec | None, names: Sequence[str], defaults: Mapping[str, Any]) -> RowDecoder:
        loads, get, at = orjson.loads, row_getter(names), bytes_at(spec, names)

        def row(data: bytes) -> tuple[Any, ...]:
            payload = loads(data)
            try:
                return as_bytes(get(payload), at)
            except KeyError:   # an older log's message, without a field added since
                return as_bytes(tuple(payload[k] if k in payload else defaults[k] for k in names), at)
        return row

    def schema_fields(self, data: bytes, schema_name: str) -> tuple[str, ...]:
        properties: dict[str, Any] = json.loads(data)["properties"]
        return tuple(properties)


ENCODING: Final = JsonEncoding()

__all__ = ["ENCODING", "JsonEncoding"]
