"""The CANopen CiA 402 protocol as one object (:class:`~dobhil.drives.plugin.DriveProtocol`),
registered as the entry point ``cia402`` of the group ``dobhil.drives`` (``pyproject.toml``)."""

from __future__ import annotations

from dobhil.drives.cia402.codec import PowerState
from dobhil.drives.cia402.drive import CiA402Drive, emcy_text
from dobhil.drives.cia402.emulator import EmulatedCiA402
from dobhil.drives.plugin import DriveProtocol
from dobhil.drives.profile import DriveProfile

__all__ = ["CiA402Protocol"]


class CiA402Protocol(DriveProtocol):
    name = "cia402"
    title = "CANopen CiA 402"

    @property
    def drive_class(self) -> type[CiA402Drive]:
        return CiA402Drive

    @property
    def emulator_class(self) -> type[EmulatedCiA402]:
        return EmulatedCiA402

    def state_name(self, profile: DriveProfile, code: int) -> str:
        """The power state the statusword reports (``operation enabled``)."""
        return PowerState(code).text if code in PowerState._value2member_map_ else super().state_name(profile, code)

    def error_text(self, profile: DriveProfile, code: int) -> str:
        """The last EMCY's error code with canopen's description of its CiA 301 class."""
        return f"EMCY 0x{code:04X} ({emcy_text(code)})" if code else "none"
