"""Wiring a run to its recording: the one place that knows both the runtime and recording.

The runtime defines the ``CycleSink`` protocol and a ``bus_wrapper`` hook; recording's
:class:`~dobhil.recording.runlog.RunLog` implements them and takes plain values. Here
the session's description becomes the log's metadata, the session's clocks and plant the
log's clock and truth, and the run's end the log's events and stop reason.
"""

from __future__ import annotations

import dataclasses
import json
import os
import platform
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from datetime import datetime, timezone
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path
from typing import Any, Final

from dobhil import __version__
from dobhil.config import Config, resolve_config, to_yaml
from dobhil.drives.profile import DriveProfile
from dobhil.errors import ConfigError, RecorderError, exception_line
from dobhil.files import check_new_output
from dobhil.recording.axeslog import AxesLog, AxisDrive, axis_record, bus_record
from dobhil.recording.codes import ProtocolCodes
from dobhil.recording.encodings import DEFAULT_ENCODING
from dobhil.recording.layouts import DEFAULT_LAYOUT
from dobhil.recording.process import WriterProcess
from dobhil.recording.runlog import RunLog
from dobhil.recording.schemas import EventKind
from dobhil.recording.writer import LiveView
from dobhil.runtime.loop import RunResult, Timing
from dobhil.realtime import run_in_background
from dobhil.runtime.buses import BusSpec
from dobhil.runtime.session import RunSession
from dobhil.runtime.stop import Stop, StopReason

_PACKAGES: Final = ("python-can", "mcap", "numpy", "scipy", "control", "pyyaml", "orjson", "zstandard")
_PROFILE_KEYS: Final = ("protocol", "firmware", "node_id", "torque_limit", "velocity_limit", "feedback_period",
                        "heartbeat_period", "watchdog_timeout", "enable_timeout", "command_delay_periods", "name")


def default_log_path(directory: Path, now: datetime | None = None) -> Path:
    """``DIR/run-YYYYmmdd-HHMMSS.mcap`` (``-2``, ``-3`` ... if taken)."""
    stamp = (now or datetime.now()).strftime("%Y%m%d-%H%M%S")
    path, n = directory / f"run-{stamp}.mcap", 2
    while path.exists():
        path, n = directory / f"run-{stamp}-{n}.mcap", n + 1
    return path


def live_address(text: str | None, log: Path | None) -> LiveView | None:
    """``--live [HOST:]PORT`` checked before a run: the address (resolvable, free to listen on),
    the SDK there, a log to serve it. The live view the log's writer process serves (a
    :class:`~dobhil.live.LiveServer` there); the warning of an address beyond loopback is
    :func:`_say_live`'s, once it listens: a run refused after this check shows nothing to anyone."""
    if text is None:
        return None
    from dobhil.errors import ConfigError
    from dobhil.live import LiveServer, parse_live_address
    from dobhil.live.server import import_sdk
    if log is None:
        raise ConfigError("--live needs a log (--log FILE.mcap): the live view is served by the log's writer")
    from dobhil.live.address import check_bindable
    address = parse_live_address(text)
    import_sdk()
    check_bindable(address)  # before the log exists: a refused address leaves no stub behind
    return LiveView(LiveServer, address.host, address.port)


def _say_live(log: RunLog | AxesLog) -> None:
    """The live view's URL on stderr once its port is known, an IPv6 host in brackets
    (``ws://[::1]:8765``: RFC 3986 section 3.2.2; ``ws://::1:8765`` is no URL a client opens),
    after one warning line when the address is not a loopback one. Said once the server
    listens, so a run refused before (an existing --log, say) is its one error line."""
    if log.live_port is not None and log.live is not None:
        from dobhil.live.address import LiveAddress, exposure_warning, shown
        address = LiveAddress(log.live.host, log.live_port)
        warning = exposure_warning(address)
        if warning is not None:
            sys.stderr.write(f"warning: {warning}\n")
        sys.stderr.write(f"live view: ws://{shown(address)}\n")
        sys.stderr.flush()


def open_run_log(path: Path | None, *, live: LiveView | None = None, fsync: bool = True,
                 encoding: str = DEFAULT_ENCODING, layout: str = DEFAULT_LAYOUT) -> RunLog | None:
    """A :class:`RunLog` for ``path`` (checked first: one line if it cannot be written), its
    messages in ``encoding`` (``dobhil.recording.encodings``) laid out as ``layout``
    (``dobhil.recording.cycles``)."""
    if path is None:
        return None
    check_new_output(path, suffix=".mcap", what="--log")
    path.parent.mkdir(parents=True, exist_ok=True)
    return RunLog(WriterProcess(path, fsync=fsync, encoding=encoding, layout=layout), live=live)


def versions() -> dict[str, str]:
    out = {"dobhil": __version__, "python": platform.python_version()}
    for name in _PACKAGES:
        try:
            out[name] = version(name)
        except PackageNotFoundError:
            continue
    return out


def drive_metadata(profile: DriveProfile) -> dict[str, str]:
    """The profile as the log keeps it (JSON per key): the common keys and, when it has
    settings, the protocol's section under the protocol's name, as in the YAML file."""
    out = {k: json.dumps(getattr(profile, k)) for k in _PROFILE_KEYS}
    if profile.options:
        out[profile.protocol] = json.dumps(dict(profile.options))
    return out


def data_bitrate(spec: BusSpec, profile: DriveProfile) -> int | None:
    """The data-phase bit rate of the drive's CAN FD frames with the bit rate switch: what
    the bus is opened with, else what the drive's protocol counts its budget at (None:
    neither says). The log records it: its frames say which are FD with the switch, not
    how fast their data phase ran, and the report times them on the bus with it."""
    from dobhil.drives.registry import preflight_probe
    given = spec.kwargs.get("data_bitrate")
    if given:
        return int(given)
    probe = preflight_probe(profile)
    return None if probe is None else probe.data_bitrate()


def _with_data_bitrate(record: dict[str, Any], rate: int | None) -> dict[str, Any]:
    if rate is not None:
        record.setdefault("data_bitrate", rate)
    return record


def run_metadata(session: RunSession, config_file: str | os.PathLike[str] | None) -> dict[str, dict[str, Any]]:
    """The ``config``, ``versions``, ``bus``, ``drive`` and ``run`` metadata records."""
    spec, profile, config = session.bus_spec, session.profile, session.config
    lockstep = session.timing is Timing.LOCKSTEP
    return {
        "config": {k: json.dumps(v) for k, v in config.flat().items()},
        "versions": {**versions(), "drive_firmware": profile.firmware},
        "bus": _with_data_bitrate({"interface": spec.interface, "channel": spec.channel,
                                   "bitrate": spec.kwargs.get("bitrate", config.drive.bitrate),
                                   "emulated": session.emulator is not None, "lockstep": lockstep},
                                  data_bitrate(spec, profile)),
        "drive": drive_metadata(profile),
        "run": {"start_time": datetime.now(timezone.utc).isoformat(timespec="milliseconds"),
                "start_time_ns": time.time_ns(), "timing": session.timing.label,
                "log_clock": "simulated" if lockstep else "wall", "period": repr(session.settings.period),
                # what the drive's sample instant is stamped with (the report's sample latency)
                "sample_clock": session.drive.sample_clock,
                "duration": repr(session.settings.duration),
                "torque_limit": repr(session.controller.torque_limit),
                "measures_velocity": session.controller.measures_velocity,
                "config_file": "" if config_file is None else os.fspath(config_file),
                "command": " ".join(sys.argv), "host": platform.node()},
    }


def _attachments(config: Config, config_file: str | os.PathLike[str] | None) -> list[tuple[str, str, bytes]]:
    """The resolved config, and the config file as given -- a path or a shipped name
    (``demo``), read from the file that name resolves to, as the run loaded it."""
    out = [("config.resolved.yaml", "application/yaml", to_yaml(config).encode())]
    if config_file is not None:
        try:
            path = resolve_config(os.fspath(config_file))
        except ConfigError:   # gone since the run loaded it: the resolved config is attached anyway
            return out
        if path.is_file():
            out.insert(0, (path.name, "application/yaml", path.read_bytes()))
    return out


def begin(log: RunLog, session: RunSession, config_file: str | os.PathLike[str] | None,
          metadata: Mapping[str, Mapping[str, str]] | None = None) -> None:
    """Metadata (the run's, then ``metadata``: records the command adds, e.g. the stability
    gate's verdict), clock (simulated time in lockstep), truth and drive status to the log."""
    sim = session.sim_clock
    origin = time.time_ns()
    drive, plant = session.drive, session.plant
    if session.timing is not Timing.LOCKSTEP and log.writer_pid is not None:
        run_in_background(log.writer_pid)  # lossy: it may lag, never delay the loop
    log.begin(metadata={**run_metadata(session, config_file), **(metadata or {})},
              attachments=_attachments(session.config, config_file),
              lossy=session.timing is not Timing.LOCKSTEP,
              clock_ns=None if sim is None else (lambda: origin + round(sim() * 1e9)),
              truth=None if plant is None else (lambda: (plant.true_position, plant.true_velocity,
                                                         plant.motor_torque, plant.interaction_torque)),
              drive=drive, own_ids=drive.frame_ids, codes=ProtocolCodes(session.profile),
              cancel=session.stop_request.reason)
    _say_live(log)


def record_run(session: RunSession, log: RunLog | None, config_file: str | os.PathLike[str] | None = None, *,
               on_begin: Callable[[RunLog], object] | None = None,
               metadata: Mapping[str, Mapping[str, str]] | None = None) -> RunResult:
    """``session.run()`` recorded by ``log``; a writer failure is the stop reason ``recorder_failed``.
    ``on_begin`` runs once the log is open, before the loop (e.g. to connect a live client);
    ``metadata``: more metadata records (name -> record) the command adds."""
    if log is None:
        return session.run()
    try:
        begin(log, session, config_file, metadata)
    except BaseException as exc:
        _close_quietly(log, exc)
        _discard_unopened(log)
        raise
    try:
        if on_begin is not None:
            on_begin(log)
        result = session.run()
    except BaseException as exc:
        _close_quietly(log, exc)
        raise
    return _end(log, session, result)


def _end(log: RunLog, session: RunSession, result: RunResult) -> RunResult:
    """The run's end events, then the log finished -- for a bounded time (a writer that is
    stopped or stuck on a dead disk is killed, and a SIGINT while it is waited for cuts the
    wait short: ``WriterProcess.close``). A run that lasted its duration but whose log failed
    ends ``recorder_failed``; any other keeps its own stop (why it stopped), and
    :func:`log_summary` says the log failed."""
    cancel = session.stop_request.newer()   # not the request that stopped the run: a new one
    stop = result.stop
    status = session.drive.status
    if stop.reason is StopReason.DRIVE_FAULT:
        log.event(EventKind.FAULT, stop.detail or "drive fault")
    if status.watchdog_tripped or bool(getattr(session.emulator, "watchdog_tripped", False)):
        log.event(EventKind.WATCHDOG, "drive watchdog expired")
    log.event(EventKind.DISABLE, "drive disabled" if result.disabled else "disable frames not sent", status.detail)
    try:
        log.end(stop.reason.name.lower(), stop.line(), cancel=cancel)
    except RecorderError as exc:
        if stop.reason is StopReason.DONE:
            return dataclasses.replace(result, stop=Stop(StopReason.RECORDER_FAILED, str(exc), stop.cycle, stop.time))
    return result


def log_summary(log: RunLog | AxesLog, stop: Stop) -> dict[str, str]:
    """The summary's keys of a run's log: ``log``, its path, and ``log_error`` when the log's
    end failed after the run stopped for another reason (its stop line names that reason,
    so the log's failure is a line of its own)."""
    out = {"log": str(log.path)}
    if log.end_failure and stop.reason is not StopReason.RECORDER_FAILED:
        out["log_error"] = log.end_failure
    return out


def _discard_unopened(log: RunLog) -> None:
    """Remove the file of a log whose writer never got ready (e.g. its live view could not
    listen, taken after ``live_address`` checked it): it holds no run, only a header, and
    left behind it would block the rerun with the same ``--log`` (a new file: ours)."""
    if not log.writer.opened:
        log.path.unlink(missing_ok=True)


def _close_quietly(log: RunLog, exc: BaseException) -> None:
    try:
        log.end("exception", exception_line(exc))
    except RecorderError:
        pass


def abort(log: RunLog | None, exc: BaseException) -> None:
    """Close the log of a run that could not even start (no file left if nothing ran)."""
    if log is not None:
        _close_quietly(log, exc)


# -- several axes ---------------------------------------------------------------------------


@dataclass(frozen=True)
class AxisRun:
    """One axis of a several-axis run as its log records it: the axis' resolved config and
    profile, its drive (``status``, ``frame_ids``, ``sample_clock``), its bus (the name its
    session gave ``AxesLog.wrap_bus``, and the spec it was opened with), its controller's
    limit and whether it measures velocity, and its emulated plant (None: a real drive)."""

    name: str
    config: Config
    profile: DriveProfile
    drive: Any
    bus: str
    bus_spec: BusSpec
    torque_limit: float
    measures_velocity: bool
    plant: Any = None

    @classmethod
    def of(cls, name: str, session: Any, bus: str) -> AxisRun:
        """The axis of a session-like object (``config``, ``profile``, ``drive``, ``bus_spec``,
        ``controller``, ``plant``: a :class:`~dobhil.runtime.session.RunSession`'s names)."""
        return cls(name, session.config, session.profile, session.drive, bus, session.bus_spec,
                   session.controller.torque_limit, session.controller.measures_velocity,
                   getattr(session, "plant", None))

    def truth(self) -> Callable[[], tuple[float, float, float, float]] | None:
        plant = self.plant
        if plant is None:
            return None
        return lambda: (plant.true_position, plant.true_velocity, plant.motor_torque, plant.interaction_torque)


def open_axes_log(path: Path | None, names: Sequence[str], *, live: LiveView | None = None,
                  fsync: bool = True, layout: str = DEFAULT_LAYOUT) -> AxesLog | None:
    """An :class:`~dobhil.recording.axeslog.AxesLog` of the axes ``names`` for ``path``
    (checked first: one line if it cannot be written)."""
    if path is None:
        return None
    check_new_output(path, suffix=".mcap", what="--log")
    path.parent.mkdir(parents=True, exist_ok=True)
    return AxesLog.open(path, names, live=live, fsync=fsync, layout=layout)


def axes_metadata(runs: Sequence[AxisRun], *, timing: Timing, period: float, duration: float,
                  emulated: bool, config_file: str | os.PathLike[str] | None) -> dict[str, dict[str, Any]]:
    """The ``versions`` and ``run`` records of the whole run, and per axis ``axis/<name>/config``,
    ``axis/<name>/drive``, ``axis/<name>/run``, per bus ``bus/<bus>`` (the axes on it)."""
    lockstep = timing is Timing.LOCKSTEP
    out: dict[str, dict[str, Any]] = {
        "versions": versions(),
        "run": {"start_time": datetime.now(timezone.utc).isoformat(timespec="milliseconds"),
                "start_time_ns": time.time_ns(), "timing": timing.label,
                "log_clock": "simulated" if lockstep else "wall", "period": repr(period),
                "duration": repr(duration), "axes": len(runs),
                "config_file": "" if config_file is None else os.fspath(config_file),
                "command": " ".join(sys.argv), "host": platform.node()}}
    for run in runs:
        out[axis_record(run.name, "config")] = {k: json.dumps(v) for k, v in run.config.flat().items()}
        out[axis_record(run.name, "drive")] = drive_metadata(run.profile)
        ids = getattr(run.drive, "frame_ids", None)
        out[axis_record(run.name, "run")] = {
            "torque_limit": repr(run.torque_limit), "measures_velocity": run.measures_velocity,
            "sample_clock": run.drive.sample_clock, "drive_firmware": run.profile.firmware,
            "frame_ids": json.dumps(None if ids is None else sorted(ids))}
        spec = run.bus_spec
        bus = out.setdefault(bus_record(run.bus), {
            "interface": spec.interface, "channel": spec.channel,
            "bitrate": spec.kwargs.get("bitrate", run.config.drive.bitrate), "emulated": emulated,
            "lockstep": lockstep, "axes": "[]"})
        _with_data_bitrate(bus, data_bitrate(spec, run.profile))
        bus["axes"] = json.dumps([*json.loads(bus["axes"]), run.name])
    return out


def axes_attachments(runs: Sequence[AxisRun], config_file: str | os.PathLike[str] | None
                     ) -> list[tuple[str, str, bytes]]:
    """The config file as given, and each axis' resolved config."""
    out = [(f"axis-{r.name}.resolved.yaml", "application/yaml", to_yaml(r.config).encode()) for r in runs]
    if config_file is not None and Path(config_file).is_file():
        out.insert(0, (Path(config_file).name, "application/yaml", Path(config_file).read_bytes()))
    return out


def begin_axes(log: AxesLog, runs: Sequence[AxisRun], *, timing: Timing, period: float, duration: float,
               emulated: bool, sim_clock: Callable[[], float] | None = None,
               couplings: Sequence[Any] = (), config_file: str | os.PathLike[str] | None = None,
               metadata: Mapping[str, Mapping[str, str]] | None = None,
               cancel: Callable[[], str] | None = None) -> None:
    """Open ``log`` for a several-axis run (each axis' bus wrapped by ``log.wrap_bus`` already):
    its metadata (then ``metadata``: records the command adds), the log clock (``sim_clock``,
    simulated seconds, in lockstep), each axis' drive, truth and codes; lossy in real time.
    ``couplings``: :class:`~dobhil.config.axes.Coupling` s (``a``, ``b``, ``stiffness``, ``damping``);
    ``cancel``: the run's stop request (a SIGINT ends a lockstep hand-over's wait for the writer)."""
    origin = time.time_ns()
    if timing is not Timing.LOCKSTEP and log.writer_pid is not None:
        run_in_background(log.writer_pid)  # lossy: it may lag, never delay the loop
    log.begin(metadata={**axes_metadata(runs, timing=timing, period=period, duration=duration, emulated=emulated,
                                        config_file=config_file), **(metadata or {})},
              attachments=axes_attachments(runs, config_file), lossy=timing is not Timing.LOCKSTEP,
              clock_ns=None if sim_clock is None else (lambda: origin + round(sim_clock() * 1e9)),
              drives={r.name: AxisDrive(r.drive, r.bus, r.truth(), getattr(r.drive, "frame_ids", None),
                                        ProtocolCodes(r.profile)) for r in runs},
              couplings=[{"a": c.a, "b": c.b, "stiffness": c.stiffness, "damping": c.damping} for c in couplings],
              cancel=cancel)
    _say_live(log)


def end_axes(log: AxesLog, stop: Stop, disabled: Mapping[str, bool], axis: str = "",
             cancel: Callable[[], str] | None = None) -> Stop:
    """The run's end to ``log``: a ``fault`` event on the axis whose drive fault stopped the
    run (``axis``), per axis a ``disable`` event (its disable frames sent or not), the stop
    event; the stop, or ``recorder_failed`` if the writer failed in a run that lasted its
    duration (any other keeps its own, :func:`log_summary` saying the log failed). The log is
    finished for a bounded time, ``cancel`` (a new stop request) cutting the wait short (``_end``)."""
    if stop.reason is StopReason.DRIVE_FAULT and axis in disabled:
        log.sink(axis).event(EventKind.FAULT, stop.detail or "drive fault")
    for name, ok in disabled.items():
        log.sink(name).event(EventKind.DISABLE, "drive disabled" if ok else "disable frames not sent")
    try:
        log.end(stop.reason.name.lower(), stop.line(), cancel)
    except RecorderError as exc:
        if stop.reason is StopReason.DONE:
            return Stop(StopReason.RECORDER_FAILED, str(exc), stop.cycle, stop.time)
    return stop


def abort_axes(log: AxesLog | None, exc: BaseException) -> None:
    """Close the log of a several-axis run that failed or could not start."""
    if log is not None:
        try:
            log.end("exception", exception_line(exc))
        except RecorderError:
            pass
        if not log.writer.opened:
            log.path.unlink(missing_ok=True)


__all__ = ["AxisRun", "abort", "abort_axes", "axes_attachments", "axes_metadata", "begin", "begin_axes",
           "default_log_path", "end_axes", "live_address", "log_summary", "open_axes_log", "open_run_log", "record_run",
           "run_metadata", "versions"]
