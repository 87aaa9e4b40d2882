"""Drive implementations by protocol name: built-in ones and entry points.

As python-can finds interfaces (its ``BACKENDS`` table beside the ``can.interface``
entry points), a protocol is found in two places:

- :data:`DRIVE_CLASSES`, the built-in table, so a source tree that was never installed
  (no entry-point metadata) still knows its own protocols;
- the entry-point group ``dobhil.drives`` (:data:`ENTRY_POINT_GROUP`) of any installed
  distribution: name ``<protocol>`` -> its :class:`~dobhil.drives.plugin.DriveProtocol`
  subclass, which names the drive class, the emulated drive and the rest.
  A protocol can live in another package without editing dobhil.

Drives (:func:`make_drive`) and emulated drives (:func:`make_emulated_drive`) are both made
here, from the one protocol object.

A built-in protocol wins over an entry point of the same name. Classes are imported
lazily, when a profile of that protocol is read or a drive of it is made.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Mapping
from importlib.metadata import EntryPoint, entry_points
from types import MappingProxyType
from typing import TYPE_CHECKING, Any

import can

from dobhil.drives.base import Drive
from dobhil.drives.emulated import EmulatedDrive, PlantLike
from dobhil.drives.plugin import DriveProtocol
from dobhil.drives.profile import DriveProfile, ProtocolLookup, ProtocolRules
from dobhil.errors import ConfigError, exception_line

if TYPE_CHECKING:
    from dobhil.drives.preflight import PreflightProbe

__all__ = [
    "ENTRY_POINT_GROUP",
    "PROFILE_LOOKUP",
    "PROTOCOL_CLASSES",
    "drive_class",
    "emulated_protocols",
    "emulator_class",
    "load_object",
    "make_drive",
    "make_emulated_drive",
    "plugin_entry_points",
    "preflight_probe",
    "profile_rules",
    "protocol",
    "protocols",
]

#: the entry-point group of drive protocols (name ``<protocol>``, value its DriveProtocol
#: subclass), named after this package as python-can's ``can.interface`` is after its own
ENTRY_POINT_GROUP = "dobhil.drives"

#: built-in protocols: name -> (module, DriveProtocol subclass name)
PROTOCOL_CLASSES: Mapping[str, tuple[str, str]] = MappingProxyType({
    "odrive": ("dobhil.drives.odrive.plugin", "ODriveProtocol"),
    "cia402": ("dobhil.drives.cia402.plugin", "CiA402Protocol"),
    "mit": ("dobhil.drives.mit.plugin", "MitProtocol"),
    "moteus": ("dobhil.drives.moteus.plugin", "MoteusProtocol"),
})


def plugin_entry_points() -> dict[str, EntryPoint]:
    """The group's entry points by name (the first of a name wins, in ``sys.path`` order,
    as importlib.metadata lists them). Read on each call: cheap next to making a drive,
    and a distribution installed (or put on ``sys.path``) since is seen."""
    found: dict[str, EntryPoint] = {}
    for ep in entry_points(group=ENTRY_POINT_GROUP):
        found.setdefault(ep.name, ep)
    return found


def load_object(name: str, builtin: tuple[str, str] | None, ep: EntryPoint | None) -> Any:
    """The object a built-in table row (preferred) or an entry point names; a failure to
    import it is one line naming the entry and the error, not a traceback."""
    load: Callable[[], Any]
    if builtin is not None:
        module_name, attr = builtin
        what, target = f"built-in {name!r}", f"{module_name}:{attr}"
        load = lambda: getattr(importlib.import_module(module_name), attr)  # noqa: E731
    elif ep is not None:
        what, target, load = f"entry point {name!r} (group {ENTRY_POINT_GROUP})", ep.value, ep.load
    else:
        raise ConfigError(f"{name!r}: neither built in nor an entry point")
    try:
        return load()
    except Exception as exc:  # whatever a third-party module raises on import
        raise ConfigError(f"{what} = {target} failed to load: {exception_line(exc)}") from None


def protocols() -> tuple[str, ...]:
    """Every protocol a profile may name: built-in and entry points, sorted."""
    names = set(PROTOCOL_CLASSES)
    names.update(plugin_entry_points())
    return tuple(sorted(names))


_INSTANCES: dict[str, DriveProtocol] = {}


def protocol(name: str) -> DriveProtocol:
    """The :class:`DriveProtocol` of ``name`` (one instance per name); ConfigError (one
    line) if unknown or broken."""
    if name in _INSTANCES:
        return _INSTANCES[name]
    builtin = PROTOCOL_CLASSES.get(name)
    ep = None if builtin is not None else plugin_entry_points().get(name)
    if builtin is None and ep is None:
        raise ConfigError(f"protocol: expected one of {list(protocols())}, got {name!r}")
    cls = load_object(name, builtin, ep)
    if not (isinstance(cls, type) and issubclass(cls, DriveProtocol)):
        raise ConfigError(f"protocol {name!r}: {cls!r} is not a dobhil DriveProtocol class")
    made = cls()
    drive = made.drive_class
    if not (isinstance(drive, type) and issubclass(drive, Drive)):
        raise ConfigError(f"protocol {name!r}: {drive!r} is not a dobhil Drive class")
    return _INSTANCES.setdefault(name, made)


def drive_class(name: str) -> type[Drive]:
    """The Drive subclass of protocol ``name``; ConfigError (one line) if unknown or broken."""
    return protocol(name).drive_class


def profile_rules(name: str) -> ProtocolRules:
    """How protocol ``name`` validates its profiles (``DriveProtocol.rules``)."""
    rules = protocol(name).rules
    if not isinstance(rules, ProtocolRules):
        raise ConfigError(f"protocol {name!r}: profile_rules is not a ProtocolRules")
    return rules


def make_drive(bus: can.BusABC, profile: DriveProfile, *, reset_faults: bool = False,
               **kwargs: Any) -> Drive:
    """Build the drive of ``profile.protocol`` on ``bus`` (kwargs go to its constructor).
    ``reset_faults``: the drive may clear a fault before enabling (``dobhil run
    --reset-faults``); off, a faulted drive refuses to enable."""
    return drive_class(profile.protocol)(bus, profile, reset_faults=reset_faults, **kwargs)


def preflight_probe(profile: DriveProfile) -> PreflightProbe | None:
    """The preflight part of ``profile.protocol`` (None: that protocol has none yet)."""
    return protocol(profile.protocol).preflight_probe(profile)


def emulated_protocols() -> tuple[str, ...]:
    """Every protocol with an emulated drive (``DriveProtocol.emulator_class``), sorted; a
    protocol that fails to load is left out here (naming it fails with its own line)."""
    out = []
    for name in protocols():
        try:
            if protocol(name).emulator_class is not None:
                out.append(name)
        except ConfigError:
            continue
    return tuple(out)


def emulator_class(name: str) -> type[EmulatedDrive]:
    """The EmulatedDrive subclass of protocol ``name``; ConfigError (one line) if none or broken."""
    cls = protocol(name).emulator_class
    if cls is None:
        raise ConfigError(f"no emulator for protocol {name!r}; emulated: {', '.join(emulated_protocols())}")
    if not (isinstance(cls, type) and issubclass(cls, EmulatedDrive)):
        raise ConfigError(f"emulator of protocol {name!r} is not a dobhil EmulatedDrive class")
    return cls


def make_emulated_drive(bus: can.BusABC, profile: DriveProfile, plant: PlantLike,
                        **kwargs: Any) -> EmulatedDrive:
    """The emulator of ``profile.protocol`` on ``bus`` driving ``plant``."""
    return emulator_class(profile.protocol)(bus, profile, plant, **kwargs)


#: what the profile validator asks this registry (``dobhil.drives.load`` passes it)
PROFILE_LOOKUP = ProtocolLookup(rules=profile_rules, names=protocols)
