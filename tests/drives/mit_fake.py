"""An MIT-mode motor of this test suite's own, on a python-can ``virtual`` bus: a daemon
thread that answers each frame to its node with the literal bytes a test's ``answer``
function gives (None: silence), and records every frame it got. Nothing here imports
dobhil's codec or emulator: the tests say the bytes.

``answer(data) -> bytes | None`` sees each frame's payload; :func:`reply_cubemars` and
:func:`reply_damiao` build the replies from codes (the layouts of the CubeMars AK manual
and Damiao's DM-J documentation, written out here by hand).
"""

from __future__ import annotations

import itertools
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager

import can

_CHANNELS = itertools.count()

ENTER = bytes.fromhex("FFFFFFFFFFFFFFFC")
EXIT = bytes.fromhex("FFFFFFFFFFFFFFFD")
ZERO = bytes.fromhex("FFFFFFFFFFFFFFFE")
CLEAR = bytes.fromhex("FFFFFFFFFFFFFFFB")
#: p = 32767, v = 2047, kp = kd = 0, t = 2047: the zero-torque command on every model
#: whose ranges are symmetric (p 16 bits, the rest 12; bytes as the command layout packs them)
ZERO_TORQUE = bytes.fromhex("7FFF7FF0000007FF")

Answer = Callable[[bytes], "bytes | None"]


def reply_cubemars(node: int, p: int = 0x7FFF, v: int = 0x7FF, t: int = 0x7FF, temp: int = 25,
                   error: int = 0) -> bytes:
    """A CubeMars 8-byte reply: id, p16, v12|t12, temperature, error."""
    return bytes((node, p >> 8, p & 0xFF, v >> 4, (v & 0xF) << 4 | t >> 8, t & 0xFF, temp, error))


def reply_cheetah(node: int, p: int = 0x7FFF, v: int = 0x7FF, t: int = 0x7FF, vbus: int = 0x99) -> bytes:
    """A Mini-Cheetah (motorcontrol) 7-byte reply: id, p16, v12|t12, bus voltage (raw)."""
    return bytes((node, p >> 8, p & 0xFF, v >> 4, (v & 0xF) << 4 | t >> 8, t & 0xFF, vbus))


def reply_damiao(node: int, state: int, p: int = 0x7FFF, v: int = 0x7FF, t: int = 0x7FF,
                 mos: int = 30, rotor: int = 31) -> bytes:
    """A Damiao 8-byte reply: state << 4 | id, p16, v12|t12, MOS and rotor temperatures."""
    return bytes((state << 4 | node, p >> 8, p & 0xFF, v >> 4, (v & 0xF) << 4 | t >> 8, t & 0xFF, mos, rotor))


class FakeMotor:
    """Answers frames to ``node`` on ``reply_id`` with ``answer(data)``; records them."""

    def __init__(self, channel: str, node: int, answer: Answer, reply_id: int = 0) -> None:
        self.node = node
        self.reply_id = reply_id
        self.answer = answer
        self.got: list[bytes] = []          # payloads to our node, in order
        self.got_ids: list[int] = []        # every arbitration id heard
        self._bus = can.Bus(interface="virtual", channel=channel)
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._thread = threading.Thread(target=self._serve, name="fake-mit", daemon=True)
        self._thread.start()

    def send(self, data: bytes) -> None:
        """An unsolicited frame from the motor's side (a late reply)."""
        self._bus.send(can.Message(arbitration_id=self.reply_id, data=data, is_extended_id=False))

    def frames(self) -> list[bytes]:
        with self._lock:
            return list(self.got)

    def wait_for(self, last: bytes, limit: float = 5.0) -> list[bytes]:
        """The frames got once the newest is ``last`` (the motor's thread reads the bus on
        its own: a frame the host sent is there a moment later). ``limit`` only ends a
        failing test; nothing is timed."""
        deadline = time.monotonic() + limit
        while time.monotonic() < deadline:
            got = self.frames()
            if got and got[-1] == last:
                return got
            time.sleep(0.002)
        return self.frames()

    def _serve(self) -> None:
        while not self._stop.is_set():
            msg = self._bus.recv(0.005)
            if msg is None:
                continue
            with self._lock:
                self.got_ids.append(msg.arbitration_id)
                if msg.arbitration_id != self.node:
                    answer = self.answer_other(msg)
                else:
                    self.got.append(bytes(msg.data))
                    answer = self.answer(bytes(msg.data))
            if answer is not None:
                self._bus.send(can.Message(arbitration_id=self.reply_id, data=answer, is_extended_id=False))

    def answer_other(self, msg: can.Message) -> bytes | None:
        """Frames to other ids (Damiao register reads on 0x7FF): none by default."""
        return None

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2.0)
        self._bus.shutdown()


@contextmanager
def fake_motor(node: int, answer: Answer, reply_id: int = 0) -> Iterator[tuple[can.BusABC, FakeMotor]]:
    """(the host's bus, the motor) on a fresh virtual channel; both closed after."""
    channel = f"mit-fake-{next(_CHANNELS)}"
    host = can.Bus(interface="virtual", channel=channel)
    motor = FakeMotor(channel, node, answer, reply_id)
    try:
        yield host, motor
    finally:
        motor.close()
        host.shutdown()
