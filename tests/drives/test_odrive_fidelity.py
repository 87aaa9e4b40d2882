"""The emulated ODrive follows the firmware per version.

Facts from the 0.5.6 firmware source (tag fw-v0.5.6 of odriverobotics/ODrive): heartbeat
RTRs are ignored and there is no Get_Version; the watchdog is checked in every axis state;
Trajectory_Done starts at 1; a NaN torque setpoint passes the clamp and faults the motor
(MODULATION_IS_NAN, axis MOTOR_FAILED), +-inf clamps to the limit. 0.6 behaviour beyond
the DBC is the emulator's documented assumption. Lockstep only: no wall clock.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
import time
from collections.abc import Iterator
from pathlib import Path

import can
import pytest

from dobhil.drives import load_profile, make_drive
from dobhil.drives.odrive import codec
from dobhil.drives.odrive.codec import AxisState, CmdId, CmdId05, CmdId06, ControlMode, Firmware, InputMode
from dobhil.drives.odrive.emulator import EMULATED_VERSION_06, EmulatedODrive
from dobhil.drives.emulated import LockstepBus
from dobhil.errors import DriveTimeoutError

from .test_drive_emulated import FakePlant

_CHANNELS = itertools.count()
DT = 0.001


@dataclasses.dataclass
class Bench:
    host: can.BusABC
    emu: EmulatedODrive
    plant: FakePlant

    def send(self, msg: object) -> None:
        self.host.send(codec.encode(msg, node_id=3, firmware=self.emu.firmware))

    def raw(self, **kwargs: object) -> None:
        self.host.send(can.Message(**kwargs))  # type: ignore[arg-type]

    def tick(self, n: int = 1) -> None:
        for _ in range(n):
            self.emu.handle_pending()
            self.emu.advance(DT)

    def replies(self) -> list[object]:
        self.emu.handle_pending()
        out = []
        msg = self.host.recv(0.0)
        while msg is not None:
            out.append(codec.decode_message(msg, self.emu.firmware))
            msg = self.host.recv(0.0)
        return out

    def enable(self) -> None:
        self.send(codec.ClearErrors())
        self.send(codec.SetControllerMode(ControlMode.TORQUE_CONTROL, InputMode.PASSTHROUGH))
        self.send(codec.SetInputTorque(0.0))
        self.send(codec.SetAxisState(AxisState.CLOSED_LOOP_CONTROL))
        self.emu.handle_pending()


@pytest.fixture(params=["odrive-0.5", "odrive-0.6"])
def bench(request: pytest.FixtureRequest) -> Iterator[Bench]:
    profile = dataclasses.replace(load_profile(request.param), bus={})
    channel = f"fidelity-{next(_CHANNELS)}"
    host = can.Bus(interface="virtual", channel=channel)
    plant = FakePlant()
    emu = EmulatedODrive(can.Bus(interface="virtual", channel=channel), profile, plant)
    try:
        yield Bench(host, emu, plant)
    finally:
        emu.close()
        host.shutdown()


def test_heartbeat_rtr_answered_on_06_only(bench: Bench) -> None:
    bench.send(codec.Request(CmdId.HEARTBEAT))
    replies = bench.replies()
    if bench.emu.firmware is Firmware.V0_5:
        assert replies == []  # can_simple.cpp: heartbeat requests are ignored
    else:
        assert replies == [codec.Heartbeat(0, AxisState.IDLE, trajectory_done=True)]


def test_get_version_answered_on_06_only(bench: Bench) -> None:
    bench.host.send(codec.encode(codec.Request(CmdId06.GET_VERSION), node_id=3))  # id 0x060
    replies = bench.replies()
    assert replies == ([] if bench.emu.firmware is Firmware.V0_5 else [EMULATED_VERSION_06])


def test_trajectory_done_is_1_in_cyclic_heartbeats(bench: Bench) -> None:
    bench.tick(100)
    beats = [r for r in bench.replies() if isinstance(r, codec.Heartbeat)]
    assert beats and all(b.trajectory_done for b in beats)


def test_watchdog_runs_in_idle_too(bench: Bench) -> None:
    """An idle axis nobody feeds sets the watchdog bit (firmware: checked in every state),
    but the watchdog disarmed nothing: ``watchdog_tripped`` stays False."""
    timeout = bench.emu.profile.watchdog_timeout
    bench.tick(round(timeout / DT) - 2)
    assert not bench.emu.watchdog_error
    bench.tick(3)
    assert bench.emu.watchdog_error and bench.emu.axis_state is AxisState.IDLE
    assert not bench.emu.watchdog_tripped
    bench.enable()  # Clear_Errors first: the handshake still works
    assert bench.emu.axis_state is AxisState.CLOSED_LOOP_CONTROL


def test_nan_torque_never_reaches_the_plant_and_faults_the_axis(bench: Bench) -> None:
    bench.enable()
    bench.send(codec.SetInputTorque(0.5))
    bench.tick(2)
    bench.send(codec.SetInputTorque(math.nan))
    bench.tick(5)
    assert all(math.isfinite(t) for t in bench.plant.torques)
    assert bench.plant.torques[-1] == 0.0 and bench.emu.axis_state is AxisState.IDLE
    bench.replies()
    if bench.emu.firmware is Firmware.V0_5:
        assert bench.emu.axis_error == codec.AxisError05.MOTOR_FAILED
        bench.send(codec.Request(CmdId05.GET_MOTOR_ERROR))
        assert bench.replies() == [codec.MotorErrorMsg(codec.MotorError05.MODULATION_IS_NAN)]
        bench.tick(100)
        beat = [r for r in bench.replies() if isinstance(r, codec.Heartbeat)][-1]
        assert beat.motor_error_flag
    else:
        assert bench.emu.axis_error == codec.ODriveError06.MISSING_INPUT
        assert bench.emu.procedure_result == codec.ProcedureResult06.DISARMED


def test_infinite_torque_clamps_to_the_limit(bench: Bench) -> None:
    bench.enable()
    for value, expected in ((math.inf, 2.0), (-math.inf, -2.0)):
        bench.send(codec.SetInputTorque(value))
        bench.tick()
        assert bench.emu.applied_torque == expected
    assert bench.emu.axis_error == 0


def test_torque_inside_the_limit_is_applied_as_sent_and_beyond_it_clamps(bench: Bench) -> None:
    """The firmware's clamp on finite setpoints (0.5.6 ``controller.cpp``): a setpoint
    within +-limit (2 N m here) reaches the plant unchanged, its sign and the limit itself
    included; one beyond it is the limit."""
    bench.enable()
    for value, expected in ((1.0, 1.0), (-1.75, -1.75), (2.0, 2.0), (-2.0, -2.0), (-0.0, -0.0),
                            (2.5, 2.0), (-7.0, -2.0)):
        bench.send(codec.SetInputTorque(value))
        bench.tick()
        applied = bench.emu.applied_torque
        assert applied == expected and math.copysign(1.0, applied) == math.copysign(1.0, expected), value
    assert bench.emu.axis_error == 0


def test_closed_loop_refused_with_an_error_says_why_on_06(bench: Bench) -> None:
    bench.emu.axis_error = codec.estop_bit(bench.emu.firmware)
    bench.send(codec.SetAxisState(AxisState.CLOSED_LOOP_CONTROL))
    bench.tick(100)
    beat = [r for r in bench.replies() if isinstance(r, codec.Heartbeat)][-1]
    assert beat.axis_state == AxisState.IDLE
    if bench.emu.firmware is Firmware.V0_6:
        assert beat.procedure_result == codec.ProcedureResult06.DISARMED


def test_frames_that_are_not_can_simple_do_not_stop_the_emulator(bench: Bench) -> None:
    """An 11-bit id above 0x7FF (python-can does not check by default), extended ids,
    error frames, short and long payloads, RTRs on every id: all applied or ignored."""
    bench.raw(arbitration_id=0x800, is_extended_id=False, data=b"\x01")
    bench.raw(arbitration_id=0xFFFF, is_extended_id=False, data=b"")
    bench.raw(arbitration_id=0x1FFFFFFF, is_extended_id=True, data=bytes(8))
    bench.raw(arbitration_id=0x06E, is_extended_id=False, data=b"\x00")  # short torque
    bench.raw(arbitration_id=0x067, is_extended_id=False, data=bytes(64), is_fd=True)
    bench.raw(arbitration_id=0, is_error_frame=True)
    for cmd in range(32):
        bench.raw(arbitration_id=(3 << 5) | cmd, is_extended_id=False, is_remote_frame=True, dlc=8)
    bench.tick(10)
    assert bench.emu.frame_errors == 0, bench.emu.last_frame_error
    assert bench.emu.frames_rejected >= 2


def test_realtime_emulator_survives_an_id_above_0x7ff() -> None:
    profile = dataclasses.replace(load_profile("odrive-0.6"), bus={}, feedback_period=0.002)
    channel = f"fidelity-{next(_CHANNELS)}"
    host = can.Bus(interface="virtual", channel=channel)
    emu = EmulatedODrive(can.Bus(interface="virtual", channel=channel), profile, FakePlant())
    try:
        emu.start()
        host.send(can.Message(arbitration_id=0x800, is_extended_id=False, data=b"\x00"))
        sent = emu.frames_sent
        deadline = time.monotonic() + 5.0
        while emu.frames_sent < sent + 5 and time.monotonic() < deadline:
            time.sleep(0.005)
        assert emu.frames_sent >= sent + 5 and emu.frames_received >= 1
    finally:
        emu.close()  # re-raises anything the thread raised
        host.shutdown()
    assert emu.frame_errors == 0


def test_position_beyond_float32_goes_out_as_inf(bench: Bench) -> None:
    bench.plant.position = 1e308
    bench.plant.frozen = True
    bench.tick(2)
    est = [r for r in bench.replies() if isinstance(r, codec.EncoderEstimates)][-1]
    assert est.position_rad == math.inf and est.velocity_rad_s == 0.0


def test_enable_failure_line_names_the_procedure_result() -> None:
    """A fault Clear_Errors cannot clear: the 0.6 drive refuses closed loop and the
    enable-timeout line says why (Procedure_Result DISARMED)."""
    profile = dataclasses.replace(load_profile("odrive-0.6"), bus={}, enable_timeout=0.3)
    channel = f"fidelity-{next(_CHANNELS)}"
    host = can.Bus(interface="virtual", channel=channel)
    emu = EmulatedODrive(can.Bus(interface="virtual", channel=channel), profile, FakePlant())

    def stuck(_msg: object) -> None:
        emu.axis_error = codec.ODriveError06.DC_BUS_UNDER_VOLTAGE

    emu._handlers[codec.ClearErrors] = stuck  # a persistent fault
    lock = LockstepBus(host, [emu], dt=profile.feedback_period)
    drive = make_drive(lock, profile, clock=lock.clock)
    try:
        with pytest.raises(DriveTimeoutError, match=r"DC_BUS_UNDER_VOLTAGE\); last state request DISARMED"):
            drive.enable()
    finally:
        lock.shutdown()
        emu.close()
        host.shutdown()


#: The Get_* each firmware answers on request (0.5.6 ``can_simple.cpp``: ``msg.rtr ||
#: msg.len == 0``; heartbeat requests ignored, no Get_Version) and the emulator's 0.6
#: assumption; ids not listed (e.g. 0.5 Get_Encoder_Count, 0.6 Get_Powers) are not emulated.
ANSWERED = {
    Firmware.V0_5: {CmdId05.GET_MOTOR_ERROR, CmdId05.GET_ENCODER_ERROR, CmdId05.GET_SENSORLESS_ERROR,
                    CmdId.GET_ENCODER_ESTIMATES, CmdId.GET_IQ, CmdId.GET_BUS_VOLTAGE_CURRENT,
                    CmdId05.GET_CONTROLLER_ERROR},
    Firmware.V0_6: {CmdId.HEARTBEAT, CmdId06.GET_VERSION, CmdId06.GET_ERROR, CmdId.GET_ENCODER_ESTIMATES,
                    CmdId.GET_IQ, CmdId.GET_BUS_VOLTAGE_CURRENT, CmdId06.GET_TORQUES},
}
DBC_FILES = {Firmware.V0_5: "odrive-cansimple-0.5.6.dbc", Firmware.V0_6: "odrive-cansimple-0.6.10.dbc"}


@pytest.mark.parametrize("request_kind", ["rtr", "zero-length"])
def test_every_get_request_is_answered_with_the_dbc_reply(bench: Bench, request_kind: str) -> None:
    """A request on each of the 32 command ids (no time passes, so no cyclic frame is
    sent): exactly the firmware's Get_* are answered, each once, on the request's id with
    DLC 8, decoded by cantools with the official DBC; the encoder estimates are the plant's."""
    cantools = pytest.importorskip("cantools")
    odrive_can = pytest.importorskip("odrive_can")
    firmware = bench.emu.firmware
    db = cantools.database.load_file(
        str(Path(odrive_can.__file__).resolve().parent / "dbc" / DBC_FILES[firmware]))
    bench.plant.position, bench.plant.velocity = 1.5, -0.25
    answered: dict[int, can.Message] = {}
    for cmd in range(32):
        if cmd in (CmdId.CLEAR_ERRORS, CmdId.ESTOP, CmdId.REBOOT):
            continue   # commands with an empty payload: a zero-length frame is the command
        arbitration_id = (3 << 5) | cmd
        if request_kind == "rtr":
            bench.raw(arbitration_id=arbitration_id, is_extended_id=False, is_remote_frame=True, dlc=8)
        else:
            bench.raw(arbitration_id=arbitration_id, is_extended_id=False, data=b"")
        bench.emu.handle_pending()
        reply = bench.host.recv(0.0)
        if reply is not None:
            answered[cmd] = reply
            assert bench.host.recv(0.0) is None   # one reply per request
    assert set(answered) == ANSWERED[firmware]
    for cmd, reply in answered.items():
        assert reply.arbitration_id == (3 << 5) | cmd and not reply.is_remote_frame
        assert reply.dlc == 8 and len(reply.data) == 8
        db.decode_message(reply.arbitration_id, reply.data)   # the DBC's layout
    est = db.decode_message(answered[CmdId.GET_ENCODER_ESTIMATES].arbitration_id,
                            answered[CmdId.GET_ENCODER_ESTIMATES].data)
    assert est["Pos_Estimate"] * 2 * math.pi == pytest.approx(1.5, rel=1e-6)
    assert est["Vel_Estimate"] * 2 * math.pi == pytest.approx(-0.25, rel=1e-6)
    assert bench.emu.frame_errors == 0, bench.emu.last_frame_error


@pytest.mark.parametrize("form", ["data", "zero-length", "rtr"])
def test_clear_errors_feeds_the_watchdog_of_an_idle_axis(bench: Bench, form: str) -> None:
    """An axis left idle past the watchdog timeout shows the bit. Clear_Errors, in any
    form, clears it and feeds the watchdog, so a Set_Axis_State sent later (here one
    tick short of the timeout) is granted: odrive-can's documented sequence works
    whatever emulator ticks fall between its frames (0.6 without the feed would flag the
    bit again at the next tick and refuse closed loop)."""
    timeout_ticks = round(bench.emu.profile.watchdog_timeout / DT)
    bench.tick(timeout_ticks + 5)
    assert bench.emu.watchdog_error and not bench.emu.watchdog_tripped
    clear = codec.arbitration_id(3, CmdId.CLEAR_ERRORS)
    if form == "data":
        bench.send(codec.ClearErrors())
    elif form == "zero-length":
        bench.raw(arbitration_id=clear, is_extended_id=False, data=b"")
    else:
        bench.raw(arbitration_id=clear, is_extended_id=False, is_remote_frame=True, dlc=1)
    bench.tick(timeout_ticks - 1)
    assert not bench.emu.watchdog_error
    bench.send(codec.SetControllerMode(ControlMode.TORQUE_CONTROL, InputMode.PASSTHROUGH))
    bench.send(codec.SetAxisState(AxisState.CLOSED_LOOP_CONTROL))
    bench.tick()
    assert bench.emu.axis_state is AxisState.CLOSED_LOOP_CONTROL and bench.emu.axis_error == 0
    # the stricter 0.6 rule is kept: without setpoints the armed axis trips at the timeout
    bench.tick(timeout_ticks)
    assert bench.emu.watchdog_tripped and bench.emu.axis_state is AxisState.IDLE


def test_an_estop_rtr_stops_the_axis(bench: Bench) -> None:
    """0.5.6 runs estop_callback for any frame on the Estop id, RTR included (no rtr check
    in can_simple.cpp); the emulator does the same on both firmwares (0.6: assumption)."""
    bench.enable()
    assert bench.emu.axis_state is AxisState.CLOSED_LOOP_CONTROL
    bench.raw(arbitration_id=codec.arbitration_id(3, CmdId.ESTOP), is_extended_id=False,
              is_remote_frame=True, dlc=0)
    bench.tick()
    assert bench.emu.axis_state is AxisState.IDLE
    assert bench.emu.axis_error & codec.estop_bit(bench.emu.firmware)
