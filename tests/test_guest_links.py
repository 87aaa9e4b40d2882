"""The guest tests' comparisons against the kernel's record (tests/socketcan/links.py), on the
host: a pass or a failure there must be the run's, never the helper's."""

from __future__ import annotations

import random

from hypothesis import given
from hypothesis import strategies as st

from tests.socketcan.links import unmatched

US = 1e-6


def test_a_short_latency_does_not_take_the_entry_a_long_one_needs() -> None:
    """Sample A was measured from the SYNC before its own (its second value, a period more),
    sample B from its own; A's short value lies within the tolerance of B's and below it. The
    first free entry in increasing order gives A's entry to B's measurement and leaves A's
    with nothing; the pairing exists, and is found (SYNC periods differ by their jitter)."""
    truth = [(3000 * US, 23000 * US), (3001.5 * US, 23010 * US)]   # periods of 20 and 20.0085 ms
    measured = [3001 * US, 23000 * US]
    assert unmatched(measured, truth, within=2 * US) == []


def test_what_has_no_entry_is_named() -> None:
    """Two measurements of one entry, and one of none: two are left over, one of the pair
    and the one of none."""
    truth = [(3000 * US,), (4000 * US, 24000 * US)]
    left = unmatched([3000.5 * US, 3000.7 * US, 9000 * US], truth, within=2 * US)
    assert len(left) == 2 and left[-1] == 9000 * US and left[0] in (3000.5 * US, 3000.7 * US)


@given(st.lists(st.tuples(st.integers(0, 400), st.integers(19900, 20100), st.integers(0, 1), st.booleans()),
                min_size=1, max_size=60),
       st.randoms(use_true_random=False))
def test_every_measurement_of_a_distinct_entry_is_matched(samples: list[tuple[int, int, int, bool]],
                                                          rnd: random.Random) -> None:
    """Entries (short, short + a jittered period) on a 1 us grid, dense enough to collide; each
    measured value one of a distinct entry's two, give or take less than the tolerance, in
    any order: nothing is left over. One more measurement than entries always is."""
    truth = [(short * US, (short + period) * US) for short, period, _, _ in samples]
    measured = [value[which] + (0.9 * US if nudge else -0.9 * US)
                for value, (_, _, which, nudge) in zip(truth, samples)]
    rnd.shuffle(measured)
    assert unmatched(measured, truth, within=2 * US) == []
    assert len(unmatched([*measured, measured[0]], truth, within=2 * US)) == 1
