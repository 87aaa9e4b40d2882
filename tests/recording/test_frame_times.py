"""The bus timestamps of recorded frames share one time base.

A sent frame is stamped with its send time on the log clock (its python-can message carries
0.0); a received frame keeps the interface's stamp in real time (the same wall clock on
virtual and SocketCAN); in lockstep both directions carry the simulated log time. So a CAN
export of a run, read back by ``dobhil log import``, keeps its date.
"""

from __future__ import annotations

import datetime
import os
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest

from dobhil.canio.canlog import CanLogFormat, export_can, import_can
from dobhil.cli.recording import record_run
from dobhil.config import load_config
from dobhil.recording.process import WriterProcess
from dobhil.recording.reader import open_log
from dobhil.recording.runlog import RunLog
from dobhil.runtime.session import RunSession
from tests.recording.test_run_logging import DEMO, lockstep_log_in

#: ASC's Begin Triggerblock date has milliseconds; each line is relative to the exact start
ASC_START_RESOLUTION = 1e-3


def frames(path: Path) -> list[tuple[str, int, float]]:
    """(topic, log time ns, bus timestamp s) of every recorded frame, in log order."""
    with open_log(path) as log:
        return [(topic, t, p["timestamp"]) for topic, t, p in log.iter_messages(["/can/rx", "/can/tx"])]


@pytest.fixture(scope="module")
def lockstep_log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return lockstep_log_in(tmp_path_factory, "frame-times", 0.1)


def test_lockstep_frames_in_both_directions_carry_the_simulated_log_time(lockstep_log: Path) -> None:
    recorded = frames(lockstep_log)
    assert {topic for topic, _, _ in recorded} == {"/can/rx", "/can/tx"}
    for topic, t, stamp in recorded:
        assert stamp == pytest.approx(t / 1e9, abs=1e-6), topic


def test_real_time_sent_frames_carry_their_send_time_on_the_received_frames_clock(tmp_path: Path) -> None:
    path = tmp_path / "rt.mcap"
    config = load_config(DEMO, ["loop.duration=0.1", "loop.feedback_timeout=0.5"])
    log = RunLog(WriterProcess(path, fsync=False))
    with RunSession(config, emulate=True, lockstep=False, sink=log, bus_wrapper=log.wrap_bus) as session:
        record_run(session, log, DEMO)
    recorded = frames(path)
    tx = [(t, stamp) for topic, t, stamp in recorded if topic == "/can/tx"]
    rx = [(t, stamp) for topic, t, stamp in recorded if topic == "/can/rx"]
    assert tx and rx
    assert all(stamp == pytest.approx(t / 1e9, abs=1e-6) for t, stamp in tx)  # never 0.0
    # a frame is received after it was sent, on the same clock: no later than its log time,
    # and not before the first frame the run recorded was even logged minus the run's span
    span = (recorded[-1][1] - recorded[0][1]) / 1e9
    assert all(stamp <= t / 1e9 + 1e-6 for t, stamp in rx)
    assert all(stamp >= recorded[0][1] / 1e9 - span - 1.0 for _, stamp in rx)


@contextmanager
def time_zone(tz: str | None) -> Iterator[None]:
    """The process' local time zone ``tz`` (a POSIX ``TZ`` string; None: as it is)."""
    if tz is None:
        yield
        return
    before = os.environ.get("TZ")
    os.environ["TZ"] = tz
    time.tzset()
    try:
        yield
    finally:
        if before is None:
            del os.environ["TZ"]
        else:
            os.environ["TZ"] = before
        time.tzset()


#: An ASC header's date has no zone: exported in one (POSIX TZ strings, no zone database
#: needed: CET, UTC+1) and imported in another (EST, UTC-5), the times stay the same.
@pytest.mark.parametrize("zones", [(None, None), ("CET-1", "EST5")])
def test_asc_export_then_import_keeps_the_date(lockstep_log: Path, tmp_path: Path,
                                               zones: tuple[str | None, str | None]) -> None:
    asc, back = tmp_path / "run.asc", tmp_path / "back.mcap"
    with time_zone(zones[0]):
        count = export_can(lockstep_log, asc, CanLogFormat.ASC)
    with time_zone(zones[1]):
        assert import_can(asc, back) == count
    original = sorted(stamp for _, _, stamp in frames(lockstep_log))
    imported = sorted(stamp for _, _, stamp in frames(back))
    year = datetime.datetime.fromtimestamp(original[0], tz=datetime.timezone.utc).year
    assert datetime.datetime.fromtimestamp(imported[0], tz=datetime.timezone.utc).year == year
    assert imported[0] == pytest.approx(original[0], abs=ASC_START_RESOLUTION)
    assert imported[-1] == pytest.approx(original[-1], abs=ASC_START_RESOLUTION)


@pytest.mark.parametrize("earliest", [1796190707.0463517, 1796190707.0, 1796190707.0999, 1796190707.1, 1796190707.5004])
def test_an_asc_start_reads_back_as_written(tmp_path: Path, earliest: float) -> None:
    """python-can writes an ASC header's milliseconds unpadded (46 ms as ``.46``) and reads
    them as a fraction: the export starts at a time that survives that (whole ms, >= 100)."""
    import can

    from dobhil.canio.canlog import asc_start
    start = asc_start(earliest)
    assert start <= earliest and earliest - start < 0.101 and round(start * 1000) % 1000 >= 100
    path = tmp_path / "start.asc"
    with can.ASCWriter(path) as writer:
        writer.log_event("start", start)
        writer.on_message_received(can.Message(arbitration_id=0x69, data=b"\x01", timestamp=earliest))
    (msg,) = list(can.LogReader(path, relative_timestamp=False))
    assert msg.timestamp == pytest.approx(earliest, abs=1e-5)
