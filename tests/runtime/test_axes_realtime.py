"""Safety across axes in real time, every node of the bus emulated in the emulator
process (:class:`~dobhil.emulator.process.EmulatorProcess`), host and feedback timing:
one axis' fault stops every axis, each stop attempted and confirmed on its own (per
protocol, two nodes of one protocol on one bus); SIGINT to a two-axis ``dobhil run
--emulate`` stops both, confirmed, with one stop line and the single-axis exit code.
Bounds come from what each run measured or configured, never from the wall clock."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest
import yaml

from dobhil.cli.common import EXIT_STOPPED
from dobhil.drives.odrive import codec
from dobhil.drives.odrive.codec import CmdId, Firmware
from dobhil.emulator.faults import Fault, InjectFrame, faulty
from dobhil.emulator.process import EmulatorProcess
from dobhil.runtime.axes_loop import AxesResult
from dobhil.runtime.axes_session import AxesSession
from dobhil.runtime.stop import StopReason

from .axes_helpers import CONFIGS, assert_all_stopped, load_two, two_axis_config
from .helpers import DRIVERS, REPO, wait_until
from .test_axes_safety import HealOnStop, LoseNode, _motion_ids, _node

#: (protocol, timing): feedback timing needs drives that stream (MIT and moteus answer
#: each command and stream nothing: host timing only)
CASES = [("odrive", "host"), ("odrive", "feedback"), ("cia402", "host"), ("cia402", "feedback"),
         ("mit", "host"), ("moteus", "host")]
#: room for a loaded 2-core machine: the emulator process or the loop unscheduled for tens
#: of ms is not the fault under test
TIMEOUT = 0.2
DURATION = 1.0
AT = 100   # the fault strikes at the 100th matching frame (about 0.1 s into the run)


def _relaxed(tmp_path: Path, proto: str) -> list[str]:
    """ODrive axes on the shipped profile with only its watchdog and enable wait relaxed
    (as helpers.realtime_profile: a scheduling hiccup of a loaded machine is not the fault
    under test)."""
    if proto != "odrive":
        return []
    # realtime_profile's copy, its bus section kept (an emulated run names the drive's bus)
    data = yaml.safe_load((DRIVERS / "odrive-0.6.yaml").read_text(encoding="utf-8"))
    data.update(watchdog_timeout=0.25, enable_timeout=2.0)
    profile = tmp_path / "odrive-0.6-relaxed.yaml"
    profile.write_text(yaml.safe_dump(data), encoding="utf-8")
    return [f"axes.{name}.drive.profile={profile}" for name in ("left", "right")]


def _run(tmp_path: Path, proto: str, timing: str, fault: Fault, sink_fault: LoseNode | None,
         *overrides: str) -> tuple[Any, AxesResult, list[float], list[bool]]:
    """A real-time two-axis run with ``fault`` on the host's side of the bus; each node's
    applied torque and whether it settled at zero after the stop (the child's newest tick)."""
    axes = load_two(tmp_path, (proto, proto), f"loop.timing={timing}", f"loop.feedback_timeout={TIMEOUT}",
                    f"loop.duration={DURATION}", *_relaxed(tmp_path, proto), *overrides)
    sinks = {"left": HealOnStop(sink_fault)} if sink_fault is not None else {}
    with AxesSession(axes, emulate=True, lockstep=False, config_dir=CONFIGS, sinks=sinks,
                     bus_wrapper=lambda bus, name: faulty(fault)(bus)) as session:
        result = session.run()
        assert session.timing.label == timing
        processes = [e for e in session.emulators if isinstance(e, EmulatorProcess)]
        assert len(processes) == 1   # one child hosts both nodes of the bus
        nodes = [processes[0].node(name) for name in ("left", "right")]
        # the child handles the safe-stop frames on its own clock: wait for its newest tick
        settled = [wait_until(lambda n=n: n.applied_torque == 0.0) for n in nodes]
        applied = [n.applied_torque for n in nodes]
    return axes, result, applied, settled


def _check_stopped_together(axes: Any, result: AxesResult, applied: list[float], settled: list[bool]) -> None:
    line = result.stop.line()
    assert result.axis == "left" and "axis left" in line and "\n" not in line, line
    # it stopped before its end, and no axis ran a cycle the other did not
    assert result.cycles + result.skipped < DURATION / axes.period, line
    assert result.axes["right"].cycles == result.axes["left"].cycles == result.cycles
    confirmable = {n: _node(axes, CONFIGS, n)[2] for n in ("left", "right")}
    assert_all_stopped(result, confirmable=confirmable)
    assert all(settled) and applied == [0.0, 0.0], applied   # both nodes hold no torque
    warned = result.warning()
    assert all((f"axis {n}" in warned) != ok for n, ok in confirmable.items()), warned


@pytest.mark.parametrize(("proto", "timing"), CASES)
def test_feedback_loss_of_one_axis_stops_both(tmp_path: Path, proto: str, timing: str) -> None:
    for attempt in range(2):
        path = tmp_path / str(attempt)
        path.mkdir()
        axes = load_two(path, (proto, proto))
        _, byte0, _ = _node(axes, CONFIGS, "left")
        # lost until the run stops (then heard again: its safe stop is confirmed)
        lost = LoseNode(_motion_ids(axes, "left"), at=AT, byte0=byte0)
        axes, result, applied, settled = _run(path, proto, timing, lost, lost)
        # a machine so loaded that the host was to blame (the emulator process starved,
        # or the drive's watch on the host expired) before the loss: once more
        if result.stop.reason is not StopReason.HOST_TOO_SLOW:
            break
    line = result.stop.line()
    assert lost.applied > 0, line
    assert result.stop.reason is StopReason.FEEDBACK_TIMEOUT, line
    # the silence lasted the feedback timeout: the stop came at least that long after
    # the run's first cycle
    assert result.stop.time >= TIMEOUT, line
    _check_stopped_together(axes, result, applied, settled)


@pytest.mark.parametrize("timing", ("host", "feedback"))
def test_a_drive_fault_of_one_axis_stops_both(tmp_path: Path, timing: str) -> None:
    """The left ODrive faults on its own (an Estop reaches it, the emulated drive drops
    to IDLE with ESTOP_REQUESTED): the run stops as a drive fault of axis left, and the
    right one, which did not fault, is stopped and confirmed too."""
    fw = Firmware.V0_6
    left_torque = codec.arbitration_id(1, CmdId.SET_INPUT_TORQUE)
    estop = InjectFrame(codec.encode(codec.Estop(), node_id=1, firmware=fw), after=AT, ids={left_torque})
    for attempt in range(2):
        path = tmp_path / str(attempt)
        path.mkdir()
        axes, result, applied, settled = _run(path, "odrive", timing, estop, None)
        if result.stop.reason is not StopReason.HOST_TOO_SLOW:
            break
        estop = InjectFrame(codec.encode(codec.Estop(), node_id=1, firmware=fw), after=AT, ids={left_torque})
    line = result.stop.line()
    assert estop.applied == 1, line
    assert result.stop.reason is StopReason.DRIVE_FAULT and "ESTOP_REQUESTED" in line, line
    _check_stopped_together(axes, result, applied, settled)


# -- SIGINT to `dobhil run` ------------------------------------------------------------


def _children(pid: int) -> list[int]:
    try:
        text = Path(f"/proc/{pid}/task/{pid}/children").read_text(encoding="ascii")
    except OSError:
        return []
    return [int(x) for x in text.split()]


#: a run's text summary starts "N cycles (": absent when nothing ran (the stop line only)
CYCLES_LINE = re.compile(r"^\d+ cycles \(", re.MULTILINE)


def _nothing_ran(out: str, err: str, summary_json: bool) -> bool:
    """The signal came before the loop's first cycle (the start-up path, tested elsewhere):
    ``"cycles": 0`` in the JSON summary, no cycles line in the text one."""
    return '"cycles": 0,' in out if summary_json else CYCLES_LINE.search(out) is None


def _interrupted_run(config: Path, timing: str, *extra: str) -> tuple[int, str, str]:
    """``dobhil run CONFIG --emulate`` in real time, SIGINT once its emulator process runs
    and it had time to enable (a long duration: the signal, not the end, stops it). Once
    more, waiting longer, when a loaded machine was too slow: the host too late for the
    drive before the signal, or the signal still during the enable. The wait after the
    emulator appeared is as long as the run took to start it, times 2, 6, 15: on a loaded
    machine the enable is slow in the same proportion as the start."""
    for factor in (2.0, 6.0, 15.0):
        code, out, err = _interrupted_once(config, timing, factor, *extra)
        text = out + err
        if not ("host_too_slow" in text or "waiting for node" in text
                or _nothing_ran(out, err, "--summary-json" in extra)):
            break
    return code, out, err


def _interrupted_once(config: Path, timing: str, factor: float, *extra: str) -> tuple[int, str, str]:
    cmd = [sys.executable, "-m", "dobhil", "run", str(config), "--emulate", "--set", f"loop.timing={timing}",
           "--set", f"loop.feedback_timeout={TIMEOUT}", "--duration", "60", *extra]
    begin = time.monotonic()
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, cwd=REPO,
                            env={**os.environ, "PYTHONUNBUFFERED": "1"})
    try:
        assert wait_until(lambda: bool(_children(proc.pid)) or proc.poll() is not None, timeout=60)
        assert proc.poll() is None, proc.communicate()
        started = time.monotonic() - begin   # interpreter, imports, emulator: this machine now
        # the loop enables and starts within a few start-ups; the checks below say whether
        # cycles ran (a signal before them is the start-up path, tested elsewhere)
        wait_until(lambda: proc.poll() is not None, timeout=max(1.0, factor * started))
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    return proc.returncode, out.decode(), err.decode()


def _sets(overrides: list[str]) -> list[str]:
    return [arg for o in overrides for arg in ("--set", o)]


@pytest.mark.parametrize("timing", ("feedback", "host"))
def test_sigint_stops_both_axes_confirmed(tmp_path: Path, timing: str) -> None:
    config = two_axis_config(tmp_path, ("odrive", "odrive"))
    code, out, err = _interrupted_run(config, timing, "--summary-json", *_sets(_relaxed(tmp_path, "odrive")))
    info = json.loads(out)
    assert info["stop_reason"] == "signal" and "SIGINT" in info["stop_detail"], info["stop_detail"]
    assert info["stop_axis"] == "" and info["cycles"] > 0, info
    assert info["timing"] == timing
    assert info["drives_disabled"] and info["not_disabled"] == [], info
    for name, axis in info["axes"].items():
        assert axis["drive_disabled"] and axis["safe_stop"]["confirmation"] == "confirmed", (name, axis)
        assert [f["what"] for f in axis["safe_stop"]["frames"]][0] == "zero torque", (name, axis)
        assert all(f["sent"] for f in axis["safe_stop"]["frames"]), (name, axis)
        assert axis["cycles"] == info["cycles"], name
    assert "WARNING" not in err and "Traceback" not in err, err
    assert code == EXIT_STOPPED


def test_sigint_is_one_stop_line_and_the_single_axis_exit_code(tmp_path: Path) -> None:
    config = two_axis_config(tmp_path, ("odrive", "odrive"))
    relaxed = _relaxed(tmp_path, "odrive")
    code, out, err = _interrupted_run(config, "feedback", *_sets(relaxed))
    lines = (out + err).splitlines()
    stops = [line for line in lines if line.startswith("stopped:") or ": stopped:" in line]
    assert len(stops) == 1 and stops[0].startswith("stopped: signal") and "SIGINT" in stops[0], lines
    assert "axis" not in stops[0]   # the signal is the run's, no axis' fault
    assert not [line for line in lines if "WARNING" in line or "Traceback" in line], lines
    single = relaxed[0].split("=", 1)[1]
    single_code, single_out, _ = _interrupted_run(REPO / "configs/demo.yaml", "feedback",
                                                  "--set", f"drive.profile={single}")
    assert "stopped: signal" in single_out, single_out
    assert code == single_code == EXIT_STOPPED, (code, single_code)


@pytest.mark.parametrize("timing", ["feedback", "host"])
def test_a_silence_while_the_host_was_stopped_is_timed_from_its_return(tmp_path: Path, timing: str) -> None:
    """Two ODrive axes, no drive watchdog: the loop's thread stalls after cycle 100 for the
    feedback timeout and 0.1 s, and what the drives sent meanwhile reaches it 0.1 s after it
    goes on (a hub forwarding late). Each axis' feedback timeout counts from the host's
    return (Drive.since_back): the frames come, the run ends done."""
    from .test_blame import STARVED_RUNS, LateBus
    from .test_safety import Recorder

    data = yaml.safe_load((DRIVERS / "odrive-0.6.yaml").read_text(encoding="utf-8"))
    data.update(watchdog_timeout=0.0, enable_timeout=2.0)
    profile = tmp_path / "odrive-0.6-unwatched.yaml"
    profile.write_text(yaml.safe_dump(data), encoding="utf-8")
    axes = load_two(tmp_path, ("odrive", "odrive"), f"loop.timing={timing}", f"loop.feedback_timeout={TIMEOUT}",
                    f"loop.duration={DURATION}",
                    *[f"axes.{name}.drive.profile={profile}" for name in ("left", "right")])
    stall = TIMEOUT + 0.1
    for _ in range(STARVED_RUNS):   # a run the machine starved says so (host_too_slow): again
        buses: list[LateBus] = []

        def wrap(bus: Any, _name: str, buses: list[LateBus] = buses) -> Any:
            buses.append(LateBus(bus))
            return buses[-1]

        def stalled(buses: list[LateBus] = buses) -> None:
            for bus in buses:
                bus.held_until = time.perf_counter() + stall + 0.1
            time.sleep(stall)

        sink = Recorder(at=100, action=stalled)
        with AxesSession(axes, emulate=True, lockstep=False, config_dir=CONFIGS, sinks={"left": sink},
                         bus_wrapper=wrap) as session:
            result = session.run()
        if result.stop.reason is not StopReason.HOST_TOO_SLOW:
            break
    assert sink.fired_at >= 0 and buses
    assert result.stop.reason is StopReason.DONE, result.stop.line()
