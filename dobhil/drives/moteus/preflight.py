"""What ``dobhil check`` reads of a moteus controller without enabling it, and the bus
budget of a run over CAN FD.

A moteus controller streams nothing: the probe sends one query (read subframes only: no
mode write, so nothing changes on the controller) for mode, position, velocity, torque,
bus voltage, board temperature and fault, and reads the reply. A controller in mode 1
(fault) or 11 (timeout) is reported; a fault refuses the run unless ``--reset-faults``
(a stop clears it), a controller already in a motion mode means another host may drive it.

Bus budget: per loop period one command (mode 10, the position-mode block, the watchdog
and the query) and one reply, each an FD frame whose arbitration phase runs at the nominal
rate (1 Mbit/s) and whose data phase runs at the data rate (5 Mbit/s with the bit rate
switch, ``docs/integration/can-fd.md``); :class:`FdCycleFrame` counts its bits in nominal
bit times, so the budget's load against the nominal rate is the time share of the bus.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from types import MappingProxyType

import can

from dobhil.drives.bus_load import CycleFrame, fd_frame_bits
from dobhil.drives.moteus.codec import Mode, Register, Resolution, arbitration_id, group_registers, pad, \
    read_subframe, split_id
from dobhil.drives.moteus.states import fault_text, mode_text
from dobhil.drives.moteus.frames import CommandFrame, Query, reply_values
from dobhil.drives.moteus.rules import resolution
from dobhil.drives.preflight import Finding, NodeReport, Observation, PreflightProbe, Setting, Severity, Stream
from dobhil.drives.profile import DriveProfile
from dobhil.errors import CodecError

__all__ = ["DATA_BITRATE", "NOMINAL_BITRATE", "FdCycleFrame", "MoteusPreflight", "fd_frame_bits"]

#: the bit rates the moteus documentation sets (docs/integration/can-fd.md)
NOMINAL_BITRATE = 1_000_000
DATA_BITRATE = 5_000_000

#: what the probe reads: the motion registers, voltage and temperature, mode and fault
PROBE_REGISTERS: Mapping[int, Resolution] = MappingProxyType({
    Register.MODE: Resolution.INT8, Register.POSITION: Resolution.F32, Register.VELOCITY: Resolution.F32,
    Register.TORQUE: Resolution.F32, Register.VOLTAGE: Resolution.F32, Register.TEMPERATURE: Resolution.F32,
    Register.FAULT: Resolution.INT8,
})
_MOTION_MODES = frozenset(range(Mode.PWM, Mode.BRAKE + 1)) - {Mode.TIMEOUT}


@dataclass(frozen=True)
class FdCycleFrame(CycleFrame):
    """A :class:`CycleFrame` of CAN FD: ``dlc`` is the payload length in bytes and
    :attr:`bits` the frame's time in nominal bit times."""

    data_ratio: float = NOMINAL_BITRATE / DATA_BITRATE
    #: the data phase's bit rate, which the frame switches to (None: no switch: the data
    #: phase runs at the nominal rate, whatever it is)
    data_bitrate: int | None = None

    @property
    def bits(self) -> int:
        return fd_frame_bits(self.dlc, extended=self.extended, data_ratio=self.data_ratio)

    def bits_at(self, bitrate: float | None) -> int:
        """At the nominal ``bitrate`` the data phase takes ``bitrate / data_bitrate`` nominal
        bit times per bit (at 500 kbit/s and 5 Mbit/s half as many as at 1 Mbit/s); unknown:
        :attr:`bits`, at the nominal rate the moteus documentation sets."""
        if not bitrate or self.data_bitrate is None:
            return self.bits
        return fd_frame_bits(self.dlc, extended=self.extended, data_ratio=bitrate / self.data_bitrate)


class MoteusPreflight(PreflightProbe):
    checks_rates = False   # nothing streams: each reply answers a frame
    budget_fewer = "narrower query resolutions"

    def __init__(self, profile: DriveProfile) -> None:
        super().__init__(profile)
        opts = profile.options
        self.source = int(opts.get("source_id", 0))
        self.prefix = int(opts.get("can_prefix", 0))
        self.brs = bool(opts.get("bitrate_switch", True))
        self.values: dict[int, float] = {}

    # -- the framework's hooks ------------------------------------------------

    def requests(self, node: int) -> Sequence[can.Message]:
        if node != self.profile.node_id:
            return ()   # another controller is never sent a frame
        payload = pad(b"".join(read_subframe(start, res, count)
                               for start, res, count in group_registers(PROBE_REGISTERS)))
        aid = arbitration_id(self.source, node, reply=True, prefix=self.prefix)
        return (can.Message(arbitration_id=aid, is_extended_id=aid > 0x7FF, is_fd=True,
                            bitrate_switch=self.brs, data=payload),)

    def observe(self, msg: can.Message) -> Observation | None:
        prefix, source, destination, reply = split_id(msg.arbitration_id)
        if msg.is_remote_frame or msg.is_error_frame or reply or prefix != self.prefix \
                or destination != self.source or not msg.data:
            return None
        data = bytes(msg.data)
        if source == self.profile.node_id:
            try:
                self.values = reply_values(data)
            except CodecError:
                return None
        return Observation(source, Stream.STATUS, data)

    def setting(self, which: Setting) -> str:
        return {Setting.NODE_ID: "id.id on the controller (moteus_tool / tview)",
                Setting.MOTION_RATE: "nothing (a moteus controller answers each command)",
                Setting.STATUS_RATE: "nothing (a moteus controller answers each command)"}[which]

    def motion_name(self) -> str:
        return "streamed feedback (none on moteus)"

    def status_name(self) -> str:
        return "replies"

    def data_bitrate(self) -> int:
        """The profile's ``bus.data_bitrate`` (what the bus is opened with), else the rate
        the moteus documentation sets."""
        return int(self.profile.bus.get("data_bitrate") or DATA_BITRATE)

    def cycle_frames(self, period: float) -> Sequence[CycleFrame]:
        """One command and one reply per loop period, FD at 1/5 Mbit/s (1/1 without BRS)."""
        profile = self.profile
        query = Query.motion(resolution(profile, "position_resolution"), resolution(profile, "velocity_resolution"),
                             resolution(profile, "torque_resolution"))
        command = CommandFrame(resolution=resolution(profile, "command_resolution"),
                               timeout=profile.watchdog_timeout, query=query)
        reply = len(pad(b"\x20" * _reply_length(query)))
        ratio = NOMINAL_BITRATE / self.data_bitrate() if self.brs else 1.0
        node, source, prefix = profile.node_id, self.source, self.prefix
        cmd_ext = arbitration_id(source, node, reply=True, prefix=prefix) > 0x7FF
        rep_ext = arbitration_id(node, source, reply=False, prefix=prefix) > 0x7FF
        data = self.data_bitrate() if self.brs else None
        return (FdCycleFrame("moteus command", len(command.payload), extended=cmd_ext, data_ratio=ratio,
                             data_bitrate=data),
                FdCycleFrame("reply", reply, extended=rep_ext, data_ratio=ratio, data_bitrate=data))

    # -- what the node said ---------------------------------------------------------

    def node_summary(self, node: NodeReport) -> str:
        v = self.values
        if node.node != self.profile.node_id or Register.MODE not in v:
            return ""
        mode = int(v[Register.MODE])
        words = [f"mode {mode_text(mode)}"]
        if mode == Mode.FAULT:
            words.append(f"fault {fault_text(int(v.get(Register.FAULT, 0)))}")
        for reg, name, unit in ((Register.POSITION, "position", "rev"), (Register.VELOCITY, "velocity", "rev/s"),
                                (Register.VOLTAGE, "bus voltage", "V"), (Register.TEMPERATURE, "temperature",
                                                                         "degC")):
            if reg in v:
                words.append(f"{name} {v[reg]:.4g} {unit}")
        return "; ".join(words)

    def node_findings(self, node: NodeReport) -> list[Finding]:
        v = self.values
        if node.node != self.profile.node_id or Register.MODE not in v:
            return []
        mode = int(v[Register.MODE])
        out: list[Finding] = []
        if mode == Mode.FAULT:
            out.append(Finding(Severity.MISMATCH, f"node {node.node} is in mode FAULT with fault "
                                                  f"{fault_text(int(v.get(Register.FAULT, 0)))}: dobhil run "
                                                  "--reset-faults sends a stop first, which clears it"))
        elif mode in _MOTION_MODES:
            out.append(Finding(Severity.MISMATCH, f"node {node.node} is in mode {mode_text(mode)}: another host "
                                                  "may be driving it; stop it first", refuses_run=True))
        elif mode == Mode.TIMEOUT:
            out.append(Finding(Severity.NOTE, f"node {node.node} is in mode TIMEOUT (a host stopped commanding "
                                              "it): the enable sends a stop first"))
        return out


def _reply_length(query: Query) -> int:
    """Bytes of the reply to ``query``: each read subframe's head and values."""
    sizes = (1, 2, 4, 4)
    total = 0
    for start, res, count in group_registers(query.registers):
        total += (2 if count <= 3 else 3) + (1 if start < 0x80 else 2) - 1 + sizes[res] * count
    return total
