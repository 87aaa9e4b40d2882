"""What every encoding module provides (:class:`Encoding`) and the types it uses."""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from operator import itemgetter
from typing import TYPE_CHECKING, Any, Protocol

if TYPE_CHECKING:
    from dobhil.recording.codes import ProtocolCodes
    from dobhil.recording.schemas import TopicSpec

Encoder = Callable[[Sequence[Any]], bytes]
Decoder = Callable[[bytes], dict[str, Any]]
RowDecoder = Callable[[bytes], tuple[Any, ...]]


def row_getter(names: Sequence[str]) -> Callable[[Mapping[str, Any]], tuple[Any, ...]]:
    """A payload dict -> the values of ``names`` in that order, a tuple for one name too
    (KeyError for one it lacks)."""
    if len(names) == 1:
        only = names[0]
        return lambda payload: (payload[only],)
    found: Callable[[Mapping[str, Any]], tuple[Any, ...]] = itemgetter(*names)
    return found


def bytes_at(spec: TopicSpec | None, names: Sequence[str]) -> tuple[int, ...]:
    """Where the bytes fields are among ``names`` (none without a spec)."""
    from dobhil.recording.schemas import FieldKind
    kinds = {f.name: f.kind for f in spec.fields} if spec is not None else {}
    return tuple(k for k, name in enumerate(names) if kinds.get(name) == FieldKind.BYTES)


def as_bytes(row: tuple[Any, ...], at: tuple[int, ...]) -> tuple[Any, ...]:
    """``row`` with its lists of integers at ``at`` as bytes."""
    if not at:
        return row
    out = list(row)
    for k in at:
        out[k] = bytes(out[k])
    return tuple(out)


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

    def row_decoder(self, spec: TopicSpec | None, names: Sequence[str], defaults: Mapping[str, Any]) -> RowDecoder:
        """Message bytes -> the values of the fields ``names``, in that order, as the
        decoder's dict holds them but a bytes field as bytes (what a python-can message
        takes; a topic ``spec`` None does not name: as the dict holds it); a field a message
        lacks: its value in ``defaults`` (KeyError for one not there; an encoding whose
        absent fields have defaults of its own gives those)."""
        ...

    def schema_fields(self, data: bytes, schema_name: str) -> tuple[str, ...]:
        """The field names of a schema record's ``data`` (as stored in the file)."""
        ...


__all__ = ["Decoder", "Encoder", "Encoding", "RowDecoder", "as_bytes", "bytes_at", "row_getter"]
