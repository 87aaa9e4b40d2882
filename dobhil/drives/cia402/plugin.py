"""The CANopen CiA 402 protocol as one object (:class:`~dobhil.drives.plugin.DriveProtocol`),
registered as the entry point ``cia402`` of the group ``dobhil.drives`` (``pyproject.toml``)."""

from __future__ import annotations

from dobhil.drives.cia402.drive import CiA402Drive
from dobhil.drives.cia402.eds import load_od
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

    def check_files(self, profile: DriveProfile) -> None:
        load_od(profile)   # the drive's own reading and check of the EDS
