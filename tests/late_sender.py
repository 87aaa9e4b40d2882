"""A model of a sender that catches up: dobhil/drives/ticks.py ``run_ticks`` as it schedules
the emulated drive, with stalls in which the process is not scheduled. Shared by the tests
of the two things such bursts must not fool: an imported log's period
(tests/identify/test_period.py) and the feedback-rate watch (tests/runtime/test_rate_watch.py)."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray


def catch_up_sends(ticks: int, stalls: list[tuple[float, float]], cost: float) -> NDArray[np.float64]:
    """[periods] when ticks 1..``ticks`` send their frames: each at its deadline ``n`` or, late,
    as soon as the sender runs, ``cost`` periods per frame (a burst after a stall); not
    scheduled in ``stalls`` (start, length) [periods]. run_ticks' skipping of ticks more than
    MAX_LAG_PERIODS behind is left out: a caller that can reach it checks the lag itself."""
    now, sent = 0.0, np.empty(ticks)
    for n in range(1, ticks + 1):
        now = max(now, float(n))
        for start, length in stalls:
            if start <= now < start + length:
                now = start + length
        sent[n - 1] = now
        now += cost
    return sent
