"""LockstepBus.send_periodic: python-can's periodic send, natively, in simulated time."""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager

import can
import pytest

from dobhil.drives.periodic import native_periodic
from dobhil.drives.load import load_profile
from dobhil.drives.emulated import EmulatedDrive, LockstepBus

DT = 1e-3
SYNC, ANSWER, CYCLIC = 0x80, 0x185, 0x705


class _Still:
    position = 0.0
    velocity = 0.0

    def step(self, torque_nm: float, dt: float) -> None:
        pass


class _Echoing(EmulatedDrive):
    """A tiny drive: notes (its time, id) of every frame it reads, answers a SYNC at once
    with a frame carrying the SYNC's count, and sends one cyclic frame every ``cyclic`` s."""

    def __init__(self, bus: can.BusABC, cyclic: float = 0.0) -> None:
        super().__init__(bus, load_profile("odrive-0.6"), _Still())
        self.seen: list[tuple[float, int]] = []
        self.syncs = 0
        self._period = cyclic

    def _on_frame(self, msg: can.Message) -> None:
        self.seen.append((self.time, msg.arbitration_id))
        if msg.arbitration_id == SYNC:
            self.syncs += 1
            self._send(can.Message(arbitration_id=ANSWER, is_extended_id=False, data=[self.syncs & 0xFF]))

    def _on_time(self, now: float) -> None:
        pass

    def _plant_torque(self) -> float:
        return 0.0

    def _cyclic_frames(self) -> Sequence[tuple[float, Callable[[], can.Message]]]:
        if not self._period:
            return ()
        return [(self._period, lambda: can.Message(arbitration_id=CYCLIC, is_extended_id=False))]


@contextmanager
def _rig(channel: str, cyclic: float = 0.0) -> Iterator[tuple[LockstepBus, _Echoing]]:
    host = can.Bus(interface="virtual", channel=channel)
    emu = _Echoing(can.Bus(interface="virtual", channel=channel), cyclic)
    lock = LockstepBus(host, [emu], dt=DT)
    try:
        yield lock, emu
    finally:
        lock.shutdown()
        emu.close()
        host.shutdown()


def _read(lock: LockstepBus, until: float) -> list[tuple[float, int, float]]:
    """(simulated time read, id, stamp) of every frame the host reads until ``until``."""
    out = []
    while (msg := lock.recv(max(until - lock.clock(), 0.0))) is not None:   # None: at ``until``
        out.append((round(lock.clock() / DT), msg.arbitration_id, msg.timestamp))
    return out


def test_a_frame_every_two_steps_reaches_the_drive_and_comes_back_stamped() -> None:
    with _rig("lockstep-periodic-1") as (lock, emu):
        assert native_periodic(lock)
        task = lock.send_periodic(can.Message(arbitration_id=SYNC, is_extended_id=False, data=b""), 2 * DT)
        got = _read(lock, 9 * DT)
        # the echo (stamped with the simulated instant) first, then the drive's answer
        assert [(step, arb) for step, arb, _ in got] == [
            (2, SYNC), (2, ANSWER), (4, SYNC), (4, ANSWER), (6, SYNC), (6, ANSWER), (8, SYNC), (8, ANSWER)]
        assert [stamp for _, arb, stamp in got if arb == SYNC] == pytest.approx([2 * DT, 4 * DT, 6 * DT, 8 * DT],
                                                                                abs=1e-12)
        assert [(round(t / DT), arb) for t, arb in emu.seen] == [(2, SYNC), (4, SYNC), (6, SYNC), (8, SYNC)]
        task.stop()
        assert _read(lock, 14 * DT) == []
        assert emu.syncs == 4


def test_the_periodic_frame_comes_after_what_the_drive_sent_before_it_and_before_host_frames() -> None:
    """At an instant where the drive's own cyclic frame falls too, the host reads it first
    (it went out as the drive reached the instant), then the echo, then the answer; a frame
    the host sends after reading them reaches the drive after the periodic one."""
    with _rig("lockstep-periodic-2", cyclic=DT) as (lock, emu):
        lock.send_periodic(can.Message(arbitration_id=SYNC, is_extended_id=False), DT)
        got = _read(lock, 2 * DT)
        assert [(step, arb) for step, arb, _ in got] == [(1, CYCLIC), (1, SYNC), (1, ANSWER),
                                                        (2, CYCLIC), (2, SYNC), (2, ANSWER)]
        lock.send(can.Message(arbitration_id=0x205, is_extended_id=False))
        _read(lock, 3 * DT)
        assert [(round(t / DT), arb) for t, arb in emu.seen] == [(1, SYNC), (2, SYNC), (2, 0x205), (3, SYNC)]


def test_start_stop_restart_duration_and_modify_data() -> None:
    with _rig("lockstep-periodic-3") as (lock, emu):
        _read(lock, 3 * DT)
        task = lock.send_periodic(can.Message(arbitration_id=SYNC, is_extended_id=False, data=b"\x01"), 2 * DT,
                                  duration=4 * DT)
        got = _read(lock, 12 * DT)
        assert [step for step, arb, _ in got if arb == SYNC] == [5, 7]   # one period after the start
        task.start()
        task.modify_data(can.Message(arbitration_id=SYNC, is_extended_id=False, data=b"\x02"))
        lock.send_periodic(can.Message(arbitration_id=0x81, is_extended_id=False), 3 * DT, duration=2 * DT)
        got = _read(lock, 20 * DT)
        assert [(step, arb) for step, arb, _ in got if arb != ANSWER] == [(14, SYNC), (16, SYNC)]
        assert [(round(t / DT), arb) for t, arb in emu.seen][-2:] == [(14, SYNC), (16, SYNC)]
        lock.stop_all_periodic_tasks()


def test_periods_that_are_not_whole_steps_are_refused() -> None:
    with _rig("lockstep-periodic-4") as (lock, _):
        msg = can.Message(arbitration_id=SYNC, is_extended_id=False)
        for bad in (1.5 * DT, 0.5 * DT, 0.0, -DT, float("nan"), float("inf")):
            with pytest.raises(ValueError, match="whole multiple"):
                lock.send_periodic(msg, bad)
        lock.send_periodic(msg, 3 * DT).stop()


def test_shutdown_stops_the_tasks() -> None:
    with _rig("lockstep-periodic-5") as (lock, emu):
        task = lock.send_periodic(can.Message(arbitration_id=SYNC, is_extended_id=False), DT)
        lock.stop_all_periodic_tasks()
        assert not task.running   # type: ignore[attr-defined]
        _read(lock, 3 * DT)
        assert emu.seen == []


def _run_once(channel: str) -> list[tuple[int, int, float, bytes]]:
    with _rig(channel, cyclic=3 * DT) as (lock, emu):
        lock.send_periodic(can.Message(arbitration_id=SYNC, is_extended_id=False), 2 * DT)
        lock.send_periodic([can.Message(arbitration_id=0x90, is_extended_id=False, data=[i]) for i in range(3)],
                           5 * DT)
        out = []
        for k in range(60):
            msg = lock.recv(DT)
            if msg is not None:
                out.append((k, msg.arbitration_id, msg.timestamp if msg.arbitration_id in (SYNC, 0x90)
                            else 0.0, bytes(msg.data)))
            if k % 7 == 0:
                lock.send(can.Message(arbitration_id=0x205, is_extended_id=False, data=[k]))
        return out + [(0, arb, t, b"") for t, arb in emu.seen]


def test_runs_are_bit_identical() -> None:
    first, second = _run_once("lockstep-periodic-6"), _run_once("lockstep-periodic-7")
    assert first == second
    assert [d for _, arb, _, d in first if arb == 0x90][:4] == [b"\x00", b"\x01", b"\x02", b"\x00"]


def test_the_recording_wrapper_forwards_a_native_periodic_send_and_records_its_echo() -> None:
    from types import SimpleNamespace

    from dobhil.recording.runlog import RecordingBus
    from dobhil.recording.schemas import Topic
    seen: list[tuple[int, int]] = []
    def frame(topic: int, msg: can.Message) -> None:
        seen.append((topic, msg.arbitration_id))
    log = SimpleNamespace(received=frame, sent=frame)   # RunLog's two frame hooks
    with _rig("lockstep-periodic-8") as (lock, emu):
        with RecordingBus(lock, log) as tap:  # type: ignore[arg-type]
            assert native_periodic(tap)
            task = tap.send_periodic(can.Message(arbitration_id=SYNC, is_extended_id=False), 2 * DT)
            assert type(task).__name__ == "LockstepPeriodicTask"
            while tap.recv(max(4 * DT - lock.clock(), 0.0)) is not None:
                pass
        assert not task.running   # type: ignore[attr-defined]   # the wrapper's shutdown stopped it
        assert seen == [(Topic.CAN_RX, SYNC), (Topic.CAN_RX, ANSWER)] * 2
        assert [(round(t / DT), arb) for t, arb in emu.seen] == [(2, SYNC), (4, SYNC)]
    # a wrapped bus without a periodic send of its own: python-can's thread, through the
    # wrapper's send (recorded as sent)
    seen.clear()
    with can.Bus(interface="virtual", channel="lockstep-periodic-9") as inner, \
            can.Bus(interface="virtual", channel="lockstep-periodic-9") as peer, \
            RecordingBus(inner, log) as tap:  # type: ignore[arg-type]
        assert not native_periodic(tap)
        task = tap.send_periodic(can.Message(arbitration_id=SYNC, is_extended_id=False), 0.001)
        assert type(task).__name__ == "ThreadBasedCyclicSendTask"
        assert peer.recv(5.0) is not None
        task.stop()
        assert seen and seen[0] == (Topic.CAN_TX, SYNC)


def test_two_tasks_due_at_one_instant_keep_the_wire_order() -> None:
    """Each periodic frame is on the wire before the answers to it, and the next after them."""
    with _rig("lockstep-periodic-10") as (lock, emu):
        lock.send_periodic(can.Message(arbitration_id=SYNC, is_extended_id=False), 2 * DT)
        lock.send_periodic(can.Message(arbitration_id=0x90, is_extended_id=False), 5 * DT)
        got = [(step, arb) for step, arb, _ in _read(lock, 10 * DT) if step == 10]
        assert got == [(10, SYNC), (10, ANSWER), (10, 0x90)]
        assert [(round(t / DT), arb) for t, arb in emu.seen][-2:] == [(10, SYNC), (10, 0x90)]
