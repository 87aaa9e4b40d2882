"""Drive base class and protocol implementations (codecs are pure, I/O lives in drives).

- :mod:`dobhil.drives.base`      :class:`Drive` (public API, timeouts, safety) and its records
- :mod:`dobhil.drives.profile`   :class:`DriveProfile` and its validator
- :mod:`dobhil.drives.load`      :func:`load_profile` (``drivers/*.yaml``) with the registry's protocols
- :mod:`dobhil.drives.registry`  :func:`make_drive` picks the protocol module lazily by name
- :mod:`dobhil.drives.odrive`    ODrive CAN Simple (firmware 0.6 default, 0.5)
"""

from __future__ import annotations

from dobhil.drives.base import Drive, DriveState, DriveStatus, Feedback
from dobhil.drives.load import load_profile
from dobhil.drives.profile import DriveProfile
from dobhil.drives.registry import make_drive

__all__ = [
    "Drive",
    "DriveProfile",
    "DriveState",
    "DriveStatus",
    "Feedback",
    "load_profile",
    "make_drive",
]
