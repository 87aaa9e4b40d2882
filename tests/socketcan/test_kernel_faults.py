"""Faults the kernel itself produces, on its real CAN stack: the interface going down (mid-run,
during the preflight, under the emulator), a transmit queue that refuses frames (ENOBUFS),
and netem's delay, jitter and loss on the drive's frames.

Every run ends as README's "Safety, whatever the drive does" and docs/hardware.md ("How a run
ends") say: one stop line, zero torque and the disable attempted, the loud ``WARNING: drive may
still be enabled`` when the disable cannot be confirmed, exit 1, never a traceback.
"""

from __future__ import annotations

import errno
import json
import math
import re
import time
from pathlib import Path
from typing import Any

import can
import numpy as np
import pytest
import yaml
from scipy.stats import binom

from dobhil.drives.cia402.codec import Cob
from dobhil.drives.odrive import codec as odrive
from dobhil.drives.odrive.codec import AxisState, CmdId, CmdId06, Firmware
from dobhil.run_report import load_run, report

from .guest import CONFIGS, DEMOS, PERIOD, START_TIMEOUT, Dobhil, Dumped, Proc, guest_overlay, summary_json
from .links import (Capture, change_fault, fault_on_ids, one_line, pause, qdisc_stats, sample_latencies,
                    sh, transit_delays, unmatched, vxcan_pair, wait_frames)

#: the demos' drives (configs/*demo.yaml, drivers/*.yaml): ODrive node 3, CiA 402 node 5, a
#: Damiao in MIT mode with ESC_ID 1
ODRIVE_NODE, CIA402_NODE, MIT_ID = 3, 5, 1
#: the frame each protocol's host sends every cycle: ODrive's Set_Input_Torque, CiA 402's
#: RPDO1 (controlword + target torque), an MIT command (to the motor's own id)
COMMAND = {"odrive": odrive.arbitration_id(ODRIVE_NODE, CmdId.SET_INPUT_TORQUE),
           "cia402": Cob.rpdo(1, CIA402_NODE), "mit": MIT_ID}
#: the ODrive's Get_Encoder_Estimates, its feedback
ENCODER = odrive.arbitration_id(ODRIVE_NODE, CmdId.GET_ENCODER_ESTIMATES)
#: (protocol, shipped profile): MIT with a Damiao, whose replies can confirm its exit
PROTOCOLS = [("odrive", None), ("cia402", None), ("mit", "dm4310")]
#: torque commands the run sends before the fault: well inside the cycles, after the enable
MID_RUN = 50
#: a run that only a fault ends (a bound, never reached)
LONG = "600"
WARNING = r"^WARNING: drive may still be enabled: .*; cut power$"
#: the drive watchdog of the guest's ODrive profile (tests/socketcan/guest.py, guest_overlay)
WATCHDOG = 0.25


def start_run(dobhil: Dobhil, config: Path, bus: str, overlay: Path, *more: str) -> Proc:
    return dobhil.start("run", ["run", str(config), "--bus", f"socketcan:{bus}", "--set-file", str(overlay),
                                "--duration", LONG, *more])


def no_traceback(*procs: Proc) -> None:
    for proc in procs:
        assert "Traceback" not in proc.text(), proc.text()


def readable_log(dobhil: Dobhil, log: Path, tmp_path: Path) -> tuple[dict[str, Any], dict[str, Any]]:
    """``dobhil log info --json`` of ``log`` -- after ``dobhil log recover`` if it needs it --
    and the summary of the analysis ``dobhil report`` makes of it (dobhil.run_report.report,
    in this process: the command's figures, minutes under software emulation, read nothing
    more)."""
    info = dobhil.run("info", ["log", "info", str(log), "--json"])
    if info.returncode != 0:
        recovered = tmp_path / "recovered.mcap"
        rec = dobhil.run("recover", ["log", "recover", str(log), "-o", str(recovered)])
        assert rec.returncode == 0, rec.text()
        log = recovered
        info = dobhil.run("info", ["log", "info", str(log), "--json"])
    assert info.returncode == 0, info.text()
    no_traceback(info)
    _, summary, _ = report(log)
    return dict(json.loads(info.text())), summary


@pytest.mark.parametrize(("protocol", "profile"), PROTOCOLS, ids=[p for p, _ in PROTOCOLS])
def test_link_down_mid_run(protocol: str, profile: str | None, vcan: str, dobhil: Dobhil,
                           tmp_path: Path) -> None:
    """``ip link set IFACE down`` while the run commands the drive: the run stops
    ``bus_error`` in the kernel's words, cannot reach the drive for the safe stop and says so
    loudly, exit 1; its log is readable; the emulator on the same interface ends in one line."""
    config = CONFIGS / DEMOS[protocol]
    overlay = guest_overlay(tmp_path, protocol, profile_name=profile)
    emulator = dobhil.emulate(config, vcan, overlay, protocol=protocol)
    log = tmp_path / "run.mcap"
    run = start_run(dobhil, config, vcan, overlay, "--log", str(log))
    wait_frames(vcan, COMMAND[protocol], MID_RUN)
    sh("ip", "link", "set", vcan, "down")

    assert run.wait() == 1, run.text()
    out = run.text()
    stop = one_line(out, r"stopped:")
    assert stop.startswith("stopped: bus_error at cycle ") and "Network is down" in stop, out
    one_line(out, WARNING)
    assert emulator.wait() == 1, emulator.text()
    lost = one_line(emulator.text(), "stopped")
    assert lost.startswith(f"dobhil emulate: stopped: bus socketcan:{vcan} lost (") and "Network is down" in lost
    no_traceback(run, emulator)
    info, summary = readable_log(dobhil, log, tmp_path)
    assert info["stop_reason"] == "bus_error" and summary["stop"] == "bus_error", (info, summary)
    assert summary["cycles"] > 0, summary


def test_link_down_before_the_run(vcan: str, dobhil: Dobhil, tmp_path: Path) -> None:
    """The interface is down when the run starts (a can0 never brought up): the preflight
    sees it in the kernel's flags and the run is refused in one line naming the interface
    and what to do, exit 1 -- not a request "not sent (bus off or transmit queue full?)"
    and a drive "not heard"."""
    config = CONFIGS / DEMOS["odrive"]
    overlay = guest_overlay(tmp_path, "odrive")
    sh("ip", "link", "set", vcan, "down")
    run = dobhil.run("run", ["run", str(config), "--bus", f"socketcan:{vcan}", "--set-file", str(overlay)])
    assert run.returncode == 1, run.text()
    assert run.text().splitlines() == [
        f"dobhil run: refused to enable: {vcan} is down: nothing can be sent or heard on it; sudo ip link set "
        f"{vcan} up (dobhil check CONFIG shows all it measured; --no-preflight skips)"], run.text()


def test_link_down_during_preflight(vcan: str, dobhil: Dobhil, tmp_path: Path) -> None:
    """The link goes down while the preflight listens (before anything is enabled): the
    refusal is the one line, in the kernel's words, exit 1 -- the run never goes on to an
    enable (on the link that is down it would end ``bus_error`` with the loud warning)."""
    config = CONFIGS / DEMOS["odrive"]
    overlay = guest_overlay(tmp_path, "odrive")
    dobhil.emulate(config, vcan, overlay)
    run = start_run(dobhil, config, vcan, overlay, "--preflight-window", "60")
    # the preflight's first act is its Get_Version request; then it listens for 60 s
    wait_frames(vcan, odrive.arbitration_id(ODRIVE_NODE, CmdId06.GET_VERSION), 1)
    sh("ip", "link", "set", vcan, "down")
    assert run.wait() == 1, run.text()
    lines = run.text().splitlines()
    assert len(lines) == 1 and lines[0].startswith("dobhil run: refused to enable: "), lines
    assert "Network is down" in lines[0], lines


# -- ENOBUFS: a transmit queue that refuses frames ----------------------------------------

#: a tbf that lets one classic frame (16 bytes in the kernel: struct can_frame) out per
#: second or more and queues one more: a queue that stays full through a safe stop's 2 x 20 ms
STUCK_TBF = ("tbf", "rate", "100bit", "burst", "16", "limit", "16")


def test_a_full_queue_refuses_with_enobufs(vcan: str) -> None:
    """The premise of the ENOBUFS tests: a sender on an interface whose queue is full gets
    ``can.CanOperationError`` with errno ENOBUFS from python-can's ``send()`` at once."""
    sh("tc", "qdisc", "add", "dev", vcan, "root", "handle", "30:", *STUCK_TBF)
    bus = can.Bus(interface="socketcan", channel=vcan)
    try:
        refused: can.CanOperationError | None = None
        for _ in range(10):
            try:
                bus.send(can.Message(arbitration_id=0x123, data=bytes(8), is_extended_id=False), 0.0)
            except can.CanOperationError as exc:
                refused = exc
                break
    finally:
        bus.shutdown()
    assert refused is not None and refused.error_code == errno.ENOBUFS, refused
    assert qdisc_stats(vcan)["drops"] == 1


def test_host_queue_full_mid_run(dobhil: Dobhil, tmp_path: Path) -> None:
    """The host's transmit queue fills mid-run (the shaping qdisc on the host's end only):
    the run stops ``bus_error`` in the kernel's words at the first refused torque frame, the
    safe stop's frames are each retried and refused, every refused attempt is counted (as
    many as the kernel dropped), the loud warning, exit 1 -- and the drive, never told,
    is stopped by its own watchdog (docs/hardware.md)."""
    config = CONFIGS / DEMOS["odrive"]
    overlay = guest_overlay(tmp_path, "odrive")
    with vxcan_pair() as (drive_end, host_end), Capture(tmp_path / "bus.log", (drive_end,)) as capture:
        emulator = dobhil.emulate(config, drive_end, overlay)
        run = start_run(dobhil, config, host_end, overlay, "--summary-json")
        wait_frames(host_end, COMMAND["odrive"], MID_RUN)
        sh("tc", "qdisc", "add", "dev", host_end, "root", "handle", "30:", *STUCK_TBF)
        assert run.wait() == 1, run.text()
        drops = qdisc_stats(host_end)["drops"]
        time.sleep(4 * WATCHDOG)   # the drive's watchdog expires (a bound, not a measurement)
        capture.stop()
        emulator.stop()
    summary = summary_json(run)
    assert summary["stop_reason"] == "bus_error", summary
    assert summary["stop_detail"].startswith("torque frame to node 3 not sent: Failed to transmit: "
                                             "No buffer space available"), summary
    frames = summary["safe_stop"]["frames"]
    assert [f["what"] for f in frames] == ["zero torque", "IDLE"] and not any(f["sent"] for f in frames)
    assert all("No buffer space available" in f["error"] and f["refused"] >= 1 for f in frames), frames
    # the torque frame that stopped the run, then every attempt of the safe stop: the kernel's count
    assert 1 + sum(f["refused"] for f in frames) == drops, (frames, drops)
    warning = one_line(run.text(), WARNING)
    assert "zero torque frame not sent" in warning and "IDLE frame not sent" in warning, warning
    no_traceback(run, emulator)
    # after the run the drive said, in its heartbeat, that its watchdog had put it to IDLE
    last = capture.frames(drive_end, odrive.arbitration_id(ODRIVE_NODE, CmdId.HEARTBEAT))[-1]
    heartbeat = odrive.decode(last.arbitration_id, last.data)
    assert heartbeat.axis_state == AxisState.IDLE, heartbeat
    assert heartbeat.axis_error & odrive.watchdog_bit(Firmware.V0_6), heartbeat


def slow_tbf(periods: float) -> tuple[str, ...]:
    """A tbf that lets one classic frame (16 bytes: struct can_frame) out every ``periods``
    loop periods and queues two more: a sender any faster is refused (ENOBUFS)."""
    rate = round(16 * 8 / (periods * PERIOD))
    return ("tbf", "rate", f"{rate}bit", "burst", "16", "limit", "32")


#: how much slower than the loop period the drive's queue lets its feedback out (over the
#: rate watch's 1.5: dobhil/runtime/loop.py, _RateWatch)
SLOW_PERIODS = 2.5


def test_drive_queue_full_mid_run(dobhil: Dobhil, tmp_path: Path) -> None:
    """The drive's transmit queue lets its encoder estimates out every 2.5 periods and
    refuses the rest (the shaping qdisc on the drive's end, on that frame only): the emulator
    counts every refused send -- exactly what the kernel dropped -- and goes on; the run, its
    feedback slower than its period, is stopped by the rate watch, in the interval the kernel
    let the frames out at, and its disable is confirmed (the heartbeats pass)."""
    config = CONFIGS / DEMOS["odrive"]
    overlay = guest_overlay(tmp_path, "odrive")
    with vxcan_pair() as (drive_end, host_end), Capture(tmp_path / "bus.log", (host_end,)) as capture:
        emulator = dobhil.emulate(config, drive_end, overlay)
        run = start_run(dobhil, config, host_end, overlay, "--summary-json")
        wait_frames(host_end, COMMAND["odrive"], MID_RUN)
        fault_on_ids(drive_end, [ENCODER], *slow_tbf(SLOW_PERIODS))
        assert run.wait() == 1, run.text()
        capture.stop()
        emulator.stop()
        drops = qdisc_stats(drive_end)["drops"]
    summary = summary_json(run)
    assert summary["stop_reason"] == "feedback_timeout", summary
    found = re.search(r"^encoder estimates come every ([0-9.]+) ms \(7 of the last (?:8|9|10) intervals\), "
                      r"expected every loop\.period = ", summary["stop_detail"])
    assert found, summary["stop_detail"]
    assert summary["drive_disabled"] is True and summary["drive_warning"] == "", summary
    candidates = intervals_before_stop(capture, host_end)
    assert any(same_figure(found.group(1), ms) for ms in candidates), (found.group(1), candidates)
    refused = re.search(r", (\d+) refused by the bus$", emulator.text().strip())
    assert refused and int(refused.group(1)) == drops > 0, (emulator.text(), drops)
    no_traceback(run, emulator)


def intervals_before_stop(capture: Capture, host_end: str) -> list[float]:
    """The feedback intervals [ms] the run may have judged last, from the kernel's receive
    stamps (candump's, the run's own to the microsecond): between the newest encoder
    estimates received before its safe stop's first frame (zero torque, the last torque
    frame before IDLE) and the 1, 2 or 3 before it, per frame (a late cycle takes the
    frames queued meanwhile: ``frames`` in _RateWatch)."""
    torque = capture.frames(host_end, COMMAND["odrive"])
    idle = capture.frames(host_end, odrive.arbitration_id(ODRIVE_NODE, CmdId.SET_AXIS_STATE))[-1]
    safe_stop = max(f.stamp for f in torque if f.stamp <= idle.stamp)
    stamps = [f.stamp for f in capture.frames(host_end, ENCODER) if f.stamp < safe_stop]
    return [(stamps[-1] - stamps[-1 - n]) / n * 1e3 for n in (1, 2, 3)]


def same_figure(printed: str, ms: float) -> bool:
    """``printed`` (three significant digits, as the stop line has it) is ``ms`` rounded,
    give or take candump's microsecond (it truncates what python-can has in nanoseconds)."""
    value = float(printed)
    exponent = math.floor(math.log10(abs(value))) if value else 0
    half_unit = 0.5 * 10.0 ** (exponent - 2)   # "%.3g" drops trailing zeros, not precision
    return abs(value - ms) <= half_unit + 1e-3


# -- netem on the drive's frames ----------------------------------------------------------

#: the netem runs' period: twice the guest's, so that the CiA 402 emulator (canopen in a guest
#: under software emulation) answers every SYNC through two runs of NETEM_RUN s
NETEM_PERIOD = 2 * PERIOD
#: netem on the drive's samples: delay D +- J (uniform, tc-netem(8)), loss L -- 300 us +- 100 us
#: at a 1 ms period, scaled to the period
DELAY, JITTER, LOSS = 0.3 * NETEM_PERIOD, 0.1 * NETEM_PERIOD, 1.0   # s, s, %
#: seconds each of the two runs lasts
NETEM_RUN = 20.0
#: CiA 402's motion TPDO: the second TPDO of a SYNC completes its sample
#: (dobhil/drives/cia402/drive.py), so its delay is the sample's delay and its loss the sample's
MOTION_TPDO = Cob.tpdo(2, CIA402_NODE)


def us(seconds: float) -> str:
    return f"{round(seconds * 1e6)}us"


def netem_overlay(tmp_path: Path) -> Path:
    """The guest's CiA 402 overlay at NETEM_PERIOD (profile and loop), observers at half the
    guest's bandwidth to match, and a feedback timeout of ten periods."""
    return guest_overlay(tmp_path, "cia402", extra={
        "loop.period": NETEM_PERIOD, "loop.feedback_timeout": 10 * NETEM_PERIOD,
        "design.dob_bandwidth": 20.0, "design.rtob_bandwidth": 20.0},
        profile={"feedback_period": NETEM_PERIOD})


def timed_run(dobhil: Dobhil, name: str, config: Path, bus: str, overlay: Path, log: Path) -> dict[str, Any]:
    """A run of NETEM_RUN s with a log; its summary (it must end ``done``)."""
    proc = dobhil.run(name, ["run", str(config), "--bus", f"socketcan:{bus}", "--set-file", str(overlay),
                             "--duration", str(NETEM_RUN), "--log", str(log), "--summary-json"],
                      timeout=START_TIMEOUT + 4 * NETEM_RUN)
    assert proc.returncode == 0, proc.text()
    no_traceback(proc)
    return summary_json(proc)


def test_netem_on_the_samples(dobhil: Dobhil, tmp_path: Path) -> None:
    """CiA 402 over a vxcan pair, the same run twice: as is, then with netem (delay D +- J,
    loss L) on the drive's motion TPDO. Against the kernel's own record (candump on both
    ends): netem lost as many frames as its counter says, consistent with L; every sample
    latency each run reports is a SYNC-to-sample interval of the kernel's stamps, to the
    microsecond (never negative: dobhil/drives/cia402/drive.py, ``_sampled_at``);
    the median the run reports shifts by the median delay netem gave those frames, to
    within the quartile spreads of the first run's latencies and of those delays; and 1 %
    of samples lost trips neither the feedback timeout nor the stale-sample check (both
    runs last their duration)."""
    config = CONFIGS / DEMOS["cia402"]
    overlay = netem_overlay(tmp_path)
    with vxcan_pair() as (drive_end, host_end), \
            Capture(tmp_path / "bus.log", (drive_end, host_end)) as capture:
        emulator = dobhil.emulate(config, drive_end, overlay, protocol="cia402")
        base = timed_run(dobhil, "base", config, host_end, overlay, tmp_path / "base.mcap")
        fault_on_ids(drive_end, [MOTION_TPDO], "netem", "delay", us(DELAY), us(JITTER), "loss", f"{LOSS}%")
        netem = timed_run(dobhil, "netem", config, host_end, overlay, tmp_path / "netem.mcap")
        capture.stop()
        emulator.stop()
        drops = qdisc_stats(drive_end)["drops"]
    syncs = capture.frames(host_end, Cob.SYNC)
    split = pause([f.stamp for f in syncs])
    runs = {"base": (-math.inf, split), "netem": (split, math.inf)}
    sent = {name: within(capture.frames(drive_end, MOTION_TPDO), *w) for name, w in runs.items()}
    got = {name: within(capture.frames(host_end, MOTION_TPDO), *w) for name, w in runs.items()}

    # what netem did: the frames it dropped, as many as the kernel's counter, as likely as L
    assert len(sent["base"]) == len(got["base"]) and len(sent["netem"]) - len(got["netem"]) == drops
    low, high = binom.interval(1 - 1e-6, len(sent["netem"]), LOSS / 100)
    assert low <= drops <= high, (drops, len(sent["netem"]), low, high)
    delays = transit_delays(sent["netem"], got["netem"], least=DELAY - JITTER - 1e-4)

    # what the runs measured: each sample's latency is the kernel's, to the microsecond
    # (from the SYNC its stamp follows, or the one before when the run's socket got it first)
    for name in ("base", "netem"):
        measured = logged(tmp_path / f"{name}.mcap", "sample_latency")
        kernel = sample_latencies(within(syncs, *runs[name]), got[name])
        assert unmatched(measured, kernel, within=2e-6) == [], name
    # the netem run's latency is X + D, the base latency X plus netem's delay D, drawn
    # independently: P(X + D > x25 + d25) >= P(X > x25) P(D > d25) = 9/16, and likewise
    # below x75 + d75, so its median lies in [x25 + d25, x75 + d75]. Less the base median:
    # the shift lies within the two quartile spreads around the median delay.
    x25, x50, x75 = np.percentile(logged(tmp_path / "base.mcap", "sample_latency"), [25, 50, 75])
    d25, d50, d75 = np.percentile(delays, [25, 50, 75])
    shift = (netem["sample_latency_us"]["p50"] - base["sample_latency_us"]["p50"]) * 1e-6
    bounds = (d50 - (x50 - x25) - (d50 - d25), d50 + (x75 - x50) + (d75 - d50))
    assert bounds[0] <= shift <= bounds[1], (shift, bounds, (x25, x50, x75), (d25, d50, d75))
    figures = {"drops": drops, "sent": len(sent["netem"]), "binomial": [low, high], "shift_s": shift,
               "shift_bounds_s": list(bounds), "base_quartiles_s": [x25, x50, x75],
               "netem_delay_s": np.percentile(delays, [0, 25, 50, 75, 100]).tolist(),
               "base_p50_us": base["sample_latency_us"]["p50"], "netem_p50_us": netem["sample_latency_us"]["p50"],
               "cycles": [base["cycles"], netem["cycles"]]}
    (tmp_path / "figures.json").write_text(json.dumps(figures))


def within(frames: list[Dumped], lo: float, hi: float) -> list[Dumped]:
    return [f for f in frames if lo <= f.stamp < hi]


def logged(log: Path, signal: str) -> list[float]:
    """A per-cycle signal of a run's log (dobhil.run_report.load_run: what ``dobhil report``
    reads), where it was measured."""
    values = load_run(log)[signal]
    return [float(v) for v in values[np.isfinite(values)]]


def test_netem_delay_beyond_the_feedback_timeout(dobhil: Dobhil, tmp_path: Path) -> None:
    """Mid-run, netem's delay on the ODrive's encoder estimates steps from 0 to three
    feedback timeouts: the frames stop coming for that long, and the run stops
    ``feedback_timeout`` inside that silence, no sooner than the timeout after its last
    frame; its disable is confirmed (the heartbeats are not delayed)."""
    config = CONFIGS / DEMOS["odrive"]
    overlay = guest_overlay(tmp_path, "odrive")
    timeout = float(yaml.safe_load(overlay.read_text())["loop.feedback_timeout"])
    with vxcan_pair() as (drive_end, host_end), Capture(tmp_path / "bus.log", (host_end,)) as capture:
        emulator = dobhil.emulate(config, drive_end, overlay)
        fault_on_ids(drive_end, [ENCODER], "netem", "delay", "0us")
        run = start_run(dobhil, config, host_end, overlay, "--summary-json")
        wait_frames(host_end, COMMAND["odrive"], MID_RUN)
        change_fault(drive_end, "netem", "delay", us(3 * timeout))
        assert run.wait() == 1, run.text()
        capture.stop()
        emulator.stop()
    summary = summary_json(run)
    assert summary["stop_reason"] == "feedback_timeout", summary
    assert summary["stop_detail"] == f"no fresh feedback for {timeout:g} s", summary
    assert summary["drive_disabled"] is True and summary["drive_warning"] == "", summary
    no_traceback(run, emulator)
    # what netem did, in the kernel's receive stamps: one silence longer than the timeout,
    # and the safe stop's first frame (zero torque) inside it, a timeout after it began
    torque = capture.frames(host_end, COMMAND["odrive"])
    idle = capture.frames(host_end, odrive.arbitration_id(ODRIVE_NODE, CmdId.SET_AXIS_STATE))[-1]
    zero = max(f.stamp for f in torque if f.stamp <= idle.stamp)
    stamps = [f.stamp for f in capture.frames(host_end, ENCODER)]
    gaps = [(b - a, a, b) for a, b in zip(stamps, stamps[1:]) if b > torque[0].stamp and a < zero]
    longest, began, ended = max(gaps)
    assert longest > timeout and sorted(gaps)[-2][0] < timeout, sorted(gaps)[-2:]
    assert began + timeout <= zero < ended, (began, zero, ended)
