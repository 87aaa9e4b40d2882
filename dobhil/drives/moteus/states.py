"""A moteus controller's mode and fault codes in words (``docs/protocol/registers.md``
0x000 and 0x00f), and whether a bus carries CAN FD."""

from __future__ import annotations

import can

from dobhil.drives.moteus.codec import Fault, Mode

__all__ = ["bus_is_classic", "fault_text", "mode_text"]


def mode_text(code: int) -> str:
    """``"POSITION"`` for 10; the number for a code the enum does not name."""
    try:
        return Mode(code).name
    except ValueError:
        return f"mode {code}"


def fault_text(code: int) -> str:
    """``"39 (START_OUTSIDE_LIMIT)"``; ``"0 (none)"``."""
    if code == 0:
        return "0 (none)"
    try:
        return f"{code} ({Fault(code).name})"
    except ValueError:
        return f"{code}"


def bus_is_classic(bus: can.BusABC) -> bool:
    """True when the bus says it runs classic CAN (python-can's ``BusABC.protocol``)."""
    proto = getattr(bus, "protocol", None)
    return proto is can.CanProtocol.CAN_20
