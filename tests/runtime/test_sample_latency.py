"""The drive's sample instant -> its feedback received (``Feedback.sampled_at``): kept per
cycle (trace, histogram, cycle record, summary) where measured; and ``loop.timing:
feedback`` refused for a drive whose feedback does not stream."""

from __future__ import annotations

import math
import time
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from dobhil.cli.main import main
from dobhil.cli.run_cmd import report
from dobhil.drives.base import Confirmation, Feedback, SafeStopReport
from dobhil.drives.odrive.drive import ODriveDrive
from dobhil.drives.load import load_profile
from dobhil.errors import ConfigError
from dobhil.runtime.loop import ForceLoop, Limits, LoopSettings, Timing
from dobhil.runtime.session import RunSession, build_controller, summary

from .helpers import demo_config

#: the sample ages the fake drive reports, in turn [s]
AGES = (100e-6, 200e-6, 300e-6, 250e-6)


class _SamplingDrive:
    """A drive whose every feedback says when it was sampled: ``AGES[k % 4]`` before the
    bus stamped its frame (``sampled_at`` NaN every fifth: unknown, not counted)."""

    node_id = 1
    notes: tuple[str, ...] = ()   # start-up notes (Drive.notes): none
    feedback_streams = True       # Drive.feedback_streams: a frame every period (lockstep reads it)

    def __init__(self) -> None:
        self.seq = 0
        self.feedback: Feedback | None = None
        self.ages: list[float] = []

    def enable(self, timeout: float | None = None, cancel: Any = None) -> None:
        pass

    def poll(self, timeout: float) -> Feedback:
        self.seq += 1
        rx = time.time()
        age = AGES[self.seq % len(AGES)] if self.seq % 5 else math.nan
        sampled = rx - age
        self.ages.append(rx - sampled)   # the age as float stamps near 1.7e9 s hold it (0.24 us steps)
        self.feedback = Feedback(self.seq * 1e-3, 0.0, 0.0, self.seq, rx_time=rx, sampled_at=sampled)
        return self.feedback

    def send_torque(self, u: float) -> None:
        pass

    def safe_stop(self, cancel: Any = None, planned: bool = False) -> SafeStopReport:
        return SafeStopReport(1, (), Confirmation.CONFIRMED)


def _loop(timing: Timing, cycles: int = 40) -> tuple[ForceLoop, _SamplingDrive]:
    config = demo_config("reference.offset=0", "reference.amplitude=0")
    period = config.loop.period
    steps = [0]

    def sim() -> float:   # lockstep: a simulated clock that advances per read
        steps[0] += 1
        return steps[0] * period

    clock = time.perf_counter if timing is Timing.HOST else sim
    drive = _SamplingDrive()
    settings = LoopSettings(period=period, duration=cycles * period, feedback_timeout=1.0, timing=timing,
                            limits=Limits(-1.0, 1.0, 10.0))
    loop = ForceLoop(drive=drive, controller=build_controller(config, load_profile("odrive-0.6")),  # type: ignore[arg-type]
                     reference=SimpleNamespace(value=lambda t: 0.0), settings=settings, clock=clock)
    return loop, drive


def test_a_timed_loop_keeps_each_cycles_sample_latency() -> None:
    loop, drive = _loop(Timing.HOST)
    result = loop.run()
    assert result.stop.reason.name == "DONE" and result.cycles > 0   # fewer than 40 when deadlines were skipped
    ran = np.isfinite(result.trace["t"])
    column = result.trace["sample_latency"][ran]
    # each cycle used the feedback of the one poll at its start (the first poll: the enable's)
    used = np.array(drive.ages[1:])
    assert used.size == result.cycles == column.size
    np.testing.assert_array_equal(column, used)
    assert np.isnan(column).sum() == np.isnan(used).sum()
    assert np.isnan(used).any() or used.size < 4   # every fifth poll had no sample instant
    t = result.timing
    finite = used[np.isfinite(used)]
    # the histogram's 1 us bins, nearest rank
    assert t.sample_latency_p50 == pytest.approx(np.percentile(finite, 50, method="inverted_cdf"), abs=1.5e-6)
    assert t.sample_latency_p99 == pytest.approx(np.percentile(finite, 99, method="inverted_cdf"), abs=1.5e-6)
    assert t.sample_latency_max == pytest.approx(finite.max(), abs=1e-9)
    info = summary(SimpleNamespace(timing=Timing.HOST, settings=loop.settings,  # type: ignore[arg-type]
                                   config=demo_config(), bus_spec=SimpleNamespace(describe=lambda: "fake"),
                                   emulator=None, drive=drive,
                                   preflight_report=None), result)
    assert info["sample_latency_us"]["p99"] == pytest.approx(t.sample_latency_p99 * 1e6)
    assert info["loop_timing"]["sample_latency_p50"] == t.sample_latency_p50


def test_lockstep_leaves_it_unmeasured() -> None:
    """Simulated SYNC stamps against wall-clock frame stamps say nothing: NaN, and the
    summary has no sample latency at all."""
    loop, _ = _loop(Timing.LOCKSTEP)
    result = loop.run()
    assert result.cycles == 40 and np.isnan(result.trace["sample_latency"]).all()
    assert result.timing.sample_latency_p99 is None


def test_odrive_runs_have_none_in_their_summary(capsys: pytest.CaptureFixture[str]) -> None:
    with RunSession(demo_config("loop.duration=0.05"), emulate=True, lockstep=True) as session:
        result = session.run()
        info = summary(session, result)
    assert "sample_latency_us" not in info
    assert not [k for k in info["loop_timing"] if k.startswith("sample_latency")]
    report(info, result.stop.line(), as_json=False)
    assert "sample latency" not in capsys.readouterr().out
    report({**info, "sample_latency_us": {"p50": 180.4, "p99": 310.0, "max": 402.0}}, result.stop.line(),
           as_json=False)
    assert "sample latency: p50 180 us, p99 310 us, max 402 us" in capsys.readouterr().out


def test_the_feedback_property() -> None:
    assert math.isnan(Feedback(0.0, 0.0, 0.0, 1).sample_latency)
    assert Feedback(0.0, 0.0, 0.0, 1, rx_time=10.5, sampled_at=10.25).sample_latency == 0.25


def test_feedback_timing_is_refused_for_a_drive_that_does_not_stream(
        monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    monkeypatch.setattr(ODriveDrive, "feedback_streams", property(lambda self: False))
    with pytest.raises(ConfigError, match=r"set loop\.timing: host$") as raised:
        RunSession(demo_config("loop.timing=feedback"), emulate=True)
    assert "\n" not in str(raised.value)
    # host and lockstep timing do not follow the stream: they run
    with RunSession(demo_config("loop.timing=host"), emulate=True) as session:
        assert session.timing is Timing.HOST
    assert main(["run", "demo", "--emulate", "--set", "loop.timing=feedback", "--duration", "0.05"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "loop.timing: host" in err[0], err
