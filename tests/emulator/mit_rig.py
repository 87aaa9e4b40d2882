"""Shared by the MIT emulator tests: model rows by name and a profile built in code
(the loop and emulator tests need no profile file, nor the MIT drive)."""

from __future__ import annotations

from typing import Any

import can

from dobhil.drives.profile import DriveProfile
from dobhil.drives.mit.emulator import EmulatedMit
from dobhil.emulator.plant import Plant
from dobhil.drives.emulated import LockstepBus, PlantLike
from dobhil.drives.emulated import private_virtual_channel

#: (vendor, model, firmware) rows of drivers/mit-models.yaml the tests use
AK80_9 = ("cubemars", "AK80-9", "manual-1.0.8")
DAMIAO = ("damiao", "DM4310", "factory")
MINI_CHEETAH = ("mini-cheetah", "motorcontrol", "3586419")


def mit_profile(row: tuple[str, str, str], *, node_id: int = 1, **options: Any) -> DriveProfile:
    vendor, model, firmware = row
    return DriveProfile(protocol="mit", firmware=firmware, node_id=node_id, torque_limit=2.0,
                        velocity_limit=20.0, enable_timeout=0.5, command_delay_periods=1,
                        options={"vendor": vendor, "model": model, **options}, name=f"{model}-test")


class Lockstep:
    """The emulated motor on a private virtual channel behind a LockstepBus; every frame
    literal. ``read`` returns (emulator time, arbitration id, data) of the frames for the host."""

    def __init__(self, row: tuple[str, str, str] = AK80_9, *, plant: PlantLike | None = None,
                 profile: DriveProfile | None = None, dt: float = 1e-3, **kwargs: Any) -> None:
        channel = private_virtual_channel()
        self.emu_bus = can.Bus(interface="virtual", channel=channel)
        self.inner = can.Bus(interface="virtual", channel=channel)
        self.plant = plant if plant is not None else Plant(inertia=0.01)
        self.profile = profile if profile is not None else mit_profile(row)
        self.emu = EmulatedMit(self.emu_bus, self.profile, self.plant, **kwargs)
        self.bus = LockstepBus(self.inner, [self.emu], dt=dt)
        self.node = self.profile.node_id

    def close(self) -> None:
        self.bus.shutdown()
        self.emu.close()
        self.inner.shutdown()

    def send(self, data: bytes, can_id: int | None = None, **kwargs: Any) -> None:
        self.bus.send(can.Message(arbitration_id=self.node if can_id is None else can_id, data=data,
                                  is_extended_id=False, **kwargs))

    def read(self, wait: float = 0.0) -> list[tuple[float, int, bytes]]:
        """Frames for the host: those already answered, then any within ``wait`` s (simulated)."""
        out = []
        end = self.emu.time + wait
        while True:
            msg = self.bus.recv(max(0.0, end - self.emu.time))
            if msg is None:
                return out
            out.append((self.emu.time, msg.arbitration_id, bytes(msg.data)))

    def ask(self, data: bytes, can_id: int | None = None) -> list[bytes]:
        """Send one frame; the data of the replies at that instant (no time passes)."""
        self.send(data, can_id)
        return [d for _, _, d in self.read()]
