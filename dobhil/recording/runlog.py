"""Recording one run: :class:`RunLog`, the runtime's ``CycleSink`` and bus tap, knowing
nothing of the runtime (``dobhil.cli.recording`` wires it with plain values). A writer
failure is a :class:`~dobhil.errors.RecorderError` from ``cycle``: the loop stops
``recorder_failed``."""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Mapping, Sequence
from typing import Any, Final

import can

from dobhil.recording.process import Batch, WriterProcess
from dobhil.recording.schemas import EventKind, Topic, event_record
from dobhil.recording.writer import RecordMode

_FEEDBACK: Final = int(Topic.DRIVE_FEEDBACK)
_RX: Final = int(Topic.CAN_RX)
_TX: Final = int(Topic.CAN_TX)


class RecordingBus(can.BusABC):
    """Records every frame sent or received on the bus it wraps (borrowed, not owned).
    ``recv`` itself is overridden: :meth:`can.BusABC.recv`'s timing and debug logging cost
    as much as the record; the wrapped bus applies its own filters."""

    def __init__(self, inner: can.BusABC, batch: Batch, **kwargs: Any) -> None:
        self._inner = inner
        self._frame = batch.frame
        self.channel_info = f"recording {inner.channel_info}"
        super().__init__(channel=getattr(inner, "channel", None) or "", **kwargs)

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self._inner.send(msg, timeout)
        self._frame(_TX, msg)

    def recv(self, timeout: float | None = None) -> can.Message | None:
        msg = self._inner.recv(timeout)
        if msg is not None:
            self._frame(_RX, msg)
        return msg

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        return self.recv(timeout), False

    def __getattr__(self, name: str) -> Any:
        if name.startswith("_"):
            raise AttributeError(name)
        return getattr(self._inner, name)


class RunLog(Batch):
    """Records one run to ``path`` (the writer process starts now: a bad path raises here)."""

    def __init__(self, path: str | os.PathLike[str], *, live: tuple[str, int] | None = None,
                 flush_interval: float = 1.0, fsync: bool = True) -> None:
        super().__init__(WriterProcess(path, flush_interval=flush_interval, fsync=fsync))
        self.path = os.fspath(path)
        self.live = live
        self.tap: RecordingBus | None = None
        self._closed = False

    @property
    def writer_pid(self) -> int | None:
        """The writer process (to set its priority), None once closed."""
        return None if self._closed else self.writer.pid

    @property
    def live_port(self) -> int | None:
        """The live view's port (after :meth:`begin`), None without one."""
        return None if self._closed else self.writer.live_port

    def wrap_bus(self, bus: can.BusABC) -> can.BusABC:
        """The session's ``bus_wrapper``: every frame on ``/can/rx`` and ``/can/tx``."""
        self.tap = RecordingBus(bus, self)
        return self.tap

    def begin(self, *, metadata: Mapping[str, Mapping[str, Any]], attachments: Sequence[tuple[str, str, bytes]],
              lossy: bool, clock_ns: Callable[[], int] | None = None,
              truth: Callable[[], tuple[float, float, float, float]] | None = None, drive: Any = None) -> None:
        """Header and metadata; the log clock, the emulator truth ``(q, dq, tau_motor, tau_int)``
        and the drive (its ``status.state`` and ``status.error_code`` go to ``/drive/feedback``)."""
        assert not self._closed, "the log is closed"
        mode = RecordMode.LOSSY if lossy else RecordMode.BACKPRESSURE
        self.writer.open(metadata, attachments, mode, self.live, early=self.take())
        self.clock_ns = clock_ns or time.time_ns
        self.truth = truth
        if drive is not None:
            self.drive = drive

    def started(self, fb: Any) -> None:
        """The feedback ``controller.initialize`` used (``cycle = -1``) and the enable event."""
        status = self.drive.status
        t = self.clock_ns()
        self.record((_FEEDBACK, t, fb.position, fb.velocity, int(status.state), status.error_code, fb.seq, -1))
        self.record(event_record(EventKind.ENABLE, t, "drive enabled", f"seq {fb.seq}"))

    def stop(self, stop: Any) -> None:
        """The loop has stopped; :meth:`end` hands the rest over, none dropped."""

    def safe_stop(self, report: Any) -> None:
        """The sink's safe-stop hook: one ``disable`` event per safe-stop frame (sent or why
        not), then what the drive confirmed (a ``fault`` event with the loud line when it
        may still be enabled)."""
        for frame in report.frames:
            self.event(EventKind.DISABLE, f"{frame.what}: {'sent' if frame.sent else 'not sent'}", frame.error)
        warning = report.warning()
        self.event(EventKind.FAULT if warning else EventKind.DISABLE,
                   f"safe stop: {report.confirmation.name.lower()}", warning or report.detail)

    def event(self, kind: EventKind, reason: str, detail: str = "") -> None:
        """An ``/events`` record after everything appended so far (events are never dropped)."""
        self.record(event_record(kind, self.clock_ns(), reason, detail))

    def end(self, stop_reason: str | None, detail: str = "") -> None:
        """The last records, the stop event, summary and footer; waits for the writer.
        Raises :class:`~dobhil.errors.RecorderError` if the writer failed (once)."""
        if self._closed:
            return
        self._closed = True
        self.writer.close(stop_reason, detail, rest=self.take())


__all__ = ["RecordingBus", "RunLog"]
