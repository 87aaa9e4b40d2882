"""Recorder: round trip of every topic through the plain mcap reader, modes, failures."""

from __future__ import annotations

import json
import threading
from collections import Counter
from pathlib import Path
from typing import Any

import can
import jsonschema
import pytest
from mcap.reader import make_reader

from dobhil.errors import LogFileError
from dobhil.recording.recorder import CanRecordListener, Recorder, RecordMode, record_can_bus
from dobhil.recording.schemas import TOPIC_SPECS, Direction, EventKind, FieldKind, Topic, TopicSpec

_SAMPLE = {
    FieldKind.NUMBER: 0.25,
    FieldKind.INTEGER: 7,
    FieldKind.BOOLEAN: True,
    FieldKind.STRING: "x",
    FieldKind.BYTES: [1, 2, 255],
}


def sample(spec: TopicSpec, i: int = 0) -> dict[str, Any]:
    """A payload valid for ``spec`` (choices respected), varying with ``i``."""
    out: dict[str, Any] = {}
    for f in spec.fields:
        value = f.choices[i % len(f.choices)] if f.choices else _SAMPLE[f.kind]
        out[f.name] = value + i if f.kind == FieldKind.INTEGER else value
    return out


def read_all(path: Path) -> list[tuple[str, int, dict[str, Any], dict[str, Any]]]:
    """(topic, log_time, payload, schema) of every message, with the plain mcap reader."""
    with open(path, "rb") as f:
        return [
            (c.topic, m.log_time, json.loads(m.data), json.loads(s.data))
            for s, c, m in make_reader(f).iter_messages()
        ]


def recorder_threads() -> list[str]:
    return [t.name for t in threading.enumerate() if t.name.startswith("dobhil-recorder")]


META = {"config": {"loop.rate_hz": "1000"}, "versions": {"dobhil": "0.1.0"}, "run": {"start_time": "0"}}


def test_round_trip_every_topic(tmp_path: Path) -> None:
    path = tmp_path / "run.mcap"
    with Recorder(path, metadata=META, attachments=[("config.yaml", "application/yaml", b"a: 1\n")],
                  mode=RecordMode.BACKPRESSURE) as rec:
        for i, topic in enumerate(Topic):
            rec.write(TOPIC_SPECS[topic].name, 1000 + i, sample(TOPIC_SPECS[topic], i))
    messages = read_all(path)
    assert [m[0] for m in messages] == [TOPIC_SPECS[t].name for t in Topic]
    for (topic, log_time, payload, schema), t in zip(messages, Topic):
        assert payload == sample(TOPIC_SPECS[t], t - 1)
        assert log_time == 1000 + t - 1
        jsonschema.validate(payload, schema)
    assert recorder_threads() == []


def test_file_has_summary_metadata_and_attachment(tmp_path: Path) -> None:
    path = tmp_path / "run.mcap"
    with Recorder(path, metadata=META, attachments=[("config.yaml", "application/yaml", b"a: 1\n")],
                  mode=RecordMode.LOSSY) as rec:
        rec.write(Topic.DRIVE_COMMAND, 5, {"torque": 0.1})
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None and summary.statistics is not None
        assert summary.statistics.message_count == 1
        assert {s.encoding for s in summary.schemas.values()} == {"jsonschema"}
        assert {c.message_encoding for c in summary.channels.values()} == {"json"}
        metadata = {m.name: m.metadata for m in reader.iter_metadata()}
        attachments = [(a.name, a.data) for a in reader.iter_attachments()]
    assert metadata["config"] == {"loop.rate_hz": "1000"}
    assert metadata["recording"]["dropped"] == "0"
    assert attachments == [("config.yaml", b"a: 1\n")]


def test_close_writes_stop_event_last(tmp_path: Path) -> None:
    path = tmp_path / "run.mcap"
    rec = Recorder(path, metadata={}, mode=RecordMode.BACKPRESSURE)
    rec.write("/drive/command", 10, {"torque": 0.0})
    rec.event(EventKind.FAULT, "axis error", "0x40")
    rec.close("operator stop")
    rec.close("again")  # idempotent
    events = [(m[2]["kind"], m[2]["reason"], m[1]) for m in read_all(path) if m[0] == "/events"]
    assert events == [("fault", "axis error", 10), ("stop", "operator stop", 10)]
    with pytest.raises(LogFileError, match="closed"):
        rec.write("/drive/command", 11, {"torque": 0.0})


def test_write_frame_both_directions(tmp_path: Path) -> None:
    path = tmp_path / "run.mcap"
    msg = can.Message(arbitration_id=0x1ABCDEF, is_extended_id=True, data=b"\x01\xff", timestamp=12.5, channel="vcan0")
    with Recorder(path, metadata={}, mode=RecordMode.BACKPRESSURE) as rec:
        rec.write_frame(msg, Direction.RX, 1)
        rec.write_frame(msg, Direction.TX, 2)
    rx, tx = read_all(path)
    assert (rx[0], tx[0]) == ("/can/rx", "/can/tx")
    assert rx[2]["data"] == [1, 255] and rx[2]["data_hex"] == "01ff"
    assert (rx[2]["direction"], tx[2]["direction"]) == ("rx", "tx")
    assert rx[2]["arbitration_id"] == 0x1ABCDEF and rx[2]["is_extended_id"] is True
    assert rx[2]["timestamp"] == 12.5 and rx[2]["channel"] == "vcan0"


class GatedRecorder(Recorder):
    """A recorder whose writer thread waits for ``gate`` before each message."""

    def __init__(self, *args: Any, gate: threading.Event, **kwargs: Any) -> None:
        self.gate = gate
        super().__init__(*args, **kwargs)

    def _write_message(self, topic: Topic, log_time_ns: int, data: bytes) -> None:
        self.gate.wait()
        super()._write_message(topic, log_time_ns, data)


def test_lossy_drops_and_counts_when_the_writer_is_slow(tmp_path: Path) -> None:
    path = tmp_path / "run.mcap"
    gate = threading.Event()
    rec = GatedRecorder(path, metadata={}, mode=RecordMode.LOSSY, queue_size=4, gate=gate)
    try:
        accepted = [rec.write("/loop", i, sample(TOPIC_SPECS[Topic.LOOP], i)) for i in range(100)]
    finally:
        gate.set()
        rec.close("done")
    assert rec.dropped == accepted.count(False) >= 95
    messages = read_all(path)
    loops = [m for m in messages if m[0] == "/loop"]
    losses = [m[2] for m in messages if m[0] == "/events" and m[2]["kind"] == "loss"]
    assert len(loops) == accepted.count(True) == 100 - rec.dropped
    assert sum(e["count"] for e in losses) == rec.dropped
    with open(path, "rb") as f:
        recording = {m.name: m.metadata for m in make_reader(f).iter_metadata()}["recording"]
    assert recording["dropped"] == str(rec.dropped)


def test_events_are_never_dropped(tmp_path: Path) -> None:
    gate = threading.Event()
    rec = GatedRecorder(tmp_path / "run.mcap", metadata={}, mode=RecordMode.LOSSY, queue_size=1, gate=gate)
    try:
        for i in range(10):
            rec.event(EventKind.INFO, f"note {i}", log_time_ns=i)
    finally:
        gate.set()
        rec.close()
    assert rec.dropped == 0
    assert len(read_all(tmp_path / "run.mcap")) == 10


def test_backpressure_loses_nothing_over_200k(tmp_path: Path) -> None:
    path = tmp_path / "run.mcap"
    n = 200_000
    with Recorder(path, metadata={}, mode=RecordMode.BACKPRESSURE, queue_size=512) as rec:
        for i in range(n):
            assert rec.write("/drive/command", i, {"torque": i})
    assert rec.dropped == 0 and rec.written == n
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None and summary.statistics is not None
        assert summary.statistics.message_count == n
        assert summary.statistics.chunk_count > 1
        times = [m.log_time for _, _, m in reader.iter_messages()]
    assert times == list(range(n))


class FailingRecorder(Recorder):
    def _write_message(self, topic: Topic, log_time_ns: int, data: bytes) -> None:
        raise OSError(28, "No space left on device")


def test_writer_failure_reaches_the_caller(tmp_path: Path) -> None:
    rec = FailingRecorder(tmp_path / "run.mcap", metadata={}, mode=RecordMode.BACKPRESSURE)
    rec.write("/drive/command", 1, {"torque": 0.0})
    with pytest.raises(LogFileError, match="recorder failed: .*No space left"):
        rec.close()
    with pytest.raises(LogFileError, match="recorder failed"):
        rec.write("/drive/command", 2, {"torque": 0.0})
    assert recorder_threads() == []


def test_unknown_topic_and_bad_path(tmp_path: Path) -> None:
    with Recorder(tmp_path / "run.mcap", metadata={}, mode=RecordMode.LOSSY) as rec:
        with pytest.raises(LogFileError, match="unknown topic"):
            rec.write("/nope", 1, {})
    with pytest.raises(LogFileError, match="cannot create"):
        Recorder(tmp_path / "missing" / "run.mcap", metadata={}, mode=RecordMode.LOSSY)


def test_listener_records_frames_from_a_notifier(tmp_path: Path) -> None:
    path = tmp_path / "run.mcap"
    with can.Bus(interface="virtual", channel="rec-test") as bus, \
            can.Bus(interface="virtual", channel="rec-test") as peer, \
            Recorder(path, metadata={}, mode=RecordMode.LOSSY) as rec:
        received = threading.Event()

        class Done(can.Listener):
            def on_message_received(self, msg: can.Message) -> None:
                received.set()

        notifier = record_can_bus(rec, bus)
        notifier.add_listener(Done())
        try:
            peer.send(can.Message(arbitration_id=0x7E0, data=b"\x02", is_extended_id=False))
            assert received.wait(5.0)
        finally:
            notifier.stop()
    assert isinstance(notifier.listeners[0], CanRecordListener)
    frames = [m for m in read_all(path) if m[0] == "/can/rx"]
    assert [(f[2]["arbitration_id"], f[2]["data"]) for f in frames] == [(0x7E0, [2])]
    assert Counter(m[0] for m in read_all(path)) == {"/can/rx": 1}
