"""Emulated drives by protocol name: built-in ones and entry points (like
:mod:`dobhil.drives.registry`).

An emulated drive is found in :data:`EMULATOR_CLASSES` (built in, so an uninstalled source
tree works) or as an entry point ``<protocol>.emulator`` of the group ``dobhil.drives``
of any installed distribution; a built-in one wins over an entry point of the same name.
"""

from __future__ import annotations

import uuid
from collections.abc import Mapping
from types import MappingProxyType
from typing import Any

import can

from dobhil.drives.profile import DriveProfile
from dobhil.drives.registry import EMULATOR_SUFFIX, load_object, plugin_entry_points
from dobhil.drives.emulated import EmulatedDrive, PlantLike
from dobhil.errors import ConfigError

__all__ = ["EMULATOR_CLASSES", "emulated_protocols", "emulator_class", "make_emulated_drive",
           "private_virtual_channel"]

#: built-in emulated drives: protocol name -> (module, class name)
EMULATOR_CLASSES: Mapping[str, tuple[str, str]] = MappingProxyType({
    "odrive": ("dobhil.emulator.odrive", "EmulatedODrive"),
    "cia402": ("dobhil.emulator.cia402", "EmulatedCiA402"),
    "mit": ("dobhil.emulator.mit", "EmulatedMit"),
})


def emulated_protocols() -> tuple[str, ...]:
    """Every protocol with an emulated drive: built-in and entry points, sorted."""
    names = set(EMULATOR_CLASSES)
    names.update(n.removesuffix(EMULATOR_SUFFIX) for n in plugin_entry_points() if n.endswith(EMULATOR_SUFFIX))
    return tuple(sorted(names))


def emulator_class(protocol: str) -> type[EmulatedDrive]:
    """The EmulatedDrive subclass of ``protocol``; ConfigError (one line) if none or broken."""
    builtin = EMULATOR_CLASSES.get(protocol)
    ep = None if builtin is not None else plugin_entry_points().get(protocol + EMULATOR_SUFFIX)
    if builtin is None and ep is None:
        raise ConfigError(f"no emulator for protocol {protocol!r}; "
                          f"emulated: {', '.join(emulated_protocols())}")
    cls = load_object(protocol + EMULATOR_SUFFIX, builtin, ep)
    if not (isinstance(cls, type) and issubclass(cls, EmulatedDrive)):
        raise ConfigError(f"emulator of protocol {protocol!r} is not a dobhil EmulatedDrive class")
    return cls


def make_emulated_drive(bus: can.BusABC, profile: DriveProfile, plant: PlantLike,
                        **kwargs: Any) -> EmulatedDrive:
    """The emulator of ``profile.protocol`` on ``bus`` driving ``plant``."""
    return emulator_class(profile.protocol)(bus, profile, plant, **kwargs)


def private_virtual_channel() -> str:
    """A virtual-bus channel name no other run in this process uses.

    It ends in a letter: python-can's log writers read trailing digits of a channel name
    as the channel number (``can.util.channel2int``), and BLF stores it in 16 bits, so a
    name ending in many digits would make ``can.logconvert run.mcap run.blf`` fail."""
    return f"dobhil-{uuid.uuid4().hex[:12]}-private"
