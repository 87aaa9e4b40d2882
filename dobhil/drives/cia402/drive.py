"""CiA 402 servo drive in cyclic synchronous torque (CST), over CANopen through canopen.

Start-up (:meth:`CiA402Drive._prepare`, before any torque), by SDO through
:mod:`dobhil.drives.cia402.link` (canopen without its notifier thread): NMT
pre-operational; identity 0x1018; statusword 0x6041 (and error code 0x603F when in
fault); supported modes 0x6502 (bit 9: CST); rated torque 0x6076 in the profile's unit,
checked against the profile's ``rated_torque``; position encoder resolution 0x608F and
gear ratio 0x6091 (where the EDS has them) checked against ``position_per_rev`` and
``gear_ratio`` (an abort of their read: a note in :attr:`CiA402Drive.notes`); the PDO mapping written with canopen's
``node.rpdo``/``node.tpdo`` (RPDO n: controlword 0x6040 + target torque 0x6071; TPDO n:
statusword 0x6041 + position 0x6064 + torque actual 0x6077; TPDO n+1: velocity 0x606C +
mode display 0x6061; all synchronous, transmission type 1); communication cycle period
0x1006; producer heartbeat 0x1017; mode of operation 0x6060 = 10 (CST); NMT operational;
then SYNC (0x80) every ``feedback_period``: python-can ``send_periodic`` where it runs
outside this process's Python threads (:func:`dobhil.drives.periodic.native_periodic`),
else sent by the drive right after each torque frame (``feedback_streams`` is False).

Enable: the power state machine stepped on the TPDO's statusword (shutdown, switch on,
enable operation), confirmed by Operation enabled with 0x6061 = 10. A node in FAULT
ends the enable with its EMCY code, unless ``reset_faults`` (one rising edge of
controlword bit 7, once).

Cycle: the RPDO (controlword 0x0F, target torque per mille of the rated torque) goes out,
the node applies it at the next SYNC, samples and answers with both TPDOs; the motion
event comes with the second one (none when the first of that SYNC was lost), sampled at
the newest SYNC the bus stamped no later than that TPDO (:meth:`CiA402Drive._sampled_at`). EMCY
(0x80 + node), a statusword out of Operation enabled, an NMT state other than operational
in the heartbeat (0x700 + node) or a lost heartbeat are faults.

Safe stop: zero torque, quick stop (0x02), SYNC, disable voltage (0x00), SYNC -- each
attempted on its own; the SYNCs make the node apply each RPDO whatever SYNC source ran
(the periodic one stops after the confirmation, a statusword out of Operation enabled).

Replay: :meth:`apply` decodes recorded frames with the layouts the profile fixes (its
EDS's data types of the mapped objects), no start-up needed.
"""

from __future__ import annotations

import math
import struct
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from typing import TYPE_CHECKING, Any, ClassVar

import can
import canopen
from canopen.emcy import EmcyError
from canopen.objectdictionary import ObjectDictionary

from dobhil.drives.base import (Clock, Confirmation, Drive, DriveEvent, HostTimeout, MotionEvent, SafeStopReport,
                                StateEvent)
from dobhil.drives.cia402 import codec
from dobhil.drives.cia402.codec import CST_MODE, Cob, Controlword, Mapped, NmtState, PowerState
# in the codec (not here) so that the preflight probe shares them without importing the drive
from dobhil.drives.cia402.codec import RATED_TORQUE_TOLERANCE, RATED_TORQUE_UNITS
from dobhil.drives.cia402.eds import STANDARD_LAYOUTS, EdsNotFound, load_od
from dobhil.drives.cia402.link import CanopenLink
from dobhil.drives.cia402.rules import CIA402_RULES
from dobhil.drives.periodic import native_periodic
from dobhil.drives.profile import DriveProfile, ProtocolRules
from dobhil.drives.waits import Cancel
from dobhil.errors import BusError, CodecError, ConfigError, DriveError, DriveFaultError, DriveTimeoutError
from dobhil.errors import exception_line

if TYPE_CHECKING:
    from canopen.pdo import PdoMap

    from dobhil.drives.preflight import PreflightProbe

__all__ = ["CiA402Drive"]

_NO_EVENTS: tuple[DriveEvent, ...] = ()
_OUT_OF_TORQUE = frozenset(PowerState) - {PowerState.OPERATION_ENABLED, PowerState.UNKNOWN}


class CiA402Drive(Drive):
    protocol: ClassVar[str] = "cia402"
    active_state_text: ClassVar[str] = "operation enabled in CST"
    disabled_state_text: ClassVar[str] = "disable voltage"
    profile_rules: ClassVar[ProtocolRules] = CIA402_RULES

    def __init__(self, bus: can.BusABC, profile: DriveProfile, *, clock: Clock = time.monotonic,
                 reset_faults: bool = False) -> None:
        super().__init__(bus, profile, clock=clock, reset_faults=reset_faults)
        opts = profile.options
        node = profile.node_id
        self._rated = float(opts["rated_torque"])
        assert profile.feedback_period is not None  # the rules require it (the base checks)
        self._period = profile.feedback_period
        self._scale = codec.UnitScale.of(position_per_rev=opts["position_per_rev"],
                                         velocity_unit=opts["velocity_unit"], gear_ratio=opts["gear_ratio"])
        # the EDS is checked now (bad input: one line before anything is sent). A profile
        # rebuilt from a log (no directory) may come without it and needs none to decode:
        # the layouts are the standard's; only a start-up would need it
        try:
            self._od: ObjectDictionary | None = load_od(profile)
            self._missing: EdsNotFound | None = None
        except EdsNotFound as exc:
            if profile.directory:
                raise
            self._od, self._missing = None, exc
        if self._od is not None and float(opts["consumer_heartbeat"]) > 0 and 0x1016 not in self._od:
            raise ConfigError(f"drive profile {profile.name!r}: cia402.consumer_heartbeat: expected 0, the EDS "
                              "has no 0x1016 (consumer heartbeat time): this node cannot watch the host")
        if self._od is not None and 0x60C2 in self._od:
            try:
                codec.interpolation_period(self._period)
            except CodecError as exc:
                raise ConfigError(f"drive profile {profile.name!r}: feedback_period: {exc}") from None
        self._layouts = STANDARD_LAYOUTS
        self._rpdo_n, self._tpdo_n = int(opts["rpdo"]), int(opts["tpdo"])
        self._rpdo_id = Cob.rpdo(self._rpdo_n, node)
        self._status_id = Cob.tpdo(self._tpdo_n, node)
        self._motion_id = Cob.tpdo(self._tpdo_n + 1, node)
        self._emcy_id = Cob.emcy(node)
        self._heartbeat_id = Cob.HEARTBEAT + node
        self._link: CanopenLink | None = None  # made at start-up: replay never needs it
        self._sync_task: Any = None
        self._native_sync = False
        self._sync_msg = can.Message(arbitration_id=Cob.SYNC, data=b"", is_extended_id=False)
        self._host_id = int(opts["host_node_id"])
        if self._host_id == node and float(opts["consumer_heartbeat"]) > 0:
            raise ConfigError(f"drive profile {profile.name!r}: cia402.host_node_id: expected an id other "
                              f"than the node's ({node}): the host's heartbeat 0x{Cob.HEARTBEAT + node:03X} "
                              "would be the node's own")
        self._host_heartbeat = can.Message(arbitration_id=Cob.HEARTBEAT + self._host_id,
                                           data=bytes((NmtState.OPERATIONAL,)), is_extended_id=False)
        self._host_heartbeat_task: Any = None
        self._host_heartbeat_due: float | None = None  # without native periodic send
        self._host_heartbeat_period = 0.0
        # hot path: one preallocated RPDO refilled per cycle
        self._rpdo_msg = can.Message(arbitration_id=self._rpdo_id, is_extended_id=False,
                                     data=bytearray(self._layouts.rpdo.size))
        self._controlword = int(Controlword.SHUTDOWN)
        self._fault_reset_sent = False
        self._operational_commanded = False  # NMT start sent by this session's start-up
        # decoded state (TPDO1 and TPDO2 of one SYNC make one feedback sample)
        self._statusword = -1
        self._power = PowerState.UNKNOWN
        self._mode = 0
        self._position = math.nan
        self._status_fresh = False  # a TPDO1 came since the last TPDO2: they make one sample
        self._torque_actual = math.nan
        self._nmt = -1
        self._emcy = 0
        self._syncs = (math.nan, math.nan)   # the two newest SYNC stamps read: (before, newest)
        self.identity: tuple[int, ...] = ()

    # -- public ---------------------------------------------------------------

    @property
    def frame_ids(self) -> frozenset[int]:
        """SYNC, NMT, and this node's EMCY, PDOs, SDO and heartbeat (and the host's own
        heartbeat when the node watches it)."""
        node = self.node_id
        pdos = {Cob.tpdo(n, node) for n in range(1, 5)} | {Cob.rpdo(n, node) for n in range(1, 5)}
        host = {self._host_heartbeat.arbitration_id} if float(self.profile.options["consumer_heartbeat"]) else set()
        return frozenset({Cob.NMT, Cob.SYNC, Cob.emcy(node), Cob.SDO_TX + node, Cob.SDO_RX + node,
                          Cob.HEARTBEAT + node} | pdos | host)

    @property
    def feedback_streams(self) -> bool:
        """False when the drive itself sends SYNC after each torque frame (no native
        periodic send on this bus): feedback then only comes when the host commands."""
        return self._native_sync or native_periodic(self._bus)

    @property
    def sample_clock(self) -> str:
        """"bus": the periodic SYNC's echo as the bus stamped it (sent outside this
        process, read back: :meth:`_decode`); "sent": the SYNC this host sends after each
        torque frame, stamped just after the send (:meth:`_send_sync`)."""
        return "bus" if self.feedback_streams else "sent"

    @property
    def rated_torque(self) -> float:
        """[Nm] the rated torque the per mille values refer to."""
        return self._rated

    @classmethod
    def preflight_probe(cls, profile: DriveProfile) -> PreflightProbe | None:
        """SDO reads of identity, modes, rated torque, heartbeat, statusword and the PDO
        mapping parameters, then listening (:mod:`dobhil.drives.cia402.preflight`)."""
        # imported here: the probe imports this module (its rated-torque tolerance)
        from dobhil.drives.cia402.preflight import CiA402Preflight
        return CiA402Preflight(profile)

    def send_torque(self, tau_nm: float) -> None:
        super().send_torque(tau_nm)
        if not self._native_sync:
            self._send_sync()
            if self._host_heartbeat_due is not None:
                self._host_heartbeat_if_due()

    def safe_stop(self, *, confirm: bool = True, timeout: float | None = None,
                  cancel: Cancel | None = None, planned: bool = False) -> SafeStopReport:
        """The base's safe stop, then the periodic SYNC stopped: after the confirmation
        (the node needed SYNCs to apply the RPDOs and to answer), or at once when not
        confirming (the safe-stop frames carried their own SYNCs). A node watching the
        host's heartbeat (``consumer_heartbeat``) is told to stop watching first when the
        stop was confirmed, so the host's heartbeat ending is not a fault on it."""
        report: SafeStopReport | None = None
        try:
            # a node this session never put in NMT operational processed none of our PDOs:
            # whatever its power state, we did not enable it, and there are no TPDOs to
            # confirm anything with (the frames still go out: harmless, and a node that was
            # operational after all takes them)
            confirm = confirm and self._operational_commanded
            report = super().safe_stop(confirm=confirm, timeout=timeout, cancel=cancel, planned=planned)
            return report
        finally:
            if report is not None and report.confirmation is Confirmation.CONFIRMED:
                self._stop_watching_host(cancel)
            self._stop_sync()

    def close(self) -> None:
        """Stop the periodic SYNC and host heartbeat (if any). The bus is borrowed: it
        stays open."""
        self._stop_sync()
        self._stop_host_heartbeat()

    # -- start-up ---------------------------------------------------------------

    def _prepare(self, deadline: float, cancel: Cancel | None) -> None:
        if self._od is None:
            assert self._missing is not None
            raise self._missing
        reached: list[str] = []
        link = self._link or CanopenLink(self._bus, self._od, node_id=self.node_id, clock=self._clock,
                                         sdo_timeout=float(self.profile.options["sdo_timeout"]),
                                         on_frame=self._startup_frame)
        self._link = link
        self._fault_reset_sent = False
        self._operational_commanded = False
        self.notes = []
        with link.session(cancel), self._one_line(link, reached):
            node = link.node
            steps: Sequence[tuple[str, Callable[[Any], None]]] = (
                ("pre-operational", lambda n: n.nmt.send_command(codec.NmtCommand.PRE_OPERATIONAL)),
                ("identity read", self._read_identity),
                ("statusword read", self._read_status),
                ("supported modes read", self._check_modes),
                ("rated torque read", self._check_rated_torque),
                ("encoder resolution and gear read", self._check_units),
                (f"RPDO{self._rpdo_n} mapped", lambda n: self._map(n.rpdo[self._rpdo_n], codec.RPDO_CST)),
                (f"TPDO{self._tpdo_n} mapped", lambda n: self._map(n.tpdo[self._tpdo_n], codec.TPDO_STATUS)),
                (f"TPDO{self._tpdo_n + 1} mapped",
                 lambda n: self._map(n.tpdo[self._tpdo_n + 1], codec.TPDO_MOTION)),
                ("timing set", self._write_timing),
                # whatever a previous run left in it, the node takes zero until our first RPDO
                ("target torque zeroed", lambda n: setattr(n.sdo[0x6071], "raw", 0)),
                ("CST mode set", lambda n: setattr(n.sdo[0x6060], "raw", CST_MODE)),
                ("operational", self._start_node),
            )
            for what, step in steps:
                if self._clock() > deadline:
                    raise DriveTimeoutError("start-up not done in time")
                step(node)
                reached.append(what)
        self._start_sync()

    @contextmanager
    def _one_line(self, link: CanopenLink, reached: list[str]) -> Iterator[None]:
        """Any SDO abort or timeout of start-up as one line: node, object, state reached."""
        try:
            yield
        except (canopen.SdoAbortedError, canopen.SdoCommunicationError) as exc:
            what = self._sdo_failure(link, exc)
            raise DriveError(f"node {self.node_id}: {what} (reached: {_reached(reached)})") from None
        except DriveError as exc:  # a refusal of ours (modes, rated torque, fault), a timeout
            if "(reached: " in str(exc):
                raise
            raise type(exc)(f"node {self.node_id}: {exc} (reached: {_reached(reached)})") from None
        except (can.CanError, OSError) as exc:  # the bus refused a request or cannot be read
            raise BusError(f"node {self.node_id}: {self._sdo_object(link)}: "
                           f"{exception_line(exc, named=False)} "
                           f"(reached: {_reached(reached)})") from exc

    @staticmethod
    def _sdo_object(link: CanopenLink) -> str:
        """``SDO 0x6502:00 (Supported drive modes)``: the transfer started last."""
        index, sub = link.adapter.last_object
        var = link.node.object_dictionary.get_variable(index, sub)
        return f"SDO 0x{index:04X}:{sub:02X} ({var.name if var is not None else 'not in the EDS'})"

    def _sdo_failure(self, link: CanopenLink, exc: Exception) -> str:
        obj = self._sdo_object(link)
        if isinstance(exc, canopen.SdoAbortedError):
            text = canopen.SdoAbortedError.CODES.get(exc.code, "unknown abort code")
            return f"{obj} aborted by the node: 0x{exc.code:08X} ({text})"
        if "No SDO response" in str(exc):
            return f"{obj} timed out after {link.adapter.timeout:g} s"
        return f"{obj} failed: {exception_line(exc, named=False)}"

    def _read_identity(self, node: Any) -> None:
        record = node.sdo[0x1018]
        od = node.object_dictionary
        present = [sub for sub in (1, 2, 3, 4) if od.get_variable(0x1018, sub) is not None]
        self.identity = tuple(int(record[sub].raw) for sub in present)

    def _read_status(self, node: Any) -> None:
        """The statusword before anything is enabled: a node in fault is refused (or reset)
        with its error code 0x603F."""
        statusword = int(node.sdo[0x6041].raw)
        self._note_statusword(statusword)
        if self._power in (PowerState.FAULT, PowerState.FAULT_REACTION_ACTIVE) and 0x603F in node.object_dictionary:
            self._emcy = int(node.sdo[0x603F].raw)

    def _check_modes(self, node: Any) -> None:
        modes = int(node.sdo[0x6502].raw)
        if not modes >> codec.CST_SUPPORTED_BIT & 1:
            raise DriveError(f"0x6502 (supported drive modes) = 0x{modes:08X}: no cyclic synchronous "
                             f"torque (bit {codec.CST_SUPPORTED_BIT}), the only mode dobhil drives")

    def _check_rated_torque(self, node: Any) -> None:
        unit = self.profile.options["rated_torque_unit"]
        raw = int(node.sdo[0x6076].raw)
        rated = raw * RATED_TORQUE_UNITS[unit]
        if rated <= 0:
            raise DriveError(f"0x6076 (motor rated torque) = {raw} {unit}: a rated torque of 0 makes "
                             "every per mille torque 0; set the motor's rated torque on the drive")
        if abs(rated - self._rated) > RATED_TORQUE_TOLERANCE * self._rated:
            raise DriveError(f"0x6076 (motor rated torque) = {raw} {unit} = {rated:g} Nm, the profile's "
                             f"cia402.rated_torque is {self._rated:g} Nm (more than 1 % apart: "
                             "wrong rated_torque_unit or a different motor?)")
        self._rated = rated  # the node's own value: per mille refers to it exactly

    def _check_units(self, node: Any) -> None:
        """0x608F (position encoder resolution) and 0x6091 (gear ratio) as the node states
        them, against the profile's ``position_per_rev`` and ``gear_ratio``, which scale
        every position and velocity: the hardware is trusted, not the config, so a node
        that says otherwise is refused. Only where the EDS lists the object; a node that
        aborts the read (the EDS lists it, this drive has not got it) or states sub 2 = 0
        is a note: its units cannot be checked here, and nothing is refused for that."""
        od = node.object_dictionary
        for obj in codec.UNIT_OBJECTS:
            if od.get_variable(obj.index, 1) is None or od.get_variable(obj.index, 2) is None:
                continue
            expected = float(self.profile.options[obj.key])
            try:
                num, den = int(node.sdo[obj.index][1].raw), int(node.sdo[obj.index][2].raw)
            except canopen.SdoAbortedError as exc:
                text = canopen.SdoAbortedError.CODES.get(exc.code, "unknown abort code")
                self.notes.append(f"node {self.node_id}: 0x{obj.index:04X} ({obj.name}) not read, aborted "
                                  f"0x{exc.code:08X} ({text}): cia402.{obj.key} {expected:.10g} not checked")
                continue
            agrees = obj.agrees(num, den, expected)
            if agrees is None:
                self.notes.append(f"node {self.node_id}: {obj.stated(num, den)} is no ratio: "
                                  f"cia402.{obj.key} {expected:.10g} not checked")
            elif not agrees:
                stated = num / den
                raise DriveError(f"{obj.stated(num, den)} = {stated:.10g}, the profile's cia402.{obj.key} is "
                                 f"{expected:.10g}: every position and velocity would be off by a factor "
                                 f"{stated / expected:.6g}; set cia402.{obj.key}: {stated:.10g} (or fix the drive)")

    def _map(self, pdo: PdoMap, objects: Sequence[Mapped]) -> None:
        """Write one PDO's mapping with canopen (read its COB-ID, clear, add the objects,
        synchronous, enabled, save)."""
        pdo.read()
        pdo.clear()
        for obj in objects:
            pdo.add_variable(obj.index, obj.subindex)
        pdo.trans_type = 1
        pdo.enabled = True
        pdo.save()

    def _write_timing(self, node: Any) -> None:
        """The SYNC period where the node has it: 0x1006 [us] (CiA 301) and 0x60C2, the
        interpolation time period CSx modes use (value :01 times 10 ** index :02 s; a
        maxon EPOS4 has only this one); the heartbeats."""
        od = node.object_dictionary
        if 0x1006 in od:
            node.sdo[0x1006].raw = round(self._period * 1e6)
        if 0x60C2 in od:
            value, exponent = codec.interpolation_period(self._period)
            node.sdo[0x60C2][1].raw = value
            node.sdo[0x60C2][2].raw = exponent
        heartbeat = self.profile.heartbeat_period
        node.sdo[0x1017].raw = round(heartbeat * 1e3) if heartbeat else 0
        consumer = float(self.profile.options["consumer_heartbeat"])
        if consumer > 0:
            # the host's heartbeat first: a consumer watches from the first one it hears
            self._start_host_heartbeat(self._host_heartbeat_interval(consumer))
            node.sdo[0x1016][1].raw = self._host_id << 16 | round(consumer * 1e3)

    def _host_heartbeat_interval(self, consumer: float) -> float:
        """[s] the host's heartbeat period for a consumer time (:func:`codec.host_heartbeat_interval
        <dobhil.drives.cia402.codec.host_heartbeat_interval>`, with this drive's SYNC period)."""
        return codec.host_heartbeat_interval(consumer, self._period)

    def _host_watch_of(self, event: StateEvent | None) -> HostTimeout | None:
        """The node's heartbeat consumer (0x1016, ``consumer_heartbeat``) when this process
        sends the host's heartbeat, with the torque frames: a late host starves it. Sent
        natively (the kernel's broadcast manager, the emulator's process), no lateness of
        this process can, and a consumer fault is not the host's. Its expiry is EMCY 0x8130,
        sent by the node at once."""
        consumer = float(self.profile.options["consumer_heartbeat"])
        not_heartbeat = event is not None and event.error_code != codec.EmcyCode.HEARTBEAT
        if consumer <= 0 or native_periodic(self._bus) or not_heartbeat:
            return None
        return HostTimeout("heartbeat consumer (0x1016)", consumer,
                           fed_every=self._host_heartbeat_interval(consumer), reported_within=self._period)

    # -- the host's heartbeat (for the node's consumer 0x1016) ------------------

    def _start_host_heartbeat(self, period: float) -> None:
        """Every ``period``: natively where SYNC is native, else with the torque frames."""
        self._stop_host_heartbeat()
        self._host_heartbeat_period = period
        if native_periodic(self._bus):
            self._host_heartbeat_task = self._bus.send_periodic(self._host_heartbeat, period)
        else:
            self._host_heartbeat_due = self._clock()
            self._host_heartbeat_if_due()

    def _host_heartbeat_if_due(self) -> None:
        due, now = self._host_heartbeat_due, self._clock()
        if due is not None and now >= due:
            self._send_all((self._host_heartbeat,), "host heartbeat")
            period = self._host_heartbeat_period
            self._host_heartbeat_due = due + period if now < due + period else now + period  # no bursts

    def _stop_host_heartbeat(self) -> None:
        task, self._host_heartbeat_task = self._host_heartbeat_task, None
        self._host_heartbeat_due = None
        if task is not None:
            try:
                task.stop()
            except Exception:  # a bus already gone stops its tasks with it
                pass

    def _stop_watching_host(self, cancel: Cancel | None) -> None:
        """0x1016:01 = 0 by SDO, then the host's heartbeat stopped; never raises (a node
        that did not hear it faults on the missing heartbeat, disabled already)."""
        if self._link is None or (self._host_heartbeat_task is None and self._host_heartbeat_due is None):
            return
        try:
            with self._link.session(cancel):
                self._link.node.sdo[0x1016][1].raw = 0
        except Exception:  # safety path: the run is over, the drive disabled
            pass
        self._stop_host_heartbeat()

    def _start_node(self, node: Any) -> None:
        self._operational_commanded = True
        node.nmt.send_command(codec.NmtCommand.START)
        # commanded, not yet heard: a boot-up or pre-operational heartbeat from before the
        # command must not count against the node (its next heartbeat tells)
        self._nmt = -1

    def _startup_frame(self, msg: can.Message) -> None:
        """A frame read while waiting for an SDO answer that is not one: the drive's."""
        self.apply(msg)

    # -- SYNC -----------------------------------------------------------------

    def _start_sync(self) -> None:
        self._stop_sync()
        self._native_sync = native_periodic(self._bus)
        if self._native_sync:
            try:
                self._sync_task = self._bus.send_periodic(self._sync_msg, self._period)
            except Exception as exc:  # whatever the interface raises (see Drive.send_torque)
                raise BusError(f"node {self.node_id}: periodic SYNC not started: "
                               f"{exception_line(exc, named=False)}") from exc

    def _stop_sync(self) -> None:
        task, self._sync_task = self._sync_task, None
        if task is not None:
            try:
                task.stop()
            except Exception:  # a bus already gone stops its tasks with it
                pass

    def _send_sync(self) -> None:
        self._send_all((self._sync_msg,), "SYNC")
        self._note_sync(time.time())  # the host's send time: the bus stamps of received frames' clock

    # -- hooks ----------------------------------------------------------------

    def _enable_start(self) -> Sequence[can.Message]:
        self._statusword = -1  # the first TPDO's statusword is news, whatever the SDO read said
        self._controlword = int(Controlword.SHUTDOWN) if self._power is PowerState.UNKNOWN else \
            int(codec.next_controlword(self._power) or self._controlword)
        return self._command_frames()

    def _enable_step(self, event: StateEvent) -> Sequence[can.Message]:
        power = PowerState(event.state) if 0 <= event.state < len(PowerState) else PowerState.UNKNOWN
        if power in (PowerState.FAULT, PowerState.FAULT_REACTION_ACTIVE):
            return self._on_fault_while_enabling(power)
        command = codec.next_controlword(power)
        if command is None or command == self._controlword:
            return ()
        self._controlword = int(command)
        return self._command_frames()

    def _on_fault_while_enabling(self, power: PowerState) -> Sequence[can.Message]:
        if power is PowerState.FAULT_REACTION_ACTIVE:
            return ()  # becomes FAULT by itself
        if not self._reset_faults:
            raise DriveFaultError(f"node {self.node_id} is in fault: {self._emcy_text()}; not reset "
                                  "(dobhil run --reset-faults resets it)")
        if self._fault_reset_sent:
            # once: the node applies it at a SYNC still to come; if it stays in fault, the
            # enable's timeout says so with the last state and error seen
            return ()
        self._fault_reset_sent = True
        frames: list[can.Message] = []
        for word in codec.fault_reset_edge(self._controlword):
            self._controlword = int(word)
            frames.extend(self._command_frames())
        return frames

    def _is_enabled_confirmation(self, event: StateEvent) -> bool:
        return event.active and event.error_code == 0

    def _is_disabled_confirmation(self, event: StateEvent) -> bool:
        return event.state in _OUT_OF_TORQUE

    def _keepalive_frames(self) -> Sequence[can.Message]:
        """The RPDO with the controlword the state machine is at and zero torque (and a
        SYNC to apply it and be answered, when no periodic SYNC runs)."""
        if self._host_heartbeat_due is not None:
            self._host_heartbeat_if_due()
        return self._command_frames()

    def _disable_frames(self) -> Sequence[can.Message]:
        return (self._rpdo(Controlword.QUICK_STOP, 0), self._sync_msg,
                self._rpdo(Controlword.DISABLE_VOLTAGE, 0), self._sync_msg)

    def _disable_frame_names(self) -> Sequence[str]:
        return ("quick stop", "SYNC", "disable voltage", "SYNC")

    def _torque_frame(self, tau_nm: float) -> can.Message:
        self._layouts.rpdo.pack_into(self._rpdo_msg.data, 0, self._controlword,
                                     codec.per_mille(tau_nm, self._rated))
        return self._rpdo_msg

    def _command_frames(self) -> Sequence[can.Message]:
        frame = self._rpdo(self._controlword, 0)
        return (frame,) if self._native_sync else (frame, self._sync_msg)

    def _rpdo(self, controlword: int, torque: int) -> can.Message:
        return can.Message(arbitration_id=self._rpdo_id, is_extended_id=False,
                           data=self._layouts.rpdo.pack(controlword, torque))

    # -- decoding -------------------------------------------------------------

    def _decode(self, msg: can.Message) -> Sequence[DriveEvent]:
        arb = msg.arbitration_id
        if msg.is_extended_id or msg.is_remote_frame or msg.is_error_frame:
            return _NO_EVENTS
        data = msg.data
        try:
            if arb == self._motion_id:
                return self._on_motion_pdo(data, msg.timestamp)
            if arb == self._status_id:
                return self._on_status_pdo(data)
            if arb == Cob.SYNC:
                self._note_sync(msg.timestamp or math.nan)
                return _NO_EVENTS
            if arb == self._heartbeat_id and len(data):
                self._nmt = data[0] & 0x7F
                return (self._state_event(),)
            if arb == self._emcy_id:
                self._emcy = codec.decode_emcy(data).code
                return (self._state_event(),)
        except (CodecError, struct.error):  # a malformed frame is not feedback; the next one will be
            return _NO_EVENTS
        return _NO_EVENTS

    def _on_status_pdo(self, data: bytearray) -> Sequence[DriveEvent]:
        statusword, position, torque = self._layouts.status.unpack_from(data)
        self._position = position * self._scale.rad_per_increment
        self._status_fresh = True
        self._torque_actual = codec.torque_from_per_mille(torque, self._rated)
        if statusword == self._statusword:
            return _NO_EVENTS
        self._note_statusword(statusword)
        return (self._state_event(),)

    def _note_sync(self, stamp: float) -> None:
        self._syncs = (self._syncs[1], stamp)

    def _sampled_at(self, stamp: float) -> float:
        """The bus stamp of the SYNC that sampled the motion TPDO stamped ``stamp``: the
        newest SYNC read, unless the bus stamped it after this TPDO -- then the one before.
        On a host with several processors, frames that enter the kernel on different ones
        (a SYNC's echo, a TPDO from the wire) can reach a socket out of the order of their
        stamps (each is stamped where it enters: netif_rx in the kernel's net/core/dev.c),
        and a SYNC read before a TPDO stamped before it would make that sample's latency
        negative (tests/socketcan/test_kernel_faults.py sees it on two processors). A TPDO
        read before its own SYNC cannot be told from a late one: it is measured from the
        SYNC before (a period more)."""
        before, newest = self._syncs
        if not stamp > 0 or not newest > stamp:   # no stamp, no SYNC yet, or in order
            return newest
        return before if before <= stamp else math.nan

    def _on_motion_pdo(self, data: bytearray, stamp: float) -> Sequence[DriveEvent]:
        velocity, mode = self._layouts.motion.unpack_from(data)
        state: StateEvent | None = None
        if mode != self._mode:
            self._mode = mode
            state = self._state_event()
        if not self._status_fresh:
            # this SYNC's first TPDO (the position) was lost: no sample, rather than a
            # position one period older than its velocity
            return _NO_EVENTS if state is None else (state,)
        self._status_fresh = False
        motion = MotionEvent(self._position, velocity * self._scale.rad_s_per_velocity_count,
                             self._sampled_at(stamp))
        return (motion,) if state is None else (state, motion)

    def _note_statusword(self, statusword: int) -> None:
        self._statusword = statusword
        self._power = codec.power_state(statusword)
        if self._power is PowerState.SWITCH_ON_DISABLED:
            self._emcy = 0  # a fault reset went through

    def _state_event(self) -> StateEvent:
        power = self._power
        nmt_ok = self._nmt in (-1, NmtState.OPERATIONAL)
        active = (power is PowerState.OPERATION_ENABLED and self._mode == CST_MODE and nmt_ok
                  and not codec.is_fault(self._statusword))
        code = self._emcy
        return StateEvent(active=active, error_code=code, watchdog_tripped=code == codec.EmcyCode.HEARTBEAT,
                          state_text=self._state_text(nmt_ok), error_text=self._emcy_text(),
                          state=int(power))

    def _state_text(self, nmt_ok: bool) -> str:
        text = self._power.text
        if self._mode != CST_MODE and self._power is PowerState.OPERATION_ENABLED:
            text += f" in mode {self._mode}"
        return text if nmt_ok else f"{text}, NMT {NmtState.text(self._nmt)}"

    def _emcy_text(self) -> str:
        if not self._emcy:
            return "none"
        return f"EMCY 0x{self._emcy:04X} ({emcy_text(self._emcy)})"


def emcy_text(code: int) -> str:
    """canopen's description of an EMCY error code (its table of CiA 301 code classes)."""
    return EmcyError(code, 0, b"", 0.0).get_desc() or "no description"


def _reached(reached: Sequence[str]) -> str:
    return ", ".join(reached) if reached else "nothing"
