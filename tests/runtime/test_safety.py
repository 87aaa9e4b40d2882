"""Every way a run can end ends safely: for each stop cause, in lockstep and in real time
where it means something, the run says why in one line, the last torque command on the
bus is 0.0 N m, Set_Axis_State(IDLE) was sent last, the emulated drive ends IDLE with
zero torque, and no thread or bus is left open (``tests/conftest.py``).

Faults come from :mod:`dobhil.emulator.faults` (host-side bus wrappers); frames are
sniffed by an extra ``virtual`` bus on the session's private channel.
"""

from __future__ import annotations

import dataclasses
import math
import os
import re
import signal
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path

import can
import numpy as np
import pytest

from dobhil.config import Config
from dobhil.drives.base import Confirmation, Feedback
from dobhil.drives.odrive import codec
from dobhil.drives.odrive.codec import AxisState, CmdId, Firmware
from dobhil.drives.load import load_profile
from dobhil.emulator.faults import (CorruptFeedback, DropFrames, Fault, InjectFrame,
                                   SilenceAfter, faulty)
from dobhil.drives.odrive.emulator import EmulatedODrive
from dobhil.emulator.plant import Plant
from dobhil.drives.emulated import LockstepBus
from dobhil.runtime.controller import ControlOutput
from dobhil.runtime.loop import RunResult, StopRequest
from dobhil.runtime.session import RunSession, summary
from dobhil.runtime.signals import stop_on_signals
from dobhil.runtime.stop import Stop, StopReason

from .helpers import (NODE, REALTIME_SLACK, STEP_FROM_ZERO, HostCommands, Sniffer,
                      assert_stopped_safely, demo_config, realtime_profile, wait_until)

TIMINGS = ("lockstep", "realtime")
ENCODER_ID = codec.arbitration_id(NODE, CmdId.GET_ENCODER_ESTIMATES)
#: the drive these tests run, for faults laid out by its protocol
ODRIVE_PROFILE = dataclasses.replace(load_profile("odrive-0.6"), node_id=NODE)
TORQUE_ID = codec.arbitration_id(NODE, CmdId.SET_INPUT_TORQUE)


# -- rig ----------------------------------------------------------------------------

def safety_config(tmp_path: Path, timing: str, *overrides: str,
                  firmware: str = "odrive-0.6") -> Config:
    """The analysed loop (contact from the start, 1 N m step), 0.4 s."""
    base = (*STEP_FROM_ZERO, "loop.duration=0.4")
    if timing == "lockstep":
        return demo_config(f"drive.profile={firmware}", *base, *overrides)
    profile = realtime_profile(tmp_path, firmware)
    return demo_config(f"drive.profile={profile}", *base, *REALTIME_SLACK, *overrides)


@dataclass
class Recorder:
    """A cycle sink recording the stop; the first cycle index >= ``at`` triggers
    ``action`` once (real time skips the indices of deadlines missed after an overrun)."""

    at: int = -1
    action: Callable[[], None] | None = None
    stops: list[Stop] = field(default_factory=list)
    cycles: int = 0
    fired_at: int = -1
    started_with: Feedback | None = None

    def started(self, fb: Feedback) -> None:
        self.started_with = fb

    def cycle(self, k: int, t: float, fb: Feedback, out: ControlOutput, period_error: float,
              exec_time: float, overrun: bool) -> None:
        self.cycles += 1
        if 0 <= self.at <= k and self.fired_at < 0 and self.action is not None:
            self.fired_at = k
            self.action()

    def stop(self, stop: Stop) -> None:
        self.stops.append(stop)


@dataclass
class Outcome:
    stop: Stop
    result: RunResult | None
    sent: HostCommands
    summary: dict[str, object] | None
    watchdog_tripped: bool


def run_case(config: Config, timing: str, reason: StopReason, *, words: Iterable[str] = (),
             faults: Iterable[Fault] = (), sink: Recorder | None = None,
             stop_request: StopRequest | None = None,
             prepare: Callable[[RunSession], None] | None = None,
             raises: type[BaseException] | None = None, confirmed: bool = True) -> Outcome:
    """Run with the emulator, check the safe stop inside the session, return what happened."""
    sink = sink or Recorder()
    faults = tuple(faults)
    with RunSession(config, emulate=True, lockstep=timing == "lockstep", sink=sink,
                    stop_request=stop_request,
                    bus_wrapper=faulty(*faults) if faults else None) as session, \
            Sniffer(session.bus_spec.channel) as sniffer:
        if prepare is not None:
            prepare(session)
        result: RunResult | None = None
        if raises is None:
            result = session.run()
            stop = result.stop
            assert result.disabled is confirmed
            assert sink.stops == [stop]
        else:
            with pytest.raises(raises):
                session.run()
            assert len(sink.stops) == 1
            stop = sink.stops[0]
        sent = assert_stopped_safely(session, sniffer, stop, reason, words=words)
        tripped = bool(getattr(session.emulator, "watchdog_tripped", False))
        info = summary(session, result) if result is not None else None
    return Outcome(stop, result, sent, info, tripped)


# -- done, limits, non-finite ------------------------------------------------------------

# test_done (a run that lasts its duration stops safely): one test over every protocol in
# tests/drives/test_drive_suite.py::test_run_that_lasts_its_duration_stops_safely


@pytest.mark.parametrize("timing", TIMINGS)
def test_feedback_timeout_when_the_drive_goes_silent(tmp_path: Path, timing: str) -> None:
    """The drive stops sending encoder estimates after 100 frames: feedback timeout."""
    sink = Recorder()
    out = run_case(safety_config(tmp_path, timing), timing, StopReason.FEEDBACK_TIMEOUT,
                   words=["no fresh feedback"], faults=[SilenceAfter(frames=100, ids={ENCODER_ID})],
                   sink=sink)
    # frames read before the first cycle count too (the run measured how many: the first
    # feedback's sequence number; real time: the drive streams while the host starts up),
    # and cycle k is the drive's k-th frame after it, skipped frames included
    assert sink.started_with is not None
    before = sink.started_with.seq
    assert 0 < before < 100
    assert out.stop.cycle == 100 - before
    if timing == "lockstep":   # the wait for the 101st frame is simulated: same cycle
        assert before <= 10


@pytest.mark.parametrize("timing", TIMINGS)
def test_lost_heartbeat_is_a_drive_fault(tmp_path: Path, timing: str) -> None:
    """Encoder frames keep coming but the heartbeats stop: after three missed heartbeat
    periods the host calls it a drive fault (the drive's state is no longer known). The
    safe-stop frames go out, but nothing confirms the drive left torque control: the
    result says so, with the loud line."""
    heartbeat = codec.arbitration_id(NODE, CmdId.HEARTBEAT)
    out = run_case(safety_config(tmp_path, timing), timing, StopReason.DRIVE_FAULT,
                   words=["no heartbeat from node"], faults=[SilenceAfter(frames=1, ids={heartbeat})],
                   confirmed=False)
    assert out.stop.cycle < 400   # before the run was up (the drive's count, not the host's clock)
    assert out.result is not None and out.result.safe_stop is not None
    assert out.result.safe_stop.warning() == ("drive may still be enabled: node 3 did not "
                                              "acknowledge IDLE (no status frame within 0.3 s); "
                                              "cut power")


@pytest.mark.parametrize("timing", TIMINGS)
def test_position_limit(tmp_path: Path, timing: str) -> None:
    """1 N m into 1e4 N m/rad is 1e-4 rad: above a 5e-5 rad position limit."""
    run_case(safety_config(tmp_path, timing, "loop.position_max=5e-5"), timing,
             StopReason.POSITION_LIMIT, words=["outside", "5e-05"])


@pytest.mark.parametrize("timing", TIMINGS)
def test_velocity_limit(tmp_path: Path, timing: str) -> None:
    """The force step moves the servo faster than a 2 mrad/s velocity limit."""
    run_case(safety_config(tmp_path, timing, "loop.velocity_limit=0.002"), timing,
             StopReason.VELOCITY_LIMIT, words=["|dq|", "0.002"])


@pytest.mark.parametrize("timing", TIMINGS)
@pytest.mark.parametrize(("field_name", "value"), [("position", math.nan), ("velocity", math.inf)])
def test_non_finite_feedback(tmp_path: Path, timing: str, field_name: str, value: float) -> None:
    """A NaN position (or infinite velocity) from the 100th encoder frame on stops the
    run before anything is computed from it. (Lockstep reads every frame, so one bad
    frame is enough there; real time uses the newest of the frames queued in a cycle, so
    a bad frame superseded before the cycle reads it is harmless -- the sensor stays bad.)"""
    count = 1 if timing == "lockstep" else 1_000_000
    out = run_case(safety_config(tmp_path, timing), timing, StopReason.NON_FINITE,
                   words=["non-finite feedback"],
                   faults=[CorruptFeedback.of_profile(ODRIVE_PROFILE, field_name, value=value, at=100,
                                                  count=count)])
    assert math.isfinite(max(abs(x) for x in out.sent.torques))


class BadReference:
    """A reference that becomes ``value`` (NaN, inf) from ``after`` seconds."""

    def __init__(self, after: float, value: float) -> None:
        self.after = after
        self.bad = value

    def value(self, t: float) -> float:
        return self.bad if t >= self.after else 1.0


@pytest.mark.parametrize("timing", TIMINGS)
@pytest.mark.parametrize("value", [math.nan, math.inf, -math.inf])
def test_non_finite_reference(tmp_path: Path, timing: str, value: float) -> None:
    """A non-finite reference never reaches the drive: the CSV reader already refuses
    one, so a Python reference object is put into the session."""
    def use_bad_reference(session: RunSession) -> None:
        session.reference = BadReference(0.05, value)

    out = run_case(safety_config(tmp_path, timing), timing, StopReason.NON_FINITE,
                   words=["non-finite command"], prepare=use_bad_reference)
    assert all(math.isfinite(x) for x in out.sent.torques)


# -- drive faults -------------------------------------------------------------------

#: [s] how long a real-time stall may wait for the drive's watchdog: a bound for a loaded
#: machine, not a measurement
WATCH_BOUND = 30.0


def stall(session: RunSession, timing: str, seconds: float, took: list[float] | None = None) -> Callable[[], None]:
    """The host loop stops commanding: for ``seconds`` of simulated time (the lockstep bus
    steps the emulator without commands), or in real time until the emulated drive's
    watchdog tripped (the loop thread blocks); ``took`` (if given) gets how long it stalled."""
    took = [] if took is None else took

    def lockstep_stall() -> None:
        bus = session.host_bus
        assert isinstance(bus, LockstepBus)
        for _ in range(round(seconds / session.settings.period)):
            bus.step()
        took.append(seconds)

    def realtime_stall() -> None:
        emulator = session.emulator
        begin = time.perf_counter()
        wait_until(lambda: bool(getattr(emulator, "watchdog_tripped", False)), WATCH_BOUND)
        took.append(time.perf_counter() - begin)

    return lockstep_stall if timing == "lockstep" else realtime_stall


@pytest.mark.parametrize("timing", TIMINGS)
@pytest.mark.parametrize("firmware", ["odrive-0.6", "odrive-0.5"])
def test_watchdog_trip_is_reported(tmp_path: Path, timing: str, firmware: str) -> None:
    """A loop that stalls longer than the drive watchdog: the emulated drive trips it,
    drops to IDLE, and the run REPORTS it, naming the watchdog -- and blames the host,
    whose commands stopped (host_too_slow, with the gap it measured: on the simulated
    clock in lockstep, where the stall is simulated time; tests/runtime/test_blame.py
    has every protocol, and the same expiry with the host on time)."""
    config = safety_config(tmp_path, timing, firmware=firmware)
    sink = Recorder(at=50)
    stalled: list[float] = []

    def arm(session: RunSession) -> None:
        sink.action = stall(session, timing, 3 * session.profile.watchdog_timeout, stalled)

    out = run_case(config, timing, StopReason.HOST_TOO_SLOW,
                   words=["watchdog", "WATCHDOG_TIMER_EXPIRED", "the host was late, not the drive"],
                   sink=sink, prepare=arm)
    assert out.watchdog_tripped
    assert out.summary is not None and out.summary["watchdog_tripped"] is True
    assert out.summary["stop_reason"] == "host_too_slow"
    found = re.search(r"no command from the host for (\d+) ms", out.stop.detail)
    assert found is not None, out.stop.detail
    gap_ms, stall_ms = int(found.group(1)), stalled[0] * 1e3
    assert gap_ms >= math.floor(stall_ms), out.stop.detail   # it spans the stall
    if timing == "lockstep":   # simulated: the stall and the cycle around it, nothing else
        assert gap_ms <= stall_ms + 2 * config.loop.period * 1e3, out.stop.detail


@pytest.mark.parametrize("timing", TIMINGS)
@pytest.mark.parametrize("firmware", ["odrive-0.6", "odrive-0.5"])
def test_estop_is_a_drive_fault(tmp_path: Path, timing: str, firmware: str) -> None:
    """An Estop frame on the bus (injected after the 100th torque command): the drive
    goes IDLE with ESTOP_REQUESTED and the run stops on drive_fault."""
    config = safety_config(tmp_path, timing, firmware=firmware)
    fw = Firmware.parse(firmware.removeprefix("odrive-"))
    estop = codec.encode(codec.Estop(), node_id=NODE, firmware=fw)
    out = run_case(config, timing, StopReason.DRIVE_FAULT, words=["fault", "IDLE"],
                   faults=[InjectFrame(estop, after=100, ids={TORQUE_ID})])
    assert out.sent.estops == 1
    assert not out.watchdog_tripped


# -- stop requests and signals -----------------------------------------------------------

def test_stop_request_in_lockstep() -> None:
    """Lockstep: a stop request set from a sink after 100 cycles stops the next cycle."""
    request = StopRequest()
    sink = Recorder(at=99, action=lambda: request.set("operator stop"))
    out = run_case(safety_config(Path(), "lockstep", "loop.duration=5"), "lockstep",
                   StopReason.SIGNAL, words=["operator stop"], sink=sink, stop_request=request)
    assert out.stop.cycle == 100


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_signal_in_real_time(tmp_path: Path, signum: signal.Signals) -> None:
    """Real time: SIGINT / SIGTERM from another thread while ``stop_on_signals`` routes
    them in the main thread: the loop stops within a cycle, safely."""
    assert threading.current_thread() is threading.main_thread()
    config = safety_config(tmp_path, "realtime", "loop.duration=30")
    timer = threading.Timer(0.3, os.kill, (os.getpid(), signum))
    with stop_on_signals(StopRequest()) as request:
        def arm(_session: RunSession) -> None:
            timer.start()
        try:
            out = run_case(config, "realtime", StopReason.SIGNAL,
                           words=[f"received {signum.name}"], stop_request=request, prepare=arm)
        finally:
            timer.join()   # the signal arrives while the handler is installed
    assert out.stop.time < 30


# -- exceptions -----------------------------------------------------------------------

class SinkFailure(RuntimeError):
    pass


def fail() -> None:
    raise SinkFailure("recorder broke")


@pytest.mark.parametrize("timing", TIMINGS)
def test_exception_in_a_sink_is_reraised_after_the_safe_stop(tmp_path: Path, timing: str) -> None:
    """An exception in the loop (here the sink) stops safely, then reaches the caller."""
    out = run_case(safety_config(tmp_path, timing), timing, StopReason.EXCEPTION,
                   words=["SinkFailure", "recorder broke"], sink=Recorder(at=50, action=fail),
                   raises=SinkFailure)
    assert out.stop.cycle >= 51 if timing == "realtime" else out.stop.cycle == 51


class FailingReference:
    def value(self, t: float) -> float:
        if t >= 0.05:
            raise ZeroDivisionError("reference table ran out")
        return 1.0


@pytest.mark.parametrize("timing", TIMINGS)
def test_exception_in_the_reference(tmp_path: Path, timing: str) -> None:
    """A reference that raises: safe stop, exception re-raised."""
    def use(session: RunSession) -> None:
        session.reference = FailingReference()

    run_case(safety_config(tmp_path, timing), timing, StopReason.EXCEPTION,
             words=["ZeroDivisionError"], prepare=use, raises=ZeroDivisionError)


# -- enable failed ---------------------------------------------------------------------

def test_enable_failed_lockstep_drive_never_answers() -> None:
    """Lockstep: every frame from the drive is lost, so the enable handshake is never
    confirmed (the profile's 1 s, simulated): enable_failed, and the disable is still sent.
    The drive got CLOSED_LOOP_CONTROL and may have taken it: not confirmed disabled, loud."""
    config = safety_config(Path(), "lockstep")
    out = run_case(config, "lockstep", StopReason.ENABLE_FAILED, confirmed=False,
                   words=["no heartbeat from node 3"], faults=[SilenceAfter(frames=0)])
    assert out.result is not None and out.result.cycles == 0
    assert out.summary is not None and out.summary["safe_stop"]["confirmation"] == "never_answered"
    assert str(out.summary["drive_warning"]).startswith("drive may still be enabled: node 3 never answered: ")


def enable_failed_realtime(config: Config, channel: str) -> tuple[Stop, HostCommands, RunSession]:
    # the enable path itself (--no-preflight); tests/runtime/test_preflight.py: the refusal
    with RunSession(config, bus=f"virtual:{channel}", preflight=False) as session, \
            Sniffer(session.bus_spec.channel) as sniffer:
        result = session.run()
        sent = assert_stopped_safely(session, sniffer, result.stop, StopReason.ENABLE_FAILED,
                                     words=["no heartbeat from node 3"], emulated=False)
    # CLOSED_LOOP_CONTROL went out: a node 3 whose heartbeat never reached the host may have
    # taken it, so its disable is not confirmed (the loud line), however likely no one is there
    report = result.safe_stop
    assert result.cycles == 0 and not result.disabled
    assert report is not None and report.sent and report.confirmation is Confirmation.NEVER_ANSWERED
    assert report.warning().startswith("drive may still be enabled: node 3 never answered: ")
    return result.stop, sent, session


def test_enable_failed_realtime_nobody_on_the_bus(tmp_path: Path) -> None:
    """Real time, no drive on the channel at all."""
    profile = realtime_profile(tmp_path, "odrive-0.6", enable_timeout=0.3)
    config = demo_config(f"drive.profile={profile}")
    enable_failed_realtime(config, f"nobody-{os.getpid()}-{id(config)}")


def test_enable_failed_realtime_wrong_node_id(tmp_path: Path) -> None:
    """Real time, a drive answers but as node 4 while the host talks to node 3: the host
    gives up and that drive was never enabled."""
    profile = realtime_profile(tmp_path, "odrive-0.6", enable_timeout=0.3)
    config = demo_config(f"drive.profile={profile}")
    channel = f"wrong-node-{os.getpid()}-{id(config)}"
    other = load_profile(realtime_profile(tmp_path, "odrive-0.6", node_id=4))
    with EmulatedODrive(can.Bus(interface="virtual", channel=channel), other,
                        Plant.from_config(config)) as emulator:
        emulator.start()
        enable_failed_realtime(config, channel)
        assert emulator.protocol_state == AxisState.IDLE and emulator.applied_torque == 0.0
        assert emulator.frames_received > 0


# -- fault injection is reproducible --------------------------------------------------------

def test_dropped_frames_are_reproducible_in_lockstep() -> None:
    """Lost encoder frames (seeded) make the loop wait a period longer for the next one;
    two lockstep runs with the same seed are identical, frame for frame."""
    def once() -> tuple[Stop, np.ndarray, int]:
        drop = DropFrames(0.1, seed=7, ids={ENCODER_ID})
        out = run_case(safety_config(Path(), "lockstep"), "lockstep", StopReason.DONE,
                       faults=[drop])
        assert out.result is not None
        return out.stop, out.result.trace["tau_int_hat"].copy(), drop.applied

    (stop1, trace1, dropped1), (stop2, trace2, dropped2) = once(), once()
    assert dropped1 == dropped2 > 10
    assert stop1 == stop2
    np.testing.assert_array_equal(trace1, trace2)


# -- the host starves the emulated drive ---------------------------------------------------

def test_a_starved_emulated_drive_is_the_host_too_slow_not_the_drive(tmp_path: Path) -> None:
    """Real time: the emulated drive's process is stopped (SIGSTOP) for three feedback
    timeouts after 100 cycles, as a loaded host would starve it. The feedback stops, but
    the drive is not to blame: the stop says host_too_slow (the emulator's own measure of
    not being scheduled), and once it runs again the drive confirms the safe stop."""
    sink = Recorder(at=100)
    timers: list[threading.Timer] = []

    def arm(session: RunSession) -> None:
        emulator = session.emulator
        assert emulator is not None
        pid = getattr(emulator, "pid", None)
        assert pid is not None   # a process of its own
        pause = 3 * session.settings.feedback_timeout

        def starve() -> None:
            os.kill(pid, signal.SIGSTOP)
            timer = threading.Timer(pause, os.kill, (pid, signal.SIGCONT))
            timers.append(timer)
            timer.start()

        sink.action = starve

    try:
        out = run_case(safety_config(tmp_path, "realtime"), "realtime", StopReason.HOST_TOO_SLOW,
                       words=["no fresh feedback", "not scheduled", "host is too slow"],
                       sink=sink, prepare=arm)
    finally:
        for timer in timers:
            timer.join()
    assert out.summary is not None and out.summary["stop_reason"] == "host_too_slow"
    assert out.stop.cycle >= 100 and not out.watchdog_tripped


def test_an_emulated_drive_that_dies_is_one_line(tmp_path: Path) -> None:
    """Real time: the emulated drive's process is killed during the run. The run stops
    on bus_error naming how it ended (one line, no traceback), and says loudly that the
    disable could not be confirmed."""
    sink = Recorder(at=100)

    def arm(session: RunSession) -> None:
        pid = getattr(session.emulator, "pid", None)
        assert pid is not None
        sink.action = lambda: os.kill(pid, signal.SIGKILL)

    config = safety_config(tmp_path, "realtime")
    with RunSession(config, emulate=True, lockstep=False, sink=sink) as session:
        arm(session)
        result = session.run()
    line = result.stop.line()
    assert result.stop.reason is StopReason.BUS_ERROR, line
    assert "\n" not in line and "emulated drive's process was killed by signal SIGKILL" in line, line
    assert result.safe_stop is not None and not result.disabled
    assert result.safe_stop.warning().endswith("cut power")
