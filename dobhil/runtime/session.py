"""A run put together from a config: buses, (emulated) drive, controller, reference, loop.

:class:`RunSession` owns everything it opens -- buses, the emulator and its thread --
and closes all of it, whatever happens (context manager). With ``emulate`` the plant
emulator runs in this process on a private python-can ``virtual`` channel; with
``lockstep`` the host bus is a :class:`~dobhil.emulator.protocol.LockstepBus` and the
whole run is deterministic.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from pathlib import Path
from typing import Any

import can

from dobhil.config.schema import Config
from dobhil.drives.base import Drive
from dobhil.drives.profile import DriveProfile, load_profile
from dobhil.drives.registry import make_drive
from dobhil.emulator.plant import Plant
from dobhil.emulator.protocol import EmulatedDrive, LockstepBus
from dobhil.emulator.registry import make_emulated_drive
from dobhil.errors import ConfigError
from dobhil.runtime.buses import BusSpec, open_bus, private_virtual_channel, resolve_bus
from dobhil.runtime.controller import ForceController
from dobhil.runtime.loop import (CycleSink, ForceLoop, Limits, LoopSettings, RunResult, StopRequest,
                                 Timing)
from dobhil.runtime.references import make_reference
from dobhil.synthesis.controller import sampled_controller
from dobhil.synthesis.params import params_from_config


def load_drive_profile(config: Config, base_dir: Path | None = None) -> DriveProfile:
    name = config.drive.profile
    candidate = (base_dir / name) if base_dir and not Path(name).is_absolute() else Path(name)
    return load_profile(str(candidate) if candidate.suffix in (".yaml", ".yml") and candidate.exists()
                        else name)


def check_rates(profile: DriveProfile, period: float) -> None:
    """The drive must send feedback at least once per control period."""
    if profile.encoder_msg_rate > period * (1 + 1e-9):
        raise ConfigError(
            f"drive profile {profile.name or profile.protocol!r} sends encoder estimates every "
            f"{profile.encoder_msg_rate:g} s, slower than loop.period = {period:g} s; set its "
            f"encoder_msg_rate (and the drive's) to the loop period")


def build_controller(config: Config, profile: DriveProfile) -> ForceController:
    """The runtime controller: the sampled synthesis, saturated at the tighter torque limit."""
    limit = min(config.loop.torque_limit, profile.torque_limit)
    return ForceController(sampled_controller(params_from_config(config)), torque_limit=limit)


def loop_settings(config: Config, timing: Timing, duration: float | None) -> LoopSettings:
    lp = config.loop
    return LoopSettings(period=lp.period, duration=duration or lp.duration,
                        feedback_timeout=lp.feedback_timeout, timing=timing,
                        limits=Limits(lp.position_min, lp.position_max, lp.velocity_limit))


class RunSession:
    """Everything one run needs; ``with RunSession(...) as s: result = s.run()``."""

    def __init__(self, config: Config, *, bus: str | None = None, emulate: bool = False,
                 lockstep: bool | None = None, duration: float | None = None,
                 config_dir: Path | None = None, sink: CycleSink | None = None,
                 stop_request: StopRequest | None = None,
                 bus_wrapper: Callable[[can.BusABC], can.BusABC] | None = None) -> None:
        lockstep = (config.loop.timing == "lockstep") if lockstep is None else lockstep
        if lockstep and not emulate:
            raise ConfigError("lockstep timing needs the in-process emulator (--emulate); "
                              "a real drive runs in real time")
        if duration is not None and not duration > 0:
            raise ConfigError(f"--duration {duration!r}: must be > 0")
        self.config = config
        self.profile = load_drive_profile(config, config_dir)
        check_rates(self.profile, config.loop.period)
        self.timing = Timing.LOCKSTEP if lockstep else Timing.REALTIME
        self.settings = loop_settings(config, self.timing, duration)
        self.controller = build_controller(config, self.profile)
        self.reference = make_reference(config.reference, config_dir,
                                        duration=self.settings.duration)
        self.sink = sink
        self.stop_request = stop_request or StopRequest()
        self.plant: Plant | None = None
        self.emulator: EmulatedDrive | None = None
        self._buses: list[can.BusABC] = []
        self._wrapper = bus_wrapper
        self.bus_spec = (BusSpec("virtual", private_virtual_channel()) if emulate
                         else resolve_bus(config, self.profile, bus))
        try:
            self.drive = self._open(emulate)
        except BaseException:
            self.close()
            raise

    # -- building ------------------------------------------------------------

    def _open(self, emulate: bool) -> Drive:
        host = self._add(open_bus(self.bus_spec))
        clock: dict[str, Any] = {}
        if emulate:
            self.plant = Plant.from_config(self.config)
            emu_bus = self._add(open_bus(self.bus_spec))
            d = self.config.drive
            self.emulator = make_emulated_drive(emu_bus, self.profile, self.plant,
                                                latency=0.0 if self.timing is Timing.LOCKSTEP else d.latency,
                                                jitter=0.0 if self.timing is Timing.LOCKSTEP else d.jitter,
                                                seed=self.config.sensor.seed)
            if self.timing is Timing.LOCKSTEP:
                lock = LockstepBus(host, [self.emulator], dt=self.config.loop.period)
                self._add(lock)
                host = lock
                clock["clock"] = lock.clock
            else:
                self.emulator.start()
        if self._wrapper is not None:
            host = self._add(self._wrapper(host))
        self.host_bus = host
        self._clock = clock.get("clock")
        return make_drive(host, self.profile, **clock)

    def _add(self, bus: can.BusABC) -> can.BusABC:
        self._buses.append(bus)
        return bus

    @property
    def sim_clock(self) -> Callable[[], float] | None:
        """Simulated time [s] of a lockstep run (the log clock); None in real time."""
        return self._clock

    # -- running -------------------------------------------------------------

    def truth(self) -> tuple[float, float]:
        assert self.plant is not None
        return self.plant.interaction_torque, self.plant.true_position

    def run(self) -> RunResult:
        loop = ForceLoop(drive=self.drive, controller=self.controller, reference=self.reference,
                         settings=self.settings, sink=self.sink, stop_request=self.stop_request,
                         truth=self.truth if self.plant is not None else None,
                         **({"clock": self._clock} if self._clock else {}))
        try:
            return loop.run()
        finally:
            self._settle()

    def _settle(self) -> None:
        """Lockstep: the emulator reads the final frames (zero torque, disable) now, so its
        state after the run is what the drive would be in; real time does this by itself."""
        if self.timing is Timing.LOCKSTEP and self.emulator is not None:
            try:
                self.emulator.handle_pending()
            except Exception:
                pass

    def close(self) -> None:
        """Stop the emulator thread and shut every bus down (never raises twice)."""
        errors: list[BaseException] = []
        if self.emulator is not None:
            try:
                self.emulator.stop()
            except BaseException as exc:
                errors.append(exc)
        for bus in reversed(self._buses):
            try:
                bus.shutdown()
            except Exception as exc:
                errors.append(exc)
        self._buses.clear()
        if errors:
            raise errors[0]

    def __enter__(self) -> RunSession:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def summary(session: RunSession, result: RunResult) -> dict[str, Any]:
    """The ``--summary-json`` object."""
    tr = result.trace
    last = tr.n - 1
    final = {"tau_ref": None, "tau_int_hat": None, "tau_int_true": None, "q": None}
    if last >= 0:
        d = tr.data
        true = float(d["tau_int_true"][last])
        final = {"tau_ref": float(d["tau_ref"][last]), "tau_int_hat": float(d["tau_int_hat"][last]),
                 "tau_int_true": None if true != true else true, "q": float(d["q"][last])}
    return {
        "cycles": result.cycles, "overruns": result.overruns,
        "stop_reason": result.stop.reason.name.lower(), "stop_detail": result.stop.detail,
        "drive_disabled": result.disabled,
        "timing": "lockstep" if session.timing is Timing.LOCKSTEP else "realtime",
        "period": session.settings.period, "bus": session.bus_spec.describe(),
        "emulated": session.emulator is not None,
        "watchdog_tripped": bool(getattr(session.emulator, "watchdog_tripped", False)),
        "final": final,
        "loop_timing": dataclasses.asdict(result.timing),
    }
