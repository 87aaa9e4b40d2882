"""The command line with a config that lists ``axes:``: ``dobhil check`` of every axis (the
bus budget of each bus, CAN-id clashes, each axis' preflight) and ``--axis NAME`` on the
commands that handle one axis (check, run, sweep, tune, certify, montecarlo). Bad input is one line on
stderr, exit 2, no traceback, nothing opened or enabled.

Real-time checks run against emulator threads on a private ``virtual`` channel and assert
only what a loaded machine cannot change (which lines, which nodes, exit codes that do not
depend on timing)."""

from __future__ import annotations

import json
import shlex
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import can
import pytest
import yaml

from dobhil.campaign.campaign import Campaign, reproduce_command
from dobhil.campaign.draws import parse_vary
from dobhil.campaign.runner import run_one
from dobhil.cli.main import main
from dobhil.config import load_config
from dobhil.config.axes import load_axes
from dobhil.drives.odrive.codec import AxisState
from dobhil.drives.odrive.emulator import EmulatedODrive
from dobhil.errors import BusError
from dobhil.runtime import axes_session, buses
from dobhil.runtime.buses import BusSpec
from odrive_nodes import odrive_nodes

#: a bus that cannot be opened: a refusal that names something else was made before opening it
NO_BUS = "socketcan:dobhil-no-such-interface"
SLACK = "loop.feedback_timeout=0.05"   # the emulator threads' pauses on a loaded machine

TWO = {"loop": {"period": 0.001, "duration": 0.05, "timing": "lockstep"},
       "axes": [{"name": "left", "drive": {"profile": "odrive-0.6", "node_id": 1}},
                {"name": "right", "drive": {"profile": "odrive-0.6", "node_id": 2}, "plant": {"inertia": 0.3},
                 "design": {"force_gain": 1.5}}],
       "environment": {"coupling": [{"axes": ["left", "right"], "stiffness": 2000.0, "damping": 20.0}]}}


def write(tmp_path: Path, data: dict[str, Any], name: str = "axes.yaml") -> Path:
    path = tmp_path / name
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def refused(args: list[str], capsys: pytest.CaptureFixture[str]) -> str:
    """Run ``dobhil ARGS``: exit 2 and one line on stderr (returned without its prefix)."""
    code = main(args)
    captured = capsys.readouterr()
    lines = captured.err.strip().splitlines()
    assert code == 2, captured
    assert len(lines) == 1 and "Traceback" not in captured.err, captured.err
    return lines[0]


def right_alone(tmp_path: Path, axes_path: Path) -> Path:
    """A single-axis config of every key axis ``right`` runs with."""
    flat = load_axes(axes_path).axis("right").config.flat()
    nested: dict[str, dict[str, Any]] = {}
    for key, value in flat.items():
        section, name = key.split(".")
        nested.setdefault(section, {})[name] = value
    return write(tmp_path, nested, "right.yaml")


# -- dobhil check: refusals before any bus opens ---------------------------------------------------


def test_check_refuses_a_node_id_clash_naming_both_axes(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    line = refused(["check", str(write(tmp_path, TWO)), "--set", "axes.right.drive.node_id=1", "--bus", NO_BUS],
                   capsys)
    assert "axes left (odrive node 1) and right (odrive node 1) on socketcan:dobhil-no-such-interface both use " \
           "CAN id 0x020" in line and "another drive.node_id" in line


def test_check_refuses_an_unknown_axis_in_set(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    line = refused(["check", str(write(tmp_path, TWO)), "--set", "axes.middle.plant.inertia=1", "--bus", NO_BUS],
                   capsys)
    assert "no axis 'middle'; axes: left, right" in line


def test_check_refuses_a_coupling_to_a_missing_axis(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    data = {**TWO, "environment": {"coupling": [{"axes": ["left", "middle"], "stiffness": 1.0}]}}
    line = refused(["check", str(write(tmp_path, data)), "--bus", NO_BUS], capsys)
    assert "couples axis 'middle', which is not in axes: left, right" in line


def test_check_refuses_a_bus_over_100_percent(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    data = {"loop": {"period": 0.001},
            "axes": [{"name": f"j{i}", "drive": {"profile": "cia402-emulated", "node_id": i}} for i in (1, 2, 3)]}
    line = refused(["check", str(write(tmp_path, data)), "--bus", NO_BUS], capsys)
    assert "bus socketcan:dobhil-no-such-interface: axes j1, j2, j3 need 1062 bits per cycle, 106 % of " \
           "1 Mbit/s at 1 kHz" in line and "loop.period and the profile's feedback_period >= 1.52 ms" in line


@pytest.mark.parametrize("command", [["check"], ["run", "--no-preflight"]])
def test_a_bus_is_opened_can_fd_for_a_can_fd_axis_listed_second(tmp_path: Path, command: list[str],
                                                                  monkeypatch: pytest.MonkeyPatch,
                                                                  capsys: pytest.CaptureFixture[str]) -> None:
    """One bus of an ODrive and a moteus controller is opened with the moteus profile's
    ``fd`` whichever axis is listed first (with the ODrive first it was opened classic, and
    the moteus drive refused it). The bus is not opened here: its spec is what is checked."""
    data = {"loop": {"period": 0.001, "duration": 0.05, "timing": "host"},
            "axes": [{"name": "od", "drive": {"profile": "odrive-0.6", "node_id": 1}},
                     {"name": "mo", "drive": {"profile": "moteus-r4.11", "node_id": 5}}]}
    opened: list[BusSpec] = []

    def not_opened(spec: BusSpec) -> can.BusABC:
        opened.append(spec)
        raise BusError(f"bus {spec.describe()}: not opened in this test")
    monkeypatch.setattr(buses, "open_bus", not_opened)
    monkeypatch.setattr(axes_session, "open_bus", not_opened)
    main([command[0], str(write(tmp_path, data)), "--bus", NO_BUS, *command[1:]])
    assert "not opened in this test" in capsys.readouterr().err
    assert [(s.describe(), s.kwargs.get("fd")) for s in opened] == [(NO_BUS, True)]


def test_check_refuses_a_node_id_out_of_range(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    line = refused(["check", str(write(tmp_path, TWO)), "--set", "axes.left.drive.node_id=64", "--bus", NO_BUS],
                   capsys)
    assert line.startswith("dobhil check: error: axis left: ")
    assert "node_id" in line and "0..63" in line


def test_check_set_zero_on_axes_needs_an_axis(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    line = refused(["check", str(write(tmp_path, TWO)), "--set-zero", "--bus", NO_BUS], capsys)
    assert "--set-zero zeroes one drive" in line and "--axis NAME" in line


# -- dobhil check: against emulated drives ------------------------------------------------------------


@pytest.fixture
def odrives() -> Iterator[tuple[str, list[EmulatedODrive]]]:
    """Emulated ODrives at nodes 1, 2 and 3 on one fresh virtual channel."""
    with odrive_nodes("axes-check", (1, 2, 3)) as nodes:
        yield nodes


def test_check_measures_every_axis_and_says_the_bus_budget(tmp_path: Path, odrives: tuple[str, list[EmulatedODrive]],
                                                           capsys: pytest.CaptureFixture[str]) -> None:
    channel, emus = odrives
    code = main(["check", str(write(tmp_path, TWO)), "--bus", f"virtual:{channel}", "--set", SLACK,
                 "--window", "0.3"])
    out = capsys.readouterr().out.splitlines()
    assert out[0] == f"bus budget virtual:{channel}: 543 bits per cycle (left 271 + right 271) = 54.3 % of " \
                     "1 Mbit/s at 1 kHz"
    # the coupled pair is judged as one loop (dobhil.cli.axes_gate): one gate line for both
    assert out[1].startswith("axes left+right: stability gate: the coupled sampled loop of axes left, right")
    assert f"axis left: bus virtual:{channel}" in out and f"axis right: bus virtual:{channel}" in out
    assert any(line.startswith("axis left: listened") and "(node 1)" in line for line in out)
    assert any(line.startswith("axis right: listened") and "(node 2)" in line for line in out)
    if code == 0:
        assert out[-1] == "preflight: ok, every axis"
    else:   # a loaded machine may pause the emulator threads: said per axis, never a refusal
        assert code == 1 and out[-1].startswith("preflight: mismatches on axis "), out
    assert all(e.axis_state is AxisState.IDLE for e in emus)   # nothing enabled


def test_check_over_70_percent_says_what_to_change(tmp_path: Path, odrives: tuple[str, list[EmulatedODrive]],
                                                   capsys: pytest.CaptureFixture[str]) -> None:
    channel, _ = odrives
    data = {**TWO, "axes": [*TWO["axes"], {"name": "third", "drive": {"profile": "odrive-0.6", "node_id": 3}}]}
    code = main(["check", str(write(tmp_path, data)), "--bus", f"virtual:{channel}", "--set", SLACK,
                 "--window", "0.2", "--json"])
    report = json.loads(capsys.readouterr().out)
    assert code == 1 and not report["ok"]
    (bus,) = report["buses"]
    assert bus["over"] and not bus["refused"] and bus["load"] == pytest.approx(3 * 271.35 / 1000)
    assert bus["advice"].startswith(f"bus virtual:{channel} (axes left, right, third): 81 % of 1 Mbit/s at 1 kHz "
                                    "is over 70 %: use a slower loop (loop.period >= 1.4 ms), or fewer axes")
    assert [a["axis"] for a in report["axes"]] == ["left", "right", "third"]
    assert [a["node_id"] for a in report["axes"]] == [1, 2, 3]
    assert {a["bus_name"] for a in report["axes"]} == {f"virtual:{channel}"}


def test_check_one_axis_with_axis(tmp_path: Path, odrives: tuple[str, list[EmulatedODrive]],
                                  capsys: pytest.CaptureFixture[str]) -> None:
    channel, _ = odrives
    main(["check", str(write(tmp_path, TWO)), "--axis", "right", "--bus", f"virtual:{channel}", "--set", SLACK,
          "--window", "0.2", "--json"])
    report = json.loads(capsys.readouterr().out)
    assert report["node_id"] == 2 and report["profile"] == "odrive-0.6" and "bus_budget" in report


# -- --axis on the single-axis commands -----------------------------------------------------------


@pytest.mark.parametrize("command", [
    ["sweep", "--vary", "plant.inertia=0.2:0.3:2"],
    ["tune", "--range", "environment.stiffness=1000:5000"],
    ["certify", "--range", "environment.stiffness=1000:5000"],
    ["montecarlo", "--runs", "2", "--vary", "plant.inertia=uniform:0.2:0.3"],
])
def test_an_axes_config_without_an_axis_names_the_axes(tmp_path: Path, command: list[str],
                                                       capsys: pytest.CaptureFixture[str]) -> None:
    line = refused([command[0], str(write(tmp_path, TWO)), *command[1:]], capsys)
    assert "lists axes left, right; this command works on one: pass --axis NAME" in line


@pytest.mark.parametrize("command, option", [
    (["sweep", "--vary", "axes.right.plant.inertia=0.2:0.3:2"], "--vary"),
    (["tune", "--range", "axes.right.environment.stiffness=1000:5000"], "--range"),
    (["montecarlo", "--runs", "2", "--vary", "axes.right.plant.inertia=uniform:0.2:0.3"], "--vary"),
])
def test_a_key_of_another_axis_is_refused(tmp_path: Path, command: list[str], option: str,
                                          capsys: pytest.CaptureFixture[str]) -> None:
    line = refused([command[0], str(write(tmp_path, TWO)), "--axis", "left", *command[1:]], capsys)
    assert f"{option} 'axes.right." in line and "a key of axis right, but this command works on axis left (--axis)" \
        in line


def test_keys_of_two_axes_are_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    line = refused(["sweep", str(write(tmp_path, TWO)), "--vary", "axes.left.plant.inertia=0.2:0.3:2",
                    "--vary", "axes.right.plant.inertia=0.2:0.3:2"], capsys)
    assert "a key of axis right, but this command works on axis left (the first key, axes.left.plant.inertia)" \
        in line


@pytest.mark.parametrize("extra, says", [
    (["--axis", "left"], "lists no axes: (a single-axis config); drop --axis"),
    (["--vary", "axes.left.plant.inertia=0.2:0.3:2"], "lists no axes: (a single-axis config); give the key as "
                                                        "plant.inertia"),
])
def test_axis_on_a_single_axis_config(extra: list[str], says: str, capsys: pytest.CaptureFixture[str]) -> None:
    args = ["sweep", "demo", *extra] + ([] if "--vary" in extra else ["--vary", "plant.inertia=0.2:0.3:2"])
    assert says in refused(args, capsys)


def test_an_unknown_axis_and_a_bad_axis_key(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = str(write(tmp_path, TWO))
    line = refused(["sweep", path, "--axis", "middle", "--vary", "plant.inertia=0.2:0.3:2"], capsys)
    assert "--axis middle: no such axis" in line and "axes: left, right" in line
    line = refused(["sweep", path, "--vary", "axes.right.inertia=0.2:0.3:2"], capsys)
    assert "expected axes.NAME.section.key" in line


def test_sweep_of_an_axis_is_the_sweep_of_that_axis_alone(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = write(tmp_path, TWO)
    assert main(["sweep", str(path), "--vary", "axes.right.plant.inertia=0.2:0.4:3", "--out",
                 str(tmp_path / "axis.csv")]) == 0
    assert main(["sweep", str(right_alone(tmp_path, path)), "--vary", "plant.inertia=0.2:0.4:3", "--out",
                 str(tmp_path / "alone.csv")]) == 0
    capsys.readouterr()
    axis, alone = (tmp_path / "axis.csv").read_text(), (tmp_path / "alone.csv").read_text()
    assert axis == alone and len(axis.splitlines()) == 4


def test_run_of_an_axis_is_the_run_of_that_axis_alone(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = write(tmp_path, TWO)
    summaries = []
    for args in (["run", str(path), "--axis", "right"], ["run", str(right_alone(tmp_path, path))]):
        assert main([*args, "--emulate", "--lockstep", "--summary-json"]) == 0
        summary = json.loads(capsys.readouterr().out)
        summary.pop("bus"), summary.pop("loop_timing")   # its private emulated bus; the host's own timing
        summaries.append(summary)
    assert summaries[0] == summaries[1]
    assert summaries[0]["cycles"] == 50


def test_a_campaign_of_an_axis_draws_that_axis_keys(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = write(tmp_path, TWO)
    campaign = Campaign(config=str(path), set_files=(), overrides=(), runs=2, seed=4, duration=0.05,
                        varies=(parse_vary("plant.inertia=uniform:0.5:0.6"),), axis="right")
    spec = campaign.spec(1)
    (key, value), = spec.draws
    assert key == "plant.inertia" and 0.5 <= value <= 0.6
    config = spec.load()
    assert config.plant.inertia == value and config.design.force_gain == 1.5   # right's own, drawn over
    assert load_axes(path, spec.all_overrides()).axis("left").config.plant.inertia == 0.25   # left untouched
    row = run_one(spec)
    assert row["error"] == "" and row["cycles"] == 50
    command = reproduce_command(spec)
    assert " --axis right " in command and f"--set axes.right.plant.inertia={value!r} " in command
    words = shlex.split(command)
    assert words[:2] == ["dobhil", "run"] and main([*words[1:], "--summary-json"]) == 0   # a command that runs
    summary = json.loads(capsys.readouterr().out)
    assert summary["cycles"] == row["cycles"]


def test_montecarlo_picks_the_axis_its_keys_name(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """The refusal of --workers 0 comes after the campaign is built: the axis was accepted."""
    line = refused(["montecarlo", str(write(tmp_path, TWO)), "--runs", "2", "--workers", "0",
                    "--vary", "axes.right.plant.inertia=uniform:0.2:0.3"], capsys)
    assert "--workers 0" in line


def test_tune_of_an_axis_is_the_tune_of_that_axis_alone(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = write(tmp_path, TWO)
    results = []
    for args in (["tune", str(path), "--range", "axes.right.environment.stiffness=1000:5000",
                  "--out", str(tmp_path / "tuned.yaml")],
                 ["tune", str(right_alone(tmp_path, path)), "--range", "environment.stiffness=1000:5000"]):
        main([*args, "--grid", "2", "--generations", "1", "--json"])
        results.append(json.loads(capsys.readouterr().out))
    assert results[0] == results[1]
    tuned = load_config(tmp_path / "tuned.yaml")   # the axis alone, its design tuned
    assert tuned.plant.inertia == 0.3 and tuned.drive.node_id == 2
    assert tuned.design.force_gain == results[0]["design"]["design.force_gain"]


def test_certify_of_an_axis_is_the_certify_of_that_axis_alone(tmp_path: Path,
                                                             capsys: pytest.CaptureFixture[str]) -> None:
    """The box tune certifies on an axis can be certified again by dobhil certify."""
    path = write(tmp_path, TWO)
    answers = []
    for args in (["certify", str(path), "--range", "axes.right.environment.stiffness=1000:5000"],
                 ["certify", str(right_alone(tmp_path, path)), "--range", "environment.stiffness=1000:5000"]):
        assert main([*args, "--loop", "continuous", "--json"]) == 0
        answers.append(json.loads(capsys.readouterr().out))
    assert answers[0] == answers[1] and answers[0]["force_gain"] == 1.5
