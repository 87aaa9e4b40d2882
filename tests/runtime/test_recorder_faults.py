"""The recorder rows of the fault matrix (``test_fault_matrix.py`` has the runtime's own):
{lockstep, feedback-synchronous real time} x {writer process killed, disk full}.

Each row asserts the stop reason ``recorder_failed`` in one line, that the drive saw zero
torque then IDLE and ended IDLE, and that ``dobhil log recover`` salvages the file (the
writer is gone, so the stop itself cannot be in it); where the log clock is the wall clock (real
time), that what recover loses before the writer died is at most the flush interval (1 s).

Then a writer that takes nothing (stopped by SIGSTOP, as one stuck on a disk that no longer
answers), lockstep and real time: the run still ends -- its safe stop, one stop line, the
warning or the confirmation, the log said unfinished, the writer killed -- within the stall
bound (``STALL_TIMEOUT``), or at once on SIGINT.
"""

from __future__ import annotations

import dataclasses
import os
import re
import resource
import signal
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pytest

from dobhil.cli.main import main
from dobhil.cli.recording import open_run_log, record_run
from dobhil.cli.run_cmd import log_hooks
from dobhil.recording import process
from dobhil.recording.process import STALL_TIMEOUT
from dobhil.recording.reader import open_log
from dobhil.recording.recover import recover
from dobhil.recording.runlog import RunLog
from dobhil.runtime.loop import StopRequest
from dobhil.runtime.session import RunSession
from dobhil.runtime.signals import stop_on_signals
from dobhil.runtime.stop import StopReason

from .helpers import Sniffer, assert_stopped_safely, wait_until, write_profile
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
    # real time: killed past the writer's 1 s flush, so what recover lost is bounded by it
    # (checked below); lockstep checks no time, only a stop and a recoverable file: killed once
    # the file has grown (a chunk reached the OS), without waiting 1.5 s of wall time for it
    after_s = 0.0 if lockstep else 1.5
    killer = KillWriterAt(log, after_s=after_s, path=path) if fault == "writer-killed" else None
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
    held = "/cycle" if open_log(saved).layout == "cycle" else "/controller"   # a cycle message holds one
    assert dict(report.counts).get(held, 0) == len(times) > 0
    if killer is not None and not lockstep:   # log time is wall time: what recover lost
        assert killer.killed_ns is not None
        lost = (killer.killed_ns - times[-1]) / 1e9
        bound = FLUSH_SLACK_S + killer.starved_s
        assert lost <= bound, (f"recover lost {lost:.2f} s before the writer died (flush slack "
                               f"{FLUSH_SLACK_S} s + {killer.starved_s:.2f} s waiting for a CPU)")
    if fault == "disk-full":
        assert path.stat().st_size <= 150_000



# -- a writer that takes nothing: stopped (SIGSTOP), as one stuck on a disk that does not answer --

#: the tests' own bound: the writer's stall bound a few times over (a hand-over, the log's
#: end), with a minute for a loaded machine's start-up; on code that waits for ever the test
#: fails here instead of hanging
FROZEN_TEST_TIMEOUT = int(6 * STALL_TIMEOUT) + 60


#: the writer's stall bound in these tests (``short_stall``): a writer stopped with SIGSTOP
#: shows no life at any load -- it takes nothing from its pipe, and neither runs nor waits for
#: a CPU -- so half a second proves what the shipped STALL_TIMEOUT would, without its seconds
STALL = 0.5


@pytest.fixture
def short_stall(monkeypatch: pytest.MonkeyPatch) -> float:
    monkeypatch.setattr(process, "STALL_TIMEOUT", STALL)
    return STALL


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return True


def _release(pids: list[int]) -> None:
    for pid in pids:
        for sig in (signal.SIGCONT, signal.SIGKILL):
            try:
                os.kill(pid, sig)
            except ProcessLookupError:
                pass


@contextmanager
def never_left_stopped(pids: list[int]) -> Iterator[None]:
    """Whatever the test does, each process in ``pids`` (filled in as they are stopped) is
    continued and killed at the end: a stopped writer is never left behind -- also by code
    that waits for it for ever even after the test's timeout (its cleanup waiting again):
    released then, the test having failed already."""
    rescue = threading.Timer(FROZEN_TEST_TIMEOUT + STALL_TIMEOUT, _release, (pids,))
    rescue.daemon = True
    rescue.start()
    try:
        yield
    finally:
        rescue.cancel()
        _release(pids)


class StopWriterAt:
    """The run's sink (the log), with the writer process stopped (SIGSTOP) at cycle ``at``;
    ``last`` is the monotonic time of the newest cycle (the loop waiting shows as none)."""

    def __init__(self, log: RunLog, at: int, stopped: list[int]) -> None:
        self.log, self.at, self.stopped = log, at, stopped
        self.stopped_at: float | None = None
        self.last = time.monotonic()

    def cycle(self, k: int, *args: Any) -> None:
        self.last = time.monotonic()
        if k >= self.at and self.stopped_at is None:
            pid = self.log.writer_pid
            assert pid is not None
            self.stopped.append(pid)
            os.kill(pid, signal.SIGSTOP)
            self.stopped_at = time.monotonic()
        self.log.cycle(k, *args)

    def __getattr__(self, name: str) -> Any:
        return getattr(self.log, name)


def _lockstep_run(tmp_path: Path) -> tuple[Any, RunLog, Path]:
    base = matrix_config(tmp_path, "lockstep")
    config = dataclasses.replace(base, loop=dataclasses.replace(base.loop, duration=200.0))
    path = tmp_path / "run.mcap"
    log = open_run_log(path, fsync=False)
    assert log is not None
    return config, log, path


def _short_stall_once_ended(session: Any, monkeypatch: pytest.MonkeyPatch) -> None:
    """Once the run's loop has ended -- every wait a SIGINT cuts short is over, the stop
    decided -- the log's end gives a still writer up after STALL s instead of the shipped
    STALL_TIMEOUT (5 s, waited for nothing): the tests that call this check that the writer
    is given up and said so, not the bound (which test_lockstep_writer_stopped_stops_the_run
    checks). Earlier, the shorter bound could fire before the SIGINT a test waits to send."""
    if wait_until(lambda: session.loop is not None and session.loop.ended is not None, FROZEN_TEST_TIMEOUT / 2):
        monkeypatch.setattr(process, "STALL_TIMEOUT", STALL)


@pytest.mark.timeout(FROZEN_TEST_TIMEOUT)
def test_lockstep_writer_stopped_stops_the_run(tmp_path: Path, short_stall: float) -> None:
    """Lockstep waits for the writer (nothing lost), but not for ever: a writer that takes
    nothing for STALL s is killed and the run stops ``recorder_failed`` with the safe
    stop, the drive confirmed disabled; not before that bound (a writer slow for a moment
    loses nothing)."""
    config, log, path = _lockstep_run(tmp_path)
    stopped: list[int] = []
    hooks = log_hooks(log)
    sink = StopWriterAt(log, 50, stopped)
    hooks["sink"] = sink
    with never_left_stopped(stopped):
        with RunSession(config, emulate=True, lockstep=True, **hooks) as session, \
                Sniffer(session.bus_spec.channel) as sniffer:
            result = record_run(session, log)
            waited = time.monotonic() - (sink.stopped_at or 0.0)
            assert_stopped_safely(session, sniffer, result.stop, StopReason.RECORDER_FAILED,
                                  words=(f"took nothing for {STALL:g} s", "dobhil log recover"))
            assert result.cycles < session.settings.cycles
            assert result.disabled and result.safe_stop is not None and result.safe_stop.warning() == ""
        assert waited >= STALL, f"given up after {waited:.2f} s, before its bound"
        assert stopped and wait_until(lambda: not _alive(stopped[0]), 30.0), "the stopped writer was left running"


@pytest.mark.timeout(FROZEN_TEST_TIMEOUT)
def test_lockstep_sigint_while_waiting_for_a_stopped_writer(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A SIGINT while the lockstep loop waits on a stopped writer stops the run at once
    (``signal``, the safe stop), not at the writer's stall bound; the log's end then gives the
    writer up (killed, said once) and the run keeps its own stop."""
    config, log, path = _lockstep_run(tmp_path)
    stopped: list[int] = []
    hooks = log_hooks(log)
    sink = StopWriterAt(log, 50, stopped)
    hooks["sink"] = sink

    def interrupt_when_blocked() -> None:
        # the loop is waiting on the writer: stopped, and no cycle for a while since
        if wait_until(lambda: sink.stopped_at is not None and time.monotonic() - sink.last > 0.5,
                      FROZEN_TEST_TIMEOUT / 2):
            os.kill(os.getpid(), signal.SIGINT)
            _short_stall_once_ended(session, monkeypatch)

    with never_left_stopped(stopped), stop_on_signals(StopRequest()) as request:
        with RunSession(config, emulate=True, lockstep=True, stop_request=request, **hooks) as session, \
                Sniffer(session.bus_spec.channel) as sniffer:
            thread = threading.Thread(target=interrupt_when_blocked, daemon=True)
            thread.start()
            result = record_run(session, log)
            thread.join()
            assert_stopped_safely(session, sniffer, result.stop, StopReason.SIGNAL, words=("SIGINT",))
            assert result.disabled and result.safe_stop is not None and result.safe_stop.warning() == ""
        assert "not finished" in log.end_failure and "dobhil log recover" in log.end_failure, log.end_failure
        assert stopped and wait_until(lambda: not _alive(stopped[0]), 30.0), "the stopped writer was left running"


def _cli_run(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str],
             act: Callable[[Any, RunLog, list[int]], None]) -> tuple[int, str, str, list[int]]:
    """``dobhil run demo --emulate --log`` in real time, in this process; ``act(session, log,
    stopped)`` runs in a thread beside the run (it stops the writer, appending its pid).
    Returns the exit code, stdout, stderr and the pids of the writer and the emulator.

    Tests of the writer, not of timing: a loaded machine can starve a real-time run into
    stopping on its own (``host_too_slow``: the drive's watchdog or the feedback timeout
    expired while the host was not scheduled) before ``act`` has done anything. So nothing
    starvation trips is armed: no drive watchdog, no feedback timeout shorter than the run;
    a killed emulated drive still ends the run at once (its bus end closes)."""
    import dobhil.cli.recording as recording
    real = recording.record_run
    pids: list[int] = []
    stopped: list[int] = []

    def record_run_beside(session: Any, log: RunLog | None, *args: Any, **kwargs: Any) -> Any:
        assert log is not None and log.writer_pid is not None
        pids.extend([log.writer_pid, session.emulator.pid])
        threading.Thread(target=act, args=(session, log, stopped), daemon=True).start()
        return real(session, log, *args, **kwargs)

    monkeypatch.setattr(recording, "record_run", record_run_beside)
    with never_left_stopped(stopped):
        profile = write_profile(tmp_path, "odrive-0.6", watchdog_timeout=0)
        code = main(["run", "demo", "--emulate", "--duration", "30", "--log", str(tmp_path / "run.mcap"),
                     "--set", f"drive.profile={profile}", "--set", "loop.feedback_timeout=30"])
        out, err = capsys.readouterr()
        assert pids and wait_until(lambda: not any(map(_alive, pids)), 30.0), "a process was left running"
    return code, out, err, pids


def _running(session: Any) -> bool:
    """The loop has run cycles (or has already ended)."""
    loop = getattr(session, "loop", None)
    return loop is not None and (loop.ended is not None or loop.trace.last > 100)


def _stop_writer_until_full(session: Any, log: RunLog, stopped: list[int]) -> bool:
    """Once the loop runs, the writer stopped until its pipe is full (the run drops a batch:
    the log's end then has more to hand over than the pipe takes). False if the run ended
    before either."""
    if not wait_until(lambda: _running(session), FROZEN_TEST_TIMEOUT / 2) or session.loop.ended is not None:
        return False
    assert log.writer_pid is not None
    stopped.append(log.writer_pid)
    os.kill(log.writer_pid, signal.SIGSTOP)
    return wait_until(lambda: log.writer.dropped > 0 or session.loop.ended is not None,
                      FROZEN_TEST_TIMEOUT / 2) and session.loop.ended is None


@pytest.mark.timeout(FROZEN_TEST_TIMEOUT)
def test_realtime_writer_stopped_then_emulator_killed(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                      capsys: pytest.CaptureFixture[str], short_stall: float) -> None:
    """The audit's run: the writer stopped, then the emulated drive killed. The run stops
    and safe-stops as ever; its log's end gives the stopped writer up after STALL s
    (killed): one stop line (the run's own reason), the loud warning, one line saying the log
    is not finished and how to recover it, exit 1."""
    def act(session: Any, log: RunLog, stopped: list[int]) -> None:
        if _stop_writer_until_full(session, log, stopped):
            os.kill(session.emulator.pid, signal.SIGKILL)

    code, out, err, _ = _cli_run(tmp_path, monkeypatch, capsys, act)
    text = out + err
    assert code == 1, text
    assert len(re.findall(r"^(dobhil run: )?stopped: ", text, re.M)) == 1, text
    assert "stopped: recorder_failed" not in text, text   # the run's own reason: the drive was lost
    assert "WARNING: drive may still be enabled" in err, text
    lines = [line for line in err.splitlines() if "not finished" in line]
    assert len(lines) == 1 and f"nothing for {STALL:g} s (stopped" in lines[0], text
    assert "dobhil log recover" in lines[0], text


@pytest.mark.timeout(FROZEN_TEST_TIMEOUT)
def test_realtime_sigint_cuts_the_wait_for_a_stopped_writer_short(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    """A real-time run whose writer is stopped, ended by SIGINT, then a second SIGINT while
    its log's end waits for the writer: the wait ends there (not at STALL_TIMEOUT), the
    writer is killed, the log is said not finished, the drive confirmed disabled, exit 1."""
    def act(session: Any, log: RunLog, stopped: list[int]) -> None:
        if not _stop_writer_until_full(session, log, stopped):
            return
        os.kill(os.getpid(), signal.SIGINT)   # the run stops
        # the log's end has begun (the log closed: no writer pid to give) and waits for the writer
        if wait_until(lambda: log.writer_pid is None, FROZEN_TEST_TIMEOUT / 2):
            time.sleep(STALL_TIMEOUT / 10)
            os.kill(os.getpid(), signal.SIGINT)

    code, out, err, _ = _cli_run(tmp_path, monkeypatch, capsys, act)
    text = out + err
    assert code == 1, text
    assert len(re.findall(r"^(dobhil run: )?stopped: ", text, re.M)) == 1, text
    assert "stopped: signal" in text, text
    assert "WARNING" not in err, text
    lines = [line for line in err.splitlines() if "not finished" in line]
    assert len(lines) == 1 and "stopped waiting for the writer process (received SIGINT)" in lines[0], text


def _pipe_still(log: Any) -> Callable[[], bool]:
    """A condition: the bytes waiting in the log writer's pipe have not moved for half a
    second (the writer stopped, the loop waiting for room)."""
    last = [-1.0, time.monotonic()]

    def still() -> bool:
        n = log.writer.queued()
        if n != last[0]:
            last[:] = [n, time.monotonic()]
            return False
        return n > 0 and time.monotonic() - last[1] > 0.5
    return still


@pytest.mark.timeout(FROZEN_TEST_TIMEOUT)
def test_axes_lockstep_sigint_while_waiting_for_a_stopped_writer(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    """A several-axis lockstep run (one writer for every axis) waiting on its stopped writer
    answers SIGINT: the ``signal`` stop line, once, the log said unfinished in one line, the
    writer killed, exit 1."""
    import dobhil.cli.axes_run as axes_run
    real = axes_run.record_axes
    stopped: list[int] = []

    def record_axes_beside(session: Any, log: Any, *args: Any, **kwargs: Any) -> Any:
        def act() -> None:
            if not wait_until(lambda: log.writer.opened, FROZEN_TEST_TIMEOUT / 2):
                return
            stopped.append(log.writer_pid)
            os.kill(log.writer_pid, signal.SIGSTOP)
            if wait_until(_pipe_still(log), FROZEN_TEST_TIMEOUT / 2):
                os.kill(os.getpid(), signal.SIGINT)
                _short_stall_once_ended(session, monkeypatch)
        threading.Thread(target=act, daemon=True).start()
        return real(session, log, *args, **kwargs)

    monkeypatch.setattr(axes_run, "record_axes", record_axes_beside)
    config = Path(__file__).resolve().parents[2] / "configs" / "two-axis-demo.yaml"
    with never_left_stopped(stopped):
        code = main(["run", str(config), "--emulate", "--lockstep", "--duration", "300",
                     "--log", str(tmp_path / "run.mcap")])
        out, err = capsys.readouterr()
        assert stopped and wait_until(lambda: not _alive(stopped[0]), 30.0), "the stopped writer was left running"
    text = out + err
    assert code == 1, text
    assert len(re.findall(r"^(dobhil run: )?stopped: ", text, re.M)) == 1, text
    assert "stopped: signal" in text and "received SIGINT" in text, text
    assert "WARNING" not in err, text
    lines = [line for line in err.splitlines() if "not finished" in line]
    assert len(lines) == 1 and f"nothing for {STALL:g} s (stopped" in lines[0], text   # the bound then in force
