"""The ODrive CANSimple protocol as one object (:class:`~dobhil.drives.plugin.DriveProtocol`),
registered as the entry point ``odrive`` of the group ``dobhil.drives`` (``pyproject.toml``)."""

from __future__ import annotations

import struct

from dobhil.drives.odrive import codec
from dobhil.drives.odrive.codec import AxisState, CmdId, Firmware
from dobhil.drives.odrive.drive import ODriveDrive
from dobhil.drives.odrive.emulator import EmulatedODrive
from dobhil.drives.plugin import DriveProtocol, FeedbackField, FrameIds
from dobhil.drives.profile import DriveProfile
from dobhil.errors import CodecError

#: the feedback values a fault may corrupt -> their slot in Get_Encoder_Estimates
_ESTIMATE_SLOTS = {"position": "position_rad", "velocity": "velocity_rad_s"}

__all__ = ["ODriveProtocol"]


class ODriveProtocol(DriveProtocol):
    name = "odrive"
    title = "ODrive CANSimple"

    @property
    def drive_class(self) -> type[ODriveDrive]:
        return ODriveDrive

    @property
    def emulator_class(self) -> type[EmulatedODrive]:
        return EmulatedODrive

    def state_name(self, profile: DriveProfile, code: int) -> str:
        """The heartbeat's Axis_State by its name (``CLOSED_LOOP_CONTROL``)."""
        return AxisState(code).name if code in {m.value for m in AxisState} else super().state_name(profile, code)

    def error_text(self, profile: DriveProfile, code: int) -> str:
        """The heartbeat's Axis_Error with the bit names of the profile's firmware."""
        try:
            return codec.describe_errors(code, Firmware.parse(profile.firmware))
        except CodecError:   # a firmware the codec does not know: the bits unnamed
            return super().error_text(profile, code)

    def frame_ids(self, profile: DriveProfile) -> FrameIds:
        """The node's 32 command ids, ``node_id << 5 | cmd`` (ODrive docs, CAN Protocol:
        "Messages"): every one is the node's own."""
        return FrameIds(frozenset(codec.arbitration_id(profile.node_id, cmd) for cmd in range(32)))

    def feedback_field(self, profile: DriveProfile, name: str) -> FeedbackField | None:
        """``position``/``velocity`` in Get_Encoder_Estimates (the codec's table for the
        profile's firmware: both share the layout, two little-endian floats)."""
        slot = _ESTIMATE_SLOTS.get(name)
        if slot is None:
            return None
        spec = codec.spec_for(CmdId.GET_ENCODER_ESTIMATES, codec.Firmware.parse(profile.firmware))
        formats = spec.struct.format.lstrip("<")
        index = [getattr(s, "name", None) for s in spec.slots].index(slot)
        return FeedbackField(arbitration_id=codec.arbitration_id(profile.node_id, CmdId.GET_ENCODER_ESTIMATES),
                             offset=struct.calcsize("<" + formats[:index]), fmt="<" + formats[index])
