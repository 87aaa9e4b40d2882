"""The writer process of run logging: modes, signals, failures, no process left behind."""

from __future__ import annotations

import os
import signal
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pytest

from dobhil.recording.process import QUEUE_BATCHES, WriterProcess
from dobhil.recording.reader import open_log
from dobhil.recording.schemas import CYCLE, EventKind, event_record
from dobhil.recording.writer import RecordMode

from tests.recording.conftest import child_processes

META = {"run": {"who": "test"}}


def cycle(k: int) -> tuple[Any, ...]:
    """A flat CYCLE record with truth (5 messages)."""
    t = 1_000_000_000 + k * 1_000_000
    return (CYCLE, t, k, 1e-4 * k, 0.1, k, 0.2, 0.19, 0.01, 0.02, 0.03, 0.03,
            0.0, 3e-5, False, 8, 0, 1e-4 * k, 0.1, 0.03, 0.19)


def batch(start: int, n: int = 256) -> list[tuple[Any, ...]]:
    return [cycle(k) for k in range(start, start + n)]


@contextmanager
def stopped(proc: WriterProcess) -> Iterator[None]:
    """The writer process frozen (SIGSTOP) for the block: a writer that lags forever."""
    os.kill(proc.pid, signal.SIGSTOP)
    try:
        yield
    finally:
        os.kill(proc.pid, signal.SIGCONT)


def test_backpressure_round_trip_and_the_process_is_joined(tmp_path: Path) -> None:
    path = tmp_path / "run.mcap"
    writer = WriterProcess(path, fsync=False)
    assert writer.pid in child_processes()
    writer.open(META, [("config.yaml", "application/yaml", b"a: 1\n")], RecordMode.BACKPRESSURE)
    for i in range(0, 5120, 256):
        assert writer.send(batch(i))
    writer.send([event_record(EventKind.INFO, 7, "note", "x")])
    writer.close("done", "all good")
    writer.close("again")  # idempotent
    assert writer.pid not in child_processes()
    info = open_log(path).info()
    counts = {c.topic: c.message_count for c in info.channels}
    assert counts["/controller"] == counts["/emulator/truth"] == 5120
    assert info.stop_reason == "done" and info.metadata["run"] == {"who": "test"}
    assert info.metadata["recording"]["mode"] == "backpressure" and writer.written == info.message_count


def test_backpressure_blocks_while_the_writer_lags_and_loses_nothing(tmp_path: Path) -> None:
    writer = WriterProcess(tmp_path / "run.mcap", fsync=False)
    writer.open(META, [], RecordMode.BACKPRESSURE)
    sent = [0]

    def produce() -> None:
        for i in range(0, 256 * 200, 256):
            writer.send(batch(i))
            sent[0] += 1

    with stopped(writer):
        thread = threading.Thread(target=produce)
        thread.start()
        time.sleep(1.0)
        in_flight = sent[0]
        time.sleep(0.3)
        assert sent[0] == in_flight <= QUEUE_BATCHES + 8  # blocked: a bounded number of batches in flight
    thread.join(30)
    assert not thread.is_alive()
    writer.close("done")
    counts = {c.topic: c.message_count for c in open_log(tmp_path / "run.mcap").info().channels}
    assert counts["/loop"] == 256 * 200


def test_lossy_never_blocks_drops_are_counted_and_events_kept(tmp_path: Path) -> None:
    path = tmp_path / "run.mcap"
    writer = WriterProcess(path, fsync=False)
    writer.open(META, [], RecordMode.LOSSY)
    accepted = 0
    with stopped(writer):
        t0 = time.perf_counter()
        for i in range(0, 256 * 200, 256):
            records = batch(i)
            if i == 256 * 150:
                records.append(event_record(EventKind.INFO, records[-1][1], "kept"))
            accepted += writer.send(records)
        elapsed = time.perf_counter() - t0
    assert elapsed < 5.0 and 0 < accepted < 200
    writer.close("done")
    log = open_log(path)
    info = log.info()
    counts = {c.topic: c.message_count for c in info.channels}
    assert counts["/loop"] == 256 * accepted
    events = [p for _, _, p in log.iter_messages(["/events"])]
    losses = [e for e in events if e["kind"] == "loss"]
    assert sum(e["count"] for e in losses) == writer.dropped == 5 * 256 * (200 - accepted)
    assert info.metadata["recording"]["dropped"] == str(writer.dropped)
    assert [e["reason"] for e in events if e["kind"] == "info"] == ["kept"]
    assert events[-1]["kind"] == "stop"


def test_the_writer_ignores_sigint_and_sigterm(tmp_path: Path) -> None:
    writer = WriterProcess(tmp_path / "run.mcap", fsync=False)
    os.kill(writer.pid, signal.SIGINT)  # may arrive before the child ignores it: blocked until then
    writer.open(META, [], RecordMode.BACKPRESSURE)
    os.kill(writer.pid, signal.SIGTERM)
    writer.send(batch(0))
    time.sleep(0.2)
    writer.close("done")
    assert open_log(tmp_path / "run.mcap").info().stop_reason == "done"


def test_closed_before_open_leaves_no_file(tmp_path: Path) -> None:
    path = tmp_path / "run.mcap"
    writer = WriterProcess(path)
    writer.abandon()
    assert not path.exists()


def test_bad_path_fails_at_once(tmp_path: Path) -> None:
    with pytest.raises(OSError):
        WriterProcess(tmp_path / "missing" / "run.mcap")
