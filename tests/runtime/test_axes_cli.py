"""``dobhil run`` / ``dobhil demo`` of a config with ``axes:``: a run per axis in one loop,
a node-id clash refused in one line before anything is sent (exit 2)."""

from __future__ import annotations

import json
from pathlib import Path

import can
import pytest

from dobhil.cli.main import main
from dobhil.errors import ConfigError
from dobhil.runtime.axes_session import AxesSession

from .axes_helpers import CONFIGS, load_two, two_axis_config


def test_run_with_axes_summarises_each_axis(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    config = two_axis_config(tmp_path, ("odrive", "odrive"), duration=0.2)
    code = main(["run", str(config), "--emulate", "--lockstep", "--summary-json"])
    out, err = capsys.readouterr()
    assert code == 0, err
    info = json.loads(out)
    assert info["stop_reason"] == "done" and info["stop_axis"] == "" and info["drives_disabled"]
    assert list(info["axes"]) == ["left", "right"]
    assert [a["node_id"] for a in info["axes"].values()] == [1, 2]
    assert all(a["cycles"] == info["cycles"] == 200 for a in info["axes"].values())
    assert all(a["safe_stop"]["confirmation"] == "confirmed" for a in info["axes"].values())
    assert "WARNING" not in err


def test_demo_with_axes_writes_a_plot_per_axis(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    config = two_axis_config(tmp_path, ("odrive", "odrive"), duration=0.1)
    code = main(["demo", str(config), "--out", str(tmp_path / "out"), "--no-log"])
    out, err = capsys.readouterr()
    assert code == 0, err
    assert "stopped: done" in out
    assert (tmp_path / "out" / "demo_run-left.png").stat().st_size > 0
    assert (tmp_path / "out" / "demo_run-right.png").stat().st_size > 0


def test_node_id_clash_is_one_line_exit_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    config = two_axis_config(tmp_path, ("odrive", "odrive"))
    code = main(["run", str(config), "--emulate", "--lockstep", "--set", "axes.right.drive.node_id=1"])
    out, err = capsys.readouterr()
    assert code == 2
    assert out == "" and err.count("\n") == 1
    # the line dobhil check gives (dobhil.drives.axes.check_clashes): both axes, the id
    assert "axes left (odrive node 1) and right (odrive node 1)" in err and "CAN id" in err
    assert "node_id" in err and "Traceback" not in err


class Sent(can.BusABC):
    """A tap that keeps what the host sends on the bus it wraps in ``sent``."""

    def __init__(self, inner: can.BusABC, sent: list[can.Message]) -> None:
        self._inner = inner
        self.sent = sent
        self.channel_info = f"tap {inner.channel_info}"
        super().__init__(channel=self.channel_info)

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self.sent.append(msg)
        self._inner.send(msg, timeout)

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        return self._inner.recv(timeout), True


@pytest.mark.parametrize(("protos", "nodes"), [(("odrive", "odrive"), (3, 3)),
                                               # ODrive node 12 uses 0x180..0x19F: CiA 402 node 5's TPDO1 0x185
                                               (("odrive", "cia402"), (12, 5))])
def test_clash_refused_before_any_frame(tmp_path: Path, protos: tuple[str, str], nodes: tuple[int, int]) -> None:
    axes = load_two(tmp_path, protos, f"axes.left.drive.node_id={nodes[0]}", f"axes.right.drive.node_id={nodes[1]}")
    sent: list[can.Message] = []
    opened: list[str] = []

    def tap(bus: can.BusABC, name: str) -> can.BusABC:
        opened.append(name)
        return Sent(bus, sent)
    with pytest.raises(ConfigError) as caught:
        AxesSession(axes, emulate=True, lockstep=True, config_dir=CONFIGS, bus_wrapper=tap)
    line = str(caught.value)
    assert "\n" not in line and line.startswith(f"axes left ({protos[0]} node {nodes[0]}) and right "
                                                f"({protos[1]} node {nodes[1]})"), line
    assert opened == [] and sent == []   # refused before a bus was opened: nothing sent, nothing enabled


def test_distinct_nodes_of_two_protocols_are_no_clash(tmp_path: Path) -> None:
    axes = load_two(tmp_path, ("odrive", "cia402"), "axes.left.drive.node_id=1", "axes.right.drive.node_id=5")
    with AxesSession(axes, emulate=True, lockstep=True, config_dir=CONFIGS) as session:
        assert [g.axes for g in session.groups] == [["left", "right"]]


@pytest.mark.parametrize("timing", [["--lockstep"], ["--set", "loop.timing=host"]])
def test_coupling_across_buses_refused_in_either_timing(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                                       timing: list[str]) -> None:
    # each bus' emulator hosts its own axes' plants: a real-time emulator process, given
    # only its bus' couplings, ran the pair uncoupled without a word
    config = two_axis_config(tmp_path, ("odrive", "odrive"), duration=0.05, coupled=True)
    code = main(["run", str(config), "--emulate", *timing, "--set", "axes.right.drive.interface=virtual",
                 "--set", "axes.right.drive.channel=other"])
    out, err = capsys.readouterr()
    assert code == 2 and out == "" and err.count("\n") == 1, err
    assert "coupling between axes 'left' and 'right': they are on different buses" in err
    assert "virtual:other" in err and "Traceback" not in err
