"""Fast reading of message payloads from a complete dobhil MCAP file.

Written by hand because the ``mcap`` package's reader parses every record of a
chunk field by field in Python (~10 us a message, all topics, before filtering),
which made replay spend nine tenths of its time reading. Here the summary's chunk
indexes locate each chunk, the chunk is decompressed once, and only the message
records of the wanted channels are sliced out with ``struct.unpack_from``. Same
file format; files without a summary (cut short) are left to the ``mcap`` reader
(``dobhil log recover`` first).
"""

from __future__ import annotations

import struct
from collections.abc import Iterable, Iterator
from typing import Any, BinaryIO, Final

from dobhil.errors import LogFileError

_RECORD_HEAD: Final = struct.Struct("<BQ")        # opcode, length
_CHUNK_HEAD: Final = struct.Struct("<QQQIi")      # start, end, uncompressed size, crc, len(compression)
_MESSAGE_HEAD: Final = struct.Struct("<HIQQ")     # channel, sequence, log time, publish time
_OP_CHUNK: Final = 0x06
_OP_MESSAGE: Final = 0x05


def iter_payloads(f: BinaryIO, summary: Any, topics: Iterable[str]) -> Iterator[tuple[str, int, bytes]]:
    """(topic, log_time_ns, data) of the wanted topics, in file (write) order."""
    wanted = {cid: ch.topic for cid, ch in summary.channels.items() if ch.topic in set(topics)}
    for index in sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset):
        if not wanted.keys() & index.message_index_offsets.keys():
            continue
        yield from _chunk_messages(_chunk_records(f, index), wanted)


def _chunk_records(f: BinaryIO, index: Any) -> bytes:
    f.seek(index.chunk_start_offset)
    raw = f.read(index.chunk_length)
    opcode, _ = _RECORD_HEAD.unpack_from(raw, 0)
    if opcode != _OP_CHUNK:
        raise LogFileError(f"chunk index points at record 0x{opcode:02x}, not a chunk")
    _, _, size, _, name_len = _CHUNK_HEAD.unpack_from(raw, 9)
    start = 9 + _CHUNK_HEAD.size + name_len + 8
    return _decompress(index.compression, raw[start:start + index.compressed_size], size)


def _decompress(compression: str, data: bytes, size: int) -> bytes:
    if compression == "":
        return data
    if compression == "zstd":
        import zstandard
        return zstandard.ZstdDecompressor().decompress(data, max_output_size=size)
    if compression == "lz4":
        import lz4.frame
        return lz4.frame.decompress(data)
    raise LogFileError(f"unknown chunk compression {compression!r}")


def _chunk_messages(records: bytes, wanted: dict[int, str]) -> Iterator[tuple[str, int, bytes]]:
    head, msg_head = _RECORD_HEAD.unpack_from, _MESSAGE_HEAD.unpack_from
    pos, end = 0, len(records)
    while pos < end:
        opcode, length = head(records, pos)
        body = pos + 9
        if opcode == _OP_MESSAGE:
            channel, _, log_time, _ = msg_head(records, body)
            topic = wanted.get(channel)
            if topic is not None:
                yield topic, log_time, records[body + 22:body + length]
        pos = body + length
