"""ODrive CAN Simple drive (firmware 0.6 default, 0.5 via the profile's ``firmware``).

Enable: Set_Input_Torque(0) (feeds the watchdog), Clear_Errors,
Set_Controller_Mode(TORQUE_CONTROL, PASSTHROUGH), Set_Input_Torque(0),
Set_Axis_State(CLOSED_LOOP_CONTROL); confirmed by a heartbeat in CLOSED_LOOP_CONTROL with
Axis_Error 0. Disable: Set_Input_Torque(0), Set_Axis_State(IDLE); on 0.6 confirmed by the
heartbeat it asks for by RTR, on 0.5 by the cyclic one. Feedback: the cyclic
Get_Encoder_Estimates and Heartbeat frames (rates configured on the drive to match the
profile). Layouts and error bits: :mod:`dobhil.drives.odrive.codec`.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from typing import TYPE_CHECKING, ClassVar

import can

from dobhil.drives.base import Clock, Drive, DriveEvent, HostTimeout, MotionEvent, StateEvent
from dobhil.drives.odrive import codec
from dobhil.drives.odrive.codec import AxisState, CmdId, ControlMode, Firmware, InputMode
from dobhil.drives.profile import DriveProfile, ProtocolRules, Rule
from dobhil.errors import CodecError, ConfigError

if TYPE_CHECKING:
    from dobhil.drives.preflight import PreflightProbe

__all__ = ["ODriveDrive"]

_NO_EVENTS: tuple[DriveEvent, ...] = ()


def _state_name(state: int) -> str:
    return state.name if isinstance(state, AxisState) else f"state {state}"


class ODriveDrive(Drive):
    protocol: ClassVar[str] = "odrive"
    active_state_text: ClassVar[str] = "CLOSED_LOOP_CONTROL"
    disabled_state_text: ClassVar[str] = "IDLE"

    #: node ids have 6 bits (``node_id << 5 | cmd``); the firmware selects layouts;
    #: the drive streams encoder estimates and heartbeats, so it needs both periods.
    #: Its section (``odrive:``) has no keys yet: accepted when empty.
    profile_rules: ClassVar[ProtocolRules] = ProtocolRules(
        section={},
        common={
            "node_id": Rule((int,), f"0..{codec.MAX_NODE_ID} for ODrive",
                            lambda v: 0 <= v <= codec.MAX_NODE_ID),
            "firmware": Rule((str,), "'0.5' or '0.6' for ODrive", lambda v: _parses(v)),
        },
        requires=frozenset({"feedback_period", "heartbeat_period"}),
    )

    def __init__(
        self, bus: can.BusABC, profile: DriveProfile, *, clock: Clock = time.monotonic,
        reset_faults: bool = False,
    ) -> None:
        # reset_faults changes nothing here: the enable always sends Clear_Errors (an
        # ODrive latches errors until told, and the handshake has always cleared them)
        super().__init__(bus, profile, clock=clock, reset_faults=reset_faults)
        self._firmware = _firmware_of(profile)
        if not 0 <= profile.node_id <= codec.MAX_NODE_ID:
            raise ConfigError(f"node_id: expected 0..63 for ODrive, got {profile.node_id}")
        self._watchdog_bit = codec.watchdog_bit(self._firmware)
        self._heartbeat_id = codec.arbitration_id(profile.node_id, CmdId.HEARTBEAT)
        self._encoder_id = codec.arbitration_id(profile.node_id, CmdId.GET_ENCODER_ESTIMATES)
        self._heartbeat_spec = codec.spec_for(CmdId.HEARTBEAT, self._firmware)
        self._encoder_spec = codec.spec_for(CmdId.GET_ENCODER_ESTIMATES, self._firmware)
        self._torque_spec = codec.spec_for(CmdId.SET_INPUT_TORQUE, self._firmware)
        self._torque_msg = self._encode(codec.SetInputTorque(0.0))

    @property
    def frame_ids(self) -> frozenset[int]:
        """The node's 32 command ids (``node_id << 5 | cmd``)."""
        return frozenset(codec.arbitration_id(self.node_id, cmd) for cmd in range(32))

    @property
    def firmware(self) -> Firmware:
        return self._firmware

    def _encode(self, msg: object) -> can.Message:
        return codec.encode(msg, node_id=self.node_id, firmware=self._firmware)

    # -- hooks ----------------------------------------------------------------

    def _enable_start(self) -> Sequence[can.Message]:
        # Set_Input_Torque(0) first feeds the watchdog: it runs in every axis state
        # (0.5.6 main.cpp), so an idle drive nobody fed shows WATCHDOG_TIMER_EXPIRED, and
        # on 0.6 only setpoints are known to feed it -- cleared without a feed, the bit
        # could come back before Set_Axis_State arrives and the request be refused.
        return (
            self._encode(codec.SetInputTorque(0.0)),
            self._encode(codec.ClearErrors()),
            self._encode(codec.SetControllerMode(ControlMode.TORQUE_CONTROL, InputMode.PASSTHROUGH)),
            self._encode(codec.SetInputTorque(0.0)),
            self._encode(codec.SetAxisState(AxisState.CLOSED_LOOP_CONTROL)),
        )

    def _disable_frames(self) -> Sequence[can.Message]:
        return (self._encode(codec.SetAxisState(AxisState.IDLE)),)

    def _keepalive_frames(self) -> Sequence[can.Message]:
        """Zero torque (feeds the watchdog) and, on 0.6, an RTR heartbeat request (fast
        confirmation; firmware 0.5.6 ignores heartbeat RTRs, so 0.5 waits for the cyclic one)."""
        if self._firmware is Firmware.V0_5:
            return (self._torque_frame(0.0),)
        return (self._torque_frame(0.0), self._encode(codec.Request(CmdId.HEARTBEAT)))

    def _status_request_frames(self) -> Sequence[can.Message]:
        """On 0.6 an RTR heartbeat request, as the enable's keepalive sends: the safe stop's
        confirmation then comes within milliseconds, not at the next cyclic heartbeat (up
        to ``heartbeat_period`` later). 0.5.6 ignores heartbeat RTRs: none."""
        if self._firmware is Firmware.V0_5:
            return ()
        return (self._encode(codec.Request(CmdId.HEARTBEAT)),)

    @classmethod
    def preflight_probe(cls, profile: DriveProfile) -> PreflightProbe:
        from dobhil.drives.odrive.preflight import ODrivePreflight
        return ODrivePreflight(profile)

    def _host_watch_of(self, event: StateEvent | None) -> HostTimeout | None:
        """The axis watchdog (``watchdog_timeout``; 0: off), fed by the setpoints; its
        expiry is the WATCHDOG_TIMER_EXPIRED bit, which reaches the host with the next
        heartbeat."""
        timeout = self.profile.watchdog_timeout
        if timeout <= 0 or (event is not None and not event.watchdog_tripped):
            return None
        return HostTimeout("watchdog", timeout, reported_within=self.profile.heartbeat_period or 0.0)

    def _torque_frame(self, tau_nm: float) -> can.Message:
        self._torque_spec.pack_into(self._torque_msg.data, tau_nm)
        return self._torque_msg

    def _decode(self, msg: can.Message) -> Sequence[DriveEvent]:
        arb = msg.arbitration_id
        if msg.is_extended_id or msg.is_remote_frame or msg.is_error_frame:
            return _NO_EVENTS
        try:
            if arb == self._encoder_id and len(msg.data):
                position, velocity = self._encoder_spec.unpack_si(msg.data)
                return (MotionEvent(position, velocity),)
            if arb == self._heartbeat_id and len(msg.data):
                return (self._state_event(self._heartbeat_spec.decode_data(msg.data)),)
        except CodecError:
            return _NO_EVENTS  # a malformed frame is not feedback; the next one will be
        return _NO_EVENTS

    def _state_event(self, hb: codec.Heartbeat) -> StateEvent:
        return StateEvent(
            active=hb.axis_state == AxisState.CLOSED_LOOP_CONTROL,
            error_code=hb.axis_error,
            watchdog_tripped=bool(hb.axis_error & self._watchdog_bit),
            state_text=_state_name(hb.axis_state),
            error_text=codec.describe_heartbeat(hb, self._firmware),
            state=int(hb.axis_state),
        )


def _parses(firmware: str) -> bool:
    try:
        Firmware.parse(firmware)
    except CodecError:
        return False
    return True


def _firmware_of(profile: DriveProfile) -> Firmware:
    try:
        return Firmware.parse(profile.firmware)
    except CodecError:
        raise ConfigError(
            f"firmware: expected '0.5' or '0.6' for ODrive, got {profile.firmware!r}"
        ) from None
