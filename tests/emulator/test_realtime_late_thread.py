"""The real-time emulator whose thread wakes late (a loaded machine, software emulation): a
command that reached its bus before a tick's deadline is applied in that tick, as a drive
applies whatever reached it before its control tick; one that came after waits for the next.

On the kernel guest's vcan such a command was otherwise applied a tick or more late (5 ticks in
500 of a 10 ms run, tests/socketcan/test_canutils.py's excitation): a sample of delay the
identification's model does not have. Here the lateness is made, not waited for: the plant's
step sends the command from the host's bus, then takes three periods."""

from __future__ import annotations

import dataclasses
import struct
import threading
import time

import can

from dobhil.drives import load_profile
from dobhil.drives.odrive import codec
from dobhil.drives.odrive.codec import AxisState, ControlMode, InputMode
from dobhil.drives.odrive.emulator import EmulatedODrive
from dobhil.drives.emulated import private_virtual_channel

PERIOD = 0.05
SLOW_STEP = 3       # the step that sends the command and overruns
STEPS = 8


class SlowStep:
    """A plant that records each step's torque; its step ``SLOW_STEP`` runs ``send`` and
    then takes three periods (the thread is late for the next deadlines)."""

    def __init__(self, send: can.Message | None, host: can.BusABC) -> None:
        self.position = 0.0
        self.velocity = 0.0
        self.torques: list[float] = []
        self.done = threading.Event()
        self._send, self._host = send, host

    def step(self, torque_nm: float, dt: float) -> None:
        self.torques.append(torque_nm)
        if len(self.torques) == SLOW_STEP and self._send is not None:
            self._host.send(self._send)          # stamped now: before the next deadline
            time.sleep(3 * PERIOD)
        if len(self.torques) >= STEPS:
            self.done.set()


def _run(command: can.Message | None) -> list[float]:
    profile = dataclasses.replace(load_profile("odrive-0.6"), bus={}, feedback_period=PERIOD,
                                  heartbeat_period=10 * PERIOD, watchdog_timeout=0.0)
    channel = private_virtual_channel()
    host = can.Bus(interface="virtual", channel=channel)
    plant = SlowStep(command, host)
    emu = EmulatedODrive(can.Bus(interface="virtual", channel=channel), profile, plant)
    try:
        for msg in (codec.ClearErrors(), codec.SetControllerMode(ControlMode.TORQUE_CONTROL, InputMode.PASSTHROUGH),
                    codec.SetAxisState(AxisState.CLOSED_LOOP_CONTROL)):
            emu.deliver(codec.encode(msg, node_id=3, firmware=emu.firmware))
        assert emu.axis_state == AxisState.CLOSED_LOOP_CONTROL
        emu.start()
        assert plant.done.wait(20 * STEPS * PERIOD), plant.torques
        emu.stop()
    finally:
        emu.close()
        host.shutdown()
    return plant.torques[:STEPS]


def test_a_command_that_came_before_a_late_ticks_deadline_is_applied_in_that_tick() -> None:
    command = codec.encode(codec.SetInputTorque(0.7), node_id=3, firmware=codec.Firmware.V0_6)
    applied = struct.unpack("<f", struct.pack("<f", 0.7))[0]     # the frame's float32 field
    torques = _run(command)
    assert torques == [0.0] * SLOW_STEP + [applied] * (STEPS - SLOW_STEP), torques
    assert _run(None) == [0.0] * STEPS
