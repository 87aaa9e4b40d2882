"""Opening python-can buses by interface name, with one-line errors."""

from __future__ import annotations

import uuid
from dataclasses import dataclass, field
from typing import Any

import can

from dobhil.config.schema import Config
from dobhil.drives.profile import DriveProfile
from dobhil.errors import BusError, ConfigError


@dataclass(frozen=True)
class BusSpec:
    """Which bus: a python-can interface name, a channel and extra ``can.Bus`` arguments."""

    interface: str
    channel: str
    kwargs: dict[str, Any] = field(default_factory=dict)

    @classmethod
    def parse(cls, text: str, **kwargs: Any) -> BusSpec:
        """``INTERFACE:CHANNEL`` (the channel may itself hold colons, e.g. a URL)."""
        interface, sep, channel = text.partition(":")
        if not sep or not interface:
            raise ConfigError(f"--bus {text!r}: expected INTERFACE:CHANNEL, e.g. socketcan:can0 "
                              f"or virtual:test; interfaces: {', '.join(sorted(can.VALID_INTERFACES))}")
        return cls(interface, channel, kwargs)

    def describe(self) -> str:
        return f"{self.interface}:{self.channel}"


def resolve_bus(config: Config, profile: DriveProfile, cli: str | None) -> BusSpec:
    """``--bus`` first, then ``drive.interface``/``drive.channel``, then the profile's bus."""
    extra = {k: v for k, v in profile.bus_kwargs().items() if k not in ("interface", "channel")}
    if config.drive.bitrate:
        extra["bitrate"] = config.drive.bitrate
    if cli:
        return BusSpec.parse(cli, **extra)
    if config.drive.interface:
        return BusSpec(config.drive.interface, config.drive.channel, extra)
    bus = profile.bus_kwargs()
    if "interface" not in bus:
        raise ConfigError(f"no bus given: use --bus INTERFACE:CHANNEL, drive.interface, or a bus: "
                          f"section in the drive profile {profile.name!r}")
    return BusSpec(str(bus["interface"]), str(bus.get("channel", "")), extra)


def open_bus(spec: BusSpec) -> can.BusABC:
    """Open the bus or raise BusError naming it and what went wrong, in one line."""
    if spec.interface not in can.VALID_INTERFACES:
        raise BusError(f"bus {spec.describe()}: unknown python-can interface {spec.interface!r}; "
                       f"known: {', '.join(sorted(can.VALID_INTERFACES))}")
    kwargs = dict(spec.kwargs)
    if spec.interface in ("virtual", "remote"):
        kwargs.pop("bitrate", None) if spec.interface == "virtual" else None
    try:
        return can.Bus(interface=spec.interface, channel=spec.channel, **kwargs)
    except Exception as exc:
        text = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise BusError(f"bus {spec.describe()} cannot be opened: {text}") from None


def private_virtual_channel() -> str:
    """A virtual-bus channel name no other run in this process uses.

    It ends in a letter: python-can's log writers read trailing digits of a channel name
    as the channel number (``can.util.channel2int``), and BLF stores it in 16 bits, so a
    name ending in many digits would make ``can.logconvert run.mcap run.blf`` fail."""
    return f"dobhil-{uuid.uuid4().hex[:12]}-private"
