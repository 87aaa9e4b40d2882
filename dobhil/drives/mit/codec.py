"""Pure codec of MIT-mode actuators (Mini-Cheetah firmware, CubeMars AK, Damiao DM-J):
bytes in, SI values out, no I/O. The numbers of each model (ranges, reply layout, axis
direction, ...) are data: ``drivers/mit-models.yaml``, read by :mod:`dobhil.drives.mit.models`.

Facts (bgkatz/motorcontrol at 3586419, ``Core/Src/can.c`` and ``math_ops.c``, the firmware
the CubeMars and Damiao motors derive from: the example code of CubeMars' AK Series Actuator
Driver Manual V1.0.8 §5.3 repeats its formula and frames; damiao-motor 1.0.6;
drivers/mit-models.yaml cites each row's source):

- Special frames, 8 bytes to the motor's id: ``FF x7`` then ``FC`` enter motor mode,
  ``FD`` exit, ``FE`` set zero, ``FB`` clear error (Damiao only).
- Command, 8 bytes, big-endian bit fields: p 16 bit, v 12, kp 12, kd 12, t 12:
  ``[p15:8] [p7:0] [v11:4] [v3:0|kp11:8] [kp7:0] [kd11:4] [kd3:0|t11:8] [t7:0]``.
- Reply: ``[id] [p15:8] [p7:0] [v11:4] [v3:0|t11:8] [t7:0]`` then the layout's extra bytes
  (Mini-Cheetah: bus voltage; CubeMars: temperature, error; Damiao: MOS and rotor
  temperature, and byte 0 split into a state nibble (high) and the id (low)).
- Scaling: ``int((x - lo) * (2^bits - 1) / (hi - lo))`` and back
  ``u * (hi - lo) / (2^bits - 1) + lo``, both in IEEE single precision, the firmware's
  ``float`` (``math_ops.c``). Ranges are symmetric (``lo = -hi``) except kp and kd (0..max).

Precision (decided by ``tests/drives/test_mit_codec.py::test_single_precision_changes_codes``):
single and double precision give different codes for some inputs, those within a few
single-precision steps of a code boundary (about 1 in 600 random positions on an AK80-9),
and different decoded values (code 2047 of an AK80-9's torque: -0.00439644 Nm in single,
-0.00439560 in double). This module does what the firmware does: every operation rounded
to single precision, in the firmware's order. Python clients that compute in double
(damiao-motor, tmotorcancontrol, canmotorlib) therefore differ from it at those inputs.

Clamping: the firmware's ``float_to_uint`` does not clamp (its callers do, CubeMars manual
``pack_cmd``: ``fminf(fmaxf(...))``); :func:`float_to_uint` clamps to ``[lo, hi]`` and
refuses NaN and infinities (a CodecError: a NaN command must never reach a motor).
:func:`pack_reply` (the emulator's side) follows the firmware for the position past the
range: ``position_at_limit: wrap`` is the firmware's int arithmetic (the code taken modulo
2^16, truncated toward zero as C's ``(int)`` cast does), ``saturate`` clamps; velocity and
torque are clamped (the firmware would corrupt the neighbouring field; a plant that
reaches them is outside the model's range anyway).

Axis direction: ``axis_direction: -1`` (older AK firmware turns the other way) negates
position, velocity and torque at the wire in every function here, so every value on the
Python side is on the output axis as the host sees it; kp and kd are not signed.

Speed: each field's :class:`Channel` builds two tables once from the formula (the smallest
double of each code, and each code's value), so encoding is a binary search and decoding an
index; :class:`TorqueFrame` (the 1 kHz hot path) rewrites two bytes of one command.
"""

from __future__ import annotations

import bisect
import functools
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from enum import IntEnum
from types import MappingProxyType
from typing import Any, Final

import numpy as np

from dobhil.errors import CodecError

__all__ = [
    "COMMAND_LENGTH",
    "FIELD_BITS",
    "POSITION_BITS",
    "REGISTER_ID",
    "REGISTER_READ",
    "SPECIAL_NAMES",
    "SPECIAL_PREFIX",
    "Channel",
    "Command",
    "MitModel",
    "Quanta",
    "Reply",
    "ReplyLayout",
    "Special",
    "TorqueFrame",
    "float_to_uint",
    "is_special",
    "pack_command",
    "pack_reply",
    "special_frame",
    "uint_to_float",
    "unpack_command",
    "unpack_reply",
]

#: every command and special frame is 8 bytes
COMMAND_LENGTH: Final = 8
#: the seven 0xFF bytes before a special frame's code
SPECIAL_PREFIX: Final = b"\xff" * 7
#: bits of each field: position 16, the rest 12
POSITION_BITS: Final = 16
FIELD_BITS: Final = 12
#: Damiao register access (damiao-motor's ``_send_register_cmd``): the arbitration id,
#: and byte 2 of a read (``[id_lo, id_hi, 0x33, rid, ...]``, answered in the same layout)
REGISTER_ID: Final = 0x7FF
REGISTER_READ: Final = 0x33
_INF = math.inf
_F32 = np.float32


class Special(IntEnum):
    """The last byte of a special frame (the first seven are 0xFF)."""

    CLEAR_ERROR = 0xFB  # Damiao only
    ENTER = 0xFC  # enter motor mode (MIT mode)
    EXIT = 0xFD  # exit motor mode
    ZERO = 0xFE  # set the current position as zero (the motor is silent for about 1 s)


#: table names of the special frames (``special: [enter, exit, zero, clear_error]``)
SPECIAL_NAMES: Final[Mapping[str, Special]] = MappingProxyType({s.name.lower(): s for s in Special})


def special_frame(kind: Special) -> bytes:
    """The 8 bytes of special frame ``kind``: ``FF FF FF FF FF FF FF <kind>``."""
    return SPECIAL_PREFIX + bytes((Special(kind),))


_SPECIAL_BY_FRAME: Final = {special_frame(s): s for s in Special}


def is_special(data: bytes | bytearray | memoryview) -> Special | None:
    """The special frame ``data`` is, or None (a command, or anything else)."""
    return _SPECIAL_BY_FRAME.get(bytes(data))


# ---------------------------------------------------------------------------
# Scaling: the firmware's formula in single precision


def _check_range(lo: float, hi: float, bits: int) -> None:
    if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
        raise CodecError(f"range [{lo!r}, {hi!r}]: expected finite lo < hi")
    if not 1 <= bits <= 24:  # 2^bits - 1 must be exact in single precision
        raise CodecError(f"bits {bits!r}: expected 1 to 24")


def _finite(x: float, what: str) -> float:
    if not -_INF < x < _INF:  # NaN fails both comparisons
        raise CodecError(f"{what} {x!r}: not a finite number; NaN and infinities are never sent")
    return x


def _scaled(x: Any, lo: Any, steps: Any, span: Any) -> Any:
    """``(x - lo) * steps / span`` as ``math_ops.c`` writes it. Its operands are float32
    (numpy scalars or arrays), so each operation rounds to single precision like the
    firmware's FPU; the one formula serves the scalar codec and the torque threshold table."""
    return (x - lo) * steps / span


def _unscaled(u: Any, lo: Any, steps: Any, span: Any) -> Any:
    """``u * span / steps + lo`` (``uint_to_float``), in single precision like :func:`_scaled`."""
    return u * span / steps + lo


@dataclass(frozen=True, slots=True)
class Channel:
    """One field's range and width, with the float32 constants the firmware computes with.

    :meth:`reference_encode` / :meth:`reference_decode` are the firmware's formula, one
    float32 operation at a time (numpy scalars). :meth:`encode` / :meth:`decode` give the
    same results from two tables built once per channel with the same formula on numpy
    arrays (the code thresholds and every code's value): a binary search and an index, a
    few hundred nanoseconds instead of ten microseconds (the codec runs once per cycle on
    each side of a 1 kHz loop). ``tests/drives/test_mit_codec.py`` checks them equal.
    """

    lo: float
    hi: float
    bits: int
    lo32: Any = field(init=False, repr=False, compare=False)
    hi32: Any = field(init=False, repr=False, compare=False)
    span32: Any = field(init=False, repr=False, compare=False)
    steps32: Any = field(init=False, repr=False, compare=False)
    _tables: list[tuple[float, ...]] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        _check_range(self.lo, self.hi, self.bits)
        lo32, hi32 = _F32(self.lo), _F32(self.hi)
        object.__setattr__(self, "lo32", lo32)
        object.__setattr__(self, "hi32", hi32)
        object.__setattr__(self, "span32", _F32(hi32 - lo32))  # float span = x_max - x_min
        object.__setattr__(self, "steps32", _F32((1 << self.bits) - 1))
        object.__setattr__(self, "_tables", [])  # [thresholds, values], built on first use

    @property
    def mask(self) -> int:
        return (1 << self.bits) - 1

    @property
    def step(self) -> float:
        """[unit] one code: ``(hi - lo) / (2^bits - 1)``."""
        return (self.hi - self.lo) / self.mask

    def reference_encode(self, x: float, what: str = "value") -> int:
        """The code of ``x`` clamped to ``[lo, hi]``, computed as the firmware does."""
        x = min(max(_finite(x, what), self.lo), self.hi)
        # clamping before the rounding to float32 equals clamping after it (rounding is
        # monotonic), and keeps a huge double from overflowing float32
        return int(_scaled(_F32(x), self.lo32, self.steps32, self.span32))

    def reference_decode(self, u: int) -> float:
        """The value of code ``u`` computed as the firmware does (``uint_to_float``)."""
        return float(_unscaled(_F32(u), self.lo32, self.steps32, self.span32))

    @property
    def thresholds(self) -> tuple[float, ...]:
        """The smallest double of each code 1 .. code(hi): ``bisect_right`` of a value is its code."""
        if not self._tables:
            self._build()
        return self._tables[0]

    @property
    def values(self) -> tuple[float, ...]:
        """Every code's decoded value, indexed by the code."""
        if not self._tables:
            self._build()
        return self._tables[1]

    def _build(self) -> None:
        codes = np.arange(1 << self.bits, dtype=np.float32)
        values = _unscaled(codes, self.lo32, self.steps32, self.span32).astype(np.float64)
        self._tables[:] = [_thresholds(self), tuple(values.tolist())]

    def encode(self, x: float, what: str = "value") -> int:
        """The code of ``x`` clamped to ``[lo, hi]``; NaN and infinities -> CodecError."""
        if not -_INF < x < _INF:  # NaN fails both comparisons
            _finite(x, what)
        return bisect.bisect_right(self.thresholds, x)

    def encode_wrapped(self, x: float, what: str = "value") -> int:
        """The firmware's code of ``x`` without clamping: the C ``(int)`` cast (toward zero)
        stored into ``bits`` bits (two's complement), as ``pack_reply`` of ``can.c`` does for
        a position past the range."""
        if self.lo <= x <= self.hi:
            return self.encode(x, what)
        _finite(x, what)
        if abs(x) > 1e30:  # far beyond any motor's angle; float32 would overflow
            raise CodecError(f"{what} {x!r}: too large to encode")
        return int(_scaled(_F32(x), self.lo32, self.steps32, self.span32)) & self.mask

    def decode(self, u: int) -> float:
        """The value of code ``u`` (``uint_to_float``, single precision)."""
        return self.values[u]


def _thresholds(channel: Channel) -> tuple[float, ...]:
    """The smallest double that encodes to each code 1 .. code(hi) of ``channel``, so that
    ``bisect_right(thresholds, x)`` is ``channel.reference_encode(x)`` for every double ``x``.

    Found by bisection over the float32 values (the code is a monotonic function of
    ``float32(x)``), all codes at once in numpy with the one formula :func:`_scaled`; then
    moved to the smallest double that rounds (to nearest, ties to even) to that float32.
    """
    top = channel.reference_encode(channel.hi)
    k = np.arange(1, top + 1, dtype=np.int64)

    def key_of(v: Any) -> Any:  # float32 -> an integer that orders like the float
        bits = np.asarray(v, dtype=np.float32).view(np.uint32).astype(np.int64)
        return np.where(bits >= 0x80000000, -(bits & 0x7FFFFFFF), bits)

    def float_of(key: Any) -> Any:
        bits = np.where(key >= 0, key, (-key) | 0x80000000).astype(np.uint32)
        return bits.view(np.float32)

    def codes(key: Any) -> Any:
        scaled = _scaled(float_of(key), channel.lo32, channel.steps32, channel.span32)
        return scaled.astype(np.int64)  # truncation toward zero (values are >= 0 here)

    low = np.full(k.shape, key_of(channel.lo32), dtype=np.int64)  # codes(low) = 0 < k
    high = np.full(k.shape, key_of(channel.hi32), dtype=np.int64)  # codes(high) = top >= k
    while np.any(high - low > 1):
        mid = (low + high) // 2
        above = codes(mid) >= k
        high = np.where(above, mid, high)
        low = np.where(above, low, mid)
    first = float_of(high).astype(np.float64)  # smallest float32 with code >= k
    below = float_of(high - 1).astype(np.float64)
    middle = (first + below) / 2  # exact in double; rounds to `first` only on a tie to even
    rounds_up = middle.astype(np.float32).astype(np.float64) == first
    thresholds = np.where(rounds_up, middle, np.nextafter(middle, np.inf))
    # below lo clamps to lo (code 0), above hi to hi: the table covers the range only
    thresholds = np.clip(thresholds, np.nextafter(channel.lo, np.inf), channel.hi)
    out = tuple(thresholds.tolist())
    if any(b <= a for a, b in zip(out, out[1:])):  # cannot happen for a monotonic formula
        raise CodecError(f"code threshold table of {channel} is not increasing")
    return out


@functools.lru_cache(maxsize=64)
def _channel(lo: float, hi: float, bits: int) -> Channel:
    return Channel(lo, hi, bits)


def float_to_uint(x: float, lo: float, hi: float, bits: int) -> int:
    """The firmware's ``float_to_uint`` (``math_ops.c``) with its callers' clamp:
    ``int((clamp(x) - lo) * (2^bits - 1) / (hi - lo))`` in single precision.
    NaN and infinities -> CodecError."""
    _check_range(lo, hi, bits)
    return _channel(lo, hi, bits).reference_encode(x)


def uint_to_float(u: int, lo: float, hi: float, bits: int) -> float:
    """The firmware's ``uint_to_float``: ``u * (hi - lo) / (2^bits - 1) + lo`` in single
    precision. ``u`` outside ``0 .. 2^bits - 1`` -> CodecError."""
    _check_range(lo, hi, bits)
    if not 0 <= u < (1 << bits):
        raise CodecError(f"code {u!r}: expected 0 to {(1 << bits) - 1} ({bits} bits)")
    return _channel(lo, hi, bits).reference_decode(u)


# ---------------------------------------------------------------------------
# The model table's records


@dataclass(frozen=True, slots=True)
class ReplyLayout:
    """What a model's reply carries past bytes 1-5 (position, velocity, torque).

    ``id_field``: ``byte0`` (the whole byte is the motor id) or ``low_nibble0`` (Damiao: the
    low nibble; the high nibble is the state, ``state_field = "high_nibble0"``).
    ``extra``: name -> byte index of each further byte. ``errors``: error code -> text
    (the byte named ``error`` in ``extra``); ``states``: Damiao state nibble -> text
    (codes >= ``first_error_state`` are faults). ``temperature``: the extra byte read as
    the temperature in degC ("" when none).
    """

    name: str
    lengths: tuple[int, ...]
    id_field: str = "byte0"
    state_field: str = ""
    # the mappings are compared but not hashed (a read-only mapping has no hash; the
    # name and lengths tell layouts apart), so a MitModel can key a dict or a cache
    extra: Mapping[str, int] = field(default_factory=lambda: MappingProxyType({}), hash=False)
    errors: Mapping[int, str] = field(default_factory=lambda: MappingProxyType({}), hash=False)
    states: Mapping[int, str] = field(default_factory=lambda: MappingProxyType({}), hash=False)
    temperature: str = ""
    first_error_state: int = 8

    def __post_init__(self) -> None:
        if not self.lengths or any(not 6 <= n <= 8 for n in self.lengths):
            raise CodecError(f"reply layout {self.name}: lengths {self.lengths}: expected 6 to 8 bytes")
        if self.id_field not in ("byte0", "low_nibble0"):
            raise CodecError(f"reply layout {self.name}: id {self.id_field!r}: expected byte0 or low_nibble0")
        if self.state_field not in ("", "high_nibble0"):
            raise CodecError(f"reply layout {self.name}: state {self.state_field!r}: expected high_nibble0")
        for key, index in self.extra.items():
            if not 6 <= index < max(self.lengths):
                raise CodecError(f"reply layout {self.name}: extra {key}: byte {index} is not in a "
                                 f"{max(self.lengths)}-byte reply past byte 5")
        if self.temperature and self.temperature not in self.extra:
            raise CodecError(f"reply layout {self.name}: temperature {self.temperature!r} is not an extra byte")
        for key in ("extra", "errors", "states"):
            object.__setattr__(self, key, MappingProxyType(dict(getattr(self, key))))
        object.__setattr__(self, "lengths", tuple(sorted(self.lengths)))

    @property
    def length(self) -> int:
        """The length :func:`pack_reply` writes (the longest the layout has)."""
        return self.lengths[-1]

    @property
    def max_motor_id(self) -> int:
        """The largest id the reply can carry (255 in a byte, 15 in a nibble)."""
        return 0xFF if self.id_field == "byte0" else 0x0F

    @property
    def has_error(self) -> bool:
        return "error" in self.extra or bool(self.state_field)


@dataclass(frozen=True, slots=True)
class Quanta:
    """One code's step of each reply field: ``2 x_max / (2^bits - 1)``."""

    position: float  # [rad]
    velocity: float  # [rad/s]
    torque: float  # [Nm]


@dataclass(frozen=True, slots=True)
class MitModel:
    """One row of ``drivers/mit-models.yaml``: a (vendor, model, firmware) and its codec."""

    vendor: str
    model: str
    firmware: str
    p_max: float  # [rad] position range +-p_max
    v_max: float  # [rad/s]
    t_max: float  # [Nm]
    kp_max: float  # [Nm/rad] kp range 0..kp_max
    kd_max: float  # [Nm s/rad]
    layout: ReplyLayout
    position_at_limit: str  # "wrap" | "saturate": what the reply does past +-p_max
    axis_direction: int  # +1, or -1: the firmware's positive is the output axis' negative
    command_timeout: float | None  # [s] the firmware zeroes kp, kd, t after this without a command
    special: frozenset[Special]
    source: str
    note: str = ""
    _channels: tuple[Channel, ...] = field(init=False, repr=False, compare=False, hash=False)

    def __post_init__(self) -> None:
        for key in ("p_max", "v_max", "t_max", "kp_max", "kd_max"):
            value = getattr(self, key)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise CodecError(f"{self.name}: {key} {value!r}: expected a number > 0")
        if self.position_at_limit not in ("wrap", "saturate"):
            raise CodecError(f"{self.name}: position_at_limit {self.position_at_limit!r}: expected wrap or saturate")
        if self.axis_direction not in (1, -1):
            raise CodecError(f"{self.name}: axis_direction {self.axis_direction!r}: expected 1 or -1")
        object.__setattr__(self, "special", frozenset(Special(s) for s in self.special))
        object.__setattr__(self, "_channels", (
            _channel(-self.p_max, self.p_max, POSITION_BITS),
            _channel(-self.v_max, self.v_max, FIELD_BITS),
            _channel(0.0, self.kp_max, FIELD_BITS),
            _channel(0.0, self.kd_max, FIELD_BITS),
            _channel(-self.t_max, self.t_max, FIELD_BITS),
        ))

    def build_tables(self) -> None:
        """Build every field's code tables now. They are otherwise built at the first encode
        or decode (tens of ms on a host, most of a second in a slow guest): a motor's first
        reply or a host's first command would come that much late."""
        for channel in self._channels:
            channel.thresholds  # noqa: B018 -- the property builds and caches the tables

    @property
    def name(self) -> str:
        """``cubemars AK80-9 firmware 'manual-1.0.8'``, for messages."""
        return f"{self.vendor} {self.model} firmware {self.firmware!r}"

    @property
    def key(self) -> tuple[str, str, str]:
        return (self.vendor, self.model, self.firmware)

    @property
    def position(self) -> Channel:
        return self._channels[0]

    @property
    def velocity(self) -> Channel:
        return self._channels[1]

    @property
    def kp(self) -> Channel:
        return self._channels[2]

    @property
    def kd(self) -> Channel:
        return self._channels[3]

    @property
    def torque(self) -> Channel:
        return self._channels[4]

    @property
    def quanta(self) -> Quanta:
        return Quanta(self.position.step, self.velocity.step, self.torque.step)

    @property
    def wrap_period(self) -> float:
        """[rad] how far the decoded position jumps when it wraps: 2^16 codes (the 16-bit
        field rolls over), one step more than the 2 p_max between the range ends."""
        return (1 << POSITION_BITS) * self.position.step

    @property
    def torque_bias(self) -> float:
        """[Nm] what a zero torque command becomes: the decoded value of zero's code
        (AK80-9: code 2047 -> -0.0044 Nm; the code for 0 lies between two steps)."""
        d = self.axis_direction
        return d * self.torque.decode(self.torque.encode(0.0))


# ---------------------------------------------------------------------------
# Commands


@dataclass(frozen=True, slots=True)
class Command:
    """An MIT command: ``T = kp (position - q) + kd (velocity - dq) + torque``."""

    position: float  # [rad]
    velocity: float  # [rad/s]
    kp: float  # [Nm/rad]
    kd: float  # [Nm s/rad]
    torque: float  # [Nm] feed-forward


def _pack(p: int, v: int, kp: int, kd: int, t: int) -> bytes:
    return bytes((p >> 8, p & 0xFF, v >> 4, ((v & 0xF) << 4) | (kp >> 8), kp & 0xFF,
                  kd >> 4, ((kd & 0xF) << 4) | (t >> 8), t & 0xFF))


def pack_command(model: MitModel, cmd: Command) -> bytes:
    """The 8 bytes of ``cmd`` for ``model``: each field clamped to its range; NaN or an
    infinity -> CodecError.

    One combination of codes spells a special frame (every field at its top and the torque
    code 0xFFB..0xFFE): the position code is then lowered by one step (0.4 mrad on an
    AK80-9) so that a command never enters, exits, zeroes or clears the motor.
    """
    d = model.axis_direction
    p = model.position.encode(d * cmd.position, "position")
    v = model.velocity.encode(d * cmd.velocity, "velocity")
    kp = model.kp.encode(cmd.kp, "kp")
    kd = model.kd.encode(cmd.kd, "kd")
    t = model.torque.encode(d * cmd.torque, "torque")
    data = _pack(p, v, kp, kd, t)
    if data in _SPECIAL_BY_FRAME:
        data = _pack(p - 1, v, kp, kd, t)
    return data


def _command_codes(data: bytes | bytearray | memoryview) -> tuple[int, int, int, int, int]:
    return ((data[0] << 8) | data[1], (data[2] << 4) | (data[3] >> 4), ((data[3] & 0xF) << 8) | data[4],
            (data[5] << 4) | (data[6] >> 4), ((data[6] & 0xF) << 8) | data[7])


def unpack_command(model: MitModel, data: bytes | bytearray | memoryview) -> Command:
    """What the firmware decodes from a command (``unpack_cmd`` of ``can.c``), on the
    output axis. Not 8 bytes, or a special frame -> CodecError."""
    if len(data) != COMMAND_LENGTH:
        raise CodecError(f"MIT command: {len(data)} bytes, expected {COMMAND_LENGTH}")
    if is_special(data) is not None:
        raise CodecError(f"MIT command: {bytes(data).hex(' ')} is a special frame, not a command")
    p, v, kp, kd, t = _command_codes(data)
    d = model.axis_direction
    return Command(d * model.position.decode(p), d * model.velocity.decode(v), model.kp.decode(kp),
                   model.kd.decode(kd), d * model.torque.decode(t))


class TorqueFrame:
    """The hot path's command: p = v = kp = kd = 0 and a torque, refilled in place.

    ``template`` is the 8 bytes of the zero-torque command (kp = kd = 0: the motor applies
    exactly the torque); :meth:`fill` rewrites only the torque code (low nibble of byte 6,
    byte 7) by a binary search of a precomputed table of code thresholds: no float32
    arithmetic, no allocation, the same code as :func:`pack_command` for every double.
    """

    __slots__ = ("_direction", "_negated", "_thresholds", "_top", "model", "template")

    def __init__(self, model: MitModel) -> None:
        self.model = model
        self.template = pack_command(model, Command(0.0, 0.0, 0.0, 0.0, 0.0))
        self._thresholds = model.torque.thresholds
        # axis direction -1: the code of -tau, from the negated table (ascending):
        # thresholds <= -tau  <=>  -thresholds >= tau
        self._negated = tuple(-t for t in reversed(self._thresholds))
        self._top = len(self._thresholds)
        self._direction = model.axis_direction

    def code(self, tau_nm: float) -> int:
        """The torque code of ``tau_nm`` [Nm] (output axis), clamped; NaN/inf -> CodecError."""
        if not -_INF < tau_nm < _INF:
            raise CodecError(f"torque {tau_nm!r}: not a finite number; NaN and infinities are never sent")
        if self._direction > 0:
            return bisect.bisect_right(self._thresholds, tau_nm)
        return self._top - bisect.bisect_left(self._negated, tau_nm)

    def fill(self, data: bytearray, tau_nm: float) -> None:
        """Write the code of ``tau_nm`` into ``data`` (a copy of :attr:`template`, or a
        ``can.Message``'s data): byte 6's low nibble and byte 7."""
        code = self.code(tau_nm)
        data[6] = (data[6] & 0xF0) | (code >> 8)
        data[7] = code & 0xFF


# ---------------------------------------------------------------------------
# Replies


@dataclass(frozen=True, slots=True)
class Reply:
    """A decoded reply, on the output axis (SI units, within the model's ranges)."""

    motor_id: int
    position: float  # [rad] within +-p_max (wrapped or saturated by the firmware)
    velocity: float  # [rad/s]
    torque: float  # [Nm]
    raw_position: int
    raw_velocity: int
    raw_torque: int
    #: 0 none; CubeMars byte 7; Damiao the state nibble when it is a fault (>= 8); -1: the
    #: layout carries no error
    error: int
    #: Damiao state nibble (0 disabled, 1 enabled, >= 8 a fault); -1: the layout has none
    state: int
    error_text: str  # "" when error is 0 or -1
    temperature: float  # [degC] CubeMars byte 6, Damiao rotor (byte 7); NaN when none
    extra: Mapping[str, int] = field(hash=False)  # every extra byte by name (bus_voltage, mos_temperature, ...)


_NO_EXTRA: Final[Mapping[str, int]] = MappingProxyType({})


def unpack_reply(model: MitModel, data: bytes | bytearray | memoryview) -> Reply:
    """Decode a reply of ``model``; a length its layout does not have -> CodecError."""
    layout = model.layout
    n = len(data)
    if n not in layout.lengths:
        raise CodecError(f"{model.name}: reply of {n} bytes, expected "
                         f"{' or '.join(str(x) for x in layout.lengths)} ({layout.name} layout)")
    p = (data[1] << 8) | data[2]
    v = (data[3] << 4) | (data[4] >> 4)
    t = ((data[4] & 0xF) << 8) | data[5]
    if layout.id_field == "byte0":
        motor_id, state = data[0], -1
    else:
        motor_id, state = data[0] & 0x0F, data[0] >> 4
    extra = MappingProxyType({k: data[i] for k, i in layout.extra.items() if i < n}) if layout.extra else _NO_EXTRA
    if "error" in layout.extra:
        error = extra.get("error", -1)
        text = layout.errors.get(error, f"unknown error code {error}") if error > 0 else ""
    elif layout.state_field:
        error = state if state >= layout.first_error_state else 0
        text = layout.states.get(error, f"unknown state {error}") if error else ""
    else:
        error, text = -1, ""
    temperature = float(extra[layout.temperature]) if layout.temperature in extra else math.nan
    d = model.axis_direction
    return Reply(motor_id, d * model.position.decode(p), d * model.velocity.decode(v),
                 d * model.torque.decode(t), p, v, t, error, state, text, temperature, extra)


def _byte(value: float, what: str) -> int:
    """A reply's extra byte: rounded, clamped to 0..255 (a temperature below 0 degC reads 0)."""
    if isinstance(value, int) and not isinstance(value, bool) and 0 <= value <= 0xFF:  # a raw byte
        return value
    return min(max(round(_finite(float(value), what)), 0), 0xFF)


def pack_reply(model: MitModel, motor_id: int, position: float, velocity: float, torque: float, *,
               error: int = 0, state: int = 1, temperature: float = 25.0,
               extra: Mapping[str, int] | None = None) -> bytes:
    """The reply the firmware of ``model`` sends (the emulator's side), of the layout's
    longest length. Position past +-p_max wraps or saturates (``position_at_limit``);
    velocity and torque are clamped. ``error``: CubeMars byte 7, or the Damiao state nibble
    when non-zero (8..15; else ``state``, 0 disabled or 1 enabled); ``temperature`` [degC]:
    the layout's temperature byte; ``extra``: any other extra byte by name (raw)."""
    layout = model.layout
    if not 0 <= motor_id <= layout.max_motor_id:
        raise CodecError(f"{model.name}: motor id {motor_id!r}: expected 0 to {layout.max_motor_id} "
                         f"({layout.name} replies)")
    d = model.axis_direction
    if model.position_at_limit == "wrap":
        p = model.position.encode_wrapped(d * position, "position")
    else:
        p = model.position.encode(d * position, "position")
    v = model.velocity.encode(d * velocity, "velocity")
    t = model.torque.encode(d * torque, "torque")
    out = bytearray(layout.length)
    out[1:6] = (p >> 8, p & 0xFF, v >> 4, ((v & 0xF) << 4) | (t >> 8), t & 0xFF)
    if layout.state_field:
        nibble = error if error else state
        if not 0 <= nibble <= 0x0F:
            raise CodecError(f"{model.name}: state {nibble!r}: expected 0 to 15 (a nibble)")
        out[0] = (nibble << 4) | motor_id
    else:
        out[0] = motor_id
    if not layout.extra:
        if extra:
            raise CodecError(f"{model.name}: extra {sorted(extra)}: not in the {layout.name} layout (has none)")
        return bytes(out)
    values: dict[str, float] = dict(extra) if extra else {}
    if "error" in layout.extra:
        values.setdefault("error", error)
    if layout.temperature:
        values.setdefault(layout.temperature, temperature)
    for key, value in values.items():
        index = layout.extra.get(key)
        if index is None:
            raise CodecError(f"{model.name}: extra {key!r}: not in the {layout.name} layout "
                             f"(has {', '.join(sorted(layout.extra))})")
        out[index] = _byte(value, key)
    return bytes(out)
