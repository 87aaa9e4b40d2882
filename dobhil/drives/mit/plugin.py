"""The MIT mode protocol as one object (:class:`~dobhil.drives.plugin.DriveProtocol`),
registered as the entry point ``mit`` of the group ``dobhil.drives`` (``pyproject.toml``)."""

from __future__ import annotations

from dobhil.drives.mit.drive import MitDrive
from dobhil.drives.mit.emulator import EmulatedMit
from dobhil.drives.plugin import DriveProtocol

__all__ = ["MitProtocol"]


class MitProtocol(DriveProtocol):
    name = "mit"
    title = "MIT mode"

    @property
    def drive_class(self) -> type[MitDrive]:
        return MitDrive

    @property
    def emulator_class(self) -> type[EmulatedMit]:
        return EmulatedMit
