"""The recorder rows of the fault matrix (``test_fault_matrix.py`` has the runtime's own):
{lockstep, feedback-synchronous real time} x {writer process killed, disk full}.

Each row asserts the stop reason ``recorder_failed`` in one line, that the drive saw zero
torque then IDLE and ended IDLE, and that ``dobhil log recover`` salvages the file (the
writer is gone, so the stop itself cannot be in it); where the log clock is the wall clock (real
time), that what recover loses before the writer died is at most the flush interval (1 s).
"""

from __future__ import annotations

import dataclasses
import os
import resource
import signal
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pytest

from dobhil.cli.recording import open_run_log, record_run
from dobhil.cli.run_cmd import log_hooks
from dobhil.recording.reader import open_log
from dobhil.recording.recover import recover
from dobhil.recording.runlog import RunLog
from dobhil.runtime.session import RunSession
from dobhil.runtime.stop import StopReason

from .helpers import Sniffer, assert_stopped_safely
from .test_fault_matrix import matrix_config

#: the writer flushes every second: what a crash may lose, plus a batch's hand-over
FLUSH_SLACK_S = 1.0 + 0.3


def _runqueue_wait_s(pid: int) -> float:
    """Seconds process ``pid`` has spent runnable but not running (Linux
    /proc/PID/schedstat, second field); 0 where the kernel does not say."""
    try:
        return int(Path(f"/proc/{pid}/schedstat").read_text().split()[1]) / 1e9
    except (OSError, IndexError, ValueError):
        return 0.0


class KillWriterAt:
    """The run's sink (the log), with the writer process killed ``after_s`` seconds (wall
    clock) after the first cycle, and not before the file at ``path`` has grown past its size
    at the first cycle: after at least one chunk reached the OS, however long a busy machine
    left the writer (SCHED_IDLE) without CPU. ``starved_s``: how long the writer waited for
    a CPU in between (what a busy machine adds to what a crash loses)."""

    def __init__(self, log: RunLog, after_s: float, path: Path) -> None:
        self.log, self.after_s, self.path = log, after_s, path
        self.t0: float | None = None
        self.size0 = 0
        self.wait0 = 0.0
        self.starved_s = 0.0
        self.killed_ns: int | None = None

    def cycle(self, k: int, *args: Any) -> None:
        now = time.monotonic()
        pid = self.log.writer_pid
        assert pid is not None
        if self.t0 is None:
            self.t0, self.size0 = now, self.path.stat().st_size
            self.wait0 = _runqueue_wait_s(pid)
        if (now - self.t0 >= self.after_s and self.killed_ns is None
                and self.path.stat().st_size > self.size0):
            self.starved_s = _runqueue_wait_s(pid) - self.wait0
            os.kill(pid, signal.SIGKILL)
            self.killed_ns = time.time_ns()
        self.log.cycle(k, *args)

    def __getattr__(self, name: str) -> Any:
        return getattr(self.log, name)


@contextmanager
def small_disk(limit: int) -> Iterator[None]:
    """Processes started inside inherit a file-size limit (a write past it fails with
    EFBIG, SIGXFSZ ignored): the writer process sees a full disk."""
    soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
    old = signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    resource.setrlimit(resource.RLIMIT_FSIZE, (limit, hard))
    try:
        yield
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))
        signal.signal(signal.SIGXFSZ, old)


def _controller_times(path: Path) -> list[int]:
    with open_log(path) as log:
        return [t for _, t, _ in log.iter_payloads(["/controller"])]


@pytest.mark.parametrize("timing", ["lockstep", "feedback"])
@pytest.mark.parametrize("fault", ["writer-killed", "disk-full"])
def test_recorder_fault(tmp_path: Path, timing: str, fault: str) -> None:
    lockstep = timing == "lockstep"
    base = matrix_config(tmp_path, timing)
    config = dataclasses.replace(base, loop=dataclasses.replace(base.loop, duration=200.0 if lockstep else 8.0))
    path = tmp_path / "run.mcap"
    if fault == "disk-full":
        with small_disk(150_000):
            log = open_run_log(path, fsync=False)
    else:
        log = open_run_log(path, fsync=False)
    assert log is not None
    hooks = log_hooks(log)
    killer = KillWriterAt(log, after_s=1.5, path=path) if fault == "writer-killed" else None
    if killer is not None:
        hooks["sink"] = killer
    with RunSession(config, emulate=True, lockstep=lockstep, **hooks) as session, \
            Sniffer(session.bus_spec.channel) as sniffer:
        result = record_run(session, log)
        assert result.stop.reason is StopReason.RECORDER_FAILED, result.stop.line()
        assert result.cycles < session.settings.cycles   # stopped early, by the recorder
        assert result.disabled and result.safe_stop is not None and result.safe_stop.warning() == ""
        assert_stopped_safely(session, sniffer, result.stop, StopReason.RECORDER_FAILED,
                              words=("recorder failed",))

    saved = tmp_path / "saved.mcap"
    report = recover(path, saved)
    times = _controller_times(saved)
    assert dict(report.counts).get("/controller", 0) == len(times) > 0
    if killer is not None and not lockstep:   # log time is wall time: what recover lost
        assert killer.killed_ns is not None
        lost = (killer.killed_ns - times[-1]) / 1e9
        bound = FLUSH_SLACK_S + killer.starved_s
        assert lost <= bound, (f"recover lost {lost:.2f} s before the writer died (flush slack "
                               f"{FLUSH_SLACK_S} s + {killer.starved_s:.2f} s waiting for a CPU)")
    if fault == "disk-full":
        assert path.stat().st_size <= 150_000

