"""``dobhil check AXES.yaml``: the preflight of every axis of a config that lists ``axes:``.

Before any bus is opened: each axis' profile with its ``drive.node_id``, CAN-id clashes of
axes on one bus and the bus budget of all the axes of each bus
(:mod:`dobhil.drives.axes`), then each design through the stability gate (an axis alone,
or the coupled loop of axes joined by couplings: :mod:`dobhil.cli.axes_gate`). A clash, a
bus over 100 % or an unstable design is refused there (one line, exit 2): nothing is sent.
Then each bus is opened once and each of its axes measured as ``dobhil check`` measures one
drive (:func:`dobhil.drives.preflight.run_preflight`, nothing enabled), its lines prefixed
with the axis' name. Exit 0 when every axis matches its profile and no bus is over 70 %,
1 otherwise (each mismatch one line saying what to set), 2 for bad input.

``--bus`` is the bus of every axis whose config names none (``drive.interface``); ``--axis
NAME`` checks one axis as a single-axis config (``--set-zero`` needs it).
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable, Sequence
from typing import Any

from dobhil.errors import ConfigError

__all__ = ["check_axes", "measure_axes"]

#: exit code when a drive does not match or a bus is over its budget (as dobhil check)
EXIT_MISMATCH = 1


def check_axes(args: argparse.Namespace, window: float) -> int:
    """``dobhil check`` of an axes config (see the module docstring), each drive listened to
    for ``window`` s."""
    from dobhil.config import resolve_config
    from dobhil.config.axes import load_axes
    from dobhil.drives.axes import axes_budget, axis_drives
    from dobhil.runtime.session import check_host_watch
    if args.set_zero:
        raise ConfigError("--set-zero zeroes one drive; with a config that lists axes give the axis: --axis NAME")
    axes = load_axes(args.config, args.overrides, args.set_files)
    drives = axis_drives(axes, resolve_config(args.config).parent, args.bus)
    for d in drives:   # as dobhil run refuses it (AxesSession: check_rates), before a bus opens
        check_host_watch(d.profile, axes.period, f"axis {d.name}: ")
    budgets = axes_budget(drives, axes.period)   # over 100 %: refused here, before a bus opens
    from dobhil.cli.axes_gate import axes_gate
    gates = list(axes_gate(axes, args.config, {d.name: d.profile for d in drives},
                           allow_unstable=args.allow_unstable, prog="dobhil check").items())
    reports = measure_axes(axes, drives, window, args.bus)
    ok = all(r.ok for _, _, r in reports) and not any(b.over for b in budgets)
    if args.json:
        json.dump(_as_json(budgets, gates, reports, ok), sys.stdout)
        sys.stdout.write("\n")
    else:
        for line in _lines(budgets, gates, reports, ok):
            print(line)
    return 0 if ok else EXIT_MISMATCH


def measure_axes(axes: Any, drives: Sequence[Any], window: float,
                 default_bus: str | None, cancel: Callable[[], str] | None = None) -> list[tuple[str, str, Any]]:
    """(axis, bus, preflight report) of every axis, each bus opened once for its axes and
    closed before the next (nothing enabled; ``dobhil run`` of a real bus calls it too);
    ``cancel`` (a stop request's ``reason``) cuts each measurement short."""
    from dobhil.drives.axes import bus_budgets
    from dobhil.drives.bus_load import frame_bits
    from dobhil.drives.preflight import run_preflight
    from dobhil.drives.registry import preflight_probe, protocol
    from dobhil.runtime.buses import open_bus, resolve_bus, shared_spec, shutdown_bus
    out: list[tuple[str, str, Any]] = []
    for bus_name in dict.fromkeys(d.bus for d in drives):
        on_bus = [(axes.axis(d.name).config, d) for d in drives if d.bus == bus_name]
        # one bus opened for every drive on it (a CAN FD drive's fd whichever axis is first)
        spec = shared_spec([resolve_bus(config, d.profile, None if config.drive.interface else default_bus)
                            for config, d in on_bus])
        # what the run adds on this bus is every axis' frames, not the measured axis' alone
        # (one 8-byte command for an axis whose protocol lists none, as run_preflight counts it)
        (budget,) = bus_budgets([d for _, d in on_bus], axes.period)
        run_bits = budget.budget.loop_bits() + len(budget.unknown) * frame_bits(8)
        bus = open_bus(spec)
        try:
            for config, drive in on_bus:
                protocol(drive.profile.protocol).check_bus(bus, drive.profile)
                report = run_preflight(bus, drive.profile, period=config.loop.period,
                                       feedback_timeout=config.loop.feedback_timeout, window=window,
                                       bitrate=drive.bitrate, probe=preflight_probe(drive.profile),
                                       cancel=cancel, run_loop_bits=run_bits)
                if cancel is not None and cancel():
                    return out
                out.append((drive.name, spec.describe(), report))
        finally:
            shutdown_bus(bus)
    return out


def _lines(budgets: Sequence[Any], gates: Sequence[tuple[str, Any]], reports: Sequence[tuple[str, str, Any]],
           ok: bool) -> list[str]:
    lines = [b.line() for b in budgets]
    lines += [f"mismatch: {b.advice()}" for b in budgets if b.over]
    lines += [f"{_who(key)}: stability gate: {gate.summary()}" for key, gate in gates]
    for name, bus, report in reports:
        lines.append(f"axis {name}: bus {bus}")
        lines += [f"axis {name}: {line}" for line in report.lines()]
    bad = [name for name, _, r in reports if not r.ok]
    over = [b.bus for b in budgets if b.over]
    lines.append("preflight: ok, every axis" if ok else "preflight: "
                 + "; ".join(([f"mismatches on axis {', '.join(bad)}"] if bad else [])
                             + ([f"bus {', '.join(over)} over its budget"] if over else [])))
    return lines


def _who(key: str) -> str:
    """``axis left`` or, for a coupled group's key, ``axes left+right``."""
    return f"axes {key}" if "+" in key else f"axis {key}"


def _as_json(budgets: Sequence[Any], gates: Sequence[tuple[str, Any]], reports: Sequence[tuple[str, str, Any]],
             ok: bool) -> dict[str, Any]:
    gate_of = {name: gate for key, gate in gates for name in key.split("+")}
    return {"ok": ok, "buses": [{"line": b.line(), "advice": b.advice(), **b.as_dict()} for b in budgets],
            "axes": [{"axis": name, "bus_name": bus, **report.as_dict(), "stability_gate": gate_of[name].as_dict()}
                     for name, bus, report in reports]}
