"""A python-can bus wrapper that records every frame the host sends and receives.

:class:`RecordingBus` is what :class:`~dobhil.runtime.session.RunSession` gets as
``bus_wrapper``: ``send`` and ``recv`` pass through to the wrapped bus (with
lockstep, the :class:`~dobhil.emulator.protocol.LockstepBus`) and append one flat raw
record per frame (plain values only, see :class:`~dobhil.recording.fastlog.RawKind`) to a
:class:`~dobhil.recording.fastlog.Batcher`; everything else (``shutdown`` aside, which
leaves the wrapped bus to its owner) is delegated. The payload of a received message is
kept by reference until the batch is marshalled (python-can hands out a new message per
receive); a sent one is copied (drives refill a preallocated torque frame).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any, Final

import can

from dobhil.recording.fastlog import Batcher, RawKind

ClockNs = Callable[[], int]

_RX: Final = int(RawKind.FRAME_RX)  # plain ints: marshal refuses IntEnum members
_TX: Final = int(RawKind.FRAME_TX)


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
        super().__init__(channel=self.channel_info, **kwargs)

    @property
    def inner(self) -> can.BusABC:
        """The wrapped bus."""
        return self._inner

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self._inner.send(msg, timeout)
        self.sent += 1
        # flags: fastlog.frame_flags inlined (a call costs as much as the record)
        self._append((_TX, self._clock_ns(), msg.arbitration_id,
                      msg.is_extended_id | msg.is_remote_frame << 1 | msg.is_error_frame << 2 | msg.is_fd << 3
                      | msg.bitrate_switch << 4 | msg.error_state_indicator << 5,
                      msg.dlc, bytes(msg.data), msg.timestamp, msg.channel))

    def recv(self, timeout: float | None = None) -> can.Message | None:
        msg = self._inner.recv(timeout)
        if msg is not None:
            self.received += 1
            self._append((_RX, self._clock_ns(), msg.arbitration_id,
                          msg.is_extended_id | msg.is_remote_frame << 1 | msg.is_error_frame << 2
                          | msg.is_fd << 3 | msg.bitrate_switch << 4 | msg.error_state_indicator << 5,
                          msg.dlc, msg.data, msg.timestamp, msg.channel))
        return msg

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        return self.recv(timeout), False

    def __getattr__(self, name: str) -> Any:
        if name.startswith("_"):
            raise AttributeError(name)
        return getattr(self._inner, name)


__all__ = ["RecordingBus"]
