"""The ODrive CANSimple protocol as one object (:class:`~dobhil.drives.plugin.DriveProtocol`),
registered as the entry point ``odrive`` of the group ``dobhil.drives`` (``pyproject.toml``)."""

from __future__ import annotations

from dobhil.drives.odrive.drive import ODriveDrive
from dobhil.drives.odrive.emulator import EmulatedODrive
from dobhil.drives.plugin import DriveProtocol

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
