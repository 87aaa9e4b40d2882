"""The writer process of run logging and the packed hand-over: modes, signals, failures,
round trips against literal records, no process left behind."""

from __future__ import annotations

import os
import signal
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from multiprocessing.connection import Connection
from pathlib import Path
from types import SimpleNamespace
from typing import cast

import can
import pytest

from dobhil import forkserver
from dobhil.errors import LogFileError, RecorderError
from dobhil.recording import process
from dobhil.recording.process import PIPE_SIZE, STALL_TIMEOUT, WriterProcess, encode, unpack
from dobhil.recording.runlog import BATCH_RECORDS, RunLog
from dobhil.recording.reader import open_log
from dobhil.recording.schemas import CYCLE, EventKind, Topic, event_record
from dobhil.recording.writer import LiveView, RecordMode
from dobhil.runtime.controller import ControlOutput

from tests.recording.conftest import child_processes
from tests.recording.helpers import topic_counts
from tests.recording.live_double import FileOutput

META = {"run": {"who": "test"}}
DRIVE = SimpleNamespace(status=SimpleNamespace(state=8, protocol_state=4, error_code=0))
OUT = ControlOutput(0.2, 0.19, 0.01, 0.02, 0.03, 0.03)


RX, TX = int(Topic.CAN_RX), int(Topic.CAN_TX)


def cycle(batch: RunLog, k: int) -> None:
    """A cycle with truth (5 messages) at log time 1 s + k ms."""
    fb = SimpleNamespace(position=1e-4 * k, velocity=0.1, seq=k)
    batch.clock_ns = lambda: 1_000_000_000 + k * 1_000_000
    batch.drive, batch.truth = DRIVE, lambda: (1e-4 * k, 0.1, 0.03, 0.19)
    batch.cycle(k, k * 1e-3, fb, OUT, 0.0, 3e-5, False)


#: Pipe bytes of one cycle record with truth.
CYCLE_BYTES = len(encode([(CYCLE, k, k, *(0.5 + k,) * 3, *OUT, 0.0, 3e-5, False, 8, 4, 0, *(k + 0.25,) * 4)
                           for k in range(BATCH_RECORDS)])) // BATCH_RECORDS


def opened(path: Path, mode: RecordMode) -> tuple[WriterProcess, RunLog]:
    writer = WriterProcess(path, fsync=False)
    writer.open(META, [("config.yaml", "application/yaml", b"a: 1\n")], mode)
    return writer, RunLog(writer)


@contextmanager
def stopped(proc: WriterProcess) -> Iterator[None]:
    """The writer process frozen (SIGSTOP) for the block: a writer that lags forever."""
    os.kill(proc.pid, signal.SIGSTOP)
    try:
        yield
    finally:
        try:
            os.kill(proc.pid, signal.SIGCONT)
        except ProcessLookupError:
            pass   # given up and killed while stopped


#: [s] a count that did not move for this long stopped: the producer is blocked (a thread
#: that runs moves it within milliseconds)
QUIET = 0.3


def still_for(count: Callable[[], int], quiet: float, bound: float = 30.0) -> int:
    """``count()`` once it moved from 0 and then stayed for ``quiet`` s (``bound``: for a
    loaded machine, not a measurement; on it the count as it is)."""
    end = time.monotonic() + bound
    value, since = count(), time.monotonic()
    while time.monotonic() < end:
        time.sleep(0.02)
        now = count()
        if now != value or now == 0:
            value, since = now, time.monotonic()
        elif time.monotonic() - since >= quiet:
            break
    return value


def counts(path: Path) -> dict[str, int]:
    return topic_counts(path)


def test_batched_records_unpack_to_the_flat_records_of_the_topic_table() -> None:
    """Literal records in, the same flat tuples out: a cycle with and without truth, an FD
    frame, a remote frame without data, channels str / int / None, a long event, numpy
    values exact."""
    import numpy as np
    batch = RunLog(SimpleNamespace(opened=False))  # type: ignore[arg-type]
    fb = SimpleNamespace(position=0.5, velocity=np.float64(-1.25), seq=np.int64(7), sample_latency=2.5e-4)
    batch.clock_ns = lambda: 11
    fd = can.Message(arbitration_id=0x1ABCDEF, is_extended_id=True, is_fd=True, bitrate_switch=True,
                     data=bytes(range(64)), channel="can0", timestamp=5.5)
    rtr = can.Message(arbitration_id=0x07B, is_extended_id=False, is_remote_frame=True, dlc=8, channel=1)
    plain = can.Message(arbitration_id=0x069, is_extended_id=False, data=b"\x01\x02", channel=None)
    batch.drive = DRIVE
    for i in range(40):
        batch.truth = None
        batch.cycle(3, 0.003, fb, OUT, 1e-6, 2e-5, True)
        batch.truth = lambda: (1.0, 2.0, 3.0, 4.0)
        batch.cycle(4, 0.004, fb, OUT, 0.0, 0.0, False)
        for topic, msg in ((RX, fd), (TX, rtr), (RX, plain)):
            batch.frame(topic, msg)
        batch.record(event_record(EventKind.INFO, 14, "note", f"{i:03}" + "\u00e9" * 5000))
    taken = batch.take()
    data = b"".join(encode(taken[i:i + 7]) for i in range(0, 240, 7))
    batches, used = unpack(data)
    records = [r for batch in batches for r in batch]
    assert used == len(data) and len(records) == 6 * 40
    assert records[0] == (CYCLE, 11, 3, 0.5, -1.25, 7, *OUT, 1e-6, 2e-5, True, 2.5e-4, 8, 4, 0)
    # packed on the loop thread (dobhil.recording.packed): numpy numbers come back as the
    # Python numbers of the same value, not as bytes
    assert type(records[0][4]) is float and type(records[0][5]) is int and records[0][4] == np.float64(-1.25)
    assert [type(r).__name__ for r in taken[:6]] == ["bytes", "bytes", "bytes", "tuple", "bytes", "tuple"]
    assert records[1] == (CYCLE, 11, 4, 0.5, -1.25, 7, *OUT, 0.0, 0.0, False, 2.5e-4, 8, 4, 0, 1.0, 2.0, 3.0, 4.0)
    no, yes = False, True
    assert records[2] == (RX, 11, 0x1ABCDEF, yes, no, no, yes, yes, no, 64, bytes(range(64)), 5.5, "can0")
    assert records[3] == (TX, 11, 0x07B, no, yes, no, no, no, no, 8, b"", 11 / 1e9, 1)  # sent: stamped at send
    assert records[4] == (RX, 11, 0x069, no, no, no, no, no, no, 2, b"\x01\x02", 0.0, None)
    assert records[5] == (int(Topic.EVENTS), 14, int(EventKind.INFO), "note", "000" + "\u00e9" * 5000, 0)


def test_a_writer_stuck_for_good_bounds_the_kept_events_and_still_counts_every_loss(tmp_path: Path) -> None:
    """More events than a batch while the writer is frozen: the kept events are dropped too
    (memory bounded), earlier loss events fold into the next, and what reaches the file
    still adds up: the loss counts = the drop count = the metadata."""
    path = tmp_path / "run.mcap"
    writer, batch = opened(path, RecordMode.LOSSY)
    total = 3 * PIPE_SIZE // CYCLE_BYTES
    with stopped(writer):
        for k in range(total):
            cycle(batch, k)
            if k % 20 == 0:
                batch.record(event_record(EventKind.INFO, 1_000_000_000 + k * 1_000_000, "note"))
        assert len(batch.records) <= 3 * BATCH_RECORDS  # bounded however long it lags
    writer.close("done", rest=batch.take())
    log = open_log(path)
    events = [p for _, _, p in log.iter_messages(["/events"])]
    losses = [e["count"] for e in events if e["kind"] == "loss"]
    written = counts(path)
    notes, sent = sum(e["kind"] == "info" for e in events), len(range(0, total, 20))
    assert 0 < notes < sent and losses
    assert sum(losses) == writer.dropped == log.info().dropped
    assert writer.dropped == 5 * (total - written["/loop"]) + sent - notes


def test_a_batch_cut_by_a_read_waits_for_the_rest() -> None:
    data = encode([event_record(EventKind.INFO, 1, "a")]) + encode([event_record(EventKind.INFO, 2, "b")])
    batches, used = unpack(data[:-3])
    assert batches == [[event_record(EventKind.INFO, 1, "a")]] and used < len(data)
    assert unpack(data[used:]) == ([[event_record(EventKind.INFO, 2, "b")]], len(data) - used)


@pytest.mark.parametrize("start", ["forked", "interpreter"])
def test_backpressure_round_trip_and_the_process_is_joined(tmp_path: Path, start: str,
                                                           monkeypatch: pytest.MonkeyPatch) -> None:
    """Both ways the writer starts: forked from dobhil's fork server (where the platform
    can) and a fresh interpreter (where it cannot)."""
    if start == "interpreter":
        monkeypatch.setattr(forkserver, "available", lambda: False)
    path = tmp_path / "run.mcap"
    writer, batch = opened(path, RecordMode.BACKPRESSURE)
    assert writer.pid in child_processes()
    parent = int(Path(f"/proc/{writer.pid}/stat").read_text().rsplit(")", 1)[1].split()[1])
    assert (parent == os.getpid()) is (start == "interpreter"), (start, parent)
    for k in range(5120):
        cycle(batch, k)
    batch.record(event_record(EventKind.INFO, 7, "note", "x"))
    writer.close("done", "all good", rest=batch.take())
    writer.close("again")  # idempotent
    assert writer.pid not in child_processes()
    info = open_log(path).info()
    assert counts(path)["/controller"] == counts(path)["/emulator/truth"] == 5120
    assert info.stop_reason == "done" and info.metadata["run"] == {"who": "test"}
    assert info.metadata["recording"]["mode"] == "backpressure" and writer.written == sum(topic_counts(path).values())


def test_the_writer_process_serves_the_live_view_it_is_given(tmp_path: Path) -> None:
    """The recording imports no live view: the caller names what to serve (a LiveView), the
    writer process makes it there with every channel, reports its port, sends it every
    message and closes it."""
    served = tmp_path / "served.txt"
    writer = WriterProcess(tmp_path / "run.mcap", fsync=False)
    writer.open(META, [], RecordMode.BACKPRESSURE, LiveView(FileOutput, str(served), 4321))
    assert writer.live_port == 4321
    batch = RunLog(writer)
    for k in range(3):
        cycle(batch, k)
    writer.close("done", rest=batch.take())
    lines = served.read_text().splitlines()
    assert "channel /controller dobhil.Controller" in lines and lines[-1] == "closed"
    # advertised before it listens: a Foxglove connected at once was refused a channel added
    # after (tests/live/test_serve.py: foxglove-sdk's race)
    assert lines.index("channel /controller dobhil.Controller") < lines.index("listening")
    assert lines.index("channel /cycle dobhil.Cycle") < lines.index("listening")
    # the default layout: each cycle's message as the file has it, not its topics apart
    assert [line for line in lines if line.startswith("/cycle ")] == [
        f"/cycle {1_000_000_000 + k * 1_000_000}" for k in range(3)]
    assert not [line for line in lines if line.startswith("/controller ")]


def test_backpressure_blocks_while_the_writer_lags_and_loses_nothing(tmp_path: Path) -> None:
    writer, batch = opened(tmp_path / "run.mcap", RecordMode.BACKPRESSURE)
    sent = [0]
    total = 3 * PIPE_SIZE // CYCLE_BYTES  # three pipes full of cycle records

    def produce() -> None:
        for k in range(total):
            cycle(batch, k)
            sent[0] += 1

    with stopped(writer):
        thread = threading.Thread(target=produce)
        thread.start()
        in_flight = still_for(lambda: sent[0], QUIET)
        assert sent[0] == in_flight < total  # blocked: at most a pipe full in flight
        assert in_flight * CYCLE_BYTES <= PIPE_SIZE + 2 * BATCH_RECORDS * CYCLE_BYTES
    thread.join(30)
    assert not thread.is_alive()
    writer.close("done", rest=batch.take())
    assert counts(tmp_path / "run.mcap")["/loop"] == total


@pytest.mark.timeout(int(6 * STALL_TIMEOUT) + 60)
@pytest.mark.parametrize("mode", [RecordMode.BACKPRESSURE, RecordMode.LOSSY])
def test_a_writer_stopped_for_good_is_given_up_after_its_stall_bound(tmp_path: Path, mode: RecordMode,
                                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    """Backpressure waits for a stopped writer (nothing lost while it is slow), but not for
    ever: after STALL_TIMEOUT s of nothing taken the hand-over raises, the writer killed, the
    file said unfinished; lossy never waits, and its close gives the writer up the same way."""
    # a writer stopped with SIGSTOP shows no life at any load: a short bound proves the same
    stall = 0.5
    monkeypatch.setattr(process, "STALL_TIMEOUT", stall)
    path = tmp_path / "run.mcap"
    writer, batch = opened(path, mode)
    t0 = time.monotonic()
    with stopped(writer), pytest.raises(RecorderError) as raised:
        for k in range(3 * PIPE_SIZE // CYCLE_BYTES):
            cycle(batch, k)
        writer.close("done", rest=batch.take())
    waited = time.monotonic() - t0
    assert "killed, the log is not finished" in str(raised.value) and "dobhil log recover" in str(raised.value)
    assert f"for {stall:g} s" in str(raised.value)
    assert waited >= stall, f"given up after {waited:.2f} s, before its bound"
    assert writer.pid not in child_processes()
    with pytest.raises(RecorderError):
        writer.close("again")   # bounded and idempotent: the same failure


def test_lossy_never_blocks_drops_are_counted_and_events_kept(tmp_path: Path) -> None:
    path = tmp_path / "run.mcap"
    writer, batch = opened(path, RecordMode.LOSSY)
    total = 2 * PIPE_SIZE // CYCLE_BYTES
    with stopped(writer):
        t0 = time.perf_counter()
        for k in range(total):
            cycle(batch, k)
            if k == total - 1000:
                batch.record(event_record(EventKind.INFO, 1_000_000_000 + k * 1_000_000, "kept"))
        elapsed = time.perf_counter() - t0
    assert elapsed < 5.0 and writer.dropped > 0
    writer.close("done", rest=batch.take())
    log = open_log(path)
    info = log.info()
    written = counts(path)["/loop"]
    assert 0 < written < total
    events = [p for _, _, p in log.iter_messages(["/events"])]
    losses = [e for e in events if e["kind"] == "loss"]
    assert sum(e["count"] for e in losses) == writer.dropped == 5 * (total - written)
    assert info.metadata["recording"]["dropped"] == str(writer.dropped)
    assert [e["reason"] for e in events if e["kind"] == "info"] == ["kept"]
    assert events[-1]["kind"] == "stop"


@pytest.mark.parametrize("mode", [RecordMode.BACKPRESSURE, RecordMode.LOSSY])
@pytest.mark.parametrize(("value", "match"), [(lambda: 0, "cannot encode a record: .*Error"),
                                              (object(), "required argument is not a float")])
def test_a_record_that_cannot_be_encoded_fails_the_recorder_in_one_line(tmp_path: Path, mode: RecordMode,
                                                                        value: object, match: str) -> None:
    """A bug, not the disk, whether the loop cannot hand the value over or the writer cannot
    encode it: RecorderError within a few hand-overs and at every later one, and the file
    ends readable with stop reason recorder_failed."""
    writer, batch = opened(tmp_path / "bad.mcap", mode)
    cycle(batch, 0)
    fb = SimpleNamespace(position=value, velocity=0.0, seq=1)
    with pytest.raises(RecorderError, match=match):
        for k in range(100_000):
            batch.cycle(k, k * 1e-3, fb, OUT, 0.0, 0.0, False)
            time.sleep(1e-5 if k % BATCH_RECORDS == 0 else 0)
    with pytest.raises(RecorderError, match=match):
        writer.close("done", rest=batch.take())
    with open_log(tmp_path / "bad.mcap") as log:
        assert log.metadata["recording"]["stop_reason"] == "recorder_failed"


def test_the_writer_ignores_sigint_and_sigterm(tmp_path: Path) -> None:
    writer = WriterProcess(tmp_path / "run.mcap", fsync=False)
    os.kill(writer.pid, signal.SIGINT)  # may arrive before the child ignores it: blocked until then
    writer.open(META, [], RecordMode.BACKPRESSURE)
    os.kill(writer.pid, signal.SIGTERM)
    batch = RunLog(writer)
    for k in range(300):
        cycle(batch, k)
    time.sleep(0.2)
    writer.close("done", rest=batch.take())
    assert open_log(tmp_path / "run.mcap").info().stop_reason == "done"


def test_a_writer_killed_is_a_recorder_error_at_the_next_write(tmp_path: Path) -> None:
    writer, batch = opened(tmp_path / "run.mcap", RecordMode.LOSSY)
    os.kill(writer.pid, signal.SIGKILL)
    with pytest.raises(RecorderError, match="writer process ended early"):
        for k in range(10_000):
            cycle(batch, k)
    with pytest.raises(RecorderError):
        writer.close("done")


def test_closed_before_open_leaves_no_file(tmp_path: Path) -> None:
    path = tmp_path / "run.mcap"
    writer = WriterProcess(path)
    writer.close()
    assert not path.exists()


def test_a_parent_gone_before_open_leaves_no_file(tmp_path: Path) -> None:
    """A run killed (``kill -9``) while it starts, before it opened its log: the writer sees
    the end of its pipe and removes the empty file its parent created, as close() does (left,
    the next ``dobhil run --log`` of the path refuses it as a recording that exists)."""
    path = tmp_path / "run.mcap"
    path.touch()
    data_r, data_w = os.pipe()
    os.close(data_w)
    try:
        assert process._serve(data_r, cast(Connection, None), str(path)).status == process.Status.DONE
    finally:
        os.close(data_r)
    assert not path.exists()


def test_bad_path_fails_at_once(tmp_path: Path) -> None:
    with pytest.raises(OSError):
        WriterProcess(tmp_path / "missing" / "run.mcap")


def test_any_record_round_trips(tmp_path: Path) -> None:
    """Whatever the records' values, what the file holds is what was packed (count)."""
    writer, batch = opened(tmp_path / "run.mcap", RecordMode.BACKPRESSURE)
    for k in range(50):
        batch.frame(RX, can.Message(arbitration_id=k, data=bytes([k] * (k % 9)), is_extended_id=False))
    writer.close("done", rest=batch.take())
    rows = [p for _, _, p in open_log(tmp_path / "run.mcap").iter_messages(["/can/rx"])]
    assert [(r["arbitration_id"], r["dlc"], r["data"]) for r in rows] == [(k, k % 9, [k] * (k % 9)) for k in range(50)]


def test_frames_before_the_log_opens_are_recorded_first(tmp_path: Path) -> None:
    """A preflight or an enable handshake talks on the tapped bus before ``begin``: those
    frames wait in memory (whatever their number) and reach the file first, in order."""
    path = tmp_path / "run.mcap"
    log = RunLog(WriterProcess(path, fsync=False))
    inner = can.Bus(interface="virtual", channel="early-test", receive_own_messages=True)
    tap = log.wrap_bus(inner)
    try:
        for k in range(300):  # several batches' worth
            tap.send(can.Message(arbitration_id=0x100 + k % 16, data=k.to_bytes(2, "little"), is_extended_id=False))
            assert tap.recv(1.0) is not None
        log.begin(metadata=META, attachments=[], lossy=True)
        tap.send(can.Message(arbitration_id=0x7FF, data=b"\xff", is_extended_id=False))
        log.end("done")
    finally:
        tap.shutdown()
        inner.shutdown()
    with open_log(path) as recorded:
        tx = [p for _, _, p in recorded.iter_messages(["/can/tx"])]
        rx = [p for _, _, p in recorded.iter_messages(["/can/rx"])]
    assert [int.from_bytes(bytes(p["data"]), "little") for p in tx[:300]] == list(range(300))
    assert tx[-1]["arbitration_id"] == 0x7FF and len(tx) == 301
    assert len(rx) == 300 and {p["channel"] for p in rx} == {"early-test"}


def test_a_frame_the_writer_cannot_encode_never_raises_into_the_bus_call(tmp_path: Path) -> None:
    """The tap sits inside the drive's send and receive: a frame the writer's encoder refuses
    is the recorder's failure, raised by a later hand-over (the loop stops recorder_failed),
    and the writer finishes the file with that stop reason."""
    writer, batch = opened(tmp_path / "bad.mcap", RecordMode.LOSSY)
    odd = can.Message(arbitration_id=0x069, data=b"\x01", is_extended_id=False)
    odd.timestamp = "noon"  # type: ignore[assignment]
    batch.frame(TX, odd)  # no exception here
    batch.frame(TX, object())  # nor here: not a message at all
    with pytest.raises(RecorderError, match="cannot encode a CAN frame: AttributeError"):
        cycle(batch, 0)
    with pytest.raises(RecorderError):
        writer.close("done", rest=batch.take())
    writer, batch = opened(tmp_path / "noon.mcap", RecordMode.LOSSY)
    batch.frame(RX, odd)  # a received frame keeps its own stamp (a sent one gets the log clock's)
    with pytest.raises(RecorderError, match="could not convert string to float: 'noon'"):
        for k in range(100_000):
            cycle(batch, k)
            time.sleep(1e-5 if k % 100 == 0 else 0)
    with pytest.raises(RecorderError):
        writer.close("done", rest=batch.take())
    for name in ("bad.mcap", "noon.mcap"):
        with open_log(tmp_path / name) as log:
            assert log.metadata["recording"]["stop_reason"] == "recorder_failed"


def test_records_reach_the_os_every_write_interval_not_only_at_fsync(tmp_path: Path) -> None:
    """A SIGKILL of run and writer loses what the writer holds in memory, its unfinished
    chunk: chunks go to the OS every ``write_interval``, whatever the fsync interval (here
    1000 s: before, the chunk waited for it). Waits (up to 30 s, a bound on failure only)
    until a copy of the file holds the records, then kills the writer: the file holds them."""
    from dobhil.recording.recover import recover
    path = tmp_path / "run.mcap"
    writer = WriterProcess(path, fsync=False, flush_interval=1000.0)
    writer.open(META, [], RecordMode.LOSSY)
    batch = RunLog(writer)
    for k in range(50):  # far below a chunk's size: only the interval ends the chunk
        cycle(batch, k)
    batch.flush()
    deadline, tries, found = time.monotonic() + 30.0, 0, 0
    while found < 50 and time.monotonic() < deadline:
        tries += 1
        copy = tmp_path / f"copy{tries}.mcap"
        copy.write_bytes(path.read_bytes())
        try:
            found = topic_counts(recover(copy, tmp_path / f"rec{tries}.mcap").output).get("/controller", 0)
        except LogFileError:   # no complete message in the file yet
            found = 0
        time.sleep(0.05)
    os.kill(writer.pid, signal.SIGKILL)
    with pytest.raises(RecorderError):
        writer.close("done")
    assert found == 50
    assert topic_counts(recover(path, tmp_path / "killed.mcap").output)["/controller"] == 50


def test_foreign_frames_are_shed_before_the_loops_own_records(tmp_path: Path) -> None:
    """A writer frozen while the bus floods (100 foreign frames per cycle, 5x what the pipe
    holds): every cycle, every sent frame and every frame of the drive's ids reaches the
    file; the foreign frames are shed (at the tap beyond FOREIGN_CAP, at the hand-over while
    the pipe is half full) and every one is counted: kept + loss counts = sent, and the
    loss counts = the drop count = the metadata."""
    from dobhil.recording.runlog import FOREIGN_CAP
    path = tmp_path / "run.mcap"
    log = RunLog(WriterProcess(path, fsync=False))
    log.begin(metadata=META, attachments=[], lossy=True, own_ids={0x069})
    own = can.Message(arbitration_id=0x069, data=bytes(8), is_extended_id=False)
    cmd = can.Message(arbitration_id=0x06E, data=bytes(4), is_extended_id=False)
    junk = [can.Message(arbitration_id=0x100 + i, data=bytes([i]) * 8, is_extended_id=False) for i in range(100)]
    cycles = 1800  # the own records: ~460 KiB, within the half of the pipe kept for them
    assert 100 * cycles * 60 > 5 * PIPE_SIZE
    with stopped(log.writer):
        for k in range(cycles):
            for msg in junk:
                log.frame(RX, msg)
            log.frame(RX, own)
            log.frame(TX, cmd)
            cycle(log, k)
            assert len(log.foreign) <= FOREIGN_CAP
    log.end("done")
    with open_log(path) as recorded:
        rx = [p["arbitration_id"] for _, _, p in recorded.iter_messages(["/can/rx"])]
        events = [p for _, _, p in recorded.iter_messages(["/events"])]
        info = recorded.info()
    assert counts(path)["/loop"] == counts(path)["/can/tx"] == rx.count(0x069) == cycles
    losses = [e["count"] for e in events if e["kind"] == "loss"]
    assert all("foreign" in e["reason"] for e in events if e["kind"] == "loss")
    assert 0 < sum(losses) == log.writer.dropped == info.dropped
    assert len(rx) - cycles + sum(losses) == 100 * cycles


def test_records_cross_the_hand_over_with_names() -> None:
    """What the loop thread builds (plain tuples, for speed) is laid out by the named record
    types: after the pickled hand-over every field reads back by name, as given."""
    from dobhil.recording.schemas import CycleRecord, EventRecord, FrameRecord, named
    log = RunLog(SimpleNamespace(opened=False))  # type: ignore[arg-type]
    log.clock_ns = lambda: 42
    log.drive, log.truth = DRIVE, lambda: (1.0, 2.0, 3.0, 4.0)
    fb = SimpleNamespace(position=0.5, velocity=-1.25, seq=7)
    msg = can.Message(arbitration_id=0x069, data=b"\x01\x02", is_extended_id=False, channel="c", timestamp=5.5)
    log.started(fb)
    log.frame(RX, msg)
    log.frame(TX, msg)
    log.cycle(3, 0.003, fb, OUT, 1e-6, 2e-5, True)
    log.truth = None
    log.cycle(4, 0.004, fb, OUT, 0.0, 0.0, False)
    (batch,), _ = unpack(encode(log.take()))
    feedback, enable, rx, tx, cycle3, cycle4 = map(named, batch)
    assert (feedback.kind, feedback.cycle, feedback.seq, feedback.drive_state) == (int(Topic.DRIVE_FEEDBACK), -1, 7, 8)
    assert type(enable) is EventRecord and (enable.event, enable.reason, enable.lost) == (EventKind.ENABLE,
                                                                                          "drive enabled", 0)
    for frame, kind in ((rx, RX), (tx, TX)):
        assert type(frame) is FrameRecord and frame.kind == kind and frame.log_time_ns == 42
        assert (frame.arbitration_id, bytes(frame.data), frame.dlc, frame.channel) == (0x069, b"\x01\x02", 2, "c")
        assert not frame.is_extended_id
    assert (rx.timestamp, tx.timestamp) == (5.5, 42 / 1e9)  # a sent frame: its send time on the log clock
    assert type(cycle3) is CycleRecord and (cycle3.cycle, cycle3.position, cycle3.velocity, cycle3.seq) == (3, 0.5,
                                                                                                          -1.25, 7)
    assert (cycle3.tau_ref, cycle3.u_sat, cycle3.period_error, cycle3.exec_time, cycle3.overrun) == (
        OUT.tau_ref, OUT.u, 1e-6, 2e-5, True)
    assert (cycle3.drive_state, cycle3.protocol_state, cycle3.protocol_error, cycle3.q, cycle3.tau_int) == (
            8, 4, 0, 1.0, 4.0)
    assert cycle4.cycle == 4 and len(cycle4) == len(CycleRecord._fields) - 4  # no truth: the fields are absent
