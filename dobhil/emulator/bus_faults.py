"""Faults of the bus itself, for :class:`~dobhil.emulator.faults.FaultyBus`: the bus
refuses frames (ENOBUFS: the transmit queue is full) or the interface goes away (a USB
adapter unplugged, ``ip link set can0 down``: every send and receive fails).

They raise what python-can raises in those cases, ``can.CanOperationError`` carrying
the errno, from the wrapped bus's ``send`` / ``recv``, so the host sees exactly what a
real interface would give it.
"""

from __future__ import annotations

import errno
import os
from collections.abc import Collection, Sequence
from typing import ClassVar

import can

from dobhil.emulator.faults import Direction, Fault

__all__ = ["InterfaceGone", "RefuseSend"]


def _error(code: int, what: str) -> can.CanOperationError:
    return can.CanOperationError(f"{what}: [Errno {code}] {os.strerror(code)}", error_code=code)


class RefuseSend(Fault):
    """Sends of matching frames ``at`` .. ``at + count - 1`` (0-based; ``count=None``:
    every one from ``at`` on) fail with ENOBUFS, as SocketCAN does when the transmit
    queue is full. Send direction."""

    direction: ClassVar[Direction] = Direction.SEND

    def __init__(self, *, at: int, count: int | None = None, code: int = errno.ENOBUFS,
                 ids: Collection[int] | None = None) -> None:
        if at < 0 or (count is not None and count < 1):
            raise ValueError(f"RefuseSend: at >= 0, count >= 1 or None; got {at}, {count}")
        super().__init__(ids)
        self.at = at
        self.count = count
        self.code = code

    def apply(self, msg: can.Message, index: int, now: float) -> Sequence[can.Message]:
        if index >= self.at and (self.count is None or index < self.at + self.count):
            self.applied += 1
            raise _error(self.code, "Failed to transmit")
        return (msg,)


class InterfaceGone(Fault):
    """After the ``after``-th matching frame sent (0-based), every send and receive of
    the bus fails with ENODEV: the interface is gone and does not come back."""

    direction: ClassVar[Direction] = Direction.SEND

    def __init__(self, *, after: int, ids: Collection[int] | None = None) -> None:
        if after < 0:
            raise ValueError(f"after: expected >= 0, got {after}")
        super().__init__(ids)
        self.after = after
        self.gone = False

    def apply(self, msg: can.Message, index: int, now: float) -> Sequence[can.Message]:
        if index >= self.after:
            self.gone = True
        return (msg,)

    def check(self, direction: Direction, now: float) -> None:
        if self.gone:
            self.applied += 1
            raise _error(errno.ENODEV, "Failed to transmit" if direction is Direction.SEND
                         else "Error receiving")
