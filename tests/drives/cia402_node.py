"""A CiA 402 test node written in the test tree, independent of dobhil's emulator.

What it is made of, and why:

- canopen's own :class:`canopen.LocalNode` gives the SDO server, the NMT slave, the
  heartbeat producer and EMCY: other people's code, so a dobhil drive that talks to
  it is checked against an implementation dobhil did not write. Its object dictionary
  is the project's EDS (``drivers/cia402-emulated.eds``): only the objects, read by
  canopen's EDS parser.
- canopen's ``LocalNode`` does not send TPDOs on SYNC, nor apply RPDOs (canopen
  issue #555): :meth:`TestNode402._on_sync` does both, from the mapping the host wrote
  into the node's object dictionary by SDO (read back with canopen's own ``PdoMap.read``).
- a SMALL power state machine of its own (:func:`next_state`, the CiA 402 transition
  table), not the emulator's: two independent readings of the standard meet on the bus.
- a trivial plant: a rigid inertia ``J`` driven by ``torque = target per mille * rated``
  while Operation enabled in CST, held between SYNCs (exact double-integrator step).

Two ways to run it:

- **pumped** (deterministic, no threads): :class:`PumpBus` is the host's bus; every
  frame the host sends reaches the node at once (``network.notify`` from
  :meth:`TestNode402.pump`), and time is simulated: ``recv(timeout)`` advances it, firing
  the host's periodic frames (SYNC, ``send_periodic`` in simulated time, echoed back to
  the host as SocketCAN's broadcast manager does) and the node's heartbeat.
  :class:`PumpedNetwork` is the same for a host written with canopen itself.
- **real time**: :meth:`TestNode402.start` runs canopen's own notifier thread on the
  node's bus (``Network.connect`` on an existing bus).

Frames of both sides travel on a python-can ``virtual`` channel of the test.
"""

from __future__ import annotations

import math
import struct
from collections import deque
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from enum import IntEnum
from pathlib import Path
from typing import Any

import can
import canopen
from can.broadcastmanager import CyclicSendTaskABC
from canopen.pdo import PdoMap

from dobhil.drives.waits import WAIT_SLICE

__all__ = ["EDS", "RIG_UNITS", "HostSyncPumpBus", "NodeState", "PumpBus", "PumpedNetwork", "TestNode402",
           "next_state", "with_rig_units"]

#: the project's EDS of a CiA 402 servo (objects only: the behaviour here is this file's)
EDS = Path(__file__).resolve().parents[2] / "drivers" / "cia402-emulated.eds"

#: this node's units (not the shipped profile's 20-bit encoder): 0x6064 at 4096 increments per
#: revolution, 0x606C in rpm; it states them in 0x608F and 0x6091, which the host checks
RIG_UNITS = {"position_per_rev": 4096, "velocity_unit": "rpm", "gear_ratio": 1.0}

SYNC_ID = 0x80
CST = 10
_EPS = 1e-9


class NodeState(IntEnum):
    """The power states with the statusword value this node reports (bits 0-6)."""

    NOT_READY = 0x00
    SWITCH_ON_DISABLED = 0x40
    READY_TO_SWITCH_ON = 0x21
    SWITCHED_ON = 0x23
    OPERATION_ENABLED = 0x27
    QUICK_STOP_ACTIVE = 0x07
    FAULT_REACTION_ACTIVE = 0x0F
    FAULT = 0x08


_S = NodeState
#: bit 4 (voltage enabled) where the power stage is on
_VOLTAGE = {_S.READY_TO_SWITCH_ON, _S.SWITCHED_ON, _S.OPERATION_ENABLED, _S.QUICK_STOP_ACTIVE}


def next_state(state: NodeState, cw: int, previous_cw: int) -> NodeState:
    """The CiA 402 device control transitions (this test's own reading of the standard).

    Commands by controlword bits (fault reset bit 7, enable operation 3, quick stop 2,
    enable voltage 1, switch on 0): disable voltage ``xxxx xx0x``, quick stop
    ``xxxx x01x``, shutdown ``xxxx x110``, switch on ``xxxx 0111``, enable operation
    ``xxxx 1111``, fault reset: rising edge of bit 7.
    """
    if state is _S.FAULT:
        return _S.SWITCH_ON_DISABLED if cw & 0x80 and not previous_cw & 0x80 else state
    if state in (_S.NOT_READY, _S.FAULT_REACTION_ACTIVE) or cw & 0x80:
        return state
    if not cw & 0x02:                                     # disable voltage: 7, 9, 10, 12
        return _S.SWITCH_ON_DISABLED
    if not cw & 0x04:                                     # quick stop: 11 (7, 10 elsewhere)
        if state is _S.OPERATION_ENABLED:
            return _S.QUICK_STOP_ACTIVE
        return state if state is _S.QUICK_STOP_ACTIVE else _S.SWITCH_ON_DISABLED
    if cw & 0x0F == 0x06:                                 # shutdown: 2, 6, 8
        return state if state is _S.QUICK_STOP_ACTIVE else _S.READY_TO_SWITCH_ON
    if cw & 0x0F == 0x07:                                 # switch on: 3, 5
        return {_S.READY_TO_SWITCH_ON: _S.SWITCHED_ON,
                _S.OPERATION_ENABLED: _S.SWITCHED_ON}.get(state, state)
    if cw & 0x0F == 0x0F:                                 # enable operation: 3 then 4, 16
        return {_S.READY_TO_SWITCH_ON: _S.SWITCHED_ON, _S.SWITCHED_ON: _S.OPERATION_ENABLED,
                _S.QUICK_STOP_ACTIVE: _S.OPERATION_ENABLED}.get(state, state)
    return state


# ---------------------------------------------------------------------------
# Periodic frames in simulated time


class SimTask(CyclicSendTaskABC):
    """A periodic frame in simulated time: due at ``start + k * period`` (k = 1, 2, ...)."""

    def __init__(self, msg: can.Message, period: float, start: float,
                 fire: Callable[[can.Message], None]) -> None:
        super().__init__(msg, period)
        self.msg = msg
        self._start = start
        self._k = 1
        self._fire = fire
        self.stopped = False

    def due(self) -> float:
        return math.inf if self.stopped else self._start + self._k * self.period

    def run_due(self, now: float) -> None:
        while self.due() <= now + _EPS:
            self._k += 1
            self._fire(self.msg)

    def update(self, data: Any) -> None:
        """canopen's heartbeat producer updates its state byte through this."""
        self.msg = can.Message(arbitration_id=self.msg.arbitration_id, data=bytes(data),
                               is_extended_id=False)

    def stop(self) -> None:
        self.stopped = True


class _NodeNetwork(canopen.Network):
    """The node's canopen network. Pumped, its periodic frames (the heartbeat producer)
    run in the pump's simulated time: canopen starts them through ``send_periodic``,
    which would otherwise be a wall-clock thread the simulated host could not follow."""

    def __init__(self, bus: can.BusABC, node: TestNode402) -> None:
        super().__init__(bus)
        self._node = node

    def send_periodic(self, can_id: int, data: bytes, period: float,
                      remote: bool = False) -> Any:
        if self._node.simulated:
            msg = can.Message(arbitration_id=can_id, data=bytes(data or b""),
                              is_extended_id=False, is_remote_frame=remote)
            return self._node.add_task(msg, period)
        return super().send_periodic(can_id, data, period, remote)


# ---------------------------------------------------------------------------
# The node


@dataclass
class Plant:
    """Rigid inertia: ``J * acc = torque``, torque held over each SYNC period."""

    inertia: float
    position: float = 0.0
    velocity: float = 0.0

    def step(self, torque: float, dt: float) -> None:
        acc = torque / self.inertia
        self.position += self.velocity * dt + 0.5 * acc * dt * dt
        self.velocity += acc * dt


class TestNode402:
    """One CiA 402 node on ``bus`` (owned: :meth:`close` shuts it down)."""

    __test__ = False  # not a pytest class

    def __init__(self, bus: can.BusABC, node_id: int = 5, *, inertia: float = 0.01,
                 eds: Path = EDS, position_per_rev: int = 4096) -> None:
        self.bus = bus
        self.simulated = True
        self.time = 0.0
        self.plant = Plant(inertia)
        self.position_per_rev = position_per_rev
        self.state = NodeState.NOT_READY
        self.cw = 0
        self.mode = 0
        self.syncs = 0
        self.torques: list[float] = []   # torque [Nm] applied at each SYNC
        self.controlwords: list[int] = []  # every controlword received (SDO or RPDO)
        self.emcy_sent: list[int] = []
        self.error_code = 0
        self._tasks: list[SimTask] = []
        self.last_sync: float | None = None  # the newest SYNC's time (simulated or its stamp)
        self._pdo_dirty = True
        self.network = _NodeNetwork(bus, self)
        self.node = canopen.LocalNode(node_id, str(eds))
        self.network.add_node(self.node)
        self.node.add_read_callback(self._on_read)
        self.node.add_write_callback(self._on_write)
        self.network.subscribe(0, self._on_nmt)      # after the NmtSlave's own subscriber
        self.network.subscribe(SYNC_ID, self._on_sync)

    # -- life cycle -------------------------------------------------------------

    @property
    def node_id(self) -> int:
        return int(self.node.id)

    def boot(self, *, application: bool = True) -> None:
        """Power on (or reset): boot-up frame, pre-operational, heartbeat from 0x1017;
        ``application``: the drive too (Switch on disabled: automatic transitions 0, 1)."""
        self.node.nmt.state = "INITIALISING"      # canopen's NmtSlave sends the boot-up
        self.node.nmt.state = "PRE-OPERATIONAL"   # and starts the heartbeat producer
        if application:
            self.state, self.cw, self.mode, self.error_code = NodeState.SWITCH_ON_DISABLED, 0, 0, 0

    def start(self) -> None:
        """Real time: canopen's notifier thread reads the node's bus."""
        self.simulated = False
        self.network.NOTIFIER_CYCLE = WAIT_SLICE   # the thread stops within a slice at close, not 1 s
        self.network.connect()
        self.boot()

    def close(self) -> None:
        """Stop the notifier and heartbeat (if any) and shut the bus down."""
        self.node.nmt.stop_heartbeat()
        self.network.disconnect()

    # -- pumping (simulated time) -------------------------------------------------

    def pump(self, now: float | None = None) -> int:
        """Hand every frame waiting on the node's bus to canopen (``network.notify``)."""
        if now is not None:
            self.time = now
        count = 0
        while (msg := self.bus.recv(0.0)) is not None:
            count += 1
            self.network.notify(msg.arbitration_id, msg.data, self.time if self.simulated else msg.timestamp)
        return count

    def add_task(self, msg: can.Message, period: float) -> SimTask:
        task = SimTask(msg, period, self.time, self.bus.send)
        self._tasks.append(task)
        return task

    def next_due(self) -> float:
        return min((t.due() for t in self._tasks), default=math.inf)

    def run_due(self, now: float) -> None:
        """Emit the node's own periodic frames (heartbeat) due by ``now``."""
        self.time = now
        for task in self._tasks:
            task.run_due(now)

    # -- faults ---------------------------------------------------------------------

    def fault(self, code: int = 0x2310, register: int = 0x03) -> None:
        """A drive fault: Fault state (torque off), 0x603F = code, EMCY with the code."""
        self.state = NodeState.FAULT
        self.error_code = code
        self.emcy_sent.append(code)
        self.node.emcy.send(code, register)

    # -- observables ------------------------------------------------------------------

    @property
    def nmt_state(self) -> str:
        return str(self.node.nmt.state)

    @property
    def statusword(self) -> int:
        sw = int(self.state) | 0x0200                               # bit 9: remote
        if self.state in _VOLTAGE:
            sw |= 0x0010
        if self.state is NodeState.OPERATION_ENABLED and self.mode == CST:
            sw |= 0x1000                                            # bit 12: follows 6071
        return sw

    @property
    def per_mille(self) -> int:
        """Target torque the plant gets now [per mille of rated]: 0 unless enabled in CST."""
        if self.state is not NodeState.OPERATION_ENABLED or self.mode != CST:
            return 0
        limit = self.raw(0x6072)
        return max(-limit, min(limit, self.raw(0x6071)))

    @property
    def torque(self) -> float:
        """Torque [Nm] applied to the plant now."""
        return self.per_mille / 1000.0 * self.raw(0x6076) / 1000.0

    @property
    def position_increments(self) -> int:
        return round(self.plant.position / (2 * math.pi) * self.position_per_rev)

    @property
    def velocity_rpm(self) -> int:
        return round(self.plant.velocity * 60.0 / (2 * math.pi))

    def raw(self, index: int, sub: int | None = None) -> int:
        """An object's value as the host would read it (through canopen's SDO server side);
        ``sub`` for a record's or array's entry (0: its number of entries)."""
        obj: Any = self.node.sdo[index]
        return int(obj.raw if sub is None else obj[sub].raw)

    # -- canopen callbacks ----------------------------------------------------------

    def _on_read(self, index: int, subindex: int, od: Any) -> int | None:
        live: dict[int, Callable[[], int]] = {
            0x6041: lambda: self.statusword, 0x6061: lambda: self.mode,
            0x6064: lambda: self.position_increments, 0x606C: lambda: self.velocity_rpm,
            0x6077: lambda: self.per_mille, 0x603F: lambda: self.error_code,
        }
        getter = live.get(index)
        if getter is None and index == 0x608F and subindex:   # position encoder resolution: N / 1 rev
            return self.position_per_rev if subindex == 1 else 1
        if getter is None and index == 0x6091 and subindex:   # gear ratio 1:1
            return 1
        return getter() if getter is not None else None

    def _on_write(self, index: int, subindex: int, od: Any, data: bytes) -> None:
        if index == 0x6040:
            self._controlword(struct.unpack("<H", bytes(data))[0])
        elif index == 0x6060:
            self.mode = struct.unpack("<b", bytes(data))[0]
        elif 0x1400 <= index <= 0x1BFF:
            self._pdo_dirty = True

    def _controlword(self, cw: int) -> None:
        previous, self.cw = self.cw, cw
        self.controlwords.append(cw)
        self.state = next_state(self.state, cw, previous)
        if self.state is NodeState.SWITCH_ON_DISABLED and previous & 0x80 == 0 and cw & 0x80:
            self.error_code = 0

    def _on_nmt(self, can_id: int, data: bytes, timestamp: float) -> None:
        cmd, target = data[0], data[1]
        if target not in (0, self.node_id):
            return
        if cmd in (0x81, 0x82):   # reset node / communication: defaults back, boot again
            keep = (lambda i: i >= 0x2000) if cmd == 0x82 else (lambda i: False)
            self.node.data_store = {i: v for i, v in self.node.data_store.items() if keep(i)}
            self._pdo_dirty = True
            self.node.nmt.stop_heartbeat()
            self.boot(application=cmd == 0x81)
        elif cmd == 0x01:
            self._load_pdos()

    def _load_pdos(self) -> None:
        """Read the PDO mapping the host wrote by SDO (canopen's own ``PdoMap.read``
        reads it back from this node's store through its SDO server)."""
        for pdo in (*self.node.rpdo.map.values(), *self.node.tpdo.map.values()):
            if pdo.enabled and pdo.cob_id is not None:
                self.network.unsubscribe(pdo.cob_id, pdo.on_message)
            pdo.read()
        self._pdo_dirty = False

    def _sync_period(self) -> float:
        """0x1006 [us] as seconds; 0 if unset or absent (a node with 0x60C2 instead, as the
        maxon EPOS4): then the time between the SYNCs themselves."""
        if 0x1006 not in self.node.object_dictionary:
            return 0.0
        return self.raw(0x1006) * 1e-6

    def _synchronous(self, pdos: Iterable[PdoMap]) -> list[PdoMap]:
        return [p for p in pdos if p.enabled and p.trans_type is not None and 1 <= p.trans_type <= 240]

    def _on_sync(self, can_id: int, data: bytes, timestamp: float) -> None:
        """SYNC: the plant moves over the period just ended with the torque held, the
        RPDOs received since the last SYNC take effect, the TPDOs sample and go out."""
        if self.node.nmt.state != "OPERATIONAL":
            return
        if self._pdo_dirty:
            self._load_pdos()
        now = self.time if self.simulated else timestamp
        dt = self._sync_period() or (now - self.last_sync if self.last_sync is not None else 0.0)
        self.last_sync = now
        self.syncs += 1
        if dt > 0:
            self.plant.step(self.torque, dt)
        for rpdo in self._synchronous(self.node.rpdo.map.values()):
            if rpdo.is_received:
                rpdo.is_received = False
                for var in rpdo.map:
                    self.node.set_data(var.index, var.subindex, var.get_data())
        self.torques.append(self.torque)
        for tpdo in self._synchronous(self.node.tpdo.map.values()):
            for var in tpdo.map:
                var.set_data(self.node.get_data(var.index, var.subindex))
            tpdo.transmit()


# ---------------------------------------------------------------------------
# Hosts in simulated time


class PumpBus(can.BusABC):
    """The host's bus to a pumped :class:`TestNode402`, in simulated time.

    ``send``: the frame reaches the node at once (it answers SDO, NMT and SYNC right
    away; RPDOs wait for the next SYNC as on a real node). ``recv(timeout)``: returns
    what the node sent; when nothing is waiting, simulated time advances to the next
    periodic frame (the host's ``send_periodic`` SYNC, the node's heartbeat), never
    beyond ``timeout`` simulated seconds. ``send_periodic`` runs in that simulated time
    and is echoed back to the host stamped with it, as SocketCAN's broadcast manager
    loops its frames back: ``native_periodic = True``. Frames come stamped with the
    simulated clock. ``recv`` is overridden, not ``_recv_internal``: python-can's
    ``BusABC.recv`` measures its timeout in wall time, this bus in simulated time.
    """

    native_periodic = True

    def __init__(self, channel: str, node: TestNode402, **kwargs: Any) -> None:
        self._inner = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)
        self._node = node
        self._queue: deque[can.Message] = deque()
        self._tasks: list[SimTask] = []
        self.time = 0.0
        self.sent: list[can.Message] = []
        self.channel_info = f"pumped node {node.node_id} over {channel}"
        super().__init__(channel=channel, **kwargs)

    def clock(self) -> float:
        """Simulated time [s] (pass as ``clock=`` to the host's Drive)."""
        return self.time

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self._inner.send(msg, timeout)
        self.sent.append(_stamped(msg, self.time, is_rx=False))
        self._node.pump(self.time)

    @property
    def tasks(self) -> list[SimTask]:
        """The periodic frames started on this bus (stopped ones included)."""
        return list(self._tasks)

    @property
    def pending(self) -> int:
        """Frames waiting for the host's ``recv``."""
        self._collect()
        return len(self._queue)

    def recv(self, timeout: float | None = None) -> can.Message | None:
        if timeout is None:
            raise ValueError("PumpBus.recv needs a finite timeout (simulated seconds)")
        end = self.time + timeout
        while True:
            self._collect()
            if self._queue:
                return self._queue.popleft()
            nxt = min([t.due() for t in self._tasks] + [self._node.next_due()])
            if nxt > end + _EPS:
                self.time = max(self.time, end)
                return None
            self._advance(nxt)

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        return self.recv(0.0 if timeout is None else timeout), False

    def advance(self, seconds: float) -> None:
        """Let simulated time run ``seconds`` (frames meanwhile stay queued for recv)."""
        end = self.time + seconds
        while (nxt := min([t.due() for t in self._tasks] + [self._node.next_due()])) <= end + _EPS:
            self._advance(nxt)
            self._collect()
        self.time = end

    def _advance(self, now: float) -> None:
        self.time = max(self.time, now)
        for task in self._tasks:
            task.run_due(self.time)
        self._node.run_due(self.time)

    def _fire(self, msg: can.Message) -> None:
        self._collect()
        self._queue.append(_stamped(msg, self.time))
        self.send(msg)

    def _collect(self) -> None:
        while (msg := self._inner.recv(0.0)) is not None:
            self._queue.append(_stamped(msg, self.time))

    def _send_periodic_internal(self, msgs: Any, period: float, duration: float | None = None,
                                autostart: bool = True, modifier_callback: Any = None) -> SimTask:
        msg = msgs[0] if isinstance(msgs, (list, tuple)) else msgs
        task = SimTask(msg, period, self.time, self._fire)
        self._tasks.append(task)
        return task

    def shutdown(self) -> None:
        super().shutdown()
        self._inner.shutdown()


class HostSyncPumpBus(PumpBus):
    """A pumped bus without native periodic send (a python-can interface whose
    ``send_periodic`` is a thread of this process): the host sends SYNC itself."""

    native_periodic = False


def _stamped(msg: can.Message, t: float, *, is_rx: bool = True) -> can.Message:
    return can.Message(timestamp=t, arbitration_id=msg.arbitration_id, data=bytes(msg.data),
                       is_extended_id=msg.is_extended_id, is_remote_frame=msg.is_remote_frame,
                       dlc=msg.dlc, is_rx=is_rx)


class PumpedNetwork(canopen.Network):
    """A host written with canopen, pumped: every frame it sends reaches the node at once,
    and the node's answers are handed back to it (``notify``) before ``send_message``
    returns, so canopen's blocking SDO client finds its answer already queued."""

    def __init__(self, bus: can.BusABC, node: TestNode402) -> None:
        super().__init__(bus)
        self._node = node

    def send_message(self, can_id: int, data: bytes, remote: bool = False) -> None:
        super().send_message(can_id, data, remote)
        self.pump()

    def pump(self) -> None:
        self._node.pump()
        assert self.bus is not None
        while (msg := self.bus.recv(0.0)) is not None:
            self.notify(msg.arbitration_id, msg.data, msg.timestamp)


def with_rig_units(profile: Any) -> Any:
    """``profile`` (the shipped emulated one) with this node's units (:data:`RIG_UNITS`)."""
    import dataclasses
    return dataclasses.replace(profile, options={**profile.options, **RIG_UNITS})
