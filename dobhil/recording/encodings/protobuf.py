"""Protocol Buffers messages (``protobuf``), as Foxglove and ``mcap-protobuf-support`` read
them: each topic's schema is a serialized ``google.protobuf.FileDescriptorSet`` (one file
``dobhil/<Message>.proto``, package ``dobhil``, proto3) built from the topic table's field
list -- field number = position in the list plus one, so a new field is appended, never
inserted -- and each message its protobuf wire encoding. No protobuf library at run time:
the descriptor and the messages are encoded here (the tests parse both with the
``protobuf`` library and ``mcap-protobuf-support``, independently of this module).

Types: a number is a ``double``, an integer an ``sfixed64``, a flag a ``bool``, text a
``string``, bytes ``bytes``. The writer lays each message out the same way: its fixed-width
fields first, in field order, with one precompiled :meth:`struct.Struct.pack` (tag and value
side by side), then its length-delimited fields. Protobuf parsers take fields in any order
and fixed-width integers as well as varints; the layout is chosen for the writer's CPU,
measured (``tools/bench.py``, this machine, 2026-12-03) at about 0.7 us for a 7-field
``/controller`` message, against 2.0 us for the same dict through orjson and 3.2 us for
building the pack's arguments at run time; so the pack's call is generated once per topic
from the field list (source built from field numbers only, as :mod:`dataclasses` builds its
methods). The reader takes any valid encoding of the schema (another writer's, with varints
and fields left at their defaults, field by field) and reads the writer's own layout with
one unpack and a tail read without a loop, by a decoder generated per topic the same way
(:func:`_fast`): a message in any other layout -- another order, a field repeated, a length
or a flag of more than one byte, a message cut short -- is left to the field-by-field path.
:func:`row_unpacker` reads only the fields a reader asks for, with no dict (``dobhil
replay``); a replay of a protobuf log takes as much CPU as of the same run in JSON or less,
where the field-by-field path took twice as much (``replay_protobuf_vs_json`` in
``tools/bench.py``, ``docs/recording.md``).
"""

from __future__ import annotations

import struct
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from enum import IntEnum
from functools import lru_cache
from types import CodeType
from typing import Any, Final, NamedTuple

from dobhil.recording.codes import ProtocolCodes
from dobhil.recording.encodings.base import Decoder, Encoder, RowDecoder, as_bytes, bytes_at, row_getter
from dobhil.recording.schemas import FieldKind, Topic, TopicSpec, field_values


class Wire(IntEnum):
    """Protobuf wire types (https://protobuf.dev/programming-guides/encoding/)."""

    VARINT = 0
    I64 = 1
    LEN = 2
    I32 = 5


class ProtoType(IntEnum):
    """``google.protobuf.FieldDescriptorProto.Type`` numbers of the types used."""

    DOUBLE = 1
    BOOL = 8
    STRING = 9
    MESSAGE = 11
    BYTES = 12
    SFIXED64 = 16


class _Kind(NamedTuple):
    type: ProtoType
    wire: Wire
    code: str  # struct code of a fixed-width value ("": length-delimited)


_KINDS: Final = {FieldKind.NUMBER: _Kind(ProtoType.DOUBLE, Wire.I64, "d"),
                 FieldKind.INTEGER: _Kind(ProtoType.SFIXED64, Wire.I64, "q"),
                 FieldKind.BOOLEAN: _Kind(ProtoType.BOOL, Wire.VARINT, "?"),  # 0 or 1: a one-byte varint
                 FieldKind.STRING: _Kind(ProtoType.STRING, Wire.LEN, ""),
                 FieldKind.BYTES: _Kind(ProtoType.BYTES, Wire.LEN, "")}
_LABEL_OPTIONAL: Final = 1
_MASK64: Final = (1 << 64) - 1
_SHORT: Final = tuple(bytes((n,)) for n in range(128))  # a length below 128: one byte


def varint(n: int) -> bytes:
    """The base-128 varint of ``n`` (negative: its 64-bit two's complement)."""
    n &= _MASK64
    out = bytearray()
    while n > 0x7F:
        out.append(n & 0x7F | 0x80)
        n >>= 7
    out.append(n)
    return bytes(out)


def tag(number: int, wire: Wire) -> bytes:
    return varint(number << 3 | wire)


def _ld(tag_bytes: bytes, data: bytes) -> bytes:
    """A length-delimited field: tag, length, data."""
    n = len(data)
    return tag_bytes + (_SHORT[n] if n < 128 else varint(n)) + data


def _lds(tag_bytes: bytes, text: str) -> bytes:
    return _ld(tag_bytes, text.encode())


# -- the schema ----------------------------------------------------------------------------


def _field_descriptor(number: int, name: str, kind: FieldKind) -> bytes:
    """A ``FieldDescriptorProto``: name (1), number (3), label (4), type (5)."""
    return (_lds(tag(1, Wire.LEN), name) + tag(3, Wire.VARINT) + varint(number)
            + tag(4, Wire.VARINT) + varint(_LABEL_OPTIONAL) + tag(5, Wire.VARINT) + varint(_KINDS[kind].type))


def descriptor_proto(spec: TopicSpec) -> bytes:
    """The ``DescriptorProto`` (name 1, field 2) of ``spec``'s message."""
    fields = b"".join(_ld(tag(2, Wire.LEN), _field_descriptor(i, f.name, f.kind))
                      for i, f in enumerate(spec.fields, 1))
    return _lds(tag(1, Wire.LEN), spec.schema_name.rpartition(".")[2]) + fields


def file_descriptor_set(spec: TopicSpec) -> bytes:
    """The serialized ``FileDescriptorSet`` of ``spec``'s message: one file (name 1, package 2,
    message_type 4, syntax 12) with one ``DescriptorProto`` (:func:`descriptor_proto`)."""
    package, _, message = spec.schema_name.rpartition(".")
    file = (_lds(tag(1, Wire.LEN), f"{package}/{message}.proto") + _lds(tag(2, Wire.LEN), package)
            + _ld(tag(4, Wire.LEN), descriptor_proto(spec)) + _lds(tag(12, Wire.LEN), "proto3"))
    return _ld(tag(1, Wire.LEN), file)


# -- messages ------------------------------------------------------------------------------


def _layout(spec: TopicSpec) -> tuple[list[int], list[int]]:
    """Indexes of the fixed-width fields and of the length-delimited ones, in field order."""
    fixed = [i for i, f in enumerate(spec.fields) if _KINDS[f.kind].code]
    return fixed, [i for i, f in enumerate(spec.fields) if not _KINDS[f.kind].code]


def _fixed_struct(spec: TopicSpec) -> struct.Struct:
    """Tag bytes (``B`` each) and value of every fixed-width field, little-endian, no padding."""
    fixed, _ = _layout(spec)
    return struct.Struct("<" + "".join("B" * len(tag(i + 1, _KINDS[spec.fields[i].kind].wire))
                                       + _KINDS[spec.fields[i].kind].code for i in fixed))


def packer(spec: TopicSpec) -> Encoder:
    """The topic's fields (a sequence in the table's order) -> its message."""
    fixed, delimited = _layout(spec)
    pairs = []
    for i in fixed:
        tag_args = ", ".join(str(b) for b in tag(i + 1, _KINDS[spec.fields[i].kind].wire))
        pairs.append(f"{tag_args}, f[{i}]")
    args = ", ".join(pairs)
    parts = [f"_pack({args})"] if fixed else ['b""']
    for i in delimited:
        helper = "_lds" if spec.fields[i].kind == FieldKind.STRING else "_ld"
        parts.append(f"{helper}({tag(i + 1, Wire.LEN)!r}, f[{i}])")
    namespace: dict[str, Any] = {"_pack": _fixed_struct(spec).pack, "_ld": _ld, "_lds": _lds}
    # the source holds field indexes and tag bytes only, nothing read from outside
    exec(f"def pack(f):\n    return {' + '.join(parts)}\n", namespace)
    pack: Encoder = namespace["pack"]
    return pack


#: The ``/can/*`` fields :func:`frame_packer` lays out itself, in the table's order.
_FRAME_KEYS: Final = ("timestamp", "arbitration_id", "is_extended_id", "is_remote_frame", "is_error_frame", "is_fd",
                      "bitrate_switch", "error_state_indicator", "dlc", "data", "data_hex", "direction", "channel")
#: Distinct channels whose encoded ``direction`` and ``channel`` fields an encoder keeps.
_CHANNELS: Final = 64


def frame_packer(spec: TopicSpec) -> Encoder | None:
    """A ``/can/*`` frame record's values -> its message, the bytes of
    ``packer(spec)(schemas.can_frame_fields(spec.topic)(values))`` in one step; None for a
    table whose frame fields are not :data:`_FRAME_KEYS`.

    Why: two of a cycle's seven messages are frames, and the writer process is the run's
    other busy process (its CPU competes with the loop's on a 2-core machine). The generic
    path builds the 13 fields first (six ``bool`` calls, a tuple) and encodes the direction
    and channel strings per frame; here the flags go straight to ``struct`` (its ``?``
    packs any value's truth, as ``bool`` does) and the direction and channel fields, the
    same for every frame of a bus, are encoded once per channel."""
    if spec.keys != _FRAME_KEYS:
        return None
    fixed, delimited = _layout(spec)
    tags = [tag(i + 1, _KINDS[spec.fields[i].kind].wire) for i in fixed]
    if fixed != list(range(9)) or delimited != list(range(9, 13)) or any(len(t) != 1 for t in tags):
        return None
    pack = _fixed_struct(spec).pack
    t0, t1, t2, t3, t4, t5, t6, t7, t8 = (t[0] for t in tags)
    data_tag, hex_tag, direction_tag, channel_tag = (tag(i + 1, Wire.LEN) for i in delimited)
    direction = "rx" if spec.topic == Topic.CAN_RX else "tx"
    tails: dict[tuple[type, Any], bytes] = {}

    def tail(channel: Any) -> bytes:
        return _lds(direction_tag, direction) + _lds(channel_tag, "" if channel is None else str(channel))

    def encode(values: Sequence[Any]) -> bytes:
        arb, ext, rtr, err, fd, brs, esi, dlc, data, stamp, channel = values
        data = bytes(data)
        key = (type(channel), channel)
        try:
            end = tails[key]
        except KeyError:
            end = tail(channel)
            if len(tails) < _CHANNELS:
                tails[key] = end
        except TypeError:   # an unhashable channel: encoded each time
            end = tail(channel)
        return (pack(t0, float(stamp or 0.0), t1, arb, t2, ext, t3, rtr, t4, err, t5, fd, t6, brs, t7, esi, t8, dlc)
                + _ld(data_tag, data) + _lds(hex_tag, data.hex()) + end)
    return encode


def read_varint(data: bytes, pos: int) -> tuple[int, int]:
    """The varint at ``pos`` and the position after it; ValueError past the end or too long."""
    n = shift = 0
    while True:
        if pos >= len(data):
            raise ValueError("a varint runs past the end of the message")
        b = data[pos]
        pos += 1
        n |= (b & 0x7F) << shift
        if b < 0x80:
            return n, pos
        shift += 7
        if shift > 63:
            raise ValueError("a varint longer than 10 bytes")


_SIZES: Final = {Wire.I64: 8, Wire.I32: 4}


def fields_on_wire(data: bytes, pos: int = 0) -> Iterator[tuple[int, Wire, Any]]:
    """(field number, wire type, value) of each field of a message: an int (varint), the
    raw bytes (fixed width, length-delimited)."""
    end = len(data)
    while pos < end:
        key, pos = read_varint(data, pos)
        number, wire = key >> 3, key & 7
        value: Any
        if wire == Wire.VARINT:
            value, pos = read_varint(data, pos)
        elif wire in (Wire.I64, Wire.I32, Wire.LEN):
            size, pos = read_varint(data, pos) if wire == Wire.LEN else (_SIZES[Wire(wire)], pos)
            value, pos = bytes(data[pos:pos + size]), pos + size
            if pos > end:
                raise ValueError(f"field {number} runs past the end of the message")
        else:
            raise ValueError(f"field {number} has wire type {wire} (expected 0, 1, 2 or 5)")
        yield number, Wire(wire), value


def _finite(value: float) -> float | None:
    return value if value - value == 0.0 else None   # NaN and infinity: None, as JSON's null


def _signed(n: int) -> int:
    return n - (1 << 64) if n >> 63 else n


def _value(kind: FieldKind, wire: Wire, raw: Any) -> Any:
    """A field's value from the wire; ValueError for a wire type its kind does not take."""
    if kind == FieldKind.NUMBER and wire in (Wire.I64, Wire.I32):
        return struct.unpack("<d" if wire == Wire.I64 else "<f", raw)[0]
    if kind == FieldKind.INTEGER and wire in (Wire.I64, Wire.VARINT):
        return struct.unpack("<q", raw)[0] if wire == Wire.I64 else _signed(raw)
    if kind == FieldKind.BOOLEAN and wire == Wire.VARINT:
        return bool(raw)
    if kind == FieldKind.STRING and wire == Wire.LEN:
        return bytes(raw).decode()
    if kind == FieldKind.BYTES and wire == Wire.LEN:
        return list(raw)
    raise ValueError(f"wire type {wire.name} for a {kind.name.lower()} field")


_DEFAULTS: Final = {FieldKind.NUMBER: 0.0, FieldKind.INTEGER: 0, FieldKind.BOOLEAN: False, FieldKind.STRING: ""}


def _generic(spec: TopicSpec) -> Callable[[bytes, int, dict[str, Any]], dict[str, Any]]:
    """Fields from ``pos`` on into ``out`` (unknown numbers skipped, as protobuf does)."""
    by_number = {i: f for i, f in enumerate(spec.fields, 1)}

    def read(data: bytes, pos: int, out: dict[str, Any]) -> dict[str, Any]:
        for number, wire, raw in fields_on_wire(data, pos):
            f = by_number.get(number)
            if f is not None:
                out[f.name] = _value(f.kind, wire, raw)
        return out
    return read


#: Distinct tails a decoder keeps decoded (a tail of text repeats every cycle: a state's name,
#: an error's text); past it the memo starts again, so a log of ever new text cannot grow it.
_TAILS: Final = 4096
Values = Callable[[bytes], "tuple[Any, ...] | None"]


@lru_cache(maxsize=256)
def _code(source: str) -> CodeType:
    """``source`` compiled, once: a log's decoders are made each time it is read (a replay
    reads three topics: compiling their decoders cost 2.5 ms of its ~150)."""
    return compile(source, "<dobhil.recording.encodings.protobuf>", "exec")


def _compiled(name: str, lines: list[str], namespace: dict[str, Any]) -> Any:
    """The function ``name(data)`` of ``lines`` (its body). The decoders are generated as
    :func:`packer` is: unrolled, a message's fields cost no loop and no call each; the source
    holds field indexes, names, tag bytes and sizes only."""
    exec(_code(f"def {name}(data):\n" + "".join(f"    {line}\n" for line in lines)), namespace)
    return namespace[name]


def _tail(spec: TopicSpec, delimited: list[int], wanted: set[int], lists: bool = True) -> Values:
    """The writer's tail (:func:`packer`): each length-delimited field in field order, a
    one-byte tag and a one-byte length (below 128), up to the message's end -> the values of
    the fields in ``wanted`` (the others checked and skipped; bytes as a new list of integers,
    or with ``lists`` False as bytes); None for any other layout. A
    tail whose wanted fields are text only (``/drive/feedback``'s names, ``/events``) is the
    same bytes cycle after cycle, so it is looked up whole by its bytes before it is read
    field by field (a short string decodes about as fast as a dict finds it: text is not
    looked up field by field)."""
    if any(len(tag(i + 1, Wire.LEN)) != 1 for i in delimited):
        return lambda data: None   # a field number above 15: the generic path reads it
    lines = [f"p = {_fixed_struct(spec).size}", "try:"]
    for i in delimited:
        raw = "data[p + 2:p + 2 + n]"
        value = f"{raw}.decode()" if spec.fields[i].kind == FieldKind.STRING else f"list({raw})" if lists else raw
        lines += ["    n = data[p + 1]", f"    if data[p] != {tag(i + 1, Wire.LEN)[0]} or n > 127: return None",
                  *([f"    v{i} = {value}"] if i in wanted else []), "    p += 2 + n"]
    lines += ["except IndexError:", "    return None",   # a field cut short: the generic path says so
              f"return ({''.join(f'v{i}, ' for i in delimited if i in wanted)}) if p == len(data) else None"]
    by_field: Values = _compiled("tail", lines, {})
    if any(spec.fields[i].kind != FieldKind.STRING for i in wanted):
        return by_field   # bytes vary with every frame
    return _whole(by_field, _fixed_struct(spec).size)


def _whole(by_field: Values, start: int, limit: int = _TAILS) -> Values:
    """``by_field`` looked up by the bytes from ``start`` on first (``limit`` kept)."""
    seen: dict[bytes, tuple[Any, ...]] = {}

    def whole(data: bytes) -> tuple[Any, ...] | None:
        key = data[start:]
        found = seen.get(key)
        if found is None:
            found = by_field(data)
            if found is not None:
                if len(seen) >= limit:
                    seen.clear()
                seen[key] = found
        return found
    return whole


def _finite_all(payload: dict[str, Any], numbers: tuple[str, ...]) -> dict[str, Any]:
    """``payload`` with each number named in ``numbers`` that is NaN or infinite as None."""
    for name in numbers:
        payload[name] = _finite(payload[name])
    return payload


def _finite_row(row: tuple[Any, ...], numbers: tuple[int, ...]) -> tuple[Any, ...]:
    """``row`` with each number at ``numbers`` that is NaN or infinite as None."""
    out = list(row)
    for k in numbers:
        out[k] = _finite(out[k])
    return tuple(out)


def _fast(spec: TopicSpec, names: Sequence[str] | None = None) -> Callable[[bytes], Any]:
    """The writer's own layout (:func:`packer`) -> the payload dict (``names`` None: the
    table's order) or the tuple of the fields ``names``, as the dict holds them but bytes as
    bytes (:meth:`~dobhil.recording.encodings.base.Encoding.row_decoder`); non-finite numbers
    as None; None for any other layout. One unpack reads the fixed-width fields
    with their tags (checked; a flag's byte too: one of 128 or more begins a longer varint,
    another layout), :func:`_tail` the rest; a dict display with the table's names builds
    the payload; the sum of the numbers tells whether all are finite (a NaN or an infinity
    makes it not finite), so a message of finite numbers takes no call per number."""
    fixed, delimited = _layout(spec)
    if not all(f.name.isidentifier() for f in spec.fields):
        raise ValueError(f"{spec.schema_name}: a field name that is not an identifier")
    picked = list(range(len(spec.fields))) if names is None else [spec.keys.index(n) for n in names]
    size = _fixed_struct(spec).size
    head = struct.Struct(_fixed_struct(spec).format.replace("?", "B")).unpack_from   # a flag as its byte
    unpacked: list[str] = []
    tags: list[str] = []
    for i in fixed:
        key = tag(i + 1, _KINDS[spec.fields[i].kind].wire)
        tags += [f"t{i}_{j}" for j in range(len(key))]
        unpacked += [f"t{i}_{j}" for j in range(len(key))] + [f"v{i}"]
    expected = tuple(b for i in fixed for b in tag(i + 1, _KINDS[spec.fields[i].kind].wire))
    flags = [i for i in fixed if spec.fields[i].kind == FieldKind.BOOLEAN]
    numbers = [k for k in picked if spec.fields[k].kind == FieldKind.NUMBER]
    lines = [f"if len(data) {'<' if delimited else '!='} {size}: return None"]
    if fixed:
        lines += [f"{', '.join(unpacked)}, = head(data)", f"if ({', '.join(tags)},) != {expected!r}: return None"]
    if flags:
        lines.append(f"if {' | '.join(f'v{i}' for i in flags)} > 127: return None")
    if delimited:
        wanted = [i for i in delimited if i in picked]
        lines += ["rest = tail(data)", "if rest is None: return None",
                  *([f"{''.join(f'v{i}, ' for i in wanted)}= rest"] if wanted else [])]
    value = {k: f"v{k} != 0" if k in flags else f"v{k}" for k in picked}
    if names is None:
        lines.append(f"out = {{{', '.join(f'{spec.fields[k].name!r}: {value[k]}' for k in picked)}}}")
        finite = f"finite_all(out, {tuple(spec.fields[k].name for k in numbers)!r})"
    else:
        lines.append(f"out = ({''.join(f'{value[k]}, ' for k in picked)})")
        finite = f"finite_row(out, {tuple(picked.index(k) for k in numbers)!r})"
    if numbers:
        lines += [f"total = {' + '.join(f'v{k}' for k in numbers)}", f"if total - total != 0.0: return {finite}"]
    lines.append("return out")
    namespace = {"head": head, "tail": _tail(spec, delimited, set(picked), names is None) if delimited else None,
                 "finite_all": _finite_all, "finite_row": _finite_row}
    return _compiled("payload", lines, namespace)


def unpacker(spec: TopicSpec) -> Decoder:
    """Message -> payload dict: the writer's layout straight to the dict (:func:`_fast`),
    any other encoding field by field; fields absent take protobuf's defaults."""
    fast, read, keys = _fast(spec), _generic(spec), spec.keys
    numbers = [f.name for f in spec.fields if f.kind == FieldKind.NUMBER]
    defaults = {f.name: _DEFAULTS.get(f.kind) for f in spec.fields}

    def decode(data: bytes) -> dict[str, Any]:
        found: dict[str, Any] | None = fast(data)
        if found is not None:
            return found
        out = read(data, 0, {})
        # the table's order, as JSON has it; fields left at their defaults (bytes: a new empty list)
        out = {k: out[k] if k in out else [] if defaults[k] is None else defaults[k] for k in keys}
        for name in numbers:
            out[name] = _finite(out[name])
        return out
    return decode


def row_unpacker(spec: TopicSpec, names: Sequence[str]) -> RowDecoder:
    """Message -> the values of the fields ``names``, in that order, as :func:`unpacker`'s
    dict holds them but bytes as bytes: the writer's layout straight to them (:func:`_fast`:
    no dict, the other fields only checked), any other encoding through the dict."""
    fast, get, at = _fast(spec, names), row_getter(names), bytes_at(spec, names)
    slow: list[Decoder] = []   # made when a message first needs it

    def row(data: bytes) -> tuple[Any, ...]:
        found: tuple[Any, ...] | None = fast(data)
        if found is not None:
            return found
        if not slow:
            slow.append(unpacker(spec))
        return as_bytes(get(slow[0](data)), at)
    return row


def descriptor_fields(data: bytes, message: str) -> tuple[str, ...]:
    """Field names, in number order, of message ``message`` (its full name) in a serialized
    ``FileDescriptorSet``; ValueError if it is not there."""
    for number, _, file in fields_on_wire(data):
        if number != 1:
            continue
        parts = [(n, v) for n, _, v in fields_on_wire(bytes(file))]
        package = next((bytes(v).decode() for n, v in parts if n == 2), "")
        for n, v in parts:
            if n != 4:
                continue
            body = list(fields_on_wire(bytes(v)))
            name = next(bytes(x).decode() for k, _, x in body if k == 1)
            if f"{package}.{name}".lstrip(".") == message:
                found = []
                for k, _, x in body:
                    if k == 2:
                        field = {fn: fv for fn, _, fv in fields_on_wire(bytes(x))}
                        found.append((field.get(3, 0), bytes(field.get(1, b"")).decode()))
                return tuple(name for _, name in sorted(found))
    raise ValueError(f"no message {message!r} in the schema's FileDescriptorSet")


@dataclass(frozen=True)
class ProtobufEncoding:
    name: str = "protobuf"
    schema_encoding: str = "protobuf"

    def schema(self, spec: TopicSpec) -> bytes:
        return file_descriptor_set(spec)

    def encoder(self, spec: TopicSpec, codes: ProtocolCodes | None) -> Encoder:
        frame = frame_packer(spec) if spec.topic in (Topic.CAN_RX, Topic.CAN_TX) else None
        if frame is not None:
            return frame
        pack, make = packer(spec), field_values(spec, codes)
        if make is None:
            return pack

        def encode(values: Sequence[Any]) -> bytes:
            return pack(make(values))
        return encode

    def decoder(self, spec: TopicSpec | None) -> Decoder:
        if spec is None:
            raise ValueError("a protobuf message needs its topic's fields")
        return unpacker(spec)

    def row_decoder(self, spec: TopicSpec | None, names: Sequence[str], defaults: Mapping[str, Any]) -> RowDecoder:
        if spec is None:
            raise ValueError("a protobuf message needs its topic's fields")
        return row_unpacker(spec, names)   # a field absent takes protobuf's default

    def schema_fields(self, data: bytes, schema_name: str) -> tuple[str, ...]:
        return descriptor_fields(data, schema_name)


ENCODING: Final = ProtobufEncoding()

__all__ = ["ENCODING", "ProtoType", "ProtobufEncoding", "Wire", "descriptor_fields", "descriptor_proto",
           "fields_on_wire", "file_descriptor_set", "frame_packer", "packer", "read_varint", "row_unpacker", "tag",
           "unpacker", "varint"]
