"""A protocol that fixes the command delay (``command_delay_periods`` in the drive profile)
makes the design's delay everywhere the design meets the drive: analyze, sweep, the run's
controller and lockstep emulator, replay and the run report's prediction."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from dobhil.analysis import report as analysis_report
from dobhil.analysis.transfer import LoopSystems
from dobhil.cli.main import main
from dobhil.config import load_config
from dobhil.config.axes import load_axes
from dobhil.drives.load import load_profile
from dobhil.drives.timing import effective_config, with_command_delay
from dobhil.runtime.session import RunSession, build_controller, lockstep_latency
from dobhil.synthesis.controller import sampled_controller
from dobhil.synthesis.params import params_from_config

from .helpers import write_profile

REPO = Path(__file__).resolve().parents[2]
#: a fractional delay the profile must replace
FRACTION = ("design.input_delay=0.0003",)


def _latched(tmp_path: Path, periods: int = 1) -> Path:
    return write_profile(tmp_path, "odrive-0.6", command_delay_periods=periods)


def _matrices(config: Any) -> list[np.ndarray]:
    systems = LoopSystems.build(params_from_config(config), sampled=True)
    return [systems.closed.a, systems.closed.b, systems.closed.c, systems.closed.d]


def test_the_profile_sets_delay_samples_and_clears_the_fraction(tmp_path: Path) -> None:
    config = load_config("demo", list(FRACTION))
    profile = load_profile(_latched(tmp_path))
    assert profile.command_delay_periods == 1
    new, note = effective_config(config, profile)
    assert (new.design.delay_samples, new.design.input_delay) == (1, 0.0)
    assert dataclasses.replace(new, design=config.design) == config   # nothing else changed
    assert "command_delay_periods = 1" in note and "design.delay_samples = 1" in note and "\n" not in note
    again, note = effective_config(new, profile)
    assert again is new and note == ""   # already so: nothing to say


def test_profiles_without_it_leave_every_shipped_config_as_it_is() -> None:
    """ODrive: bit for bit the same config object, so the same analysis and controller."""
    configs = sorted((REPO / "configs").rglob("*.yaml"))
    assert configs
    for name in ("odrive-0.6", "odrive-0.5", "odrive-0.6-factory"):
        profile = load_profile(name)
        assert profile.command_delay_periods is None
        for path in configs:
            for axis in load_axes(path).axes:   # each axis of a config that lists axes
                assert effective_config(axis.config, profile) == (axis.config, "")
    assert with_command_delay(load_config("demo"), None) == (load_config("demo"), "")


def test_analyze_uses_the_protocols_delay_and_says_so(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                                      monkeypatch: pytest.MonkeyPatch) -> None:
    seen: list[Any] = []
    original = analysis_report.analyze

    def spy(config: Any) -> Any:
        seen.append(original(config))
        return seen[-1]

    monkeypatch.setattr(analysis_report, "analyze", spy)
    profile = _latched(tmp_path)
    assert main(["analyze", "demo", "--set", f"drive.profile={profile}", "--set", FRACTION[0]]) == 0
    out = capsys.readouterr().out
    assert out.splitlines()[0].startswith(f"drive profile {profile.stem!r}: command_delay_periods = 1")
    expected = load_config("demo", ["design.delay_samples=1", "design.input_delay=0"])
    for got, want in zip(_matrices(seen[0].config), _matrices(expected), strict=True):
        np.testing.assert_array_equal(got, want)
    assert seen[0].config.design == expected.design
    # the fraction the profile replaced changes the model: the comparison can fail
    assert not np.array_equal(_matrices(load_config("demo", list(FRACTION)))[0], _matrices(expected)[0])
    # --json: stdout stays one JSON object, the note goes to stderr
    assert main(["analyze", "demo", "--set", f"drive.profile={profile}", "--json"]) == 0
    captured = capsys.readouterr()
    json.loads(captured.out)
    assert "command_delay_periods = 1" in captured.err
    # ODrive: no note, the config as given
    assert main(["analyze", "demo"]) == 0
    assert "command_delay_periods" not in capsys.readouterr().out
    assert seen[-1].config == load_config("demo")


def test_sweep_uses_it_and_says_so(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    profile = _latched(tmp_path, 2)
    assert main(["sweep", "demo", "--set", f"drive.profile={profile}", "--vary", "design.force_gain=1:2:2",
                 "--sampled"]) == 0
    assert "command_delay_periods = 2" in capsys.readouterr().out


def test_the_run_controller_and_lockstep_latency(tmp_path: Path) -> None:
    config = load_config("demo", list(FRACTION))
    latched = load_profile(_latched(tmp_path))
    odrive = load_profile("odrive-0.6")
    expected = load_config("demo", ["design.delay_samples=1", "design.input_delay=0"])
    assert lockstep_latency(config, latched) == 0.0   # the emulated drive's latch makes the delay
    assert lockstep_latency(config, odrive) == pytest.approx(3e-4)
    assert lockstep_latency(expected, odrive) == pytest.approx(1e-3)
    got = build_controller(config, latched).ss
    want = sampled_controller(params_from_config(expected))
    for name in ("a", "b_y", "b_u", "b_i", "c", "d_y"):
        np.testing.assert_array_equal(getattr(got, name), getattr(want, name))
    with RunSession(load_config("demo", [f"drive.profile={_latched(tmp_path)}", *FRACTION]), emulate=True,
                    lockstep=True) as session:
        assert session.design_config.design == expected.design and session.design_note
        assert session.config == load_config("demo", [f"drive.profile={_latched(tmp_path)}", *FRACTION])
        assert session.emulator is not None and session.emulator._latency == 0.0  # type: ignore[union-attr]


def test_the_run_report_uses_the_recorded_profiles_delay() -> None:
    from dobhil.run_report import RunData, command_delay_periods, design_config
    config = load_config("demo", list(FRACTION))
    data = RunData(path="x", config=config, metadata={"drive": {"command_delay_periods": "1"}}, t=np.zeros(0))
    assert command_delay_periods(data) == 1
    got = design_config(data)
    assert got is not None and (got.design.delay_samples, got.design.input_delay) == (1, 0.0)
    for meta in ({"drive": {"command_delay_periods": "null"}}, {"drive": {}}, {}):   # ODrive, older logs
        old = RunData(path="x", config=config, metadata=meta, t=np.zeros(0))
        assert command_delay_periods(old) is None and design_config(old) is config


def test_a_recorded_run_replays_and_reports_with_the_recorded_delay(tmp_path: Path,
                                                                      capsys: pytest.CaptureFixture[str]) -> None:
    from dobhil.replay import replay
    from dobhil.run_report import latency_stats, load_run
    log = tmp_path / "run.mcap"
    profile = _latched(tmp_path)
    assert main(["run", "demo", "--emulate", "--lockstep", "--set", f"drive.profile={profile}", "--set",
                 FRACTION[0], "--duration", "0.1", "--log", str(log)]) == 0
    err = capsys.readouterr().err
    assert "command_delay_periods = 1" in err
    result = replay(log)
    assert result.recording.profile.command_delay_periods == 1 and result.first_mismatch() is None
    assert main(["replay", str(log), "--verify"]) == 0
    assert "bit for bit" in capsys.readouterr().out
    latency = latency_stats(load_run(log))
    assert latency["protocol_delay_periods"] == 1 and latency["assumed_s"] == pytest.approx(1e-3)


def test_the_report_line_of_a_latched_drive() -> None:
    from dobhil.run_report import _latency_verdict
    assert "in time for it" in _latency_verdict({"protocol_delay_periods": 1, "matches": True})
    assert "miss the drive's latch" in _latency_verdict({"protocol_delay_periods": 1, "matches": False})
