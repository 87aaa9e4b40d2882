"""A host's view of the emulated CiA 402 node in lockstep, in literal frames (shared by the
CiA 402 emulator tests)."""

from __future__ import annotations

import struct
from typing import Any

import can

from dobhil.drives.profile import DriveProfile
from dobhil.drives.cia402.emulator import EmulatedCiA402
from dobhil.emulator.plant import Plant
from dobhil.drives.emulated import LockstepBus, PlantLike
from dobhil.drives.emulated import private_virtual_channel

NODE = 5
DT = 0.001
SYNC, EMCY, TPDO1, TPDO2, RPDO1 = 0x80, 0x80 + NODE, 0x180 + NODE, 0x280 + NODE, 0x200 + NODE
SDO_RX, SDO_TX, HEARTBEAT = 0x600 + NODE, 0x580 + NODE, 0x700 + NODE
#: the profile's cia402 section (SPEC-17's drivers/cia402-emulated.yaml)
OPTIONS = {"eds": "cia402-emulated.eds", "rated_torque": 1.0, "rated_torque_unit": "mNm",
           "position_per_rev": 4096, "velocity_unit": "rpm", "gear_ratio": 1.0}


def cia402_profile(**changes: Any) -> DriveProfile:
    """The emulated node's profile (SPEC-17), built in code."""
    base: dict[str, Any] = dict(protocol="cia402", firmware="1.0", node_id=NODE, torque_limit=2.0,
                                velocity_limit=50.0, feedback_period=DT, heartbeat_period=0.1,
                                command_delay_periods=1, watchdog_timeout=0.0, enable_timeout=2.0,
                                name="cia402-emulated", options=OPTIONS)
    return DriveProfile(**{**base, **changes})


def upload(index: int, sub: int = 0) -> bytes:
    """SDO initiate upload request (CiA 301: ccs 2)."""
    return bytes([0x40, index & 0xFF, index >> 8, sub, 0, 0, 0, 0])


def download(index: int, sub: int, value: int, size: int) -> bytes:
    """SDO expedited download request of ``size`` bytes (ccs 1, e=1, s=1, n = 4 - size)."""
    command = 0x23 | (4 - size) << 2
    return bytes([command, index & 0xFF, index >> 8, sub]) + value.to_bytes(4, "little", signed=value < 0)


class Lockstep:
    """The node on a private virtual channel behind a LockstepBus; every frame literal."""

    def __init__(self, plant: PlantLike | None = None, **kwargs: Any) -> None:
        channel = private_virtual_channel()
        self.emu_bus = can.Bus(interface="virtual", channel=channel)
        self.inner = can.Bus(interface="virtual", channel=channel)
        self.plant = plant if plant is not None else Plant(inertia=0.01)
        profile = kwargs.pop("profile", cia402_profile())
        self.emu = EmulatedCiA402(self.emu_bus, profile, self.plant, **kwargs)
        self.bus = LockstepBus(self.inner, [self.emu], dt=DT)
        self.node = profile.node_id
        self.seen: list[tuple[float, int, bytes]] = []   # (emulator time, id, data) of every frame read

    def close(self) -> None:
        self.bus.shutdown()
        self.emu.close()
        self.inner.shutdown()

    def send(self, can_id: int, data: bytes | list[int] = b"") -> None:
        self.bus.send(can.Message(arbitration_id=can_id, data=bytes(data), is_extended_id=False))

    def read(self, wait: float = 0.0) -> list[tuple[int, bytes]]:
        """Frames for the host: those already answered, then any within ``wait`` s (simulated)."""
        out = []
        end = self.emu.time + wait
        while True:
            msg = self.bus.recv(max(0.0, end - self.emu.time))
            if msg is None:
                return out
            self.seen.append((self.emu.time, msg.arbitration_id, bytes(msg.data)))
            out.append((msg.arbitration_id, bytes(msg.data)))

    def run(self, seconds: float) -> list[tuple[int, bytes]]:
        """Advance ``seconds`` of simulated time, reading every frame meanwhile."""
        return self.read(seconds)

    def sdo(self, request: bytes) -> bytes:
        """One SDO request; its one response."""
        self.send(0x600 + self.node, request)
        answers = [data for can_id, data in self.read() if can_id == 0x580 + self.node]
        assert len(answers) == 1, answers
        return answers[0]

    def write(self, index: int, sub: int, value: int, size: int) -> None:
        response = self.sdo(download(index, sub, value, size))
        assert response == bytes([0x60, index & 0xFF, index >> 8, sub, 0, 0, 0, 0]), response.hex()

    def value(self, index: int, sub: int = 0, fmt: str = "<I") -> int:
        response = self.sdo(upload(index, sub))
        assert response[0] & 0xE3 == 0x43, response.hex()   # expedited upload response, size given
        size = 4 - (response[0] >> 2 & 3)
        (value,) = struct.unpack(fmt, response[4:4 + size])
        return int(value)

    def sync(self) -> dict[int, bytes]:
        """A SYNC; the frames it was answered with, by id."""
        self.send(SYNC)
        return dict(self.read())

    def rpdo(self, controlword: int, torque: int = 0) -> None:
        self.send(0x200 + self.node, struct.pack("<Hh", controlword, torque))


def configure_wire_mapping(rig: Lockstep) -> None:
    """SPEC-17's wire mapping written by SDO the way CiA 301 says (and canopen's
    PdoMap.save does): PDO invalid, count 0, entries, count, valid again."""
    for com, mapping, cob, entries in (
        (0x1400, 0x1600, 0x200 + rig.node, [0x60400010, 0x60710010]),
        (0x1800, 0x1A00, 0x180 + rig.node, [0x60410010, 0x60640020, 0x60770010]),
        (0x1801, 0x1A01, 0x280 + rig.node, [0x606C0020, 0x60610008]),
    ):
        rig.write(com, 1, cob | 1 << 31, 4)
        rig.write(com, 2, 1, 1)                    # synchronous, every SYNC
        rig.write(mapping, 0, 0, 1)
        for sub, entry in enumerate(entries, 1):
            rig.write(mapping, sub, entry, 4)
        rig.write(mapping, 0, len(entries), 1)
        rig.write(com, 1, cob, 4)


def enable_cst(rig: Lockstep) -> None:
    """Mapping, NMT operational, mode CST by SDO, then shutdown / switch on / enable
    operation by RPDO, each applied at a SYNC."""
    configure_wire_mapping(rig)
    rig.send(0x000, [0x01, rig.node])
    rig.write(0x6060, 0, 10, 1)
    for controlword in (0x06, 0x07, 0x0F):
        rig.rpdo(controlword)
        rig.sync()
