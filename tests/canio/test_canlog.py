"""CAN frames out to candump/ASC/BLF and back in, through python-can's own readers."""

from __future__ import annotations

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
            bytes(msg.data), msg.is_rx)


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
    original = [(t, p["arbitration_id"], p["data"], p["is_remote_frame"], p["is_fd"])
                for t, _, p in open_log(src).iter_messages(["/can/rx", "/can/tx"])]
    imported = [(t, p["arbitration_id"], p["data"], p["is_remote_frame"], p["is_fd"])
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


def test_asc_starts_at_the_earliest_frame_even_when_a_later_line_is_older(tmp_path: Path) -> None:
    """In log order a received frame may be older than a command logged before it; ASC times
    are relative to the file's start, and python-can writes an older frame as an absolute
    time (another date when read back): the export starts at the earliest frame."""
    late = can.Message(timestamp=T0 + 0.5, arbitration_id=0x00C, data=b"\x01", channel="can0")
    early = can.Message(timestamp=T0, arbitration_id=0x009, data=b"\x02", channel="can0")
    src = write_log(tmp_path / "run.mcap", [frame(late, Topic.CAN_TX, 1_000), frame(early, Topic.CAN_RX, 2_000)])
    out = tmp_path / "run.asc"
    export_can(src, out, CanLogFormat.ASC)
    with can.ASCReader(out, relative_timestamp=False) as reader:
        back = {m.arbitration_id: m.timestamp for m in reader}
    assert back[0x009] == pytest.approx(T0, abs=1e-3) and back[0x00C] == pytest.approx(T0 + 0.5, abs=1e-3)
    assert back[0x00C] - back[0x009] == pytest.approx(0.5, abs=RESOLUTION[CanLogFormat.ASC])
