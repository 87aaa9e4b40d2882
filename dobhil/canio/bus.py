"""``can.Bus(interface="dobhil", channel="demo")``: a bus with an emulated drive behind it.

:class:`DobhilBus` is a python-can bus whose only other participant is the plant
emulator of a config (drive profile, plant, environment, sensor, bus latency), running
in real time on a thread of its own, exactly as ``dobhil run --emulate`` runs it: a
private ``virtual`` channel joins this bus and the emulator. Any python-can program
can so talk to an emulated drive without hardware or a kernel module:

.. code-block:: console

    python -m can.viewer -i dobhil -c demo
    python -m can.logger -i dobhil -c demo -f capture.mcap
    python -m can.viewer -i dobhil -c configs/demo.yaml --bus-kwargs overrides=plant.inertia=0.1

``channel`` is a shipped config name (``demo``, ``paper/fig2c``; the default is
``demo``) or a path to a config file. ``overrides`` takes ``--set``-style
``key=value`` items: a mapping, a list of strings, or one string with items separated by
commas (the form ``--bus-kwargs`` can pass).

Each bus has its own emulated drive (and time); :meth:`DobhilBus.shutdown` stops the
emulator's thread and closes both ends of the private channel.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from typing import Any

import can
from can.interfaces.virtual import VirtualBus
from can.typechecking import AutoDetectedConfig, CanFilters

from dobhil.config import Config, load_config, resolve_config
from dobhil.data import shipped_configs
from dobhil.drives.profile import load_drive_profile
from dobhil.emulator.plant import Plant
from dobhil.emulator.protocol import EmulatedDrive
from dobhil.emulator.registry import make_emulated_drive, private_virtual_channel
from dobhil.errors import BusError, DobhilError

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
                 overrides: Overrides = None, receive_own_messages: bool = False, **kwargs: Any) -> None:
        name = DEFAULT_CONFIG if channel is None else str(channel)
        try:
            path = resolve_config(name)
            self.config: Config = load_config(path, override_items(overrides))
            profile = load_drive_profile(self.config, path.parent)
            plant = Plant.from_config(self.config)
        except DobhilError as exc:
            raise EmulatedBusError(f"dobhil bus {name!r}: {exc}") from None
        self._name = name
        self._closed = False
        self.channel_info = (f"dobhil emulated {profile.protocol} (firmware {profile.firmware}, "
                             f"node {profile.node_id}) of {path}")
        private = private_virtual_channel()
        self._host = VirtualBus(private, receive_own_messages=receive_own_messages)
        emulator_bus = VirtualBus(private)
        emulator: EmulatedDrive | None = None
        try:
            drive = self.config.drive
            emulator = make_emulated_drive(emulator_bus, profile, plant, latency=drive.latency,
                                           jitter=drive.jitter, seed=self.config.sensor.seed)
            self.emulator: EmulatedDrive = emulator
            super().__init__(channel=name, can_filters=can_filters, **kwargs)
            emulator.start()
        except BaseException as exc:
            self._closed = True
            can.BusABC.shutdown(self)   # a no-op unless BusABC.__init__ ran
            try:
                if emulator is not None:
                    emulator.close()   # stops its thread (if started), shuts its bus down
                else:
                    emulator_bus.shutdown()
            finally:
                self._host.shutdown()
            if isinstance(exc, DobhilError):
                raise EmulatedBusError(f"dobhil bus {name!r}: {exc}") from None
            raise

    @property
    def plant(self) -> Any:
        """The emulated plant (ground truth: ``true_position``, ``interaction_torque``, ...)."""
        return self.emulator.plant

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        msg = self._host.recv(timeout)
        if msg is not None:
            msg.channel = self._name
        return msg, False

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self._host.send(msg, timeout)

    def shutdown(self) -> None:
        """Stop the emulator thread (re-raising what it raised) and close the channel."""
        if self._closed:
            return
        self._closed = True
        super().shutdown()
        try:
            self.emulator.close()
        finally:
            self._host.shutdown()

    @staticmethod
    def _detect_available_configs() -> Sequence[AutoDetectedConfig]:
        return [{"interface": INTERFACE, "channel": name} for name in shipped_configs()]


__all__ = ["DEFAULT_CONFIG", "DobhilBus", "EmulatedBusError", "override_items"]
