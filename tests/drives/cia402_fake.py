"""A CiA 402 node of this test suite's own, in simulated time on one thread: canopen's
``LocalNode`` (SDO server, NMT slave, heartbeat producer, EMCY producer) plus a small power
state machine and an inertia written here -- not the emulator's code, so the drive is
checked against something independent of it.

:class:`SimBus` is the host's bus: ``send`` reaches the node at once; ``recv(timeout)``
moves simulated time to the next periodic frame (the host's SYNC, the node's heartbeat)
until a frame for the host is there or ``timeout`` simulated seconds passed. Its
``send_periodic`` runs in simulated time (``native_periodic = True``), each SYNC also
echoed to the host, as SocketCAN loops BCM frames back.
"""

from __future__ import annotations

import heapq
import math
import struct
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import can
import canopen

EDS = Path(__file__).resolve().parents[2] / "drivers" / "cia402-emulated.eds"

# statuswords (bit 9 remote, bit 4 voltage enabled, bit 12 CST: follows the target torque)
SW = {"switch on disabled": 0x0250, "ready to switch on": 0x0231, "switched on": 0x0233,
      "operation enabled": 0x1237, "quick stop active": 0x0217, "fault": 0x0218}
RPDO = struct.Struct("<Hh")
TPDO1 = struct.Struct("<Hih")
TPDO2 = struct.Struct("<ib")
#: the mapping the drive must have written (CiA 301 mapping entries: index, sub, bits)
EXPECTED_MAPS = {0x1600: (0x60400010, 0x60710010), 0x1A00: (0x60410010, 0x60640020, 0x60770010),
                 0x1A01: (0x606C0020, 0x60610008)}


@dataclass(order=True)
class _Periodic:
    due: float
    period: float = field(compare=False)
    msg: can.Message = field(compare=False)
    to_node: bool = field(compare=False)
    stopped: bool = field(default=False, compare=False)

    def stop(self) -> None:
        self.stopped = True

    def modify_data(self, msg: can.Message) -> None:
        self.msg = msg


class SimBus:
    """The host's bus to one :class:`FakeNode`, in simulated time (see the module)."""

    native_periodic = True
    channel_info = "simulated CiA 402 node"

    def __init__(self) -> None:
        self.now = 0.0
        self.inbox: deque[can.Message] = deque()
        self.tasks: list[_Periodic] = []
        self.node: FakeNode | None = None
        self.sent: list[can.Message] = []

    def clock(self) -> float:
        return self.now

    def to_host(self, msg: can.Message) -> None:
        self.inbox.append(can.Message(arbitration_id=msg.arbitration_id, data=bytes(msg.data),
                                      is_extended_id=False, timestamp=self.now))

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        copy = can.Message(arbitration_id=msg.arbitration_id, data=bytes(msg.data),
                           is_extended_id=False, timestamp=self.now)
        self.sent.append(copy)
        assert self.node is not None
        self.node.receive(copy)

    def send_periodic(self, msg: can.Message, period: float, *, to_node: bool = True) -> _Periodic:
        task = _Periodic(self.now + period, period, msg, to_node)
        heapq.heappush(self.tasks, task)
        return task

    def recv(self, timeout: float | None = None) -> can.Message | None:
        assert timeout is not None
        end = self.now + timeout
        while not self.inbox:
            while self.tasks and self.tasks[0].stopped:
                heapq.heappop(self.tasks)
            if not self.tasks or self.tasks[0].due > end + 1e-12:
                self.now = max(self.now, end)
                return None
            self.fire(heapq.heappop(self.tasks))
        return self.inbox.popleft()

    def fire(self, task: _Periodic) -> None:
        """One frame of a periodic task, at its due time: to the host and (if it says so) to
        the node; the task is due again a period later."""
        self.now = task.due
        task.due += task.period
        heapq.heappush(self.tasks, task)
        self.to_host(task.msg)
        if task.to_node and self.node is not None:
            self.node.receive(self.inbox[-1])


class _Outbox:
    """The node network's bus: what the node sends goes to the host."""

    def __init__(self, bus: SimBus) -> None:
        self.bus = bus

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self.bus.to_host(msg)

    def send_periodic(self, msg: can.Message, period: float) -> _Periodic:
        return self.bus.send_periodic(msg, period, to_node=False)


class FakeNode:
    """canopen's LocalNode with a power state machine and an inertia ``J`` [kg m^2]."""

    def __init__(self, bus: SimBus, node_id: int = 5, *, inertia: float = 0.01,
                 od: Any = None, rated_mnm: int | None = None) -> None:
        self.bus = bus
        bus.node = self
        self.node_id = node_id
        self.network = canopen.Network(_Outbox(bus))  # type: ignore[arg-type]
        self.local = self.network.create_node(node_id, od or canopen.import_od(str(EDS), node_id))
        if 0x608F in self.local.object_dictionary:   # this node's encoder (not the EDS default): 4096 / rev
            self.local.sdo[0x608F][1].raw = 4096
        if rated_mnm is not None:
            self.local.sdo[0x6076].raw = rated_mnm
        self.state = "switch on disabled"
        self.inertia = inertia
        self.position = 0.0  # rad
        self.velocity = 0.0  # rad/s
        self.torque = 0.0  # Nm applied
        self.rpdo: bytes | None = None
        self.controlword = 0
        self.last_sync = math.nan
        self.controlwords: list[int] = []
        self.syncs = 0
        self._publish()

    @property
    def sdo(self) -> Any:
        return self.local.sdo

    @property
    def rated_nm(self) -> float:
        return float(self.local.sdo[0x6076].raw) / 1000.0

    def receive(self, msg: can.Message) -> None:
        arb = msg.arbitration_id
        if arb == 0x80:
            self.on_sync(msg.timestamp)
        elif arb == 0x200 + self.node_id:
            self.rpdo = bytes(msg.data)
        else:
            self.network.notify(arb, bytearray(msg.data), msg.timestamp)

    def fault(self, code: int) -> None:
        """A fault: state FAULT and an EMCY with ``code``."""
        self.state = "fault"
        self.local.emcy.send(code, 0x01)
        self._publish()

    def on_sync(self, stamp: float) -> None:
        self.syncs += 1
        if self.local.nmt.state != "OPERATIONAL":
            return
        dt = 0.0 if math.isnan(self.last_sync) else stamp - self.last_sync
        self.last_sync = stamp
        self._step_plant(dt)
        if self.rpdo is not None:
            controlword, target = RPDO.unpack(self.rpdo)
            self._command(controlword)
            cst = self.local.sdo[0x6060].raw == 10
            self.torque = target * self.rated_nm / 1000.0 if self.state == "operation enabled" and cst else 0.0
        self._publish()
        self._send_tpdos()

    def _step_plant(self, dt: float) -> None:
        acceleration = self.torque / self.inertia
        self.position += self.velocity * dt + 0.5 * acceleration * dt * dt
        self.velocity += acceleration * dt

    def _command(self, cw: int) -> None:
        """CiA 402 transitions on the controlword (masks of the standard's command table)."""
        rising_reset = cw & 0x80 and not self.controlword & 0x80
        self.controlword = cw
        self.controlwords.append(cw)
        s = self.state
        if s == "fault":
            if rising_reset:
                self.state = "switch on disabled"
            return
        if cw & 0x82 == 0x00:                         # disable voltage
            self.state = "switch on disabled"
        elif cw & 0x86 == 0x02:                       # quick stop
            self.state = "quick stop active" if s == "operation enabled" else "switch on disabled"
        elif cw & 0x87 == 0x06:                       # shutdown
            self.state = "ready to switch on"
        elif cw & 0x8F == 0x07 and s in ("ready to switch on", "operation enabled"):
            self.state = "switched on"
        elif cw & 0x8F == 0x0F and s in ("switched on", "quick stop active"):
            self.state = "operation enabled"

    def _publish(self) -> None:
        od = self.local.sdo
        od[0x6041].raw = SW[self.state]
        od[0x6061].raw = od[0x6060].raw
        od[0x6064].raw = round(self.position / (2 * math.pi) * 4096)
        od[0x606C].raw = round(self.velocity * 60 / (2 * math.pi))
        od[0x6077].raw = round(self.torque / self.rated_nm * 1000) if self.rated_nm else 0

    def mapping(self, index: int) -> tuple[int, ...]:
        record = self.local.sdo[index]
        return tuple(record[i].raw for i in range(1, record[0].raw + 1))

    def _send_tpdos(self) -> None:
        od = self.local.sdo
        for number, layout, objects in ((1, TPDO1, (0x6041, 0x6064, 0x6077)), (2, TPDO2, (0x606C, 0x6061))):
            cob = od[0x1800 + number - 1][1].raw
            if cob & 0x80000000 or od[0x1800 + number - 1][2].raw != 1:
                continue
            assert self.mapping(0x1A00 + number - 1) == EXPECTED_MAPS[0x1A00 + number - 1]
            data = layout.pack(*(od[i].raw for i in objects))
            self.network.send_message(cob & 0x7FF, data)
