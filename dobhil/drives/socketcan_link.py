"""What the Linux kernel says about a SocketCAN interface, for the preflight.

python-can's SocketCAN bus does not report the controller state (``bus.state`` is always
ACTIVE there), the bit rate or the transmit queue length; the kernel does, through
``ip -details -json link show CHANNEL`` (iproute2). Written by hand because no library
in the dependency set reads it: this module runs that command once, parses its JSON
(:func:`parse_link`, pure, tested against literal output) and turns it into findings:

- the interface down (no ``UP`` among its flags): nothing can be sent (``send()`` fails with
  ENETDOWN) nor heard on it;
- controller state other than ERROR-ACTIVE (ERROR-WARNING, ERROR-PASSIVE, BUS-OFF);
- ``txqueuelen`` below 100: a burst fills SocketCAN's default queue of 10 and ``send()``
  fails at once with ENOBUFS;
- ``restart-ms`` 0: after a bus-off the controller stays off until someone resets it;
- the bit rate, used for the bus load instead of ``drive.bitrate`` and compared with it.

A virtual interface (vcan) has no controller: only the queue length applies.
"""

from __future__ import annotations

import json
import shutil
import subprocess
from dataclasses import dataclass
from typing import Any

import can

__all__ = ["LinkInfo", "link_down_text", "link_info", "link_problems", "parse_link"]

#: below this, bursts overflow the queue (ENOBUFS)
MIN_TXQUEUELEN = 100


@dataclass(frozen=True)
class LinkInfo:
    name: str
    kind: str                # "can", "vcan", ...
    txqueuelen: int | None
    state: str | None        # "ERROR-ACTIVE", "BUS-OFF", ... (None: no controller)
    bitrate: int | None
    restart_ms: int | None
    up: bool | None = None   # administratively up ("UP" among the flags); None: not said


def parse_link(text: str) -> LinkInfo | None:
    """The first interface of ``ip -details -json link show`` output; None if unreadable."""
    try:
        data = json.loads(text)
        entry: dict[str, Any] = data[0]
        info = entry.get("linkinfo", {}) or {}
        details = info.get("info_data", {}) or {}
        bittiming = details.get("bittiming", {}) or {}
        return LinkInfo(
            name=str(entry.get("ifname", "")), kind=str(info.get("info_kind", "")),
            txqueuelen=_int(entry.get("txqlen")), state=details.get("state"),
            bitrate=_int(bittiming.get("bitrate")), restart_ms=_int(details.get("restart_ms")),
            up=_flag(entry.get("flags"), "UP"),
        )
    except (ValueError, LookupError, TypeError, AttributeError):
        return None


def _flag(flags: Any, name: str) -> bool | None:
    """Whether ``name`` is among an interface's ``flags`` (None: no list of flags)."""
    return name in flags if isinstance(flags, list) else None


def _int(value: Any) -> int | None:
    return int(value) if isinstance(value, (int, float)) and not isinstance(value, bool) else None


def link_info(bus: can.BusABC, timeout: float = 1.0) -> LinkInfo | None:
    """Kernel facts about ``bus`` if it is a SocketCAN bus and ``ip`` is there, else None."""
    try:
        from can.interfaces.socketcan import SocketcanBus
    except ImportError:  # pragma: no cover - python-can always ships it
        return None
    channel = getattr(bus, "channel", None)
    ip = shutil.which("ip")
    if not isinstance(bus, SocketcanBus) or not isinstance(channel, str) or ip is None:
        return None
    try:
        done = subprocess.run([ip, "-details", "-json", "link", "show", channel], capture_output=True,
                              text=True, timeout=timeout, check=False)
    except (OSError, subprocess.SubprocessError):
        return None
    return parse_link(done.stdout) if done.returncode == 0 else None


def link_down_text(name: str) -> str:
    """The one line for an interface that is down."""
    return f"{name} is down: nothing can be sent or heard on it; sudo ip link set {name} up"


def link_problems(link: LinkInfo, expected_bitrate: int | None) -> list[tuple[bool, str]]:
    """(is a mismatch, text) per problem; notes have False. An interface that is down is
    the only problem said: nothing else about it can be measured or matters first."""
    out: list[tuple[bool, str]] = []
    name = link.name
    if link.up is False:
        return [(True, link_down_text(name))]
    if link.state is not None and link.state != "ERROR-ACTIVE":
        out.append((True, f"{name} is {link.state}: check wiring, termination (120 ohm at both ends) "
                          f"and bit rate; then sudo ip link set {name} down && sudo ip link set {name} up"))
    if link.txqueuelen is not None and link.txqueuelen < MIN_TXQUEUELEN:
        out.append((True, f"{name} txqueuelen {link.txqueuelen}: bursts fail with ENOBUFS; "
                          f"sudo ip link set {name} txqueuelen 1000"))
    if link.kind == "can" and link.restart_ms == 0:
        out.append((False, f"{name} has restart-ms 0: after a bus-off it stays off; "
                           f"sudo ip link set {name} type can restart-ms 100 (interface down)"))
    if link.bitrate and expected_bitrate and link.bitrate != expected_bitrate:
        out.append((True, f"{name} runs at {link.bitrate} bit/s, drive.bitrate is {expected_bitrate}: "
                          "set the interface and the drive to the same bit rate (and drive.bitrate)"))
    return out
