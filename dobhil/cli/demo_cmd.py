"""``dobhil demo``: the main job on a fresh clone -- a force-control run of ``configs/demo.yaml``
(the paper's Fig. 3 servo touching its environment, then a force step) over the emulated
drive of its profile on a CAN bus, in lockstep; prints a summary and writes a PNG."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from dobhil.cli.common import add_config_args, add_log_layout_arg, output_path
from dobhil.cli.stability_gate import add_gate_args


def demo_config_path() -> Path:
    """The shipped ``demo`` config (``configs/demo.yaml`` in the repository)."""
    from dobhil.config import resolve_config
    return resolve_config("demo")


def demo_title(profile: Any, period: float) -> str:
    """The figure's title: the run, and the drive it ran on (the profile's name, else its
    protocol's title) at the loop's rate."""
    from dobhil.drives.registry import protocol
    drive = profile.name or protocol(profile.protocol).title
    return f"dobhil demo: contact, then a force step (emulated {drive}, {1e-3 / period:g} kHz)"


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser("demo", help="emulated force-control run of configs/demo.yaml, with a plot")
    add_config_args(p, required=False)
    p.add_argument("--out", type=output_path, default=Path("out/demo"), help="output directory")
    p.add_argument("--realtime", action="store_true", help="real time instead of lockstep")
    p.add_argument("--log", type=output_path, metavar="FILE.mcap",
                   help="MCAP recording (default: OUT/run-YYYYmmdd-HHMMSS.mcap)")
    p.add_argument("--no-log", action="store_true", help="do not record the run")
    add_log_layout_arg(p)
    p.add_argument("--live", metavar="[HOST:]PORT",
                   help="then play the recorded run to Foxglove over WebSocket at its pace, as `dobhil log serve` "
                        "does: prints the address and waits for a client to subscribe (Ctrl-C to stop); the "
                        "demo lasts about a second, over before Foxglove could connect (127.0.0.1 unless a host "
                        "is given; needs the [live] extra)")
    add_gate_args(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from dobhil.cli.recording import abort, default_log_path, log_summary, open_run_log, record_run
    from dobhil.cli.run_cmd import EXIT_STOPPED, log_hooks, report
    from dobhil.cli.stability_gate import gate_metadata, stability_gate
    from dobhil.config import load_config
    from dobhil.files import check_output
    from dobhil.plotting.run_plot import run_figure
    from dobhil.runtime.loop import StopRequest
    from dobhil.drives.load import load_drive_profile
    from dobhil.runtime.session import RunSession, check_lockstep_run, summary
    from dobhil.runtime.signals import stop_on_signals
    from dobhil.config import resolve_config
    from dobhil.errors import ConfigError
    if args.no_log and args.log is not None:
        raise ConfigError("--no-log with --log: give one (record the run to --log, or not at all)")
    if args.no_log and args.live is not None:   # not "--live needs a log (--log ...)": --log is refused with it
        raise ConfigError("--no-log with --live: the live view plays the run's log; drop --no-log "
                          "(the run is then recorded to OUT/run-*.mcap) or --live")
    if args.live is not None:   # the address and the extra checked before the run, served after it
        _check_live(args.live)
    path = resolve_config(args.config) if args.config else demo_config_path()
    from dobhil.config.axes import has_axes
    if has_axes(path):   # several axes in one loop: a PNG per axis, one log of every axis
        from dobhil.cli.axes_run import run_axes
        args.config = str(path)
        axes_log = None if args.no_log else (args.log or default_log_path(args.out))
        code = run_axes(args, prog="dobhil demo", emulate=True, lockstep=not args.realtime,
                        plot=args.out / "demo_run.png", log=axes_log)
        if axes_log is not None:
            print(f"next: dobhil report {axes_log} --out {args.out / 'report'}")
            _play_live(axes_log, args.live)
        return code
    config = load_config(path, args.overrides, args.set_files)
    png = check_output(args.out / "demo_run.png", inputs=[path], what="--out")
    if not args.realtime:
        check_lockstep_run(load_drive_profile(config, path.parent), config.loop.period)
    gate = stability_gate(config, path, allow_unstable=args.allow_unstable, prog="dobhil demo")
    log_path = None if args.no_log else (args.log or default_log_path(args.out))
    log = open_run_log(log_path, layout=args.log_layout)
    try:
        with stop_on_signals(StopRequest()) as request, \
                RunSession(config, emulate=True, lockstep=not args.realtime, config_dir=path.parent,
                           stop_request=request, **log_hooks(log)) as session:
            result = record_run(session, log, path, metadata={
                "stability_gate": gate_metadata(gate, allow_unstable=args.allow_unstable)})
            info = summary(session, result)
    except BaseException as exc:
        abort(log, exc)
        raise
    if log is not None:
        info.update(log_summary(log, result.stop))
    report(info, result.stop.line(), as_json=False)
    print(f"wrote {run_figure(result.trace, png, demo_title(session.profile, config.loop.period))}")
    if log is not None:
        print(f"next: dobhil report {log.path} --out {args.out / 'report'}")
        _play_live(log.path, args.live)
    return 0 if result.stop.reason.name == "DONE" else EXIT_STOPPED


def _check_live(live: str) -> None:
    """One line (exit 2) before the run if ``--live`` cannot be served: a bad or busy address,
    no foxglove-sdk."""
    from dobhil.live.address import check_bindable, parse_live_address
    from dobhil.live.server import import_sdk
    address = parse_live_address(live)
    import_sdk()
    check_bindable(address)


def _play_live(log: Path, live: str | None) -> None:
    """``--live``: the recorded run played to Foxglove once a client subscribes. A demo lasts
    about a second (a fraction of it in lockstep): served while it ran, it was over before a
    person could open the connection. Ctrl-C ends the live view, not the demo's exit code; a
    run Ctrl-C stopped is not played (whoever pressed it wants the demo to end, not to wait)."""
    if live is None:
        return
    from dobhil.live.cli import serve_command
    from dobhil.recording.reader import open_log
    from dobhil.runtime.stop import StopReason
    if open_log(log).info().stop_reason == StopReason.SIGNAL.name.lower():
        return
    try:
        serve_command(log, live=live, speed=1.0, loop=False)
    except KeyboardInterrupt:
        print("live view: stopped", flush=True)
