"""The MIT demo on the command line, in process (``dobhil.cli.main.main``):
``dobhil run configs/mit-demo.yaml --emulate --lockstep --log x.mcap`` converges with the
same summary fields as the ODrive demo, ``dobhil replay x.mcap --verify`` reproduces it bit
for bit, ``dobhil report`` works on it; bad MIT input (a model the table lacks, a firmware
it lacks, a torque limit above the model's range) is one line, exit 2, and nothing ran.

The demo's motor is a CubeMars AK80-9: its exit frame cannot be confirmed (its replies
carry no mode), so a run that lasted its duration ends with one NOTE line saying what was
confirmed (the reply to the exit arrived, zero torque in it), never the loud WARNING --
on stderr, in the summary and in the log's events.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest
import yaml


from dobhil.cli.main import main
from dobhil.config import load_config
from dobhil.drives.mit.rules import model_of
from dobhil.drives.load import load_drive_profile
from dobhil.recording.reader import open_log

from .helpers import DEMO, DRIVERS, REPO, summary_shape

MIT_DEMO = REPO / "configs" / "mit-demo.yaml"
EXIT_USAGE = 2


def _run(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    code = main(argv)
    out, err = capsys.readouterr()
    return code, out, err


def test_the_mit_demo_converges_replays_bit_for_bit_and_reports(tmp_path: Path,
                                                                capsys: pytest.CaptureFixture[str]) -> None:
    log = tmp_path / "x.mcap"
    code, out, err = _run(["run", str(MIT_DEMO), "--emulate", "--lockstep", "--log", str(log), "--summary-json"],
                          capsys)
    assert code == 0, err
    info = json.loads(out)
    assert info["stop_reason"] == "done" and info["cycles"] == 1200 and info["overruns"] == 0

    # converged: the force reached the reference within what the motor can apply -- its
    # torque command is truncated to a 2 t_max / 4095 grid (8.8 mN m on an AK80-9)
    quantum = model_of(load_drive_profile(load_config(MIT_DEMO))).quanta.torque
    final = info["final"]
    assert final["tau_ref"] == 1.0
    assert abs(final["tau_int_true"] - 1.0) <= quantum and abs(final["tau_int_hat"] - 1.0) <= quantum, final

    # the same summary fields, of the same types, as the ODrive demo's (run the same way)
    code, odrive_out, odrive_err = _run(["run", str(DEMO), "--emulate", "--lockstep", "--summary-json",
                                         "--duration", "0.05", "--log", str(tmp_path / "odrive.mcap")], capsys)
    assert code == 0, odrive_err
    assert summary_shape(info) == summary_shape(json.loads(odrive_out))

    # the exit frame went out and was answered with zero torque; that it cannot be confirmed
    # is a note at this planned end, not the loud line
    assert info["safe_stop"]["confirmation"] == "unconfirmable" and info["safe_stop"]["planned"] is True
    assert [f["what"] for f in info["safe_stop"]["frames"]] == ["zero torque", "exit motor mode"]
    assert all(f["sent"] for f in info["safe_stop"]["frames"]) and info["drive_disabled"] is False
    note = info["drive_note"]
    assert info["drive_warning"] == "" and note.startswith("node 1 cannot confirm its disable by design: ")
    assert "the last (to exit motor mode) with torque -0.0044 N m (zero)" in note and "carries no motor mode" in note
    assert err.strip().splitlines() == [f"NOTE: {note}"]
    with open_log(log) as f:
        events = [p for _, _, p in f.iter_messages(("/events",))]
    last = [e for e in events if e["reason"].startswith("safe stop:")]
    assert [(e["reason"], e["detail"]) for e in last] == [("safe stop: unconfirmable", note)], last

    # replay: the drive decodes the recorded replies again, unwrap state and all
    code, out, err = _run(["replay", str(log), "--verify"], capsys)
    assert code == 0, err
    assert "replayed 1200 cycles" in out
    assert "identical: every command and estimate reproduced bit for bit" in out, out

    # report: the analysis' prediction of the same design (one period of delay) against the run
    report_dir = tmp_path / "report"
    code, out, err = _run(["report", str(log), "--out", str(report_dir), "--json"], capsys)
    assert code == 0, err
    summary = json.loads(out)
    assert summary["cycles"] == 1200 and summary["stop"] == "done"
    assert summary["latency"]["protocol_delay_periods"] == 1
    assert summary["prediction"]["available"] and summary["prediction"]["rms_difference"] > 0
    assert all((report_dir / name).stat().st_size > 0 for name in ("force.png", "summary.json", "summary.txt"))


def test_a_motor_that_never_replies_to_enter_motor_mode_is_the_loud_line(tmp_path: Path,
                                                                        capsys: pytest.CaptureFixture[str]) -> None:
    """Real time on a channel where no motor replies, without the preflight: enter motor mode
    went out, so a motor whose replies never reach the host (a wrong mit.reply_id, a broken
    receive path) may be in motor mode. The run says enable_failed, then the loud line; the
    summary never calls the motor disabled."""
    path = _profile(tmp_path, "ak80-9", enable_timeout=0.2)
    code, out, err = _run(["run", str(MIT_DEMO), "--bus", f"virtual:mit-nobody-{id(path)}", "--no-preflight",
                           "--set", f"drive.profile={path}", "--summary-json"], capsys)
    assert code == 1, err
    info = json.loads(out)
    assert info["stop_reason"] == "enable_failed" and "after enter motor mode" in info["stop_detail"]
    assert info["safe_stop"]["confirmation"] == "never_answered" and info["drive_disabled"] is False
    assert [f["what"] for f in info["safe_stop"]["frames"]] == ["zero torque", "exit motor mode"]
    warning = info["drive_warning"]
    assert warning == ("drive may still be enabled: node 1 never answered: its enable frames (for motor mode) went "
                       "out and nothing was heard from it since, so exit motor mode cannot be confirmed; cut power")
    assert f"WARNING: {warning}" in err.splitlines() and info["drive_note"] == "", err


def _profile(tmp_path: Path, name: str, *, mit: dict[str, Any] | None = None, **changes: Any) -> Path:
    data = yaml.safe_load((DRIVERS / f"{name}.yaml").read_text(encoding="utf-8"))
    data.update(changes)
    if mit:
        data["mit"] = {**data["mit"], **mit}
    path = tmp_path / f"{name}-bad.yaml"
    path.write_text(yaml.safe_dump(data), encoding="utf-8")
    return path


@pytest.mark.parametrize(("profile", "changes", "says"), [
    ("ak80-9", {"mit": {"model": "AK99-1"}},
     "mit.model: no row for cubemars AK99-1 firmware 'manual-1.0.8'"),
    ("ak80-9", {"firmware": "9.9"}, "no row for cubemars AK80-9 firmware '9.9'"),
    ("ak80-9", {"torque_limit": 19.0}, "torque_limit: expected a number > 0 and <= 18 Nm"),
    ("dm4310", {"torque_limit": 10.5}, "torque_limit: expected a number > 0 and <= 10 Nm"),
])
def test_bad_mit_input_is_one_line_exit_2_and_nothing_ran(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                                          monkeypatch: pytest.MonkeyPatch, profile: str,
                                                          changes: dict[str, Any], says: str) -> None:
    """Refused while reading the profile: not even a bus was opened (so no motor could
    have been told to enter motor mode)."""
    def no_bus(*args: Any, **kwargs: Any) -> None:
        raise AssertionError("a bus was opened for a refused profile")

    monkeypatch.setattr("dobhil.runtime.session.open_bus", no_bus)
    path = _profile(tmp_path, profile, **changes)
    code, out, err = _run(["run", str(MIT_DEMO), "--emulate", "--lockstep", "--set", f"drive.profile={path}"],
                          capsys)
    assert code == EXIT_USAGE, (out, err)
    lines = err.strip().splitlines()
    assert len(lines) == 1 and says in lines[0], err
    assert "cycles" not in out and "WARNING" not in err   # no loop ran: nothing was enabled
