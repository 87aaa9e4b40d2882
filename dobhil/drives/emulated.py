"""Emulated drive, protocol side: a real participant on a python-can bus.

:class:`EmulatedDrive` owns its bus, answers frames addressed to its node and keeps the
protocol state; the dynamics are injected as a :class:`PlantLike`. Each protocol
subclass (``dobhil.drives.odrive.emulator``) fills in the hooks :meth:`EmulatedDrive._on_frame`,
:meth:`EmulatedDrive._on_time`, :meth:`EmulatedDrive._plant_torque` and
:meth:`EmulatedDrive._cyclic_frames`.

Two timing modes, one state machine:

- **lockstep** (deterministic, no threads): :meth:`EmulatedDrive.handle_pending` applies
  every frame already received without blocking; :meth:`EmulatedDrive.advance` steps the
  plant ``dt`` and emits the cyclic frames that fall due in that interval. A received
  frame takes effect ``latency`` s after it was received (the host's compute and bus
  delay, ``design.input_delay``), exactly: the plant steps to that instant with the torque
  held so far, the frame is applied, and the plant steps on -- each piece an exact ZOH
  step of the plant, so a command computed from the sample at ``t_k`` acts from
  ``t_k + latency``, as the sampled analysis with a fractional input delay models.
  :class:`LockstepBus` is the host's view of such a bus: whenever the host
  waits on ``recv(timeout)``, simulated time advances instead of wall time, so a
  :class:`dobhil.drives.base.Drive` built with ``clock=lockstep_bus.clock`` runs its
  timeouts in simulated seconds.
- **real time**: :meth:`EmulatedDrive.start` runs a thread on absolute
  ``time.perf_counter`` deadlines (period = the profile's encoder rate) with optional
  seeded latency and jitter before received commands take effect; :meth:`EmulatedDrive.stop`
  joins it and re-raises anything the thread raised.
"""

from __future__ import annotations

import errno
import heapq
import math
import random
import threading
import time
import uuid
from abc import ABC, abstractmethod
from collections import deque
from collections.abc import Callable, Sequence
from typing import Any, Protocol

import can
from can.broadcastmanager import (LimitedDurationCyclicSendTaskABC, ModifiableCyclicTaskABC,
                                  RestartableCyclicTaskABC)

from dobhil.drives.clocked import ClockedBus
from dobhil.drives.profile import DriveProfile
from dobhil.drives.ticks import TickReader, run_ticks
from dobhil.errors import BusError, exception_line
from dobhil.realtime import lower_priority

__all__ = ["EmulatedDrive", "LockstepBus", "LockstepPeriodicTask", "PlantLike", "lockstep_steps",
           "private_virtual_channel"]

_EPS = 1e-9
#: [s] real-time tick of an emulated drive whose protocol streams no feedback of its own
DEFAULT_TICK = 1e-3


#: errnos of a send that no later send can get through: the interface is down (ENETDOWN) or
#: gone (ENODEV; ENXIO once the socket's interface no longer exists). Linux's net/can/af_can.c
#: (``can_send``: ENETDOWN when the interface is not up) and net/can/raw.c (``raw_notify`` sets
#: ENETDOWN / ENODEV as the socket's pending error, which the next ``send`` or ``recv`` returns
#: -- whichever comes first -- and ``raw_sendmsg``: ENXIO).
BUS_GONE_ERRNOS = frozenset({errno.ENETDOWN, errno.ENODEV, errno.ENXIO})


def bus_gone(exc: can.CanError) -> bool:
    """True when a python-can error says the interface itself is down or gone (its
    ``error_code``, the errno python-can's SocketCAN bus passes on), not that it refused one
    frame (ENOBUFS: a full transmit queue drains)."""
    return exc.error_code in BUS_GONE_ERRNOS


def tick_period(profile: DriveProfile) -> float:
    """[s] an emulated drive's real-time tick: the profile's ``feedback_period`` (its
    cyclic frames are due on it), or :data:`DEFAULT_TICK` when the protocol streams none."""
    return DEFAULT_TICK if profile.feedback_period is None else profile.feedback_period


class PlantLike(Protocol):
    """The injected dynamics (not part of this package's protocol code)."""

    position: float  # rad, measured
    velocity: float  # rad/s, measured

    def step(self, torque_nm: float, dt: float) -> None:
        """Advance ``dt`` seconds with this motor torque."""


class _Cyclic:
    """One cyclic stream: emit at k * period for k = 1, 2, ..."""

    __slots__ = ("period", "make", "index")

    def __init__(self, period: float, make: Callable[[], can.Message]) -> None:
        self.period = period
        self.make = make
        self.index = 1

    def due(self, now: float) -> int:
        count = 0
        while self.index * self.period <= now + _EPS:
            self.index += 1
            count += 1
        return count


class EmulatedDrive(ABC):
    """Base of emulated drives. The bus is owned: :meth:`close` shuts it down."""

    def __init__(
        self, bus: can.BusABC, profile: DriveProfile, plant: PlantLike, *,
        latency: float = 0.0, jitter: float = 0.0, seed: int = 0,
    ) -> None:
        if latency < 0 or jitter < 0:
            raise ValueError(f"latency and jitter: expected >= 0 s, got {latency}, {jitter}")
        self._bus = bus
        self._profile = profile
        self._plant = plant
        self._latency = latency
        self._jitter = jitter
        self._rng = random.Random(seed)
        self._time = 0.0
        self._delayed: list[tuple[float, int, can.Message]] = []
        self._delay_seq = 0
        self._last_apply = 0.0
        self._cyclic: list[_Cyclic] = []
        self._thread: threading.Thread | None = None
        self._stop_event = threading.Event()
        self._thread_error: BaseException | None = None
        self._priority_drop = 0
        self.frames_received = 0
        #: frames received that were for another node or not of this protocol (a shared bus
        #: carries every node's traffic; the protocol's own filter decides, nothing is applied)
        self.frames_not_addressed = 0
        self.frame_errors = 0  # frames whose handling raised (a bug: tests demand 0)
        self.last_frame_error = ""
        self.frames_sent = 0
        self.send_errors = 0
        self.overruns = 0
        #: real time: the frames already queued behind the one being handled, read with it
        #: (empty in lockstep): a protocol may skip work a newer frame supersedes
        self._queued_after: Sequence[can.Message] = ()
        #: real time: the bus read into ticks (dobhil.drives.ticks)
        self._ticks = TickReader(bus, self._stop_event.is_set)

    # -- observables ----------------------------------------------------------

    @property
    def profile(self) -> DriveProfile:
        return self._profile

    @property
    def plant(self) -> PlantLike:
        return self._plant

    @property
    def time(self) -> float:
        """Emulator time [s]: simulated in lockstep, ticks * period in real time."""
        return self._time

    @property
    def applied_torque(self) -> float:
        """Torque [Nm] the plant receives now."""
        return self._plant_torque()

    # -- lockstep -------------------------------------------------------------

    def handle_pending(self, limit: int | None = None) -> int:
        """Apply the frames already received (never blocks); returns how many were read.

        ``limit``: read at most this many (a caller that knows how many frames were
        sent saves the final empty read).
        """
        count = 0
        recv = self._bus.recv
        while limit is None or count < limit:
            msg = recv(0.0)
            if msg is None:
                break
            count += 1
            self._receive(msg, self._time)
        delayed = self._delayed
        if delayed and delayed[0][0] <= self._time + _EPS:   # inline: a frame is due at most
            self._apply_due(self._time)                      # once a period, not every call
        return count

    def advance(self, dt: float) -> None:
        """Step the plant ``dt`` s; frames due inside the interval take effect at their
        instant (the plant steps to it with the torque held so far). Emit the cyclic
        frames due by the end."""
        if dt <= 0:
            raise ValueError(f"dt: expected > 0 s, got {dt}")
        end = self._time + dt
        rest = dt
        delayed = self._delayed
        while delayed and delayed[0][0] < end - _EPS:
            at = delayed[0][0]
            if at > self._time + _EPS:
                # the pieces' lengths are rounded to 1e-12 s, so a periodic delay gives
                # the same two lengths every period (the plant caches its ZOH matrices
                # per length); the end of the step stays exact
                self._plant.step(self._plant_torque(), round(at - self._time, 12))
                self._time = at
                rest = round(end - at, 12)
            self._apply_due(at)
        self._plant.step(self._plant_torque(), rest)
        self._time = end
        if delayed and delayed[0][0] <= end + _EPS:   # inline: rarely any left due
            self._apply_due(end)
        self._on_time(end)
        self._emit_cyclic(self._time)

    def _advance_held(self, dt: float) -> None:
        """Real time: step the whole ``dt`` with the current torque (frames received
        meanwhile were applied when their wall-clock delay ran out)."""
        self._plant.step(self._plant_torque(), dt)
        self._time += dt
        self._apply_due(self._time)
        self._on_time(self._time)
        self._emit_cyclic(self._time)

    # -- real time ------------------------------------------------------------

    @property
    def tick_period(self) -> float:
        """[s] the real-time tick (:func:`tick_period` of the profile)."""
        return tick_period(self._profile)

    def prepare(self) -> None:
        """Pay every one-off set-up cost now, before the first frame: the plant's matrices
        for the real-time tick and the protocol's own (:meth:`_warm_up`). A drive answers its
        first frame as promptly as its thousandth; an emulator that built a table at the first
        frame answered it most of a second late in a slow guest (a host refused to enable)."""
        prepare = getattr(self._plant, "prepare", None)
        if callable(prepare):
            prepare(self.tick_period)
        self._warm_up()

    def start(self, *, priority_drop: int = 0) -> None:
        """Run on a thread of its own (period: :attr:`tick_period`), its nice
        value raised by ``priority_drop`` where the OS allows (below the control loop)."""
        if self._thread is not None:
            raise RuntimeError("emulator already started")
        self.prepare()  # one-off set-up cost here, not in the first real-time tick
        self._stop_event.clear()
        self._priority_drop = priority_drop
        self._thread = threading.Thread(
            target=self._run_guarded, name=f"{type(self).__name__}-node{self._profile.node_id}"
        )
        self._thread.start()

    def stop(self, timeout: float = 2.0) -> None:
        """Stop and join the thread; re-raise what it raised. No-op if not started."""
        thread, self._thread = self._thread, None
        if thread is None:
            return
        self._stop_event.set()
        thread.join(timeout)
        if thread.is_alive():
            raise RuntimeError(f"{thread.name} did not stop within {timeout} s")
        error, self._thread_error = self._thread_error, None
        if error is not None:
            raise error

    @property
    def running(self) -> bool:
        return self._thread is not None

    @property
    def alive(self) -> bool:
        """The thread runs; False once it ended by itself (its bus failed: :meth:`stop`
        raises the BusError) or was never started."""
        thread = self._thread
        return thread is not None and thread.is_alive()

    def close(self) -> None:
        """Stop the thread (if any) and shut the owned bus down."""
        try:
            self.stop()
        finally:
            self._bus.shutdown()

    def __enter__(self) -> EmulatedDrive:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def deliver(self, msg: can.Message) -> None:
        """A frame the bus itself puts on the wire now (a periodic frame the emulator
        process sends for the host, as a kernel's broadcast manager would), received as
        if read from the bus at the emulator's current time."""
        self._receive(msg, self._time)
        self._apply_due(self._time)

    # -- hooks ----------------------------------------------------------------

    @abstractmethod
    def _on_frame(self, msg: can.Message) -> None:
        """Apply one received frame (ignore frames not addressed to this node)."""

    @abstractmethod
    def _on_time(self, now: float) -> None:
        """Time-driven protocol behaviour at ``now`` (watchdogs)."""

    @abstractmethod
    def _plant_torque(self) -> float:
        """Torque [Nm] applied to the plant in the current protocol state."""

    @abstractmethod
    def _cyclic_frames(self) -> Sequence[tuple[float, Callable[[], can.Message]]]:
        """(period [s], frame factory) of each cyclic message."""

    def _warm_up(self) -> None:
        """The protocol's one-off set-up costs (code tables ...), paid by :meth:`prepare`."""
        return

    # -- helpers for subclasses -------------------------------------------------

    def _superseded(self, arbitration_id: int) -> bool:
        """Real time: a frame with ``arbitration_id`` is already queued behind the one being
        handled (it came while the drive was busy); always False in lockstep."""
        return any(m.arbitration_id == arbitration_id for m in self._queued_after)

    def _send(self, msg: can.Message) -> None:
        try:
            self._bus.send(msg)
        except can.CanError as exc:
            if not bus_gone(exc):   # refused (ENOBUFS: the queue is full): counted, the drive goes on
                self.send_errors += 1
                return
            raise BusError(f"{self._bus.channel_info}: send failed: {exception_line(exc)}") from exc
        except Exception as exc:  # a transport's own error (a hub gone): the bus is gone
            raise BusError(f"{self._bus.channel_info}: send failed: {exception_line(exc)}") from exc
        self.frames_sent += 1

    # -- internals ------------------------------------------------------------

    def _receive(self, msg: can.Message, now: float) -> None:
        self.frames_received += 1
        delay = self._latency + (self._rng.uniform(0.0, self._jitter) if self._jitter else 0.0)
        if delay <= 0.0 and not self._delayed:
            self._dispatch(msg)
            return
        apply_at = max(now + delay, self._last_apply)  # CAN keeps frame order
        self._last_apply = apply_at
        self._delay_seq += 1
        heapq.heappush(self._delayed, (apply_at, self._delay_seq, msg))

    def _apply_due(self, now: float) -> None:
        while self._delayed and self._delayed[0][0] <= now + _EPS:
            self._dispatch(heapq.heappop(self._delayed)[2])

    def _dispatch(self, msg: can.Message) -> None:
        """Apply one frame. A drive never stops because of what arrives on its bus: a
        frame whose handling raises is counted (``frame_errors``, the text in
        ``last_frame_error``) and dropped; protocols reject malformed frames themselves,
        so a nonzero count is an emulator bug the property tests look for. The bus gone
        while the frame was answered (:meth:`_send`'s BusError) is no fault of the frame:
        it ends the drive as any other send into a bus that is gone does."""
        try:
            self._on_frame(msg)
        except BusError:
            raise
        except Exception as exc:  # last line of defence of a bus participant
            self.frame_errors += 1
            self.last_frame_error = exception_line(exc)

    def _emit_cyclic(self, now: float) -> None:
        cyclic = self._cyclic
        if not cyclic:
            cyclic = self._cyclic = [_Cyclic(p, make) for p, make in self._cyclic_frames()]
        limit = now + _EPS
        for stream in cyclic:
            # inline, :meth:`_Cyclic.due`'s first test: a slow stream (a heartbeat) is not
            # due in most steps, and then costs no call
            if stream.index * stream.period <= limit:
                for _ in range(stream.due(now)):
                    self._send(stream.make())

    def _run_guarded(self) -> None:
        try:
            if self._priority_drop:
                lower_priority(self._priority_drop)  # this thread only (Linux)
            self._run()
        except BaseException as exc:  # surfaced by stop()
            self._thread_error = exc

    def _run(self) -> None:
        self.run_realtime()

    def run_realtime(self, on_tick: Callable[[float, float], None] | None = None,
                     at_tick_start: Callable[[], None] | None = None) -> None:
        """The real-time ticks on the calling thread, until :meth:`stop` (from another
        thread) or until the bus raises. ``on_tick(deadline, lateness)`` after each tick:
        its deadline (``time.perf_counter``) and how late its frames went out -- the
        emulator's own measure of being starved (a process of its own publishes it).
        ``at_tick_start()`` before each tick reads the bus: a bus that sends periodic
        frames itself delivers them then (:meth:`deliver`)."""
        period = self.tick_period

        def tick(tick_start: float, deadline: float) -> None:
            if at_tick_start is not None:
                at_tick_start()
            self._ticks.receive_until(deadline, tick_start, self._take)
            self._advance_held(period)
            if on_tick is not None:
                on_tick(deadline, time.perf_counter() - deadline)

        def skipped(count: int) -> None:
            self.overruns += count

        run_ticks(period, self._stop_event.is_set, tick, skipped)

    def _take(self, batch: list[can.Message], tick_start: float, deadline: float) -> None:
        """Receive ``batch`` at the emulator time of now, within this tick, each frame knowing
        what was queued behind it (:meth:`_superseded`)."""
        if not batch:
            return
        now = self._time + min(max(0.0, time.perf_counter() - tick_start), deadline - tick_start)
        for i, msg in enumerate(batch):
            self._queued_after = batch[i + 1:]
            try:
                self._receive(msg, now)
            finally:
                self._queued_after = ()
        self._apply_due(now)


def lockstep_steps(period: float, dt: float) -> int:
    """How many lockstep steps ``dt`` a periodic send of ``period`` s takes: a whole number
    >= 1 (to a relative 1e-9, float sums), or 0 when ``period`` is none such -- the
    :class:`LockstepBus` fires periodic frames only at its steps, and refuses such a task
    (:func:`dobhil.runtime.session.check_lockstep` refuses the run before a bus opens)."""
    steps = round(period / dt) if math.isfinite(period) and period > 0 and dt > 0 else 0
    return steps if steps >= 1 and abs(steps * dt - period) <= 1e-9 * period else 0


def _stamped(msg: can.Message, stamp: float) -> can.Message:
    """A received copy of ``msg`` stamped ``stamp`` (each reader gets its own)."""
    return can.Message(timestamp=stamp, arbitration_id=msg.arbitration_id, is_extended_id=msg.is_extended_id,
                       is_remote_frame=msg.is_remote_frame, is_error_frame=msg.is_error_frame, is_fd=msg.is_fd,
                       bitrate_switch=msg.bitrate_switch, error_state_indicator=msg.error_state_indicator,
                       dlc=msg.dlc, data=bytes(msg.data), channel=msg.channel, is_rx=True, check=False)


class LockstepPeriodicTask(LimitedDurationCyclicSendTaskABC, ModifiableCyclicTaskABC,
                           RestartableCyclicTaskABC):
    """A periodic send of a :class:`LockstepBus`, in simulated time.

    Its frames go out every ``period`` s of the lockstep clock (a whole number of steps
    ``dt``), the first one period after :meth:`start` -- as the kernel's broadcast manager
    does without TX_ANNOUNCE -- each message of ``messages`` in turn. ``duration``:
    simulated seconds after which it stops by itself (None: until :meth:`stop`).
    ``modify_data`` (python-can's) changes the frames from the next one on. The bus
    sends them at their steps (:meth:`take_frame`); the task only counts steps.
    """

    def __init__(self, bus: LockstepBus, messages: Sequence[can.Message] | can.Message, period: float,
                 steps: int, duration: float | None = None, *, autostart: bool = True,
                 modifier_callback: Callable[[can.Message], None] | None = None) -> None:
        super().__init__(messages, period, duration)
        self._bus = bus
        self.steps = steps            # lockstep steps per period
        self._modifier = modifier_callback
        self.next_step = -1           # bus step of the next frame (-1: stopped)
        self._last_step = -1          # the last step a frame may go out at (-1: no end)
        self._index = 0               # the message sent next
        if autostart:
            self.start()

    @property
    def running(self) -> bool:
        return self.next_step >= 0

    def start(self) -> None:
        """(Re)start: the next frame one period from now."""
        now = self._bus.steps
        self.next_step = now + self.steps
        self._last_step = -1 if self.duration is None else \
            now + self.steps * math.floor(self.duration / self.period + _EPS)
        self._index = 0
        self._bus.add_task(self)
        if self._last_step >= 0 and self.next_step > self._last_step:
            self.stop()   # shorter than one period: nothing to send

    def stop(self) -> None:
        self.next_step = -1
        self._bus.remove_task(self)

    def take_frame(self) -> can.Message:
        """The frame due now (the bus calls this at :attr:`next_step`); advances to the next
        message and the next period."""
        msg = self.messages[self._index % len(self.messages)]
        self._index += 1
        if self._modifier is not None:
            self._modifier(msg)
        self.next_step += self.steps
        if 0 <= self._last_step < self.next_step:
            self.stop()
        return msg


class LockstepBus(ClockedBus):
    """Host-side view of a bus shared with lockstep emulators.

    ``recv(timeout)`` first lets every emulator apply what it received; if no frame is
    waiting for the host it advances every emulator by ``dt`` and tries again, until
    ``timeout`` simulated seconds have passed; a frame ``set_filters`` rejects does not end
    the wait (:mod:`dobhil.drives.clocked`). ``recv(0)`` never advances time. The
    wrapped bus is borrowed: :meth:`shutdown` leaves it open.

    The host and these emulators must be the only participants of the channel (a
    private ``virtual`` channel): the bus counts the frames in flight in each
    direction and reads exactly those, so no read comes back empty.

    Periodic send (python-can's ``send_periodic``) is native here, in simulated time:
    a task's frame goes out at every ``k * period`` (k = 1, 2, ...) after its start, the
    period a whole number of steps ``dt``. At that instant -- right after the emulators
    advanced to it, before anything else happens at it -- the emulators read it (and
    answer it at the same simulated instant: a CiA 402 node's TPDOs on a SYNC), and the
    host's ``recv`` returns it too, before those answers, stamped with the simulated
    time, as SocketCAN loops the kernel's broadcast-manager frames back to the other
    sockets of the host. Deterministic, like everything else here. An emulator built
    with a ``latency`` applies a periodic frame that much later too (it cannot tell who
    sent it): protocols that latch commands on such a frame run with latency 0.
    """

    #: send_periodic runs outside the host's Python threads (dobhil.drives.periodic)
    native_periodic = True

    def __init__(
        self, inner: can.BusABC, emulators: Sequence[EmulatedDrive], *, dt: float, **kwargs: Any
    ) -> None:
        if dt <= 0 or not emulators:
            raise ValueError(f"LockstepBus needs dt > 0 and an emulator, got dt={dt}, {len(emulators)}")
        self._inner = inner
        self._emulators = tuple(emulators)
        self._lead = self._emulators[0]   # whose time is the clock
        self._dt = dt
        self.channel_info = f"lockstep over {inner.channel_info}"
        self._to_emulators = 0  # host frames the emulators have not read yet
        self._to_host = 0       # emulator frames the host has not read yet
        self.steps = 0          # steps dt taken (the periodic tasks' clock: exact)
        self._tasks: list[LockstepPeriodicTask] = []   # running, in start order
        #: frames for the host taken off the inner bus in order, and the periodic frames'
        #: echoes between them (the host reads this first)
        self._host_queue: deque[can.Message] = deque()
        super().__init__(channel=self.channel_info, **kwargs)
        # the host's view carries what the channel carries (CAN FD)
        self._can_protocol = getattr(inner, "protocol", can.CanProtocol.CAN_20)

    @property
    def dt(self) -> float:
        return self._dt

    def clock(self) -> float:
        """Simulated time [s] (pass as ``clock=`` to the host's Drive): the first
        emulator's :attr:`EmulatedDrive.time`, read without the property's call (this
        module's own class; the host reads it about seven times a cycle)."""
        return self._lead._time

    def step(self) -> None:
        """One lockstep tick: every emulator applies pending frames, then advances ``dt``."""
        self._deliver_host_frames()
        self._advance_all()

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self._inner.send(msg, timeout)
        self._to_emulators += 1

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        """The whole wait, in simulated seconds (:mod:`dobhil.drives.clocked`): a frame the
        filters reject is dropped and the wait goes on to the same simulated deadline."""
        if timeout is None:
            raise ValueError("LockstepBus.recv needs a finite timeout (simulated seconds)")
        # A positive wait takes at least one step, however short: the clock is a sum of
        # steps dt, so a caller's deadline (enable, the safe stop's confirmation) can lie
        # 1e-13 s past it, and a wait that returned at once without advancing would be
        # asked for again and again, for ever. ``recv(0)`` never advances, so it never
        # reads the clock either (a cycle's drains are such reads: two a cycle).
        must_step = timeout > 0
        end = self.clock() + timeout if must_step else 0.0
        # The host and the emulators are the only participants of the channel, and the
        # host is inside this call: the bus counts the frames in flight each way, so no
        # read comes back empty (the bare-bus cost is two reads per cycle, so is this).
        if self._to_emulators:
            self._deliver_host_frames()
        host_queue = self._host_queue
        while True:
            msg: can.Message | None = None
            if host_queue:
                msg = host_queue.popleft()
            elif self._to_host > 0:
                msg = self._inner.recv(0.0)
                self._to_host = self._to_host - 1 if msg is not None else 0
            if msg is None:
                # the first step of a positive wait is taken without looking at the clock
                if not must_step and (timeout <= 0 or self.clock() + _EPS >= end):
                    return None, True
                self._advance_all()
                must_step = False
            elif not self.filtering or self._matches_filters(msg):
                return msg, True

    def _sent_by_emulators(self) -> int:
        total = 0
        for emulator in self._emulators:
            total += emulator.frames_sent
        return total

    def _deliver_host_frames(self) -> None:
        emulators = self._emulators
        before = 0
        for emulator in emulators:   # inline, not _sent_by_emulators: once a cycle
            before -= emulator.frames_sent
        count, self._to_emulators = self._to_emulators, 0
        for emulator in emulators:
            emulator.handle_pending(count)
        for emulator in emulators:
            before += emulator.frames_sent
        self._to_host += before

    def _advance_all(self) -> None:
        emulators, dt = self._emulators, self._dt
        before = 0
        for emulator in emulators:   # inline, not _sent_by_emulators: once a cycle
            before -= emulator.frames_sent
        for emulator in emulators:
            emulator.advance(dt)
        for emulator in emulators:
            before += emulator.frames_sent
        self._to_host += before
        self.steps += 1
        if self._tasks:
            self._fire_periodic()

    # -- periodic send (python-can's hook for a backend's own periodic send) ----------

    def _send_periodic_internal(
        self, msgs: Sequence[can.Message] | can.Message, period: float, duration: float | None = None,
        autostart: bool = True, modifier_callback: Callable[[can.Message], None] | None = None,
    ) -> LockstepPeriodicTask:
        steps = lockstep_steps(period, self._dt)
        if not steps:
            raise ValueError(f"send_periodic period {period!r} s: expected a whole multiple (>= 1) of "
                             f"the lockstep step dt = {self._dt!r} s")
        return LockstepPeriodicTask(self, msgs, period, steps, duration, autostart=autostart,
                                    modifier_callback=modifier_callback)

    def add_task(self, task: LockstepPeriodicTask) -> None:
        """Fire ``task`` at its steps (its :meth:`~LockstepPeriodicTask.start` calls this)."""
        if task not in self._tasks:
            self._tasks.append(task)

    def remove_task(self, task: LockstepPeriodicTask) -> None:
        """Fire ``task`` no more (its :meth:`~LockstepPeriodicTask.stop` calls this)."""
        if task in self._tasks:
            self._tasks.remove(task)

    def _fire_periodic(self) -> None:
        """The periodic frames due at this step: to the emulators, which read them (and
        answer) now, and echoed to the host after the frames the emulators sent before.

        The emulators get each frame straight (:meth:`EmulatedDrive.deliver`), not through
        the inner bus: it is the bus's own frame, read at this instant, after whatever the
        host sent before it; this saves the ``virtual`` bus's copy of a frame every
        period (a quarter of a CiA 402 cycle's bus cost)."""
        steps = self.steps
        due = [task for task in self._tasks if task.next_step == steps]
        if not due:
            return
        if self._to_emulators:   # what the host sent before this instant comes first
            self._deliver_host_frames()
        now = self.clock()
        for task in due:
            # the echo after what the emulators sent before it, their answers after it
            self._take_host_frames()
            msg = task.take_frame()
            self._host_queue.append(_stamped(msg, now))
            before = self._sent_by_emulators()
            for emulator in self._emulators:
                emulator.deliver(_stamped(msg, now))
            self._to_host += self._sent_by_emulators() - before

    def _take_host_frames(self) -> None:
        """Move the frames in flight to the host off the inner bus, in order, so what
        comes after them (an echo) is read after them."""
        recv, queue = self._inner.recv, self._host_queue
        while self._to_host > 0:
            msg = recv(0.0)
            if msg is None:
                self._to_host = 0
                break
            self._to_host -= 1
            queue.append(msg)


def private_virtual_channel() -> str:
    """A virtual-bus channel name no other run in this process uses.

    It ends in a letter: python-can's log writers read trailing digits of a channel name
    as the channel number (``can.util.channel2int``), and BLF stores it in 16 bits, so a
    name ending in many digits would make ``can.logconvert run.mcap run.blf`` fail."""
    return f"dobhil-{uuid.uuid4().hex[:12]}-private"
