"""``can.Bus(interface="dobhil", channel="demo")``: a bus with an emulated drive behind it.

:class:`DobhilBus` is a python-can bus whose only other participant is the plant
emulator of a config (drive profile, plant, environment, sensor, bus latency), running
in real time in a process of its own, exactly as ``dobhil run --emulate`` runs it
(:class:`~dobhil.emulator.process.EmulatorProcess`: a socket pair joins this bus and the
emulator; no thread here, so a program that never calls :meth:`DobhilBus.shutdown` still
ends, and the emulator with it). Any python-can program can so talk to an emulated drive
without hardware or a kernel module:

.. code-block:: console

    python -m can.viewer -i dobhil -c demo
    python -m can.logger -i dobhil -c demo -f capture.mcap
    python -m can.viewer -i dobhil -c configs/demo.yaml --bus-kwargs overrides=plant.inertia=0.1

``channel`` is a shipped config name (``demo``, ``paper/fig2c``; the default is
``demo``) or a path to a config file. ``overrides`` takes ``--set``-style
``key=value`` items: a mapping, a list of strings, or one string with items separated by
commas (the form ``--bus-kwargs`` can pass).

A config that lists ``axes:`` puts every axis' emulated drive on the one bus, in one
process on one tick clock, their plants coupled as ``environment.coupling`` says
(:class:`~dobhil.emulator.process.EmulatorProcess` with several nodes); ``axes`` (a list or
one comma-separated string, ``--bus-kwargs axes=left,right``) picks the axes of one bus when
they sit on several (:mod:`dobhil.emulator.axes_nodes`). :attr:`DobhilBus.emulator`'s
``node(name)`` has each node's truth and counters.

Each bus has its own emulated drives (and time) in its own process; :meth:`DobhilBus.shutdown`
closes this end, and the emulator's process ends.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping, Sequence
from typing import Any

import can
from can.typechecking import AutoDetectedConfig, CanFilters

from dobhil.config import Config, load_config, resolve_config
from dobhil.config.axes import SINGLE_AXIS, Axes, Coupling, has_axes, load_axes
from dobhil.data import shipped_configs
from dobhil.drives.load import load_drive_profile
from dobhil.emulator.axes_nodes import hosted_axes, node_specs
from dobhil.emulator.process import EmulatorProcess, EmulatorSpec, PlantView
from dobhil.drives.registry import emulated_protocols
from dobhil.errors import BusError, ConfigError, DobhilError

#: The channel when none is given.
DEFAULT_CONFIG = "demo"
#: Interface name (the ``can.interface`` entry point).
INTERFACE = "dobhil"

Overrides = Mapping[str, Any] | Iterable[str] | str | None


class EmulatedBusError(BusError, can.CanInitializationError):
    """The dobhil bus could not be opened (a dobhil error and a python-can one)."""


def override_items(overrides: Overrides) -> tuple[str, ...]:
    """``key=value`` strings from a mapping, a list of strings or one comma-separated string."""
    if overrides is None:
        return ()
    if isinstance(overrides, str):
        return tuple(item.strip() for item in overrides.split(",") if item.strip())
    if isinstance(overrides, Mapping):
        return tuple(f"{key}={value}" for key, value in overrides.items())
    return tuple(str(item) for item in overrides)


class DobhilBus(can.BusABC):
    """A bus with the emulated drive and plant of a config behind it, in real time."""

    def __init__(self, channel: Any = None, can_filters: CanFilters | None = None, *,
                 overrides: Overrides = None, receive_own_messages: bool = False,
                 axes: Iterable[str] | str | None = None, **kwargs: Any) -> None:
        name = DEFAULT_CONFIG if channel is None else str(channel)
        try:
            path = resolve_config(name)
            specs, couplings = self._nodes(path, override_items(overrides), axes)
        except DobhilError as exc:
            raise EmulatedBusError(f"dobhil bus {name!r}: {exc}") from None
        self._name = name
        self._closed = True   # until the emulator runs: shutdown() has nothing to stop
        self.channel_info = f"dobhil emulated {_described(specs)} of {path}"
        try:
            self.emulator: EmulatorProcess = EmulatorProcess(
                specs, channel=name, receive_own_messages=receive_own_messages, couplings=couplings)
        except DobhilError as exc:
            raise EmulatedBusError(f"dobhil bus {name!r}: {exc}") from None
        self._host = self.emulator.bus
        self._can_protocol = self._host.protocol   # CAN FD: the pipe carries FD frames
        self._closed = False
        try:
            super().__init__(channel=name, can_filters=can_filters, **kwargs)
        except BaseException:
            self.shutdown()
            raise

    def _nodes(self, path: Any, overrides: tuple[str, ...], axes: Iterable[str] | str | None
               ) -> tuple[list[EmulatorSpec], tuple[Coupling, ...]]:
        """The nodes of the config at ``path``: its one drive, or the axes of one bus."""
        if not has_axes(path):
            if axes is not None:
                raise ConfigError(f"axes={axes!r}: {path} lists no axes (a single-axis config); drop axes")
            self.config: Config = load_config(path, overrides)
            self.axes: Axes | None = None
            profile = load_drive_profile(self.config, path.parent)
            if profile.protocol not in emulated_protocols():
                raise ConfigError(f"no emulator for protocol {profile.protocol!r}; "
                                  f"emulated: {', '.join(emulated_protocols())}")
            return [EmulatorSpec.of(self.config, profile)], ()
        self.axes = load_axes(path, overrides)
        names = override_items(axes) if axes is not None else ()
        hosted = hosted_axes(self.axes, names, how="axes=NAME,NAME (--bus-kwargs axes=...)")
        self.config = hosted[0].config
        return node_specs(self.axes, hosted, path.parent)

    @property
    def plant(self) -> PlantView:
        """The emulated plant's ground truth (``true_position``, ``interaction_torque``, ...),
        as the emulator's process published it after its newest tick."""
        return self.emulator.plant

    #: periodic frames (a CiA 402 SYNC) are sent by the emulator's process on its own clock
    #: and echoed back, as SocketCAN's broadcast manager does (dobhil.drives.periodic)
    native_periodic = True

    def _send_periodic_internal(
        self, msgs: Sequence[can.Message] | can.Message, period: float, duration: float | None = None,
        autostart: bool = True, modifier_callback: Callable[[can.Message], None] | None = None,
    ) -> can.broadcastmanager.CyclicSendTaskABC:
        return self._host.send_periodic(msgs, period, duration, autostart=autostart,
                                        modifier_callback=modifier_callback)

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        return self._host.recv(timeout), False

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self._host.send(msg, timeout)

    def shutdown(self) -> None:
        """Close this end of the bus; the emulator's process ends (joined, killed if it does not)."""
        if self._closed:
            can.BusABC.shutdown(self)   # a no-op unless BusABC.__init__ ran
            return
        self._closed = True
        try:
            super().shutdown()
        finally:
            self.emulator.close()

    @staticmethod
    def _detect_available_configs() -> Sequence[AutoDetectedConfig]:
        return [{"interface": INTERFACE, "channel": name} for name in shipped_configs()]


def _described(specs: Sequence[EmulatorSpec]) -> str:
    """``PROTOCOL (firmware F, node N)``, or each axis' ``NAME: PROTOCOL ...`` for several."""
    def one(spec: EmulatorSpec) -> str:
        p = spec.profile
        return f"{p.protocol} (firmware {p.firmware}, node {p.node_id})"
    if len(specs) == 1 and specs[0].name == SINGLE_AXIS:
        return one(specs[0])
    return ", ".join(f"{s.name}: {one(s)}" for s in specs)


__all__ = ["DEFAULT_CONFIG", "DobhilBus", "EmulatedBusError", "override_items"]
