"""Pure codec of CiA 402 cyclic synchronous torque (CST) over CANopen: bytes and numbers,
no I/O, no canopen.

Facts (CiA 301 / CiA 402; drivers/README.md's CiA 402 section; canopen's
``profiles/p402.py`` tables agree, ``tests/drives/test_cia402_codec.py`` checks that):

- COB-IDs: NMT 0x000 ``[command, node]``; SYNC 0x080; EMCY 0x080 + node; TPDO1..4
  0x180/0x280/0x380/0x480 + node; RPDO1..4 0x200/0x300/0x400/0x500 + node; SDO response
  0x580 + node, request 0x600 + node; heartbeat 0x700 + node (one byte: NMT state).
- Controlword 0x6040: 0x06 shutdown, 0x07 switch on, 0x0F enable operation, 0x00 disable
  voltage, 0x02 quick stop, bit 7 (0x80) fault reset on its rising edge.
- Statusword 0x6041 -> power state by (mask, value) (:data:`STATUSWORD_TABLE`).
- Target torque 0x6071 and torque actual 0x6077: I16 per mille of the rated torque 0x6076;
  a drive rounds to the nearest count and saturates at the I16 range.
- PDO layouts: the mapped objects packed little-endian, in mapping order, without gaps;
  a PDO carries at most 64 bits. The struct format of a layout comes from each object's
  CiA 301 data type (:data:`DATA_TYPE_FORMATS`), the type canopen's object dictionary
  reports for it (``ODVariable.data_type``).
"""

from __future__ import annotations

import math
import struct
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from enum import IntEnum
from fractions import Fraction
from types import MappingProxyType

from dobhil.errors import CodecError

__all__ = [
    "CST_MODE",
    "CST_SUPPORTED_BIT",
    "DATA_TYPE_FORMATS",
    "EMCY_LAYOUT",
    "EmcyCode",
    "ErrorRegister",
    "FAULT_RESET_BIT",
    "HOST_HEARTBEATS_PER_CONSUMER_TIME",
    "host_heartbeat_interval",
    "MAX_PDO_BITS",
    "RATED_TORQUE_TOLERANCE",
    "RATED_TORQUE_UNITS",
    "RPDO_CST",
    "RPDO_CST_STRUCT",
    "STATUSWORD_TABLE",
    "TPDO_MOTION",
    "TPDO_STATUS",
    "TPDO_STATUS_STRUCT",
    "TPDO_MOTION_STRUCT",
    "Cob",
    "Controlword",
    "DataType",
    "Emcy",
    "Mapped",
    "NmtCommand",
    "NmtState",
    "PowerState",
    "UNIT_OBJECTS",
    "UnitObject",
    "UnitScale",
    "VelocityUnit",
    "decode_emcy",
    "encode_rpdo",
    "fault_reset_edge",
    "interpolation_period",
    "is_fault",
    "layout_bits",
    "layout_struct",
    "next_controlword",
    "per_mille",
    "power_state",
    "torque_from_per_mille",
]

#: 0x6060/0x6061 value of cyclic synchronous torque mode
CST_MODE = 10
#: bit of 0x6502 (supported drive modes) that says CST is supported
CST_SUPPORTED_BIT = 9
#: a CAN 2.0 PDO carries at most 8 bytes
MAX_PDO_BITS = 64
#: statusword bit 3: fault (also set in fault reaction active)
STATUSWORD_FAULT_BIT = 0x0008
#: controlword bit 7: fault reset, acts on its rising edge
FAULT_RESET_BIT = 0x0080

_I16 = (-(1 << 15), (1 << 15) - 1)


class Cob(IntEnum):
    """Function codes of the pre-defined connection set (add the node id where it has one).

    SYNC and EMCY share function code 0001b (CiA 301, pre-defined connection set): SYNC is
    COB-ID 0x080 itself, a node's EMCY 0x080 + node id (1..127). EMCY is :meth:`emcy`, not a
    member: a member of the same value would be an alias of SYNC and print as SYNC."""

    NMT = 0x000
    SYNC = 0x080
    TPDO1 = 0x180
    RPDO1 = 0x200
    TPDO2 = 0x280
    RPDO2 = 0x300
    TPDO3 = 0x380
    RPDO3 = 0x400
    TPDO4 = 0x480
    RPDO4 = 0x500
    SDO_TX = 0x580  # server -> client: the node's answers
    SDO_RX = 0x600  # client -> server: our requests
    HEARTBEAT = 0x700

    @staticmethod
    def emcy(node_id: int) -> int:
        """COB-ID of the EMCY of ``node_id`` (1..127) in the pre-defined set."""
        return 0x080 + node_id

    @staticmethod
    def tpdo(number: int, node_id: int) -> int:
        """COB-ID of TPDO ``number`` (1..4) of ``node_id`` in the pre-defined set."""
        return 0x180 + 0x100 * (number - 1) + node_id

    @staticmethod
    def rpdo(number: int, node_id: int) -> int:
        """COB-ID of RPDO ``number`` (1..4) of ``node_id`` in the pre-defined set."""
        return 0x200 + 0x100 * (number - 1) + node_id


class NmtCommand(IntEnum):
    """NMT command specifier (first byte of COB-ID 0)."""

    START = 0x01
    STOP = 0x02
    PRE_OPERATIONAL = 0x80
    RESET_NODE = 0x81
    RESET_COMMUNICATION = 0x82


class NmtState(IntEnum):
    """The heartbeat's state byte (bit 7, the guarding toggle, masked off)."""

    BOOT_UP = 0x00
    STOPPED = 0x04
    OPERATIONAL = 0x05
    PRE_OPERATIONAL = 0x7F

    @classmethod
    def text(cls, value: int) -> str:
        try:
            return cls(value).name.lower().replace("_", "-")
        except ValueError:
            return f"NMT state 0x{value:02X}"


class Controlword(IntEnum):
    """Device control commands written to 0x6040 (CiA 402 table of commands)."""

    DISABLE_VOLTAGE = 0x0000
    QUICK_STOP = 0x0002
    SHUTDOWN = 0x0006
    SWITCH_ON = 0x0007
    ENABLE_OPERATION = 0x000F
    FAULT_RESET = 0x0080


class PowerState(IntEnum):
    """States of the CiA 402 power state machine; UNKNOWN: a statusword matching none."""

    NOT_READY_TO_SWITCH_ON = 0
    SWITCH_ON_DISABLED = 1
    READY_TO_SWITCH_ON = 2
    SWITCHED_ON = 3
    OPERATION_ENABLED = 4
    QUICK_STOP_ACTIVE = 5
    FAULT_REACTION_ACTIVE = 6
    FAULT = 7
    UNKNOWN = 8

    @property
    def text(self) -> str:
        """``"operation enabled"``: the state as messages name it."""
        return self.name.lower().replace("_", " ")


#: statusword (mask, value) -> power state (CiA 402; the same table as canopen's
#: ``State402.SW_MASK``); the rows are mutually exclusive
STATUSWORD_TABLE: Mapping[PowerState, tuple[int, int]] = MappingProxyType({
    PowerState.NOT_READY_TO_SWITCH_ON: (0x4F, 0x00),
    PowerState.SWITCH_ON_DISABLED: (0x4F, 0x40),
    PowerState.READY_TO_SWITCH_ON: (0x6F, 0x21),
    PowerState.SWITCHED_ON: (0x6F, 0x23),
    PowerState.OPERATION_ENABLED: (0x6F, 0x27),
    PowerState.QUICK_STOP_ACTIVE: (0x6F, 0x07),
    PowerState.FAULT_REACTION_ACTIVE: (0x4F, 0x0F),
    PowerState.FAULT: (0x4F, 0x08),
})

# the decoder runs once per cycle: one dict lookup instead of eight tests. Every
# statusword's low 7 bits decide its state, so the table has 128 entries.
_STATE_OF_LOW_BITS: tuple[PowerState, ...] = tuple(
    next((state for state, (mask, value) in STATUSWORD_TABLE.items() if low & mask == value),
         PowerState.UNKNOWN)
    for low in range(0x80)
)


def power_state(statusword: int) -> PowerState:
    """The power state a statusword reports (UNKNOWN when it matches no row)."""
    return _STATE_OF_LOW_BITS[statusword & 0x7F]


#: the next command on the way to Operation enabled, from each state (transitions 2, 3,
#: 4 of CiA 402; from Quick stop active through Switch on disabled -- transition 12 --
#: as canopen's ``State402.next_state_indirect`` goes). None: nothing to command (the
#: drive moves on by itself, or a fault needs a reset the caller decides on).
_NEXT: Mapping[PowerState, Controlword | None] = MappingProxyType({
    PowerState.NOT_READY_TO_SWITCH_ON: None,  # transition 1 is automatic
    PowerState.SWITCH_ON_DISABLED: Controlword.SHUTDOWN,
    PowerState.READY_TO_SWITCH_ON: Controlword.SWITCH_ON,
    PowerState.SWITCHED_ON: Controlword.ENABLE_OPERATION,
    PowerState.OPERATION_ENABLED: Controlword.ENABLE_OPERATION,  # hold it
    PowerState.QUICK_STOP_ACTIVE: Controlword.DISABLE_VOLTAGE,
    PowerState.FAULT_REACTION_ACTIVE: None,  # transition 14 is automatic
    PowerState.FAULT: None,
    PowerState.UNKNOWN: None,
})


def next_controlword(state: PowerState) -> Controlword | None:
    """The controlword that moves ``state`` one step toward Operation enabled."""
    return _NEXT[state]


# -- torque ---------------------------------------------------------------------


def per_mille(tau_nm: float, rated_nm: float) -> int:
    """Torque [Nm] as the I16 per mille of the rated torque 0x6071 carries: rounded to the
    nearest count (half away from zero, symmetric for both signs), saturated at the I16
    range as a drive saturates its setpoint (never wrapped)."""
    x = tau_nm * 1000.0 / rated_nm
    if not x < _I16[1]:  # also NaN: the base refuses non-finite torque before this
        return _I16[1] if x == x else 0
    if x <= _I16[0]:
        return _I16[0]
    return int(math.copysign(math.floor(abs(x) + 0.5), x))


def torque_from_per_mille(value: int, rated_nm: float) -> float:
    """A 0x6071/0x6077 per mille value in Nm."""
    return value * rated_nm / 1000.0


# -- units ----------------------------------------------------------------------


#: newton-metres per unit of 0x6076 (mNm per CiA 402; uNm on a maxon EPOS4)
RATED_TORQUE_UNITS: Mapping[str, float] = MappingProxyType({"mNm": 1e-3, "uNm": 1e-6})
#: rated torque of the node within this fraction of the profile's, else refused (start-up, preflight)
RATED_TORQUE_TOLERANCE = 0.01
#: the host sends its heartbeat this many times per consumer time of the node (0x1016)
HOST_HEARTBEATS_PER_CONSUMER_TIME = 4


def host_heartbeat_interval(consumer: float, sync_period: float) -> float:
    """[s] the host's heartbeat period for a node's consumer time ``consumer`` (0x1016):
    :data:`HOST_HEARTBEATS_PER_CONSUMER_TIME` per consumer time at the least, as a whole
    number (>= 1) of SYNC periods ``sync_period`` (the SYNC's clock is the one a native
    periodic send surely keeps, and the lockstep bus takes whole steps only)."""
    return max(1, int(consumer / HOST_HEARTBEATS_PER_CONSUMER_TIME / sync_period)) * sync_period


class VelocityUnit(IntEnum):
    """Unit of 0x606C velocity actual on a drive (the profile's ``velocity_unit``)."""

    RPM = 0
    INCREMENTS_PER_S = 1
    MILLI_RPM = 2

    @classmethod
    def parse(cls, text: str) -> VelocityUnit:
        return {"rpm": cls.RPM, "increments_per_s": cls.INCREMENTS_PER_S,
                "milli_rpm": cls.MILLI_RPM}[text]


@dataclass(frozen=True, slots=True)
class UnitScale:
    """rad and rad/s at the output (after the gear) per count of 0x6064 and 0x606C."""

    rad_per_increment: float
    rad_s_per_velocity_count: float

    @classmethod
    def of(cls, *, position_per_rev: float, velocity_unit: str, gear_ratio: float) -> UnitScale:
        """From a profile's ``cia402`` section: position rad = inc / position_per_rev * 2 pi
        / gear_ratio; velocity per ``velocity_unit`` (motor side), / gear_ratio."""
        rad_per_inc = 2.0 * math.pi / position_per_rev / gear_ratio
        per_count = {
            VelocityUnit.RPM: 2.0 * math.pi / 60.0 / gear_ratio,
            VelocityUnit.INCREMENTS_PER_S: rad_per_inc,
            VelocityUnit.MILLI_RPM: 2.0 * math.pi / 60.0 / 1000.0 / gear_ratio,
        }[VelocityUnit.parse(velocity_unit)]
        return cls(rad_per_inc, per_count)


@dataclass(frozen=True)
class UnitObject:
    """A CiA 402 ratio object the position and velocity scale depend on: sub 1 per sub 2
    (both U32), which the profile's ``cia402.<key>`` states as one number."""

    index: int
    name: str
    numerator: str      # what sub 1 counts
    denominator: str    # what sub 2 counts
    key: str            # the profile's cia402 key that is sub 1 / sub 2

    def stated(self, numerator: int, denominator: int) -> str:
        """``0x608F (position encoder resolution) = 4096 encoder increments / 1 motor revolutions``"""
        return (f"0x{self.index:04X} ({self.name}) = {numerator} {self.numerator} / "
                f"{denominator} {self.denominator}")

    def agrees(self, numerator: int, denominator: int, profile_value: float) -> bool | None:
        """Whether sub 1 / sub 2 is the profile's number (None: sub 2 is 0, no ratio stated).
        Both are ratios of integers: only float rounding may differ."""
        if denominator == 0:
            return None
        return math.isclose(numerator / denominator, profile_value, rel_tol=UNIT_RATIO_TOLERANCE)

    @staticmethod
    def ratio_of(value: float) -> tuple[int, int]:
        """The (sub 1, sub 2) a node states for the profile's number: the nearest fraction
        with a U32 denominator (4096 -> (4096, 1), 3.7 -> (37, 10))."""
        fraction = Fraction(value).limit_denominator(_U32_MAX)
        return fraction.numerator, fraction.denominator


_U32_MAX = 0xFFFF_FFFF
#: relative difference allowed between sub 1 / sub 2 and the profile's number (float rounding)
UNIT_RATIO_TOLERANCE = 1e-9
#: 0x608F position encoder resolution: encoder increments (of 0x6064) per MOTOR revolution
#: = ``position_per_rev``; 0x6091 gear ratio: motor revolutions per SHAFT (output)
#: revolution = ``gear_ratio`` (CiA 402 names the subs so)
UNIT_OBJECTS = (
    UnitObject(0x608F, "position encoder resolution", "encoder increments", "motor revolutions",
               "position_per_rev"),
    UnitObject(0x6091, "gear ratio", "motor revolutions", "shaft revolutions", "gear_ratio"),
)


# -- PDO layouts ----------------------------------------------------------------


class DataType(IntEnum):
    """CiA 301 data type indices (the numbers canopen's ``objectdictionary`` uses)."""

    BOOLEAN = 0x01
    INTEGER8 = 0x02
    INTEGER16 = 0x03
    INTEGER32 = 0x04
    UNSIGNED8 = 0x05
    UNSIGNED16 = 0x06
    UNSIGNED32 = 0x07
    REAL32 = 0x08
    INTEGER64 = 0x15
    UNSIGNED64 = 0x1B


#: struct character of each byte-aligned data type a PDO may map
DATA_TYPE_FORMATS: Mapping[int, str] = MappingProxyType({
    DataType.BOOLEAN: "?", DataType.INTEGER8: "b", DataType.INTEGER16: "h",
    DataType.INTEGER32: "i", DataType.UNSIGNED8: "B", DataType.UNSIGNED16: "H",
    DataType.UNSIGNED32: "I", DataType.REAL32: "f", DataType.INTEGER64: "q",
    DataType.UNSIGNED64: "Q",
})


@dataclass(frozen=True, slots=True)
class Mapped:
    """One object mapped into a PDO: index, sub-index, CiA 301 data type, and a name."""

    index: int
    subindex: int
    data_type: int
    name: str

    @property
    def bits(self) -> int:
        return struct.calcsize("<" + _format_of(self.data_type)) * 8

    @property
    def label(self) -> str:
        """``0x6071:00 (target torque)``."""
        return f"0x{self.index:04X}:{self.subindex:02X} ({self.name})"


#: RPDO (host -> drive): controlword, target torque
RPDO_CST: tuple[Mapped, ...] = (
    Mapped(0x6040, 0, DataType.UNSIGNED16, "controlword"),
    Mapped(0x6071, 0, DataType.INTEGER16, "target torque"),
)
#: first TPDO (drive -> host): statusword, position actual, torque actual (8 bytes)
TPDO_STATUS: tuple[Mapped, ...] = (
    Mapped(0x6041, 0, DataType.UNSIGNED16, "statusword"),
    Mapped(0x6064, 0, DataType.INTEGER32, "position actual value"),
    Mapped(0x6077, 0, DataType.INTEGER16, "torque actual value"),
)
#: second TPDO: velocity actual, modes of operation display (5 bytes); with the
#: velocity in the first one it would need 10 bytes, more than a PDO carries
TPDO_MOTION: tuple[Mapped, ...] = (
    Mapped(0x606C, 0, DataType.INTEGER32, "velocity actual value"),
    Mapped(0x6061, 0, DataType.INTEGER8, "modes of operation display"),
)


def _format_of(data_type: int) -> str:
    try:
        return DATA_TYPE_FORMATS[data_type]
    except KeyError:
        raise CodecError(f"PDO mapping: data type 0x{data_type:02X} is not a byte-aligned number "
                         f"(allowed: {', '.join(DataType(t).name for t in DATA_TYPE_FORMATS)})") from None


def layout_bits(data_types: Sequence[int]) -> int:
    """Bits a PDO with objects of these data types needs."""
    return sum(struct.calcsize("<" + _format_of(t)) * 8 for t in data_types)


def layout_struct(data_types: Sequence[int]) -> struct.Struct:
    """The little-endian struct of a PDO mapping these data types in order (CodecError
    beyond 64 bits: a PDO carries 8 bytes)."""
    bits = layout_bits(data_types)
    if bits > MAX_PDO_BITS:
        raise CodecError(f"PDO mapping needs {bits} bits, a PDO carries {MAX_PDO_BITS}")
    return struct.Struct("<" + "".join(_format_of(t) for t in data_types))


# -- EMCY -----------------------------------------------------------------------

#: EMCY payload (CiA 301): error code U16, error register U8, 5 manufacturer bytes
EMCY_LAYOUT = struct.Struct("<HB5s")


class EmcyCode(IntEnum):
    """CiA 301 / CiA 402 emergency error codes dobhil names (the drive's watch of the
    host's heartbeat, the emulated node's faults)."""

    NO_ERROR = 0x0000
    COMMUNICATION = 0x8100      # NMT operational left while enabled (0x6007 "fault")
    HEARTBEAT = 0x8130          # life guard / heartbeat consumer error
    PDO_LENGTH = 0x8210         # PDO not processed due to length error
    EXCESS_TORQUE = 0x8311


class ErrorRegister(IntEnum):
    """0x1001 bits (CiA 301)."""

    GENERIC = 0x01
    COMMUNICATION = 0x10
    PROFILE = 0x20


@dataclass(frozen=True, slots=True)
class Emcy:
    code: int  # 0x0000: error reset / no error
    register: int  # 0x1001 error register at the time


def decode_emcy(data: bytes | bytearray) -> Emcy:
    """An EMCY frame's code and error register (CodecError when shorter than 3 bytes;
    the 5 manufacturer bytes may be missing on some drives)."""
    if len(data) < 3:
        raise CodecError(f"EMCY: expected at least 3 bytes, got {len(data)}")
    code, register = struct.unpack_from("<HB", data)
    return Emcy(code, register)


def fault_reset_edge(previous: int) -> tuple[int, ...]:
    """Controlwords that give bit 7 one rising edge after ``previous`` (the last one
    sent): a drive resets a fault on the edge, not on the level, so after a controlword
    that already had bit 7 set it first needs one without."""
    if previous & FAULT_RESET_BIT:
        return (previous & ~FAULT_RESET_BIT & 0xFFFF, Controlword.FAULT_RESET)
    return (Controlword.FAULT_RESET,)


def is_fault(statusword: int) -> bool:
    """Statusword bit 3: Fault or Fault reaction active."""
    return bool(statusword & STATUSWORD_FAULT_BIT)


#: the RPDO layout of :data:`RPDO_CST` (what a drive whose EDS types the objects as the
#: standard does receives); the drive derives its own from the node's object dictionary
RPDO_CST_STRUCT = layout_struct([m.data_type for m in RPDO_CST])
TPDO_STATUS_STRUCT = layout_struct([m.data_type for m in TPDO_STATUS])
TPDO_MOTION_STRUCT = layout_struct([m.data_type for m in TPDO_MOTION])


def interpolation_period(period: float) -> tuple[int, int]:
    """0x60C2's (value U8, index I8) for ``period`` s = value * 10 ** index, the largest
    unit that gives a whole value up to 255 (1 ms: (1, -3); 2.5 ms: (25, -4)); CodecError
    when none does (a period not a whole number of microseconds, or above 255 s)."""
    for exponent in range(0, -7, -1):
        value = round(period / 10.0 ** exponent)
        if 1 <= value <= 0xFF and math.isclose(value * 10.0 ** exponent, period, rel_tol=1e-9):
            return value, exponent
    raise CodecError(f"interpolation time period 0x60C2: {period!r} s is no whole value up to 255 "
                     "of a power-of-ten second unit")


def encode_rpdo(controlword: int, torque_per_mille: int) -> bytes:
    """The 4 data bytes of the CST RPDO."""
    return RPDO_CST_STRUCT.pack(controlword, torque_per_mille)

