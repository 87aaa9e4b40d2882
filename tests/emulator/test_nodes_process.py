"""Several emulated nodes on one bus in one child process (EmulatorProcess with a list of
specs), in real time: each node answers its own frames, one tick clock, coupled plants.

Two ODrive nodes, ids 1 and 2, from a two-axis config. Waits poll with a generous bound;
nothing asserts wall-clock timing."""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from pathlib import Path

import can
import pytest

from dobhil.config.axes import Axes, Coupling, load_axes
from dobhil.drives.load import load_drive_profile
from dobhil.drives.odrive import codec
from dobhil.drives.odrive.codec import AxisState, ControlMode, InputMode
from dobhil.emulator.process import EmulatorProcess, EmulatorSpec

BOUND = 20.0

TWO_AXES = """\
loop: {period: 0.001, duration: 0.5}
axes:
  - name: left
    drive: {profile: odrive-0.6, node_id: 1}
  - name: right
    drive: {profile: odrive-0.6, node_id: 2}
    plant: {inertia: 0.3}
environment:
  contact_position: 1.0     # far away: only the coupling acts between them
"""


def _axes(tmp_path: Path, coupling: str = "") -> Axes:
    path = tmp_path / "two.yaml"
    path.write_text(TWO_AXES + coupling)
    return load_axes(path)


def _specs(axes: Axes, tmp_path: Path) -> list[EmulatorSpec]:
    out = []
    for axis in axes.axes:
        # no watchdog: this test's host feeds no setpoints on a schedule
        profile = dataclasses.replace(load_drive_profile(axis.config, tmp_path), watchdog_timeout=0.0)
        out.append(EmulatorSpec.of(axis.config, profile, name=axis.name))
    return out


def _until(condition: Callable[[], bool], what: str, bus: can.BusABC) -> None:
    end = time.monotonic() + BOUND
    while not condition():
        assert time.monotonic() < end, what
        bus.recv(0.005)   # keep reading: the nodes' cyclic frames must not pile up


def _enable(bus: can.BusABC, node: int) -> None:
    for msg in (codec.ClearErrors(), codec.SetControllerMode(ControlMode.TORQUE_CONTROL, InputMode.PASSTHROUGH),
                codec.SetAxisState(AxisState.CLOSED_LOOP_CONTROL)):
        bus.send(codec.encode(msg, node_id=node))


def test_two_odrive_nodes_answer_their_own_frames_and_the_coupling_pushes(tmp_path: Path) -> None:
    axes = _axes(tmp_path, "  coupling:\n    - {axes: [left, right], stiffness: 2000.0, damping: 20.0}\n")
    assert axes.couplings == (Coupling("left", "right", 2000.0, 20.0),)
    with EmulatorProcess(_specs(axes, tmp_path), couplings=axes.couplings) as process:
        bus = process.bus
        left, right = process.node("left"), process.node("right")
        assert (left.profile.node_id, right.profile.node_id) == (1, 2) and process.node(1) is right
        # both nodes stream their encoder estimates, each on its own id
        seen: set[int] = set()
        end = time.monotonic() + BOUND
        while len(seen) < 2:
            assert time.monotonic() < end, f"encoder estimates from {seen} only"
            msg = bus.recv(0.1)
            if msg is not None and msg.arbitration_id & 0x1F == codec.CmdId.GET_ENCODER_ESTIMATES:
                seen.add(msg.arbitration_id >> 5)
        assert seen == {1, 2}
        # node 1 alone is enabled and pushed: node 2 keeps its state and applies nothing
        _enable(bus, 1)
        _until(lambda: left.protocol_state == AxisState.CLOSED_LOOP_CONTROL, "node 1 closed loop", bus)
        bus.send(codec.encode(codec.SetInputTorque(0.5), node_id=1))
        _until(lambda: left.applied_torque == 0.5, "node 1's torque", bus)
        assert right.protocol_state == AxisState.IDLE and right.applied_torque == 0.0
        # node 2 has no torque and no environment (1 rad away): only the coupling moves it
        _until(lambda: right.plant.true_position > 1e-3, "node 2 dragged along", bus)
        assert left.plant.true_position > right.plant.true_position > 0.0
        # what each node's force sensor reads of the spring: equal and opposite within the
        # change over one tick (the two blocks are read one after the other)
        tau_left, _ = process.truth("left")
        tau_right, _ = process.truth(1)
        assert tau_left > 0.0 > tau_right
        # node 2 enabled now, pushed back harder: it answers its own frames
        _enable(bus, 2)
        _until(lambda: right.protocol_state == AxisState.CLOSED_LOOP_CONTROL, "node 2 closed loop", bus)
        bus.send(codec.encode(codec.SetInputTorque(-2.0), node_id=2))
        _until(lambda: right.applied_torque == -2.0, "node 2's torque", bus)
        assert left.applied_torque == 0.5
        _until(lambda: left.plant.true_velocity < 0.0, "node 1 pulled back", bus)
        for node in process.nodes:
            assert node.frame_errors == 0 and node.frames_rejected == 0 and node.send_errors == 0
        # one tick clock: both blocks come from the same child ticks
        assert abs(left.time - right.time) <= 2 * process.tick
        assert process.starved(1.0) == ""


def test_uncoupled_nodes_do_not_move_each_other(tmp_path: Path) -> None:
    axes = _axes(tmp_path)
    with EmulatorProcess(_specs(axes, tmp_path)) as process:
        bus = process.bus
        _enable(bus, 2)
        _until(lambda: process.node(1).protocol_state == AxisState.CLOSED_LOOP_CONTROL, "node 2", bus)
        bus.send(codec.encode(codec.SetInputTorque(1.0), node_id=2))
        _until(lambda: process.node("right").plant.true_position > 1e-3, "node 2 moves", bus)
        assert process.plant.true_position == 0.0 and process.plant.true_velocity == 0.0
        assert process.protocol_state == AxisState.IDLE
        assert process.truth() == (0.0, 0.0)


def test_refuses_nodes_one_bus_cannot_carry(tmp_path: Path) -> None:
    specs = _specs(_axes(tmp_path), tmp_path)
    same_id = [specs[0], dataclasses.replace(specs[1], profile=specs[0].profile)]
    with pytest.raises(ValueError, match="axes left and right are both node 1"):
        EmulatorProcess(same_id)
    with pytest.raises(ValueError, match="two nodes are axis 'left'"):
        EmulatorProcess([specs[0], dataclasses.replace(specs[1], name="left")])
    with pytest.raises(ValueError, match="no node of axis 'up'"):
        EmulatorProcess(specs, couplings=[Coupling("left", "up", 1.0, 0.0)])


def test_an_odrive_and_an_mit_motor_share_the_bus(tmp_path: Path) -> None:
    """Two protocols in one process: the MIT motor (id 5) answers its own frames on the
    master id, the ODrive (node 1) goes on streaming and applies none of them."""
    from dobhil.config import load_config

    from .mit_rig import MINI_CHEETAH, mit_profile
    from .test_mit_emulator import AK_ONE_NM, ENTER

    odrive = _specs(_axes(tmp_path), tmp_path)[0]
    mit = EmulatorSpec.of(load_config("demo", ["environment.contact_position=1.0"]),
                          mit_profile(MINI_CHEETAH, node_id=5), name="wrist")
    with EmulatorProcess([odrive, mit]) as process:
        bus = process.bus
        motor, left = process.node("wrist"), process.node("left")
        bus.send(can.Message(arbitration_id=5, data=ENTER, is_extended_id=False))
        replies: list[bytes] = []
        estimates = 0
        end = time.monotonic() + BOUND
        while not (replies and estimates):
            assert time.monotonic() < end, f"replies {replies}, encoder estimates {estimates}"
            msg = bus.recv(0.1)
            if msg is None:
                continue
            if msg.arbitration_id == 0:
                replies.append(bytes(msg.data))
            elif msg.arbitration_id == (1 << 5) | codec.CmdId.GET_ENCODER_ESTIMATES:
                estimates += 1
        assert replies[0][0] == 5   # the reply names its motor
        _until(lambda: motor.protocol_state == 1, "motor mode", bus)
        bus.send(can.Message(arbitration_id=5, data=AK_ONE_NM, is_extended_id=False))
        _until(lambda: motor.plant.true_velocity > 0.0, "the motor moves", bus)
        assert left.protocol_state == AxisState.IDLE and left.applied_torque == 0.0
        assert left.plant.true_position == 0.0
        assert motor.frame_errors == left.frame_errors == 0
