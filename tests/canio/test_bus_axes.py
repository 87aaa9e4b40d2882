"""``can.Bus(interface="dobhil", channel=CONFIG)`` with a config that lists axes: every axis'
emulated drive on the one bus, in one process, each answering its own frames; the axes of
one bus picked with ``axes=`` when they sit on several; a coupling across buses refused."""

from __future__ import annotations

import time
from pathlib import Path

import can
import pytest

from dobhil.canio.bus import DobhilBus, EmulatedBusError
from dobhil.drives.odrive import codec
from dobhil.drives.odrive.codec import CmdId

from runtime.axes_helpers import BOUND, TWO_AXES


def _config(tmp_path: Path, right_bus: str = "", coupled: bool = True) -> Path:
    text = TWO_AXES % right_bus
    if not coupled:
        text = text.split("environment:")[0]
    path = tmp_path / "two.yaml"
    path.write_text(text, encoding="utf-8")
    return path


def _answers(bus: can.BusABC, node: int) -> list[codec.BusVoltageCurrent]:
    """Ask node ``node`` for its bus voltage (an RTR request) and collect the answers."""
    bus.send(codec.encode(codec.Request(CmdId.GET_BUS_VOLTAGE_CURRENT), node_id=node))
    end = time.monotonic() + BOUND
    got: list[codec.BusVoltageCurrent] = []
    quiet = 0
    while time.monotonic() < end and quiet < 20:   # until 20 reads in a row bring no answer
        msg = bus.recv(0.01)
        if msg is not None and msg.arbitration_id & 0x1F == CmdId.GET_BUS_VOLTAGE_CURRENT \
                and not msg.is_remote_frame:
            assert msg.arbitration_id >> 5 == node, "another node answered"
            got.append(codec.decode_message(msg))
            quiet = 0
        elif got:
            quiet += 1
    return got


def test_every_axis_drive_on_the_one_bus(tmp_path: Path) -> None:
    with can.Bus(interface="dobhil", channel=str(_config(tmp_path))) as bus:
        assert isinstance(bus, DobhilBus)
        assert "left: odrive (firmware 0.6, node 1), right: odrive (firmware 0.6, node 2)" in bus.channel_info
        assert bus.emulator.names == ("left", "right") and len(bus.emulator.couplings) == 1
        for node in (1, 2):
            assert len(_answers(bus, node)) == 1
        assert bus.emulator.node("left").frames_received >= 2   # its request and the other's
        assert bus.emulator.node("right").plant.true_position == 0.0


def test_axes_on_two_buses_need_a_pick(tmp_path: Path) -> None:
    two_buses = _config(tmp_path, right_bus=", interface: socketcan, channel: can1", coupled=False)
    with pytest.raises(EmulatedBusError, match=r"2 buses \(the default bus: left; socketcan:can1: right\); "
                                               r"one emulated bus hosts one bus's axes: select them with axes="):
        can.Bus(interface="dobhil", channel=str(two_buses))
    with can.Bus(interface="dobhil", channel=str(two_buses), axes="right") as bus:
        assert bus.emulator.names == ("right",) and bus.emulator.node(0).profile.node_id == 2
        assert len(_answers(bus, 2)) == 1
    coupled = _config(tmp_path, right_bus=", interface: socketcan, channel: can1")
    with pytest.raises(EmulatedBusError, match="coupling left-right: axis right is not emulated with left"):
        can.Bus(interface="dobhil", channel=str(coupled), axes=["left"])
    with pytest.raises(EmulatedBusError, match="no axis 'up'"):
        can.Bus(interface="dobhil", channel=str(coupled), axes="left,up")
