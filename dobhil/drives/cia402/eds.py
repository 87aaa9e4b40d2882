"""The node's object dictionary from the profile's EDS, checked, and the PDO layouts it
gives: everything a CiA 402 drive (or its emulator) refuses before any frame is sent.

One line per refusal (ConfigError, ``dobhil run`` exit 2, nothing enabled): an EDS not
found or not readable by canopen, an object the drive needs missing (0x6040, 0x6071, ...),
supported drive modes 0x6502 without CST (bit 9), a rated torque 0x6076 of 0, a PDO
mapping beyond 64 bits (the data types come from the EDS, through canopen's PDO map).
"""

from __future__ import annotations

import struct
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import canopen
from canopen.objectdictionary import ObjectDictionary, ObjectDictionaryError, ODVariable

from dobhil.drives.cia402 import codec
from dobhil.drives.cia402.codec import Mapped
from dobhil.drives.cia402.link import quiet_canopen
from dobhil.drives.profile import DriveProfile, default_drivers_dir
from dobhil.errors import CodecError, ConfigError

__all__ = ["REQUIRED_OBJECTS", "Layouts", "eds_path", "layouts_of", "load_od", "pdo_data_types"]

#: objects the drive reads or writes besides the mapped ones (the EDS must have them)
REQUIRED_OBJECTS = {0x1006: "communication cycle period", 0x1017: "producer heartbeat time",
                    0x1018: "identity", 0x6060: "modes of operation", 0x6076: "motor rated torque",
                    0x6502: "supported drive modes"}


@dataclass(frozen=True, slots=True)
class Layouts:
    """The three PDOs' structs, derived from the object dictionary's data types."""

    rpdo: struct.Struct
    status: struct.Struct
    motion: struct.Struct


def eds_path(profile: DriveProfile) -> Path:
    """The profile's ``cia402.eds``: a path, or relative to the profile's directory."""
    name = Path(str(profile.options["eds"]))
    base = getattr(profile, "directory", None)
    candidates = [name] if name.is_absolute() else \
        [*([Path(base) / name] if base else []), name, _shipped(name)]
    for path in candidates:
        if path.is_file():
            return path
    raise ConfigError(f"drive profile {profile.name!r}: cia402.eds: file {str(name)!r} not found "
                      f"(relative to the profile's directory, or a path)")


def _shipped(name: Path) -> Path:
    return default_drivers_dir() / name


def load_od(profile: DriveProfile) -> ObjectDictionary:
    """The profile's EDS read by canopen, with every object the drive uses; ConfigError
    (one line) otherwise."""
    path = eds_path(profile)
    try:
        od = canopen.import_od(str(path), profile.node_id)
    except (ObjectDictionaryError, ValueError, KeyError, OSError) as exc:
        raise ConfigError(f"{path}: not a readable EDS: {' '.join(str(exc).split())}") from None
    objects = {**REQUIRED_OBJECTS, **{m.index: m.name for m in (*codec.RPDO_CST, *codec.TPDO_STATUS,
                                                          *codec.TPDO_MOTION)}}
    for index, name in objects.items():
        if index not in od:
            raise ConfigError(f"{path}: object 0x{index:04X} ({name}) missing: a CiA 402 drive in CST "
                              "needs it")
    _check_eds_values(od, path)
    return od


def _check_eds_values(od: ObjectDictionary, path: Path) -> None:
    modes = _default(od, 0x6502)
    if modes is not None and not int(modes) >> codec.CST_SUPPORTED_BIT & 1:
        raise ConfigError(f"{path}: 0x6502 (supported drive modes) = 0x{int(modes):08X} has no cyclic "
                          f"synchronous torque (bit {codec.CST_SUPPORTED_BIT}); dobhil drives CST only")
    rated = _default(od, 0x6076)
    if rated is not None and int(rated) <= 0:
        raise ConfigError(f"{path}: 0x6076 (motor rated torque) = {rated}: a rated torque of 0 makes "
                          "every per mille torque 0; give the motor's rated torque")


def _default(od: ObjectDictionary, index: int) -> Any:
    var = od[index]
    return var.default if isinstance(var, ODVariable) else None


def layouts_of(od: ObjectDictionary, profile: DriveProfile) -> Layouts:
    """The PDOs' structs from the data types canopen gives the mapped objects (a PDO map
    built offline: canopen's ``PdoMap.add_variable`` on a node that is on no bus). A
    mapping beyond 64 bits is refused in one line."""
    with quiet_canopen():  # canopen logs a warning beyond 64 bits: the ConfigError says it
        return _layouts(od, profile)


def _layouts(od: ObjectDictionary, profile: DriveProfile) -> Layouts:
    node = canopen.RemoteNode(profile.node_id, od)
    opts = profile.options
    maps = ((node.rpdo, int(opts["rpdo"]), codec.RPDO_CST), (node.tpdo, int(opts["tpdo"]), codec.TPDO_STATUS),
            (node.tpdo, int(opts["tpdo"]) + 1, codec.TPDO_MOTION))
    structs = []
    for pdos, number, objects in maps:
        types = pdo_data_types(pdos, number, objects)
        try:
            structs.append(codec.layout_struct(types))
        except CodecError as exc:
            names = " + ".join(f"{m.label} {len_bits(t)} bits" for m, t in zip(objects, types))
            raise ConfigError(f"drive profile {profile.name!r}: PDO {number} mapping does not fit: "
                              f"{names}: {exc}") from None
    return Layouts(*structs)


def len_bits(data_type: int) -> int:
    return codec.layout_bits([data_type])


def pdo_data_types(pdos: Any, number: int, objects: Sequence[Mapped]) -> list[int]:
    """Data types of ``objects`` as canopen maps them into PDO ``number`` (offline)."""
    try:
        pdo = pdos[number]
    except KeyError:
        raise ConfigError(f"the EDS has no PDO {number} (its communication and mapping records)") from None
    pdo.clear()
    for obj in objects:
        pdo.add_variable(obj.index, obj.subindex)
    return [var.od.data_type for var in pdo.map]
