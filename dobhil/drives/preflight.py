"""Preflight: measure what a drive actually does on the bus before trusting the profile.

:func:`run_preflight` listens on a bus for a short window WITHOUT enabling anything (the
only frames it sends are the protocol's read requests, e.g. ODrive Get_Version RTRs),
finds the nodes on the bus, measures each node's motion-feedback and status periods and
their jitter, reads firmware version and state where the protocol allows, looks at the
bus (python-can's ``bus.state`` where the interface reports it, error frames, load), and
compares all of it with the drive profile and the loop period. On SocketCAN the
kernel's view of the interface (controller state, bit rate, queue length, restart-ms;
:mod:`dobhil.drives.socketcan_link`) is checked too. Each mismatch is one
line saying what to set on the drive (``set <axis>.config.can.encoder_msg_rate_ms = 1
(now 10 ms)``) or in the config.

The protocol-neutral part lives here; what frames mean and what the drive-side settings
are called is a :class:`PreflightProbe`, returned by the protocol's
:meth:`dobhil.drives.base.Drive.preflight_probe` hook (ODrive:
:mod:`dobhil.drives.odrive.preflight`; CiA 402: :mod:`dobhil.drives.cia402.preflight`).
A protocol without a probe gets a report that says so, never a silent pass.

How the window is spent is the probe's :meth:`PreflightProbe.listen` hook: by default
the listening above (ODrive: its state and rates stream by themselves); a protocol whose
drive says what it is only when asked (CiA 402: SDO reads of its object dictionary)
overrides it, asks, and listens for the rest of the window through the same
:class:`Capture`. The **bus budget** (:class:`dobhil.drives.bus_load.BusBudget`): the
frames a run puts on the bus per loop period (the probe's
:meth:`PreflightProbe.cycle_frames`) against the bit rate, one line, and a finding with
what to change above 70 %.

:func:`profile_rate_findings` is the profile-only part (feedback at least once per
loop period), shared with :func:`dobhil.runtime.session.check_rates`: one place.
"""

from __future__ import annotations

import math
import statistics
import time
from abc import ABC, abstractmethod
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from enum import IntEnum
from typing import Any

import can

from dobhil.drives.bus_load import BusBudget, CycleFrame
from dobhil.drives.bus_load import budget as make_budget
from dobhil.drives.bus_load import fd_frame_bits
from dobhil.drives.bus_load import frame_bits as wire_bits
from dobhil.drives.profile import DriveProfile
from dobhil.drives.socketcan_link import link_down_text, link_info, link_problems
from dobhil.drives.waits import Cancel, sliced_frames
from dobhil.errors import WaitCancelled, exception_line

__all__ = [
    "DEFAULT_WINDOW",
    "BusReport",
    "Capture",
    "Finding",
    "NodeReport",
    "Observation",
    "PreflightProbe",
    "PreflightReport",
    "Rate",
    "Setting",
    "Severity",
    "Stream",
    "budget_findings",
    "configured_bitrate",
    "listen_window",
    "profile_rate_findings",
    "run_preflight",
]

#: default listening window [s]: 5 heartbeats at the ODrive's 100 ms default
DEFAULT_WINDOW = 0.5
#: a measured period may exceed the expected one by this factor before it is a mismatch
#: (bus and host timestamp jitter; a 1 ms stream measured at 1.02 ms is fine, 2 ms is not)
PERIOD_TOLERANCE = 1.25
#: a window of this many periods holds at least two frames of a stream, whatever its phase
RESOLVE_PERIODS = 3
#: load above this fraction of the bit rate leaves too little room for retransmissions
MAX_LOAD = 0.8


class Stream(IntEnum):
    """What a frame is, to the preflight."""

    STATUS = 1   # cyclic status (ODrive heartbeat)
    MOTION = 2   # cyclic motion feedback (ODrive encoder estimates)
    VERSION = 3  # a reply to the probe's version request


class Setting(IntEnum):
    """Drive-side settings a finding may ask to change."""

    NODE_ID = 1
    MOTION_RATE = 2
    STATUS_RATE = 3


class Severity(IntEnum):
    NOTE = 1      # worth knowing, nothing to change
    MISMATCH = 2  # the drive or the config must change


@dataclass(frozen=True)
class Finding:
    severity: Severity
    text: str  # one line
    stale_feedback: bool = False  # a run would sample stale (held) feedback: refuse it
    refuses_run: bool = False     # another reason dobhil run refuses to enable (e.g. the axis is driven)

    @property
    def refuses(self) -> bool:
        """``dobhil run`` refuses to enable the drive on this finding (every other mismatch
        is printed and the run goes on: its words must not claim otherwise)."""
        return self.stale_feedback or self.refuses_run


@dataclass(frozen=True)
class Observation:
    """One frame as the probe reads it."""

    node: int
    stream: Stream
    data: bytes = b""


@dataclass(frozen=True)
class Rate:
    """A cyclic stream over the window: period = span / (count - 1); jitter = standard
    deviation of the intervals; max_gap = the longest interval. None below 2 frames."""

    count: int
    period: float | None = None
    jitter: float | None = None
    max_gap: float | None = None

    @classmethod
    def of(cls, times: Sequence[float]) -> Rate:
        if len(times) < 2:
            return cls(len(times))
        gaps = [b - a for a, b in zip(times, times[1:])]
        return cls(len(times), (times[-1] - times[0]) / len(gaps), statistics.pstdev(gaps), max(gaps))

    def describe(self, what: str) -> str:
        if self.period is None:
            return f"{what}: {self.count} frame{'s' if self.count != 1 else ''}"
        return (f"{what} every {_ms(self.period)} (jitter {_ms(self.jitter or 0.0)}, "
                f"max gap {_ms(self.max_gap or 0.0)}, {self.count} frames)")


@dataclass(frozen=True)
class NodeReport:
    node: int
    motion: Rate
    status: Rate
    status_data: bytes = b""          # payload of the last status frame
    version_data: bytes | None = None  # payload of the version reply, if any
    summary: str = ""                 # the probe's words: state, errors, firmware
    window: float = 0.0               # how long the preflight listened [s]


@dataclass(frozen=True)
class BusReport:
    state: str                  # python-can BusState name, or "unknown"
    frames: int
    error_frames: int
    bits_per_s: float
    bitrate: int | None
    run_bits_per_s: float       # what the run adds: one command frame per loop period

    @property
    def load(self) -> float | None:
        return self.bits_per_s / self.bitrate if self.bitrate else None

    @property
    def run_load(self) -> float | None:
        """Measured traffic plus the run's command frames, as a fraction of the bit rate."""
        return (self.bits_per_s + self.run_bits_per_s) / self.bitrate if self.bitrate else None


@dataclass(frozen=True)
class PreflightReport:
    profile: str
    node_id: int
    window: float
    nodes: tuple[NodeReport, ...]
    bus: BusReport
    findings: tuple[Finding, ...]
    budget: BusBudget | None = None   # the run's frames per loop period vs the bit rate

    @property
    def ok(self) -> bool:
        return not any(f.severity is Severity.MISMATCH for f in self.findings)

    @property
    def stale_feedback(self) -> bool:
        return any(f.stale_feedback for f in self.findings)

    @property
    def refuses(self) -> bool:
        """``dobhil run`` refuses to enable the drive (stale feedback, or another refusing finding)."""
        return any(f.refuses for f in self.findings)

    def mismatches(self) -> list[str]:
        return [f.text for f in self.findings if f.severity is Severity.MISMATCH]

    def lines(self) -> list[str]:
        """What was measured, then one line per finding (``mismatch:``/``note:``)."""
        out = [f"listened {_ms(self.window)} for profile {self.profile!r} (node {self.node_id}): "
               f"{self.bus.frames} frames, bus {self.bus.state}, {self.bus.error_frames} error frames"
               + (f", load {self.bus.load:.0%} (with the run's commands {self.bus.run_load:.0%} "
                  f"of {self.bus.bitrate} bit/s)" if self.bus.load is not None
                  and self.bus.run_load is not None else "")]
        out += [self.budget.line()] if self.budget is not None else []
        out += [f"node {n.node}: {n.summary}" for n in self.nodes]
        out += [f"{'mismatch' if f.severity is Severity.MISMATCH else 'note'}: {f.text}"
                for f in self.findings]
        out.append("preflight: ok" if self.ok else f"preflight: {len(self.mismatches())} mismatch(es) -- "
                   + self._verdict())
        return out

    def _verdict(self) -> str:
        """What ``dobhil run`` does with these mismatches, in the words it acts on."""
        if self.stale_feedback:
            return "dobhil run refuses to enable: a run would sample stale feedback"
        if self.refuses:
            # the finding's head, up to its first ": " (an object such as 0x1018:01 has no space)
            return "dobhil run refuses to enable: " + next(f.text for f in self.findings if f.refuses).split(": ")[0]
        return "dobhil run does not refuse these: it prints them and runs"

    def as_dict(self) -> dict[str, Any]:
        return {
            "ok": self.ok, "stale_feedback": self.stale_feedback, "refuses_run": self.refuses,
            "profile": self.profile,
            "node_id": self.node_id, "window": self.window,
            "nodes": [{"node": n.node, "summary": n.summary,
                       "motion": _rate_dict(n.motion), "status": _rate_dict(n.status)}
                      for n in self.nodes],
            "bus": {"state": self.bus.state, "frames": self.bus.frames,
                    "error_frames": self.bus.error_frames, "bits_per_s": self.bus.bits_per_s,
                    "bitrate": self.bus.bitrate, "load": self.bus.load, "run_load": self.bus.run_load},
            "bus_budget": None if self.budget is None else {"line": self.budget.line(), **self.budget.as_dict()},
            "findings": [{"severity": f.severity.name.lower(), "text": f.text,
                          "stale_feedback": f.stale_feedback, "refuses_run": f.refuses} for f in self.findings],
        }


class PreflightProbe(ABC):
    """A protocol's part of the preflight: what frames mean, what settings are called."""

    def __init__(self, profile: DriveProfile) -> None:
        self.profile = profile

    @abstractmethod
    def requests(self, node: int) -> Sequence[can.Message]:
        """Read-only requests to send to ``node`` when it is first expected or seen."""

    @abstractmethod
    def observe(self, msg: can.Message) -> Observation | None:
        """What ``msg`` is (None: not a frame the preflight measures). Never raises."""

    @abstractmethod
    def setting(self, which: Setting) -> str:
        """The drive-side name of a setting, e.g. ``<axis>.config.can.encoder_msg_rate_ms``."""

    def setting_value(self, which: Setting, value: float) -> str:
        """A value in the setting's unit; default: periods in milliseconds."""
        return str(int(value)) if which is Setting.NODE_ID else f"{value * 1e3:g}"

    def shortest_period(self, which: Setting) -> float:
        """The shortest period [s] the drive-side rate setting ``which`` can take (0: any):
        advice never asks the drive for a faster stream than this."""
        return 0.0

    @abstractmethod
    def node_summary(self, node: NodeReport) -> str:
        """State, errors and firmware of ``node`` in words (one line)."""

    @abstractmethod
    def node_findings(self, node: NodeReport) -> list[Finding]:
        """Protocol checks of the profile's node: firmware version, state, errors."""

    def motion_name(self) -> str:
        return "motion feedback"

    def rate_advice(self, period: float) -> str:
        """What to change when the motion feedback comes slower than ``period`` (the loop's),
        in the protocol's words; default: the drive's own rate setting."""
        value = self.setting_value(Setting.MOTION_RATE, period)
        return f"set {self.setting(Setting.MOTION_RATE)} = {value} on the drive"

    def status_name(self) -> str:
        return "status"

    #: the measured stream periods are compared with the profile (False: the protocol's
    #: start-up sets them itself and its probe reads and compares the settings instead)
    checks_rates: bool = True
    #: what one drive of the protocol can change to put fewer frames on the bus, in the advice
    #: of its own budget (a run or check of that one drive: the budget counts its frames
    #: only, so fewer axes would change nothing); "" when nothing but the other ways helps
    budget_fewer: str = ""

    def listen(self, bus: can.BusABC, window: float, clock: Callable[[], float],
               stamp: Callable[[can.Message], float], cancel: Cancel | None) -> Capture:
        """Spend the window on ``bus``: default, send :meth:`requests` and listen (a
        protocol that must ask its drive, e.g. by SDO, overrides this and fills the same
        :class:`Capture`, its findings included). Within WAIT_SLICE s of ``cancel()``."""
        return listen_window(bus, self, window, clock, stamp, cancel)

    def cycle_frames(self, period: float) -> Sequence[CycleFrame]:
        """The frames a run puts on the bus per loop ``period`` (for the bus budget);
        default: none known, no budget."""
        return ()

    def budget(self, period: float, bitrate: int | None) -> BusBudget | None:
        """The bus budget of a run at ``period`` on ``bitrate`` (None: no frames known)."""
        return make_budget(self.cycle_frames(period), period, bitrate, fewer=self.budget_fewer)

    def data_bitrate(self) -> int | None:
        """The data-phase bit rate of the protocol's CAN FD frames with the bit rate switch,
        as its bus budget counts them (a run's log records it, so that its report can time
        those frames on the bus); None: the protocol sends no such frames."""
        return None


# ---------------------------------------------------------------------------
# Profile-only checks (no bus)


def profile_rate_findings(profile: DriveProfile, period: float,
                          frames: str = "motion feedback", shortest: float = 0.0) -> list[Finding]:
    """The profile must promise feedback at least once per loop period; ``frames``: the
    protocol's name of its feedback (its probe's :meth:`PreflightProbe.motion_name`);
    ``shortest``: the shortest feedback period the drive can be set to (its probe's
    :meth:`PreflightProbe.shortest_period`; 0: any)."""
    if profile.feedback_period is not None and profile.feedback_period > period * (1 + 1e-9):
        # a loop faster than any feedback the drive can send needs a slower loop, not a
        # drive setting nobody can enter
        fix = (f"set loop.period >= {shortest:g} s (a drive sends its {frames} at most every {shortest:g} s)"
               if period < shortest * (1 - 1e-9) else "set its feedback_period (and the drive's) to the loop period")
        return [Finding(Severity.MISMATCH,
                        f"drive profile {profile.name or profile.protocol!r} has {frames} every "
                        f"{profile.feedback_period:g} s (feedback_period), slower than loop.period = "
                        f"{period:g} s; {fix}",
                        stale_feedback=True)]
    return []


# ---------------------------------------------------------------------------
# Listening


@dataclass
class _NodeLog:
    motion: list[float] = field(default_factory=list)
    status: list[float] = field(default_factory=list)
    status_data: bytes = b""
    version_data: bytes | None = None


@dataclass
class Capture:
    """What the window gave: frames per node and stream, bus counts, and (a probe that
    asks its drive) the probe's own findings. Filled on the caller's thread only: the
    listening loop, or the probe's own reads (CiA 402 reads SDO answers itself, no thread)."""

    nodes: dict[int, _NodeLog] = field(default_factory=dict)
    frames: int = 0
    error_frames: int = 0
    bits: int = 0   # of the classic frames
    #: the CAN FD frames by (payload length, extended id, bit rate switch): their time on the
    #: bus depends on the data bit rate, known once the bus' bit rate is (:meth:`bits_at`)
    fd_frames: Counter[tuple[int, bool, bool]] = field(default_factory=Counter)
    send_errors: list[str] = field(default_factory=list)
    read_error: str = ""   # the bus failed while listening (gone): listening ended there
    findings: list[Finding] = field(default_factory=list)  # the probe's, from what it asked
    #: the probe's one verdict on the profile's node (e.g. it never answered): it replaces
    #: the node findings, so that one cause is one line
    verdict: Finding | None = None

    def take(self, msg: can.Message, probe: PreflightProbe, stamp: Callable[[can.Message], float]) -> int | None:
        """Count ``msg`` and log what the probe reads in it; the node it came from (None:
        not a frame the preflight measures)."""
        self.frames += 1
        if msg.is_fd:
            self.fd_frames[msg.dlc, msg.is_extended_id, msg.bitrate_switch] += 1
        else:
            self.bits += frame_bits(msg)
        if msg.is_error_frame:
            self.error_frames += 1
            return None
        obs = probe.observe(msg)
        if obs is None:
            return None
        log = self.nodes.setdefault(obs.node, _NodeLog())
        if obs.stream is Stream.MOTION:
            log.motion.append(stamp(msg))
        elif obs.stream is Stream.STATUS:
            log.status.append(stamp(msg))
            log.status_data = obs.data
        else:
            log.version_data = obs.data
        return obs.node


    def bits_at(self, data_ratio: float | None) -> int:
        """Bit times (nominal) of every frame heard: a CAN FD frame's data phase at
        ``data_ratio`` (nominal/data bit rate) when it switched bit rate; None: no data rate
        known, so at the nominal rate (the longest such a frame can take)."""
        ratio = 1.0 if data_ratio is None else data_ratio
        return self.bits + sum(n * fd_frame_bits(length, extended=ext, data_ratio=ratio if brs else 1.0)
                               for (length, ext, brs), n in self.fd_frames.items())


def frame_bits(msg: can.Message) -> int:
    """Bits of ``msg`` on the wire (worst-case stuffing)."""
    return wire_bits(msg.dlc, msg.is_extended_id)


def listen_window(bus: can.BusABC, probe: PreflightProbe, window: float, clock: Callable[[], float],
                  stamp: Callable[[can.Message], float], cancel: Cancel | None,
                  cap: Capture | None = None) -> Capture:
    """The default window: the probe's read requests, then every frame for ``window`` s
    (into ``cap`` when given: the rest of a window a probe began by asking)."""
    cap = Capture() if cap is None else cap
    asked: set[int] = set()

    def ask(node: int) -> None:
        asked.add(node)
        for request in probe.requests(node):
            try:
                bus.send(request, 0.0)
            except Exception as exc:  # any interface's refusal (a transport's own, too)
                cap.send_errors.append(exception_line(exc, named=False))

    ask(probe.profile.node_id)
    def read(timeout: float) -> can.Message | None:
        try:
            return bus.recv(timeout)
        except Exception as exc:  # any interface's failure: the bus is gone
            cap.read_error = exception_line(exc)
            raise

    try:
        for msg in sliced_frames(read, clock, clock() + window, cancel=cancel):
            node = cap.take(msg, probe, stamp)
            if node is not None and node not in asked:
                ask(node)
    except WaitCancelled:
        pass   # the caller stops (SIGINT): what was heard so far is all there is
    except Exception:
        if not cap.read_error:
            raise   # not the bus's failure: a bug of the probe, not to be taken for a bus gone
    return cap


def _bus_state(bus: can.BusABC) -> str:
    try:
        return str(bus.state.name)
    except Exception:  # an interface without state reporting
        return "unknown"


def run_preflight(
    bus: can.BusABC, profile: DriveProfile, *, period: float, feedback_timeout: float | None = None,
    window: float = DEFAULT_WINDOW, bitrate: int | None = None,
    clock: Callable[[], float] = time.monotonic,
    stamp: Callable[[can.Message], float] | None = None,
    probe: PreflightProbe | None, cancel: Cancel | None = None, run_loop_bits: float | None = None,
) -> PreflightReport:
    """Listen ``window`` s on ``bus`` (borrowed, not enabled, not shut down) and compare.

    ``probe``: the protocol's part, :func:`dobhil.drives.registry.preflight_probe` of the
    profile (None: the protocol has no preflight yet; the report says so).

    ``stamp``: a frame's time [s]; default its receive timestamp (kernel time on
    SocketCAN) or ``clock()`` when the interface gives none. Pass ``clock``/``stamp`` of a
    simulated clock for a lockstep bus.

    ``cancel``: listening ends within WAIT_SLICE s of it returning a reason (SIGINT);
    the report then covers only what was heard (the caller stops anyway).

    ``run_loop_bits``: the bits per loop period the whole run sends or triggers on this bus,
    which the report adds to what it heard (a several-axis run: every axis' frames, each
    axis' drive silent but for its stream while it is measured); None: this drive's own.
    """
    if not (math.isfinite(window) and window > 0):
        from dobhil.errors import ConfigError
        raise ConfigError(f"preflight window: expected a number of seconds > 0, got {window!r}")
    if probe is None:
        finding = Finding(Severity.NOTE, f"no preflight for protocol {profile.protocol!r} yet: "
                                         "its settings are taken on trust")
        return PreflightReport(profile.name or profile.protocol, profile.node_id, window, (),
                               BusReport(_bus_state(bus), 0, 0, 0.0, bitrate, 0.0),
                               tuple([*profile_rate_findings(profile, period), finding]))
    when = stamp or (lambda m: m.timestamp if m.timestamp > 0 else clock())
    link = link_info(bus)  # SocketCAN: the kernel's controller state, bit rate, queue
    if link is not None and link.up is False:
        return _link_down_report(profile, window, bitrate, link.name)
    link_found = [Finding(Severity.MISMATCH if bad else Severity.NOTE, text)
                  for bad, text in (link_problems(link, bitrate) if link is not None else [])]
    state = link.state if link is not None and link.state else _bus_state(bus)
    bitrate = link.bitrate if link is not None and link.bitrate else bitrate
    cap = probe.listen(bus, window, clock, when, cancel)
    nodes = tuple(_node_report(probe, n, log, window) for n, log in sorted(cap.nodes.items()))
    bus_budget = probe.budget(period, bitrate)
    # what the run adds to what was heard: the frames it sends or triggers each loop period
    # (the budget's; ODrive: the torque command; CiA 402: SYNC, RPDO and the TPDOs answering
    # SYNC), or one 8-byte command frame when the protocol lists none
    command_bits = (run_loop_bits if run_loop_bits is not None else bus_budget.loop_bits()
                    if bus_budget is not None else frame_bits(can.Message(dlc=8, is_extended_id=False))) / period
    data = probe.data_bitrate()
    heard = cap.bits_at(bitrate / data if bitrate and data else None)
    bus_report = BusReport(state, cap.frames, cap.error_frames, heard / window, bitrate, command_bits)
    # a bus that failed while listening ended the window there: rates over a window not
    # listened would be false ("1 frame in 60000 ms"), and the failure is the one cause
    node_found = ([] if cap.read_error else [cap.verdict] if cap.verdict is not None
                  else _node_findings(probe, nodes, period, feedback_timeout, window))
    findings = [*profile_rate_findings(profile, period, probe.motion_name(),
                                       probe.shortest_period(Setting.MOTION_RATE)), *link_found,
                *_bus_findings(bus_report, cap.send_errors, cap.read_error),
                *budget_findings(bus_budget), *node_found, *cap.findings]
    return PreflightReport(profile.name or profile.protocol, profile.node_id, window, nodes,
                           bus_report, tuple(findings), bus_budget)


def _link_down_report(profile: DriveProfile, window: float, bitrate: int | None, name: str) -> PreflightReport:
    """An interface that is down: nothing to ask (every send fails with ENETDOWN) and
    nothing to hear, so nothing is listened to; its one finding refuses the run, rather
    than a request "not sent (bus off or transmit queue full?)" and a drive "not heard"."""
    finding = Finding(Severity.MISMATCH, link_down_text(name), refuses_run=True)
    return PreflightReport(profile.name or profile.protocol, profile.node_id, window, (),
                           BusReport("DOWN", 0, 0, 0.0, bitrate, 0.0), (finding,))


def configured_bitrate(drive_bitrate: int, profile: DriveProfile) -> int | None:
    """The bit rate a run opens its bus with: ``drive.bitrate``, else the profile's
    ``bus.bitrate`` (as :func:`dobhil.runtime.buses.resolve_bus` gives them); None: unknown."""
    try:
        return int(drive_bitrate or profile.bus.get("bitrate") or 0) or None
    except (TypeError, ValueError):
        return None


def budget_findings(bus_budget: BusBudget | None) -> list[Finding]:
    """Over :data:`~dobhil.drives.bus_load.MAX_BUDGET`: what to change. A run does not
    refuse on it (the frames may still fit; late ones show in the run's timing), it says it;
    over 100 % ``dobhil run`` and ``dobhil check`` refused the config before a bus opened
    (:func:`dobhil.drives.axes.drive_budget`)."""
    if bus_budget is None or not bus_budget.over:
        return []
    return [Finding(Severity.MISMATCH, bus_budget.advice())]


def _node_report(probe: PreflightProbe, node: int, log: _NodeLog, window: float) -> NodeReport:
    bare = NodeReport(node, Rate.of(log.motion), Rate.of(log.status), log.status_data, log.version_data,
                      window=window)
    rates = f"{bare.motion.describe(probe.motion_name())}; {bare.status.describe(probe.status_name())}"
    summary = probe.node_summary(bare)
    return NodeReport(node, bare.motion, bare.status, bare.status_data, bare.version_data,
                      f"{rates}; {summary}" if summary else rates, window)


# ---------------------------------------------------------------------------
# Comparisons


_KERNEL_STATES = ("ERROR-ACTIVE", "ERROR-WARNING", "ERROR-PASSIVE", "BUS-OFF", "STOPPED", "SLEEPING")


def _bus_findings(bus: BusReport, send_errors: list[str], read_error: str = "") -> list[Finding]:
    out: list[Finding] = []
    if read_error:   # nothing can be measured, nor a run made, on a bus that is gone
        out.append(Finding(Severity.MISMATCH, f"bus read failed while listening: {read_error}",
                           stale_feedback=True))
    if bus.state not in ("ACTIVE", "unknown") and bus.state not in _KERNEL_STATES:  # those: socketcan_link
        out.append(Finding(Severity.MISMATCH, f"bus state {bus.state}: check wiring, termination "
                                              "(120 ohm at both ends) and that every node uses the same bit rate"))
    if bus.error_frames:
        out.append(Finding(Severity.MISMATCH, f"{bus.error_frames} error frames while listening: check wiring, "
                                              "termination and bit rate"))
    if send_errors:
        out.append(Finding(Severity.MISMATCH, f"read request not sent: {send_errors[0]} (bus off or "
                                              "transmit queue full? raise txqueuelen, set restart-ms)"))
    if bus.run_load is not None and bus.run_load > MAX_LOAD:
        out.append(Finding(Severity.MISMATCH,
                           f"bus load with the run's commands would be {bus.run_load:.0%} of {bus.bitrate} "
                           f"bit/s (measured {bus.load or 0.0:.0%}): use a higher bit rate (1 Mbit/s on the "
                           "drive and the interface) or a longer loop.period"))
    return out


def _node_findings(probe: PreflightProbe, nodes: tuple[NodeReport, ...], period: float,
                   feedback_timeout: float | None, window: float) -> list[Finding]:
    profile = probe.profile
    by_id = {n.node: n for n in nodes}
    subject = by_id.get(profile.node_id)
    out: list[Finding] = []
    if subject is None:
        if not nodes:
            return [Finding(Severity.MISMATCH,
                            f"no {probe.status_name()} or {probe.motion_name()} from any node within "
                            f"{_ms(window)}: check power, wiring, the bus bit rate and the interface",
                            stale_feedback=True)]
        found = ", ".join(str(n.node) for n in nodes)
        name = profile.name or profile.protocol
        out.append(Finding(Severity.MISMATCH,
                           f"node {profile.node_id} is not on the bus, node(s) {found} are: set "
                           f"{probe.setting(Setting.NODE_ID)} = {profile.node_id} on the drive, or "
                           f"node_id: {nodes[0].node} in profile {name!r}", stale_feedback=True))
        if len(nodes) != 1:
            return out
        subject = nodes[0]  # the only drive there: check the rest of its settings too
    if probe.checks_rates:
        out += _rate_findings(probe, subject, period, feedback_timeout, window)
    out += probe.node_findings(subject)
    return out


def _rate_findings(probe: PreflightProbe, node: NodeReport, period: float,
                   feedback_timeout: float | None, window: float) -> list[Finding]:
    profile = probe.profile
    out: list[Finding] = []
    if profile.feedback_period is not None:   # None: feedback does not stream, no rate to check
        out += _motion_findings(probe, node, period, feedback_timeout, window, profile.feedback_period)
    if profile.heartbeat_period is not None:   # None: no heartbeat watched, none to check
        out += _status_findings(probe, node, window, profile.heartbeat_period)
    return out


def _motion_findings(probe: PreflightProbe, node: NodeReport, period: float, feedback_timeout: float | None,
                     window: float, feedback_period: float) -> list[Finding]:
    out: list[Finding] = []
    motion = node.motion
    want_motion = min(feedback_period, period)
    shortest = probe.shortest_period(Setting.MOTION_RATE)
    set_motion = (f"set {probe.setting(Setting.MOTION_RATE)} = "
                  f"{probe.setting_value(Setting.MOTION_RATE, max(want_motion, shortest))}")
    if want_motion < shortest * (1 - 1e-9):
        # what the profile or the loop asks for is faster than the drive can send: the
        # advice is the drive's fastest and the config's keys that must follow it
        keys = "loop.period and feedback_period" if period < shortest * (1 - 1e-9) else "feedback_period"
        set_config = f"{keys} >= {_ms(shortest)}, the drive's fastest"
        fast_enough = motion.period is not None and motion.period <= shortest * PERIOD_TOLERANCE
        set_motion = f"set {set_config}" if fast_enough else f"{set_motion}, and {set_config}"
    if motion.period is None:
        now = "off" if motion.count == 0 else f"1 frame in {_ms(window)}"
        out.append(Finding(Severity.MISMATCH, f"node {node.node} sends no cyclic {probe.motion_name()}: "
                                              f"{set_motion} (now {now})", stale_feedback=True))
    elif motion.period > want_motion * PERIOD_TOLERANCE:
        stale = motion.period > period * PERIOD_TOLERANCE
        why = (f"loop.period {_ms(period)} would use each sample {motion.period / period:.0f} times" if stale else
               f"the profile's feedback_period is {_ms(feedback_period)}; each loop period still "
               "gets a fresh sample")
        out.append(Finding(Severity.MISMATCH, f"{set_motion} (now {_ms(motion.period)}; {why})",
                           stale_feedback=stale))
    elif feedback_timeout is not None and motion.max_gap is not None and motion.max_gap > feedback_timeout:
        # one pause in the window is no verdict on the run (it may not come back): the run
        # goes on, and stops only if a pause this long happens while it runs
        out.append(Finding(Severity.MISMATCH,
                           f"node {node.node}'s {probe.motion_name()} paused up to {_ms(motion.max_gap)}, "
                           f"longer than loop.feedback_timeout {_ms(feedback_timeout)}: a pause like it during "
                           "a run stops that run (feedback timeout); check bus load and other senders"))
    return out


def _status_findings(probe: PreflightProbe, node: NodeReport, window: float, want_status: float) -> list[Finding]:
    out: list[Finding] = []
    status = node.status
    set_status = (f"set {probe.setting(Setting.STATUS_RATE)} = "
                  f"{probe.setting_value(Setting.STATUS_RATE, want_status)}")
    if status.period is None:
        # none heard says "off" only after a whole period of listening: a window shorter
        # than the profile's period may fall between two frames of a drive that sends them
        if window >= RESOLVE_PERIODS * want_status or (status.count == 0 and window >= want_status):
            now = "off" if status.count == 0 else f"1 frame in {_ms(window)}"
            out.append(Finding(Severity.MISMATCH, f"node {node.node} {probe.status_name()}: {set_status} "
                                                  f"(now {now})"))
        else:
            out.append(Finding(Severity.NOTE, f"a {_ms(window)} window cannot measure a {_ms(want_status)} "
                                              f"{probe.status_name()}: listen at least "
                                              f"{RESOLVE_PERIODS * want_status:g} s"))
    elif status.period > want_status * PERIOD_TOLERANCE:
        out.append(Finding(Severity.MISMATCH,
                           f"{set_status} (now {_ms(status.period)}; the run calls a drive silent for "
                           f"3 x {_ms(want_status)} faulted)"))
    return out


def _rate_dict(rate: Rate) -> dict[str, Any]:
    return {"count": rate.count, "period": rate.period, "jitter": rate.jitter, "max_gap": rate.max_gap}


def _ms(seconds: float) -> str:
    ms = seconds * 1e3
    return f"{ms:.3g} ms" if ms < 100 else f"{ms:.0f} ms"
