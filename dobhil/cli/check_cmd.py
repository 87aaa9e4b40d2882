"""``dobhil check``: measure the drive on the bus without enabling it (the preflight).

Exit codes: 0 the drive matches the profile and ``loop.period``; 1 mismatches found
(each printed as one line saying what to set); 2 bad input (config, bus, arguments).
``dobhil run`` runs the same preflight before it enables a drive and refuses to start
when a run would sample stale feedback or the axis is already in closed loop
(``--no-preflight`` skips it); other mismatches it prints and runs, and the last line
here says which of the two the found mismatches mean. A bus that cannot be opened
names the way to try without hardware (``--bus dobhil:demo``). A config that lists
``axes:`` is checked axis by axis, with the bus budget of each bus and CAN-id clashes
between axes (:mod:`dobhil.cli.axes_check`); ``--axis NAME`` checks one of them alone.

``--set-zero`` (only for a protocol whose drives set their zero on command,
``DriveProtocol.sets_zero``; refused for any other before a bus opens): make the present
position the drive's zero, wait until it answers and print the position it reads. dobhil
never zeroes a drive otherwise.

Before the bus is opened, the design ``dobhil run`` would close on this drive passes the
stability gate (:mod:`dobhil.cli.stability_gate`): an unstable one is refused as ``run``
refuses it (exit 2; ``--allow-unstable`` measures the drive anyway), and the report's
second line is the gate's (``stability_gate`` in ``--json``).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
from pathlib import Path
from typing import Any

from dobhil.cli.axis_option import add_axis_arg, select_axis
from dobhil.cli.common import add_config_args, config_from_args
from dobhil.cli.stability_gate import add_gate_args
from dobhil.config.axes import has_axes
from dobhil.errors import ConfigError

#: exit code when the drive does not match (bad input stays 2)
EXIT_MISMATCH = 1


def register(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg,unused-ignore]
    p = sub.add_parser("check", help="measure the drive on the bus (no enable) and compare with the profile")
    add_config_args(p)
    add_axis_arg(p)
    p.add_argument("--bus", metavar="INTERFACE:CHANNEL",
                   help="any python-can interface, e.g. socketcan:can0 (default: config/profile)")
    p.add_argument("--window", type=float, metavar="S", default=None,
                   help="how long to listen (default 0.5 s: five heartbeats at a 0.1 s period)")
    p.add_argument("--json", action="store_true", help="print the report as one JSON object")
    p.add_argument("--set-zero", action="store_true",
                   help="drives that set their zero on command only: make the present position the "
                        "drive's zero, wait for its reply, print the new position; nothing else (no preflight)")
    add_gate_args(p)
    p.set_defaults(func=check)


def window_of(value: float | None, option: str) -> float:
    from dobhil.drives.preflight import DEFAULT_WINDOW
    if value is None:
        return DEFAULT_WINDOW
    if not (math.isfinite(value) and 0 < value <= 60):
        raise ConfigError(f"{option} {value!r}: expected seconds, > 0 and <= 60")
    return value


def preflight_kwargs(args: argparse.Namespace) -> dict[str, Any]:
    """RunSession keyword arguments from ``dobhil run``'s preflight options."""
    kwargs: dict[str, Any] = {"preflight_window": window_of(args.preflight_window, "--preflight-window")}
    if args.no_preflight:
        kwargs["preflight"] = False
    return kwargs


def check(args: argparse.Namespace) -> int:
    from dobhil.drives.preflight import run_preflight
    from dobhil.drives.registry import preflight_probe, protocol
    from dobhil.runtime.buses import open_bus, resolve_bus
    from dobhil.drives.load import load_drive_profile
    window = window_of(args.window, "--window")
    if args.axis is None and has_axes(args.config):   # every axis, its bus budget and clashes
        from dobhil.cli.axes_check import check_axes
        return check_axes(args, window)
    select_axis(args)
    config = config_from_args(args)
    profile = load_drive_profile(config, Path(args.config).parent)
    if args.set_zero:
        return set_zero(args, config, profile)
    from dobhil.runtime.session import check_host_watch
    check_host_watch(profile, config.loop.period)   # as dobhil run refuses it, before the bus opens
    refuse_budget(args, config, args.bus)
    from dobhil.cli.stability_gate import stability_gate
    # the design dobhil run would close on this drive, judged before the bus is opened
    gate = stability_gate(config, args.config, allow_unstable=args.allow_unstable, prog="dobhil check")
    spec = resolve_bus(config, profile, args.bus)
    bus = open_bus(spec)
    try:
        protocol(profile.protocol).check_bus(bus, profile)
        report = run_preflight(bus, profile, period=config.loop.period,
                               feedback_timeout=config.loop.feedback_timeout, window=window,
                               bitrate=spec.kwargs.get("bitrate") or None, probe=preflight_probe(profile))
    finally:
        bus.shutdown()
    if args.json:
        json.dump({"bus": spec.describe(), **report.as_dict(), "stability_gate": gate.as_dict()}, sys.stdout)
        sys.stdout.write("\n")
    else:
        print(f"bus {spec.describe()}")
        print(f"stability gate: {gate.summary()}")   # the design's line; the drive's follow
        for line in report.lines():
            print(line)
    return 0 if report.ok else EXIT_MISMATCH


def set_zero(args: argparse.Namespace, config: Any, profile: Any) -> int:
    """``--set-zero``: the only way dobhil zeroes a drive (``DriveProtocol.set_zero``), refused
    for a protocol that cannot before a bus is opened; Ctrl-C ends the wait within a slice."""
    import time

    from dobhil.drives.registry import protocol
    from dobhil.runtime.buses import open_bus, resolve_bus
    from dobhil.runtime.loop import StopRequest
    from dobhil.runtime.signals import stop_on_signals
    drive_protocol = protocol(profile.protocol)
    if not drive_protocol.sets_zero:
        able = " or ".join(repr(name) for name in zeroing_protocols())
        raise ConfigError(f"--set-zero: expected a profile of protocol {able} (drives that set their zero on "
                          f"command), profile {profile.name or profile.protocol!r} is protocol {profile.protocol!r}")
    spec = resolve_bus(config, profile, args.bus)
    bus = open_bus(spec)
    try:
        with stop_on_signals(StopRequest()) as request:
            result = drive_protocol.set_zero(bus, profile, clock=time.monotonic, cancel=request.reason)
    finally:
        bus.shutdown()
    if args.json:
        json.dump({"bus": spec.describe(), "node_id": result.node, "position": result.position,
                   "zero_silence": result.silence}, sys.stdout)
        sys.stdout.write("\n")
    else:
        print(f"bus {spec.describe()}")
        print(result.line())
    return 0


def zeroing_protocols() -> list[str]:
    """The protocols whose drives set their zero on command (one that fails to load is left
    out: naming it fails with its own line)."""
    from dobhil.drives.registry import protocol, protocols
    able = []
    for name in protocols():
        try:
            if protocol(name).sets_zero:
                able.append(name)
        except ConfigError:
            continue
    return able


def refuse_budget(args: argparse.Namespace, config: Any, bus: str | None) -> None:
    """Before any bus opens, a single-axis run's or check's bus budget over 100 % is refused
    (ConfigError, one line, exit 2) by the rule and in the words of a several-axis one
    (:func:`dobhil.drives.axes.drive_budget`): the frames of one period do not fit in it, and
    the run would end in a bus error. ``bus``: ``--bus`` (None with ``--emulate``)."""
    from dobhil.config import resolve_config
    from dobhil.config.axes import SINGLE_AXIS, Axis
    from dobhil.drives.axes import drive_budget
    from dobhil.drives.load import load_drive_profile
    config_dir = resolve_config(args.config).parent
    # the profile read as the run reads it first: a bad one is the run's own line, not an axis'
    load_drive_profile(config, config_dir)
    if bus:   # --bus comes before drive.interface in a single-axis run (resolve_bus)
        config = dataclasses.replace(config, drive=dataclasses.replace(config.drive, interface="", channel=""))
    drive_budget(Axis(args.axis or SINGLE_AXIS, config), config_dir, bus)


def run_budget(profile: Any, period: float, bitrate: int | None) -> Any:
    """The bus budget of a run of ``profile`` at ``period`` (None: its protocol lists no
    frames), without a bus: what ``dobhil analyze`` and an emulated ``dobhil run`` say."""
    from dobhil.drives.registry import preflight_probe
    probe = preflight_probe(profile)
    return None if probe is None else probe.budget(period, bitrate)
