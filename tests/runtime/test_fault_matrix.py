"""The fault matrix: one suite over {lockstep, feedback-synchronous and host-timed real
time} x every
fault the runtime meets on its own -- silence, late frames, corrupted and NaN feedback,
a spoofed heartbeat, an Estop, a bus that refuses frames (ENOBUFS, once or for good),
the interface going away, a flood of foreign frames, SIGINT and SIGTERM.

Each row asserts the stop reason (one line), the safe-stop report the sink received
(zero torque, then IDLE, each with its own result), the last frames the drive actually
saw on the bus (zero torque, then IDLE) and the drive's final state -- or, where the bus
itself is gone, that the run says loudly that the drive may still be enabled and that
the drive's own watchdog is then what stops it.

SIGKILL of the emulator or of the loop process: ``test_process_kill.py`` (across
processes). The recorder's rows (writer killed, disk full, ``dobhil log recover``):
``test_recorder_faults.py``.
"""

from __future__ import annotations

import dataclasses
import os
import signal
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest

from dobhil.config import Config
from dobhil.drives import base as drive_base
from dobhil.drives.base import Confirmation, Feedback, SafeStopReport
from dobhil.drives.odrive import codec
from dobhil.drives.odrive.codec import AxisState, CmdId, CmdId05, CmdId06, Firmware
from dobhil.emulator.bus_faults import InterfaceGone, RefuseSend
from dobhil.drives.load import load_profile
from dobhil.emulator.faults import (CorruptFeedback, Fault, Flood, HoldFrames, InjectFrame,
                                    InjectReceived, KeepEvery, LoseSent, SilenceAfter, faulty)
from dobhil.runtime.controller import ControlOutput
from dobhil.runtime.loop import RunResult, StopRequest, Timing
from dobhil.runtime.session import RunSession, summary
from dobhil.runtime.signals import stop_on_signals
from dobhil.runtime.stop import Stop, StopReason

from .helpers import (NODE, REALTIME_SLACK, STEP_FROM_ZERO, Sniffer, assert_stopped_safely,
                      demo_config, realtime_profile, wait_until, write_profile)

TIMINGS = ("lockstep", "feedback", "host")
TIMING = {"lockstep": Timing.LOCKSTEP, "feedback": Timing.FEEDBACK, "host": Timing.HOST}
FW = Firmware.V0_6
ENCODER = codec.arbitration_id(NODE, CmdId.GET_ENCODER_ESTIMATES)
#: the drive these tests run, for faults laid out by its protocol
ODRIVE_PROFILE = dataclasses.replace(load_profile("odrive-0.6"), node_id=NODE)
TORQUE = codec.arbitration_id(NODE, CmdId.SET_INPUT_TORQUE)
AXIS_STATE = codec.arbitration_id(NODE, CmdId.SET_AXIS_STATE)
NODE_IDS = frozenset(codec.arbitration_id(NODE, c) for ids in (CmdId, CmdId05, CmdId06) for c in ids)
AT = 100   # the fault strikes around the 100th frame (0.1 s into a 0.4 s run)
#: [s] the run of a row that ends on its fault: its fault strikes at a frame count (the host's
#: 100th torque frame ...), and a busy host that skips the deadlines it missed sends fewer
#: than that in 0.4 s. Only a bound: the fault ends the run long before it.
UNTIL_THE_FAULT = 10.0
#: runs of one real-time row at most: a run the machine starved, stopped as ``host_too_slow``
#: by the run itself (the host or the emulated drive not scheduled for longer than the drive's
#: watchdog or the feedback timeout allows), ended before its fault could strike, and is made
#: again with new faults; the last is checked (a row never expects ``host_too_slow``)
STARVED_RUNS = 3


@dataclass
class Sink:
    """Records what the loop hands a sink; ``action`` runs once at cycle ``at``."""

    at: int = AT
    action: Callable[[], None] | None = None
    stops: list[Stop] = field(default_factory=list)
    reports: list[SafeStopReport] = field(default_factory=list)
    fired: bool = False

    def started(self, fb: Feedback) -> None:
        pass

    def cycle(self, k: int, t: float, fb: Feedback, out: ControlOutput, period_error: float,
              exec_time: float, overrun: bool) -> None:
        if k >= self.at and not self.fired and self.action is not None:
            self.fired = True
            self.action()

    def stop(self, stop: Stop) -> None:
        self.stops.append(stop)

    def safe_stop(self, report: SafeStopReport) -> None:
        self.reports.append(report)


@dataclass(frozen=True)
class Row:
    """One fault: what to inject (per timing), what must come of it."""

    faults: Callable[[str], list[Fault]]
    reason: StopReason
    words: tuple[str, ...] = ()
    signum: int = 0            # a signal sent to this process at cycle AT
    bus_dead: bool = False     # the safe stop cannot reach the drive
    idle_lost: bool = False    # the disable frame is lost on the bus (no watchdog either)


def _spoofed_idle() -> list[Fault]:
    beat = codec.encode(codec.Heartbeat(0, AxisState.IDLE), node_id=NODE, firmware=FW)
    return [InjectReceived(beat, after=AT, ids={ENCODER})]


def _estop() -> list[Fault]:
    return [InjectFrame(codec.encode(codec.Estop(), node_id=NODE, firmware=FW), after=AT,
                        ids={TORQUE})]


def _bad_feedback(timing: str, value: float, field_name: str = "position") -> list[Fault]:
    # real time uses the newest of the frames queued in a cycle: the sensor stays bad
    count = 1 if timing == "lockstep" else 1_000_000
    return [CorruptFeedback.of_profile(ODRIVE_PROFILE, field_name, value=value, at=AT, count=count)]


ROWS: dict[str, Row] = {
    "silence": Row(lambda t: [SilenceAfter(frames=AT, ids={ENCODER})],
                   StopReason.FEEDBACK_TIMEOUT, ("no fresh feedback",)),
    "late-frames": Row(lambda t: [HoldFrames(at=AT, count=3, ids={ENCODER})], StopReason.DONE),
    "late-beyond-timeout": Row(lambda t: [HoldFrames(at=AT, count=60, ids={ENCODER})],
                               StopReason.FEEDBACK_TIMEOUT, ("no fresh feedback",)),
    "drive-slower-than-profile": Row(lambda t: [KeepEvery(4, at=AT, ids={ENCODER})],
                                     StopReason.FEEDBACK_TIMEOUT,
                                     ("encoder estimates come every", "expected every loop.period = 1 ms",
                                      "encoder_msg_rate_ms = 1 on the drive")),
    "nan-position": Row(lambda t: _bad_feedback(t, float("nan")), StopReason.NON_FINITE,
                        ("non-finite feedback",)),
    "inf-velocity": Row(lambda t: _bad_feedback(t, float("inf"), "velocity"),
                        StopReason.NON_FINITE, ("non-finite feedback",)),
    "corrupted-position": Row(lambda t: _bad_feedback(t, 1e6), StopReason.POSITION_LIMIT,
                              ("outside",)),
    "spoofed-heartbeat": Row(lambda t: _spoofed_idle(), StopReason.DRIVE_FAULT, ("IDLE",)),
    "estop": Row(lambda t: _estop(), StopReason.DRIVE_FAULT, ("ESTOP_REQUESTED",)),
    "enobufs-once": Row(lambda t: [RefuseSend(at=AT, count=3, ids={TORQUE})],
                        StopReason.BUS_ERROR, ("torque frame to node 3 not sent",
                                               "No buffer space")),
    "enobufs-for-good": Row(lambda t: [RefuseSend(at=AT)], StopReason.BUS_ERROR,
                            ("not sent", "No buffer space"), bus_dead=True),
    "interface-gone": Row(lambda t: [InterfaceGone(after=AT, ids={TORQUE})],
                          StopReason.BUS_ERROR, ("No such device",), bus_dead=True),
    "idle-lost": Row(lambda t: [LoseSent(frames=1, ids={AXIS_STATE})], StopReason.SIGNAL,
                     ("received SIGINT",), signum=signal.SIGINT, idle_lost=True),
    "foreign-flood": Row(lambda t: [Flood(3, avoid=NODE_IDS, seed=5)], StopReason.DONE),
    "sigint": Row(lambda t: [], StopReason.SIGNAL, ("received SIGINT",), signum=signal.SIGINT),
    "sigterm": Row(lambda t: [], StopReason.SIGNAL, ("received SIGTERM",),
                   signum=signal.SIGTERM),
}


def matrix_config(tmp_path: Path, timing: str, *overrides: str, **profile_changes: object) -> Config:
    """The rows' run: 0.4 s of the demo on an ODrive 0.6 (real time: the relaxed profile and
    feedback timeout of tests/runtime/helpers.py), ``overrides`` last."""
    base = (*STEP_FROM_ZERO, "loop.duration=0.4")
    if timing == "lockstep" and not profile_changes:
        return demo_config("drive.profile=odrive-0.6", *base, *overrides)
    if timing == "lockstep":
        profile = write_profile(tmp_path, "odrive-0.6", **profile_changes)
        return demo_config(f"drive.profile={profile}", *base, *overrides)
    profile = realtime_profile(tmp_path, "odrive-0.6", **profile_changes)
    return demo_config(f"drive.profile={profile}", f"loop.timing={timing}", *base, *REALTIME_SLACK, *overrides)


def kill_self(signum: int) -> Callable[[], None]:
    return lambda: os.kill(os.getpid(), signum)


def watchdog_stops_it(session: RunSession) -> bool:
    """The host cannot reach the drive any more: the drive's own watchdog must end in
    IDLE with zero torque (lockstep: let simulated time run past the watchdog)."""
    emu = session.emulator
    assert emu is not None

    def idle() -> bool:
        return (emu.protocol_state == AxisState.IDLE  # type: ignore[attr-defined]
                and emu.applied_torque == 0.0 and bool(emu.watchdog_tripped))  # type: ignore[attr-defined]

    if session.timing is Timing.LOCKSTEP:
        emu.handle_pending()
        for _ in range(round(2 * session.profile.watchdog_timeout / session.settings.period)):
            emu.advance(session.settings.period)
        return idle()
    return wait_until(idle)


@pytest.mark.parametrize("timing", TIMINGS)
@pytest.mark.parametrize("name", list(ROWS))
def test_fault(tmp_path: Path, timing: str, name: str) -> None:
    row = ROWS[name]
    until = () if row.reason is StopReason.DONE else (f"loop.duration={UNTIL_THE_FAULT}",)
    config = matrix_config(tmp_path, timing, *until, **({"watchdog_timeout": 0} if row.idle_lost else {}))
    runs = 1 if timing == "lockstep" else STARVED_RUNS
    for attempt in range(1, runs + 1):
        faults = row.faults(timing)
        sink = Sink(action=kill_self(row.signum) if row.signum else None)
        with stop_on_signals(StopRequest()) as request, \
                RunSession(config, emulate=True, lockstep=timing == "lockstep", sink=sink,
                           stop_request=request,
                           bus_wrapper=faulty(*faults) if faults else None) as session, \
                Sniffer(session.bus_spec.channel) as sniffer:
            assert session.timing is TIMING[timing]
            result = session.run()
            if result.stop.reason is not StopReason.HOST_TOO_SLOW or attempt == runs:
                check_row(row, result, sink, session, sniffer)
                return


def check_row(row: Row, result: RunResult, sink: Sink, session: RunSession,
              sniffer: Sniffer) -> None:
    stop, report = result.stop, result.safe_stop
    line = stop.line()
    assert stop.reason is row.reason, line
    assert sink.stops == [stop] and sink.reports == [report]
    assert report is not None
    assert [f.what for f in report.frames] == ["zero torque", "IDLE"]
    info = summary(session, result)
    assert info["stop_reason"] == row.reason.name.lower()
    if row.idle_lost:   # sent, but the drive never saw it: still enabled, said loudly
        assert report.sent and report.confirmation is Confirmation.NOT_ACKNOWLEDGED
        assert not result.disabled
        assert report.warning() == ("drive may still be enabled: node 3 did not acknowledge "
                                    "IDLE (still CLOSED_LOOP_CONTROL after 0.3 s); cut power")
        sent = sniffer.host_commands(FW)
        assert sent.torques[-1] == 0.0 and AxisState.IDLE not in sent.axis_states
        emu = session.emulator
        assert emu is not None and emu.protocol_state == AxisState.CLOSED_LOOP_CONTROL  # type: ignore[attr-defined]
        assert emu.applied_torque == 0.0   # the zero torque did arrive
        return
    if row.bus_dead:
        assert not report.sent and report.confirmation is Confirmation.NOT_SENT
        assert not result.disabled
        warning = report.warning()
        assert warning.startswith("drive may still be enabled: node 3 ") and warning.endswith(
            "; cut power"), warning
        assert "zero torque frame not sent" in warning and "IDLE frame not sent" in warning
        assert info["drive_warning"] == warning
        for word in row.words:
            assert word.lower() in line.lower(), (word, line)
        assert watchdog_stops_it(session), "the drive's watchdog did not take it to IDLE"
        return
    assert report.sent and report.confirmation is Confirmation.CONFIRMED, report
    assert result.disabled and report.warning() == ""
    sent = assert_stopped_safely(session, sniffer, stop, row.reason, words=row.words)
    assert all(abs(x) <= session.controller.torque_limit for x in sent.torques)
    if row.reason is StopReason.DONE:
        assert result.cycles + result.skipped == session.settings.cycles
    if row.faults is ROWS["late-frames"].faults and session.timing is not Timing.HOST:
        # the burst's newest frame is used: the held frames' cycles are skipped
        assert result.skipped >= 3 if session.timing is Timing.FEEDBACK else result.skipped == 3


def test_transient_enobufs_is_retried_in_the_safe_stop() -> None:
    """The bus refuses the torque frame and, once, the safe stop's zero torque: the safe
    stop retries it, so the drive still sees zero torque then IDLE; the report counts the
    refused attempt."""
    config = matrix_config(Path(), "lockstep")
    refuse = RefuseSend(at=AT, count=2, ids={TORQUE})
    with RunSession(config, emulate=True, lockstep=True, bus_wrapper=faulty(refuse)) as session, \
            Sniffer(session.bus_spec.channel) as sniffer:
        result = session.run()
        assert refuse.applied == 2
        assert result.safe_stop is not None and result.safe_stop.sent
        assert [f.refused for f in result.safe_stop.frames] == [1, 0]
        assert_stopped_safely(session, sniffer, result.stop, StopReason.BUS_ERROR)


class _StarvedTime:
    """``time`` for dobhil.drives.base as a busy machine gives it: each sleep, however
    short, ends 30 ms later (the process was not run meanwhile)."""

    def __init__(self) -> None:
        self.lost = 0.0

    def monotonic(self) -> float:
        return time.monotonic() + self.lost

    def sleep(self, seconds: float) -> None:
        self.lost += 0.03

    def __getattr__(self, name: str) -> Any:
        return getattr(time, name)


def test_a_starved_safe_stop_still_retries_a_refused_frame(monkeypatch: pytest.MonkeyPatch) -> None:
    """The bus refuses the torque frame and twice the safe stop's zero torque, on a host the
    machine does not run for 30 ms at each wait between attempts: the SAFE_STOP_RETRY window
    is gone after one retry, yet the zero torque is tried again until it goes out -- a
    starved host's attempts, not the window alone, decide when to give up."""
    monkeypatch.setattr(drive_base, "time", _StarvedTime())
    config = matrix_config(Path(), "lockstep")
    refuse = RefuseSend(at=AT, count=3, ids={TORQUE})
    with RunSession(config, emulate=True, lockstep=True, bus_wrapper=faulty(refuse)) as session, \
            Sniffer(session.bus_spec.channel) as sniffer:
        result = session.run()
        assert result.safe_stop is not None and result.safe_stop.sent, result.safe_stop
        assert [f.refused for f in result.safe_stop.frames] == [2, 0]
        assert_stopped_safely(session, sniffer, result.stop, StopReason.BUS_ERROR)


def test_lockstep_bus_is_really_stepped_past_the_watchdog() -> None:
    """The dead-bus rows rely on the emulator's watchdog; without the stall it stays
    enabled (so ``watchdog_stops_it`` is not true by construction)."""
    config = matrix_config(Path(), "lockstep")
    gone = InterfaceGone(after=AT, ids={TORQUE})
    with RunSession(config, emulate=True, lockstep=True, bus_wrapper=faulty(gone)) as session:
        result = session.run()
        assert result.stop.reason is StopReason.BUS_ERROR
        assert session.timing is Timing.LOCKSTEP
        emu = session.emulator
        assert emu is not None
        emu.handle_pending()
        assert emu.protocol_state == AxisState.CLOSED_LOOP_CONTROL  # type: ignore[attr-defined]
        assert emu.applied_torque != 0.0
