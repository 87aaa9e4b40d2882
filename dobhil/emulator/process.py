"""The real-time emulated drive in a process of its own, so the loop it serves cannot starve it.

A drive has a CPU of its own; an emulator thread in the host's interpreter does not: it
needs the interpreter lock the control loop holds while it spins around each expected
frame, and a loop thread preempted while holding the lock stops the drive as well (on a
busy 2-core machine: feedback pauses of 14-88 ms, runs stopped on ``feedback_timeout``).
:class:`EmulatorProcess` runs the same :class:`~dobhil.drives.emulated.EmulatedDrive`
and the same :class:`~dobhil.emulator.plant.Plant` in a child process instead:

- frames cross on a :class:`~dobhil.emulator.pipe.PipeBus` (a local socket pair): the
  host's end is the bus the host talks on (``bus``); no thread on either side;
- a periodic send on the host's end (python-can ``send_periodic``: a host's SYNC) is
  done by the child, on the emulated drive's tick clock: each frame due goes out at the
  start of a tick, echoed to the host first, then read by the emulated drive -- as the
  kernel's broadcast manager sends it on SocketCAN, outside the host's interpreter;
- the child publishes its state after every tick into shared memory (an unlinked
  temporary file both processes map; a sequence counter around each write, so a reader
  retries instead of mixing two ticks, and never waits for the child): the ground truth
  (:attr:`EmulatorProcess.plant`, a :class:`PlantView`), the protocol state the host may
  look at (``protocol_state``, ``watchdog_tripped`` ...), frame counters, and how late its
  own ticks ran (:meth:`EmulatorProcess.starved`: the host, not the drive, is to blame
  when the emulated drive itself was not scheduled);
- the child dies with its parent: it blocks on its end of the socket pair, and reads the
  end of the stream when the parent's end closes -- also when the parent is killed. It
  ignores the stop signals (``forkserver.STOP_SIGNALS``: a Ctrl-C reaches the whole process
  group, and the drive must outlive the host's safe stop to confirm the disable, as a real
  drive would), and is started with them blocked, so that one sent before it ignores them waits and is dropped;
- every failure of the child reaches the host as one line: a FAILED record before it
  exits, or the end of the stream with its exit code (:class:`~can.CanOperationError` on
  the host's bus, a ``bus_error`` stop of the run), never a traceback;
- the child is forked from dobhil's fork server (:mod:`dobhil.forkserver`: one process per
  host that imported the drive code once; the two file descriptors and the pickled spec
  handed to it), not a ``multiprocessing`` process: those re-run the parent's main
  module, and a python-can program opening ``can.Bus(interface="dobhil")`` at the top of a
  script without a ``__main__`` guard would start itself again; never a bare ``fork`` of
  a process that may have threads. The first child of a host costs the server's start
  (an interpreter and the imports, 0.3-0.4 s of CPU here), each further one a fork (a few
  ms). Where the platform cannot fork a server's child (no ``os.fork`` or
  ``socket.send_fds``), the child is a fresh interpreter (``subprocess``, its spec pickled
  on its stdin).

Several nodes on one bus (a multi-axis device): ``EmulatorProcess([spec1, spec2],
couplings=...)`` runs every node's emulated drive in the one child, on one tick clock
(:class:`~dobhil.drives.emulated_nodes.EmulatedNodes`: any mix of protocols, each node
answering its own frames), their plants coupled by
:func:`~dobhil.emulator.coupling.couple_plants`; each node has its own block of the status
(:meth:`EmulatorProcess.node`, :meth:`EmulatorProcess.truth` by index or axis name). One
spec runs exactly as before.

The lockstep path (deterministic, simulated time) stays in-process: it has no clock to
fall behind.
"""

from __future__ import annotations

import atexit
import dataclasses
import gc
import math
import mmap
import os
import pickle
import signal
import socket
import subprocess
import sys
import tempfile
import time
import warnings
from array import array
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from enum import IntEnum
from typing import Any, cast

import can

from dobhil.config.axes import SINGLE_AXIS, Coupling
from dobhil.config.schema import Config
from dobhil.drives.profile import DriveProfile
from dobhil.emulator.pipe import PipeBus, RecordKind, socket_pair
from dobhil.drives.emulated import tick_period
from dobhil import forkserver
from dobhil.errors import BusError, exception_line

__all__ = ["EmulatorProcess", "EmulatorSpec", "NodeStatus", "PlantView", "Slot"]

#: how long a child may take to start (a loaded 2-core machine importing numpy): a bound
START_TIMEOUT = 60.0
#: how long a child may take to end after its bus closed, before it is killed
STOP_TIMEOUT = 2.0
#: a tick this many periods late is a stall of the emulated drive (it missed a frame)
STALL_PERIODS = 1.0
#: the share of a silent window the emulated drive must have stalled for the host to be blamed
STARVED_SHARE = 0.5
_READ_TRIES = 64


class Slot(IntEnum):
    """Layout of the shared status block (float64 each)."""

    SEQ = 0               # odd while the child writes
    TIME = 1              # emulator time [s]
    DEADLINE = 2          # perf_counter deadline of the newest tick
    TRUE_POSITION = 3
    TRUE_VELOCITY = 4
    MOTOR_TORQUE = 5
    INTERACTION_TORQUE = 6
    POSITION = 7          # measured (encoder)
    VELOCITY = 8
    APPLIED_TORQUE = 9
    FRAMES_RECEIVED = 10
    FRAMES_SENT = 11
    SEND_ERRORS = 12
    FRAME_ERRORS = 13
    OVERRUNS = 14         # ticks the emulator skipped (far behind)
    LATE_TICKS = 15       # ticks at least STALL_PERIODS late
    MAX_LATENESS = 16
    STALL_START = 17      # perf_counter deadline of the newest stalled tick
    STALL_LENGTH = 18     # how late it ran [s]
    PROTOCOL_STATE = 19   # the drive's own state code (NaN when the protocol has none)
    PROTOCOL_ERROR = 20   # the drive's own error code
    WATCHDOG_TRIPPED = 21
    FRAMES_REJECTED = 22


#: protocol state published when the emulator has it (an attribute of that name)
OBSERVED: dict[str, Slot] = {"protocol_state": Slot.PROTOCOL_STATE, "protocol_error": Slot.PROTOCOL_ERROR,
                             "watchdog_tripped": Slot.WATCHDOG_TRIPPED,
                             "frames_rejected": Slot.FRAMES_REJECTED}


@dataclass(frozen=True)
class EmulatorSpec:
    """What the child builds its emulated drive from (picklable)."""

    config: Config
    profile: DriveProfile
    latency: float = 0.0
    jitter: float = 0.0
    seed: int = 0
    priority_drop: int = 0   # nice increment of the child (0: the drive's own CPU)
    #: the drive's clock starts with the host's first frame (power on when the host is
    #: ready): a run's host starts up without frames piling up for it; False: at once
    on_first_frame: bool = False
    #: the axis this node drives (what couplings and :meth:`EmulatorProcess.node` name)
    name: str = SINGLE_AXIS

    @classmethod
    def of(cls, config: Config, profile: DriveProfile, *, priority_drop: int = 0,
           on_first_frame: bool = False, name: str = SINGLE_AXIS) -> EmulatorSpec:
        d = config.drive
        # the profile's bus settings are the host's business (and a read-only mapping)
        return cls(config, dataclasses.replace(profile, bus={}), d.latency, d.jitter,
                   config.sensor.seed, priority_drop, on_first_frame, name)


class PlantView:
    """The child's plant of node ``index`` as the host sees it: the ground truth of the
    newest tick."""

    def __init__(self, owner: EmulatorProcess, index: int = 0) -> None:
        self._owner = owner
        self._index = index

    def _get(self, slot: Slot) -> float:
        return self._owner.snapshot(self._index)[slot]

    @property
    def true_position(self) -> float:
        return self._get(Slot.TRUE_POSITION)

    @property
    def true_velocity(self) -> float:
        return self._get(Slot.TRUE_VELOCITY)

    @property
    def motor_torque(self) -> float:
        return self._get(Slot.MOTOR_TORQUE)

    @property
    def interaction_torque(self) -> float:
        return self._get(Slot.INTERACTION_TORQUE)

    @property
    def position(self) -> float:
        return self._get(Slot.POSITION)

    @property
    def velocity(self) -> float:
        return self._get(Slot.VELOCITY)

    @property
    def time(self) -> float:
        return self._get(Slot.TIME)


class _Shared:
    """The status blocks, one per node: float64 slots in an unlinked temporary file both
    processes map (the child finds how many from its size)."""

    def __init__(self, fd: int | None = None, nodes: int = 1) -> None:
        self._file = None
        if fd is None:
            self._file = tempfile.TemporaryFile()
            fd = self._file.fileno()
            os.ftruncate(fd, nodes * len(Slot) * 8)
        self.fd = fd
        size = os.fstat(fd).st_size
        self._map = mmap.mmap(fd, size)
        values = memoryview(self._map).cast("d")
        self.blocks = [values[i * len(Slot):(i + 1) * len(Slot)] for i in range(size // (8 * len(Slot)))]
        self.values = self.blocks[0]
        if self._file is not None:
            for block in self.blocks:
                block[:] = array("d", [math.nan] * len(Slot))
                block[Slot.SEQ] = 0.0


def _renamed(old: str, new: str) -> None:
    """Warn once per call site that ``old`` is ``new`` now: one name, one meaning (the drive's
    own code, where ``axis_*`` read as one protocol's word for every protocol)."""
    warnings.warn(f"EmulatorProcess.{old} is renamed {new}; {old} is removed in dobhil 0.2",
                  DeprecationWarning, stacklevel=3)


def warm_child() -> None:
    """What a child imports before it serves, done once in the fork server: every
    protocol's emulated drive (dobhil.drives.registry) and the plant's modules."""
    from dobhil.drives.registry import emulated_protocols
    import dobhil.drives.emulated_nodes
    import dobhil.emulator.coupling
    import dobhil.emulator.plant  # noqa: F401
    emulated_protocols()


#: the fork server's preload for the emulator's children
_PRELOAD = (f"{__name__}:warm_child",)


class EmulatorProcess:
    """The emulated drives of one bus in a child process; ``bus`` is the host's end of it.

    ``spec``: one node's :class:`EmulatorSpec`, or a sequence of them (distinct names and
    node ids; any mix of protocols), whose plants ``couplings`` join
    (:func:`~dobhil.emulator.coupling.couple_plants`). The observables without an index
    (``plant``, ``protocol_state``, ``frames_received`` ...) are the first node's;
    :meth:`node` gives any node's."""

    def __init__(self, spec: EmulatorSpec | Sequence[EmulatorSpec], *, channel: Any = None,
                 mirror: can.BusABC | None = None, receive_own_messages: bool = False,
                 start_timeout: float = START_TIMEOUT, couplings: Sequence[Coupling] = ()) -> None:
        self.specs = (spec,) if isinstance(spec, EmulatorSpec) else tuple(spec)
        self.couplings = tuple(couplings)
        _check_nodes(self.specs, self.couplings)
        self.spec = self.specs[0]
        self.profile = self.spec.profile
        self.names = tuple(s.name for s in self.specs)
        #: [s] the child's tick: the shortest of the nodes' (dobhil.drives.emulated_nodes)
        self.tick = min(tick_period(s.profile) for s in self.specs)
        self._closed = False
        self._process: subprocess.Popen[bytes] | forkserver.Child | None = None
        host_end, child_end = socket_pair()
        self._shared = _Shared(nodes=len(self.specs))
        self._last = [cast("list[float]", block.tolist()) for block in self._shared.blocks]
        self._nodes = tuple(NodeStatus(self, i) for i in range(len(self.specs)))
        # periodic frames (a host's SYNC) are sent by the child on its own clock
        self.bus = PipeBus(host_end, channel, gone=self._gone, mirror=mirror,
                           receive_own_messages=receive_own_messages, periodic_peer=True)
        try:
            try:
                self._process = self._start(child_end)
            finally:
                child_end.close()   # the child's copy is its own: ours would hide its end
            self._wait_ready(start_timeout)
            self._read_first_blocks(time.monotonic() + start_timeout)
        except BaseException:
            self.close()
            raise
        # a program that never closes this still ends without waiting for it: the child
        # reads the end of its stream once this process's end is closed -- here, or by the
        # kernel when the process ends in any way
        atexit.register(self.close)

    # -- life -----------------------------------------------------------------

    def _start(self, child_end: socket.socket) -> subprocess.Popen[bytes] | forkserver.Child:
        # the stop signals blocked while the child starts (it inherits the mask, ignores them,
        # then unblocks them, :func:`child_main`): a Ctrl-C in its first milliseconds ends
        # the drive no sooner than one later would -- after the host's safe stop
        old = signal.pthread_sigmask(signal.SIG_BLOCK, forkserver.STOP_SIGNALS)
        try:
            return self._spawn(child_end)
        finally:
            signal.pthread_sigmask(signal.SIG_SETMASK, old)

    def _spawn(self, child_end: socket.socket) -> subprocess.Popen[bytes] | forkserver.Child:
        fds = (child_end.fileno(), self._shared.fd)
        if forkserver.available():
            # forked from a process that imported the drive code once (dobhil/forkserver.py:
            # the imports are most of a start's CPU)
            return forkserver.server(_PRELOAD).start(f"{__name__}:child_main", (
                pickle.dumps((self.specs, self.couplings)),), fds)
        code = f"from {__name__} import child_main; child_main({fds[0]}, {fds[1]})"
        process = subprocess.Popen([sys.executable, "-c", code], pass_fds=fds, stdin=subprocess.PIPE,
                                   stdout=subprocess.DEVNULL, env=forkserver.child_env(), close_fds=True)
        assert process.stdin is not None
        try:
            process.stdin.write(pickle.dumps((self.specs, self.couplings)))
            process.stdin.close()
        except OSError:
            pass   # it is gone already: the wait for READY says how
        return process

    def _wait_ready(self, timeout: float) -> None:
        try:
            record = self.bus.read_record(time.monotonic() + timeout)
        except can.CanOperationError as exc:
            raise BusError(f"emulated drive did not start: {exc}") from None
        if record is None:
            raise BusError(f"emulated drive did not start within {timeout:g} s")
        text = record[1:].decode("utf-8", "replace")
        if record[0] == RecordKind.FAILED:
            raise BusError(f"emulated drive did not start: {text}")
        self.bus.peer_text = text

    def _read_first_blocks(self, deadline: float) -> None:
        """Read each node's first block once, consistently: the child published it before
        READY, but until a read succeeds :meth:`snapshot` answers with the blank block of shared
        memory (a protocol state of 0, not the one the drive is in). A child preempted in the
        middle of a write (a busy machine) is given the CPU until it finishes."""
        for index in range(len(self._last)):
            while self.snapshot(index)[Slot.SEQ] == 0.0:
                if time.monotonic() > deadline:
                    raise BusError(f"emulated drive {self.names[index]!r} published no status block")
                time.sleep(0.001)

    def _gone(self) -> str:
        process = self._process
        code = None
        if process is not None:
            try:
                code = process.wait(0.2)   # it is ending: its exit code names how
            except subprocess.TimeoutExpired:
                pass
        how = ("is still running" if code is None else f"exited with code {code}" if code >= 0
               else f"was killed by signal {signal.Signals(-code).name}")
        return f"the emulated drive's process {how} (its bus end closed)"

    @property
    def pid(self) -> int | None:
        return None if self._process is None else self._process.pid

    @property
    def running(self) -> bool:
        return not self._closed and self._process is not None and self._process.poll() is None

    def stop(self, timeout: float = STOP_TIMEOUT) -> None:
        """Close the host's end (the child reads the end of its stream and exits); kill it
        if it has not ended within ``timeout`` s. Never raises: a failure of the child
        reached the host as a bus error while it ran."""
        if self._closed:
            return
        self._closed = True
        atexit.unregister(self.close)
        self.bus.shutdown()
        process = self._process
        if process is None:
            return
        try:
            process.wait(timeout)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()
        self.snapshot()

    close = stop

    def __enter__(self) -> EmulatorProcess:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- observables -----------------------------------------------------------

    def snapshot(self, index: int = 0) -> list[float]:
        """The newest consistent status block of node ``index`` (the last one read if the
        child is writing every time it is looked at: the reader never waits for the child)."""
        status, last = self._shared.blocks[index], self._last[index]
        if status[Slot.SEQ] == last[Slot.SEQ]:
            return last   # no tick since: several reads in one cycle cost one look
        for _ in range(_READ_TRIES):
            seq = status[Slot.SEQ]
            if seq % 2 == 0:
                values = cast("list[float]", status.tolist())   # a 'd' view: floats
                if values[Slot.SEQ] == seq:
                    self._last[index] = values
                    break
        return self._last[index]

    def node(self, which: int | str = 0) -> NodeStatus:
        """One node's observables, by index (the order of the specs) or axis name."""
        if isinstance(which, str):
            if which not in self.names:
                raise KeyError(f"no node of axis {which!r}; axes: {', '.join(self.names)}")
            return self._nodes[self.names.index(which)]
        return self._nodes[which]

    @property
    def nodes(self) -> tuple[NodeStatus, ...]:
        return self._nodes

    @property
    def plant(self) -> PlantView:
        return PlantView(self)

    def truth(self, which: int | str = 0) -> tuple[float, float]:
        """Interaction torque [N m] and true position [rad] of one tick, of one node."""
        return self.node(which).truth()

    @property
    def time(self) -> float:
        return self.snapshot()[Slot.TIME]

    @property
    def applied_torque(self) -> float:
        return self._nodes[0].applied_torque

    @property
    def protocol_state(self) -> int:
        """The (first) emulated drive's own state code, as its protocol reports it."""
        return self._nodes[0].protocol_state

    @property
    def protocol_error(self) -> int:
        """The (first) emulated drive's own error code (0: none)."""
        return self._nodes[0].protocol_error

    @property
    def axis_state(self) -> int:
        """Deprecated name of :attr:`protocol_state` (removed in dobhil 0.2)."""
        _renamed("axis_state", "protocol_state")
        return self.protocol_state

    @property
    def axis_error(self) -> int:
        """Deprecated name of :attr:`protocol_error` (removed in dobhil 0.2)."""
        _renamed("axis_error", "protocol_error")
        return self.protocol_error

    @property
    def watchdog_tripped(self) -> bool:
        return self._nodes[0].watchdog_tripped

    @property
    def frames_received(self) -> int:
        return self._nodes[0].frames_received

    @property
    def frames_sent(self) -> int:
        return self._nodes[0].frames_sent

    @property
    def frames_rejected(self) -> int:
        return self._nodes[0].frames_rejected

    @property
    def send_errors(self) -> int:
        return self._nodes[0].send_errors

    @property
    def frame_errors(self) -> int:
        return self._nodes[0].frame_errors

    @property
    def overruns(self) -> int:
        return self._nodes[0].overruns

    @property
    def late_ticks(self) -> int:
        """Ticks the emulated drives ran at least a period late (they were not scheduled)."""
        return self._nodes[0].count(Slot.LATE_TICKS)

    @property
    def max_lateness(self) -> float:
        return self.snapshot()[Slot.MAX_LATENESS]

    def stalled(self, window: float, now: float | None = None) -> float:
        """How long the emulated drives were stalled (not scheduled) during the last
        ``window`` s: the newest stalled tick, or the tick owed now (one clock for all)."""
        now = time.perf_counter() if now is None else now
        s = self.snapshot()
        begin, period = now - window, self.tick
        past = _overlap(s[Slot.STALL_START], s[Slot.STALL_START] + s[Slot.STALL_LENGTH], begin, now)
        due = s[Slot.DEADLINE] + period   # the next tick's deadline
        ongoing = _overlap(due, now, begin, now) if now - due >= STALL_PERIODS * period else 0.0
        return max(past, ongoing)

    def starved(self, window: float) -> str:
        """Why the feedback stopped if the host, not the drive, is to blame: the emulated
        drive was itself not scheduled for at least half of the silent ``window``; "" if not,
        and "" when its process is gone (killed: a silent drive, whose last tick only looks
        like a stall that never ends)."""
        if not self.running:
            return ""
        stall = self.stalled(window)
        if not stall >= STARVED_SHARE * window:   # NaN: nothing published
            return ""
        return (f"the emulated drive itself was not scheduled for {stall * 1e3:.0f} ms of them "
                "(the host is too slow, not the drive)")


class NodeStatus:
    """One node of an :class:`EmulatorProcess`, as its child published it after its newest
    tick: the plant's truth and the drive's counters and protocol state."""

    def __init__(self, owner: EmulatorProcess, index: int) -> None:
        self._owner = owner
        self.index = index
        self.name = owner.specs[index].name
        self.profile = owner.specs[index].profile

    def count(self, slot: Slot) -> int:
        value = self._owner.snapshot(self.index)[slot]
        return int(value) if value == value else 0

    @property
    def plant(self) -> PlantView:
        return PlantView(self._owner, self.index)

    def truth(self) -> tuple[float, float]:
        """Interaction torque [N m] and true position [rad] of one tick."""
        s = self._owner.snapshot(self.index)
        return s[Slot.INTERACTION_TORQUE], s[Slot.TRUE_POSITION]

    @property
    def time(self) -> float:
        return self._owner.snapshot(self.index)[Slot.TIME]

    @property
    def applied_torque(self) -> float:
        return self._owner.snapshot(self.index)[Slot.APPLIED_TORQUE]

    @property
    def protocol_state(self) -> int:
        return self.count(Slot.PROTOCOL_STATE)

    @property
    def protocol_error(self) -> int:
        return self.count(Slot.PROTOCOL_ERROR)

    @property
    def watchdog_tripped(self) -> bool:
        return self._owner.snapshot(self.index)[Slot.WATCHDOG_TRIPPED] == 1.0

    @property
    def frames_received(self) -> int:
        return self.count(Slot.FRAMES_RECEIVED)

    @property
    def frames_sent(self) -> int:
        return self.count(Slot.FRAMES_SENT)

    @property
    def frames_rejected(self) -> int:
        return self.count(Slot.FRAMES_REJECTED)

    @property
    def send_errors(self) -> int:
        return self.count(Slot.SEND_ERRORS)

    @property
    def frame_errors(self) -> int:
        return self.count(Slot.FRAME_ERRORS)

    @property
    def overruns(self) -> int:
        return self.count(Slot.OVERRUNS)


def _check_nodes(specs: Sequence[EmulatorSpec], couplings: Sequence[Coupling]) -> None:
    """ValueError for nodes one bus cannot carry: none, two of one name or node id, a
    coupling to an axis that is not among them."""
    if not specs:
        raise ValueError("EmulatorProcess: expected at least one EmulatorSpec")
    names = [s.name for s in specs]
    for i, spec in enumerate(specs):
        if spec.name in names[:i]:
            raise ValueError(f"EmulatorProcess: two nodes are axis {spec.name!r}; each needs its own name")
        for other in specs[:i]:
            if other.profile.node_id == spec.profile.node_id:
                raise ValueError(f"EmulatorProcess: axes {other.name} and {spec.name} are both node "
                                 f"{spec.profile.node_id}; nodes on one bus need distinct ids")
    for c in couplings:
        for name in (c.a, c.b):
            if name not in names:
                raise ValueError(f"EmulatorProcess: coupling {c.a}-{c.b}: no node of axis {name!r}; "
                                 f"axes: {', '.join(names)}")


def _overlap(a0: float, a1: float, b0: float, b1: float) -> float:
    length = min(a1, b1) - max(a0, b0)
    return length if length > 0 else 0.0


# -- the child ---------------------------------------------------------------------

class _Publisher:
    """Writes the status block of one node after every tick (the child's side of
    :meth:`snapshot`); ``period``: the child's tick."""

    def __init__(self, status: Any, emulator: Any, plant: Any, period: float | None = None) -> None:
        self._status = status
        self._emulator = emulator
        self._plant = plant
        self._period = emulator.tick_period if period is None else period
        self._observed = [(slot, name) for name, slot in OBSERVED.items() if hasattr(emulator, name)]
        status[Slot.SEQ] = 0.0
        for slot in (Slot.LATE_TICKS, Slot.MAX_LATENESS, Slot.STALL_LENGTH):
            status[slot] = 0.0
        status[Slot.STALL_START] = -math.inf

    def tick(self, deadline: float, lateness: float) -> None:
        s, emu, plant = self._status, self._emulator, self._plant
        seq = s[Slot.SEQ] + 1.0
        s[Slot.SEQ] = seq
        s[Slot.TIME] = emu.time
        s[Slot.DEADLINE] = deadline
        s[Slot.TRUE_POSITION] = plant.true_position
        s[Slot.TRUE_VELOCITY] = plant.true_velocity
        s[Slot.MOTOR_TORQUE] = plant.motor_torque
        s[Slot.INTERACTION_TORQUE] = plant.interaction_torque
        s[Slot.POSITION] = plant.position
        s[Slot.VELOCITY] = plant.velocity
        s[Slot.APPLIED_TORQUE] = emu.applied_torque
        s[Slot.FRAMES_RECEIVED] = emu.frames_received
        s[Slot.FRAMES_SENT] = emu.frames_sent
        s[Slot.SEND_ERRORS] = emu.send_errors
        s[Slot.FRAME_ERRORS] = emu.frame_errors
        s[Slot.OVERRUNS] = emu.overruns
        for slot, name in self._observed:
            s[slot] = float(getattr(emu, name))
        if lateness >= STALL_PERIODS * self._period:
            s[Slot.LATE_TICKS] += 1.0
            s[Slot.STALL_START] = deadline
            s[Slot.STALL_LENGTH] = lateness
        if lateness > s[Slot.MAX_LATENESS]:
            s[Slot.MAX_LATENESS] = lateness
        s[Slot.SEQ] = seq + 1.0


def child_main(sock_fd: int, status_fd: int, specs_pickled: bytes | None = None) -> None:
    """The child: read its spec (``specs_pickled``, or pickled on its standard input),
    build the emulated drive, say READY, tick until the host's end closes."""
    # the drive outlives the host's signals: it must confirm the host's safe stop
    for sig in forkserver.STOP_SIGNALS:
        signal.signal(sig, signal.SIG_IGN)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, forkserver.STOP_SIGNALS)   # blocked by _start
    sock = socket.socket(fileno=sock_fd)
    sock.setblocking(False)
    status = _Shared(status_fd).blocks
    closed: list[bool] = []

    def gone() -> str:
        closed.append(True)
        return "host end closed"

    # a host that stops reading never stalls the drive's ticks: frames that find no room
    # are held, the newest per id, and go out once the host reads again
    bus = PipeBus(sock, "emulator", gone=gone, send_wait=0.0, coalesce=True, serve_periodic=True)
    try:
        specs, couplings = (pickle.loads(specs_pickled) if specs_pickled is not None
                            else pickle.load(sys.stdin.buffer))
        if len(specs) == 1 and not couplings:
            _serve(bus, status[0], specs[0])
        else:
            _serve_nodes(bus, status, specs, couplings)
    except can.CanOperationError as exc:
        if not closed:
            _fail(bus, f"emulated drive stopped: {exc}")
    except BaseException as exc:  # one line to the host, never a traceback
        _fail(bus, f"emulated drive failed: {exception_line(exc)}")
    finally:
        bus.shutdown()


def _fail(bus: PipeBus, text: str) -> None:
    bus.send_text(RecordKind.FAILED, text)
    bus.shutdown()
    sys.exit(1)


def _serve(bus: PipeBus, status: Any, spec: EmulatorSpec) -> None:
    from dobhil.emulator.plant import Plant
    from dobhil.drives.registry import make_emulated_drive
    from dobhil.realtime import lower_priority, raise_priority

    if spec.priority_drop:
        lower_priority(spec.priority_drop)   # the whole child: it has one thread
    else:
        # feedback timing: the drive is the loop's clock and has a CPU of its own; where the
        # OS allows it (root, CAP_SYS_NICE), ahead of ordinary processes, so parallel jobs
        # starve it less (docs/hardware.md gives the campaign runs completed
        # with and without it); where not, at the loop's priority, as before
        raise_priority()
    plant = Plant.from_config(spec.config)
    emulator = make_emulated_drive(bus, spec.profile, plant, latency=spec.latency,
                                   jitter=spec.jitter, seed=spec.seed)
    emulator.prepare()   # set-up costs before READY, not in a tick
    publisher = _Publisher(status, emulator, plant)
    publisher.tick(math.nan, 0.0)
    # everything imported and built so far is never garbage: out of the collector's way, or
    # a full collection over it (numpy, the config ...) stalls a tick for ~10 ms
    gc.collect()
    gc.freeze()
    bus.send_text(RecordKind.READY, f"{spec.profile.protocol} node {spec.profile.node_id}")
    if spec.on_first_frame:
        bus.wait_readable()
    emulator.run_realtime(publisher.tick, _periodic_sender(bus, emulator))


def _serve_nodes(bus: PipeBus, status: list[Any], specs: Sequence[EmulatorSpec],
                 couplings: Sequence[Coupling]) -> None:
    """:func:`_serve` for several nodes on the one bus: one tick clock, coupled plants."""
    from dobhil.drives.emulated_nodes import EmulatedNodes
    from dobhil.drives.registry import make_emulated_drive
    from dobhil.emulator.coupling import couple_plants
    from dobhil.emulator.plant import Plant
    from dobhil.realtime import lower_priority, raise_priority

    drop = max(s.priority_drop for s in specs)
    if drop:
        lower_priority(drop)
    else:
        raise_priority()   # as _serve: the drives' own CPU
    plants = couple_plants({s.name: Plant.from_config(s.config) for s in specs}, couplings)
    nodes = EmulatedNodes(bus)
    drives = [make_emulated_drive(nodes.tap(), s.profile, plants[s.name], latency=s.latency,
                                  jitter=s.jitter, seed=s.seed) for s in specs]
    nodes.attach(drives)
    nodes.prepare()
    publishers = [_Publisher(block, drive, plants[s.name], nodes.tick_period)
                  for block, drive, s in zip(status, drives, specs)]

    def publish(deadline: float, lateness: float) -> None:
        for publisher in publishers:
            publisher.tick(deadline, lateness)

    publish(math.nan, 0.0)
    gc.collect()
    gc.freeze()
    bus.send_text(RecordKind.READY, ", ".join(f"{s.name}: {s.profile.protocol} node {s.profile.node_id}"
                                              for s in specs))
    try:
        if any(s.on_first_frame for s in specs):
            bus.wait_readable()
        nodes.run_realtime(publish, _periodic_sender(bus, nodes))
    finally:
        nodes.stop()   # the nodes' taps closed, as the one drive's bus is


def _periodic_sender(bus: PipeBus, emulator: Any) -> Callable[[], None]:
    """At each tick's start: the periodic frames the host asked for that are due, echoed to
    the host first (on the wire before any answer; the host's end copies it to its mirror),
    then read by the emulated drive -- sent by this process on the drive's clock, outside
    the host's interpreter, as the kernel's broadcast manager sends on SocketCAN."""
    table = bus.periodic
    assert table is not None
    table.clock = lambda: emulator.time

    def at_tick_start() -> None:
        if not len(table):
            return
        for msg in table.due(emulator.time):
            msg.timestamp = time.time()   # the table's own copy, stamped as it goes out
            try:
                bus.send(msg)   # never blocks (held when the host is not reading)
            except can.CanError:
                pass   # the host's end is gone: the next read says so
            emulator.deliver(msg)
    return at_tick_start
