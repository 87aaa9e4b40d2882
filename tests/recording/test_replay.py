"""``dobhil replay``: bit-exact verification, a changed frame found, overrides, bad files."""

from __future__ import annotations

import json
import struct
from pathlib import Path

import pytest
from mcap.reader import make_reader
from mcap.writer import Writer

from dobhil.cli.main import main
from dobhil.drives.odrive import codec
from dobhil.replay import replay
from tests.recording.helpers import decode_message, encode_message
from tests.recording.test_run_logging import logged_lockstep_run


@pytest.fixture(scope="module")
def recorded(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("replay") / "run.mcap"
    logged_lockstep_run(path, duration=0.4)
    return path


def rewrite_with_altered_frame(src: Path, dst: Path, motion_index: int) -> None:
    """Copy ``src`` to ``dst`` with the velocity of the ``motion_index``-th encoder frame changed
    (the measured-velocity observers do not use the position)."""
    encoder_cmd = codec.CmdId.GET_ENCODER_ESTIMATES
    seen = 0
    with open(src, "rb") as f_in, open(dst, "wb") as f_out:
        reader = make_reader(f_in)
        summary = reader.get_summary()
        assert summary is not None
        writer = Writer(f_out)
        writer.start(library="dobhil/test (one frame altered)")
        schemas = {sid: writer.register_schema(s.name, s.encoding, s.data) for sid, s in summary.schemas.items()}
        channels = {cid: writer.register_channel(c.topic, c.message_encoding, schemas[c.schema_id])
                    for cid, c in summary.channels.items()}
        for record in reader.iter_metadata():
            writer.add_metadata(record.name, record.metadata)
        for schema, channel, message in reader.iter_messages(log_time_order=False):
            data = message.data
            if channel.topic == "/can/rx":
                p = decode_message(schema, channel, data)
                if p["arbitration_id"] & 0x1F == encoder_cmd:
                    seen += 1
                    if seen == motion_index:
                        pos, vel = struct.unpack("<ff", bytes(p["data"]))
                        p["data"] = list(struct.pack("<ff", pos, vel + 1e-3))
                        data = encode_message(schema, channel, p)
            writer.add_message(channels[channel.id], message.log_time, data, message.publish_time)
        writer.finish()


def test_verify_reproduces_the_recorded_commands(recorded: Path, capsys: pytest.CaptureFixture[str]) -> None:
    result = replay(recorded)
    assert result.first_mismatch() is None
    assert result.recording.cycles == 400
    assert main(["replay", str(recorded), "--verify"]) == 0
    assert "bit for bit" in capsys.readouterr().out


def test_one_changed_feedback_frame_fails_and_says_where(recorded: Path, tmp_path: Path,
                                                         capsys: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / "altered.mcap"
    rewrite_with_altered_frame(recorded, bad, motion_index=150)
    mismatch = replay(bad).first_mismatch()
    assert mismatch is not None and 140 <= mismatch.cycle <= 150
    capsys.readouterr()
    assert main(["replay", str(bad), "--verify"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"cycle {mismatch.cycle}" in err[0] and "recorded" in err[0] and "replayed" in err[0]


def test_override_shows_another_tuning(recorded: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    csv_path, png = tmp_path / "r.csv", tmp_path / "r.png"
    code = main(["replay", str(recorded), "--set", "design.identified_inertia=0.2", "--json",
                 "--out", str(csv_path), "--plot", str(png)])
    assert code == 0
    info = json.loads(capsys.readouterr().out)
    assert not info["identical"] and info["difference"]["u_sat"]["max_abs"] > 0
    assert csv_path.read_text().count("\n") == 401 and png.stat().st_size > 10000


@pytest.mark.parametrize("key", ["plant.inertia=0.3", "environment.stiffness=1", "drive.profile=/nonexist.yaml",
                                 "drive.node_id=99", "reference.amplitude=2", "sensor.velocity_noise=0.1",
                                 "loop.period=0.002"])
def test_a_key_the_replay_does_not_apply_is_refused(recorded: Path, key: str,
                                                    capsys: pytest.CaptureFixture[str]) -> None:
    """A replay re-runs the recorded controller on the recorded feedback: a --set it would
    not apply (the plant, the environment, the drive, the reference, the sensor, the loop's
    timing are the recording's) is one line, exit 2 -- not 'replayed with KEY' and
    'identical' as if it had been tried."""
    assert main(["replay", str(recorded), "--verify", "--set", key]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"--set {key}: a replay re-runs the recorded controller" in err, err
    assert "design.* keys, loop.torque_limit and loop.mode" in err


@pytest.mark.parametrize("command", ["replay", "report"])
@pytest.mark.parametrize("case", ["empty", "not-mcap", "truncated", "missing"])
def test_bad_files_one_line_exit_2(recorded: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                   command: str, case: str) -> None:
    path = tmp_path / f"{case}.mcap"
    if case == "empty":
        path.write_bytes(b"")
    elif case == "not-mcap":
        path.write_text("hello\n")
    elif case == "truncated":
        path.write_bytes(recorded.read_bytes()[: recorded.stat().st_size // 2])
    args = [command, str(path)] + (["--out", str(tmp_path / "rep")] if command == "report" else [])
    capsys.readouterr()
    assert main(args) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err


@pytest.fixture(scope="module")
def recorded_long(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A run long enough for more than two chunks (a chunk ends every 0.05 s of the writer's time)."""
    path = tmp_path_factory.mktemp("replay") / "long.mcap"
    logged_lockstep_run(path, duration=1.5)
    return path


def test_a_recovered_log_with_a_gap_names_the_missing_cycles(recorded_long: Path, tmp_path: Path,
                                                             capsys: pytest.CaptureFixture[str]) -> None:
    """A log recovered with a damaged chunk in its middle: --verify says which cycles are
    missing in one line (exit 1: not all was verified), not a controller mismatch; the cycles
    before the gap are re-run and match bit for bit (the recording's and the intact log's).
    Its report's bus load is over the time it kept, the gap's left out as its frames are."""
    import re

    import numpy as np

    from dobhil.recording.recover import recover
    from tests.recording.test_logs_never_lie import damage_one_chunk
    bad, saved = tmp_path / "damaged.mcap", tmp_path / "saved.mcap"
    damage_one_chunk(recorded_long, bad)
    recover(bad, saved)
    capsys.readouterr()
    assert main(["replay", str(saved), "--verify"]) == 1
    out, err = capsys.readouterr()
    assert err.count("\n") == 1 and "differs" not in err, err
    found = re.search(r"verification incomplete: cycles (\d+)\.\.(\d+) missing \(recovered log\)", err)
    assert found is not None, err
    first, last = int(found[1]), int(found[2])
    assert 0 < first <= last < 1499 and "bit for bit" in out
    result, whole = replay(saved), replay(recorded_long)
    assert result.first_mismatch() is None and result.recording.cycles == first
    assert np.array_equal(result.replayed.view(np.int64), whole.replayed[:first].view(np.int64))
    # a recovered log recovered again keeps its gaps: the same cycles are named missing
    again = tmp_path / "again.mcap"
    recover(saved, again)
    assert replay(again).recording.missing == result.recording.missing
    from dobhil.run_report import bus_stats, load_run
    kept, intact = bus_stats(load_run(saved)), bus_stats(load_run(recorded_long))
    # how much the damaged chunk held depends on where the writer cut its chunks (0.05 s of
    # its own time: 21 to 200 of 1617 frames seen): the rates over the time kept are the intact
    # run's, where over the whole span they would read low by the fraction lost
    lost = 1 - kept["rx_frames"] / intact["rx_frames"]
    assert lost > 0 and kept["duration_s"] < intact["duration_s"]
    for key in ("bus_load", "rx_frames_per_s"):
        assert abs(kept[key] / intact[key] - 1) < lost / 2, (key, kept[key], intact[key], lost)


@pytest.mark.parametrize("verify", [[], ["--verify"]])
def test_a_recovered_log_without_its_start_is_refused_in_one_line(recorded_long: Path, tmp_path: Path,
                                                                    capsys: pytest.CaptureFixture[str],
                                                                    verify: list[str]) -> None:
    """Its first chunk damaged, the copy lost the initial feedback record (cycle -1) and the
    first cycles: nothing can be re-run (every cycle after a gap depends on those lost), so
    replay refuses it in one line, exit 2, rather than naming a gap after no cycle
    (docs/recording.md); report reads what it kept."""
    from dobhil.recording.recover import recover
    with open(recorded_long, "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    first = min(summary.chunk_indexes, key=lambda c: c.chunk_start_offset)
    data = bytearray(recorded_long.read_bytes())
    middle = first.chunk_start_offset + first.chunk_length // 2
    data[middle:middle + 16] = bytes(b ^ 0xFF for b in data[middle:middle + 16])
    bad, saved = tmp_path / "damaged.mcap", tmp_path / "saved.mcap"
    bad.write_bytes(bytes(data))
    recover(bad, saved)
    capsys.readouterr()
    assert main(["replay", str(saved), *verify]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "no initial feedback record (cycle -1)" in err
    assert "lost with the start of this recovered log" in err and "Traceback" not in err
