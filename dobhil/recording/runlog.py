"""Recording one run: :class:`RunLog` is the runtime's cycle sink and bus tap.

It implements the ``CycleSink`` protocol (``started``, ``cycle``, ``stop``) and wraps the
host bus, knowing nothing of the runtime: the wiring (``dobhil.cli.recording``) passes
plain values. The loop thread only appends short tuples of *references* (the frame, the
feedback, the controller output: objects nobody changes afterwards) to one list and
hands every :data:`BATCH_SIZE` of them to the writer process's sender thread, which
flattens them (:func:`flatten`) and serializes them while the loop sleeps. A writer
failure surfaces as :class:`~dobhil.errors.RecorderError` from :meth:`RunLog.cycle`,
which the loop turns into the stop reason ``recorder_failed``.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Mapping, Sequence
from types import SimpleNamespace
from typing import Any, Final

import can

from dobhil.recording.process import WriterProcess
from dobhil.recording.schemas import CYCLE, Direction, EventKind, Topic, can_frame_record, event_record
from dobhil.recording.writer import RecordMode

ClockNs = Callable[[], int]
#: Records per batch handed to the writer process (~85 cycles).
BATCH_SIZE: Final = 256
_FEEDBACK: Final = int(Topic.DRIVE_FEEDBACK)
#: Kinds of the loop thread's records of references, flattened off the loop thread
_REF_RX, _REF_TX, _REF_CYCLE = -1, -2, -3
_NO_DRIVE: Final = SimpleNamespace(status=SimpleNamespace(state=0, error_code=0))


class RecordingBus(can.BusABC):
    """Appends a record per frame sent or received on the bus it wraps (borrowed, not owned).

    ``recv`` is overridden, not only ``_recv_internal``: :meth:`can.BusABC.recv` spends as
    long on its per-frame timing and debug logging as the record itself, on the loop thread.
    The wrapper has no filters of its own (the wrapped bus applies its own), so nothing of
    the base's filtering is lost; ``_recv_internal`` serves any other caller.
    """

    def __init__(self, inner: can.BusABC, records: list[tuple[Any, ...]], **kwargs: Any) -> None:
        self._inner = inner
        self._append = records.append
        self.clock_ns: ClockNs = time.time_ns
        self.channel_info = f"recording {inner.channel_info}"
        super().__init__(channel=getattr(inner, "channel", None) or "", **kwargs)

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self._inner.send(msg, timeout)
        # a sender may refill a preallocated message's data (drives do): the data is copied
        self._append((_REF_TX, self.clock_ns(), msg, bytes(msg.data)))

    def recv(self, timeout: float | None = None) -> can.Message | None:
        msg = self._inner.recv(timeout)
        if msg is not None:  # python-can hands out a new message per receive: kept by reference
            self._append((_REF_RX, self.clock_ns(), msg))
        return msg

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        return self.recv(timeout), False

    def __getattr__(self, name: str) -> Any:
        if name.startswith("_"):
            raise AttributeError(name)
        return getattr(self._inner, name)


class RunLog:
    """Records one run to ``path`` (the writer process starts now: a bad path raises here)."""

    def __init__(self, path: str | os.PathLike[str], *, live: tuple[str, int] | None = None,
                 flush_interval: float = 1.0, fsync: bool = True) -> None:
        self.path = os.fspath(path)
        self.live = live
        self.records: list[tuple[Any, ...]] = []
        self.clock_ns: ClockNs = time.time_ns
        self.truth: Callable[[], tuple[float, float, float, float]] | None = None
        self.drive: Any = _NO_DRIVE
        self.tap: RecordingBus | None = None
        self._writer: WriterProcess | None = WriterProcess(path, flush_interval=flush_interval, fsync=fsync,
                                                           prepare=flatten)
        self._opened = False

    @property
    def writer_pid(self) -> int | None:
        """The writer process (for its scheduling priority), None once closed."""
        return None if self._writer is None else self._writer.pid

    @property
    def live_port(self) -> int | None:
        """The port the live view listens on (after :meth:`begin`), None without one."""
        return None if self._writer is None else self._writer.live_port

    def wrap_bus(self, bus: can.BusABC) -> can.BusABC:
        """The session's ``bus_wrapper``: every frame on ``/can/rx`` and ``/can/tx``."""
        self.tap = RecordingBus(bus, self.records)
        return self.tap

    def begin(self, *, metadata: Mapping[str, Mapping[str, Any]], attachments: Sequence[tuple[str, str, bytes]],
              lossy: bool, clock_ns: ClockNs | None = None,
              truth: Callable[[], tuple[float, float, float, float]] | None = None, drive: Any = None) -> None:
        """Header and metadata; the log clock, the emulator truth ``(q, dq, tau_motor, tau_int)``
        and the drive (its ``status.state`` and ``status.error_code`` go to ``/drive/feedback``)."""
        assert self._writer is not None, "the log is closed"
        mode = RecordMode.LOSSY if lossy else RecordMode.BACKPRESSURE
        self._writer.open(metadata, attachments, mode, self.live)
        self._opened = True
        self.clock_ns = clock_ns or time.time_ns
        if self.tap is not None:
            self.tap.clock_ns = self.clock_ns
        self.truth = truth
        self.drive = drive if drive is not None else _NO_DRIVE

    # -- the CycleSink ---------------------------------------------------------------

    def started(self, fb: Any) -> None:
        """The feedback ``controller.initialize`` used (``cycle = -1``) and the enable event."""
        status = self.drive.status
        t = self.clock_ns()
        self.records.append((_FEEDBACK, t, fb.position, fb.velocity, int(status.state), status.error_code, fb.seq,
                             -1))
        self.records.append(event_record(EventKind.ENABLE, t, "drive enabled", f"seq {fb.seq}"))

    def cycle(self, k: int, t: float, fb: Any, out: Sequence[float], period_error: float, exec_time: float,
              overrun: bool) -> None:
        """One record of references per cycle; never blocks in real time (lossy)."""
        records = self.records
        truth = self.truth
        records.append((_REF_CYCLE, self.clock_ns(), k, fb, out, period_error, exec_time, overrun, self.drive.status,
                        None if truth is None else truth()))
        if len(records) >= BATCH_SIZE:
            self._hand_over()

    def stop(self, stop: Any) -> None:
        """The loop has stopped; :meth:`end` hands the rest over, none dropped."""

    # -- events and the end ------------------------------------------------------------

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
        self.records.append(event_record(kind, self.clock_ns(), reason, detail))

    def end(self, stop_reason: str | None, detail: str = "") -> None:
        """The last records, the stop event, summary and footer; waits for the writer.
        Raises :class:`~dobhil.errors.RecorderError` if the writer failed (once)."""
        writer, self._writer = self._writer, None
        if writer is None:
            return
        if not self._opened:
            writer.abandon()
            return
        try:
            if self.records:
                writer.send(self.records.copy(), force=True)
        finally:
            self.records.clear()
            writer.close(stop_reason, detail)

    def _hand_over(self) -> None:
        if self._writer is not None and self._opened:
            batch = self.records.copy()
            self.records.clear()
            self._writer.send(batch)


def flatten(records: list[tuple[Any, ...]]) -> list[tuple[Any, ...]]:
    """The loop thread's records of references as the flat records of the topic table."""
    out = []
    for r in records:
        kind = r[0]
        if kind == _REF_CYCLE:
            _, t, k, fb, o, period_error, exec_time, overrun, status, truth = r
            flat = (CYCLE, t, k, fb.position, fb.velocity, fb.seq, *o, period_error, exec_time, overrun,
                    int(status.state), status.error_code)
            out.append(flat if truth is None else (*flat, *truth))
        elif kind == _REF_RX:
            out.append(can_frame_record(r[2], Direction.RX, r[1]))
        elif kind == _REF_TX:  # the data as it was sent (the message may have been refilled since)
            frame = can_frame_record(r[2], Direction.TX, r[1])
            out.append((*frame[:5], r[3], *frame[6:]))
        else:
            out.append(r)
    return out


__all__ = ["BATCH_SIZE", "RecordingBus", "RunLog", "flatten"]
