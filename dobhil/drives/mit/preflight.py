"""MIT-mode part of the preflight (:mod:`dobhil.drives.preflight`), and set-zero.

An MIT motor does not stream: it answers the frames it gets. So the probe asks, with the
one harmless frame there is -- a zero-torque command, p = v = kp = kd = t_ff = 0 (the
motor applies ``kp (p - q) + kd (v - dq) + t_ff`` = 0, and a motor not in motor mode
ignores it but still answers) -- and reads the reply:

- no reply at all is ONE finding, and the run refuses: a motor that is not in MIT mode
  answers nothing (CubeMars: set MIT mode with the vendor's tool); else the node id, the
  bit rate or the power is wrong. A silent Damiao is asked its control mode (register 10,
  CTRL_MODE, 1 = MIT): answering it in another mode names that mode instead;
- a reply whose length the model row's layout lacks is bad input (ConfigError: one line,
  exit 2, nothing enabled): the profile's vendor/model/firmware do not describe the motor;
- the reply's error code (CubeMars byte 7; Damiao a state nibble >= 8) and, on a Damiao,
  state 1 (already in motor mode: another host may drive it) refuse the run;
- a saturating position reading on its rail (``position_at_limit: saturate``) refuses
  the run: the angle beyond the range is lost;
- Damiao: the mapping ranges PMAX, VMAX, TMAX (registers 21, 22, 23, read as
  damiao-motor's ``_send_register_cmd`` does: id 0x7FF, ``[id_lo, id_hi, 0x33, rid, 0 x 4]``,
  the answer ``[id_lo, id_hi, 0x33, rid, float32 LE]`` on the reply id) are compared with
  the table: every value the codec packs and decodes is scaled by them, so a difference is
  bad input ("ranges do not match", ConfigError). A motor that does not answer a register
  read leaves them unchecked (a note).

Listening for the rest of the window hears other motors' replies on the shared reply id.
The bus budget per loop period: one 8-byte command and one reply (the layout's longest).

:func:`set_zero` is ``dobhil check --set-zero``: the only place dobhil sends set zero
(0xFE); never implicitly.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TypeVar

import can

from dobhil.drives.bus_load import CycleFrame
from dobhil.drives.mit.codec import (REGISTER_ID, REGISTER_READ, MitModel, Reply, Special, pack_command, special_frame,
                                     unpack_reply)
from dobhil.drives.mit.replies import DAMIAO_ENABLED, ZERO_COMMAND, reply_node, state_of
from dobhil.drives.mit.rules import model_of
from dobhil.drives.preflight import (Capture, Finding, NodeReport, Observation, PreflightProbe, Setting,
                                     Severity, Stream, listen_window)
from dobhil.drives.profile import DriveProfile
from dobhil.drives.waits import Cancel, sliced_frames
from dobhil.errors import CodecError, ConfigError, DriveTimeoutError, WaitCancelled, exception_line

__all__ = ["RANGE_REGISTERS", "REGISTER_ID", "REGISTER_READ", "MitPreflight", "ZeroResult", "register_request",
           "set_zero"]

T = TypeVar("T")

#: Damiao registers of the mapping ranges (damiao-motor's REGISTER_TABLE: PMAX, VMAX, TMAX)
RANGE_REGISTERS = ((21, "PMAX", "p_max"), (22, "VMAX", "v_max"), (23, "TMAX", "t_max"))
#: Damiao register CTRL_MODE (uint32) and its value for MIT mode (damiao-motor's REGISTER_TABLE)
CTRL_MODE = 10
MIT_CONTROL_MODE = 1
#: how long a register read may take before it is called unanswered [s]
REGISTER_TIMEOUT = 0.1
#: a register is a float32: a range equal to the table's within its rounding agrees
RANGE_TOLERANCE = 1e-6


def register_request(node: int, rid: int) -> can.Message:
    """A Damiao register read: ``[id_lo, id_hi, 0x33, rid, 0, 0, 0, 0]`` on 0x7FF."""
    return can.Message(arbitration_id=REGISTER_ID, is_extended_id=False,
                       data=bytes((node & 0xFF, node >> 8 & 0xFF, REGISTER_READ, rid, 0, 0, 0, 0)))


def _register_value(node: int, rid: int, data: bytes, fmt: str = "<f") -> float | None:
    """The value a register answer carries, a float32 or (``fmt`` ``<I``) a uint32 (None: not
    the answer to ``rid`` of ``node``)."""
    if len(data) != 8 or data[2] != REGISTER_READ or data[3] != rid or data[0] | data[1] << 8 != node:
        return None
    return float(struct.unpack(fmt, bytes(data[4:8]))[0])


class MitPreflight(PreflightProbe):
    """Asks the node with one zero-torque command, reads its reply (and a Damiao's
    ranges), then listens for the rest of the window."""

    checks_rates = False   # nothing streams: every reply answers a frame

    def __init__(self, profile: DriveProfile) -> None:
        super().__init__(profile)
        # bad input before anything is sent: no row in the table (one line)
        self.model: MitModel = model_of(profile)
        self.model.build_tables()   # the probe's reply is decoded at once, not after a build
        self.reply_id = int(profile.options.get("reply_id", 0))
        self.reply: Reply | None = None           # the node's answer to the probe
        self.ranges: dict[str, float] = {}        # what a Damiao's registers said
        self._registers_pending = False

    # -- the framework's hooks ------------------------------------------------

    def requests(self, node: int) -> Sequence[can.Message]:
        return ()   # the profile's node is asked in listen(); another motor is never sent a frame

    def observe(self, msg: can.Message) -> Observation | None:
        if msg.arbitration_id != self.reply_id or msg.is_extended_id or msg.is_remote_frame \
                or msg.is_error_frame or not msg.data:
            return None
        data = bytes(msg.data)
        if self._registers_pending and len(data) == 8 and data[2] == REGISTER_READ:
            return Observation(data[0] | data[1] << 8, Stream.VERSION, data)
        return Observation(reply_node(self.model, data), Stream.STATUS, data)

    def setting(self, which: Setting) -> str:
        return {Setting.NODE_ID: "the motor's CAN id (the vendor's tool)",
                Setting.MOTION_RATE: "nothing (an MIT motor answers each command)",
                Setting.STATUS_RATE: "nothing (an MIT motor answers each command)"}[which]

    def motion_name(self) -> str:
        return "streamed feedback (none in MIT mode)"

    def status_name(self) -> str:
        return "replies"

    def cycle_frames(self, period: float) -> Sequence[CycleFrame]:
        """One 8-byte command and one reply (the layout's longest) per loop period."""
        return (CycleFrame("MIT command", 8), CycleFrame("reply", max(self.model.layout.lengths)))

    # -- the window -------------------------------------------------------------

    def listen(self, bus: can.BusABC, window: float, clock: Callable[[], float],
               stamp: Callable[[can.Message], float], cancel: Cancel | None) -> Capture:
        cap = Capture()
        end = clock() + window
        node = self.profile.node_id
        command = can.Message(arbitration_id=node, is_extended_id=False,
                              data=pack_command(self.model, ZERO_COMMAND))
        try:
            bus.send(command, 0.0)
        except Exception as exc:  # any interface's refusal
            cap.send_errors.append(exception_line(exc, named=False))
            return cap
        try:
            data = _await(bus, clock, end, cancel, lambda m: self._is_reply(m),
                          lambda m: cap.take(m, self, stamp))
        except WaitCancelled:
            return cap
        except Exception as exc:  # the bus is gone
            cap.read_error = exception_line(exc)
            return cap
        if data is None:
            mode = self._control_mode(bus, clock, end, cancel, cap, stamp) if self.model.vendor == "damiao" else None
            cap.verdict = Finding(Severity.MISMATCH, self._silence(window, mode) + self._others(cap), refuses_run=True)
            return cap
        self.reply = self._decode(data)
        if self.model.vendor == "damiao":   # its ranges are registers the user may change
            self._read_ranges(bus, clock, end, cancel, cap, stamp)
        if clock() < end:
            listen_window(bus, self, end - clock(), clock, stamp, cancel, cap)
        return cap

    def _is_reply(self, msg: can.Message) -> bytes | None:
        obs = self.observe(msg)
        if obs is None or obs.stream is not Stream.STATUS or obs.node != self.profile.node_id:
            return None
        return obs.data

    def _decode(self, data: bytes) -> Reply:
        try:
            return unpack_reply(self.model, data)
        except CodecError:
            m = self.model
            raise ConfigError(
                f"drive profile {self._name()!r}: node {self.profile.node_id} replied in {len(data)} bytes, the "
                f"{m.vendor} {m.model} (firmware {m.firmware!r}) row's layout has {_lengths(m)}: the profile's "
                "mit.vendor, mit.model and firmware do not describe this motor") from None

    def _read_ranges(self, bus: can.BusABC, clock: Callable[[], float], end: float, cancel: Cancel | None,
                     cap: Capture, stamp: Callable[[can.Message], float]) -> None:
        node = self.profile.node_id
        self._registers_pending = True
        try:
            for rid, name, _ in RANGE_REGISTERS:
                bus.send(register_request(node, rid), 0.0)
                until = min(end, clock() + REGISTER_TIMEOUT)
                value = _await(bus, clock, until, cancel, self._register_answer(rid),
                               lambda m: cap.take(m, self, stamp))
                if value is None:
                    cap.findings.append(Finding(Severity.NOTE, f"node {node} did not answer the register read of "
                                                               f"{name} (register {rid}): its ranges are not checked "
                                                               "against the model table"))
                    return
                self.ranges[name] = float(value)
        except WaitCancelled:
            return
        except Exception as exc:  # the bus refused the request or is gone: the window's findings say it
            cap.send_errors.append(exception_line(exc, named=False))
            return
        finally:
            self._registers_pending = False
        self._compare_ranges()

    def _register_answer(self, rid: int, fmt: str = "<f") -> Callable[[can.Message], float | None]:
        def answer(msg: can.Message) -> float | None:
            if msg.arbitration_id != self.reply_id or msg.is_extended_id:
                return None
            return _register_value(self.profile.node_id, rid, bytes(msg.data), fmt)
        return answer

    def _control_mode(self, bus: can.BusABC, clock: Callable[[], float], end: float, cancel: Cancel | None,
                      cap: Capture, stamp: Callable[[can.Message], float]) -> int | None:
        """A Damiao silent to MIT frames may be in another control mode (it then listens on
        0x100 + id or 0x200 + id): register CTRL_MODE (10, uint32; 1 = MIT) says which.
        None: no answer either (or the read could not be made)."""
        self._registers_pending = True
        try:
            bus.send(register_request(self.profile.node_id, CTRL_MODE), 0.0)
            value = _await(bus, clock, max(end, clock() + REGISTER_TIMEOUT), cancel,
                           self._register_answer(CTRL_MODE, "<I"), lambda m: cap.take(m, self, stamp))
        except Exception:  # the verdict says silence either way; this only adds why
            return None
        finally:
            self._registers_pending = False
        return None if value is None else int(value)

    def _compare_ranges(self) -> None:
        m = self.model
        wrong = [(name, self.ranges[name], float(getattr(m, key))) for _, name, key in RANGE_REGISTERS
                 if not math.isclose(self.ranges[name], float(getattr(m, key)), rel_tol=RANGE_TOLERANCE)]
        if wrong:
            said = ", ".join(f"{name} {got:g} (table {want:g})" for name, got, want in wrong)
            raise ConfigError(f"drive profile {self._name()!r}: ranges do not match: node {self.profile.node_id}'s "
                              f"registers say {said} for the {m.vendor} {m.model} (firmware {m.firmware!r}); set "
                              "mit.model to the motor's model (or its registers to the table's ranges)")

    def _silence(self, window: float, mode: int | None = None) -> str:
        if mode is not None and mode != MIT_CONTROL_MODE:
            return (f"no reply from node {self.profile.node_id} on id 0x{self.reply_id:X} to a zero-torque command "
                    f"within {window * 1e3:.0f} ms, but it answers register reads: its control mode (register "
                    f"{CTRL_MODE}, CTRL_MODE) is {mode}, not {MIT_CONTROL_MODE} (MIT): set CTRL_MODE = "
                    f"{MIT_CONTROL_MODE} with Damiao's tool")
        vendor = " (CubeMars: set MIT mode with the vendor's tool)" if self.model.vendor == "cubemars" else ""
        return (f"no reply from node {self.profile.node_id} on id 0x{self.reply_id:X} to a zero-torque command "
                f"within {window * 1e3:.0f} ms: a motor not in MIT mode answers nothing{vendor}; else the node id, "
                "the bus bit rate or the motor's power is wrong")

    def _others(self, cap: Capture) -> str:
        others = sorted(n for n in cap.nodes if n != self.profile.node_id)
        if not others:
            return ""
        return (f"; node(s) {', '.join(map(str, others))} replied on the bus: node_id: {others[0]} in profile "
                f"{self._name()!r} if that is the motor")

    def _name(self) -> str:
        return self.profile.name or self.profile.protocol

    # -- what the node said ---------------------------------------------------------

    def node_summary(self, node: NodeReport) -> str:
        if node.node != self.profile.node_id or self.reply is None:
            return ""
        r, m = self.reply, self.model
        words = [f"{m.vendor} {m.model} reply: position {r.position:.4f} rad, velocity {r.velocity:.3f} rad/s, "
                 f"torque {r.torque:.3f} Nm"]
        if not math.isnan(r.temperature):
            words.append(f"temperature {r.temperature:g} degC")
        if r.state >= 0:
            words.append(state_of(m, r)[1])
        elif r.error >= 0:
            words.append(f"error {r.error}" + (f" ({r.error_text})" if r.error else " (none)"))
        if self.ranges:
            words.append("registers " + ", ".join(f"{k} {v:g}" for k, v in self.ranges.items()))
        return "; ".join(words)

    def node_findings(self, node: NodeReport) -> list[Finding]:
        r = self.reply
        if node.node != self.profile.node_id or r is None:
            return []
        out: list[Finding] = []
        if r.error > 0:
            fix = ("dobhil run --reset-faults clears it (clear error 0xFB)" if Special.CLEAR_ERROR in self.model.special
                   else "power-cycle the motor once the cause is gone")
            out.append(Finding(Severity.MISMATCH, f"node {node.node} reports error {r.error} ({r.error_text}): {fix}",
                               refuses_run=Special.CLEAR_ERROR not in self.model.special))
        if r.state == DAMIAO_ENABLED:
            out.append(Finding(Severity.MISMATCH, f"node {node.node} is already in motor mode (state 1): another "
                                                  "host may be driving it; exit motor mode first", refuses_run=True))
        if self.model.position_at_limit != "wrap" and r.raw_position in (0, (1 << 16) - 1):
            out.append(Finding(Severity.MISMATCH,
                               f"node {node.node}'s position is at the end of the encodable range "
                               f"(+-{self.model.p_max:g} rad): the reading saturates there; move the axis back "
                               "into the range (or set zero: dobhil check --set-zero)", refuses_run=True))
        return out


def _lengths(model: MitModel) -> str:
    return " or ".join(str(n) for n in model.layout.lengths) + " bytes"


def _await(bus: can.BusABC, clock: Callable[[], float], until: float, cancel: Cancel | None,
           match: Callable[[can.Message], T | None], take: Callable[[can.Message], object]) -> T | None:
    """Read ``bus`` in slices until ``match`` gives a value (returned) or ``until``
    (None); every frame goes to ``take`` first. WaitCancelled within a slice of ``cancel``."""
    for msg in sliced_frames(bus.recv, clock, until, cancel=cancel):
        take(msg)
        found = match(msg)
        if found is not None:
            return found
    return None


def _nothing(msg: can.Message) -> None:
    return None


# ---------------------------------------------------------------------------
# Set zero: only when asked (dobhil check --set-zero)


@dataclass(frozen=True)
class ZeroResult:
    """What set zero left: the node's first reply after its silence."""

    node: int
    position: float      # [rad] the reading after zeroing (near 0 when it took)
    silence: float       # [s] how long dobhil waited before asking
    reply: Reply

    def line(self) -> str:
        return (f"node {self.node}: set zero sent; after {self.silence:g} s the position reads "
                f"{self.position:+.4f} rad")


#: [s] set zero: how often the position is asked again while no reply has come
ASK_AGAIN = 0.1


def set_zero(bus: can.BusABC, profile: DriveProfile, *, clock: Callable[[], float],
             cancel: Cancel | None = None, timeout: float | None = None) -> ZeroResult:
    """Send set zero (0xFE) to the profile's node, wait ``mit.zero_silence`` s (the motor is
    silent while it stores the offset; frames meanwhile are read and dropped), then ask with
    a zero-torque command (again every :data:`ASK_AGAIN` s until a reply) and return the
    position of the reply. ConfigError for a profile
    that is not MIT; DriveTimeoutError when no reply comes within ``timeout`` (default the
    profile's ``enable_timeout``); WaitCancelled within WAIT_SLICE s of ``cancel()``."""
    if profile.protocol != "mit":
        raise ConfigError(f"--set-zero: expected a profile of protocol 'mit' (MIT-mode motors), profile "
                          f"{profile.name or profile.protocol!r} is protocol {profile.protocol!r}")
    model = model_of(profile)
    node = profile.node_id
    reply_id = int(profile.options.get("reply_id", 0))
    silence = float(profile.options.get("zero_silence", 1.0))
    bus.send(can.Message(arbitration_id=node, is_extended_id=False, data=special_frame(Special.ZERO)))
    _await(bus, clock, clock() + silence, cancel, _nothing, _nothing)
    ask = can.Message(arbitration_id=node, is_extended_id=False, data=pack_command(model, ZERO_COMMAND))
    wait = profile.enable_timeout if timeout is None else timeout

    def ours(msg: can.Message) -> bytes | None:
        ok = msg.arbitration_id == reply_id and not msg.is_extended_id and not msg.is_remote_frame \
            and reply_node(model, msg.data) == node
        return bytes(msg.data) if ok else None

    # asked again every ASK_AGAIN s: a motor still silent when the first ask arrives (its
    # flash write a little longer than zero_silence, or a busy host's frame late) drops it,
    # and one lost ask must not read as "not in MIT mode"; a zero-torque command is harmless
    deadline = clock() + wait
    data = None
    while data is None and clock() < deadline:
        bus.send(ask)
        data = _await(bus, clock, min(clock() + ASK_AGAIN, deadline), cancel, ours, _nothing)
    if data is None:
        raise DriveTimeoutError(f"node {node}: no reply within {wait:g} s after set zero and {silence:g} s of "
                                "silence: a motor not in MIT mode answers nothing; check node_id, the bit rate "
                                "and the power (mit.zero_silence if it needs longer)")
    try:
        reply = unpack_reply(model, data)
    except CodecError as exc:
        raise ConfigError(f"node {node}: reply after set zero: {exc}") from None
    return ZeroResult(node, reply.position, silence, reply)
