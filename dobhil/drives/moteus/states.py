"""A moteus controller's mode and fault codes in words (``docs/protocol/registers.md``
0x000 and 0x00f)."""

from __future__ import annotations

from dobhil.drives.moteus.codec import Fault, Mode

__all__ = ["fault_text", "mode_text"]


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

