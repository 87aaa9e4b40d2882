"""Emulated drives by protocol name: each protocol's ``DriveProtocol.emulator_class``
(:mod:`dobhil.drives.registry`)."""

from __future__ import annotations

import uuid
from typing import Any

import can

from dobhil.drives.emulated import EmulatedDrive, PlantLike
from dobhil.drives.profile import DriveProfile
from dobhil.drives.registry import protocol, protocols
from dobhil.errors import ConfigError

__all__ = ["emulated_protocols", "emulator_class", "make_emulated_drive", "private_virtual_channel"]


def emulated_protocols() -> tuple[str, ...]:
    """Every protocol with an emulated drive (``DriveProtocol.emulator_class``), sorted; a
    protocol that fails to load is left out here (naming it fails with its own line)."""
    out = []
    for name in protocols():
        try:
            if protocol(name).emulator_class is not None:
                out.append(name)
        except ConfigError:
            continue
    return tuple(out)


def emulator_class(name: str) -> type[EmulatedDrive]:
    """The EmulatedDrive subclass of protocol ``name``; ConfigError (one line) if none or broken."""
    cls = protocol(name).emulator_class
    if cls is None:
        raise ConfigError(f"no emulator for protocol {name!r}; emulated: {', '.join(emulated_protocols())}")
    if not (isinstance(cls, type) and issubclass(cls, EmulatedDrive)):
        raise ConfigError(f"emulator of protocol {name!r} is not a dobhil EmulatedDrive class")
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
