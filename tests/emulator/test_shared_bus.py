"""An emulated drive on a bus it shares with other nodes: every frame for another node is
counted in ``frames_not_addressed`` and changes nothing (the counter ``dobhil emulate``
prints when it stops; tests/socketcan/test_peers.py checks it against candump's log of two
runs on one vcan). Lockstep, literal frames, one case per protocol."""

from __future__ import annotations

import dataclasses
import struct

import can

from dobhil.drives import load_profile
from dobhil.drives.odrive import codec
from dobhil.drives.odrive.codec import AxisState, ControlMode, InputMode
from dobhil.drives.odrive.emulator import EmulatedODrive
from dobhil.emulator.plant import Plant
from dobhil.drives.emulated import LockstepBus
from dobhil.drives.emulated import private_virtual_channel


from . import cia402_rig, mit_rig
from .cia402_rig import NODE as CIA402_NODE
from .cia402_rig import enable_cst


def test_an_odrive_counts_another_nodes_commands_and_applies_none() -> None:
    profile = dataclasses.replace(load_profile("odrive-0.6"), bus={})   # node 3
    channel = private_virtual_channel()
    host = can.Bus(interface="virtual", channel=channel)
    emu = EmulatedODrive(can.Bus(interface="virtual", channel=channel), profile, Plant(inertia=0.25))
    bus = LockstepBus(host, [emu], dt=1e-3)
    try:
        def send(node: int, msg: object) -> None:
            bus.send(codec.encode(msg, node_id=node, firmware=emu.firmware))
            emu.handle_pending()

        for node in (3, 4):
            send(node, codec.ClearErrors())
            send(node, codec.SetControllerMode(ControlMode.TORQUE_CONTROL, InputMode.PASSTHROUGH))
            send(node, codec.SetAxisState(AxisState.CLOSED_LOOP_CONTROL))
        assert emu.frames_not_addressed == 3 and emu.axis_state == AxisState.CLOSED_LOOP_CONTROL
        send(4, codec.SetInputTorque(1.5))
        send(4, codec.SetAxisState(AxisState.IDLE))
        assert emu.frames_not_addressed == 5
        assert emu.axis_state == AxisState.CLOSED_LOOP_CONTROL and emu.applied_torque == 0.0
        send(3, codec.SetInputTorque(0.5))
        assert emu.applied_torque == 0.5 and emu.frames_not_addressed == 5
        assert emu.frames_received == 9 and emu.frames_rejected == 0
    finally:
        bus.shutdown()
        emu.close()
        host.shutdown()


def test_an_mit_motor_counts_another_motors_frames_and_answers_none() -> None:
    rig = mit_rig.Lockstep(mit_rig.DAMIAO)   # node 1, replies on 0x11
    try:
        enter = bytes.fromhex("fffffffffffffffc")
        assert rig.ask(enter, can_id=2) == [] and not rig.emu.motor_mode
        assert rig.emu.frames_not_addressed == 1
        # Damiao's register read carries the motor's id in its data: another motor's is not ours
        assert rig.ask(bytes([2, 0, 0x33, 21, 0, 0, 0, 0]), can_id=0x7FF) == []
        assert rig.emu.frames_not_addressed == 2
        assert len(rig.ask(enter)) == 1 and rig.emu.motor_mode
        assert rig.emu.frames_not_addressed == 2
    finally:
        rig.close()


def test_a_cia402_node_counts_another_nodes_frames_and_applies_none() -> None:
    rig = cia402_rig.Lockstep()
    try:
        enable_cst(rig)
        before = rig.emu.frames_not_addressed
        other = CIA402_NODE + 1
        rig.send(0x200 + other, struct.pack("<Hh", 0x0F, 500))   # another node's RPDO 1
        rig.send(0x000, [0x02, other])                          # NMT stop to another node
        rig.send(0x600 + other, cia402_rig.upload(0x6041))      # an SDO request to it
        rig.send(0x180 + other, bytes(8))                       # its TPDO 1
        assert rig.read() == []
        assert rig.emu.frames_not_addressed == before + 4
        assert rig.emu.nmt_state == "OPERATIONAL" and rig.sync()   # still answers its SYNCs
        assert rig.emu.applied_torque == 0.0
        rig.rpdo(0x0F, 500)                                     # its own: 0.5 N m at the SYNC
        rig.sync()
        assert rig.emu.applied_torque == 0.5
        assert rig.emu.frames_not_addressed == before + 4
    finally:
        rig.close()
