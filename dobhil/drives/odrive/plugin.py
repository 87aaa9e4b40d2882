"""The ODrive CANSimple protocol as one object (:class:`~dobhil.drives.plugin.DriveProtocol`),
registered as the entry point ``odrive`` of the group ``dobhil.drives`` (``pyproject.toml``)."""

from __future__ import annotations

from dobhil.drives.odrive import codec
from dobhil.drives.odrive.codec import AxisState, Firmware
from dobhil.drives.odrive.drive import ODriveDrive
from dobhil.drives.odrive.emulator import EmulatedODrive
from dobhil.drives.plugin import DriveProtocol
from dobhil.drives.profile import DriveProfile
from dobhil.errors import CodecError

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
        return AxisState(code).name if code in AxisState._value2member_map_ else super().state_name(profile, code)

    def error_text(self, profile: DriveProfile, code: int) -> str:
        """The heartbeat's Axis_Error with the bit names of the profile's firmware."""
        try:
            return codec.describe_errors(code, Firmware.parse(profile.firmware))
        except CodecError:   # a firmware the codec does not know: the bits unnamed
            return super().error_text(profile, code)
