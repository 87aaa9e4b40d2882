"""Emulated MIT-mode actuator (Mini-Cheetah firmware, CubeMars AK, Damiao), drive side.

The frames are the codec's (:mod:`dobhil.drives.mit.codec`): the command is decoded with
``unpack_command`` -- what the firmware decodes, the host's sign (the codec applies the
model's axis direction) -- and every reply is packed by ``pack_reply``, so the host sees
the quantised, wrapped or saturated values a motor of that model row sends. Behaviour
follows the reference firmware (bgkatz/motorcontrol, which the CubeMars and Damiao
firmware copy: its ``CAN/CAN_com.cpp`` packing and ``main.cpp`` special frames) where it is known, and says so where
it is the emulator's own choice:

- **one reply to every frame to its node** (arbitration id = ``node_id``, an 8-byte data
  frame; the special frames included), on the profile's ``mit.reply_id`` (the firmware's
  CAN master id), carrying the state at the instant the frame is applied: position and
  velocity of that instant, the torque applied up to it (the firmware's reply carries the
  measured current, which the new command has not changed yet), the mode and error after
  the frame (a Damiao confirms its enable with state 1 in the reply to it). The firmware
  replies from its receive interrupt; here the frame is applied ``latency`` after it was
  received (lockstep: 0, the same simulated instant). Other frames are not answered: a
  wrong length (counted in ``frames_rejected``), RTR and extended frames, other ids
  (Damiao's position-velocity 0x100+id and velocity 0x200+id modes are not emulated);
- **motor mode** (rest / motor): enter 0xFC, exit 0xFD. A command is decoded and kept
  only in motor mode (the firmware unpacks commands only in MOTOR_MODE). A CubeMars motor
  remembers the last command across exit and enter and applies it again at the next
  enter (users' "initial kick": canmotorlib's enable/disable comments, the table's AK80-9
  note) -- why a safe stop sends zero torque before the exit; the other vendors start
  from kp = kd = t_ff = 0 at each enter (exit zeroes the command);
- **torque law** ``kp (p - q) + kd (v - dq) + t_ff``, clamped to +-``t_max``, applied
  only in motor mode; ``q``, ``dq`` are the plant's measured position (from the zero
  set last) and velocity at the start of each plant step (the firmware evaluates it at
  tens of kHz; the plant steps are the emulator's ZOH pieces -- exact for pure torque,
  kp = kd = 0, which is all dobhil sends);
- **command timeout** (the model row's ``command_timeout``; none when it has none): with
  no frame to the node for that long in motor mode, kp, kd and t_ff are zeroed (the
  firmware's CAN timeout; any frame to the node feeds it, as bgkatz's receive handler
  resets its counter for its id); a Damiao instead leaves motor mode with state 0xD, lost
  communication (damiao-motor clears exactly that state to resume);
  :attr:`EmulatedMit.watchdog_tripped` says it happened;
- **set zero** 0xFE: the current position becomes 0 (the offset stays until the next set
  zero, as the encoder offset written to flash does), and the motor is silent for
  ``mit.zero_silence`` s (about 1 s in the reference firmware while it writes flash): no reply to
  the zero frame nor to anything received meanwhile, and nothing received meanwhile is
  applied (``frames_ignored``);
- **clear error** 0xFB, only on models whose row lists it (Damiao): clears a latched
  fault once its cause is gone. On other models the frame is not special: a motor in
  motor mode decodes it as a command, as their firmware would (the drive never sends it);
- **temperature** (first-order thermal model, :class:`Thermal`): the winding temperature
  approaches ``ambient + rise_at_t_max * (tau / t_max)^2`` with time constant
  ``time_constant`` (copper loss ~ current^2 ~ torque^2); ``over_temperature`` reached:
  the over-temperature fault. **Over-current**: the torque law demanding more than
  ``over_current_ratio * t_max`` before the clamp (a kp/kd term driving the current loop
  far past its range; the emulator's proxy for the phase-current trip, which a rigid plant
  does not model); pure torque (t_ff within +-t_max) never reaches it. A fault leaves motor
  mode (torque 0) and latches its code: CubeMars error byte 1 over temperature, 2 over
  current; Damiao state 0xC rotor over temperature, 0xA over current; the Mini-Cheetah
  reply has no error field (the motor just stops). It clears (cause gone: the winding
  ``hysteresis`` K below the limit) with the next enter (CubeMars, Mini-Cheetah) or a
  clear error (Damiao); an enter while it is latched is refused (the reply says so).
  Reply temperature: the winding (CubeMars byte 6, Damiao rotor byte 7); Damiao MOS byte 6:
  ambient plus ``mos_share`` of the winding's rise (a stand-in: no MOSFET model);
- **Damiao registers** (0x7FF, read 0x33 -- damiao-motor's ``_send_register_cmd`` layout):
  PMAX, VMAX, TMAX (21-23, the row's ranges, float32), MST_ID 7, ESC_ID 8, CTRL_MODE 10
  (1: MIT) and OT_Value 2, answered on ``reply_id`` as ``id_l id_h 0x33 rid value``.

Observables for :class:`~dobhil.emulator.process.EmulatorProcess` (``OBSERVED``):
``protocol_state`` (1 motor mode, 0 rest), ``protocol_error`` (the vendor's code, 0 none),
``watchdog_tripped`` (the command timeout fired) and ``frames_rejected``.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import can

from dobhil.drives.mit.codec import (REGISTER_ID, REGISTER_READ, Command, MitModel, ReplyLayout, Special,
                                     float_to_uint, is_special, pack_reply, unpack_command)
from dobhil.drives.mit.replies import ZERO_COMMAND
from dobhil.drives.mit.rules import MIT_RULES, model_of
from dobhil.drives.profile import DriveProfile
from dobhil.drives.emulated import EmulatedDrive, PlantLike
from dobhil.errors import CodecError

__all__ = ["EmulatedMit", "Fault", "Thermal", "model_of"]

#: the profile section's defaults (its rules'): master id 0, 1 s of silence
DEFAULT_REPLY_ID = int(MIT_RULES.section["reply_id"].default)
DEFAULT_ZERO_SILENCE = float(MIT_RULES.section["zero_silence"].default)
_F32 = struct.Struct("<f")
_U32 = struct.Struct("<I")


@dataclass(frozen=True, slots=True)
class Thermal:
    """The first-order winding model (the emulator's constants, not a motor's datasheet).

    Steady state at a constant torque ``tau``: ``ambient + rise_at_t_max * (tau/t_max)^2``
    [degC]; approached with ``time_constant`` [s]. With the defaults a motor held at its
    peak torque ``t_max`` reaches ``over_temperature`` after 60 s * ln(250/175) = 21 s,
    and at half of it (about the rated torque of an AK80-9, 9 of 18 Nm) it settles at
    87.5 degC, below the limit: peak torque is for bursts, as on the real motors."""

    ambient: float = 25.0            # [degC]
    rise_at_t_max: float = 250.0     # [K] steady-state rise at |tau| = t_max
    time_constant: float = 60.0      # [s]
    over_temperature: float = 100.0  # [degC] the over-temperature fault
    hysteresis: float = 10.0         # [K] below the limit before the fault can be cleared
    over_current_ratio: float = 1.5  # torque-law demand / t_max that trips over-current
    mos_share: float = 0.4           # Damiao MOS byte: this share of the winding's rise

    def __post_init__(self) -> None:
        if not (self.time_constant > 0 and self.rise_at_t_max >= 0 and self.hysteresis >= 0
                and self.over_temperature > self.ambient and self.over_current_ratio >= 1.0):
            raise ValueError(f"thermal model: needs time_constant > 0, rise >= 0, hysteresis >= 0, "
                             f"over_temperature > ambient, over_current_ratio >= 1; got {self}")


class Fault:
    """The faults the emulator produces, and their codes in a reply layout: looked up by
    their text in the model table's ``errors`` (CubeMars byte 7: 1 over temperature, 2 over
    current) or ``states`` (Damiao nibble: 12 rotor over temperature, 10 over current, 13
    communication lost), so the codes are the table's, not the emulator's. A layout without
    an error field (Mini-Cheetah, mbed) has none: the fault still stops the motor."""

    OVER_TEMPERATURE = "over_temperature"
    OVER_CURRENT = "over_current"
    LOST_COMMUNICATION = "lost_communication"

    #: fault -> the texts it may have in a table (the first found wins)
    TEXTS: Mapping[str, tuple[str, ...]] = {
        OVER_TEMPERATURE: ("over temperature", "rotor over temperature"),
        OVER_CURRENT: ("over current",),
        LOST_COMMUNICATION: ("communication lost",),
    }

    @classmethod
    def codes(cls, layout: ReplyLayout) -> Mapping[str, int]:
        """fault -> code in ``layout`` (only the faults it can report)."""
        table = {text: code for code, text in (*layout.errors.items(), *layout.states.items())}
        out: dict[str, int] = {}
        for fault, texts in cls.TEXTS.items():
            code = next((table[t] for t in texts if t in table), None)
            if code is not None:
                out[fault] = code
        return out


class EmulatedMit(EmulatedDrive):
    """An MIT-mode actuator on a python-can bus, dynamics from the injected plant.

    Its model row: :func:`model_of` of the profile (or ``model``). ``thermal``: the
    winding model and fault thresholds (:class:`Thermal`); ``bus_voltage`` [V]: the
    Mini-Cheetah reply's optional byte."""

    def __init__(self, bus: can.BusABC, profile: DriveProfile, plant: PlantLike, *,
                 model: MitModel | None = None, thermal: Thermal | None = None,
                 bus_voltage: float = 24.0, **kwargs: Any) -> None:
        super().__init__(bus, profile, plant, **kwargs)
        self.model = model_of(profile) if model is None else model
        self.thermal = Thermal() if thermal is None else thermal
        self.node_id = profile.node_id
        self.reply_id = int(profile.options.get("reply_id", DEFAULT_REPLY_ID))
        self.zero_silence = float(profile.options.get("zero_silence", DEFAULT_ZERO_SILENCE))
        self.bus_voltage = bus_voltage
        self._layout = self.model.layout
        self._codes = Fault.codes(self._layout)
        self._specials = frozenset(self.model.special)
        #: the last command survives exit and enter (CubeMars; see the module docstring)
        self.remembers_command = self.model.vendor == "cubemars"
        self.motor_mode = False
        self.command = ZERO_COMMAND
        self.fault = ""            # the latched fault (a Fault name), "" none
        self.temperature = self.thermal.ambient   # [degC] winding
        self.offset = 0.0          # [rad] plant position of the last set zero
        self.silent_until = -math.inf
        self.watchdog_tripped = False
        self.frames_rejected = 0
        self.frames_ignored = 0    # received while silent after a set zero
        self.replies = 0
        self._last_frame = 0.0     # emulator time of the last frame to the node
        self._thermal_time = 0.0
        self._thermal_dt = math.nan
        self._thermal_keep = 1.0

    # -- observables ----------------------------------------------------------

    @property
    def protocol_state(self) -> int:
        """1 in motor mode, 0 at rest."""
        return int(self.motor_mode)

    @property
    def protocol_error(self) -> int:
        """The vendor's code of the latched fault (0 none, or none on this layout)."""
        return self._codes.get(self.fault, 0) if self.fault else 0

    @property
    def position(self) -> float:
        """[rad] the motor's own position reading: the plant's, from the last set zero."""
        return self._plant.position - self.offset

    # -- hooks ----------------------------------------------------------------

    def _warm_up(self) -> None:
        self.model.build_tables()   # every reply is packed through them

    def _plant_torque(self) -> float:
        if not self.motor_mode:
            return 0.0
        limit = self.model.t_max
        return min(max(self._demand(), -limit), limit)

    def _demand(self) -> float:
        """The torque law before the clamp [Nm]."""
        c = self.command
        if c.kp == 0.0 and c.kd == 0.0:   # pure torque: the hot path, and q unused
            return c.torque
        q, dq = self.position, self._plant.velocity
        return c.kp * (c.position - q) + c.kd * (c.velocity - dq) + c.torque

    def _cyclic_frames(self) -> Sequence[tuple[float, Callable[[], can.Message]]]:
        return ()   # an MIT motor only answers

    def _on_time(self, now: float) -> None:
        self._heat(now)
        if not self.motor_mode:
            return
        timeout = self.model.command_timeout
        if timeout is not None and timeout > 0 and now - self._last_frame >= timeout - 1e-9:
            self._command_timeout()
        self._check_limits()

    def _on_frame(self, msg: can.Message) -> None:
        if msg.is_error_frame or msg.is_extended_id or msg.is_remote_frame:
            self.frames_not_addressed += 1
            return
        if msg.arbitration_id == REGISTER_ID and self._layout.state_field:   # Damiao
            self._register(msg.data)
            return
        if msg.arbitration_id != self.node_id:
            self.frames_not_addressed += 1   # another motor's command, or any reply
            return
        if self._time < self.silent_until - 1e-9:
            self.frames_ignored += 1   # writing the zero to flash: deaf and mute
            return
        data = bytes(msg.data)
        if len(data) != 8:
            self.frames_rejected += 1
            return
        self._last_frame = self._time
        torque = self._plant_torque()   # what the motor applied up to now (its reply's)
        special = is_special(data)
        if special is not None and special in self._specials:
            if self._special(special):
                return   # set zero: silent
        elif self.motor_mode:
            try:
                self.command = unpack_command(self.model, data)
            except CodecError:
                self.frames_rejected += 1
                return
            self._check_limits()
        self._reply(torque)

    # -- frames ---------------------------------------------------------------

    def _special(self, kind: Special) -> bool:
        """Apply a special frame; True when the motor stays silent (set zero)."""
        if kind is Special.ENTER:
            self._enter()
        elif kind is Special.EXIT:
            self._leave()
        elif kind is Special.ZERO:
            self.offset = self._plant.position
            self.silent_until = self._time + self.zero_silence
            return True
        elif kind is Special.CLEAR_ERROR and self.fault and self._cause_gone():
            self.fault = ""
        return False

    def _enter(self) -> None:
        if self.fault and Special.CLEAR_ERROR not in self._specials and self._cause_gone():
            self.fault = ""   # CubeMars, Mini-Cheetah: a new enter clears a fault whose cause is gone
        if self.fault:
            return            # refused: the reply still carries the fault
        if not self.motor_mode:
            if not self.remembers_command:
                self.command = ZERO_COMMAND
            self.watchdog_tripped = False
        self.motor_mode = True

    def _leave(self) -> None:
        self.motor_mode = False
        if not self.remembers_command:
            self.command = ZERO_COMMAND

    def _reply(self, torque: float) -> None:
        model = self.model
        state = 1 if self.motor_mode else 0
        error = self.protocol_error
        extra: dict[str, int] = {}
        layout = self._layout
        if "mos_temperature" in layout.extra:
            th = self.thermal
            extra["mos_temperature"] = _byte(th.ambient + th.mos_share * (self.temperature - th.ambient))
        if "bus_voltage" in layout.extra:   # the firmware's float_to_uint(vbus, 0, 40, 8)
            extra["bus_voltage"] = float_to_uint(self.bus_voltage, 0.0, 40.0, 8)
        data = pack_reply(model, self.node_id, self.position, self._plant.velocity, torque,
                          error=error, state=state, temperature=self.temperature, extra=extra)
        self._send(can.Message(arbitration_id=self.reply_id, is_extended_id=False, data=data))
        self.replies += 1

    def _register(self, data: bytearray) -> None:
        """Damiao register read (0x7FF): ``id_l id_h 0x33 rid`` -> ``id_l id_h 0x33 rid value``."""
        if len(data) != 8 or data[0] | data[1] << 8 != self.node_id:
            self.frames_not_addressed += 1   # another motor's (the register id is shared)
            return
        if data[2] != REGISTER_READ:
            return   # a write/store (not emulated)
        m = self.model
        floats = {21: m.p_max, 22: m.v_max, 23: m.t_max, 2: self.thermal.over_temperature}
        ints = {7: self.reply_id, 8: self.node_id, 10: 1}
        rid = data[3]
        if rid in floats:
            value = _F32.pack(floats[rid])
        elif rid in ints:
            value = _U32.pack(ints[rid])
        else:
            self.frames_rejected += 1
            return
        self._send(can.Message(arbitration_id=self.reply_id, is_extended_id=False,
                               data=bytes(data[:4]) + value))

    # -- faults ---------------------------------------------------------------

    def _command_timeout(self) -> None:
        self.watchdog_tripped = True
        if Fault.LOST_COMMUNICATION in self._codes:   # Damiao: disabled, state 0xD
            self._trip(Fault.LOST_COMMUNICATION)
        else:                                         # bgkatz: kp = kd = t_ff = 0
            c = self.command
            self.command = Command(c.position, c.velocity, 0.0, 0.0, 0.0)

    def _check_limits(self) -> None:
        if not self.motor_mode:
            return
        if self.temperature >= self.thermal.over_temperature:
            self._trip(Fault.OVER_TEMPERATURE)
        elif abs(self._demand()) > self.thermal.over_current_ratio * self.model.t_max:
            self._trip(Fault.OVER_CURRENT)

    def _trip(self, fault: str) -> None:
        self.fault = fault
        self._leave()

    def _cause_gone(self) -> bool:
        """A latched fault may be cleared: the winding has cooled below the limit by the
        hysteresis (over-current and lost communication end with the frame that caused
        them)."""
        if self.fault != Fault.OVER_TEMPERATURE:
            return True
        return self.temperature <= self.thermal.over_temperature - self.thermal.hysteresis

    def _heat(self, now: float) -> None:
        """The winding temperature over the interval since the last call, the torque of
        now held over it (exact for the ZOH torque of a lockstep period)."""
        dt = now - self._thermal_time
        if dt <= 0:
            return
        self._thermal_time = now
        th = self.thermal
        if dt != self._thermal_dt:   # one exp per distinct interval (lockstep: one)
            self._thermal_dt = dt
            self._thermal_keep = math.exp(-dt / th.time_constant)
        ratio = self._plant_torque() / self.model.t_max
        target = th.ambient + th.rise_at_t_max * ratio * ratio
        self.temperature = target + (self.temperature - target) * self._thermal_keep


def _byte(value: float) -> int:
    """A temperature or voltage as the one unsigned byte the reply has (clamped)."""
    return min(max(int(round(value)), 0), 255)
