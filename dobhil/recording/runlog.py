"""Recording one run, the loop side: :class:`RunLog`, the runtime's ``CycleSink`` and bus tap,
knowing nothing of the runtime (``dobhil.cli.recording`` wires it with plain values). Records
are flat tuples of the topic table (a cycle or a CAN frame packed into one ``bytes`` by
:mod:`dobhil.recording.packed`: one object for the batch's pickle to copy, not 13 or 23); every
``BATCH_RECORDS``, after a cycle's command, they are pickled into the writer process's pipe with
one ``os.write`` (no thread: a sender thread held
the GIL the loop then waited for). A writer failure is a :class:`~dobhil.errors.RecorderError`
from ``cycle``: the loop stops ``recorder_failed``.

In real time, frames received from other ids than the drive's (``own_ids``) are foreign: they
wait in a list of their own, capped at ``FOREIGN_CAP`` per hand-over, and ride along only while
the pipe is less than half full; the rest are shed and counted (``loss`` events). A flood of
foreign traffic so never takes the room the loop's own records (cycles, sent frames, the drive's
frames, events) need.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Collection, Mapping, Sequence
from pathlib import Path
from types import SimpleNamespace
from typing import Any, Final

import can

from dobhil.drives.clocked import ClockedBus, bus_clock
from dobhil.drives.periodic import native_periodic
from dobhil.errors import RecorderError, exception_line
from dobhil.recording.codes import ProtocolCodes
from dobhil.recording.packed import CYCLE_PLAIN, CYCLE_TRUTH, FRAME_HEAD, UNFIT, channel_bytes, unpacked
from dobhil.recording.process import PIPE_SIZE, WriterProcess
from dobhil.recording.schemas import (CYCLE, LANE_MASK, RECORD_TYPES, EventKind, EventRecord, Topic, event_record,
                                      lane_kind, message_count, named)
from dobhil.recording.writer import Lane, LiveView, RecordMode

#: Records handed over at once (~40 cycles with their frames, ~12 KiB pickled).
BATCH_RECORDS: Final = 128
#: Records after which a frame hands them over (no cycle for a while: enable, preflight).
FRAME_FLUSH: Final = 4 * BATCH_RECORDS
#: Foreign frames kept per hand-over (~70 KiB pickled); more are shed at once, counted.
FOREIGN_CAP: Final = 8 * BATCH_RECORDS
#: Foreign frames ride along only while the pipe holds less than this: the rest of it is
#: kept for the loop's own records (half of 1 MiB: ~1.8 s of a 1 kHz run).
FOREIGN_ROOM: Final = PIPE_SIZE // 2
#: Pipe bytes of a foreign frame, about (pickled: 50 to 70).
FOREIGN_BYTES: Final = 64
_RX, _TX, _FEEDBACK, _EVENTS = (int(t) for t in (Topic.CAN_RX, Topic.CAN_TX, Topic.DRIVE_FEEDBACK, Topic.EVENTS))
_LOSS: Final = int(EventKind.LOSS)
_NAN: Final = float("nan")
_pack_cycle, _pack_cycle_truth, _pack_frame = CYCLE_PLAIN.pack, CYCLE_TRUTH.pack, FRAME_HEAD.pack
_join = b"".join


class RecordingBus(ClockedBus):
    """Records every frame sent or received on the bus it wraps (borrowed, not owned), in
    ``lane`` of ``log`` (0: ``/can/rx`` and ``/can/tx``; a bus of a several-axis log has a
    lane of its own). Its waits run on the wrapped bus's clock (:mod:`dobhil.drives.clocked`:
    simulated seconds over a lockstep bus); a frame this bus's ``set_filters`` rejects is not
    received, so not recorded."""

    def __init__(self, inner: can.BusABC, log: RunLog, lane: int = 0, **kwargs: Any) -> None:
        self._inner = inner
        self._received = log.received   # the filtered path (_recv_internal) records through it
        self._rx, self._tx = lane_kind(_RX, lane), lane_kind(_TX, lane)
        # what recv and send call, each read as one attribute: a class with __getattr__ pays
        # a slower lookup (CPython's slot_tp_getattr_hook) for every attribute of self
        self._recv_path = (inner.recv, log.received, self._rx)
        self._send_path = (inner.send, log.sent, self._tx)
        self._clock = bus_clock(inner)
        self.channel_info = f"recording {inner.channel_info}"
        super().__init__(channel=getattr(inner, "channel", None) or "", **kwargs)
        # a wrapper carries what the wrapped bus carries (CAN FD)
        self._can_protocol = getattr(inner, "protocol", can.CanProtocol.CAN_20)

    def clock(self) -> float:
        """The wrapped bus's clock."""
        return self._clock()

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        send, sent, topic = self._send_path
        send(msg, timeout)
        sent(topic, msg)

    def recv(self, timeout: float | None = None) -> can.Message | None:
        """The next frame that passes the filters within ``timeout`` (:class:`ClockedBus`),
        recorded. Without filters (the control path) the wrapped bus's ``recv`` is all the
        wait: the loop thread pays one call and the record, no deadline arithmetic."""
        if self.filtering:
            return self._recv_internal(timeout)[0]
        recv, received, topic = self._recv_path
        msg = recv(timeout)
        if msg is not None:
            received(topic, msg)
        return msg

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        deadline = None if timeout is None else self._clock() + timeout
        msg = self._inner.recv(timeout)
        while msg is not None and not self.passes(msg):
            msg = self._inner.recv(None if deadline is None else max(0.0, deadline - self._clock()))
        if msg is not None:
            self._received(self._rx, msg)
        return msg, True

    @property
    def native_periodic(self) -> bool:
        """As the wrapped bus (:func:`dobhil.drives.periodic.native_periodic`): its periodic
        send is forwarded to it."""
        return native_periodic(self._inner)

    def _send_periodic_internal(
        self, msgs: Sequence[can.Message] | can.Message, period: float, duration: float | None = None,
        autostart: bool = True, modifier_callback: Callable[[can.Message], None] | None = None,
    ) -> can.broadcastmanager.CyclicSendTaskABC:
        """A wrapped bus that sends periodic frames itself (SocketCAN's broadcast manager,
        the lockstep bus, the emulator process's) does so here too: its echo of each frame
        is recorded on ``/can/rx`` as it is read. Otherwise python-can's thread sends them
        through :meth:`send`, recorded on ``/can/tx``."""
        if native_periodic(self._inner):
            return self._inner.send_periodic(msgs, period, duration, autostart=autostart,
                                             modifier_callback=modifier_callback)
        return super()._send_periodic_internal(msgs, period, duration, autostart, modifier_callback)

    def __getattr__(self, name: str) -> Any:
        if name.startswith("_"):
            raise AttributeError(name)
        return getattr(self._inner, name)


class LaneSink:
    """The runtime's ``CycleSink`` for one drive: its cycles, its feedback and its events as
    records of ``lane`` in ``log``'s batches (the :class:`RunLog` itself for a single-axis
    run, lane 0; one per axis of a several-axis log). ``drive`` (its ``status``) and
    ``truth`` (the emulator's ``(q, dq, tau_motor, tau_int)``) are this lane's drive and plant."""

    def __init__(self, log: RunLog, lane: int = 0) -> None:
        self._log = log
        self.lane = lane
        self._cycle, self._feedback, self._events = (lane_kind(k, lane) for k in (CYCLE, _FEEDBACK, _EVENTS))
        self.truth: Callable[[], tuple[float, float, float, float]] | None = None
        self.drive: Any = SimpleNamespace(status=SimpleNamespace(state=0, protocol_state=-1, error_code=0))

    def cycle(self, k: int, t: float, fb: Any, out: Sequence[float], period_error: float, exec_time: float,
              overrun: bool) -> None:
        """The ``CycleSink`` hook: a cycle record (a ``schemas.CycleRecord``, built as a plain
        tuple in its field order: see ``schemas``); the one place a writer failure is raised
        on the loop thread, after the cycle's command went out."""
        log = self._log
        records, status, truth = log.records, self.drive.status, self.truth
        # the loop's measure (dobhil.drives.base.Feedback.sample_latency): NaN on a simulated
        # log clock, where the stamps are of two clocks
        sampled = _NAN if log.simulated else getattr(fb, "sample_latency", _NAN)
        kind, clock = self._cycle, log.clock_ns
        t = clock()
        extra: tuple[float, ...] = truth() if truth is not None else ()
        try:  # packed (dobhil.recording.packed); a value or a length that does not fit: the tuple
            # named, not starred: a call with ``*out`` builds a list and a tuple of its arguments
            tau_ref, tau_int_hat, tau_dis_hat, tau_per, u_unsat, u_sat = out
            if truth is None:
                records.append(_pack_cycle(kind, t, k, fb.position, fb.velocity, fb.seq, tau_ref, tau_int_hat,
                                           tau_dis_hat, tau_per, u_unsat, u_sat, period_error, exec_time, overrun,
                                           sampled, status.state, status.protocol_state, status.error_code))
            else:
                q, dq, tau_motor, tau_int = extra
                records.append(_pack_cycle_truth(kind, t, k, fb.position, fb.velocity, fb.seq, tau_ref, tau_int_hat,
                                                 tau_dis_hat, tau_per, u_unsat, u_sat, period_error, exec_time,
                                                 overrun, sampled, status.state, status.protocol_state,
                                                 status.error_code, q, dq, tau_motor, tau_int))
        except (*UNFIT, ValueError):
            records.append((kind, t, k, fb.position, fb.velocity, fb.seq, *out, period_error, exec_time, overrun,
                            sampled, status.state, status.protocol_state, status.error_code, *extra))
        if len(records) >= BATCH_RECORDS or log._failure is not None:
            log.flush()

    def started(self, fb: Any) -> None:
        """The feedback ``controller.initialize`` used (``cycle = -1``) and the enable event."""
        status = self.drive.status
        t = self._log.clock_ns()
        self._log.record(RECORD_TYPES[_FEEDBACK](
            kind=self._feedback, log_time_ns=t, position=fb.position, velocity=fb.velocity,
            drive_state=int(status.state), protocol_state=status.protocol_state, protocol_error=status.error_code,
            seq=fb.seq, cycle=-1))
        self.event(EventKind.ENABLE, "drive enabled", f"seq {fb.seq}")

    def stop(self, stop: Any) -> None:
        """The loop has stopped; :meth:`RunLog.end` hands the rest over, none dropped."""

    def safe_stop(self, report: Any) -> None:
        """The sink's safe-stop hook: one ``disable`` event per safe-stop frame (sent or why
        not), then what the drive confirmed (a ``fault`` event with the loud line when it
        may still be enabled; a ``disable`` event with the note of a drive that cannot
        confirm by design, at a planned end)."""
        for frame in report.frames:
            self.event(EventKind.DISABLE, f"{frame.what}: {'sent' if frame.sent else 'not sent'}", frame.error)
        warning = report.warning()
        self.event(EventKind.FAULT if warning else EventKind.DISABLE,
                   f"safe stop: {report.confirmation.name.lower()}", warning or report.note() or report.detail)

    def event(self, kind: EventKind, reason: str, detail: str = "") -> None:
        """An event of this lane (``/events`` in lane 0) after everything appended so far
        (events are never dropped)."""
        self._log.record(EventRecord(self._events, self._log.clock_ns(), int(kind), reason, detail, 0))


class RunLog(LaneSink):
    """Records one run through ``writer`` (started, not yet open: records wait until
    :meth:`begin`, as a preflight talks on the tapped bus): the batches, the loss accounting
    and the bus taps of every lane, and itself the sink of lane 0 (a single-axis run)."""

    def __init__(self, writer: WriterProcess, *, live: LiveView | None = None) -> None:
        super().__init__(self, 0)
        self.writer, self.live = writer, live
        self.clock_ns: Callable[[], int] = time.time_ns
        self.records: list[Any] = []  # tuples and packed records (bytes)
        #: foreign frames (real time, the drive's ids known), else the same list as ``records``
        self.foreign: list[tuple[Any, ...]] = self.records
        self.shed = 0  # foreign frames dropped since the last loss event
        self._own: dict[int, frozenset[int]] = {}  # received frames' kind -> the ids not foreign there
        self._channels: dict[Any, bytes] = {}  # a frame's channel -> packed (packed.channel_bytes)
        self.tap: RecordingBus | None = None
        self.simulated = False  # lockstep: frames stamped on the simulated log clock
        self._failure: RecorderError | None = None
        self._closed = False
        #: why the log's end failed (:meth:`end` raised it), "" while it did not
        self.end_failure = ""

    @property
    def path(self) -> Path:
        return self.writer.path

    @property
    def writer_pid(self) -> int | None:
        """The writer process (to set its priority), None once closed."""
        return None if self._closed else self.writer.pid

    @property
    def live_port(self) -> int | None:
        """The live view's port (after :meth:`begin`), None without one."""
        return None if self._closed else self.writer.live_port

    def wrap_bus(self, bus: can.BusABC, lane: int = 0) -> can.BusABC:
        """The session's ``bus_wrapper``: every frame on ``/can/rx`` and ``/can/tx`` (of ``lane``)."""
        self.tap = RecordingBus(bus, self, lane)
        return self.tap

    def begin(self, *, metadata: Mapping[str, Mapping[str, Any]], attachments: Sequence[tuple[str, str, bytes]],
              lossy: bool, clock_ns: Callable[[], int] | None = None,
              truth: Callable[[], tuple[float, float, float, float]] | None = None, drive: Any = None,
              own_ids: Collection[int] | None = None, codes: ProtocolCodes | None = None,
              lanes: Sequence[Lane] = (), own: Mapping[int, Collection[int]] | None = None,
              cancel: Callable[[], str] | None = None) -> None:
        """Header and metadata; the log clock, the emulator truth ``(q, dq, tau_motor, tau_int)``
        and the drive (its ``status.state``, ``status.protocol_state`` and ``status.error_code``
        go to ``/drive/feedback``, the last two named by ``codes``);
        ``own_ids``: the arbitration ids of the drive's frames (``lossy`` only: other frames
        received are foreign, shed first; None: every frame is the loop's own).
        A several-axis log gives ``lanes`` (:class:`~dobhil.recording.writer.LogWriter`) and
        ``own``: per lane of a bus, the ids of its drives' frames (a lane not in it: none foreign).
        ``cancel`` (the run's stop request: why, or "") ends a lockstep hand-over's wait for
        the writer, the rest kept for the next (:class:`WriterProcess`)."""
        assert not self._closed, "the log is closed"
        self.writer.cancel = cancel
        mode = RecordMode.LOSSY if lossy else RecordMode.BACKPRESSURE
        self.writer.open(metadata, attachments, mode, self.live, early=self.take(), codes=codes, lanes=lanes)
        owned = dict(own or {}) if own_ids is None else {0: own_ids}
        if lossy and owned:
            self._own, self.foreign = {lane_kind(_RX, lane): frozenset(ids) for lane, ids in owned.items()}, []
        self.clock_ns = clock_ns or time.time_ns
        self.simulated = clock_ns is not None
        self.truth = truth
        if drive is not None:
            self.drive = drive

    def frame(self, topic: int, msg: Any) -> None:
        """A frame (``topic``: ``/can/rx`` or ``/can/tx``'s kind in its bus's lane) as it is
        now: :meth:`received` or :meth:`sent` by the topic."""
        if topic & LANE_MASK == _RX:
            self.received(topic, msg)
        else:
            self.sent(topic, msg)

    def received(self, topic: int, msg: Any) -> None:
        """A received frame (``topic``: ``/can/rx``'s kind in its bus's lane): python-can
        hands out a new message per receive, so its data is kept as it is (not copied).
        ``schemas.can_frame_record`` spelled out for speed (a ``FrameRecord`` as a plain
        tuple in its field order). A foreign frame beyond ``FOREIGN_CAP`` is shed here
        (counted): a flood costs the loop a count, not a record. Never raises into the bus
        call that recorded it.

        Its bus timestamp: a received frame keeps the interface's, which in real time is the
        wall clock the log clock runs on (SocketCAN, virtual); in lockstep (a simulated log
        clock) it gets the simulated time, as a sent frame does (:meth:`sent`), so a CAN
        export of the run has one time base."""
        try:
            own = self._own.get(topic) if self._own else None
            if own and msg.arbitration_id not in own:
                self._foreign_frame(topic, msg)
                return
            records, clock = self.records, self.clock_ns  # an attribute, then called: a
            t = clock()  # method-style call of an instance attribute is not specialised (CPython 3.11)
            stamp, data = t / 1e9 if self.simulated else msg.timestamp, msg.data
            try:  # packed (dobhil.recording.packed); a value that does not fit: the tuple
                records.append(_join((_pack_frame(
                    topic, t, msg.arbitration_id, msg.is_extended_id, msg.is_remote_frame, msg.is_error_frame,
                    msg.is_fd, msg.bitrate_switch, msg.error_state_indicator, msg.dlc, stamp, len(data)), data,
                    self._channels.get(msg.channel) or channel_bytes(msg.channel, self._channels))))
            except UNFIT:
                records.append((topic, t, msg.arbitration_id, msg.is_extended_id, msg.is_remote_frame,
                                msg.is_error_frame, msg.is_fd, msg.bitrate_switch, msg.error_state_indicator,
                                msg.dlc, data, stamp, msg.channel))
            if len(records) >= FRAME_FLUSH:
                self.flush()
        except RecorderError as exc:
            self._failure = exc  # the next cycle raises it
        except Exception as exc:  # not a python-can message
            self._failure = self.writer.refuse(f"cannot encode a CAN frame: {exception_line(exc)}")

    def sent(self, topic: int, msg: Any) -> None:
        """A sent frame (``topic``: ``/can/tx``'s kind in its bus's lane), its data copied (the
        drive refills its torque message), stamped with the log clock now, just after the
        send (its message carries none, 0.0): in real time the wall clock received frames
        are stamped on, in lockstep the simulated time. As :meth:`received` otherwise."""
        try:
            records, clock = self.records, self.clock_ns
            t = clock()
            data = msg.data
            try:  # packed: the data copied into it
                records.append(_join((_pack_frame(
                    topic, t, msg.arbitration_id, msg.is_extended_id, msg.is_remote_frame, msg.is_error_frame,
                    msg.is_fd, msg.bitrate_switch, msg.error_state_indicator, msg.dlc, t / 1e9, len(data)), data,
                    self._channels.get(msg.channel) or channel_bytes(msg.channel, self._channels))))
            except UNFIT:
                records.append((topic, t, msg.arbitration_id, msg.is_extended_id, msg.is_remote_frame,
                                msg.is_error_frame, msg.is_fd, msg.bitrate_switch, msg.error_state_indicator,
                                msg.dlc, bytes(data), t / 1e9, msg.channel))
            if len(records) >= FRAME_FLUSH:
                self.flush()
        except RecorderError as exc:
            self._failure = exc
        except Exception as exc:
            self._failure = self.writer.refuse(f"cannot encode a CAN frame: {exception_line(exc)}")

    def _foreign_frame(self, topic: int, msg: Any) -> None:
        """A received frame of another participant: kept up to ``FOREIGN_CAP``, else shed."""
        foreign = self.foreign
        if len(foreign) >= FOREIGN_CAP:
            self.shed += 1
            return
        foreign.append((topic, self.clock_ns(), msg.arbitration_id, msg.is_extended_id, msg.is_remote_frame,
                        msg.is_error_frame, msg.is_fd, msg.bitrate_switch, msg.error_state_indicator, msg.dlc,
                        msg.data, msg.timestamp, msg.channel))

    def record(self, record: Sequence[Any]) -> None:
        """A flat record of the topic table (an event): never dropped."""
        self.records.append(tuple(record))

    def flush(self) -> None:
        """Hand the records over (with the foreign frames, if the pipe has room for them); dropped
        if the writer lags: the events kept for the next, with a ``loss`` event counting the rest."""
        if self._failure is not None:
            failure, self._failure = self._failure, None
            raise failure
        if not self.writer.opened:
            return
        records, self.records = self.records, []
        if self.foreign is not records:
            records = self._with_foreign(records)
        else:
            self.foreign = self.records
        if not self.writer.write(self.writer.encode(records)):
            self._drop(records)

    def _drop(self, records: list[tuple[Any, ...]]) -> None:
        """A batch the writer had no room for: its events kept for the next, a ``loss`` event
        counting the rest (read by name, unpacked: this path is rare)."""
        records = [unpacked(r) for r in records]
        kept = [r for r in map(named, records) if r.kind & LANE_MASK == _EVENTS]
        lost, carried = sum(message_count(r) for r in records) - len(kept), 0
        if len(kept) > BATCH_RECORDS:  # a writer stuck for good: memory stays bounded
            carried = sum(r.lost for r in kept if r.event == _LOSS)  # earlier losses fold into this one
            lost += sum(r.event != _LOSS for r in kept)
            kept = []
        self.writer.dropped += lost
        if lost + carried:
            kept.append(event_record(EventKind.LOSS, named(records[-1]).log_time_ns, f"{lost + carried} messages "
                                     "dropped (writer lagging)", f"total {self.writer.dropped}", lost + carried))
        self.records[:0] = kept

    def _with_foreign(self, records: list[tuple[Any, ...]]) -> list[tuple[Any, ...]]:
        """``records`` and the foreign frames if the pipe is less than half full, else the
        foreign frames shed; a ``loss`` event counts what was shed."""
        foreign, self.foreign = self.foreign, []
        if foreign and self.writer.queued() + FOREIGN_BYTES * len(foreign) < FOREIGN_ROOM:
            records += foreign
        else:
            self.shed += len(foreign)
        if self.shed:
            self.writer.dropped += self.shed
            records.append(event_record(EventKind.LOSS, self.clock_ns(), f"{self.shed} foreign frames dropped "
                                        "(bus flood, writer lagging)", f"total {self.writer.dropped}", self.shed))
            self.shed = 0
        return records

    def take(self) -> list[tuple[Any, ...]]:
        """Every record not yet handed over (foreign frames included); none are left after."""
        records, self.records = self.records, []
        if self.foreign is not records:
            records += self.foreign
            self.foreign = []
            if self.shed:
                self.writer.dropped += self.shed
                records.append(event_record(EventKind.LOSS, self.clock_ns(), f"{self.shed} foreign frames dropped "
                                            "(bus flood)", f"total {self.writer.dropped}", self.shed))
                self.shed = 0
        else:
            self.foreign = self.records
        return records

    def end(self, stop_reason: str | None, detail: str = "", cancel: Callable[[], str] | None = None) -> None:
        """The last records, the stop event, summary and footer; waits for the writer, for a
        bounded time (:meth:`WriterProcess.close`; ``cancel``: why to stop waiting, or "").
        Raises :class:`~dobhil.errors.RecorderError` if the writer failed (once)."""
        if self._closed:
            return
        self._closed = True
        try:
            self.writer.close(stop_reason, detail, rest=self.take(), cancel=cancel)
        except RecorderError as exc:
            self.end_failure = str(exc)
            raise


__all__ = ["BATCH_RECORDS", "FOREIGN_CAP", "FOREIGN_ROOM", "LaneSink", "RecordingBus", "RunLog"]
