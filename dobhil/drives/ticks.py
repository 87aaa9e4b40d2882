"""The real-time tick clock of emulated drives: reading a bus into ticks, and the ticks.

An emulated drive (:class:`~dobhil.drives.emulated.EmulatedDrive`) and several drives sharing
one bus (:class:`~dobhil.drives.emulated_nodes.EmulatedNodes`) run the same clock: every
``period`` s a tick applies the frames that arrived during it, then the plants step and the
cyclic frames go out. :class:`TickReader` is the one reader of the bus (what arrived before a
deadline, in batches); :func:`run_ticks` the clock (ticks far behind are skipped, not
replayed: a drive that was starved does not catch up with a burst of stale ticks).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from typing import Final

import can

from dobhil.errors import BusError, exception_line

#: real time: ticks later than this many periods are skipped, not replayed
MAX_LAG_PERIODS: Final = 10
#: real time: frames read together at most (a flood must not stall the ticks)
MAX_BATCH: Final = 64

#: applies a batch of frames read within the tick (tick start, deadline: ``time.perf_counter``)
Take = Callable[[list[can.Message], float, float], None]


class TickReader:
    """Reads ``bus`` for a tick clock until ``stopped()``. The bus stays the caller's."""

    def __init__(self, bus: can.BusABC, stopped: Callable[[], bool]) -> None:
        self.bus = bus
        self._stopped = stopped
        #: the smallest (wall clock - bus stamp) seen, the offset of a bus whose stamps run on
        #: another clock (a hub on another machine); see :meth:`arrived_by`
        self.least_lag = math.inf
        #: a frame read after a deadline the thread reached late, that arrived after that
        #: deadline too: the next tick's (a read frame cannot go back to the socket)
        self.next_tick: can.Message | None = None

    def receive_until(self, deadline: float, tick_start: float, take: Take) -> None:
        """``take`` the frames that arrive before ``deadline`` (``time.perf_counter``), each
        batch as it is read; at the deadline, those that arrived before it but were not read
        yet (:meth:`arrived_by`)."""
        held, self.next_tick = self.next_tick, None
        if held is not None:
            self.saw([held])
            take([held], tick_start, deadline)
        while not self._stopped():
            remaining = deadline - time.perf_counter()
            if remaining <= 0:
                batch = self.arrived_by(deadline)
            else:
                batch = self.read_batch(remaining)
            if batch:
                self.saw(batch)
                take(batch, tick_start, deadline)
            if remaining <= 0:
                return

    def saw(self, batch: list[can.Message]) -> None:
        """Account for the bus stamps of frames read now (:attr:`least_lag`)."""
        wall = time.time()
        for msg in batch:
            if msg.timestamp:
                self.least_lag = min(self.least_lag, wall - msg.timestamp)

    def arrived_by(self, deadline: float) -> list[can.Message]:
        """The frames already queued at ``deadline`` that the bus stamped before it: a drive
        applies whatever reached it before its control tick. Why: a thread that wakes late (a
        loaded machine; software emulation) finds the deadline passed, and would otherwise
        leave a command that came in time to a later tick -- a sample of delay the sampled
        model does not have (measured in the kernel guest: 5 in 500 ticks of a 10 ms run).
        The first frame stamped after the deadline, or with no stamp, waits for the next tick.
        Stamps are the bus's receive times on the wall clock (SocketCAN's kernel stamps,
        python-can's ``virtual``), shifted by the smallest lag seen (:attr:`least_lag`) when
        a bus stamps on another clock."""
        cutoff = time.time() - (time.perf_counter() - deadline)
        if math.isfinite(self.least_lag):
            cutoff -= self.least_lag
        batch: list[can.Message] = []
        while len(batch) < MAX_BATCH and not self._stopped():
            msg = self.read(0.0)
            if msg is None:
                break
            if not (msg.timestamp and msg.timestamp <= cutoff):
                self.next_tick = msg
                break
            batch.append(msg)
        return batch

    def read_batch(self, timeout: float) -> list[can.Message]:
        """The next frame (waiting up to ``timeout`` s) and every frame already queued
        behind it, at most :data:`MAX_BATCH`: what came while the drive was busy is handled
        together, newest last, so a protocol can skip what a newer frame supersedes."""
        batch: list[can.Message] = []
        wait = timeout
        while len(batch) < MAX_BATCH:
            try:
                msg = self.read(wait)
            except BusError:
                if not batch:
                    raise
                break   # the frames read so far first; the next read raises again
            if msg is None:
                break
            batch.append(msg)
            wait = 0.0
        return batch

    def read(self, timeout: float) -> can.Message | None:
        """One frame, None after ``timeout`` s; a failing bus is a BusError (it ends the ticks)."""
        try:
            return self.bus.recv(timeout)
        except Exception as exc:  # the bus is gone: the ticks end with this
            raise BusError(f"{self.bus.channel_info}: read failed: {exception_line(exc)}") from exc


def run_ticks(period: float, stopped: Callable[[], bool], tick: Callable[[float, float], None],
              skipped: Callable[[int], None]) -> None:
    """Every ``period`` s (``time.perf_counter``) until ``stopped()``: ``tick(tick_start,
    deadline)``; when the clock falls more than :data:`MAX_LAG_PERIODS` behind, the ticks
    it missed are ``skipped(count)``, not run."""
    start = time.perf_counter()
    n = 1
    while not stopped():
        tick(start + (n - 1) * period, start + n * period)
        n += 1
        lag = time.perf_counter() - (start + n * period)
        if lag > MAX_LAG_PERIODS * period:
            missed = int(lag / period)
            n += missed
            skipped(missed)


__all__ = ["MAX_BATCH", "MAX_LAG_PERIODS", "Take", "TickReader", "run_ticks"]
