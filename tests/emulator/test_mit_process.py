"""The emulated MIT motor in its own process (EmulatorProcess, as ``dobhil run --emulate``
and ``can.Bus(interface="dobhil")`` run it), in real time: every frame answered, the
torque applied, the protocol state published through shared memory; and the command
timeout firing on the wall clock when the host goes quiet.

Waits poll with a generous bound; nothing asserts wall-clock timing."""

from __future__ import annotations

import os
import signal
import time
from pathlib import Path

import can
import pytest

from dobhil import forkserver
from dobhil.config import load_config
from dobhil.emulator.process import EmulatorProcess, EmulatorSpec

from .mit_rig import MINI_CHEETAH, mit_profile
from .test_mit_emulator import AK_ONE_NM, ENTER, EXIT, f32_decode

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


def _command_until_applied(process: EmulatorProcess, bus: can.BusABC, torque: float) -> None:
    """Command ``torque`` until the motor is seen applying it. The 25 ms command timeout
    zeroes it again 25 ms after each command: a test thread that a loaded machine parks for
    longer between the reply and its look would find zero and wait forever for a torque no
    longer applied. Each command reopens that window; a motor that never applies the torque
    still fails at BOUND."""
    end = time.monotonic() + BOUND
    while True:
        bus.send(can.Message(arbitration_id=1, data=AK_ONE_NM, is_extended_id=False))
        _reply(bus)
        if process.applied_torque == torque:
            return
        assert time.monotonic() < end, f"torque again: {process.applied_torque} applied, not {torque}"


@pytest.mark.parametrize("start", ["forked", "interpreter"])
def test_emulator_process_answers_applies_and_times_out(start: str,
                                                        monkeypatch: pytest.MonkeyPatch) -> None:
    """Both ways a child starts: forked from dobhil's fork server (where the platform can)
    and a fresh interpreter (where it cannot)."""
    if start == "interpreter":
        monkeypatch.setattr(forkserver, "available", lambda: False)
    elif not forkserver.available():
        pytest.skip("no fork server on this platform")
    # the Mini-Cheetah firmware's row: its 25 ms command timeout, 7-byte replies
    spec = EmulatorSpec.of(load_config("demo", ["plant.initial_position=-0.05"]), mit_profile(MINI_CHEETAH))
    with EmulatorProcess(spec) as process:
        assert process.pid is not None
        parent = int(Path(f"/proc/{process.pid}/stat").read_text().rsplit(")", 1)[1].split()[1])
        assert (parent == os.getpid()) is (start == "interpreter"), (start, parent)
        bus = process.bus
        bus.send(can.Message(arbitration_id=1, data=ENTER, is_extended_id=False))
        # at -0.05 rad: int(12.45 * 65535 / 25) = 32636 = 0x7F7C; v, t 0: 0x7FF each; byte 6
        # the bus voltage, int(24 * 255 / 40) = 153
        assert _reply(bus) == bytes([1, 0x7F, 0x7C, 0x7F, 0xF7, 0xFF, 153])
        _until(lambda: process.protocol_state == 1, "motor mode")
        bus.send(can.Message(arbitration_id=1, data=AK_ONE_NM, is_extended_id=False))
        _reply(bus)
        # the host then says nothing: the firmware's 25 ms timeout zeroes the torque (2.2 N m:
        # code 2161 of +-40 N m)
        _until(lambda: process.watchdog_tripped, "command timeout")
        assert process.protocol_state == 1 and process.applied_torque == 0.0
        # it was applied before: the plant, free of the environment (5 cm away), moves
        assert process.plant.true_velocity > 0
        _command_until_applied(process, bus, f32_decode(2161, -40, 40, 12))
        bus.send(can.Message(arbitration_id=1, data=EXIT, is_extended_id=False))
        _reply(bus)
        _until(lambda: process.protocol_state == 0 and process.applied_torque == 0.0, "rest")
        assert process.frame_errors == 0 and process.frames_rejected == 0
        # the old names, which read as ODrive's for every protocol, still answer, with a warning
        with pytest.warns(DeprecationWarning, match="axis_state is renamed protocol_state; .* dobhil 0.2"):
            assert process.axis_state == process.protocol_state
        with pytest.warns(DeprecationWarning, match="axis_error is renamed protocol_error"):
            assert process.axis_error == process.protocol_error == 0


def _mask(pid: int, field: str) -> set[int]:
    """The signals of ``SigBlk``/``SigIgn`` in /proc/PID/status (proc(5): a hex bit mask,
    bit n-1 for signal n)."""
    line = next(x for x in Path(f"/proc/{pid}/status").read_text().splitlines() if x.startswith(f"{field}:"))
    bits = int(line.split()[1], 16)
    return {n for n in range(1, 65) if bits >> (n - 1) & 1}


@pytest.mark.parametrize("start", ["forked", "interpreter"])
def test_the_emulated_drive_outlives_sigint_and_sigterm_from_its_start(start: str,
                                                                      monkeypatch: pytest.MonkeyPatch) -> None:
    """A Ctrl-C reaches the whole process group, and the drive must outlive the host's safe
    stop: the child is started with SIGINT and SIGTERM blocked (a signal in its first
    milliseconds waits: tests/test_forkserver.py shows a blocked one stays pending), then
    ignores both and blocks neither; sent both, it still answers."""
    if start == "interpreter":
        monkeypatch.setattr(forkserver, "available", lambda: False)
    elif not forkserver.available():
        pytest.skip("no fork server on this platform")
    masks: list[set[int]] = []
    spawn = EmulatorProcess._spawn

    def spy(self: EmulatorProcess, child_end: object) -> object:
        masks.append(set(signal.pthread_sigmask(signal.SIG_BLOCK, [])))
        return spawn(self, child_end)   # type: ignore[arg-type]

    monkeypatch.setattr(EmulatorProcess, "_spawn", spy)
    before = signal.pthread_sigmask(signal.SIG_BLOCK, [])
    spec = EmulatorSpec.of(load_config("demo", ["plant.initial_position=-0.05"]), mit_profile(MINI_CHEETAH))
    with EmulatorProcess(spec) as process:
        assert signal.pthread_sigmask(signal.SIG_BLOCK, []) == before   # the caller's mask again
        assert masks and {signal.SIGINT, signal.SIGTERM} <= masks[0]
        assert process.pid is not None
        assert {signal.SIGINT, signal.SIGTERM} <= _mask(process.pid, "SigIgn")
        assert not {signal.SIGINT, signal.SIGTERM} & _mask(process.pid, "SigBlk")
        os.kill(process.pid, signal.SIGINT)
        os.kill(process.pid, signal.SIGTERM)
        process.bus.send(can.Message(arbitration_id=1, data=ENTER, is_extended_id=False))
        assert len(_reply(process.bus)) == 7 and process.running
