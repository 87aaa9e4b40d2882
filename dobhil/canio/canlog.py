"""CAN logs in python-can's formats to and from dobhil recordings: ``dobhil log export
--can`` (a checked recording's ``/can/rx`` and ``/can/tx`` through python-can's writers) and
``dobhil log import`` (any log python-can reads, through :class:`LogWriter`, the same frame
records as ``can.Logger("x.mcap")``); outputs checked first and written under a temporary name.

A log cut short (a logger killed mid-write, a copy interrupted) is imported up to its last
complete record, with one warning saying what was dropped at the end: such a log is what a
killed run leaves, and refusing it would leave no way in (``dobhil log recover`` salvages
MCAP only); a cut record is never imported as a shorter frame. Damage before the end (a
malformed line in the middle of a candump file) is refused. A gzip-compressed log
(``run.log.gz``, python-can's ``LogReader`` reads the format of the suffix before ``.gz``) gets
the same checks on its uncompressed bytes; its compressed stream stopping before its end
marker (a logger killed mid-write) is a cut too, damaged compressed data is refused.
"""

from __future__ import annotations

import gzip
import io
import locale
import math
import os
import re
import struct
import zlib
from datetime import datetime, timezone
from collections.abc import Callable, Mapping
from enum import IntEnum
from pathlib import Path
from types import MappingProxyType
from typing import IO, Any, BinaryIO, Final, cast

import can

from dobhil.canio.frames import frame_channels, is_frame_topic, topic_of
from dobhil.errors import LogFileError, exception_line
from dobhil.files import atomic_path, check_output, input_problem
from dobhil.recording.reader import open_log
from dobhil.recording.schemas import can_frame_message, can_frame_record
from dobhil.recording.writer import LogWriter

ProgressFn = Callable[[int], None]


class CanLogFormat(IntEnum):
    CANDUMP = 1
    ASC = 2
    BLF = 3


class CandumpWriter(can.CanutilsLogWriter):
    """python-can's candump writer, a remote frame's DLC kept: it writes ``ID#R`` for every
    remote frame, which reads back as DLC 0, where can-utils' candump writes ``ID#R8`` for a
    remote frame of DLC 8 (lib.c ``snprintf_canframe``: the DLC after the ``R`` when it is 1
    to 8), and python-can's own reader takes that digit back as the DLC."""

    def on_message_received(self, msg: can.Message) -> None:
        if not msg.is_remote_frame or msg.is_error_frame or not 0 < msg.dlc <= 8:
            super().on_message_received(msg)
            return
        file, self.file = self.file, io.StringIO()
        try:
            super().on_message_received(msg)
            head, _, tail = cast(io.StringIO, self.file).getvalue().rpartition("#R")
        finally:
            self.file = file
        file.write(f"{head}#R{msg.dlc}{tail}")


#: Format -> (file suffix, python-can writer class).
FORMATS: Final[Mapping[CanLogFormat, tuple[str, type[can.io.generic.MessageWriter]]]] = MappingProxyType({
    CanLogFormat.CANDUMP: (".log", CandumpWriter), CanLogFormat.ASC: (".asc", can.ASCWriter),
    CanLogFormat.BLF: (".blf", can.BLFWriter)})


def parse_format(name: str) -> CanLogFormat:
    try:
        return CanLogFormat[name.upper()]
    except KeyError:
        known = ", ".join(f.name.lower() for f in CanLogFormat)
        raise LogFileError(f"unknown CAN log format {name!r}; expected one of {known}") from None


def default_can_output(mcap_path: str | os.PathLike[str], fmt: CanLogFormat) -> Path:
    """``run.mcap`` -> ``run.log`` / ``run.asc`` / ``run.blf``."""
    return Path(mcap_path).with_suffix(FORMATS[fmt][0])


def export_can(mcap_path: str | os.PathLike[str], out: str | os.PathLike[str], fmt: CanLogFormat, *,
               progress: ProgressFn | None = None) -> int:
    """The recording's CAN frames to ``out`` in ``fmt`` (every bus' of a several-axis log, in
    the order recorded, each frame with the channel its bus gave it); the frame count."""
    check_output(out, inputs=[mcap_path], what="output", suffix=FORMATS[fmt][0])
    # describe: a copy of what was recorded never applies the config, so a newer dobhil's log is exported too
    with open_log(mcap_path, describe=True) as log:
        topics = [t for t in log.topics() if is_frame_topic(t)]
        if not topics:
            raise LogFileError(f"{os.fspath(mcap_path)}: no CAN frames (no /can/rx or /can/tx topic)")
        with atomic_path(out) as tmp, FORMATS[fmt][1](tmp) as writer:
            count = 0
            _start_at_earliest(writer, log, topics)
            bus_channel = frame_channels(log.metadata, mcap_path)
            for topic, t, payload in log.iter_messages(topics):
                msg = can_frame_message(payload, t)
                if msg.channel is None:
                    msg.channel = bus_channel.get(topic)
                if fmt is CanLogFormat.BLF:  # BLF stores channels as small integers
                    number = can.util.channel2int(msg.channel)
                    msg.channel = number if number is not None and 0 <= number <= 0xFFFF else None
                writer.on_message_received(msg)
                count += 1
                if progress is not None:
                    progress(1)
            return count


def _start_at_earliest(writer: can.io.generic.MessageWriter, log: Any, topics: list[str]) -> None:
    """Every python-can writer times its frames from the first one it is given, and writes
    a frame older than that wrongly: ASC as an absolute time (another date when read back),
    BLF and candump at the first frame's time (BLFWriter clamps its offset at 0,
    CanutilsLogWriter any older time to the first). Frames are exported in log-time order,
    where a received frame may be older than a command sent before it was read: so the file
    starts at the earliest frame (ASC and BLF: one event line there; candump has no events,
    its writer is told the earliest time as its first)."""
    earliest = min((p.get("timestamp") or t / 1e9 for _, t, p in log.iter_messages(topics)), default=None)
    if earliest is None:
        return
    if isinstance(writer, can.ASCWriter):
        start = asc_start(earliest)
        writer.log_event(f"{ASC_EXPORT_EVENT} (start {_utc_text(start)})", start)
    elif isinstance(writer, can.BLFWriter):
        writer.log_event("dobhil log export", earliest)
    elif isinstance(writer, can.CanutilsLogWriter):
        writer.last_timestamp = earliest


#: The event an ASC export starts with. Its text names the start in UTC: an ASC header's date
#: has no time zone, python-can's ASCWriter writes it in the local one and its ASCReader reads
#: it in the local one of the machine that reads it (can/io/asc.py: ``datetime.fromtimestamp``,
#: ``strptime(...).timestamp()``), so an export imported where the zone (``TZ``) differs, or
#: within a daylight saving time change's repeated hour, would be off by the difference;
#: :func:`import_can` takes the UTC start from this line instead.
ASC_EXPORT_EVENT: Final = "dobhil log export"
_ASC_EXPORT_LINE: Final = re.compile(rf"\s*(?P<offset>\d+\.\d+) {ASC_EXPORT_EVENT} \(start (?P<utc>[0-9T:.+-]+)\)\s*")


def _utc_text(t: float) -> str:
    """``t`` (a whole millisecond, :func:`asc_start`) in ISO 8601 UTC, to the millisecond."""
    return datetime.fromtimestamp(t, timezone.utc).isoformat(timespec="milliseconds")


def asc_start(earliest: float) -> float:
    """A start time for an ASC file, at or before ``earliest``, that python-can reads back
    as it wrote it. Workaround: python-can's ASCWriter writes the header's milliseconds
    without leading zeros (``12:00:07.46`` for 46 ms) and its reader takes them as a
    fraction (0.46 s), so a start in the first 100 ms of a second would read back up to
    0.9 s late. A whole millisecond (the header holds no more) from 100 to 999 reads back
    exactly: the nearest one at or before ``earliest``."""
    ms = math.floor(earliest * 1000)
    if ms % 1000 < 100:
        ms -= ms % 1000 + 1   # the last millisecond of the second before
    return ms / 1000


#: python-can's readers of line-oriented text logs, by suffix (as ``can.LogReader`` picks them,
#: python-can's can/io/player.py); each reads any text file object it is given.
TEXT_READERS: Final[Mapping[str, Callable[..., can.io.generic.MessageReader]]] = MappingProxyType({
    ".log": can.CanutilsLogReader, ".asc": can.ASCReader, ".trc": can.TRCReader, ".csv": can.CSVReader})

#: A ``candump -L`` line as can-utils writes it (lib.c: ``(TIME) IFACE ID#DATA``, the ID 3 hex
#: digits (standard) or 8 (extended), DATA hex pairs, ``R`` (+ a DLC digit) for a remote frame,
#: ``#F`` + pairs for CAN FD), with python-can's optional `` R``/`` T`` direction.
_CANDUMP_LINE = re.compile(r"\(\d+(?:\.\d*)?\)\s+\S+\s+(?:[0-9A-Fa-f]{3}|[0-9A-Fa-f]{8})#(?P<data>\S*)(?:\s+[RrTt])?")
_CANDUMP_DATA = re.compile(r"[Rr]\d?|(?P<fd>#[0-9A-Fa-f])?(?P<hex>[0-9A-Fa-f]*)")
#: The data lengths of a CAN FD frame (ISO 11898-1: DLC 0..15).
_FD_LENGTHS: Final = frozenset((*range(9), 12, 16, 20, 24, 32, 48, 64))
_CANDUMP_FORM = "(TIME) IFACE ID#DATA, DATA 0 to 8 bytes as hex pairs (ID##F + 0 to 64 bytes for CAN FD)"


def candump_problem(line: str) -> str | None:
    """What is wrong with a candump line (None: nothing). python-can's CanutilsLogReader does
    not check the data: it yields a frame for a line with an odd number of hex digits (the
    last digit read as a byte) or more than 8 bytes without ``##``, so such a line is checked
    here before python-can parses it."""
    text = line.strip()
    if not text:
        return None   # python-can skips empty lines
    match = _CANDUMP_LINE.fullmatch(text)
    data = _CANDUMP_DATA.fullmatch(match["data"]) if match else None
    if match is None or data is None:
        return f"not a candump -L frame line {text[:60]!r}; expected {_CANDUMP_FORM}"
    digits = data["hex"] or ""
    if len(digits) % 2:
        return f"data {match['data']!r} has an odd number of hex digits; expected {_CANDUMP_FORM}"
    if len(digits) // 2 > 8 and not data["fd"] or data["fd"] and len(digits) // 2 not in _FD_LENGTHS:
        kind = "CAN FD frame" if data["fd"] else "CAN frame"
        return f"{len(digits) // 2} data bytes is no {kind} length; expected {_CANDUMP_FORM}"
    return None


class _Gunzipped(io.RawIOBase):
    """The uncompressed bytes of a gzip file (RFC 1952), read through :class:`gzip.GzipFile`.
    A compressed stream that stops before its end marker (what a logger killed mid-write
    leaves) ends where its data does, ``cut`` set: GzipFile raises ``EOFError`` there, after
    every byte it could decompress (``read1``: one read of its reader, so none is held back).
    Damaged compressed data (a bad deflate block, a CRC or length that does not match) raises
    a :class:`LogFileError` naming how far it read."""

    def __init__(self, path: Path) -> None:
        super().__init__()
        self.path = path
        self.cut = False
        self._gz = gzip.GzipFile(path, "rb")

    def readable(self) -> bool:
        return True

    def seekable(self) -> bool:
        return True

    def readinto(self, buffer: Any) -> int:
        view = memoryview(buffer).cast("B")
        try:
            data = self._gz.read1(len(view))
        except EOFError:
            self.cut = True
            return 0
        except (OSError, zlib.error) as exc:   # gzip.BadGzipFile is an OSError
            at = self._gz.tell()
            what = "not gzip data" if at == 0 else f"damaged gzip data after {at} uncompressed bytes"
            raise LogFileError(f"{self.path}: {what} ({exception_line(exc)})") from None
        view[:len(data)] = data
        return len(data)

    def seek(self, offset: int, whence: int = io.SEEK_SET) -> int:
        return self._gz.seek(offset, whence)

    def tell(self) -> int:
        return self._gz.tell()

    def size(self) -> int:
        """The uncompressed size (one pass through the stream; ``cut`` set when it stops
        before its end marker), the position back at the start."""
        chunk = bytearray(1 << 16)
        total = 0
        self.seek(0)
        while n := self.readinto(chunk):
            total += n
        self.seek(0)
        return total

    def close(self) -> None:
        self._gz.close()
        super().close()


#: What a ``.gz`` log's warning adds when its compressed stream stops before its end marker.
_GZIP_CUT: Final = "the gzip stream stops before its end marker"


def _format_suffix(path: Path) -> str:
    """The suffix that says a log's format: ``.log`` of ``run.log`` and of ``run.log.gz``
    (python-can's ``LogReader`` reads a ``.gz`` as the format of the suffix before it)."""
    suffixes = [s.lower() for s in path.suffixes]
    return suffixes[-2] if len(suffixes) >= 2 and suffixes[-1] == ".gz" else path.suffix.lower()


class _Lines:
    """A text log's lines, for a python-can reader to iterate as its file: stops before a
    last line without an end of line (every writer ends each record with one, so that line
    is a record cut short, ``cut`` says which), raises a :class:`LogFileError` naming the
    line ``check`` finds wrong; ``number`` is the line last read. ``gz``: the lines of a
    gzip file's uncompressed bytes, its stream stopping early a cut as well."""

    def __init__(self, path: Path, check: Callable[[str], str | None] | None, gz: _Gunzipped | None = None,
                 asc: bool = False) -> None:
        self.path, self.check, self.gz, self.asc = path, check, gz, asc
        self.number = 0
        self.cut: str | None = None
        #: an ASC export's start in UTC and its offset in the file (:data:`ASC_EXPORT_EVENT`)
        self.asc_export: tuple[float, float] | None = None
        # the encoding python-can's TextIOMessageReader opens a path with
        encoding = locale.getpreferredencoding(False)
        self._file: IO[str] = (open(path, encoding=encoding) if gz is None
                               else io.TextIOWrapper(io.BufferedReader(gz), encoding=encoding))

    def __iter__(self) -> _Lines:
        return self

    def __next__(self) -> str:
        try:
            line = next(self._file)
        except StopIteration:
            if self.gz is not None and self.gz.cut:
                self.cut = f"what followed line {self.number}: {_GZIP_CUT}"
            raise
        self.number += 1
        if not line.endswith("\n"):
            self.cut = f"line {self.number}, a record cut short ({len(line)} characters and no end of line)"
            if self.gz is not None and self.gz.cut:   # a line without one ends only at the stream's end
                self.cut += f"; {_GZIP_CUT}"
            raise StopIteration
        problem = self.check(line) if self.check is not None else None
        if problem is not None:
            raise LogFileError(f"{self.path}: line {self.number}: {problem}")
        if self.asc and self.asc_export is None and (match := _ASC_EXPORT_LINE.fullmatch(line)):
            try:
                self.asc_export = datetime.fromisoformat(match["utc"]).timestamp(), float(match["offset"])
            except ValueError:
                pass   # not a time: the header's date, as for any ASC
        return line

    def close(self) -> None:
        self._file.close()


#: BLF's file header start (signature ``LOGG``, header size) and object header (signature
#: ``LOBJ``, header size, header version, object size, object type), as python-can's
#: can/io/blf.py reads them (FILE_HEADER_STRUCT, OBJ_HEADER_BASE_STRUCT).
_BLF_FILE_HEAD = struct.Struct("<4sL")
_BLF_OBJECT_HEAD = struct.Struct("<4sHHLL")
#: An object header and a log container's (compression method, size: LOG_CONTAINER_STRUCT).
_BLF_WHOLE = _BLF_OBJECT_HEAD.size + 16


class _BlfBytes:
    """A BLF file's bytes, for python-can's BLFReader to read as its file (it calls ``read``
    only). ``cut`` says what the file lost at its end (None: nothing seen), found by walking
    its top-level objects (each a header, its size, padding to 4 bytes: python-can's reader)
    and by the header's file size. Of an object the file ends within, the reader yields the
    whole frames its part holds (never a partial one: its own test, can/io/blf.py
    ``_parse_data``); one whose headers are not all there (its own and its log container's,
    :data:`_BLF_WHOLE`) it fails to unpack, after every frame before it: so the bytes end
    before such an object."""

    def __init__(self, path: Path, gz: _Gunzipped | None = None) -> None:
        self.path = path
        self.cut: str | None = None
        # a gzip file: its uncompressed bytes, walked as a plain file's (forward seeks decompress)
        size = self.size = path.stat().st_size if gz is None else gz.size()
        self._file: IO[bytes] = open(path, "rb") if gz is None else io.BufferedReader(gz)
        self._left = size
        head = self._file.read(_BLF_FILE_HEAD.size)
        pos = _BLF_FILE_HEAD.unpack(head)[1] if len(head) == _BLF_FILE_HEAD.size and head[:4] == b"LOGG" else size
        while pos + _BLF_OBJECT_HEAD.size <= size:
            self._file.seek(pos)
            signature, _, _, obj_size, _ = _BLF_OBJECT_HEAD.unpack(self._file.read(_BLF_OBJECT_HEAD.size))
            if signature != b"LOBJ" or obj_size < _BLF_OBJECT_HEAD.size:
                break   # damage, not a cut: python-can's reader says what
            if pos + obj_size > size:
                self.cut = f"the part past byte {size} of the {obj_size}-byte object at byte {pos}"
                if size - pos < _BLF_WHOLE:
                    self._left = pos
                break
            pos += obj_size + obj_size % 4
        else:
            if pos < size:
                self._left = pos
                self.cut = f"the object at byte {pos}, cut {size - pos} bytes into its header"
        if gz is not None and gz.cut:
            self.cut = f"{self.cut}; {_GZIP_CUT}" if self.cut else f"what followed byte {size}: {_GZIP_CUT}"
        self._file.seek(0)

    def read(self, n: int = -1) -> bytes:
        data = self._file.read(self._left if n < 0 else min(n, self._left))
        self._left -= len(data)
        return data

    def close(self) -> None:
        self._file.close()

    def check_header(self, reader: Any) -> None:
        """The header's file size and object count (set when the writer closed the file;
        python-can's BLFReader sets them as ``file_size`` and ``object_count``, attributes
        its API documentation does not list, hence looked up with a default): a file shorter
        than that was cut, maybe between two objects, which the walk cannot see."""
        promised, objects = getattr(reader, "file_size", None), getattr(reader, "object_count", None)
        size = self.size
        if isinstance(promised, int) and promised > size:
            gives = f"its header gives {promised} bytes" + (f", {objects} objects" if isinstance(objects, int) else "")
            self.cut = f"{self.cut or f'the {promised - size} bytes past byte {size}'}; {gives}"


def _can_reader(path: Path) -> tuple[Any, _Lines | _BlfBytes | None]:
    """python-can's reader of ``path`` and, for a text log, the lines it reads, for a BLF
    log, the bytes."""
    problem = input_problem(path)
    if problem is not None:
        raise LogFileError(f"{path}: {problem}; expected a CAN log file python-can reads (.asc, .blf, .log, .trc, ...)")
    if path.stat().st_size == 0:
        raise LogFileError(f"{path}: empty file")
    suffix = _format_suffix(path)
    # ASC: absolute times (its Begin Triggerblock date plus each line's offset), as every
    # other format gives; python-can's default for ASC is times from 0, i.e. 1970
    absolute = {"relative_timestamp": False} if suffix == ".asc" else {}
    text_reader = TEXT_READERS.get(suffix)
    if suffix != ".blf" and text_reader is None:   # a format without checks of its own: python-can's
        try:
            return can.LogReader(path, **absolute), None
        except Exception as exc:  # python-can readers raise what their parsers raise
            raise LogFileError(f"{path}: not a CAN log python-can reads ({exception_line(exc)})") from exc
    gz = _Gunzipped(path) if path.suffix.lower() == ".gz" else None
    source: _Lines | _BlfBytes | None = None
    try:
        if suffix == ".blf":
            source = _BlfBytes(path, gz)
            reader = can.BLFReader(cast(BinaryIO, source))   # it calls read() and close() only
            source.check_header(reader)
            return reader, source
        source = _Lines(path, candump_problem if text_reader is can.CanutilsLogReader else None, gz,
                        asc=suffix == ".asc")
        return cast(Callable[..., Any], text_reader)(source, **absolute), source
    except Exception as exc:  # python-can readers raise what their parsers raise
        if source is not None:
            source.close()
        elif gz is not None:
            gz.close()
        if isinstance(exc, LogFileError):
            raise
        raise LogFileError(f"{path}: not a CAN log python-can reads ({exception_line(exc)})") from exc


def short_frame(msg: can.Message) -> str | None:
    """What is wrong with a data frame whose data is shorter than its DLC says (None:
    nothing). python-can's readers build a frame from what a record holds without checking
    it against the DLC: ASCReader's from ``d 8 00 11`` has DLC 8 and 2 bytes. A longer one
    is left alone: python-can's CSV format keeps no FD flag, so its CAN FD frames read back as
    classic frames of their length."""
    if msg.is_remote_frame or msg.is_error_frame:
        return None
    want = msg.dlc if msg.is_fd else min(msg.dlc, 8)   # a classic DLC 9..15 means 8 bytes
    if len(msg.data) < want:
        return f"a frame with {len(msg.data)} data bytes where its DLC says {msg.dlc}; its record is damaged"
    return None


def import_metadata(source: Path) -> dict[str, str]:
    """The ``import`` metadata record of an imported log: its file name and its format, by
    the suffix python-can's ``LogReader`` reads it by (``log``: candump, ``asc``, ``blf``, ...;
    of ``run.log.gz`` the ``log`` before ``.gz``, the format of what the gzip stream holds), and
    ``compression: gzip`` for a gzip-compressed one."""
    meta = {"source": source.name, "format": _format_suffix(source).lstrip(".")}
    if source.suffix.lower() == ".gz":
        meta["compression"] = "gzip"
    return meta


def _asc_shift(reader: Any, lines: _Lines | _BlfBytes | None) -> float:
    """Seconds to add to the times of an ASC export read in another time zone than it was
    written in (:data:`ASC_EXPORT_EVENT`): its UTC start less the start python-can's reader
    took from the header (``start_time``, the header's date read as local time, plus the
    event's offset), in whole seconds (a zone's offset; what is left is the header's
    rounding). 0 for any other log."""
    if not isinstance(lines, _Lines) or lines.asc_export is None:
        return 0.0
    start = getattr(reader, "start_time", None)
    if not isinstance(start, float) or start == 0.0:   # relative times: no date to correct
        return 0.0
    utc, offset = lines.asc_export
    return float(round(utc - (start + offset)))


def import_can(canlog: str | os.PathLike[str], out: str | os.PathLike[str], *,
               progress: ProgressFn | None = None, warn: Callable[[str], None] | None = None) -> int:
    """Every complete frame of a python-can readable log into a new MCAP; the frame count.
    A log cut short is imported up to its last complete record and ``warn`` gets one line
    saying what was dropped at the end (module docstring); damage before the end raises."""
    source = Path(canlog)
    check_output(out, inputs=[source], suffix=".mcap", what="output", new=True)
    count, meta = 0, {"import": import_metadata(source)}
    reader, lines = _can_reader(source)
    shift: float | None = None
    with reader, atomic_path(out) as tmp:
        log = LogWriter(open(tmp, "wb"), metadata=meta, fsync=False)
        try:
            for msg in reader:
                if shift is None:
                    shift = _asc_shift(reader, lines)
                msg.timestamp += shift
                problem = short_frame(msg)
                if problem is not None:
                    where = f"line {lines.number}" if isinstance(lines, _Lines) else f"frame {count + 1}"
                    raise LogFileError(f"{source}: {where}: {problem}")
                log.write([can_frame_record(msg, topic_of(msg),
                                            round((msg.timestamp or 0.0) * 1e9))])
                count += 1
                if progress is not None:
                    progress(1)
        except LogFileError:
            log.close()
            raise
        except Exception as exc:  # whatever a damaged log makes the reader raise
            log.close()
            where = f"line {lines.number}: " if isinstance(lines, _Lines) else ""
            raise LogFileError(f"{source}: {where}unreadable after {count} frames ({exception_line(exc)})") from exc
        cut = lines.cut if lines is not None else None
        if count == 0:
            log.close()
            if cut is not None:
                raise LogFileError(f"{source}: no complete CAN frame before the end was cut short ({cut})")
            raise LogFileError(f"{source}: no CAN frames found (is it a {_format_suffix(source) or 'CAN'} log?)")
        log.finish(None)
    if cut is not None and warn is not None:
        warn(f"{source}: cut short: imported the {count} complete frames; dropped {cut}")
    return count


__all__ = ["FORMATS", "TEXT_READERS", "CanLogFormat", "CandumpWriter", "candump_problem", "default_can_output",
           "export_can", "import_can", "import_metadata", "parse_format", "short_frame"]
