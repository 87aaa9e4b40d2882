"""``loop.mode: torque`` (open loop, for identification): the emulated plant receives
exactly the reference (as the protocol carries it, saturated at the torque limit), every
safety of a force run stops it the same way, and replay reproduces it bit for bit."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from dobhil.cli.main import main
from dobhil.cli.recording import record_run
from dobhil.config import Config
from dobhil.emulator.faults import CorruptFeedback, SilenceAfter
from dobhil.recording.process import WriterProcess
from dobhil.recording.runlog import RunLog
from dobhil.replay import replay
from dobhil.runtime.controller import ControlOutput
from dobhil.runtime.session import RunSession
from dobhil.runtime.stop import StopReason

from .helpers import DEMO, demo_config
from .test_safety import ENCODER_ID, ODRIVE_PROFILE, Recorder, run_case, safety_config, stall

#: open loop, in contact from the start, a multisine torque well inside the 2 N m limits
TORQUE = ("loop.mode=torque", "plant.initial_position=0", "reference.kind=multisine",
          "reference.start=0", "reference.amplitude=1.5", "reference.offset=0.2",
          "reference.frequency=2",
          "reference.frequency_end=40", "reference.lines=20", "loop.duration=0.3")


class Outputs(Recorder):
    """Records every cycle's controller output too."""

    def __init__(self) -> None:
        super().__init__()
        self.outs: list[tuple[float, ControlOutput]] = []

    def cycle(self, k: int, t: float, fb: Any, out: ControlOutput, period_error: float,
              exec_time: float, overrun: bool) -> None:
        super().cycle(k, t, fb, out, period_error, exec_time, overrun)
        self.outs.append((t, out))


def lockstep_torque_run(config: Config) -> tuple[Outputs, list[float], Any]:
    """A lockstep run; what the controller computed and every torque the plant was stepped with."""
    sink = Outputs()
    seen: list[float] = []
    with RunSession(config, emulate=True, lockstep=True, sink=sink) as session:
        plant = session.plant
        assert plant is not None
        step = plant.step

        def spy(torque_nm: float, dt: float) -> None:
            seen.append(torque_nm)
            step(torque_nm, dt)

        plant.step = spy  # type: ignore[method-assign]
        result = session.run()
        reference = session.reference
    assert result.stop.reason is StopReason.DONE, result.stop.line()
    return sink, seen, reference


def _runs(values: list[float]) -> list[float]:
    """Consecutive equal values collapsed (the plant is stepped in pieces within a period)."""
    return [v for i, v in enumerate(values) if i == 0 or v != values[i - 1]]


def test_the_plant_receives_exactly_the_reference() -> None:
    sink, seen, reference = lockstep_torque_run(demo_config(*TORQUE))
    assert len(sink.outs) == 300
    assert len({out.u for _, out in sink.outs}) > 250   # a multisine: the command moves
    for t, out in sink.outs:   # the command is the reference, bit for bit; no force feedback
        r = reference.value(t)
        assert out.tau_ref == r and out.u_unsat == r and out.u == r and out.tau_per == 0.0
    # the ODrive protocol carries the torque as float32: the plant sees each command so rounded
    sent = [float(np.float32(out.u)) for _, out in sink.outs]
    # (the last command is not applied for a whole period: the run ends, the safe stop's
    # zero torque follows it)
    applied = _runs([x for x in seen if x != 0.0])
    expected = _runs(sent)[:-1]
    start = applied.index(sent[0])
    assert applied[start:start + len(expected)] == expected
    # the observers still run: in contact, the RTOb sees the spring the torque presses
    assert any(abs(out.tau_int_hat) > 0.1 for _, out in sink.outs)


def test_a_torque_beyond_the_limit_is_saturated_like_any_command() -> None:
    """A 3 N m prbs against the 2 N m limit: +-2 N m reach the plant, u_unsat says 3."""
    config = demo_config(*TORQUE, "reference.kind=prbs", "reference.amplitude=3",
                         "reference.offset=0", "reference.clock_period=0.01")
    sink, seen, _ = lockstep_torque_run(config)
    assert {out.u_unsat for _, out in sink.outs} == {3.0, -3.0}
    assert {out.u for _, out in sink.outs} == {2.0, -2.0}
    assert set(seen) <= {0.0, 2.0, -2.0} and {2.0, -2.0} <= set(seen)


def test_force_mode_is_still_the_force_loop() -> None:
    """The same config in force mode tracks the reference instead of applying it."""
    config = demo_config(*(o for o in TORQUE if o != "loop.mode=torque"))
    sink, _, reference = lockstep_torque_run(config)
    assert any(out.u != reference.value(t) for t, out in sink.outs)
    assert all(out.tau_per != 0.0 for _, out in sink.outs[1:])


# -- safeties: the checks of tests/runtime/test_safety.py on a torque run -------------

def torque_config(tmp_path: Path, timing: str, *overrides: str) -> Config:
    return safety_config(tmp_path, timing, "loop.mode=torque", *overrides)


@pytest.mark.parametrize("timing", ["lockstep", "realtime"])
def test_position_limit_stops_a_torque_run(tmp_path: Path, timing: str) -> None:
    """1 N m of torque into 1e4 N m/rad is 1e-4 rad: above a 5e-5 rad position limit."""
    run_case(torque_config(tmp_path, timing, "loop.position_max=5e-5"), timing,
             StopReason.POSITION_LIMIT, words=["outside", "5e-05"])


def test_velocity_limit_stops_a_torque_run(tmp_path: Path) -> None:
    run_case(torque_config(tmp_path, "lockstep", "loop.velocity_limit=0.002"), "lockstep",
             StopReason.VELOCITY_LIMIT, words=["|dq|", "0.002"])


def test_free_motion_torque_run_is_stopped_by_the_position_limit(tmp_path: Path) -> None:
    """No environment: a constant 1 N m accelerates the servo until it leaves the range."""
    out = run_case(torque_config(tmp_path, "lockstep", "environment.stiffness=0",
                                 "environment.damping=0", "loop.duration=2"), "lockstep",
                   StopReason.POSITION_LIMIT, words=["outside"])
    assert out.stop.cycle < 2000


def test_feedback_timeout_stops_a_torque_run(tmp_path: Path) -> None:
    run_case(torque_config(tmp_path, "lockstep"), "lockstep", StopReason.FEEDBACK_TIMEOUT,
             words=["no fresh feedback"], faults=[SilenceAfter(frames=100, ids={ENCODER_ID})])


def test_non_finite_feedback_stops_a_torque_run(tmp_path: Path) -> None:
    out = run_case(torque_config(tmp_path, "lockstep"), "lockstep", StopReason.NON_FINITE,
                   words=["non-finite feedback"],
                   faults=[CorruptFeedback.of_profile(ODRIVE_PROFILE, "position", value=math.nan, at=100)])
    assert all(math.isfinite(x) for x in out.sent.torques)


def test_watchdog_trip_stops_a_torque_run(tmp_path: Path) -> None:
    """The loop stalls for three drive watchdog periods: the drive trips, the run reports it
    and blames the host, whose commands stopped (host_too_slow)."""
    sink = Recorder(at=50)

    def arm(session: RunSession) -> None:
        sink.action = stall(session, "lockstep", 3 * session.profile.watchdog_timeout)

    out = run_case(torque_config(tmp_path, "lockstep"), "lockstep", StopReason.HOST_TOO_SLOW,
                   words=["watchdog", "WATCHDOG_TIMER_EXPIRED", "the host was late, not the drive"],
                   sink=sink, prepare=arm)
    assert out.watchdog_tripped


def test_stop_request_stops_a_torque_run(tmp_path: Path) -> None:
    from dobhil.runtime.loop import StopRequest
    request = StopRequest()
    sink = Recorder(at=50, action=lambda: request.set("test"))
    out = run_case(torque_config(tmp_path, "lockstep"), "lockstep", StopReason.SIGNAL,
                   sink=sink, stop_request=request)
    assert out.stop.cycle >= 50


# -- replay -------------------------------------------------------------------------

@pytest.fixture(scope="module")
def torque_log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A recorded lockstep torque run (a prbs pressing into the environment)."""
    path = tmp_path_factory.mktemp("torque") / "torque.mcap"
    config = demo_config(*TORQUE, "reference.kind=prbs", "reference.amplitude=0.5",
                         "reference.offset=0.3")
    log = RunLog(WriterProcess(path, fsync=False))
    with RunSession(config, emulate=True, lockstep=True, sink=log, bus_wrapper=log.wrap_bus) as session:
        assert record_run(session, log, DEMO).stop.reason is StopReason.DONE
    return path


def test_replay_verifies_a_torque_run_bit_for_bit(torque_log: Path,
                                                  capsys: pytest.CaptureFixture[str]) -> None:
    path = torque_log
    result = replay(path)
    assert result.config.loop.mode == "torque"
    assert result.first_mismatch() is None and result.recording.cycles == 300
    assert main(["replay", str(path), "--verify"]) == 0
    assert "bit for bit" in capsys.readouterr().out
    # the same log replayed as a force run is another controller: verification fails
    assert main(["replay", str(path), "--verify", "--set", "loop.mode=force"]) == 1


def test_the_report_of_a_torque_run_has_no_force_tracking(torque_log: Path) -> None:
    """The prbs's many jumps are torque levels, not force steps: no step metrics, no
    tracking error, no force-loop prediction; the text says why."""
    from dobhil.run_report import report, summary_text
    _, summary, predicted = report(torque_log)
    assert predicted is None and summary["steps"] == []
    assert summary["prediction"]["available"] is False
    assert "loop.mode = torque" in summary["prediction"]["why"]
    assert summary["tracking"]["rms_error_estimated"] is None
    assert summary["estimation"]["rms_error"] is not None   # the observers still ran
    assert "mode: torque (open loop" in summary_text(summary)


def test_the_report_figures_of_a_torque_run_say_open_loop(torque_log: Path, tmp_path: Path) -> None:
    """The figures name the reference a torque command (not a force reference) in a torque
    run, and the force run's names otherwise; the figures are written either way."""
    from dobhil.plotting.report_figures import labels, open_loop, report_figures
    from dobhil.run_report import report
    data, summary, predicted = report(torque_log)
    assert open_loop(data)
    names = labels(data)
    assert "torque command" in names["tau_ref"] and "open-loop" in names["force_title"]
    assert "= 0" in names["tau_per"]
    paths = report_figures(data, predicted, summary, tmp_path)
    assert all(p.is_file() and p.stat().st_size > 0 for p in paths)
    assert labels(_ForceRun(data))["tau_ref"] == "reference $\\tau^{ref}_{int}$"


class _ForceRun:
    """``data`` as a force run: its config with loop.mode force."""

    def __init__(self, data: object) -> None:
        import dataclasses
        config = data.config  # type: ignore[attr-defined]
        self.config = dataclasses.replace(config, loop=dataclasses.replace(config.loop, mode="force"))


def test_the_run_says_it_is_a_torque_run(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["run", "identify-contact", "--emulate", "--lockstep", "--duration", "0.2"]) == 0
    first = capsys.readouterr().out.splitlines()[0]
    assert first.startswith("200 cycles (lockstep, torque mode (open loop), T = 0.001 s"), first
    assert main(["run", "identify-contact", "--emulate", "--lockstep", "--duration", "0.05",
                 "--summary-json"]) == 0
    assert json.loads(capsys.readouterr().out)["mode"] == "torque"


# -- bad keys -------------------------------------------------------------------------

@pytest.mark.parametrize(("override", "words"), [
    ("loop.mode=position", ["loop.mode", "force", "torque"]),
    ("reference.kind=noise", ["reference.kind", "prbs", "multisine"]),
    ("reference.phases=zero", ["reference.phases", "schroeder", "random"]),
    ("reference.lines=0", ["reference.lines", "> 0"]),
    ("reference.clock_period=-1", ["reference.clock_period", "> 0"]),
    ("reference.seed=-3", ["reference.seed", ">= 0"]),
    ("reference.frequency_end=0.5", ["reference.frequency_end", "band"]),
])
def test_bad_excitation_keys_are_one_line_exit_2(override: str, words: list[str],
                                                 capsys: pytest.CaptureFixture[str]) -> None:
    args = ["run", str(DEMO), "--emulate", "--set", "reference.kind=multisine", "--set", override]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err, err
    for word in words:
        assert word in err, (word, err)


# -- the shipped excitation configs -------------------------------------------------

class Contact(Recorder):
    """Whether the emulated servo was in contact at each cycle, and the largest |q|."""

    def __init__(self) -> None:
        super().__init__()
        self.plant: Any = None
        self.contact: list[bool] = []
        self.q_max = 0.0

    def cycle(self, k: int, t: float, fb: Any, out: ControlOutput, period_error: float,
              exec_time: float, overrun: bool) -> None:
        super().cycle(k, t, fb, out, period_error, exec_time, overrun)
        self.contact.append(bool(self.plant.in_contact))
        self.q_max = max(self.q_max, abs(fb.position))


@pytest.mark.parametrize("name", ["identify-free", "identify-contact"])
def test_the_shipped_excitation_runs_last_their_duration(name: str) -> None:
    """identify-free never touches anything and stays well inside its position limits;
    identify-contact never leaves the contact (its torque never drops below 0.5 N m)."""
    from dobhil.config import load_config
    config = load_config(name)
    assert config.loop.mode == "torque"
    sink = Contact()
    with RunSession(config, emulate=True, lockstep=True, sink=sink) as session:
        sink.plant = session.plant
        result = session.run()
    assert result.stop.reason is StopReason.DONE, result.stop.line()
    assert len(sink.contact) == round(config.loop.duration / config.loop.period)
    if name == "identify-free":
        assert config.environment.stiffness == 0.0 and not any(sink.contact)
        assert sink.q_max < 0.5 * config.loop.position_max
    else:
        assert all(sink.contact)
        assert sink.q_max < 0.1 * config.loop.position_max
