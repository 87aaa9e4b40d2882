"""The feedback-rate watch in host timing: it stops a run on a drive that streams slower
than ``loop.period`` (an ODrive left at its factory rate), and leaves alone a drive that
only answers the host (an MIT motor): its replies come as often as the host commands, so
slow replies there measure the host, whose lateness the overruns already count."""

from __future__ import annotations

import re
import time
from types import SimpleNamespace
from typing import Any

import pytest
from hypothesis import assume, example, given, settings
from hypothesis import strategies as st

from dobhil.drives.base import Confirmation, Feedback, SafeStopReport
from dobhil.drives.load import load_profile
from dobhil.drives.registry import drive_class
from dobhil.drives.ticks import MAX_LAG_PERIODS
from dobhil.runtime.loop import ForceLoop, Limits, LoopSettings, Timing, _Halt, _RateWatch
from dobhil.runtime.session import build_controller
from dobhil.runtime.stop import StopReason
from tests.late_sender import catch_up_sends

from .helpers import demo_config

#: the bus stamps of the fake's frames are this many loop periods apart
SPACING = 3
#: cycles of a run the watch must stop: the fake's frames come one per cycle the loop runs,
#: and a busy host skips the deadlines it missed (2 of 30 cycles run, seen under load), so
#: the run lasts until the watch has had its frames; only a bound, the watch stops it first
UNTIL_STOPPED = 5000


class _SlowFrames:
    """A fresh frame at every poll, stamped SPACING periods after the last one."""

    node_id = 1
    notes: tuple[str, ...] = ()

    def __init__(self, streams: bool, period: float) -> None:
        self.feedback_streams = streams
        self.period = period
        self.seq = 0
        self.feedback: Feedback | None = None

    def enable(self, timeout: float | None = None, cancel: Any = None) -> None:
        pass

    def poll(self, timeout: float) -> Feedback:
        self.seq += 1
        stamp = self.seq * SPACING * self.period
        self.feedback = Feedback(stamp, 0.0, 0.0, self.seq, rx_time=stamp)
        return self.feedback

    def send_torque(self, u: float) -> None:
        pass

    def safe_stop(self, cancel: Any = None, planned: bool = False) -> SafeStopReport:
        return SafeStopReport(1, (), Confirmation.CONFIRMED)


def _run(streams: bool, cycles: int = 30) -> Any:
    return _run_drive(_SlowFrames(streams, demo_config().loop.period), cycles)


def _run_drive(drive: _SlowFrames, cycles: int = 30) -> Any:
    config = demo_config("reference.offset=0", "reference.amplitude=0")
    period = config.loop.period
    settings = LoopSettings(period=period, duration=cycles * period, feedback_timeout=1.0,
                            timing=Timing.HOST, limits=Limits(-1.0, 1.0, 10.0))
    loop = ForceLoop(drive=drive,  # type: ignore[arg-type]
                     controller=build_controller(config, load_profile("odrive-0.6")),
                     reference=SimpleNamespace(value=lambda t: 0.0), settings=settings,
                     clock=time.perf_counter)
    return loop.run()


def test_a_streaming_drive_slower_than_the_loop_stops_the_run() -> None:
    result = _run(streams=True, cycles=UNTIL_STOPPED)
    assert result.stop.reason is StopReason.FEEDBACK_TIMEOUT
    assert "come every 3 ms" in result.stop.detail


def test_a_drive_that_only_answers_is_not_blamed_for_the_hosts_pace() -> None:
    result = _run(streams=False, cycles=30)
    assert result.stop.reason is StopReason.DONE, result.stop.line()
    assert result.cycles + result.skipped == 30


@pytest.mark.parametrize(("name", "words"), [
    ("odrive-0.6", ("encoder estimates come every 3 ms", "set <axis>.config.can.encoder_msg_rate_ms = 1 on the drive")),
    ("cia402-emulated", ("TPDOs come every 3 ms", "node 5 answers fewer SYNCs than the host sends")),
])
def test_the_stop_is_in_the_protocols_words(name: str, words: tuple[str, ...]) -> None:
    """What comes late and what to change, as the drive's protocol calls them (the host sends
    a CiA 402 node its SYNC: slow TPDOs are a node that skips SYNCs, not a rate to set)."""
    profile = load_profile(name)
    real = drive_class(profile.protocol)

    class Fake(_SlowFrames):
        @classmethod
        def preflight_probe(cls, p: Any) -> Any:
            return real.preflight_probe(p)

    drive = Fake(True, 1e-3)
    drive.profile = profile   # type: ignore[attr-defined]
    result = _run_drive(drive, UNTIL_STOPPED)
    assert result.stop.reason is StopReason.FEEDBACK_TIMEOUT
    for text in words:
        assert text in result.stop.detail, result.stop.detail
    if profile.protocol != "odrive":
        assert "encoder" not in result.stop.detail


def _sent(ticks: int, keep: int, stalls: list[tuple[float, float]]) -> list[float]:
    """[periods] when the catching-up sender of tests/late_sender.py (5e-3 periods per frame)
    sends every ``keep``-th tick's frame."""
    return [float(t) for t in catch_up_sends(ticks, stalls, 5e-3)[keep - 1::keep]]


def _watched(stamps: list[float]) -> str | None:
    """The rate watch's stop detail over ``stamps`` [periods] (1 ms), one frame per cycle;
    None when it let them all pass."""
    watch = _RateWatch(1e-3)
    try:
        for stamp in stamps:
            watch.frame(stamp * 1e-3, 1)
    except _Halt as halt:
        assert halt.reason is StopReason.FEEDBACK_TIMEOUT
        return halt.detail
    return None


STALLS = st.lists(st.tuples(st.floats(1.0, 390.0), st.floats(0.5, MAX_LAG_PERIODS - 0.5)), max_size=6)


@settings(max_examples=300, deadline=None)
@given(stalls=STALLS)
def test_bursts_of_a_sender_at_the_loop_period_are_not_slow(stalls: list[tuple[float, float]]) -> None:
    """A sender at the loop period that was not scheduled for up to 9.5 periods, up to six
    times, sends what it missed in a burst: one long interval and short ones, never seven
    slow of ten (each slow interval takes a stall of its own)."""
    assert _watched(_sent(400, 1, stalls)) is None


#: stalls one after another: (periods after the previous one ended, length)
PACKED = st.lists(st.tuples(st.floats(0.0, 3.0), st.floats(0.5, MAX_LAG_PERIODS - 0.5)), min_size=2, max_size=12)


def _packed(gaps: list[tuple[float, float]], first: float = 100.0) -> list[tuple[float, float]]:
    stalls, end = [], first
    for gap, length in gaps:
        stalls.append((end + gap, length))
        end += gap + length
    return stalls


@settings(max_examples=300, deadline=None)
@given(gaps=PACKED)
# a stall of 1.7 periods just after each send, every other period: sends at 101.71, 102,
# 103.71, 104 ...: slow and short in turn, 5 of every 10 (a rule of 5 of 10 stops it)
@example(gaps=[(0.01, 1.7)] + [(0.3, 1.7)] * 8)
def test_packed_stalls_of_a_sender_at_the_loop_period_are_not_slow(gaps: list[tuple[float, float]]) -> None:
    """Up to twelve stalls, each within 3 periods of the previous one's end: every long
    interval a stall makes is followed by at least one short one (the frames it held back, or
    the next one due), so at most 5 of any 10 intervals are slow, and the rule's 7 leaves a
    margin; the example is that worst case."""
    sent = _sent(400, 1, _packed(gaps))
    # run_ticks skips ticks further behind than this (left out of the model)
    assume(max(s - n for n, s in enumerate(sent, 1)) <= MAX_LAG_PERIODS)
    assert _watched(sent) is None


@settings(max_examples=300, deadline=None)
@given(keep=st.integers(2, 4), stalls=STALLS)
def test_a_slower_sender_is_found_through_its_bursts(keep: int, stalls: list[tuple[float, float]]) -> None:
    """The same sender keeping every 2nd to 4th frame (a drive streaming slower than the
    loop: row "drive-slower-than-profile" of tests/runtime/test_fault_matrix.py), up to six
    stalls: it is stopped, naming a slow interval's figure."""
    _assert_stopped(_watched(_sent(400, keep, stalls)))


@pytest.mark.parametrize(("every", "length"), [(12, 5.0), (20, 5.0), (40, 9.0)])
def test_a_slower_sender_stalled_again_and_again_is_found(every: int, length: float) -> None:
    """A sender keeping every 4th frame, not scheduled for ``length`` periods every
    ``every``: each stall's burst puts a short interval among the slow ones (1.49 periods,
    or 0.02 and 1.47), so no ten slow intervals come in a row, and a rule that waits for
    them lets the run end; 7 of 10 are slow all the same. The sender keeping every frame,
    stalled alike, is not stopped."""
    stalls = [(every * j + 1.5, length) for j in range(400 // every)]
    _assert_stopped(_watched(_sent(400, 4, stalls)))
    assert _watched(_sent(400, 1, stalls)) is None


def _assert_stopped(detail: str | None) -> None:
    assert detail is not None and re.search(r"\(7 of the last (8|9|10) intervals\)", detail), detail
    every = float(detail.split("come every ")[1].split(" ms")[0])
    assert every > 1.5
