"""The node's object dictionary from the profile's EDS, checked, and the PDO layouts it
gives: everything a CiA 402 drive (or its emulator) refuses before any frame is sent.

One line per refusal (ConfigError, ``dobhil run`` exit 2, nothing enabled): an EDS not
found or not readable by canopen, an object the drive needs missing (0x6040, 0x6071, ...),
supported drive modes 0x6502 without CST (bit 9), a rated torque 0x6076 of 0, a PDO
mapping beyond 64 bits (the data types come from the EDS, through canopen's PDO map).
"""

from __future__ import annotations

import configparser

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
from dobhil.errors import CodecError, ConfigError, exception_line

__all__ = ["REQUIRED_OBJECTS", "STANDARD_LAYOUTS", "EdsNotFound", "Layouts", "check_od", "eds_path", "load_od",
           "pdo_data_types"]

#: objects the drive reads or writes besides the mapped ones (the EDS must have them)
REQUIRED_OBJECTS = {0x1017: "producer heartbeat time",
                    0x1018: "identity", 0x6060: "modes of operation", 0x6076: "motor rated torque",
                    0x6502: "supported drive modes"}


@dataclass(frozen=True, slots=True)
class Layouts:
    """The three PDOs' structs, derived from the object dictionary's data types."""

    rpdo: struct.Struct
    status: struct.Struct
    motion: struct.Struct


class EdsNotFound(ConfigError):
    """The profile's EDS is not there (a replay needs none: the layouts are the standard's)."""


def eds_path(profile: DriveProfile) -> Path:
    """The profile's ``cia402.eds``: a path, or relative to the profile's directory (the
    shipped profiles' directory for a profile without one: built in code, or from a log)."""
    name = Path(str(profile.options["eds"]))
    if name.is_absolute():
        candidates = [name]
    elif profile.directory:
        candidates = [Path(profile.directory) / name]
    else:
        candidates = [name, default_drivers_dir() / name]
    for path in candidates:
        if path.is_file():
            return path
    where = f"in {profile.directory}" if profile.directory and not name.is_absolute() else "(a path, or " \
        "relative to the profile's directory)"
    raise EdsNotFound(f"drive profile {profile.name!r}: cia402.eds: file {str(name)!r} not found {where}")


def load_od(profile: DriveProfile) -> ObjectDictionary:
    """The profile's EDS read by canopen and checked (:func:`check_od`); ConfigError (one
    line) otherwise, EdsNotFound when there is no such file."""
    path = eds_path(profile)
    try:
        with quiet_canopen():
            od = canopen.import_od(str(path), profile.node_id)
    # canopen reads an EDS with configparser: a file that is not INI raises its Error
    # (MissingSectionHeaderError, ParsingError), which is none of the others
    except (ObjectDictionaryError, ValueError, KeyError, OSError, configparser.Error) as exc:
        raise ConfigError(f"{path}: not a readable EDS (expected CiA 306's INI format, sections such as [1000] "
                          f"and [6040]): {exception_line(exc, named=False)}") from None
    check_od(od, profile, str(path))
    return od


def check_od(od: ObjectDictionary, profile: DriveProfile, source: str) -> None:
    """Every object the drive uses is there; the EDS's defaults allow CST with a rated
    torque; the PDOs the profile names exist and take the mapping with the standard's data
    types (so a recorded run decodes with them, EDS or not)."""
    objects = {**REQUIRED_OBJECTS, **{m.index: m.name for m in (*codec.RPDO_CST, *codec.TPDO_STATUS,
                                                                 *codec.TPDO_MOTION)}}
    for index, name in objects.items():
        if index not in od:
            raise ConfigError(f"{source}: object 0x{index:04X} ({name}) missing: a CiA 402 drive in CST "
                              "needs it")
    if 0x1006 not in od and 0x60C2 not in od:
        raise ConfigError(f"{source}: neither 0x1006 (communication cycle period) nor 0x60C2 (interpolation "
                          "time period) in it: the node must be told the SYNC period")
    modes = _default(od, 0x6502)
    if modes is not None and not int(modes) >> codec.CST_SUPPORTED_BIT & 1:
        raise ConfigError(f"{source}: 0x6502 (supported drive modes) = 0x{int(modes):08X} has no cyclic "
                          f"synchronous torque (bit {codec.CST_SUPPORTED_BIT}); dobhil drives CST only")
    rated = _default(od, 0x6076)
    if rated is not None and int(rated) <= 0:
        raise ConfigError(f"{source}: 0x6076 (motor rated torque) = {rated}: a rated torque of 0 makes "
                          "every per mille torque 0; give the motor's rated torque")
    with quiet_canopen():  # canopen logs a warning beyond 64 bits: the ConfigError says it
        _check_mapping(od, profile, source)


def _default(od: ObjectDictionary, index: int) -> Any:
    var = od[index]
    return var.default if isinstance(var, ODVariable) else None


#: the three PDOs: their structs, the standard's data types (codec's tables)
STANDARD_LAYOUTS = Layouts(codec.RPDO_CST_STRUCT, codec.TPDO_STATUS_STRUCT, codec.TPDO_MOTION_STRUCT)


def _check_mapping(od: ObjectDictionary, profile: DriveProfile, source: str) -> None:
    """The data types canopen gives the mapped objects (a PDO map built offline: its
    ``PdoMap.add_variable`` on a node that is on no bus): within 64 bits, and the
    standard's (the drive decodes with :data:`STANDARD_LAYOUTS`)."""
    node = canopen.RemoteNode(profile.node_id, od)
    rpdo, tpdo = int(profile.options["rpdo"]), int(profile.options["tpdo"])
    for kind, pdos, number, objects in (("RPDO", node.rpdo, rpdo, codec.RPDO_CST),
                                        ("TPDO", node.tpdo, tpdo, codec.TPDO_STATUS),
                                        ("TPDO", node.tpdo, tpdo + 1, codec.TPDO_MOTION)):
        types = pdo_data_types(pdos, number, objects, f"{source}: {kind}{number}")
        try:
            codec.layout_struct(types)
        except CodecError as exc:
            names = " + ".join(f"{m.label} {codec.layout_bits([t])} bits" for m, t in zip(objects, types))
            raise ConfigError(f"{source}: {kind} {number} mapping does not fit: {names}: {exc}") from None
        for obj, data_type in zip(objects, types):
            if data_type != obj.data_type:
                raise ConfigError(f"{source}: {obj.label} is {_type_name(data_type)} in the EDS, "
                                  f"CiA 402 has {_type_name(obj.data_type)}")


def _type_name(data_type: int) -> str:
    try:
        return codec.DataType(data_type).name
    except ValueError:
        return f"data type 0x{data_type:04X}"


def pdo_data_types(pdos: Any, number: int, objects: Sequence[Mapped], what: str) -> list[int]:
    """Data types of ``objects`` as canopen maps them into PDO ``number`` (offline)."""
    try:
        pdo = pdos[number]
    except KeyError:
        raise ConfigError(f"{what}: the EDS has no such PDO (its communication and mapping "
                          "records)") from None
    pdo.clear()
    for obj in objects:
        pdo.add_variable(obj.index, obj.subindex)
    return [var.od.data_type for var in pdo.map]
