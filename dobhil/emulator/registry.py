"""Emulated drives by protocol name, imported lazily (like :mod:`dobhil.drives.registry`).

A new protocol's emulator is one new module plus one line in :data:`EMULATOR_CLASSES`.
"""

from __future__ import annotations

import importlib
from collections.abc import Mapping
from types import MappingProxyType
from typing import Any

import can

from dobhil.drives.profile import DriveProfile
from dobhil.emulator.protocol import EmulatedDrive, PlantLike
from dobhil.errors import ConfigError

#: protocol name -> (module, class name)
EMULATOR_CLASSES: Mapping[str, tuple[str, str]] = MappingProxyType({
    "odrive": ("dobhil.emulator.odrive", "EmulatedODrive"),
})


def make_emulated_drive(bus: can.BusABC, profile: DriveProfile, plant: PlantLike,
                        **kwargs: Any) -> EmulatedDrive:
    """The emulator of ``profile.protocol`` on ``bus`` driving ``plant``."""
    try:
        module_name, class_name = EMULATOR_CLASSES[profile.protocol]
    except KeyError:
        raise ConfigError(f"no emulator for protocol {profile.protocol!r}; "
                          f"emulated: {', '.join(sorted(EMULATOR_CLASSES))}") from None
    cls = getattr(importlib.import_module(module_name), class_name)
    return cls(bus, profile, plant, **kwargs)
