"""Emulated drives by protocol name, imported lazily (like :mod:`dobhil.drives.registry`).

A new protocol's emulator is one new module plus one line in :data:`EMULATOR_CLASSES`.
"""

from __future__ import annotations

import importlib
import uuid
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
    "cia402": ("dobhil.emulator.cia402", "EmulatedCiA402"),
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


def private_virtual_channel() -> str:
    """A virtual-bus channel name no other run in this process uses.

    It ends in a letter: python-can's log writers read trailing digits of a channel name
    as the channel number (``can.util.channel2int``), and BLF stores it in 16 bits, so a
    name ending in many digits would make ``can.logconvert run.mcap run.blf`` fail."""
    return f"dobhil-{uuid.uuid4().hex[:12]}-private"
