"""How many bits a CAN frame takes on the wire: the one formula the preflight's measured
bus load and the run report's bus load both use."""

from __future__ import annotations


def frame_bits(dlc: int, extended: bool = False) -> int:
    """Bits on the wire of a classic data frame incl. worst-case stuffing (EOF, IFS included)."""
    base, stuffable = (67, 54) if extended else (47, 34)
    return base + 8 * dlc + (stuffable + 8 * dlc - 1) // 4


__all__ = ["frame_bits"]
