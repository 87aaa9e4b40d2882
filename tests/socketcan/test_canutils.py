"""can-utils as peers of a run on the kernel's vcan: ``candump -l`` records the run, the log
goes through ``dobhil log import`` and ``dobhil identify --drive``, and gives the numbers the
run's own MCAP gives; ``cansend`` puts frames the drive did not expect on its ids during a
run, and the run records them and reacts as tests/runtime/test_fault_matrix.py and
tests/drives/test_codec_properties.py say it must."""

from __future__ import annotations

import dataclasses
import math
import struct
from pathlib import Path
from typing import Any

import can
import numpy as np
import yaml

from dobhil.drives.odrive import codec
from dobhil.drives.odrive.codec import AxisState, CmdId, Firmware
from dobhil.drives.load import load_profile
from dobhil.identify.data import IdentData, Segment, read_log
from dobhil.identify.fit import _SETTLED, LEVEL, simulate

from .guest import CONFIGS, START_TIMEOUT, Dobhil, guest_overlay, read_candump, summary_json
from .peers import crashes_say_where  # noqa: F401 (an autouse fixture: applies here)
from .peers import (Recorded, candump_log, cansend, cansend_text, cli, cli_json, heartbeat_state, own_bus,
                    read_run, start_candump, watch)

NODE = 3   # the shipped odrive-0.6 profile's
ENCODER = codec.arbitration_id(NODE, CmdId.GET_ENCODER_ESTIMATES)
HEARTBEAT = codec.arbitration_id(NODE, CmdId.HEARTBEAT)
TORQUE = codec.arbitration_id(NODE, CmdId.SET_INPUT_TORQUE)
#: identify-free in the guest: what a real rig has (velocity noise, seeded), at 20 ms -- twice
#: tests/socketcan/guest.py's period: identify takes the loop's records up to the first cycle
#: the loop skipped (a gap breaks the uniform sampling), and at 10 ms a loaded machine's guest
#: skipped cycles 2 to 113 of 400 -- with the multisine's lines to 10 Hz (a fifth of the rate)
RATE = 0.02
EXCITATION = {"loop.duration": 6.0, "loop.period": RATE, "loop.feedback_timeout": 10 * RATE,
              "reference.frequency_end": 10.0, "reference.lines": 20, "sensor.velocity_noise": 0.001,
              "sensor.seed": 1}


# -- candump's log identified like the run's own MCAP ------------------------------------------

def _window(frames: IdentData, loop: IdentData) -> int:
    """Where the loop records' samples are among the capture's motion frames: the one offset
    at which every position and velocity is the same float (both are the drive class's
    decoding of the same frames, ``dobhil/drives/decode.py``)."""
    n = loop.samples
    starts = np.flatnonzero((frames.position[: frames.samples - n + 1] == loop.position[0])
                            & (frames.velocity[: frames.samples - n + 1] == loop.velocity[0]))
    found = [int(j) for j in starts if (frames.position[j:j + n] == loop.position).all()
             and (frames.velocity[j:j + n] == loop.velocity).all()]
    assert len(found) == 1, f"the loop's {n} samples are at {found} in the capture"
    return found[0]


def _stamps_differ_by_candump_resolution(dumped: Path, run: Recorded) -> int:
    """Every encoder frame both logs hold has both stamps from the kernel's one receive time:
    candump's in microseconds (SO_TIMESTAMP, a timeval), the MCAP's as python-can gave it
    (SO_TIMESTAMPNS as a float, can/interfaces/socketcan/socketcan.py). So the MCAP's is at
    most 1 us after candump's, to the doubles' rounding. Returns how many were compared."""
    capture = {(f.stamp, f.data) for f in read_candump(dumped) if f.arbitration_id == ENCODER}
    ordered = sorted(capture)
    stamps = [s for s, _ in ordered]
    compared = 0
    for msg in run.frames("/can/rx"):
        if msg.arbitration_id != ENCODER:
            continue
        i = int(np.searchsorted(stamps, msg.timestamp, side="right")) - 1
        assert i >= 0 and ordered[i][1] == bytes(msg.data), f"MCAP frame at {msg.timestamp!r} not in candump's log"
        ulp = 2 * math.ulp(msg.timestamp)
        assert -ulp <= msg.timestamp - ordered[i][0] < 1e-6 + ulp, (msg.timestamp, ordered[i][0])
        compared += 1
    return compared


def _tolerances(mcap: dict[str, Any], loop: IdentData, frames: IdentData, start: int) -> dict[str, float]:
    """How far apart the two fits may end, parameter by parameter, from what the records
    differ in: the same samples, but the torque (the MCAP's ``u_sat``, a float64; the
    capture's, the command's float32 field and, where a command reached the bus after the
    next feedback frame, the one before it). With ``dr`` that difference's effect on the
    velocity residual at the MCAP's estimates and ``s`` the residual's RMS, a least-squares
    estimate moves by at most ``stderr * |dr| / s`` (first order; Cauchy-Schwarz on
    ``(J^T J)^-1 J^T dr``): the fit's own standard error sets the scale.

    Plus where each fit stops: its last round lowered the cost by less than ``_SETTLED``
    noise variances (dobhil/identify/fit.py, ``_refine``), and a parameter ``x`` standard
    errors off costs ``x^2`` of them, so each may end up to ``sqrt(_SETTLED)`` standard
    errors from the optimum. Measured in the guest: a capture with one command late (the
    previous torque in its sample) and the MCAP fitted 5e-4 standard errors apart in the
    viscous friction, 11 times the first-order part alone."""
    values = {k: e["value"] for k, e in mcap["estimates"].items() if e["identifiable"]}
    n = loop.samples
    initial = (float(loop.position[0]), float(loop.velocity[0]))
    _, own = simulate(values, loop, Segment(0, n, "free"), initial)
    at_t = dataclasses.replace(frames, period=loop.period)
    _, captured = simulate(values, at_t, Segment(start, start + n, "free"), initial)
    ratio = float(np.linalg.norm(captured - own)) / mcap["residual"]["rms"]
    settled = 2.0 * math.sqrt(_SETTLED)
    return {k: e["stderr"] * (ratio + settled) for k, e in mcap["estimates"].items() if e["identifiable"]}


def _excitation(vcan: str, dobhil: Dobhil, tmp_path: Path) -> tuple[Path, Path, str]:
    """``dobhil run identify-free`` over vcan against ``dobhil emulate``, ``candump -l`` on the
    bus throughout: (the run's MCAP, candump's log, the drive profile's path)."""
    config = CONFIGS / "identify-free.yaml"
    overlay = guest_overlay(tmp_path, "odrive", extra=EXCITATION, profile={"feedback_period": RATE})
    profile = str(yaml.safe_load(overlay.read_text(encoding="utf-8"))["drive.profile"])
    emulator = dobhil.emulate(config, vcan, overlay)
    dump = start_candump(dobhil, vcan)
    log = tmp_path / "run.mcap"
    run = dobhil.run("run", ["run", str(config), "--bus", f"socketcan:{vcan}", "--set-file", str(overlay),
                             "--log", str(log), "--summary-json"], timeout=4 * START_TIMEOUT)
    dump.stop()
    emulator.stop()
    assert run.returncode == 0 and summary_json(run)["stop_reason"] == "done", run.text()
    return log, candump_log(dobhil), profile


def _agree(mcap: dict[str, Any], capture: dict[str, Any], tolerance: dict[str, float], scale: float,
           dof: int) -> None:
    """Every parameter identifiable in both or neither; each value within its tolerance, each
    interval end within that plus ``z stderr / sqrt(2 dof)`` (the spread of the standard
    error's own estimate); the inertia and the delay compared per period (``scale``)."""
    spread = _z() / math.sqrt(2.0 * dof)
    for name, e in mcap["estimates"].items():
        c = capture["estimates"][name]
        assert c["identifiable"] == e["identifiable"], (name, c["why"], e["why"], c, e)
        if not e["identifiable"]:
            continue
        k = scale if name in ("inertia", "delay") else 1.0
        print(f"{name}: MCAP {e['value']:.9g} [{e['low']:.9g}, {e['high']:.9g}], candump {c['value']:.9g} "
              f"[{c['low']:.9g}, {c['high']:.9g}] (x {k:.9f}); tolerance {tolerance[name]:.3g}")
        assert abs(c["value"] * k - e["value"]) <= tolerance[name], name
        for end in ("low", "high"):
            assert abs(c[end] * k - e[end]) <= tolerance[name] + spread * e["stderr"], (name, end)


def test_candump_log_identifies_like_the_runs_own_mcap(vcan: str, dobhil: Dobhil, tmp_path: Path) -> None:
    """The candump log of a real-time excitation run, imported and identified with ``--drive``
    (its period the one its microsecond stamps scatter around), against the run's MCAP (its
    loop records, ``loop.period``) over the same samples. A free segment's fit is the same
    under a change of the time unit with the inertia and the delay scaled alike (``J dv/dt =
    u - b v - F_c sgn v`` keeps its form), so those two are compared per period; every value
    within the tolerance the records' differences allow (:func:`_tolerances`)."""
    log, dumped, profile = _excitation(vcan, dobhil, tmp_path)
    imported = tmp_path / "candump.mcap"
    cli(["log", "import", str(dumped), "-o", str(imported)])
    loop = read_log(log)
    frames = read_log(imported, profile=load_profile(profile))
    start, n = _window(frames, loop), loop.samples
    compared = _stamps_differ_by_candump_resolution(dumped, read_run(log, ("/can/rx",)))
    late = int(np.count_nonzero(frames.torque[start:start + n] != loop.torque.astype(np.float32)))

    mcap = cli_json(["identify", str(log), "--segment", f"0:{n * loop.period!r}:free"])
    capture = cli_json(["identify", str(imported), "--drive", profile, "--segment",
                        f"{start * frames.period!r}:{(start + n) * frames.period!r}:free"])
    assert capture["period"] == frames.period and mcap["period"] == loop.period
    assert [(s["t0"], s["t1"]) for s in capture["segments"]] == [(start * frames.period, (start + n) * frames.period)]
    print(f"{n} samples (capture offset {start}, {late} torque samples differ beyond float32, "
          f"{compared} encoder stamps compared); period MCAP {loop.period!r} s, candump {frames.period!r} s")
    tolerance = _tolerances(mcap, loop, frames, start)
    _agree(mcap, capture, tolerance, loop.period / frames.period, dof=n - 1 - len(tolerance))


def _z() -> float:
    """The normal quantile of the fit's two-sided intervals (dobhil/identify/fit.py LEVEL)."""
    from scipy.stats import norm
    return float(norm.ppf(0.5 + LEVEL / 2))


# -- cansend on the drive's ids during a run ---------------------------------------------------

def test_cansend_on_the_drives_ids_is_recorded_and_handled(vcan: str, dobhil: Dobhil, tmp_path: Path) -> None:
    """During a run (the demo force loop), ``cansend`` puts on node 3's ids first a malformed
    encoder estimate -- 4 bytes, a float32 NaN: not feedback, the run goes on (the drive fed
    arbitrary frames keeps running: tests/drives/test_codec_properties.py) -- then a heartbeat
    saying IDLE, as another node would spoof it: the run stops with drive_fault naming IDLE,
    zero torque then IDLE, confirmed (row "spoofed-heartbeat" of
    tests/runtime/test_fault_matrix.py). Both frames are in the MCAP's /can/rx at their
    kernel stamps; the loop's records go on after the first and end after the second."""
    config = CONFIGS / "demo.yaml"
    overlay = guest_overlay(tmp_path, "odrive", extra={"loop.duration": 60.0})
    emulator = dobhil.emulate(config, vcan, overlay)
    log = tmp_path / "run.mcap"
    malformed = can.Message(arbitration_id=ENCODER, is_extended_id=False, data=struct.pack("<f", math.nan))
    spoofed = codec.encode(codec.Heartbeat(0, AxisState.IDLE), node_id=NODE, firmware=Firmware.V0_6)
    with own_bus(vcan) as bus:
        run = dobhil.start("run", ["run", str(config), "--bus", f"socketcan:{vcan}", "--set-file", str(overlay),
                                   "--log", str(log), "--summary-json"])
        watch(bus, lambda m: heartbeat_state(m, NODE) == AxisState.CLOSED_LOOP_CONTROL)
        watch(bus, lambda m: m.arbitration_id == TORQUE, count=20)      # the loop commands
        cansend(vcan, cansend_text(malformed))
        after = watch(bus, lambda m: m.arbitration_id == TORQUE, count=50)   # ... and goes on
        cansend(vcan, cansend_text(spoofed))
        run.wait(START_TIMEOUT)
    emulator.stop()
    summary = summary_json(run)
    assert summary["stop_reason"] == "drive_fault" and "IDLE" in summary["stop_detail"], run.text()
    assert [f["what"] for f in summary["safe_stop"]["frames"]] == ["zero torque", "IDLE"]
    assert all(f["sent"] for f in summary["safe_stop"]["frames"]), summary["safe_stop"]
    assert summary["safe_stop"]["confirmation"] == "confirmed" and summary["drive_disabled"] is True

    rec = read_run(log, ("/can/rx", "/loop", "/drive/feedback", "/events"))
    rx = rec.frames("/can/rx")
    bad = [m for m in rx if m.arbitration_id == ENCODER and bytes(m.data) == bytes(malformed.data)]
    spoof = [m for m in rx if m.arbitration_id == HEARTBEAT and bytes(m.data) == bytes(spoofed.data)]
    assert len(bad) == 1 and bad[0].dlc == 4 and len(spoof) == 1, (bad, spoof)
    assert bad[0].timestamp < after[-1].timestamp <= spoof[0].timestamp
    cycles = [ns / 1e9 for ns, _ in rec.timed("/loop")]
    between = sum(bad[0].timestamp < t < spoof[0].timestamp for t in cycles)
    assert between > 0, "no cycle after the malformed frame"
    assert all(math.isfinite(p["position"]) and math.isfinite(p["velocity"]) for p in rec.topic("/drive/feedback"))
    stops = [(ns, e) for ns, e in rec.timed("/events") if e["kind"] == "stop"]
    assert len(stops) == 1 and "IDLE" in stops[0][1]["detail"] + stops[0][1]["reason"], stops
    assert cycles[-1] < stops[0][0] / 1e9 and stops[0][0] / 1e9 > spoof[0].timestamp   # the cycle it read it in stopped
    print(f"{between} cycles between the malformed frame and the spoofed heartbeat; stop: {summary['stop_detail']}")
