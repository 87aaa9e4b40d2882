"""The force-control loop: feedback in, DOb/RTOb controller, torque out, safety around it.

One cycle: read the newest feedback from the drive, check it (age, limits,
finiteness), compute the controller (:class:`~dobhil.runtime.controller.ForceController`),
check the command, send it. No printing, logging or file I/O in the cycle: per-cycle
values go into a bounded :class:`Trace` (for plots), timing into fixed-size histograms
(:class:`TimingStats`), and to an optional non-blocking ``sink`` (the recorder).

Timing (:class:`Timing`):

- **feedback** (the default for drives that stream feedback): each cycle is triggered by
  the drive's feedback frame and the command goes out at once, so the feedback-to-command
  latency is the computation time, never a fraction of a period that drifts between the
  drive's clock and the host's. The wait blocks on the bus until ``loop.spin`` s before
  the frame is expected (one period after the last), then spins on the bus around that
  instant, then blocks again. Frames that came while a cycle was late are skipped (the
  newest is used) and counted; no frame for ``loop.feedback_timeout`` after the last one
  stops the run (``host_too_slow`` instead of ``feedback_timeout`` when the ``starved``
  hook says the emulated drive itself was not scheduled meanwhile: the host, not the
  drive, is to blame).
- **host**: absolute deadlines ``t0 + k T`` on the host clock, for drives that need a
  host-timed request. The cycle reads the newest feedback without blocking, then sleeps
  to the next deadline -- ``time.sleep`` to ``loop.spin`` s before it, then a spin on the
  clock (sleep alone wakes up tens to hundreds of microseconds late). A cycle that ends
  after the next deadline is an overrun: counted, the missed deadlines skipped (as
  ros2_control does), never replayed in a burst.
- **lockstep**: the bus is a :class:`dobhil.drives.emulated.LockstepBus`; waiting for
  feedback advances the emulator by one period, so the loop is feedback-synchronous in
  simulated time, runs as fast as the machine allows and exactly as the sampled analysis
  models it (the emulator applies each command ``design.input_delay`` after the sample,
  or, for a protocol that fixes the delay itself, at its own latch: a SYNC, say).
  A drive whose feedback does not stream (``Drive.feedback_streams`` False: a drive
  that answers each command at once) runs the host algorithm on simulated time
  instead: cycle at ``t0 + k T`` on the newest feedback, then poll until the next
  deadline (:meth:`ForceLoop._run_lockstep_requests`).

Garbage collection (feedback and host): everything alive at start-up is collected once
and frozen (``gc.freeze``) before the drive is enabled, the collector is disabled during
the cycles, and the young generations are collected *between* cycles when the time to
the next deadline (or expected frame) allows, or when they grow past a hard bound. The
collector's state is restored after the run.

Blame: a drive that watches the host (its watchdog on the commands, a heartbeat
consumer, a command timeout: :attr:`Drive.host_watch <dobhil.drives.base.Drive.host_watch>`)
faults when the host's frames stop, whoever stopped them. The loop keeps its own measure of
that: the gaps between the commands it sent (a cycle start each, on the wall clock, so a
process that was not scheduled or was stopped counts them too; in lockstep on the simulated
clock). When the drive's fault is that watch expiring (:meth:`Drive.host_timeout
<dobhil.drives.base.Drive.host_timeout>`) and a gap long enough to starve it went on, or
ended within the time the drive takes to report it, the stop is ``host_too_slow`` with the
gap measured; otherwise ``drive_fault``, saying how long the longest gap was.

Safety: every way out of :meth:`ForceLoop.run` -- done, feedback timeout, position or
velocity limit, non-finite value, instability (:mod:`dobhil.runtime.instability`: the
command chattering at its limit, or its oscillation growing), drive fault, bus error, stop
request (SIGINT/SIGTERM), or any exception -- runs the drive's safe stop (zero torque, then the disable frames,
each attempted on its own, then a confirmation from the drive) and is recorded as a
:class:`~dobhil.runtime.stop.Stop`. Exceptions are re-raised after the safe stop
(``ForceLoop.ended`` still holds the stop and the safe stop's report). Any failure of the
bus, whatever the interface raises, is ``bus_error``. Waits longer than
:data:`~dobhil.drives.waits.WAIT_SLICE` -- the enable, the first feedback, a silent
drive, a long host period -- are cut into slices, so a stop request ends them within
one; a request made during the safe stop's confirmation wait ends that wait too
(unconfirmed: the loud warning), the one that stopped the run does not.
"""

from __future__ import annotations

import gc
import math
import threading
import time
import warnings
from array import array
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from enum import EnumMeta, IntEnum
from types import MappingProxyType
from typing import Any, Final, Protocol

import numpy as np
from numpy.typing import NDArray

from dobhil import __version__
from dobhil.drives.base import Drive, Feedback, HostTimeout, SafeStopReport
from dobhil.drives.waits import WAIT_SLICE, Cancel
from dobhil.errors import BusError, DriveError, DriveFaultError, RecorderError, WaitCancelled, exception_line
from dobhil.runtime.deadlines import next_deadline, sleep_until
from dobhil.runtime.controller import ControlOutput, ForceController
from dobhil.runtime.instability import InstabilityWatch, WatchSettings
from dobhil.runtime.stop import Stop, StopReason


def _next_minor(version: str) -> str:
    major, minor = version.split(".")[:2]
    return f"{major}.{int(minor) + 1}"


#: The release that drops the old names this one still accepts with a warning.
REMOVED_IN: Final = _next_minor(__version__)
#: Old name -> the name that replaced it (``Timing.REALTIME``, ``loop.timing: realtime``).
OLD_TIMING_NAMES: Final = MappingProxyType({"REALTIME": "HOST"})


def old_name_warning(old: str, new: str) -> str:
    """The text of the warning an old name gets."""
    return f"{old} is deprecated, use {new} (removed in dobhil {REMOVED_IN})"


class _TimingType(EnumMeta):
    """``Timing.REALTIME`` still works, with a DeprecationWarning (the warning for code: it
    shows in the caller's tests and ``__main__``), but is no member: a member of HOST's value
    would be an alias, and print as HOST."""

    def __getattr__(cls, name: str) -> Any:
        new = OLD_TIMING_NAMES.get(name)
        if new is None:
            raise AttributeError(name)
        warnings.warn(old_name_warning(f"Timing.{name}", f"Timing.{new}"), DeprecationWarning, stacklevel=2)
        return cls[new]


class Timing(IntEnum, metaclass=_TimingType):
    """How cycles are clocked."""

    LOCKSTEP = 0   # simulated time, one cycle per emulated feedback frame
    HOST = 1       # host-clock deadlines (``loop.timing: host``)
    FEEDBACK = 2   # each cycle triggered by the drive's feedback frame

    @property
    def label(self) -> str:
        return self.name.lower()


class Reference(Protocol):
    def value(self, t: float) -> float: ...


class CycleSink(Protocol):
    """Receives the run as it goes; must never block (the recorder's lossy mode). A sink
    whose output failed raises :class:`~dobhil.errors.RecorderError` from ``cycle``: the
    loop stops safely with reason ``recorder_failed``."""

    def started(self, fb: Feedback) -> None:
        """The drive is enabled and the controller initialised from ``fb``."""

    def cycle(self, k: int, t: float, fb: Feedback, out: ControlOutput, period_error: float,
              exec_time: float, overrun: bool) -> None: ...

    def stop(self, stop: Stop) -> None: ...

    def safe_stop(self, report: SafeStopReport) -> None:
        """After the safe stop: each frame's result and the drive's confirmation
        (one event each). Optional for sinks written before it existed."""


@dataclass(frozen=True)
class Limits:
    position_min: float
    position_max: float
    velocity_limit: float
    #: the key the velocity limit is from, for the stop line ("" : loop.velocity_limit)
    velocity_key: str = ""


#: default ``loop.spin``: seconds spun on the clock before a host-timing deadline
SPIN = 2.0e-4


@dataclass(frozen=True)
class LoopSettings:
    period: float
    duration: float
    feedback_timeout: float
    timing: Timing
    limits: Limits
    spin: float = SPIN
    #: the instability watch's thresholds (``instability.*``); None: no watch
    watch: WatchSettings | None = None

    @property
    def cycles(self) -> int:
        """Cycles (deadlines, or feedback frames) the run lasts."""
        return int(math.ceil(self.duration / self.period))


FIELDS = ("t", "q", "dq", "tau_ref", "tau_int_hat", "tau_dis_hat", "tau_per", "u_unsat", "u",
          "period_error", "exec_time", "overrun", "tau_int_true", "q_true", "latency", "sample_latency")

#: rows a Trace keeps at most (16 float64 fields: 17 MB); longer runs are decimated
TRACE_ROWS = 1 << 17


class Trace:
    """Per-cycle values for plots and summaries, bounded in memory.

    Row ``j`` holds cycle ``j * stride``. A run of up to ``max_rows`` cycles keeps every
    cycle (stride 1); when a longer run fills the rows, every other row is dropped and
    the stride doubles, so a run of any length holds at most ``max_rows`` rows spread
    over the whole run (the MCAP recording keeps every cycle). Deadlines skipped after
    an overrun are NaN rows. The newest cycle is always available (:meth:`latest`).
    """

    def __init__(self, cycles: int, max_rows: int = TRACE_ROWS) -> None:
        if max_rows < 2:
            raise ValueError(f"max_rows: expected >= 2, got {max_rows}")
        self.cycles = max(int(cycles), 1)
        self.capacity = min(self.cycles, max_rows + max_rows % 2)
        self.stride = 1
        self.n = 0
        self.last = -1   # row of the newest cycle (``capacity``: the scratch row)
        # one extra row: the newest cycle when the stride does not keep it
        self.data: dict[str, NDArray[np.float64]] = {
            name: np.full(self.capacity + 1, np.nan) for name in FIELDS}

    def __getitem__(self, name: str) -> NDArray[np.float64]:
        return self.data[name][:self.n]

    def row(self, k: int) -> int:
        """The row cycle ``k`` is written to (cycles come in increasing order)."""
        stride = self.stride
        if k % stride:
            return self.capacity
        r = k // stride
        if r >= self.capacity:
            self._decimate()
            return self.row(k)
        if r >= self.n:
            self.n = r + 1
        return r

    def latest(self, name: str) -> float:
        """The newest cycle's value of ``name`` (NaN before the first cycle)."""
        return float(self.data[name][self.last]) if self.last >= 0 else math.nan

    def _decimate(self) -> None:
        half = self.capacity // 2
        for values in self.data.values():
            values[:half] = values[0:self.capacity:2].copy()
            values[half:self.capacity] = np.nan
        self.stride *= 2
        self.n = (self.n + 1) // 2


class Histogram:
    """Counts of durations in 1 us bins up to 100 ms (longer ones in the last bin) and
    the exact maximum: percentiles of a run of any length in fixed memory, and one
    array increment per sample in the cycle."""

    BIN = 1e-6
    BINS = 100_000

    def __init__(self) -> None:
        self.counts = array("q", bytes(8 * self.BINS))
        self.n = 0
        self.max = 0.0

    def add(self, x: float) -> None:
        i = int(x * 1e6)
        if i >= self.BINS:
            i = self.BINS - 1
        elif i < 0:
            i = 0
        self.counts[i] += 1
        self.n += 1
        if x > self.max:
            self.max = x

    def percentile(self, p: float) -> float:
        """The ``p``-th percentile (bin centre, at most the maximum); 0 when empty."""
        if self.n == 0:
            return 0.0
        cumulative = np.cumsum(np.frombuffer(self.counts, dtype=np.int64))
        rank = max(1, math.ceil(p / 100.0 * self.n))
        index = int(np.searchsorted(cumulative, rank))
        if index >= self.BINS - 1:   # the overflow bin: only the maximum is known
            return self.max
        return min((index + 0.5) * self.BIN, self.max)


@dataclass(frozen=True)
class TimingStats:
    """Timing of the cycles run. ``period_error``: lateness of the cycle start against
    its deadline (host), or the deviation of the feedback frame interval from the period
    (feedback); ``latency``: feedback frame received (the bus's stamp) -> command sent,
    per cycle also in the trace (0 in lockstep: simulated); ``sample_latency``: the
    instant the drive sampled the feedback (``Feedback.sampled_at``, e.g. a SYNC as
    the bus stamped it) -> the feedback received (the bus's stamp), None when no cycle
    had both stamps (a drive that reports no sample instant; lockstep, where it is not
    measured)."""

    period_error_p50: float
    period_error_p99: float
    period_error_max: float
    exec_time_p50: float
    exec_time_p99: float
    exec_time_max: float
    latency_p50: float = 0.0
    latency_p99: float = 0.0
    latency_max: float = 0.0
    sample_latency_p50: float | None = None
    sample_latency_p99: float | None = None
    sample_latency_max: float | None = None

    @classmethod
    def of(cls, period_error: Histogram, exec_time: Histogram, latency: Histogram,
           sample_latency: Histogram | None = None) -> TimingStats:
        sampled = sample_latency if sample_latency is not None and sample_latency.n else None
        return cls(period_error.percentile(50), period_error.percentile(99), period_error.max,
                   exec_time.percentile(50), exec_time.percentile(99), exec_time.max,
                   latency.percentile(50), latency.percentile(99), latency.max,
                   *((sampled.percentile(50), sampled.percentile(99), sampled.max) if sampled is not None
                     else (None, None, None)))


@dataclass(frozen=True)
class RunResult:
    cycles: int             # cycles run
    overruns: int           # cycles that ended late (host) / found a frame missed (feedback)
    stop: Stop
    timing: TimingStats
    trace: Trace
    disabled: bool          # the safe stop went out and the drive confirmed it
    skipped: int = 0        # deadlines (host) or feedback frames (feedback) skipped
    safe_stop: SafeStopReport | None = None


class StopRequest:
    """A thread-safe flag the loop polls every cycle (set by signal handlers), and the
    ``cancel`` of every wait before, during and after the cycles (within WAIT_SLICE s)."""

    def __init__(self) -> None:
        self._event = threading.Event()
        self.why = ""
        self.count = 0   # requests so far: a wait started after one sees only newer ones

    def set(self, why: str) -> None:
        self.why = why
        self.count += 1
        self._event.set()

    def is_set(self) -> bool:
        return self._event.is_set()

    def reason(self) -> str:
        """Why a stop was requested; "" while none was (a wait's ``cancel``)."""
        return (self.why or "stop requested") if self._event.is_set() else ""

    def newer(self) -> Cancel:
        """A ``cancel`` that answers only requests made after this call: the safe stop
        that a SIGINT started still waits for its confirmation, a second one ends it."""
        seen = self.count

        def cancel() -> str:
            return self.reason() if self.count != seen else ""
        return cancel


class _Halt(Exception):
    """Internal: leave the cycle loop with a stop record."""

    def __init__(self, reason: StopReason, detail: str) -> None:
        super().__init__(detail)
        self.reason = reason
        self.detail = detail


class _RateWatch:
    """Feedback that comes slower than ``loop.period`` (a drive still at its factory
    rate, e.g. 10 ms) would run the controller on held samples or at the wrong
    sample time without any error: ``OF`` of the last ``RUN`` frame intervals longer than
    ``SLOW`` periods each stop the run. Intervals are taken from the frames' bus stamps
    (real time) or the drive clock (lockstep), per frame received (a burst after a late
    cycle is not slow).

    Why not ``RUN`` in a row: a sender that was not scheduled for a while sends what it
    missed in a burst (the emulated drive does, ``dobhil/drives/ticks.py``), and a burst
    breaks a row of slow intervals with short ones: on a loaded host a drive streaming 4
    times slower than the loop can run a 0.4 s run to its end with no ten in a row (stalls
    that do so: tests/runtime/test_rate_watch.py). A stream at the loop period
    cannot have 7 slow intervals of 10: each one long is paid back by short ones, and 7
    above 1.5 periods add up to more than the 10 periods the ten span, unless the sender
    fell more than half a period further behind within them -- that is, it was slower."""

    SLOW = 1.5
    RUN = 10    # the newest frame intervals judged together
    OF = 7      # ... of which this many slow stop the run

    def __init__(self, period: float, frames: str = "feedback frames",
                 advice: str = "make the drive's feedback period (the profile's feedback_period) "
                               "the loop period") -> None:
        self.period = period
        self.last = math.nan
        self.recent: deque[bool] = deque(maxlen=self.RUN)   # slow or not, oldest first
        self.slow = 0                                       # how many of them are slow
        self.frames = frames    # the protocol's name of its feedback (its probe's motion_name)
        self.advice = advice    # and what to change, in its words

    def frame(self, stamp: float, frames: int) -> None:
        last, self.last = self.last, stamp
        slow = stamp - last > self.SLOW * self.period * frames   # NaN (the first): not slow
        if len(self.recent) == self.RUN:
            self.slow -= self.recent[0]
        self.recent.append(slow)
        self.slow += slow
        if slow and self.slow >= self.OF:
            every = (stamp - last) / max(frames, 1)
            raise _Halt(StopReason.FEEDBACK_TIMEOUT,
                        f"{self.frames} come every {every * 1e3:.3g} ms ({self.slow} of the last "
                        f"{len(self.recent)} intervals), expected every loop.period = {self.period * 1e3:g} ms: "
                        f"{self.advice}")


def _rate_watch(drive: Drive, period: float) -> _RateWatch:
    """The rate watch with the drive protocol's words for its feedback and its rate setting
    (its preflight probe has them; a drive without one gets the generic words)."""
    probe_of = getattr(type(drive), "preflight_probe", None)
    profile = getattr(drive, "profile", None)
    probe = probe_of(profile) if probe_of is not None and profile is not None else None
    if probe is None:
        return _RateWatch(period)
    return _RateWatch(period, probe.motion_name(), probe.rate_advice(period))


class _CommandGaps:
    """The host's lateness as a drive's watch on it sees it: the gaps between consecutive
    torque commands, each taken at its cycle's start (real time: ``time.perf_counter``, the
    command goes out microseconds later, and a process stopped or not scheduled counts in
    it; lockstep: the simulated clock). Per cycle only a subtraction and two comparisons:
    the longest gap of the run, and the newest gaps of at least ``floor`` s (long enough to
    starve the drive's watch; rare, a few kept)."""

    #: gaps >= floor kept (each one starved the watch or nearly: a run has few)
    KEPT = 8

    def __init__(self) -> None:
        self.floor = math.inf
        self.last = math.nan     # the newest command (or the enable)
        self.longest = 0.0
        self.late: deque[tuple[float, float]] = deque(maxlen=self.KEPT)   # (gap, when it ended)

    def start(self, t: float, floor: float) -> None:
        """Measure from ``t`` (the enable: its keepalives fed the watch up to it)."""
        self.last, self.floor = t, floor

    def sent(self, t: float) -> None:
        gap = t - self.last
        self.last = t
        if gap > self.longest:
            self.longest = gap
        if gap >= self.floor:
            self.late.append((gap, t))

    def starving(self, now: float, window: float) -> float:
        """The gap that starved the watch: the longest of the one going on at ``now`` (a
        drive that sends its status on its own can say so before the next command goes
        out) and those that ended within ``window`` s before ``now`` (a drive that only
        answers commands says so in its reply to the first command after the gap), each
        counted only when long enough; 0.0 when none was. The longest, not the newest: a
        host starved once can be late again, by less, before the reply that names the
        first gap is read."""
        ongoing = now - self.last
        gap = ongoing if ongoing >= self.floor else 0.0
        for late, end in self.late:
            if now - end <= window and late > gap:
                gap = late
        return gap


class _QuietGc:
    """Keeps the garbage collector out of the cycles (see the module docstring)."""

    #: collect between cycles only with at least this fraction of a period left
    SLACK = 0.3
    #: collect anyway once the young generation is this many thresholds large
    HARD = 20

    def __init__(self) -> None:
        self._was_enabled = False
        self._active = False
        self._threshold = gc.get_threshold()[0] or 700
        self.collections = 0

    def start(self) -> None:
        self._was_enabled = gc.isenabled()
        gc.collect()
        gc.freeze()
        gc.disable()
        self._active = True

    def between_cycles(self, slack: float, period: float) -> None:
        """Collect the young generations if due and ``slack`` s are left before the
        next deadline (or if they grew past the hard bound)."""
        count = gc.get_count()[0]
        if count < self._threshold:
            return
        if slack > self.SLACK * period or count >= self.HARD * self._threshold:
            gc.collect(1)
            self.collections += 1

    def stop(self) -> None:
        if not self._active:
            return
        self._active = False
        gc.unfreeze()
        if self._was_enabled:
            gc.enable()


class ForceLoop:
    """Runs the controller against a drive until the duration ends or something stops it."""

    def __init__(self, *, drive: Drive, controller: ForceController, reference: Reference,
                 settings: LoopSettings, clock: Callable[[], float] = time.perf_counter,
                 truth: Callable[[], tuple[float, float]] | None = None,
                 sink: CycleSink | None = None, stop_request: StopRequest | None = None,
                 trace_rows: int = TRACE_ROWS,
                 starved: Callable[[float], str] | None = None) -> None:
        self.drive = drive
        self.controller = controller
        self.reference = reference
        self.settings = settings
        self.clock = clock
        self.truth = truth
        # an emulated drive in a process of its own says whether it was starved during a
        # silent window of this many seconds ("" if not): a timeout is then the host's fault
        self.starved = starved
        self.sink = sink
        self.stop_request = stop_request or StopRequest()
        self.cycles = 0      # cycles run
        self.overruns = 0
        self.skipped = 0     # deadlines / feedback frames skipped
        self._at = 0         # index of the next cycle (for the stop record)
        self._t0 = 0.0
        self._last_out: ControlOutput | None = None
        self._rate = _rate_watch(drive, settings.period)
        self._last = (0.0, 0.0, 0.0)   # t, period error, exec time of the newest cycle
        #: how the run ended and the safe stop's report, also when run() raised
        self.ended: tuple[Stop, SafeStopReport] | None = None
        self._gc = _QuietGc()
        self._gaps = _CommandGaps()
        self.period_error = Histogram()
        self.exec_time = Histogram()
        self.latency = Histogram()
        self.sample_latency = Histogram()
        self.trace = Trace(settings.cycles, trace_rows)
        #: the instability watch (None when off); its ``peaks`` say how close a run came
        self.watch = (InstabilityWatch(settings.watch, controller.torque_limit)
                      if settings.watch is not None else None)

    # -- public --------------------------------------------------------------

    def run(self) -> RunResult:
        """Enable, run the cycles, always stop safely; exceptions reach the caller after."""
        stop: Stop | None = None
        try:
            stop = self._enable_and_run()
        except BaseException as exc:
            self._gc.stop()
            stop = Stop(StopReason.EXCEPTION, exception_line(exc), self._at,
                        self._now())
            self.ended = (stop, self._safe_stop(stop))
            raise
        self._gc.stop()
        report = self._safe_stop(stop)
        self.ended = (stop, report)
        timing = TimingStats.of(self.period_error, self.exec_time, self.latency, self.sample_latency)
        return RunResult(cycles=self.cycles, overruns=self.overruns, stop=stop, timing=timing,
                         trace=self.trace, disabled=report.safe, skipped=self.skipped,
                         safe_stop=report)

    # -- internals -------------------------------------------------------------

    def _now(self) -> float:
        return self.clock() - self._t0

    def _enable_and_run(self) -> Stop:
        self._t0 = self.clock()  # stop times before the first cycle: from the enable
        if self.stop_request.is_set():   # a signal during start-up: never enable
            return Stop(StopReason.SIGNAL, self.stop_request.why or "stop requested", -1, 0.0)
        if self.settings.timing is not Timing.LOCKSTEP:
            self._gc.start()
        try:
            self.drive.enable(cancel=self.stop_request.reason)
        except WaitCancelled as exc:   # before DriveError, its base
            return Stop(StopReason.SIGNAL, str(exc), -1, self._now())
        except BusError as exc:
            return Stop(StopReason.BUS_ERROR, str(exc), -1, 0.0)
        except DriveError as exc:
            return Stop(StopReason.ENABLE_FAILED, str(exc), -1, 0.0)
        self._watch_gaps()
        try:
            first = self._first_feedback()
            self.controller.initialize(first.position, first.velocity)
            if self.sink is not None:
                self.sink.started(first)
            self._t0 = self.clock()
            if self.settings.timing is Timing.HOST:
                self._run_host()
            elif self.settings.timing is Timing.LOCKSTEP and not self.drive.feedback_streams:
                # lockstep on a drive that only answers requests (one reply per command)
                self._run_lockstep_requests(first)
            else:
                self._run_feedback(first, self.settings.timing is Timing.FEEDBACK)
        except _Halt as halt:
            return Stop(halt.reason, halt.detail, self._at, self._now())
        except DriveFaultError as exc:
            reason, detail = self._blame(str(exc))
            return Stop(reason, detail, self._at, self._now())
        except BusError as exc:
            return Stop(StopReason.BUS_ERROR, str(exc), self._at, self._now())
        return Stop(StopReason.DONE, f"ran {self.settings.duration:g} s", self._at, self._now())

    def _watch_gaps(self) -> None:
        """Start measuring the gaps between commands against the drive's watch on the
        host: on the wall clock in real time, on the simulated clock in lockstep (where
        only a host that stopped stepping, as a test does, is ever late). A gap one
        period short of starving the watch still counts: a drive checks it on its own
        tick, and a frame's way to it varies by up to a period."""
        watch: HostTimeout | None = getattr(self.drive, "host_watch", None)
        floor = math.inf
        if watch is not None:
            floor = max(watch.starving_gap - self.settings.period, self.settings.period)
        self._gaps.start(self._gap_clock(), floor)

    def _gap_clock(self) -> float:
        return self.clock() if self.settings.timing is Timing.LOCKSTEP else time.perf_counter()

    def _blame(self, detail: str) -> tuple[StopReason, str]:
        """A drive fault: ``host_too_slow`` when it is the drive's watch on the host
        expiring after a gap between this loop's commands long enough to starve it (the
        host was late, not the drive), else ``drive_fault``."""
        timeout = getattr(self.drive, "host_timeout", None)
        watch: HostTimeout | None = timeout() if timeout is not None else None
        if watch is None:
            return StopReason.DRIVE_FAULT, detail
        period = self.settings.period
        allows = f"the drive's {watch.what} allows {watch.timeout * 1e3:g} ms" + (
            f", fed every {watch.fed_every * 1e3:g} ms" if watch.fed_every else "")
        gap = self._gaps.starving(self._gap_clock(), watch.timeout + watch.reported_within + 2 * period)
        if gap > 0:
            return StopReason.HOST_TOO_SLOW, (f"{detail}: no command from the host for {gap * 1e3:.0f} ms "
                                              f"({allows}): the host was late, not the drive")
        return StopReason.DRIVE_FAULT, (f"{detail} (the host was on time: no gap between its commands before "
                                        f"the fault starved it, {allows}; the longest gap between commands "
                                        f"of the run was {self._gaps.longest * 1e3:.3g} ms)")

    def _first_feedback(self) -> Feedback:
        fb = self._poll_or_stop(self.clock() + self.settings.feedback_timeout)
        if fb is None:
            fb = self.drive.feedback
        if fb is None:
            raise self._silent(f"no feedback within {self.settings.feedback_timeout:g} s of enabling",
                               self.settings.feedback_timeout)
        return fb

    def _silent(self, detail: str, window: float) -> _Halt:
        """The stop for no fresh feedback during the last ``window`` s: the drive went
        silent, or the host starved the emulated drive (``host_too_slow``)."""
        why = self.starved(window) if self.starved is not None else ""
        if why:
            return _Halt(StopReason.HOST_TOO_SLOW, f"{detail}: {why}")
        return _Halt(StopReason.FEEDBACK_TIMEOUT, detail)

    def _run_feedback(self, first: Feedback, timed: bool) -> None:
        """One cycle per feedback frame, the command sent as soon as it is computed.

        Frames that came while a cycle ran are skipped (the newest is used) and their
        cycle indices with them, so cycle ``k`` is always the drive's ``k``-th frame.
        ``timed``: real time (feedback timing); otherwise lockstep, where waiting
        advances the emulator and the cycle time is exactly ``k T``."""
        s = self.settings
        period, timeout, n = s.period, s.feedback_timeout, s.cycles
        clock, poll = self.clock, self.drive.poll
        last_seq, last_wake = first.seq, math.nan
        k = 0
        while k < n:
            fb = self._wait_frame(last_wake + period, last_wake + timeout) if timed and \
                last_wake == last_wake else poll(timeout)
            if fb is None and timed and (back := self.drive.since_back(timeout)) < timeout:
                # the host read nothing for the whole timeout (its process stopped): what the
                # drive sent meanwhile may still be on its way; the timeout from its return
                fb = self._poll_or_stop(clock() + timeout - back)
            wake = clock()
            start = time.perf_counter()
            if fb is None:
                self._check_stop_request()
                raise self._silent(f"no fresh feedback for {timeout:g} s"
                                   + ("" if timed else " (simulated)"), timeout)
            frames = fb.seq - last_seq   # 1 unless frames came while the last cycle ran
            last_seq = fb.seq
            self._rate.frame(fb.rx_time if timed else fb.timestamp, frames)
            late = frames > 1
            if late:
                self.overruns += timed   # lockstep: a lost frame, never a late host
                self.skipped += min(frames - 1, n - k)
                k += frames - 1
                if k >= n:
                    break
            if timed:
                error = (wake - last_wake) - frames * period if last_wake == last_wake else 0.0
                last_wake = wake
                self._cycle(k, wake - self._t0, fb, error, start, True)
            else:
                self._cycle(k, k * period, fb, 0.0, start, False)
            if late:
                self.trace.data["overrun"][self.trace.last] = 1.0
            if self.sink is not None:   # (no call for a run nobody records)
                self._emit(k, fb, late)
            k += 1
            if timed:
                self._gc.between_cycles(last_wake + period - clock(), period)

    def _run_lockstep_requests(self, first: Feedback) -> None:
        """Lockstep for a drive whose feedback does not stream (it answers each command
        with one reply): the host algorithm on simulated time.

        Waiting for a fresh frame, as :meth:`_run_feedback` does, cannot work here: the
        emulated motor answers a command at the very instant it applies it (lockstep
        latency 0), so the reply is there at once and simulated time would never move.
        Instead each cycle runs at the deadline ``t0 + k T``: it takes the newest feedback
        (the reply to the last command: the state at ``t_{k-1}``, so the torque of cycle
        k acts from ``t_k`` on a sample one period old -- the profile's
        ``command_delay_periods: 1``), computes, sends, then polls the drive until the
        clock reaches the next deadline (the LockstepBus advances the emulator while the
        host waits on it). Fresh means a new ``Feedback.seq``, not what poll returned: the
        reply is read during the previous wait. No fresh feedback for
        ``loop.feedback_timeout`` (simulated) stops the run as in host timing."""
        s = self.settings
        period, timeout, n = s.period, s.feedback_timeout, s.cycles
        clock, drive = self.clock, self.drive
        t0 = self._t0
        # the clock advances in steps dt = T (summed): a deadline counts as reached within
        # a tiny fraction of a period, never a whole step later
        tolerance = 1e-6 * period
        last_seq, last_fresh = first.seq - 1, t0   # the first feedback counts as fresh
        k = 0
        while k < n:
            deadline = t0 + k * period
            while clock() < deadline - tolerance:
                # returns early with the reply (read as soon as the command was applied),
                # then waits out the period; a wait reads what came at its very end too,
                # and poll drains what is queued behind a frame: nothing is left unread
                drive.poll(deadline - clock())
            start = time.perf_counter()
            fb = drive.feedback or first
            now = clock()
            if fb.seq != last_seq:   # (no rate watch: replies come as often as commands go)
                last_seq, last_fresh = fb.seq, now
            elif now - last_fresh > timeout + tolerance:
                self._check_stop_request()
                raise self._silent(f"no fresh feedback for {now - last_fresh:.4g} s (simulated)", timeout)
            self._cycle(k, k * period, fb, 0.0, start, False)
            self._emit(k, fb, False)
            k += 1
        # the last command acts for its whole period before the stop, as in host timing
        # (:meth:`_run_host` sleeps to the deadline after it): the run lasts n T of
        # simulated time, not one period less
        end = t0 + n * period
        while clock() < end - tolerance:
            drive.poll(end - clock())

    def _wait_frame(self, expected: float, deadline: float) -> Feedback | None:
        """Feedback timing: the next frame, expected at ``expected`` and given up at
        ``deadline`` (loop clock). Blocks on the bus to ``loop.spin`` s before the
        expected time (a frame that comes early ends the wait at once), then spins on the
        bus until ``loop.spin`` s after it (a blocked thread wakes up tens of
        microseconds or more late), then blocks again until the deadline."""
        poll, clock, spin = self.drive.poll, self.clock, self.settings.spin
        if spin > 0:
            early = expected - spin - clock()
            if early > 0:
                fb = poll(early)
                if fb is not None:
                    return fb
            end = min(expected + spin, deadline)
            while clock() < end:
                fb = poll(0.0)
                if fb is not None:
                    return fb
        return self._poll_or_stop(deadline)

    def _poll_or_stop(self, deadline: float) -> Feedback | None:
        """Feedback by ``deadline`` (loop clock), or None; waits longer than WAIT_SLICE
        are cut into slices so a stop request (SIGINT) ends them within one."""
        poll, clock = self.drive.poll, self.clock
        while True:
            remaining = deadline - clock()
            if remaining <= WAIT_SLICE:
                return poll(max(remaining, 0.0))
            fb = poll(WAIT_SLICE)
            if fb is not None or self.stop_request.is_set():
                return fb

    def _check_stop_request(self) -> None:
        if self.stop_request.is_set():
            raise _Halt(StopReason.SIGNAL, self.stop_request.why or "stop requested")

    def _run_host(self) -> None:
        s = self.settings
        period, timeout = s.period, s.feedback_timeout
        t0 = self._t0
        k = 0
        last_fresh = t0
        last_seq = self.drive.feedback.seq if self.drive.feedback is not None else 0
        n = s.cycles
        # a drive that only answers (one reply per command) replies as often as this loop commands:
        # slow replies then measure the host, whose lateness the overruns count already;
        # the rate watch would blame the drive for it (the silence check still runs)
        watch_rate = self.drive.feedback_streams
        while k < n:
            wake = self.clock()
            start = time.perf_counter()
            fb = self.drive.poll(0.0)
            if fb is not None:
                last_fresh = wake
                if watch_rate:
                    self._rate.frame(fb.rx_time, fb.seq - last_seq)
                last_seq = fb.seq
            elif min(wake - last_fresh, self.drive.since_back(timeout)) > timeout:
                # (counted from the host's return when it read nothing for the whole
                # timeout, its process stopped: what the drive sent meanwhile may still
                # be on its way)
                raise self._silent(f"no fresh feedback for {wake - last_fresh:.4f} s (limit {timeout:g} s)",
                                   wake - last_fresh)
            fb = fb or self.drive.feedback
            if fb is None:
                raise _Halt(StopReason.FEEDBACK_TIMEOUT, "no feedback")
            self._cycle(k, wake - t0, fb, wake - (t0 + k * period), start, True)
            k = self._next_deadline(k, fb, t0, period)

    def _next_deadline(self, k: int, fb: Feedback, t0: float, period: float) -> int:
        """Count an overrun and skip the missed deadlines; sleep (then spin) to the next."""
        nxt = next_deadline(k, self.clock(), t0, period)
        overrun = nxt > k + 1
        if overrun:
            self.overruns += 1
            self.trace.data["overrun"][self.trace.last] = 1.0
            self.skipped += min(nxt, self.settings.cycles) - k - 1
        self._emit(k, fb, overrun)
        deadline = t0 + nxt * period
        self._gc.between_cycles(deadline - self.clock(), period)
        self._sleep_until(deadline)
        return nxt

    def _sleep_until(self, deadline: float) -> None:
        """``time.sleep`` to ``loop.spin`` s before ``deadline``, then spin on the clock."""
        sleep_until(deadline, spin=self.settings.spin, clock=self.clock, stop=self.stop_request)

    def _cycle(self, k: int, t: float, fb: Feedback, period_error: float, start: float,
               timed: bool) -> None:
        self._send(k, t, fb, self._compute(t, fb), period_error, start, timed)

    def _compute(self, t: float, fb: Feedback) -> ControlOutput:
        """The command of the cycle at ``t`` on ``fb``, checked (feedback, finiteness, the
        instability watch); nothing is sent. Raises _Halt when the run must stop."""
        if self.stop_request.is_set():   # inline: the cycle's cost
            raise _Halt(StopReason.SIGNAL, self.stop_request.why or "stop requested")
        q, dq = fb.position, fb.velocity
        self._check_feedback(q, dq)
        out = self.controller.step(q, dq if self.controller.measures_velocity else None,
                                   self.reference.value(t))
        if not math.isfinite(out.u) or not math.isfinite(out.tau_ref):
            raise _Halt(StopReason.NON_FINITE, f"non-finite command u = {out.u!r} "
                        f"(tau_ref = {out.tau_ref!r}, tau_int^ = {out.tau_int_hat!r})")
        watch = self.watch
        if watch is not None:   # before the send: a tripping command never goes out
            why = watch.cycle(out.u_unsat, out.u)
            if why:
                raise _Halt(StopReason.UNSTABLE, why)
        return out

    def _send(self, k: int, t: float, fb: Feedback, out: ControlOutput, period_error: float,
              start: float, timed: bool) -> None:
        """Send the command ``out`` of cycle ``k`` and account for the cycle (timing
        histograms, the trace row); ``start``: the cycle's start (``time.perf_counter``)."""
        q, dq = fb.position, fb.velocity
        self.drive.send_torque(out.u)
        exec_time = time.perf_counter() - start
        latency = sample_latency = math.nan
        if timed:
            self._gaps.sent(start)
            self.period_error.add(abs(period_error))
            if fb.rx_time == fb.rx_time:   # not NaN: the bus stamped the frame
                latency = time.time() - fb.rx_time
                self.latency.add(latency)
                # the drive's sample instant (its SYNC) -> its feedback received, both bus
                # stamps; lockstep (not timed) leaves it NaN: there the SYNC's stamp is
                # simulated and the frames' are the wall clock, and the emulated drive
                # answers at the SYNC's very instant (0 by construction, not a measurement)
                sample_latency = fb.sample_latency
                if sample_latency == sample_latency:
                    self.sample_latency.add(sample_latency)
        else:
            self._gaps.sent(self.clock())   # lockstep: simulated time
        self.exec_time.add(exec_time)
        self._store(k, t, q, dq, out, period_error, exec_time, latency, sample_latency)
        self.cycles += 1
        self._at = k + 1

    def _check_feedback(self, q: float, dq: float) -> None:
        lim = self.settings.limits
        if not (math.isfinite(q) and math.isfinite(dq)):
            raise _Halt(StopReason.NON_FINITE, f"non-finite feedback q = {q!r}, dq = {dq!r}")
        if not lim.position_min <= q <= lim.position_max:
            raise _Halt(StopReason.POSITION_LIMIT, f"q = {q:.6g} rad outside "
                        f"[{lim.position_min:g}, {lim.position_max:g}]")
        if abs(dq) > lim.velocity_limit:
            raise _Halt(StopReason.VELOCITY_LIMIT,
                        f"|dq| = {abs(dq):.6g} rad/s above {lim.velocity_limit:g}"
                        + (f" ({lim.velocity_key})" if lim.velocity_key else ""))

    def _store(self, k: int, t: float, q: float, dq: float, out: ControlOutput,
               period_error: float, exec_time: float, latency: float, sample_latency: float) -> None:
        trace = self.trace
        r = trace.row(k)
        d = trace.data
        d["t"][r], d["q"][r], d["dq"][r] = t, q, dq
        d["tau_ref"][r], d["tau_int_hat"][r], d["tau_dis_hat"][r] = out.tau_ref, out.tau_int_hat, out.tau_dis_hat
        d["tau_per"][r], d["u_unsat"][r], d["u"][r] = out.tau_per, out.u_unsat, out.u
        d["period_error"][r], d["exec_time"][r], d["overrun"][r] = period_error, exec_time, 0.0
        d["latency"][r], d["sample_latency"][r] = latency, sample_latency
        if self.truth is not None:
            d["tau_int_true"][r], d["q_true"][r] = self.truth()
        trace.last = r
        self._last_out = out
        self._last = (t, period_error, exec_time)

    def _emit(self, k: int, fb: Feedback, overrun: bool) -> None:
        out = self._last_out  # set by the cycle just stored; None only before the first
        if self.sink is not None and out is not None:
            t, period_error, exec_time = self._last
            try:
                self.sink.cycle(k, t, fb, out, period_error, exec_time, overrun)
            except RecorderError as exc:
                raise _Halt(StopReason.RECORDER_FAILED, str(exc)) from exc

    def _safe_stop(self, stop: Stop, cancel: Cancel | None = None) -> SafeStopReport:
        """Zero torque, disable, confirm; never raises. The sink hears of each step.
        ``cancel`` ends the confirmation wait (default: a stop requested from now on; the
        several-axis loop gives every axis the one it made before the first axis' stop)."""
        try:
            if self.sink is not None:
                self.sink.stop(stop)
        except Exception:
            pass
        # a request made during the confirmation wait ends it (unconfirmed, said loudly);
        # the one that stopped the run does not
        # a drive that cannot confirm its disable by design says what it did confirm in a
        # note when the run lasted its duration; any other end keeps the loud line
        cancel = self.stop_request.newer() if cancel is None else cancel
        report = self.drive.safe_stop(cancel=cancel, planned=stop.reason is StopReason.DONE)
        hook = getattr(self.sink, "safe_stop", None)
        if hook is not None:
            try:
                hook(report)
            except Exception:
                pass
        return report
