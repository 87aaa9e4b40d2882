"""Recording a run: every frame on the bus, the per-cycle channels, Ctrl-C and SIGKILL."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path

import can
import pytest
from mcap.reader import make_reader

from dobhil.config import load_config
from dobhil.errors import LogFileError
from dobhil.cli.recording import record_run
from dobhil.canio.canlog import CanLogFormat, export_can
from dobhil.canio.canlog import default_can_output as default_output
from dobhil.recording.process import PARENT_EXITED, WriterProcess
from dobhil.recording.reader import open_log
from dobhil.recording.recover import recover
from dobhil.recording.runlog import RunLog
from dobhil.runtime.session import RunSession
from tests.recording.helpers import decode_message, topic_counts
from tests.runtime.helpers import write_profile

ROOT = Path(__file__).resolve().parents[2]
DEMO = ROOT / "configs" / "demo.yaml"
TOPICS = {"/can/rx", "/can/tx", "/drive/feedback", "/drive/command", "/controller", "/loop",
          "/emulator/truth", "/events"}


def logged_lockstep_run(path: Path, duration: float = 0.3, encoding: str = "protobuf",
                        layout: str = "topics") -> tuple[list[can.Message], int, int]:
    """A lockstep demo run recorded to ``path`` (messages in ``encoding``, laid out as
    ``layout``); every frame a sniffer saw, the cycles and the frames the emulated drive sent."""
    config = load_config(DEMO, [f"loop.duration={duration}"])
    log = RunLog(WriterProcess(path, fsync=False, encoding=encoding, layout=layout))
    with RunSession(config, emulate=True, lockstep=True, sink=log, bus_wrapper=log.wrap_bus) as session:
        sniffer = can.Bus(interface="virtual", channel=session.bus_spec.channel)
        try:
            result = record_run(session, log, DEMO)
            seen = []
            msg = sniffer.recv(0.0)
            while msg is not None:
                seen.append(msg)
                msg = sniffer.recv(0.0)
        finally:
            sniffer.shutdown()
        assert session.emulator is not None
        sent_by_drive = session.emulator.frames_sent
    return seen, result.cycles, sent_by_drive


def lockstep_log_in(tmp_path_factory: pytest.TempPathFactory, folder: str, duration: float) -> Path:
    """A module's recorded lockstep demo run (:func:`logged_lockstep_run`) in a folder of its own."""
    path = tmp_path_factory.mktemp(folder) / "run.mcap"
    logged_lockstep_run(path, duration=duration)
    return path


Run = tuple[Path, list[can.Message], int, int]


@pytest.fixture(scope="module")
def run_log(tmp_path_factory: pytest.TempPathFactory) -> Run:
    path = tmp_path_factory.mktemp("run") / "run.mcap"
    return (path, *logged_lockstep_run(path))


def test_every_frame_and_channel_with_plain_mcap_reader(run_log: Run) -> None:
    path, seen, cycles, sent_by_drive = run_log
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None
        schemas = {c.topic: summary.schemas[c.schema_id] for c in summary.channels.values()}
        assert set(schemas) == TOPICS
        assert all(s.encoding == "protobuf" and s.data for s in schemas.values())
        counts: Counter[str] = Counter()
        frames: list[tuple[str, int, bytes]] = []
        for schema, channel, message in reader.iter_messages(log_time_order=False):
            counts[channel.topic] += 1
            if channel.topic.startswith("/can/"):
                p = decode_message(schema, channel, message.data)
                frames.append((p["direction"], p["arbitration_id"], bytes(p["data"])))
    assert counts["/can/rx"] + counts["/can/tx"] == len(seen)
    assert sorted((f[1], f[2]) for f in frames) == sorted((m.arbitration_id, bytes(m.data)) for m in seen)
    assert counts["/can/rx"] == sent_by_drive  # the drive's counter: every frame it sent
    assert counts["/can/tx"] == len(seen) - sent_by_drive
    assert Counter(d for d, _, _ in frames) == {"rx": counts["/can/rx"], "tx": counts["/can/tx"]}
    for topic in ("/controller", "/loop", "/drive/command", "/emulator/truth"):
        assert counts[topic] == cycles
    assert counts["/drive/feedback"] == cycles + 1  # + the feedback controller.initialize used
    meta = open_log(path).metadata
    assert {"config", "versions", "bus", "run", "drive", "recording"} <= set(meta)
    assert meta["recording"]["dropped"] == "0" and meta["bus"]["bitrate"] == "1000000"
    assert meta["run"]["sample_clock"] == ""   # ODrive does not tell its sample instant
    assert {"demo.yaml", "config.resolved.yaml"} <= {a for a, _, _ in open_log(path).attachments}


def test_a_shipped_config_name_attaches_its_file(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``dobhil run demo`` (a shipped name, not a path) attaches the file the name loaded, as
    a path does."""
    from dobhil.cli.main import main
    path = tmp_path / "named.mcap"
    assert main(["run", "demo", "--emulate", "--lockstep", "--set", "loop.duration=0.1", "--log", str(path)]) == 0
    capsys.readouterr()
    attached = {name: data for name, _, data in open_log(path).attachments}
    assert set(attached) == {"demo.yaml", "config.resolved.yaml"}
    assert attached["demo.yaml"] == DEMO.read_bytes()


def test_events_enable_disable_stop(run_log: Run) -> None:
    events = [p for _, _, p in open_log(run_log[0]).iter_messages(["/events"])]
    kinds = [e["kind"] for e in events]
    assert kinds[0] == "enable" and "disable" in kinds and kinds[-1] == "stop"
    assert events[-1]["reason"] == "done"


def test_a_watchdog_that_expires_after_the_safe_stop_is_no_watchdog_event(tmp_path: Path,
                                                                          capsys: pytest.CaptureFixture[str]) -> None:
    """An ODrive checks its watchdog in every axis state: firmware 0.5 answers no heartbeat
    request, so the safe stop waits for the cyclic heartbeat (every 0.1 s), which comes after
    the 0.05 s watchdog of the axis nobody feeds any more and carries its bit. The run's log
    recorded "drive watchdog expired" for every such run; the watchdog expired after the drive
    was disabled, not while it was enabled (tests/drives/test_drive_emulated.py trips it then)."""
    from dobhil.cli.main import main
    path = tmp_path / "run.mcap"
    assert main(["run", "demo", "--emulate", "--lockstep", "--set", "drive.profile=odrive-0.5",
                 "--set", "loop.duration=0.1", "--log", str(path)]) == 0
    capsys.readouterr()
    events = [(p["kind"], p["reason"]) for _, _, p in open_log(path).iter_messages(["/events"])]
    assert ("disable", "safe stop: confirmed") in events and events[-1] == ("stop", "done")
    assert not [e for e in events if e[0] == "watchdog"], events


@pytest.mark.parametrize("fmt", list(CanLogFormat), ids=lambda f: f.name.lower())
def test_can_export_of_a_run_reads_back(run_log: Run, tmp_path: Path,
                                        fmt: CanLogFormat) -> None:
    path, seen, _, _ = run_log
    out = default_output(tmp_path / "frames.mcap", fmt)
    count = export_can(path, out, fmt)
    with can.LogReader(out) as reader:
        back = [(m.arbitration_id, bytes(m.data)) for m in reader]
    assert count == len(seen) == len(back)
    assert sorted(back) == sorted((m.arbitration_id, bytes(m.data)) for m in seen)


def _start_realtime_run(path: Path, duration: float) -> subprocess.Popen[bytes]:
    """``dobhil run --log`` in its own process group (the group a terminal's Ctrl-C hits),
    real time: the emulated drive is a process of that group too. A signal test, not a
    timing one: a loaded machine can starve a real-time run into stopping on its own
    (``host_too_slow``: the drive's watchdog or the feedback timeout expired while the host
    was not scheduled), and a run that stopped before the signal tests nothing. So nothing
    starvation trips is armed: no drive watchdog, no feedback timeout shorter than the run."""
    profile = write_profile(path.parent, "odrive-0.6", watchdog_timeout=0)
    return _start_run(path, "--duration", str(duration), "--set", f"drive.profile={profile}",
                      "--set", f"loop.feedback_timeout={duration}")


def _start_lockstep_run(path: Path) -> subprocess.Popen[bytes]:
    """``dobhil run --lockstep --log`` of an hour, in its own process group: a run the test
    kills long before its end, whatever the machine's load. The kill tests are about the
    writer process and the file, not real time: a real-time run on a loaded machine could
    stop on its own (a feedback timeout) before the kill, and the kill would test nothing."""
    return _start_run(path, "--lockstep", "--duration", "3600")


def _start_run(path: Path, *args: str) -> subprocess.Popen[bytes]:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.Popen([sys.executable, "-m", "dobhil", "run", str(DEMO), "--emulate", "--log", str(path),
                             *args],
                            env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, start_new_session=True)


def _wait_for_cycles(path: Path, proc: subprocess.Popen[bytes], seconds: float) -> None:
    deadline = time.monotonic() + 20
    while time.monotonic() < deadline and (not path.exists() or path.stat().st_size < 20000):
        assert proc.poll() is None, proc.communicate()
        time.sleep(0.05)
    time.sleep(seconds)


def _wait_for_recorded(path: Path, proc: subprocess.Popen[bytes], scratch: Path, cycles: int) -> int:
    """Until the file being written holds ``cycles`` complete ``/controller`` records (read
    by ``recover`` from a copy of it, as a reader after a crash would): the count the file
    had, a floor for what it must still hold after a kill. A count the run itself wrote,
    not a rate assumed of a machine that may be loaded."""
    deadline = time.monotonic() + 120   # a bound, not a measurement
    seen = 0
    while time.monotonic() < deadline:
        assert proc.poll() is None, proc.communicate()
        if path.exists():
            copy = scratch / "partial.mcap"
            copy.write_bytes(path.read_bytes())
            try:
                seen = topic_counts(recover(copy, scratch / "partial-recovered.mcap").output).get("/controller", 0)
            except LogFileError:   # not even the header yet
                seen = 0
            (scratch / "partial-recovered.mcap").unlink(missing_ok=True)
            if seen >= cycles:
                return seen
        time.sleep(0.2)
    raise AssertionError(f"the file held {seen} cycles of {cycles} after 120 s")


def _group_alive(pgid: int) -> bool:
    """A member of the process group is still running. One that has exited but is not reaped
    yet (a zombie: the killed run's children are reaped by the machine's init, measured here to
    take up to 2 s) has finished its work, the file included, and counts as gone; read from
    /proc (Linux), else any member that can still be signalled counts."""
    proc = Path("/proc")
    if not (proc / "self" / "stat").is_file():
        try:
            os.killpg(pgid, 0)
        except ProcessLookupError:
            return False
        return True
    for stat in proc.glob("[0-9]*/stat"):
        try:
            text = stat.read_text()
        except OSError:   # gone while we looked
            continue
        # after the command's closing parenthesis (the command may hold any character):
        # the state, the parent's pid, the process group
        state, _, group = text[text.rindex(")") + 2:].split()[:3]
        if int(group) == pgid and state != "Z":
            return True
    return False


def _wait_for_group_exit(pgid: int) -> None:
    """The writer process (same group) is gone too: it has finished the file."""
    deadline = time.monotonic() + 20
    while _group_alive(pgid) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not _group_alive(pgid), "the writer process outlived its parent"


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGHUP, signal.SIGQUIT], ids=lambda s: s.name)
def test_ctrl_c_to_the_process_group_leaves_a_complete_file_with_stop_signal(tmp_path: Path,
                                                                             signum: signal.Signals) -> None:
    """What a terminal sends the whole process group -- Ctrl-C, its closing (SIGHUP), Ctrl-\\
    (SIGQUIT) -- is a safe stop: the run's helpers (the writer, the emulated drive, the fork
    server) ignore it, so the drive confirms its disable and the file is finished."""
    path = tmp_path / "rt.mcap"
    proc = _start_realtime_run(path, 30.0)
    _wait_for_cycles(path, proc, 0.5)
    os.killpg(proc.pid, signum)  # the writer process gets it too, and ignores it
    out, err = proc.communicate(timeout=20)
    assert proc.returncode == 1, err
    stop = [line for line in out.decode().splitlines() if line.startswith("stopped: ")]
    assert len(stop) == 1 and stop[0].startswith("stopped: signal "), out
    assert stop[0].endswith(f"received {signum.name}"), out
    assert b"WARNING" not in err and b"Traceback" not in err, err
    _wait_for_group_exit(proc.pid)
    info = open_log(path).info()
    assert info.stop_reason == "signal"
    counts = topic_counts(path)
    assert counts["/controller"] > 100 and counts["/can/rx"] > 100
    assert info.metadata["recording"]["mode"] == "lossy"
    events = [p for _, _, p in open_log(path).iter_messages(["/events"])]
    assert [e["kind"] for e in events][0] == "enable" and events[-1]["kind"] == "stop"


def test_sigkill_of_the_run_the_writer_finishes_the_file(tmp_path: Path) -> None:
    path = tmp_path / "killed.mcap"
    proc = _start_lockstep_run(path)
    scratch = tmp_path / "scratch"
    scratch.mkdir()
    on_disk = _wait_for_recorded(path, proc, scratch, 2000)
    proc.kill()  # the main process only: the writer sees end of file on its pipe
    proc.communicate(timeout=20)
    _wait_for_group_exit(proc.pid)
    info = open_log(path).info()
    assert info.stop_reason == PARENT_EXITED
    counts = topic_counts(path)
    # everything the loop handed over: at least what was already on disk before the kill
    assert counts["/controller"] >= on_disk
    report = recover(path, tmp_path / "rec.mcap")
    assert report.complete and topic_counts(report.output)["/controller"] == counts["/controller"]


def test_sigkill_of_run_and_writer_leaves_a_recoverable_file(tmp_path: Path) -> None:
    path = tmp_path / "killed.mcap"
    proc = _start_lockstep_run(path)
    scratch = tmp_path / "scratch"
    scratch.mkdir()
    on_disk = _wait_for_recorded(path, proc, scratch, 1000)
    os.killpg(proc.pid, signal.SIGKILL)  # power-loss like: nobody finishes the file
    proc.communicate(timeout=20)
    _wait_for_group_exit(proc.pid)
    assert not open_log_ok(path)
    report = recover(path, tmp_path / "rec.mcap")
    counts = topic_counts(report.output)
    # at least every record that was in the file before the kill: a kill loses none of it
    assert not report.complete and counts.get("/controller", 0) >= on_disk
    assert open_log(tmp_path / "rec.mcap").info().message_count == report.message_count


def open_log_ok(path: Path) -> bool:
    try:
        open_log(path)
    except LogFileError:
        return False
    return True


def test_a_sent_frame_is_recorded_with_the_data_it_had_when_sent() -> None:
    """Drives refill one preallocated torque message every cycle: the tap packs the frame
    as it is when sent."""
    from types import SimpleNamespace

    from dobhil.recording.packed import unpacked
    from dobhil.recording.runlog import RecordingBus, RunLog
    from dobhil.recording.schemas import FRAME_ATTRIBUTES, Topic
    data = 2 + FRAME_ATTRIBUTES.index("data")
    batch = RunLog(SimpleNamespace(opened=False))  # type: ignore[arg-type]
    inner = can.Bus(interface="virtual", channel="refill-test", receive_own_messages=True)
    tap = RecordingBus(inner, batch)
    try:
        msg = can.Message(arbitration_id=0x06E, data=bytes(4), is_extended_id=False)
        for value in (1, 2):
            msg.data[0] = value
            tap.send(msg)
        assert tap.recv(1.0) is not None
        msg.data[0] = 9  # refilled after the last send
        flat = [unpacked(r) for r in batch.take()]  # cycles and frames are taken packed
    finally:
        tap.shutdown()
        inner.shutdown()
    assert [(r[0], bytes(r[data])[0]) for r in flat] == [(int(Topic.CAN_TX), 1), (int(Topic.CAN_TX), 2),
                                                        (int(Topic.CAN_RX), 1)]
    assert all(r[2] == 0x06E and r[data - 1] == 4 for r in flat)
    assert flat[-1][-1] == "refill-test"  # the received frame's channel, named on first use
