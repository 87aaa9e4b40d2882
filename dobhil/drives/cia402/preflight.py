"""CANopen CiA 402 part of the preflight (:mod:`dobhil.drives.preflight`).

A CiA 402 drive says what it is only when asked: the probe reads its object dictionary
by SDO with canopen's SDO client, through the drive's own link
(:class:`dobhil.drives.cia402.link.CanopenLink`: no notifier thread; the answers are
read on the preflight's clock in WAIT_SLICE slices, so a stop request ends a read
within a slice and a lockstep preflight stays deterministic). Nothing is written, no
NMT command sent:

- identity 0x1018:01..04 (vendor id, product code, revision, serial number): the node
  answers SDO at all. A node that never answers is ONE finding naming the node and the
  SDO object asked (``node 9 does not answer SDO: no reply to the upload of 0x1018:01
  (identity: vendor id) within 0.3 s``), and the run refuses it;
- supported drive modes 0x6502: bit 9 = cyclic synchronous torque (CST), the mode dobhil
  runs in (CiA 402);
- motor rated torque 0x6076 in the profile's ``cia402.rated_torque_unit`` (mNm per
  CiA 402, uNm on an EPOS4), in Nm against ``cia402.rated_torque`` within the drive's
  own tolerance: every torque command is per mille of it, so a wrong value scales every
  torque, and the run refuses (the drive's start-up would refuse it too);
- the PDO mapping: SPEC-17's mapping of each PDO, typed by the profile's EDS, fits a
  PDO's 64 bits (:func:`dobhil.drives.cia402.eds.load_od`, the drive's own check: an
  EDS that does not fit, or lacks an object the drive needs, is bad input, one line,
  before anything is sent), every mapped object is PDO-mappable in the EDS, and the
  mapping parameters of the profile's RPDO and TPDOs exist on the node (0x1600 + n - 1,
  0x1A00 + n - 1, sub 0);
- position encoder resolution 0x608F:01/02 and gear ratio 0x6091:01/02 (where the EDS
  has them), against the profile's ``position_per_rev`` and ``gear_ratio`` (sub 1 / sub 2,
  :data:`dobhil.drives.cia402.codec.UNIT_OBJECTS`): they scale every position and
  velocity, so a difference refuses the run (the drive's start-up would refuse it too);
  an aborted read is a note (the drive lacks the object: its units are not checked);
- producer heartbeat time 0x1017 against the profile's ``heartbeat_period`` (the drive's
  start-up writes it: a difference is a note; the period is measured while listening);
- statusword 0x6041: a drive already in Operation enabled may be driven by another
  host, and the run refuses (as ODrive's CLOSED_LOOP_CONTROL); a drive in Fault (or Fault
  reaction active) is a mismatch: the enable refuses it unless ``--reset-faults``.

Listening for the rest of the window hears heartbeats (0x700 + id: NMT state, period),
SDO replies and TPDOs (none before the drive's start-up: a TPDO answers SYNC, in NMT
operational). The bus budget per SYNC: SYNC (0 bytes), the RPDO (4: controlword +
target torque), TPDO1 (8: statusword + position + torque actual), TPDO2 (5: velocity +
mode display), and the heartbeat's share (1 byte every ``heartbeat_period``; the host's
own, for ``consumer_heartbeat``, at the drive's period for it).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import can
import canopen
from canopen.objectdictionary import ObjectDictionary
from canopen.sdo import SdoAbortedError, SdoCommunicationError

from dobhil.drives.bus_load import CycleFrame
from dobhil.drives.cia402.codec import (CST_SUPPORTED_BIT, host_heartbeat_interval,
                                        RATED_TORQUE_TOLERANCE, RATED_TORQUE_UNITS, RPDO_CST, TPDO_MOTION,
                                        TPDO_STATUS, UNIT_OBJECTS, Cob, Mapped, NmtState, PowerState, UnitObject,
                                        layout_bits, power_state)
from dobhil.drives.cia402.eds import STANDARD_LAYOUTS, load_od
from dobhil.drives.cia402.link import CanopenLink
from dobhil.drives.preflight import (Capture, Finding, NodeReport, Observation, PreflightProbe, Setting,
                                     Severity, Stream, listen_window)
from dobhil.drives.profile import DriveProfile
from dobhil.drives.waits import Cancel
from dobhil.errors import WaitCancelled, exception_line

__all__ = ["READS", "UNIT_READS", "CiA402Preflight", "SdoRead"]

_TPDO_COBS = frozenset({Cob.TPDO1, Cob.TPDO2, Cob.TPDO3, Cob.TPDO4})


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
#: in this order: the first read tells whether the node answers at all
READS = (VENDOR, PRODUCT, REVISION, SERIAL, MODES, RATED_TORQUE, HEARTBEAT, STATUSWORD)
#: objects without which dobhil cannot run the drive: an abort of their read refuses the run
_NEEDED = frozenset({MODES, RATED_TORQUE})
#: 0x608F and 0x6091, sub 1 and sub 2 each (read where the EDS lists them)
UNIT_READS: tuple[tuple[UnitObject, SdoRead, SdoRead], ...] = tuple(
    (obj, SdoRead(obj.index, 1, f"{obj.name}: {obj.numerator}"),
     SdoRead(obj.index, 2, f"{obj.name}: {obj.denominator}")) for obj in UNIT_OBJECTS)


class _Unanswered(Exception):
    """The node did not answer one read (the exception's text is the one line)."""


class CiA402Preflight(PreflightProbe):
    """Reads the node's objects by SDO, then listens for the rest of the window."""

    checks_rates = False  # the start-up writes 0x1006/0x1017 itself; TPDOs only follow SYNC
    budget_fewer = "fewer TPDOs"

    def __init__(self, profile: DriveProfile) -> None:
        super().__init__(profile)
        self.options: Mapping[str, Any] = profile.options
        self.values: dict[SdoRead, int] = {}     # what the node answered
        self.mapping_sizes: dict[str, int] = {}  # "RPDO1" -> bits (the EDS's types, checked = the standard's)

    # -- the framework's hooks ------------------------------------------------

    def requests(self, node: int) -> Sequence[can.Message]:
        return ()   # everything is asked by SDO in listen()

    def observe(self, msg: can.Message) -> Observation | None:
        if msg.is_extended_id or msg.is_remote_frame or msg.is_error_frame:
            return None
        base, node = msg.arbitration_id & 0x780, msg.arbitration_id & 0x7F
        if not node:
            return None   # NMT (0x000), SYNC (0x080): no node's own frame
        data = bytes(msg.data)
        if base == Cob.HEARTBEAT and data:
            return Observation(node, Stream.STATUS, data[:1])
        if base == Cob.SDO_TX:
            return Observation(node, Stream.VERSION, data)
        if base in _TPDO_COBS:
            return Observation(node, Stream.MOTION, data)
        return None

    def setting(self, which: Setting) -> str:
        return {Setting.NODE_ID: "the node id (the vendor's tool, or LSS)",
                Setting.MOTION_RATE: "0x1006 communication cycle period [us]",
                Setting.STATUS_RATE: "0x1017 producer heartbeat time [ms]"}[which]

    def setting_value(self, which: Setting, value: float) -> str:
        if which is Setting.MOTION_RATE:
            return f"{value * 1e6:g}"
        return super().setting_value(which, value)

    def motion_name(self) -> str:
        return "TPDOs"

    def rate_advice(self, period: float) -> str:
        # the host writes the cycle period and sends every SYNC itself: TPDOs slower than the
        # SYNC are a node that skips SYNCs, not a setting to change on it
        return (f"node {self.profile.node_id} answers fewer SYNCs than the host sends: it cannot keep "
                f"up with loop.period = {period * 1e3:g} ms (raise it), or its TPDO transmission type "
                f"(0x1800:02) skips SYNCs")

    def status_name(self) -> str:
        return "heartbeat"

    def cycle_frames(self, period: float) -> Sequence[CycleFrame]:
        """The RPDO once per loop period; per SYNC, the SYNC itself (no data) and both TPDOs
        (SPEC-17's mapping at the standard data types); the heartbeat (1 byte) at its own period.

        The SYNC goes after each command where the bus sends no periodic frame natively, and
        every ``feedback_period`` where it does (:meth:`CiA402Drive._start_sync
        <dobhil.drives.cia402.drive.CiA402Drive._start_sync>`): which one is known only once the
        bus is open, so the SYNC and the TPDOs answering it count at the faster of the two."""
        rpdo, tpdo = self._pdo_numbers()
        sync = self.profile.feedback_period
        # one SYNC per bus drives every node's PDOs
        key = "the profile's feedback_period"
        frames = [CycleFrame("SYNC", 0, shared=True, or_every=sync, or_every_key=key)]
        (command, command_map), *answers = self._mappings(rpdo, tpdo)
        frames.append(CycleFrame(command, layout_bits([m.data_type for m in command_map]) // 8))
        frames += [CycleFrame(name, layout_bits([m.data_type for m in mapping]) // 8, or_every=sync,
                              or_every_key=key) for name, mapping in answers]
        heartbeat = self.profile.heartbeat_period
        if heartbeat:
            frames.append(CycleFrame("heartbeat", 1, every=heartbeat))
        consumer = float(self.options.get("consumer_heartbeat", 0.0))
        if consumer > 0:   # the host's own heartbeat for the node's consumer 0x1016 (the drive's period)
            frames.append(CycleFrame("host heartbeat", 1, every=host_heartbeat_interval(consumer, sync or period)))
        return tuple(frames)

    # -- the window: SDO reads, then listening ----------------------------------

    def listen(self, bus: can.BusABC, window: float, clock: Callable[[], float],
               stamp: Callable[[can.Message], float], cancel: Cancel | None) -> Capture:
        cap = Capture()
        end = clock() + window
        # the drive's own checks of the EDS first: bad input is one line (ConfigError, exit
        # 2) before anything is sent
        od = load_od(self.profile)   # checks the mapping fits, with the standard's data types
        layouts = STANDARD_LAYOUTS
        for (name, _), layout in zip(self._mappings(*self._pdo_numbers()),
                                     (layouts.rpdo, layouts.status, layouts.motion)):
            self.mapping_sizes[name] = layout.size * 8

        def take(msg: can.Message) -> None:
            cap.take(msg, self, stamp)

        link = CanopenLink(bus, od, node_id=self.profile.node_id,
                           clock=clock, sdo_timeout=self._sdo_timeout(), on_frame=take)
        # the node's SDO answers go to canopen's client; counted here too (bus load, the node heard)
        link.network.subscribe(Cob.SDO_TX + self.profile.node_id,
                               lambda cob, data, ts: take(can.Message(arbitration_id=cob, data=bytes(data),
                                                                      timestamp=ts, is_extended_id=False)))
        unanswered = ""
        try:
            with link.session(cancel):
                unanswered = self._read_all(link.node, cap)
                if not unanswered:
                    self._read_units(link.node, od, cap)
        except WaitCancelled:
            return cap   # the caller stops (SIGINT): what was heard so far is all there is
        except Exception as exc:  # the bus refused a request (gone, queue full): nothing more to ask
            cap.send_errors.append(exception_line(exc, named=False))
        if clock() < end:
            listen_window(bus, self, end - clock(), clock, stamp, cancel, cap)
        if unanswered:
            cap.verdict = Finding(Severity.MISMATCH, unanswered + self._others(cap), refuses_run=True)
        else:
            cap.findings += self._mappable_findings(od)
        return cap

    def _read_all(self, node: canopen.RemoteNode, cap: Capture) -> str:
        """Read every object in turn; the one line when the node does not answer ("": it did)."""
        try:
            for read in READS:
                try:
                    self.values[read] = self._upload(node, read)
                except SdoAbortedError as exc:
                    why = "dobhil needs it to run the drive in CST" if read in _NEEDED else "the drive lacks it"
                    cap.findings.append(Finding(
                        Severity.MISMATCH, f"node {node.id} aborted the SDO upload of {read.label()}: {exc} ({why})",
                        refuses_run=read in _NEEDED))
            rpdo, tpdo = self._pdo_numbers()
            for name, index in ((f"RPDO{rpdo}", 0x1600 + rpdo - 1), (f"TPDO{tpdo}", 0x1A00 + tpdo - 1),
                                (f"TPDO{tpdo + 1}", 0x1A00 + tpdo)):
                read = SdoRead(index, 0, f"{name} mapping: number of entries", 1)
                try:
                    self._upload(node, read)
                except SdoAbortedError as exc:
                    cap.findings.append(Finding(
                        Severity.MISMATCH, f"node {node.id} has no {name} mapping: SDO upload of {read.label()} "
                                           f"aborted: {exc} (set cia402.rpdo/tpdo to PDOs the drive has)",
                        refuses_run=True))
        except _Unanswered as exc:
            return str(exc)
        return ""

    def _read_units(self, node: canopen.RemoteNode, od: ObjectDictionary, cap: Capture) -> None:
        """0x608F and 0x6091 where the EDS lists them; an abort is a note (not checked)."""
        for obj, num, den in UNIT_READS:
            if od.get_variable(num.index, num.subindex) is None or od.get_variable(den.index, den.subindex) is None:
                continue
            try:
                self.values[num] = self._upload(node, num)
                self.values[den] = self._upload(node, den)
            except SdoAbortedError as exc:
                self.values.pop(num, None)
                cap.findings.append(Finding(
                    Severity.NOTE, f"node {node.id} aborted the SDO upload of 0x{obj.index:04X} ({obj.name}): "
                                   f"{exc}: cia402.{obj.key} not checked against the drive"))

    def _upload(self, node: canopen.RemoteNode, read: SdoRead) -> int:
        try:
            data = node.sdo.upload(read.index, read.subindex)
        except SdoCommunicationError:
            raise _Unanswered(f"node {node.id} does not answer SDO: no reply to the upload of {read.label()} "
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

    @staticmethod
    def _mappings(rpdo: int, tpdo: int) -> tuple[tuple[str, tuple[Mapped, ...]], ...]:
        return ((f"RPDO{rpdo}", RPDO_CST), (f"TPDO{tpdo}", TPDO_STATUS), (f"TPDO{tpdo + 1}", TPDO_MOTION))

    # -- what the node said -------------------------------------------------------

    def node_summary(self, node: NodeReport) -> str:
        words = [f"NMT {_nmt_state(node.status_data[0])}"] if node.status_data else []
        if node.node != self.profile.node_id or VENDOR not in self.values:
            return "; ".join(words)
        v = self.values
        words.append("identity vendor 0x{:08X} product 0x{:08X} revision 0x{:08X} serial 0x{:08X}".format(
            *(v.get(r, 0) for r in (VENDOR, PRODUCT, REVISION, SERIAL))))
        if MODES in v:
            cst = "supported" if v[MODES] >> CST_SUPPORTED_BIT & 1 else "NOT supported"
            words.append(f"modes 0x{v[MODES]:08X} (CST {cst})")
        if RATED_TORQUE in v:
            unit = self._unit()
            words.append(f"rated torque {v[RATED_TORQUE]} {unit} = {v[RATED_TORQUE] * RATED_TORQUE_UNITS[unit]:.6g} Nm")
        for obj, num, den in UNIT_READS:
            if num in v and den in v:
                words.append(f"{obj.stated(v[num], v[den])}")
        if HEARTBEAT in v:
            words.append(f"heartbeat 0x1017 = {v[HEARTBEAT]} ms")
        if STATUSWORD in v:
            words.append(f"statusword 0x{v[STATUSWORD]:04X} ({power_state(v[STATUSWORD]).text})")
        if self.mapping_sizes:
            words.append("PDOs " + ", ".join(f"{k} {b} bits" for k, b in self.mapping_sizes.items()))
        return "; ".join(words)

    def node_findings(self, node: NodeReport) -> list[Finding]:
        if node.node != self.profile.node_id:
            return []
        v, out = self.values, []
        if MODES in v and not v[MODES] >> CST_SUPPORTED_BIT & 1:
            out.append(Finding(Severity.MISMATCH,
                               f"node {node.node} does not support cyclic synchronous torque: 0x6502 = "
                               f"0x{v[MODES]:08X}, bit 9 (CST) clear; dobhil runs CiA 402 drives in CST",
                               refuses_run=True))
        if RATED_TORQUE in v:
            out += self._rated_torque_findings(node.node, v[RATED_TORQUE])
        out += self._unit_findings(node.node)
        expected = self.profile.heartbeat_period
        if HEARTBEAT in v and expected and abs(v[HEARTBEAT] - expected * 1e3) >= 0.5:
            now = "off" if v[HEARTBEAT] == 0 else f"{v[HEARTBEAT]} ms"
            out.append(Finding(Severity.NOTE,
                               f"node {node.node}'s producer heartbeat 0x1017 is {now}, the profile's "
                               f"heartbeat_period {expected * 1e3:g} ms: the drive's start-up writes it"))
        state = power_state(v[STATUSWORD]) if STATUSWORD in v else None
        if state is PowerState.OPERATION_ENABLED:
            out.append(Finding(Severity.MISMATCH,
                               f"node {node.node} is in operation enabled (statusword 0x{v[STATUSWORD]:04X}): "
                               "another host may be driving it; disable it first", refuses_run=True))
        elif state in (PowerState.FAULT, PowerState.FAULT_REACTION_ACTIVE):
            # the enable refuses a node in fault unless --reset-faults (CiA402Drive): not a refusal
            # of the preflight, as a moteus or MIT fault that the run can clear is not
            out.append(Finding(Severity.MISMATCH,
                               f"node {node.node} is in {state.text} (statusword 0x{v[STATUSWORD]:04X}): dobhil "
                               "run --reset-faults resets it (controlword bit 7) once the cause is gone"))
        return out

    def _unit(self) -> str:
        unit = str(self.options.get("rated_torque_unit", "mNm"))
        return unit if unit in RATED_TORQUE_UNITS else "mNm"

    def _rated_torque_findings(self, node: int, raw: int) -> list[Finding]:
        unit = self._unit()
        measured = raw * RATED_TORQUE_UNITS[unit]
        expected = self.options.get("rated_torque")
        if raw == 0:
            return [Finding(Severity.MISMATCH, f"node {node}'s motor rated torque 0x6076 is 0: every torque "
                                               "command is per mille of it; set it on the drive", refuses_run=True)]
        if expected is None or abs(measured - float(expected)) <= RATED_TORQUE_TOLERANCE * float(expected):
            return []
        other = next(u for u in RATED_TORQUE_UNITS if u != unit)
        return [Finding(Severity.MISMATCH,
                        f"node {node}'s motor rated torque 0x6076 = {raw} {unit} = {measured:.6g} Nm is not the "
                        f"profile's cia402.rated_torque {float(expected):g} Nm: every torque would be scaled by "
                        f"{measured / float(expected):.4g}; set cia402.rated_torque: {measured:.6g} (or, if 0x6076 "
                        f"is in {other} on this drive, cia402.rated_torque_unit: {other} = "
                        f"{raw * RATED_TORQUE_UNITS[other]:.6g} Nm)", refuses_run=True)]

    def _unit_findings(self, node: int) -> list[Finding]:
        """The drive's 0x608F / 0x6091 against the profile's position_per_rev / gear_ratio."""
        out: list[Finding] = []
        for obj, num, den in UNIT_READS:
            if num not in self.values or den not in self.values or obj.key not in self.options:
                continue
            n, d, expected = self.values[num], self.values[den], float(self.options[obj.key])
            agrees = obj.agrees(n, d, expected)
            if agrees is None:
                out.append(Finding(Severity.NOTE, f"node {node}'s {obj.stated(n, d)} is no ratio: "
                                                  f"cia402.{obj.key} not checked against the drive"))
            elif not agrees:
                out.append(Finding(Severity.MISMATCH,
                                   f"node {node}'s {obj.stated(n, d)} = {n / d:.10g} is not the profile's "
                                   f"cia402.{obj.key} {expected:.10g}: every position and velocity would be off "
                                   f"by a factor {n / d / expected:.6g}; set cia402.{obj.key}: {n / d:.10g} "
                                   "(or fix the drive)", refuses_run=True))
        return out

    def _mappable_findings(self, od: ObjectDictionary) -> list[Finding]:
        """Every object SPEC-17 maps is PDO-mappable in the EDS (else the node aborts the
        drive's mapping write at start-up, 0x06040041)."""
        return [Finding(Severity.MISMATCH, f"{name}: {m.label} is not PDO-mappable in the EDS", refuses_run=True)
                for name, mapping in self._mappings(*self._pdo_numbers()) for m in mapping
                if (var := od.get_variable(m.index, m.subindex)) is not None and not var.pdo_mappable]


def _nmt_state(byte: int) -> str:
    """The NMT state a heartbeat's byte names (bit 7 is the toggle bit of node guarding)."""
    try:
        return NmtState(byte & 0x7F).name.lower().replace("_", "-")
    except ValueError:
        return f"state 0x{byte & 0x7F:02X}"
