"""The emulated drives' tick clock (dobhil/drives/ticks.py): what a tick reads, and ticks skipped."""

from __future__ import annotations

import time
import uuid
from typing import Any

import can
import pytest

from dobhil.drives.ticks import MAX_BATCH, MAX_LAG_PERIODS, TickReader, run_ticks
from dobhil.errors import BusError


def _pair() -> tuple[can.BusABC, can.BusABC]:
    channel = f"ticks-{uuid.uuid4().hex}"
    return can.Bus(interface="virtual", channel=channel), can.Bus(interface="virtual", channel=channel)


def _wait_past(stamp: float) -> None:
    """Until the wall clock is past ``stamp`` (a frame sent then is stamped after it)."""
    while time.time() <= stamp:
        time.sleep(1e-4)


def test_a_frame_stamped_after_the_deadline_waits_for_the_next_tick() -> None:
    host, drive = _pair()
    try:
        reader = TickReader(drive, lambda: False)
        host.send(can.Message(arbitration_id=1))
        deadline, wall = time.perf_counter(), time.time()
        _wait_past(wall)
        host.send(can.Message(arbitration_id=2))
        assert [m.arbitration_id for m in reader.arrived_by(deadline)] == [1]
        assert reader.next_tick is not None and reader.next_tick.arbitration_id == 2
        taken: list[list[int]] = []
        reader.receive_until(time.perf_counter(), 0.0, lambda b, s, d: taken.append([m.arbitration_id for m in b]))
        assert taken[0] == [2], taken   # the held frame first, in the next tick
        assert reader.least_lag < 1.0   # the stamps seen are of this clock
    finally:
        host.shutdown()
        drive.shutdown()


def test_a_batch_is_what_was_queued_at_most_max_batch() -> None:
    host, drive = _pair()
    try:
        for i in range(MAX_BATCH + 3):
            host.send(can.Message(arbitration_id=i))
        reader = TickReader(drive, lambda: False)
        first = reader.read_batch(0.1)
        assert [m.arbitration_id for m in first] == list(range(MAX_BATCH))
        assert [m.arbitration_id for m in reader.read_batch(0.1)] == [MAX_BATCH, MAX_BATCH + 1, MAX_BATCH + 2]
    finally:
        host.shutdown()
        drive.shutdown()


class _Failing(can.BusABC):
    """Gives ``frames`` then fails, as a bus whose interface went away."""

    def __init__(self, frames: int) -> None:
        self.left = frames
        self.channel_info = "failing"
        super().__init__(channel="failing")

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        if self.left <= 0:
            raise can.CanOperationError("interface gone")
        self.left -= 1
        return can.Message(arbitration_id=self.left), False

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        raise can.CanOperationError("interface gone")


def test_the_frames_read_before_a_bus_failure_come_first_then_the_failure() -> None:
    bus = _Failing(2)
    try:
        reader = TickReader(bus, lambda: False)
        assert len(reader.read_batch(0.0)) == 2
        with pytest.raises(BusError, match="failing: read failed: CanOperationError: interface gone"):
            reader.read_batch(0.0)
    finally:
        bus.shutdown()


def test_ticks_far_behind_are_skipped_not_replayed() -> None:
    period = 1e-3
    ticks: list[tuple[float, float]] = []
    skips: list[int] = []
    stall = (MAX_LAG_PERIODS + 5) * period

    def tick(start: float, deadline: float) -> None:
        ticks.append((start, deadline))
        if len(ticks) == 3:
            time.sleep(stall)   # the thread was starved

    def stopped() -> bool:
        return len(ticks) >= 6

    run_ticks(period, stopped, tick, skips.append)
    assert skips and all(s >= MAX_LAG_PERIODS for s in skips), skips
    index = [round((d - ticks[0][1]) / period) for _, d in ticks]
    steps = [b - a for a, b in zip(index, index[1:])]
    # every tick is one period after the last, except after a skip: the skipped ticks later
    assert sorted(s - 1 for s in steps if s != 1) == sorted(skips), (steps, skips)
    assert all(abs((d - s) - period) < 1e-9 for s, d in ticks)


def test_the_reader_stops_reading_when_told() -> None:
    host, drive = _pair()
    try:
        stop = [False]
        reader = TickReader(drive, lambda: stop[0])
        stop[0] = True
        taken: list[Any] = []
        reader.receive_until(time.perf_counter() + 10.0, 0.0, lambda b, s, d: taken.append(b))
        assert taken == []   # returned at once, nothing read
    finally:
        host.shutdown()
        drive.shutdown()
