"""Opening python-can buses by interface name, with one-line errors."""

from __future__ import annotations

import logging
import threading
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, Final

import can

from dobhil.config.schema import Config
from dobhil.drives.profile import DriveProfile
from dobhil.errors import BusError, ConfigError, exception_line


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


def shared_spec(specs: Sequence[BusSpec]) -> BusSpec:
    """The one bus several drives share (``specs``: each drive's :func:`resolve_bus`, all
    naming that bus): the first's interface and channel, with the ``can.Bus`` arguments of
    every drive on it -- a CAN FD drive's profile asks for ``fd`` whichever axis is listed
    first, and a classic drive's frames travel on a CAN FD bus too (where two drives give
    one argument two values, the first's; two bit rates on one bus are refused before,
    :func:`dobhil.drives.axes.axis_drives`)."""
    kwargs: dict[str, Any] = {}
    for spec in specs:
        for key, value in spec.kwargs.items():
            kwargs.setdefault(key, value)
    return BusSpec(specs[0].interface, specs[0].channel, kwargs)


def open_bus(spec: BusSpec) -> can.BusABC:
    """Open the bus or raise BusError naming it and what went wrong, in one line."""
    if spec.interface not in can.VALID_INTERFACES:
        raise BusError(f"bus {spec.describe()}: unknown python-can interface {spec.interface!r}; "
                       f"known: {', '.join(sorted(can.VALID_INTERFACES))}")
    kwargs = dict(spec.kwargs)
    if spec.interface in ("virtual", "remote"):
        kwargs.pop("bitrate", None) if spec.interface == "virtual" else None
    error: Exception | None = None
    with _CaughtWarnings() as caught:  # python-can logs a missing driver library on import
        try:
            bus = can.Bus(interface=spec.interface, channel=spec.channel, **kwargs)
        except Exception as exc:
            text = exception_line(exc, named=False)
            error = exc
    if error is None:  # opened after all: what python-can warned of still matters (timestamps ...)
        for line in caught.lines:
            logging.getLogger("can").warning("%s", line)
        return bus
    hint = "" if spec.interface in _SOFTWARE_BUSES else f" ({NO_HARDWARE_HINT})"
    raise BusError(f"bus {spec.describe()} cannot be opened: {_explain(spec.interface, text, caught.lines)}"
                   f"{hint}") from error


#: python-can interfaces that need no CAN hardware (dobhil's emulated drive, in-process, a hub)
_SOFTWARE_BUSES: Final = frozenset({"dobhil", "virtual", "remote", "udp_multicast"})
#: said when a hardware bus cannot be opened: the way to try dobhil without one
NO_HARDWARE_HINT: Final = ("no CAN hardware here? --bus dobhil:demo is a bus with the emulated drive "
                           "on it; dobhil run --emulate runs the emulator itself")


#: what to install when an interface's driver library is missing (python-can's own wording
#: names the library, not how to get it)
_INSTALL_HINTS: dict[str, str] = {
    "pcan": "install PEAK-System's PCAN-Basic library (libpcanbasic)",
    "kvaser": "install Kvaser CANlib (libcanlib)",
    "serial": "pip install pyserial", "slcan": "pip install pyserial",
    "seeedstudio": "pip install pyserial", "robotell": "pip install pyserial",
    "cantact": "pip install cantact", "gs_usb": "pip install gs_usb", "neovi": "pip install python-ics",
    "canalystii": "pip install canalystii",
}


def _explain(interface: str, text: str, warned: list[str]) -> str:
    """python-can's error, the warnings it logged while loading the interface, and a hint."""
    def missing(t: str) -> bool:
        return any(k in t.lower() for k in ("not found", "not installed", "unavailable", "no module",
                                            "cannot import", "without the"))
    # the warnings matter when the error itself is obscure (kvaser: "name ... is not defined")
    notes = [] if missing(text) else [w for w in dict.fromkeys(warned) if w.lower() not in text.lower()]
    line = text.rstrip(".") + "".join(f"; {n.rstrip('.')}" for n in notes)
    hint = _INSTALL_HINTS.get(interface) if missing(line) else None
    return f"{line} ({hint})" if hint else line


class _CaughtWarnings(logging.Handler):
    """Collects the log records python-can emits while a bus opens, instead of letting
    Python's last-resort handler print them to stderr above dobhil's own one line."""

    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.lines: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.lines.append(" ".join(record.getMessage().split()))

    def __enter__(self) -> _CaughtWarnings:
        # on the root logger: python-can's interfaces log under "can.*" and some under their
        # own names ("seeedbus"); a handler here also keeps the last-resort print away
        logging.getLogger().addHandler(self)
        return self

    def __exit__(self, *exc: object) -> None:
        logging.getLogger().removeHandler(self)


#: seconds a bus's shutdown may take before it is given up (a python-can-remote bus whose
#: hub is frozen waits for the hub's close answer for ever)
SHUTDOWN_TIMEOUT = 2.0


def shutdown_bus(bus: can.BusABC, timeout: float = SHUTDOWN_TIMEOUT) -> str:
    """Shut ``bus`` down; "" if that went well, else one line saying what failed. Never
    raises and never takes longer than ``timeout`` s: a bus whose link is already gone
    fails its own shutdown (python-can-remote with its hub stopped: ENOTCONN) or waits
    for ever (its hub frozen), and neither may hide how the run ended. The shutdown runs
    on a daemon thread (left behind if it hangs: the process still exits); after a
    failure the base class's shutdown runs on its own, so python-can does not try again
    (and print a traceback) when the object is collected."""
    outcome: list[str] = []

    def shut() -> None:
        try:
            bus.shutdown()
            outcome.append("")
        except Exception as exc:
            outcome.append(exception_line(exc))

    thread = threading.Thread(target=shut, name="dobhil-bus-shutdown", daemon=True)
    thread.start()
    thread.join(timeout)
    problem = outcome[0] if outcome else f"shutdown did not finish within {timeout:g} s"
    if problem:
        try:
            can.BusABC.shutdown(bus)
        except Exception:
            pass
    return problem
