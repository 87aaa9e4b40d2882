"""Pure codec of ODrive CAN Simple frames: bytes in, SI values out, no I/O.

Facts follow the official DBC files shipped in the ``odrive-can`` package
(``odrive-cansimple-0.6.10.dbc`` for firmware 0.6, the default, and
``odrive-cansimple-0.5.6.dbc`` for firmware 0.5); ``tests/drives/test_odrive_cantools.py``
checks every message of this table against both files.

- Arbitration id: 11 bit, ``node_id << 5 | cmd_id`` (both firmwares).
- Little-endian, IEEE-754 float32. Units on the wire: turns, turns/s, Nm, A, V;
  this module converts turns -> rad and turns/s -> rad/s (factor 2*pi); Nm stays Nm.
- Heartbeat (0x01): 0.6 = Axis_Error u32, Axis_State u8, Procedure_Result u8,
  Trajectory_Done bit 48; 0.5 = Axis_Error u32, Axis_State u8, Motor_Error_Flag bit 40,
  Encoder_Error_Flag bit 48, Controller_Error_Flag bit 56, Trajectory_Done bit 63.
- Frame length: every message is encoded with the DLC its DBC gives it (8 for every
  data message, zero padding after the payload; 0 for Estop; Clear_Errors (0x18) and
  Reboot (0x16): DLC 0 on 0.5, 1 on 0.6). Firmware reads commands without a length
  check, but DBC-strict peers (cantools, odrive-can's mock) drop shorter frames.
  Decoding accepts any length >= the payload (the firmware's leniency).
- ``Get_*`` requests are RTR frames whose DLC is the data frame's DLC (as CAN asks of
  requesters, so two requests on one id never collide with different lengths).
- Get_Version (0x00), Get_Error (0x03) and Get_Torques (0x1C) exist on 0.6 only; 0.5
  uses 0x03/0x04/0x05/0x1D for Get_Motor_Error/Get_Encoder_Error/Get_Sensorless_Error/
  Get_Controller_Error (firmware 0.5.6 ``can_simple.cpp``; 0x00 is the CANopen NMT id
  there, which 0.5.6 ignores: a 0.5 drive never answers Get_Version).
- Error tables: firmware 0.5 (``AxisError05``, ``MotorError05``, ``EncoderError05``,
  ``ControllerError05``, ``SensorlessError05``) from ``tools/odrive/enums.py`` of tag
  fw-v0.5.6 of odriverobotics/ODrive (generated from ``odrive-interface.yaml``) and the
  0.5.6 DBC's value tables; firmware 0.6 (``ODriveError06``, ``ProcedureResult06``) from
  the 0.6.10 DBC's value tables and ``odrive_can.enums`` (copied from firmware 0.6.7).
  The 0.5 heartbeat carries Axis_Error plus one flag byte each for motor, encoder and
  controller errors (their codes come from the Get_*_Error messages); the 0.6
  heartbeat carries the active ODriveError bits and Procedure_Result.
- Watchdog error bit: 0x800 AxisError.WATCHDOG_TIMER_EXPIRED on 0.5,
  0x01000000 ODriveError.WATCHDOG_TIMER_EXPIRED on 0.6.
- Floats that do not fit float32 (|x| > 3.4e38 after unit scaling) are a CodecError,
  never a silent inf; NaN and inf themselves are representable and pass through.

One table (:data:`_TABLE`) of messages drives both :func:`encode` and :func:`decode`;
each scale factor is written once.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, fields
from enum import IntEnum, IntFlag
from operator import mul, truediv
from types import MappingProxyType
from typing import Any

import can

from dobhil.errors import CodecError

__all__ = [
    "AxisError05",
    "ControllerError05",
    "ControllerErrorMsg",
    "EncoderError05",
    "EncoderErrorMsg",
    "MotorError05",
    "MotorErrorMsg",
    "ProcedureResult06",
    "SensorlessError05",
    "SensorlessErrorMsg",
    "Version",
    "describe_heartbeat",
    "specs",
    "AxisState",
    "BusVoltageCurrent",
    "ClearErrors",
    "AnyCmdId",
    "CmdId",
    "CmdId05",
    "CmdId06",
    "ControlMode",
    "EncoderEstimates",
    "Estop",
    "Firmware",
    "GetError",
    "Heartbeat",
    "InputMode",
    "Iq",
    "MessageSpec",
    "ODriveError06",
    "ODriveMessage",
    "Reboot",
    "Request",
    "SetAxisState",
    "SetControllerMode",
    "SetInputTorque",
    "SetInputVel",
    "SetLimits",
    "Torques",
    "arbitration_id",
    "decode",
    "decode_message",
    "describe_errors",
    "encode",
    "encode_data",
    "estop_bit",
    "spec_for",
    "split_id",
    "watchdog_bit",
]

TURN = 2.0 * math.pi  # rad per turn: the one scale of positions and velocities
MAX_NODE_ID = 0x3F


class Firmware(IntEnum):
    """ODrive firmware family; the value is the minor version."""

    V0_5 = 5
    V0_6 = 6

    @classmethod
    def parse(cls, text: str) -> Firmware:
        """``"0.6"``/``"0.6.10"`` -> V0_6, ``"0.5"``/``"0.5.6"`` -> V0_5."""
        parts = text.strip().lstrip("v").split(".")
        if len(parts) >= 2 and parts[0] == "0" and parts[1] in ("5", "6"):
            return cls(int(parts[1]))
        raise CodecError(f"firmware: expected '0.5' or '0.6', got {text!r}")

    @property
    def label(self) -> str:
        return f"0.{int(self)}"


class CmdId(IntEnum):
    """Command ids (5 bit) with the same message in firmware 0.5 and 0.6.

    Some ids name different messages in the two families (0x03: 0.5's Get_Motor_Error,
    0.6's Get_Error), so the ids of one family only are enums of their own,
    :class:`CmdId05` and :class:`CmdId06`: one name per value in each, so every id prints
    its own message's name. Sources: ODrive's CAN protocol pages, docs.odriverobotics.com
    ``v/0.5.6/can-protocol.html`` and ``v/latest/manual/can-protocol.html``.
    """

    HEARTBEAT = 0x01
    ESTOP = 0x02
    SET_AXIS_STATE = 0x07
    GET_ENCODER_ESTIMATES = 0x09
    SET_CONTROLLER_MODE = 0x0B
    SET_INPUT_VEL = 0x0D
    SET_INPUT_TORQUE = 0x0E
    SET_LIMITS = 0x0F
    GET_IQ = 0x14
    REBOOT = 0x16
    GET_BUS_VOLTAGE_CURRENT = 0x17
    CLEAR_ERRORS = 0x18


class CmdId05(IntEnum):
    """Command ids of firmware 0.5 only (see :class:`CmdId`)."""

    GET_MOTOR_ERROR = 0x03
    GET_ENCODER_ERROR = 0x04
    GET_SENSORLESS_ERROR = 0x05
    GET_CONTROLLER_ERROR = 0x1D


class CmdId06(IntEnum):
    """Command ids of firmware 0.6 only (see :class:`CmdId`)."""

    GET_VERSION = 0x00
    GET_ERROR = 0x03
    GET_TORQUES = 0x1C


#: a command id of either family
AnyCmdId = CmdId | CmdId05 | CmdId06


class AxisState(IntEnum):
    """Axis states (0.5 and 0.6; 0.6 adds 5 and 14)."""

    UNDEFINED = 0
    IDLE = 1
    STARTUP_SEQUENCE = 2
    FULL_CALIBRATION_SEQUENCE = 3
    MOTOR_CALIBRATION = 4
    SENSORLESS_CONTROL = 5
    ENCODER_INDEX_SEARCH = 6
    ENCODER_OFFSET_CALIBRATION = 7
    CLOSED_LOOP_CONTROL = 8
    LOCKIN_SPIN = 9
    ENCODER_DIR_FIND = 10
    HOMING = 11
    ENCODER_HALL_POLARITY_CALIBRATION = 12
    ENCODER_HALL_PHASE_CALIBRATION = 13
    ANTICOGGING_CALIBRATION = 14


class ControlMode(IntEnum):
    VOLTAGE_CONTROL = 0
    TORQUE_CONTROL = 1
    VELOCITY_CONTROL = 2
    POSITION_CONTROL = 3


class InputMode(IntEnum):
    INACTIVE = 0
    PASSTHROUGH = 1
    VEL_RAMP = 2
    POS_FILTER = 3
    MIX_CHANNELS = 4
    TRAP_TRAJ = 5
    TORQUE_RAMP = 6
    MIRROR = 7
    TUNING = 8


class AxisError05(IntFlag):
    """Axis error bits of firmware 0.5 (the heartbeat's Axis_Error), complete for 0.5.6."""

    INVALID_STATE = 0x00000001
    MOTOR_FAILED = 0x00000040
    SENSORLESS_ESTIMATOR_FAILED = 0x00000080
    ENCODER_FAILED = 0x00000100
    CONTROLLER_FAILED = 0x00000200
    WATCHDOG_TIMER_EXPIRED = 0x00000800
    MIN_ENDSTOP_PRESSED = 0x00001000
    MAX_ENDSTOP_PRESSED = 0x00002000
    ESTOP_REQUESTED = 0x00004000
    HOMING_WITHOUT_ENDSTOP = 0x00020000
    OVER_TEMP = 0x00040000
    UNKNOWN_POSITION = 0x00080000


class MotorError05(IntFlag):
    """Motor error bits of firmware 0.5.6 (Get_Motor_Error; heartbeat: motor flag)."""

    PHASE_RESISTANCE_OUT_OF_RANGE = 0x00000001
    PHASE_INDUCTANCE_OUT_OF_RANGE = 0x00000002
    DRV_FAULT = 0x00000008
    CONTROL_DEADLINE_MISSED = 0x00000010
    MODULATION_MAGNITUDE = 0x00000080
    CURRENT_SENSE_SATURATION = 0x00000400
    CURRENT_LIMIT_VIOLATION = 0x00001000
    MODULATION_IS_NAN = 0x00010000
    MOTOR_THERMISTOR_OVER_TEMP = 0x00020000
    FET_THERMISTOR_OVER_TEMP = 0x00040000
    TIMER_UPDATE_MISSED = 0x00080000
    CURRENT_MEASUREMENT_UNAVAILABLE = 0x00100000
    CONTROLLER_FAILED = 0x00200000
    I_BUS_OUT_OF_RANGE = 0x00400000
    BRAKE_RESISTOR_DISARMED = 0x00800000
    SYSTEM_LEVEL = 0x01000000
    BAD_TIMING = 0x02000000
    UNKNOWN_PHASE_ESTIMATE = 0x04000000
    UNKNOWN_PHASE_VEL = 0x08000000
    UNKNOWN_TORQUE = 0x10000000
    UNKNOWN_CURRENT_COMMAND = 0x20000000
    UNKNOWN_CURRENT_MEASUREMENT = 0x40000000
    UNKNOWN_VBUS_VOLTAGE = 0x80000000
    UNKNOWN_VOLTAGE_COMMAND = 0x100000000
    UNKNOWN_GAINS = 0x200000000
    CONTROLLER_INITIALIZING = 0x400000000
    UNBALANCED_PHASES = 0x800000000


class EncoderError05(IntFlag):
    """Encoder error bits of firmware 0.5.6 (Get_Encoder_Error; heartbeat: encoder flag)."""

    UNSTABLE_GAIN = 0x00000001
    CPR_POLEPAIRS_MISMATCH = 0x00000002
    NO_RESPONSE = 0x00000004
    UNSUPPORTED_ENCODER_MODE = 0x00000008
    ILLEGAL_HALL_STATE = 0x00000010
    INDEX_NOT_FOUND_YET = 0x00000020
    ABS_SPI_TIMEOUT = 0x00000040
    ABS_SPI_COM_FAIL = 0x00000080
    ABS_SPI_NOT_READY = 0x00000100
    HALL_NOT_CALIBRATED_YET = 0x00000200


class ControllerError05(IntFlag):
    """Controller error bits of firmware 0.5.6 (Get_Controller_Error; heartbeat: controller flag)."""

    OVERSPEED = 0x00000001
    INVALID_INPUT_MODE = 0x00000002
    UNSTABLE_GAIN = 0x00000004
    INVALID_MIRROR_AXIS = 0x00000008
    INVALID_LOAD_ENCODER = 0x00000010
    INVALID_ESTIMATE = 0x00000020
    INVALID_CIRCULAR_RANGE = 0x00000040
    SPINOUT_DETECTED = 0x00000080


class SensorlessError05(IntFlag):
    """Sensorless estimator error bits of firmware 0.5.6 (Get_Sensorless_Error)."""

    UNSTABLE_GAIN = 0x00000001
    UNKNOWN_CURRENT_MEASUREMENT = 0x00000002


class ProcedureResult06(IntEnum):
    """Why the last state request ended (0.6 heartbeat byte 5; 0.6.10 DBC value table)."""

    SUCCESS = 0
    BUSY = 1
    CANCELLED = 2
    DISARMED = 3
    NO_RESPONSE = 4
    POLE_PAIR_CPR_MISMATCH = 5
    PHASE_RESISTANCE_OUT_OF_RANGE = 6
    PHASE_INDUCTANCE_OUT_OF_RANGE = 7
    UNBALANCED_PHASES = 8
    INVALID_MOTOR_TYPE = 9
    ILLEGAL_HALL_STATE = 10
    TIMEOUT = 11
    HOMING_WITHOUT_ENDSTOP = 12
    INVALID_STATE = 13
    NOT_CALIBRATED = 14
    NOT_CONVERGING = 15


class ODriveError06(IntFlag):
    """Error bits of firmware 0.6 (the heartbeat's Axis_Error = active errors; also
    Get_Error's Active_Errors and Disarm_Reason), complete for the 0.6.10 DBC."""

    INITIALIZING = 0x00000001
    SYSTEM_LEVEL = 0x00000002
    TIMING_ERROR = 0x00000004
    MISSING_ESTIMATE = 0x00000008
    BAD_CONFIG = 0x00000010
    DRV_FAULT = 0x00000020
    MISSING_INPUT = 0x00000040
    DC_BUS_OVER_VOLTAGE = 0x00000100
    DC_BUS_UNDER_VOLTAGE = 0x00000200
    DC_BUS_OVER_CURRENT = 0x00000400
    DC_BUS_OVER_REGEN_CURRENT = 0x00000800
    CURRENT_LIMIT_VIOLATION = 0x00001000
    MOTOR_OVER_TEMP = 0x00002000
    INVERTER_OVER_TEMP = 0x00004000
    VELOCITY_LIMIT_VIOLATION = 0x00008000
    POSITION_LIMIT_VIOLATION = 0x00010000
    WATCHDOG_TIMER_EXPIRED = 0x01000000
    ESTOP_REQUESTED = 0x02000000
    SPINOUT_DETECTED = 0x04000000
    BRAKE_RESISTOR_DISARMED = 0x08000000
    THERMISTOR_DISCONNECTED = 0x10000000
    CALIBRATION_ERROR = 0x40000000


def _error_enum(firmware: Firmware) -> type[IntFlag]:
    return AxisError05 if firmware is Firmware.V0_5 else ODriveError06


def watchdog_bit(firmware: Firmware) -> int:
    """The Axis_Error bit a watchdog expiry sets."""
    return int(_error_enum(firmware)["WATCHDOG_TIMER_EXPIRED"])


def estop_bit(firmware: Firmware) -> int:
    """The Axis_Error bit an Estop sets."""
    return int(_error_enum(firmware)["ESTOP_REQUESTED"])


def describe_flags(code: int, enum: type[IntFlag]) -> str:
    """``0x01000800`` -> ``"0x01000800 (WATCHDOG_TIMER_EXPIRED|DC_BUS_OVER_REGEN_CURRENT)"``."""
    if code == 0:
        return "0x00000000 (none)"
    names = [m.name for m in enum if m.value & code and m.name]
    unknown = code & ~sum(m.value for m in enum)
    if unknown:
        names.append(f"unknown 0x{unknown:08X}")
    return f"0x{code:08X} ({'|'.join(names)})"


def describe_errors(code: int, firmware: Firmware) -> str:
    """The heartbeat's Axis_Error of ``firmware`` with its bit names."""
    return describe_flags(code, _error_enum(firmware))


def procedure_result_name(value: int) -> str:
    """``3`` -> ``"DISARMED"``; unknown values as ``"procedure result 99"``."""
    try:
        return ProcedureResult06(value).name
    except ValueError:
        return f"procedure result {value}"


def describe_heartbeat(hb: Heartbeat, firmware: Firmware) -> str:
    """Axis_Error with names plus what else the heartbeat says about a fault:
    on 0.6 a Procedure_Result other than SUCCESS, on 0.5 the motor/encoder/controller
    error flags (the codes themselves: Get_Motor_Error etc.)."""
    text = describe_errors(hb.axis_error, firmware)
    extra: list[str] = []
    if firmware is Firmware.V0_6:
        if hb.procedure_result != ProcedureResult06.SUCCESS:
            extra.append(f"last state request {procedure_result_name(hb.procedure_result)}")
    else:
        flags = (("motor", hb.motor_error_flag), ("encoder", hb.encoder_error_flag),
                 ("controller", hb.controller_error_flag))
        extra.extend(f"{name} error flag set" for name, on in flags if on)
    return f"{text}; {', '.join(extra)}" if extra else text


def _enum_or_int(enum: type[IntEnum]) -> Callable[[int], int]:
    def convert(value: int) -> int:
        try:
            return enum(value)
        except ValueError:
            return value

    return convert


# ---------------------------------------------------------------------------
# Messages as frozen dataclasses (SI units)


@dataclass(frozen=True, slots=True)
class Heartbeat:
    axis_error: int
    axis_state: int  # AxisState when known
    procedure_result: int = 0  # 0.6 only
    trajectory_done: bool = False
    motor_error_flag: bool = False  # 0.5 only
    encoder_error_flag: bool = False  # 0.5 only
    controller_error_flag: bool = False  # 0.5 only


@dataclass(frozen=True, slots=True)
class Estop:
    pass


@dataclass(frozen=True, slots=True)
class Version:
    """Get_Version reply (0.6 only): protocol, hardware and firmware version bytes."""

    protocol_version: int
    hw_major: int
    hw_minor: int
    hw_variant: int
    fw_major: int
    fw_minor: int
    fw_revision: int
    fw_unreleased: int

    @property
    def firmware_text(self) -> str:
        dev = "-dev" if self.fw_unreleased else ""
        return f"{self.fw_major}.{self.fw_minor}.{self.fw_revision}{dev}"

    @property
    def hardware_text(self) -> str:
        return f"{self.hw_major}.{self.hw_minor}.{self.hw_variant}"


@dataclass(frozen=True, slots=True)
class MotorErrorMsg:
    """Get_Motor_Error reply (0.5 only; the firmware sends the 64-bit code)."""

    motor_error: int


@dataclass(frozen=True, slots=True)
class EncoderErrorMsg:
    """Get_Encoder_Error reply (0.5 only)."""

    encoder_error: int


@dataclass(frozen=True, slots=True)
class SensorlessErrorMsg:
    """Get_Sensorless_Error reply (0.5 only)."""

    sensorless_error: int


@dataclass(frozen=True, slots=True)
class ControllerErrorMsg:
    """Get_Controller_Error reply (0.5 only)."""

    controller_error: int


@dataclass(frozen=True, slots=True)
class GetError:
    active_errors: int
    disarm_reason: int


@dataclass(frozen=True, slots=True)
class SetAxisState:
    requested_state: int


@dataclass(frozen=True, slots=True)
class EncoderEstimates:
    position_rad: float
    velocity_rad_s: float


@dataclass(frozen=True, slots=True)
class SetControllerMode:
    control_mode: int
    input_mode: int


@dataclass(frozen=True, slots=True)
class SetInputVel:
    velocity_rad_s: float
    torque_ff_nm: float = 0.0


@dataclass(frozen=True, slots=True)
class SetInputTorque:
    torque_nm: float


@dataclass(frozen=True, slots=True)
class SetLimits:
    velocity_limit_rad_s: float
    current_limit_a: float


@dataclass(frozen=True, slots=True)
class Iq:
    setpoint_a: float
    measured_a: float


@dataclass(frozen=True, slots=True)
class Reboot:
    action: int = 0  # 0.6 only (0 reboot, 1 save config, 2 erase config)


@dataclass(frozen=True, slots=True)
class BusVoltageCurrent:
    voltage_v: float
    current_a: float


@dataclass(frozen=True, slots=True)
class ClearErrors:
    identify: int = 0  # 0.6 only


@dataclass(frozen=True, slots=True)
class Torques:
    target_nm: float
    estimate_nm: float


@dataclass(frozen=True, slots=True)
class Request:
    """A ``Get_*`` request: RTR frame (or zero-length data frame) on the message's id."""

    cmd: AnyCmdId


ODriveMessage = (
    Heartbeat | Estop | GetError | Version | MotorErrorMsg | EncoderErrorMsg | SensorlessErrorMsg
    | ControllerErrorMsg | SetAxisState | EncoderEstimates | SetControllerMode
    | SetInputVel | SetInputTorque | SetLimits | Iq | Reboot | BusVoltageCurrent | ClearErrors
    | Torques | Request
)


# ---------------------------------------------------------------------------
# The table


@dataclass(frozen=True)
class Scalar:
    """One struct slot mapped to one dataclass field.

    ``scale``: SI units per wire unit (None = integer passed through ``convert``).
    """

    name: str
    scale: float | None = None
    convert: Callable[[int], Any] = int


@dataclass(frozen=True)
class Flags:
    """One struct byte holding boolean fields as bit masks."""

    bits: tuple[tuple[str, int], ...]


Slot = Scalar | Flags


@dataclass(frozen=True)
class MessageSpec:
    """Layout of one message for one firmware: the single source of encode and decode."""

    cmd: AnyCmdId
    name: str
    cls: type
    struct: struct.Struct
    slots: tuple[Slot, ...]
    #: frame length on the wire (the DBC's DLC); the payload is zero-padded to it
    dlc: int = 8
    #: each slot's scale to SI (1.0 for unscaled slots); derived, for the hot paths
    scales: tuple[float, ...] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        scales = tuple(float(getattr(s, "scale", None) or 1.0) for s in self.slots)
        object.__setattr__(self, "scales", scales)
        if not self.struct.size <= self.dlc <= 8:
            raise ValueError(f"{self.name}: payload {self.struct.size} B does not fit DLC {self.dlc}")

    @property
    def size(self) -> int:
        """Payload bytes that carry data (the frame's DLC may add zero padding)."""
        return self.struct.size

    def encode_data(self, msg: Any) -> bytes:
        """The frame's data: the payload, zero-padded to the DBC's DLC."""
        try:
            payload = self.struct.pack(*[_to_wire(slot, msg) for slot in self.slots])
        except (struct.error, TypeError, ValueError, OverflowError) as exc:
            raise CodecError(f"{self.name}: cannot encode {msg!r}: {exc}") from None
        return payload.ljust(self.dlc, b"\x00")

    def new_frame_data(self) -> bytearray:
        """A zeroed data buffer of the DBC's length, for :meth:`pack_into`."""
        return bytearray(self.dlc)

    def pack_into(self, buffer: bytearray, *values: float) -> None:
        """Hot path: pack SI scalar values (slot order) into ``buffer`` without a dataclass.

        CodecError if a value does not fit the wire type (e.g. beyond float32 range).
        """
        try:
            # map over the derived scales: no Python-level loop (the same divisions)
            self.struct.pack_into(buffer, 0, *map(truediv, values, self.scales))
        except (struct.error, OverflowError) as exc:
            raise CodecError(f"{self.name}: cannot encode {values!r}: {exc}") from None

    def unpack_si(self, data: bytes | bytearray) -> tuple[float, ...]:
        """Hot path: the scaled slots' SI values, in slot order, without a dataclass.

        Only for messages whose slots all carry a scale factor (e.g. encoder
        estimates, input torque); the scales are those of the one table.
        """
        if len(data) < self.struct.size:
            raise CodecError(
                f"{self.name} (0x{self.cmd:02X}) needs {self.size} data bytes, got {len(data)}"
            )
        return tuple(map(mul, self.struct.unpack_from(data, 0), self.scales))   # no generator frame

    def decode_data(self, data: bytes | bytearray) -> Any:
        if len(data) < self.size:
            raise CodecError(
                f"{self.name} (0x{self.cmd:02X}) needs {self.size} data bytes, got {len(data)}"
            )
        raw = self.struct.unpack_from(data, 0)
        kwargs: dict[str, Any] = {}
        for slot, value in zip(self.slots, raw):
            _from_wire(slot, value, kwargs)
        return self.cls(**kwargs)


def _to_wire(slot: Slot, msg: Any) -> int | float:
    if isinstance(slot, Flags):
        return sum(mask for name, mask in slot.bits if getattr(msg, name))
    value = getattr(msg, slot.name)
    return value / slot.scale if slot.scale is not None else int(value)


def _from_wire(slot: Slot, value: int | float, out: dict[str, Any]) -> None:
    if isinstance(slot, Flags):
        for name, mask in slot.bits:
            out[name] = bool(int(value) & mask)
    elif slot.scale is not None:
        out[slot.name] = value * slot.scale
    else:
        out[slot.name] = slot.convert(int(value))


def _spec(cmd: AnyCmdId, cls: type, fmt: str, *slots: Slot, dlc: int | None = None,
          name: str | None = None) -> MessageSpec:
    """One table entry; ``dlc`` defaults to the DBC's 8 (0 for an empty payload)."""
    packed = struct.Struct("<" + fmt)
    name = name or "_".join(part.capitalize() for part in cmd.name.split("_"))
    length = dlc if dlc is not None else (8 if packed.size else 0)
    return MessageSpec(cmd, name, cls, packed, tuple(slots), length)


_STATE = _enum_or_int(AxisState)

_COMMON: tuple[MessageSpec, ...] = (
    _spec(CmdId.ESTOP, Estop, ""),
    _spec(CmdId.SET_AXIS_STATE, SetAxisState, "I", Scalar("requested_state", convert=_STATE)),
    _spec(
        CmdId.GET_ENCODER_ESTIMATES, EncoderEstimates, "ff",
        Scalar("position_rad", TURN), Scalar("velocity_rad_s", TURN),
    ),
    _spec(
        CmdId.SET_CONTROLLER_MODE, SetControllerMode, "II",
        Scalar("control_mode", convert=_enum_or_int(ControlMode)),
        Scalar("input_mode", convert=_enum_or_int(InputMode)),
    ),
    _spec(
        CmdId.SET_INPUT_VEL, SetInputVel, "ff",
        Scalar("velocity_rad_s", TURN), Scalar("torque_ff_nm", 1.0),
    ),
    _spec(CmdId.SET_INPUT_TORQUE, SetInputTorque, "f", Scalar("torque_nm", 1.0)),
    _spec(
        CmdId.SET_LIMITS, SetLimits, "ff",
        Scalar("velocity_limit_rad_s", TURN), Scalar("current_limit_a", 1.0),
    ),
    _spec(CmdId.GET_IQ, Iq, "ff", Scalar("setpoint_a", 1.0), Scalar("measured_a", 1.0)),
    _spec(
        CmdId.GET_BUS_VOLTAGE_CURRENT, BusVoltageCurrent, "ff",
        Scalar("voltage_v", 1.0), Scalar("current_a", 1.0),
    ),
)

_ONLY_05: tuple[MessageSpec, ...] = (
    _spec(
        CmdId.HEARTBEAT, Heartbeat, "IBBBB",
        Scalar("axis_error"), Scalar("axis_state", convert=_STATE),
        Flags((("motor_error_flag", 0x01),)),
        Flags((("encoder_error_flag", 0x01),)),
        Flags((("controller_error_flag", 0x01), ("trajectory_done", 0x80))),
    ),
    _spec(CmdId.REBOOT, Reboot, ""),
    _spec(CmdId.CLEAR_ERRORS, ClearErrors, ""),
    _spec(CmdId05.GET_MOTOR_ERROR, MotorErrorMsg, "Q", Scalar("motor_error")),
    _spec(CmdId05.GET_ENCODER_ERROR, EncoderErrorMsg, "I", Scalar("encoder_error")),
    _spec(CmdId05.GET_SENSORLESS_ERROR, SensorlessErrorMsg, "I", Scalar("sensorless_error")),
    _spec(CmdId05.GET_CONTROLLER_ERROR, ControllerErrorMsg, "I", Scalar("controller_error")),
)

_ONLY_06: tuple[MessageSpec, ...] = (
    _spec(
        CmdId.HEARTBEAT, Heartbeat, "IBBBx",
        Scalar("axis_error"), Scalar("axis_state", convert=_STATE),
        Scalar("procedure_result"), Flags((("trajectory_done", 0x01),)),
    ),
    _spec(
        CmdId06.GET_VERSION, Version, "BBBBBBBB",
        *(Scalar(name) for name in ("protocol_version", "hw_major", "hw_minor", "hw_variant",
                                    "fw_major", "fw_minor", "fw_revision", "fw_unreleased")),
    ),
    _spec(CmdId06.GET_ERROR, GetError, "II", Scalar("active_errors"), Scalar("disarm_reason")),
    _spec(CmdId.REBOOT, Reboot, "B", Scalar("action"), dlc=1),
    _spec(CmdId.CLEAR_ERRORS, ClearErrors, "B", Scalar("identify"), dlc=1),
    _spec(CmdId06.GET_TORQUES, Torques, "ff", Scalar("target_nm", 1.0), Scalar("estimate_nm", 1.0)),
)


def _index(specs: tuple[MessageSpec, ...]) -> Mapping[int, MessageSpec]:
    return MappingProxyType({int(s.cmd): s for s in specs})


_TABLE: Mapping[Firmware, Mapping[int, MessageSpec]] = MappingProxyType({
    Firmware.V0_5: _index(_COMMON + _ONLY_05),
    Firmware.V0_6: _index(_COMMON + _ONLY_06),
})

_BY_CLASS: Mapping[Firmware, Mapping[type, MessageSpec]] = MappingProxyType({
    fw: MappingProxyType({s.cls: s for s in table.values()}) for fw, table in _TABLE.items()
})


# ---------------------------------------------------------------------------
# Public functions


def arbitration_id(node_id: int, cmd: int) -> int:
    """``node_id << 5 | cmd``; CodecError outside 0..63 / 0..31."""
    if not 0 <= node_id <= MAX_NODE_ID:
        raise CodecError(f"node_id: expected 0..63, got {node_id}")
    if not 0 <= cmd <= 0x1F:
        raise CodecError(f"cmd id: expected 0..31, got {cmd}")
    return (node_id << 5) | cmd


def split_id(arb_id: int) -> tuple[int, int]:
    """Arbitration id -> (node_id, cmd_id)."""
    if not 0 <= arb_id <= 0x7FF:
        raise CodecError(f"arbitration id: expected an 11-bit id, got 0x{arb_id:X}")
    return arb_id >> 5, arb_id & 0x1F


def specs(firmware: Firmware = Firmware.V0_6) -> tuple[MessageSpec, ...]:
    """Every message this codec implements for ``firmware``, by command id."""
    return tuple(spec for _, spec in sorted(_TABLE[firmware].items()))


def spec_for(cmd: int, firmware: Firmware = Firmware.V0_6) -> MessageSpec:
    """The table entry of ``cmd`` for ``firmware``; CodecError if unknown."""
    try:
        return _TABLE[firmware][cmd]
    except KeyError:
        raise CodecError(
            f"unknown ODrive command id 0x{cmd:02X} for firmware {Firmware(firmware).label}"
        ) from None


def _spec_of(msg: Any, firmware: Firmware) -> MessageSpec:
    try:
        return _BY_CLASS[firmware][type(msg)]
    except KeyError:
        raise CodecError(
            f"{type(msg).__name__} is not an ODrive message of firmware {Firmware(firmware).label}"
        ) from None


def encode_data(msg: Any, firmware: Firmware = Firmware.V0_6) -> bytes:
    """Payload bytes of ``msg`` (a data message, not a Request)."""
    return _spec_of(msg, firmware).encode_data(msg)


def encode(msg: Any, *, node_id: int, firmware: Firmware = Firmware.V0_6) -> can.Message:
    """A python-can frame carrying ``msg`` for ``node_id``; Request -> RTR frame."""
    if isinstance(msg, Request):
        spec = spec_for(msg.cmd, firmware)
        return can.Message(
            arbitration_id=arbitration_id(node_id, spec.cmd), is_extended_id=False,
            is_remote_frame=True, dlc=spec.dlc,
        )
    spec = _spec_of(msg, firmware)
    return can.Message(
        arbitration_id=arbitration_id(node_id, spec.cmd), is_extended_id=False,
        data=spec.encode_data(msg),
    )


def decode(
    arb_id: int, data: bytes | bytearray, firmware: Firmware = Firmware.V0_6, *,
    is_remote: bool = False,
) -> Any:
    """Frame payload -> message dataclass (SI units).

    An RTR frame, or a zero-length data frame on a message whose payload is not empty,
    decodes to :class:`Request`. A payload shorter than the table's layout raises
    CodecError; longer payloads (DBC DLC 8 padding) are accepted. CodecError is the
    only exception this raises, whatever ``arb_id`` and ``data`` are.
    """
    spec = spec_for(split_id(arb_id)[1], firmware)
    if is_remote or (len(data) == 0 and spec.size > 0):
        return Request(spec.cmd)
    if len(data) > 8:
        raise CodecError(f"{spec.name}: expected at most 8 data bytes, got {len(data)}")
    return spec.decode_data(data)


def decode_message(msg: can.Message, firmware: Firmware = Firmware.V0_6) -> Any:
    """:func:`decode` of a python-can frame (extended ids are not ODrive CAN Simple)."""
    if msg.is_extended_id:
        raise CodecError(f"expected an 11-bit ODrive id, got extended id 0x{msg.arbitration_id:X}")
    return decode(msg.arbitration_id, msg.data, firmware, is_remote=msg.is_remote_frame)


def message_fields(cls: type) -> tuple[str, ...]:
    """Field names of a message dataclass (for tests and tools)."""
    return tuple(f.name for f in fields(cls))
