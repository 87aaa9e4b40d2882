"""The MCAP recorder: the caller encodes and enqueues, one writer thread writes.

This is the general-purpose recorder (``dobhil log import``, tools, tests). Run logging
uses a writer *process* instead (:mod:`~dobhil.recording.writerproc`), so the control
loop does not share the GIL with the encoding; both write through the same
:class:`~dobhil.recording.filewriter.LogFileWriter`.

:class:`Recorder` turns each record into compact JSON in the caller's thread
(so the payload may be reused right after :meth:`Recorder.write`) and puts it
on an unbounded C queue whose length is bounded by two single-writer counters:

- :attr:`RecordMode.BACKPRESSURE` (lockstep runs): ``write`` waits for room; nothing is lost.
- :attr:`RecordMode.LOSSY` (real time): ``write`` never waits; a record that finds
  the queue full is dropped and counted. The writer thread writes an ``/events``
  record ``kind=loss`` with the count as soon as it runs again, and the total is
  in the ``recording`` metadata record written on close.

The writer thread owns the :class:`~dobhil.recording.filewriter.LogFileWriter`. Every ``flush_interval``
seconds it ends the current chunk, flushes and fsyncs the file, so a ``kill -9``
loses at most about that much (``dobhil log recover`` salvages the rest). Events
(:meth:`Recorder.event`) are never dropped. A failure of the writer thread (disk
full, ...) is raised from the next ``write``/``event``/``close`` call.
"""

from __future__ import annotations

import itertools
import os
import queue
import threading
import time
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import Any, Final
from collections.abc import Callable

import can

from dobhil.errors import LogFileError
from dobhil.recording.fastlog import event_payload, loss_payload, messages_per_record
from dobhil.recording.filewriter import (
    CHUNK_SIZE,
    RECORDING_METADATA,
    LogFileWriter,
    RecordMode,
    chunk_compression,
)
from dobhil.recording.schemas import Direction, EventKind, Topic, encode, spec_for

#: Most records the writer thread handles between two looks at the flush clock.
_BATCH: Final = 4096
#: LOSSY mode: raw records encoded between two hand-backs of the GIL.
_YIELD_EVERY: Final = 16


@dataclass(frozen=True)
class _Stop:
    """Queue sentinel: finish the file, optionally after a stop event."""

    reason: str | None
    detail: str = ""


@dataclass(frozen=True)
class _Batch:
    """Raw records (:mod:`dobhil.recording.fastlog`) encoded by the writer thread."""

    records: list[tuple[Any, ...]]
    count: int


_Item = tuple[Topic, int, bytes]


def frame_payload(msg: can.Message, direction: Direction) -> dict[str, Any]:
    """The ``/can/rx`` or ``/can/tx`` payload of a python-can message."""
    data = bytes(msg.data or b"")
    return {
        "timestamp": float(msg.timestamp or 0.0),
        "arbitration_id": msg.arbitration_id,
        "is_extended_id": msg.is_extended_id,
        "is_remote_frame": msg.is_remote_frame,
        "is_error_frame": msg.is_error_frame,
        "is_fd": msg.is_fd,
        "bitrate_switch": msg.bitrate_switch,
        "error_state_indicator": msg.error_state_indicator,
        "dlc": msg.dlc,
        "data": list(data),
        "data_hex": data.hex(),
        "direction": direction.name.lower(),
        "channel": "" if msg.channel is None else str(msg.channel),
    }


class Recorder:
    """Records dobhil topics to one MCAP file from any thread; see the module doc.

    ``metadata`` maps record names ("config", "versions", "bus", "run") to flat
    str -> str dicts (values are passed through ``str``); ``attachments`` are
    ``(name, media_type, data)`` triples, e.g. the run's config YAML.
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        *,
        metadata: Mapping[str, Mapping[str, Any]],
        attachments: Iterable[tuple[str, str, bytes]] = (),
        mode: RecordMode,
        queue_size: int = 65536,
        flush_interval: float = 1.0,
        fsync: bool = True,
    ) -> None:
        if queue_size < 1 or flush_interval <= 0:
            raise LogFileError(f"queue_size must be >= 1 and flush_interval > 0, got {queue_size}, {flush_interval}")
        self.path = Path(path)
        self.mode = RecordMode(mode)
        self._size = queue_size
        self._interval = flush_interval
        self._fsync = fsync
        self._queue: queue.SimpleQueue[_Item | _Batch | _Stop] = queue.SimpleQueue()
        self._room = threading.Event()
        # Counters: itertools.count is atomic under the GIL, so callers in several
        # threads (control loop, CAN notifier) neither lose nor double counts.
        self._enqueue_count = itertools.count(1)
        self._drop_count = itertools.count(1)
        self._enqueued = 0
        self._dequeued = 0  # written by the writer thread only
        self._dropped = 0
        self._reported_drops = 0
        self._last_drop_ns = 0
        self._last_log_ns = 0
        self._accepting = True
        self._failure: BaseException | None = None
        self._log = self._open(metadata, attachments)
        self._thread = threading.Thread(target=self._run, name=f"dobhil-recorder:{self.path.name}", daemon=True)
        self._thread.start()

    # -- caller side -------------------------------------------------------

    @property
    def dropped(self) -> int:
        """Records dropped so far because the queue was full (LOSSY only)."""
        return self._dropped

    @property
    def written(self) -> int:
        """Messages written to the file so far (by the writer thread)."""
        return self._log.written

    def write(self, topic: str | Topic, log_time_ns: int, payload: Mapping[str, Any]) -> bool:
        """Record one payload; False if dropped (LOSSY, queue full)."""
        spec = spec_for(topic)
        return self._put((spec.topic, log_time_ns, encode(payload)), force=False)

    def write_frame(self, msg: can.Message, direction: Direction, log_time_ns: int) -> bool:
        """Record one CAN frame on ``/can/rx`` or ``/can/tx``."""
        topic = Topic.CAN_RX if direction == Direction.RX else Topic.CAN_TX
        return self._put((topic, log_time_ns, encode(frame_payload(msg, direction))), force=False)

    def write_batch(self, records: list[tuple[Any, ...]]) -> bool:
        """Record raw records (see :mod:`~dobhil.recording.fastlog`), JSON-encoded by the
        writer thread; False if the whole batch was dropped (LOSSY, queue full)."""
        if not records:
            return True
        count = sum(map(messages_per_record, records))
        return self._put_batch(_Batch(records, count), records[-1][1])

    def event(
        self, kind: EventKind, reason: str, detail: str = "", *, log_time_ns: int | None = None
    ) -> None:
        """Record an ``/events`` record; never dropped. Time defaults to the last record's."""
        stamp = self._default_time() if log_time_ns is None else log_time_ns
        self._put((Topic.EVENTS, stamp, encode(event_payload(EventKind(kind), reason, detail))), force=True)

    def close(self, stop_reason: str | None = None, detail: str = "") -> None:
        """Drain the queue, write a stop event if a reason is given, finish the file."""
        if not self._thread.is_alive() and self._log.file.closed:
            self._raise_failure()
            return
        self._accepting = False
        self._queue.put(_Stop(stop_reason, detail))
        self._thread.join()
        self._log.close()
        self._raise_failure()

    def __enter__(self) -> Recorder:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close(None if exc is None else f"error: {type(exc).__name__}: {exc}")

    def _put(self, item: _Item, *, force: bool) -> bool:
        if not self._accepting:
            self._raise_failure()
            raise LogFileError(f"{self.path}: recorder is closed")
        if not force and self._enqueued - self._dequeued >= self._size:
            if self.mode == RecordMode.LOSSY:
                self._dropped = next(self._drop_count)
                self._last_drop_ns = item[1]
                return False
            self._wait_for_room()
        self._last_log_ns = item[1]
        self._enqueued = next(self._enqueue_count)
        self._queue.put(item)
        return True

    def _put_batch(self, batch: _Batch, last_ns: int) -> bool:
        if not self._accepting:
            self._raise_failure()
            raise LogFileError(f"{self.path}: recorder is closed")
        if self._enqueued - self._dequeued >= self._size:
            if self.mode == RecordMode.LOSSY:
                for _ in range(batch.count):
                    self._dropped = next(self._drop_count)
                self._last_drop_ns = last_ns
                return False
            self._wait_for_room()
        self._last_log_ns = last_ns
        for _ in range(batch.count):
            self._enqueued = next(self._enqueue_count)
        self._queue.put(batch)
        return True

    def _wait_for_room(self) -> None:
        while self._enqueued - self._dequeued >= self._size:
            self._room.clear()
            if self._enqueued - self._dequeued < self._size:
                return
            self._room.wait(0.1)
            if self._failure is not None:
                self._raise_failure()

    def _default_time(self) -> int:
        return self._last_log_ns or time.time_ns()

    def _raise_failure(self) -> None:
        if self._failure is not None:
            raise LogFileError(f"{self.path}: recorder failed: {self._failure}") from self._failure

    # -- writer side ---------------------------------------------------------

    def _open(
        self, metadata: Mapping[str, Mapping[str, Any]], attachments: Iterable[tuple[str, str, bytes]]
    ) -> LogFileWriter:
        try:
            file = open(self.path, "wb")
        except OSError as exc:
            raise LogFileError(f"{self.path}: cannot create: {exc.strerror}") from exc
        try:
            return LogFileWriter(file, metadata=metadata, attachments=attachments, mode=self.mode,
                                 fsync=self._fsync)
        except BaseException:
            file.close()
            raise

    def _run(self) -> None:
        try:
            self._loop()
        except BaseException as exc:
            self._failure = exc
            self._accepting = False
            self._room.set()

    def _loop(self) -> None:
        next_flush = time.monotonic() + self._interval
        while True:
            stop = self._drain(max(0.0, next_flush - time.monotonic()))
            self._report_drops()
            if stop is not None:
                self._finish(stop)
                return
            if time.monotonic() >= next_flush:
                self._flush()
                next_flush = time.monotonic() + self._interval

    def _drain(self, timeout: float) -> _Stop | None:
        """Write up to one batch; wait at most ``timeout`` for the first item."""
        try:
            item = self._queue.get(timeout=timeout)
        except queue.Empty:
            return None
        for _ in range(_BATCH):
            if isinstance(item, _Stop):
                return item
            self._take(item)
            try:
                item = self._queue.get_nowait()
            except queue.Empty:
                return None
        if isinstance(item, _Stop):
            return item
        self._take(item)
        return None

    def _take(self, item: _Item | _Batch) -> None:
        """Write one dequeued item and tell a waiting caller there is room."""
        if isinstance(item, _Batch):
            self._write_batch(item)
        else:
            self._dequeued += 1
            self._write_message(*item)
        if not self._room.is_set():
            self._room.set()

    def _write_message(self, topic: Topic, log_time_ns: int, data: bytes) -> None:
        """Write one message (the hook tests override to slow the writer down)."""
        self._log.write_message(topic, log_time_ns, data)

    def _write_batch(self, batch: _Batch) -> None:
        """Encode and write a batch; in LOSSY (real-time) mode hand the GIL back to the
        caller every few records, so a batch never delays it by a switch interval."""
        if self.mode == RecordMode.LOSSY:
            records = batch.records
            for i in range(0, len(records), _YIELD_EVERY):
                self._log.write_records(records[i:i + _YIELD_EVERY])
                time.sleep(0)
        else:
            self._log.write_records(batch.records)
        self._dequeued += batch.count

    def _report_drops(self) -> None:
        dropped = self._dropped
        if dropped == self._reported_drops:
            return
        count = dropped - self._reported_drops
        self._reported_drops = dropped
        self._log.dropped = dropped
        self._write_message(Topic.EVENTS, self._last_drop_ns, encode(loss_payload(count, dropped)))

    def _flush(self) -> None:
        self._log.flush()

    def _finish(self, stop: _Stop) -> None:
        self._drain_rest()
        self._report_drops()
        if stop.reason is not None:
            payload = event_payload(EventKind.STOP, stop.reason, stop.detail)
            self._write_message(Topic.EVENTS, self._default_time(), encode(payload))
        self._log.finish(stop.reason)

    def _drain_rest(self) -> None:
        """Items a racing caller put after the stop sentinel."""
        while True:
            try:
                item = self._queue.get_nowait()
            except queue.Empty:
                return
            if not isinstance(item, _Stop):
                self._take(item)


class CanRecordListener(can.Listener):
    """A :class:`can.Listener` that records every received frame on ``/can/rx``."""

    def __init__(self, recorder: Recorder, *, clock: Callable[[], int] = time.time_ns) -> None:
        self._recorder = recorder
        self._clock = clock

    def on_message_received(self, msg: can.Message) -> None:
        self._recorder.write_frame(msg, Direction.RX, self._clock())

    def stop(self) -> None:
        """Nothing to release; the recorder is closed by its owner."""


def record_can_bus(
    recorder: Recorder, bus: can.BusABC, *, clock: Callable[[], int] = time.time_ns
) -> can.Notifier:
    """A notifier recording every frame ``bus`` receives; the caller stops it."""
    return can.Notifier(bus, [CanRecordListener(recorder, clock=clock)])


__all__ = [
    "CHUNK_SIZE",
    "RECORDING_METADATA",
    "CanRecordListener",
    "RecordMode",
    "Recorder",
    "chunk_compression",
    "event_payload",
    "frame_payload",
    "record_can_bus",
]
