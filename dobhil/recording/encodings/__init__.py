"""How recorded messages are encoded: one module per encoding, chosen by name from
:data:`ENCODINGS` (the channel's MCAP ``message_encoding``) and imported only when asked,
as python-can loads its interfaces. A new encoding is a new module holding an
:class:`Encoding` named ``ENCODING``, and a line here.

The topic table (:data:`~dobhil.recording.schemas.TOPIC_SPECS`) is the one source of each
message's fields; an encoding turns a topic's values into bytes and back, and a topic's
field list into its schema.
"""

from __future__ import annotations

from collections.abc import Mapping
from importlib import import_module
from types import MappingProxyType
from typing import Final

from dobhil.errors import LogFileError
from dobhil.recording.encodings.base import Decoder, Encoder, Encoding, RowDecoder

#: MCAP message encoding -> the module holding it
ENCODINGS: Final[Mapping[str, str]] = MappingProxyType({
    "protobuf": "dobhil.recording.encodings.protobuf",
    "json": "dobhil.recording.encodings.json_messages",
})
#: What dobhil writes (protobuf: a third of JSON's payload bytes and less writer CPU,
#: ``docs/recording.md``); JSON logs of earlier versions are read alike.
DEFAULT_ENCODING: Final = "protobuf"

def encoding(name: str) -> Encoding:
    """The encoding called ``name``; LogFileError naming the ones there are."""
    module = ENCODINGS.get(name)
    if module is None:
        raise LogFileError(f"unknown message encoding {name!r}; expected one of {', '.join(ENCODINGS)}")
    found: Encoding = import_module(module).ENCODING
    return found


__all__ = ["DEFAULT_ENCODING", "ENCODINGS", "Decoder", "Encoder", "Encoding", "RowDecoder", "encoding"]
