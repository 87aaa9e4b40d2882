"""SIGKILL of each process of a cross-process run (through the loopback hub): nothing
can clean up after a SIGKILL, so what must hold is what the *other* side does.

- the emulator (the drive) dies: the loop stops on ``feedback_timeout``, still sends
  its safe-stop frames, and -- nothing confirming them -- says loudly that the drive may
  still be enabled;
- the loop dies mid-run: the drive's own watchdog takes it to IDLE with zero torque.

(The recording writer's SIGKILL belongs with the recording tests.)
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import can

from dobhil.drives.base import Confirmation
from dobhil.drives.odrive.codec import AxisState
from dobhil.drives.load import load_profile
from dobhil.drives.odrive.emulator import EmulatedODrive
from dobhil.emulator.plant import Plant
from dobhil.runtime.session import RunSession
from dobhil.runtime.stop import StopReason

from .helpers import DEMO, REPO, demo_config, wait_until
from .hub import STARTUP_TIMEOUT, child_env, stop_process, wait_for_emulator
from .test_cross_process import slow_overrides


def start_child(args: list[str], log: Path) -> subprocess.Popen[bytes]:
    with log.open("wb") as out:
        return subprocess.Popen([sys.executable, "-m", "dobhil", *args], stdout=out,
                                stderr=subprocess.STDOUT, env=child_env(), cwd=REPO)


def sets(overrides: list[str]) -> list[str]:
    return [a for o in overrides for a in ("--set", o)]


class KillAt:
    """A sink that SIGKILLs ``pid`` at cycle ``at``."""

    def __init__(self, pid: int, at: int) -> None:
        self.pid, self.at, self.killed = pid, at, False

    def started(self, fb: object) -> None:
        pass

    def cycle(self, k: int, *args: object) -> None:
        if k >= self.at and not self.killed:
            self.killed = True
            os.kill(self.pid, signal.SIGKILL)

    def stop(self, stop: object) -> None:
        pass


def test_emulator_killed(tmp_path: Path, hub: int) -> None:
    url = f"remote:ws://127.0.0.1:{hub}/"
    overrides = slow_overrides(tmp_path)
    out = tmp_path / "emulate.log"
    emulate = start_child(["emulate", str(DEMO), "--bus", url, "--duration", "60",
                           *sets(overrides)], out)
    try:
        wait_for_emulator(emulate, out)
        sink = KillAt(emulate.pid, at=60)   # 0.3 s into the run at 200 Hz
        with RunSession(demo_config(*overrides, "loop.duration=10"), bus=url,
                        sink=sink) as session:  # type: ignore[arg-type]
            result = session.run()
    finally:
        stop_process(emulate)
    assert sink.killed and emulate.returncode == -signal.SIGKILL
    assert result.stop.reason is StopReason.FEEDBACK_TIMEOUT, result.stop.line()
    report = result.safe_stop
    assert report is not None and report.sent   # the hub still takes the frames
    assert report.confirmation is Confirmation.NOT_ACKNOWLEDGED and not result.disabled
    assert report.warning().startswith("drive may still be enabled: node 3 did not "
                                       "acknowledge IDLE (no status frame within")


def test_loop_killed(tmp_path: Path, hub: int) -> None:
    url = f"ws://127.0.0.1:{hub}/"
    overrides = slow_overrides(tmp_path)
    config = demo_config(*overrides)
    profile = load_profile(overrides[0].split("=", 1)[1])
    emulator = EmulatedODrive(can.Bus(interface="remote", channel=url), profile,
                              Plant.from_config(config))
    out = tmp_path / "run.log"
    with emulator:
        emulator.start()
        run = start_child(["run", str(DEMO), "--bus", f"remote:{url}",
                           *sets([*overrides, "loop.duration=60"])], out)
        try:
            def commanding() -> bool:
                return (emulator.protocol_state == AxisState.CLOSED_LOOP_CONTROL
                        and emulator.applied_torque != 0.0)

            assert wait_until(commanding, STARTUP_TIMEOUT), out.read_text(errors="replace")
            run.send_signal(signal.SIGKILL)
            run.wait(timeout=10)
        finally:
            stop_process(run)

        def stopped_by_watchdog() -> bool:
            return (emulator.protocol_state == AxisState.IDLE and emulator.applied_torque == 0.0
                    and emulator.watchdog_tripped)

        assert run.returncode == -signal.SIGKILL
        assert wait_until(stopped_by_watchdog, 10 * profile.watchdog_timeout)
