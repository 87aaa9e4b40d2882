"""The run-time instability watch: a loop that chatters or grows stops as ``unstable``.

A force loop whose gain is above what the plant, the environment and the delay allow
(``dobhil analyze``: "max stable C_f" of the sampled loop) does not blow up on a drive: the
torque limit bounds it, and what remains is a limit cycle -- the command slammed against
its limit, up to every period -- or, just above the boundary, an oscillation that grows by
a per cent or so per period until it reaches the limit. Both are violent on a motor, and in
a stiff contact neither trips a position or velocity limit. The watch looks at the command
the controller computes each cycle, before and after the clip at the torque limit ``L``,
and decides with two rules:

- **chatter**, over the last ``W`` cycles (``instability.window``): the command was clipped
  in at least ``instability.saturation * W`` of them *and* turned back from the limit at
  least ``instability.limit_reversals * W`` times. A turn is a reversal of the command by
  more than ``instability.hysteresis * L`` (a peak detector with that hysteresis: noise
  below it turns nothing, an oscillation of any frequency above it turns twice a period);
  a turn "from the limit" ends a swing that reached the limit. A stable loop held at its
  limit (a reference beyond it, an impact) saturates without turning back; one tracking a
  fast reference turns without saturating; a stable transient clips for a burst, which a
  long window dilutes, while a limit cycle clips for as long as it lasts.
- **growth**: the swings of the *unclipped* command (how far the loop wants to go; the
  torque the estimate's oscillation asks for, ``C_f`` times it plus the disturbance
  estimate's) grew ``instability.growth_swings`` times in a row, each larger than the
  swing before it in the same direction (up-swings against up-swings: a drift does not
  break the streak), and by ``instability.growth`` in all. This stops an unstable
  oscillation while it is still below the limit.

Bounds on the detection delay, tested in ``tests/runtime/test_instability.py``: a limit
cycle that clips at least ``saturation`` of the time and turns back from the limit at least
``limit_reversals`` per cycle stops within ``W`` cycles of its start (both counts are over
the last ``W`` cycles; a harsher one sooner: the counts are absolute, so a command clipped
every cycle trips after ``saturation * W`` cycles). An oscillation growing by ``r`` per
swing (r up to sqrt(SMOOTH)) stops within ``max(growth_swings, log(growth) / log(r)) + 3`` swings of its swings
first exceeding the hysteresis (one swing per cycle at z = -1, where the delayed loops of
``configs/`` cross).

What it cannot see: a divergence without oscillation (a real pole outside the unit circle:
the servo drifts or pushes one way; the position and velocity limits are for that); an
oscillation below the hysteresis (a slow growth is caught once it exceeds
``hysteresis * L``); a growth too slow to reach ``growth`` within a streak that jitter
breaks (sampled peaks of an oscillation not at z = -1 jitter); a limit cycle that turns back
from the limit less than ``limit_reversals`` per cycle (a slow bounce off the environment)
or clips less than ``saturation`` of the time (just above the boundary a sine-like limit
cycle barely exceeds the limit); and an instability that the drive's quantisation freezes
(an AK80-9 in stiff contact: nothing moves, so nothing chatters). ``docs/hardware.md``
gives the defaults and the margins measured on the shipped designs.

Cost: per cycle a few comparisons, two peak-detector steps and one update of a preallocated
``bytearray`` ring (about 0.9 us with ``timeit`` on a loaded 2-core machine); the peaks are
kept as counts and turned into fractions only when asked (:attr:`InstabilityWatch.peaks`);
nothing prints or blocks. :meth:`InstabilityWatch.cycle` returns "" or the one-line detail of
the stop, built only then.
"""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["InstabilityWatch", "WatchPeaks", "WatchSettings"]

#: growth rule: a swing more than this many times the one before it in its direction breaks
#: the streak. A linear mode grows smoothly; sensor noise amplified by the observers makes
#: swings that jump (measured on the demo with the campaign's noise: streaks of up to 7 of
#: merely larger swings). A faster growth reaches the limit within a few swings anyway.
SMOOTH = 2.0


@dataclass(frozen=True)
class WatchSettings:
    """The thresholds (``instability.*`` config keys) in the loop's units."""

    window: int               # W: cycles the chatter statistics are taken over (>= 2)
    saturation: float         # fraction of W with the command clipped (chatter rule)
    limit_reversals: float    # turns back from the limit per cycle of W (chatter rule)
    hysteresis: float         # a turn smaller than this fraction of the limit is none
    growth: float             # swing growth factor over a growing streak (growth rule)
    growth_swings: int        # swings in a row, each above the one before it in its direction

    def __post_init__(self) -> None:
        if self.window < 2:
            raise ValueError(f"window: expected >= 2 cycles, got {self.window}")
        if not 0.0 < self.saturation <= 1.0 or not 0.0 < self.limit_reversals <= 1.0:
            raise ValueError("saturation and limit_reversals: expected fractions in (0, 1]")
        if not 0.0 < self.hysteresis <= 2.0 or not self.growth > 1.0 or self.growth_swings < 1:
            raise ValueError("hysteresis in (0, 2], growth > 1 and growth_swings >= 1 expected")


@dataclass(frozen=True)
class WatchPeaks:
    """The largest value each statistic reached in a run: its margin to the threshold."""

    saturation: float = 0.0       # fraction of a window clipped
    limit_reversals: float = 0.0  # turns back from the limit per cycle, over a window
    chatter: float = 0.0          # min of the two above over their thresholds (>= 1 trips)
    growth_swings: int = 0        # longest streak of growing swings
    growth: float = 0.0           # largest growth of a streak's swing over its base


class _Swings:
    """A peak detector with hysteresis ``h``: :meth:`add` returns the swing (the distance
    between the last two turning points, 0 for the first turn) when the signal turns back
    by more than ``h`` from its running extreme, else -1. Noise smaller than ``h`` turns
    nothing."""

    __slots__ = ("h", "rising", "extreme", "turn")

    def __init__(self, h: float) -> None:
        self.h = h
        self.rising = True
        self.extreme = float("nan")   # the running extreme since the last turn
        self.turn = float("nan")      # the extreme at the last turn

    def add(self, x: float) -> float:
        e = self.extreme
        if e != e:   # first sample: both ends start here
            self.extreme = self.turn = x
            return -1.0
        if self.rising:
            if x >= e:
                self.extreme = x
                return -1.0
            if x > e - self.h:
                return -1.0
        else:
            if x <= e:
                self.extreme = x
                return -1.0
            if x < e + self.h:
                return -1.0
        swing = abs(e - self.turn)
        self.rising = not self.rising
        self.turn, self.extreme = e, x
        return swing


class InstabilityWatch:
    """The two rules of the module docstring, updated once per cycle in O(1)."""

    def __init__(self, settings: WatchSettings, torque_limit: float) -> None:
        self.s = settings
        self.limit = torque_limit
        self._w = settings.window
        # ring of the last W cycles, one byte each: bit 0 the command was clipped, bit 1 it
        # turned back from a swing that reached the limit
        self._ring = bytearray(self._w)
        self._i = 0
        self._full = False         # the ring has wrapped: it holds W cycles
        self._n_sat = 0
        self._n_hit = 0
        self._need_sat = settings.saturation * self._w
        self._need_hit = settings.limit_reversals * self._w
        self._touched = 0          # the command's swing under way reached the limit
        h = settings.hysteresis * torque_limit
        self._applied = _Swings(h)     # the command sent (clipped)
        self._unclipped = _Swings(h)   # the command before the clip: how far the loop wants to go
        self._last = 0.0           # the unclipped command's last swing
        self._before = 0.0         # and the one before it (the same direction as this one)
        self._streak = 0           # swings in a row larger than the one before in their direction
        self._base = 0.0           # the smaller swing before the streak began
        self._peak_sat = self._peak_hit = self._peak_streak = 0
        self._peak_chatter = self._peak_growth = 0.0

    def cycle(self, u_unsat: float, u: float) -> str:
        """One cycle's command before and after the clip; the stop's detail when a rule
        trips, else ""."""
        limit = self.limit
        clipped = 1 if (u_unsat >= limit or u_unsat <= -limit) else 0
        if self._applied.add(u) >= 0.0:
            hit, self._touched = self._touched, clipped
        else:
            hit = 0
            if clipped:
                self._touched = 1
        i = self._i
        old = self._ring[i]
        self._ring[i] = clipped | hit << 1
        self._n_sat += clipped - (old & 1)
        self._n_hit += hit - (old >> 1)
        i += 1
        if i == self._w:
            i, self._full = 0, True
        self._i = i
        if clipped or hit:   # a count grew: the only time the chatter rule can newly trip
            if self._n_sat >= self._need_sat and self._n_hit >= self._need_hit:
                return self._chatter_detail()
            self._note_chatter()
        swing = self._unclipped.add(u_unsat)
        return self._swing(swing) if swing > 0.0 else ""

    def _note_chatter(self) -> None:
        """Keep the largest counts (ints: cheap in a clipped cycle) for :attr:`peaks`."""
        n_sat, n_hit = self._n_sat, self._n_hit
        if n_sat > self._peak_sat:
            self._peak_sat = n_sat
        if n_hit > self._peak_hit:
            self._peak_hit = n_hit
        if n_hit:
            chatter = min(n_sat / self._need_sat, n_hit / self._need_hit)
            if chatter > self._peak_chatter:
                self._peak_chatter = chatter

    @property
    def peaks(self) -> WatchPeaks:
        """The largest value each statistic reached so far (a copy)."""
        w = self._w
        return WatchPeaks(self._peak_sat / w, self._peak_hit / w, self._peak_chatter,
                          self._peak_streak, self._peak_growth)

    def _swing(self, swing: float) -> str:
        """A new swing of the unclipped command: does it extend a growing streak?"""
        before, self._before, self._last = self._before, self._last, swing
        if before <= 0.0 or not before < swing <= SMOOTH * before:
            self._streak = 0
            return ""
        if self._streak == 0:
            self._base = min(before, self._before)
        self._streak += 1
        growth = swing / self._base
        self._peak_streak = max(self._peak_streak, self._streak)
        self._peak_growth = max(self._peak_growth, growth)
        if self._streak >= self.s.growth_swings and growth >= self.s.growth:
            return self._growth_detail(swing, growth)
        return ""

    def _chatter_detail(self) -> str:
        self._note_chatter()
        n, s = (self._w if self._full else self._i), self.s   # cycles run (frames may be skipped)
        return (f"torque at its limit ({self.limit:g} N m) in {self._n_sat} of the last {n} cycles "
                f"({100.0 * self._n_sat / n:.0f} %), turned back from it {self._n_hit} times (thresholds: "
                f"instability.saturation = {s.saturation:g}, instability.limit_reversals = "
                f"{s.limit_reversals:g} per cycle)")

    def _growth_detail(self, swing: float, growth: float) -> str:
        s = self.s
        return (f"the command's oscillation grew {self._streak} swings in a row, x{growth:.3g} to a swing "
                f"of {swing:.4g} N m (limit {self.limit:g} N m; thresholds: instability.growth_swings = "
                f"{s.growth_swings}, instability.growth = {s.growth:g})")
