"""How recorded messages are encoded: one module per encoding, chosen by name from
:data:`ENCODINGS` (the channel's MCAP ``message_encoding``) and imported only when asked,
as python-can loads its interfaces. A new encoding is a new module holding an
:class:`Encoding` named ``ENCODING``, and a line here.

The topic table (:data:`~dobhil.recording.schemas.TOPIC_SPECS`) is the one source of each
message's fields; an encoding turns a topic's values into bytes and back, and a topic's
field list into its schema.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from importlib import import_module
from types import MappingProxyType
from typing import TYPE_CHECKING, Any, Final, Protocol

from dobhil.errors import LogFileError

if TYPE_CHECKING:
    from dobhil.recording.codes import ProtocolCodes
    from dobhil.recording.schemas import TopicSpec

#: MCAP message encoding -> the module holding it
ENCODINGS: Final[Mapping[str, str]] = MappingProxyType({
    "protobuf": "dobhil.recording.encodings.protobuf",
    "json": "dobhil.recording.encodings.json_messages",
})
#: What dobhil writes (protobuf: a third of JSON's payload bytes and less writer CPU,
#: ``docs/recording.md``); JSON logs of earlier versions are read alike.
DEFAULT_ENCODING: Final = "protobuf"

Encoder = Callable[[Sequence[Any]], bytes]
Decoder = Callable[[bytes], dict[str, Any]]


class Encoding(Protocol):
    """One message encoding: its MCAP names, a topic's schema, encoder and decoder."""

    @property
    def name(self) -> str: ...             # MCAP message_encoding
    @property
    def schema_encoding(self) -> str: ...  # MCAP schema encoding

    def schema(self, spec: TopicSpec) -> bytes:
        """The schema record's data of ``spec``'s topic."""
        ...

    def encoder(self, spec: TopicSpec, codes: ProtocolCodes | None) -> Encoder:
        """Values (``spec.inputs``, in order) -> message bytes; the drive's codes named by
        ``codes`` (None: numbers only)."""
        ...

    def decoder(self, spec: TopicSpec | None) -> Decoder:
        """Message bytes -> the payload dict, the same for every encoding (non-finite
        numbers as None, bytes as a list of integers); ``spec`` None: a topic the table
        does not have (ValueError for an encoding that needs the table's fields)."""
        ...

    def schema_fields(self, data: bytes, schema_name: str) -> tuple[str, ...]:
        """The field names of a schema record's ``data`` (as stored in the file)."""
        ...


def encoding(name: str) -> Encoding:
    """The encoding called ``name``; LogFileError naming the ones there are."""
    module = ENCODINGS.get(name)
    if module is None:
        raise LogFileError(f"unknown message encoding {name!r}; expected one of {', '.join(ENCODINGS)}")
    found: Encoding = import_module(module).ENCODING
    return found


__all__ = ["DEFAULT_ENCODING", "ENCODINGS", "Decoder", "Encoder", "Encoding", "encoding"]
