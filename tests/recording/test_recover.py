"""Crash safety: a recorder killed with SIGKILL leaves a file ``recover`` salvages."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from dobhil.errors import LogFileError
from dobhil.files import OutputError
from dobhil.recording.reader import open_log
from dobhil.recording.recover import default_output, recover
from tests.recording.helpers import command, write_log

ROOT = Path(__file__).resolve().parents[2]

CHILD = """
import sys, time
from dobhil.recording.writer import LogWriter, RecordMode
log = LogWriter(open(sys.argv[1], "wb"), metadata={"run": {"who": "child"}},
                attachments=[("config.yaml", "application/yaml", b"a: 1\\n")], mode=RecordMode.LOSSY)
print("ready", flush=True)
i, next_flush = 0, time.monotonic() + 1.0
while True:
    log.write([(6, time.time_ns(), i, 0.0, 1e-5, False, float("nan"))])
    i += 1
    if time.monotonic() > next_flush:
        log.flush()
        next_flush += 1.0
    time.sleep(0.0002)
"""


@pytest.mark.skipif(sys.platform == "win32", reason="SIGKILL")
def test_kill_9_loses_at_most_about_one_second(tmp_path: Path) -> None:
    path = tmp_path / "run.mcap"
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    child = subprocess.Popen([sys.executable, "-c", CHILD, str(path)], stdout=subprocess.PIPE, env=env, cwd=ROOT)
    try:
        assert child.stdout is not None and child.stdout.readline().strip() == b"ready"
        start_ns = time.time_ns()
        time.sleep(2.5)
    finally:
        child.send_signal(signal.SIGKILL)
        child.wait()
        child.stdout.close()  # type: ignore[union-attr]
    run_s = (time.time_ns() - start_ns) / 1e9
    with pytest.raises(LogFileError, match="cut short"):
        open_log(path)
    report = recover(path)
    assert report.output == str(default_output(path)) and not report.complete
    assert report.message_count > 0
    assert report.duration_s >= run_s - 1.5
    log = open_log(report.output)
    info = log.info()
    assert info.message_count == report.message_count
    assert info.metadata["run"] == {"who": "child"}
    assert info.attachments == ("config.yaml",)


def test_recover_a_complete_file_copies_everything(tmp_path: Path) -> None:
    path = write_log(tmp_path / "run.mcap", [command(i, float(i)) for i in range(1000)], metadata={"run": {"a": "1"}})
    report = recover(path, tmp_path / "out.mcap")
    assert report.complete and report.counts == (("/drive/command", 1000),)
    assert (report.start_ns, report.end_ns) == (0, 999)
    original = list(open_log(path).iter_messages())
    assert list(open_log(tmp_path / "out.mcap").iter_messages()) == original


def test_recover_a_cut_file_keeps_whole_chunks(tmp_path: Path) -> None:
    path = write_log(tmp_path / "run.mcap", [command(i, float(i)) for i in range(50_000)])
    cut = tmp_path / "cut.mcap"
    data = path.read_bytes()
    cut.write_bytes(data[: len(data) // 2])
    report = recover(cut)
    assert 0 < report.message_count < 50_000
    times = [t for _, t, _ in open_log(report.output).iter_messages()]
    assert times == list(range(report.message_count))


def test_recover_refuses_to_overwrite_its_input(tmp_path: Path) -> None:
    path = write_log(tmp_path / "run.mcap", [])
    with pytest.raises(OutputError, match="is an input"):
        recover(path, path)


@pytest.mark.parametrize("keep", [9, 200])   # the magic and a bit: no complete message
def test_nothing_to_recover_writes_nothing(tmp_path: Path, keep: int) -> None:
    """A file cut before its first complete message is refused in one line: an empty
    recording would only look like a recovered one."""
    path = write_log(tmp_path / "run.mcap", [command(i, float(i)) for i in range(1000)])
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(path.read_bytes()[:keep])
    with pytest.raises(LogFileError, match=r"cut.mcap: no complete message to recover \(.*\); nothing written$"):
        recover(cut)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cut.mcap", "run.mcap"]
