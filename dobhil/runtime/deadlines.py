"""How host timing waits for its deadlines, shared by the loops and by anything that must
wait exactly as they do (``tools/bench.py``'s bare loop, the loop's own yardstick).

Absolute deadlines ``t0 + k T``: ``time.sleep`` to ``spin`` s before a deadline (a blocked
thread wakes tens of microseconds late), then spin on the clock to it; after an overrun the
deadlines already passed are skipped, never run late one after the other (a loop that caught
up would send a burst of commands computed on stale feedback).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Protocol

from dobhil.drives.waits import WAIT_SLICE


class StopFlag(Protocol):
    """What a wait polls to end early (the loop's ``StopRequest``)."""

    def is_set(self) -> bool: ...


def next_deadline(k: int, now: float, t0: float, period: float) -> int:
    """The index of the deadline to wait for after cycle ``k`` ended at ``now``: ``k + 1``, or
    after an overrun (``now`` past it) the first deadline not yet passed. An index above
    ``k + 1`` is an overrun; the ones between were skipped."""
    nxt = k + 1
    if now > t0 + nxt * period:
        nxt = int((now - t0) / period) + 1
    return nxt


def sleep_until(deadline: float, *, spin: float, clock: Callable[[], float], stop: StopFlag) -> None:
    """``time.sleep`` to ``spin`` s before ``deadline``, then spin on ``clock`` to it. Sleeps
    longer than WAIT_SLICE are cut in slices, so a long period still answers ``stop``."""
    remaining = deadline - clock() - spin
    while remaining > WAIT_SLICE:
        time.sleep(WAIT_SLICE)
        if stop.is_set():
            return   # the next cycle stops
        remaining = deadline - clock() - spin
    if remaining > 0:
        time.sleep(remaining)
    while clock() < deadline:
        pass
