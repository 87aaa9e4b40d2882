"""Recording one run: the cycle sink, the bus tap, events and metadata, in one object.

Use::

    log = RunLog(path, config, config_file=...)
    with RunSession(config, ..., sink=log.sink, bus_wrapper=log.wrap_bus) as session:
        log.start(session)          # metadata to the writer process, hooks
        try:
            result = session.run()
        finally:
            log.finish(result)      # (or log.abort(exc)) events, summary, footer

What goes where (``docs/recording.md``): ``/can/rx`` ``/can/tx`` from the tap
(:class:`~dobhil.recording.tap.RecordingBus`); per cycle ``/drive/feedback`` (with the
frame's ``seq``), ``/drive/command``, ``/controller``, ``/loop`` and, when emulated,
``/emulator/truth`` from :class:`CycleRecorder`; the feedback ``controller.initialize``
used as a ``/drive/feedback`` record with ``cycle = -1``; ``/events`` for enable,
disable, stop, fault and watchdog. Log times: wall clock (ns since the epoch) in real
time; in lockstep the start time plus the simulated time, so the log is deterministic
apart from its origin.

Modes: lockstep records with back-pressure (nothing lost), real time lossy (the loop
never waits; losses become ``/events`` ``kind=loss``).

Where the work happens: the loop thread only appends flat tuples of plain values and,
every :data:`BATCH_SIZE` records, hands the batch to the writer process
(:class:`~dobhil.recording.writerproc.WriterProcess`, started when the :class:`RunLog` is
created, before the session and the loop). JSON encoding, MCAP writing, compression and
flushing run there, on another core, instead of competing with the loop for the GIL.
"""

from __future__ import annotations

import json
import os
import platform
import sys
import time
from collections.abc import Callable, Mapping
from datetime import datetime, timezone
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path
from typing import TYPE_CHECKING, Any, Final

import can

from dobhil import __version__
from dobhil.errors import LogFileError
from dobhil.recording.fastlog import Batcher, RawKind
from dobhil.recording.filewriter import RecordMode
from dobhil.recording.schemas import EventKind
from dobhil.recording.tap import RecordingBus
from dobhil.recording.writerproc import WriterProcess

if TYPE_CHECKING:
    from dobhil.config.schema import Config
    from dobhil.drives.base import Drive, Feedback
    from dobhil.runtime.controller import ControlOutput
    from dobhil.runtime.loop import RunResult
    from dobhil.runtime.session import RunSession
    from dobhil.runtime.stop import Stop

ClockNs = Callable[[], int]
Truth = Callable[[], tuple[float, float, float, float]]

#: Packages whose versions go to the ``versions`` metadata record.
_PACKAGES: Final = ("python-can", "mcap", "numpy", "scipy", "control", "pyyaml", "zstandard", "lz4")
_CYCLE: Final = int(RawKind.CYCLE)
_EVENT: Final = int(RawKind.EVENT)
#: Raw records per batch handed to the writer process (~85 cycles: one pipe write each).
BATCH_SIZE: Final = 256


def default_log_path(directory: Path, now: datetime | None = None) -> Path:
    """``DIR/run-YYYYmmdd-HHMMSS.mcap`` (``-2``, ``-3`` ... if taken)."""
    stamp = (now or datetime.now()).strftime("%Y%m%d-%H%M%S")
    path = directory / f"run-{stamp}.mcap"
    n = 2
    while path.exists():
        path = directory / f"run-{stamp}-{n}.mcap"
        n += 1
    return path


def config_metadata(config: Config) -> dict[str, str]:
    """Every config key as ``section.key -> JSON value`` (floats exact: ``repr``)."""
    return {k: json.dumps(v) for k, v in config.flat().items()}


def config_from_metadata(record: Mapping[str, str]) -> Config:
    """The :class:`Config` of a ``config`` metadata record written by :func:`config_metadata`."""
    from dobhil.config import build_config
    return build_config({k: json.loads(v) for k, v in record.items()}, source="recorded config")


def versions() -> dict[str, str]:
    """dobhil, Python and dependency versions."""
    out = {"dobhil": __version__, "python": platform.python_version()}
    for name in _PACKAGES:
        try:
            out[name] = version(name)
        except PackageNotFoundError:
            continue
    return out


class CycleRecorder:
    """The :class:`~dobhil.runtime.loop.CycleSink`: one flat tuple per cycle, never blocks.

    The tuple holds plain values only (the CYCLE layout of
    :class:`~dobhil.recording.fastlog.RawKind`), so the batch is marshalled without
    touching an object.
    """

    def __init__(self, batcher: Batcher) -> None:
        self._batcher = batcher
        self._buffer = batcher.buffer
        self._size = BATCH_SIZE
        self.clock_ns: ClockNs = time.time_ns
        self.truth: Truth | None = None
        self.drive: Drive | None = None
        self.stopped: Stop | None = None
        self.on_started: Callable[[Feedback], None] | None = None

    def started(self, fb: Feedback) -> None:
        if self.on_started is not None:
            self.on_started(fb)

    def cycle(self, k: int, t: float, fb: Feedback, out: ControlOutput, period_error: float,
              exec_time: float, overrun: bool) -> None:
        buf = self._buffer
        truth = self.truth
        status = self.drive.status  # type: ignore[union-attr]
        if truth is None:
            buf.append((_CYCLE, self.clock_ns(), k, fb.position, fb.velocity, fb.seq, *out, period_error,
                        exec_time, overrun, int(status.state), status.error_code))
        else:
            buf.append((_CYCLE, self.clock_ns(), k, fb.position, fb.velocity, fb.seq, *out, period_error,
                        exec_time, overrun, int(status.state), status.error_code, *truth()))
        if len(buf) >= self._size:
            self._batcher.flush()

    def stop(self, stop: Stop) -> None:
        self.stopped = stop
        self._batcher.flush()


class RunLog:
    """Records one :class:`~dobhil.runtime.session.RunSession` to ``path``.

    Creating it creates the file (a bad path raises :class:`~dobhil.errors.LogFileError`
    here) and starts the writer process, so the process is ready by the time the loop
    runs; :meth:`finish` or :meth:`abort` always closes it (a log aborted before
    :meth:`start` leaves no file).
    """

    def __init__(self, path: str | os.PathLike[str], config: Config, *,
                 config_file: str | os.PathLike[str] | None = None,
                 flush_interval: float = 1.0, fsync: bool = True) -> None:
        self.path = Path(path)
        self.config = config
        self._config_file = None if config_file is None else Path(config_file)
        self.batcher = Batcher(self._hand_over, BATCH_SIZE)
        self.sink = CycleRecorder(self.batcher)
        self.tap: RecordingBus | None = None
        self._session: RunSession | None = None
        self._pending: list[list[tuple[Any, ...]]] = []
        self._opened = False
        self.writer: WriterProcess | None = WriterProcess(self.path, flush_interval=flush_interval, fsync=fsync)

    # -- wiring --------------------------------------------------------------

    def wrap_bus(self, bus: can.BusABC) -> can.BusABC:
        """The ``bus_wrapper`` of RunSession: the tap, on simulated time with lockstep."""
        clock = self._clock_for(bus)
        self.sink.clock_ns = clock
        self.tap = RecordingBus(bus, self.batcher, clock_ns=clock)
        return self.tap

    @staticmethod
    def _clock_for(bus: can.BusABC) -> ClockNs:
        from dobhil.emulator.protocol import LockstepBus
        if not isinstance(bus, LockstepBus):
            return time.time_ns
        origin = time.time_ns()
        sim = bus.clock
        return lambda: origin + round(sim() * 1e9)

    def start(self, session: RunSession) -> None:
        """Send the run's metadata to the writer process; hook truth and initialisation."""
        from dobhil.runtime.loop import Timing
        if self.writer is None:
            raise LogFileError(f"{self.path}: the log is closed")
        self._session = session
        lockstep = session.timing is Timing.LOCKSTEP
        mode = RecordMode.BACKPRESSURE if lockstep else RecordMode.LOSSY
        self.writer.open(self._metadata(session), self._attachments(), mode)
        self._opened = True
        for batch in self._pending:
            self.writer.send(batch)
        self._pending.clear()
        self.sink.drive = session.drive
        if session.plant is not None:
            plant = session.plant
            self.sink.truth = lambda: (plant.true_position, plant.true_velocity,
                                       plant.motor_torque, plant.interaction_torque)
        self.sink.on_started = self._initialized

    def _initialized(self, fb: Feedback) -> None:
        """The feedback ``controller.initialize`` used (cycle -1) and the enable event."""
        assert self._session is not None
        status = self._session.drive.status
        t = self.sink.clock_ns()
        self.batcher.buffer.append((int(RawKind.FEEDBACK), t, fb.position, fb.velocity, int(status.state),
                                    status.error_code, fb.seq, -1))
        self.event(EventKind.ENABLE, "drive enabled",
                   json.dumps({"seq": fb.seq, "position": fb.position, "velocity": fb.velocity}))

    # -- events and end ------------------------------------------------------

    def event(self, kind: EventKind, reason: str, detail: str = "") -> None:
        """An ``/events`` record after everything appended so far, sent at once (never
        dropped: a dropped batch's events go with the next one)."""
        if self.writer is not None:
            self.batcher.buffer.append((_EVENT, self.sink.clock_ns(), int(kind), reason, detail))
            self.batcher.flush()

    def finish(self, result: RunResult) -> None:
        """Disable/fault/watchdog events, the stop event, summary and footer."""
        stop = result.stop
        session = self._session
        drive = session.drive if session is not None else None
        status = drive.status if drive is not None else None
        if stop.reason.name == "DRIVE_FAULT":
            self.event(EventKind.FAULT, stop.detail or "drive fault")
        if (status is not None and status.watchdog_tripped) or \
                bool(getattr(getattr(session, "emulator", None), "watchdog_tripped", False)):
            self.event(EventKind.WATCHDOG, "drive watchdog expired")
        self.event(EventKind.DISABLE, "drive disabled" if result.disabled else "disable frames not sent",
                   status.detail if status is not None else "")
        self._close(stop.reason.name.lower(), stop.line())

    def abort(self, exc: BaseException | None) -> None:
        """Close after an error (or before the run started)."""
        stop = self.sink.stopped
        if stop is not None:
            self._close(stop.reason.name.lower(), stop.line())
        else:
            self._close("exception" if exc is not None else "not run",
                        "" if exc is None else f"{type(exc).__name__}: {exc}")

    def _close(self, reason: str, detail: str) -> None:
        """The last records (never dropped: the loop is over), stop event, summary; joins
        the writer process."""
        if self.writer is None:
            return
        writer, self.writer = self.writer, None
        rest = self.batcher.buffer.copy()
        self.batcher.buffer.clear()
        try:
            if self._opened and rest:
                writer.send(rest, force=True)
        finally:
            writer.close(reason, detail)

    def _hand_over(self, batch: list[tuple[Any, ...]]) -> None:
        if self.writer is None:
            return
        if self._opened:
            self.writer.send(batch)
        else:
            self._pending.append(batch)

    # -- metadata ------------------------------------------------------------

    def _metadata(self, session: RunSession) -> dict[str, Mapping[str, Any]]:
        from dobhil.runtime.loop import Timing
        spec = session.bus_spec
        profile = session.profile
        lockstep = session.timing is Timing.LOCKSTEP
        return {
            "config": config_metadata(self.config),
            "versions": {**versions(), "drive_firmware": profile.firmware},
            "bus": {"interface": spec.interface, "channel": spec.channel,
                    "bitrate": spec.kwargs.get("bitrate", self.config.drive.bitrate),
                    "emulated": session.emulator is not None, "lockstep": lockstep},
            "drive": {k: json.dumps(v) for k, v in _profile_fields(profile).items()},
            "run": {"start_time": datetime.now(timezone.utc).isoformat(timespec="milliseconds"),
                    "start_time_ns": time.time_ns(), "timing": "lockstep" if lockstep else "realtime",
                    "log_clock": "simulated" if lockstep else "wall",
                    "period": repr(session.settings.period), "duration": repr(session.settings.duration),
                    "torque_limit": repr(session.controller.torque_limit),
                    "measures_velocity": session.controller.measures_velocity,
                    "config_file": "" if self._config_file is None else os.fspath(self._config_file),
                    "command": " ".join(sys.argv), "host": platform.node()},
        }

    def _attachments(self) -> list[tuple[str, str, bytes]]:
        from dobhil.config import to_yaml
        out = [("config.resolved.yaml", "application/yaml", to_yaml(self.config).encode())]
        if self._config_file is not None and self._config_file.is_file():
            out.insert(0, (self._config_file.name, "application/yaml", self._config_file.read_bytes()))
        return out


def run_recorded(session: RunSession, log: RunLog | None) -> RunResult:
    """``session.run()``, recorded by ``log`` (started here, finished or aborted here)."""
    if log is None:
        return session.run()
    try:
        log.start(session)
        result = session.run()
    except BaseException as exc:
        log.abort(exc)
        raise
    log.finish(result)
    return result


def _profile_fields(profile: Any) -> dict[str, Any]:
    return {k: getattr(profile, k) for k in ("protocol", "firmware", "node_id", "torque_limit", "velocity_limit",
                                             "encoder_msg_rate", "heartbeat_msg_rate", "watchdog_timeout",
                                             "enable_timeout", "name")}


__all__ = ["BATCH_SIZE", "CycleRecorder", "RunLog", "config_from_metadata", "config_metadata",
           "default_log_path", "run_recorded", "versions"]
