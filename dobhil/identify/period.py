"""The control period of a CAN log imported without one, and each frame's place on it: the
nominal period its frame stamps scatter around, and the deadline each frame belongs to.

Why not the median spacing: stamps are the capturing host's clock, jittered by the bus and
the host and rounded -- an epoch time of ~1.8e9 s held in a double is a multiple of 2.4e-7 s,
so every spacing is too -- and their median spacing is a few parts in 1e5 off the period the
loop ran at (measured: 0.999928 ms for a 1 ms run exported with ``dobhil log export --can
--format candump``); the fit scales the inertia with the period squared, and J came out
0.249982 with an interval of +-2e-8 that excludes the true 0.25.

Why not each spacing counted in periods on its own either: a sender that was not scheduled
for a while sends the frames of the deadlines it missed in a burst when it runs again (the
emulated drive does: ``dobhil/drives/ticks.py``, up to ten periods behind), and a burst of
three frames after a gap of three periods counts as 3 + 1 + 1 = 5 periods. Measured in the
kernel guest: a 20 ms run's candump log gave 19.533 ms, 2.3 % short.

So each frame gets the number of the deadline it belongs to on a lattice ``t0 + k T``: its
stamp rounded to the nearest deadline, then, as stamps only ever come late, a frame that
rounds onto or past the next frame's deadline takes the one before (a burst fills the
deadlines it missed; a frame lost on the bus leaves its number out). The period ``T`` is the
least-squares slope of the stamps against those numbers (the jitter and the rounding average
out, ~jitter / n^1.5), frames further than :data:`CLIP` robust standard deviations off the
line left out (the late ones of a burst), the lattice refined on a window that doubles until it spans
the log (a first guess off by a percent drifts half a period only after 50 frames), the
first window the log's most regular stretch and its phase an on-time frame's. A
control loop runs at a whole number of microseconds: the slope is snapped to it when within
:data:`SNAP` plus three of the slope's standard errors (a host clock's skew, tens of ppm, is
below SNAP; a loop period that is not whole -- 333.33 us -- keeps the slope itself).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view
from numpy.typing import NDArray

__all__ = ["CLIP", "SNAP", "Lattice", "frame_lattice", "nominal_period"]

#: the largest relative difference between the mean spacing and a whole number of
#: microseconds that still counts as that period seen through a host clock's skew
SNAP = 2e-4
#: frames further off the fitted line than this many robust standard deviations of its
#: residuals are late ones (a burst after a gap), left out of the fit; uniform jitter
#: reaches 1.35 of them, so none of it is left out
CLIP = 3.0
#: the first window the lattice is fitted on, in frames (doubled until it spans the log)
_FIRST_WINDOW = 16
#: passes of the clipped fit at most (a pass that leaves out the same frames as the one before ends it)
_MAX_CLIPS = 20
#: a normal distribution's standard deviation per median absolute deviation
_MAD_SIGMA = 1.4826


@dataclass(frozen=True)
class Lattice:
    """The deadlines a log's frames belong to: ``period`` [s], how it was found
    (``"nominal"``: a whole number of microseconds; ``"mean"``: the fitted slope, no whole
    one near it) and each frame's deadline ``number`` (increasing, the first 0; a number left
    out is a deadline no frame came for)."""

    period: float
    how: str
    number: NDArray[np.int64]
    #: the fitted slope [s] and how far from it a period still agrees with the stamps:
    #: :data:`SNAP` of it (a host clock's skew) plus three of its standard errors (the jitter)
    slope: float = float("nan")
    spread: float = float("inf")

    def agrees(self, period: float) -> bool:
        """Whether the stamps could have been taken of a loop running at ``period`` [s] (the
        test that snaps the slope to a whole microsecond; any period when they tell none)."""
        return not math.isfinite(self.slope) or abs(period - self.slope) <= self.spread


def nominal_period(stamps: NDArray[np.float64]) -> tuple[float, str]:
    """The period ``stamps`` [s] (increasing) scatter around and how it was found
    (:class:`Lattice`). NaN when the stamps do not increase."""
    found = frame_lattice(stamps)
    return found.period, found.how


def frame_lattice(stamps: NDArray[np.float64]) -> Lattice:
    """The period ``stamps`` [s] (increasing) scatter around and each frame's deadline on it
    (the module docstring). A NaN period, every frame numbered in turn, when the stamps do
    not increase."""
    t = np.asarray(stamps, float)
    t = t - t[0] if t.size else t                    # small numbers: no epoch's rounding
    in_turn = np.arange(t.size, dtype=np.int64)
    spacing = np.diff(t)
    median = float(np.median(spacing)) if spacing.size else float("nan")
    if not median > 0.0:
        return Lattice(float("nan"), "mean", in_turn)
    if t.size < 3:
        return Lattice(median, "mean", in_turn)
    lo = _quietest(spacing, median, min(t.size, _FIRST_WINDOW))
    hi = lo + min(t.size, _FIRST_WINDOW)
    slope, offset, stderr = median, float(t[lo]), 0.0   # the lattice through an on-time frame
    while True:
        number = _numbers(t[lo:hi], slope, offset)
        slope, offset, stderr = _clipped_fit(number, t[lo:hi], slope)
        if lo == 0 and hi == t.size:
            break
        grow = hi - lo
        lo, hi = max(0, lo - grow // 2), min(t.size, hi + grow - grow // 2)
    number = _numbers(t, slope, offset)
    number -= number[0]
    whole = round(slope * 1e6) * 1e-6
    spread = SNAP * slope + 3.0 * stderr
    if whole > 0.0 and abs(whole - slope) <= spread:
        return Lattice(whole, "nominal", number, slope, spread)
    return Lattice(slope, "mean", number, slope, spread)


def _quietest(spacing: NDArray[np.float64], median: float, frames: int) -> int:
    """The first frame of the ``frames`` consecutive ones whose spacing strays least from
    ``median`` (the most regular stretch: frames on time, no burst in it -- a lattice
    started on a burst's late frames would put the on-time ones half a period off)."""
    if frames < 2 or spacing.size < frames - 1:
        return 0
    stray = np.abs(spacing - median)
    return int(np.argmin(sliding_window_view(stray, frames - 1).max(axis=1)))


def _numbers(t: NDArray[np.float64], period: float, offset: float) -> NDArray[np.int64]:
    """Each stamp's deadline on ``offset + k period``: the nearest, or, where that is not
    before the next stamp's, the one before it (stamps only come late)."""
    nearest = np.round((t - offset) / period).astype(np.int64)
    order = np.arange(t.size, dtype=np.int64)
    # number[i] <= number[i + 1] - 1 for every i is (number - order) non-decreasing:
    # a running minimum from the end
    return np.minimum.accumulate((nearest - order)[::-1])[::-1] + order


def _clipped_fit(number: NDArray[np.int64], t: NDArray[np.float64], guess: float) -> tuple[float, float, float]:
    """(slope, offset, the slope's standard error) of ``t`` against ``number`` by least
    squares over the stamps within :data:`CLIP` robust standard deviations (1.4826 times the
    median absolute deviation) of the line; the first line ``guess``'s slope through the
    lower quarter of the stamps. Why robust: a burst's late stamps at a window's end pull a
    least-squares line towards them far enough to hide inside three of its own standard
    deviations."""
    k = number.astype(float)
    slope, offset = guess, float(np.median(t - guess * k))
    keep = np.ones(t.size, dtype=bool)
    for clip in range(_MAX_CLIPS):
        resid = t - (slope * k + offset)
        if clip == 0:
            # stamps only come late: the on-time ones are the lowest, so the first line goes
            # through the lower quarter and takes its scale from the lower half -- a window
            # that starts with a burst of more than half its frames still finds them
            low = resid[resid <= np.median(resid)]
            centre = float(np.percentile(resid, 25))
            scale = _MAD_SIGMA * float(np.median(np.abs(low - centre)))
        else:
            centre = float(np.median(resid[keep]))
            scale = _MAD_SIGMA * float(np.median(np.abs(resid[keep] - centre)))
        kept = np.abs(resid - centre) <= CLIP * max(scale, 1e-9 * abs(slope))
        if clip > 0 and (kept.sum() < 3 or (kept == keep).all()):
            break
        if kept.sum() >= 3:
            keep = kept
        (slope, offset), *_ = np.linalg.lstsq(np.column_stack([k[keep], np.ones(int(keep.sum()))]), t[keep],
                                              rcond=None)
    resid = t - (slope * k + offset)
    spread = float(np.sqrt(np.sum(resid[keep] ** 2) / (int(keep.sum()) - 2))) if keep.sum() > 2 else 0.0
    centred = k[keep] - k[keep].mean()
    stderr = spread / float(np.sqrt(np.sum(centred ** 2))) if centred.size > 1 else 0.0
    return float(slope), float(offset), stderr
