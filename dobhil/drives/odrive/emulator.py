"""Emulated ODrive (CAN Simple), drive side; firmware 0.6 default, 0.5 via the profile.

Follows the layouts of :mod:`dobhil.drives.odrive.codec` (official DBCs 0.6.10 / 0.5.6)
and, where behaviour is concerned, the 0.5.6 firmware source (tag fw-v0.5.6 of
odriverobotics/ODrive); 0.6 firmware is not public, so 0.6 behaviour beyond the DBC is
an assumption, marked as such below. Behaviour emulated:

- axis states IDLE and CLOSED_LOOP_CONTROL (other requested states are ignored);
  CLOSED_LOOP_CONTROL is refused while Axis_Error is nonzero (Clear_Errors first); on
  0.6 the heartbeat's Procedure_Result then says DISARMED (assumption: 0.6 reports a
  refused or aborted closed-loop request as DISARMED), SUCCESS after a granted request;
- torque reaches the plant only in CLOSED_LOOP_CONTROL with control mode
  TORQUE_CONTROL (power-on default is POSITION_CONTROL, as on a fresh ODrive);
- Set_Input_Torque is clamped to ``profile.torque_limit`` (0.5.6 ``controller.cpp``:
  ``if (torque > Tlim) ... if (torque < -Tlim)``, so +-inf clamps to the limit). NaN
  passes that clamp in the firmware and makes the FOC modulation NaN: the motor sets
  MODULATION_IS_NAN, the axis MOTOR_FAILED and disarms (``foc.cpp``). The emulator does
  the same on 0.5 and never hands NaN to the plant; on 0.6 it disarms with
  MISSING_INPUT (assumption);
- Estop (any frame on its id, RTR included, as 0.5.6 ``can_simple.cpp``; 0.6 assumed the
  same): IDLE plus the ESTOP_REQUESTED bit; Clear_Errors clears every bit;
- ``Get_*`` requests, an RTR frame or a zero-length data frame (0.5.6 ``can_simple.cpp``:
  ``if (msg.rtr || msg.len == 0)``), answered with the DLC-8 reply: Get_Encoder_Estimates
  (the cyclic frame's values), Get_Iq and Get_Bus_Voltage_Current on both; on 0.5
  Get_Motor/Encoder/Sensorless/Controller_Error; on 0.6 Heartbeat, Get_Version, Get_Error
  and Get_Torques (0.6: the same rule for every drive-to-host message, an assumption).
  Firmware 0.5.6 ignores heartbeat RTRs (``can_simple.cpp``: "We don't currently do
  anything to respond to ODrive heartbeat messages") and has no Get_Version (id 0 is
  CANopen NMT). 0.5.6 answers Get_Controller_Error to a data frame too; the emulator
  answers requests only, so that an interface echoing the drive's own reply back cannot
  make it answer itself. Not emulated (no answer): 0.5 Get_Encoder_Count,
  Get_Sensorless_Estimates, Get_ADC_Voltage; 0.6 Get_Temperature, Get_Powers;
- watchdog (``profile.watchdog_timeout`` > 0) checked in every axis state, as 0.5.6's
  ``main.cpp`` does: without a feed for the timeout the WATCHDOG_TIMER_EXPIRED bit is set
  (0x800 on 0.5, 0x01000000 on 0.6) and the axis drops to IDLE. An idle axis nobody
  talks to therefore shows the bit, like a real drive. Fed on 0.5 by every frame
  addressed to the node (``CANSimple::do_command``); entering CLOSED_LOOP_CONTROL feeds
  it on both (0.5.6 ``axis.cpp``). On 0.6 (firmware not public: an assumption, not
  confirmed on a drive) it is fed by the setpoint frames Set_Input_Pos/Vel/Torque and by
  Clear_Errors in any form (data, zero-length or RTR). Clear_Errors must feed it:
  otherwise an axis that sat idle past the timeout flags the bit again at the next check,
  before the Set_Axis_State that follows, and the sequence documented clients use (odrive-can:
  Clear_Errors, Set_Controller_Mode, Set_Axis_State CLOSED_LOOP_CONTROL, then setpoints)
  is refused at random, depending on whether a check falls between two frames sent
  back to back. Set_Controller_Mode and a refused Set_Axis_State do not feed it on 0.6
  (the stricter choice: nothing but setpoints keeps an armed axis armed).
  :attr:`EmulatedODrive.watchdog_tripped` is True only if the watchdog disarmed the
  motor (expired in CLOSED_LOOP_CONTROL); :attr:`EmulatedODrive.watchdog_error` is the bit;
- heartbeat Trajectory_Done is 1 (0.5.6 ``controller.hpp``: ``trajectory_done_ = true``;
  no trajectory runs in torque control);
- cyclic Heartbeat and Get_Encoder_Estimates at the profile's rates; a position or
  velocity beyond float32 range goes out as +-inf (what a float32 drive variable holds);
- any frame, well-formed or not (ids above 0x7FF, any DLC, RTR, error frames), is
  applied or counted in ``frames_rejected``; none stops the emulator.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Any

import can

from dobhil.drives.odrive import codec
from dobhil.drives.odrive.codec import (AxisState, CmdId, CmdId05, CmdId06, ControlMode, Firmware, InputMode,
                                        ProcedureResult06)
from dobhil.drives.profile import DriveProfile
from dobhil.drives.emulated import EmulatedDrive, PlantLike
from dobhil.errors import CodecError, ConfigError

__all__ = ["EmulatedODrive"]

#: 0.6 watchdog feeders (Set_Input_Pos 0x0C is not in the codec table: fed by raw id).
_FEEDS_06 = frozenset({0x0C, CmdId.SET_INPUT_VEL, CmdId.SET_INPUT_TORQUE})
_DRIVE_TO_HOST = (
    codec.Heartbeat, codec.EncoderEstimates, codec.Iq, codec.Torques, codec.GetError,
    codec.BusVoltageCurrent, codec.Version, codec.MotorErrorMsg, codec.EncoderErrorMsg,
    codec.SensorlessErrorMsg, codec.ControllerErrorMsg,
)
_FLOAT32_MAX = 3.4028234663852886e38
#: what the emulated 0.6 drive reports to Get_Version: protocol 2, ODrive Pro hardware
#: 4.4.58, firmware 0.6.10 (the DBC's version); values of the emulator, not of a drive
EMULATED_VERSION_06 = codec.Version(2, 4, 4, 58, 0, 6, 10, 0)


def _float32_or_inf(value: float, scale: float) -> float:
    """``value`` [SI], or +-inf if it does not fit float32 after scaling to wire units."""
    return value if abs(value / scale) <= _FLOAT32_MAX else math.copysign(math.inf, value)


class EmulatedODrive(EmulatedDrive):
    """An ODrive axis on a python-can bus, dynamics from the injected plant."""

    def __init__(
        self, bus: can.BusABC, profile: DriveProfile, plant: PlantLike, *,
        torque_constant: float = 0.0827, bus_voltage: float = 24.0, **kwargs: Any,
    ) -> None:
        super().__init__(bus, profile, plant, **kwargs)
        self.firmware = Firmware.parse(profile.firmware)
        self.node_id = profile.node_id
        self.torque_constant = torque_constant  # Nm/A, for Get_Iq
        self.bus_voltage = bus_voltage
        self.axis_state: AxisState = AxisState.IDLE
        self.axis_error = 0
        self.control_mode: int = ControlMode.POSITION_CONTROL
        self.input_mode: int = InputMode.PASSTHROUGH
        self.input_torque = 0.0
        self.procedure_result: int = ProcedureResult06.SUCCESS
        self.motor_error = 0  # 0.5 Get_Motor_Error code (heartbeat motor flag)
        self.frames_rejected = 0
        self.watchdog_tripped = False
        self._last_feed = 0.0
        self._watchdog_bit = codec.watchdog_bit(self.firmware)
        self._encoder_spec = codec.spec_for(CmdId.GET_ENCODER_ESTIMATES, self.firmware)
        self._encoder_id = codec.arbitration_id(self.node_id, CmdId.GET_ENCODER_ESTIMATES)
        self._torque_spec = codec.spec_for(CmdId.SET_INPUT_TORQUE, self.firmware)
        self._torque_cmd = int(CmdId.SET_INPUT_TORQUE)   # a plain int: the hot path's compare
        self._handlers: dict[type, Callable[[Any], None]] = {
            codec.SetAxisState: self._set_axis_state,
            codec.SetControllerMode: self._set_controller_mode,
            codec.SetInputTorque: self._set_input_torque,
            codec.ClearErrors: self._clear_errors,
            codec.Estop: self._estop,
            codec.Request: self._answer,
        }

    # -- observables ----------------------------------------------------------

    @property
    def protocol_state(self) -> int:
        """The heartbeat's Axis_State (the emulator process publishes it by this name)."""
        return int(self.axis_state)

    @property
    def protocol_error(self) -> int:
        """The heartbeat's Axis_Error."""
        return self.axis_error

    @property
    def watchdog_error(self) -> bool:
        """The watchdog's Axis_Error bit is set (also on an idle axis nobody feeds)."""
        return bool(self.axis_error & self._watchdog_bit)

    # -- hooks ----------------------------------------------------------------

    def _plant_torque(self) -> float:
        if (
            self.axis_state == AxisState.CLOSED_LOOP_CONTROL
            and self.control_mode == ControlMode.TORQUE_CONTROL
        ):
            return self.input_torque
        return 0.0

    def _cyclic_frames(self) -> Sequence[tuple[float, Callable[[], can.Message]]]:
        feedback, heartbeat = self._profile.feedback_period, self._profile.heartbeat_period
        if feedback is None or heartbeat is None:  # the ODrive's profile rules require both
            raise ConfigError(f"drive profile {self._profile.name!r}: an ODrive needs feedback_period "
                              "and heartbeat_period")
        return ((feedback, self._encoder_frame), (heartbeat, self._heartbeat_frame))

    def _on_time(self, now: float) -> None:
        """The firmware's watchdog_check(), in every axis state (0.5.6 ``main.cpp``)."""
        timeout = self._profile.watchdog_timeout
        if timeout > 0 and now - self._last_feed >= timeout - 1e-9:
            if self.axis_state == AxisState.CLOSED_LOOP_CONTROL:
                self.watchdog_tripped = True
                self._disarm()
            self.axis_error |= self._watchdog_bit

    def _on_frame(self, msg: can.Message) -> None:
        if msg.is_extended_id or msg.is_error_frame or not 0 <= msg.arbitration_id <= 0x7FF:
            self.frames_not_addressed += 1
            return  # not CAN Simple on this bus (the firmware filters 11-bit node ids)
        arb = msg.arbitration_id   # an 11-bit id (checked above): codec.split_id inline
        if arb >> 5 != self.node_id:
            self.frames_not_addressed += 1   # another node's (the firmware's id filter)
            return
        cmd = arb & 0x1F
        if self.firmware is Firmware.V0_5 or (cmd in _FEEDS_06 and not msg.is_remote_frame):
            self._last_feed = self._time   # the watchdog's feed (module docstring), inline
        if cmd == self._torque_cmd and not msg.is_remote_frame:
            try:  # hot path (every period): the table's scale, no dataclass
                (torque,) = self._torque_spec.unpack_si(msg.data)
            except CodecError:
                self.frames_rejected += 1
                return
            self._apply_torque(torque)
            return
        try:
            decoded = codec.decode_message(msg, self.firmware)
        except CodecError:
            self.frames_rejected += 1
            return
        handler = self._handlers.get(type(decoded))
        if handler is not None:
            handler(decoded)
        elif not isinstance(decoded, _DRIVE_TO_HOST):
            self.frames_rejected += 1  # known but not emulated (e.g. Set_Limits)

    # -- frames out -----------------------------------------------------------

    def _encode(self, msg: Any) -> can.Message:
        return codec.encode(msg, node_id=self.node_id, firmware=self.firmware)

    def _heartbeat(self) -> codec.Heartbeat:
        if self.firmware is Firmware.V0_6:
            return codec.Heartbeat(self.axis_error, self.axis_state,
                                   procedure_result=self.procedure_result, trajectory_done=True)
        return codec.Heartbeat(self.axis_error, self.axis_state, trajectory_done=True,
                               motor_error_flag=self.motor_error != 0)

    def _heartbeat_frame(self) -> can.Message:
        return self._encode(self._heartbeat())

    def _encoder_frame(self) -> can.Message:
        # hot path (every period): the table's scales through pack_into, no dataclass
        msg = can.Message(arbitration_id=self._encoder_id, is_extended_id=False,
                          data=self._encoder_spec.new_frame_data())
        spec, position, velocity = self._encoder_spec, self._plant.position, self._plant.velocity
        try:
            spec.pack_into(msg.data, position, velocity)
        except CodecError:  # beyond float32: what a float32 estimate would hold
            spec.pack_into(msg.data, _float32_or_inf(position, spec.scales[0]),
                           _float32_or_inf(velocity, spec.scales[1]))
        return msg

    def _reply_for(self, cmd: int) -> Any:
        applied = self._plant_torque()
        common: dict[int, Callable[[], Any]] = {
            CmdId.GET_IQ: lambda: codec.Iq(
                self.input_torque / self.torque_constant, applied / self.torque_constant),
            CmdId.GET_BUS_VOLTAGE_CURRENT: lambda: codec.BusVoltageCurrent(self.bus_voltage, 0.0),
        }
        per_firmware: dict[int, Callable[[], Any]] = {
            CmdId.HEARTBEAT: self._heartbeat,
            CmdId06.GET_VERSION: lambda: EMULATED_VERSION_06,
            CmdId06.GET_TORQUES: lambda: codec.Torques(self.input_torque, applied),
            CmdId06.GET_ERROR: lambda: codec.GetError(self.axis_error, self.axis_error),
        } if self.firmware is Firmware.V0_6 else {
            CmdId05.GET_MOTOR_ERROR: lambda: codec.MotorErrorMsg(self.motor_error),
            CmdId05.GET_ENCODER_ERROR: lambda: codec.EncoderErrorMsg(0),
            CmdId05.GET_SENSORLESS_ERROR: lambda: codec.SensorlessErrorMsg(0),
            CmdId05.GET_CONTROLLER_ERROR: lambda: codec.ControllerErrorMsg(0),
        }
        make = common.get(cmd) or per_firmware.get(cmd)
        return make() if make is not None else None

    # -- commands -------------------------------------------------------------

    def _set_axis_state(self, msg: codec.SetAxisState) -> None:
        if msg.requested_state == AxisState.IDLE:
            self.axis_state = AxisState.IDLE
            self.procedure_result = ProcedureResult06.SUCCESS
        elif msg.requested_state == AxisState.CLOSED_LOOP_CONTROL:
            if self.axis_error != 0:
                self.procedure_result = ProcedureResult06.DISARMED
                return
            self.axis_state = AxisState.CLOSED_LOOP_CONTROL
            self.procedure_result = ProcedureResult06.SUCCESS
            self._last_feed = self._time

    def _set_controller_mode(self, msg: codec.SetControllerMode) -> None:
        self.control_mode = msg.control_mode
        self.input_mode = msg.input_mode

    def _set_input_torque(self, msg: codec.SetInputTorque) -> None:
        self._apply_torque(msg.torque_nm)

    def _apply_torque(self, torque: float) -> None:
        """The firmware's clamp (inf -> the limit); NaN faults the axis, as the FOC would."""
        if math.isnan(torque):
            self.input_torque = 0.0
            if self.firmware is Firmware.V0_5:
                self.motor_error |= codec.MotorError05.MODULATION_IS_NAN
                self.axis_error |= codec.AxisError05.MOTOR_FAILED
            else:
                self.axis_error |= codec.ODriveError06.MISSING_INPUT
            if self.axis_state == AxisState.CLOSED_LOOP_CONTROL:
                self._disarm()
            return
        limit = self._profile.torque_limit   # min(max(...)) as comparisons: every frame
        self.input_torque = -limit if torque < -limit else (limit if torque > limit else torque)

    def _disarm(self) -> None:
        """An error ends closed-loop control (0.6: Procedure_Result DISARMED, assumption)."""
        self.axis_state = AxisState.IDLE
        self.procedure_result = ProcedureResult06.DISARMED

    def _clear_errors(self, _msg: codec.ClearErrors) -> None:
        # feeds the watchdog (0.5: as every frame does; 0.6: the assumption in the
        # module docstring), or a long-idle axis would flag it again at the next check
        self._last_feed = self._time
        self.axis_error = 0
        self.motor_error = 0
        self.watchdog_tripped = False

    def _estop(self, _msg: codec.Estop) -> None:
        self._disarm()
        self.axis_error |= codec.estop_bit(self.firmware)

    def _answer(self, msg: codec.Request) -> None:
        if msg.cmd == CmdId.CLEAR_ERRORS:  # zero-length Clear_Errors on 0.6
            self._clear_errors(codec.ClearErrors())
            return
        if msg.cmd == CmdId.ESTOP:
            # 0.5.6 estops on any frame with the Estop id, RTR included (can_simple.cpp has no
            # rtr check there); 0.6 assumed the same: an Estop in any form stops the axis
            self._estop(codec.Estop())
            return
        if msg.cmd == CmdId.GET_ENCODER_ESTIMATES:
            # the cyclic frame itself: the same estimates, float32 overflow sent as +-inf
            self._send(self._encoder_frame())
            return
        reply = self._reply_for(msg.cmd)
        if reply is not None:
            self._send(self._encode(reply))
