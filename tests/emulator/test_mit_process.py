"""The emulated MIT motor in its own process (EmulatorProcess, as ``dobhil run --emulate``
and ``can.Bus(interface="dobhil")`` run it), in real time: every frame answered, the
torque applied, the protocol state published through shared memory; and the command
timeout firing on the wall clock when the host goes quiet.

Waits poll with a generous bound; nothing asserts wall-clock timing."""

from __future__ import annotations

import time

import can

from dobhil.config import load_config
from dobhil.emulator.process import EmulatorProcess, EmulatorSpec

from .mit_rig import AK80_9, mit_profile
from .test_mit_emulator import AK_ONE_NM, AK_ONE_NM_DECODED, AK_REPLY_AT_REST, ENTER, EXIT

BOUND = 20.0


def _reply(bus: can.BusABC) -> bytes:
    end = time.monotonic() + BOUND
    while True:
        assert time.monotonic() < end, "no reply"
        msg = bus.recv(0.1)
        if msg is not None:
            assert msg.arbitration_id == 0 and not msg.is_extended_id
            return bytes(msg.data)


def _until(condition: object, what: str) -> None:
    end = time.monotonic() + BOUND
    while not condition():   # type: ignore[operator]
        assert time.monotonic() < end, what
        time.sleep(0.005)


def test_emulator_process_answers_applies_and_times_out() -> None:
    spec = EmulatorSpec.of(load_config("demo", ["plant.initial_position=-0.05"]), mit_profile(AK80_9))
    with EmulatorProcess(spec) as process:
        bus = process.bus
        bus.send(can.Message(arbitration_id=1, data=ENTER, is_extended_id=False))
        reply = _reply(bus)   # at -0.05 rad: int(12.45 * 65535 / 25) = 32636 = 0x7F7C
        assert reply == bytes([1, 0x7F, 0x7C]) + AK_REPLY_AT_REST[3:]
        _until(lambda: process.axis_state == 1, "motor mode")
        bus.send(can.Message(arbitration_id=1, data=AK_ONE_NM, is_extended_id=False))
        _reply(bus)
        # the host then says nothing: the firmware's 25 ms timeout zeroes the torque
        _until(lambda: process.watchdog_tripped, "command timeout")
        assert process.axis_state == 1 and process.applied_torque == 0.0
        # it was applied before: the plant, free of the environment (5 cm away), moves
        assert process.plant.true_velocity > 0
        bus.send(can.Message(arbitration_id=1, data=AK_ONE_NM, is_extended_id=False))
        _reply(bus)
        _until(lambda: abs(process.applied_torque - AK_ONE_NM_DECODED) < 1e-12, "torque again")
        bus.send(can.Message(arbitration_id=1, data=EXIT, is_extended_id=False))
        _reply(bus)
        _until(lambda: process.axis_state == 0 and process.applied_torque == 0.0, "rest")
        assert process.frame_errors == 0 and process.frames_rejected == 0
