"""``dobhil run`` (the force loop) and ``dobhil emulate`` (the emulator alone on a bus)."""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

from dobhil.cli.common import add_config_args, config_from_args

#: exit code of a run that ended in a safety stop (not bad input)
EXIT_STOPPED = 1


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("run", help="run the force-control loop on a drive (or the emulator)")
    add_config_args(p)
    p.add_argument("--bus", metavar="INTERFACE:CHANNEL",
                   help="any python-can interface, e.g. socketcan:can0 (default: config/profile)")
    p.add_argument("--emulate", action="store_true", help="run against the in-process emulator")
    p.add_argument("--lockstep", action="store_true",
                   help="deterministic, as fast as possible (needs --emulate)")
    p.add_argument("--duration", type=float, metavar="S", help="override loop.duration")
    p.add_argument("--summary-json", action="store_true", help="print the summary as one JSON object")
    p.add_argument("--plot", type=Path, metavar="FILE.png", help="plot reference and interaction torque")
    p.add_argument("--log", type=Path, metavar="FILE.mcap",
                   help="record the run to MCAP (see docs/recording.md)")
    p.add_argument("--live", metavar="[HOST:]PORT",
                   help="serve the run to Foxglove over WebSocket while it records (127.0.0.1 unless a host "
                        "is given; needs --log and the [live] extra)")
    p.set_defaults(func=run)
    e = sub.add_parser("emulate", help="run the drive emulator alone on a bus (vcan0, a hub)")
    add_config_args(e)
    e.add_argument("--bus", required=True, metavar="INTERFACE:CHANNEL")
    e.add_argument("--duration", type=float, metavar="S", help="stop after S seconds (default: until Ctrl-C)")
    e.set_defaults(func=emulate)


def run(args: argparse.Namespace) -> int:
    from dobhil.cli.recording import abort, live_address, open_run_log, record_run
    from dobhil.files import check_output
    from dobhil.runtime.loop import StopRequest
    from dobhil.runtime.session import RunSession, summary
    from dobhil.runtime.signals import stop_on_signals
    config = config_from_args(args)
    if args.plot:
        check_output(args.plot, inputs=[args.config], suffix=".png", what="--plot")
    log = open_run_log(args.log, live=live_address(args.live, args.log))
    try:
        with stop_on_signals(StopRequest()) as request, \
                RunSession(config, bus=args.bus, emulate=args.emulate,
                           lockstep=True if args.lockstep else None, duration=args.duration,
                           config_dir=Path(args.config).parent, stop_request=request,
                           **log_hooks(log)) as session:
            warn_realtime(session)
            result = record_run(session, log, args.config)
            info = summary(session, result)
    except BaseException as exc:
        abort(log, exc)
        raise
    if log is not None:
        info["log"] = str(log.path)
    report(info, result.stop.line(), as_json=args.summary_json)
    if args.plot:
        from dobhil.plotting.run_plot import run_figure
        sys.stderr.write(f"wrote {run_figure(result.trace, args.plot)}\n")
    return 0 if result.stop.reason.name == "DONE" else EXIT_STOPPED


def warn_realtime(session: Any) -> None:
    """Ask for SCHED_FIFO / locked memory for a real-time run; warn (before the loop) if refused."""
    from dobhil.runtime.loop import Timing
    from dobhil.runtime.realtime import apply_realtime
    if session.timing is Timing.REALTIME:
        for line in apply_realtime(session.config.loop.realtime_priority):
            sys.stderr.write(f"dobhil run: warning: {line}\n")


def log_hooks(log: Any) -> dict[str, Any]:
    """RunSession keyword arguments that record the run (none without a log)."""
    return {} if log is None else {"sink": log, "bus_wrapper": log.wrap_bus}


def report(info: dict[str, Any], stop_line: str, *, as_json: bool) -> None:
    if as_json:
        json.dump(info, sys.stdout)
        sys.stdout.write("\n")
        return
    if info["cycles"] == 0:  # nothing ran (e.g. the drive never answered): the reason only
        sys.stderr.write(f"dobhil run: {stop_line}\n")
        return
    f, t = info["final"], info["loop_timing"]
    print(f"{info['cycles']} cycles ({info['timing']}, T = {info['period']:g} s, bus {info['bus']}"
          f"{', emulated' if info['emulated'] else ''}); overruns {info['overruns']}")
    print(stop_line)
    if f["tau_ref"] is not None:
        true = "-" if f["tau_int_true"] is None else f"{f['tau_int_true']:.4f}"
        print(f"final: tau_ref {f['tau_ref']:.4f} N m, tau_int^ {f['tau_int_hat']:.4f} N m, "
              f"true tau_int {true} N m, q {f['q']:.6f} rad")
    print(f"loop: exec time p50 {t['exec_time_p50'] * 1e6:.0f} us, p99 {t['exec_time_p99'] * 1e6:.0f} us; "
          f"period error p99 {t['period_error_p99'] * 1e6:.0f} us, max {t['period_error_max'] * 1e6:.0f} us")
    if info.get("log"):
        print(f"log: {info['log']}")
    if not info["drive_disabled"]:
        print("WARNING: the disable frames could not be sent; check the drive")


def emulate(args: argparse.Namespace) -> int:
    from dobhil.emulator.plant import Plant
    from dobhil.emulator.registry import make_emulated_drive
    from dobhil.runtime.buses import BusSpec, open_bus
    from dobhil.runtime.loop import StopRequest
    from dobhil.runtime.session import load_drive_profile
    from dobhil.runtime.signals import stop_on_signals
    config = config_from_args(args)
    profile = load_drive_profile(config, Path(args.config).parent)
    spec = BusSpec.parse(args.bus)
    bus = open_bus(spec)
    emulator = make_emulated_drive(bus, profile, Plant.from_config(config),
                                   latency=config.drive.latency, jitter=config.drive.jitter,
                                   seed=config.sensor.seed)
    print(f"emulating {profile.protocol} node {profile.node_id} (firmware {profile.firmware}) "
          f"on {spec.describe()}; Ctrl-C to stop", flush=True)
    with stop_on_signals(StopRequest()) as request:
        emulator.start()
        try:
            end = time.monotonic() + (args.duration or float("inf"))
            while not request.is_set() and time.monotonic() < end:
                time.sleep(0.05)
        finally:
            emulator.close()
    print(f"emulator stopped: {emulator.frames_received} frames received, "
          f"{emulator.frames_sent} sent", flush=True)
    return 0
