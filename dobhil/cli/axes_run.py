"""``dobhil run`` and ``dobhil demo`` of a config that lists ``axes:`` (several axes in one
loop, :class:`~dobhil.runtime.axes_session.AxesSession`): the same options as a
single-axis run where they mean the same, one stop line naming the axis that stopped the
run, one loud line naming every axis not confirmed disabled, the exit codes of a
single-axis run (0 done, 1 a safety stop, 2 bad input)."""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

from dobhil.cli.common import EXIT_STOPPED
from dobhil.recording.layouts import DEFAULT_LAYOUT
from dobhil.cli.recording import AxisRun, begin_axes, end_axes, log_summary
from dobhil.recording.axeslog import axis_record

if TYPE_CHECKING:   # the session is built when a run starts: --help stays light
    from dobhil.recording.axeslog import AxesLog
    from dobhil.runtime.axes_loop import AxesResult
    from dobhil.runtime.axes_session import AxesSession


def run_axes(args: argparse.Namespace, *, prog: str, emulate: bool, lockstep: bool | None,
             plot: Path | None = None, log: Path | None = None, live: str | None = None) -> int:
    """Run the axes of ``args.config``; ``plot``: one PNG per axis (``NAME-<axis>.png``);
    ``log``: record the run (:class:`~dobhil.recording.axeslog.AxesLog`, topics per axis and
    per bus), ``live``: serve it to Foxglove as well."""
    from dobhil.cli.axes_gate import axes_gate_metadata
    from dobhil.cli.recording import abort_axes, live_address, open_axes_log
    from dobhil.cli.stability_gate import summary_of_records
    from dobhil.config import resolve_config
    from dobhil.config.axes import load_axes
    from dobhil.files import check_output
    from dobhil.runtime.axes_session import AxesSession, axes_summary
    from dobhil.runtime.loop import StopRequest
    from dobhil.runtime.session import check_duration
    from dobhil.runtime.signals import stop_on_signals
    duration = getattr(args, "duration", None)
    check_duration(duration)
    path = resolve_config(args.config)
    axes = load_axes(path, args.overrides, args.set_files)
    if plot is not None:
        for axis in axes.axes:
            check_output(_axis_png(plot, axis.name), inputs=[path], suffix=".png", what="--plot")
    # before any bus or log file: clashes, a bus over 100 % and an unstable design (each axis
    # alone, each coupled group as one loop) are refused with nothing opened
    gates = preflight_axes(args, axes, path, prog=prog, emulate=emulate, lockstep=lockstep)
    if gates is None:
        return EXIT_STOPPED
    gate_records = axes_gate_metadata(gates, allow_unstable=args.allow_unstable)
    recorder = open_axes_log(log, axes.names, live=live_address(live, log),
                             layout=getattr(args, "log_layout", DEFAULT_LAYOUT))
    if recorder is not None and recorder.writer_pid is not None:
        # the writer below the loop (nice +10): it is lossy in real time and may lag
        from dobhil.realtime import WRITER_PRIORITY_DROP, lower_priority
        lower_priority(WRITER_PRIORITY_DROP, pid=recorder.writer_pid)
    session: Any = None
    try:
        with stop_on_signals(StopRequest()) as request, \
                AxesSession(axes, bus=getattr(args, "bus", None), emulate=emulate, lockstep=lockstep,
                            duration=duration, config_dir=path.parent, stop_request=request,
                            reset_faults=getattr(args, "reset_faults", False), **log_hooks(recorder)) as session:
            _realtime(session, prog)
            result = record_axes(session, recorder, path, _gate_records(gate_records))
            info = axes_summary(session, result)
            info["stability_gate"] = summary_of_records(gate_records)
    except BaseException as exc:
        abort_axes(recorder, exc)
        tell_unfinished(session, prog)
        raise
    if recorder is not None:
        info.update(log_summary(recorder, result.stop))
    report(info, result.stop.line(), prog=prog, as_json=getattr(args, "summary_json", False))
    for problem in session.shutdown_problems:
        if result.stop.reason.name != "BUS_ERROR":
            sys.stderr.write(f"{prog}: warning: bus shutdown failed: {problem}\n")
    if plot is not None:
        from dobhil.plotting.run_plot import run_figure
        for name, part in result.axes.items():
            sys.stdout.write(f"wrote {run_figure(part.trace, _axis_png(plot, name), f'axis {name}')}\n")
    return 0 if result.stop.reason.name == "DONE" else EXIT_STOPPED


def preflight_axes(args: argparse.Namespace, axes: Any, path: Path, *, prog: str,
                   emulate: bool, lockstep: bool | None = None) -> dict[str, Any] | None:
    """What a run checks before it opens a bus for the loop: every axis' drive and the
    clashes between them, each bus' budget (over 100 %: refused; over 70 %: one line of
    advice), the stability gate of every axis and coupled group
    (:func:`~dobhil.cli.axes_gate.axes_gate`), and on a real bus each axis' preflight as
    ``dobhil check`` measures it (:func:`~dobhil.cli.axes_check.measure_axes`). Returns the
    gate's verdicts, or None when a preflight refused the run (its lines printed)."""
    from dobhil.cli.axes_check import measure_axes
    from dobhil.cli.axes_gate import axes_gate
    from dobhil.cli.check_cmd import window_of
    from dobhil.cli.preflight_lines import report_preflight, tell_refusal
    from dobhil.drives.axes import axes_budget, axis_drives
    from dobhil.runtime.session import check_host_watch, check_lockstep, is_lockstep
    bus = None if emulate else getattr(args, "bus", None)
    drives = axis_drives(axes, path.parent, bus)
    for budget in axes_budget(drives, axes.period):
        if budget.over:
            sys.stderr.write(f"{prog}: warning: {budget.advice()}\n")
    in_lockstep = emulate and is_lockstep(axes.axes[0].config, lockstep)
    for d in drives:   # the session refuses these too; here before a bus opens and the gate's lines
        check_host_watch(d.profile, axes.period, f"axis {d.name}: ")   # as check does
        if in_lockstep:   # each bus' lockstep bus steps at the axes' period
            check_lockstep(d.profile, axes.period, f"axis {d.name}: ")
    gates = axes_gate(axes, path, {d.name: d.profile for d in drives},
                      allow_unstable=args.allow_unstable, prog=prog)
    if emulate or getattr(args, "no_preflight", False):
        return gates
    window = window_of(getattr(args, "preflight_window", None), "--preflight-window")
    from dobhil.runtime.loop import StopRequest
    from dobhil.runtime.signals import stop_on_signals
    from dobhil.runtime.stop import Stop, StopReason
    # a signal while the drives are measured stops as in the loop, nothing ever enabled
    # (dobhil run of one axis: RunSession.preflight)
    with stop_on_signals(StopRequest()) as request:
        measured = measure_axes(axes, drives, window, bus, cancel=request.reason)
    if request.is_set():
        sys.stderr.write(f"{prog}: {Stop(StopReason.SIGNAL, request.reason(), -1, 0.0).line()}\n")
        return None
    refused = False
    for name, _, report in measured:
        if report.refuses:
            tell_refusal(report, f"{prog}: axis {name}")
            refused = True
        else:
            report_preflight(report, prog=f"{prog}: axis {name}")
    return None if refused else gates


def _gate_records(records: Mapping[str, Mapping[str, str]]) -> dict[str, dict[str, str]]:
    """The gate's records as the log's metadata: one axis' under ``axis/<name>/stability_gate``,
    a coupled group's (``left+right``) under ``stability_gate/<group>``."""
    return {(f"stability_gate/{key}" if "+" in key else axis_record(key, "stability_gate")): dict(record)
            for key, record in records.items()}


def log_hooks(log: AxesLog | None) -> dict[str, Any]:
    """AxesSession keyword arguments that record the run: ``sinks`` (one per axis) and
    ``bus_wrapper`` (one tap per bus, its frames on ``/bus/<bus>/can/...``); none without a log."""
    if log is None:
        return {}
    return {"sinks": {name: log.sink(name) for name in log.names}, "bus_wrapper": log.wrap_bus}


def axis_runs(session: AxesSession) -> list[AxisRun]:
    """Each axis of ``session`` as its log records it (its bus under the configured name)."""
    runs = []
    for group in session.groups:
        for name in group.axes:
            controller = session.controllers[name]
            runs.append(AxisRun(name, session.axes.axis(name).config, session.profiles[name], session.drives[name],
                                group.name, group.spec, controller.torque_limit, controller.measures_velocity,
                                session.plant(name)))
    order = {name: i for i, name in enumerate(session.axes.names)}
    return sorted(runs, key=lambda r: order[r.name])


def record_axes(session: AxesSession, log: AxesLog | None, config_file: Path,
                metadata: Mapping[str, Mapping[str, str]]) -> AxesResult:
    """``session.run()`` recorded by ``log`` (each axis' drive, profile, bus and truth before
    the loop; each axis' disable and the stop after it); a writer failure is the stop reason
    ``recorder_failed``. The caller aborts the log if this raises."""
    if log is None:
        return session.run()
    begin_axes(log, axis_runs(session), timing=session.timing, period=session.period,
               duration=session.settings[session.axes.names[0]].duration, emulated=session.emulate,
               sim_clock=session.sim_clock, couplings=session.axes.couplings, config_file=config_file,
               metadata=metadata, cancel=session.stop_request.reason)
    result = session.run()
    stop = end_axes(log, result.stop, {name: part.disabled for name, part in result.axes.items()},
                    axis=result.axis, cancel=session.stop_request.newer())
    return result if stop is result.stop else dataclasses.replace(result, stop=stop)


def _axis_png(plot: Path, axis: str) -> Path:
    return plot.with_name(f"{plot.stem}-{axis}{plot.suffix or '.png'}")


def _realtime(session: Any, prog: str) -> None:
    """Ask for SCHED_FIFO / locked memory for a real-time run; warn (before the loop) if refused."""
    from dobhil.realtime import apply_realtime
    from dobhil.runtime.loop import Timing
    if session.timing is not Timing.LOCKSTEP:
        loop = session.axes.axes[0].config.loop
        for line in apply_realtime(loop.realtime_priority, loop.cpu_affinity):
            sys.stderr.write(f"{prog}: warning: {line}\n")


def tell_unfinished(session: Any, prog: str) -> None:
    """An exception ended the run after the loop started: its stop line and the loud line
    for every axis not confirmed disabled, before the error line main() prints."""
    loop = getattr(session, "loop", None)
    ended = getattr(loop, "ended", None)
    if loop is None or ended is None:
        return
    stop, _ = ended
    from dobhil.cli.stop_lines import flush_stdout
    flush_stdout()
    sys.stderr.write(f"{prog}: {stop.line()}\n")
    warnings = []
    for name, axis_loop in loop.loops.items():
        report = axis_loop.ended[1] if axis_loop.ended is not None else None
        if report is None or report.warning():
            warnings.append(f"axis {name}: " + (report.warning() if report is not None else "no safe stop"))
    if warnings:
        sys.stderr.write(f"WARNING: {'; '.join(warnings)}\n")


def report(info: dict[str, Any], stop_line: str, *, prog: str, as_json: bool) -> None:
    """The run's account: the summary (or its JSON), the stop line, the loud line last,
    whatever stdout does (:func:`dobhil.cli.stop_lines.stop_said`)."""
    from dobhil.cli.stop_lines import say_last, stop_said
    warning = info.get("drive_warning") or ""
    notes = "; ".join(f"axis {n}: {a['drive_note']}" for n, a in info["axes"].items() if a.get("drive_note"))
    with stop_said(prog, stop_line, lambda: say_last(prog, info.get("log_error") or "", warning, notes)):
        if as_json:
            json.dump(info, sys.stdout)
            sys.stdout.write("\n")
        else:
            _print_summary(info, stop_line, prog)
        sys.stdout.flush()


def _print_summary(info: dict[str, Any], stop_line: str, prog: str) -> None:
    if info["cycles"] == 0:   # nothing ran (an axis never enabled): the reason only
        sys.stderr.write(f"{prog}: {stop_line}\n")
        return
    buses = info["buses"]
    skipped = info.get("skipped", 0)
    print(f"{info['cycles']} cycles ({info['timing']}, T = {info['period']:g} s, {len(info['axes'])} axes on "
          f"{len(buses)} bus{'es' if len(buses) > 1 else ''}{', emulated' if info['emulated'] else ''}); "
          f"overruns {info['overruns']}" + (f", {skipped} deadlines skipped" if skipped else ""))
    print(stop_line)
    for name, axis in info["axes"].items():
        f = axis["final"]
        head = f"axis {name} ({axis['protocol']} node {axis['node_id']}, bus {axis['bus']})"
        if f["tau_ref"] is None:
            print(f"{head}: no cycle")
            continue
        true = "-" if f["tau_int_true"] is None else f"{f['tau_int_true']:.4f}"
        print(f"{head}: final tau_ref {f['tau_ref']:.4f} N m, tau_int^ {f['tau_int_hat']:.4f} N m, "
              f"true tau_int {true} N m, q {f['q']:.6f} rad")
        if axis.get("frames_lost"):   # its bus queue overflowed: frames for it never read
            print(f"axis {name}: {axis['frames_lost']} frames lost (its queue on the shared bus was full)")
    if info.get("log"):
        print(f"log: {info['log']}")
    t = info["loop_timing"]
    print(f"loop: exec time (all axes) p50 {t['exec_time_p50'] * 1e6:.0f} us, p99 {t['exec_time_p99'] * 1e6:.0f} us; "
          f"period error p99 {t['period_error_p99'] * 1e6:.0f} us, max {t['period_error_max'] * 1e6:.0f} us")
