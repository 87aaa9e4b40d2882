"""A moteus profile or bus that cannot work is one line and exit 2, before anything is sent:
a register resolution the multiplex protocol lacks, a node id beyond its 7 bits, and the
CAN FD protocol on a bus opened as classic CAN."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import can
import pytest
import yaml

from dobhil.cli.main import main
from dobhil.drives import load_profile, make_drive
from dobhil.errors import ConfigError

REPO = Path(__file__).resolve().parents[2]
EXIT_USAGE = 2


def write_setup(tmp_path: Path, **changes: Any) -> Path:
    profile = yaml.safe_load((REPO / "drivers" / "moteus-r4.11.yaml").read_text())
    section = changes.pop("moteus", {})
    profile.update(changes)
    profile["moteus"] = {**profile["moteus"], **section}
    (tmp_path / "node.yaml").write_text(yaml.safe_dump(profile))
    config = yaml.safe_load((REPO / "configs" / "moteus-demo.yaml").read_text())
    config["drive"]["profile"] = str(tmp_path / "node.yaml")
    path = tmp_path / "config.yaml"
    path.write_text(yaml.safe_dump(config))
    return path


def one_line_exit_2(argv: list[str], capsys: pytest.CaptureFixture[str]) -> str:
    code = main(argv)
    out, err = capsys.readouterr()
    assert code == EXIT_USAGE, (out, err)
    assert err.count("\n") == 1 and "Traceback" not in err and "internal error" not in err, err
    return err


@pytest.mark.parametrize("command", ["run", "analyze"])
def test_a_resolution_moteus_lacks_is_one_line(tmp_path: Path, command: str,
                                               capsys: pytest.CaptureFixture[str]) -> None:
    config = write_setup(tmp_path, moteus={"position_resolution": "int64"})
    argv = ["run", str(config), "--emulate", "--lockstep", "--duration", "0.01"] if command == "run" \
        else ["analyze", str(config)]
    err = one_line_exit_2(argv, capsys)
    assert "moteus.position_resolution" in err and "int8, int16, int32, f32" in err and "int64" in err


def test_a_node_id_above_127_is_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    err = one_line_exit_2(["run", str(write_setup(tmp_path, node_id=200)), "--emulate", "--lockstep"], capsys)
    assert "node_id" in err and "1 to 126" in err and "200" in err


def test_an_fd_profile_on_a_classic_bus_is_one_line_and_sends_nothing(tmp_path: Path,
                                                                      capsys: pytest.CaptureFixture[str]) -> None:
    channel = "moteus-classic-bus"
    with can.Bus(interface="virtual", channel=channel) as sniffer:
        err = one_line_exit_2(["run", str(REPO / "configs" / "moteus-demo.yaml"), "--bus", f"virtual:{channel}",
                               "--no-preflight"], capsys)
        assert "CAN FD" in err and "classic CAN" in err
        assert sniffer.recv(0.05) is None   # nothing enabled, nothing sent


def test_the_drive_refuses_a_classic_bus_and_takes_an_fd_one() -> None:
    profile = load_profile("moteus-r4.11")
    with can.Bus(interface="virtual", channel="moteus-fd-check") as classic:
        with pytest.raises(ConfigError, match="needs a CAN FD bus"):
            make_drive(classic, profile)
    with can.Bus(interface="virtual", channel="moteus-fd-check", protocol=can.CanProtocol.CAN_FD) as fd:
        assert make_drive(fd, profile).frame_ids == {0x8001, 0x100}
