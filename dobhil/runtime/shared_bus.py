"""One python-can bus shared by several drives, each through a view of its own.

A :class:`~dobhil.drives.base.Drive` borrows a bus and reads every frame on it: two drives
on one bus would each take the other's frames. :class:`SharedBus` sits between them and
the one bus (its ``inner``): each drive gets a :class:`BusView`, a full ``can.BusABC``
(python-can's public contract: ``send``, ``recv`` through ``_recv_internal``,
``send_periodic``, filters, ``shutdown``), so the drive classes stay as they are.

- **Receive**: one *receive pass* (:meth:`SharedBus.receive_pass`) reads what the inner
  bus has and hands each frame to every view whose drive takes it (its
  :attr:`~dobhil.drives.base.Drive.frame_ids`; a view without ids takes every frame).
  A view's own ``recv`` runs receive passes until a frame for it came or its wait ended,
  so a drive that waits (its enable, its safe stop's confirmation) still works alone,
  and the frames of the others it reads meanwhile are queued for them. The queues are
  bounded (:data:`QUEUE_FRAMES`): a view that is not read loses its oldest frames,
  counted in :attr:`BusView.lost`, and the bus never grows without end.
- **Send**: straight through to the inner bus, in the caller's order (one cycle's
  commands go out as one burst, one batch per tick as a transport's ``cycle`` sends it).
  Inside a burst (:meth:`SharedBus.burst_begin` .. :meth:`SharedBus.burst_end`) a frame of
  the bus rather than of one node -- its id taken by more than one view, a SYNC a drive
  sends itself after its command where the bus has no periodic send of its own -- is
  held and sent once, after every node's command: each node's command is in before the
  one SYNC that latches them all.
- **Periodic send**: the same frame at the same period asked by several views (a SYNC,
  a host heartbeat: frames of the bus, not of one node) is one task on the inner bus,
  shared by reference count and stopped when the last view stops it: nodes on one bus
  share one SYNC, as a network has one SYNC producer (CiA 301). Other periodic
  sends are the inner bus's own tasks, one per call.

Waits run on the inner bus's clock (:func:`~dobhil.drives.clocked.bus_clock`: simulated
seconds over a lockstep bus).
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Collection, Sequence
from typing import Any, Final

import can
from can.broadcastmanager import CyclicSendTaskABC

from dobhil.drives.clocked import ClockedBus, bus_clock
from dobhil.drives.periodic import native_periodic
from dobhil.errors import BusError, exception_line

__all__ = ["QUEUE_FRAMES", "BusView", "SharedBus"]

#: frames a view holds unread at most (4 s of a 1 kHz stream of one frame per cycle)
QUEUE_FRAMES: Final = 4096
#: frames one receive pass reads at most: a bus that never runs dry cannot hold the loop
PASS_FRAMES: Final = 1024

#: a view's recv(None) waits on the inner bus for ever
WAIT_FOREVER: Final = None

_Key = tuple[int, bool, bool, bytes, float]


def _key(msg: can.Message, period: float) -> _Key:
    return (msg.arbitration_id, msg.is_extended_id, msg.is_fd, bytes(msg.data), period)


class _SharedTask(CyclicSendTaskABC):
    """A view's handle on a periodic task it shares: its ``stop`` drops the view's
    reference; the inner task stops with the last one."""

    def __init__(self, bus: SharedBus, key: _Key, msg: can.Message, period: float) -> None:
        super().__init__(msg, period)
        self._shared = bus
        self._task_key: _Key | None = key

    def stop(self) -> None:
        key, self._task_key = self._task_key, None
        if key is not None:
            self._shared.release(key)


class SharedBus:
    """The one bus under several :class:`BusView` (see the module's text). The inner bus
    is borrowed: :meth:`shutdown` stops the shared periodic tasks and leaves it open."""

    def __init__(self, inner: can.BusABC, *, queue_frames: int = QUEUE_FRAMES) -> None:
        if queue_frames < 1:
            raise ValueError(f"queue_frames: expected >= 1, got {queue_frames}")
        self.inner = inner
        self.clock: Callable[[], float] = bus_clock(inner)
        self.queue_frames = queue_frames
        self.views: list[BusView] = []
        self._tasks: dict[_Key, tuple[CyclicSendTaskABC, int]] = {}
        #: ids more than one view takes (the bus's own frames, not one node's)
        self.bus_wide: frozenset[int] = frozenset()
        self._held: dict[tuple[int, bool, bytes], can.Message] | None = None   # in a burst
        #: frames read that no view took (another node's, foreign traffic)
        self.unclaimed = 0

    def view(self, name: str, ids: Collection[int] | None = None) -> BusView:
        """A new view named ``name`` taking frames with arbitration ids ``ids`` (None: every
        frame; set later with :meth:`BusView.accept`, once its drive says its ids)."""
        view = BusView(self, name, ids)
        self.views.append(view)
        self.recount()
        return view

    def recount(self) -> None:
        """Which ids are the bus's own (taken by more than one view); views call this when
        their ids change."""
        seen: set[int] = set()
        wide: set[int] = set()
        for view in self.views:
            ids = view.ids
            if ids is not None:
                wide |= seen & ids
                seen |= ids
        self.bus_wide = frozenset(wide)

    def receive_pass(self, timeout: float | None = 0.0) -> int:
        """Read what the inner bus has -- waiting up to ``timeout`` s of its clock for the
        first frame -- and hand each frame to the views that take it; the frames read."""
        recv, views = self.inner.recv, self.views
        try:
            msg = recv(timeout)
            count = 0
            while msg is not None:
                count += 1
                taken = False
                for view in views:
                    if view.takes(msg):
                        view.put(msg)
                        taken = True
                if not taken:
                    self.unclaimed += 1
                if count >= PASS_FRAMES:
                    break
                msg = recv(0.0)
        except BusError:
            raise
        except Exception as exc:   # python-can's, the OS's or a transport's own: the bus is gone
            # the loop calls a pass itself, not through a drive (which names such a failure a
            # BusError, dobhil/drives/base.py): the same stop, bus_error, either way
            raise BusError(f"bus read on {self.inner.channel_info} failed: "
                           f"{exception_line(exc, named=not isinstance(exc, (can.CanError, OSError)))}") from exc
        return count

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        held = self._held
        if held is not None and msg.arbitration_id in self.bus_wide:
            held.setdefault((msg.arbitration_id, msg.is_extended_id, bytes(msg.data)), msg)
            return
        self.inner.send(msg, timeout)

    def burst_begin(self) -> None:
        """From now on, hold the bus's own frames (see the module's text)."""
        self._held = {}

    def burst_end(self) -> None:
        """Send the held frames, each once, in the order they were first asked for."""
        held, self._held = self._held, None
        for msg in (held or {}).values():
            self.inner.send(msg)

    def send_periodic(self, msgs: Sequence[can.Message] | can.Message, period: float,
                      duration: float | None, autostart: bool,
                      modifier_callback: Callable[[can.Message], None] | None) -> CyclicSendTaskABC:
        """One frame, sent for ever, started now, unchanged: shared with every view that
        asks for the same (:func:`_key`). Anything else: a task of its own on the inner bus."""
        single = msgs if isinstance(msgs, can.Message) else (msgs[0] if len(msgs) == 1 else None)
        if single is None or duration is not None or not autostart or modifier_callback is not None:
            return self.inner.send_periodic(msgs, period, duration, store_task=False, autostart=autostart,
                                            modifier_callback=modifier_callback)
        key = _key(single, period)
        task, refs = self._tasks.get(key, (None, 0))
        if task is None:
            task = self.inner.send_periodic(single, period, store_task=False)
        self._tasks[key] = (task, refs + 1)
        return _SharedTask(self, key, single, period)

    def release(self, key: _Key) -> None:
        """One view stopped its shared task: stop the inner one when none is left."""
        entry = self._tasks.get(key)
        if entry is None:
            return
        task, refs = entry
        if refs > 1:
            self._tasks[key] = (task, refs - 1)
            return
        del self._tasks[key]
        task.stop()

    @property
    def shared_tasks(self) -> int:
        """Periodic tasks running on the inner bus for the views (each once)."""
        return len(self._tasks)

    def shutdown(self) -> None:
        """Stop the shared periodic tasks (the inner bus stays open: it is borrowed)."""
        tasks, self._tasks = list(self._tasks.values()), {}
        for task, _ in tasks:
            try:
                task.stop()
            except Exception:   # a bus already gone: nothing left to stop
                pass


class BusView(ClockedBus):
    """One drive's bus on a :class:`SharedBus`: its frames, and the whole bus to send on."""

    def __init__(self, shared: SharedBus, name: str, ids: Collection[int] | None = None,
                 **kwargs: Any) -> None:
        self._shared = shared
        self.name = name
        self._ids: frozenset[int] | None = None if ids is None else frozenset(ids)
        self._queue: deque[can.Message] = deque()
        #: frames dropped because this view's queue was full (its oldest)
        self.lost = 0
        inner = shared.inner
        self.channel_info = f"{name} on {inner.channel_info}"
        super().__init__(channel=getattr(inner, "channel", None) or self.channel_info, **kwargs)
        # a view carries what the bus carries (CAN FD)
        self._can_protocol = getattr(inner, "protocol", can.CanProtocol.CAN_20)

    def accept(self, ids: Collection[int] | None) -> None:
        """Take the frames with these arbitration ids (None: every frame)."""
        self._ids = None if ids is None else frozenset(ids)
        self._shared.recount()

    @property
    def ids(self) -> frozenset[int] | None:
        """The arbitration ids this view takes (None: every frame)."""
        return self._ids

    def takes(self, msg: can.Message) -> bool:
        ids = self._ids
        return ids is None or msg.arbitration_id in ids

    def put(self, msg: can.Message) -> None:
        """A frame read by a receive pass, for this view."""
        queue = self._queue
        if len(queue) >= self._shared.queue_frames:
            queue.popleft()
            self.lost += 1
        queue.append(msg)

    @property
    def pending(self) -> int:
        """Frames queued for this view, not yet read."""
        return len(self._queue)

    def clock(self) -> float:
        """The shared bus's clock (simulated seconds over a lockstep bus)."""
        return self._shared.clock()

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self._shared.send(msg, timeout)

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        """The next frame for this view that passes its filters, running receive passes
        until one came or ``timeout`` s (the bus's clock) passed; at least one pass."""
        queue, shared = self._queue, self._shared
        if timeout == 0.0 and not self.filtering:   # the cycle's read: no clock, one pass at most
            if not queue:
                shared.receive_pass(0.0)
            return (queue.popleft() if queue else None), True
        clock = shared.clock
        deadline = None if timeout is None else clock() + timeout
        first = True
        while True:
            while queue:
                msg = queue.popleft()
                if self.passes(msg):
                    return msg, True
            remaining = None if deadline is None else deadline - clock()
            if remaining is not None and remaining <= 0 and not first:
                return None, True
            # (None: wait for ever, a pass at a time: the bus's own blocking read)
            shared.receive_pass(WAIT_FOREVER if remaining is None else max(remaining, 0.0))
            first = False

    @property
    def native_periodic(self) -> bool:
        """As the inner bus (:func:`dobhil.drives.periodic.native_periodic`): periodic
        frames are its own."""
        return native_periodic(self._shared.inner)

    def _send_periodic_internal(self, msgs: Sequence[can.Message] | can.Message, period: float,
                                duration: float | None = None, autostart: bool = True,
                                modifier_callback: Callable[[can.Message], None] | None = None,
                                ) -> CyclicSendTaskABC:
        return self._shared.send_periodic(msgs, period, duration, autostart, modifier_callback)

    def shutdown(self) -> None:
        """Drop this view (its queued frames with it); the shared bus stays."""
        self._queue.clear()
        super().shutdown()
