"""``dobhil emulate CONFIG`` with a config that lists axes: every axis' drive on the one bus,
in its own process (here on a python-can-remote hub, as another machine's host would see
it), each node answering its own frames; bad axis selections are one line, exit 2."""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import can
import pytest

from dobhil.cli.main import main
from dobhil.drives.odrive import codec
from dobhil.drives.odrive.codec import CmdId

from .axes_helpers import BOUND, TWO_AXES
from .helpers import DEMO, REPO
from .hub import child_env, stop_process, wait_for_emulator

EXIT_USAGE = 2


def _config(tmp_path: Path, right_bus: str = "") -> Path:
    path = tmp_path / "two.yaml"
    path.write_text(TWO_AXES % right_bus, encoding="utf-8")
    return path


def _answered_by(bus: can.BusABC, node: int) -> set[int]:
    """The nodes that answer a bus-voltage request to ``node`` (asked until one answers)."""
    end = time.monotonic() + BOUND
    while time.monotonic() < end:
        bus.send(codec.encode(codec.Request(CmdId.GET_BUS_VOLTAGE_CURRENT), node_id=node))
        answered: set[int] = set()
        until = time.monotonic() + 0.5
        while time.monotonic() < until:
            msg = bus.recv(0.05)
            if msg is not None and msg.arbitration_id & 0x1F == CmdId.GET_BUS_VOLTAGE_CURRENT \
                    and not msg.is_remote_frame:
                answered.add(msg.arbitration_id >> 5)
        if answered:
            return answered
    return set()


def test_emulate_hosts_every_axis_on_the_bus(tmp_path: Path, hub: int) -> None:
    url = f"ws://127.0.0.1:{hub}/"
    out = tmp_path / "emulate.log"
    with out.open("wb") as log:
        proc = subprocess.Popen([sys.executable, "-m", "dobhil", "emulate", str(_config(tmp_path)),
                                 "--bus", f"remote:{url}", "--duration", "60"],
                                stdout=log, stderr=subprocess.STDOUT, env=child_env(), cwd=REPO)
    try:
        wait_for_emulator(proc, out)
        assert "emulating odrive node 1 (left), odrive node 2 (right) on remote:" in out.read_text()
        assert "coupled left-right" in out.read_text()
        with can.Bus(interface="remote", channel=url) as bus:
            assert _answered_by(bus, 1) == {1}
            assert _answered_by(bus, 2) == {2}
    finally:
        stop_process(proc)
    text = out.read_text(errors="replace")
    assert proc.returncode == 0, text
    assert "emulator stopped: left: " in text and "; right: " in text


def test_bad_axis_selections_are_one_line_exit_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    def one_line(args: list[str]) -> str:
        assert main(["emulate", *args, "--bus", "virtual:never-opened", "--duration", "0.1"]) == EXIT_USAGE
        lines = capsys.readouterr().err.strip().splitlines()
        assert len(lines) == 1, lines
        return lines[0]

    two_buses = str(_config(tmp_path, ", interface: socketcan, channel: can1"))
    assert "2 buses (the default bus: left; socketcan:can1: right)" in one_line([two_buses])
    assert "--axis NAME (one dobhil emulate per bus)" in one_line([two_buses])
    assert "coupling left-right: axis right is not emulated with left" in one_line([two_buses, "--axis", "left"])
    assert "no axis 'up'" in one_line([two_buses, "--axis", "up"])
    assert "lists no axes" in one_line([str(DEMO), "--axis", "left"])
