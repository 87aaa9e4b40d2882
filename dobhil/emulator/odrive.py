"""Emulated ODrive (CAN Simple), drive side; firmware 0.6 default, 0.5 via the profile.

Follows the layouts of :mod:`dobhil.drives.odrive.codec` (official DBCs 0.6.10 / 0.5.6).
Behaviour emulated:

- axis states IDLE and CLOSED_LOOP_CONTROL (other requested states are ignored);
  CLOSED_LOOP_CONTROL is refused while Axis_Error is nonzero (Clear_Errors first);
- torque reaches the plant only in CLOSED_LOOP_CONTROL with control mode
  TORQUE_CONTROL (power-on default is POSITION_CONTROL, as on a fresh ODrive);
- Set_Input_Torque is clamped to ``profile.torque_limit``;
- Estop: IDLE plus the ESTOP_REQUESTED bit; Clear_Errors clears every bit;
- ``Get_*`` requests (RTR or zero-length frames) for Heartbeat, Get_Encoder_Estimates,
  Get_Iq, Get_Bus_Voltage_Current and, on 0.6, Get_Error and Get_Torques are answered;
- watchdog (``profile.watchdog_timeout`` > 0): in CLOSED_LOOP_CONTROL without a feed for
  the timeout -> IDLE plus WATCHDOG_TIMER_EXPIRED (0x800 on 0.5, 0x01000000 on 0.6).
  Fed on 0.5 by every frame addressed to the node (the reference's fact); on 0.6 by the
  setpoint frames Set_Input_Pos/Vel/Torque only — an assumption (not confirmed against
  0.6 firmware) that is the stricter of the two: RTR polling alone does not keep the
  axis alive. Entering CLOSED_LOOP_CONTROL feeds it.
- cyclic Heartbeat and Get_Encoder_Estimates at the profile's rates.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import can

from dobhil.drives.odrive import codec
from dobhil.drives.odrive.codec import AxisState, CmdId, ControlMode, Firmware, InputMode
from dobhil.drives.profile import DriveProfile
from dobhil.emulator.protocol import EmulatedDrive, PlantLike
from dobhil.errors import CodecError

__all__ = ["EmulatedODrive"]

#: 0.6 watchdog feeders (Set_Input_Pos 0x0C is not in the codec table: fed by raw id).
_FEEDS_06 = frozenset({0x0C, CmdId.SET_INPUT_VEL, CmdId.SET_INPUT_TORQUE})
_DRIVE_TO_HOST = (
    codec.Heartbeat, codec.EncoderEstimates, codec.Iq, codec.Torques, codec.GetError,
    codec.BusVoltageCurrent,
)


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
        self.frames_rejected = 0
        self._last_feed = 0.0
        self._watchdog_bit = codec.watchdog_bit(self.firmware)
        self._encoder_spec = codec.spec_for(CmdId.GET_ENCODER_ESTIMATES, self.firmware)
        self._encoder_id = codec.arbitration_id(self.node_id, CmdId.GET_ENCODER_ESTIMATES)
        self._torque_spec = codec.spec_for(CmdId.SET_INPUT_TORQUE, self.firmware)
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
    def watchdog_tripped(self) -> bool:
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
        return (
            (self._profile.encoder_msg_rate, self._encoder_frame),
            (self._profile.heartbeat_msg_rate, self._heartbeat_frame),
        )

    def _on_time(self, now: float) -> None:
        timeout = self._profile.watchdog_timeout
        if (
            timeout > 0
            and self.axis_state == AxisState.CLOSED_LOOP_CONTROL
            and now - self._last_feed >= timeout - 1e-9
        ):
            self.axis_state = AxisState.IDLE
            self.axis_error |= self._watchdog_bit

    def _on_frame(self, msg: can.Message) -> None:
        if msg.is_extended_id or msg.is_error_frame:
            return
        node, cmd = codec.split_id(msg.arbitration_id)
        if node != self.node_id:
            return
        self._maybe_feed(cmd, msg)
        if cmd == CmdId.SET_INPUT_TORQUE and not msg.is_remote_frame:
            try:  # hot path (every period): the table's scale, no dataclass
                (torque,) = self._torque_spec.unpack_si(msg.data)
            except CodecError:
                self.frames_rejected += 1
                return
            limit = self._profile.torque_limit
            self.input_torque = min(max(torque, -limit), limit)
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

    def _heartbeat_frame(self) -> can.Message:
        return self._encode(codec.Heartbeat(self.axis_error, self.axis_state))

    def _encoder_frame(self) -> can.Message:
        # hot path (every period): the table's scales through pack_into, no dataclass
        msg = can.Message(arbitration_id=self._encoder_id, is_extended_id=False,
                          data=bytearray(self._encoder_spec.size))
        self._encoder_spec.pack_into(msg.data, self._plant.position, self._plant.velocity)
        return msg

    def _reply_for(self, cmd: CmdId) -> Any:
        applied = self._plant_torque()
        replies: dict[CmdId, Callable[[], Any]] = {
            CmdId.HEARTBEAT: lambda: codec.Heartbeat(self.axis_error, self.axis_state),
            CmdId.GET_ENCODER_ESTIMATES: lambda: codec.EncoderEstimates(
                self._plant.position, self._plant.velocity),
            CmdId.GET_IQ: lambda: codec.Iq(
                self.input_torque / self.torque_constant, applied / self.torque_constant),
            CmdId.GET_BUS_VOLTAGE_CURRENT: lambda: codec.BusVoltageCurrent(self.bus_voltage, 0.0),
            CmdId.GET_TORQUES: lambda: codec.Torques(self.input_torque, applied),
            CmdId.GET_ERROR: lambda: codec.GetError(self.axis_error, self.axis_error),
        }
        make = replies.get(cmd)
        return make() if make is not None else None

    # -- commands -------------------------------------------------------------

    def _maybe_feed(self, cmd: int, msg: can.Message) -> None:
        if self.firmware is Firmware.V0_5 or (cmd in _FEEDS_06 and not msg.is_remote_frame):
            self._last_feed = self._time

    def _set_axis_state(self, msg: codec.SetAxisState) -> None:
        if msg.requested_state == AxisState.IDLE:
            self.axis_state = AxisState.IDLE
        elif msg.requested_state == AxisState.CLOSED_LOOP_CONTROL and self.axis_error == 0:
            self.axis_state = AxisState.CLOSED_LOOP_CONTROL
            self._last_feed = self._time

    def _set_controller_mode(self, msg: codec.SetControllerMode) -> None:
        self.control_mode = msg.control_mode
        self.input_mode = msg.input_mode

    def _set_input_torque(self, msg: codec.SetInputTorque) -> None:
        limit = self._profile.torque_limit
        self.input_torque = min(max(msg.torque_nm, -limit), limit)

    def _clear_errors(self, _msg: codec.ClearErrors) -> None:
        self.axis_error = 0

    def _estop(self, _msg: codec.Estop) -> None:
        self.axis_state = AxisState.IDLE
        self.axis_error |= codec.estop_bit(self.firmware)

    def _answer(self, msg: codec.Request) -> None:
        if msg.cmd == CmdId.CLEAR_ERRORS:  # zero-length Clear_Errors on 0.6
            self._clear_errors(codec.ClearErrors())
            return
        reply = self._reply_for(msg.cmd)
        if reply is not None:
            self._send(self._encode(reply))
