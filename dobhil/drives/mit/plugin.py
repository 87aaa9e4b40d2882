"""The MIT mode protocol as one object (:class:`~dobhil.drives.plugin.DriveProtocol`),
registered as the entry point ``mit`` of the group ``dobhil.drives`` (``pyproject.toml``)."""

from __future__ import annotations

from dobhil.drives.mit.drive import MitDrive
from dobhil.drives.mit.emulator import EmulatedMit
from dobhil.drives.mit.replies import DAMIAO_ENABLED, MitFault
from dobhil.drives.mit.rules import model_of
from dobhil.drives.plugin import DriveProtocol
from dobhil.drives.profile import DriveProfile

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

    def state_name(self, profile: DriveProfile, code: int) -> str:
        """A Damiao reply's state nibble in its model's words; CubeMars and Mini-Cheetah
        replies carry no state (-1)."""
        if code < 0:
            return "none (the reply carries no mode)"
        named = {0: "disabled", DAMIAO_ENABLED: "enabled", **model_of(profile).layout.states}
        return named.get(code, f"state 0x{code:X}")

    def error_text(self, profile: DriveProfile, code: int) -> str:
        """The reply's error byte (or Damiao fault nibble) in its model's words, or what
        dobhil read from the reply's values (:class:`~dobhil.drives.mit.replies.MitFault`)."""
        if code in MitFault._value2member_map_:
            return MitFault(code).name.lower().replace("_", " ")
        layout = model_of(profile).layout
        text = layout.errors.get(code) if "error" in layout.extra else layout.states.get(code)
        return text if code and text else super().error_text(profile, code)
