"""Emulated CiA 402 servo drive (CANopen, cyclic synchronous torque), drive side.

The CANopen services are canopen's, not ours: a :class:`canopen.LocalNode` built from the
project's EDS (``drivers/cia402-emulated.eds``, the profile's ``cia402.eds``) gives the
SDO server (expedited and segmented), the NMT slave, the EMCY producer and the object
dictionary store. It sits on a :class:`canopen.Network` that is never ``connect()``-ed
(no notifier thread): every frame the emulator receives goes to ``network.notify()``,
canopen's documented entry for a custom interface, and everything canopen sends goes
through the emulator's counted send (``Network.send_message``, the hook canopen names for
a custom backend), so lockstep stays deterministic and real time has one thread.

What canopen's LocalNode does not do, this module does (CiA 301, CiA 402 / IEC 61800-7-201):

- heartbeat producer in emulator time: canopen's NMT slave starts a python-can periodic
  task (a thread) for 0x1017; the network's ``send_periodic`` builds canopen's own task on
  this emulator's clock instead (:class:`_ClockSchedule`), so the period written by SDO, the
  state byte canopen keeps up to date and the boot-up frame are canopen's, the timing ours.
  The node boots (boot-up frame, NMT pre-operational) at its first tick or frame, and again
  after an NMT reset (node: the whole object dictionary back to the EDS; communication:
  0x1000-0x1FFF); canopen's slave only changes its state on a reset;
- SDO in NMT pre-operational and operational (not stopped, as CiA 301 says; canopen's
  server would answer in any state). PDOs only in NMT operational, from the object
  dictionary as the host configured it by SDO (0x1400-0x1403/0x1600-0x1603,
  0x1800-0x1803/0x1A00-0x1A03; a mapping entry must name a mappable object with its own
  size, at most 64 bits in all, or the SDO write is aborted with CiA 301's code).
  Synchronous RPDOs (transmission type 0-240) are latched at the next SYNC, asynchronous
  ones (254/255) applied at once; an RPDO shorter than its
  mapping is dropped with EMCY 0x8210. On SYNC (COB-ID 0x1005): the latched RPDOs are
  applied, then every enabled synchronous TPDO due (type n: every n-th SYNC; type 0:
  every SYNC) goes out, its bytes the mapped objects' values as the object dictionary
  encodes them (little-endian, their data types). Event-driven (254/255) and RTR-only
  TPDOs are not sent. In real time a SYNC with a newer SYNC queued behind it (both came while
  the node was busy) is counted in ``syncs_missed`` and not answered (the latched RPDOs wait
  for the newer one), as a drive whose cycle cannot keep up with the SYNC rate skips cycles;
- the object dictionary is read and checked by the drive's own
  :func:`dobhil.drives.cia402.eds.load_od` (one line for an EDS without 0x6071 or CST);
  objects an EDS may lack take what a drive does without them (no 0x6072, as on a maxon
  EPOS4: the profile's torque limit alone; no 0x605A: quick stop option 2);
- process values read live (SDO or TPDO): 0x6041 statusword, 0x6064 position [increments:
  ``position_per_rev`` per motor revolution, ``gear_ratio`` motor revolutions per joint
  revolution, wrapped to 32 bits as an encoder counter does], 0x606C velocity
  (``velocity_unit``: rpm, increments_per_s or milli_rpm of the motor), 0x6077 torque actual
  [per mille of 0x6076], 0x6061 mode display, 0x603F error code, 0x1001 error register;
  0x608F position encoder resolution and 0x6091 gear ratio state ``position_per_rev`` and
  ``gear_ratio`` (the scale this node encodes with; read only here);
- the CiA 402 power state machine on the controlword (:data:`TRANSITIONS`; fault reset on
  the rising edge of bit 7), the statusword of CiA 402 (the codec's ``STATUSWORD_TABLE``;
  plus bit 4 voltage enabled, bit 9 remote, bit 11 internal limit active while the torque
  is clamped, bit 12 in CST when the drive follows 0x6071). Quick stop option 0x605A: 0 disables at once,
  1-4 go to switch on disabled at the next tick (torque is zero from the quick stop on: the
  emulator has no torque ramp), 5-8 stay in quick stop active (enable operation resumes);
- modes 0x6060 -> 0x6061: 0 or a mode of 0x6502 (CSP 8, CSV 9, CST 10), anything else is
  aborted (SDO) or dropped (RPDO). Torque reaches the plant only in operation enabled AND
  CST: 0x6071 per mille of 0x6076 (``rated_torque_unit``), clamped to 0x6072 and to the
  profile's ``torque_limit``. CSP and CSV are accepted but produce no torque here;
- faults: over-torque -- 0x6071 above 0x6072 or above the profile's torque limit (half a
  per mille of slack for the host's rounding) for ``over_torque_cycles`` SYNCs in a row --
  EMCY 0x8311 (excess torque), error register 0x21; heartbeat consumer (0x1016, from the
  first heartbeat of the producer on) timed out: EMCY 0x8130, register 0x11; NMT
  operational left while operation enabled (CiA 402 0x6007 default: fault): EMCY 0x8100,
  register 0x11. Each ends in FAULT with torque off at once, 0x603F = the code; a fault
  reset clears them and sends the EMCY error reset (code 0).

Observables for :class:`~dobhil.emulator.process.EmulatorProcess` (``OBSERVED``):
``protocol_state`` (the drive's :class:`~dobhil.drives.cia402.codec.PowerState` code, the
same the host's CiA 402 drive reports),
``protocol_error`` (the EMCY code, 0 none), ``watchdog_tripped`` (a heartbeat-consumer or NMT
fault took the torque away) and ``frames_rejected``.
"""

from __future__ import annotations

import dataclasses
import math
import struct
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import can
import canopen
from can.broadcastmanager import ModifiableCyclicTaskABC
from canopen.network import PeriodicMessageTask
from canopen.objectdictionary import ODVariable
from canopen.sdo import SdoAbortedError, SdoVariable

from dobhil.drives.cia402.codec import (CST_MODE, FAULT_RESET_BIT, RATED_TORQUE_UNITS, STATUSWORD_TABLE, UNIT_OBJECTS,
                                        Cob, Controlword, EmcyCode, ErrorRegister, NmtCommand, PowerState,
                                        UnitObject, UnitScale, per_mille)
from dobhil.drives.cia402.eds import load_od
from dobhil.drives.cia402.link import quiet_canopen
from dobhil.drives.cia402.rules import CIA402_RULES
from dobhil.drives.profile import DriveProfile
from dobhil.drives.emulated import EmulatedDrive, PlantLike
from dobhil.errors import ConfigError

__all__ = ["EmulatedCiA402", "TRANSITIONS", "decode_command", "statusword"]

#: the ``cia402:`` section of a profile built in code without one: the section's own
#: defaults (its rules), and the shipped emulated node's values for the keys it requires
DEFAULT_OPTIONS: Mapping[str, Any] = {
    **{key: rule.default for key, rule in CIA402_RULES.section.items() if not rule.required},
    "eds": "cia402-emulated.eds", "rated_torque": 1.0, "position_per_rev": 1 << 20,
}
#: modes of operation by their bit in 0x6502 (CiA 402)
MODE_BITS: Mapping[int, int] = {1: 0, 2: 1, 3: 2, 4: 3, 6: 5, 7: 6, 8: 7, 9: 8, 10: 9}

_U8, _U16, _U32 = struct.Struct("<B"), struct.Struct("<H"), struct.Struct("<I")
_I16 = struct.Struct("<h")
_I8 = struct.Struct("<b")
_I16_MAX = 32767
_U32_MAX = 0xFFFF_FFFF
_PDO_INVALID = 1 << 31
#: SDO abort (ccs 4), no object, code 0x05040001: client/server command specifier not valid
_SDO_ABORT_UNKNOWN_COMMAND = bytes([0x80, 0, 0, 0]) + (0x05040001).to_bytes(4, "little")


_S = PowerState
_C = Controlword
#: (state, command) -> next state, CiA 402 transitions 2-12 (16 in code: it depends on 0x605A)
TRANSITIONS: Mapping[tuple[PowerState, Controlword], PowerState] = {
    (_S.SWITCH_ON_DISABLED, _C.SHUTDOWN): _S.READY_TO_SWITCH_ON,                  # 2
    (_S.READY_TO_SWITCH_ON, _C.SWITCH_ON): _S.SWITCHED_ON,                        # 3
    (_S.READY_TO_SWITCH_ON, _C.ENABLE_OPERATION): _S.OPERATION_ENABLED,           # 3 + 4
    (_S.READY_TO_SWITCH_ON, _C.DISABLE_VOLTAGE): _S.SWITCH_ON_DISABLED,           # 7
    (_S.READY_TO_SWITCH_ON, _C.QUICK_STOP): _S.SWITCH_ON_DISABLED,                # 7
    (_S.SWITCHED_ON, _C.ENABLE_OPERATION): _S.OPERATION_ENABLED,                  # 4
    (_S.SWITCHED_ON, _C.SHUTDOWN): _S.READY_TO_SWITCH_ON,                         # 6
    (_S.SWITCHED_ON, _C.DISABLE_VOLTAGE): _S.SWITCH_ON_DISABLED,                  # 10
    (_S.SWITCHED_ON, _C.QUICK_STOP): _S.SWITCH_ON_DISABLED,                       # 10
    (_S.OPERATION_ENABLED, _C.SWITCH_ON): _S.SWITCHED_ON,                         # 5
    (_S.OPERATION_ENABLED, _C.SHUTDOWN): _S.READY_TO_SWITCH_ON,                   # 8
    (_S.OPERATION_ENABLED, _C.DISABLE_VOLTAGE): _S.SWITCH_ON_DISABLED,            # 9
    (_S.OPERATION_ENABLED, _C.QUICK_STOP): _S.QUICK_STOP_ACTIVE,                  # 11
    (_S.QUICK_STOP_ACTIVE, _C.DISABLE_VOLTAGE): _S.SWITCH_ON_DISABLED,            # 12
}
_FAULTED = frozenset({_S.FAULT, _S.FAULT_REACTION_ACTIVE})

# statusword bits beside the state bits
SW_VOLTAGE_ENABLED = 1 << 4
SW_REMOTE = 1 << 9
SW_INTERNAL_LIMIT = 1 << 11
SW_FOLLOWS_TARGET = 1 << 12     # CST: the target torque is used


def decode_command(controlword: int) -> Controlword:
    """The command of bits 0-3 (CiA 402 table; bit 7, fault reset, is not looked at)."""
    if not controlword & 0x02:
        return Controlword.DISABLE_VOLTAGE
    if not controlword & 0x04:
        return Controlword.QUICK_STOP
    if not controlword & 0x01:
        return Controlword.SHUTDOWN
    return Controlword.ENABLE_OPERATION if controlword & 0x08 else Controlword.SWITCH_ON


def statusword(state: PowerState, *, follows_target: bool = False, limited: bool = False) -> int:
    """The statusword of ``state``: its state bits, voltage enabled (the emulated DC link is
    always on), remote (controlled over CAN), internal limit, CST target followed."""
    return (STATUSWORD_TABLE[state][1] | SW_VOLTAGE_ENABLED | SW_REMOTE | (SW_INTERNAL_LIMIT if limited else 0)
            | (SW_FOLLOWS_TARGET if follows_target else 0))


def _wrap32(value: float) -> int:
    """A 32-bit signed counter's reading of ``value`` (an encoder counter wraps)."""
    return ((int(round(value)) + (1 << 31)) % (1 << 32)) - (1 << 31)


def _clamp(value: float, low: int, high: int) -> int:
    if not math.isfinite(value):
        return high if value > 0 else low if value < 0 else 0
    return min(max(int(round(value)), low), high)


@dataclass(frozen=True)
class _Entry:
    """One PDO mapping entry: object, sub-index, size in bytes; index < 0x1000 is a dummy."""

    index: int
    subindex: int
    size: int


@dataclass
class _Pdo:
    number: int
    cob_id: int
    trans_type: int
    entries: tuple[_Entry, ...]
    countdown: int = 1
    #: a TPDO's bytes, one reader per entry (built with the PDO: no lookups per SYNC)
    readers: tuple[Callable[[], bytes], ...] = ()

    @property
    def size(self) -> int:
        return sum(entry.size for entry in self.entries)

    @property
    def synchronous(self) -> bool:
        return self.trans_type <= 240


class _ClockTask(ModifiableCyclicTaskABC):
    """A periodic frame sent on the emulator's clock: the python-can task that canopen's
    :class:`~canopen.network.PeriodicMessageTask` (the heartbeat) drives through python-can's
    task API, ``stop()`` and ``modify_data()`` (canopen's ``update`` calls the latter)."""

    def __init__(self, schedule: _ClockSchedule, msg: can.Message, period: float, start: float) -> None:
        super().__init__(msg, period)
        self._schedule = schedule
        self._start_time = start
        self._count = 1

    def due(self, now: float) -> bool:
        """True once per period reached (a long stall skips the missed ones)."""
        elapsed = now - self._start_time
        if self._count * self.period > elapsed + 1e-9:
            return False
        self._count = max(self._count, int(elapsed / self.period + 1e-9)) + 1
        return True

    def stop(self) -> None:
        self._schedule.remove(self)


class _ClockSchedule:
    """The emulator's periodic frames, on its clock. To canopen's ``PeriodicMessageTask``
    this is the bus it is built with (its documented ``bus`` parameter): it only calls the
    bus's ``send_periodic(msg, period)``, answered here with a :class:`_ClockTask` instead
    of a python-can thread, so canopen's own task (its ``__init__``, ``update``, ``stop``)
    runs unchanged and the frames go out in emulator time, deterministic in lockstep."""

    def __init__(self, clock: Callable[[], float]) -> None:
        self._clock = clock
        self.tasks: list[_ClockTask] = []

    def send_periodic(self, msg: can.Message, period: float) -> _ClockTask:
        task = _ClockTask(self, msg, period, self._clock())
        self.tasks.append(task)
        return task

    def remove(self, task: _ClockTask) -> None:
        if task in self.tasks:
            self.tasks.remove(task)

    def due(self, now: float) -> list[can.Message]:
        """The frames due at ``now``, in the tasks' start order."""
        return [task.messages[0] for task in tuple(self.tasks) if task.due(now)]

    def stop_all(self) -> None:
        self.tasks.clear()


class _EmulatorNetwork(canopen.Network):
    """canopen's network on the emulator's bus, never connected: frames come in through
    :meth:`notify` (called by the emulator), go out through the emulator's counted send."""

    def __init__(self, bus: can.BusABC, *, send: Callable[[can.Message], None],
                 schedule: _ClockSchedule) -> None:
        super().__init__(bus)
        self._send_frame = send
        self._schedule = schedule

    def send_message(self, can_id: int, data: bytes, remote: bool = False) -> None:
        # canopen's documented hook for a custom backend: the emulator counts what it sends
        # (LockstepBus reads exactly that many frames) and survives a refused send
        self._send_frame(can.Message(arbitration_id=can_id, is_extended_id=can_id > 0x7FF,
                                     data=bytes(data), is_remote_frame=remote))

    def send_periodic(self, can_id: int, data: bytes, period: float,
                      remote: bool = False) -> PeriodicMessageTask:
        # canopen's own task, built on the emulator's clock instead of a python-can thread
        return PeriodicMessageTask(can_id, data, period, self._schedule, remote)


class EmulatedCiA402(EmulatedDrive):
    """A CiA 402 servo drive in CST on a python-can bus, dynamics from the injected plant.

    Its settings are the profile's ``cia402:`` section (``profile.options``; a key it lacks,
    as in a profile built in code, from :data:`DEFAULT_OPTIONS`). ``over_torque_cycles``:
    SYNCs in a row above the torque limits before the over-torque fault.
    """

    def __init__(self, bus: can.BusABC, profile: DriveProfile, plant: PlantLike, *,
                 over_torque_cycles: int = 3, **kwargs: Any) -> None:
        super().__init__(bus, profile, plant, **kwargs)
        self.options: Mapping[str, Any] = {**DEFAULT_OPTIONS, **profile.options}
        # the drive's own reading of the EDS: a bad one (no 0x6071, no CST, a rated torque
        # of 0) ends in the one line the drive gives, before any frame
        od = load_od(dataclasses.replace(profile, options=self.options))
        # the drive's units (one source): what the host decodes, this node encodes
        self._torque_unit = RATED_TORQUE_UNITS[self.options["rated_torque_unit"]]
        scale = UnitScale.of(position_per_rev=float(self.options["position_per_rev"]),
                             velocity_unit=str(self.options["velocity_unit"]),
                             gear_ratio=float(self.options["gear_ratio"]))
        self._inc_per_rad = 1.0 / scale.rad_per_increment
        self._vel_per_rad_s = 1.0 / scale.rad_s_per_velocity_count
        self.over_torque_cycles = over_torque_cycles
        self.node_id = profile.node_id
        self.node = canopen.LocalNode(self.node_id, od)
        self._periodic = _ClockSchedule(lambda: self.time)
        self.network = _EmulatorNetwork(bus, send=self._send, schedule=self._periodic)
        self.network.add_node(self.node)
        self.node.add_write_callback(self._on_write)
        self.node.add_read_callback(self._on_read)
        self.network.subscribe(Cob.NMT, self._on_nmt)   # after the NMT slave's: sees its new state
        self.state = PowerState.NOT_READY_TO_SWITCH_ON
        self.frames_rejected = 0
        self.watchdog_tripped = False
        self.sync_count = 0
        self.syncs_missed = 0   # real time: SYNCs a newer one superseded (see _on_sync)
        self._booted = False
        self._nmt_before = ""
        self._sync_id: int | None = None
        self._consumer_id: int | None = None
        self._consumer_timeout = 0.0
        self._last_host_heartbeat: float | None = None
        self._rpdo_ids: tuple[int, ...] = ()
        self._writers: dict[int, Callable[[int, bytes], None]] = {
            0x6040: self._write_controlword, 0x6060: self._write_mode, 0x6071: self._write_target,
            0x6072: self._write_max_torque, 0x6076: self._write_rated_torque,
            0x605A: self._write_quick_stop_option, 0x1005: self._write_sync_id,
            0x1016: self._write_consumer_heartbeat,
        }
        self._live: dict[int, Callable[[], int]] = {
            0x6041: self._statusword, 0x6064: self._position, 0x606C: self._velocity,
            0x6077: self._torque_actual, 0x6061: lambda: self.mode, 0x603F: lambda: self.error_code,
            0x1001: lambda: self.error_register,
        }
        self._stated = self._units_stated(profile)
        self._load_application()

    # -- observables ----------------------------------------------------------

    @property
    def protocol_state(self) -> int:
        return int(self.state)

    @property
    def protocol_error(self) -> int:
        return self.error_code

    @property
    def nmt_state(self) -> str:
        """canopen's name of the NMT state ('PRE-OPERATIONAL', 'OPERATIONAL', ...)."""
        return str(self.node.nmt.state)

    @property
    def statusword(self) -> int:
        return self._statusword()

    @property
    def target_torque(self) -> int:
        """0x6071 in effect [per mille of rated torque]."""
        return self._target_pm

    # -- hooks ----------------------------------------------------------------

    def _plant_torque(self) -> float:
        if self.state is PowerState.OPERATION_ENABLED and self.mode == CST_MODE:
            return self._torque_nm
        return 0.0

    def _cyclic_frames(self) -> Sequence[tuple[float, Callable[[], can.Message]]]:
        return ()   # TPDOs answer SYNC; the heartbeat runs on _ClockSchedule

    def _on_time(self, now: float) -> None:
        if not self._booted:
            self._boot()
        for msg in self._periodic.due(now):
            self._send(msg)
        if self.state is PowerState.QUICK_STOP_ACTIVE and 1 <= self._quick_stop_option <= 4:
            self._enter(PowerState.SWITCH_ON_DISABLED)   # the stop is done: no ramp here
        timeout, last = self._consumer_timeout, self._last_host_heartbeat
        if timeout > 0 and last is not None and now - last > timeout + 1e-9:
            self._last_host_heartbeat = None    # watched again from the next heartbeat on
            self.watchdog_tripped |= self._fault(EmcyCode.HEARTBEAT,
                                                 ErrorRegister.GENERIC | ErrorRegister.COMMUNICATION)

    def _on_frame(self, msg: can.Message) -> None:
        if not self._booted:
            self._boot()
        if msg.is_extended_id or msg.is_error_frame or msg.is_remote_frame:
            self.frames_not_addressed += 1
            return   # CANopen (CiA 301) uses 11-bit data frames; RTR of PDOs is not emulated
        can_id, data = msg.arbitration_id, msg.data
        if (can_id == Cob.NMT and len(data) < 2) or (can_id == self.node.sdo.rx_cobid and len(data) != 8):
            self.frames_rejected += 1   # canopen's handlers expect these lengths
            return
        if self._pdo_dirty:
            self._compile_pdos()        # subscribes the RPDOs' ids: before the check below
        if can_id != self.node.sdo.rx_cobid and can_id not in self.network.subscribers:
            # no consumer of this id on the node (canopen's Network.notify would call none):
            # another node's PDOs, SDOs, heartbeat or EMCY
            self.frames_not_addressed += 1
            return
        if can_id == self.node.sdo.rx_cobid:
            if self.nmt_state != "STOPPED":   # CiA 301: a stopped node answers NMT only
                self._sdo_request(data, msg.timestamp)
            return
        self.network.notify(can_id, data, msg.timestamp)

    def _sdo_request(self, data: bytearray, timestamp: float) -> None:
        """canopen's SDO server, around two of its failure paths (canopen 2.4.1): a segment
        request with no transfer in progress makes its own abort raise (it packs the
        transfer's index, None: ``struct.error``), and it logs refused requests (block
        transfers) through Python's last-resort handler, i.e. prints them. Here the abort
        is sent for it (0x05040001, command specifier not valid) and its log kept quiet:
        a drive answers a bad request on the bus, it does not print."""
        with quiet_canopen():
            try:
                self.network.notify(self.node.sdo.rx_cobid, data, timestamp)
            except struct.error:
                self.frames_rejected += 1
                self.network.send_message(self.node.sdo.tx_cobid, _SDO_ABORT_UNKNOWN_COMMAND)

    # -- boot and NMT -----------------------------------------------------------

    def _load_application(self) -> None:
        """The application's variables from the object dictionary (power-on, reset node).
        Objects an EDS may lack (a maxon EPOS4 has no 0x6072) take what the drive does
        without them: no max torque but the profile's limit, quick stop option 2."""
        raw = self._raw
        self._controlword = raw(0x6040)
        self.mode = raw(0x6060)
        self._target_pm = raw(0x6071)
        self._max_pm = raw(0x6072, default=_I16_MAX)
        self._rated_nm = raw(0x6076) * self._torque_unit
        self._quick_stop_option = raw(0x605A, default=2)
        self.error_code = 0
        self.error_register = 0
        self._over_count = 0
        self._limited = False
        self._update_torque()
        self._load_communication()

    def _load_communication(self) -> None:
        """The communication objects' effects (power-on, reset communication)."""
        self._write_sync_id(0, _U32.pack(self._raw(0x1005, default=Cob.SYNC)))
        self._write_consumer_heartbeat(1, _U32.pack(self._raw(0x1016, 1, default=0)))
        self._rpdos: dict[int, _Pdo] = {}
        self._tpdos: tuple[_Pdo, ...] = ()
        self._pending: dict[int, list[tuple[_Entry, bytes]]] = {}
        self._pdo_dirty = True

    def _raw(self, index: int, subindex: int = 0, *, default: int | None = None) -> int:
        """An integer object's value, read through canopen's SDO server object (no frame);
        ``default`` when the object dictionary has no such object (None: it must have it)."""
        if default is not None and index not in self.node.object_dictionary:
            return default
        entry = self.node.sdo[index]
        if not isinstance(entry, SdoVariable):
            entry = entry[subindex]
        return int(entry.raw)

    def _boot(self) -> None:
        """Power on / reset: boot-up frame, NMT pre-operational (canopen's slave starts the
        heartbeat of 0x1017 then), the power state machine to switch on disabled."""
        self._booted = True
        self.node.nmt.state = "INITIALISING"       # canopen sends the boot-up frame
        self.node.nmt.state = "PRE-OPERATIONAL"
        self._nmt_before = self.nmt_state
        if self.state is PowerState.NOT_READY_TO_SWITCH_ON:
            self._enter(PowerState.SWITCH_ON_DISABLED)  # transition 1: self-test passed

    def _on_nmt(self, can_id: int, data: bytearray, timestamp: float) -> None:
        command, node = data[0], data[1]
        if node not in (0, self.node_id):
            self.frames_not_addressed += 1   # a command to another node
            return
        before, self._nmt_before = self._nmt_before, self.nmt_state
        if command in (NmtCommand.RESET_NODE, NmtCommand.RESET_COMMUNICATION):
            self._periodic.stop_all()
            self._reset(application=command == NmtCommand.RESET_NODE)
        elif before == "OPERATIONAL" and self._nmt_before != "OPERATIONAL":
            self._pending.clear()
            if self.state is PowerState.OPERATION_ENABLED:   # 0x6007 default: fault
                self.watchdog_tripped |= self._fault(EmcyCode.COMMUNICATION,
                                                     ErrorRegister.GENERIC | ErrorRegister.COMMUNICATION)

    def _reset(self, *, application: bool) -> None:
        store = self.node.data_store
        for index in [i for i in store if application or i < 0x2000]:
            del store[index]
        if application:   # the drive restarts; a communication reset leaves its state alone
            self.state = PowerState.NOT_READY_TO_SWITCH_ON
            self.watchdog_tripped = False
            self._load_application()
        else:
            self._load_communication()
        self._boot()

    def _operational(self) -> bool:
        return self.node.nmt.state == "OPERATIONAL"

    # -- object dictionary callbacks ------------------------------------------------

    def _on_read(self, index: int, subindex: int, od: ODVariable) -> int | None:
        live = self._live.get(index)
        return self._stated.get((index, subindex)) if live is None else live()

    def _units_stated(self, profile: DriveProfile) -> dict[tuple[int, int], int]:
        """0x608F:01/02 and 0x6091:01/02 as this node encodes 0x6064 and 0x606C: the
        profile's ``position_per_rev`` and ``gear_ratio`` as U32 ratios (a drive states
        its own encoder and gear; the host checks them at start-up). Fixed: a write is
        refused (read only), changing the scale by SDO is not emulated."""
        stated: dict[tuple[int, int], int] = {}
        for obj in UNIT_OBJECTS:
            value = float(self.options[obj.key])
            num, den = UnitObject.ratio_of(value)
            if num > _U32_MAX:
                raise ConfigError(f"drive profile {profile.name!r}: cia402.{obj.key}: the emulated node states "
                                  f"it in 0x{obj.index:04X} as U32 / U32; {value:.10g} does not fit")
            stated[obj.index, 1], stated[obj.index, 2] = num, den
            self._writers[obj.index] = self._write_read_only
        return stated

    @staticmethod
    def _write_read_only(_sub: int, _data: bytes) -> None:
        raise SdoAbortedError(0x06010002)   # attempt to write a read only object

    def _on_write(self, index: int, subindex: int, od: ODVariable, data: bytes) -> None:
        """Before canopen stores a value (SDO or RPDO): check it, act on it; an
        SdoAbortedError aborts the SDO transfer and nothing is stored."""
        if 0x1400 <= index <= 0x1BFF:
            self._check_pdo_write(index, subindex, bytes(data))
            self._pdo_dirty = True
        writer = self._writers.get(index)
        if writer is not None:
            writer(subindex, bytes(data))

    def _write_controlword(self, _sub: int, data: bytes) -> None:
        (value,) = _U16.unpack(data)
        previous, self._controlword = self._controlword, value
        if self.state in _FAULTED:
            if value & FAULT_RESET_BIT and not previous & FAULT_RESET_BIT:
                self._fault_reset()
            return
        command = decode_command(value)
        target = TRANSITIONS.get((self.state, command))
        if (self.state is PowerState.QUICK_STOP_ACTIVE and command is Controlword.ENABLE_OPERATION
                and 5 <= self._quick_stop_option <= 8):
            target = PowerState.OPERATION_ENABLED     # transition 16
        if target is PowerState.QUICK_STOP_ACTIVE and self._quick_stop_option == 0:
            target = PowerState.SWITCH_ON_DISABLED    # option 0: disable drive function
        if target is not None:
            self._enter(target)

    def _write_mode(self, _sub: int, data: bytes) -> None:
        (mode,) = _I8.unpack(data)
        bit = MODE_BITS.get(mode)
        if mode != 0 and (bit is None or not self._raw(0x6502) >> bit & 1):
            raise SdoAbortedError(0x06090030)   # value range of parameter exceeded
        self.mode = mode

    def _write_target(self, _sub: int, data: bytes) -> None:
        (self._target_pm,) = _I16.unpack(data)
        self._update_torque()

    def _write_max_torque(self, _sub: int, data: bytes) -> None:
        (self._max_pm,) = _U16.unpack(data)
        self._update_torque()

    def _write_rated_torque(self, _sub: int, data: bytes) -> None:
        (value,) = _U32.unpack(data)
        if value == 0:
            raise SdoAbortedError(0x06090032)   # value of parameter written too low
        self._rated_nm = value * self._torque_unit
        self._update_torque()

    def _write_quick_stop_option(self, _sub: int, data: bytes) -> None:
        (value,) = _I16.unpack(data)
        if not 0 <= value <= 8:
            raise SdoAbortedError(0x06090030)
        self._quick_stop_option = value

    def _write_sync_id(self, _sub: int, data: bytes) -> None:
        (value,) = _U32.unpack(data)
        if self._sync_id is not None:
            self.network.unsubscribe(self._sync_id, self._on_sync)
        self._sync_id = value & 0x7FF
        self.network.subscribe(self._sync_id, self._on_sync)

    def _write_consumer_heartbeat(self, sub: int, data: bytes) -> None:
        if sub != 1:
            return
        (value,) = _U32.unpack(data)
        if self._consumer_id is not None:
            self.network.unsubscribe(self._consumer_id, self._on_host_heartbeat)
        producer, millis = (value >> 16) & 0x7F, value & 0xFFFF
        self._consumer_id = Cob.HEARTBEAT + producer if producer and millis else None
        self._consumer_timeout = millis / 1000.0 if self._consumer_id is not None else 0.0
        self._last_host_heartbeat = None
        if self._consumer_id is not None:
            self.network.subscribe(self._consumer_id, self._on_host_heartbeat)

    def _on_host_heartbeat(self, can_id: int, data: bytearray, timestamp: float) -> None:
        self._last_host_heartbeat = self._time

    # -- PDOs ---------------------------------------------------------------------

    def _check_pdo_write(self, index: int, subindex: int, data: bytes) -> None:
        """CiA 301's checks of a mapping write (communication parameters are taken as written)."""
        if not (0x1600 <= index <= 0x17FF or 0x1A00 <= index <= 0x1BFF):
            return
        if subindex == 0:
            (count,) = _U8.unpack(data)
            entries = [self._entry(self._raw(index, s)) for s in range(1, count + 1)] if count else []
            if count > 8 or sum(entry.size for entry in entries) > 8:
                raise SdoAbortedError(0x06040042)   # PDO length exceeded
            return
        (value,) = _U32.unpack(data)
        self._entry(value)

    def _entry(self, value: int) -> _Entry:
        """A mapping entry, checked: an existing, mappable object of that size (or a dummy)."""
        index, subindex, bits = value >> 16, (value >> 8) & 0xFF, value & 0xFF
        if value == 0 or 0x0002 <= index <= 0x0007:   # empty, or a dummy of a standard type
            return _Entry(index, subindex, bits // 8)
        if index not in self.node.object_dictionary:
            raise SdoAbortedError(0x06020000)   # object does not exist
        obj = self.node.object_dictionary[index]
        var = obj if isinstance(obj, ODVariable) else obj[subindex] if subindex in obj else None
        if var is None:
            raise SdoAbortedError(0x06090011)   # sub-index does not exist
        if not var.pdo_mappable or len(var) != bits:
            raise SdoAbortedError(0x06040041)   # object cannot be mapped to the PDO
        return _Entry(index, subindex, bits // 8)

    def _read_pdo(self, number: int, com: int, mapping: int) -> _Pdo | None:
        cob_id = self._raw(com, 1)
        if cob_id & _PDO_INVALID:
            return None
        count = self._raw(mapping, 0)
        entries = tuple(self._entry(self._raw(mapping, s)) for s in range(1, count + 1))
        trans_type = self._raw(com, 2)
        return _Pdo(number, cob_id & 0x7FF, trans_type, entries, countdown=max(trans_type, 1))

    def _compile_pdos(self) -> None:
        """The PDOs as the object dictionary defines them now (after any SDO write to them)."""
        self._pdo_dirty = False
        od = self.node.object_dictionary
        for cob_id in self._rpdo_ids:
            self.network.unsubscribe(cob_id, self._on_rpdo)
        rpdos = [self._read_pdo(n + 1, 0x1400 + n, 0x1600 + n) for n in range(512) if 0x1400 + n in od]
        tpdos = [self._read_pdo(n + 1, 0x1800 + n, 0x1A00 + n) for n in range(512) if 0x1800 + n in od]
        self._rpdos = {pdo.cob_id: pdo for pdo in rpdos if pdo is not None}
        self._tpdos = tuple(dataclasses.replace(pdo, readers=tuple(self._reader(e) for e in pdo.entries))
                            for pdo in tpdos if pdo is not None and pdo.synchronous)
        self._rpdo_ids = tuple(self._rpdos)
        for cob_id in self._rpdo_ids:
            self.network.subscribe(cob_id, self._on_rpdo)
        self._pending.clear()

    def _reader(self, entry: _Entry) -> Callable[[], bytes]:
        """The bytes of one TPDO entry: a process value encoded by canopen as its object's
        data type, or what the object dictionary holds (as an SDO upload reads it)."""
        if entry.index < 0x1000:
            zeros = bytes(entry.size)
            return lambda: zeros
        live = self._live.get(entry.index)
        if live is not None:
            obj = self.node.object_dictionary[entry.index]
            var = obj if isinstance(obj, ODVariable) else obj[entry.subindex]
            encode = var.encode_raw
            return lambda: encode(live())
        get_data, index, subindex, size = self.node.get_data, entry.index, entry.subindex, entry.size
        return lambda: get_data(index, subindex)[:size]

    def _on_rpdo(self, can_id: int, data: bytearray, timestamp: float) -> None:
        pdo = self._rpdos.get(can_id)
        if pdo is None or not self._operational():
            return
        if len(data) < pdo.size:
            self.frames_rejected += 1
            self.node.emcy.send(EmcyCode.PDO_LENGTH, self.error_register | ErrorRegister.COMMUNICATION)
            return
        values, offset = [], 0
        for entry in pdo.entries:
            values.append((entry, bytes(data[offset:offset + entry.size])))
            offset += entry.size
        if pdo.synchronous:
            self._pending[pdo.number] = values    # applied at the next SYNC
        else:
            self._apply(values)

    def _apply(self, values: list[tuple[_Entry, bytes]]) -> None:
        for entry, raw in values:
            if entry.index < 0x1000:
                continue   # dummy
            try:
                self.node.set_data(entry.index, entry.subindex, raw)
            except SdoAbortedError:
                self.frames_rejected += 1   # a value the drive refuses (a mode it lacks)

    def _on_sync(self, can_id: int, data: bytearray, timestamp: float) -> None:
        if not self._operational():
            return
        if self._superseded(can_id):
            # real time, and a newer SYNC came while this one waited: a drive runs its cycle
            # from the newest SYNC and never answers a stale one; an emulator that cannot keep
            # up (a slow guest at 1 kHz) would otherwise answer every queued SYNC in turn,
            # seconds late, and acknowledge a disable long after the host gave up
            self.syncs_missed += 1
            return
        self.sync_count += 1
        pending, self._pending = self._pending, {}
        for number in sorted(pending):
            self._apply(pending[number])
        self._check_over_torque()
        for pdo in self._tpdos:
            pdo.countdown -= 1
            if pdo.countdown > 0:
                continue
            pdo.countdown = max(pdo.trans_type, 1)
            payload = b"".join([read() for read in pdo.readers])
            self._send(can.Message(arbitration_id=pdo.cob_id, is_extended_id=False, data=payload))

    # -- the drive ----------------------------------------------------------------

    def _enter(self, state: PowerState) -> None:
        self.state = state
        if state is not PowerState.OPERATION_ENABLED:
            self._over_count = 0

    def _update_torque(self) -> None:
        """The torque the plant gets in operation enabled + CST: 0x6071 clamped to 0x6072
        (per mille) and to the profile's limit (Nm)."""
        limit_pm = min(self._max_pm, _I16_MAX)
        target = min(max(self._target_pm, -limit_pm), limit_pm)
        torque = target * self._rated_nm / 1000.0
        limit = self._profile.torque_limit
        clamped = min(max(torque, -limit), limit)
        self._torque_nm = clamped
        self._limited = clamped != self._target_pm * self._rated_nm / 1000.0

    def _check_over_torque(self) -> None:
        """One SYNC of the over-torque watch: above 0x6072 or the profile's limit (half a
        per mille of slack: the host rounds to whole per mille) ``over_torque_cycles`` times
        in a row faults."""
        if self.state is not PowerState.OPERATION_ENABLED or self.mode != CST_MODE:
            return
        target = abs(self._target_pm)
        limit_pm = self._profile.torque_limit / self._rated_nm * 1000.0 + 0.5
        if target > self._max_pm or target > limit_pm:
            self._over_count += 1
            if self._over_count >= self.over_torque_cycles:
                self._fault(EmcyCode.EXCESS_TORQUE, ErrorRegister.GENERIC | ErrorRegister.PROFILE)
        else:
            self._over_count = 0

    def _fault(self, code: EmcyCode, register: int) -> bool:
        """Into FAULT (torque off at once), 0x603F/0x1001 set, the EMCY sent; True if it
        took the torque away (it was in operation enabled). A fault in FAULT is ignored."""
        if self.state in _FAULTED:
            return False
        was_enabled = self.state is PowerState.OPERATION_ENABLED
        self._enter(PowerState.FAULT)
        self.error_code, self.error_register = int(code), int(register)
        if self.nmt_state != "STOPPED":
            self.node.emcy.send(code, register)
        return was_enabled

    def _fault_reset(self) -> None:
        """Transition 15: FAULT -> switch on disabled, errors cleared, EMCY error reset."""
        self._enter(PowerState.SWITCH_ON_DISABLED)
        self.error_code = self.error_register = 0
        self.watchdog_tripped = False
        if self.nmt_state != "STOPPED":
            self.node.emcy.reset()

    # -- process values (read live: SDO upload or TPDO) ----------------------------------

    def _statusword(self) -> int:
        enabled = self.state is PowerState.OPERATION_ENABLED
        return statusword(self.state, follows_target=enabled and self.mode == CST_MODE,
                          limited=enabled and self._limited)

    def _position(self) -> int:
        return _wrap32(self._plant.position * self._inc_per_rad)

    def _velocity(self) -> int:
        return _clamp(self._plant.velocity * self._vel_per_rad_s, -(1 << 31), (1 << 31) - 1)

    def _torque_actual(self) -> int:
        return per_mille(self._plant_torque(), self._rated_nm)   # quantised as 0x6071 is
