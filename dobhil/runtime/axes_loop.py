"""Several axes in one loop: one period, one burst of commands, one receive pass.

Each axis keeps everything a single-axis run has -- its controller, reference, limits,
feedback timeout, stale-sample check, instability watch, trace and histograms -- in a
:class:`~dobhil.runtime.loop.ForceLoop` of its own, whose per-cycle code
(:meth:`ForceLoop._compute <dobhil.runtime.loop.ForceLoop._compute>`: check the feedback,
step the controller, check the command; ``_send``: send it and account for it) this loop
runs for every axis. So an axis computes exactly what it would alone.

One cycle:

1. every axis' newest feedback (a drive on a :class:`~dobhil.runtime.shared_bus.BusView`
   reads what the bus's receive pass queued for it; nobody waits for one axis' reply);
2. every axis' command computed and checked, then all of them sent back to back (the
   burst; a command that fails a check stops the run before any of this cycle's goes out
   after it);
3. the time to the next cycle.

Timing (:class:`~dobhil.runtime.loop.Timing`):

- **lockstep**: every :class:`~dobhil.drives.emulated.LockstepBus` (one per bus) advances
  one step ``dt`` = ``loop.period`` per cycle, then one receive pass per bus hands the
  frames to their axes. An axis whose drive streams feedback needs its fresh sample of
  the step; while one has not come, the cycle waits a step more (counted in ``skipped``)
  until it comes or that axis' ``loop.feedback_timeout`` (simulated) ends the run. A
  drive that only answers commands runs on the newest reply (as
  :meth:`ForceLoop._run_lockstep_requests <dobhil.runtime.loop.ForceLoop>` does).
  Per cycle each emulator sees the same frames at the same simulated instants as alone,
  so each axis' cycles are the ones of its single-axis run -- as long as its plant does
  not move while the other axes enable (a plant at rest, no velocity noise: the noise is
  drawn per step, and the other axes' enables take steps).
- **host**: absolute deadlines ``t0 + k T``, sleep then spin, an overrun counted and the
  missed deadlines skipped, as :class:`~dobhil.runtime.loop.ForceLoop` does; each cycle
  starts with one non-blocking receive pass per bus.
- **feedback**: each cycle waits for every axis' sample of the cycle -- a fresh frame of
  each drive -- and runs at once when the last one came, or at the period's deadline
  (one period after the cycle was expected) with what came: a drive whose frame is late
  is then run on its newest sample, and its silence beyond its feedback timeout stops the
  run. Frames that came while a cycle was late are skipped (the newest is used) and their
  cycle indices with them, as :class:`~dobhil.runtime.loop.ForceLoop` does; ``skipped``
  and ``overruns`` count them. Every drive must stream its feedback.

Safety. The axes are enabled in order; an enable that fails ends the run before any
cycle. However the run ends -- done, an axis' fault, feedback timeout, limit, non-finite
value, instability, a bus error, a signal, an exception -- every axis is stopped: first
every drive gets its zero torque and disable frames (no axis keeps its last torque while
another one's confirmation is awaited), then each axis' full safe stop (the frames again,
then the drive's confirmation) runs on its own, each attempted even if another raised.
The one :class:`~dobhil.runtime.stop.Stop` names the axis that stopped the run;
:meth:`AxesResult.warning` lists every axis not confirmed disabled.

Sinks: each axis' ``sink`` is called exactly as a single-axis loop calls its own
(``started``, ``cycle``, ``stop``, ``safe_stop``).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from types import MappingProxyType

from dobhil.drives.base import Confirmation, Drive, Feedback, SafeStopReport
from dobhil.drives.emulated import LockstepBus
from dobhil.drives.waits import WAIT_SLICE
from dobhil.errors import BusError, DriveError, DriveFaultError, WaitCancelled, exception_line
from dobhil.runtime.deadlines import next_deadline, sleep_until
from dobhil.runtime.controller import ControlOutput, ForceController
from dobhil.runtime.loop import (TRACE_ROWS, CycleSink, ForceLoop, Histogram, LoopSettings, Reference, RunResult,
                                 StopRequest, Timing, TimingStats, _Halt, _QuietGc)
from dobhil.runtime.shared_bus import SharedBus
from dobhil.runtime.stop import Stop, StopReason

__all__ = ["AxesLoop", "AxesResult", "AxisParts"]


@dataclass(frozen=True)
class AxisParts:
    """What one axis brings to the loop. ``settings``: the axis' own limits, feedback
    timeout and instability watch (period, duration, timing and spin are the loop's:
    the first axis' are used). ``clock``: the axis' drive's clock (a lockstep bus's
    simulated seconds; None: the loop's)."""

    name: str
    drive: Drive
    controller: ForceController
    reference: Reference
    settings: LoopSettings
    sink: CycleSink | None = None
    truth: Callable[[], tuple[float, float]] | None = None
    starved: Callable[[float], str] | None = None
    clock: Callable[[], float] | None = None
    #: the shared bus the drive is on (feedback timing waits on it; None: the loop's first)
    bus: SharedBus | None = None


@dataclass(frozen=True)
class AxesResult:
    """How a run of several axes went: each axis' part (its trace, timing, safe stop;
    ``stop`` is the run's one stop) and the shared cycle timing (``period_error``: the
    cycle's lateness; ``exec_time``: the cycle's start to its burst's last send)."""

    axes: Mapping[str, RunResult]
    stop: Stop
    axis: str               # the axis that stopped the run ("" when none did: done, a signal)
    cycles: int
    overruns: int
    skipped: int
    timing: TimingStats

    @property
    def disabled(self) -> bool:
        """Every axis' safe stop went out and its drive confirmed it."""
        return all(r.disabled for r in self.axes.values())

    @property
    def not_disabled(self) -> tuple[str, ...]:
        """The axes whose drive may still be enabled (their loud line is not empty)."""
        return tuple(name for name, r in self.axes.items()
                     if r.safe_stop is None or r.safe_stop.warning())

    def warning(self) -> str:
        """One loud line naming every axis not confirmed disabled; "" when all are."""
        parts = []
        for name in self.not_disabled:
            report = self.axes[name].safe_stop
            parts.append(f"axis {name}: " + (report.warning() if report is not None else "no safe stop report"))
        return "; ".join(parts)

    def notes(self) -> str:
        """What drives that cannot confirm their disable by design did confirm (planned end)."""
        return "; ".join(f"axis {name}: {r.safe_stop.note()}" for name, r in self.axes.items()
                         if r.safe_stop is not None and r.safe_stop.note())


@dataclass
class _Axis:
    name: str
    loop: ForceLoop
    streams: bool
    clock: Callable[[], float]
    timeout: float
    bus: SharedBus | None = None
    last_seq: int = 0
    last_fresh: float = 0.0
    enabled: bool = False
    fb: Feedback | None = None
    out: ControlOutput | None = None
    report: SafeStopReport | None = None


class AxesLoop:
    """Runs N axes in one loop until the duration ends or anything stops one of them
    (then all). ``buses``: the shared buses under the axes' drives (one receive pass each
    per cycle); ``lockstep``: their lockstep buses (each advanced one step per cycle)."""

    def __init__(self, axes: Sequence[AxisParts], *, buses: Sequence[SharedBus],
                 lockstep: Sequence[LockstepBus] = (), clock: Callable[[], float] = time.perf_counter,
                 stop_request: StopRequest | None = None, trace_rows: int = TRACE_ROWS) -> None:
        if not axes:
            raise ValueError("AxesLoop needs at least one axis")
        names = [a.name for a in axes]
        if len(set(names)) != len(names):
            raise ValueError(f"axis names must be distinct, got {names}")
        self.settings = axes[0].settings
        if (self.settings.timing is Timing.LOCKSTEP) != bool(lockstep):
            raise ValueError("lockstep timing needs the lockstep buses, and only lockstep timing takes them")
        self.stop_request = stop_request or StopRequest()
        self.clock = lockstep[0].clock if lockstep else clock
        self.buses = tuple(buses)
        self.lockstep = tuple(lockstep)
        self._axes = [self._axis(a, trace_rows) for a in axes]
        self.cycles = 0
        self.overruns = 0
        self.skipped = 0
        self._at = 0
        self._t0 = 0.0
        self._current = ""   # the axis whose part of the cycle runs (named by a stop)
        self._gc = _QuietGc()
        self.period_error = Histogram()
        self.exec_time = Histogram()
        #: how the run ended (stop, the axis that stopped it), also when run() raised
        self.ended: tuple[Stop, str] | None = None

    def _axis(self, a: AxisParts, trace_rows: int) -> _Axis:
        s = self.settings
        settings = LoopSettings(period=s.period, duration=s.duration, feedback_timeout=a.settings.feedback_timeout,
                                timing=s.timing, limits=a.settings.limits, spin=s.spin, watch=a.settings.watch)
        clock = a.clock or self.clock
        loop = ForceLoop(drive=a.drive, controller=a.controller, reference=a.reference,
                         settings=settings, clock=clock, truth=a.truth, sink=a.sink,
                         stop_request=self.stop_request, trace_rows=trace_rows, starved=a.starved)
        return _Axis(a.name, loop, loop.drive.feedback_streams, clock, settings.feedback_timeout, a.bus)

    @property
    def loops(self) -> Mapping[str, ForceLoop]:
        """Each axis' own loop (its trace, histograms, instability watch)."""
        return MappingProxyType({a.name: a.loop for a in self._axes})

    # -- public --------------------------------------------------------------

    def run(self) -> AxesResult:
        """Enable in order, run the cycles, always stop every axis safely; an exception
        reaches the caller after that."""
        try:
            stop, culprit = self._enable_and_run()
        except BaseException as exc:
            self._gc.stop()
            culprit = self._current
            stop = Stop(StopReason.EXCEPTION, _named(culprit, exception_line(exc)), self._at, self._now())
            self.ended = (stop, culprit)
            self._stop_all(stop)
            raise
        self._gc.stop()
        self.ended = (stop, culprit)
        self._stop_all(stop)
        return self._result(stop, culprit)

    # -- start ---------------------------------------------------------------

    def _now(self) -> float:
        return self.clock() - self._t0

    def _enable_and_run(self) -> tuple[Stop, str]:
        self._t0 = self.clock()
        if self.stop_request.is_set():   # a signal during start-up: never enable
            return Stop(StopReason.SIGNAL, self.stop_request.why or "stop requested", -1, 0.0), ""
        if self.settings.timing is not Timing.LOCKSTEP:
            self._gc.start()
        for axis in self._axes:
            failed = self._enable(axis)
            if failed is not None:
                return failed, axis.name
        try:
            self._start()
            if self.settings.timing is Timing.LOCKSTEP:
                self._run_lockstep()
            elif self.settings.timing is Timing.FEEDBACK:
                self._run_feedback()
            else:
                self._run_host()
        except _Halt as halt:
            # a signal is the run's, not the axis' whose cycle it interrupted
            culprit = "" if halt.reason is StopReason.SIGNAL else self._current
            return Stop(halt.reason, _named(culprit, halt.detail), self._at, self._now()), culprit
        except DriveFaultError as exc:
            faulted = self._by_name(self._current)
            reason, detail = (faulted.loop._blame(str(exc)) if faulted is not None
                              else (StopReason.DRIVE_FAULT, str(exc)))
            return Stop(reason, _named(self._current, detail), self._at, self._now()), self._current
        except BusError as exc:
            return Stop(StopReason.BUS_ERROR, _named(self._current, str(exc)), self._at, self._now()), self._current
        return Stop(StopReason.DONE, f"ran {self.settings.duration:g} s", self._at, self._now()), ""

    def _enable(self, axis: _Axis) -> Stop | None:
        """Enable one axis (the stop when it failed)."""
        self._current = axis.name
        try:
            axis.loop.drive.enable(cancel=self.stop_request.reason)
        except WaitCancelled as exc:   # before DriveError, its base
            return Stop(StopReason.SIGNAL, _named(axis.name, str(exc)), -1, self._now())
        except BusError as exc:
            return Stop(StopReason.BUS_ERROR, _named(axis.name, str(exc)), -1, self._now())
        except DriveError as exc:
            return Stop(StopReason.ENABLE_FAILED, _named(axis.name, str(exc)), -1, self._now())
        axis.enabled = True
        axis.loop._watch_gaps()
        return None

    def _start(self) -> None:
        """Every axis' first feedback, its controller initialised from it; then t0."""
        for axis in self._axes:
            self._current = axis.name
            first = axis.loop._first_feedback()
            axis.fb = first
            axis.loop.controller.initialize(first.position, first.velocity)
            if axis.loop.sink is not None:
                axis.loop.sink.started(first)
        self._current = ""
        self._t0 = self.clock()
        for axis in self._axes:
            fb = axis.fb
            assert fb is not None
            axis.loop._t0 = axis.clock()
            # a streaming drive's next frame is the first cycle's; a drive that only
            # answers runs its first cycle on the first feedback (counted as fresh)
            axis.last_seq = fb.seq if axis.streams else fb.seq - 1
            axis.last_fresh = axis.clock()

    def _by_name(self, name: str) -> _Axis | None:
        for axis in self._axes:
            if axis.name == name:
                return axis
        return None

    # -- lockstep --------------------------------------------------------------

    def _run_lockstep(self) -> None:
        n, period = self.settings.cycles, self.settings.period
        axes = self._axes
        tolerance = 1e-6 * period
        step_first = any(a.streams for a in axes)
        k = 0
        while k < n:
            if k > 0 or step_first:
                self._step()
            start = time.perf_counter()
            if self._waiting(tolerance):
                self.skipped += 1
                k += 1
                continue
            t = k * period
            self._burst(k, t, 0.0, start, False)
            for axis in axes:
                assert axis.fb is not None
                axis.loop._emit(k, axis.fb, False)
            self._current = ""
            for bus in self.buses:   # the commands to the emulators now, their answers read
                bus.receive_pass(0.0)
            k += 1
        if not step_first:
            # the last commands act for their whole period before the stop, as a streaming
            # axis' step before each cycle and host timing's sleep to the next deadline give
            # them: the run lasts n T of simulated time, not one period less
            self._step()

    def _step(self) -> None:
        """Every lockstep bus one step; then every axis reads what came for it."""
        self._current = ""
        for bus in self.lockstep:
            bus.step()
        for shared in self.buses:
            shared.receive_pass(0.0)
        for axis in self._axes:
            self._current = axis.name
            axis.loop.drive.poll(0.0)

    def _waiting(self, tolerance: float) -> bool:
        """Lockstep: take each axis' newest feedback; True while a streaming axis' sample
        of this step has not come (the cycle waits a step). Silence beyond an axis'
        feedback timeout stops the run."""
        waiting = False
        for axis in self._axes:
            self._current = axis.name
            fb = axis.loop.drive.feedback or axis.fb
            assert fb is not None
            now = axis.clock()
            if fb.seq != axis.last_seq:
                if axis.streams:   # the rate watch, as a single-axis lockstep run keeps it
                    axis.loop._rate.frame(fb.timestamp, fb.seq - axis.last_seq)
                axis.last_seq, axis.last_fresh, axis.fb = fb.seq, now, fb
            elif now - axis.last_fresh > axis.timeout + tolerance:
                axis.loop._check_stop_request()
                raise axis.loop._silent(f"no fresh feedback for {now - axis.last_fresh:.4g} s (simulated)",
                                        axis.timeout)
            elif axis.streams:
                waiting = True
        return waiting

    # -- feedback timing ---------------------------------------------------------

    def _run_feedback(self) -> None:
        s = self.settings
        period, n = s.period, s.cycles
        last_wake = math.nan
        k = 0
        while k < n:
            self._wait_samples(last_wake + period if last_wake == last_wake else math.nan)
            wake = self.clock()
            start = time.perf_counter()
            late = 0
            for axis in self._axes:
                late = max(late, self._fresh_feedback(axis, wake))
            if late:   # frames came while a cycle was late: their cycles are skipped
                self.overruns += 1
                self.skipped += min(late, n - k)
                k += late
                if k >= n:
                    break
            error = (wake - last_wake) - (late + 1) * period if last_wake == last_wake else 0.0
            last_wake = wake
            self._burst(k, wake - self._t0, error, start, True)
            for axis in self._axes:
                self._current = axis.name
                trace = axis.loop.trace
                if late:
                    trace.data["overrun"][trace.last] = 1.0
                assert axis.fb is not None
                axis.loop._emit(k, axis.fb, bool(late))
            self._current = ""
            k += 1
            self._gc.between_cycles(last_wake + period - self.clock(), period)

    def _wait_samples(self, expected: float) -> None:
        """Feedback timing: read until every axis has a fresh sample, or until the period's
        deadline (one period after ``expected``; NaN: the first cycle, bounded by the
        shortest feedback timeout). Blocks on the bus of an axis still waited for (slices
        of WAIT_SLICE: a stop request ends the wait; with several buses, slices of
        ``loop.spin``, so a frame on another bus waits no longer than that)."""
        clock, axes = self.clock, self._axes
        now = clock()
        deadline = (now + min(a.timeout for a in axes)) if expected != expected else expected + self.settings.period
        slice_ = WAIT_SLICE if len(self.buses) == 1 else max(self.settings.spin, 1e-5)
        while True:
            waiting = None
            for axis in axes:
                self._current = axis.name
                fb = axis.loop.drive.poll(0.0) or axis.loop.drive.feedback
                if fb is None or fb.seq == axis.last_seq:
                    waiting = waiting or axis
            self._current = ""
            remaining = deadline - clock()
            if waiting is None or remaining <= 0 or self.stop_request.is_set():
                return
            self._bus_of(waiting).receive_pass(min(remaining, slice_))

    def _bus_of(self, axis: _Axis) -> SharedBus:
        return axis.bus if axis.bus is not None else self.buses[0]

    def _fresh_feedback(self, axis: _Axis, wake: float) -> int:
        """Feedback timing: take the axis' newest sample; the frames it skipped (0: none).
        Its silence beyond its feedback timeout stops the run."""
        self._current = axis.name
        fb = axis.loop.drive.feedback
        if fb is not None and fb.seq != axis.last_seq:
            frames = fb.seq - axis.last_seq
            axis.loop._rate.frame(fb.rx_time, frames)
            axis.last_seq, axis.last_fresh, axis.fb = fb.seq, wake, fb
            return frames - 1
        if min(wake - axis.last_fresh, axis.loop.drive.since_back(axis.timeout)) > axis.timeout:
            # (from the host's return when it read nothing for the timeout: Drive.since_back)
            axis.loop._check_stop_request()
            raise axis.loop._silent(f"no fresh feedback for {wake - axis.last_fresh:.4f} s "
                                    f"(limit {axis.timeout:g} s)", wake - axis.last_fresh)
        return 0

    # -- host timing -------------------------------------------------------------

    def _run_host(self) -> None:
        s = self.settings
        period, n, t0 = s.period, s.cycles, self._t0
        k = 0
        while k < n:
            wake = self.clock()
            start = time.perf_counter()
            self._current = ""
            for shared in self.buses:   # one pass: everything that came, to its axis
                shared.receive_pass(0.0)
            for axis in self._axes:
                self._fresh_host(axis, wake)
            self._burst(k, wake - t0, wake - (t0 + k * period), start, True)
            k = self._next_deadline(k, t0, period)

    def _fresh_host(self, axis: _Axis, wake: float) -> None:
        """Host timing: the axis' newest feedback (without waiting); its silence beyond
        its feedback timeout stops the run."""
        self._current = axis.name
        fb = axis.loop.drive.poll(0.0)
        if fb is not None:
            axis.last_fresh = wake
            if axis.streams:   # (a drive that only answers replies as often as the host asks)
                axis.loop._rate.frame(fb.rx_time, fb.seq - axis.last_seq)
            axis.last_seq = fb.seq
            axis.fb = fb
        elif min(wake - axis.last_fresh, axis.loop.drive.since_back(axis.timeout)) > axis.timeout:
            # (from the host's return when it read nothing for the timeout: Drive.since_back)
            raise axis.loop._silent(f"no fresh feedback for {wake - axis.last_fresh:.4f} s "
                                    f"(limit {axis.timeout:g} s)", wake - axis.last_fresh)

    def _next_deadline(self, k: int, t0: float, period: float) -> int:
        """Count an overrun and skip the missed deadlines; sleep (then spin) to the next."""
        nxt = next_deadline(k, self.clock(), t0, period)
        overrun = nxt > k + 1
        if overrun:
            self.overruns += 1
            self.skipped += min(nxt, self.settings.cycles) - k - 1
        for axis in self._axes:
            self._current = axis.name
            trace = axis.loop.trace
            if overrun:
                trace.data["overrun"][trace.last] = 1.0
            assert axis.fb is not None
            axis.loop._emit(k, axis.fb, overrun)
        self._current = ""
        deadline = t0 + nxt * period
        self._gc.between_cycles(deadline - self.clock(), period)
        self._sleep_until(deadline)
        return nxt

    def _sleep_until(self, deadline: float) -> None:
        """``time.sleep`` to ``loop.spin`` s before ``deadline``, then spin on the clock."""
        sleep_until(deadline, spin=self.settings.spin, clock=self.clock, stop=self.stop_request)

    # -- the cycle ---------------------------------------------------------------

    def _burst(self, k: int, t: float, period_error: float, start: float, timed: bool) -> None:
        """Every axis' command computed and checked, then all sent back to back."""
        axes = self._axes
        for axis in axes:
            self._current = axis.name
            assert axis.fb is not None
            axis.out = axis.loop._compute(t, axis.fb)
        for shared in self.buses:
            shared.burst_begin()
        try:
            for axis in axes:
                self._current = axis.name
                assert axis.fb is not None and axis.out is not None
                axis.loop._send(k, t, axis.fb, axis.out, period_error, start, timed)
        finally:
            self._current = ""
            self._burst_end()
        end = time.perf_counter()
        self._current = ""
        self.exec_time.add(end - start)
        if timed:
            self.period_error.add(abs(period_error))
        self.cycles += 1
        self._at = k + 1

    def _burst_end(self) -> None:
        """The bus's own frames held during the burst (one SYNC) go out after it."""
        for shared in self.buses:
            try:
                shared.burst_end()
            except Exception as exc:   # any interface's failure is the bus's
                raise BusError(f"{shared.inner.channel_info}: frame after the commands not sent: "
                               f"{exception_line(exc)}") from exc

    # -- the end -----------------------------------------------------------------

    def _stop_all(self, stop: Stop) -> None:
        """Zero torque and disable to every drive first, then each axis' safe stop with
        its confirmation; each attempted whatever another one did."""
        pending: BaseException | None = None
        for axis in self._axes:
            try:
                axis.loop.drive.disable()   # never raises (its own contract); guarded anyway
            except BaseException as exc:
                pending = pending or exc
        # one cancel for every axis' confirmation wait: a stop requested once the safe stop
        # began (a second Ctrl-C) ends the wait of the axis it finds and of each after it
        cancel = self.stop_request.newer()
        for axis in self._axes:
            try:
                axis.report = axis.loop._safe_stop(stop, cancel)
            except BaseException as exc:   # every axis gets its turn
                pending = pending or exc
                axis.report = SafeStopReport(axis.loop.drive.node_id, (), Confirmation.NOT_SENT,
                                             f"safe stop raised: {exception_line(exc)}")
            axis.loop.ended = (stop, axis.report)
        if pending is not None and not isinstance(pending, Exception):
            raise pending   # KeyboardInterrupt, SystemExit: after every axis had its turn

    def _result(self, stop: Stop, culprit: str) -> AxesResult:
        parts: dict[str, RunResult] = {}
        for axis in self._axes:
            loop, report = axis.loop, axis.report
            timing = TimingStats.of(loop.period_error, loop.exec_time, loop.latency, loop.sample_latency)
            parts[axis.name] = RunResult(cycles=loop.cycles, overruns=self.overruns, stop=stop, timing=timing,
                                         trace=loop.trace, disabled=report is not None and report.safe,
                                         skipped=self.skipped, safe_stop=report)
        empty = Histogram()
        return AxesResult(axes=MappingProxyType(parts), stop=stop, axis=culprit, cycles=self.cycles,
                          overruns=self.overruns, skipped=self.skipped,
                          timing=TimingStats.of(self.period_error, self.exec_time, empty))


def _named(axis: str, detail: str) -> str:
    """A stop's detail with the axis it is about."""
    return f"axis {axis}: {detail}" if axis else detail

