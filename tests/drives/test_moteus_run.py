"""``dobhil run configs/moteus-demo.yaml --emulate --lockstep --log x.mcap`` converges on the
force reference, and ``dobhil replay --verify`` reproduces it bit for bit; the emulated
frames are CAN FD with the bit rate switch, on the library's arbitration ids."""

from __future__ import annotations

from pathlib import Path

import can
import pytest

from dobhil.cli.main import main

REPO = Path(__file__).resolve().parents[2]


def test_the_demo_converges_and_replays_bit_for_bit(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    log = tmp_path / "x.mcap"
    assert main(["run", str(REPO / "configs" / "moteus-demo.yaml"), "--emulate", "--lockstep",
                 "--log", str(log)]) == 0
    out = capsys.readouterr().out
    assert "stopped: done at cycle 1200" in out
    final = next(line for line in out.splitlines() if line.startswith("final:"))
    ref, est, true = (float(final.split(name)[1].split()[0]) for name in ("tau_ref", "tau_int^", "true tau_int"))
    assert ref == 1.0 and abs(true - ref) < 1e-3 and abs(est - ref) < 1e-3, final
    assert main(["replay", str(log), "--verify"]) == 0
    assert "identical: every command and estimate reproduced bit for bit" in capsys.readouterr().out
    with can.LogReader(str(log)) as reader:
        frames = [m for m in reader if not m.is_error_frame]
    commands = [m for m in frames if m.arbitration_id == 0x8001]
    replies = [m for m in frames if m.arbitration_id == 0x100]
    assert len(commands) >= 1200 and len(replies) >= 1200
    assert all(m.is_fd and m.bitrate_switch and m.is_extended_id for m in commands)
    assert all(m.is_fd and not m.is_extended_id for m in replies)
    # the report's measured load times the FD frames as the budget does (data phase at the
    # recorded 5 Mbit/s): 245 bits per cycle at 1 kHz, 24.5 % of 1 Mbit/s (the enable's
    # and stop's few frames are no cycle's); as classic frames they read 83 %
    from dobhil.run_report import bus_stats, load_run
    bus = bus_stats(load_run(log))
    assert bus["bus_load"] == pytest.approx(0.245, abs=0.01) and bus.get("data_bitrate") == 5e6


def test_a_position_lost_on_its_rail_stops_with_the_stop_confirmed(tmp_path: Path,
                                                                   capsys: pytest.CaptureFixture[str]) -> None:
    """A position on the int8 rail (1.27 rev) is a drive fault, but the reply still carries
    the mode register: the stop is confirmed by it (mode 0), no 'cut power' warning."""
    import yaml
    profile = yaml.safe_load((REPO / "drivers" / "moteus-r4.11.yaml").read_text())
    profile["moteus"]["position_resolution"] = "int8"
    (tmp_path / "int8.yaml").write_text(yaml.safe_dump(profile))
    code = main(["run", str(REPO / "configs" / "moteus-demo.yaml"), "--emulate", "--lockstep", "--duration", "0.3",
                 "--set", f"drive.profile={tmp_path / 'int8.yaml'}", "--set", "loop.mode=torque",
                 "--set", "reference.offset=1.5", "--set", "plant.initial_position=7.9",
                 "--set", "environment.contact_position=15", "--set", "loop.position_max=20"])
    out, err = capsys.readouterr()
    assert code == 1 and "stopped: drive_fault" in out and "position +1.27 rev: at the end of the queried" in out, out
    assert "WARNING" not in err, err
