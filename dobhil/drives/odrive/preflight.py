"""ODrive CAN Simple part of the preflight (:mod:`dobhil.drives.preflight`).

- Status = Heartbeat (0x01), motion = Get_Encoder_Estimates (0x09), both cyclic.
- Firmware version: Get_Version (0x00, 0.6 only) requested by RTR. Firmware 0.5.6 has no
  Get_Version (0x00 is the CANopen NMT id there, ignored), so silence is what a 0.5
  drive gives; its heartbeat says 0.5 another way: byte 7 is the controller flag byte
  with Trajectory_Done in bit 7, which starts at 1 (``controller.hpp``) and stays 1 in
  torque control, while byte 7 of a 0.6 heartbeat is reserved (0).
- Drive-side setting names: 0.6 ``<axis>.config.can.{node_id, encoder_msg_rate_ms,
  heartbeat_msg_rate_ms}``, 0.5 ``<axis>.config.can.{node_id, encoder_rate_ms,
  heartbeat_rate_ms}`` (0.5.6 ``odrive-interface.yaml``), ``<axis>`` being e.g.
  ``odrv0.axis0`` in odrivetool.
- State and errors from the heartbeat: an axis already in CLOSED_LOOP_CONTROL is a
  mismatch on which ``dobhil run`` refuses to enable (someone else drives it); errors are
  notes, since enabling clears them, except that the watchdog bit of an idle axis is
  expected (the watchdog runs in every state) and the node's summary says so.
- Bus budget per loop period: the torque command (Set_Input_Torque), the encoder
  estimates every ``feedback_period`` and the heartbeat's share, each at the DLC of the
  codec's table (the DBC's 8 bytes).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import can

from dobhil.drives.bus_load import CycleFrame
from dobhil.drives.odrive import codec
from dobhil.drives.odrive.codec import AxisState, CmdId, CmdId06, Firmware
from dobhil.drives.preflight import Finding, NodeReport, Observation, PreflightProbe, Setting, Severity, Stream
from dobhil.drives.profile import DriveProfile
from dobhil.errors import CodecError

__all__ = ["ODrivePreflight", "heartbeat_family"]

_SETTINGS = {
    Firmware.V0_6: {Setting.NODE_ID: "node_id", Setting.MOTION_RATE: "encoder_msg_rate_ms",
                    Setting.STATUS_RATE: "heartbeat_msg_rate_ms"},
    Firmware.V0_5: {Setting.NODE_ID: "node_id", Setting.MOTION_RATE: "encoder_rate_ms",
                    Setting.STATUS_RATE: "heartbeat_rate_ms"},
}
_STREAMS = {CmdId.HEARTBEAT: Stream.STATUS, CmdId.GET_ENCODER_ESTIMATES: Stream.MOTION,
            CmdId06.GET_VERSION: Stream.VERSION}


def heartbeat_family(data: bytes) -> Firmware | None:
    """Firmware 0.5 if byte 7 carries the 0.5 Trajectory_Done bit, else unknown."""
    return Firmware.V0_5 if len(data) >= 8 and data[7] & 0x80 else None


class ODrivePreflight(PreflightProbe):
    #: the encoder estimates stream every feedback_period whatever the loop does, and a loop
    #: needs one per period: fewer frames means both slower
    budget_fewer = ("a slower loop and encoder stream together (loop.period and feedback_period, "
                    "<axis>.config.can.encoder_msg_rate_ms to match)")

    def __init__(self, profile: DriveProfile) -> None:
        super().__init__(profile)
        self.firmware = Firmware.parse(profile.firmware)

    def requests(self, node: int) -> Sequence[can.Message]:
        if not 0 <= node <= codec.MAX_NODE_ID:
            return ()
        return (codec.encode(codec.Request(CmdId06.GET_VERSION), node_id=node, firmware=Firmware.V0_6),)

    def observe(self, msg: can.Message) -> Observation | None:
        if msg.is_extended_id or msg.is_remote_frame or not 0 <= msg.arbitration_id <= 0x7FF:
            return None
        node, cmd = codec.split_id(msg.arbitration_id)
        stream = _STREAMS.get(cmd)  # type: ignore[call-overload]
        if stream is None or len(msg.data) < 8:
            return None
        return Observation(node, stream, bytes(msg.data))

    def setting(self, which: Setting) -> str:
        return f"<axis>.config.can.{_SETTINGS[self.firmware][which]}"

    def setting_value(self, which: Setting, value: float) -> str:
        """Rates in whole milliseconds, as the drive takes them (``encoder_msg_rate_ms`` is
        an integer; 0 turns the stream off), rounded down: a faster stream still serves."""
        if which is Setting.NODE_ID:
            return str(int(value))
        return str(max(1, math.floor(value * 1e3 + 1e-6)))

    def shortest_period(self, which: Setting) -> float:
        """1 ms: the shortest rate in whole milliseconds (0 is off)."""
        return 0.0 if which is Setting.NODE_ID else 1e-3

    def motion_name(self) -> str:
        return "encoder estimates"

    def cycle_frames(self, period: float) -> Sequence[CycleFrame]:
        """Torque command per loop period; encoder estimates and heartbeat at the
        profile's periods (the drive sends them by itself, whatever the loop does)."""
        def dlc(cmd: CmdId) -> int:
            return codec.spec_for(cmd, self.firmware).dlc
        profile = self.profile
        frames = [CycleFrame("torque command", dlc(CmdId.SET_INPUT_TORQUE))]
        if profile.feedback_period:   # ODrive's rules require both periods; None only in code
            frames.append(CycleFrame("encoder estimates", dlc(CmdId.GET_ENCODER_ESTIMATES),
                                     every=profile.feedback_period))
        if profile.heartbeat_period:
            frames.append(CycleFrame("heartbeat", dlc(CmdId.HEARTBEAT), every=profile.heartbeat_period))
        return tuple(frames)

    def status_name(self) -> str:
        return "heartbeat"

    # -- the node's firmware, state and errors ---------------------------------

    def _version(self, node: NodeReport) -> codec.Version | None:
        if node.version_data is None:
            return None
        try:
            version = codec.decode(codec.arbitration_id(node.node, CmdId06.GET_VERSION), node.version_data)
        except CodecError:
            return None
        return version if isinstance(version, codec.Version) else None

    def _family(self, node: NodeReport) -> tuple[Firmware | None, str]:
        version = self._version(node)
        if version is not None:
            try:
                return Firmware.parse(version.firmware_text), f"{version.firmware_text} (Get_Version)"
            except CodecError:
                return None, f"{version.firmware_text} (Get_Version)"
        if heartbeat_family(node.status_data) is Firmware.V0_5:
            return Firmware.V0_5, "0.5 (heartbeat layout; no Get_Version reply)"
        return None, "unknown (no Get_Version reply)"

    def _heartbeat(self, node: NodeReport, firmware: Firmware) -> codec.Heartbeat | None:
        if not node.status_data:
            return None
        try:
            hb = codec.decode(codec.arbitration_id(node.node, CmdId.HEARTBEAT), node.status_data, firmware)
        except CodecError:
            return None
        return hb if isinstance(hb, codec.Heartbeat) else None

    def node_summary(self, node: NodeReport) -> str:
        family, firmware_text = self._family(node)
        hb = self._heartbeat(node, family or self.firmware)
        state = "no heartbeat" if hb is None else (
            f"{_state_name(hb.axis_state)}, error {codec.describe_heartbeat(hb, family or self.firmware)}"
            + self._expected_watchdog(hb, family or self.firmware))
        return f"{state}; firmware {firmware_text}"

    def _expected_watchdog(self, hb: codec.Heartbeat, firmware: Firmware) -> str:
        """Words for a watchdog bit that is no fault: on an idle axis with the watchdog on,
        nothing feeds it (the preflight sends no commands), so it expires; enable clears it."""
        watchdog = codec.watchdog_bit(firmware)
        if (hb.axis_error & watchdog and not hb.axis_error & ~watchdog and hb.axis_state == AxisState.IDLE
                and self.profile.watchdog_timeout > 0):
            return " (expected: the watchdog is on and nothing feeds an idle axis; enable clears it)"
        return ""

    def node_findings(self, node: NodeReport) -> list[Finding]:
        family, firmware_text = self._family(node)
        out: list[Finding] = []
        if family is not None and family is not self.firmware:
            out.append(Finding(Severity.MISMATCH,
                               f"node {node.node} runs firmware {firmware_text}, profile "
                               f"{self.profile.name or 'odrive'!r} is for {self.firmware.label}: use drive.profile "
                               f"odrive-{family.label} (--set drive.profile=odrive-{family.label})"))
        elif family is None and self.firmware is Firmware.V0_6 and node.status_data:
            out.append(Finding(Severity.NOTE, f"node {node.node} did not answer Get_Version: firmware "
                                              "0.5 (which has none) or a slow reply"))
        hb = self._heartbeat(node, family or self.firmware)
        if hb is None:
            return out
        if hb.axis_state == AxisState.CLOSED_LOOP_CONTROL:
            out.append(Finding(Severity.MISMATCH,
                               f"node {node.node} is already in CLOSED_LOOP_CONTROL: another host may be "
                               "driving it; set it IDLE first", refuses_run=True))
        watchdog = codec.watchdog_bit(family or self.firmware)
        if hb.axis_error & ~watchdog:
            out.append(Finding(Severity.NOTE, f"node {node.node} reports error "
                                              f"{codec.describe_heartbeat(hb, family or self.firmware)}; "
                                              "enable clears it -- if it comes back, the drive has a fault"))
        elif hb.axis_error & watchdog and self.profile.watchdog_timeout == 0:
            out.append(Finding(Severity.MISMATCH,
                               f"node {node.node}'s watchdog is on but profile watchdog_timeout is 0: set "
                               f"watchdog_timeout in the profile to the drive's <axis>.config.watchdog_timeout"))
        elif self._watchdog_looks_off(node, hb, watchdog):
            out.append(Finding(Severity.MISMATCH,
                               f"node {node.node}'s watchdog looks off (idle, unfed for "
                               f"{node.window:g} s, no WATCHDOG_TIMER_EXPIRED): set <axis>.config.enable_watchdog "
                               f"= True and <axis>.config.watchdog_timeout = {self.profile.watchdog_timeout:g}"))
        return out

    def _watchdog_looks_off(self, node: NodeReport, hb: codec.Heartbeat, watchdog: int) -> bool:
        """The watchdog runs in every state (0.5.6 ``main.cpp``) and nothing this preflight
        sends feeds it on 0.6 (0.5: the one Get_Version request does): an idle axis whose
        last heartbeat came more than two timeouts after listening began shows the bit."""
        timeout = self.profile.watchdog_timeout
        heartbeat = node.status.period or self.profile.heartbeat_period or 0.0
        return (timeout > 0 and hb.axis_state == AxisState.IDLE and not hb.axis_error & watchdog
                and node.status.count >= 2 and node.window >= 2 * timeout + 2 * heartbeat)


def _state_name(state: int) -> str:
    return state.name if isinstance(state, AxisState) else f"state {state}"
