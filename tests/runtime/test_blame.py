"""Who is to blame when a drive's watch on the host expires: real time, every protocol.

A drive that watches the host -- an ODrive's watchdog on its setpoints, a CiA 402 node's
heartbeat consumer (0x1016), an MIT motor's command timeout -- faults when the host's
frames stop, whoever stopped them. The loop measures its own lateness (the gaps between
the commands it sent): a fault of that kind after a gap long enough to starve the watch
is ``host_too_slow`` with the gap in its detail; the same fault with the host on time
(its frames lost on the way) stays ``drive_fault``.

Host lateness is injected: the loop's own thread stalls in the cycle sink (called right
after a command went out) until the emulated drive says its watch fired, or, across
processes, the ``dobhil run`` process is stopped (SIGSTOP) until then. Every bound is
what the run or the stall measured, never a wall-clock constant.
"""

from __future__ import annotations

import json
import math
import os
import re
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import can
import pytest
import yaml
from hypothesis import example, given, settings
from hypothesis import strategies as st

from dobhil.cli.run_cmd import LOCKSTEP_HINT, report, stop_hint
from dobhil.config import Config, load_config
from dobhil.drives.cia402.codec import Cob
from dobhil.drives.odrive import codec
from dobhil.drives.odrive.codec import CmdId
from dobhil.emulator.faults import FaultyBus, LoseSent, faulty
from dobhil.runtime.loop import RunResult, _CommandGaps
from dobhil.runtime.session import RunSession, summary
from dobhil.runtime.stop import StopReason

from .helpers import DEMO, DRIVERS, NODE, REPO, STEP_FROM_ZERO, damiao_with_timeout, demo_config, wait_until, \
    write_profile
from .hub import child_env, hub_process, stop_process, wait_for_emulator
from .test_cross_process import start_emulate
from .test_safety import Recorder

TORQUE_ID = codec.arbitration_id(NODE, CmdId.SET_INPUT_TORQUE)
#: "no command from the host for N ms" in a host_too_slow detail
GAP = re.compile(r"no command from the host for (\d+) ms")
#: how long a stall waits for the drive's watch at most: a bound, not a measurement
WATCH_BOUND = 30.0
#: runs of a check that must not be starved at most: a run the machine starved says so
#: (``host_too_slow``) and is made again (the rule of tests/drives/test_drive_suite.py)
STARVED_RUNS = 3
#: a feedback timeout five times the drives' watches here: on a machine loaded enough to
#: starve the emulated drive for half of it (a host_too_slow of another kind), nothing
#: here would be measured
SLACK = ("loop.feedback_timeout=0.5",)


class Stall:
    """A cycle sink action: stall the loop's thread (right after it sent a command) until
    ``fired()`` says the drive's watch expired; ``seconds``: how long it stalled."""

    def __init__(self, fired: Callable[[], bool]) -> None:
        self.fired = fired
        self.seconds = math.nan
        self.expired = False

    def __call__(self) -> None:
        begin = time.perf_counter()
        self.expired = wait_until(self.fired, WATCH_BOUND)
        self.seconds = time.perf_counter() - begin


def emulated(session: RunSession) -> Any:
    emulator = session.emulator
    assert emulator is not None and getattr(emulator, "pid", None) is not None   # a process of its own
    return emulator


def run_stalled(config: Config, *, at: int = 100, wrapper: Any = None) -> tuple[RunResult, Stall, dict[str, Any]]:
    """A real-time emulated run whose loop stalls after cycle ``at`` until the drive's
    watch fires: its result, the stall, its ``--summary-json`` object."""
    sink = Recorder(at=at)
    with RunSession(config, emulate=True, lockstep=False, sink=sink, bus_wrapper=wrapper) as session:
        emulator = emulated(session)
        stall = Stall(lambda: bool(emulator.watchdog_tripped))
        sink.action = stall
        result = session.run()
        tripped = bool(emulator.watchdog_tripped)
        info = summary(session, result)
    assert stall.expired, "the drive's watch never fired during the stall"
    assert tripped
    return result, stall, info


def assert_host_blamed(result: RunResult, stall: Stall, allows: str) -> None:
    """host_too_slow, naming the drive's fault and watch, with a gap at least the stall."""
    line = result.stop.line()
    assert result.stop.reason is StopReason.HOST_TOO_SLOW, line
    assert "the host was late, not the drive" in line and allows in line, line
    found = GAP.search(line)
    assert found is not None, line
    # the gap spans the stall (the command before it, the first after it), rounded to ms
    assert int(found.group(1)) >= math.floor(stall.seconds * 1e3), (line, stall.seconds)
    assert result.disabled, result.safe_stop


# -- ODrive: the watchdog on the setpoints ---------------------------------------------------

def odrive_config(tmp_path: Path, *overrides: str) -> Config:
    profile = write_profile(tmp_path, "odrive-0.6", watchdog_timeout=0.1, enable_timeout=2.0)
    return demo_config(f"drive.profile={profile}", *STEP_FROM_ZERO, "loop.duration=3", *SLACK,
                       *overrides)


def test_odrive_watchdog_after_a_late_host_is_the_host(tmp_path: Path) -> None:
    """The loop stalls after cycle 100 until the emulated ODrive's watchdog (100 ms) has
    expired: WATCHDOG_TIMER_EXPIRED reaches the host, and the stop says the host was late,
    by at least as long as it stalled."""
    result, stall, _ = run_stalled(odrive_config(tmp_path))
    assert "WATCHDOG_TIMER_EXPIRED" in result.stop.detail
    assert_host_blamed(result, stall, "the drive's watchdog allows 100 ms")


def test_odrive_watchdog_with_the_host_on_time_is_the_drive(tmp_path: Path) -> None:
    """The same watchdog expiry with the host on time: its setpoints are lost on the way
    after 100 of them (the host's sends succeed). The drive is blamed, and the stop says
    the host's longest gap between commands, shorter than the watchdog."""
    lose = LoseSent(frames=100, ids={TORQUE_ID})
    with RunSession(odrive_config(tmp_path), emulate=True, lockstep=False, bus_wrapper=faulty(lose)) as session:
        emulator = emulated(session)
        result = session.run()
        tripped = bool(emulator.watchdog_tripped)
    line = result.stop.line()
    assert result.stop.reason is StopReason.DRIVE_FAULT, line
    assert tripped and lose.applied > 0
    longest = re.search(r"longest gap between commands of the run was ([0-9.]+) ms", line)
    assert longest is not None and "the host was on time" in line, line
    assert float(longest.group(1)) < 100.0


# -- CiA 402: the heartbeat consumer (0x1016) -------------------------------------------------

class ThreadPeriodicBus(can.BusABC):
    """A bus whose periodic sends are python-can's thread in this process (as on
    python-can-remote): the CiA 402 drive then sends the SYNC and its heartbeat with its
    torque frames, so a late host starves the node's heartbeat consumer."""

    def __init__(self, inner: can.BusABC) -> None:
        super().__init__(channel=inner.channel_info)
        self.inner = inner
        self.channel_info = f"threaded periodic over {inner.channel_info}"

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self.inner.send(msg, timeout)

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        return self.inner.recv(timeout), False


def cia402_config(tmp_path: Path, consumer: float) -> Config:
    data = yaml.safe_load((DRIVERS / "cia402-emulated.yaml").read_text(encoding="utf-8"))
    data["cia402"].update(consumer_heartbeat=consumer, eds=str(DRIVERS / "cia402-emulated.eds"))
    data["bus"] = {}
    profile = tmp_path / "cia402-consumer.yaml"
    profile.write_text(yaml.safe_dump(data), encoding="utf-8")
    return load_config(REPO / "configs" / "cia402-demo.yaml",
                       [f"drive.profile={profile}", "loop.timing=host", "loop.duration=3", *SLACK])


def test_cia402_heartbeat_consumer_after_a_late_host_is_the_host(tmp_path: Path) -> None:
    """The node watches the host's heartbeat (100 ms), which this process sends with its
    torque frames: the loop stalls until the node's consumer fired (EMCY 0x8130). The
    host was late, not the drive."""
    result, stall, _ = run_stalled(cia402_config(tmp_path, 0.1), wrapper=ThreadPeriodicBus)
    assert "0x8130" in result.stop.detail
    assert_host_blamed(result, stall, "the drive's heartbeat consumer (0x1016) allows 100 ms, fed every 25 ms")


def test_cia402_heartbeat_consumer_with_the_host_on_time_is_the_drive(tmp_path: Path) -> None:
    """The host's heartbeats are lost on the way after 20 of them, its torque frames go on
    time: the node's consumer fires, and the drive (its bus) is blamed, not the host."""
    config = cia402_config(tmp_path, 0.1)
    lose = LoseSent(frames=20, ids={Cob.HEARTBEAT + 127})

    def wrap(bus: can.BusABC) -> can.BusABC:
        return FaultyBus(ThreadPeriodicBus(bus), [lose], owns_inner=True)

    with RunSession(config, emulate=True, lockstep=False, bus_wrapper=wrap) as session:
        result = session.run()
    line = result.stop.line()
    assert result.stop.reason is StopReason.DRIVE_FAULT, line
    assert "0x8130" in line and "the host was on time" in line, line
    assert lose.applied > 0


def test_cia402_native_host_heartbeat_is_never_the_loops_lateness(tmp_path: Path) -> None:
    """Sent natively (here by the emulator's process, on SocketCAN by the kernel), the
    host's heartbeat does not depend on the loop: the drive watches nothing the loop's
    lateness can starve."""
    with RunSession(cia402_config(tmp_path, 0.1), emulate=True, lockstep=False) as session:
        assert session.drive.host_watch is None
    with RunSession(cia402_config(tmp_path, 0.1), emulate=True, lockstep=False,
                    bus_wrapper=ThreadPeriodicBus) as session:
        watch = session.drive.host_watch
        assert watch is not None and watch.timeout == 0.1 and watch.starving_gap == 0.1 - watch.fed_every


# -- MIT: the command timeout -----------------------------------------------------------------

def mit_config(tmp_path: Path, timeout: float) -> Config:
    """configs/mit-demo.yaml on a DM4310 whose model row has a command timeout (a Damiao
    says it fired with state 0xD, communication lost)."""
    profile = damiao_with_timeout(tmp_path, timeout)
    return load_config(REPO / "configs" / "mit-demo.yaml",
                       [f"drive.profile={profile}", "loop.duration=3", *SLACK,
                        "plant.initial_position=0", "reference.offset=0", "reference.start=0"])


def test_mit_command_timeout_after_a_late_host_is_the_host(tmp_path: Path) -> None:
    """The loop stalls until the motor's command timeout (100 ms) took it out of motor
    mode; its reply to the next command says communication lost. The host was late."""
    result, stall, _ = run_stalled(mit_config(tmp_path, 0.1))
    assert "communication lost" in result.stop.detail
    assert_host_blamed(result, stall, "the drive's command timeout allows 100 ms")


def test_a_killed_emulated_drive_is_silent_not_starved() -> None:
    """The emulated drive's process killed (SIGKILL): its last published tick then looks
    like a stall that never ends, and a run whose feedback timed out would blame the host
    (host_too_slow, with its --lockstep hint) for a drive that is gone. A dead drive is not
    starved: ``starved`` says nothing once the process has ended."""
    from dobhil.drives.load import load_drive_profile
    from dobhil.emulator.process import STARVED_SHARE, EmulatorProcess, EmulatorSpec, Slot
    config = demo_config()
    with EmulatorProcess(EmulatorSpec.of(config, load_drive_profile(config, DEMO.parent))) as emulator:
        assert emulator.pid is not None
        # a tick published and read (what a running loop always has): then the kill
        assert wait_until(lambda: math.isfinite(emulator.snapshot()[Slot.DEADLINE]), 30.0)
        os.kill(emulator.pid, signal.SIGKILL)
        assert wait_until(lambda: not emulator.running)
        window = 0.05
        # the stall the dead drive shows: what would blame the host if it still ran
        assert wait_until(lambda: emulator.stalled(window) >= STARVED_SHARE * window, 30.0)
        assert emulator.starved(window) == ""


def test_a_motor_that_reports_no_timeout_watches_nothing(tmp_path: Path) -> None:
    """A Mini-Cheetah's command timeout only zeroes its command, silently: nothing for the
    host to classify; the shipped Damiao rows have no timeout at all."""
    mini = write_profile(tmp_path, "mini-cheetah")
    for profile in (str(mini), "dm4310"):
        config = load_config(REPO / "configs" / "mit-demo.yaml", [f"drive.profile={profile}"])
        with RunSession(config, emulate=True, lockstep=True) as session:
            assert session.drive.host_watch is None


# -- across processes: dobhil emulate on the hub, dobhil run stopped --------------------------

def watchdog_fired(bus: can.BusABC, bound: float) -> bool:
    """Until a heartbeat of the node on ``bus`` has the watchdog's Axis_Error bit (False
    after ``bound`` s: a bound for a loaded machine, not a measurement)."""
    beat, bit = codec.arbitration_id(NODE, CmdId.HEARTBEAT), codec.watchdog_bit(codec.Firmware.V0_6)
    end = time.monotonic() + bound
    while time.monotonic() < end:
        msg = bus.recv(0.1)
        if msg is not None and msg.arbitration_id == beat:
            decoded = codec.decode_message(msg, codec.Firmware.V0_6)
            if isinstance(decoded, codec.Heartbeat) and decoded.axis_error & bit:
                return True
    return False


def test_a_stopped_run_process_is_the_host_across_processes(tmp_path: Path, hub: int) -> None:
    """``dobhil emulate`` (an ODrive, watchdog 250 ms) in one process, ``dobhil run`` in
    another, on a python-can-remote hub. Once the run commands torque, its process is
    stopped (SIGSTOP) until the emulator's heartbeat says its watchdog fired, then
    continued. The run stops host_too_slow with a gap of at least the time it was stopped
    (measured by this test)."""
    _stopped_run_is_the_host(tmp_path, hub, heartbeat=0.05)


def test_a_stopped_run_waits_for_the_frames_sent_while_it_was_stopped(tmp_path: Path) -> None:
    """As above with a hub that forwards late: the hub is stopped with the run, for 0.6 s
    (the watchdog's 0.25 s and two heartbeat periods of 0.1 s, and some: the emulator's
    watchdog fires, and a heartbeat says so, while the hub holds its frames), then the
    run is continued, and the hub 0.1 s later. The heartbeats sent meanwhile reach the run
    late, its heartbeat watch (three periods) from the last heartbeat it read long passed:
    the silence is not the drive's, the run waits the watch again from its return, reads
    the watchdog's expiry and stops host_too_slow (calling the silence the drive's, it
    stopped drive_fault: "no heartbeat from node 3")."""
    with hub_process(tmp_path) as (hub, port):
        _stopped_run_is_the_host(tmp_path, port, heartbeat=0.1, hub=hub)


#: how long the hub and the run are stopped together, and the hub held after the run goes
#: on (test_a_stopped_run_waits_for_the_frames_sent_while_it_was_stopped)
HUB_STOPPED, HUB_LATE = 0.6, 0.1


def _stopped_run_is_the_host(tmp_path: Path, port: int, *, heartbeat: float,
                             hub: subprocess.Popen[bytes] | None = None) -> None:
    """The run stopped until its drive's watchdog fired: by the emulator's word on the
    hub, or (``hub`` stopped with it) HUB_STOPPED s; then continued, the hub HUB_LATE s
    later."""
    url = f"ws://127.0.0.1:{port}/"
    watchdog = 0.25
    profile = write_profile(tmp_path, "odrive-0.6", feedback_period=5e-3, heartbeat_period=heartbeat,
                            watchdog_timeout=watchdog, enable_timeout=5.0)
    overrides = [f"drive.profile={profile}", "loop.period=5e-3", *SLACK,
                 "design.dob_bandwidth=100", "design.rtob_bandwidth=100", *STEP_FROM_ZERO,
                 "loop.duration=30"]
    out = tmp_path / "emulate.log"
    emulate = start_emulate(DEMO, url, overrides, out)
    run: subprocess.Popen[bytes] | None = None
    sniffer = None
    try:
        wait_for_emulator(emulate, out)
        sniffer = can.Bus(interface="remote", channel=url)
        run = subprocess.Popen([sys.executable, "-m", "dobhil", "run", str(DEMO), "--bus", f"remote:{url}",
                                "--summary-json", *[a for o in overrides for a in ("--set", o)]],
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=child_env(), cwd=REPO)
        seen = 0
        deadline = time.monotonic() + 60.0
        while seen < 50:   # torque commands: the loop runs
            assert run.poll() is None and time.monotonic() < deadline, run.communicate()
            msg = sniffer.recv(0.5)
            seen += msg is not None and msg.arbitration_id == TORQUE_ID
        if hub is None:
            os.kill(run.pid, signal.SIGSTOP)
            begin = time.monotonic()
            fired = watchdog_fired(sniffer, WATCH_BOUND)
            stopped = time.monotonic() - begin
            assert fired, "the emulator's heartbeat never said its watchdog fired"
            os.kill(run.pid, signal.SIGCONT)
        else:
            os.kill(hub.pid, signal.SIGSTOP)
            try:
                os.kill(run.pid, signal.SIGSTOP)
                begin = time.monotonic()
                time.sleep(HUB_STOPPED)
                os.kill(run.pid, signal.SIGCONT)
                stopped = time.monotonic() - begin
                time.sleep(HUB_LATE)
            finally:
                os.kill(hub.pid, signal.SIGCONT)
        stdout, stderr = run.communicate(timeout=60)
    finally:
        if sniffer is not None:
            sniffer.shutdown()
        if run is not None and run.poll() is None:
            os.kill(run.pid, signal.SIGCONT)
            stop_process(run)
        stop_process(emulate)
    info = json.loads(stdout.decode().strip().splitlines()[-1])
    detail = info["stop_detail"]
    assert info["stop_reason"] == "host_too_slow", (detail, stderr.decode())
    assert "WATCHDOG_TIMER_EXPIRED" in detail and "the drive's watchdog allows 250 ms" in detail
    found = GAP.search(detail)
    assert found is not None and int(found.group(1)) >= math.floor(stopped * 1e3), (detail, stopped)
    assert info["drive_disabled"] is True
    assert LOCKSTEP_HINT not in stderr.decode()   # not emulated by this run: no --lockstep advice


class LateBus(can.BusABC):
    """A bus that hands the host nothing received until ``held_until`` (perf_counter),
    then all it queued meanwhile: a hub forwarding late."""

    def __init__(self, inner: can.BusABC) -> None:
        super().__init__(channel=inner.channel_info)
        self.inner = inner
        self.held_until = -math.inf
        self.channel_info = f"late over {inner.channel_info}"

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self.inner.send(msg, timeout)

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        wait = self.held_until - time.perf_counter()
        if wait > 0:
            time.sleep(wait if timeout is None else min(wait, timeout))
            return None, False
        return self.inner.recv(timeout), False

    def shutdown(self) -> None:
        self.inner.shutdown()
        super().shutdown()


@pytest.mark.parametrize("timing", ["feedback", "host"])
def test_a_silence_while_the_host_was_stopped_is_timed_from_its_return(tmp_path: Path, timing: str) -> None:
    """The loop's thread stalls after cycle 100 for its feedback timeout and 0.1 s (no
    drive watchdog: nothing fires), and what the drive sent meanwhile reaches it only
    0.1 s after it goes on (a hub forwarding late). The silence began while the host read
    nothing: its feedback timeout and the drive's heartbeat watch count from its return,
    the frames come, the run ends done (timed from the last fresh frame it stopped
    feedback_timeout, or drive_fault: "no heartbeat")."""
    profile = write_profile(tmp_path, "odrive-0.6", watchdog_timeout=0.0, enable_timeout=2.0)
    config = demo_config(f"drive.profile={profile}", *STEP_FROM_ZERO, "loop.duration=1.5",
                         f"loop.timing={timing}", *SLACK)
    stall = config.loop.feedback_timeout + 0.1
    for _ in range(STARVED_RUNS):   # a run the machine starved says so (host_too_slow): again
        buses: list[LateBus] = []

        def wrap(bus: can.BusABC, buses: list[LateBus] = buses) -> can.BusABC:
            buses.append(LateBus(bus))
            return buses[-1]

        def stalled(buses: list[LateBus] = buses) -> None:
            buses[0].held_until = time.perf_counter() + stall + 0.1
            time.sleep(stall)

        sink = Recorder(at=100, action=stalled)
        with RunSession(config, emulate=True, lockstep=False, sink=sink, bus_wrapper=wrap) as session:
            result = session.run()
        if result.stop.reason is not StopReason.HOST_TOO_SLOW:
            break
    assert sink.fired_at >= 0 and len(buses) == 1
    assert result.stop.reason is StopReason.DONE, result.stop.line()


# -- the measure itself ------------------------------------------------------------------------

@settings(max_examples=200, deadline=None)
@example(gaps=[1.0, 0.15], floor=0.098, since=0.0984, window=0.104)
@given(gaps=st.lists(st.floats(0.0, 0.5), min_size=1, max_size=40),
       floor=st.floats(0.001, 0.3), since=st.floats(0.0, 0.6), window=st.floats(0.0, 1.0))
def test_command_gaps_find_the_gap_that_starved_the_watch(gaps: list[float], floor: float, since: float,
                                                          window: float) -> None:
    """Against a brute force over every gap kept: ``starving`` is the longest of the ongoing
    gap (when it reaches the floor) and the gaps >= floor that ended within the window (0.0
    if none; a run keeps the newest few of those: each is a watch nearly starved, ~0.1 s or
    more, so more than a few within one window is not a run's); ``longest`` is the longest."""
    measure = _CommandGaps()
    measure.start(0.0, floor)
    t = 0.0
    ended: list[tuple[float, float]] = []
    for gap in gaps:
        before, t = t, t + gap
        measure.sent(t)
        ended.append((t, t - before))   # the gap as the clock gives it (rounded)
    now = t + since
    late = [(end, gap) for end, gap in ended if gap >= floor][-_CommandGaps.KEPT:]
    candidates = [now - t] if now - t >= floor else []
    candidates += [gap for end, gap in late if now - end <= window]
    expected = max(candidates, default=0.0)
    assert measure.starving(now, window) == expected
    assert measure.longest == max(gap for _, gap in ended)


def test_the_lockstep_hint_follows_only_an_emulated_real_time_host_too_slow(tmp_path: Path,
                                                                            capsys: Any) -> None:
    """``dobhil run`` prints the hint on the line after the stop line, for an emulated
    real-time run stopped host_too_slow only."""
    base = {"stop_reason": "host_too_slow", "emulated": True, "timing": "feedback"}
    assert stop_hint(base) == LOCKSTEP_HINT and "--lockstep" in LOCKSTEP_HINT
    assert stop_hint({**base, "emulated": False}) == ""
    assert stop_hint({**base, "timing": "lockstep"}) == ""
    assert stop_hint({**base, "stop_reason": "drive_fault"}) == ""
    result, _, info = run_stalled(odrive_config(tmp_path))
    report(info, result.stop.line(), as_json=False)
    lines = capsys.readouterr().out.splitlines()
    at = lines.index(result.stop.line())
    assert lines[at + 1] == LOCKSTEP_HINT
