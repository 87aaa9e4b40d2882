"""A third-party ODrive client, built ONLY from cantools and the official DBC of
``odrive-can`` (0.6.10 and 0.5.6), drives :class:`EmulatedODrive` on a virtual bus in
lockstep: the emulator speaks the real protocol, not just dobhil's codec.

The client enables torque control the documented way (Clear_Errors,
Set_Controller_Mode(TORQUE_CONTROL, PASSTHROUGH), Set_Axis_State(CLOSED_LOOP_CONTROL)),
commands a torque and reads Heartbeat and Get_Encoder_Estimates in the DBC's units
(turns, turns/s), which must match the plant's rad, rad/s; the plant accelerates at
torque / inertia.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import can
import pytest

from dobhil.drives.load import load_profile
from dobhil.drives.odrive.emulator import EmulatedODrive
from dobhil.emulator.plant import Plant

from .helpers import NODE, demo_config

cantools = pytest.importorskip("cantools")
odrive_can = pytest.importorskip("odrive_can")

DBC = {"odrive-0.6": "odrive-cansimple-0.6.10.dbc", "odrive-0.5": "odrive-cansimple-0.5.6.dbc"}
TURN = 2.0 * math.pi
DT = 1e-3
_CHANNELS = itertools.count()


@dataclass
class Client:
    """The third party: a bus and a cantools database, nothing from dobhil."""

    bus: can.BusABC
    db: Any
    node: int = NODE

    def send(self, name: str, signals: dict[str, float] | None = None) -> None:
        message = self.db.get_message_by_name(f"Axis{self.node}_{name}")
        data = message.encode(signals or {}) if message.length else b""
        self.bus.send(can.Message(arbitration_id=message.frame_id, is_extended_id=False,
                                  data=data))

    def read_all(self) -> dict[str, dict[str, Any]]:
        """The newest decoded payload of each message name waiting on the bus."""
        newest: dict[str, dict[str, Any]] = {}
        msg = self.bus.recv(0.0)
        while msg is not None:
            message = self.db.get_message_by_frame_id(msg.arbitration_id)
            if msg.data:
                newest[message.name.split("_", 1)[1]] = message.decode(msg.data,
                                                                       decode_choices=False)
            msg = self.bus.recv(0.0)
        return newest


@pytest.fixture(params=sorted(DBC), ids=sorted(DBC))
def rig(request: pytest.FixtureRequest) -> Iterator[tuple[Client, EmulatedODrive, Plant]]:
    """Client and emulated drive on a fresh virtual channel; the plant free in space
    (no contact: far from the environment), no friction, so J ddq = torque."""
    name = request.param
    config = demo_config(f"drive.profile={name}", "plant.viscous_friction=0",
                         "plant.initial_position=-1", "loop.position_min=-10")
    channel = f"third-party-{next(_CHANNELS)}"
    plant = Plant.from_config(config)
    dbc = Path(odrive_can.__file__).resolve().parent / "dbc" / DBC[name]
    client = Client(can.Bus(interface="virtual", channel=channel),
                    cantools.database.load_file(str(dbc)))
    emulator = EmulatedODrive(can.Bus(interface="virtual", channel=channel), load_profile(name),
                              plant)
    try:
        yield client, emulator, plant
    finally:
        emulator.close()
        client.bus.shutdown()


def tick(emulator: EmulatedODrive, n: int = 1, *, client: Client | None = None,
         torque: float = 0.0) -> None:
    """``n`` lockstep periods; with ``client`` it commands ``torque`` every period, as
    a client must to keep the drive's watchdog (50 ms in the profile) fed."""
    for _ in range(n):
        if client is not None:
            client.send("Set_Input_Torque", {"Input_Torque": torque})
        emulator.handle_pending()
        emulator.advance(DT)


def test_enable_and_torque_with_the_official_dbc(
        rig: tuple[Client, EmulatedODrive, Plant]) -> None:
    """The documented enable sequence puts the emulated axis in CLOSED_LOOP_CONTROL
    (heartbeat Axis_State 8, no error); a torque command accelerates the plant at
    torque / inertia; encoder estimates read in turns and turns/s."""
    client, emulator, plant = rig
    tick(emulator, 5)
    first = client.read_all()
    assert first["Get_Encoder_Estimates"]["Pos_Estimate"] == pytest.approx(-1.0 / TURN, rel=1e-6)

    clear = client.db.get_message_by_name(f"Axis{NODE}_Clear_Errors")  # DLC 0 on 0.5.6
    client.send("Clear_Errors", {signal.name: 0 for signal in clear.signals})
    client.send("Set_Controller_Mode", {"Control_Mode": 1, "Input_Mode": 1})
    client.send("Set_Axis_State", {"Axis_Requested_State": 8})
    tick(emulator, 100, client=client)   # a heartbeat every 100 ms
    hb = client.read_all()["Heartbeat"]
    assert hb["Axis_State"] == 8 and hb["Axis_Error"] == 0

    torque = 0.5
    q0, v0 = plant.true_position, plant.true_velocity
    steps = 20
    tick(emulator, steps, client=client, torque=torque)
    assert emulator.applied_torque == pytest.approx(torque)
    t = steps * DT
    accel = torque / plant.inertia
    assert plant.true_velocity == pytest.approx(v0 + accel * t, rel=1e-9)
    assert plant.true_position == pytest.approx(q0 + v0 * t + 0.5 * accel * t * t, rel=1e-9)

    enc = client.read_all()["Get_Encoder_Estimates"]
    assert enc["Pos_Estimate"] * TURN == pytest.approx(plant.position, rel=1e-6)
    assert enc["Vel_Estimate"] * TURN == pytest.approx(plant.velocity, rel=1e-6)
    assert enc["Vel_Estimate"] == pytest.approx(accel * t / TURN, rel=1e-6)

    client.send("Set_Axis_State", {"Axis_Requested_State": 1})
    tick(emulator, 100)
    assert not emulator.watchdog_tripped   # IDLE before the watchdog could expire
    assert client.read_all()["Heartbeat"]["Axis_State"] == 1
    assert emulator.applied_torque == 0.0
