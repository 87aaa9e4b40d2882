"""Emulated moteus controller, drive side: answers like the firmware as far as the official
Python library (PyPI ``moteus`` 1.1.1) and dobhil's drive can tell.

Frames (the codec's, :mod:`dobhil.drives.moteus.codec`): any frame (FD or classic, standard
or extended id) whose low 7 bits are the node id or the broadcast 0x7f and whose prefix is
the profile's ``moteus.can_prefix``. Its subframes are applied in order, as
``mjlib/multiplex/micro_server.cc`` does: a mode write resets every command register to
its default (position 0 -- NaN means "hold where you are" -- velocity 0, feedforward 0,
kp/kd scale 1, watchdog 0 = ``servo.default_timeout_s``), later writes fill them in, and
the command takes effect at the end of the frame. A write to a register the emulator does
not hold is answered ``0x30 register 1`` (unknown register) where it occurs. Only when bit
15 asks for it, one reply: on ``node << 8 | source | prefix << 16`` (extended when above
0x7ff), FD with the request's bit rate switch, one reply subframe per read subframe (same
start, count and type), padded with 0x50 to the next FD length; a register the emulator
does not model is a ``0x31 register 1`` read error.

Modes (``registers.md``, ``fw/bldc_servo.cc``): 0 stopped (clears a fault, torque 0), 10
position with the torque law ``kp_scale kp (p_cmd - p) + kd_scale kd (v_cmd - v) + ff``
(kp = ``pid_kp``, kd = ``pid_kd``: the emulator's stand-ins for ``servo.pid_position``;
with kp = kd = 0 it is the feedforward torque, which is all dobhil sends), clamped to the
command's max torque (0x025, NaN: the emulator's ``max_torque``, default the profile's
``torque_limit``). Other modes are not emulated: such a command is ignored and counted
(``frames_rejected``). A controller in mode 1 or 11 ignores every command but a stop.
The firmware passes through modes 2-4 on the way out of stopped; the emulator goes to 10
at once (the drive waits for 10 either way).

Watchdog: in mode 10, no command for the frame's 0x027 (0: ``default_timeout`` 0.1 s, the
firmware default; NaN: none) puts the controller in mode 11 (``watchdog_tripped``), where
it brakes as the firmware's default ``servo.timeout_mode`` 12 (zero velocity) does: a
damping torque ``-pid_kd_timeout * v``, limited to ``timeout_max_torque`` (5 N m, the
firmware default). Only a stop leaves 11.

Observables for :class:`~dobhil.emulator.process.EmulatorProcess`: ``protocol_state`` (the
mode), ``protocol_error`` (the fault code), ``watchdog_tripped``, ``frames_rejected``.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import can

from dobhil.drives.emulated import EmulatedDrive, PlantLike
from dobhil.drives.moteus.codec import (BROADCAST, Mode, Opcode, Parser, Register, Resolution, encode_value, pad,
                                        reply_subframe, split_id, varuint)
from dobhil.drives.profile import DriveProfile
from dobhil.errors import CodecError

__all__ = ["Command", "EmulatedMoteus"]

_TAU = 2.0 * math.pi
#: ``servo.default_timeout_s``, ``servo.timeout_max_torque_Nm`` (firmware defaults)
DEFAULT_TIMEOUT = 0.1
TIMEOUT_MAX_TORQUE = 5.0
_UNKNOWN_REGISTER = 1
#: what a frame asks back (read groups, and write errors where they occurred), and the reply's
#: constant bytes and value slots for it
_Answer = tuple[tuple[int, Resolution, int] | bytes, ...]
_Plan = tuple[bytes | tuple[int, Resolution], ...]
_SIZES = {Resolution.INT8: 1, Resolution.INT16: 2, Resolution.INT32: 4, Resolution.F32: 4}
_PACK = {res: struct.Struct(fmt).pack for res, fmt in
         ((Resolution.INT8, "<b"), (Resolution.INT16, "<h"), (Resolution.INT32, "<i"), (Resolution.F32, "<f"))}


@dataclass(frozen=True, slots=True)
class Command:
    """The position-mode command registers after a mode write (their defaults)."""

    mode: int = Mode.STOPPED
    position: float = 0.0      # [rev] NaN: where the output is
    velocity: float = 0.0      # [rev/s]
    feedforward: float = 0.0   # [N m]
    kp_scale: float = 1.0
    kd_scale: float = 1.0
    max_torque: float = math.nan
    timeout: float = 0.0       # [s] 0: the default; NaN: none


_FIELDS = {Register.COMMAND_POSITION: "position", Register.COMMAND_VELOCITY: "velocity",
           Register.COMMAND_FEEDFORWARD_TORQUE: "feedforward", Register.COMMAND_KP_SCALE: "kp_scale",
           Register.COMMAND_KD_SCALE: "kd_scale", Register.COMMAND_MAX_TORQUE: "max_torque",
           Register.COMMAND_TIMEOUT: "timeout"}


class EmulatedMoteus(EmulatedDrive):
    """A moteus controller on a python-can bus, dynamics from the injected plant."""

    def __init__(self, bus: can.BusABC, profile: DriveProfile, plant: PlantLike, *,
                 bus_voltage: float = 24.0, board_temperature: float = 30.0, max_torque: float | None = None,
                 pid_kp: float = 4.0, pid_kd: float = 0.05, default_timeout: float = DEFAULT_TIMEOUT,
                 **kwargs: Any) -> None:
        super().__init__(bus, profile, plant, **kwargs)
        opts = profile.options
        self.node_id = profile.node_id
        self.prefix = int(opts.get("can_prefix", 0))
        self.bus_voltage = bus_voltage
        self.board_temperature = board_temperature
        self.max_torque = profile.torque_limit if max_torque is None else max_torque
        self.pid_kp, self.pid_kd = pid_kp, pid_kd
        self.default_timeout = default_timeout
        self.mode = int(Mode.STOPPED)
        self.fault = 0
        self.command = Command()
        self.hold = 0.0             # [rev] where "position NaN" holds
        self.watchdog_tripped = False
        self.frames_rejected = 0
        self.replies = 0
        self._last_command = 0.0
        self._parser = Parser()   # the host's commands: one shape
        self._plans: dict[_Answer, _Plan] = {}

    # -- observables ----------------------------------------------------------

    @property
    def protocol_state(self) -> int:
        return self.mode

    @property
    def protocol_error(self) -> int:
        return self.fault

    @property
    def position(self) -> float:
        """[rev] of the output shaft."""
        return self._plant.position / _TAU

    @property
    def velocity(self) -> float:
        """[rev/s]"""
        return self._plant.velocity / _TAU

    # -- hooks ----------------------------------------------------------------

    def _plant_torque(self) -> float:
        if self.mode == Mode.POSITION:
            c = self.command
            if c.kp_scale == 0.0 and c.kd_scale == 0.0:   # torque by position mode: the hot path
                tau = c.feedforward
            else:
                target = self.hold if math.isnan(c.position) else c.position
                tau = (c.kp_scale * self.pid_kp * (target - self.position)
                       + c.kd_scale * self.pid_kd * (c.velocity - self.velocity) + c.feedforward)
            limit = self.max_torque if math.isnan(c.max_torque) else min(c.max_torque, self.max_torque)
            return min(max(tau, -limit), limit)
        if self.mode == Mode.TIMEOUT:
            tau = -self.pid_kd * self.velocity
            return min(max(tau, -TIMEOUT_MAX_TORQUE), TIMEOUT_MAX_TORQUE)
        return 0.0

    def _cyclic_frames(self) -> Sequence[tuple[float, Callable[[], can.Message]]]:
        return ()   # a moteus controller only answers

    def _on_time(self, now: float) -> None:
        if self.mode != Mode.POSITION:
            return
        timeout = self.command.timeout
        if timeout == 0.0:
            timeout = self.default_timeout
        if not math.isnan(timeout) and now - self._last_command >= timeout - 1e-9:
            self.mode = int(Mode.TIMEOUT)
            self.watchdog_tripped = True

    def _on_frame(self, msg: can.Message) -> None:
        prefix, source, destination, wants_reply = split_id(msg.arbitration_id)
        if msg.is_error_frame or msg.is_remote_frame or prefix != self.prefix or \
                destination not in (self.node_id, BROADCAST):
            self.frames_not_addressed += 1   # another controller's, or a reply
            return
        torque = self._plant_torque()
        try:
            answer = self._apply(bytes(msg.data))
        except CodecError:
            self.frames_rejected += 1
            return
        if wants_reply:
            self._reply(source, msg.bitrate_switch, answer, torque)

    # -- frames ---------------------------------------------------------------

    def _apply(self, data: bytes) -> list[tuple[int, Resolution, int] | bytes]:
        """Apply the writes in order; the reads (and write errors where they occurred)."""
        fields: dict[str, float] | None = None
        answer: list[tuple[int, Resolution, int] | bytes] = []
        for sub in self._parser.parse(data):
            if sub.opcode is Opcode.WRITE:
                name = _FIELDS.get(sub.register)   # type: ignore[call-overload]
                if sub.register == Register.MODE:
                    fields = {"mode": int(sub.value or 0)}
                elif name is not None and fields is not None:
                    fields[name] = float(sub.value if sub.value is not None else math.nan)
                elif name is None:
                    answer.append(bytes((Opcode.WRITE_ERROR,)) + varuint(sub.register) + varuint(_UNKNOWN_REGISTER))
            elif sub.opcode is Opcode.READ and sub.resolution is not None:
                last = answer[-1] if answer else None
                if isinstance(last, tuple) and last[1] is sub.resolution and last[0] + last[2] == sub.register:
                    answer[-1] = (last[0], last[1], last[2] + 1)
                else:
                    answer.append((sub.register, sub.resolution, 1))
        if fields is not None:
            self._command(Command(**fields))   # type: ignore[arg-type]
        return answer

    def _command(self, command: Command) -> None:
        if command.mode == Mode.STOPPED:
            self.mode, self.fault, self.command = int(Mode.STOPPED), 0, command
            self.watchdog_tripped = False
            return
        if self.mode in (Mode.FAULT, Mode.TIMEOUT):
            return   # only a stop leaves them
        if command.mode != Mode.POSITION:
            self.frames_rejected += 1   # not emulated
            return
        if self.mode != Mode.POSITION:
            self.hold = self.position
        self.mode, self.command = int(Mode.POSITION), command
        self._last_command = self._time

    def _value(self, register: int, torque: float) -> float | None:
        if register == Register.MODE:
            return float(self.mode)
        if register == Register.POSITION:
            return self.position
        if register == Register.VELOCITY:
            return self.velocity
        if register == Register.TORQUE:
            return torque
        if register == Register.VOLTAGE:
            return self.bus_voltage
        if register == Register.TEMPERATURE:
            return self.board_temperature
        if register == Register.FAULT:
            return float(self.fault)
        return None

    def _plan(self, answer: _Answer) -> _Plan:
        """The reply to ``answer`` as constant bytes (subframe heads, errors) and value slots
        (register, resolution), made once per query (a run asks the same every frame)."""
        plan: list[bytes | tuple[int, Resolution]] = []
        for item in answer:
            if isinstance(item, bytes):
                plan.append(item)
                continue
            start, res, count = item
            modelled = [self._value(start + i, 0.0) is not None for i in range(count)]
            if all(modelled):
                plan.append(reply_subframe(start, res, [0.0] * count)[:-_SIZES[res] * count])
                plan.extend((start + i, res) for i in range(count))
                continue
            for i, known in enumerate(modelled):   # the modelled ones one by one, the rest as read errors
                reg = start + i
                if known:
                    plan.append(reply_subframe(reg, res, (0.0,))[:-_SIZES[res]])
                    plan.append((reg, res))
                else:
                    plan.append(bytes((Opcode.READ_ERROR,)) + varuint(reg) + varuint(_UNKNOWN_REGISTER))
        return tuple(plan)

    def _reply(self, source: int, brs: bool, answer: list[tuple[int, Resolution, int] | bytes],
               torque: float) -> None:
        key = tuple(answer)
        plan = self._plans.get(key)
        if plan is None:
            plan = self._plans[key] = self._plan(key)
        parts: list[bytes] = []
        for item in plan:
            if isinstance(item, bytes):
                parts.append(item)
            else:
                reg, res = item
                parts.append(_PACK[res](encode_value(reg, res, self._value(reg, torque) or 0.0)))
        try:
            data = pad(b"".join(parts))
        except CodecError:
            self.frames_rejected += 1   # a query whose answer exceeds 64 bytes
            return
        reply_id = self.node_id << 8 | source | self.prefix << 16
        self._send(can.Message(arbitration_id=reply_id, is_extended_id=reply_id > 0x7FF, is_fd=True,
                               bitrate_switch=brs, data=data))
        self.replies += 1
