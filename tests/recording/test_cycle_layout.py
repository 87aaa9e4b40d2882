"""The cycle layout (dobhil/recording/cycles.py): one MCAP message per control cycle, read
back as the topics layout's messages by dobhil's reader and python-can's, and decoded from
the file's own schema by mcap's reader with mcap-protobuf-support (Foxglove's decoding)."""

from __future__ import annotations

import math
import tempfile
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import can
import pytest
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
from hypothesis import given, settings
from hypothesis import strategies as st
from mcap.reader import make_reader
from mcap.writer import Writer
from mcap_protobuf.decoder import DecoderFactory

from dobhil.cli.main import main
from dobhil.errors import LogFileError
from dobhil.recording.cycles import cycle_schema, frame_part, signal_part, unfold
from dobhil.recording.layouts import CYCLE_SCHEMA, LAYOUTS
from dobhil.recording.reader import LogFile, open_log
from dobhil.recording.schemas import CYCLE, LANE_STRIDE, EventKind, Topic, event_record
from dobhil.recording.writer import LIBRARY, Lane, LogWriter
from tests.recording.test_run_logging import logged_lockstep_run


def test_a_cycle_message_is_these_bytes() -> None:
    """Field number = the topic's number, length-delimited; a frame's log time offset a
    zigzag varint (-1 -> 1) before the frame (field 2)."""
    assert signal_part(Topic.LOOP, b"\x08\x01") == b"\x32\x02\x08\x01"          # field 6
    assert signal_part(Topic.DRIVE_FEEDBACK, b"") == b"\x1a\x00"                # field 3
    assert frame_part(Topic.CAN_TX, b"\x01", -1) == b"\x12\x05\x08\x01\x12\x01\x01"  # field 2
    assert frame_part(Topic.CAN_RX, b"", 1000) == b"\x0a\x05\x08\xd0\x0f\x12\x00"     # field 1, 2000
    data = signal_part(Topic.LOOP, b"\x08\x01") + frame_part(Topic.CAN_TX, b"\x01", -1)
    assert list(unfold(data, 100)) == [(Topic.LOOP, 100, b"\x08\x01"), (Topic.CAN_TX, 99, b"\x01")]
    # another writer's CycleFrame: the frame first, a field dobhil does not know, a long offset
    other = b"\x12\x01\x05" + b"\x18\x07" + b"\x08\xd0\x0f"
    assert list(unfold(b"\x0a" + bytes([len(other)]) + other, 0)) == [(Topic.CAN_RX, 1000, b"\x05")]


@pytest.mark.parametrize(("data", "what"), [
    (b"\x08\x01", "field 1 \\(wire type 0\\)"),        # rx as a varint
    (b"\x42\x00", "field 8"),                         # /events is never folded
    (b"\x0a\x02\x08\x01", "holds no frame"),          # an rx entry with an offset only
    (b"\x32\x05\x08", "runs past the end"),           # cut short
])
def test_what_is_not_a_cycle_message_is_refused(data: bytes, what: str) -> None:
    with pytest.raises(ValueError, match=what):
        list(unfold(data, 0))


def _cycle_class() -> Any:
    pool = descriptor_pool.DescriptorPool()
    for file in descriptor_pb2.FileDescriptorSet.FromString(cycle_schema()).file:
        pool.Add(file)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(CYCLE_SCHEMA))


@given(offsets=st.lists(st.integers(-2 ** 62, 2 ** 62), max_size=4),
       loop=st.just(b"") | st.just(b"\x09" + (7).to_bytes(8, "little")))   # Loop.cycle: sfixed64
@settings(max_examples=50, deadline=None)
def test_the_protobuf_library_reads_a_cycle_message(offsets: list[int], loop: bytes) -> None:
    """The schema is a FileDescriptorSet the protobuf library builds a class from; a message
    it parses holds the offsets and sub-messages written (frame data in CanFrame field 10)."""
    frames = [b"\x52\x01" + bytes([i]) for i in range(len(offsets))]   # CanFrame.data (field 10)
    data = signal_part(Topic.LOOP, loop) + b"".join(
        frame_part(Topic.CAN_RX if i % 2 else Topic.CAN_TX, f, o) for i, (f, o) in enumerate(zip(frames, offsets)))
    proto = _cycle_class().FromString(data)
    entries = [(e.log_time_offset_ns, e.frame.data) for e in proto.rx] + \
              [(e.log_time_offset_ns, e.frame.data) for e in proto.tx]
    assert sorted(entries) == sorted((o, bytes([i])) for i, o in enumerate(offsets))
    assert proto.loop.cycle == (7 if loop else 0)


# -- the writer: the same records in either layout read the same --------------------------

_LANES = (Lane(""), Lane("/axis/b"))


def _frame(topic: Topic, lane: int, t: int, k: int) -> tuple[Any, ...]:
    return (int(topic) + LANE_STRIDE * lane, t, 0x60 + k % 32, False, False, False, k % 5 == 0, False, False,
            8, bytes((k + i) % 256 for i in range(8)), t / 1e9, "" if k % 3 else "can0")


def _cycle(lane: int, t: int, k: int, truth: bool) -> tuple[Any, ...]:
    x = math.sin(k / 7)
    record = (CYCLE + LANE_STRIDE * lane, t, k, 1e-4 * x, 0.1 * x, k, 0.2, x / 7, 0.01 * x, 0.02, x / 3, x / 3,
              1e-6 * x, 3e-5, k % 4 == 0, math.nan if k % 2 else 1e-4, 1, 8, k % 3)
    return record + ((1e-4 * x, 0.1 * x, 0.03, 0.19) if truth else ())


_STEP = st.tuples(st.sampled_from(("cycle", "short", "rx", "tx", "event", "flush")), st.integers(0, 1),
                  st.integers(-3_000_000, 3_000_000))


def _records(steps: Sequence[tuple[str, int, int]]) -> list[tuple[Any, ...] | None]:
    """Records of ``steps`` (None: the writer flushes there), log times moving by each step's
    amount (backwards too: a frame stamped before the cycle it follows)."""
    t, out = 10 ** 12, []
    for k, (what, lane, dt) in enumerate(steps):
        t += dt
        if what in ("cycle", "short"):
            out.append(_cycle(lane, t, k, what == "cycle"))
        elif what in ("rx", "tx"):
            out.append(_frame(Topic.CAN_RX if what == "rx" else Topic.CAN_TX, lane, t, k))
        elif what == "event":
            out.append(event_record(EventKind.INFO, t, f"note {k}"))
        else:
            out.append(None)
    return out


def _written(path: Path, records: Sequence[tuple[Any, ...] | None], layout: str) -> LogFile:
    log = LogWriter(open(path, "wb"), metadata={}, fsync=False, lanes=_LANES, layout=layout)
    for record in records:
        if record is None:
            log.flush(sync=False)
        else:
            log.write([record])
    log.finish(None)   # a stop event would be stamped by the clock when no record came
    return LogFile(path)


@given(steps=st.lists(_STEP, max_size=40))
@settings(max_examples=60, deadline=None)   # 0.5 s; a frame of another lane folded, or a zigzag sign
# wrong, failed it within these examples (each mutation tried when written)
def test_any_records_read_the_same_in_both_layouts(steps: list[tuple[str, int, int]]) -> None:
    """Cycles of two lanes (with and without truth), frames of either lane before, between
    and after them, events and chunk ends anywhere: the cycle layout's reader gives every
    message of the topics layout, in its order, with its log time and values, and counts
    each topic's messages alike."""
    records = _records(steps)
    with tempfile.TemporaryDirectory() as tmp:
        logs = {layout: _written(Path(tmp) / f"{layout}.mcap", records, layout) for layout in LAYOUTS}
        topics, cycle = logs["topics"], logs["cycle"]
        assert list(cycle.iter_messages()) == list(topics.iter_messages())
        assert set(cycle.topics()) == set(topics.topics())
        counts = cycle.message_counts()
        assert {t: counts.get(t, 0) for t in topics.topics()} == topics.message_counts()
        some = [t for t in topics.topics() if t.endswith(("/loop", "/can/rx"))]
        assert list(cycle.iter_messages(some)) == list(topics.iter_messages(some))
        assert cycle.layout == ("cycle" if any(r is not None and r[0] % LANE_STRIDE == CYCLE for r in records)
                                else "topics")


def test_the_cycle_layout_is_protobufs() -> None:
    with tempfile.TemporaryFile() as f:
        with pytest.raises(ValueError, match="protobuf"):
            LogWriter(f, metadata={}, fsync=False, encoding="json", layout="cycle")
        with pytest.raises(ValueError, match="topics, cycle"):
            LogWriter(f, metadata={}, fsync=False, layout="packed")


def test_a_damaged_cycle_message_is_one_line(tmp_path: Path) -> None:
    """A /cycle message that is not one fails the read naming the topic and the time."""
    path = tmp_path / "bad.mcap"
    with open(path, "wb") as f:
        writer = Writer(f)
        writer.start("", LIBRARY)
        schema = writer.register_schema(CYCLE_SCHEMA, "protobuf", cycle_schema())
        channel = writer.register_channel("/cycle", "protobuf", schema)
        writer.add_message(channel, log_time=5, data=b"\x42\x00", publish_time=5)
        writer.finish()
    log = LogFile(path)
    assert "/loop" in log.topics() and log.layout == "cycle"
    with pytest.raises(LogFileError, match=r"a /cycle message at log time 5 is not a dobhil.Cycle message"):
        list(log.iter_messages(["/loop"]))


# -- a recorded run in both layouts -------------------------------------------------------


@pytest.fixture(scope="module")
def runs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """The same lockstep demo run recorded in each layout, long enough for a cycle log of
    several chunks (256 KiB each before compression: about 580 cycles)."""
    out = {}
    for layout in LAYOUTS:
        out[layout] = tmp_path_factory.mktemp(layout) / "run.mcap"
        logged_lockstep_run(out[layout], duration=1.5, layout=layout)
    return out


def _relative(messages: list[tuple[str, int, dict[str, Any]]]) -> list[tuple[str, int, dict[str, Any]]]:
    """Messages with times from the first (a lockstep log's clock starts at the wall time),
    without what differs between two runs of it: the CPU time of a cycle, the bus' name."""
    t0 = messages[0][1]
    out = []
    for topic, t, payload in messages:
        p = {k: v for k, v in payload.items() if k not in ("exec_time", "channel")}
        if p.get("timestamp"):
            p["timestamp"] = round(p["timestamp"] - t0 / 1e9, 6)
        out.append((topic, t - t0, p))
    return out


def test_a_run_reads_the_same_in_both_layouts(runs: dict[str, Path]) -> None:
    topics, cycle = (open_log(runs[layout]) for layout in LAYOUTS)
    assert cycle.layout == "cycle" and "/cycle" in {c.topic for c in cycle.channels()}
    assert "/cycle" not in cycle.topics()
    assert _relative(list(cycle.iter_messages())) == _relative(list(topics.iter_messages()))
    assert cycle.message_counts() == topics.message_counts()


def test_python_can_reads_the_same_frames_in_both_layouts(runs: dict[str, Path]) -> None:
    def frames(path: Path) -> list[tuple[int, bytes, bool, float]]:
        read = list(can.LogReader(path))
        return [(m.arbitration_id, bytes(m.data), m.is_rx, round(m.timestamp - read[0].timestamp, 6)) for m in read]
    assert frames(runs["cycle"]) == frames(runs["topics"])
    assert len(frames(runs["cycle"])) > 2500   # 1.5 s of 1 kHz, both ways


def test_mcap_and_its_protobuf_decoder_read_a_cycle_log(runs: dict[str, Path]) -> None:
    """mcap's reader with mcap-protobuf-support's DecoderFactory (no dobhil in the decode
    path) decodes each /cycle message to the values dobhil reads as its topics."""
    with open(runs["cycle"], "rb") as f:
        decoded = [(message.log_time, proto)
                   for _, channel, message, proto in make_reader(f, decoder_factories=[DecoderFactory()])
                   .iter_decoded_messages(topics=["/cycle"], log_time_order=False)]
    log = open_log(runs["cycle"])
    loops = list(log.iter_messages(["/loop"]))
    controllers = list(log.iter_messages(["/controller"]))
    assert len(decoded) == len(loops) == len(controllers) > 1400
    for (t, proto), (_, t_loop, loop), (_, _, controller) in zip(decoded, loops, controllers):
        assert t == t_loop
        assert (proto.loop.cycle, proto.loop.overrun) == (loop["cycle"], loop["overrun"])
        assert proto.controller.u_sat == controller["u_sat"]
    rx = [(t + e.log_time_offset_ns, tuple(e.frame.data)) for t, proto in decoded for e in proto.rx]
    ours = iter([(t, tuple(p["data"])) for _, t, p in log.iter_messages(["/can/rx"])])
    assert len(rx) >= len(decoded) - 2 and all(frame in ours for frame in rx)   # in dobhil's order


def test_replay_verifies_and_log_info_says_the_layout(runs: dict[str, Path], capsys: pytest.CaptureFixture[str]
                                                      ) -> None:
    assert main(["replay", str(runs["cycle"]), "--verify"]) == 0
    capsys.readouterr()
    assert main(["log", "info", str(runs["cycle"])]) == 0
    out = capsys.readouterr().out
    assert "layout:     cycle" in out and "dobhil.Cycle (protobuf)" in out
    held = out.split("in cycle messages:\n")[1].split("metadata")[0].split()
    counts, own = open_log(runs["topics"]).message_counts(), open_log(runs["cycle"]).channels()
    for topic, count in zip(held[::2], map(int, held[1::2])):   # with the messages outside cycles: all
        assert count + sum(c.message_count for c in own if c.topic == topic) == counts[topic]
    assert {"/loop", "/controller", "/can/rx", "/can/tx"} <= set(held[::2])


def test_an_unknown_layout_is_one_line(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exit_:
        main(["run", "configs/demo.yaml", "--emulate", "--log", "x.mcap", "--log-layout", "packed"])
    assert exit_.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) <= 2 and "invalid choice: 'packed'" in err[-1] and "topics" in err[-1]


def test_a_cut_cycle_log_is_recovered_read_and_replayed(runs: dict[str, Path], tmp_path: Path) -> None:
    """A cycle log cut inside its data (a writer killed): ``recover`` keeps the intact
    chunks' cycle messages, read back as their topics, replayed bit for bit; the topics'
    counts, the writer's summary lost with the end, are recover's count of what the copied
    cycle messages hold, frames included: exactly what a reader gets."""
    from dobhil.recording.recover import recover
    data = runs["cycle"].read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[:len(data) * 2 // 3])
    recover(cut, tmp_path / "saved.mcap")
    saved = open_log(tmp_path / "saved.mcap")
    cycles = next(c.message_count for c in saved.channels() if c.topic == "/cycle")
    assert 100 < cycles < 1400   # the intact chunks: some, not all
    assert saved.message_counts()["/loop"] == cycles == len(list(saved.iter_messages(["/loop"])))
    read: dict[str, int] = {}
    for topic, _, _ in saved.iter_payloads():
        read[topic] = read.get(topic, 0) + 1
    assert saved.message_counts() == read and read["/can/rx"] > cycles   # the frames counted too
    assert main(["replay", str(tmp_path / "saved.mcap"), "--verify"]) == 0
    again = tmp_path / "again.mcap"   # a recovered file recovered: counted anew, not added up
    recover(saved.path, again)
    assert open_log(again).message_counts() == read


@pytest.mark.parametrize(("config", "cycles"), [("configs/demo.yaml", ["/cycle"]),
                                                ("configs/two-axis-demo.yaml", ["/axis/left/cycle",
                                                                                "/axis/right/cycle"])])
def test_dobhil_run_writes_the_layout_it_is_asked_for(config: str, cycles: list[str], tmp_path: Path,
                                                      capsys: pytest.CaptureFixture[str]) -> None:
    """``dobhil run --log-layout cycle``, one axis or several (a cycle channel per axis; the
    bus' frames, in a lane without cycles, on their own topics): replayed bit for bit."""
    path = tmp_path / "run.mcap"
    assert main(["run", config, "--emulate", "--lockstep", "--duration", "0.2", "--log", str(path),
                 "--log-layout", "cycle"]) == 0
    log = open_log(path)
    assert sorted(c.topic for c in log.channels() if c.schema_name == "dobhil.Cycle") == sorted(cycles)
    assert all(c.message_count == 200 for c in log.channels() if c.schema_name == "dobhil.Cycle")
    capsys.readouterr()
    assert main(["replay", str(path), "--verify"]) == 0
