"""A several-axis log: topics per axis and per bus, each axis' records those it has run
alone, ``replay --verify`` bit for bit over every axis (and a changed value found on its
axis), ``report`` per axis with the shared timing and each bus' load, export and info; a
single-axis log of any version read as one axis."""

from __future__ import annotations

import json
import math
import re
from collections import Counter
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import can
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from mcap.reader import make_reader
from mcap.writer import Writer

from dobhil.cli.main import main
from dobhil.config.axes import load_axes
from dobhil.drives.odrive import codec
from dobhil.errors import RecorderError
from dobhil.recording.axes import AxisLog, axis_log, axis_logs, axis_names, layout
from dobhil.recording.axeslog import AxesLog, AxisDrive
from dobhil.recording.packed import unpacked
from dobhil.recording.process import WriterProcess
from dobhil.recording.reader import open_log
from dobhil.recording.relayout import relayout
from dobhil.recording.runlog import RunLog
from dobhil.recording.schemas import CYCLE, SPECS_BY_NAME, EventKind, Topic, lane_kind
from dobhil.recording.writer import LogWriter
from dobhil.replay import replay, replay_axes
from dobhil.runtime.session import RunSession
from tests.recording.axes_harness import BUSES, record_axes, write_config
from tests.recording.test_old_logs import as_old_log
from tests.recording.helpers import decode_message, encode_message
from tests.recording.test_run_logging import logged_lockstep_run

AXES = ("left", "right", "wrist")
#: the topics of one axis, as a single-axis log has them (its bus' frames apart)
AXIS_TOPICS = ("/drive/feedback", "/drive/command", "/controller", "/loop", "/emulator/truth", "/events")


@pytest.fixture(scope="module")
def recorded(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, dict[str, Any]]:
    directory = tmp_path_factory.mktemp("axes")
    config = write_config(directory)
    path = directory / "run.mcap"
    results = record_axes(path, config)
    return path, config, results


def _payloads(path: Path, topic: str) -> list[dict[str, Any]]:
    return [p for _, _, p in open_log(path).iter_messages([topic])]


def test_topics_per_axis_and_bus_with_the_single_axis_schemas(recorded: tuple[Path, Path, Any],
                                                              tmp_path: Path) -> None:
    """The file's own channels in the topics layout (the recording converted to it), and the
    topics dobhil's reader gives of the recording in its own layout, are the same set."""
    path = recorded[0]
    topics_copy = tmp_path / "topics.mcap"
    if open_log(path).layout == "topics":
        topics_copy.write_bytes(path.read_bytes())
    else:
        relayout(path, "topics", topics_copy)
    with open(topics_copy, "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    schemas = {c.topic: summary.schemas[c.schema_id].name for c in summary.channels.values()}
    expected = {f"/axis/{a}{t}" for a in AXES for t in AXIS_TOPICS}
    expected |= {f"/bus/{b}/can/{d}" for b in ("can0", "can1") for d in ("rx", "tx")} | {"/events"}
    assert set(schemas) == expected
    assert set(open_log(path).message_counts()) == expected
    for topic, schema in schemas.items():   # every topic keeps the schema of its single-axis name
        assert schema == SPECS_BY_NAME[topic[topic.index("/", 6):] if topic != "/events" else topic].schema_name
    log = open_log(path)
    lay = layout(log)
    assert lay.names == AXES and dict(lay.bus_of) == dict(BUSES)
    assert dict(lay.buses) == {"can0": "/bus/can0", "can1": "/bus/can1"}
    assert json.loads(log.metadata["bus/can0"]["axes"]) == ["left", "right"]
    assert json.loads(log.metadata["axis/right/drive"]["node_id"]) == 2
    assert json.loads(log.metadata["axis/wrist/drive"]["protocol"]) == "cia402"
    right = axis_log(log, "right")
    assert right.config.plant.inertia == 0.3 and right.config.drive.node_id == 2
    assert dict(right.metadata["drive"]) == dict(log.metadata["axis/right/drive"])
    assert right.metadata["bus"] is log.metadata["bus/can0"] and right.bus == "can0"


def test_each_axis_records_what_it_records_run_alone(recorded: tuple[Path, Path, Any], tmp_path: Path) -> None:
    """The same messages, value for value, as the axis' own single-axis log of the same run."""
    path, config, results = recorded
    axes = load_axes(config)
    for axis in axes.axes:
        alone = tmp_path / f"{axis.name}.mcap"
        log = RunLog(WriterProcess(alone, fsync=False))
        with RunSession(axis.config, emulate=True, lockstep=True, sink=log, bus_wrapper=log.wrap_bus) as session:
            from dobhil.cli.recording import record_run
            result = record_run(session, log)
        assert result.cycles == results[axis.name].cycles == 300
        for topic in ("/controller", "/drive/feedback", "/drive/command", "/emulator/truth"):
            assert _payloads(path, f"/axis/{axis.name}{topic}") == _payloads(alone, topic), (axis.name, topic)


def test_replay_verifies_every_axis_bit_for_bit(recorded: tuple[Path, Path, Any],
                                                capsys: pytest.CaptureFixture[str]) -> None:
    path = recorded[0]
    results = replay_axes(path)
    assert [r.recording.axis for r in results] == list(AXES)
    assert all(r.first_mismatch() is None and r.recording.cycles == 300 for r in results)
    assert main(["replay", str(path), "--verify"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert [line.split(":")[0].strip() for line in lines[1:]] == [f"axis {a}" for a in AXES]
    assert all("300 cycles, identical" in line and "bit for bit" in line for line in lines[1:])


def _rewrite(src: Path, dst: Path, change: Any) -> None:
    """``src`` copied to ``dst``, each message's payload passed through ``change(topic, payload)``;
    a cycle-layout log is changed in the topics layout (``dobhil log convert``) and converted
    back, so the copy is in its source's layout."""
    layout = open_log(src).layout
    if layout != "topics":
        topics, changed = dst.with_suffix(".src-topics.mcap"), dst.with_suffix(".topics.mcap")
        relayout(src, "topics", topics)
        _rewrite(topics, changed, change)
        relayout(changed, layout, dst)
        return
    with open(src, "rb") as f_in, open(dst, "wb") as f_out:
        reader = make_reader(f_in)
        summary, header = reader.get_summary(), reader.get_header()
        assert summary is not None
        writer = Writer(f_out)
        writer.start(profile=header.profile, library=header.library)
        schemas = {sid: writer.register_schema(s.name, s.encoding, s.data) for sid, s in summary.schemas.items()}
        channels = {cid: writer.register_channel(c.topic, c.message_encoding, schemas[c.schema_id])
                    for cid, c in summary.channels.items()}
        for record in reader.iter_metadata():
            writer.add_metadata(record.name, record.metadata)
        for schema, channel, message in reader.iter_messages(log_time_order=False):
            p = change(channel.topic, decode_message(schema, channel, message.data))
            writer.add_message(channels[channel.id], message.log_time, encode_message(schema, channel, p),
                               message.publish_time)
        writer.finish()


def test_one_changed_recorded_value_fails_on_its_axis(recorded: tuple[Path, Path, Any], tmp_path: Path,
                                                      capsys: pytest.CaptureFixture[str]) -> None:
    """u_sat of one cycle of axis right one ulp off: that axis, that cycle, named in one line."""
    bad = tmp_path / "altered.mcap"

    def change(topic: str, p: dict[str, Any]) -> dict[str, Any]:
        if topic == "/axis/right/controller" and p["cycle"] == 123:
            p["u_sat"] = math.nextafter(p["u_sat"], math.inf)
        return p
    _rewrite(recorded[0], bad, change)
    capsys.readouterr()
    assert main(["replay", str(bad), "--verify"]) == 1
    out, err = capsys.readouterr()
    assert err.startswith("dobhil replay: verification failed on axis right: replay differs at cycle 123 (t = ")
    assert ": u_sat recorded" in err and len(err.strip().splitlines()) == 1
    lines = {line.split(":")[0].strip(): line for line in out.splitlines()[1:]}
    assert "identical" in lines["axis left"] and "identical" in lines["axis wrist"]
    assert "differs at cycle 123" in lines["axis right"]


def test_a_changed_frame_on_a_shared_bus_is_found_on_its_axis_only(recorded: tuple[Path, Path, Any],
                                                                   tmp_path: Path) -> None:
    """Axes left and right share can0: a velocity of node 2's encoder frame changed moves
    right's replay from that cycle on, not left's (each drive class keeps its own frames)."""
    bad = tmp_path / "frame.mcap"
    encoder = codec.arbitration_id(2, codec.CmdId.GET_ENCODER_ESTIMATES)
    seen = [0]

    def change(topic: str, p: dict[str, Any]) -> dict[str, Any]:
        if topic == "/bus/can0/can/rx" and p["arbitration_id"] == encoder:
            seen[0] += 1
            if seen[0] == 150:
                import struct
                pos, vel = struct.unpack("<ff", bytes(p["data"]))
                p["data"] = list(struct.pack("<ff", pos, vel + 1e-3))
        return p
    _rewrite(recorded[0], bad, change)
    results = {r.recording.axis: r.first_mismatch() for r in replay_axes(bad)}
    assert results["left"] is None and results["wrist"] is None
    assert results["right"] is not None and 140 <= results["right"].cycle <= 150


def test_report_per_axis_with_shared_timing_and_bus_load(recorded: tuple[Path, Path, Any], tmp_path: Path,
                                                         capsys: pytest.CaptureFixture[str]) -> None:
    path = recorded[0]
    earlier = tmp_path / "r"   # a one-axis report there before: its figures would read as this log's
    earlier.mkdir()
    for name in ("force.png", "position.png", "summary.json"):
        (earlier / name).write_text("{}")
    assert main(["report", str(path), "--out", str(tmp_path / "r")]) == 0
    out, err = capsys.readouterr()
    assert "(removed 2 figures of the report it held before)" in out
    # every axis' messages counted, to the total (the bus' frames once per axis on it)
    assert re.fullmatch(r"report: (\d+)/\1 messages \(100 %\), .*", err.splitlines()[-1])
    assert sorted(p.name for p in earlier.iterdir()) == sorted([*AXES, "summary.json", "summary.txt"])
    summary = json.loads((earlier / "summary.json").read_text())
    assert list(summary["axes"]) == list(AXES)
    assert all(s["cycles"] == 300 and s["stop"] == "done" for s in summary["axes"].values())
    assert summary["loop_timing"]["cycles"] == 300 and summary["loop_timing"]["overruns"] == 0
    buses = summary["buses"]
    assert {b: v["axes"] for b, v in buses.items()} == {"can0": ["left", "right"], "can1": ["wrist"]}
    for bus in buses:   # the bus' frames from its first axis' first cycle to its last (excluded)
        cycles = [t for _, t, _ in open_log(path).iter_messages([f"/axis/{buses[bus]['axes'][0]}/controller"])]
        counts = Counter(topic for topic, t, _ in open_log(path).iter_messages([f"/bus/{bus}/can/rx",
                                                                                 f"/bus/{bus}/can/tx"])
                         if cycles[0] <= t < cycles[-1])
        assert buses[bus]["rx_frames"] == counts[f"/bus/{bus}/can/rx"] > 0
        assert buses[bus]["tx_frames"] == counts[f"/bus/{bus}/can/tx"] > 0
        assert 0 < buses[bus]["bus_load"] < 1
    assert summary["axes"]["right"]["bus"]["name"] == "can0"
    for axis in AXES:
        assert sorted(p.name for p in (tmp_path / "r" / axis).iterdir()) == [
            "commands.png", "force.png", "loop_timing.png", "position.png", "tracking_error.png"]
    text = (tmp_path / "r" / "summary.txt").read_text()
    assert "axis wrist:" in text and "bus can0 (axes left, right)" in text and "loop (all axes, 300 cycles)" in text


def test_export_and_info_read_every_bus(recorded: tuple[Path, Path, Any], tmp_path: Path,
                                        capsys: pytest.CaptureFixture[str]) -> None:
    path = recorded[0]
    frames = sum(c.message_count for c in open_log(path).channels() if "/can/" in c.topic)
    assert main(["log", "export", str(path), "--can", "--format", "candump", "-o", str(tmp_path / "f.log")]) == 0
    assert f"wrote {frames} CAN frames" in capsys.readouterr().out
    assert sum(1 for _ in can.LogReader(path)) == frames
    # a sent frame (recorded with no channel) goes on its bus' channel, not the writer's vcan0
    log = open_log(path)
    sent = Counter(m.channel for m in can.LogReader(tmp_path / "f.log") if not m.is_rx)
    assert sent == {log.metadata[f"bus/{b}"]["channel"]: c.message_count for b in ("can0", "can1")
                    for c in log.channels() if c.topic == f"/bus/{b}/can/tx"}
    # and so does python-can's reader of the log itself, indexed and (a copy cut short, no
    # summary) front to back: each sent frame on the channel of the bus it went on
    assert Counter(m.channel for m in can.LogReader(path) if not m.is_rx) == sent
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(path.read_bytes()[:path.stat().st_size // 2])
    front: list[can.Message] = []
    with pytest.raises(ValueError, match="truncated"):
        front.extend(can.LogReader(cut))
    assert any(not m.is_rx for m in front) and {m.channel for m in front if not m.is_rx} <= set(sent)
    assert main(["log", "export", str(path), "--topic", "/axis/wrist/controller", "--format", "csv",
                 "-o", str(tmp_path / "w.csv")]) == 0
    assert len((tmp_path / "w.csv").read_text().splitlines()) == 301
    assert main(["log", "info", str(path)]) == 0
    assert "axes:       left (bus can0), right (bus can0), wrist (bus can1)" in capsys.readouterr().out


def _count_ends(lines: list[str]) -> set[int]:
    """Where the count of each ``  TOPIC  COUNT ...`` line ends."""
    ends = set()
    for line in lines:
        topic, count = line.split()[:2]
        ends.add(line.index(count, line.index(topic) + len(topic)) + len(count))
    return ends


def test_info_and_recover_keep_the_counts_in_a_column(recorded: tuple[Path, Path, Any], tmp_path: Path,
                                                      capsys: pytest.CaptureFixture[str]) -> None:
    """The topic column is as wide as the longest topic: a several-axis log's prefixed topics
    (``/axis/right/emulator/truth``, 26 characters) do not push their counts out of line."""
    path = recorded[0]
    capsys.readouterr()
    assert main(["log", "info", str(path)]) == 0
    out = capsys.readouterr().out.splitlines()
    log = open_log(path)
    rows = [line for line in out if line.startswith("  /")]   # channels, then the cycle messages' topics
    assert len(rows) == len(log.channels()) + len(log.info().folded or {}) and len(set(log.message_counts())) == 23
    assert any(len(r.split()[0]) > 20 for r in rows)
    assert len(_count_ends(rows)) == 1, "\n".join(rows)
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(path.read_bytes()[:-1000])
    assert main(["log", "recover", str(cut), "-o", str(tmp_path / "saved.mcap")]) == 0
    rows = [line for line in capsys.readouterr().out.splitlines() if line.startswith("  /")]
    assert len(rows) > 10 and any(len(r.split()[0]) > 20 for r in rows)
    assert len(_count_ends(rows)) == 1, "\n".join(rows)


def test_an_axis_config_key_this_version_does_not_know(recorded: tuple[Path, Path, Any], tmp_path: Path,
                                                      capsys: pytest.CaptureFixture[str]) -> None:
    """An axis' recorded config with a key this version does not know: ``log info`` names it
    and the axis in one note line, an export says it on stderr; replay of that axis refuses
    the log in one line naming both, the other axis replays."""
    from tests.recording.test_logs_never_lie import rewrite_metadata
    path = rewrite_metadata(recorded[0], tmp_path / "newer.mcap", "design.new_gain", "2", "axis/right/config")
    capsys.readouterr()
    assert main(["log", "info", str(path)]) == 0
    notes = [line for line in capsys.readouterr().out.splitlines() if line.startswith("note:")]
    assert len(notes) == 1 and "does not know (axis right: design.new_gain)" in notes[0], notes
    # an export copies what was recorded, that axis' topics too, with the same note on stderr
    assert main(["log", "export", str(path), "--topic", "/axis/right/controller", "--format", "csv",
                 "-o", str(tmp_path / "right.csv")]) == 0
    err = capsys.readouterr().err
    assert [line for line in err.splitlines() if "note" in line] == [f"dobhil log: {notes[0]}".replace(
        "note:       ", "note: ")], err
    assert main(["replay", str(path), "--axis", "left"]) == 0
    capsys.readouterr()
    _refused(capsys, ["replay", str(path)], "axis right's recorded config has keys dobhil", "design.new_gain")


@pytest.mark.parametrize(("key", "value", "words"), [
    ("design.delay_samples", "-3", ("delay_samples",)),
    ("loop.period", '"fast"', ("loop.period",)),
])
def test_an_axis_config_value_out_of_range_is_one_line(recorded: tuple[Path, Path, Any], tmp_path: Path,
                                                      capsys: pytest.CaptureFixture[str], key: str, value: str,
                                                      words: tuple[str, ...]) -> None:
    """An axis' recorded config value its schema refuses is checked as a single-axis log's
    config is: ``log info``, the exports and replay (of any axis) refuse the file in one line
    naming the axis and the key, nothing written."""
    from tests.recording.test_logs_never_lie import rewrite_metadata
    path = rewrite_metadata(recorded[0], tmp_path / "crafted.mcap", key, value, "axis/right/config")
    out = tmp_path / "out"
    out.mkdir()
    for argv in (["log", "info", str(path)], ["log", "info", str(path), "--json"],
                 ["log", "export", str(path), "--topic", "/axis/left/controller", "--format", "csv",
                  "-o", str(out / "c.csv")],
                 ["log", "export", str(path), "--can", "--format", "candump", "-o", str(out / "c.log")],
                 ["replay", str(path), "--axis", "left"]):
        _refused(capsys, argv, f"{path}: invalid recorded config of axis right", *words)
    assert list(out.iterdir()) == []


def test_overrides_per_axis_and_unknown_axes(recorded: tuple[Path, Path, Any],
                                             capsys: pytest.CaptureFixture[str]) -> None:
    path = recorded[0]
    changed = {r.recording.axis: r.first_mismatch() for r in replay_axes(path, ["axes.left.design.force_gain=3"])}
    assert changed["left"] is not None and changed["right"] is None and changed["wrist"] is None
    every = replay_axes(path, ["design.force_gain=3"])
    assert all(r.first_mismatch() is not None for r in every)
    for argv in (["--set", "axes.nope.design.force_gain=3"], ["--axis", "nope"]):
        capsys.readouterr()
        assert main(["replay", str(path), *argv]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "nope" in err[0] and "left, right, wrist" in err[0]
    with pytest.raises(Exception, match="name one with --axis"):
        replay(path)
    assert replay(path, axis="wrist").recording.profile.protocol == "cia402"


# -- single-axis logs ----------------------------------------------------------------------


@pytest.fixture(scope="module")
def single(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("single") / "single.mcap"
    logged_lockstep_run(path, duration=0.2)
    return path


def test_a_single_axis_log_reads_as_one_axis(single: Path, capsys: pytest.CaptureFixture[str]) -> None:
    log = open_log(single)
    (axis,) = axis_logs(log)
    assert axis.name == "axis" and not axis.listed and axis.config == log.config
    assert axis.topics() == log.topics() and axis.frame_ids is None
    assert main(["replay", str(single), "--verify"]) == 0
    out = capsys.readouterr().out
    assert out.startswith("replayed 200 cycles of") and "bit for bit" in out   # the single-axis lines, unchanged


@pytest.mark.parametrize("version", ["numeric_state", "axis_error"])
def test_old_single_axis_logs_read_as_one_axis(single: Path, tmp_path: Path, version: str) -> None:
    old = tmp_path / f"{version}.mcap"
    as_old_log(single, old, version)
    assert axis_names(open_log(old)) == ("axis",)
    (result,) = replay_axes(old)
    assert result.first_mismatch() is None and result.recording.cycles == 200


# -- the writer: lanes ---------------------------------------------------------------------


def _fb(seq: int, position: float) -> Any:
    return SimpleNamespace(position=position, velocity=-position, seq=seq, sample_latency=float("nan"))


_STATUS = SimpleNamespace(status=SimpleNamespace(state=1, protocol_state=8, error_code=0))


def test_many_axes_through_the_writer_process(tmp_path: Path) -> None:
    """Nine axes and two buses: record kinds beyond 100 (axis a8's events: 152, lane 11's
    frames: 178), even one alone in a batch, are records, not the writer's control messages;
    each axis reads back its own cycles."""
    names = tuple(f"a{i}" for i in range(9))
    log = AxesLog.open(tmp_path / "nine.mcap", names, fsync=False)
    inner = {b: can.Bus(interface="virtual", channel=f"nine-{b}") for b in ("x", "y/z")}
    taps = {b: log.wrap_bus(bus, b) for b, bus in inner.items()}
    late = can.Bus(interface="virtual", channel="late")
    try:
        log.begin(metadata={}, attachments=(), lossy=False, drives={
            n: AxisDrive(_STATUS, "x" if i % 2 else "y/z", own_ids={i}) for i, n in enumerate(names)})
        with pytest.raises(RecorderError, match="wrapped after the log began"):
            log.wrap_bus(late, "late")
        for k in range(300):
            for i, n in enumerate(names):
                log.sink(n).cycle(k, k * 1e-3, _fb(k + 1, i + k / 1000), (0.5, i, 0.0, 0.0, k, k), 0.0, 1e-5, False)
            taps["y/z"].send(can.Message(arbitration_id=k % 9, data=[k % 256]))
        log.log.flush()
        log.sink("a8").event(EventKind.INFO, "the last axis' last word")   # alone in the last batch
        log.end("done")
    finally:
        for bus in (*taps.values(), *inner.values(), late):
            bus.shutdown()
    file = open_log(tmp_path / "nine.mcap")
    assert layout(file).buses == {"x": "/bus/x", "y/z": "/bus/y_z"}
    for i, axis in enumerate(axis_logs(file)):
        rows = [p for _, _, p in axis.iter_messages(["/controller"])]
        assert [p["cycle"] for p in rows] == list(range(300)) and {p["tau_int_hat"] for p in rows} == {i}
    assert [p["reason"] for _, _, p in axis_log(file, "a8").iter_messages(["/events"])] == [
        "the last axis' last word", "done"]
    tx = [p for _, _, p in file.iter_messages(["/bus/y_z/can/tx"])]
    assert [p["data"] for p in tx] == [[k % 256] for k in range(300)]


def test_foreign_frames_are_told_per_bus(tmp_path: Path) -> None:
    """In real time a received frame of an id no axis on its bus owns is foreign (shed first);
    the same id on the bus of the axis that owns it is the loop's own."""
    log = AxesLog.open(tmp_path / "f.mcap", ("p", "q"), fsync=False)
    inner = [can.Bus(interface="virtual", channel=f"f-{b}") for b in ("one", "two")]
    buses = [log.wrap_bus(bus, b) for bus, b in zip(inner, ("one", "two"))]
    try:
        log.begin(metadata={}, attachments=(), lossy=True, drives={
            "p": AxisDrive(_STATUS, "one", own_ids={1}), "q": AxisDrive(_STATUS, "two", own_ids={2})})
        rx = {b: lane_kind(Topic.CAN_RX, 3 + i) for i, b in enumerate(("one", "two"))}
        for bus in ("one", "two"):
            for arb in (1, 2):
                log.log.frame(rx[bus], can.Message(arbitration_id=arb, data=[arb]))
        assert [(r[0], r[2]) for r in map(unpacked, log.log.records)] == [(rx["one"], 1), (rx["two"], 2)]
        assert [(r[0], r[2]) for r in log.log.foreign] == [(rx["one"], 2), (rx["two"], 1)]
        log.end("done")
    finally:
        for bus in (*buses, *inner):
            bus.shutdown()
    file = open_log(tmp_path / "f.mcap")
    got = sorted((t, p["arbitration_id"]) for t, _, p in file.iter_messages(["/bus/one/can/rx", "/bus/two/can/rx"]))
    assert got == [("/bus/one/can/rx", 1), ("/bus/one/can/rx", 2), ("/bus/two/can/rx", 1), ("/bus/two/can/rx", 2)]


_LANES = 4   # the run's, two axes', one bus'


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.lists(st.tuples(st.integers(0, _LANES - 1), st.sampled_from((CYCLE, Topic.EVENTS, Topic.CAN_RX)),
                          st.floats(allow_nan=False, allow_infinity=False, width=32)), max_size=60))
def test_any_interleaving_of_lanes_reads_back_per_axis(tmp_path_factory: pytest.TempPathFactory,
                                                      items: list[tuple[int, int, float]]) -> None:
    """Whatever order the lanes' records come in, each axis reads exactly its own records
    (and the run's events), in order, under its single-axis topic names."""
    path = tmp_path_factory.mktemp("lanes") / "l.mcap"
    lanes = [("", None), ("/axis/a", None), ("/axis/b", None), ("/bus/c", None)]
    metadata = {"axes": {"names": '["a", "b"]', "bus_of": '{"a": "c", "b": "c"}', "buses": '{"c": "/bus/c"}'}}
    writer = LogWriter(open(path, "wb"), metadata=metadata, fsync=False, lanes=lanes)
    expected: dict[str, list[tuple[str, float]]] = {"a": [], "b": []}
    records = []
    for t, (lane, base, value) in enumerate(items):
        if base == CYCLE and lane in (1, 2):
            records.append((lane_kind(CYCLE, lane), t, t, value, 0.0, t, 0.0, value, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0,
                            False, float("nan"), 1, -1, 0))
            expected["ab"[lane - 1]].append(("/controller", value))
        elif base == Topic.EVENTS and lane in (0, 1, 2):
            records.append((lane_kind(base, lane), t, int(EventKind.INFO), repr(value), "", 0))
            for name in ("ab" if lane == 0 else "ab"[lane - 1]):
                expected[name].append(("/events", float(value)))
        elif base == Topic.CAN_RX and lane == 3:
            records.append((lane_kind(base, lane), t, 7, False, False, False, False, False, False, 1, b"\x01",
                            value, "c"))
            for name in "ab":
                expected[name].append(("/can/rx", value))
    writer.write(records)
    writer.finish(None)
    for axis in axis_logs(path):
        got = [(topic, float(p["reason"]) if topic == "/events" else p["tau_int_hat"] if topic == "/controller"
                else p["timestamp"]) for topic, _, p in axis.iter_messages(["/controller", "/events", "/can/rx"])]
        assert got == expected[axis.name]
        assert isinstance(axis, AxisLog)


def test_a_run_that_fails_leaves_a_complete_log_or_none(tmp_path: Path) -> None:
    """Before the log began: no file; after: a complete file ending ``exception`` (never half
    written); a begin without every axis' drive, or on a bus never wrapped, is refused."""
    from dobhil.cli.recording import abort_axes
    early = AxesLog.open(tmp_path / "early.mcap", ("p", "q"), fsync=False)
    with pytest.raises(RecorderError, match="no drive for axis 'q'"):
        early.begin(metadata={}, attachments=(), lossy=False, drives={"p": AxisDrive(_STATUS, "one")})
    abort_axes(early, RuntimeError("the session could not start"))
    assert not (tmp_path / "early.mcap").exists()
    late = AxesLog.open(tmp_path / "late.mcap", ("p",), fsync=False)
    inner = can.Bus(interface="virtual", channel="late-one")
    tap = late.wrap_bus(inner, "one")
    try:
        with pytest.raises(RecorderError, match="bus 'two' of an axis was never wrapped"):
            late.begin(metadata={}, attachments=(), lossy=False, drives={"p": AxisDrive(_STATUS, "two")})
        late.begin(metadata={}, attachments=(), lossy=False, drives={"p": AxisDrive(_STATUS, "one")})
        late.sink("p").cycle(0, 0.0, _fb(1, 0.0), (0.0,) * 6, 0.0, 1e-5, False)
        abort_axes(late, RuntimeError("the loop failed"))
    finally:
        tap.shutdown()
        inner.shutdown()
    file = open_log(tmp_path / "late.mcap")
    assert file.stop_reason() == "exception" and axis_names(file) == ("p",)
    assert [p["cycle"] for _, _, p in axis_log(file).iter_messages(["/controller"])] == [0]


def test_a_single_axis_tool_names_the_axes(recorded: tuple[Path, Path, Any],
                                           capsys: pytest.CaptureFixture[str]) -> None:
    # an axis' prefix alone names no topic: the example is one of its topics, not the prefix twice
    assert main(["log", "export", str(recorded[0]), "--topic", "/axis/left", "--format", "csv",
                 "-o", str(recorded[0].with_suffix(".csv"))]) == 2
    err = capsys.readouterr().err
    assert "(e.g. /axis/left/controller)" in err and "/axis/left/axis/left" not in err, err


def _refused(capsys: pytest.CaptureFixture[str], argv: list[str], *words: str) -> None:
    capsys.readouterr()
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err, err
    assert all(w in err for w in words), err


def test_compare_takes_an_axis_of_a_several_axis_log(recorded: tuple[Path, Path, Any], single: Path,
                                                     capsys: pytest.CaptureFixture[str]) -> None:
    """``compare`` reads one axis of a several-axis log, named by ``--axis``, and refuses
    without one or with an unknown one in the words ``identify`` and ``replay`` use; a
    single-axis log given with it is its one axis (an axis of a run against a run alone)."""
    path = str(recorded[0])
    _refused(capsys, ["compare", path, path], "a log of 3 axes (left, right, wrist); name one with --axis NAME")
    for command in (["identify", path], ["compare", path, path]):
        _refused(capsys, [*command, "--axis", "elbow"], "no axis 'elbow'; axes: left, right, wrist")
    _refused(capsys, ["compare", str(single), str(single), "--axis", "left"], "no axis 'left'; axes: axis")
    assert main(["compare", path, path, "--axis", "right", "--json"]) == 0
    same = json.loads(capsys.readouterr().out)
    assert same["axis"] == "right" and same["cycles"] == 300 and same["rms"] == same["max_abs"] == 0.0
    assert main(["compare", path, str(single), "--axis", "left", "--json"]) == 0
    mixed = json.loads(capsys.readouterr().out)
    left = {p["cycle"]: p["tau_int_hat"] for _, _, p in axis_log(open_log(path), "left").iter_messages(["/controller"])}
    alone = {p["cycle"]: p["tau_int_hat"] for _, _, p in open_log(single).iter_messages(["/controller"])}
    diff = [alone[c] - left[c] for c in sorted(left.keys() & alone.keys())]
    assert mixed["cycles"] == len(diff) > 0
    assert mixed["rms"] == pytest.approx(math.sqrt(sum(d * d for d in diff) / len(diff)), rel=1e-12)
    assert main(["compare", path, path, "--axis", "wrist"]) == 0
    assert capsys.readouterr().out.startswith("axis wrist: compared 300 cycles")


def test_a_real_time_several_axis_log_replays_bit_for_bit(tmp_path: Path) -> None:
    """In real time (lossy, wall clock, the emulator in its own process) each axis' records
    still replay bit for bit (every motion frame of each drive on the shared bus recorded);
    nothing is dropped on a run this short. Timing is the machine's: nothing is asserted of it."""
    path = tmp_path / "rt.mcap"
    config = write_config(tmp_path, CONFIG_2)
    results = record_axes(path, config, {"left": "can0", "right": "can0"}, lockstep=False)
    assert all(r.cycles > 0 for r in results.values())
    file = open_log(path)
    assert file.metadata["recording"]["mode"] == "lossy" and file.info().dropped == 0
    assert file.metadata["run"]["log_clock"] == "wall"
    replayed = {r.recording.axis: r for r in replay_axes(path)}
    for name, result in results.items():
        assert replayed[name].recording.cycles == result.cycles
        assert replayed[name].first_mismatch() is None


#: two ODrive axes on one bus, timed by the drives' feedback in real time
CONFIG_2 = """\
loop: {period: 0.001, duration: 0.3, timing: feedback, feedback_timeout: 0.05}
reference: {kind: step, offset: 0.2, amplitude: 0.8, start: 0.1}
axes:
  - name: left
    drive: {profile: odrive-0.6, node_id: 1}
  - name: right
    drive: {profile: odrive-0.6, node_id: 2}
    plant: {inertia: 0.3}
"""


class _Output:
    """A second output (the live view's place) that keeps what it is told."""

    def __init__(self) -> None:
        self.channels: list[str] = []
        self.published: list[str] = []
        self.dropped = 0

    def add_channel(self, topic: str, *, schema_name: str, json_schema: dict[str, Any] | bytes,
                    message_encoding: str = "json", schema_encoding: str = "jsonschema") -> None:
        self.channels.append(topic)

    def publish(self, topic: str, payload: bytes, log_time_ns: int) -> None:
        self.published.append(topic)

    def close(self) -> None:
        pass


def test_the_live_view_is_told_each_lanes_own_topics(tmp_path: Path) -> None:
    """An axis' lane has its loop topics, a bus' its frames, the run's its events: the
    live view is told those and no empty others; a record a lane has no topic for is refused."""
    log = AxesLog.open(tmp_path / "x.mcap", ("p",), fsync=False)
    inner = can.Bus(interface="virtual", channel="lanes-one")
    tap = log.wrap_bus(inner, "one")
    try:
        lanes = log.lanes({"p": AxisDrive(_STATUS, "one")})
    finally:
        for bus in (tap, inner):
            bus.shutdown()
        log.writer.close()
    writer = LogWriter(open(tmp_path / "l.mcap", "wb"), metadata={}, fsync=False, lanes=lanes)
    out = _Output()
    writer.add_output(out)
    # the axis' cycle messages as the file has them (the default layout), then every topic
    axis = ("/drive/feedback", "/drive/command", "/controller", "/loop", "/emulator/truth", "/events")
    assert out.channels == ["/axis/p/cycle", "/events", *(f"/axis/p{t}" for t in axis),
                            "/bus/one/can/rx", "/bus/one/can/tx"]
    writer.write([(lane_kind(Topic.CAN_TX, 2), 1, 5, False, False, False, False, False, False, 0, b"", 0.0, "")])
    assert out.published == ["/bus/one/can/tx"]
    with pytest.raises(KeyError):
        writer.write([(lane_kind(Topic.CAN_TX, 1), 2, 5, False, False, False, False, False, False, 0, b"", 0.0, "")])
    writer.finish(None)
    topics = LogWriter(open(tmp_path / "t.mcap", "wb"), metadata={}, fsync=False, lanes=lanes, layout="topics")
    out = _Output()
    topics.add_output(out)   # the topics layout: every topic, no cycle channel
    assert out.channels == ["/events", *(f"/axis/p{t}" for t in axis), "/bus/one/can/rx", "/bus/one/can/tx"]
    topics.finish(None)
