"""CAN frames out to candump/ASC/BLF and back in, through python-can's own readers."""

from __future__ import annotations

import gzip
from collections.abc import Callable
from pathlib import Path

import can
import pytest

from dobhil.errors import LogFileError
from dobhil.canio.canlog import CanLogFormat, export_can, import_can, parse_format
from dobhil.canio.canlog import default_can_output as default_output
from dobhil.recording.reader import open_log
from dobhil.recording.schemas import Topic
from tests.recording.helpers import command, frame, write_log

T0 = 1_700_000_000.0

FRAMES = (
    (Topic.CAN_RX, can.Message(timestamp=T0, arbitration_id=0x123, data=bytes(range(8)), channel="can0")),
    (Topic.CAN_TX, can.Message(timestamp=T0 + 0.001, arbitration_id=0x1ABCDEF, is_extended_id=True,
                               data=b"\x01\x02\x03", channel="can0")),
    (Topic.CAN_RX, can.Message(timestamp=T0 + 0.0015, arbitration_id=0x456, is_remote_frame=True, dlc=0,
                               channel="can0")),
    (Topic.CAN_TX, can.Message(timestamp=T0 + 0.0017, arbitration_id=0x061, is_extended_id=False,
                               is_remote_frame=True, dlc=8, channel="can0")),   # an ODrive request: its DLC kept
    (Topic.CAN_TX, can.Message(timestamp=T0 + 0.002, arbitration_id=0x001, data=b"", channel="can0")),
    (Topic.CAN_RX, can.Message(timestamp=T0 + 0.003, arbitration_id=0x7FF, is_fd=True, bitrate_switch=True,
                               data=bytes(range(12)), channel="can0")),
)

#: Timestamp resolution of each format (candump and ASC write microseconds).
RESOLUTION = {CanLogFormat.CANDUMP: 2e-6, CanLogFormat.ASC: 2e-6, CanLogFormat.BLF: 2e-6}


def record(path: Path) -> Path:
    records = [frame(msg, direction, 1_000 + i) for i, (direction, msg) in enumerate(FRAMES)]
    return write_log(path, [*records, command(1_000, 0.0)])


def key(msg: can.Message) -> tuple[object, ...]:
    return (msg.arbitration_id, msg.is_extended_id, msg.is_remote_frame, msg.is_fd, msg.bitrate_switch,
            msg.dlc, bytes(msg.data), msg.is_rx)


@pytest.mark.parametrize("fmt", list(CanLogFormat), ids=lambda f: f.name.lower())
def test_export_reads_back_through_python_can(tmp_path: Path, fmt: CanLogFormat) -> None:
    src = record(tmp_path / "run.mcap")
    out = default_output(src, fmt)
    assert export_can(src, out, fmt) == len(FRAMES)
    back = list(can.LogReader(out))
    assert [key(m) for m in back] == [key(m) if d == Topic.CAN_RX else key(_tx(m)) for d, m in FRAMES]
    first = back[0].timestamp
    for got, (_, want) in zip(back, FRAMES):
        assert got.timestamp - first == pytest.approx(want.timestamp - T0, abs=RESOLUTION[fmt])


def _tx(msg: can.Message) -> can.Message:
    return can.Message(**{**{s: getattr(msg, s) for s in ("timestamp", "arbitration_id", "is_extended_id",
                                                         "is_remote_frame", "is_fd", "bitrate_switch",
                                                         "dlc", "data", "channel")}, "is_rx": False})


@pytest.mark.parametrize("fmt", list(CanLogFormat), ids=lambda f: f.name.lower())
def test_import_round_trip(tmp_path: Path, fmt: CanLogFormat) -> None:
    src = record(tmp_path / "run.mcap")
    canlog = default_output(src, fmt)
    export_can(src, canlog, fmt)
    assert import_can(canlog, tmp_path / "back.mcap") == len(FRAMES)
    log = open_log(tmp_path / "back.mcap")
    assert set(log.topics()) == {"/can/rx", "/can/tx"}
    original = [(t, p["arbitration_id"], p["data"], p["is_remote_frame"], p["is_fd"], p["dlc"])
                for t, _, p in open_log(src).iter_messages(["/can/rx", "/can/tx"])]
    imported = [(t, p["arbitration_id"], p["data"], p["is_remote_frame"], p["is_fd"], p["dlc"])
                for t, _, p in log.iter_messages()]
    assert imported == original
    assert log.metadata["import"]["source"] == canlog.name


def test_export_without_can_frames_and_bad_format(tmp_path: Path) -> None:
    path = write_log(tmp_path / "run.mcap", [command(1, 0.0)])
    with pytest.raises(LogFileError, match="no CAN frames"):
        export_can(path, tmp_path / "x.log", CanLogFormat.CANDUMP)
    with pytest.raises(LogFileError, match="unknown CAN log format 'pcap'"):
        parse_format("pcap")


def test_import_rejects_missing_and_unknown_files(tmp_path: Path) -> None:
    with pytest.raises(LogFileError, match="no such file"):
        import_can(tmp_path / "none.log", tmp_path / "out.mcap")
    odd = tmp_path / "frames.xyz"
    odd.write_text("hello\n")
    with pytest.raises(LogFileError, match="not a CAN log"):
        import_can(odd, tmp_path / "out.mcap")


@pytest.mark.parametrize("head", [b"LOGG", b"\x00\x01"], ids=["blf-magic", "random"])
def test_import_of_a_garbage_blf_is_one_line(tmp_path: Path, head: bytes) -> None:
    bad = tmp_path / "garbage.blf"
    bad.write_bytes(head + bytes(range(256)) * 4)
    with pytest.raises(LogFileError, match="garbage.blf"):
        import_can(bad, tmp_path / "out.mcap")
    assert not (tmp_path / "out.mcap").exists() and not list(tmp_path.glob(".*partial*"))


@pytest.mark.parametrize("fmt", list(CanLogFormat), ids=lambda f: f.name.lower())
def test_export_starts_at_the_earliest_frame_even_when_a_later_line_is_older(tmp_path: Path,
                                                                             fmt: CanLogFormat) -> None:
    """In log order a received frame may be older than a command logged before it; every
    python-can writer times its frames from the first it is given (an older one: ASC writes
    an absolute time, another date when read back; BLF and candump write the first one's
    time): the export starts at the earliest frame, and each frame reads back at its time."""
    late = can.Message(timestamp=T0 + 0.5, arbitration_id=0x00C, data=b"\x01", channel="can0")
    early = can.Message(timestamp=T0 + 0.0004, arbitration_id=0x009, data=b"\x02", channel="can0")
    src = write_log(tmp_path / "run.mcap", [frame(late, Topic.CAN_TX, 1_000), frame(early, Topic.CAN_RX, 2_000)])
    out = default_output(src, fmt)
    export_can(src, out, fmt)
    import_can(out, tmp_path / "back.mcap")   # ASC read with absolute times: its date kept
    back = {p["arbitration_id"]: p["timestamp"] for _, _, p in open_log(tmp_path / "back.mcap").iter_messages()}
    assert back[0x009] == pytest.approx(T0 + 0.0004, abs=RESOLUTION[fmt])
    assert back[0x00C] == pytest.approx(T0 + 0.5, abs=RESOLUTION[fmt])


#: A candump -L log as python-can's CanutilsLogWriter writes it (`` R``/`` T``: direction).
CANDUMP = ("(1700000000.000000) can0 123#0011223344556677 R\n"
           "(1700000000.001000) can0 1ABCDEF0#010203 T\n"
           "(1700000000.002000) can0 456#R R\n")


def imported_frames(path: Path) -> list[tuple[int, bytes]]:
    return [(p["arbitration_id"], bytes(p["data"])) for _, _, p in open_log(path).iter_messages()]


def test_candump_cut_mid_line_imports_the_complete_frames_and_warns(tmp_path: Path) -> None:
    """The last line of a logger killed mid-write: ``7FF#DEADBE`` reads as a 3-byte frame,
    but the line has no end of line: it is dropped, with one warning, never imported short."""
    cut = tmp_path / "cut.log"
    cut.write_text(CANDUMP + "(1700000000.003000) can0 7FF#DEADBE")
    warned: list[str] = []
    assert import_can(cut, tmp_path / "out.mcap", warn=warned.append) == 3
    assert imported_frames(tmp_path / "out.mcap") == [(0x123, bytes.fromhex("0011223344556677")),
                                                      (0x1ABCDEF0, b"\x01\x02\x03"), (0x456, b"")]
    assert len(warned) == 1 and "cut.log" in warned[0] and "imported the 3 complete frames" in warned[0]
    assert "dropped line 4" in warned[0]


def test_candump_complete_imports_without_warning(tmp_path: Path) -> None:
    good = tmp_path / "good.log"
    good.write_text(CANDUMP)
    warned: list[str] = []
    assert import_can(good, tmp_path / "out.mcap", warn=warned.append) == 3 and warned == []


def test_candump_only_a_cut_line_is_refused(tmp_path: Path) -> None:
    cut = tmp_path / "cut.log"
    cut.write_text("(1700000000.000000) can0 123#00112")
    with pytest.raises(LogFileError, match=r"cut.log: no complete CAN frame .*line 1, a record cut short"):
        import_can(cut, tmp_path / "out.mcap")
    assert not list(tmp_path.glob("*.mcap"))


@pytest.mark.parametrize(("line", "said"), [
    ("(1700000000.001000) can0 1ABCDEF0#0102030 T", "data '0102030' has an odd number of hex digits"),
    ("(1700000000.001000) can0 1ABCDEF0#010203040506070809 T", "9 data bytes is no CAN frame length"),
    ("(1700000000.001000) can0 123##1000102030405060708 T", "9 data bytes is no CAN FD frame length"),
    ("(1700000000.001000) can0 123#01zz T", "not a candump -L frame line"),
    ("(1700000000.001000) can0 12#01 T", "not a candump -L frame line"),
], ids=["odd-digits", "9-bytes", "fd-9-bytes", "not-hex", "short-id"])
def test_candump_bad_line_in_the_middle_is_refused(tmp_path: Path, line: str, said: str) -> None:
    """python-can's reader yields a frame for the first three (a byte of the odd digit, 9
    bytes of classic CAN): the line is checked before it parses it."""
    first, _, third = CANDUMP.splitlines(keepends=True)
    bad = tmp_path / "bad.log"
    bad.write_text(first + line + "\n" + third)
    with pytest.raises(LogFileError, match=rf"bad.log: line 2: {said}"):
        import_can(bad, tmp_path / "out.mcap")
    assert not list(tmp_path.glob("*.mcap"))


def test_candump_fd_and_remote_lines_pass_the_check(tmp_path: Path) -> None:
    fd = tmp_path / "fd.log"
    fd.write_text("(1700000000.000000) can0 123##1" + "AB" * 12 + " R\n(1700000000.001000) can0 456#R8 T\n\n")
    assert import_can(fd, tmp_path / "out.mcap") == 2
    assert imported_frames(tmp_path / "out.mcap") == [(0x123, b"\xab" * 12), (0x456, b"")]


#: An ASC log as python-can's ASCWriter writes it.
ASC = ("date Sat Dec 05 05:41:02.760 2026\nbase hex  timestamps absolute\ninternal events logged\n"
       "Begin Triggerblock Sat Dec 05 05:41:00.999 2026\n 0.000000 Start of measurement\n"
       " 0.016913 1  6E              Tx   d 8 00 11 22 33 44 55 66 77\n"
       " 0.017913 1  78              Rx   d 1 05\n")


def test_asc_cut_mid_line_drops_that_line(tmp_path: Path) -> None:
    cut = tmp_path / "cut.asc"
    cut.write_text(ASC + " 0.018913 1  6E              Tx   d 8 00 11 22")
    warned: list[str] = []
    assert import_can(cut, tmp_path / "out.mcap", warn=warned.append) == 2
    assert imported_frames(tmp_path / "out.mcap") == [(0x6E, bytes.fromhex("0011223344556677")), (0x78, b"\x05")]
    assert len(warned) == 1 and "dropped line 8," in warned[0]


def blf(path: Path, frames: int, container: int = 128 * 1024) -> Path:
    """A BLF of ``frames`` 8-byte frames by python-can's BLFWriter (``container``: the
    uncompressed bytes of a log container, python-can's ``max_container_size``)."""
    with can.BLFWriter(path, max_container_size=container) as writer:
        for i in range(frames):
            writer.on_message_received(can.Message(timestamp=T0 + i * 1e-3, arbitration_id=0x100 + i,
                                                   data=bytes([i] * 8), channel=0))
    return path


def blf_objects(path: Path) -> list[tuple[int, int]]:
    """(offset, size) of each top-level object (python-can's can/io/blf.py layout)."""
    data, out = path.read_bytes(), []
    pos = int.from_bytes(data[4:8], "little")
    while pos < len(data):
        size = int.from_bytes(data[pos + 8:pos + 12], "little")
        out.append((pos, size))
        pos += size + size % 4
    return out


def test_blf_cut_mid_object_imports_its_whole_frames_and_warns(tmp_path: Path) -> None:
    good = blf(tmp_path / "good.blf", 40)
    (start, size), = blf_objects(good)
    cut = tmp_path / "cut.blf"
    cut.write_bytes(good.read_bytes()[:start + size // 2])
    warned: list[str] = []
    count = import_can(cut, tmp_path / "out.mcap", warn=warned.append)
    assert 0 < count < 40
    assert imported_frames(tmp_path / "out.mcap") == [(0x100 + i, bytes([i] * 8)) for i in range(count)]
    assert len(warned) == 1 and f"imported the {count} complete frames" in warned[0]
    assert f"dropped the part past byte {start + size // 2} of the {size}-byte object at byte {start}" in warned[0]
    assert f"its header gives {good.stat().st_size} bytes, 40 objects" in warned[0]


def test_blf_cut_between_objects_is_seen_by_its_header(tmp_path: Path) -> None:
    good = blf(tmp_path / "good.blf", 40, container=256)
    objects = blf_objects(good)
    assert len(objects) > 2
    start, _ = objects[-1]
    cut = tmp_path / "cut.blf"
    cut.write_bytes(good.read_bytes()[:start])
    warned: list[str] = []
    count = import_can(cut, tmp_path / "out.mcap", warn=warned.append)
    assert 0 < count < 40 and imported_frames(tmp_path / "out.mcap") == [(0x100 + i, bytes([i] * 8))
                                                                          for i in range(count)]
    assert warned == [f"{cut}: cut short: imported the {count} complete frames; dropped the "
                      f"{good.stat().st_size - start} bytes past byte {start}; its header gives "
                      f"{good.stat().st_size} bytes, 40 objects"]


@pytest.mark.parametrize("into", [6, 20], ids=["object-header", "container-header"])
def test_blf_cut_in_the_first_headers_is_refused(tmp_path: Path, into: int) -> None:
    good = blf(tmp_path / "good.blf", 5)
    (start, _), = blf_objects(good)
    cut = tmp_path / "cut.blf"
    cut.write_bytes(good.read_bytes()[:start + into])
    with pytest.raises(LogFileError, match=rf"cut.blf: no complete CAN frame .*object at byte {start}"):
        import_can(cut, tmp_path / "out.mcap")
    assert not list(tmp_path.glob("*.mcap")) and not list(tmp_path.glob(".*partial*"))


def test_blf_complete_imports_without_warning(tmp_path: Path) -> None:
    warned: list[str] = []
    assert import_can(blf(tmp_path / "good.blf", 40, container=256), tmp_path / "out.mcap", warn=warned.append) == 40
    assert warned == []


def test_asc_frame_shorter_than_its_dlc_is_refused(tmp_path: Path) -> None:
    """python-can's ASCReader yields a frame of DLC 8 and 2 bytes for ``d 8 00 11``: refused,
    naming the line, not imported short."""
    bad = tmp_path / "bad.asc"
    bad.write_text(ASC.replace("d 1 05", "d 8 00 11") + " 0.018913 1  6E              Tx   d 1 01\n")
    with pytest.raises(LogFileError, match="bad.asc: line 7: a frame with 2 data bytes where its DLC says 8"):
        import_can(bad, tmp_path / "out.mcap")
    assert not list(tmp_path.glob("*.mcap")) and not list(tmp_path.glob(".*partial*"))


def test_classic_dlc_above_8_and_every_writers_round_trip_pass(tmp_path: Path) -> None:
    """A classic DLC 9..15 means 8 bytes (ISO 11898-1); the frames of every format python-can
    writes (CSV keeps no FD flag: its FD frame reads back longer than 8 bytes) import whole."""
    asc = tmp_path / "dlc15.asc"
    asc.write_text(ASC.replace("d 8 00 11 22 33 44 55 66 77", "d F 00 11 22 33 44 55 66 77"))
    assert import_can(asc, tmp_path / "asc.mcap") == 2
    for suffix in (".csv", ".log", ".asc", ".blf"):
        with can.Logger(tmp_path / f"all{suffix}") as writer:
            for _, msg in FRAMES:
                writer.on_message_received(msg)
        assert import_can(tmp_path / f"all{suffix}", tmp_path / f"{suffix[1:]}-all.mcap") == len(FRAMES)


# -- gzip-compressed logs: the checks of the plain ones -------------------------------------


def gzipped(path: Path, keep: int | None = None) -> Path:
    """``path`` compressed to ``path.gz`` (its first ``keep`` compressed bytes only: a stream
    cut short), the plain file removed."""
    data = gzip.compress(path.read_bytes(), mtime=0)
    out = path.with_name(path.name + ".gz")
    out.write_bytes(data if keep is None else data[:keep])
    path.unlink()
    return out


def _import(path: Path, out: Path) -> tuple[int, list[tuple[int, int, bytes]], list[str]] | str:
    """(frames, (log time, id, data) of each, warnings) of importing ``path``, or the refusal,
    with the file's name left out (the plain and the gzipped file differ only by it)."""
    warned: list[str] = []
    try:
        count = import_can(path, out, warn=warned.append)
    except LogFileError as exc:
        assert not out.exists()
        return str(exc).replace(str(path), "LOG")
    frames = [(t, p["arbitration_id"], bytes(p["data"])) for _, t, p in open_log(out).iter_messages()]
    return count, frames, [w.replace(str(path), "LOG") for w in warned]


def _cut_blf(path: Path, frames: int, container: int, at: Callable[[list[tuple[int, int]]], int]) -> None:
    good = blf(path.with_name("whole.blf"), frames, container)
    path.write_bytes(good.read_bytes()[:at(blf_objects(good))])


#: name -> a writer of a plain CAN log (cut, damaged or whole) at the path it is given
GZ_CASES: dict[str, Callable[[Path], None]] = {
    "candump-cut-mid-line": lambda p: p.write_text(CANDUMP + "(1700000000.003000) can0 7FF#DEADBE"),
    "candump-whole": lambda p: p.write_text(CANDUMP),
    "candump-only-a-cut-line": lambda p: p.write_text("(1700000000.000000) can0 123#00112"),
    "candump-bad-line-in-the-middle": lambda p: p.write_text(
        CANDUMP.replace("#010203 T", "#0102030 T")),
    "asc-cut-mid-line": lambda p: p.write_text(ASC + " 0.018913 1  6E              Tx   d 8 00 11 22"),
    "asc-short-frame": lambda p: p.write_text(ASC.replace("d 1 05", "d 8 00 11") + " 0.0189 1  6E  Tx   d 1 01\n"),
    "blf-cut-mid-object": lambda p: _cut_blf(p, 40, 128 * 1024, lambda o: o[0][0] + o[0][1] // 2),
    "blf-cut-between-objects": lambda p: _cut_blf(p, 40, 256, lambda o: o[-1][0]),
    "blf-cut-in-the-first-headers": lambda p: _cut_blf(p, 5, 128 * 1024, lambda o: o[0][0] + 6),
    "blf-whole": lambda p: _cut_blf(p, 40, 256, lambda o: 1 << 40),
}


@pytest.mark.parametrize("case", list(GZ_CASES))
def test_a_gzipped_log_gets_the_checks_of_a_plain_one(tmp_path: Path, case: str) -> None:
    """``run.log.gz`` is read as ``run.log`` is: a cut last record warned of and dropped,
    damage before the end refused, nothing written then; the same frames, times and words."""
    suffix = ".blf" if case.startswith("blf") else ".asc" if case.startswith("asc") else ".log"
    plain = tmp_path / f"run{suffix}"
    GZ_CASES[case](plain)
    expected = _import(plain, tmp_path / "plain.mcap")
    got = _import(gzipped(plain), tmp_path / "gz.mcap")
    assert got == expected
    if case.endswith("whole"):
        assert isinstance(got, tuple) and got[0] > 0 and got[2] == []
    elif "cut" in case and "only" not in case and "first" not in case:
        assert isinstance(got, tuple) and len(got[2]) == 1 and "cut short" in got[2][0]
    else:
        assert isinstance(got, str)


@pytest.mark.parametrize("suffix", [".log", ".blf"])
def test_a_gzip_stream_cut_short_imports_its_whole_records_and_says_so(tmp_path: Path, suffix: str) -> None:
    """A ``.gz`` whose compressed stream stops before its end marker (a logger killed while
    compressing): the whole records of what it holds are imported, the warning names the cut."""
    plain = tmp_path / f"run{suffix}"
    if suffix == ".blf":
        blf(plain, 250, container=256)
    else:
        plain.write_text("".join(f"(1700000000.{i:06d}) can0 {i % 0x7FF:03X}#{i % 256:02X}0102 R\n"
                                 for i in range(400)))
    whole = _import(plain, tmp_path / "whole.mcap")
    assert isinstance(whole, tuple)
    size = len(gzip.compress(plain.read_bytes(), mtime=0))
    got = _import(gzipped(plain, keep=size * 2 // 3), tmp_path / "gz.mcap")
    assert isinstance(got, tuple), got
    count, frames, warned = got
    assert 0 < count < whole[0] and frames == whole[1][:count]
    assert len(warned) == 1 and warned[0].startswith(f"LOG: cut short: imported the {count} complete frames; dropped ")
    assert "; the gzip stream stops before its end marker" in warned[0], warned


def test_damaged_gzip_data_is_refused(tmp_path: Path) -> None:
    """Damage is refused wherever gzip or the format's check finds it: a byte flipped in the
    middle of the compressed data makes lines no candump writer writes, one in the trailer's
    CRC (RFC 1952) data gzip finds wrong at the end; a plain file named .gz is no gzip data."""
    plain = tmp_path / "run.log"
    plain.write_text("".join(f"(1700000000.{i:06d}) can0 123#{i % 256:02X}{i // 256:02X} R\n" for i in range(2000)))
    data = gzip.compress(plain.read_bytes(), mtime=0)
    size = plain.stat().st_size
    for at, said in ((len(data) // 2, r"run.log.gz: line \d+: not a candump -L frame line"),
                     (len(data) - 8, rf"run.log.gz: damaged gzip data after {size} uncompressed bytes "
                                     r"\(BadGzipFile: CRC check failed")):
        damaged = tmp_path / "run.log.gz"
        damaged.write_bytes(data[:at] + bytes([data[at] ^ 0xFF]) + data[at + 1:])
        with pytest.raises(LogFileError, match=said):
            import_can(damaged, tmp_path / "out.mcap")
    not_gzip = tmp_path / "text.log.gz"
    not_gzip.write_text(CANDUMP)
    with pytest.raises(LogFileError, match=r"text.log.gz: not gzip data \(BadGzipFile"):
        import_can(not_gzip, tmp_path / "out.mcap")
    assert not list(tmp_path.glob("*.mcap")) and not list(tmp_path.glob(".*partial*"))
