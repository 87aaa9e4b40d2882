"""The frames dobhil sends a moteus controller, built from :mod:`dobhil.drives.moteus.codec`.

- **Torque command** (torque by position mode, ``docs/guides/control-modes.md`` "Torque
  Control"): write mode 10 first (a mode write resets every command register to its
  default, so it must lead the frame), then position NaN ("use the current position"),
  velocity 0, feedforward torque, kp scale 0 and kd scale 0 (0x020-0x024, one subframe at
  the profile's ``command_resolution``), then the watchdog timeout 0x027 (float; NaN: no
  watchdog), then the query. With kp = kd = 0 the controller's position loop adds nothing:
  the torque it applies is the feedforward torque.
- **Stop**: mode 0 and the query (the reply's mode confirms it).
- **Query**: the read subframes alone (mode, position, velocity, torque, fault at the
  profile's resolutions; mode and fault as int8).
"""

from __future__ import annotations

import math
import struct
from collections.abc import Mapping
from dataclasses import dataclass
from types import MappingProxyType

from dobhil.drives.moteus.codec import (Mode, Opcode, Parser, Register, Resolution, encode_value, group_registers, pad,
                                        parse, read_subframe, write_subframe)

__all__ = ["CommandFrame", "Query", "RESOLUTION_NAMES", "reply_values", "stop_payload"]

#: profile words for the resolutions (``moteus.INT8`` ... in the library)
RESOLUTION_NAMES: Mapping[str, Resolution] = MappingProxyType({
    "int8": Resolution.INT8, "int16": Resolution.INT16, "int32": Resolution.INT32, "f32": Resolution.F32,
})
_TYPES = {Resolution.INT8: struct.Struct("<b"), Resolution.INT16: struct.Struct("<h"),
          Resolution.INT32: struct.Struct("<i"), Resolution.F32: struct.Struct("<f")}


@dataclass(frozen=True)
class Query:
    """What every frame asks back: register -> resolution."""

    registers: Mapping[int, Resolution]

    @classmethod
    def motion(cls, position: Resolution, velocity: Resolution, torque: Resolution) -> Query:
        """Mode, position, velocity, torque and fault (mode and fault: int8)."""
        return cls(MappingProxyType({Register.MODE: Resolution.INT8, Register.POSITION: position,
                                     Register.VELOCITY: velocity, Register.TORQUE: torque,
                                     Register.FAULT: Resolution.INT8}))

    def payload(self) -> bytes:
        return b"".join(read_subframe(start, res, count) for start, res, count in group_registers(self.registers))


def _mode_write(mode: Mode) -> bytes:
    return write_subframe(Register.MODE, Resolution.INT8, (float(mode),))


def stop_payload(query: Query) -> bytes:
    """Mode 0 (stopped: leaves fault and timeout too), then the query."""
    return pad(_mode_write(Mode.STOPPED) + query.payload())


class CommandFrame:
    """The torque command's payload, built once; :meth:`fill` rewrites only the
    feedforward torque's bytes (the hot path)."""

    def __init__(self, *, resolution: Resolution, timeout: float, query: Query) -> None:
        self.resolution = resolution
        head = _mode_write(Mode.POSITION)
        block = write_subframe(Register.COMMAND_POSITION, resolution, (math.nan, 0.0, 0.0, 0.0, 0.0))
        size = _TYPES[resolution].size
        # the block's values start after its opcode and register bytes; torque is the third
        self.offset = len(head) + len(block) - 5 * size + 2 * size
        watchdog = write_subframe(Register.COMMAND_TIMEOUT, Resolution.F32,
                                  (timeout if timeout > 0 else math.nan,))
        self.payload = pad(head + block + watchdog + query.payload())
        self._pack = _TYPES[resolution].pack_into

    def fill(self, data: bytearray, tau_nm: float) -> None:
        """Write ``tau_nm`` into a copy of :attr:`payload` (a message's data)."""
        self._pack(data, self.offset, encode_value(Register.COMMAND_FEEDFORWARD_TORQUE, self.resolution, tau_nm))


def reply_values(data: bytes, parser: Parser | None = None) -> dict[int, float]:
    """register -> value (SI) of every reply subframe in ``data`` (errors and writes
    skipped); CodecError when the frame does not parse. ``parser``: one that keeps the
    replies' shape (:class:`~dobhil.drives.moteus.codec.Parser`), for a stream of them."""
    out: dict[int, float] = {}
    for sub in (parse(data) if parser is None else parser.parse(data)):
        if sub.opcode is Opcode.REPLY and sub.value is not None:
            out[sub.register] = sub.value
    return out
