"""The README's hardware workflow, as written, on the kernel's SocketCAN: ``tools/setup_vcan.sh``,
``dobhil emulate CONFIG --bus socketcan:vcan0`` in one process, ``dobhil check`` and ``dobhil run
CONFIG --bus socketcan:vcan0 --log`` in others, then ``dobhil replay --verify`` -- for ODrive,
CiA 402 and MIT mode."""

from __future__ import annotations

from pathlib import Path

import pytest

from .guest import CONFIGS, DEMOS, Dobhil, guest_overlay, summary_json


def emulated_summary_keys(dobhil: Dobhil, config: Path, overlay: Path, tmp_path: Path) -> set[str]:
    """The fields of ``dobhil run CONFIG --emulate`` (real time, the emulator in a process of
    its own) with the same overlay and a log."""
    proc = dobhil.run("emulated", ["run", str(config), "--emulate", "--set-file", str(overlay),
                                   "--log", str(tmp_path / "emulated.mcap"), "--summary-json"])
    assert proc.returncode == 0, proc.text()
    return set(summary_json(proc))


#: (protocol, shipped profile): MIT with a Damiao, whose replies carry the motor's mode, so
#: that its exit can be confirmed (a CubeMars reply cannot confirm it: tests/socketcan/test_mit.py)
CASES = [("odrive", None), ("cia402", None), ("mit", "dm4310")]


@pytest.mark.parametrize(("protocol", "profile"), CASES, ids=[c[0] for c in CASES])
def test_emulate_check_run_replay(protocol: str, profile: str | None, vcan: str, dobhil: Dobhil,
                                  tmp_path: Path) -> None:
    """Two processes on vcan: the run converges with the emulated run's summary fields, the
    safe stop is confirmed, and the log replays bit for bit."""
    config = CONFIGS / DEMOS[protocol]
    overlay = guest_overlay(tmp_path, protocol, profile_name=profile)
    emulator = dobhil.emulate(config, vcan, overlay, protocol=protocol)

    check = dobhil.run("check", ["check", str(config), "--bus", f"socketcan:{vcan}", "--set-file", str(overlay)])
    assert check.returncode == 0, check.text()

    log = tmp_path / "run.mcap"
    run = dobhil.run("run", ["run", str(config), "--bus", f"socketcan:{vcan}", "--set-file", str(overlay),
                             "--log", str(log), "--summary-json"])
    summary = summary_json(run)
    assert run.returncode == 0, run.text()
    assert summary["stop_reason"] == "done", run.text()
    assert summary["drive_disabled"] is True and summary["drive_warning"] == "", run.text()
    assert summary["safe_stop"]["confirmation"] == "confirmed", run.text()
    final = summary["final"]
    assert abs(final["tau_int_hat"] - final["tau_ref"]) < 0.03 * abs(final["tau_ref"]), final
    assert summary["bus"] == f"socketcan:{vcan}"
    assert set(summary) == emulated_summary_keys(dobhil, config, overlay, tmp_path)

    replay = dobhil.run("replay", ["replay", str(log), "--verify"])
    assert replay.returncode == 0, replay.text()
    emulator.stop()
    assert emulator.returncode == 0, emulator.text()
