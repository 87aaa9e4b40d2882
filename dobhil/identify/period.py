"""The control period of a CAN log imported without one: the nominal period its frame
stamps scatter around.

Why not the median spacing: stamps are the capturing host's clock, jittered by the bus and
the host and rounded -- an epoch time of ~1.8e9 s held in a double is a multiple of 2.4e-7 s,
so every spacing is too -- and their median spacing is a few parts in 1e5 off the period the
loop ran at (measured: 0.999928 ms for a 1 ms run exported with ``dobhil log export --can
--format candump``); the fit scales the inertia with the period squared, and J came out
0.249982 with an interval of +-2e-8 that excludes the true 0.25.

So the period is the slope of the stamps against their frame numbers (least squares: the
jitter and the rounding average out, ~jitter / n^1.5), every interval counted in periods (a
frame lost on the bus is two periods, not one long one). A control loop runs at a whole
number of microseconds: the slope is snapped to it when within :data:`SNAP` plus three of
the slope's standard errors (a host clock's skew, tens of ppm, is below SNAP; a loop period
that is not whole -- 333.33 us -- keeps the slope itself).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

__all__ = ["SNAP", "nominal_period"]

#: the largest relative difference between the mean spacing and a whole number of
#: microseconds that still counts as that period seen through a host clock's skew
SNAP = 2e-4


def nominal_period(stamps: NDArray[np.float64]) -> tuple[float, str]:
    """The period ``stamps`` [s] (increasing) scatter around and how it was found:
    ``"nominal"`` (a whole number of microseconds, see the module docstring) or ``"mean"``
    (the fitted mean spacing: no whole one near it). NaN when the stamps do not increase."""
    spacing = np.diff(np.asarray(stamps, float))
    median = float(np.median(spacing)) if spacing.size else float("nan")
    if not median > 0.0:
        return float("nan"), "mean"
    index = np.concatenate([[0.0], np.cumsum(np.maximum(np.round(spacing / median), 1.0))])
    t = np.asarray(stamps, float) - float(stamps[0])      # small numbers: no epoch's rounding
    if index.size < 3:
        return median, "mean"
    (slope, offset), *_ = np.linalg.lstsq(np.column_stack([index, np.ones_like(index)]), t, rcond=None)
    resid = t - (slope * index + offset)
    spread = float(np.sqrt(np.sum(resid ** 2) / (index.size - 2)))
    stderr = spread / float(np.sqrt(np.sum((index - index.mean()) ** 2)))
    whole = round(float(slope) * 1e6) * 1e-6
    if whole > 0.0 and abs(whole - slope) <= SNAP * slope + 3.0 * stderr:
        return whole, "nominal"
    return float(slope), "mean"
