"""CANopen CiA 402 part of the preflight (:mod:`dobhil.drives.preflight`).

A CiA 402 drive says what it is only when asked: the probe reads its object dictionary
by SDO with canopen's SDO client (a ``canopen.Network`` on the borrowed bus, fed by a
python-can ``Notifier`` for the window only: the preflight runs before the loop, in
real time; the notifier is stopped and the node removed before the run), nothing
written, no NMT command sent:

- identity 0x1018:01..04 (vendor id, product code, revision, serial number): the node
  answers SDO at all. A node that never answers is ONE finding naming the node and the
  SDO object asked (``node 9 does not answer SDO: no reply to the upload of 0x1018:01
  (identity: vendor id) within 0.3 s``), and the run refuses it;
- supported drive modes 0x6502: bit 9 = cyclic synchronous torque (CST), the mode dobhil
  runs in (CiA 402);
- motor rated torque 0x6076 in the profile's ``cia402.rated_torque_unit`` (mNm per
  CiA 402, uNm on an EPOS4), in Nm against ``cia402.rated_torque``: every torque
  command is per mille of it, so a wrong value scales every torque, and the run refuses;
- the PDO mapping: the mapping parameters of the profile's RPDO and TPDOs exist on the
  node (0x1600 + n - 1, 0x1A00 + n - 1 sub 0), and the SPEC-17 mapping of each PDO fits
  its 8 data bytes (sizes from the profile's EDS);
- producer heartbeat time 0x1017 against the profile's ``heartbeat_period`` (the drive's
  start-up writes it: a difference is a note, measured too while listening);
- statusword 0x6041: a drive already in Operation enabled may be driven by another
  host, and the run refuses (as ODrive's CLOSED_LOOP_CONTROL).

Listening meanwhile hears heartbeats (0x700 + id: NMT state, period), SDO replies and
TPDOs (none before the drive's start-up: a TPDO answers SYNC, in NMT operational).
The bus budget per SYNC: SYNC (0 bytes), the RPDO (4: controlword + target torque),
TPDO1 (8: statusword + position + torque actual), TPDO2 (5: velocity + mode display),
and the heartbeat's share (1 byte every ``heartbeat_period``).

An SDO read blocks up to ``cia402.sdo_timeout`` (canopen's client waits on its own
queue): a stop request (SIGINT) is seen between reads and in the listening that
follows, so within ``sdo_timeout`` s rather than WAIT_SLICE s.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import can
import canopen
from canopen.objectdictionary import ObjectDictionary
from canopen.sdo import SdoAbortedError, SdoCommunicationError

from dobhil.drives.bus_load import CycleFrame
from dobhil.drives.preflight import (Capture, Finding, NodeReport, Observation, PreflightProbe, Setting,
                                     Severity, Stream)
from dobhil.drives.profile import DriveProfile
from dobhil.drives.waits import WAIT_SLICE, Cancel

__all__ = ["CST_BIT", "RPDO_MAPPING", "TPDO_MAPPINGS", "CiA402Preflight", "SdoRead"]

#: 0x6502 supported drive modes: bit 9 = cyclic synchronous torque (CiA 402)
CST_BIT = 1 << 9
#: SPEC-17's wire mapping, (index, subindex) in PDO order: RPDO = controlword + target
#: torque; TPDO n = statusword + position + torque actual; TPDO n+1 = velocity + mode display
RPDO_MAPPING = ((0x6040, 0), (0x6071, 0))
TPDO_MAPPINGS = (((0x6041, 0), (0x6064, 0), (0x6077, 0)), ((0x606C, 0), (0x6061, 0)))
#: a classic CAN PDO carries at most 8 data bytes
PDO_BITS = 64
#: 0x6076's unit on the wire -> Nm
TORQUE_UNITS = {"mNm": 1e-3, "uNm": 1e-6}
#: NMT state byte of the heartbeat (CiA 301)
NMT_STATES = {0x00: "boot-up", 0x04: "stopped", 0x05: "operational", 0x7F: "pre-operational"}
#: statusword (mask, value) -> CiA 402 power state
POWER_STATES = (
    (0x4F, 0x00, "not ready to switch on"), (0x4F, 0x40, "switch on disabled"),
    (0x6F, 0x21, "ready to switch on"), (0x6F, 0x23, "switched on"), (0x6F, 0x27, "operation enabled"),
    (0x6F, 0x07, "quick stop active"), (0x4F, 0x0F, "fault reaction active"), (0x4F, 0x08, "fault"),
)
#: the data types of CiA 301 (DataType codes) -> bits, for objects an EDS maps
_TYPE_BITS = {0x01: 1, 0x02: 8, 0x03: 16, 0x04: 32, 0x05: 8, 0x06: 16, 0x07: 32, 0x08: 32,
              0x10: 24, 0x12: 40, 0x13: 48, 0x14: 56, 0x15: 64, 0x16: 24, 0x18: 40, 0x19: 48,
              0x1A: 56, 0x1B: 64, 0x11: 64}
_COB_SDO_TX, _COB_HEARTBEAT = 0x580, 0x700
_COB_TPDOS = (0x180, 0x280, 0x380, 0x480)


@dataclass(frozen=True)
class SdoRead:
    """One object the probe reads: where, what it is called, its size and sign."""

    index: int
    subindex: int
    what: str
    size: int = 4        # bytes
    signed: bool = False

    def label(self) -> str:
        return f"0x{self.index:04X}:{self.subindex:02X} ({self.what})"


VENDOR = SdoRead(0x1018, 1, "identity: vendor id")
PRODUCT = SdoRead(0x1018, 2, "identity: product code")
REVISION = SdoRead(0x1018, 3, "identity: revision number")
SERIAL = SdoRead(0x1018, 4, "identity: serial number")
MODES = SdoRead(0x6502, 0, "supported drive modes")
RATED_TORQUE = SdoRead(0x6076, 0, "motor rated torque")
HEARTBEAT = SdoRead(0x1017, 0, "producer heartbeat time", 2)
STATUSWORD = SdoRead(0x6041, 0, "statusword", 2)


class _Unanswered(Exception):
    """The node did not answer one read (the line says which)."""


class CiA402Preflight(PreflightProbe):
    """Reads the node's objects by SDO, then listens for the rest of the window."""

    checks_rates = False  # the start-up writes 0x1006/0x1017 itself; TPDOs only follow SYNC
    budget_fewer = "fewer axes or TPDOs on this bus"

    def __init__(self, profile: DriveProfile) -> None:
        super().__init__(profile)
        self.options: Mapping[str, Any] = getattr(profile, "options", {}) or {}
        self.values: dict[SdoRead, int] = {}     # what the node answered
        self.mapping_sizes: dict[str, int] = {}  # "RPDO1" -> bits, from the EDS
        self.heard_from: set[int] = set()

    # -- the framework's hooks ------------------------------------------------

    def requests(self, node: int) -> Sequence[can.Message]:
        return ()   # everything is asked by SDO in listen()

    def observe(self, msg: can.Message) -> Observation | None:
        if msg.is_extended_id or msg.is_remote_frame or msg.is_error_frame:
            return None
        cob, data = msg.arbitration_id, bytes(msg.data)
        base, node = cob & 0x780, cob & 0x7F
        if not node:
            return None   # NMT (0x000), SYNC (0x080): no node's own frame
        if base == _COB_HEARTBEAT and len(data) >= 1:
            return Observation(node, Stream.STATUS, data[:1])
        if base == _COB_SDO_TX:
            return Observation(node, Stream.VERSION, data)
        if base in _COB_TPDOS:
            return Observation(node, Stream.MOTION, data)
        return None

    def setting(self, which: Setting) -> str:
        return {Setting.NODE_ID: "the node id (vendor tool or LSS)",
                Setting.MOTION_RATE: "0x1006 communication cycle period [us]",
                Setting.STATUS_RATE: "0x1017 producer heartbeat time [ms]"}[which]

    def setting_value(self, which: Setting, value: float) -> str:
        if which is Setting.MOTION_RATE:
            return f"{value * 1e6:g}"
        return super().setting_value(which, value)

    def motion_name(self) -> str:
        return "TPDOs"

    def status_name(self) -> str:
        return "heartbeat"

    def cycle_frames(self, period: float) -> Sequence[CycleFrame]:
        """Per SYNC: the SYNC itself, the RPDO, both TPDOs; the heartbeat's share."""
        rpdo, tpdo = self._pdo_numbers()
        sizes = [sum(_STANDARD_BITS[o] for o in m) // 8 for m in (RPDO_MAPPING, *TPDO_MAPPINGS)]
        frames = [CycleFrame("SYNC", 0), CycleFrame(f"RPDO{rpdo}", sizes[0]),
                  CycleFrame(f"TPDO{tpdo}", sizes[1]), CycleFrame(f"TPDO{tpdo + 1}", sizes[2])]
        heartbeat = _heartbeat_period(self.profile)
        if heartbeat:
            frames.append(CycleFrame("heartbeat", 1, every=heartbeat))
        return tuple(frames)

    # -- the window: SDO reads, then listening ----------------------------------

    def listen(self, bus: can.BusABC, window: float, clock: Callable[[], float],
               stamp: Callable[[can.Message], float], cancel: Cancel | None) -> Capture:
        cap = Capture()
        end = clock() + window
        node_id = self.profile.node_id
        od = self._object_dictionary(cap)
        network = canopen.Network(bus)
        remote = canopen.RemoteNode(node_id, od if od is not None else ObjectDictionary())
        network.add_node(remote)
        remote.sdo.RESPONSE_TIMEOUT = self._sdo_timeout()  # canopen's documented per-client setting
        notifier = can.Notifier(bus, [*network.listeners, _Tap(cap, self, stamp)], timeout=WAIT_SLICE)
        try:
            with quiet_sdo_client():
                unanswered = self._read_all(remote, cap, cancel)
            while (now := clock()) < end and not cap.read_error and not (cancel is not None and cancel()):
                time.sleep(min(end - now, WAIT_SLICE))
        finally:
            notifier.stop(timeout=1.0)
            del network[node_id]   # unsubscribes the node's SDO/heartbeat/EMCY callbacks
        if unanswered:
            cap.verdict = Finding(Severity.MISMATCH, unanswered + self._others(cap), refuses_run=True)
        elif od is not None:
            cap.findings += self._mapping_findings(od)
        return cap

    def _read_all(self, remote: canopen.RemoteNode, cap: Capture, cancel: Cancel | None) -> str:
        """Read every object in turn; the one line when the node does not answer ("": it did)."""
        for read in (VENDOR, PRODUCT, REVISION, SERIAL, MODES, RATED_TORQUE, HEARTBEAT, STATUSWORD):
            if cancel is not None and cancel():
                return ""
            try:
                self.values[read] = self._upload(remote, read)
            except _Unanswered as exc:
                return str(exc)
            except SdoAbortedError as exc:
                cap.findings.append(Finding(
                    Severity.MISMATCH, f"node {remote.id}: SDO upload of {read.label()} aborted: {exc} "
                                       f"({_abort_hint(read)})", refuses_run=read in (MODES, RATED_TORQUE)))
        rpdo, tpdo = self._pdo_numbers()
        for name, index in ((f"RPDO{rpdo}", 0x1600 + rpdo - 1), (f"TPDO{tpdo}", 0x1A00 + tpdo - 1),
                            (f"TPDO{tpdo + 1}", 0x1A00 + tpdo)):
            read = SdoRead(index, 0, f"{name} mapping: number of entries", 1)
            try:
                self._upload(remote, read)
            except _Unanswered as exc:
                return str(exc)
            except SdoAbortedError as exc:
                cap.findings.append(Finding(
                    Severity.MISMATCH, f"node {remote.id} has no {name} mapping: SDO upload of {read.label()} "
                                       f"aborted: {exc} (set cia402.rpdo/tpdo to PDOs the drive has)",
                    refuses_run=True))
        return ""

    def _upload(self, remote: canopen.RemoteNode, read: SdoRead) -> int:
        try:
            data = remote.sdo.upload(read.index, read.subindex)
        except SdoCommunicationError:
            raise _Unanswered(f"node {remote.id} does not answer SDO: no reply to the upload of {read.label()} "
                              f"within {self._sdo_timeout():g} s") from None
        return int.from_bytes(bytes(data[:read.size]), "little", signed=read.signed)

    def _others(self, cap: Capture) -> str:
        others = sorted(n for n in cap.nodes if n != self.profile.node_id)
        if not others:
            return ""
        name = self.profile.name or self.profile.protocol
        return (f"; node(s) {', '.join(map(str, others))} heard on the bus: node_id: {others[0]} in "
                f"profile {name!r} if that is the drive")

    # -- the profile's options ----------------------------------------------------

    def _sdo_timeout(self) -> float:
        return float(self.options.get("sdo_timeout", 0.3))

    def _pdo_numbers(self) -> tuple[int, int]:
        return int(self.options.get("rpdo", 1)), int(self.options.get("tpdo", 1))

    def _object_dictionary(self, cap: Capture) -> ObjectDictionary | None:
        """The profile's EDS (None, with a finding, when it cannot be read)."""
        eds = self.options.get("eds")
        if not eds:
            return None
        path = _eds_path(self.profile, str(eds))
        try:
            return canopen.import_od(str(path), self.profile.node_id)
        except Exception as exc:   # canopen raises what its parser meets (OSError, ValueError ...)
            cap.findings.append(Finding(Severity.NOTE, f"EDS {path} not read ({type(exc).__name__}: {exc}): "
                                                       "PDO sizes not checked"))
            return None

    # -- what the node said -------------------------------------------------------

    def node_summary(self, node: NodeReport) -> str:
        words = [f"NMT {_nmt_state(node.status_data)}"] if node.status_data else []
        if node.node != self.profile.node_id or VENDOR not in self.values:
            return "; ".join(words)
        v = self.values
        words.append("identity vendor 0x{:08X} product 0x{:08X} revision 0x{:08X} serial 0x{:08X}".format(
            *(v.get(r, 0) for r in (VENDOR, PRODUCT, REVISION, SERIAL))))
        if MODES in v:
            words.append(f"modes 0x{v[MODES]:08X} (CST {'supported' if v[MODES] & CST_BIT else 'NOT supported'})")
        if RATED_TORQUE in v:
            unit = self._unit()
            words.append(f"rated torque {v[RATED_TORQUE]} {unit} = {v[RATED_TORQUE] * TORQUE_UNITS[unit]:.6g} Nm")
        if HEARTBEAT in v:
            words.append(f"heartbeat 0x1017 = {v[HEARTBEAT]} ms")
        if STATUSWORD in v:
            words.append(f"statusword 0x{v[STATUSWORD]:04X} ({power_state(v[STATUSWORD])})")
        if self.mapping_sizes:
            words.append("PDOs " + ", ".join(f"{k} {b} bits" for k, b in self.mapping_sizes.items()))
        return "; ".join(words)

    def node_findings(self, node: NodeReport) -> list[Finding]:
        if node.node != self.profile.node_id:
            return []
        v, out = self.values, []
        if MODES in v and not v[MODES] & CST_BIT:
            out.append(Finding(Severity.MISMATCH,
                               f"node {node.node} does not support cyclic synchronous torque: 0x6502 = "
                               f"0x{v[MODES]:08X}, bit 9 (CST) clear; dobhil runs CiA 402 drives in CST",
                               refuses_run=True))
        if RATED_TORQUE in v:
            out += self._rated_torque_findings(node.node, v[RATED_TORQUE])
        expected = _heartbeat_period(self.profile)
        if HEARTBEAT in v and expected and abs(v[HEARTBEAT] - expected * 1e3) >= 0.5:
            now = "off" if v[HEARTBEAT] == 0 else f"{v[HEARTBEAT]} ms"
            out.append(Finding(Severity.NOTE,
                               f"node {node.node}'s producer heartbeat 0x1017 is {now}, the profile's "
                               f"heartbeat_period {expected * 1e3:g} ms: the drive's start-up writes it"))
        if STATUSWORD in v and power_state(v[STATUSWORD]) == "operation enabled":
            out.append(Finding(Severity.MISMATCH,
                               f"node {node.node} is in operation enabled (statusword 0x{v[STATUSWORD]:04X}): "
                               "another host may be driving it; disable it first", refuses_run=True))
        return out

    def _unit(self) -> str:
        unit = str(self.options.get("rated_torque_unit", "mNm"))
        return unit if unit in TORQUE_UNITS else "mNm"

    def _rated_torque_findings(self, node: int, raw: int) -> list[Finding]:
        unit = self._unit()
        measured = raw * TORQUE_UNITS[unit]
        expected = self.options.get("rated_torque")
        if raw == 0:
            return [Finding(Severity.MISMATCH, f"node {node}: 0x6076 motor rated torque is 0: every torque "
                                               "command is per mille of it; set it on the drive", refuses_run=True)]
        if expected is None or abs(measured - float(expected)) <= TORQUE_UNITS[unit] / 2 + 1e-9 * measured:
            return []
        other = next(u for u in TORQUE_UNITS if u != unit)
        return [Finding(Severity.MISMATCH,
                        f"node {node}: 0x6076 motor rated torque = {raw} {unit} = {measured:.6g} Nm, profile "
                        f"cia402.rated_torque is {float(expected):g} Nm: every torque would be scaled by "
                        f"{measured / float(expected):.4g}; set cia402.rated_torque: {measured:.6g} (or, if 0x6076 "
                        f"is in {other} on this drive, cia402.rated_torque_unit: {other} = "
                        f"{raw * TORQUE_UNITS[other]:.6g} Nm)", refuses_run=True)]

    def _mapping_findings(self, od: ObjectDictionary) -> list[Finding]:
        """SPEC-17's mapping, sized from the EDS: each PDO within 8 bytes, every object mappable."""
        rpdo, tpdo = self._pdo_numbers()
        out: list[Finding] = []
        for name, entries in ((f"RPDO{rpdo}", RPDO_MAPPING), (f"TPDO{tpdo}", TPDO_MAPPINGS[0]),
                              (f"TPDO{tpdo + 1}", TPDO_MAPPINGS[1])):
            bits = 0
            for index, sub in entries:
                var = od.get_variable(index, sub)
                if var is None:
                    out.append(Finding(Severity.MISMATCH, f"{name}: 0x{index:04X}:{sub:02X} is not in the EDS",
                                       refuses_run=True))
                    continue
                bits += _TYPE_BITS.get(var.data_type or 0, 0)
                if not var.pdo_mappable:
                    out.append(Finding(Severity.MISMATCH, f"{name}: 0x{index:04X}:{sub:02X} ({var.name}) is not "
                                                          "PDO-mappable in the EDS", refuses_run=True))
            self.mapping_sizes[name] = bits
            if bits > PDO_BITS:
                out.append(Finding(Severity.MISMATCH, f"{name} mapping is {bits} bits, over the {PDO_BITS} of a "
                                                      "CAN frame", refuses_run=True))
        return out


class _Tap(can.Listener):
    """Every frame the notifier reads goes into the capture too (the preflight's counts)."""

    def __init__(self, cap: Capture, probe: PreflightProbe, stamp: Callable[[can.Message], float]) -> None:
        self._cap, self._probe, self._stamp = cap, probe, stamp

    def on_message_received(self, msg: can.Message) -> None:
        self._cap.take(msg, self._probe, self._stamp)

    def on_error(self, exc: Exception) -> None:
        # the bus failed under the notifier: the window ends (as the default path's
        # listening does). Handled here, python-can's notifier keeps reading the dead
        # bus until it is stopped: the pause keeps that from spinning a core meanwhile
        self._cap.read_error = " ".join(f"{type(exc).__name__}: {exc}".split())
        time.sleep(WAIT_SLICE)


#: sizes of SPEC-17's mapped objects (CiA 402 data types), for the budget without an EDS
_STANDARD_BITS = {(0x6040, 0): 16, (0x6071, 0): 16, (0x6041, 0): 16, (0x6064, 0): 32, (0x6077, 0): 16,
                  (0x606C, 0): 32, (0x6061, 0): 8}


class _DropBelowCritical(logging.Filter):
    def filter(self, record: logging.LogRecord) -> bool:
        return record.levelno >= logging.CRITICAL


@contextmanager
def quiet_sdo_client() -> Iterator[None]:
    """canopen's SDO client logs an ERROR record ("Transfer aborted by client with code
    0x05040000") when a read times out: without a logging configuration Python prints it
    through its last-resort handler, a second, unexplained line beside the preflight's
    own (which names the node and the object). The workaround, isolated here: a filter on
    that one logger while the preflight reads, removed after."""
    logger = logging.getLogger("canopen.sdo.client")
    quiet = _DropBelowCritical()
    logger.addFilter(quiet)
    try:
        yield
    finally:
        logger.removeFilter(quiet)


def power_state(statusword: int) -> str:
    """The CiA 402 power state a statusword shows."""
    for mask, value, name in POWER_STATES:
        if statusword & mask == value:
            return name
    return "unknown state"


def _nmt_state(data: bytes) -> str:
    state = data[0] & 0x7F
    return NMT_STATES.get(state, f"state 0x{state:02X}")


def _heartbeat_period(profile: DriveProfile) -> float | None:
    return getattr(profile, "heartbeat_period", None)


def _eds_path(profile: DriveProfile, eds: str) -> Path:
    """The EDS as the drive finds it: a path, or relative to the profile's directory."""
    source = getattr(profile, "source", None)
    path = Path(eds)
    if path.is_absolute() or source is None:
        return path
    return Path(source).parent / path


def _abort_hint(read: SdoRead) -> str:
    if read in (MODES, RATED_TORQUE):
        return "dobhil needs it to run the drive in CST"
    return "the drive's object dictionary lacks it"
