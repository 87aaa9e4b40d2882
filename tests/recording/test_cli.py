"""``dobhil log``: output of each action and one-line errors (exit 2) on bad files."""

from __future__ import annotations

import csv
import gzip
import json
from pathlib import Path

import can
import pytest

from dobhil.cli.main import main
from dobhil.recording.schemas import EventKind, Topic
from tests.recording.helpers import event, feedback, frame, write_log


@pytest.fixture
def run_file(tmp_path: Path) -> Path:
    meta = {"config": {"loop.period": "0.001"}, "run": {"start_time": "2026-01-01T00:00:00"}}
    records = [event(EventKind.ENABLE, 1_000_000_000, "start")]
    for i in range(100):
        t = 1_000_000_000 + i * 1_000_000
        records += [feedback(t, 0.1 * i), frame(can.Message(arbitration_id=0x10, data=bytes([i])), Topic.CAN_RX, t)]
    return write_log(tmp_path / "run.mcap", records, metadata=meta, stop="reference finished")


def bad_files(tmp_path: Path, good: Path) -> dict[str, tuple[Path, str]]:
    empty = tmp_path / "empty.mcap"
    empty.write_bytes(b"")
    text = tmp_path / "text.mcap"
    text.write_text("not mcap at all\n")
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(good.read_bytes()[:-100])
    return {
        "missing": (tmp_path / "none.mcap", "no such file"),
        "empty": (empty, "empty file"),
        "not-mcap": (text, "not an MCAP file (bad magic)"),
        "truncated": (cut, "cut short"),
    }


ACTIONS = {
    "info": lambda f: ["log", "info", str(f)],
    "export-csv": lambda f: ["log", "export", str(f), "--topic", "/drive/feedback", "--format", "csv"],
    "export-can": lambda f: ["log", "export", str(f), "--can", "--format", "candump"],
}


@pytest.mark.parametrize("action", list(ACTIONS))
@pytest.mark.parametrize("case", ["missing", "empty", "not-mcap", "truncated"])
def test_bad_files_give_one_line_and_exit_2(
    tmp_path: Path, run_file: Path, capsys: pytest.CaptureFixture[str], action: str, case: str
) -> None:
    path, expected = bad_files(tmp_path, run_file)[case]
    capsys.readouterr()
    assert main(ACTIONS[action](path)) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and expected in err and "Traceback" not in err


@pytest.mark.parametrize("case", ["missing", "empty", "not-mcap"])
def test_recover_bad_files_give_one_line_and_exit_2(
    tmp_path: Path, run_file: Path, capsys: pytest.CaptureFixture[str], case: str
) -> None:
    path, expected = bad_files(tmp_path, run_file)[case]
    capsys.readouterr()
    assert main(["log", "recover", str(path)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and expected in err


def test_info_text_and_json(run_file: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["log", "info", str(run_file)]) == 0
    text = capsys.readouterr().out
    assert "reference finished" in text and "/drive/feedback" in text and "loop.period = 0.001" in text
    assert main(["log", "info", str(run_file), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    counts = {c["topic"]: c["message_count"] for c in info["channels"]}
    assert counts == {"/events": 2, "/drive/feedback": 100, "/can/rx": 100}
    assert info["stop_reason"] == "reference finished" and info["dropped"] == 0
    assert info["duration_s"] == pytest.approx(0.099)
    assert info["metadata"]["config"] == {"loop.period": "0.001"}


def test_recover_truncated_file_by_cli(tmp_path: Path, run_file: Path, capsys: pytest.CaptureFixture[str]) -> None:
    cut = bad_files(tmp_path, run_file)["truncated"][0]
    assert main(["log", "recover", str(cut)]) == 0
    out = capsys.readouterr().out
    assert "recovered 202 messages" in out and (tmp_path / "cut.recovered.mcap").is_file()
    assert main(["log", "info", str(tmp_path / "cut.recovered.mcap")]) == 0
    # a recording is never overwritten, as `run --log` refuses: the second recover is one line
    recovered = (tmp_path / "cut.recovered.mcap").read_bytes()
    capsys.readouterr()
    assert main(["log", "recover", str(cut)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "exists; refusing to overwrite a recording" in err
    assert (tmp_path / "cut.recovered.mcap").read_bytes() == recovered


def test_export_csv_columns_from_schema(tmp_path: Path, run_file: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "fb.csv"
    assert main(["log", "export", str(run_file), "--topic", "/drive/feedback", "--format", "csv", "-o", str(out)]) == 0
    rows = list(csv.reader(out.open()))
    assert rows[0] == ["log_time_ns", "position", "velocity", "drive_state", "protocol_state", "protocol_state_name",
                       "protocol_error", "protocol_error_text", "seq", "cycle"]
    assert len(rows) == 101 and rows[1] == ["1000000000", "0.0", "1.0", "code 8", "-1", "not reported", "0", "none",
                                            "0", "0"]
    # the progress counts the exported topic's messages only: its last line is at 100 %
    assert capsys.readouterr().err.splitlines()[-1].startswith("export: 100/100 messages (100 %)")
    assert main(["log", "export", str(run_file), "--topic", "/can/rx", "--format", "csv"]) == 0
    can_rows = list(csv.DictReader((tmp_path / "run.can_rx.csv").open()))
    assert can_rows[5]["data"] == "5" and can_rows[5]["is_fd"] == "false"


def test_export_csv_writes_only_a_csv_name(tmp_path: Path, run_file: Path,
                                          capsys: pytest.CaptureFixture[str]) -> None:
    """As the CAN exports check their suffix: a figure given as the output stays untouched."""
    png = tmp_path / "figure.png"
    png.write_bytes(b"\x89PNG")
    assert main(["log", "export", str(run_file), "--topic", "/drive/feedback", "--format", "csv", "-o", str(png)]) == 2
    assert capsys.readouterr().err.endswith("expected a .csv file name\n") and png.read_bytes() == b"\x89PNG"


def test_export_unknown_topic_lists_available(run_file: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["log", "export", str(run_file), "--topic", "/nope", "--format", "csv"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "available: " in err and "/drive/feedback" in err


@pytest.mark.parametrize(
    "argv",
    [
        ["--can", "--format", "csv"],
        ["--topic", "/can/rx", "--format", "blf"],
        ["--topic", "/can/rx", "--can", "--format", "csv"],
        ["--format", "csv"],
    ],
)
def test_export_flag_mismatch(run_file: Path, capsys: pytest.CaptureFixture[str], argv: list[str]) -> None:
    assert main(["log", "export", str(run_file), *argv]) == 2
    assert capsys.readouterr().err.count("\n") == 1


def test_export_can_and_import_by_cli(tmp_path: Path, run_file: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["log", "export", str(run_file), "--can", "--format", "asc"]) == 0
    # the progress counts the CAN frames only, not the log's other messages
    assert capsys.readouterr().err.splitlines()[-1].startswith("export: 100/100 messages (100 %)")
    asc = tmp_path / "run.asc"
    assert len(list(can.LogReader(asc))) == 100
    assert main(["log", "import", str(asc), "-o", str(tmp_path / "back.mcap")]) == 0
    assert "imported 100 CAN frames" in capsys.readouterr().out
    assert main(["log", "import", str(asc), "-o", str(tmp_path / "back.mcap")]) == 2   # exists: kept
    assert "exists; refusing to overwrite a recording" in capsys.readouterr().err
    assert main(["log", "import", str(tmp_path / "none.asc"), "-o", str(tmp_path / "x.mcap")]) == 2
    assert capsys.readouterr().err.count("\n") == 1


@pytest.mark.parametrize("compressed", [False, True], ids=["plain", "gz"])
@pytest.mark.parametrize(("fmt", "suffix"), [("candump", "log"), ("asc", "asc"), ("blf", "blf")])
def test_import_records_the_format_inside_a_gz(tmp_path: Path, run_file: Path, capsys: pytest.CaptureFixture[str],
                                               fmt: str, suffix: str, compressed: bool) -> None:
    """The ``import`` metadata names the log's own format (the suffix python-can reads it
    by), for a gzip-compressed log the one before ``.gz``, with ``compression = gzip``; ``log
    info`` shows both."""
    exported = tmp_path / f"frames.{suffix}"
    assert main(["log", "export", str(run_file), "--can", "--format", fmt, "-o", str(exported)]) == 0
    source = exported
    if compressed:
        source = tmp_path / f"frames.{suffix}.gz"
        source.write_bytes(gzip.compress(exported.read_bytes()))
    out = tmp_path / "back.mcap"
    assert main(["log", "import", str(source), "-o", str(out)]) == 0
    capsys.readouterr()
    assert main(["log", "info", str(out), "--json"]) == 0
    expected = {"source": source.name, "format": suffix, **({"compression": "gzip"} if compressed else {})}
    assert json.loads(capsys.readouterr().out)["metadata"]["import"] == expected
    assert main(["log", "info", str(out)]) == 0
    text = capsys.readouterr().out
    record = text[text.index("metadata import:\n"):].splitlines()[1:1 + len(expected)]
    assert record == [f"  {k} = {v}" for k, v in expected.items()], text


@pytest.mark.parametrize("compressed", [False, True], ids=["plain", "gz"])
def test_import_of_a_cut_candump_warns_in_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                                   compressed: bool) -> None:
    text = "(1700000000.000000) can0 123#0011223344556677 R\n(1700000000.001000) can0 124#00112233"
    cut = tmp_path / ("cut.log.gz" if compressed else "cut.log")
    cut.write_bytes(gzip.compress(text.encode()) if compressed else text.encode())
    assert main(["log", "import", str(cut), "-o", str(tmp_path / "back.mcap")]) == 0
    captured = capsys.readouterr()
    assert "imported 1 CAN frames" in captured.out
    said = [line for line in captured.err.splitlines() if line.startswith("dobhil log:")]
    assert said == [f"dobhil log: warning: {cut}: cut short: imported the 1 complete frames; "
                    "dropped line 2, a record cut short (37 characters and no end of line)"]


@pytest.mark.parametrize("compressed", [False, True], ids=["plain", "gz"])
def test_import_of_a_bad_candump_line_is_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                                  compressed: bool) -> None:
    text = "(1700000000.000000) can0 123#0011223 R\n(1700000000.001000) can0 124#00 R\n"
    bad = tmp_path / ("bad.log.gz" if compressed else "bad.log")
    bad.write_bytes(gzip.compress(text.encode()) if compressed else text.encode())
    assert main(["log", "import", str(bad), "-o", str(tmp_path / "back.mcap")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"{bad}: line 1: data '0011223' has an odd number of hex digits" in err
    assert not list(tmp_path.glob("*.mcap"))
