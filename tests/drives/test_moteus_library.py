"""dobhil's moteus side against mjbots' official library (PyPI ``moteus`` 1.1.1), both ways:

- the library's ``moteus.Controller`` over its ``moteus.PythonCan`` transport, opened on
  ``interface="dobhil"`` (python-can's plugin entry point: the emulated controller in its own
  process, in real time), drives dobhil's emulated controller: a stop, then torque by
  position mode gives the plant's acceleration tau / J, and the watchdog trips to mode 11
  once the commands stop;
- a controller node written from the library's own parsers (``moteus.protocol.
  parse_registers``) and value coding (``moteus.multiplex.saturate``) answers dobhil's
  :class:`~dobhil.drives.moteus.drive.MoteusDrive`: enable, torque, safe stop.
"""

from __future__ import annotations

import asyncio
import math
import struct
import threading
from pathlib import Path

import can
import moteus
import numpy as np
from moteus import multiplex as mp
from moteus import protocol as mprot

from dobhil.drives import DriveState, load_profile, make_drive
from dobhil.drives.base import Confirmation

REPO = Path(__file__).resolve().parents[2]
DEMO = REPO / "configs" / "moteus-demo.yaml"
INERTIA = 0.25     # plant.inertia of the demo
TAU = 0.5          # [N m]
EPS32 = float(np.finfo(np.float32).eps)


async def _drive_the_emulator() -> tuple[list[moteus.protocol.Result], moteus.protocol.Result,
                                         moteus.protocol.Result]:
    transport = moteus.PythonCan(interface="dobhil", channel=str(DEMO),
                                 overrides="plant.viscous_friction=0,environment.contact_position=1000")
    try:
        ctrl = moteus.Controller(id=1, transport=transport)
        stopped = await asyncio.wait_for(ctrl.set_stop(query=True), 10)
        replies = []
        for _ in range(60):
            replies.append(await asyncio.wait_for(
                ctrl.set_position(position=math.nan, velocity=0.0, kp_scale=0.0, kd_scale=0.0,
                                  feedforward_torque=TAU, query=True), 10))
        await asyncio.sleep(0.5)   # no command for 5 x the default watchdog (0.1 s)
        timed_out = await asyncio.wait_for(ctrl.query(), 10)
        await asyncio.wait_for(ctrl.set_stop(), 10)
        return replies, stopped, timed_out
    finally:
        transport.close()


def test_the_librarys_controller_drives_the_emulated_controller() -> None:
    replies, stopped, timed_out = asyncio.run(_drive_the_emulator())
    R = moteus.Register
    assert stopped.values[R.MODE] == moteus.Mode.STOPPED and stopped.values[R.TORQUE] == 0.0
    assert all(r.values[R.MODE] == moteus.Mode.POSITION for r in replies)
    # each reply is sampled as its command is applied: from the second on, TAU is applied
    assert all(r.values[R.TORQUE] == TAU for r in replies[1:])
    # constant acceleration from the first reply to the last: v2^2 - v1^2 = 2 a (p2 - p1)
    first, last = replies[1].values, replies[-1].values
    p1, v1, p2, v2 = (first[R.POSITION], first[R.VELOCITY], last[R.POSITION], last[R.VELOCITY])
    assert p2 > p1 and v2 > v1
    accel = (v2 ** 2 - v1 ** 2) / (2.0 * (p2 - p1)) * 2.0 * math.pi   # rev/s^2 -> rad/s^2
    # the quanta: every value a float32 (relative EPS32 each), propagated through the formula
    dv, dp = EPS32 * max(abs(v1), abs(v2)), EPS32 * max(abs(p1), abs(p2))
    bound = accel * (2 * (abs(v1) + abs(v2)) * dv / max(v2 ** 2 - v1 ** 2, 1e-30) + 2 * dp / (p2 - p1))
    assert abs(accel - TAU / INERTIA) <= bound + 1e-9 * TAU / INERTIA, (accel, bound)
    # the watchdog (0x027 not written: 0, the default 0.1 s) put it in mode 11
    assert timed_out.values[R.MODE] == moteus.Mode.TIMEOUT


class LibraryNode:
    """A moteus controller of the library's parsers: applies mode/feedforward writes, answers
    each read with the library's own value coding, on a thread; a rigid body J = INERTIA."""

    def __init__(self, channel: str, node: int = 1) -> None:
        self.bus = can.Bus(interface="virtual", channel=channel, protocol=can.CanProtocol.CAN_FD)
        self.node = node
        self.mode = 0
        self.commands: list[dict[int, float]] = []
        self.position = self.velocity = self.torque = 0.0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def __enter__(self) -> LibraryNode:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join(2)
        self.bus.shutdown()

    def _run(self) -> None:
        while not self._stop.is_set():
            msg = self.bus.recv(0.01)
            if msg is None or msg.arbitration_id & 0x7F != self.node:
                continue
            dt = 1e-3
            self.position += self.velocity * dt + 0.5 * self.torque / INERTIA * dt * dt
            self.velocity += self.torque / INERTIA * dt
            parsed = mprot.parse_registers(bytes(msg.data))
            if mprot.Register.MODE in parsed.command:
                self.commands.append(parsed.command)
                self.mode = int(parsed.command[mprot.Register.MODE])
                self.torque = parsed.command.get(mprot.Register.COMMAND_FEEDFORWARD_TORQUE, 0.0) \
                    if self.mode == 10 else 0.0
            if msg.arbitration_id & 0x8000:
                self._reply((msg.arbitration_id >> 8) & 0x7F, parsed.query)

    def _reply(self, source: int, query: list[tuple[int, int]]) -> None:
        R = mprot.Register
        values = {R.MODE: self.mode, R.POSITION: self.position / (2 * math.pi),
                  R.VELOCITY: self.velocity / (2 * math.pi), R.TORQUE: self.torque, R.FAULT: 0}
        data = bytearray()
        for register, res in query:
            # the library's own step of this register at this resolution (code 1 scaled)
            scale = 1.0 if res == mp.F32 or register in (R.MODE, R.FAULT) else \
                float(mprot.scale_register(register, res, 1))
            code = mp.saturate(float(values[register]), res, scale)
            data += bytes((0x21 | res << 2, register)) + mp.TYPES[res].pack(code)
        length = next(n for n in (8, 12, 16, 20, 24, 32, 48, 64) if n >= len(data))
        data += bytes((mp.NOP,)) * (length - len(data))
        self.bus.send(can.Message(arbitration_id=self.node << 8 | source, is_extended_id=False, is_fd=True,
                                  bitrate_switch=True, data=bytes(data[:64])))


def test_dobhils_drive_runs_against_a_node_of_the_librarys_parsers() -> None:
    channel = "moteus-library-node"
    profile = load_profile("moteus-r4.11")
    with LibraryNode(channel) as node, \
            can.Bus(interface="virtual", channel=channel, protocol=can.CanProtocol.CAN_FD) as bus:
        drive = make_drive(bus, profile)
        drive.enable(timeout=2.0)
        assert drive.status.state is DriveState.ENABLED and node.mode == 10
        for _ in range(50):
            drive.send_torque(0.3)
            drive.poll(0.05)
        R = mprot.Register
        last = node.commands[-1]
        assert last[R.COMMAND_FEEDFORWARD_TORQUE] == struct.unpack("<f", struct.pack("<f", 0.3))[0]
        assert math.isnan(last[R.COMMAND_POSITION]) and last[R.COMMAND_VELOCITY] == 0.0
        assert last[R.COMMAND_KP_SCALE] == 0.0 and last[R.COMMAND_KD_SCALE] == 0.0
        assert last[R.COMMAND_TIMEOUT] == struct.unpack("<f", struct.pack("<f", profile.watchdog_timeout))[0]
        feedback = drive.feedback
        assert feedback is not None and feedback.velocity > 0 and feedback.position > 0
        # the node's float32 position (rev) back in rad
        assert abs(feedback.position - node.position) < 0.3 / INERTIA * 2e-3 + 1e-6
        report = drive.safe_stop()
        assert report.confirmation is Confirmation.CONFIRMED, report.detail
        assert node.mode == 0 and node.torque == 0.0
