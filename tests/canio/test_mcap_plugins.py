"""``.mcap`` in python-can: ``can.LogReader``/``can.Logger`` plugins, and python-can's own
tools (``can.logconvert``, ``can.player``, ``can.logger``) on dobhil recordings."""

from __future__ import annotations

import errno
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import can
import can.logconvert
import can.player
import pytest

from dobhil.canio.mcap_reader import McapReader
from dobhil.canio.mcap_writer import METADATA, McapWriter, OutputIsInputError, program_name
from dobhil.cli.main import main as dobhil_main
from dobhil.recording.reader import open_log
from tests.runtime.hub import accepts, free_port, stop_process
from dobhil.recording.schemas import SPECS_BY_NAME

REPO = Path(__file__).resolve().parents[2]
DEMO = REPO / "configs" / "demo.yaml"
T0 = 1_700_000_000.0
BOUND = 30.0  # s: how long a loaded CI machine may take to start a process, not a measurement

#: Every flag python-can has, classic and FD, both directions, with and without channel (a
#: name, or a number as Kvaser and Vector interfaces give).
FRAMES = (
    can.Message(timestamp=T0, arbitration_id=0x123, data=bytes(range(8)), channel="can0"),
    can.Message(timestamp=T0 + 0.001, arbitration_id=0x1ABCDEF, is_extended_id=True, data=b"\x01\x02\x03",
                is_rx=False, channel="can0"),
    can.Message(timestamp=T0 + 0.0015, arbitration_id=0x456, is_extended_id=False, is_remote_frame=True, dlc=6),
    can.Message(timestamp=T0 + 0.002, arbitration_id=0x001, is_extended_id=False, data=b"", is_rx=False, channel=0),
    can.Message(timestamp=T0 + 0.003, arbitration_id=0x7FF, is_extended_id=False, is_fd=True, bitrate_switch=True,
                data=bytes(range(12)), channel="vcan1"),
    can.Message(timestamp=T0 + 0.004, arbitration_id=0x18DAF110, is_extended_id=True, is_fd=True,
                error_state_indicator=True, data=bytes(range(64)), channel="vcan1"),
    can.Message(timestamp=T0 + 0.005, arbitration_id=0x20000004, is_extended_id=True, is_error_frame=True, dlc=8,
                data=bytes([0, 4, 0, 0, 0, 0, 0, 0]), channel="can0"),
    can.Message(timestamp=T0 + 0.0051234567, arbitration_id=0x3FF, is_extended_id=False, is_fd=True,
                bitrate_switch=True, error_state_indicator=True, data=b"\xff" * 48, is_rx=False),
)


def flags(msg: can.Message) -> tuple[object, ...]:
    return (msg.arbitration_id, msg.is_extended_id, msg.is_remote_frame, msg.is_error_frame, msg.is_fd,
            msg.bitrate_switch, msg.error_state_indicator, msg.dlc, bytes(msg.data), msg.is_rx)


def write(path: Path, frames: tuple[can.Message, ...] = FRAMES) -> Path:
    with can.Logger(path) as logger:
        assert isinstance(logger, McapWriter)
        for msg in frames:
            logger(msg)
    return path


def test_round_trip_keeps_every_flag_timestamp_and_channel(tmp_path: Path) -> None:
    path = write(tmp_path / "frames.mcap")
    with can.LogReader(path) as reader:
        assert isinstance(reader, McapReader)
        back = list(reader)
    assert len(back) == len(FRAMES)
    for want, got in zip(FRAMES, back):
        assert want.equals(got, timestamp_delta=None), f"{want} != {got}"
        assert got.timestamp == want.timestamp   # the very same double
        assert flags(got) == flags(want)


def test_file_is_a_dobhil_recording(tmp_path: Path) -> None:
    """``dobhil log info`` reads it: a summary, /can/rx and /can/tx with the schema of the
    one topic table, counts per direction, who wrote it."""
    path = write(tmp_path / "frames.mcap")
    log = open_log(path)
    info = log.info()
    assert log.statistics is not None
    counts = {c.topic: c.message_count for c in info.channels}
    assert counts == {"/can/rx": sum(m.is_rx for m in FRAMES), "/can/tx": sum(not m.is_rx for m in FRAMES)}
    assert {c.schema_name for c in info.channels} == {"dobhil.CanFrame"}
    assert {c.message_encoding for c in info.channels} == {"protobuf"}
    for topic in counts:
        assert log.schema_properties(topic) == SPECS_BY_NAME[topic].keys
    started, stopped = info.metadata[METADATA], info.metadata[f"{METADATA}.stop"]
    assert started["writer"] == "dobhil.canio.mcap_writer.McapWriter"
    assert stopped["frames"] == str(len(FRAMES))
    payloads = [p for _, _, p in log.iter_messages(["/can/rx", "/can/tx"])]
    assert [p["direction"] for p in payloads] == ["rx" if m.is_rx else "tx" for m in FRAMES]
    assert payloads[0]["data_hex"] == "0001020304050607"


def test_program_name() -> None:
    assert program_name(can.__file__.replace("__init__.py", "logger.py")) == "can.logger"
    assert program_name("/usr/bin/my-tool") == "my-tool"


def test_empty_capture_and_bad_options(tmp_path: Path) -> None:
    empty = write(tmp_path / "empty.mcap", ())
    assert list(can.LogReader(empty)) == []
    assert {c.topic for c in open_log(empty).channels()} == {"/can/rx", "/can/tx"}
    with pytest.raises(ValueError, match="cannot append"):
        can.Logger(tmp_path / "a.mcap", append=True)
    with pytest.raises(ValueError, match="unknown option.*level"):
        can.Logger(tmp_path / "b.mcap", level=3)
    with pytest.raises(ValueError, match="compression 'gzip'"):
        can.Logger(tmp_path / "c.mcap", compression="gzip")
    with can.Logger(tmp_path / "d.mcap", compression="none") as logger:
        logger(FRAMES[0])
    assert len(list(can.LogReader(tmp_path / "d.mcap"))) == 1
    logger.stop()   # again: no-op
    with pytest.raises(ValueError, match="after stop"):
        logger(FRAMES[0])


def test_reader_errors_are_one_clear_line(tmp_path: Path) -> None:
    text = tmp_path / "frames.mcap"
    text.write_text("not mcap\n")
    with pytest.raises(ValueError, match="not an MCAP file"):
        can.LogReader(text)
    with pytest.raises(ValueError, match="unknown option"):
        can.LogReader(write(tmp_path / "ok.mcap"), channel=1)
    from mcap.writer import Writer
    no_can = tmp_path / "no-can.mcap"
    with open(no_can, "wb") as stream:
        writer = Writer(stream)
        writer.start()
        schema = writer.register_schema("dobhil.DriveCommand", "jsonschema", b"{}")
        channel = writer.register_channel("/drive/command", "json", schema)
        writer.add_message(channel, log_time=1_000, publish_time=1_000, data=b'{"torque": 0.0}')
        writer.finish()
    with pytest.raises(ValueError, match=r"no CAN frames.*/drive/command"):
        list(can.LogReader(no_can))


def test_truncated_file_yields_what_is_complete_then_says_so(tmp_path: Path) -> None:
    """A logger killed before stop(): every flushed frame is read, then a ValueError."""
    path = tmp_path / "live.mcap"
    logger = McapWriter(path, flush_interval=1e-9)   # a chunk per frame
    try:
        for msg in FRAMES[:5]:
            logger(msg)
        cut = tmp_path / "cut.mcap"
        shutil.copyfile(path, cut)
    finally:
        logger.stop()
    got: list[can.Message] = []
    with pytest.raises(ValueError, match="truncated.*dobhil log recover"):
        for msg in can.LogReader(cut):
            got.append(msg)
    assert [flags(m) for m in got] == [flags(m) for m in FRAMES[:5]]


@pytest.mark.parametrize("compression", ["none", "zstd"])
def test_a_damaged_chunk_is_one_value_error_not_silent_frames(tmp_path: Path, compression: str) -> None:
    """Bytes flipped inside a chunk: uncompressed, only its CRC tells; compressed, the
    decompressor too. Either way one ValueError naming the damage, as python-can's tools
    expect of a reader."""
    path = tmp_path / "frames.mcap"
    with McapWriter(path, compression=compression, chunk_size=64) as logger:
        for k in range(40):
            logger(can.Message(arbitration_id=0x100 + k, data=bytes([k] * 8), is_extended_id=False,
                               timestamp=1.0 + k))
    data = bytearray(path.read_bytes())
    with open(path, "rb") as f:
        from mcap.reader import make_reader
        summary = make_reader(f).get_summary()
    assert summary is not None
    chunk = sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset)[1]
    middle = chunk.chunk_start_offset + chunk.chunk_length // 2
    for i in range(middle, middle + 8):
        data[i] ^= 0xFF
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(bytes(data))
    with pytest.raises(ValueError, match="damaged .*dobhil log recover"):
        list(can.LogReader(bad))
    assert len(list(can.LogReader(path))) == 40


@pytest.fixture(scope="module")
def run_log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A lockstep emulated run recorded by ``dobhil run --log`` (the CLI, in process)."""
    path = tmp_path_factory.mktemp("run") / "run.mcap"
    code = dobhil_main(["run", str(DEMO), "--emulate", "--lockstep", "--duration", "0.3", "--log", str(path)])
    assert code == 0
    return path


def test_frame_count_equals_log_info(run_log: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``sum(1 for _ in can.LogReader(run.mcap))`` is /can/rx + /can/tx of ``dobhil log info``,
    in log-time order, each frame as the recording has it."""
    capsys.readouterr()
    assert dobhil_main(["log", "info", str(run_log), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    counts = {c["topic"]: c["message_count"] for c in info["channels"]}
    for topic, held in (info["folded"] or {}).items():   # the cycle layout: frames in cycle messages
        counts[topic] = counts.get(topic, 0) + held
    assert counts["/can/rx"] > 250 and counts["/can/tx"] > 250   # 0.3 s at 1 kHz, both ways
    assert sum(1 for _ in can.LogReader(run_log)) == counts["/can/rx"] + counts["/can/tx"]

    frames = list(can.LogReader(run_log))
    assert sum(m.is_rx for m in frames) == counts["/can/rx"]
    recorded = list(open_log(run_log).iter_messages(["/can/rx", "/can/tx"]))
    # a sent frame has no bus timestamp (0.0 in the record): the reader gives its log time
    assert [(m.arbitration_id, list(m.data), m.is_rx, m.timestamp) for m in frames] == \
        [(p["arbitration_id"], p["data"], p["direction"] == "rx", p["timestamp"] or t / 1e9)
         for _, t, p in recorded]
    log_times = [t for _, t, _ in recorded]
    assert log_times == sorted(log_times)


def test_logconvert_to_blf_reads_back_with_python_can(run_log: Path, tmp_path: Path,
                                                      monkeypatch: pytest.MonkeyPatch) -> None:
    blf = tmp_path / "run.blf"
    monkeypatch.setattr(sys, "argv", ["can.logconvert", str(run_log), str(blf)])
    can.logconvert.main()
    ours = list(can.LogReader(run_log))
    with can.BLFReader(blf) as reader:
        theirs = list(reader)
    assert [flags(m) for m in theirs] == [flags(m) for m in ours]
    for a, b in zip(ours, theirs):
        assert b.timestamp == pytest.approx(a.timestamp, abs=2e-6)


def test_player_sends_a_recording_onto_a_virtual_bus(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                     capsys: pytest.CaptureFixture[str]) -> None:
    """``python -m can.player FILE.mcap -i virtual``: python-can's own main(), in process."""
    path = write(tmp_path / "frames.mcap")
    channel = f"player-{os.getpid()}"
    with can.Bus(interface="virtual", channel=channel) as listener:
        monkeypatch.setattr(sys, "argv", ["can.player", "-i", "virtual", "-c", channel, "--error-frames",
                                          "--ignore-timestamps", str(path)])
        can.player.main()
        got = [listener.recv(1.0) for _ in FRAMES]
        assert listener.recv(0.0) is None
    assert [flags(m) for m in got if m is not None] == [flags(m)[:-1] + (True,) for m in FRAMES]


def test_can_logger_in_a_subprocess_on_the_dobhil_bus(tmp_path: Path) -> None:
    """``python -m can.logger -i dobhil -c demo -f x.mcap``, stopped with Ctrl-C (SIGINT):
    a finished file (summary), the emulated drive's frames, written by can.logger."""
    out = tmp_path / "capture.mcap"
    proc = subprocess.Popen([sys.executable, "-u", "-m", "can.logger", "-i", "dobhil", "-c", "demo", "-f", str(out)],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, cwd=tmp_path,
                            env={**os.environ, "PYTHONUNBUFFERED": "1"})
    try:
        assert proc.stdout is not None
        line = proc.stdout.readline().decode()
        assert line.startswith("Connected to DobhilBus: dobhil emulated odrive"), line
        deadline = time.monotonic() + BOUND
        while not out.exists() or out.stat().st_size < 2000:   # frames flushed (every second)
            assert time.monotonic() < deadline and proc.poll() is None
            time.sleep(0.05)
        proc.send_signal(signal.SIGINT)
        rest = proc.communicate(timeout=BOUND)[0].decode()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0, rest
    log = open_log(out)
    info = log.info()
    assert log.statistics is not None
    counts = {c.topic: c.message_count for c in info.channels}
    assert counts["/can/rx"] > 100 and counts["/can/tx"] == 0
    assert info.metadata[METADATA]["program"] == "can.logger"
    assert int(info.metadata[f"{METADATA}.stop"]["frames"]) == counts["/can/rx"]
    frames = list(can.LogReader(out))
    assert len(frames) == counts["/can/rx"] and {m.channel for m in frames} == {"demo"}
    assert {m.arbitration_id for m in frames} >= {3 << 5 | 0x01, 3 << 5 | 0x09}   # heartbeat, encoder


def test_gzip_compressed_mcap(tmp_path: Path) -> None:
    """``x.mcap.gz``: python-can's gzip wrapping around the plugins (read from a decompressed copy)."""
    path = write(tmp_path / "frames.mcap.gz")
    assert [flags(m) for m in can.LogReader(path)] == [flags(m) for m in FRAMES]


def test_truncated_gz_yields_what_is_complete_then_says_how_to_recover(tmp_path: Path) -> None:
    """A .mcap.gz cut short (a logger killed under gzip): the frames of the complete chunks,
    then a ValueError naming the way to recover it (recover reads MCAP, not gzip)."""
    frames = tuple(can.Message(timestamp=T0 + k * 1e-3, arbitration_id=k & 0x7FF, is_extended_id=False,
                               data=os.urandom(8)) for k in range(12000))  # several chunks
    whole = write(tmp_path / "whole.mcap.gz", frames)
    cut = tmp_path / "cut.mcap.gz"
    cut.write_bytes(whole.read_bytes()[: whole.stat().st_size // 2])
    read: list[can.Message] = []
    with pytest.raises(ValueError, match=r"truncated.*`zcat .*cut\.mcap\.gz > x\.mcap` then `dobhil log recover"):
        for msg in can.LogReader(cut):
            read.append(msg)
    assert 0 < len(read) < len(frames)
    assert [flags(m) for m in read] == [flags(m) for m in frames[: len(read)]]


def test_logconvert_onto_its_own_input_is_refused(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Refused before the output is opened, the input intact; an OSError, as python-can's
    writers raise for an output they cannot open (and a ValueError, as before)."""
    path = write(tmp_path / "frames.mcap")
    before = path.read_bytes()
    monkeypatch.setattr(sys, "argv", ["can.logconvert", str(path), str(path)])
    with pytest.raises(OutputIsInputError, match="is being read as input") as info:
        can.logconvert.main()
    assert isinstance(info.value, OSError) and isinstance(info.value, ValueError)
    assert path.read_bytes() == before
    write(tmp_path / "frames.mcap")   # once the reader is closed, overwriting is python-can's usual


def test_missing_output_folder_raises_what_python_cans_writers_raise(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A missing folder: FileNotFoundError (same errno) from can.Logger for .mcap as for
    python-can's own .asc and .blf writers, directly and through can.logconvert; no
    folder or file is created."""
    source = write(tmp_path / "frames.mcap")
    missing = tmp_path / "missing"
    raised = {}
    for suffix in (".mcap", ".asc", ".blf"):
        with pytest.raises(OSError) as direct:
            can.Logger(missing / f"out{suffix}")
        monkeypatch.setattr(sys, "argv", ["can.logconvert", str(source), str(missing / f"conv{suffix}")])
        with pytest.raises(OSError) as converted:
            can.logconvert.main()
        raised[suffix] = {(type(e.value), e.value.errno) for e in (direct, converted)}
    assert raised[".mcap"] == raised[".asc"] == raised[".blf"] == {(FileNotFoundError, errno.ENOENT)}
    assert not missing.exists()


def test_logconvert_gz_onto_itself_keeps_the_frames(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """python-can's .gz writer truncates its output before any writer is called: the
    reader works from a decompressed copy, so every frame is written back. The input is
    larger than gzip's read buffer (8 KiB), or the first read would have held all of it."""
    frames = tuple(can.Message(timestamp=T0 + k * 1e-3, arbitration_id=k & 0x7FF, is_extended_id=False,
                               data=os.urandom(8)) for k in range(12000))  # several chunks
    path = write(tmp_path / "frames.mcap.gz", frames)
    assert path.stat().st_size > 4 * 8192
    monkeypatch.setattr(sys, "argv", ["can.logconvert", str(path), str(path)])
    can.logconvert.main()
    assert [flags(m) for m in can.LogReader(path)] == [flags(m) for m in frames]


def _frames_so_far(path: Path, sentinel: int) -> int:
    """Frames other than ``sentinel`` in a capture still being written (complete chunks)."""
    count = 0
    try:
        for msg in McapReader(path):
            count += msg.arbitration_id != sentinel
    except ValueError:   # truncated: the logger is still running
        pass
    return count


def test_player_to_logger_across_processes(run_log: Path, tmp_path: Path) -> None:
    """``can.player run.mcap`` in one process, ``can.logger -f capture.mcap`` in another, on a
    python-can-remote hub (127.0.0.1): the capture holds every frame of the run, in order."""
    pytest.importorskip("can_remote")
    port = free_port()
    url = f"ws://127.0.0.1:{port}/"
    hub_log = (tmp_path / "hub.log").open("wb")
    hub = subprocess.Popen([sys.executable, "-m", "can_remote", "-i", "virtual", "-c", f"canio-{port}",
                            "-H", "127.0.0.1", "-p", str(port)], stdout=hub_log, stderr=subprocess.STDOUT)
    procs = [hub]
    sentinel = 0x7FE
    try:
        deadline = time.monotonic() + BOUND
        while not accepts(port):
            if hub.poll() is not None or time.monotonic() > deadline:
                pytest.skip("python-can-remote hub did not start on 127.0.0.1")
            time.sleep(0.05)
        capture = tmp_path / "capture.mcap"
        logger = subprocess.Popen([sys.executable, "-u", "-m", "can.logger", "-i", "remote", "-c", url,
                                   "-f", str(capture), "--flush-interval=0.05"],
                                  stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
        procs.append(logger)
        assert logger.stdout is not None
        assert logger.stdout.readline().decode().startswith("Connected to")
        player = subprocess.run([sys.executable, "-m", "can.player", "-i", "remote", "-c", url, str(run_log)],
                                capture_output=True, timeout=BOUND * 4)
        assert player.returncode == 0, player.stdout + player.stderr
        expected = list(can.LogReader(run_log))
        with can.Bus(interface="remote", channel=url) as poke:   # keeps the logger's chunks flushing
            while _frames_so_far(capture, sentinel) < len(expected):
                assert time.monotonic() < deadline + BOUND * 4 and logger.poll() is None
                poke.send(can.Message(arbitration_id=sentinel, is_extended_id=False))
                time.sleep(0.1)
        logger.send_signal(signal.SIGINT)
        logger.communicate(timeout=BOUND)
        assert logger.returncode == 0
    finally:
        for proc in reversed(procs):
            stop_process(proc)
        hub_log.close()
    got = [m for m in can.LogReader(capture) if m.arbitration_id != sentinel]
    assert [flags(m)[:-1] for m in got] == [flags(m)[:-1] for m in expected]
    assert all(m.is_rx for m in got)   # everything the logger captured was received
    assert open_log(capture).info().metadata[METADATA]["program"] == "can.logger"
