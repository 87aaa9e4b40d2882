"""``[HOST:]PORT`` of the live view, bound to the loopback interface unless a host is given."""

from __future__ import annotations

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


__all__ = ["DEFAULT_HOST", "LiveAddress", "LiveAddressError", "parse_live_address"]
