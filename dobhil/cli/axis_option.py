"""``--axis NAME``: one axis of a config that lists ``axes:``, for the commands that handle
one axis (tune, certify, sweep, montecarlo, check, run).

On an axes config the command works on that axis' whole config (the top level's keys with the
axis' own over them, :func:`dobhil.config.axes.load_axes`), exactly as on a single-axis config.
A key the command varies may name the axis, ``axes.NAME.section.key`` (``--range
axes.left.plant.inertia=0.2:0.3``): the command then picks that axis (when ``--axis`` does not
name it already) and varies ``section.key`` of it. Bad input is one line (ConfigError): an
axes config without an axis picked (naming the axes there are), ``--axis`` or an
``axes.NAME.`` key on a single-axis config, a key of another axis than the one picked.
"""

from __future__ import annotations

import argparse
from collections.abc import Iterable, Sequence

from dobhil.config import Config, load_config
from dobhil.config.axes import has_axes, load_axes
from dobhil.config.yamlio import show_value
from dobhil.errors import ConfigError

__all__ = ["AXIS_PREFIX", "add_axis_arg", "axis_config", "axis_keys", "item_axis", "select_axis", "strip_axis"]

#: how a varied key names an axis: ``axes.NAME.section.key``
AXIS_PREFIX = "axes."


def add_axis_arg(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--axis", metavar="NAME",
                        help="with a config that lists axes: the axis to work on (its whole config: the "
                        "top level's keys with the axis' own over them)")


def item_axis(item: str, option: str) -> str | None:
    """The axis ``item`` (``KEY=...``) names with an ``axes.NAME.section.key`` key, else None."""
    key = item.partition("=")[0].strip()
    if not key.startswith(AXIS_PREFIX):
        return None
    parts = key.split(".")
    if len(parts) != 4 or not parts[1]:
        raise ConfigError(f"{option} {show_value(item)}: expected axes.NAME.section.key, "
                          "e.g. axes.left.plant.inertia")
    return parts[1]


def strip_axis(item: str) -> str:
    """``axes.left.plant.inertia=0.2:0.3`` -> ``plant.inertia=0.2:0.3`` (others as they are)."""
    key, sep, rest = item.partition("=")
    if not key.strip().startswith(AXIS_PREFIX):
        return item
    return ".".join(key.strip().split(".")[2:]) + sep + rest


def select_axis(args: argparse.Namespace, keyed: Iterable[tuple[str, Sequence[str]]] = ()) -> str | None:
    """The axis the command works on, set as ``args.axis`` (None: a single-axis config):
    ``--axis``, else the one axis the ``axes.NAME.`` keys of ``keyed`` ((option, items) pairs)
    name. ConfigError (one line) for what the module docstring lists."""
    named = [(option, item, item_axis(item, option)) for option, items in keyed for item in items]
    named = [(o, i, a) for o, i, a in named if a is not None]
    listed = has_axes(args.config)
    if not listed:
        if args.axis is not None:
            raise ConfigError(f"--axis {args.axis}: {args.config} lists no axes: (a single-axis config); "
                              "drop --axis")
        if named:
            option, item, _ = named[0]
            raise ConfigError(f"{option} {show_value(item)}: {args.config} lists no axes: (a single-axis "
                              f"config); give the key as {strip_axis(item).partition('=')[0]}")
        return None
    names = load_axes(args.config, args.overrides, args.set_files).names
    axis = args.axis if args.axis is not None else (named[0][2] if named else None)
    if axis is None:
        raise ConfigError(f"{args.config} lists axes {', '.join(names)}; this command works on one: "
                          "pass --axis NAME")
    if axis not in names:
        raise ConfigError(f"--axis {axis}: no such axis in {args.config}; axes: {', '.join(names)}")
    for option, item, other in named:
        if other != axis:
            picked = "--axis" if args.axis is not None else f"the first key, {named[0][1].partition('=')[0]}"
            raise ConfigError(f"{option} {show_value(item)}: a key of axis {other}, but this command works "
                              f"on axis {axis} ({picked}); one axis per command")
    args.axis = axis
    return axis


def axis_keys(args: argparse.Namespace, options: dict[str, str]) -> str | None:
    """:func:`select_axis` over the varied keys in ``args.<attr>`` (``options``: attr ->
    option, ``{"ranges": "--range"}``), then those items with their ``axes.NAME.`` taken off."""
    axis = select_axis(args, [(option, getattr(args, attr)) for attr, option in options.items()])
    for attr in options:
        setattr(args, attr, [strip_axis(item) for item in getattr(args, attr)])
    return axis


def axis_config(args: argparse.Namespace) -> Config:
    """The config the command works on: ``args.axis``' of an axes config (after
    :func:`select_axis`), else the single-axis config."""
    if getattr(args, "axis", None):
        return load_axes(args.config, args.overrides, args.set_files).axis(args.axis).config
    return load_config(args.config, args.overrides, args.set_files)
