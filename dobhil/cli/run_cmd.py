"""``dobhil run`` (the force loop) and ``dobhil emulate`` (the emulator alone on a bus)."""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Callable
from typing import Any

from dobhil.cli.axis_option import add_axis_arg, select_axis
from dobhil.cli.common import EXIT_STOPPED, add_config_args, add_log_layout_arg, config_from_args, output_path
from dobhil.cli.preflight_lines import report_preflight, tell_refusal
from dobhil.cli.stop_lines import flush_stdout, say_last, say_safe_stop, stop_said
from dobhil.cli.stability_gate import add_gate_args


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser("run", help="run the force-control loop on a drive (or the emulator)")
    add_config_args(p)
    add_axis_arg(p)
    p.add_argument("--bus", metavar="INTERFACE:CHANNEL",
                   help="any python-can interface, e.g. socketcan:can0 (default: config/profile)")
    p.add_argument("--emulate", action="store_true", help="run against the in-process emulator")
    p.add_argument("--lockstep", action="store_true",
                   help="deterministic, as fast as possible (needs --emulate)")
    p.add_argument("--duration", type=float, metavar="S", help="override loop.duration")
    p.add_argument("--summary-json", action="store_true", help="print the summary as one JSON object")
    p.add_argument("--plot", type=output_path, metavar="FILE.png", help="plot reference and interaction torque")
    p.add_argument("--log", type=output_path, metavar="FILE.mcap",
                   help="record the run to MCAP (see docs/recording.md)")
    add_log_layout_arg(p)
    p.add_argument("--no-preflight", action="store_true",
                   help="do not measure the drive before enabling it (see dobhil check; "
                        "always skipped with --emulate, whose emulator is built from the profile)")
    p.add_argument("--preflight-window", type=float, metavar="S", default=None,
                   help="how long the preflight listens (default 0.5 s)")
    p.add_argument("--reset-faults", action="store_true",
                   help="let the drive clear a latched fault before enabling (the protocol's fault reset); "
                        "off: a faulted drive refuses to enable")
    p.add_argument("--live", metavar="[HOST:]PORT",
                   help="serve the run to Foxglove over WebSocket while it records (127.0.0.1 unless a host "
                        "is given; needs --log and the [live] extra)")
    add_gate_args(p)
    p.set_defaults(func=run)
    e = sub.add_parser("emulate", help="run the drive emulator alone on a bus (vcan0, a hub)")
    add_config_args(e)
    e.add_argument("--bus", required=True, metavar="INTERFACE:CHANNEL")
    e.add_argument("--duration", type=float, metavar="S", help="stop after S seconds (default: until Ctrl-C)")
    # dest of its own: a list of axes hosted together, not the single-axis commands' --axis
    e.add_argument("--axis", dest="emulate_axes", action="append", default=[], metavar="NAME",
                   help="with a config that lists axes: emulate this axis' drive (repeatable; default: "
                        "every axis, when they sit on one bus)")
    e.set_defaults(func=emulate)


def run(args: argparse.Namespace) -> int:
    from dobhil.config.axes import has_axes
    from dobhil.errors import PreflightError
    if has_axes(args.config) and args.axis is None:   # several axes in one loop
        from dobhil.cli.axes_run import run_axes
        return run_axes(args, prog="dobhil run", emulate=args.emulate, lockstep=True if args.lockstep else None,
                        plot=args.plot, log=args.log, live=args.live)
    try:
        return run_checked(args)
    except PreflightError as exc:  # the drive is not set up for this run: nothing was enabled
        tell_refusal(exc.report, "dobhil run")
        return EXIT_STOPPED


def run_checked(args: argparse.Namespace) -> int:
    """``dobhil run`` after the preflight (raises PreflightError when it refuses)."""
    from dobhil.cli.check_cmd import preflight_kwargs, refuse_budget
    from dobhil.config import resolve_config
    from dobhil.cli.recording import abort, live_address, log_summary, open_run_log, record_run
    from dobhil.cli.stability_gate import gate_metadata, gate_record, stability_gate
    from dobhil.files import check_output
    from dobhil.runtime.loop import StopRequest
    from dobhil.drives.load import load_drive_profile
    from dobhil.runtime.session import RunSession, check_duration, check_lockstep_run, is_lockstep, summary
    from dobhil.runtime.signals import stop_on_signals
    check_duration(args.duration)
    if args.axis is not None:   # one axis of an axes config, run alone
        select_axis(args)
    config = config_from_args(args)
    if args.plot:
        check_output(args.plot, inputs=[args.config], suffix=".png", what="--plot")
    refuse_budget(args, config, None if args.emulate else args.bus)   # over 100 %: before a bus opens
    if args.emulate and is_lockstep(config, True if args.lockstep else None):
        check_lockstep_run(load_drive_profile(config, resolve_config(args.config).parent), config.loop.period)
    # before any bus or log file: an unstable design is refused with nothing opened
    gate = stability_gate(config, args.config, allow_unstable=args.allow_unstable, prog="dobhil run")
    log = open_run_log(args.log, live=live_address(args.live, args.log), layout=args.log_layout)
    lower_writer(log)
    session: Any = None
    try:
        with stop_on_signals(StopRequest()) as request, \
                RunSession(config, bus=args.bus, emulate=args.emulate,
                           lockstep=True if args.lockstep else None, duration=args.duration,
                           config_dir=resolve_config(args.config).parent, stop_request=request,
                           reset_faults=args.reset_faults,
                           **log_hooks(log), **preflight_kwargs(args)) as session:
            if session.design_note:   # the drive's protocol fixes the command delay
                sys.stderr.write(f"dobhil run: {session.design_note}\n")
            report_preflight(session.preflight())
            if session.preflight_report is None:   # the preflight says it otherwise
                warn_budget(session)
            warn_realtime(session)
            result = record_run(session, log, args.config, metadata={
                "stability_gate": gate_metadata(gate, allow_unstable=args.allow_unstable)})
            info = summary(session, result)
            info["stability_gate"] = gate_record(gate, allow_unstable=args.allow_unstable)
    except BaseException as exc:
        abort(log, exc)
        tell_unfinished(session)
        raise
    if log is not None:
        info.update(log_summary(log, result.stop))
    report(info, result.stop.line(), as_json=args.summary_json)
    for problem in session.shutdown_problems:  # after the run's account, never instead of it
        if result.stop.reason.name != "BUS_ERROR":   # there the bus is already known gone
            sys.stderr.write(f"dobhil run: warning: bus shutdown failed: {problem}\n")
    if args.plot:
        from dobhil.plotting.run_plot import run_figure
        sys.stderr.write(f"wrote {run_figure(result.trace, args.plot)}\n")
    return 0 if result.stop.reason.name == "DONE" else EXIT_STOPPED


def tell_unfinished(session: Any) -> None:
    """An exception ended the run after the loop started: its stop line and, when the
    disable is not confirmed, the loud warning, before the error line main() prints."""
    ended = getattr(getattr(session, "loop", None), "ended", None)
    if ended is None:
        return
    stop, safe_stop = ended
    flush_stdout()
    sys.stderr.write(f"dobhil run: {stop.line()}\n")
    say_safe_stop(safe_stop.warning(), safe_stop.note())


def warn_budget(session: Any) -> None:
    """A bus budget over 70 % (and at most 100 %: over it :func:`run_checked` refused the
    run) is said, not refused (the frames still fit; late feedback then shows in the run's
    timing)."""
    from dobhil.cli.check_cmd import run_budget
    from dobhil.drives.preflight import configured_bitrate
    # an emulated bus has no bit rate: the budget is the one the configured bus would carry
    bitrate = (session.bus_spec.kwargs.get("bitrate")
               or configured_bitrate(session.config.drive.bitrate, session.profile))
    budget = run_budget(session.profile, session.settings.period, bitrate)
    if budget is not None and budget.over:
        sys.stderr.write(f"dobhil run: note (not refused: the run goes on): {budget.advice()}\n")


def warn_realtime(session: Any) -> None:
    """Ask for SCHED_FIFO / locked memory for a real-time run; warn (before the loop) if refused."""
    from dobhil.runtime.loop import Timing
    from dobhil.realtime import apply_realtime
    if session.timing is not Timing.LOCKSTEP:
        loop = session.config.loop
        for line in apply_realtime(loop.realtime_priority, loop.cpu_affinity):
            sys.stderr.write(f"dobhil run: warning: {line}\n")


def lower_writer(log: Any) -> None:
    """The writer process below the loop (nice +10): it is lossy in real time and may lag."""
    from dobhil.realtime import WRITER_PRIORITY_DROP, lower_priority
    if log is not None and log.writer_pid is not None:
        lower_priority(WRITER_PRIORITY_DROP, pid=log.writer_pid)


def log_hooks(log: Any) -> dict[str, Any]:
    """RunSession keyword arguments that record the run (none without a log)."""
    return {} if log is None else {"sink": log, "bus_wrapper": log.wrap_bus}


#: after a host_too_slow stop of an emulated real-time run: what to do instead
LOCKSTEP_HINT = ("dobhil run: hint: this machine was too busy for a real-time emulated run; on a loaded "
                 "machine run excitation runs (identify-free, identify-contact) with --lockstep: simulated "
                 "time, the same record, nothing can be late")


def stop_hint(info: dict[str, Any]) -> str:
    """One line of advice after the stop line, or "": an emulated real-time run stopped
    ``host_too_slow`` would not have with ``--lockstep``."""
    if info.get("stop_reason") == "host_too_slow" and info.get("emulated") and info.get("timing") != "lockstep":
        return LOCKSTEP_HINT
    return ""


def report(info: dict[str, Any], stop_line: str, *, as_json: bool) -> None:
    """The run's account: the summary (or its JSON) and the stop line, the loud line last
    (:func:`stop_said`)."""
    warning, stopped = info.get("drive_warning") or "", info.get("drive_note") or ""
    log_error = info.get("log_error") or ""
    with stop_said("dobhil run", stop_line, lambda: say_last("dobhil run", log_error, warning, stopped)):
        _account(info, stop_line, as_json=as_json)


def _account(info: dict[str, Any], stop_line: str, *, as_json: bool) -> None:
    hint = stop_hint(info)
    if not as_json:   # (in the JSON: drive_notes)
        for note in info.get("drive_notes", ()):
            sys.stderr.write(f"dobhil run: note (not refused: the run went on): {note}\n")
    if as_json:
        json.dump(info, sys.stdout)
        sys.stdout.write("\n")
        sys.stdout.flush()
        if hint:
            sys.stderr.write(f"{hint}\n")
        return
    if info["cycles"] == 0:  # nothing ran (e.g. the drive never answered): the reason only
        sys.stderr.write(f"dobhil run: {stop_line}\n")
        if hint:
            sys.stderr.write(f"{hint}\n")
        return
    f, t = info["final"], info["loop_timing"]
    skipped = info.get("skipped", 0)
    mode = ", torque mode (open loop)" if info.get("mode") == "torque" else ""
    print(f"{info['cycles']} cycles ({info['timing']}{mode}, T = {info['period']:g} s, bus {info['bus']}"
          f"{', emulated' if info['emulated'] else ''}); overruns {info['overruns']}"
          + (f", {skipped} {'frames' if info['timing'] == 'feedback' else 'deadlines'} skipped"
             if skipped else ""))
    print(stop_line)
    if hint:
        print(hint)
    if f["tau_ref"] is not None:
        true = "-" if f["tau_int_true"] is None else f"{f['tau_int_true']:.4f}"
        print(f"final: tau_ref {f['tau_ref']:.4f} N m, tau_int^ {f['tau_int_hat']:.4f} N m, "
              f"true tau_int {true} N m, q {f['q']:.6f} rad")
    print(f"loop: exec time p50 {t['exec_time_p50'] * 1e6:.0f} us, p99 {t['exec_time_p99'] * 1e6:.0f} us; "
          f"period error p99 {t['period_error_p99'] * 1e6:.0f} us, max {t['period_error_max'] * 1e6:.0f} us"
          + (f"; latency p99 {t['latency_p99'] * 1e6:.0f} us" if t.get("latency_p99") else ""))
    sampled = info.get("sample_latency_us")
    if sampled:   # the drive's sample instant (its SYNC) -> its feedback received
        print(f"sample latency: p50 {sampled['p50']:.0f} us, p99 {sampled['p99']:.0f} us, "
              f"max {sampled['max']:.0f} us")
    if info.get("log"):
        print(f"log: {info['log']}")
    sys.stdout.flush()


def emulate(args: argparse.Namespace) -> int:
    from dobhil.config import resolve_config
    from dobhil.drives.load import load_drive_profile
    from dobhil.emulator.plant import Plant
    from dobhil.drives.registry import make_emulated_drive
    from dobhil.runtime.buses import BusSpec, open_bus
    from dobhil.runtime.session import check_duration
    check_duration(args.duration)
    from dobhil.config.axes import has_axes
    if has_axes(args.config):
        return emulate_axes(args)
    if args.emulate_axes:
        from dobhil.errors import ConfigError
        raise ConfigError(f"--axis {args.emulate_axes[0]}: {args.config} lists no axes (a single-axis "
                          "config); drop --axis")
    config = config_from_args(args)
    profile = load_drive_profile(config, resolve_config(args.config).parent)
    spec = BusSpec.parse(args.bus)
    bus = open_bus(spec)
    _bus_carries(bus, [profile])
    emulator = make_emulated_drive(bus, profile, Plant.from_config(config),
                                   latency=config.drive.latency, jitter=config.drive.jitter,
                                   seed=config.sensor.seed)
    hello = (f"emulating {profile.protocol} node {profile.node_id} (firmware {profile.firmware}) "
             f"on {spec.describe()}")
    return _serve(emulator, bus, spec.describe(), hello, args.duration, lambda: emulator_counts(emulator))


def _bus_carries(bus: Any, profiles: list[Any]) -> None:
    """The emulated drives' frames can travel on ``bus`` (a CAN FD protocol on a classic bus
    would answer nothing, and say nothing of why), else one line, the bus shut down."""
    from dobhil.drives.registry import protocol
    try:
        for profile in profiles:
            protocol(profile.protocol).check_bus(bus, profile)
    except BaseException:
        bus.shutdown()
        raise


def _serve(emulator: Any, bus: Any, where: str, hello: str, duration: float | None,
           counts: Callable[[], str]) -> int:
    """Run ``emulator`` (a drive, or the nodes of one bus) on its thread until Ctrl-C,
    ``duration`` s or its bus fails; then stop it, shut ``bus`` down and print its counts
    (exit EXIT_STOPPED, on stderr, when the bus was lost)."""
    from dobhil.realtime import EMULATOR_PRIORITY_DROP
    from dobhil.runtime.loop import StopRequest
    from dobhil.runtime.signals import stop_on_signals
    with stop_on_signals(StopRequest()) as request:
        emulator.start(priority_drop=EMULATOR_PRIORITY_DROP)   # prepared: it answers at once
        print(f"{hello}; Ctrl-C to stop", flush=True)
        try:
            end = time.monotonic() + (duration or float("inf"))
            # the thread ends by itself when its bus fails (a hub stopped, an interface gone)
            while not request.is_set() and time.monotonic() < end and emulator.alive:
                time.sleep(0.05)
        finally:
            lost, problem = stop_emulator(emulator, bus)
    if lost:
        sys.stdout.flush()
        sys.stderr.write(f"dobhil emulate: stopped: bus {where} lost ({lost}); {counts()}\n")
        return EXIT_STOPPED
    print(f"emulator stopped: {counts()}", flush=True)
    if problem:
        sys.stderr.write(f"dobhil emulate: warning: bus shutdown failed: {problem}\n")
    return 0


def emulate_axes(args: argparse.Namespace) -> int:
    """``dobhil emulate`` of a config that lists axes: the hosted axes' drives on the one bus,
    on one tick clock, their plants coupled (dobhil.drives.emulated_nodes)."""
    from dobhil.config import resolve_config
    from dobhil.config.axes import load_axes
    from dobhil.drives.emulated_nodes import EmulatedNodes
    from dobhil.drives.registry import make_emulated_drive
    from dobhil.emulator.axes_nodes import hosted_axes, node_specs
    from dobhil.emulator.coupling import couple_plants
    from dobhil.emulator.plant import Plant
    from dobhil.runtime.buses import BusSpec, open_bus
    axes = load_axes(args.config, args.overrides, args.set_files)
    hosted = hosted_axes(axes, args.emulate_axes, how="--axis NAME (one dobhil emulate per bus)")
    specs, couplings = node_specs(axes, hosted, resolve_config(args.config).parent)
    spec = BusSpec.parse(args.bus)
    plants = couple_plants({s.name: Plant.from_config(s.config) for s in specs}, couplings)
    bus = open_bus(spec)
    _bus_carries(bus, [s.profile for s in specs])
    nodes = EmulatedNodes(bus)
    nodes.attach([make_emulated_drive(nodes.tap(), s.profile, plants[s.name], latency=s.latency,
                                      jitter=s.jitter, seed=s.seed) for s in specs])
    hosted_text = ", ".join(f"{s.profile.protocol} node {s.profile.node_id} ({s.name})" for s in specs)
    coupled = "".join(f"; coupled {c.a}-{c.b}" for c in couplings)
    return _serve(nodes, bus, spec.describe(), f"emulating {hosted_text} on {spec.describe()}{coupled}",
                  args.duration,
                  lambda: "; ".join(f"{s.name}: {emulator_counts(d)}" for s, d in zip(specs, nodes.drives)))


def emulator_counts(emulator: Any) -> str:
    """The emulator's frame counts for its last line: received (and of them, those for another
    node: a shared bus), sent, and the sends its bus
    refused (ENOBUFS: its transmit queue full; counted, the emulated drive goes on), the
    frames the host never got (dobhil/drives/emulated.py, ``EmulatedDrive._send``)."""
    counts = (f"{emulator.frames_received} frames received ({emulator.frames_not_addressed} not addressed to "
              f"node {emulator.profile.node_id}), {emulator.frames_sent} sent")
    refused = int(emulator.send_errors)
    return counts + (f", {refused} refused by the bus" if refused else "")


def stop_emulator(emulator: Any, bus: Any) -> tuple[str, str]:
    """Stop the emulator's thread, then shut its bus down: (why the bus was lost, why its
    shutdown failed), "" each when it did not. Any other error of the thread is raised
    (a bug), after the bus is shut down."""
    from dobhil.errors import BusError
    from dobhil.runtime.buses import shutdown_bus
    lost = ""
    try:
        emulator.stop()
    except BusError as exc:
        lost = str(exc)
    finally:
        problem = shutdown_bus(bus)
    return lost, problem
