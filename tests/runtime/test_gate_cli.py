"""The stability gate where the commands meet it: ``dobhil run``, ``demo`` and ``check`` refuse
an unstable design in one line before any bus or log file is opened, ``--allow-unstable``
runs it and records the override in the log, a low margin is one warning line."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from dobhil.cli.main import main
from dobhil.data import shipped_configs
from dobhil.recording.reader import open_log
from dobhil.run_report import analyse, load_run, summary_text

from .helpers import DEMO

EXIT_USAGE = 2
UNSTABLE = ["--set", "design.force_gain=20"]      # the demo's sampled loop is stable to 8.72
RUN = ["run", str(DEMO), "--emulate", "--lockstep"]


def files_in(directory: Path) -> list[Path]:
    return sorted(p for p in directory.rglob("*"))


def test_run_refuses_an_unstable_design_in_one_line_and_writes_nothing(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    log = tmp_path / "run.mcap"
    code = main([*RUN, *UNSTABLE, "--log", str(log), "--plot", str(tmp_path / "run.png")])
    out, err = capsys.readouterr()
    assert code == EXIT_USAGE and out == ""
    assert err.count("\n") == 1 and "Traceback" not in err
    assert err.startswith("dobhil run: error: refused: ")
    for said in ("UNSTABLE", "at C_f = 20", "max stable C_f: 8.72", "lower design.force_gain below 8.72",
                 "--allow-unstable"):
        assert said in err
    assert files_in(tmp_path) == []


@pytest.mark.parametrize("command", [["run", str(DEMO)], ["check", str(DEMO)]])
def test_the_gate_comes_before_the_bus(command: list[str], capsys: pytest.CaptureFixture[str]) -> None:
    """A bus that cannot be opened would be the error if the bus came first."""
    code = main([*command, "--bus", "nosuchif:x", *UNSTABLE])
    err = capsys.readouterr().err
    assert code == EXIT_USAGE and err.count("\n") == 1
    assert "refused" in err and "UNSTABLE" in err and "nosuchif" not in err


def test_demo_refuses_too_and_leaves_its_out_directory_alone(tmp_path: Path,
                                                            capsys: pytest.CaptureFixture[str]) -> None:
    code = main(["demo", "--out", str(tmp_path / "out"), *UNSTABLE])
    err = capsys.readouterr().err
    assert code == EXIT_USAGE and err.count("\n") == 1 and err.startswith("dobhil demo: error: refused")
    assert files_in(tmp_path) == []


def test_allow_unstable_runs_says_so_once_and_the_log_records_it(tmp_path: Path,
                                                                  capsys: pytest.CaptureFixture[str]) -> None:
    log = tmp_path / "run.mcap"
    code = main([*RUN, *UNSTABLE, "--allow-unstable", "--duration", "0.05", "--log", str(log)])
    out, err = capsys.readouterr()
    assert code in (0, 1), err    # 50 ms may end before the instability watch has seen enough
    gate_lines = [line for line in err.splitlines() if "stability gate" in line]
    assert gate_lines == [line for line in err.splitlines() if "overridden" in line] and len(gate_lines) == 1
    assert "UNSTABLE" in gate_lines[0] and "the run goes on" in gate_lines[0]
    meta = {k: json.loads(v) for k, v in open_log(log).metadata["stability_gate"].items()}
    assert meta["status"] == "unstable" and meta["overridden"] is True and meta["allow_unstable"] is True
    assert meta["force_gain"] == 20.0 and meta["max_stable_force_gain"] == pytest.approx(8.72386, rel=1e-5)
    assert meta["assumed"]["sampled"] is True and meta["assumed"]["delay_samples"] == 0
    # and the run's report says so
    summary, _ = analyse(load_run(log))
    assert summary["stability_gate"]["overridden"] is True
    assert "stability gate: OVERRIDDEN by --allow-unstable: " in summary_text(summary)


def test_a_stable_run_records_the_verdict_without_an_override(tmp_path: Path,
                                                               capsys: pytest.CaptureFixture[str]) -> None:
    log = tmp_path / "run.mcap"
    assert main([*RUN, "--duration", "0.05", "--log", str(log), "--summary-json"]) == 0
    out, err = capsys.readouterr()
    assert "stability gate" not in err
    meta = {k: json.loads(v) for k, v in open_log(log).metadata["stability_gate"].items()}
    assert meta["status"] == "stable" and meta["overridden"] is False
    assert meta["gain_margin_db"] == pytest.approx(12.7936, abs=1e-3)
    # the summary gives the same verdict, its values as values (not the log's JSON strings)
    assert json.loads(out)["stability_gate"] == meta


def test_a_low_margin_is_one_warning_line_and_the_run_goes_on(capsys: pytest.CaptureFixture[str]) -> None:
    code = main([*RUN, "--set", "design.force_gain=7", "--duration", "0.05"])
    out, err = capsys.readouterr()
    assert code == 0 and "stopped: done" in out
    assert err.count("\n") == 1
    assert err.startswith("dobhil run: warning: low stability margin: gain margin 1.91 dB < "
                          "analysis.min_gain_margin = 3 dB")
    code = main([*RUN, "--set", "design.force_gain=7", "--set", "analysis.min_gain_margin=1", "--duration", "0.05"])
    assert code == 0 and capsys.readouterr().err == ""


def test_check_reports_the_gate(capsys: pytest.CaptureFixture[str]) -> None:
    code = main(["check", str(DEMO), "--bus", "dobhil:demo", "--json"])
    report = json.loads(capsys.readouterr().out)
    assert code in (0, 1)   # the emulated drive's own timing decides the preflight
    assert report["stability_gate"]["status"] == "stable"
    assert report["stability_gate"]["max_stable_force_gain"] == pytest.approx(8.72386, rel=1e-5)


@pytest.mark.parametrize("name", shipped_configs())
def test_no_shipped_config_is_refused(name: str, capsys: pytest.CaptureFixture[str]) -> None:
    """Each shipped config runs (a short lockstep run); those without a force loop (the
    identification runs, loop.mode torque) get one note line naming why."""
    code = main(["run", name, "--emulate", "--lockstep", "--duration", "0.02"])
    err = capsys.readouterr().err
    assert code == 0, err
    assert "refused" not in err and "stability margin" not in err
    notes = [line for line in err.splitlines() if "stability gate" in line]
    assert notes == ([] if "identify" not in name else
                     ["dobhil run: note: stability gate not applied: loop.mode = torque (the reference is the "
                      "torque command: no force loop closes)"])


def test_the_refusal_as_a_user_sees_it(tmp_path: Path) -> None:
    """The command of the report that showed the problem, as its own process: exactly one
    line on stderr, nothing on stdout, exit 2, no log file."""
    import subprocess
    import sys
    log = tmp_path / "run.mcap"
    done = subprocess.run([sys.executable, "-m", "dobhil", *RUN, *UNSTABLE, "--log", str(log)],
                          capture_output=True, text=True, cwd=tmp_path, timeout=120)
    assert done.returncode == EXIT_USAGE and done.stdout == ""
    assert len(done.stderr.splitlines()) == 1 and done.stderr.startswith("dobhil run: error: refused: ")
    assert "Traceback" not in done.stderr and files_in(tmp_path) == []


def test_an_overridden_unstable_design_is_stopped_unstable_long_before_its_end(tmp_path: Path) -> None:
    """The same command with ``--allow-unstable``, as its own process: the gate lets it run,
    the instability watch stops it (exit 1, the safe stop's line) well before its duration."""
    import subprocess
    import sys
    done = subprocess.run([sys.executable, "-m", "dobhil", *RUN, *UNSTABLE, "--allow-unstable", "--summary-json"],
                          capture_output=True, text=True, cwd=tmp_path, timeout=120)
    assert done.returncode == 1, done.stderr
    info = json.loads(done.stdout)
    assert info["stop_reason"] == "unstable", info["stop_detail"]
    assert "torque at its limit" in info["stop_detail"]
    # the demo lasts 1.2 s; the watch's window is 0.5 s: a stop within the first third of
    # the run is "well before" whatever the machine's speed (lockstep: simulated time)
    assert info["cycles"] * info["period"] < 1.2 / 3
    assert "stability gate overridden" in done.stderr and "Traceback" not in done.stderr
