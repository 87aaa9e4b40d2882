"""What the loop holds and leaves behind: a trace bounded whatever the duration
(decimated, the newest cycle always kept), timing statistics in fixed memory, the
garbage collector restored after a real-time run, no enable after an early stop
request, and host timing (deadlines, sleep-then-spin) against the emulator."""

from __future__ import annotations

import gc
import math
import re
from pathlib import Path

import numpy as np
import pytest

from dobhil.drives.odrive.codec import Firmware
from dobhil.runtime.loop import (REMOVED_IN, TRACE_ROWS, ForceLoop, Histogram, StopRequest, Timing, Trace,
                                 _QuietGc)
from dobhil.runtime.session import RunSession
from dobhil.runtime.stop import StopReason

from .helpers import (REALTIME_SLACK, REPO, STEP_FROM_ZERO, Sniffer, demo_config, finite_tail,
                      realtime_profile)


def test_trace_keeps_every_cycle_of_a_short_run() -> None:
    trace = Trace(10, max_rows=16)
    for k in range(10):
        trace.data["t"][trace.row(k)] = k
    assert trace.stride == 1 and trace["t"].tolist() == list(range(10))


def test_finite_tail_is_made_of_cycles_that_ran() -> None:
    """The tests' steady-state tail: the last 100 ms of a 1 kHz trace; when the host was
    not scheduled for those 100 ms (NaN rows, one cycle at the end), its last 10 cycles
    that ran instead of the one the window holds."""
    t = np.arange(1000) * 1e-3
    values = 1.0 + t
    assert finite_tail(values, t, 0.1).tolist() == values[-101:].tolist()
    starved = np.where((t > 0.85) & (t < 0.999), np.nan, values)
    t_run = np.where(np.isnan(starved), np.nan, t)
    tail = finite_tail(starved, t_run, 0.1)
    assert tail.tolist() == [*values[842:851].tolist(), values[-1]]


def test_trace_decimates_a_long_run_and_keeps_the_newest() -> None:
    """1000 cycles into 16 rows: stride 64, rows spread over the whole run, the newest
    cycle still readable."""
    trace = Trace(1000, max_rows=16)
    assert all(v.size == 17 for v in trace.data.values())
    for k in range(1000):
        r = trace.row(k)
        trace.data["t"][r] = k
        trace.last = r
    t = trace["t"]
    assert trace.stride == 64 and t.size <= 16
    np.testing.assert_array_equal(t, np.arange(0, 1000, 64))
    assert trace.latest("t") == 999.0


def test_trace_keeps_skipped_rows_nan_through_decimation() -> None:
    trace = Trace(100, max_rows=8)
    for k in range(0, 100, 3):    # only every third cycle ran
        trace.data["t"][trace.row(k)] = k
    t = trace["t"]
    kept = np.arange(t.size) * trace.stride
    np.testing.assert_array_equal(np.isfinite(t), kept % 3 == 0)
    np.testing.assert_array_equal(t[np.isfinite(t)], kept[kept % 3 == 0])


def test_a_ten_hour_run_allocates_a_bounded_trace() -> None:
    """10 h at 1 kHz is 36e6 cycles: the trace and the timing histograms stay a few MB."""
    config = demo_config("loop.duration=36000")
    with RunSession(config, emulate=True, lockstep=True) as session:
        loop = ForceLoop(drive=session.drive, controller=session.controller,
                         reference=session.reference, settings=session.settings)
    nbytes = sum(v.nbytes for v in loop.trace.data.values())
    assert loop.settings.cycles == 36_000_000
    assert loop.trace.capacity == TRACE_ROWS and nbytes < 20e6
    assert len(loop.exec_time.counts) == Histogram.BINS


def test_histogram_percentiles() -> None:
    h = Histogram()
    for us in range(1, 101):
        h.add(us * 1e-6)
    h.add(0.5)   # beyond the last bin: counted there, the max is exact
    assert h.n == 101 and h.max == 0.5
    assert h.percentile(50) == pytest.approx(51e-6, abs=1e-6)    # 1 us bins
    assert h.percentile(99) == pytest.approx(100e-6, abs=1e-6)
    assert h.percentile(100) == 0.5
    assert Histogram().percentile(99) == 0.0


def test_lockstep_stats_come_from_the_histograms() -> None:
    config = demo_config("loop.duration=0.2")
    with RunSession(config, emulate=True, lockstep=True) as session:
        result = session.run()
    assert result.cycles == 200 and result.skipped == 0 and result.overruns == 0
    timing = result.timing
    assert timing.period_error_max == 0.0 and timing.latency_max == 0.0
    assert 0 < timing.exec_time_p50 <= timing.exec_time_p99 <= timing.exec_time_max


class GcProbe:
    """A sink noting the collector's state during the cycles."""

    def __init__(self) -> None:
        self.seen: list[tuple[bool, int]] = []

    def started(self, fb: object) -> None:
        pass

    def cycle(self, k: int, *args: object) -> None:
        if k % 50 == 0:
            self.seen.append((gc.isenabled(), gc.get_freeze_count()))

    def stop(self, stop: object) -> None:
        pass


def test_gc_is_off_during_the_cycles_and_restored_after(tmp_path: Path) -> None:
    profile = realtime_profile(tmp_path, "odrive-0.6")
    config = demo_config(f"drive.profile={profile}", *REALTIME_SLACK, "loop.duration=0.2")
    assert gc.isenabled() and gc.get_freeze_count() == 0
    probe = GcProbe()
    with RunSession(config, emulate=True, lockstep=False, sink=probe) as session:  # type: ignore[arg-type]
        assert session.timing is Timing.FEEDBACK
        result = session.run()
    assert result.stop.reason is StopReason.DONE, result.stop.line()
    assert probe.seen and all(not on and frozen > 0 for on, frozen in probe.seen)
    assert gc.isenabled() and gc.get_freeze_count() == 0
    assert result.timing.latency_max > 0   # frame received -> command sent, measured
    assert np.nanmax(result.trace["latency"]) > 0


def test_a_stop_request_before_the_start_never_enables(tmp_path: Path) -> None:
    """SIGINT before the loop starts (e.g. while the bus opens): no enable frame at all."""
    request = StopRequest()
    request.set("received SIGINT")
    with RunSession(demo_config(), emulate=True, lockstep=True,
                    stop_request=request) as session, Sniffer(session.bus_spec.channel) as sniffer:
        result = session.run()
        sent = sniffer.host_commands(Firmware.V0_6)
    assert result.stop.reason is StopReason.SIGNAL and result.stop.cycle == -1
    assert result.cycles == 0
    assert 8 not in sent.axis_states   # never asked for CLOSED_LOOP_CONTROL


@pytest.mark.parametrize("spin", ["0", "2e-4"])
def test_host_timing_reaches_the_reference(tmp_path: Path, spin: str) -> None:
    """Host-clock deadlines (sleep only, and sleep-then-spin) against the real-time
    emulator: the loop reaches its force reference; cycles run plus deadlines skipped
    is the run's length."""
    profile = realtime_profile(tmp_path, "odrive-0.6")
    config = demo_config(f"drive.profile={profile}", *REALTIME_SLACK, *STEP_FROM_ZERO,
                         "loop.duration=0.5", "loop.timing=host", f"loop.spin={spin}")
    with RunSession(config, emulate=True) as session:
        assert session.timing is Timing.HOST
        result = session.run()
    assert result.stop.reason is StopReason.DONE, result.stop.line()
    assert result.cycles + result.skipped == 500
    tail = finite_tail(result.trace["tau_int_true"], result.trace["t"], 0.1)
    assert tail.size >= 10 and abs(float(np.mean(tail)) - 1.0) < 0.03
    assert math.isfinite(result.timing.period_error_p99)


def test_realtime_is_the_old_name_of_host_and_warns() -> None:
    config = demo_config("loop.timing=realtime")
    with pytest.warns(FutureWarning) as caught, RunSession(config, emulate=True) as session:
        assert session.timing is Timing.HOST
    assert [str(w.message) for w in caught] == [
        f"loop.timing: realtime is deprecated, use loop.timing: host (removed in dobhil {REMOVED_IN})"]
    with pytest.warns(DeprecationWarning) as caught:
        assert Timing.REALTIME is Timing.HOST
    assert [str(w.message) for w in caught] == [
        f"Timing.REALTIME is deprecated, use Timing.HOST (removed in dobhil {REMOVED_IN})"]
    assert "REALTIME" not in Timing.__members__ and str(Timing.HOST) == "1" and Timing.HOST.name == "HOST"


def test_the_command_line_shows_the_old_name_warning_as_one_line(capsys: pytest.CaptureFixture[str]) -> None:
    from dobhil.cli.main import main
    main(["run", str(REPO / "configs/demo.yaml"), "--emulate", "--set", "loop.timing=realtime",
          "--set", "loop.duration=0.02"])
    err = capsys.readouterr().err.splitlines()
    assert err[0] == ("dobhil: warning: loop.timing: realtime is deprecated, use loop.timing: host "
                      f"(removed in dobhil {REMOVED_IN})")
    assert not any("FutureWarning" in line or "session.py" in line for line in err)


def test_old_names_are_removed_in_the_next_minor_release() -> None:
    version = re.search(r'^version = "([^"]+)"', (REPO / "pyproject.toml").read_text(), re.M)
    assert version is not None
    major, minor, *_ = version[1].split(".")
    assert REMOVED_IN == f"{major}.{int(minor) + 1}"
    # the key table (dobhil/config/schema.py, below the runtime) says the same release
    assert f"deprecated, removed in dobhil {REMOVED_IN}" in (REPO / "docs/config.md").read_text()


def test_feedback_timing_needs_one_frame_per_period(tmp_path: Path) -> None:
    from dobhil.errors import ConfigError
    profile = realtime_profile(tmp_path, "odrive-0.6", feedback_period=5e-4)
    with pytest.raises(ConfigError, match="loop.timing: host"):
        RunSession(demo_config(f"drive.profile={profile}", "loop.timing=feedback"), emulate=True)


def test_young_generation_is_collected_between_cycles_only_with_time_left() -> None:
    quiet = _QuietGc()
    was = gc.isenabled()
    gc.disable()
    try:
        young = [[i] for i in range(2 * gc.get_threshold()[0])]   # alive: counted
        before = gc.get_count()[0]
        quiet.between_cycles(slack=0.0, period=1e-3)          # no time left: not now
        assert quiet.collections == 0 and gc.get_count()[0] >= before
        quiet.between_cycles(slack=0.5e-3, period=1e-3)       # half a period left: now
        assert quiet.collections == 1 and gc.get_count()[0] < before
        hoard = [[i] for i in range((_QuietGc.HARD + 1) * gc.get_threshold()[0])]
        quiet.between_cycles(slack=0.0, period=1e-3)          # past the bound: anyway
        assert quiet.collections == 2
        del hoard, young
    finally:
        if was:
            gc.enable()


def test_any_duration_is_accepted_or_one_config_error() -> None:
    """Property: every float as ``--duration`` either makes a session whose cycle count
    is a positive integer, or a ConfigError; never another exception."""
    hypothesis = pytest.importorskip("hypothesis")
    from hypothesis import strategies as st

    from dobhil.errors import ConfigError
    config = demo_config()

    @hypothesis.settings(max_examples=60, deadline=None, derandomize=True)
    @hypothesis.given(st.floats(allow_nan=True, allow_infinity=True))
    def check(duration: float) -> None:
        try:
            session = RunSession(config, emulate=True, lockstep=True, duration=duration)
        except ConfigError as exc:
            assert "\n" not in str(exc)
            return
        with session:
            assert math.isfinite(duration) and duration > 0
            assert session.settings.cycles >= 1

    check()
