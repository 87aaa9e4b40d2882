"""Several emulated drives on one bus, on one real-time tick clock.

A bus of a multi-axis device carries several nodes (two drives of one protocol, or drives
of several protocols side by side). :class:`EmulatedNodes` runs every :class:`~dobhil.drives.emulated.EmulatedDrive`
of one bus on the calling thread, as :meth:`EmulatedDrive.run_realtime` runs one:

- one tick clock: the shortest real-time tick of the nodes (:func:`tick_period` of each
  profile); each tick every node applies the frames that arrived during it (at their
  arrival instant inside the tick, with its own latency and jitter), then every node's
  plant steps the tick in the nodes' order (coupled plants,
  :mod:`dobhil.emulator.coupling`, exchange their states so), then each node sends the
  cyclic frames that fell due -- a node whose own period is longer sends them at the first
  tick at or after they fall due;
- one reader: each frame read from the shared bus goes to every node, which keeps what is
  addressed to it (its protocol's filter; the rest is counted in ``frames_not_addressed``),
  as every node on a CAN bus receives every frame;
- the nodes hear each other: a frame one node sends goes to the bus and, as on a real bus,
  to the other nodes' taps, which they read (:meth:`EmulatedDrive.handle_pending`) once the
  node that sent it is done, so their counters read as on the wire.

Each node talks through a :class:`NodeTap`: its sends go to the shared bus and to the other
taps; what it reads are the other nodes' frames (the runner reads the shared bus for all).
The shared bus is borrowed: the caller shuts it.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from typing import Any

import can

from dobhil.drives.emulated import EmulatedDrive, tick_period
from dobhil.drives.ticks import TickReader, run_ticks
from dobhil.realtime import lower_priority

__all__ = ["EmulatedNodes", "NodeTap"]

#: [s] the longest a tap's ``recv`` sleeps at a time while nothing is queued
_IDLE_WAIT = 1e-3


class NodeTap(can.BusABC):
    """One node's view of a bus shared with other emulated nodes of :class:`EmulatedNodes`:
    sends go to the shared bus and to the other nodes' taps; ``recv`` returns what the other
    nodes sent (the host's frames the runner reads from the shared bus and hands over)."""

    def __init__(self, shared: can.BusABC, on_sent: Callable[[NodeTap, can.Message], None]) -> None:
        self._shared = shared
        self._on_sent = on_sent
        self.inbox: deque[can.Message] = deque()
        self.channel_info = shared.channel_info
        super().__init__(channel=str(shared.channel_info))
        self._can_protocol = getattr(shared, "protocol", can.CanProtocol.CAN_20)

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self._shared.send(msg, timeout)
        self._on_sent(self, msg)

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        if self.inbox:
            return self.inbox.popleft(), False
        if timeout:   # nothing queued: the frames come from this thread; python-can waits on
            time.sleep(min(timeout, _IDLE_WAIT))
        return None, False

    def shutdown(self) -> None:
        super().shutdown()   # the shared bus is the runner's caller's


class EmulatedNodes:
    """The emulated drives of one bus, run together (module docstring). Build the drives on
    :meth:`tap` buses, then :meth:`attach` them in the order their plants step."""

    def __init__(self, bus: can.BusABC) -> None:
        self._bus = bus
        self._taps: list[NodeTap] = []
        self.drives: tuple[EmulatedDrive, ...] = ()
        self._crosstalk = False   # a node sent a frame the others have not read yet
        self._stopped = False
        self._ticks = TickReader(bus, lambda: self._stopped)   # one reader for every node
        self._thread: threading.Thread | None = None
        self._error: BaseException | None = None
        self.overruns = 0

    def tap(self) -> NodeTap:
        """The bus the next node is built on."""
        tap = NodeTap(self._bus, self._sent)
        self._taps.append(tap)
        return tap

    def attach(self, drives: Sequence[EmulatedDrive]) -> None:
        """The nodes built on :meth:`tap` buses, in the same order."""
        if len(drives) != len(self._taps) or not drives:
            raise ValueError(f"EmulatedNodes: {len(drives)} drives for {len(self._taps)} taps")
        self.drives = tuple(drives)

    @property
    def tick_period(self) -> float:
        """[s] the shortest real-time tick of the nodes."""
        return min(tick_period(d.profile) for d in self.drives)

    @property
    def time(self) -> float:
        """Emulator time [s] (every node's: they step together)."""
        return self.drives[0].time

    def prepare(self) -> None:
        """Every node's one-off set-up costs, its plant's matrices for the shared tick too."""
        for drive in self.drives:
            drive.prepare()
            prepare = getattr(drive.plant, "prepare", None)
            if callable(prepare):
                prepare(self.tick_period)

    def deliver(self, msg: can.Message) -> None:
        """A frame the bus itself puts on the wire now (a periodic frame), to every node."""
        for drive in self.drives:
            drive.deliver(msg)
        self._flush_crosstalk()

    def start(self, *, priority_drop: int = 0) -> None:
        """Run on a thread of its own, its nice value raised by ``priority_drop`` where the
        OS allows (below the control loop), as :meth:`EmulatedDrive.start` runs one node."""
        if self._thread is not None:
            raise RuntimeError("emulated nodes already started")
        self.prepare()
        self._stopped = False
        self._thread = threading.Thread(target=self._run_guarded, args=(priority_drop,),
                                        name=f"EmulatedNodes-{len(self.drives)}")
        self._thread.start()

    def stop(self, timeout: float = 2.0) -> None:
        """End :meth:`run_realtime` after the tick under way; with a thread of :meth:`start`,
        join it and re-raise what it raised (a BusError: the bus was lost). The nodes' taps
        are closed (the shared bus is the caller's)."""
        self._stopped = True
        thread, self._thread = self._thread, None
        try:
            if thread is None:
                return
            thread.join(timeout)
            if thread.is_alive():
                raise RuntimeError(f"{thread.name} did not stop within {timeout} s")
            error, self._error = self._error, None
            if error is not None:
                raise error
        finally:
            if thread is None or not thread.is_alive():
                for tap in self._taps:
                    tap.shutdown()

    @property
    def alive(self) -> bool:
        """The thread of :meth:`start` runs (False once it ended by itself: its bus failed)."""
        thread = self._thread
        return thread is not None and thread.is_alive()

    def _run_guarded(self, priority_drop: int) -> None:
        try:
            if priority_drop:
                lower_priority(priority_drop)   # this thread only (Linux)
            self.run_realtime()
        except BaseException as exc:   # surfaced by stop()
            self._error = exc

    # -- real time ------------------------------------------------------------------

    def run_realtime(self, on_tick: Callable[[float, float], None] | None = None,
                     at_tick_start: Callable[[], None] | None = None) -> None:
        """The ticks, until :meth:`stop` or the bus raises (BusError); ``on_tick`` and
        ``at_tick_start`` as for :meth:`EmulatedDrive.run_realtime`."""
        period = self.tick_period

        def tick(tick_start: float, deadline: float) -> None:
            if at_tick_start is not None:
                at_tick_start()
            self._ticks.receive_until(deadline, tick_start, self._take)
            for drive in self.drives:
                drive._advance_held(period)
            self._flush_crosstalk()
            if on_tick is not None:
                on_tick(deadline, time.perf_counter() - deadline)

        def skipped(count: int) -> None:
            self.overruns += count
            for drive in self.drives:
                drive.overruns += count

        run_ticks(period, lambda: self._stopped, tick, skipped)

    def _sent(self, tap: NodeTap, msg: can.Message) -> None:
        for other in self._taps:
            if other is not tap:
                other.inbox.append(msg)
        self._crosstalk = True

    def _flush_crosstalk(self) -> None:
        """The other nodes read what the nodes sent (and what they answer, in turn)."""
        while self._crosstalk:
            self._crosstalk = False
            for drive in self.drives:
                drive.handle_pending()

    def _take(self, batch: list[can.Message], tick_start: float, deadline: float) -> None:
        """Every node takes the batch (its protocol's filter keeps what is addressed to it),
        then reads what the others answered."""
        for drive in self.drives:
            drive._take(batch, tick_start, deadline)
        self._flush_crosstalk()

    def counters(self) -> dict[str, Any]:
        """Frame counters summed over the nodes (``dobhil emulate``'s last line)."""
        return {name: sum(getattr(d, name) for d in self.drives)
                for name in ("frames_received", "frames_not_addressed", "frames_sent", "send_errors")}
