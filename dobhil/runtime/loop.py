"""The force-control loop: feedback in, DOb/RTOb controller, torque out, safety around it.

One cycle: read the newest feedback from the drive, check it (age, limits,
finiteness), compute the controller (:class:`~dobhil.runtime.controller.ForceController`),
check the command, send it. No printing, logging or file I/O in the cycle: per-cycle
values go into preallocated arrays (:class:`Trace`) and to an optional non-blocking
``sink`` (the MCAP recorder in its lossy mode).

Timing:

- **lockstep**: the bus is a :class:`dobhil.emulator.protocol.LockstepBus`; waiting for
  feedback advances the emulator by one period, so the loop runs as fast as the machine
  allows and exactly as the sampled analysis models it.
- **real time**: absolute deadlines ``t0 + k T``; the cycle reads the newest feedback
  without blocking, and sleeps to the next deadline. A cycle that finishes after the
  next deadline is an overrun: it is counted and the missed deadlines are skipped
  (as ros2_control does), never replayed in a burst.

Safety: every way out of :meth:`ForceLoop.run` -- done, feedback timeout, position or
velocity limit, non-finite value, drive fault, stop request (SIGINT/SIGTERM), or any
exception -- sends zero torque and disables the drive, and is recorded as a
:class:`~dobhil.runtime.stop.Stop`. Exceptions are re-raised after the safe stop.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from enum import IntEnum
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from dobhil.drives.base import Drive, Feedback
from dobhil.errors import DriveError, DriveFaultError, RecorderError
from dobhil.runtime.controller import ControlOutput, ForceController
from dobhil.runtime.stop import Stop, StopReason


class Timing(IntEnum):
    LOCKSTEP = 0
    REALTIME = 1


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


@dataclass(frozen=True)
class Limits:
    position_min: float
    position_max: float
    velocity_limit: float


@dataclass(frozen=True)
class LoopSettings:
    period: float
    duration: float
    feedback_timeout: float
    timing: Timing
    limits: Limits


FIELDS = ("t", "q", "dq", "tau_ref", "tau_int_hat", "tau_dis_hat", "tau_per", "u_unsat", "u",
          "period_error", "exec_time", "overrun", "tau_int_true", "q_true")


@dataclass
class Trace:
    """Per-cycle values in preallocated arrays (filled up to ``n``)."""

    capacity: int
    data: dict[str, NDArray[np.float64]] = field(default_factory=dict)
    n: int = 0

    def __post_init__(self) -> None:
        self.data = {name: np.full(self.capacity, np.nan) for name in FIELDS}

    def __getitem__(self, name: str) -> NDArray[np.float64]:
        return self.data[name][:self.n]


@dataclass(frozen=True)
class TimingStats:
    period_error_p50: float
    period_error_p99: float
    period_error_max: float
    exec_time_p50: float
    exec_time_p99: float
    exec_time_max: float

    @classmethod
    def of(cls, trace: Trace) -> TimingStats:
        # rows of deadlines skipped after an overrun were never run: NaN, left out
        ran = np.isfinite(trace["exec_time"])
        pe, ex = np.abs(trace["period_error"][ran]), trace["exec_time"][ran]
        if pe.size == 0:
            return cls(0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
        p = np.percentile
        return cls(float(p(pe, 50)), float(p(pe, 99)), float(pe.max()),
                   float(p(ex, 50)), float(p(ex, 99)), float(ex.max()))


@dataclass(frozen=True)
class RunResult:
    cycles: int
    overruns: int
    stop: Stop
    timing: TimingStats
    trace: Trace
    disabled: bool          # the drive acknowledged the disable (or the attempt failed: False)


class StopRequest:
    """A thread-safe flag the loop polls every cycle (set by signal handlers)."""

    def __init__(self) -> None:
        self._event = threading.Event()
        self.why = ""

    def set(self, why: str) -> None:
        self.why = why
        self._event.set()

    def is_set(self) -> bool:
        return self._event.is_set()


class _Halt(Exception):
    """Internal: leave the cycle loop with a stop record."""

    def __init__(self, reason: StopReason, detail: str) -> None:
        super().__init__(detail)
        self.reason = reason
        self.detail = detail


class ForceLoop:
    """Runs the controller against a drive until the duration ends or something stops it."""

    def __init__(self, *, drive: Drive, controller: ForceController, reference: Reference,
                 settings: LoopSettings, clock: Callable[[], float] = time.perf_counter,
                 truth: Callable[[], tuple[float, float]] | None = None,
                 sink: CycleSink | None = None, stop_request: StopRequest | None = None) -> None:
        self.drive = drive
        self.controller = controller
        self.reference = reference
        self.settings = settings
        self.clock = clock
        self.truth = truth
        self.sink = sink
        self.stop_request = stop_request or StopRequest()
        self.cycles = 0
        self.overruns = 0
        self._t0 = 0.0
        self._last_out: ControlOutput | None = None
        self.trace = Trace(int(math.ceil(settings.duration / settings.period)) + 1)

    # -- public --------------------------------------------------------------

    def run(self) -> RunResult:
        """Enable, run the cycles, always stop safely; exceptions reach the caller after."""
        stop: Stop | None = None
        try:
            stop = self._enable_and_run()
        except BaseException as exc:
            stop = Stop(StopReason.EXCEPTION, f"{type(exc).__name__}: {exc}", self.cycles,
                        self._now())
            self._safe_stop(stop)
            raise
        disabled = self._safe_stop(stop)
        return RunResult(cycles=self.cycles, overruns=self.overruns, stop=stop,
                         timing=TimingStats.of(self.trace), trace=self.trace, disabled=disabled)

    # -- internals -------------------------------------------------------------

    def _now(self) -> float:
        return self.clock() - self._t0

    def _enable_and_run(self) -> Stop:
        self._t0 = self.clock()  # stop times before the first cycle: from the enable
        try:
            self.drive.enable()
        except DriveError as exc:
            return Stop(StopReason.ENABLE_FAILED, str(exc), -1, 0.0)
        try:
            first = self._first_feedback()
            self.controller.initialize(first.position, first.velocity)
            if self.sink is not None:
                self.sink.started(first)
            self._t0 = self.clock()
            if self.settings.timing is Timing.LOCKSTEP:
                self._run_lockstep()
            else:
                self._run_realtime()
        except _Halt as halt:
            return Stop(halt.reason, halt.detail, self.cycles, self._now())
        except DriveFaultError as exc:
            return Stop(StopReason.DRIVE_FAULT, str(exc), self.cycles, self._now())
        return Stop(StopReason.DONE, f"ran {self.settings.duration:g} s", self.cycles, self._now())

    def _first_feedback(self) -> Feedback:
        fb = self.drive.poll(self.settings.feedback_timeout)
        if fb is None:
            fb = self.drive.feedback
        if fb is None:
            raise _Halt(StopReason.FEEDBACK_TIMEOUT,
                        f"no feedback within {self.settings.feedback_timeout:g} s of enabling")
        return fb

    def _cycle_count(self) -> int:
        return self.trace.capacity - 1

    def _run_lockstep(self) -> None:
        timeout = self.settings.feedback_timeout
        period = self.settings.period
        for k in range(self._cycle_count()):
            start = time.perf_counter()
            fb = self.drive.poll(timeout)
            if fb is None:
                raise _Halt(StopReason.FEEDBACK_TIMEOUT,
                            f"no fresh feedback for {timeout:g} s (simulated)")
            self._cycle(k, k * period, fb, 0.0, start)
            self._emit(k, fb, False)

    def _run_realtime(self) -> None:
        s = self.settings
        period, timeout = s.period, s.feedback_timeout
        t0 = self._t0
        k = 0
        last_fresh = t0
        n = self._cycle_count()
        while k < n:
            wake = self.clock()
            start = time.perf_counter()
            fb = self.drive.poll(0.0)
            if fb is not None:
                last_fresh = wake
            elif wake - last_fresh > timeout:
                raise _Halt(StopReason.FEEDBACK_TIMEOUT,
                            f"no fresh feedback for {wake - last_fresh:.4f} s (limit {timeout:g} s)")
            fb = fb or self.drive.feedback
            if fb is None:
                raise _Halt(StopReason.FEEDBACK_TIMEOUT, "no feedback")
            self._cycle(k, wake - t0, fb, wake - (t0 + k * period), start)
            k = self._next_deadline(k, fb, t0, period)

    def _next_deadline(self, k: int, fb: Feedback, t0: float, period: float) -> int:
        """Count an overrun and skip the missed deadlines; sleep to the next one."""
        nxt = k + 1
        now = self.clock()
        overrun = now > t0 + nxt * period
        if overrun:
            self.overruns += 1
            self.trace.data["overrun"][k] = 1.0
            nxt = int((now - t0) / period) + 1
        self._emit(k, fb, overrun)
        delay = t0 + nxt * period - self.clock()
        if delay > 0:
            time.sleep(delay)
        return nxt

    def _cycle(self, k: int, t: float, fb: Feedback, period_error: float, start: float) -> None:
        if self.stop_request.is_set():
            raise _Halt(StopReason.SIGNAL, self.stop_request.why or "stop requested")
        q, dq = fb.position, fb.velocity
        self._check_feedback(q, dq)
        out = self.controller.step(q, dq if self.controller.measures_velocity else None,
                                   self.reference.value(t))
        if not math.isfinite(out.u) or not math.isfinite(out.tau_ref):
            raise _Halt(StopReason.NON_FINITE, f"non-finite command u = {out.u!r} "
                        f"(tau_ref = {out.tau_ref!r}, tau_int^ = {out.tau_int_hat!r})")
        self.drive.send_torque(out.u)
        exec_time = time.perf_counter() - start
        self._store(k, t, q, dq, out, period_error, exec_time)
        self.cycles = k + 1

    def _check_feedback(self, q: float, dq: float) -> None:
        lim = self.settings.limits
        if not (math.isfinite(q) and math.isfinite(dq)):
            raise _Halt(StopReason.NON_FINITE, f"non-finite feedback q = {q!r}, dq = {dq!r}")
        if not lim.position_min <= q <= lim.position_max:
            raise _Halt(StopReason.POSITION_LIMIT, f"q = {q:.6g} rad outside "
                        f"[{lim.position_min:g}, {lim.position_max:g}]")
        if abs(dq) > lim.velocity_limit:
            raise _Halt(StopReason.VELOCITY_LIMIT,
                        f"|dq| = {abs(dq):.6g} rad/s above {lim.velocity_limit:g}")

    def _store(self, k: int, t: float, q: float, dq: float, out: ControlOutput,
               period_error: float, exec_time: float) -> None:
        d = self.trace.data
        d["t"][k], d["q"][k], d["dq"][k] = t, q, dq
        d["tau_ref"][k], d["tau_int_hat"][k], d["tau_dis_hat"][k] = out.tau_ref, out.tau_int_hat, out.tau_dis_hat
        d["tau_per"][k], d["u_unsat"][k], d["u"][k] = out.tau_per, out.u_unsat, out.u
        d["period_error"][k], d["exec_time"][k], d["overrun"][k] = period_error, exec_time, 0.0
        if self.truth is not None:
            d["tau_int_true"][k], d["q_true"][k] = self.truth()
        self.trace.n = k + 1
        self._last_out = out

    def _emit(self, k: int, fb: Feedback, overrun: bool) -> None:
        if self.sink is not None:
            d = self.trace.data
            try:
                self.sink.cycle(k, float(d["t"][k]), fb, self._last_out, float(d["period_error"][k]),
                                float(d["exec_time"][k]), overrun)
            except RecorderError as exc:
                raise _Halt(StopReason.RECORDER_FAILED, str(exc)) from exc

    def _safe_stop(self, stop: Stop) -> bool:
        """Zero torque, disable; never raises. Returns whether the disable went through."""
        try:
            if self.sink is not None:
                self.sink.stop(stop)
        except Exception:
            pass
        return bool(self.drive.disable())
