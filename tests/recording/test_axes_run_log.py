"""``dobhil run AXES.yaml --log``: the several-axis loop recorded through one AxesLog, then
``replay --verify`` bit for bit on every axis (lockstep and real time, coupled), ``report``
per axis, ``identify --axis`` of each axis' plant, and a run that fails before its loop
leaves no file behind."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path
from typing import Any

import can
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from dobhil.cli.main import main
from dobhil.config.axes import load_axes
from dobhil.identify.intervals import read_identified
from dobhil.recording.axes import axis_log, layout
from dobhil.recording.reader import open_log
from dobhil.replay import replay_axes
from tests.recording.test_axes_log import _rewrite

DEMO = Path(__file__).resolve().parents[2] / "configs" / "two-axis-demo.yaml"
AXES = ("left", "right")

#: two uncoupled ODrive axes in open-loop torque mode: left a multisine, right a prbs
IDENTIFY = """\
plant: {inertia: 0.25, viscous_friction: 0.02, torque_limit: 2.0}
environment: {stiffness: 0.0, damping: 0.0, contact_position: 10.0}
design: {nominal_inertia: 0.25, identified_inertia: 0.125, dob_bandwidth: 500.0, rtob_bandwidth: 500.0,
         force_gain: 2.0}
loop: {mode: torque, period: 0.001, duration: 3.0, timing: lockstep, feedback_timeout: 0.01, torque_limit: 1.0,
       position_min: -3.0, position_max: 3.0, velocity_limit: 5.0}
reference: {kind: multisine, amplitude: 0.5, offset: 0.0, start: 0.0, frequency: 0.5, frequency_end: 20.0,
            lines: 40, phases: schroeder}
sensor: {encoder_resolution: 16384, velocity_noise: 0.02}   # a real encoder: intervals of real width
drive: {profile: odrive-0.6}
axes:
  - name: left
    drive: {node_id: 1}
  - name: right
    drive: {node_id: 2}
    plant: {inertia: 0.3}
    sensor: {seed: 7}
    reference: {kind: prbs, amplitude: 0.4, clock_period: 0.01, seed: 3}
"""


def _run(config: Path, log: Path, *more: str) -> int:
    return main(["run", str(config), "--emulate", "--log", str(log), *more])


@pytest.fixture(scope="module")
def lockstep_log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("axes-run") / "demo.mcap"
    assert _run(DEMO, path) == 0
    return path


def test_a_can_export_puts_each_sent_frame_on_its_bus_channel(lockstep_log: Path, tmp_path: Path) -> None:
    """The CLI names a bus ``socketcan:can0`` and its topics ``/bus/socketcan_can0/...``: a
    sent frame (recorded with no channel) is exported on that bus' channel, not candump's
    ``vcan0`` (a topic parsed by hand looked for ``bus/socketcan_can0`` and found none)."""
    log = open_log(lockstep_log)
    (channel,) = {log.metadata[f"bus/{bus}"]["channel"] for bus in layout(log).buses}
    out = tmp_path / "frames.log"
    assert main(["log", "export", str(lockstep_log), "--can", "--format", "candump", "-o", str(out)]) == 0
    sent = [m for m in can.LogReader(out) if not m.is_rx]
    assert sent and {m.channel for m in sent} == {channel}


def _messages(path: Path, topic: str) -> list[tuple[int, dict[str, Any]]]:
    return [(t, p) for _, t, p in open_log(path).iter_messages([topic])]


def test_the_demo_run_is_recorded_per_axis_on_the_simulated_clock(lockstep_log: Path) -> None:
    log = open_log(lockstep_log)
    lay = layout(log)
    assert lay.names == AXES and set(lay.bus_of.values()) == {"socketcan:can0"}
    assert [(c["a"], c["b"], c["stiffness"]) for c in lay.couplings] == [("left", "right", 5000.0)]
    assert log.metadata["run"]["log_clock"] == "simulated"
    for name in AXES:
        loop = _messages(lockstep_log, f"/axis/{name}/loop")
        assert len(loop) == 1200
        # the log clock is the simulated one: one period between cycles, exactly (to the ns)
        steps = {b[0] - a[0] for a, b in zip(loop, loop[1:])}
        assert steps == {1_000_000}
        truth = _messages(lockstep_log, f"/axis/{name}/emulator/truth")
        assert len(truth) == 1200
        events = [p for _, p in _messages(lockstep_log, f"/axis/{name}/events")]
        assert [e["reason"] for e in events][-1] == "drive disabled"
    right = axis_log(log, "right")
    assert right.config.plant.inertia == 0.3 and right.config.drive.node_id == 2
    assert json.loads(right.metadata["drive"]["node_id"]) == 2
    stop = [p for _, p in _messages(lockstep_log, "/events")]
    assert stop[-1]["reason"] == "done"


def test_the_coupled_demo_replays_bit_for_bit_on_both_axes(lockstep_log: Path,
                                                          capsys: pytest.CaptureFixture[str]) -> None:
    capsys.readouterr()
    assert main(["replay", str(lockstep_log), "--verify"]) == 0
    lines = capsys.readouterr().out.splitlines()[1:]
    assert [line.split(":")[0].strip() for line in lines] == [f"axis {a}" for a in AXES]
    assert all("1200 cycles, identical" in line and "bit for bit" in line for line in lines)


def test_a_changed_value_of_one_axis_fails_the_verify_naming_it(lockstep_log: Path, tmp_path: Path,
                                                              capsys: pytest.CaptureFixture[str]) -> None:
    """tau_int^ of one cycle of axis left one ulp off: left fails at that cycle, right does not."""
    bad = tmp_path / "altered.mcap"

    def change(topic: str, p: dict[str, Any]) -> dict[str, Any]:
        if topic == "/axis/left/controller" and p["cycle"] == 700:
            p["tau_int_hat"] = math.nextafter(p["tau_int_hat"], math.inf)
        return p
    _rewrite(lockstep_log, bad, change)
    capsys.readouterr()
    assert main(["replay", str(bad), "--verify"]) == 1
    out, err = capsys.readouterr()
    assert err.startswith("dobhil replay: verification failed on axis left: replay differs at cycle 700")
    lines = {line.split(":")[0].strip(): line for line in out.splitlines()[1:]}
    assert "identical" in lines["axis right"] and "differs at cycle 700" in lines["axis left"]


def test_a_sink_wired_to_the_wrong_axis_fails_the_verify(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                        capsys: pytest.CaptureFixture[str]) -> None:
    """The recorder's wiring is what the verify checks: right's cycles recorded into left's
    lanes (and left's into right's) replay against the other axis' config and frames."""
    from dobhil.cli import axes_run
    real = axes_run.log_hooks

    def crossed(log: Any) -> dict[str, Any]:
        hooks = real(log)
        if log is not None:
            sinks = hooks["sinks"]
            hooks["sinks"] = {"left": sinks["right"], "right": sinks["left"]}
        return hooks
    monkeypatch.setattr(axes_run, "log_hooks", crossed)
    path = tmp_path / "crossed.mcap"
    assert _run(DEMO, path) == 0
    capsys.readouterr()
    assert main(["replay", str(path), "--verify"]) == 1
    err = capsys.readouterr().err
    assert err.startswith("dobhil replay: verification failed on axes left, right (first: left): "
                          "replay differs at cycle ")


def test_a_real_time_coupled_run_is_logged_verified_and_reported_per_axis(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "rt.mcap"
    # on a busy machine the real-time run may end in a safety stop (exit 1): its log is
    # verified all the same, over the cycles it ran
    code = _run(DEMO, path, "--set", "loop.timing=feedback", "--summary-json")
    info = json.loads(capsys.readouterr().out)
    assert code == (0 if info["stop_reason"] == "done" else 1)
    assert info["timing"] == "feedback" and info["log"] == str(path)
    log = open_log(path)
    assert log.metadata["run"]["log_clock"] == "wall"
    assert [p["reason"] for _, p in _messages(path, "/events")][-1] == info["stop_reason"]
    cycles = {name: len(_messages(path, f"/axis/{name}/controller")) for name in AXES}
    # the writer is lossy in real time: at most the cycles the run counted, each replayed
    assert all(0 < cycles[name] <= info["axes"][name]["cycles"] for name in AXES)
    assert main(["replay", str(path), "--verify"]) == 0
    lines = capsys.readouterr().out.splitlines()[1:]
    assert all(f"{cycles[a]} cycles, identical" in line for a, line in zip(AXES, lines))
    assert main(["report", str(path), "--out", str(tmp_path / "report")]) == 0
    out = capsys.readouterr().out
    for name in AXES:
        assert f"axis {name}:" in out
        # a coupled axis' loop is the coupled one: no single-axis prediction, and not "unstable"
        assert f"analysis prediction: none (axis {name} is coupled to " in out, out
    assert "unstable" not in out, out
    assert "bus socketcan:can0 (axes left, right)" in out


def test_a_run_that_fails_before_its_loop_leaves_no_log(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A clash is refused before the log is opened; a session that fails after it was opened
    (a drive that cannot run feedback-timed, found when the session is built) leaves no file
    either (the writer creates it only when the run begins); one line, exit 2 each, and the
    same --log is free for the rerun."""
    path = tmp_path / "clash.mcap"
    assert _run(DEMO, path, "--set", "axes.right.drive.node_id=1") == 2
    err = capsys.readouterr().err
    assert "axes left" in err and "right" in err and "both use CAN id" in err, err
    assert len(err.strip().splitlines()) == 1 and not path.exists()
    assert _run(DEMO, path, "--set", "loop.timing=feedback", "--set", "axes.right.drive.profile=ak80-9") == 2
    err = capsys.readouterr().err
    assert "has no feedback_period" in err and len(err.strip().splitlines()) == 1, err
    assert not path.exists()
    assert _run(DEMO, path) == 0


@pytest.fixture(scope="module")
def torque_log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    directory = tmp_path_factory.mktemp("axes-identify")
    config = directory / "identify-axes.yaml"
    config.write_text(IDENTIFY)
    path = directory / "torque.mcap"
    assert _run(config, path) == 0
    return path


@pytest.mark.parametrize(("name", "inertia"), [("left", 0.25), ("right", 0.3)])
def test_identify_each_axis_of_a_several_axis_log(torque_log: Path, name: str, inertia: float, tmp_path: Path,
                                                  capsys: pytest.CaptureFixture[str]) -> None:
    capsys.readouterr()
    overlay = tmp_path / f"{name}.yaml"
    assert main(["identify", str(torque_log), "--axis", name, "--json", "--out", str(overlay)]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["axis"] == name and "note" not in info   # not coupled: nothing to say
    e = info["estimates"]["inertia"]
    assert e["identifiable"] and e["low"] <= inertia <= e["high"]
    # the other axis' inertia is outside this axis' interval: the fit read this axis' records
    other = 0.3 if inertia == 0.25 else 0.25
    assert not e["low"] <= other <= e["high"]
    # the overlay sets this axis' keys only, also over a key the axis sets itself (right's
    # plant.inertia): the other axis keeps its config's
    config = tmp_path / "identify-axes.yaml"
    config.write_text(IDENTIFY)
    axes = load_axes(config, set_files=[overlay])
    assert axes.axis(name).config.plant.inertia == e["value"]
    assert axes.axis(name).config.design.identified_inertia == e["value"]
    untouched = axes.axis("right" if name == "left" else "left").config
    assert untouched.plant.inertia == other and untouched.design.identified_inertia == 0.125
    assert read_identified(overlay, "--draw-from").keys[0] == "plant.inertia"   # what --axis NAME varies


def test_the_axes_log_records_each_uncoupled_axis_stability_gate(torque_log: Path) -> None:
    log = open_log(torque_log)
    for name in AXES:
        gate = log.metadata[f"axis/{name}/stability_gate"]
        assert json.loads(gate["allow_unstable"]) is False and json.loads(gate["overridden"]) is False
        assert dict(axis_log(log, name).metadata["stability_gate"]) == dict(gate)


def test_identify_without_an_axis_names_the_axes(torque_log: Path, capsys: pytest.CaptureFixture[str]) -> None:
    capsys.readouterr()
    assert main(["identify", str(torque_log)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "(left, right)" in err[0] and "--axis NAME" in err[0]
    assert main(["identify", str(torque_log), "--axis", "wrist"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no axis 'wrist'; axes: left, right" in err[0]


def test_identify_of_a_coupled_axis_says_what_its_environment_is(lockstep_log: Path,
                                                                capsys: pytest.CaptureFixture[str]) -> None:
    capsys.readouterr()
    assert main(["identify", str(lockstep_log), "--axis", "right"]) == 0
    out = capsys.readouterr().out
    assert "identified demo.mcap axis right" in out
    note = next(line for line in out.splitlines() if line.startswith("note: "))
    assert "coupled to left (K 5000 N m/rad, D 30 N m s/rad)" in note and "coupling plus" in note
    assert "method: open-loop" in out  # one axis' loop simulated alone would miss the coupling
    assert main(["identify", str(lockstep_log), "--axis", "right", "--method", "closed-loop"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "records several axes" in err[0]


def test_demo_of_an_axes_config_records_by_default(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    config = tmp_path / "demo2.yaml"
    shutil.copy(DEMO, config)
    out_dir = tmp_path / "out"
    assert main(["demo", str(config), "--out", str(out_dir), "--set", "loop.duration=0.2"]) == 0
    logs = sorted(out_dir.glob("run-*.mcap"))
    assert len(logs) == 1 and layout(open_log(logs[0])).names == AXES
    assert f"next: dobhil report {logs[0]}" in capsys.readouterr().out


@pytest.fixture(scope="module")
def short_log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("axes-short") / "short.mcap"
    assert _run(DEMO, path, "--set", "loop.duration=0.3", "--set", "reference.start=0.1") == 0
    return path


@settings(max_examples=6, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(axis=st.sampled_from(AXES), cycle=st.integers(0, 299),
       field=st.sampled_from(["u_sat", "u_unsat", "tau_int_hat", "tau_dis_hat"]))
def test_any_changed_controller_value_is_found_on_its_axis_and_cycle(short_log: Path, tmp_path: Path, axis: str,
                                                                     cycle: int, field: str) -> None:
    bad = tmp_path / f"{axis}-{cycle}-{field}.mcap"

    def change(topic: str, p: dict[str, Any]) -> dict[str, Any]:
        if topic == f"/axis/{axis}/controller" and p["cycle"] == cycle:
            p[field] = math.nextafter(p[field], math.inf)
        return p
    _rewrite(short_log, bad, change)
    found = {r.recording.axis: r.first_mismatch() for r in replay_axes(bad)}
    mismatch = found.pop(axis)
    assert mismatch is not None and mismatch.cycle == cycle
    assert all(m is None for m in found.values())
