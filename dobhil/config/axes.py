"""Several axes in one loop: the ``axes:`` list of a config, and couplings between axes.

A config file with an ``axes:`` list describes one loop that runs several drives::

    loop: {period: 0.001, duration: 2.0}     # one period, one duration, one timing for all
    design: {force_gain: 2.0}                # the top-level sections are every axis' defaults
    axes:
      - name: left
        drive: {profile: odrive-0.6, node_id: 1}
        reference: {amplitude: 1.0}
      - name: right
        drive: {profile: odrive-0.6, node_id: 2}
        plant: {inertia: 0.3}
    environment:
      coupling:                              # a spring and damper between two axes' positions
        - {axes: [left, right], stiffness: 2000.0, damping: 20.0}

Each axis is a complete single-axis :class:`~dobhil.config.schema.Config`: the top-level
sections, then the axis' own keys over them. So everything that handles one axis (the
analysis, the controller synthesis, the emulator's plant) handles each axis unchanged.
``--set axes.NAME.section.key=value`` overrides one axis' key, ``--set section.key=value``
every axis' default. The loop's shared keys (:data:`SHARED_LOOP_KEYS`) may only be set at
the top level: one loop cannot run two periods.

A config without ``axes:`` is one axis (:func:`load_axes` gives it the name
:data:`SINGLE_AXIS`), and is read exactly as before by :func:`dobhil.config.load.load_config`.
"""

from __future__ import annotations

import math
import os
import re
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Final

from dobhil.config.load import (CWD_PATH_KEYS, _flatten, build_config, parse_override, read_set_file, read_yaml,
                                resolve_config)
from dobhil.config.schema import Config
from dobhil.config.yamlio import show_value
from dobhil.errors import ConfigError

__all__ = ["AXIS_NAME", "SHARED_LOOP_KEYS", "SINGLE_AXIS", "Axes", "Axis", "Coupling", "has_axes",
           "load_axes"]

#: the name of the one axis of a config without ``axes:``
SINGLE_AXIS: Final = "axis"
#: what an axis name may be: it is a topic path component (``/axis/<name>/...``) and a
#: ``--set axes.<name>.key`` component, so no dots, slashes or spaces
AXIS_NAME: Final = re.compile(r"[A-Za-z][A-Za-z0-9_-]{0,31}")
#: loop keys one loop has once: set at the top level only
SHARED_LOOP_KEYS: Final = ("loop.period", "loop.duration", "loop.timing", "loop.spin", "loop.mode",
                           "loop.realtime_priority", "loop.cpu_affinity")
#: keys of a coupling entry
_COUPLING_KEYS: Final = ("axes", "stiffness", "damping")


@dataclass(frozen=True)
class Coupling:
    """A spring ``stiffness`` [N m/rad] and damper ``damping`` [N m s/rad] between the
    positions of axes ``a`` and ``b``: it pushes ``a`` with ``K (q_b - q_a) + D (dq_b - dq_a)``
    and ``b`` with the opposite torque (two actuators pressing on each other, or a
    master/slave pair through a compliant link)."""

    a: str
    b: str
    stiffness: float
    damping: float


@dataclass(frozen=True)
class Axis:
    """One axis: its name, and its whole single-axis config (the top level's keys with the
    axis' own over them)."""

    name: str
    config: Config


@dataclass(frozen=True)
class Axes:
    """The axes of one loop, in the order they are enabled, and the couplings between them."""

    axes: tuple[Axis, ...]
    couplings: tuple[Coupling, ...] = ()
    #: True when the config listed ``axes:`` (False: a single-axis config read as one axis)
    listed: bool = True

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(a.name for a in self.axes)

    @property
    def period(self) -> float:
        """The one ``loop.period`` of every axis."""
        return self.axes[0].config.loop.period

    def axis(self, name: str) -> Axis:
        """The axis called ``name``; ConfigError naming the axes there are otherwise."""
        for a in self.axes:
            if a.name == name:
                return a
        raise ConfigError(f"no axis {show_value(name)}; axes: {', '.join(self.names)}")

    def coupled(self, name: str) -> tuple[Coupling, ...]:
        """The couplings that act on axis ``name``."""
        return tuple(c for c in self.couplings if name in (c.a, c.b))

    def __len__(self) -> int:
        return len(self.axes)


def has_axes(path: str | Path) -> bool:
    """True when the config file (or shipped name) ``path`` lists ``axes:``."""
    return "axes" in read_yaml(resolve_config(path))


def load_axes(path: str | Path | None = None, overrides: Iterable[str] = (),
              set_files: Iterable[str | Path] = ()) -> Axes:
    """The axes of a config (see the module docstring); a config without ``axes:`` is one
    axis named :data:`SINGLE_AXIS`. ``set_files`` and ``overrides`` as in
    :func:`~dobhil.config.load.load_config`, plus ``axes.NAME.section.key`` for one axis."""
    data = dict(read_yaml(resolve_config(path))) if path is not None else {}
    source = str(path) if path is not None else "defaults"
    raw_axes = data.pop("axes", None)
    environment = data.get("environment")
    raw_couplings: Any = None
    if isinstance(environment, Mapping) and "coupling" in environment:
        environment = dict(environment)
        raw_couplings = environment.pop("coupling")
        data["environment"] = environment
    base = _flatten(data, "")
    listed = raw_axes is not None
    entries = _axis_entries(raw_axes, source) if listed else [(SINGLE_AXIS, {})]
    own: dict[str, dict[str, Any]] = {name: flat for name, flat in entries}
    for extra in set_files:   # an axis' key in a --set-file goes to that axis, as with --set
        for name, value in read_set_file(extra).items():
            if name.endswith("." + CWD_PATH_KEYS[0]) and isinstance(value, str) and value:
                # an axis' path as read_set_file takes the top level's: from the file's own directory
                value = os.path.join(os.path.dirname(os.path.abspath(extra)), value)
            _assign(name, value, base, own, listed, f"--set-file {extra}: {name}")
    for item in overrides:
        name, value = parse_override(item)
        if name in CWD_PATH_KEYS or name.endswith("." + CWD_PATH_KEYS[0]):
            value = os.path.abspath(value) if isinstance(value, str) and value else value
        _assign(name, value, base, own, listed, f"--set {show_value(item)}")
    axes = tuple(_axis(name, base, own[name], source) for name, _ in entries)
    if raw_couplings is not None and not listed:
        raise ConfigError(f"{source}: environment.coupling joins two named axes; the config lists no "
                          "axes: (give an axes: list with a name: for each)")
    couplings = _couplings(raw_couplings, {a.name for a in axes}, source)
    return Axes(axes, couplings, listed)


def _assign(name: str, value: Any, base: dict[str, Any], own: Mapping[str, dict[str, Any]], listed: bool,
            item: str) -> None:
    """One overridden key: ``axes.NAME.section.key`` to that axis, any other to every axis."""
    if not name.startswith("axes."):
        base[name] = value
        return
    if not listed:
        raise ConfigError(f"{item}: the config lists no axes: (a single-axis config); set section.key "
                          "without axes.NAME.")
    axis, key = _axis_override(name, own, item)
    own[axis][key] = value


def _axis_entries(raw: Any, source: str) -> list[tuple[str, dict[str, Any]]]:
    """``axes:`` as (name, flat keys) pairs, names checked and distinct."""
    if not isinstance(raw, Sequence) or isinstance(raw, (str, bytes)) or not raw:
        raise ConfigError(f"{source}: axes: expected a non-empty list of axes (each a mapping with a "
                          f"name: and its sections), got {show_value(raw)}")
    entries: list[tuple[str, dict[str, Any]]] = []
    for i, item in enumerate(raw):
        if not isinstance(item, Mapping):
            raise ConfigError(f"{source}: axes[{i}]: expected a mapping with name: and sections "
                              f"(drive:, plant:, ...), got {show_value(item)}")
        item = dict(item)
        name = item.pop("name", None)
        if not isinstance(name, str) or not AXIS_NAME.fullmatch(name):
            raise ConfigError(f"{source}: axes[{i}].name = {show_value(name)}: expected a name of letters, "
                              "digits, _ or - (at most 32, starting with a letter)")
        if name in (n for n, _ in entries):
            raise ConfigError(f"{source}: axes[{i}].name = {name!r}: two axes have this name; "
                              "each axis needs its own")
        bad = [k for k, v in item.items() if not isinstance(v, Mapping)]
        if bad:
            raise ConfigError(f"{source}: axes[{i}] ({name}): {show_value(bad[0])} is not a section "
                              "(expected e.g. drive: {profile: odrive-0.6, node_id: 1})")
        entries.append((name, _flatten(item, "")))
    return entries


def _axis_override(name: str, own: Mapping[str, Any], item: str) -> tuple[str, str]:
    """``axes.NAME.section.key`` -> (NAME, section.key)."""
    parts = name.split(".")
    if len(parts) != 4:
        raise ConfigError(f"{item}: expected axes.NAME.section.key=value, e.g. axes.left.plant.inertia=0.3")
    axis, key = parts[1], ".".join(parts[2:])
    if axis not in own:
        raise ConfigError(f"{item}: no axis {show_value(axis)}; axes: {', '.join(own)}")
    return axis, key


def _axis(name: str, base: Mapping[str, Any], own: Mapping[str, Any], source: str) -> Axis:
    shared = [k for k in own if k in SHARED_LOOP_KEYS]
    if shared:
        raise ConfigError(f"{source}: axis {name}: {shared[0]} is shared by every axis of the loop; "
                          "set it at the top level (loop:), not in the axis")
    try:
        config = build_config({**base, **own}, source=source)
    except ConfigError as exc:
        raise ConfigError(f"axis {name}: {exc}") from None
    return Axis(name, config)


def _couplings(raw: Any, names: set[str], source: str) -> tuple[Coupling, ...]:
    if raw is None:
        return ()
    if not isinstance(raw, Sequence) or isinstance(raw, (str, bytes)):
        raise ConfigError(f"{source}: environment.coupling: expected a list of "
                          "{axes: [A, B], stiffness: K, damping: D}, got " + show_value(raw))
    out: list[Coupling] = []
    for i, item in enumerate(raw):
        where = f"{source}: environment.coupling[{i}]"
        if not isinstance(item, Mapping):
            raise ConfigError(f"{where}: expected {{axes: [A, B], stiffness: K, damping: D}}, got "
                              f"{show_value(item)}")
        unknown = [k for k in item if k not in _COUPLING_KEYS]
        if unknown:
            raise ConfigError(f"{where}: unknown key {show_value(unknown[0])}; allowed: "
                              f"{', '.join(_COUPLING_KEYS)}")
        pair = item.get("axes")
        if (not isinstance(pair, Sequence) or isinstance(pair, (str, bytes)) or len(pair) != 2
                or not all(isinstance(p, str) for p in pair)):
            raise ConfigError(f"{where}.axes = {show_value(pair)}: expected the names of two axes, "
                              "e.g. [left, right]")
        a, b = pair
        for p in (a, b):
            if p not in names:
                raise ConfigError(f"{where}: couples axis {p!r}, which is not in axes: "
                                  f"{', '.join(sorted(names))}")
        if a == b:
            raise ConfigError(f"{where}: couples axis {a!r} to itself; a coupling joins two axes")
        if any({a, b} == {c.a, c.b} for c in out):
            raise ConfigError(f"{where}: axes {a} and {b} are coupled twice; give one coupling "
                              "its summed stiffness and damping")
        out.append(Coupling(a, b, _nonnegative(f"{where}.stiffness", item.get("stiffness", 0.0)),
                            _nonnegative(f"{where}.damping", item.get("damping", 0.0))))
    return tuple(out)


def _nonnegative(what: str, raw: Any) -> float:
    if isinstance(raw, bool) or not isinstance(raw, (int, float)) or not math.isfinite(raw) \
            or raw < 0 or raw > 1e10:
        raise ConfigError(f"{what} = {show_value(raw)}: expected a finite number >= 0 and <= 1e10")
    return float(raw)
