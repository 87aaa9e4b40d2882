"""A run of several axes put together from an :class:`~dobhil.config.axes.Axes` config.

:class:`AxesSession` is :class:`~dobhil.runtime.session.RunSession` for N axes: each
axis' profile (with its ``drive.node_id``), controller, reference and limits, built by
the very functions a single-axis run uses; the axes grouped by bus (an axis'
``drive.interface``/``drive.channel``, else the default bus); per bus one python-can bus
shared by its axes' drives (:class:`~dobhil.runtime.shared_bus.SharedBus`); one
:class:`~dobhil.runtime.axes_loop.AxesLoop`. It owns everything it opens and closes all
of it (context manager).

Two drives on one bus must not use one arbitration id: the session refuses a clash
before anything is opened, in the one line of :func:`dobhil.drives.axes.check_clashes`
(the check ``dobhil check`` makes), naming both axes and the id.

Emulation: ``lockstep`` puts per bus one private ``virtual`` channel, one emulated drive
per axis (its plant from its config; coupled plants when the config couples axes) and one
:class:`~dobhil.drives.emulated.LockstepBus` over them. In real time the emulator process
hosts every node of a bus (:class:`~dobhil.emulator.process.EmulatorProcess` given a list
of specs).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import can

from dobhil.config.axes import Axes, Axis
from dobhil.drives.axes import axis_drives
from dobhil.drives.base import Drive
from dobhil.drives.emulated import EmulatedDrive, LockstepBus, PlantLike, private_virtual_channel
from dobhil.drives.load import load_drive_profile
from dobhil.drives.registry import drive_class, make_drive, make_emulated_drive, protocol
from dobhil.emulator.coupling import couple_plants
from dobhil.emulator.plant import Plant
from dobhil.emulator.process import EmulatorProcess, EmulatorSpec
from dobhil.errors import ConfigError
from dobhil.realtime import EMULATOR_PRIORITY_DROP
from dobhil.runtime.axes_loop import AxesLoop, AxesResult, AxisParts
from dobhil.runtime.buses import BusSpec, open_bus, resolve_bus, shared_spec
from dobhil.runtime.loop import CycleSink, LoopSettings, StopRequest, Timing
from dobhil.runtime.references import make_reference
from dobhil.runtime.session import (build_controller, check_cycles, check_duration, check_feedback_streams,
                                    check_lockstep, check_rates, final_values, is_lockstep, lockstep_latency,
                                    loop_settings, resolve_timing, stop_and_shut)
from dobhil.runtime.shared_bus import SharedBus

__all__ = ["AxesSession", "BusGroup", "BusWrapper", "axes_summary"]

#: wraps the host's side of one bus (bus name given): a recorder's tap, a fault injector
BusWrapper = Callable[[can.BusABC, str], can.BusABC]


@dataclass
class BusGroup:
    """One bus and the axes on it."""

    name: str                   # the configured bus (``INTERFACE:CHANNEL``), the key of a wrapper
    spec: BusSpec               # what is opened (a private channel when emulated)
    axes: list[str] = field(default_factory=list)
    shared: SharedBus | None = None
    lockstep: LockstepBus | None = None


class AxesSession:
    """Everything a run of several axes needs; ``with AxesSession(...) as s: result = s.run()``."""

    def __init__(self, axes: Axes, *, bus: str | None = None, emulate: bool = False,
                 lockstep: bool | None = None, duration: float | None = None,
                 config_dir: Path | None = None, sinks: Mapping[str, CycleSink] | None = None,
                 stop_request: StopRequest | None = None, bus_wrapper: BusWrapper | None = None,
                 reset_faults: bool = False) -> None:
        first = axes.axes[0].config
        lockstep = is_lockstep(first, lockstep)
        if lockstep and not emulate:
            raise ConfigError("lockstep timing needs the in-process emulator (--emulate); "
                              "a real drive runs in real time")
        if emulate and bus:
            raise ConfigError(f"--bus {bus} with --emulate: the emulator runs on its own private virtual "
                              "bus; drop --bus")
        check_duration(duration)
        unknown = sorted(set(sinks or {}) - {a.name for a in axes.axes})
        if unknown:
            raise ConfigError(f"sinks for unknown axes {unknown}; axes: {[a.name for a in axes.axes]}")
        self.axes = axes
        self.emulate = emulate
        self.config_dir = config_dir
        self.sinks = dict(sinks or {})
        self.stop_request = stop_request or StopRequest()
        self.reset_faults = reset_faults
        self._wrapper = bus_wrapper
        self.profiles = {a.name: load_drive_profile(a.config, config_dir) for a in axes.axes}
        # a clash refused before anything is opened, in the line dobhil check gives
        axis_drives(axes, config_dir, bus)
        for a in axes.axes:
            check_rates(self.profiles[a.name], a.config.loop.period, f"axis {a.name}: ")
        self.timing = self._timing(lockstep)
        if self.timing is Timing.LOCKSTEP:   # one lockstep bus per bus group, stepped at the axes' period
            for a in axes.axes:
                check_lockstep(self.profiles[a.name], axes.period, f"axis {a.name}: ")
        self.settings = {a.name: loop_settings(a.config, self.timing, duration, self.profiles[a.name])
                         for a in axes.axes}
        for name, settings in self.settings.items():
            check_cycles(settings, f"axis {name}: ")
        self.controllers = {a.name: build_controller(a.config, self.profiles[a.name]) for a in axes.axes}
        self.references = {a.name: make_reference(a.config.reference, config_dir,
                                                  duration=self.settings[a.name].duration)
                           for a in axes.axes}
        self.plants: dict[str, PlantLike] = {}
        self.emulators: list[EmulatedDrive | EmulatorProcess] = []
        self.drives: dict[str, Drive] = {}
        #: the emulator process of each axis emulated in real time
        self._processes: dict[str, EmulatorProcess] = {}
        self.groups: list[BusGroup] = []
        self.loop: AxesLoop | None = None
        #: buses whose shutdown failed (one line each; close() does not raise for them)
        self.shutdown_problems: list[str] = []
        self._buses: list[can.BusABC] = []
        self._shared: list[SharedBus] = []
        try:
            self.groups = self._group(bus)
            if emulate:
                self._check_couplings()
            for group in self.groups:
                self._open(group)
        except BaseException:
            self.close()
            raise

    # -- building ------------------------------------------------------------

    def _timing(self, lockstep: bool) -> Timing:
        """One timing for every axis (each axis' as a single-axis run resolves it; host
        when they differ)."""
        timings = {resolve_timing(a.config, self.profiles[a.name], lockstep, f"axis {a.name}: ")
                   for a in self.axes.axes}
        return timings.pop() if len(timings) == 1 else Timing.HOST

    def _group(self, cli_bus: str | None) -> list[BusGroup]:
        groups: dict[str, BusGroup] = {}
        for a in self.axes.axes:
            profile = self.profiles[a.name]
            spec = resolve_bus(a.config, profile, None if a.config.drive.interface else cli_bus)
            name = spec.describe()
            group = groups.get(name)
            if group is None:
                if self.emulate:
                    spec = BusSpec("virtual", private_virtual_channel(), {})
                group = groups[name] = BusGroup(name, spec)
            elif not self.emulate:   # one bus opened for every drive on it (a CAN FD one's fd too)
                group.spec = shared_spec([group.spec, spec])
            group.axes.append(a.name)
            if self.emulate and protocol(profile.protocol).fd:
                # CAN FD when any axis of the bus needs it, whichever axis the config lists first
                # (a classic frame travels on a CAN FD bus; an FD frame not on a classic one)
                group.spec = BusSpec("virtual", group.spec.channel, {"protocol": can.CanProtocol.CAN_FD})
        return list(groups.values())

    def _check_couplings(self) -> None:
        """Refuse a coupling between axes emulated on different buses, before any bus or
        emulator is opened: each bus' emulator (the lockstep one and the real-time process
        alike) hosts the plants of its own bus' axes only, so it could not join them."""
        bus_of = {name: g.name for g in self.groups for name in g.axes}
        for c in self.axes.couplings:
            if bus_of[c.a] != bus_of[c.b]:
                raise ConfigError(f"coupling between axes {c.a!r} and {c.b!r}: they are on different buses "
                                  f"({bus_of[c.a]}, {bus_of[c.b]}); an emulated coupling joins axes of one bus")

    def _open(self, group: BusGroup) -> None:
        host = self._add(open_bus(group.spec))
        if self.emulate and self.timing is Timing.LOCKSTEP:
            emulators = self._lockstep_emulators(group)
            lock = LockstepBus(host, emulators, dt=self.axes.period)
            self._add(lock)
            group.lockstep = lock
            host = lock
        elif self.emulate:
            host = self._add(self._realtime_emulator(group, host))
        if self._wrapper is not None:
            host = self._add(self._wrapper(host, group.name))
        shared = group.shared = SharedBus(host)
        self._shared.append(shared)
        clock: dict[str, Any] = {"clock": group.lockstep.clock} if group.lockstep is not None else {}
        for name in group.axes:
            view = shared.view(name)
            self._add(view)
            drive = make_drive(view, self.profiles[name], reset_faults=self.reset_faults, **clock)
            view.accept(drive.frame_ids)
            check_feedback_streams(self.timing, drive, f"axis {name}: ")
            self.drives[name] = drive

    def _lockstep_emulators(self, group: BusGroup) -> list[EmulatedDrive]:
        plants = self._plants(group.axes)
        # the emulators share one end of the channel: each reads every frame the host sends
        # (a lockstep emulator reads exactly as many as were sent), none reads another
        # emulator's (two ends on a virtual channel would copy each one's frames to the other)
        nodes = SharedBus(self._add(open_bus(group.spec)))
        self._shared.append(nodes)
        emulators = []
        for name in group.axes:
            axis, profile = self.axes.axis(name), self.profiles[name]
            emu_bus = self._add(nodes.view(f"{name} emulator"))
            emulator = make_emulated_drive(emu_bus, profile, plants[name],
                                           latency=lockstep_latency(axis.config, profile), jitter=0.0,
                                           seed=axis.config.sensor.seed)
            emulators.append(emulator)
            self.emulators.append(emulator)
        return emulators

    def _plants(self, names: list[str]) -> dict[str, PlantLike]:
        """Each axis' plant; the coupled ones through the coupling module."""
        plants: dict[str, Plant] = {name: Plant.from_config(self.axes.axis(name).config) for name in names}
        # a coupling to another bus' axis was refused before anything opened (_check_couplings)
        couplings = [c for c in self.axes.couplings if c.a in plants and c.b in plants]
        if not couplings:
            self.plants.update(plants)
            return dict(plants)
        coupled = couple_plants(plants, couplings)
        self.plants.update(coupled)
        return coupled

    def _realtime_emulator(self, group: BusGroup, mirror: can.BusABC) -> can.BusABC:
        """The emulator process hosting every node of the bus, in real time."""
        drop = EMULATOR_PRIORITY_DROP if self.timing is Timing.HOST else 0
        specs = []
        for name in group.axes:
            profile = self.profiles[name]
            drive_class(profile.protocol)   # imported now: the drive streams from its start
            # named: the axis the node drives (its truth, its couplings)
            specs.append(EmulatorSpec.of(self.axes.axis(name).config, profile, priority_drop=drop,
                                         on_first_frame=True, name=name))
        couplings = [c for c in self.axes.couplings if c.a in group.axes and c.b in group.axes]
        emulator = EmulatorProcess(specs, channel=group.spec.channel, mirror=mirror, couplings=couplings)
        self.emulators.append(emulator)
        for name in group.axes:
            self._processes[name] = emulator
        return emulator.bus

    def _add(self, bus: can.BusABC) -> can.BusABC:
        self._buses.append(bus)
        return bus

    # -- running -------------------------------------------------------------

    @property
    def period(self) -> float:
        return self.axes.period

    @property
    def sim_clock(self) -> Callable[[], float] | None:
        """Simulated time [s] of a lockstep run (the first bus's); None in real time."""
        lock = next((g.lockstep for g in self.groups if g.lockstep is not None), None)
        return None if lock is None else lock.clock

    def truth(self, name: str) -> Callable[[], tuple[float, float]] | None:
        """The emulated plant's interaction torque and true position of axis ``name``."""
        process = self._processes.get(name)
        if process is not None:   # the child's plant of this node: one tick's values

            of_node: Any = process.truth

            def child() -> tuple[float, float]:
                return of_node(name)
            return child
        plant = self.plants.get(name)
        if plant is None:
            return None

        def read() -> tuple[float, float]:
            return plant.interaction_torque, plant.true_position  # type: ignore[attr-defined]
        return read

    def plant(self, name: str) -> Any:
        """The emulated plant of axis ``name`` as its truth is read (``true_position``,
        ``true_velocity``, ``motor_torque``, ``interaction_torque``): the plant stepped in
        lockstep (a coupled axis' own plant, its coupling in place), the child's plant of
        its node in real time; None for a real drive."""
        process = self._processes.get(name)
        if process is not None:
            return process.node(name).plant
        plant = self.plants.get(name)
        return getattr(plant, "plant", plant)

    def parts(self) -> list[AxisParts]:
        clocks = {name: g.lockstep.clock for g in self.groups if g.lockstep is not None for name in g.axes}
        buses = {name: g.shared for g in self.groups for name in g.axes}
        return [AxisParts(name=a.name, drive=self.drives[a.name], controller=self.controllers[a.name],
                          reference=self.references[a.name], settings=self._settings(a),
                          sink=self.sinks.get(a.name), truth=self.truth(a.name), clock=clocks.get(a.name),
                          starved=self._starved(a.name), bus=buses[a.name])
                for a in self.axes.axes]

    def _starved(self, name: str) -> Callable[[float], str] | None:
        """An emulator process says whether it was starved (the host to blame for a silence)."""
        process = self._processes.get(name)
        return None if process is None else process.starved

    def _settings(self, axis: Axis) -> LoopSettings:
        return self.settings[axis.name]

    def run(self) -> AxesResult:
        loop = AxesLoop(self.parts(), buses=self._shared,
                        lockstep=[g.lockstep for g in self.groups if g.lockstep is not None],
                        stop_request=self.stop_request)
        self.loop = loop
        try:
            return loop.run()
        finally:
            self._settle()

    def _settle(self) -> None:
        """Lockstep: the emulators read the final frames (zero torque, disable) now."""
        for emulator in self.emulators:
            if isinstance(emulator, EmulatedDrive) and self.timing is Timing.LOCKSTEP:
                try:
                    emulator.handle_pending()
                except Exception:
                    pass

    def close(self) -> None:
        """Stop the emulators, the shared periodic tasks, and shut every bus down."""
        for shared in self._shared:
            shared.shutdown()
        self._shared.clear()
        stop_and_shut(list(self.emulators), self._buses, self.shutdown_problems)

    def __enter__(self) -> AxesSession:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _frames_lost(session: AxesSession, name: str) -> int:
    """Frames the axis' view of its bus dropped, its queue full (:class:`SharedBus`: bounded,
    the loss counted): its drive read too little of what came for it."""
    for group in session.groups:
        if group.shared is not None and name in group.axes:
            return sum(view.lost for view in group.shared.views if view.name == name)
    return 0


def axes_summary(session: AxesSession, result: AxesResult) -> dict[str, Any]:
    """The ``--summary-json`` object of a run of several axes: the run's stop and shared
    timing, and per axis what a single-axis summary says of its drive and its final values."""
    per_axis: dict[str, Any] = {}
    for name, part in result.axes.items():
        report, final = part.safe_stop, final_values(part.trace)
        profile = session.profiles[name]
        per_axis[name] = {
            "protocol": profile.protocol, "node_id": profile.node_id,
            # the bus opened (an emulated run's private channel), as a single axis' summary says
            "bus": next(g.spec.describe() for g in session.groups if name in g.axes),
            "cycles": part.cycles, "drive_disabled": part.disabled,
            "drive_warning": report.warning() if report is not None else "",
            "drive_note": report.note() if report is not None else "",
            "drive_notes": list(session.drives[name].notes),
            "safe_stop": None if report is None else {
                "frames": [{"what": f.what, "sent": f.sent, "error": f.error, "refused": f.refused}
                           for f in report.frames],
                "confirmation": report.confirmation.name.lower(), "detail": report.detail,
                "planned": report.planned},
            "final": final,
            "loop_timing": {k: v for k, v in dataclasses.asdict(part.timing).items() if v is not None},
            "frames_lost": _frames_lost(session, name),
        }
    return {
        "axes": per_axis, "cycles": result.cycles, "skipped": result.skipped, "overruns": result.overruns,
        "stop_reason": result.stop.reason.name.lower(), "stop_detail": result.stop.detail,
        "stop_axis": result.axis, "drives_disabled": result.disabled,
        "not_disabled": list(result.not_disabled), "drive_warning": result.warning(),
        "timing": session.timing.label, "period": session.period,
        "buses": {g.name: list(g.axes) for g in session.groups}, "emulated": session.emulate,
        # frames a receive pass read that no axis' drive takes (another node's, foreign traffic)
        "frames_unclaimed": {g.name: g.shared.unclaimed if g.shared is not None else 0 for g in session.groups},
        "loop_timing": {k: v for k, v in dataclasses.asdict(result.timing).items() if v is not None},
    }
