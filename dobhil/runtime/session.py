"""A run put together from a config: buses, (emulated) drive, controller, reference, loop.

:class:`RunSession` owns everything it opens -- buses, the emulator and its process --
and closes all of it, whatever happens (context manager). With ``emulate`` in real time
the plant emulator runs in a process of its own
(:class:`~dobhil.emulator.process.EmulatorProcess`: the loop cannot starve it), and every
frame is copied to a private python-can ``virtual`` channel (``bus_spec``) that in-process
observers may watch; with ``lockstep`` the emulator runs in this process behind a
:class:`~dobhil.drives.emulated.LockstepBus` and the whole run is deterministic.
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

import can

from dobhil.config.schema import Config
from dobhil.drives.base import Drive
from dobhil.drives.preflight import DEFAULT_WINDOW, PreflightReport, Setting, profile_rate_findings, run_preflight
from dobhil.drives.load import load_drive_profile
from dobhil.drives.plugin import PeriodicSend
from dobhil.drives.profile import DriveProfile
from dobhil.drives.registry import drive_class, make_drive, preflight_probe, protocol
from dobhil.drives.timing import effective_config
from dobhil.emulator.plant import Plant
from dobhil.emulator.process import EmulatorProcess, EmulatorSpec, PlantView
from dobhil.drives.emulated import EmulatedDrive, LockstepBus, lockstep_steps
from dobhil.drives.registry import make_emulated_drive
from dobhil.drives.emulated import private_virtual_channel
from dobhil.errors import ConfigError, PreflightError
from dobhil.runtime.buses import BusSpec, open_bus, resolve_bus, shutdown_bus
from dobhil.runtime.controller import ForceController
from dobhil.runtime.instability import WatchSettings
from dobhil.realtime import EMULATOR_PRIORITY_DROP
from dobhil.runtime.loop import (CycleSink, ForceLoop, Limits, LoopSettings, RunResult, StopRequest,
                                 Timing, old_name_warning)
from dobhil.runtime.references import make_reference
from dobhil.synthesis.controller import sampled_controller
from dobhil.synthesis.params import params_from_config


def check_rates(profile: DriveProfile, period: float, prefix: str = "") -> None:
    """The drive must send feedback at least once per control period (the profile's
    promise; :meth:`RunSession.preflight` measures what the drive really does), and its
    timeout on the host's frames must tolerate one every period (:func:`check_host_watch`).
    ``prefix``: before the error line (``axis NAME: `` in a several-axis run)."""
    probe = preflight_probe(profile)
    frames, shortest = (probe.motion_name(), probe.shortest_period(Setting.MOTION_RATE)) if probe else (
        "motion feedback", 0.0)
    for finding in profile_rate_findings(profile, period, frames, shortest):
        raise ConfigError(f"{prefix}{finding.text}")
    check_host_watch(profile, period, prefix)


def check_host_watch(profile: DriveProfile, period: float, prefix: str = "") -> None:
    """ConfigError (one line) when ``period`` is too long for the drive's timeout on the
    host's frames, as its protocol reads it from the profile
    (:meth:`~dobhil.drives.plugin.DriveProtocol.host_watch`: a command watchdog, a heartbeat
    consumer, a command timeout; None: no limit): allowed is ``period < timeout / 2``.

    The drive must see the frame that feeds it at least every ``timeout``, and the loop sends
    one every period; but the drive checks it on its own tick and a frame's way to the
    drive varies by up to a period, so two frames sent on time may reach it up to two
    periods apart. That is the margin :meth:`ForceLoop._watch_gaps
    <dobhil.runtime.loop.ForceLoop._watch_gaps>` gives when it blames the host
    (``host_too_slow``): a gap of ``timeout - period`` or more between commands counts as
    starving the watch. A period of half the timeout or more makes every on-time gap such
    a gap: the drive may trip with no one late, and the host would be blamed for it (at a
    period over the timeout, at the very first cycle, even in lockstep)."""
    watch = protocol(profile.protocol).host_watch(profile)
    if watch is None or 2 * period < watch.timeout:
        return
    where = f" in {watch.where}" if watch.where else ""
    remedy = watch.remedy or f"a longer {watch.key} (on the drive too)"
    raise ConfigError(
        f"{prefix}loop.period = {period:g} s is too long for the {watch.what} of drive profile "
        f"{profile.name or profile.protocol!r} ({watch.key} = {watch.timeout:g} s{where}; a {watch.fed_by} every "
        f"period may reach the drive up to two periods apart); allowed: loop.period < {watch.timeout / 2:g} s "
        f"(half of {watch.key}), or {remedy}")


def is_lockstep(config: Config, lockstep: bool | None) -> bool:
    """Whether a run of ``config`` is a lockstep one: ``lockstep`` when the command says
    (``--lockstep``, ``dobhil demo`` unless ``--realtime``), else ``loop.timing``."""
    return (config.loop.timing == "lockstep") if lockstep is None else lockstep


def check_lockstep(profile: DriveProfile, period: float, prefix: str = "") -> None:
    """ConfigError (one line) when a lockstep run at ``period`` could not send a frame the
    drive sends by itself at a fixed period (its protocol's
    :meth:`~dobhil.drives.plugin.DriveProtocol.periodic_sends`: a SYNC).

    The lockstep bus (:class:`~dobhil.drives.emulated.LockstepBus`) advances simulated
    time one step per loop period and sends a periodic frame only at its steps: each
    period must be a whole number (>= 1) of loop periods (:func:`~dobhil.drives.emulated.lockstep_steps`),
    or the drive's start would fail with the run's bus and emulator open. Refused before
    any bus opens, naming the loop periods that work (those dividing the frame's period
    that the drive's feedback keeps up with, :func:`check_rates`)."""
    sends = protocol(profile.protocol).periodic_sends(profile)
    for send in sends:
        if not lockstep_steps(send.period, period):
            raise ConfigError(
                f"{prefix}lockstep timing steps the emulated bus once per loop.period = {period:g} s and sends a "
                f"periodic frame only every whole number of steps, but drive profile "
                f"{profile.name or profile.protocol!r} sends {send.what} every {send.period:g} s ({send.key}); "
                f"allowed in lockstep: {_lockstep_periods(profile, sends, send)}, or a run in real time")


def check_lockstep_feedback(profile: DriveProfile, period: float) -> None:
    """ConfigError (one line) when a single-axis lockstep run at ``period`` would skip
    cycles: its loop runs one cycle per feedback frame of a drive whose feedback streams
    (:meth:`ForceLoop._run_feedback <dobhil.runtime.loop.ForceLoop>`, ``Timing.LOCKSTEP``),
    so feedback every ``feedback_period`` < ``period`` counts each step's extra frames as
    skipped cycles (feedback every 1 ms under a 24 ms loop ran no cycle at all, and said done).
    The rule of feedback timing (:func:`resolve_timing`); a several-axis lockstep run steps
    once per period and takes the newest sample (:mod:`dobhil.runtime.axes_loop`): no limit."""
    rate = profile.feedback_period
    if rate is None or not protocol(profile.protocol).feedback_streams or abs(rate - period) <= 1e-9 * period:
        return
    probe = preflight_probe(profile)
    frames = probe.motion_name() if probe is not None else "motion feedback"
    raise ConfigError(
        f"lockstep timing runs one cycle per feedback frame, but drive profile {profile.name or profile.protocol!r} "
        f"has {frames} every {rate:g} s (feedback_period) and loop.period = {period:g} s; make them equal "
        "(a profile of its own with feedback_period = loop.period), or a run in real time")


def check_lockstep_run(profile: DriveProfile, period: float) -> None:
    """What :class:`RunSession` refuses of a lockstep run at ``period`` before it opens a bus
    (:func:`check_rates`, :func:`check_lockstep`, :func:`check_lockstep_feedback`), for a
    command to say before its own lines (the stability gate's): the refusal is then the only line."""
    check_rates(profile, period)
    check_lockstep(profile, period)
    check_lockstep_feedback(profile, period)


def _lockstep_periods(profile: DriveProfile, sends: tuple[PeriodicSend, ...], send: PeriodicSend) -> str:
    """The loop periods a lockstep run of ``profile`` allows, in words: ``send``'s period
    over a whole number k, each of ``sends`` a whole number of them, no shorter than the
    feedback period (:func:`check_rates`; without one, every k)."""
    floor = profile.feedback_period
    if floor is None:
        return f"loop.period = {send.period:g} s / k for a whole k >= 1"
    allowed: list[float] = []
    k = 1
    while send.period / k * (1 + 1e-9) >= floor and k <= 10_000:   # bounded: a few values are said
        dt = send.period / k
        if all(lockstep_steps(s.period, dt) for s in sends):
            if len(allowed) == 3:
                return f"loop.period = {', '.join(f'{a:g} s' for a in allowed)}, ... (down to {floor:g} s)"
            allowed.append(dt)
        k += 1
    if not allowed:
        return "no loop.period"
    own = f" ({send.key})" if allowed == [send.period] else ""
    return f"loop.period = {' or '.join(f'{a:g} s' for a in allowed)}{own}"


def build_controller(config: Config, profile: DriveProfile) -> ForceController:
    """The runtime controller: the sampled synthesis of the design on this drive (its
    protocol's command delay, :func:`~dobhil.drives.timing.effective_config`), saturated
    at the tighter torque limit, open loop in torque mode (``loop.mode``). ``dobhil replay``
    rebuilds it with this very function."""
    limit = min(config.loop.torque_limit, profile.torque_limit)
    design, _ = effective_config(config, profile)
    return ForceController(sampled_controller(params_from_config(design)), torque_limit=limit,
                           open_loop=config.loop.mode == "torque")


def loop_settings(config: Config, timing: Timing, duration: float | None, profile: DriveProfile) -> LoopSettings:
    """The loop's settings; its velocity bound is the lower of ``loop.velocity_limit`` and the
    drive profile's ``velocity_limit``, as its torque bound is of the two torque limits: a
    drive whose reading saturates at the end of its codec's range never reports a speed
    above it, so only a bound below it can stop an overspeed."""
    lp = config.loop
    # named in the stop line when it is the profile's: the config's loop.velocity_limit was higher
    if lp.velocity_limit <= profile.velocity_limit:
        velocity = Limits(lp.position_min, lp.position_max, lp.velocity_limit)
    else:
        velocity = Limits(lp.position_min, lp.position_max, profile.velocity_limit,
                          f"the drive profile's velocity_limit, below loop.velocity_limit {lp.velocity_limit:g}")
    return LoopSettings(period=lp.period, duration=duration or lp.duration,
                        feedback_timeout=lp.feedback_timeout, timing=timing, limits=velocity,
                        spin=lp.spin, watch=watch_settings(config))


def watch_settings(config: Config) -> WatchSettings | None:
    """The instability watch of a force run (``instability.*``); None when
    ``instability.window`` is 0, and in torque mode: an open loop cannot go unstable, and
    an excitation there chatters by design."""
    w = config.instability
    if w.window == 0 or config.loop.mode == "torque":
        return None
    return WatchSettings(window=max(2, round(w.window / config.loop.period)), saturation=w.saturation,
                         limit_reversals=w.limit_reversals, hysteresis=w.hysteresis, growth=w.growth,
                         growth_swings=w.growth_swings)


def max_duration() -> float:
    """The longest run: ``loop.duration``'s own ceiling, read from its key
    (dobhil/config/schema.py): its maximum when it has one, else the bound every config
    number has (:data:`dobhil.config.load.MAX_MAGNITUDE`)."""
    from dobhil.config.load import MAX_MAGNITUDE
    from dobhil.config.schema import key_fields
    top = key_fields()["loop.duration"].metadata["maximum"]
    return float(top) if top is not None else MAX_MAGNITUDE


def check_duration(duration: float | None, what: str = "--duration") -> None:
    """A run lasts a finite, positive number of seconds, no more than ``loop.duration``
    allows (None: the config's): a command-line duration is that key given another way,
    and a value the config would refuse must not run (emulate: until stopped)."""
    if duration is None:
        return
    top = max_duration()
    if not (math.isfinite(duration) and 0 < duration <= top):
        raise ConfigError(f"{what} {duration!r}: expected a finite number of seconds > 0 and <= {top:g} "
                          "(loop.duration's range)")


def check_cycles(settings: LoopSettings, prefix: str = "") -> None:
    """A run lasts at least one period (a shorter one would enable the drive and disable it
    without a command: a run of nothing) and fewer cycles than a float counts exactly."""
    duration, period = settings.duration, settings.period
    if duration < period:
        raise ConfigError(f"{prefix}a run of {duration!r} s is shorter than one period (loop.period = "
                          f"{period!r} s); allowed: a duration of at least loop.period")
    if not duration / period < 2.0 ** 53:
        raise ConfigError(f"{prefix}a run of {duration!r} s at loop.period = {period!r} s has too many "
                          "cycles to count; allowed: fewer than 2**53")


def resolve_timing(config: Config, profile: DriveProfile, lockstep: bool | None, prefix: str = "") -> Timing:
    """``loop.timing`` (``realtime``: the old name of ``host``, with a FutureWarning: the
    warning for a config's user, shown by default, which a DeprecationWarning is not), or
    lockstep when asked;
    a real-time run of a lockstep config (``demo --realtime``) is feedback-synchronous.
    Feedback timing needs the drive to stream feedback once per ``loop.period``.
    ``prefix``: before the error line (``axis NAME: `` in a several-axis run, whose axes
    may share one profile)."""
    name = config.loop.timing
    if lockstep is None:
        lockstep = name == "lockstep"
    if lockstep:
        return Timing.LOCKSTEP
    if name == "realtime":
        warnings.warn(old_name_warning("loop.timing: realtime", "loop.timing: host"), FutureWarning, stacklevel=2)
    if name in ("host", "realtime"):
        return Timing.HOST
    period, rate = config.loop.period, profile.feedback_period
    if rate is None:
        raise ConfigError(
            f"{prefix}loop.timing = feedback runs one cycle per feedback frame, but drive profile "
            f"{profile.name or profile.protocol!r} has no feedback_period (its feedback does not "
            f"stream); set loop.timing: host")
    if abs(rate - period) > 1e-9 * period:
        probe = preflight_probe(profile)
        frames = probe.motion_name() if probe is not None else "motion feedback"
        raise ConfigError(
            f"{prefix}loop.timing = feedback runs one cycle per feedback frame, but drive profile "
            f"{profile.name or profile.protocol!r} has {frames} every {rate:g} s (feedback_period) and "
            f"loop.period = {period:g} s; make them equal (on the drive too) or set "
            f"loop.timing: host")
    return Timing.FEEDBACK


def check_feedback_streams(timing: Timing, drive: Drive, prefix: str = "") -> None:
    """A loop timed by feedback needs a drive that streams it on its own; one that only
    answers the host each cycle (a SYNC the bus cannot send periodically) cannot start it.
    ``prefix``: before the error line (``axis NAME: ``)."""
    if timing is Timing.FEEDBACK and not drive.feedback_streams:
        raise ConfigError(
            f"{prefix}loop.timing = feedback runs one cycle per feedback frame, but node {drive.node_id} "
            f"({drive.protocol}) only sends feedback when the host asks for it on this bus; "
            f"set loop.timing: host")


def lockstep_latency(config: Config, profile: DriveProfile) -> float:
    """When the lockstep emulator applies a command after the sample it was computed
    from: the delay the sampled analysis models, ``design.delay_samples`` whole periods
    plus ``design.input_delay`` (the fractional compute + bus delay) -- or 0 when the
    drive's protocol fixes the delay itself (``command_delay_periods``): the emulated
    drive's own latch (a command applied at the next SYNC) makes it, and a latency
    on top would count it twice."""
    if profile.command_delay_periods is not None:
        return 0.0
    d = config.design
    return d.delay_samples * config.loop.period + d.input_delay


class RunSession:
    """Everything one run needs; ``with RunSession(...) as s: result = s.run()``."""

    def __init__(self, config: Config, *, bus: str | None = None, emulate: bool = False,
                 lockstep: bool | None = None, duration: float | None = None,
                 config_dir: Path | None = None, sink: CycleSink | None = None,
                 stop_request: StopRequest | None = None,
                 bus_wrapper: Callable[[can.BusABC], can.BusABC] | None = None,
                 preflight: bool | None = None, preflight_window: float = DEFAULT_WINDOW,
                 reset_faults: bool = False) -> None:
        lockstep = is_lockstep(config, lockstep)
        if lockstep and not emulate:
            raise ConfigError("lockstep timing needs the in-process emulator (--emulate); "
                              "a real drive runs in real time")
        if emulate and bus:
            raise ConfigError(f"--bus {bus} with --emulate: the emulator runs on its own private virtual "
                              "bus; drop --bus, or run 'dobhil emulate CONFIG --bus ...' beside "
                              "'dobhil run CONFIG --bus ...'")
        check_duration(duration)
        self.config = config
        self.profile = load_drive_profile(config, config_dir)
        #: the design on this drive: the protocol's command delay, when it fixes one (the
        #: run's controller, its lockstep emulator); ``design_note`` says what that changed
        self.design_config, self.design_note = effective_config(config, self.profile)
        check_rates(self.profile, config.loop.period)
        self.timing = resolve_timing(config, self.profile, lockstep)
        if self.timing is Timing.LOCKSTEP:
            check_lockstep(self.profile, config.loop.period)
            check_lockstep_feedback(self.profile, config.loop.period)
        self.settings = loop_settings(config, self.timing, duration, self.profile)
        check_cycles(self.settings)
        self.controller = build_controller(config, self.profile)
        self.reference = make_reference(config.reference, config_dir,
                                        duration=self.settings.duration)
        self.sink = sink
        self.stop_request = stop_request or StopRequest()
        self.plant: Plant | PlantView | None = None
        self.emulator: EmulatedDrive | EmulatorProcess | None = None
        self._buses: list[can.BusABC] = []
        #: buses whose shutdown failed (one line each; close() does not raise for them)
        self.shutdown_problems: list[str] = []
        self._wrapper = bus_wrapper
        # preflight: on for a drive this session did not build; off with --emulate, whose
        # emulator is made from this very profile (a measurement could only restate it, and
        # in lockstep listening would advance the simulated plant before the run)
        self.preflight_enabled = (not emulate) if preflight is None else preflight
        self.preflight_window = preflight_window
        self.preflight_report: PreflightReport | None = None
        #: the drive may clear a fault before enabling (``dobhil run --reset-faults``)
        self.reset_faults = reset_faults
        self.loop: ForceLoop | None = None   # the run's loop, once run() started it
        # an FD protocol's private channel is opened as CAN FD (its drive refuses a classic bus)
        fd = {"protocol": can.CanProtocol.CAN_FD} if protocol(self.profile.protocol).fd else {}
        self.bus_spec = (BusSpec("virtual", private_virtual_channel(), fd) if emulate
                         else resolve_bus(config, self.profile, bus))
        try:
            self.drive = self._open(emulate)
            check_feedback_streams(self.timing, self.drive)
        except BaseException:
            self.close()
            raise

    # -- building ------------------------------------------------------------

    def _open(self, emulate: bool) -> Drive:
        host = self._add(open_bus(self.bus_spec))
        clock: dict[str, Any] = {}
        if emulate and self.timing is Timing.LOCKSTEP:
            self.plant = Plant.from_config(self.config)
            emu_bus = self._add(open_bus(self.bus_spec))
            self.emulator = make_emulated_drive(emu_bus, self.profile, self.plant,
                                                latency=lockstep_latency(self.config, self.profile),
                                                jitter=0.0,
                                                seed=self.config.sensor.seed)
            lock = LockstepBus(host, [self.emulator], dt=self.config.loop.period)
            self._add(lock)
            host = lock
            clock["clock"] = lock.clock
        elif emulate:
            # host timing: the emulator below the loop, which keeps its own deadlines;
            # feedback timing: the emulator is the loop's clock (the drive it stands
            # for has a CPU of its own) and keeps its priority
            drop = EMULATOR_PRIORITY_DROP if self.timing is Timing.HOST else 0
            drive_class(self.profile.protocol)   # imported now: the drive streams from its start
            mirror = host   # the private virtual channel: a copy of every frame
            # its clock starts with the enable: no frames pile up while the host starts up
            spec = EmulatorSpec.of(self.config, self.profile, priority_drop=drop, on_first_frame=True)
            emulator = EmulatorProcess(spec, channel=self.bus_spec.channel, mirror=mirror)
            self.emulator = emulator
            self.plant = emulator.plant
            host = self._add(emulator.bus)
        self._unwrapped_host = host  # the preflight listens here: not recorded as the run's frames
        if self._wrapper is not None:
            host = self._add(self._wrapper(host))
        self.host_bus = host
        self._clock = clock.get("clock")
        return make_drive(host, self.profile, reset_faults=self.reset_faults, **clock)

    def _add(self, bus: can.BusABC) -> can.BusABC:
        self._buses.append(bus)
        return bus

    @property
    def sim_clock(self) -> Callable[[], float] | None:
        """Simulated time [s] of a lockstep run (the log clock); None in real time."""
        return self._clock

    # -- running -------------------------------------------------------------

    def truth(self) -> tuple[float, float]:
        if isinstance(self.emulator, EmulatorProcess):
            return self.emulator.truth()   # both of one tick
        assert self.plant is not None
        return self.plant.interaction_torque, self.plant.true_position

    def preflight(self) -> PreflightReport | None:
        """Measure the drive before it is enabled (once; None when skipped). Raises
        PreflightError if a run would sample stale feedback (or find no drive), or on another
        refusing finding (:attr:`~dobhil.drives.preflight.Finding.refuses`)."""
        if not self.preflight_enabled:
            return None
        if self.preflight_report is None:
            sim = self._clock if self.timing is Timing.LOCKSTEP else None  # simulated time
            self.preflight_report = run_preflight(
                self._unwrapped_host, self.profile, period=self.config.loop.period,
                feedback_timeout=self.config.loop.feedback_timeout, window=self.preflight_window,
                bitrate=self.bus_spec.kwargs.get("bitrate") or None,
                probe=preflight_probe(self.profile), cancel=self.stop_request.reason,
                **({"clock": sim, "stamp": lambda _m: sim()} if sim is not None else {}))
        if self.stop_request.is_set():
            # cut short by SIGINT/SIGTERM: a partial measurement says nothing, and the
            # loop stops at once with the signal as its reason (never enabling)
            self.preflight_enabled = False
            return None
        if self.preflight_report.refuses:
            raise PreflightError(self.preflight_report)
        return self.preflight_report

    def run(self) -> RunResult:
        self.preflight()
        loop = ForceLoop(drive=self.drive, controller=self.controller, reference=self.reference,
                         settings=self.settings, sink=self.sink, stop_request=self.stop_request,
                         truth=self.truth if self.plant is not None else None,
                         starved=self.emulator.starved if isinstance(self.emulator, EmulatorProcess)
                         else None,
                         **({"clock": self._clock} if self._clock else {}))
        self.loop = loop
        try:
            return loop.run()
        finally:
            self._settle()

    def _settle(self) -> None:
        """Lockstep: the emulator reads the final frames (zero torque, disable) now, so its
        state after the run is what the drive would be in; real time does this by itself."""
        if self.timing is Timing.LOCKSTEP and isinstance(self.emulator, EmulatedDrive):
            try:
                self.emulator.handle_pending()
            except Exception:
                pass

    def close(self) -> None:
        """Stop the emulator (its thread or process) and shut every bus down (never raises
        twice). A bus that fails to shut down (its link already gone) is noted in
        ``shutdown_problems``, not raised: how the run ended must still be told."""
        stop_and_shut([self.emulator] if self.emulator is not None else [], self._buses, self.shutdown_problems)

    def __enter__(self) -> RunSession:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def stop_and_shut(emulators: list[Any], buses: list[can.BusABC], problems: list[str]) -> None:
    """A session's end: stop ``emulators`` (their threads or processes), then shut ``buses``
    down, the last opened first (the list emptied). A bus that fails to shut down (its link
    already gone) is noted in ``problems``, not raised: how the run ended must still be told;
    the first emulator's error is raised once every bus is shut."""
    errors: list[BaseException] = []
    for emulator in emulators:
        try:
            emulator.stop()
        except BaseException as exc:
            errors.append(exc)
    for bus in reversed(buses):
        problem = shutdown_bus(bus)
        if problem:
            problems.append(f"{bus.channel_info}: {problem}")
    buses.clear()
    if errors:
        raise errors[0]


def final_values(tr: Any) -> dict[str, float | None]:
    """The last cycle's ``tau_ref``, ``tau_int_hat``, true ``tau_int`` and ``q`` of a run's
    trace (None before the first cycle; the true value None where no emulator knows it)."""
    if tr.last < 0:
        return {"tau_ref": None, "tau_int_hat": None, "tau_int_true": None, "q": None}
    true = tr.latest("tau_int_true")
    return {"tau_ref": tr.latest("tau_ref"), "tau_int_hat": tr.latest("tau_int_hat"),
            "tau_int_true": None if true != true else true, "q": tr.latest("q")}


def summary(session: RunSession, result: RunResult) -> dict[str, Any]:
    """The ``--summary-json`` object."""
    final = final_values(result.trace)
    report = result.safe_stop
    return {
        "cycles": result.cycles, "skipped": result.skipped, "overruns": result.overruns,
        "stop_reason": result.stop.reason.name.lower(), "stop_detail": result.stop.detail,
        "drive_disabled": result.disabled,
        "drive_warning": report.warning() if report is not None else "",
        "drive_note": report.note() if report is not None else "",
        "drive_notes": list(session.drive.notes),
        "safe_stop": None if report is None else {
            "frames": [{"what": f.what, "sent": f.sent, "error": f.error, "refused": f.refused}
                       for f in report.frames],
            "confirmation": report.confirmation.name.lower(), "detail": report.detail,
            "planned": report.planned},
        "timing": session.timing.label, "mode": session.config.loop.mode,
        "period": session.settings.period, "bus": session.bus_spec.describe(),
        "emulated": session.emulator is not None,
        "watchdog_tripped": bool(getattr(session.emulator, "watchdog_tripped", False)),
        "preflight": None if session.preflight_report is None else session.preflight_report.as_dict(),
        "final": final,
        # how close the run came to an ``unstable`` stop (null: no watch)
        "instability": watch_peaks(getattr(session, "loop", None)),
        # a sample latency only where one was measured (absent, not null, otherwise)
        "loop_timing": {k: v for k, v in dataclasses.asdict(result.timing).items() if v is not None},
        **sample_latency_us(result),
    }


def watch_peaks(loop: ForceLoop | None) -> dict[str, Any] | None:
    """The instability watch's peaks of a run (None: no watch, or no loop ran)."""
    watch = loop.watch if loop is not None else None
    return None if watch is None else dataclasses.asdict(watch.peaks)


def sample_latency_us(result: RunResult) -> dict[str, Any]:
    """``{"sample_latency_us": {"p50", "p99", "max"}}`` when any cycle measured the drive's
    sample -> feedback received latency (:attr:`Feedback.sample_latency`), else ``{}``."""
    t = result.timing
    if t.sample_latency_p50 is None or t.sample_latency_p99 is None or t.sample_latency_max is None:
        return {}
    return {"sample_latency_us": {"p50": t.sample_latency_p50 * 1e6, "p99": t.sample_latency_p99 * 1e6,
                                  "max": t.sample_latency_max * 1e6}}
