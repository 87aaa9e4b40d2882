"""Across processes: a python-can-remote hub (loopback only), ``dobhil emulate`` in a
second process, and the force loop in this one, all on ``remote:ws://127.0.0.1:PORT/``.

The websocket hub adds milliseconds of latency, so the loop runs slowly enough for it:
200 Hz, observer bandwidths 100 rad/s (``dobhil analyze --set design.delay_samples=1``
and ``=2``: stable, max C_f 10.3 and 3.9 > C_f = 2), a 50 ms feedback timeout. The true
interaction torque lives in the other process; the estimate must reach the reference.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np

from dobhil.config import load_config
from dobhil.runtime.session import RunSession
from dobhil.runtime.stop import StopReason

from .helpers import DEMO, REPO, demo_config, finite_tail, write_profile
from .hub import child_env, stop_process, wait_for_emulator

def slow_overrides(tmp_path: Path) -> list[str]:
    profile = write_profile(tmp_path, "odrive-0.6", feedback_period=5e-3,
                            heartbeat_period=0.05, watchdog_timeout=0.5, enable_timeout=5.0)
    return [f"drive.profile={profile}", "loop.period=5e-3", "loop.feedback_timeout=0.05",
            "design.dob_bandwidth=100", "design.rtob_bandwidth=100", "plant.initial_position=0",
            "reference.offset=0", "reference.amplitude=1", "reference.start=0",
            "loop.duration=1.5"]


def start_emulate(config: Path, url: str, overrides: list[str], out: Path) -> subprocess.Popen[bytes]:
    """``dobhil emulate CONFIG`` on the hub at ``url`` in a child process, its output to ``out``."""
    with out.open("wb") as log:
        return subprocess.Popen(
            [sys.executable, "-m", "dobhil", "emulate", str(config), "--bus", f"remote:{url}",
             "--duration", "60", *[a for o in overrides for a in ("--set", o)]],
            stdout=log, stderr=subprocess.STDOUT, env=child_env(), cwd=REPO)


def test_force_loop_across_processes(tmp_path: Path, hub: int) -> None:
    """The loop in this process converges on a drive emulated by another process,
    through the hub: stop reason done, tau_int^ at the 1 N m reference."""
    url = f"ws://127.0.0.1:{hub}/"
    overrides = slow_overrides(tmp_path)
    out = tmp_path / "emulate.log"
    emulate = start_emulate(DEMO, url, overrides, out)
    try:
        wait_for_emulator(emulate, out)
        config = demo_config(*overrides)
        with RunSession(config, bus=f"remote:{url}") as session:
            assert session.bus_spec.interface == "remote"
            assert "bitrate" in session.bus_spec.kwargs   # the remote bus takes it along
            result = session.run()
        assert result.stop.reason is StopReason.DONE, result.stop.line()
        assert result.disabled
        tail = finite_tail(result.trace["tau_int_hat"], result.trace["t"], 0.2)
        assert tail.size >= 10
        assert abs(float(np.mean(tail)) - 1.0) < 0.03
        assert np.all(np.isnan(result.trace["tau_int_true"]))   # not visible from here
    finally:
        stop_process(emulate)
    text = out.read_text(errors="replace")
    assert emulate.returncode == 0, text
    assert "emulator stopped" in text


def test_mit_force_loop_across_processes(tmp_path: Path, hub: int) -> None:
    """The same with an MIT motor: ``dobhil emulate configs/mit-demo.yaml`` (a DM4310, whose
    replies say its mode, so the exit is confirmed) in the other process, host timing here
    (the motor answers each command), the MIT preflight asking it first."""
    url = f"ws://127.0.0.1:{hub}/"
    overrides = ["drive.profile=dm4310", "loop.period=5e-3", "loop.feedback_timeout=0.05",
                 "design.dob_bandwidth=100", "design.rtob_bandwidth=100", "plant.initial_position=0",
                 "reference.offset=0", "reference.amplitude=1", "reference.start=0", "loop.duration=1.5"]
    config_path = REPO / "configs" / "mit-demo.yaml"
    out = tmp_path / "emulate.log"
    emulate = start_emulate(config_path, url, overrides, out)
    try:
        wait_for_emulator(emulate, out, "mit")
        config = load_config(config_path, overrides)
        with RunSession(config, bus=f"remote:{url}") as session:
            result = session.run()
            assert session.preflight_report is not None and not session.preflight_report.refuses
        assert result.stop.reason is StopReason.DONE, result.stop.line()
        assert result.disabled
        tail = finite_tail(result.trace["tau_int_hat"], result.trace["t"], 0.2)
        assert tail.size >= 10
        assert abs(float(np.mean(tail)) - 1.0) < 0.03
    finally:
        stop_process(emulate)
    text = out.read_text(errors="replace")
    assert emulate.returncode == 0, text
