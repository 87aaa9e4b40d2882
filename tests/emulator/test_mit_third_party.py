"""A published client drives the emulated MIT motor through python-can's own entry,
``can.Bus(interface="dobhil", channel=<an MIT config>)`` (the emulator in its own process,
real time): damiao-motor's ``DaMiaoMotor`` (PyPI damiao-motor 1.0.6, used as its docs show)
enables the emulated DM4310, commands a torque in MIT mode, reads the replies with its own
decoder and the mapping registers with its own register reader, and disables it.

Waits poll with a generous bound; nothing asserts wall-clock timing."""

from __future__ import annotations

import time
from pathlib import Path

import can
import pytest

damiao = pytest.importorskip("damiao_motor.core.motor")

REPO = Path(__file__).resolve().parents[2]
BOUND = 20.0
REPLY_ID = 0x11   # drivers/dm4310.yaml: mit.reply_id (the motor's MST_ID)


def _feedback(bus: can.BusABC, motor: object, want: object = None) -> dict[str, object]:
    """Replies on the master id fed to the client's own decoder until ``want(state)``."""
    end = time.monotonic() + BOUND
    while True:
        assert time.monotonic() < end, "no reply"
        msg = bus.recv(0.1)
        if msg is None or msg.arbitration_id != REPLY_ID:
            continue
        motor.process_feedback_frame(bytes(msg.data), msg.arbitration_id)   # type: ignore[attr-defined]
        state = dict(motor.state or {})   # type: ignore[attr-defined]
        if want is None or want(state):   # type: ignore[operator]
            return state


def test_damiao_motor_drives_the_emulated_dm4310() -> None:
    config = str(REPO / "configs" / "mit-demo.yaml")
    with can.Bus(interface="dobhil", channel=config, overrides="drive.profile=dm4310") as bus:
        motor = damiao.DaMiaoMotor(1, REPLY_ID, bus, motor_type="4310")
        motor.enable()
        state = _feedback(bus, motor)
        assert state["can_id"] == 1 and state["status"] == "ENABLED"
        assert state["t_rotor"] == 25.0 and state["t_mos"] == 25.0
        motor.send_cmd_mit(feedforward_torque=0.5)
        # the reply to a command carries the torque applied up to it: the next one shows 0.5
        motor.send_cmd_mit(feedforward_torque=0.5)
        state = _feedback(bus, motor, lambda s: abs(s["torq"] - 0.5) < 0.01)   # type: ignore[operator]
        assert state["status"] == "ENABLED"
        for rid, value in ((21, 12.5), (22, 30.0), (23, 10.0)):
            motor.request_register_reading(rid)
            _feedback(bus, motor, lambda s, rid=rid: rid in motor.registers)   # type: ignore[misc]
            assert motor.registers[rid] == value
        motor.disable()
        state = _feedback(bus, motor, lambda s: s["status"] != "ENABLED")
        assert state["status"] == "DISABLED"
