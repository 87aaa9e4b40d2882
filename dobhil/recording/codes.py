"""The drive's own state and error codes in its protocol's words, for the log and its report.

A cycle record holds the drive's codes as numbers (``protocol_state``, ``protocol_error``:
cheap on the loop thread); the writer process names them once per distinct code through
the run's protocol object (:meth:`~dobhil.drives.plugin.DriveProtocol.state_name`,
:meth:`~dobhil.drives.plugin.DriveProtocol.error_text`), so that ``/drive/feedback`` carries
the names beside the codes (Foxglove's State Transitions panel plots a string by its value).
The report names the codes of a log written before the names were recorded the same way,
from the profile of the run's recorded config.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Final

from dobhil.errors import DobhilError

if TYPE_CHECKING:
    from dobhil.drives.plugin import DriveProtocol
    from dobhil.drives.profile import DriveProfile

__all__ = ["NO_STATE", "ProtocolCodes"]

#: ``protocol_state`` before the drive reported a state, or of a protocol that has none
NO_STATE: Final = -1


class ProtocolCodes:
    """Names of one drive's codes (``profile``'s protocol), each code named once; without
    a profile, or for a protocol not installed where the log is read, the codes as numbers.
    Picklable: the writer process gets it with the log's metadata."""

    def __init__(self, profile: DriveProfile | None = None) -> None:
        self.profile = profile
        self._states: dict[int, str] = {}
        self._errors: dict[int, str] = {}
        self._found: tuple[DriveProtocol | None] | None = None   # the protocol, once looked up

    def __getstate__(self) -> DriveProfile | None:
        return self.profile   # the names are made again where they are used

    def __setstate__(self, profile: DriveProfile | None) -> None:
        self.__init__(profile)  # type: ignore[misc]

    def prepare(self) -> None:
        """Look the protocol up now (its modules imported): the writer process does it
        while it opens the log, before the run starts, not at the first message."""
        self._protocol()

    def state_name(self, code: int) -> str:
        name = self._states.get(code)
        if name is None:
            name = self._states[code] = self._name(code, state=True)
        return name

    def error_text(self, code: int) -> str:
        text = self._errors.get(code)
        if text is None:
            text = self._errors[code] = self._name(code, state=False)
        return text

    def _name(self, code: int, *, state: bool) -> str:
        protocol, profile = self._protocol(), self.profile
        name = str(code) if state else (f"0x{code:X}" if code else "none")
        if protocol is not None and profile is not None:
            try:
                name = protocol.state_name(profile, code) if state else protocol.error_text(profile, code)
            except DobhilError:   # e.g. a model table gone where the log is read: the number
                pass
        # no state frame yet, or a protocol without states that does not say so itself
        return "not reported" if state and code == NO_STATE and name == str(code) else name

    def _protocol(self) -> DriveProtocol | None:
        if self._found is None:
            self._found = (self._lookup(),)
        return self._found[0]

    def _lookup(self) -> DriveProtocol | None:
        if self.profile is None:
            return None
        from dobhil.drives.registry import protocol
        try:
            return protocol(self.profile.protocol)
        except DobhilError:   # a plugin's protocol not installed here: its codes unnamed
            return None
