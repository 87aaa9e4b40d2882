"""Logs that never lie and are never destroyed: damage, foreign files, outputs that are inputs,
disk full during a run, every payload against its schema, bounded memory."""

from __future__ import annotations

import json
import os
import resource
import signal
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import jsonschema
import pytest
from mcap.reader import make_reader
from mcap.writer import Writer

from dobhil.cli.main import main
from dobhil.recording.reader import open_log
from dobhil.recording.recover import recover
from dobhil.recording.schemas import SPECS_BY_SCHEMA
from tests.recording.helpers import decode_message, topic_counts
from tests.recording.test_run_logging import logged_lockstep_run

ROOT = Path(__file__).resolve().parents[2]
DEMO = ROOT / "configs" / "demo.yaml"


@pytest.fixture(scope="module")
def recorded(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("lie") / "run.mcap"
    # long enough for more than two chunks (protobuf messages fill a chunk more slowly than JSON)
    logged_lockstep_run(path, duration=1.5)
    return path


def readers(path: Path, out: Path) -> dict[str, list[str]]:
    """Every command that reads a log, writing (if at all) under ``out``."""
    return {
        "info": ["log", "info", str(path)],
        "export-csv": ["log", "export", str(path), "--topic", "/controller", "--format", "csv",
                       "-o", str(out / "c.csv")],
        "export-can": ["log", "export", str(path), "--can", "--format", "candump", "-o", str(out / "c.log")],
        "replay": ["replay", str(path), "--verify"],
        "report": ["report", str(path), "--out", str(out / "report")],
    }


def one_line(capsys: pytest.CaptureFixture[str], argv: list[str], *words: str) -> str:
    capsys.readouterr()
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err, err
    for word in words:
        assert word in err, err
    return err


def damage_one_chunk(src: Path, dst: Path) -> int:
    """A copy of ``src`` with bytes flipped inside the compressed data of its second chunk."""
    with open(src, "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None and len(summary.chunk_indexes) > 2
    chunk = sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset)[1]
    data = bytearray(src.read_bytes())
    middle = chunk.chunk_start_offset + chunk.chunk_length // 2
    for i in range(middle, middle + 16):
        data[i] ^= 0xFF
    dst.write_bytes(bytes(data))
    return chunk.chunk_start_offset


@pytest.mark.parametrize("command", ["info", "export-csv", "export-can", "replay", "report"])
def test_a_damaged_chunk_is_one_line_naming_the_byte(recorded: Path, tmp_path: Path, command: str,
                                                     capsys: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / "damaged.mcap"
    offset = damage_one_chunk(recorded, bad)
    one_line(capsys, readers(bad, tmp_path)[command], "damaged at byte", str(offset))
    assert not list(tmp_path.glob("c.*")) and not (tmp_path / "report").exists()


def test_recover_keeps_every_chunk_but_the_damaged_one(recorded: Path, tmp_path: Path) -> None:
    bad = tmp_path / "damaged.mcap"
    damage_one_chunk(recorded, bad)
    report = recover(bad, tmp_path / "saved.mcap")
    assert report.skipped_chunks == 1 and 0 < report.message_count < open_log(recorded).info().message_count
    assert open_log(tmp_path / "saved.mcap").info().message_count == report.message_count


def damage_the_summary(src: Path, dst: Path) -> int:
    """A copy of ``src`` with one bit flipped in its Statistics record's message count (what
    ``dobhil log info`` prints), found by walking the summary section's records (opcode,
    length, body; the MCAP spec); the summary section's start."""
    data = bytearray(src.read_bytes())
    footer_at = len(data) - 8 - (1 + 8 + 8 + 8 + 4)   # the Footer, then the closing magic
    assert data[footer_at] == 0x02
    start = pos = int.from_bytes(data[footer_at + 9:footer_at + 17], "little")
    while data[pos] != 0x0B:   # Statistics
        pos += 1 + 8 + int.from_bytes(data[pos + 1:pos + 9], "little")
        assert pos < footer_at, "no Statistics record"
    data[pos + 1 + 8] ^= 0x01   # the low byte of message_count, the record's first field
    dst.write_bytes(bytes(data))
    return start


@pytest.mark.parametrize("command", ["info", "export-csv", "replay", "report"])
def test_a_damaged_summary_is_one_line_not_false_figures(recorded: Path, tmp_path: Path, command: str,
                                                         capsys: pytest.CaptureFixture[str]) -> None:
    """The summary section (the message counts, the channels' names that ``log info`` and
    the readers use) is checked by its CRC: a flipped bit there is one line naming the byte,
    not figures that lie with exit 0; ``log recover`` rebuilds it from the intact chunks."""
    bad = tmp_path / "damaged-summary.mcap"
    start = damage_the_summary(recorded, bad)
    one_line(capsys, readers(bad, tmp_path)[command], "damaged at byte", str(start), "summary section's CRC")
    report = recover(bad, tmp_path / "saved.mcap")
    assert report.message_count == open_log(recorded).info().message_count


def write_foreign(path: Path) -> None:
    """Another tool's MCAP: several channels, protobuf and JSON."""
    with open(path, "wb") as f:
        writer = Writer(f)
        writer.start(profile="", library="other-tool/2.0")
        pb = writer.register_schema("pkg.Pose", "protobuf", b"\x0a\x05proto")
        js = writer.register_schema("Temp", "jsonschema", b'{"type":"object"}')
        channels = [writer.register_channel("/pose", "protobuf", pb), writer.register_channel("/temp", "json", js),
                    writer.register_channel("/controller", "json", js)]
        for i in range(100):
            for c in channels:
                writer.add_message(c, i, b"\x08\x01" if c == channels[0] else b'{"t":1}', i)
        writer.add_metadata("config", {"design.delay_samples": "100000"})
        writer.finish()


@pytest.mark.parametrize("command", ["info", "export-csv", "export-can", "replay", "report"])
def test_a_foreign_mcap_is_one_line(tmp_path: Path, command: str, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "foreign.mcap"
    write_foreign(path)
    one_line(capsys, readers(path, tmp_path)[command], "not a dobhil log", "other-tool/2.0")


def test_recover_does_not_make_a_foreign_mcap_a_dobhil_log(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``log recover`` writes its copy as dobhil's: of another tool's MCAP it would make a
    file every command then takes for a dobhil log (and ``log export --can`` failed on its
    frames). Refused as every other reader refuses it; nothing written."""
    path = tmp_path / "foreign.mcap"
    write_foreign(path)
    one_line(capsys, ["log", "recover", str(path)], "not a dobhil log", "other-tool/2.0")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["foreign.mcap"]


@pytest.mark.parametrize(("key", "value", "words"), [
    ("design.delay_samples", "-3", ("invalid recorded config", "delay_samples")),
    ("loop.period", '"fast"', ("invalid recorded config", "loop.period")),
])
def test_crafted_metadata_is_one_line(recorded: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                      key: str, value: str, words: tuple[str, ...]) -> None:
    path = rewrite_metadata(recorded, tmp_path / "crafted.mcap", key, value)
    for argv in readers(path, tmp_path).values():
        one_line(capsys, argv, *words)


@pytest.mark.parametrize("key", ["plant.magnet_force", "nonsense.key"])
def test_a_config_key_this_version_does_not_know_refuses_only_what_needs_the_config(
        recorded: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], key: str) -> None:
    """A log whose recorded config has a key this version does not know (a newer dobhil's):
    ``log info`` describes the file with one note line naming the key; the exports copy what
    was recorded (the files the original log gives) and say the same note on stderr; every
    command that applies the config refuses it in one line naming the key, nothing written."""
    path = rewrite_metadata(recorded, tmp_path / "newer.mcap", key, "1")
    capsys.readouterr()
    assert main(["log", "info", str(path)]) == 0
    out = capsys.readouterr().out
    notes = [line for line in out.splitlines() if line.startswith("note:")]
    assert len(notes) == 1 and f"does not know ({key})" in notes[0], out
    note = notes[0].removeprefix("note:").strip()
    assert "channels:" in out and "/controller" in out and f"  {key} = 1" in out
    assert main(["log", "info", str(path), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["unknown_config_keys"] == {"config": [key]}
    out_dir, original = tmp_path / "out", tmp_path / "original"
    out_dir.mkdir()
    original.mkdir()
    for name in ("export-csv", "export-can"):
        assert main(readers(recorded, original)[name]) == 0
        capsys.readouterr()
        assert main(readers(path, out_dir)[name]) == 0
        err = capsys.readouterr().err
        said = [line for line in err.splitlines() if line.startswith("dobhil log:")]
        assert said == [f"dobhil log: note: {note}"], err
    for made in original.iterdir():
        assert (out_dir / made.name).read_bytes() == made.read_bytes(), made.name
    # bad input to an export stays its one line, the note left out
    one_line(capsys, ["log", "export", str(path), "--topic", "/nope", "--format", "csv", "-o", str(tmp_path / "n.csv")],
             "no topic '/nope'")
    one_line(capsys, ["log", "export", str(path), "--can", "--format", "candump", "-o", str(tmp_path / "c.png")],
             ".log")
    for name in ("replay", "report"):
        one_line(capsys, readers(path, out_dir)[name], "its recorded config has keys dobhil",
                 f"does not know: {key} (the log was written by dobhil/")
    one_line(capsys, ["compare", str(path), str(recorded)], f"does not know: {key}")
    assert sorted(p.name for p in out_dir.iterdir()) == sorted(p.name for p in original.iterdir())
    capsys.readouterr()
    assert main(["log", "info", str(recorded), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["unknown_config_keys"] == {}


def test_a_huge_delay_does_not_blow_up_the_report(recorded: Path, tmp_path: Path,
                                                  capsys: pytest.CaptureFixture[str]) -> None:
    """``design.delay_samples: 100000`` once made ``report`` allocate 74 GiB; the config schema
    now bounds it (<= 20), so the recorded value is refused in one line, before any work."""
    path = rewrite_metadata(recorded, tmp_path / "delay.mcap", "design.delay_samples", "100000")
    for argv in readers(path, tmp_path).values():
        one_line(capsys, argv, "invalid recorded config", "delay_samples", "<= 20")


def rewrite_metadata(src: Path, dst: Path, key: str, value: str, record_name: str = "config") -> Path:
    """A copy of ``src`` (same library) with one value of its ``record_name`` metadata changed."""
    with open(src, "rb") as f_in, open(dst, "wb") as f_out:
        reader = make_reader(f_in)
        summary = reader.get_summary()
        assert summary is not None
        writer = Writer(f_out)
        writer.start(library=reader.get_header().library)
        schemas = {sid: writer.register_schema(s.name, s.encoding, s.data) for sid, s in summary.schemas.items()}
        channels = {cid: writer.register_channel(c.topic, c.message_encoding, schemas[c.schema_id])
                    for cid, c in summary.channels.items()}
        for record in reader.iter_metadata():
            data = dict(record.metadata)
            if record.name == record_name:
                data[key] = value
            writer.add_metadata(record.name, data)
        for _, channel, message in reader.iter_messages(log_time_order=False):
            writer.add_message(channels[channel.id], message.log_time, message.data, message.publish_time)
        writer.finish()
    return dst


Writes = Callable[[Path, Path], list[str]]
#: Every command that writes, given its input and an output path (or the input itself).
WRITERS: dict[str, Writes] = {
    "export-csv": lambda src, out: ["log", "export", str(src), "--topic", "/controller", "--format", "csv",
                                    "-o", str(out)],
    "export-can": lambda src, out: ["log", "export", str(src), "--can", "--format", "candump", "-o", str(out)],
    "recover": lambda src, out: ["log", "recover", str(src), "-o", str(out)],
    "replay-out": lambda src, out: ["replay", str(src), "--out", str(out)],
    "replay-plot": lambda src, out: ["replay", str(src), "--plot", str(out)],
    "report": lambda src, out: ["report", str(src), "--out", str(out)],
}


@pytest.mark.parametrize("command", list(WRITERS))
@pytest.mark.parametrize("how", ["same", "symlink"])
def test_an_output_that_is_the_input_is_refused(recorded: Path, tmp_path: Path, command: str, how: str,
                                                capsys: pytest.CaptureFixture[str]) -> None:
    src = tmp_path / "run.mcap"
    src.write_bytes(recorded.read_bytes())
    before = src.read_bytes()
    out = src
    if how == "symlink":
        out = tmp_path / "link.mcap"
        out.symlink_to(src)
    one_line(capsys, WRITERS[command](src, out))
    assert src.read_bytes() == before


def test_import_and_default_outputs_never_overwrite_the_input(recorded: Path, tmp_path: Path,
                                                              capsys: pytest.CaptureFixture[str]) -> None:
    log = tmp_path / "frames.log"
    assert main(["log", "export", str(recorded), "--can", "--format", "candump", "-o", str(log)]) == 0
    before = log.read_bytes()
    one_line(capsys, ["log", "import", str(log), "-o", str(log)])
    one_line(capsys, ["log", "export", str(log), "--can", "--format", "candump"])  # default output: frames.log
    assert log.read_bytes() == before


@pytest.mark.parametrize("argv", [
    ["--plot", "{tmp}/x.txt"],
    ["--log", "{tmp}/x.txt"],
    ["--log", "{tmp}"],
    ["--log", "{tmp}/afile/run.mcap"],
    ["--log", "{existing}"],
])
def test_unwritable_outputs_are_refused_before_the_run(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                                       argv: list[str]) -> None:
    (tmp_path / "afile").write_text("x")
    existing = tmp_path / "old.mcap"
    existing.write_bytes(b"precious")
    args = [a.format(tmp=tmp_path, existing=existing) for a in argv]
    one_line(capsys, ["run", str(DEMO), "--emulate", "--lockstep", "--duration", "0.2", *args])
    assert existing.read_bytes() == b"precious" and not list(tmp_path.glob("*.mcap*"))[1:]


def test_every_payload_of_a_demo_run_matches_its_json_schema(tmp_path: Path) -> None:
    """Each message, read as protobuf by its schema, is the payload its topic's JSON schema
    documents (the table's types, the choices of its text fields). In the topics layout, one
    message per topic; a cycle message holds the same bytes (tests/recording/test_cycle_layout.py)."""
    assert main(["demo", "--out", str(tmp_path), "--set", "loop.duration=0.5", "--log-layout", "topics"]) == 0
    (path,) = tmp_path.glob("run-*.mcap")
    with open(path, "rb") as f:
        reader = make_reader(f)
        validators = {}
        count = 0
        for schema, channel, message in reader.iter_messages():
            assert schema is not None and schema.encoding == "protobuf" and channel.message_encoding == "protobuf"
            if channel.topic not in validators:
                validators[channel.topic] = jsonschema.Draft202012Validator(
                    SPECS_BY_SCHEMA[schema.name].json_schema())
            validators[channel.topic].validate(decode_message(schema, channel, message.data))
            count += 1
    assert set(validators) == {"/can/rx", "/can/tx", "/drive/feedback", "/drive/command", "/controller", "/loop",
                               "/emulator/truth", "/events"} and count > 3000


def _limit_file_size() -> None:
    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # a write past the limit fails with EFBIG instead
    resource.setrlimit(resource.RLIMIT_FSIZE, (400_000, 400_000))


def test_disk_full_during_a_run_stops_it_with_recorder_failed(tmp_path: Path) -> None:
    path = tmp_path / "full.mcap"
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.run([sys.executable, "-m", "dobhil", "run", str(DEMO), "--emulate", "--lockstep",
                           "--duration", "30", "--log", str(path)], env=env, capture_output=True, text=True,
                          preexec_fn=_limit_file_size, timeout=120)
    assert proc.returncode == 1, proc.stderr
    assert "stopped: recorder_failed" in proc.stdout and "File too large" in proc.stdout
    assert "Traceback" not in proc.stderr
    cycles = int(proc.stdout.split()[0])
    assert 0 < cycles < 30_000  # the run stopped early, safely (the stop line says the drive was disabled)
    assert "WARNING" not in proc.stdout
    recover(path, tmp_path / "saved.mcap")
    assert topic_counts(tmp_path / "saved.mcap")["/controller"] > 100


RSS = """
import json, resource, sys
from dobhil.cli.main import main
code = main(sys.argv[1:])
print(json.dumps({"code": code, "self": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss,
                  "writer": resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss}))
"""


def _peak_rss_kib(duration: float, path: Path) -> dict[str, int]:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.run([sys.executable, "-c", RSS, "run", str(DEMO), "--emulate", "--lockstep", "--duration",
                           str(duration), "--log", str(path)], env=env, capture_output=True, text=True, timeout=7200)
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    assert out["code"] == 0, proc.stderr
    return out  # type: ignore[no-any-return]


@pytest.mark.skipif(not os.environ.get("DOBHIL_SLOW"), reason="a 1 h lockstep run (minutes): set DOBHIL_SLOW=1")
def test_a_1h_run_holds_no_more_memory_than_a_1min_run(tmp_path: Path) -> None:
    short = _peak_rss_kib(60.0, tmp_path / "short.mcap")
    long = _peak_rss_kib(3600.0, tmp_path / "long.mcap")
    for who in ("self", "writer"):
        assert long[who] - short[who] < 50 * 1024, (who, short, long)


def flipped(src: Path, dst: Path, at: int, count: int = 1) -> Path:
    """A copy of ``src`` with the ``count`` bytes from ``at`` inverted."""
    data = bytearray(src.read_bytes())
    for i in range(at, at + count):
        data[i] ^= 0xFF
    dst.write_bytes(bytes(data))
    return dst


def recovered_lines(capsys: pytest.CaptureFixture[str], bad: Path, out: Path) -> list[str]:
    capsys.readouterr()
    assert main(["log", "recover", str(bad), "-o", str(out)]) == 0
    return capsys.readouterr().out.splitlines()


def test_recover_skips_a_damaged_metadata_record_near_the_start(recorded: Path, tmp_path: Path,
                                                                 capsys: pytest.CaptureFixture[str]) -> None:
    """A metadata record's length damaged (its framing lost, before any data): every chunk
    after it is still saved; one line names the skipped record's byte."""
    offset = next(pos for pos, kind in record_offsets(recorded) if kind == "Metadata")
    bad = flipped(recorded, tmp_path / "meta.mcap", offset + 1 + 5)   # a high byte of its length
    lines = recovered_lines(capsys, bad, tmp_path / "saved.mcap")
    total = open_log(recorded).info().message_count
    assert lines[0].startswith(f"recovered {total} messages"), lines
    skipped = [line for line in lines if line.startswith("skipped")]
    assert len(skipped) == 1 and f"at byte {offset} " in skipped[0], lines
    saved = open_log(tmp_path / "saved.mcap")
    assert saved.info().message_count == total and "config" not in saved.metadata


def test_recover_skips_a_damaged_first_chunk_of_a_finished_file(recorded: Path, tmp_path: Path,
                                                                 capsys: pytest.CaptureFixture[str]) -> None:
    """The first chunk holds every schema and channel record: damaged, the channels are read
    from the summary section, and every later chunk is saved; the line gives the chunk's byte,
    its messages (by its message indexes) and the log time lost."""
    offsets = record_offsets(recorded)
    chunk = next(pos for pos, kind in offsets if kind == "Chunk")
    bad = flipped(recorded, tmp_path / "first.mcap", chunk + 200, 16)
    lines = recovered_lines(capsys, bad, tmp_path / "saved.mcap")
    total = open_log(recorded).info().message_count
    saved = open_log(tmp_path / "saved.mcap").info().message_count
    skipped = [line for line in lines if line.startswith("skipped")]
    assert len(skipped) == 1 and f"skipped a damaged chunk at byte {chunk} (" in skipped[0], lines
    assert f"{total - saved} messages" in skipped[0] and "log time" in skipped[0] and "lost" in skipped[0]
    assert 0 < saved < total
    # its report: the first cycle kept at its time in the run, not at 0 s, and no step from 0 there
    from dobhil.run_report import load_run, step_infos
    whole, kept = load_run(recorded), load_run(tmp_path / "saved.mcap")
    first = int(kept["cycle"][0])
    assert first > 0 and kept.t[0] == pytest.approx(whole.t[first], abs=1e-9)
    later = [s.time for s in step_infos(whole) if s.time > kept.t[0]]
    assert later and [s.time for s in step_infos(kept)] == pytest.approx(later, abs=1e-9)


def test_recover_of_a_cut_file_names_channels_lost_with_their_first_chunk(tmp_path: Path,
                                                                          capsys: pytest.CaptureFixture[str]) -> None:
    """Without the summary (a file cut short) a channel defined only in a damaged chunk cannot
    be read: its messages are counted on one line, not copied; a channel defined in a later
    chunk still is."""
    from dobhil.recording.writer import LogWriter
    from tests.recording.helpers import command, feedback
    path = tmp_path / "run.mcap"
    log = LogWriter(open(path, "wb"), metadata={}, fsync=False)
    log.write([command(i, 1.0) for i in range(100)])
    log.flush()                        # the first chunk: /drive/command's channel and 100 messages
    log.write([feedback(100 + i, 1.0) for i in range(50)])
    log.flush()                        # the second: /drive/feedback's channel and 50 messages
    log.write([command(200 + i, 1.0) for i in range(30)])
    log.flush()                        # the third: 30 more of /drive/command, its channel not repeated
    log.close()                        # not finished: no summary repeats the channels
    chunk = next(pos for pos, kind in record_offsets(path) if kind == "Chunk")
    bad = flipped(path, tmp_path / "bad.mcap", chunk + 40, 8)
    lines = recovered_lines(capsys, bad, tmp_path / "saved.mcap")
    assert lines[0].startswith("recovered 50 messages"), lines
    assert any(line.startswith(f"skipped a damaged chunk at byte {chunk} ") for line in lines), lines
    lost = [line for line in lines if line.startswith("lost ")]
    assert lost == ["lost 30 messages of channel 1: its channel record was in damaged bytes and is repeated "
                    "nowhere readable"], lines
    assert open_log(tmp_path / "saved.mcap").topics() == ("/drive/feedback",)


def test_recover_names_lost_channels_when_nothing_else_is_left(recorded: Path, tmp_path: Path,
                                                               capsys: pytest.CaptureFixture[str]) -> None:
    """A cut file whose first chunk (every channel record) is damaged: nothing is readable,
    said in one line with the messages of channels lost; nothing written."""
    offsets = record_offsets(recorded)
    chunk = next(pos for pos, kind in offsets if kind == "Chunk")
    data_end = next(pos for pos, kind in offsets if kind == "DataEnd")
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(recorded.read_bytes()[:data_end])
    bad = flipped(cut, tmp_path / "cut-first.mcap", chunk + 200, 16)
    one_line(capsys, ["log", "recover", str(bad), "-o", str(tmp_path / "saved.mcap")],
             "no complete message to recover", "channels whose channel records were in damaged bytes")
    assert not (tmp_path / "saved.mcap").exists()


def record_offsets(path: Path) -> list[tuple[int, str]]:
    """(byte offset, record type) of each record of ``path`` in file order, up to its footer
    or to where it stops reading (a file cut short)."""
    from mcap.stream_reader import StreamReader
    out = []
    with open(path, "rb") as f:
        f.seek(8)
        reader = StreamReader(f, skip_magic=True, emit_chunks=True).records
        while True:
            pos = f.tell()
            try:
                record = next(reader)
            except Exception:
                return out
            out.append((pos, type(record).__name__))


def test_recover_resynchronises_after_a_chunk_whose_length_is_damaged(recorded: Path, tmp_path: Path,
                                                                       capsys: pytest.CaptureFixture[str]) -> None:
    """A chunk's length damaged: its record cannot be framed, so reading goes on at the next
    record that reads and checks; the bytes skipped are one line, with the chunk the summary's
    index placed there and its log time."""
    chunks = [pos for pos, kind in record_offsets(recorded) if kind == "Chunk"]
    bad = flipped(recorded, tmp_path / "length.mcap", chunks[1] + 1 + 6)
    lines = recovered_lines(capsys, bad, tmp_path / "saved.mcap")
    skipped = [line for line in lines if line.startswith("skipped")]
    assert len(skipped) == 1 and skipped[0].startswith(f"skipped unreadable bytes at byte {chunks[1]} ("), lines
    assert "1 chunks" in skipped[0] and "log time" in skipped[0], lines
    total = open_log(recorded).info().message_count
    assert 0 < open_log(tmp_path / "saved.mcap").info().message_count < total


@pytest.mark.parametrize("command", ["info", "export-csv", "replay"])
def test_a_damaged_message_index_is_named_at_its_own_byte(recorded: Path, tmp_path: Path, command: str,
                                                          capsys: pytest.CaptureFixture[str]) -> None:
    """A message index has no CRC of its own: the data section's, checked at the DataEnd
    record, catches its damage. The line names the message index's byte, not the DataEnd's."""
    offsets = record_offsets(recorded)
    index = [pos for pos, kind in offsets if kind == "MessageIndex"][9]   # one of the second chunk's
    data_end = next(pos for pos, kind in offsets if kind == "DataEnd")
    # a log time of its first entry: opcode, length, channel id (2), the entries' length (4)
    bad = flipped(recorded, tmp_path / "index.mcap", index + 1 + 8 + 2 + 4 + 3, 2)
    err = one_line(capsys, readers(bad, tmp_path)[command], f"damaged at byte {index} ", "message index")
    assert str(data_end) not in err
