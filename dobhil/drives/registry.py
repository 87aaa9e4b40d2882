"""Drive implementations by protocol name, imported lazily (python-can interface style).

A new protocol (CiA 402, MIT) is one new module plus one line in :data:`DRIVE_CLASSES`;
protocol modules never import each other.
"""

from __future__ import annotations

import importlib
from collections.abc import Mapping
from types import MappingProxyType
from typing import TYPE_CHECKING, Any

import can

from dobhil.drives.base import Drive
from dobhil.drives.profile import DriveProfile
from dobhil.errors import ConfigError

if TYPE_CHECKING:
    from dobhil.drives.preflight import PreflightProbe

__all__ = ["DRIVE_CLASSES", "drive_class", "make_drive", "preflight_probe"]

#: protocol name -> (module, class name)
DRIVE_CLASSES: Mapping[str, tuple[str, str]] = MappingProxyType({
    "odrive": ("dobhil.drives.odrive.drive", "ODriveDrive"),
})


def drive_class(protocol: str) -> type[Drive]:
    """The Drive subclass of ``protocol``; ConfigError if unknown."""
    try:
        module_name, class_name = DRIVE_CLASSES[protocol]
    except KeyError:
        raise ConfigError(
            f"protocol: expected one of {sorted(DRIVE_CLASSES)}, got {protocol!r}"
        ) from None
    cls = getattr(importlib.import_module(module_name), class_name)
    if not (isinstance(cls, type) and issubclass(cls, Drive)):
        raise ConfigError(f"protocol {protocol!r}: {module_name}.{class_name} is not a Drive")
    return cls


def make_drive(bus: can.BusABC, profile: DriveProfile, **kwargs: Any) -> Drive:
    """Build the drive of ``profile.protocol`` on ``bus`` (kwargs go to its constructor)."""
    return drive_class(profile.protocol)(bus, profile, **kwargs)


def preflight_probe(profile: DriveProfile) -> PreflightProbe | None:
    """The preflight part of ``profile.protocol`` (None: that protocol has none yet)."""
    return drive_class(profile.protocol).preflight_probe(profile)
