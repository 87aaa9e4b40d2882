"""``dobhil run`` and ``dobhil demo`` through ``dobhil.cli.main.main`` (in process):
the JSON summary, the demo PNG, and one-line errors with the right exit codes."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

from dobhil.cli.main import main

from .helpers import DEMO, realtime_profile

EXIT_USAGE = 2


def one_line(text: str) -> str:
    lines = text.strip().splitlines()
    assert len(lines) == 1, text
    return lines[0]


def test_run_summary_json(capsys: pytest.CaptureFixture[str]) -> None:
    """``run --emulate --lockstep --summary-json`` prints exactly one JSON object with
    cycles, overruns, stop reason and the final values; the demo reaches its 1 N m."""
    code = main(["run", str(DEMO), "--emulate", "--lockstep", "--summary-json"])
    out = capsys.readouterr().out
    info = json.loads(one_line(out))
    assert code == 0
    assert info["cycles"] == 1200 and info["overruns"] == 0
    assert info["stop_reason"] == "done"
    final = info["final"]
    assert set(final) >= {"tau_ref", "tau_int_hat", "tau_int_true", "q"}
    assert final["tau_ref"] == 1.0
    assert final["tau_int_true"] == pytest.approx(1.0, abs=1e-3)
    assert final["tau_int_hat"] == pytest.approx(1.0, abs=1e-3)


def test_demo_writes_the_png(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``dobhil demo --out DIR`` runs and writes DIR/demo_run.png."""
    assert main(["demo", "--out", str(tmp_path)]) == 0
    png = tmp_path / "demo_run.png"
    assert png.is_file() and png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert str(png) in capsys.readouterr().out


def test_bad_key_is_one_line_exit_2(capsys: pytest.CaptureFixture[str]) -> None:
    code = main(["run", str(DEMO), "--emulate", "--lockstep", "--set", "loop.nokey=1"])
    err = one_line(capsys.readouterr().err)
    assert code == EXIT_USAGE and "loop.nokey" in err


def test_unknown_interface_is_one_line_exit_2(capsys: pytest.CaptureFixture[str]) -> None:
    code = main(["run", str(DEMO), "--bus", "nosuchif:x"])
    err = one_line(capsys.readouterr().err)
    assert code == EXIT_USAGE and "'nosuchif'" in err


def test_lockstep_needs_emulate(capsys: pytest.CaptureFixture[str]) -> None:
    code = main(["run", str(DEMO), "--lockstep"])
    err = one_line(capsys.readouterr().err)
    assert code == EXIT_USAGE and "--emulate" in err


def test_no_drive_answers(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Real time on a channel where nobody answers: one clear line saying the drive did
    not answer, a non-zero exit, no thread or bus left (conftest). The preflight finds
    no drive and refuses before enabling; without it, the enable handshake times out."""
    profile = realtime_profile(tmp_path, "odrive-0.6", enable_timeout=0.3)
    code = main(["run", str(DEMO), "--bus", f"virtual:nobody-{os.getpid()}",
                 "--set", f"drive.profile={profile}", "--preflight-window", "0.2"])
    captured = capsys.readouterr()
    lines = captured.err.splitlines()
    assert code == 1 and captured.out == ""
    assert len(lines) == 1 and "refused to enable" in lines[0] and "no heartbeat" in lines[0], captured.err
    code = main(["run", str(DEMO), "--bus", f"virtual:nobody-{os.getpid()}",
                 "--set", f"drive.profile={profile}", "--no-preflight"])
    captured = capsys.readouterr()
    lines = captured.err.splitlines()
    assert code != 0
    assert captured.out == ""
    assert len(lines) == 1 and "enable_failed" in lines[0] and "no heartbeat from node 3" in lines[0], captured.err
