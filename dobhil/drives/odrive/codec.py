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
- Clear_Errors (0x18) and Reboot (0x16): DLC 0 on 0.5, one byte on 0.6.
- Get_Error (0x03) and Get_Torques (0x1C) exist on 0.6 only (0.5 uses those ids for
  Get_Motor_Error and Get_ADC_Voltage, which this codec does not implement).
- Watchdog error bit: 0x800 AxisError.WATCHDOG_TIMER_EXPIRED on 0.5,
  0x01000000 ODriveError.WATCHDOG_TIMER_EXPIRED on 0.6.

One table (:data:`_TABLE`) of messages drives both :func:`encode` and :func:`decode`;
each scale factor is written once.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, fields
from enum import IntEnum, IntFlag
from types import MappingProxyType
from typing import Any

import can

from dobhil.errors import CodecError

__all__ = [
    "AxisError05",
    "AxisState",
    "BusVoltageCurrent",
    "ClearErrors",
    "CmdId",
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
    """Command ids (5 bit) of the messages this codec implements."""

    HEARTBEAT = 0x01
    ESTOP = 0x02
    GET_ERROR = 0x03  # 0.6 only
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
    GET_TORQUES = 0x1C  # 0.6 only


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
    """Axis error bits of firmware 0.5 (the heartbeat's Axis_Error)."""

    INVALID_STATE = 0x00000001
    WATCHDOG_TIMER_EXPIRED = 0x00000800
    MIN_ENDSTOP_PRESSED = 0x00001000
    MAX_ENDSTOP_PRESSED = 0x00002000
    ESTOP_REQUESTED = 0x00004000
    HOMING_WITHOUT_ENDSTOP = 0x00020000
    OVER_TEMP = 0x00040000
    UNKNOWN_POSITION = 0x00080000


class ODriveError06(IntFlag):
    """Error bits of firmware 0.6 (the heartbeat's Axis_Error = active errors)."""

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


def describe_errors(code: int, firmware: Firmware) -> str:
    """``0x01000800`` -> ``"0x01000800 (WATCHDOG_TIMER_EXPIRED|DC_BUS_OVER_REGEN_CURRENT)"``."""
    if code == 0:
        return "0x00000000 (none)"
    enum = _error_enum(firmware)
    names = [m.name for m in enum if m.value & code and m.name]
    unknown = code & ~sum(m.value for m in enum)
    if unknown:
        names.append(f"unknown 0x{unknown:08X}")
    return f"0x{code:08X} ({'|'.join(names)})"


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

    cmd: CmdId


ODriveMessage = (
    Heartbeat | Estop | GetError | SetAxisState | EncoderEstimates | SetControllerMode
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

    cmd: CmdId
    name: str
    cls: type
    struct: struct.Struct
    slots: tuple[Slot, ...]
    #: each slot's scale to SI (1.0 for unscaled slots); derived, for the hot paths
    scales: tuple[float, ...] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        scales = tuple(float(getattr(s, "scale", None) or 1.0) for s in self.slots)
        object.__setattr__(self, "scales", scales)

    @property
    def size(self) -> int:
        return self.struct.size

    def encode_data(self, msg: Any) -> bytes:
        try:
            return self.struct.pack(*[_to_wire(slot, msg) for slot in self.slots])
        except (struct.error, TypeError, ValueError) as exc:
            raise CodecError(f"{self.name}: cannot encode {msg!r}: {exc}") from None

    def pack_into(self, buffer: bytearray, *values: float) -> None:
        """Hot path: pack SI scalar values (slot order) into ``buffer`` without a dataclass."""
        self.struct.pack_into(buffer, 0, *[v / s.scale for v, s in zip(values, self.slots)])  # type: ignore[union-attr,operator]

    def unpack_si(self, data: bytes | bytearray) -> tuple[float, ...]:
        """Hot path: the scaled slots' SI values, in slot order, without a dataclass.

        Only for messages whose slots all carry a scale factor (e.g. encoder
        estimates, input torque); the scales are those of the one table.
        """
        if len(data) < self.struct.size:
            raise CodecError(
                f"{self.name} (0x{self.cmd:02X}) needs {self.size} data bytes, got {len(data)}"
            )
        return tuple(v * s for v, s in zip(self.struct.unpack_from(data, 0), self.scales))

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


def _spec(cmd: CmdId, cls: type, fmt: str, *slots: Slot) -> MessageSpec:
    name = "_".join(part.capitalize() for part in cmd.name.split("_"))
    return MessageSpec(cmd, name, cls, struct.Struct("<" + fmt), tuple(slots))


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
)

_ONLY_06: tuple[MessageSpec, ...] = (
    _spec(
        CmdId.HEARTBEAT, Heartbeat, "IBBBx",
        Scalar("axis_error"), Scalar("axis_state", convert=_STATE),
        Scalar("procedure_result"), Flags((("trajectory_done", 0x01),)),
    ),
    _spec(CmdId.GET_ERROR, GetError, "II", Scalar("active_errors"), Scalar("disarm_reason")),
    _spec(CmdId.REBOOT, Reboot, "B", Scalar("action")),
    _spec(CmdId.CLEAR_ERRORS, ClearErrors, "B", Scalar("identify")),
    _spec(CmdId.GET_TORQUES, Torques, "ff", Scalar("target_nm", 1.0), Scalar("estimate_nm", 1.0)),
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
            is_remote_frame=True, dlc=0,
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
    CodecError; longer payloads (DBC DLC 8 padding) are accepted.
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
