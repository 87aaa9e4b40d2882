"""Emulated ODrives at several node ids on one fresh ``virtual`` channel, for the tests of
several axes that talk to real (emulated) drives through python-can."""

from __future__ import annotations

import dataclasses
import itertools
from collections.abc import Iterator
from contextlib import contextmanager

import can

from dobhil.config import load_config
from dobhil.drives import load_profile
from dobhil.drives.odrive.emulator import EmulatedODrive
from dobhil.emulator.plant import Plant

_CHANNELS = itertools.count()


@contextmanager
def odrive_nodes(prefix: str, nodes: tuple[int, ...]) -> Iterator[tuple[str, list[EmulatedODrive]]]:
    """(channel, the started drives at ``nodes``: the shipped odrive-0.6 profile, the demo's
    plant); each closed at the end."""
    channel = f"{prefix}-{next(_CHANNELS)}"
    emus: list[EmulatedODrive] = []
    try:
        for node in nodes:
            profile = dataclasses.replace(load_profile("odrive-0.6"), bus={}, node_id=node)
            emus.append(EmulatedODrive(can.Bus(interface="virtual", channel=channel), profile,
                                       Plant.from_config(load_config("demo"))))
            emus[-1].start()
        yield channel, emus
    finally:
        for emu in emus:
            emu.close()
