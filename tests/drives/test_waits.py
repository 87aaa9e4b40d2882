"""dobhil.drives.waits.sliced_frames: the one cancellable, sliced bus wait.

On a simulated bus whose clock moves only while a read waits (as the lockstep bus's),
so every bound below is on that clock and exact, not a wall-clock count.
"""

from __future__ import annotations

import time
from collections.abc import Iterable

import can
import pytest
from hypothesis import given
from hypothesis import strategies as st

from dobhil.drives.waits import WAIT_SLICE, sliced_frames
from dobhil.errors import WaitCancelled

EPS = 1e-9


class SimBus:
    """Frames due at given times; ``read(timeout)`` returns the next one due within
    ``timeout`` (the clock moves to its time) or moves the clock by ``timeout``."""

    def __init__(self, arrivals: Iterable[float] = ()) -> None:
        self.now = 0.0
        self.due = sorted(arrivals)
        self.reads: list[tuple[float, float]] = []   # (clock at the read, its timeout)

    def clock(self) -> float:
        return self.now

    def read(self, timeout: float) -> can.Message | None:
        assert 0.0 <= timeout <= WAIT_SLICE + EPS
        self.reads.append((self.now, timeout))
        if self.due and self.due[0] <= self.now + timeout:
            self.now = max(self.now, self.due.pop(0))
            return can.Message(arbitration_id=0x123, timestamp=self.now)
        self.now += timeout
        return None


def test_a_frame_arriving_is_given_and_the_caller_stops_there() -> None:
    bus = SimBus([0.05, 0.3])
    got = next(iter(sliced_frames(bus.read, bus.clock, 1.0)))
    assert got.timestamp == pytest.approx(0.05)
    assert bus.now == pytest.approx(0.05)      # nothing read after it
    assert bus.due == [0.3]


def test_the_deadline_ends_the_wait_in_slices_never_past_it() -> None:
    bus = SimBus()
    assert list(sliced_frames(bus.read, bus.clock, 0.105)) == []
    assert bus.now == pytest.approx(0.105)
    assert all(t <= WAIT_SLICE + EPS for _, t in bus.reads)
    assert all(at + t <= 0.105 + EPS for at, t in bus.reads)
    assert len(bus.reads) == 6                  # 5 whole slices and the 5 ms left


def test_cancel_mid_wait_raises_within_one_slice_naming_the_wait() -> None:
    bus = SimBus([0.01])
    asked: list[float] = []

    def cancel() -> str:
        asked.append(bus.now)
        return "received SIGINT" if bus.now >= 0.5 else ""

    frames = sliced_frames(bus.read, bus.clock, 10.0, cancel=cancel, what="waiting for node 3")
    assert next(frames).timestamp == pytest.approx(0.01)
    with pytest.raises(WaitCancelled, match="^received SIGINT while waiting for node 3$"):
        next(frames)
    assert 0.5 <= bus.now <= 0.5 + WAIT_SLICE + EPS
    assert len(asked) == len(bus.reads) + 1     # before every read, and the one that stopped it


def test_drain_gives_what_is_queued_once_the_deadline_passed() -> None:
    bus = SimBus([0.0, 0.0])
    bus.now = 2.0                               # the caller was late: the wait is over already
    cancelled = list(sliced_frames(bus.read, bus.clock, 1.0, cancel=lambda: "never asked", drain=True))
    assert len(cancelled) == 2 and bus.reads == [(2.0, 0.0)] * 3
    assert list(sliced_frames(bus.read, bus.clock, 1.0)) == []


def test_between_needs_a_period() -> None:
    bus = SimBus()
    with pytest.raises(ValueError, match="every must be > 0"):
        next(iter(sliced_frames(bus.read, bus.clock, 1.0, between=lambda: None)))


@given(arrivals=st.lists(st.floats(0.0, 2.0), max_size=30), until=st.floats(0.0, 1.0),
       every=st.floats(0.001, 0.5), stop_at=st.floats(0.0, 3.0))
def test_any_schedule(arrivals: list[float], until: float, every: float, stop_at: float) -> None:
    """Every frame due before the end is given, in order; no read passes the deadline or
    the next keepalive; keepalives come every ``every`` s; a cancel is heard within one
    slice of its reason."""
    bus = SimBus(arrivals)
    ticks: list[float] = []
    got: list[float] = []
    frames = sliced_frames(bus.read, bus.clock, until, cancel=lambda: "stop" if bus.now >= stop_at else "",
                           between=lambda: ticks.append(bus.now), every=every)
    cancelled = False
    try:
        got.extend(m.timestamp for m in frames)
    except WaitCancelled:
        cancelled = True
    end = bus.now
    assert got == sorted(arrivals)[:len(got)] and all(a <= end for a in got)
    assert len(got) >= sum(a < end for a in arrivals)
    if cancelled:
        assert stop_at <= end <= stop_at + WAIT_SLICE + EPS
    else:
        assert until <= end <= until + EPS and stop_at > max((at for at, _ in bus.reads), default=-1.0)
    for at, t in bus.reads:
        last_tick = max(k for k in ticks if k <= at)
        assert at + t <= min(until, last_tick + every) + EPS
    if ticks:
        assert ticks[0] == 0.0
        gaps = [b - a for a, b in zip([*ticks, end], [*ticks, end][1:])]
        assert all(g <= every + EPS for g in gaps)
        assert all(g >= every - EPS for g in gaps[:-1])
    else:
        assert until == 0.0 or stop_at == 0.0


def test_on_a_virtual_bus_a_frame_sent_ends_the_wait() -> None:
    with can.Bus(interface="virtual", channel="waits-test", receive_own_messages=False) as rx, \
            can.Bus(interface="virtual", channel="waits-test") as tx:
        tx.send(can.Message(arbitration_id=0x701, data=b"\x05", is_extended_id=False))
        msg = next(iter(sliced_frames(rx.recv, time.monotonic, time.monotonic() + 60.0,
                                      cancel=lambda: "")))
        assert msg.arbitration_id == 0x701
