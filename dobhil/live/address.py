"""``[HOST:]PORT`` of the live view, bound to the loopback interface unless a host is given."""

from __future__ import annotations

import errno
import ipaddress
import socket
from typing import Final, NamedTuple

from dobhil.errors import ConfigError

#: Host bound when the address names only a port.
DEFAULT_HOST: Final = "127.0.0.1"
_ALLOWED: Final = "expected [HOST:]PORT, e.g. 8765, 127.0.0.1:8765 or [::1]:8765, with PORT 0..65535 (0: any free)"


class LiveAddressError(ConfigError):
    """A ``--live`` address is not ``[HOST:]PORT``."""


class LiveAddress(NamedTuple):
    """Where the live view listens; unpacks as ``host, port``."""

    host: str
    port: int


def _fail(text: str, why: str) -> LiveAddressError:
    return LiveAddressError(f"--live {text!r}: {why}; {_ALLOWED}")


def _port(text: str, port: str) -> int:
    if not port.isascii() or not port.isdigit():
        raise _fail(text, f"port {port!r} is not a number")
    value = int(port)
    if value > 65535:
        raise _fail(text, f"port {value} is out of range")
    return value


def _split(text: str) -> tuple[str, str]:
    """(host, port) strings; host is '' when only a port is given."""
    if text.startswith("["):
        host, sep, port = text[1:].partition("]:")
        if not sep or not host:
            raise _fail(text, "a bracketed IPv6 host must look like [::1]:PORT")
        return host, port
    host, sep, port = text.rpartition(":")
    if not sep:
        return "", text
    if not host or ":" in host:
        raise _fail(text, "empty host" if not host else "an IPv6 host needs brackets")
    return host, port


def parse_live_address(text: str) -> LiveAddress:
    """``"8765"`` -> (127.0.0.1, 8765); ``"HOST:PORT"`` and ``"[IPv6]:PORT"`` bind HOST.

    Raises :class:`LiveAddressError` (a :class:`~dobhil.errors.ConfigError`) with one
    line naming what was wrong and what is allowed.
    """
    text = text.strip()
    if not text:
        raise _fail(text, "empty address")
    host, port = _split(text)
    if any(c.isspace() for c in host) or "/" in host:
        raise _fail(text, f"host {host!r} is not a host name or address")
    return LiveAddress(host or DEFAULT_HOST, _port(text, port))


def _resolved(address: LiveAddress) -> list[tuple[int, tuple[str, int]]]:
    """(family, sockaddr) of each address the host names; one line if it names none."""
    try:
        infos = socket.getaddrinfo(address.host, address.port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
    except (socket.gaierror, UnicodeError) as exc:
        why = exc.strerror if isinstance(exc, socket.gaierror) and exc.strerror else str(exc)
        raise _fail(shown(address), f"host {address.host!r} is not known ({why})") from None
    return [(family, (str(sockaddr[0]), int(sockaddr[1]))) for family, _, _, _, sockaddr in infos]


def check_bindable(address: LiveAddress) -> None:
    """Raise :class:`LiveAddressError` (one line) unless the live view can listen at ``address``.

    Checked before a run opens its log: the server itself starts in the log's writer, and
    a refusal there would leave a log with no run in it. A socket is bound and closed at
    once, with SO_REUSEADDR as the server's own listener sets it (so a port whose last
    connections linger in TIME_WAIT is free, as it is to the server). A port taken between
    this check and the server's start is still reported, only later.
    """
    family, sockaddr = _resolved(address)[0]
    try:
        with socket.socket(family, socket.SOCK_STREAM) as probe:
            probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            probe.bind(sockaddr)
            probe.listen(1)  # a port in use by a listener fails here on some systems, at bind on Linux
    except OSError as exc:
        why = exc.strerror or type(exc).__name__
        hint = "; pick another port, or 0 for any free one" if exc.errno == errno.EADDRINUSE else ""
        raise LiveAddressError(f"--live {shown(address)}: cannot listen there: {why}{hint}") from None


def is_loopback(host: str) -> bool:
    """True if every address ``host`` names is a loopback address (127.0.0.0/8, ::1).

    0.0.0.0 and :: mean every interface: not loopback. A name that does not resolve is
    not loopback either (the caller reports it as unknown)."""
    try:
        infos = socket.getaddrinfo(host, None, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
    except (socket.gaierror, UnicodeError):
        return False
    addresses = {str(info[4][0]).split("%", 1)[0] for info in infos}
    return bool(addresses) and all(ipaddress.ip_address(a).is_loopback for a in addresses)


def exposure_warning(address: LiveAddress) -> str | None:
    """The one line to print when the live view listens beyond this machine (None on loopback)."""
    if is_loopback(address.host):
        return None
    everywhere = " (every network interface)" if address.host in ("0.0.0.0", "::") else ""
    return (f"the live view on {shown(address)}{everywhere} shows this run to anyone who can reach this "
            "machine there, with no password; it is read-only (no publishing, services or parameters); "
            f"use {DEFAULT_HOST} to keep it to this machine")


def shown(address: LiveAddress) -> str:
    """``HOST:PORT``, an IPv6 host in brackets."""
    return f"[{address.host}]:{address.port}" if ":" in address.host else f"{address.host}:{address.port}"


__all__ = ["DEFAULT_HOST", "LiveAddress", "LiveAddressError", "check_bindable", "exposure_warning", "is_loopback",
           "parse_live_address", "shown"]
