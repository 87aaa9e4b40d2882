"""CiA 402 through the kernel's CAN stack: the SYNC of SocketCAN's broadcast manager (BCM) and
the kernel's receive stamps, between ``dobhil emulate`` and ``dobhil run`` on vcan.

On SocketCAN the drive hands its SYNC to the kernel (python-can ``send_periodic``, a BCM
``TX_SETUP``: dobhil/drives/periodic.py, dobhil/drives/cia402/drive.py ``_start_sync``): the
kernel sends it on its own timer whatever the loop does, and deletes it with the socket that
set it up (the kernel's Documentation/networking/can.rst, "Broadcast Manager protocol
sockets"). Each frame a socket reads carries the kernel's receive stamp (SO_TIMESTAMP; python-can
asks for SO_TIMESTAMPNS): ``candump`` prints the same stamp, to the microsecond.

- a run stopped by SIGSTOP for a while: the SYNC goes on (the node answers each one, the
  loop finds them all queued and carries on), and ends when the run's safe stop is confirmed;
- a run killed by SIGKILL: the SYNC and the host's heartbeat end with the process, and the
  node's heartbeat consumer notices;
- the SYNC's interval jitter, broadcast manager against the loop sending it
  (tools/canvm/figures.py ``bcm_sync_jitter``, reported, not asserted);
- the log's receive stamps are candump's, and so is every cycle's sample latency (SYNC echo ->
  TPDO); the report says which clock each latency is on.

Every bound below comes from the run itself (its SYNC intervals, its stop window, its node's
configured consumer time); time-outs are generous bounds, not measurements.
"""

from __future__ import annotations

import bisect
import importlib.util
import json
import math
import os
import signal
import sys
import time
from collections import defaultdict
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np
import pytest

from .guest import (CONFIGS, DEMOS, REPO, REPORT_TIMEOUT, START_TIMEOUT, Dobhil, Dumped, Proc, guest_overlay,
                    candump_drops, read_candump, summary_json)


def _figures() -> ModuleType:
    """tools/canvm/figures.py, loaded by path (tools/ is not a package), as tests/conftest.py
    loads the canvm plugin."""
    spec = importlib.util.spec_from_file_location("dobhil_canvm_figures", REPO / "tools" / "canvm" / "figures.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module   # its dataclasses look their module up there
    spec.loader.exec_module(module)
    return module


figures = _figures()
IDS = figures.Cia402Ids.of()
CONFIG = CONFIGS / DEMOS["cia402"]
#: the loop's duration of the stopped run, and how long its loop runs before the SIGSTOP
RUN_S, LEAD_S = 5.0, 1.5
#: how long the run's process stays stopped (the test's sleep; the window is measured around it)
STOP_S = 0.5
#: the node's heartbeat frames after a run's end that show candump was still recording
LIVE_HEARTBEATS = 5
#: the node's heartbeat consumer time (0x1016) in the SIGKILL test [s]
CONSUMER_S = 0.5
#: the emergency code of a heartbeat consumer that timed out (CiA 301)
EMCY_HEARTBEAT = 0x8130


# -- helpers -------------------------------------------------------------------------------------


def wait_until(what: str, predicate: Callable[[], bool], timeout: float = START_TIMEOUT) -> None:
    """Until ``predicate()``; fails naming ``what`` after ``timeout`` s (a bound, not a measurement)."""
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            raise AssertionError(f"{what}: not within {timeout:.0f} s")
        time.sleep(0.1)


def wait_for_loop(run: Proc, dump: Path, iface: str) -> None:
    """Until the run's loop commands torque on ``iface`` (an RPDO with a torque: the enable's
    are zero); fails with the run's output if it ends first."""
    def running() -> bool:
        assert run.popen.poll() is None, f"the run ended before its loop commanded torque:\n{run.text()}"
        return any(f.iface == iface and f.arbitration_id == IDS.rpdo and figures.rpdo_command(f.data)[1]
                   for f in read_candump(dump))
    wait_until("the loop commands torque", running)


def node_heartbeats_after(dump: Path, t: float) -> int:
    return sum(1 for f in read_candump(dump) if f.arbitration_id == IDS.heartbeat and f.stamp > t)


def state_of(pid: int) -> str:
    """The process state letter of /proc/PID/stat (proc(5)): T when stopped."""
    text = Path(f"/proc/{pid}/stat").read_text()
    return text[text.rindex(")") + 2]


def bcm_intervals(frames: Sequence[Dumped], iface: str) -> list[tuple[float, float]]:
    """Consecutive SYNC stamps while the loop ran (the broadcast manager's: the drive sends
    SYNC itself only in its safe stop, after this window)."""
    window = figures.loop_window(frames, iface, IDS)
    assert window is not None, "the run never commanded a torque"
    syncs = figures.stamps(frames, iface, IDS.sync, window)
    return list(zip(syncs, syncs[1:]))


def slowest_running(frames: Sequence[Dumped], iface: str, stopped: tuple[float, float]) -> float:
    """[s] the slowest SYNC interval while the loop ran, outside the window it was stopped."""
    start, end = stopped
    return max(b - a for a, b in bcm_intervals(frames, iface) if b < start or a > end)


def recorded_after(frames: Sequence[Dumped], iface: str, stopped: tuple[float, float], exited: float) -> bool:
    """Whether candump recorded :data:`LIVE_HEARTBEATS` node heartbeats after the run
    ``exited``, spanning ten of the slowest SYNC intervals while it ran (what the test asks
    of the capture: a machine that slowed the SYNCs down is given as much longer)."""
    heard = [f.stamp for f in frames if f.arbitration_id == IDS.heartbeat and f.stamp > exited]
    return len(heard) >= LIVE_HEARTBEATS and heard[-1] - exited >= 10 * slowest_running(frames, iface, stopped)


def log_messages(path: Path, topic: str) -> list[tuple[int, dict[str, Any]]]:
    """(log time [ns], payload) of ``topic`` in the run's MCAP log, by log time."""
    from dobhil.recording.reader import open_log
    with open_log(path) as log:
        return sorted(((t, p) for _, t, p in log.iter_messages([topic])), key=lambda m: m[0])


@pytest.fixture(scope="module")
def module_vcan() -> Iterator[str]:
    """One vcan interface for the module's shared run (tools/setup_vcan.sh)."""
    with figures.vcan_interfaces([f"kst{os.getpid() % 10000}"]) as made:
        yield made[0]


# -- the stopped run (shared: SYNC under SIGSTOP, and the receive stamps) ------------------------


@dataclass(frozen=True)
class StoppedRun:
    """A run whose process was stopped (SIGSTOP) for a while, as candump and its log saw it."""

    iface: str
    frames: list[Dumped]            # candump -L of the interface, from before the run to after it
    stopped: tuple[float, float]    # wall clock of SIGSTOP sent, SIGCONT sent
    state: str                      # the process's state letter while stopped
    exited: float                   # wall clock once the process was reaped
    summary: dict[str, Any]
    output: str
    log: Path
    report: dict[str, Any]          # dobhil report's summary.json of the log
    drops: list[str]                # candump's DROPCOUNT lines: frames its capture lacks


@pytest.fixture(scope="module")
def stopped_run(module_vcan: str, tmp_path_factory: pytest.TempPathFactory) -> Iterator[StoppedRun]:
    work = tmp_path_factory.mktemp("stopped")
    runner = Dobhil(work)
    dump, log = work / "run.candump", work / "run.mcap"
    try:
        with figures.candump(dump, [module_vcan]):
            overlay = guest_overlay(work, "cia402")
            emulator = runner.emulate(CONFIG, module_vcan, overlay, protocol="cia402")
            run = runner.start("run", ["run", str(CONFIG), "--bus", f"socketcan:{module_vcan}", "--set-file",
                                       str(overlay), "--duration", str(RUN_S), "--log", str(log), "--summary-json"])
            wait_for_loop(run, dump, module_vcan)
            stopped, state = stop_for_a_while(run)
            run.wait(START_TIMEOUT + RUN_S)
            exited = time.time()
            wait_until("node heartbeats after the run, for ten of the slowest SYNC intervals",
                       lambda: recorded_after(read_candump(dump), module_vcan, stopped, exited))
            emulator.stop()
        out = runner.run("report", ["report", str(log), "--out", str(work / "report")], timeout=REPORT_TIMEOUT)
        assert out.returncode == 0, out.text()
        yield StoppedRun(module_vcan, read_candump(dump), stopped, state, exited, summary_json(run), run.text(), log,
                         json.loads((work / "report" / "summary.json").read_text()), candump_drops(dump))
    finally:
        runner.stop_all()


def stop_for_a_while(run: Proc) -> tuple[tuple[float, float], str]:
    """SIGSTOP after the loop ran ``LEAD_S``, SIGCONT ``STOP_S`` later: (sent, resumed), state."""
    time.sleep(LEAD_S)
    sent = time.time()
    run.signal(signal.SIGSTOP)
    try:
        time.sleep(0.05)   # signal delivery is asynchronous: look once it had time to land
        state = state_of(run.popen.pid)
        time.sleep(STOP_S)
    finally:
        resumed = time.time()
        run.signal(signal.SIGCONT)
    return (sent, resumed), state


def test_bcm_sync_goes_on_while_the_loop_is_stopped_and_ends_with_its_safe_stop(stopped_run: StoppedRun) -> None:
    """While the run's process is stopped the kernel keeps sending SYNC at least at the pace
    of its slowest interval while the process ran; the node answers each and the loop, once
    resumed, counts them as skipped frames and runs to its end; no SYNC follows the safe
    stop's confirmation, in a capture that goes on ten of those intervals longer."""
    r = stopped_run
    s = r.summary
    assert s["stop_reason"] == "done" and s["safe_stop"]["confirmation"] == "confirmed", r.output
    assert r.state == "T", f"the run's process was not stopped (state {r.state})"
    start, end = r.stopped
    pairs = bcm_intervals(r.frames, r.iface)
    running = [b - a for a, b in pairs if b < start or a > end]
    slowest = slowest_running(r.frames, r.iface, r.stopped)
    during = [b for _, b in pairs if start < b < end]
    assert len(during) >= math.floor((end - start) / slowest), (
        f"{len(during)} SYNCs in the {end - start:.3f} s the process was stopped; its slowest interval "
        f"while running {slowest * 1e3:.2f} ms")
    answers = [f for f in r.frames if f.arbitration_id == IDS.motion and start < f.stamp < end]
    assert s["skipped"] >= len(answers) - 1, (s["skipped"], len(answers))
    print(f"stopped {end - start:.3f} s: {len(during)} SYNCs, {len(answers)} TPDOs, {s['skipped']} frames skipped; "
          f"slowest SYNC interval while running {slowest * 1e3:.2f} ms of {len(running)}")

    confirmed = [t for t, e in log_messages(r.log, "/events")
                 if e["kind"] == "disable" and e["reason"].startswith("safe stop: confirmed")]
    assert confirmed, "no confirmed safe stop in the log"
    at = confirmed[0] / 1e9
    late = [f.stamp - at for f in r.frames if f.arbitration_id == IDS.sync and f.stamp > at]
    assert not late, f"{len(late)} SYNC after the safe stop was confirmed, the first {late[0]:.4f} s after"
    heard = [f.stamp for f in r.frames if f.arbitration_id == IDS.heartbeat]
    assert heard[-1] - r.exited >= 10 * slowest, "candump did not record long enough after the run"


def test_log_stamps_are_candumps_and_so_is_each_sample_latency(stopped_run: StoppedRun) -> None:
    """Every frame the run read has candump's stamp of it (both sockets get the kernel's
    receive stamp; candump prints microseconds, truncated); each cycle's sample latency (SYNC
    echo -> TPDO, ``/loop.sample_latency``) is what candump's stamps of the SYNC and the TPDO
    that fed the cycle give; the report's sample latency is on those bus stamps, says so,
    and its percentiles are candump's."""
    r = stopped_run
    assert r.report["dropped"] == 0, "the recorder dropped records: frames cannot be matched to cycles"
    assert not r.drops, f"candump lost frames (its capture is no record to compare with): {r.drops}"
    twins = candump_twins(r.frames)
    rx = log_messages(r.log, "/can/rx")
    offsets = [p["timestamp"] - twin_of(twins, p).stamp for _, p in rx]
    assert offsets and all(-math.ulp(p["timestamp"]) <= d < 1e-6 + math.ulp(p["timestamp"])
                           for d, (_, p) in zip(offsets, rx)), (min(offsets), max(offsets))

    measured, derived = sample_latencies(r, twins, rx)
    assert len(measured) == r.summary["cycles"], (len(measured), r.summary["cycles"])
    tolerance = 1e-6 + 4 * math.ulp(r.exited)
    m, d = np.array(measured), np.array(derived)
    assert np.array_equal(np.isnan(m), np.isnan(d)), "a cycle without a sample latency in one and not the other"
    worst = float(np.max(np.abs(m - d), initial=0.0, where=~np.isnan(d)))
    assert worst <= tolerance, f"a cycle's sample latency is {worst * 1e6:.2f} us off candump's"

    latency, timing = r.report["latency"], r.report["loop_timing"]
    assert latency["clock"] == "log" and latency["sample_clock"] == "bus", latency
    assert "interface socketcan" in latency["sample_clock_text"], latency
    for p in (50, 99):
        assert abs(timing[f"sample_latency_p{p}"] - float(np.nanpercentile(derived, p))) <= tolerance, (p, timing)
    print(f"{len(rx)} frames: log - candump {min(offsets) * 1e6:.3f} .. {max(offsets) * 1e6:.3f} us; {len(measured)} "
          f"sample latencies within {worst * 1e6:.3f} us of candump's, "
          f"p50 {np.nanpercentile(derived, 50) * 1e6:.0f} us")


def candump_twins(frames: Sequence[Dumped]) -> dict[tuple[int, bytes], list[tuple[float, int]]]:
    """candump's frames by (id, data): (stamp, index in candump's order), by stamp."""
    twins: dict[tuple[int, bytes], list[tuple[float, int]]] = defaultdict(list)
    for i, f in enumerate(frames):
        twins[(f.arbitration_id, f.data)].append((f.stamp, i))
    return twins


@dataclass(frozen=True)
class Twin:
    stamp: float
    index: int


def twin_of(twins: dict[tuple[int, bytes], list[tuple[float, int]]], payload: dict[str, Any]) -> Twin:
    """candump's frame of a logged one: same id and data, the nearest stamp."""
    candidates = twins.get((payload["arbitration_id"], bytes(payload["data"])), [])
    assert candidates, f"candump has no frame 0x{payload['arbitration_id']:03X}#{bytes(payload['data']).hex()}"
    i = bisect.bisect_left(candidates, (payload["timestamp"], -1))
    near = min(candidates[max(0, i - 1):i + 1], key=lambda c: abs(c[0] - payload["timestamp"]))
    return Twin(*near)


def sample_latencies(r: StoppedRun, twins: dict[tuple[int, bytes], list[tuple[float, int]]],
                     rx: list[tuple[int, dict[str, Any]]]) -> tuple[list[float], list[float]]:
    """Per cycle with a sample latency: the run's, and candump's -- its stamp of the TPDO the
    cycle used (the last motion frame the loop read before the cycle's record) less its stamp
    of the SYNC that sampled it: of the two newest SYNCs the run had read before that TPDO,
    the newer, unless candump stamped it after the TPDO -- then the older (a TPDO can reach
    the run's socket before the echo of its own SYNC on two processors: the rule of
    dobhil/drives/cia402/drive.py ``_sampled_at``, here on candump's stamps)."""
    motions = [(t, k) for k, (t, p) in enumerate(rx) if p["arbitration_id"] == IDS.motion]
    read_at = [t for t, _ in motions]
    syncs_read = [k for k, (_, p) in enumerate(rx) if p["arbitration_id"] == IDS.sync]
    measured, derived = [], []
    for t, cycle in log_messages(r.log, "/loop"):
        if cycle.get("sample_latency") is None:
            continue
        k = motions[bisect.bisect_right(read_at, t) - 1][1]
        tpdo = twin_of(twins, rx[k][1]).stamp
        newest_two = syncs_read[max(0, bisect.bisect_left(syncs_read, k) - 2):bisect.bisect_left(syncs_read, k)]
        stamps = [twin_of(twins, rx[j][1]).stamp for j in newest_two]
        sampled = next((s for s in reversed(stamps) if s <= tpdo), math.nan)
        measured.append(float(cycle["sample_latency"]))
        derived.append(tpdo - sampled)
    return measured, derived


# -- SIGKILL -------------------------------------------------------------------------------------


def test_bcm_sync_and_host_heartbeat_end_with_the_killed_process(vcan: str, dobhil: Dobhil, tmp_path: Path) -> None:
    """SIGKILL of a running loop: its broadcast-manager tasks, the SYNC and the host's
    heartbeat the node watches (``cia402.consumer_heartbeat``), go with its sockets. They
    ran up to the kill; none is stamped after the process was reaped; the node's heartbeat
    consumer reports the host lost (EMCY 0x8130) no sooner than its consumer time after the
    host's last heartbeat; candump recorded for ten SYNC intervals and more after."""
    dump = tmp_path / "kill.candump"
    overlay = guest_overlay(tmp_path, "cia402", profile={"cia402.consumer_heartbeat": CONSUMER_S})
    host = 0x700 + int(profile_option("host_node_id"))
    with figures.candump(dump, [vcan]):
        dobhil.emulate(CONFIG, vcan, overlay, protocol="cia402")
        run = dobhil.start("run", ["run", str(CONFIG), "--bus", f"socketcan:{vcan}", "--set-file", str(overlay),
                                   "--duration", "600"])
        wait_for_loop(run, dump, vcan)
        time.sleep(LEAD_S)
        killed = time.time()
        run.signal(signal.SIGKILL)
        assert run.wait() == -signal.SIGKILL, run.text()
        reaped = time.time()
        wait_until("the node's heartbeat consumer EMCY", lambda: emcy_after(read_candump(dump), reaped) is not None)
        wait_until("node heartbeats after the EMCY",
                   lambda: node_heartbeats_after(dump, emcy_after(read_candump(dump), reaped) or math.inf)
                   >= LIVE_HEARTBEATS)
    frames = read_candump(dump)
    pairs = bcm_intervals_until(frames, vcan, killed)
    slowest = max(b - a for a, b in pairs)
    assert killed - pairs[-1][1] <= slowest, "the SYNC was not running when the process was killed"
    after = [f for f in frames if f.arbitration_id in (IDS.sync, host) and f.stamp > reaped]
    assert not after, f"{len(after)} SYNC/host heartbeat frames after the process was reaped"
    emcy = emcy_after(frames, reaped)
    assert emcy is not None
    last_host = max(f.stamp for f in frames if f.arbitration_id == host)
    assert emcy - last_host >= CONSUMER_S, (emcy - last_host)
    assert frames[-1].stamp - reaped >= 10 * slowest
    print(f"last SYNC {(killed - pairs[-1][1]) * 1e3:.2f} ms before SIGKILL, reaped {(reaped - killed) * 1e3:.0f} ms "
          f"after; EMCY 0x8130 {emcy - last_host:.3f} s after the last host heartbeat; "
          f"recorded {frames[-1].stamp - reaped:.2f} s after")


def profile_option(key: str) -> Any:
    """A setting of the shipped drivers/cia402-emulated.yaml (its default where it has none)."""
    from dobhil.drives.load import load_profile
    return load_profile("cia402-emulated").options[key]


def emcy_after(frames: Sequence[Dumped], t: float) -> float | None:
    """The stamp of the node's first heartbeat-consumer EMCY after ``t`` (None: none yet)."""
    for f in frames:
        if f.arbitration_id == IDS.emcy and f.stamp > t and len(f.data) >= 2 \
                and int.from_bytes(f.data[:2], "little") == EMCY_HEARTBEAT:
            return f.stamp
    return None


def bcm_intervals_until(frames: Sequence[Dumped], iface: str, t: float) -> list[tuple[float, float]]:
    """Consecutive SYNC stamps from the loop's first torque command to ``t``."""
    start = next(f.stamp for f in frames if f.iface == iface and f.arbitration_id == IDS.rpdo
                 and figures.rpdo_command(f.data)[1])
    syncs = figures.stamps(frames, iface, IDS.sync, (start, t))
    return list(zip(syncs, syncs[1:]))


# -- jitter: broadcast manager against the loop ----------------------------------------------------


def test_sync_jitter_bcm_against_the_loop(tmp_path: Path) -> None:
    """tools/canvm/figures.py ``bcm_sync_jitter`` (the bench's figure): every run ran to its
    end, the broadcast manager's on feedback timing, the loop-sent ones on host timing with
    their sample instant stamped at their own send; the loop's SYNC follows each torque frame
    (kernel stamps: the torque frame -> its SYNC is shorter than the SYNC -> the next torque
    frame); the figures count the SYNC intervals while each loop ran, per kind."""
    result = figures.bcm_sync_jitter(tmp_path)
    (tmp_path / "figures.json").write_text(json.dumps(result))
    print(f"figures: {json.dumps(result)}")
    timing = {"bcm": "feedback", "loop_sent": "host"}
    for run in result["runs"]:
        assert run["stop_reason"] == "done" and run["timing"] == timing[run["kind"]], run
    assert {run.get("sample_clock") for run in result["runs"] if run["kind"] == "loop_sent"} == {"sent"}
    frames = read_candump(Path(result["candump"]))
    counted: dict[str, int] = defaultdict(int)
    for run in result["runs"]:
        window = figures.loop_window(frames, result["interface"], IDS, within=(run["started"], run["ended"]))
        assert window is not None, run
        counted[run["kind"]] += len(figures.stamps(frames, result["interface"], IDS.sync, window)) - 1
        if run["kind"] == "loop_sent":
            after, before = torque_sync_gaps(frames, result["interface"], window)
            assert np.median(after) < np.median(before), (run, np.median(after), np.median(before))
    assert counted["bcm"] == result["intervals"] > 0 and counted["loop_sent"] == result["loop_sent"]["intervals"] > 0


def torque_sync_gaps(frames: Sequence[Dumped], iface: str,
                     window: tuple[float, float]) -> tuple[list[float], list[float]]:
    """On ``iface`` within ``window``: torque frame -> the SYNC after it, and SYNC -> the next torque frame."""
    ordered = [f for f in frames if f.iface == iface and window[0] <= f.stamp <= window[1]
               and f.arbitration_id in (IDS.rpdo, IDS.sync)]
    after = [b.stamp - a.stamp for a, b in zip(ordered, ordered[1:])
             if a.arbitration_id == IDS.rpdo and b.arbitration_id == IDS.sync]
    before = [b.stamp - a.stamp for a, b in zip(ordered, ordered[1:])
              if a.arbitration_id == IDS.sync and b.arbitration_id == IDS.rpdo]
    return after, before
