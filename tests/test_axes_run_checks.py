"""What ``dobhil run`` of a config that lists axes checks before its loop: each bus' budget
(refused over 100 % with nothing opened, one line of advice over 70 %), the same budget in
``dobhil analyze``, and on a real bus each axis' preflight as ``dobhil check`` measures it
(a refusing preflight: nothing enabled). Real-bus runs go against emulated ODrive threads
on a private ``virtual`` channel; they assert only what a loaded machine cannot change."""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import yaml

from dobhil.cli.main import main
from dobhil.config.axes import load_axes
from dobhil.drives.axes import axis_drives, bus_budgets
from dobhil.drives.odrive.codec import AxisState
from dobhil.drives.odrive.emulator import EmulatedODrive
from odrive_nodes import odrive_nodes
from tests.runtime.helpers import HOST_WATCHES, host_watch_cases

SLACK = "loop.feedback_timeout=0.05"   # the emulator threads' pauses on a loaded machine
HOST = "loop.timing=host"              # a real bus runs in real time


def axes_config(tmp_path: Path, profile: str, nodes: tuple[int, ...]) -> Path:
    """Uncoupled axes ``j<node>`` of one profile, each pressing on its own wall."""
    data: dict[str, Any] = {"loop": {"period": 0.001, "duration": 0.02, "timing": "lockstep"},
                            "axes": [{"name": f"j{n}", "drive": {"profile": profile, "node_id": n}} for n in nodes]}
    path = tmp_path / "axes.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def budget_of(path: Path) -> Any:
    axes = load_axes(path)
    (budget,) = bus_budgets(axis_drives(axes, path.parent), axes.period)
    return budget


@pytest.fixture
def no_session(monkeypatch: pytest.MonkeyPatch) -> None:
    import dobhil.runtime.axes_session as axes_session

    def refuse(*_: Any, **__: Any) -> None:
        raise AssertionError("a session was opened")
    monkeypatch.setattr(axes_session, "AxesSession", refuse)


def test_run_refuses_a_bus_over_100_percent_before_anything_opens(tmp_path: Path, no_session: None,
                                                                  capsys: pytest.CaptureFixture[str]) -> None:
    path = axes_config(tmp_path, "cia402-emulated", (1, 2, 3))
    budget = budget_of(path)
    assert budget.refused   # 3 CiA 402 axes at 1 kHz on 1 Mbit/s
    code = main(["run", str(path), "--emulate", "--lockstep"])
    out, err = capsys.readouterr()
    assert code == 2 and out == "" and err.count("\n") == 1 and "Traceback" not in err
    assert err.strip().endswith(budget.refusal())
    assert "axes j1, j2, j3 need" in err and "loop.period and the profile's feedback_period >= 1.52 ms" in err


def test_run_over_70_percent_says_what_to_change_and_runs(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = axes_config(tmp_path, "odrive-0.6", (1, 2, 3))
    budget = budget_of(path)
    assert budget.over and not budget.refused   # 3 ODrive axes: 81 %
    code = main(["run", str(path), "--emulate", "--lockstep"])
    err = capsys.readouterr().err.splitlines()
    assert code == 0
    assert [line for line in err if "bus " in line and "%" in line] == [f"dobhil run: warning: {budget.advice()}"]


def test_run_within_70_percent_says_nothing_of_the_budget(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code = main(["run", str(axes_config(tmp_path, "odrive-0.6", (1, 2))), "--emulate", "--lockstep"])
    assert code == 0 and "%" not in capsys.readouterr().err


@pytest.mark.parametrize(("nodes", "over"), [((1, 2), False), ((1, 2, 3), True)])
def test_analyze_says_each_bus_budget(tmp_path: Path, nodes: tuple[int, ...], over: bool,
                                      capsys: pytest.CaptureFixture[str]) -> None:
    path = axes_config(tmp_path, "odrive-0.6", nodes)
    budget = budget_of(path)
    assert main(["analyze", str(path)]) == 0
    text = capsys.readouterr().out.splitlines()
    assert text[0] == budget.line()
    assert (f"  {budget.advice()}" in text) is over
    assert main(["analyze", str(path), "--json"]) == 0
    (bus,) = json.loads(capsys.readouterr().out)["buses"]
    assert bus["line"] == budget.line() and bus["over"] is over and bus["axes"] == dict(budget.per_axis)


# -- the preflight of each axis on a real bus -----------------------------------------------------


@pytest.fixture
def odrives() -> Iterator[tuple[str, list[EmulatedODrive]]]:
    """Emulated ODrives at nodes 1 and 2 on one fresh virtual channel."""
    with odrive_nodes("axes-run", (1, 2)) as nodes:
        yield nodes


def test_a_refusing_preflight_of_one_axis_enables_nothing(tmp_path: Path, odrives: tuple[str, list[EmulatedODrive]],
                                                          no_session: None, capsys: pytest.CaptureFixture[str]) -> None:
    """Axis j4 has no drive on the bus: its preflight refuses the run as a single-axis run's
    does (exit 1, the refusal line names the axis) and no axis is enabled: the loop's
    session is never opened."""
    channel, emus = odrives
    path = axes_config(tmp_path, "odrive-0.6", (1, 4))
    code = main(["run", str(path), "--bus", f"virtual:{channel}", "--set", SLACK, "--set", HOST,
                 "--preflight-window", "0.2"])
    out, err = capsys.readouterr()
    assert code == 1 and out == ""
    assert "dobhil run: axis j4: refused to enable: node 4 is not on the bus, node(s) 1, 2 are" in err
    assert "preflight is not run" not in err
    assert all(e.axis_state is AxisState.IDLE for e in emus)   # nothing enabled


def test_each_axis_is_measured_before_the_run(tmp_path: Path, odrives: tuple[str, list[EmulatedODrive]],
                                              capsys: pytest.CaptureFixture[str]) -> None:
    channel, _ = odrives
    path = axes_config(tmp_path, "odrive-0.6", (1, 2))
    code = main(["run", str(path), "--bus", f"virtual:{channel}", "--set", SLACK, "--set", HOST,
                 "--preflight-window", "0.3",
                 "--duration", "0.02"])
    err = capsys.readouterr().err
    for name, node in (("j1", 1), ("j2", 2)):
        # measured and passed, or (a loaded machine pausing the emulator threads) refused: said per axis
        assert (f"dobhil run: axis {name}: preflight: node {node}: " in err
                or f"dobhil run: axis {name}: refused to enable: " in err), err
    assert code in (0, 1)


def test_each_axis_preflight_adds_every_axis_frames_of_its_bus_to_what_it_heard(tmp_path: Path) -> None:
    """Three ODrive axes on one bus: the run adds three torque commands (135 bits each) per
    period to what each axis' preflight heard, 40.5 % of 1 Mbit/s at 1 kHz, not its own one
    (13.5 %): the per-axis "with the run's commands" matches the bus budget."""
    from dobhil.cli.axes_check import measure_axes
    path = axes_config(tmp_path, "odrive-0.6", (1, 2, 3))
    axes = load_axes(path)
    drives = axis_drives(axes, path.parent, "virtual:nobody-measured")
    reports = measure_axes(axes, drives, 0.02, "virtual:nobody-measured")
    assert [name for name, _, _ in reports] == ["j1", "j2", "j3"]
    for _, _, report in reports:
        assert report.bus.run_bits_per_s == pytest.approx(3 * 135 / 0.001)


def test_no_preflight_skips_it(tmp_path: Path, odrives: tuple[str, list[EmulatedODrive]],
                               capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch) -> None:
    import dobhil.cli.axes_check as axes_check

    def measured(*_: Any, **__: Any) -> None:
        raise AssertionError("the preflight ran")
    monkeypatch.setattr(axes_check, "measure_axes", measured)
    channel, _ = odrives
    code = main(["run", str(axes_config(tmp_path, "odrive-0.6", (1, 2))), "--bus", f"virtual:{channel}",
                 "--set", SLACK, "--set", HOST, "--no-preflight", "--duration", "0.02"])
    assert code in (0, 1) and "preflight" not in capsys.readouterr().err


@pytest.mark.parametrize("command", ["run", "check"])
@pytest.mark.parametrize("case", HOST_WATCHES)
def test_a_period_an_axis_timeout_on_the_host_cannot_tolerate_is_refused(
        command: str, case: str, tmp_path: Path, no_session: None, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str]) -> None:
    """The one rule of a single axis (a command watchdog, a CiA 402 heartbeat consumer, an
    MIT command timeout: a period of half of it refused) per axis: one line naming the
    axis, exit 2, from run and check alike, no session and no bus opened."""
    def no_bus(*args: object, **kwargs: object) -> None:
        raise AssertionError("a bus was opened for a refused period")

    monkeypatch.setattr("dobhil.runtime.buses.open_bus", no_bus)
    watch = host_watch_cases(tmp_path)[case]
    path = axes_config(tmp_path, watch.profile, (1, 2))
    code = main([command, str(path), "--set", f"loop.period={watch.period}", "--set", "loop.feedback_timeout=0.5",
                 *(["--emulate"] if command == "run" else ["--bus", "virtual:nobody"])])
    captured = capsys.readouterr()
    assert code == 2 and captured.out == "", captured.err
    (line,) = captured.err.splitlines()
    assert line.startswith(watch.refusal(f"dobhil {command}: error: axis j1: ")) and watch.allowed() in line, line


@pytest.mark.parametrize("command", ["run", "check"])
def test_a_period_an_axis_watchdog_cannot_tolerate_is_refused_before_anything_opens(
        command: str, tmp_path: Path, no_session: None, capsys: pytest.CaptureFixture[str]) -> None:
    """odrive-0.6's watchdog allows 50 ms: a command every 30 ms may reach it 60 ms apart.
    One line naming the axis, exit 2, from run and check alike, no session opened."""
    path = axes_config(tmp_path, "odrive-0.6", (1, 2))
    code = main([command, str(path), "--set", "loop.period=0.03", "--set", "loop.feedback_timeout=0.5",
                 *(["--emulate"] if command == "run" else ["--bus", "virtual:nobody"])])
    captured = capsys.readouterr()
    assert code == 2 and captured.out == ""
    assert captured.err.splitlines() == [
        f"dobhil {command}: error: axis j1: loop.period = 0.03 s is too long for the command watchdog of drive "
        "profile 'odrive-0.6' (watchdog_timeout = 0.05 s; a command every period may reach the drive up to two "
        "periods apart); allowed: loop.period < 0.025 s (half of watchdog_timeout), or a longer watchdog_timeout "
        "(on the drive too)"]


@pytest.mark.parametrize("command", [["run", "--emulate", "--lockstep"], ["demo"]], ids=["run", "demo"])
@pytest.mark.parametrize(("profiles", "refused"), [
    (("cia402-emulated", "cia402-emulated"), "j1"),
    (("odrive-0.6", "cia402-emulated"), "j2"),    # the odrive axis has no periodic frame: the CiA 402 one says
], ids=["cia402", "odrive-cia402"])
@pytest.mark.parametrize("period", ["0.002", "0.02"])   # odrive-0.6 watchdog: < 0.025 s
def test_a_lockstep_period_an_axis_sync_cannot_follow_is_refused_before_anything_opens(
        command: list[str], profiles: tuple[str, str], refused: str, period: str, tmp_path: Path,
        monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    """The single-axis rule per axis: the lockstep bus steps once per loop period and sends
    a periodic frame (a CiA 402 SYNC, every feedback_period = 1 ms) only every whole number
    of steps. One line naming the axis, exit 2, from run and demo alike, no bus opened."""
    def no_bus(*args: object, **kwargs: object) -> None:
        raise AssertionError("a bus was opened for a refused lockstep period")

    monkeypatch.setattr("dobhil.runtime.axes_session.open_bus", no_bus)
    data: dict[str, Any] = {"loop": {"period": 0.001, "duration": 0.1, "timing": "lockstep"},
                            "axes": [{"name": f"j{n}", "drive": {"profile": p, "node_id": n}}
                                     for n, p in enumerate(profiles, start=1)]}
    path = tmp_path / "axes.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    out = tmp_path / "out"
    code = main([command[0], str(path), *command[1:], *(["--out", str(out)] if command[0] == "demo" else []),
                 "--set", f"loop.period={period}", "--set", "loop.feedback_timeout=0.5", "--allow-unstable"])
    captured = capsys.readouterr()
    assert code == 2 and captured.out == "", captured.err
    assert captured.err.splitlines() == [
        f"dobhil {command[0]}: error: axis {refused}: lockstep timing steps the emulated bus once per loop.period = "
        f"{float(period):g} s and sends a periodic frame only every whole number of steps, but drive profile "
        "'cia402-emulated' sends SYNC every 0.001 s (feedback_period); allowed in lockstep: loop.period = 0.001 s "
        "(feedback_period), or a run in real time"]
    assert not out.exists() or not any(out.iterdir())


def test_the_session_itself_refuses_such_a_lockstep_period_before_a_bus_opens(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A caller of the library (no command's checks before it) gets the same refusal."""
    from dobhil.errors import ConfigError
    from dobhil.runtime.axes_session import AxesSession

    def no_bus(*args: object, **kwargs: object) -> None:
        raise AssertionError("a bus was opened for a refused lockstep period")

    monkeypatch.setattr("dobhil.runtime.axes_session.open_bus", no_bus)
    axes = load_axes(axes_config(tmp_path, "cia402-emulated", (1, 2)), ["loop.period=0.002"])
    with pytest.raises(ConfigError, match=r"^axis j1: lockstep timing steps the emulated bus once per loop.period "
                                          r"= 0.002 s .* sends SYNC every 0.001 s \(feedback_period\)"):
        AxesSession(axes, emulate=True, lockstep=True, config_dir=tmp_path)


@pytest.mark.parametrize(("profiles", "period", "refused", "why"), [
    (("odrive-0.6", "odrive-0.6"), 0.002, "j1", "'odrive-0.6' has encoder estimates every 0.001 s (feedback_period) "
                                                "and loop.period = 0.002 s"),
    (("odrive-0.6", "moteus-r4.11"), 0.001, "j2", "'moteus-r4.11' has no feedback_period"),
], ids=["same-profile", "moteus"])
def test_feedback_timing_an_axis_cannot_keep_is_refused_naming_the_axis(
        profiles: tuple[str, str], period: float, refused: str, why: str, tmp_path: Path,
        monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    """Feedback timing runs a cycle per feedback frame of each axis: an axis whose profile
    streams none, or at another period, is refused in one line naming the axis (two axes of
    one profile are told apart by it), exit 2, no bus opened."""
    def no_bus(*args: object, **kwargs: object) -> None:
        raise AssertionError("a bus was opened for a refused timing")

    monkeypatch.setattr("dobhil.runtime.axes_session.open_bus", no_bus)
    data: dict[str, Any] = {"loop": {"period": period, "duration": 0.02, "timing": "feedback", "feedback_timeout": 0.5},
                            "axes": [{"name": f"j{n}", "drive": {"profile": p, "node_id": n}}
                                     for n, p in enumerate(profiles, start=1)]}
    path = tmp_path / "axes.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    code = main(["run", str(path), "--emulate", "--allow-unstable"])
    captured = capsys.readouterr()
    assert code == 2 and captured.out == "", captured.err
    (line,) = captured.err.splitlines()
    assert line.startswith(f"dobhil run: error: axis {refused}: loop.timing = feedback runs one cycle per feedback "
                           f"frame, but drive profile {why}"), line
