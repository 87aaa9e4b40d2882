"""The moteus multiplex register protocol over CAN FD: pure functions of bytes.

Facts from mjbots' public documentation (``docs/protocol/can.md``, ``docs/protocol/
registers.md`` of github.com/mjbots/moteus) and the official Python library (PyPI
``moteus`` 1.1.1: ``moteus/multiplex.py``, ``moteus/protocol.py``, ``moteus/transport.py``):

- **Arbitration id** (bit 0 = least significant): bits 0-6 the destination, bits 8-14 the
  source, bit 15 "reply requested", bits 16-28 the ``can.prefix`` (default 0). The host is
  source 0 by default; a controller replies on ``node << 8 | source``, bit 15 clear.
  The library marks a frame extended when its id is above 0x7ff; the firmware does the same
  for its replies.
- **Payload**: a sequence of subframes. Write/read/reply opcodes are ``base | type << 2 |
  count`` (base 0x00 write, 0x10 read, 0x20 reply; type 0 int8, 1 int16, 2 int32, 3 float;
  a count of 1-3 in the low two bits, else 0 there and a varuint count after the opcode),
  then the start register as a varuint, then the values (little-endian) for writes and
  replies. 0x30/0x31 write/read error: register, error code (varuints). 0x50: no
  operation, the padding up to the next CAN FD length.
- **Integer resolutions** (value = code x step; the step per quantity is
  :data:`SCALINGS`); the most negative code means NaN; the firmware and the library both
  saturate at +-max and convert by C's / Python's integer conversion, which **truncates
  toward zero** (``static_cast<T>`` in ``fw/moteus_controller.cc`` ``ScaleSaturate``,
  ``int()`` in ``multiplex.py`` ``saturate``).

Positions are revolutions of the output shaft, velocities revolutions per second, torques
N m at the output: :mod:`dobhil.drives.moteus.drive` converts to radians.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from enum import IntEnum
from types import MappingProxyType

from dobhil.errors import CodecError

__all__ = [
    "BROADCAST",
    "FD_LENGTHS",
    "MAX_NODE_ID",
    "NAN_CODES",
    "REGISTER_SCALING",
    "REPLY_REQUESTED",
    "SCALINGS",
    "Fault",
    "Mode",
    "Opcode",
    "Parser",
    "Quantity",
    "Register",
    "Resolution",
    "Scaling",
    "Subframe",
    "arbitration_id",
    "decode_value",
    "encode_value",
    "group_registers",
    "pad",
    "parse",
    "read_subframe",
    "read_varuint",
    "reply_subframe",
    "split_id",
    "varuint",
    "write_subframe",
]

#: bit 15 of the arbitration id: the sender asks for a reply
REPLY_REQUESTED = 0x8000
#: destination 0x7f addresses every controller
BROADCAST = 0x7F
#: the largest controller id (7 bits; 0x7f is the broadcast)
MAX_NODE_ID = 0x7E
#: CAN FD payload lengths (ISO 11898-1: DLC 9-15 mean 12, 16, 20, 24, 32, 48, 64 bytes)
FD_LENGTHS = (0, 1, 2, 3, 4, 5, 6, 7, 8, 12, 16, 20, 24, 32, 48, 64)
_MAX_PAYLOAD = 64
_VARUINT_BYTES = 5


class Resolution(IntEnum):
    """A register value's type on the wire (the opcode's type bits)."""

    INT8 = 0
    INT16 = 1
    INT32 = 2
    F32 = 3


class Opcode(IntEnum):
    """Subframe opcodes (the register ones are a base plus type and count bits)."""

    WRITE = 0x00
    READ = 0x10
    REPLY = 0x20
    WRITE_ERROR = 0x30
    READ_ERROR = 0x31
    NOP = 0x50


class Register(IntEnum):
    """The registers dobhil reads or writes (``docs/protocol/registers.md``)."""

    MODE = 0x000
    POSITION = 0x001
    VELOCITY = 0x002
    TORQUE = 0x003
    Q_CURRENT = 0x004
    D_CURRENT = 0x005
    ABS_POSITION = 0x006
    POWER = 0x007
    MOTOR_TEMPERATURE = 0x00A
    TRAJECTORY_COMPLETE = 0x00B
    HOME_STATE = 0x00C
    VOLTAGE = 0x00D
    TEMPERATURE = 0x00E
    FAULT = 0x00F
    COMMAND_POSITION = 0x020
    COMMAND_VELOCITY = 0x021
    COMMAND_FEEDFORWARD_TORQUE = 0x022
    COMMAND_KP_SCALE = 0x023
    COMMAND_KD_SCALE = 0x024
    COMMAND_MAX_TORQUE = 0x025
    COMMAND_STOP_POSITION = 0x026
    COMMAND_TIMEOUT = 0x027
    COMMAND_VELOCITY_LIMIT = 0x028
    COMMAND_ACCEL_LIMIT = 0x029
    COMMAND_FIXED_VOLTAGE_OVERRIDE = 0x02A
    COMMAND_ILIMIT_SCALE = 0x02B


class Mode(IntEnum):
    """Register 0x000 (``registers.md``): what the controller does."""

    STOPPED = 0
    FAULT = 1
    ENABLING = 2
    CALIBRATING = 3
    CALIBRATION_COMPLETE = 4
    PWM = 5
    VOLTAGE = 6
    VOLTAGE_FOC = 7
    VOLTAGE_DQ = 8
    CURRENT = 9
    POSITION = 10
    TIMEOUT = 11
    ZERO_VELOCITY = 12
    STAY_WITHIN = 13
    MEASURE_INDUCTANCE = 14
    BRAKE = 15


class Fault(IntEnum):
    """Register 0x00f while the mode is FAULT (``registers.md``). Codes 96 and up name an
    active limiter in normal modes and are not faults."""

    CALIBRATION = 32
    MOTOR_DRIVER = 33
    OVER_VOLTAGE = 34
    ENCODER = 35
    MOTOR_NOT_CONFIGURED = 36
    PWM_CYCLE_OVERRUN = 37
    OVER_TEMPERATURE = 38
    START_OUTSIDE_LIMIT = 39
    UNDER_VOLTAGE = 40
    CONFIG_CHANGED = 41
    THETA_INVALID = 42
    POSITION_INVALID = 43
    DRIVER_ENABLE = 44
    STOP_POSITION_DEPRECATED = 45
    TIMING_VIOLATION = 46
    BEMF_FEEDFORWARD_NO_ACCEL = 47
    INVALID_LIMITS = 48
    POSITION_ERROR = 49
    VELOCITY_ERROR = 50


class Quantity(IntEnum):
    """What a register holds, which decides its integer steps."""

    INTEGER = 0
    POSITION = 1
    VELOCITY = 2
    TORQUE = 3
    CURRENT = 4
    VOLTAGE = 5
    TEMPERATURE = 6
    TIME = 7
    SCALE = 8
    POWER = 9
    ACCELERATION = 10


@dataclass(frozen=True, slots=True)
class Scaling:
    """One code's value at int8, int16 and int32 (float carries SI units directly)."""

    int8: float
    int16: float
    int32: float

    def step(self, resolution: Resolution) -> float:
        """One code in SI units (0.0 for float: no integer step)."""
        return (self.int8, self.int16, self.int32, 0.0)[resolution]


#: ``registers.md`` "Mappings" (and ``protocol.py`` ``Writer``/``scale_register``)
SCALINGS: Mapping[Quantity, Scaling] = MappingProxyType({
    Quantity.INTEGER: Scaling(1.0, 1.0, 1.0),
    Quantity.POSITION: Scaling(0.01, 0.0001, 0.00001),
    Quantity.VELOCITY: Scaling(0.1, 0.00025, 0.00001),
    Quantity.TORQUE: Scaling(0.5, 0.01, 0.001),
    Quantity.CURRENT: Scaling(1.0, 0.1, 0.001),
    Quantity.VOLTAGE: Scaling(0.5, 0.1, 0.001),
    Quantity.TEMPERATURE: Scaling(1.0, 0.1, 0.001),
    Quantity.TIME: Scaling(0.01, 0.001, 0.000001),
    Quantity.SCALE: Scaling(1.0 / 127.0, 1.0 / 32767.0, 1.0 / 2147483647.0),
    Quantity.POWER: Scaling(10.0, 0.05, 0.0001),
    Quantity.ACCELERATION: Scaling(0.05, 0.001, 0.00001),
})

_R = Register
REGISTER_SCALING: Mapping[Register, Quantity] = MappingProxyType({
    _R.MODE: Quantity.INTEGER, _R.POSITION: Quantity.POSITION, _R.VELOCITY: Quantity.VELOCITY,
    _R.TORQUE: Quantity.TORQUE, _R.Q_CURRENT: Quantity.CURRENT, _R.D_CURRENT: Quantity.CURRENT,
    _R.ABS_POSITION: Quantity.POSITION, _R.POWER: Quantity.POWER,
    _R.MOTOR_TEMPERATURE: Quantity.TEMPERATURE, _R.TRAJECTORY_COMPLETE: Quantity.INTEGER,
    _R.HOME_STATE: Quantity.INTEGER, _R.VOLTAGE: Quantity.VOLTAGE, _R.TEMPERATURE: Quantity.TEMPERATURE,
    _R.FAULT: Quantity.INTEGER, _R.COMMAND_POSITION: Quantity.POSITION,
    _R.COMMAND_VELOCITY: Quantity.VELOCITY, _R.COMMAND_FEEDFORWARD_TORQUE: Quantity.TORQUE,
    _R.COMMAND_KP_SCALE: Quantity.SCALE, _R.COMMAND_KD_SCALE: Quantity.SCALE,
    _R.COMMAND_MAX_TORQUE: Quantity.TORQUE, _R.COMMAND_STOP_POSITION: Quantity.POSITION,
    _R.COMMAND_TIMEOUT: Quantity.TIME, _R.COMMAND_VELOCITY_LIMIT: Quantity.VELOCITY,
    _R.COMMAND_ACCEL_LIMIT: Quantity.ACCELERATION, _R.COMMAND_FIXED_VOLTAGE_OVERRIDE: Quantity.VOLTAGE,
    _R.COMMAND_ILIMIT_SCALE: Quantity.SCALE,
})

_TYPES = (struct.Struct("<b"), struct.Struct("<h"), struct.Struct("<i"), struct.Struct("<f"))
_MAX = (0x7F, 0x7FFF, 0x7FFFFFFF)
#: the most negative code of each integer resolution: NaN ("unset")
NAN_CODES = (-0x80, -0x8000, -0x80000000)


def _scaling(register: int) -> Scaling:
    quantity = REGISTER_SCALING.get(register)   # type: ignore[call-overload]
    return SCALINGS[Quantity.INTEGER if quantity is None else quantity]


# -- values ---------------------------------------------------------------------


def encode_value(register: int, resolution: Resolution, value: float) -> int | float:
    """``value`` (SI) as the code the library and the firmware send: NaN/inf -> the most
    negative code, else saturated at +-max and truncated toward zero; float as is."""
    if resolution is Resolution.F32:
        return float(value)
    if not math.isfinite(value):
        return NAN_CODES[resolution]
    scaled = value / _scaling(register).step(resolution)
    top = _MAX[resolution]
    return int(min(max(scaled, -top), top))


def decode_value(register: int, resolution: Resolution, raw: int | float) -> float:
    """A code back to SI units (the most negative integer code: NaN)."""
    if resolution is Resolution.F32:
        return float(raw)
    if raw == NAN_CODES[resolution]:
        return math.nan
    return raw * _scaling(register).step(resolution)


# -- varuint ------------------------------------------------------------------------


def varuint(value: int) -> bytes:
    """7 bits per byte, least significant group first, bit 7 set on all but the last."""
    if value < 0:
        raise CodecError(f"varuint: expected a value >= 0, got {value}")
    out = bytearray()
    while True:
        byte = value & 0x7F
        value >>= 7
        if value:
            out.append(byte | 0x80)
        else:
            out.append(byte)
            return bytes(out)


def read_varuint(data: bytes, offset: int) -> tuple[int, int]:
    """(value, next offset); CodecError when it runs off the end or past 5 bytes."""
    value = shift = 0
    for i in range(_VARUINT_BYTES):
        if offset + i >= len(data):
            raise CodecError(f"varuint at byte {offset}: the frame ends inside it")
        byte = data[offset + i]
        value |= (byte & 0x7F) << shift
        shift += 7
        if not byte & 0x80:
            return value, offset + i + 1
    raise CodecError(f"varuint at byte {offset}: longer than {_VARUINT_BYTES} bytes")


# -- subframes ----------------------------------------------------------------------


def _head(base: Opcode, resolution: Resolution, count: int, start: int) -> bytes:
    if not 1 <= count:
        raise CodecError(f"subframe: expected at least one register, got {count}")
    opcode = base | resolution << 2
    if count <= 3:
        return bytes((opcode | count,)) + varuint(start)
    return bytes((opcode,)) + varuint(count) + varuint(start)


def _values(resolution: Resolution, values: Iterable[int | float]) -> bytes:
    pack = _TYPES[resolution].pack
    return b"".join(pack(v) for v in values)


def write_subframe(start: int, resolution: Resolution, values: Sequence[float]) -> bytes:
    """Write ``values`` (SI) to ``start``, ``start + 1``, ... at ``resolution``."""
    codes = [encode_value(start + i, resolution, v) for i, v in enumerate(values)]
    return _head(Opcode.WRITE, resolution, len(codes), start) + _values(resolution, codes)


def read_subframe(start: int, resolution: Resolution, count: int) -> bytes:
    """Ask for ``count`` registers from ``start`` at ``resolution``."""
    return _head(Opcode.READ, resolution, count, start)


def reply_subframe(start: int, resolution: Resolution, values: Sequence[float]) -> bytes:
    """A controller's answer: ``values`` (SI) of ``start``, ... at ``resolution``."""
    codes = [encode_value(start + i, resolution, v) for i, v in enumerate(values)]
    return _head(Opcode.REPLY, resolution, len(codes), start) + _values(resolution, codes)


def group_registers(wanted: Mapping[int, Resolution]) -> tuple[tuple[int, Resolution, int], ...]:
    """Read subframes for ``wanted`` (register -> resolution): runs of consecutive
    registers of one resolution, in register order, as ``(start, resolution, count)``."""
    out: list[tuple[int, Resolution, int]] = []
    for register in sorted(wanted):
        resolution = wanted[register]
        if out:
            start, res, count = out[-1]
            if res is resolution and start + count == register:
                out[-1] = (start, res, count + 1)
                continue
        out.append((register, resolution, 1))
    return tuple(out)


@dataclass(frozen=True, slots=True)
class Subframe:
    """One parsed subframe: for WRITE/REPLY a register and its value (SI), for READ the
    register and resolution, for the errors the register and the code (``value``)."""

    opcode: Opcode
    register: int
    resolution: Resolution | None
    value: float | None


def parse(data: bytes) -> Iterator[Subframe]:
    """Every subframe of ``data``, one per register; NOP padding skipped. CodecError on an
    opcode this codec does not know (the stream subframes 0x40-0x44 included: dobhil
    never opens a stream) or a frame cut short."""
    offset, end = 0, len(data)
    while offset < end:
        opcode = data[offset]
        offset += 1
        upper = opcode & 0xF0
        if opcode == Opcode.NOP:
            continue
        if opcode in (Opcode.WRITE_ERROR, Opcode.READ_ERROR):
            register, offset = read_varuint(data, offset)
            code, offset = read_varuint(data, offset)
            yield Subframe(Opcode(opcode), register, None, float(code))
            continue
        if upper not in (Opcode.WRITE, Opcode.READ, Opcode.REPLY):
            raise CodecError(f"subframe opcode 0x{opcode:02x} at byte {offset - 1}: not a register "
                             "write, read, reply or error")
        resolution = Resolution((opcode >> 2) & 3)
        count = opcode & 3
        if not count:
            count, offset = read_varuint(data, offset)
        start, offset = read_varuint(data, offset)
        kind = Opcode(upper)
        if kind is Opcode.READ:
            for i in range(count):
                yield Subframe(kind, start + i, resolution, None)
            continue
        size = _TYPES[resolution].size
        if offset + size * count > end:
            raise CodecError(f"subframe 0x{opcode:02x} of {count} values: the frame ends inside it")
        unpack = _TYPES[resolution].unpack_from
        for i in range(count):
            raw = unpack(data, offset)[0]
            offset += size
            yield Subframe(kind, start + i, resolution, decode_value(start + i, resolution, raw))


_FORMAT_CHARS = "bhif"


class Parser:
    """:func:`parse` for a stream of frames of one shape (the commands of a run, whose
    torque alone changes; the replies to one query): the shape of the last frame -- its
    opcodes, registers and where its values lie -- is kept, and a frame of the same shape
    is read with one ``struct`` unpack instead of byte by byte. Any other frame goes
    through :func:`parse` and becomes the new shape. Same result either way."""

    def __init__(self) -> None:
        self._length = -1
        self._heads: tuple[tuple[int, bytes], ...] = ()
        self._format: struct.Struct | None = None
        self._entries: tuple[tuple[Opcode, int, Resolution | None, float, int | None], ...] = ()

    def parse(self, data: bytes) -> tuple[Subframe, ...]:
        if len(data) == self._length and self._format is not None and \
                all(data[at:at + len(head)] == head for at, head in self._heads):
            raws = iter(self._format.unpack_from(data))
            out = []
            for opcode, register, res, step, nan in self._entries:
                if res is None or opcode is Opcode.READ:
                    out.append(Subframe(opcode, register, res, None if opcode is Opcode.READ else step))
                    continue
                raw = next(raws)
                value = float(raw) if nan is None else (math.nan if raw == nan else raw * step)
                out.append(Subframe(opcode, register, res, value))
            return tuple(out)
        subframes = tuple(parse(data))
        self._learn(data)
        return subframes

    def _learn(self, data: bytes) -> None:
        """The shape of ``data`` (already parsed without error)."""
        heads: list[tuple[int, bytes]] = []
        fmt = ["<"]
        entries: list[tuple[Opcode, int, Resolution | None, float, int | None]] = []
        offset, end = 0, len(data)
        while offset < end:
            begin = offset
            opcode = data[offset]
            offset += 1
            if opcode == Opcode.NOP:
                heads.append((begin, data[begin:offset]))
                fmt.append("x")
                continue
            if opcode in (Opcode.WRITE_ERROR, Opcode.READ_ERROR):
                register, offset = read_varuint(data, offset)
                code, offset = read_varuint(data, offset)
                heads.append((begin, data[begin:offset]))
                fmt.append(f"{offset - begin}x")
                entries.append((Opcode(opcode), register, None, float(code), None))
                continue
            resolution = Resolution((opcode >> 2) & 3)
            count = opcode & 3
            if not count:
                count, offset = read_varuint(data, offset)
            start, offset = read_varuint(data, offset)
            heads.append((begin, data[begin:offset]))
            fmt.append(f"{offset - begin}x")
            kind = Opcode(opcode & 0xF0)
            for i in range(count):
                step = _scaling(start + i).step(resolution)
                nan = None if resolution is Resolution.F32 else NAN_CODES[resolution]
                entries.append((kind, start + i, resolution, step, nan))
            if kind is not Opcode.READ:
                fmt.append(_FORMAT_CHARS[resolution] * count)
                offset += _TYPES[resolution].size * count
        self._length, self._heads, self._entries = len(data), tuple(heads), tuple(entries)
        self._format = struct.Struct("".join(fmt))


def pad(data: bytes) -> bytes:
    """``data`` padded with NOP (0x50) to the next CAN FD length; CodecError beyond 64 bytes."""
    if len(data) > _MAX_PAYLOAD:
        raise CodecError(f"multiplex frame of {len(data)} bytes: more than a CAN FD frame's 64")
    length = next(n for n in FD_LENGTHS if n >= len(data))
    return data + bytes((Opcode.NOP,)) * (length - len(data))


# -- arbitration ids ------------------------------------------------------------------


def arbitration_id(source: int, destination: int, *, reply: bool, prefix: int = 0) -> int:
    """``destination | source << 8 | reply-requested << 15 | prefix << 16``."""
    return destination | source << 8 | (REPLY_REQUESTED if reply else 0) | prefix << 16


def split_id(arbitration: int) -> tuple[int, int, int, bool]:
    """(prefix, source, destination, reply requested) of an arbitration id."""
    return (arbitration >> 16) & 0x1FFF, (arbitration >> 8) & 0x7F, arbitration & 0x7F, \
        bool(arbitration & REPLY_REQUESTED)
