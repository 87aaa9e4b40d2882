"""What every encoding module provides (:class:`Encoding`) and the types it uses."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Any, Protocol

if TYPE_CHECKING:
    from dobhil.recording.codes import ProtocolCodes
    from dobhil.recording.schemas import TopicSpec

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


__all__ = ["Decoder", "Encoder", "Encoding"]
