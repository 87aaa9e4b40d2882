"""Fault injection: small, composable faults applied by a python-can bus wrapper.

A :class:`Fault` looks at one frame at a time, in one direction (frames the wrapped
side *receives* or *sends*), and returns the frames to pass on: none (dropped), the
frame itself, a changed copy, or the frame plus injected ones. :class:`FaultyBus`
chains faults in front of any ``can.BusABC``; :func:`faulty` makes the
``bus_wrapper=`` callable :class:`dobhil.runtime.session.RunSession` takes::

    wrapper = faulty(SilenceAfter(seconds=0.2), CorruptFeedback.of_profile(profile, "position", at=100))
    with RunSession(config, emulate=True, bus_wrapper=wrapper) as s: ...

On the host side (``bus_wrapper``) receive faults model what the drive sends and the
host sees (silence, NaN, lost frames); send faults model what the host puts on the
bus (an injected Estop). To fault the drive side instead, wrap the emulator's bus
with ``FaultyBus(bus, faults, owns_inner=True)``.

Periodic frames (``send_periodic``: a host's SYNC) are the inner bus's own, so
the wrapper is as native as what it wraps (:func:`dobhil.drives.periodic.native_periodic`);
send faults do not see them, receive faults see their echo.

Time: faults that trigger on time read the wrapper's clock, the inner bus's
``clock()`` if it has one (a :class:`~dobhil.drives.emulated.LockstepBus`: simulated
seconds) or ``time.monotonic``; the clock starts at 0 when the wrapper is made.
Randomness is seeded: a faulted run is reproducible in lockstep.

A new fault (roadmap: a fault-injection and fuzzing campaign) is one new subclass of
:class:`Fault`: set :attr:`Fault.direction` and write :meth:`Fault.apply` (and
:meth:`Fault.check` for a fault of the bus itself, which may raise before any frame
moves). Frame faults live here; the bus failing (refused sends, the interface going
away) in :mod:`dobhil.emulator.bus_faults`.
"""

from __future__ import annotations

import math
import random
import struct
from abc import ABC, abstractmethod
from collections import deque
from collections.abc import Callable, Collection, Sequence
from enum import Enum
from typing import Any, ClassVar

import can
import can.broadcastmanager

from dobhil.drives.clocked import ClockedBus, bus_clock
from dobhil.drives.periodic import native_periodic
from dobhil.drives.profile import DriveProfile
from dobhil.drives.registry import protocol

__all__ = [
    "CorruptFeedback",
    "Direction",
    "DropFrames",
    "Fault",
    "FaultyBus",
    "Flood",
    "HoldFrames",
    "InjectFrame",
    "InjectReceived",
    "KeepEvery",
    "LoseSent",
    "SilenceAfter",
    "faulty",
]

#: the longest frame payload (CAN FD) a field may sit in
MAX_PAYLOAD = 64


class Direction(Enum):
    RECV = "recv"   # frames the wrapped side receives
    SEND = "send"   # frames the wrapped side sends


def _copy(msg: can.Message, data: bytes | bytearray) -> can.Message:
    return can.Message(timestamp=msg.timestamp, arbitration_id=msg.arbitration_id,
                       is_extended_id=msg.is_extended_id, is_remote_frame=msg.is_remote_frame,
                       is_error_frame=msg.is_error_frame, channel=msg.channel, dlc=len(data),
                       data=bytearray(data), is_rx=msg.is_rx, is_fd=msg.is_fd,
                       bitrate_switch=msg.bitrate_switch, error_state_indicator=msg.error_state_indicator)


class Fault(ABC):
    """One fault. ``ids``: the arbitration ids it acts on (None: every frame);
    other frames pass untouched and are not counted."""

    direction: ClassVar[Direction] = Direction.RECV

    def __init__(self, ids: Collection[int] | None = None) -> None:
        self.ids = None if ids is None else frozenset(ids)
        self.matched = 0   # frames of ``ids`` seen so far
        self.applied = 0   # frames this fault dropped, changed or injected

    def matches(self, msg: can.Message) -> bool:
        return self.ids is None or msg.arbitration_id in self.ids

    def __call__(self, msg: can.Message, now: float) -> Sequence[can.Message]:
        if not self.matches(msg):
            return (msg,)
        index = self.matched
        self.matched += 1
        return self.apply(msg, index, now)

    @abstractmethod
    def apply(self, msg: can.Message, index: int, now: float) -> Sequence[can.Message]:
        """Frames to pass on for the ``index``-th matching frame (0-based) at ``now`` [s]."""

    def check(self, direction: Direction, now: float) -> None:
        """Called before every send and receive of the wrapped bus, frame or not; a
        fault of the bus itself raises here (python-can's ``CanOperationError``)."""
        return None


class SilenceAfter(Fault):
    """The drive goes silent: every matching frame after the first ``frames`` of them,
    or after ``seconds`` on the wrapper's clock, is dropped. With ``ids`` the drive's
    motion feedback frame, ``frames`` counts control cycles."""

    def __init__(self, *, frames: int | None = None, seconds: float | None = None,
                 ids: Collection[int] | None = None) -> None:
        if (frames is None) == (seconds is None):
            raise ValueError("SilenceAfter: give exactly one of frames= or seconds=")
        if (frames is not None and frames < 0) or (seconds is not None and not seconds >= 0):
            raise ValueError(f"SilenceAfter: expected >= 0, got frames={frames}, seconds={seconds}")
        super().__init__(ids)
        self.frames = frames
        self.seconds = seconds

    def apply(self, msg: can.Message, index: int, now: float) -> Sequence[can.Message]:
        silent = index >= self.frames if self.frames is not None else now >= self.seconds  # type: ignore[operator]
        if silent:
            self.applied += 1
            return ()
        return (msg,)


class CorruptFeedback(Fault):
    """Replaces the value of ``struct`` format ``fmt`` (little-endian float32 by default) at
    byte ``offset`` of matching frames ``at`` .. ``at + count - 1`` (0-based) by ``value``
    (NaN by default). :meth:`of_profile` finds the frame and the field through the drive's
    protocol (``DriveProtocol.feedback_field``)."""

    def __init__(self, arbitration_id: int, *, offset: int = 0, fmt: str = "<f", value: float = math.nan,
                 at: int = 0, count: int = 1) -> None:
        try:
            size = struct.calcsize(fmt)
        except struct.error:
            raise ValueError(f"CorruptFeedback: fmt: expected a struct format such as '<f', got {fmt!r}") from None
        if offset < 0 or offset + size > MAX_PAYLOAD or at < 0 or count < 1:
            raise ValueError(f"CorruptFeedback: offset 0..{MAX_PAYLOAD - size}, at >= 0, count >= 1; "
                             f"got {offset}, {at}, {count}")
        try:
            struct.pack(fmt, value)
        except struct.error:
            raise ValueError(f"CorruptFeedback: value: expected a value {fmt!r} holds, got {value!r}") from None
        super().__init__((arbitration_id,))
        self.offset = offset
        self.fmt = fmt
        self.size = size
        self.value = value
        self.at = at
        self.count = count

    @classmethod
    def of_profile(cls, profile: DriveProfile, field: str = "position", **kwargs: Any) -> CorruptFeedback:
        """On the frame that carries ``field`` (``position`` or ``velocity``) of the drive
        ``profile`` describes, as its protocol lays it out; ValueError (one line) when the
        protocol offers no such field."""
        where = protocol(profile.protocol).feedback_field(profile, field)
        if where is None:
            raise ValueError(f"CorruptFeedback: field: protocol {profile.protocol!r} offers no feedback "
                             f"field {field!r} to corrupt (position and velocity where it lays them out)")
        return cls(where.arbitration_id, offset=where.offset, fmt=where.fmt, **kwargs)

    def apply(self, msg: can.Message, index: int, now: float) -> Sequence[can.Message]:
        if not self.at <= index < self.at + self.count or len(msg.data) < self.offset + self.size:
            return (msg,)
        data = bytearray(msg.data)
        struct.pack_into(self.fmt, data, self.offset, self.value)
        self.applied += 1
        return (_copy(msg, data),)


class DropFrames(Fault):
    """Each matching frame is lost with ``probability`` (seeded)."""

    def __init__(self, probability: float, *, seed: int = 0,
                 ids: Collection[int] | None = None) -> None:
        if not 0.0 <= probability <= 1.0:
            raise ValueError(f"probability: expected 0..1, got {probability}")
        super().__init__(ids)
        self.probability = float(probability)
        self._rng = random.Random(seed)

    def apply(self, msg: can.Message, index: int, now: float) -> Sequence[can.Message]:
        if self._rng.random() < self.probability:
            self.applied += 1
            return ()
        return (msg,)


class InjectFrame(Fault):
    """Sends ``frame`` once, right after the ``after``-th matching frame the wrapped side
    sends (0-based), e.g. an Estop in the middle of a run. Send direction."""

    direction: ClassVar[Direction] = Direction.SEND

    def __init__(self, frame: can.Message, *, after: int,
                 ids: Collection[int] | None = None) -> None:
        if after < 0:
            raise ValueError(f"after: expected >= 0, got {after}")
        super().__init__(ids)
        self.frame = frame
        self.after = after

    def apply(self, msg: can.Message, index: int, now: float) -> Sequence[can.Message]:
        if index == self.after:
            self.applied += 1
            return (msg, self.frame)
        return (msg,)


class KeepEvery(Fault):
    """Only every ``n``-th matching frame (from ``at`` on, 0-based) gets through: a drive
    streaming ``n`` times slower than its profile says (a drive left at a factory 10 ms
    feedback period under a 1 ms profile)."""

    def __init__(self, n: int, *, at: int = 0, ids: Collection[int] | None = None) -> None:
        if n < 2 or at < 0:
            raise ValueError(f"KeepEvery: n >= 2, at >= 0; got {n}, {at}")
        super().__init__(ids)
        self.n = n
        self.at = at

    def apply(self, msg: can.Message, index: int, now: float) -> Sequence[can.Message]:
        if index < self.at or (index - self.at) % self.n == 0:
            return (msg,)
        self.applied += 1
        return ()


class LoseSent(SilenceAfter):
    """Frames the wrapped side sends are lost on the way (after the first ``frames`` of
    them, or after ``seconds``): the sender's ``send`` succeeds, the drive never sees
    them. Send direction."""

    direction: ClassVar[Direction] = Direction.SEND


class InjectReceived(InjectFrame):
    """Delivers ``frame`` once, right after the ``after``-th matching frame the wrapped
    side receives (0-based): a frame that was never sent by the drive, e.g. a spoofed
    heartbeat. Receive direction."""

    direction: ClassVar[Direction] = Direction.RECV


class HoldFrames(Fault):
    """Late frames: matching frames ``at`` .. ``at + count - 1`` (0-based) are held back
    and delivered together with the next one, in order (a stall of ``count`` frames on
    the way, then a burst)."""

    def __init__(self, *, at: int, count: int, ids: Collection[int] | None = None) -> None:
        if at < 0 or count < 1:
            raise ValueError(f"HoldFrames: at >= 0, count >= 1; got {at}, {count}")
        super().__init__(ids)
        self.at = at
        self.count = count
        self._held: list[can.Message] = []

    def apply(self, msg: can.Message, index: int, now: float) -> Sequence[can.Message]:
        if self.at <= index < self.at + self.count:
            self._held.append(msg)
            self.applied += 1
            return ()
        if self._held:
            held, self._held = self._held, []
            return (*held, msg)
        return (msg,)


class Flood(Fault):
    """Foreign traffic: each matching frame is followed by ``per_frame`` frames of other
    participants (other node ids, extended ids, remote frames), seeded. Receive
    direction."""

    def __init__(self, per_frame: int, *, avoid: Collection[int] = (), seed: int = 0,
                 ids: Collection[int] | None = None) -> None:
        if per_frame < 1:
            raise ValueError(f"per_frame: expected >= 1, got {per_frame}")
        super().__init__(ids)
        self.per_frame = per_frame
        self.avoid = frozenset(avoid)
        self._rng = random.Random(seed)

    def _foreign(self) -> can.Message:
        rng = self._rng
        extended = rng.random() < 0.25
        while True:
            arb = rng.randrange(1 << 29) if extended else rng.randrange(0x800)
            if extended or arb not in self.avoid:
                break
        size = rng.randrange(9)
        return can.Message(arbitration_id=arb, is_extended_id=extended,
                           is_remote_frame=rng.random() < 0.1, dlc=size,
                           data=bytes(rng.randrange(256) for _ in range(size)))

    def apply(self, msg: can.Message, index: int, now: float) -> Sequence[can.Message]:
        self.applied += self.per_frame
        return (msg, *(self._foreign() for _ in range(self.per_frame)))


class FaultyBus(ClockedBus):
    """``inner`` with ``faults`` applied in order to what it receives and sends.

    The inner bus is borrowed (a session shuts it down) unless ``owns_inner``.
    ``recv(timeout)`` keeps the timeout in the inner bus's time (simulated seconds
    over a LockstepBus): dropped frames do not end the wait early.
    """

    def __init__(self, inner: can.BusABC, faults: Sequence[Fault], *,
                 clock: Callable[[], float] | None = None, owns_inner: bool = False,
                 **kwargs: Any) -> None:
        self._inner = inner
        self._recv_faults = [f for f in faults if f.direction is Direction.RECV]
        self._send_faults = [f for f in faults if f.direction is Direction.SEND]
        self.faults = tuple(faults)
        self._clock = clock or bus_clock(inner)
        self._t0 = self._clock()
        self._owns_inner = owns_inner
        self._pending: deque[can.Message] = deque()
        self.channel_info = f"faulty {inner.channel_info}"
        super().__init__(channel=self.channel_info, **kwargs)
        # a wrapper carries what the wrapped bus carries (CAN FD)
        self._can_protocol = getattr(inner, "protocol", can.CanProtocol.CAN_20)

    def now(self) -> float:
        """Seconds since the wrapper was made, on its clock."""
        return self._clock() - self._t0

    @staticmethod
    def _chain(faults: Sequence[Fault], msg: can.Message, now: float) -> list[can.Message]:
        frames = [msg]
        for fault in faults:
            frames = [out for frame in frames for out in fault(frame, now)]
        return frames

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        now = self.now()
        for fault in self.faults:
            fault.check(Direction.SEND, now)
        for frame in self._chain(self._send_faults, msg, now):
            self._inner.send(frame, timeout)

    def clock(self) -> float:
        """The inner bus's clock (simulated seconds over a LockstepBus), or ``time.monotonic``."""
        return self._clock()

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        """The whole wait on :meth:`clock` (:mod:`dobhil.drives.clocked`): dropped frames and
        frames the filters reject do not end it early; filters see the faulted frames."""
        now = self.now()
        for fault in self.faults:
            fault.check(Direction.RECV, now)
        deadline = None if timeout is None else self._clock() + timeout
        while True:
            while self._pending:
                frame = self._pending.popleft()
                if self.passes(frame):
                    return frame, True
            remaining = None if deadline is None else max(0.0, deadline - self._clock())
            msg = self._inner.recv(remaining)
            if msg is None:
                return None, True
            self._pending.extend(self._chain(self._recv_faults, msg, self.now()))

    @property
    def native_periodic(self) -> bool:
        """As the inner bus: periodic frames are the inner bus's (see below), so a drive
        that wants its SYNC outside this process's threads still gets it behind faults."""
        return native_periodic(self._inner)

    def _send_periodic_internal(self, msgs: Sequence[can.Message] | can.Message, period: float,
                                duration: float | None = None, autostart: bool = True,
                                modifier_callback: Callable[[can.Message], None] | None = None,
                                ) -> can.broadcastmanager.CyclicSendTaskABC:
        """The inner bus's own periodic send (the kernel's broadcast manager, the lockstep
        clock, the emulator process): the send faults do not see these frames -- they model
        what the host's code sends, and a periodic frame leaves without it; their echo
        comes back through :meth:`recv` and its faults. The task belongs to this wrapper
        (``store_task=False`` below): its shutdown stops it."""
        return self._inner.send_periodic(msgs, period, duration, store_task=False,
                                         autostart=autostart, modifier_callback=modifier_callback)

    def shutdown(self) -> None:
        if self._owns_inner:
            self._inner.shutdown()
        super().shutdown()


def faulty(*faults: Fault, clock: Callable[[], float] | None = None
           ) -> Callable[[can.BusABC], FaultyBus]:
    """A ``bus_wrapper`` for RunSession applying ``faults`` on the host side."""
    def wrap(inner: can.BusABC) -> FaultyBus:
        return FaultyBus(inner, faults, clock=clock)
    return wrap
