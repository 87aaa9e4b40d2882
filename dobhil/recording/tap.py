"""A python-can bus wrapper that records every frame the host sends and receives.

:class:`RecordingBus` is what :class:`~dobhil.runtime.session.RunSession` gets as
``bus_wrapper``: ``send`` and ``recv`` pass through to the wrapped bus (with
lockstep, the :class:`~dobhil.emulator.protocol.LockstepBus`) and append one raw
record per frame to a :class:`~dobhil.recording.fastlog.Batcher`; everything else
(``shutdown`` aside, which leaves the wrapped bus to its owner) is delegated.
Received messages are kept by reference (python-can hands out a new message per
receive); sent ones are copied (drives refill a preallocated torque frame).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import can

from dobhil.recording.fastlog import Batcher, RawKind

ClockNs = Callable[[], int]

_RX = RawKind.FRAME_RX
_TX = RawKind.FRAME_TX


class RecordingBus(can.BusABC):
    """Records ``/can/rx`` and ``/can/tx`` of the bus it wraps (borrowed, not owned)."""

    def __init__(self, inner: can.BusABC, batcher: Batcher, *, clock_ns: ClockNs = time.time_ns,
                 **kwargs: Any) -> None:
        self._inner = inner
        self._append = batcher.buffer.append
        self._clock_ns = clock_ns
        self.channel_info = f"recording {inner.channel_info}"
        self.sent = 0
        self.received = 0
        super().__init__(channel=getattr(inner, "channel", None), **kwargs)

    @property
    def inner(self) -> can.BusABC:
        """The wrapped bus."""
        return self._inner

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self._inner.send(msg, timeout)
        self.sent += 1
        self._append((_TX, self._clock_ns(), msg, bytes(msg.data)))

    def recv(self, timeout: float | None = None) -> can.Message | None:
        msg = self._inner.recv(timeout)
        if msg is not None:
            self.received += 1
            self._append((_RX, self._clock_ns(), msg, msg.data))
        return msg

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        return self.recv(timeout), False

    def __getattr__(self, name: str) -> Any:
        if name.startswith("_"):
            raise AttributeError(name)
        return getattr(self._inner, name)


__all__ = ["RecordingBus"]
