"""The emulated nodes of a config that lists ``axes:`` (:func:`dobhil.config.axes.load_axes`):
which axes one emulated bus hosts, and their :class:`~dobhil.emulator.process.EmulatorSpec`.

One emulated bus hosts the axes of one bus. An axis' bus is its ``drive.interface`` and
``drive.channel`` (its own or the top level's; axes that name none share the default bus).
Without a selection every axis is hosted, provided they all sit on one bus; axes on
several buses need a selection (one emulated bus each), and the message names the buses
and their axes. A coupling joins two hosted axes: one to an axis hosted elsewhere cannot
be emulated (the two plants would step in two processes) and is refused.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from pathlib import Path

from dobhil.config.axes import Axes, Axis, Coupling
from dobhil.drives.load import load_drive_profile
from dobhil.drives.registry import emulated_protocols
from dobhil.emulator.process import EmulatorSpec
from dobhil.errors import ConfigError

__all__ = ["DEFAULT_BUS", "axis_bus", "hosted_axes", "node_specs"]

#: the bus of axes whose config names none
DEFAULT_BUS = "the default bus"


def axis_bus(axis: Axis) -> str:
    """``INTERFACE:CHANNEL`` of the axis' configured bus, or :data:`DEFAULT_BUS`."""
    d = axis.config.drive
    return f"{d.interface}:{d.channel}" if d.interface else DEFAULT_BUS


def hosted_axes(axes: Axes, names: Iterable[str] = (), *, how: str = "--axis NAME") -> tuple[Axis, ...]:
    """The axes one emulated bus hosts: ``names`` (each checked), else every axis when they
    share one bus; ConfigError otherwise, naming the buses and saying ``how`` to select."""
    picked = list(dict.fromkeys(names))
    if picked:
        return tuple(axes.axis(name) for name in picked)
    buses: dict[str, list[str]] = {}
    for axis in axes.axes:
        buses.setdefault(axis_bus(axis), []).append(axis.name)
    if len(buses) > 1:
        where = "; ".join(f"{bus}: {', '.join(on)}" for bus, on in buses.items())
        raise ConfigError(f"the axes sit on {len(buses)} buses ({where}); one emulated bus hosts one "
                          f"bus's axes: select them with {how}")
    return axes.axes


def node_specs(axes: Axes, hosted: Sequence[Axis], config_dir: Path, *, priority_drop: int = 0,
               on_first_frame: bool = False) -> tuple[list[EmulatorSpec], tuple[Coupling, ...]]:
    """The specs of the ``hosted`` axes' nodes (each axis' drive profile, its node id
    applied) and the couplings between them; ConfigError for a protocol with no emulator
    or a coupling to an axis not hosted."""
    names = {a.name for a in hosted}
    specs: list[EmulatorSpec] = []
    for axis in hosted:
        profile = load_drive_profile(axis.config, config_dir)
        if profile.protocol not in emulated_protocols():
            raise ConfigError(f"axis {axis.name}: no emulator for protocol {profile.protocol!r}; "
                              f"emulated: {', '.join(emulated_protocols())}")
        for other in specs:
            if other.profile.node_id == profile.node_id:
                raise ConfigError(f"axes {other.name} and {axis.name} are both node {profile.node_id} on one "
                                  "bus; give each its own drive.node_id")
        specs.append(EmulatorSpec.of(axis.config, profile, priority_drop=priority_drop,
                                     on_first_frame=on_first_frame, name=axis.name))
    couplings = []
    for c in axes.couplings:
        inside = [n in names for n in (c.a, c.b)]
        if all(inside):
            couplings.append(c)
        elif any(inside):
            away = c.b if inside[0] else c.a
            raise ConfigError(f"coupling {c.a}-{c.b}: axis {away} is not emulated with "
                              f"{c.a if away == c.b else c.b}; a coupling joins two axes of one "
                              "emulated bus (select both)")
    return specs, tuple(couplings)
