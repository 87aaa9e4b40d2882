"""A CiA 402 profile that cannot describe a real node is one line and exit 2 wherever a command
reads it: an EDS that is not an EDS (not INI, objects missing, a data type that is not one, a
mapped object missing or of another type than CiA 402's) and an encoder resolution 0x608F
cannot hold, in ``run``, ``check`` and ``analyze`` (which reads the EDS through the protocol's
``check_files``); nothing is sent on the bus, no log is written."""

from __future__ import annotations

import re
from pathlib import Path

import can
import pytest
from dobhil_forks import DobhilForks
import yaml

from dobhil.cli.main import main

REPO = Path(__file__).resolve().parents[2]
EXIT_USAGE = 2
COMMANDS = {
    "run": ["run", "{config}", "--emulate", "--lockstep", "--duration", "0.01"],
    "check": ["check", "{config}", "--bus", "virtual:bad-profile", "--window", "0.05"],
    "analyze": ["analyze", "{config}"],
}
SHIPPED_EDS = (REPO / "drivers" / "cia402-emulated.eds").read_text()
TARGET_TORQUE = SHIPPED_EDS[SHIPPED_EDS.index("[6071]"):SHIPPED_EDS.index("[6072]")]
EDS_CASES = {
    "not INI": "this is not an EDS\nat all\n",
    "objects missing": "[FileInfo]\nFileName=x.eds\n[DeviceInfo]\nVendorName=x\n",
    # an object whose DataType is no number: canopen's int() of it raises ValueError
    "wrong type": (REPO / "drivers" / "cia402-emulated.eds").read_text().replace(
        "DataType=0x0007", "DataType=seven", 1),
    # RPDO1 maps 0x6071 (target torque, INTEGER16 per CiA 402)
    "mapped object missing": SHIPPED_EDS.replace(TARGET_TORQUE, ""),
    "mapped object of another type": SHIPPED_EDS.replace(
        TARGET_TORQUE, TARGET_TORQUE.replace("DataType=0x0003", "DataType=0x0007")),
}
#: what each case's line says (what was wrong, what is allowed)
EDS_SAYS = {
    "not INI": r"not a readable EDS \(expected CiA 306's INI format",
    "objects missing": r"object 0x[0-9A-F]{4} \(.*\) missing: a CiA 402 drive in CST needs it",
    "wrong type": r"not a readable EDS",
    "mapped object missing": r"object 0x6071 \(target torque\) missing",
    "mapped object of another type": r"0x6071:00 \(target torque\) is UNSIGNED32 in the EDS, CiA 402 has INTEGER16",
}


def write_setup(tmp_path: Path, eds_text: str | None = None, **section: object) -> Path:
    """A copy of the shipped emulated node's profile (its EDS replaced or its section changed)
    and a copy of configs/cia402-demo.yaml that names it by path."""
    profile = yaml.safe_load((REPO / "drivers" / "cia402-emulated.yaml").read_text())
    eds = REPO / "drivers" / "cia402-emulated.eds"
    if eds_text is not None:
        eds = tmp_path / "node.eds"
        eds.write_text(eds_text)
    profile["cia402"] = {**profile["cia402"], "eds": str(eds), **section}
    (tmp_path / "node.yaml").write_text(yaml.safe_dump(profile))
    config = yaml.safe_load((REPO / "configs" / "cia402-demo.yaml").read_text())
    config["drive"]["profile"] = str(tmp_path / "node.yaml")
    path = tmp_path / "config.yaml"
    path.write_text(yaml.safe_dump(config))
    return path


def one_line_exit_2(command: str, config: Path, capsys: pytest.CaptureFixture[str]) -> str:
    code = main([part.format(config=config) for part in COMMANDS[command]])
    out, err = capsys.readouterr()
    assert code == EXIT_USAGE, (out, err)
    assert err.count("\n") == 1 and "Traceback" not in err and "internal error" not in err, err
    return err


def test_the_wrong_type_case_really_changes_a_data_type() -> None:
    assert "DataType=seven" in EDS_CASES["wrong type"]


def test_the_mapped_cases_really_change_the_target_torque() -> None:
    assert "ParameterName=Target torque" in TARGET_TORQUE and "DataType=0x0003" in TARGET_TORQUE
    assert "[6071]" not in EDS_CASES["mapped object missing"]
    assert EDS_CASES["mapped object of another type"].count("DataType=0x0007") == \
        SHIPPED_EDS.count("DataType=0x0007") + 1


@pytest.mark.parametrize("case", EDS_CASES)
@pytest.mark.parametrize("command", COMMANDS)
def test_a_malformed_eds_is_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                     command: str, case: str) -> None:
    err = one_line_exit_2(command, write_setup(tmp_path, EDS_CASES[case]), capsys)
    assert "node.eds" in err and re.search(EDS_SAYS[case], err), err


@pytest.mark.parametrize("case", EDS_CASES)
@pytest.mark.parametrize("command", ["run", "check"])
def test_a_malformed_eds_sends_nothing_and_writes_no_log(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                                         command: str, case: str) -> None:
    config, log = write_setup(tmp_path, EDS_CASES[case]), tmp_path / "run.mcap"
    argv = [command, str(config), "--bus", f"virtual:bad-eds-{command}"]
    argv += ["--log", str(log), "--duration", "0.01"] if command == "run" else ["--window", "0.05"]
    with can.Bus(interface="virtual", channel=f"bad-eds-{command}") as listener:
        assert main(argv) == EXIT_USAGE
        assert listener.recv(0.0) is None   # not a frame: no NMT, no SDO, no enable
    assert not log.exists()
    assert capsys.readouterr().err.count("\n") == 1


@pytest.mark.parametrize("value", [1.5, 0, -4096, 2**32, "4096"])
@pytest.mark.parametrize("command", COMMANDS)
def test_an_encoder_resolution_0x608f_cannot_hold_is_one_line(
        tmp_path: Path, capsys: pytest.CaptureFixture[str], command: str, value: object) -> None:
    err = one_line_exit_2(command, write_setup(tmp_path, position_per_rev=value), capsys)
    assert "position_per_rev" in err and re.search(r"an integer from 1 to 4294967295", err)


def test_a_whole_resolution_still_runs(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["run", str(write_setup(tmp_path, position_per_rev=2**32 - 1)), "--emulate", "--lockstep",
                 "--duration", "0.01"]) == 0


@pytest.mark.parametrize("command", COMMANDS)
def test_a_file_that_is_not_an_eds_is_one_line_as_a_process(tmp_path: Path, command: str,
                                                            dobhil_forks: DobhilForks) -> None:
    """As a user meets it: a process, its stderr one line, exit 2, no traceback."""
    config = write_setup(tmp_path, EDS_CASES["not INI"])
    argv = [part.format(config=config) for part in COMMANDS[command]]
    done = dobhil_forks.run(argv, tmp_path, timeout=120)
    assert done.returncode == EXIT_USAGE, done.stderr
    assert done.stderr.count("\n") == 1 and "Traceback" not in done.stderr
    assert re.search(EDS_SAYS["not INI"], done.stderr), done.stderr


@pytest.mark.parametrize("node_id", ["profile", "--set"])
@pytest.mark.parametrize("command", COMMANDS)
def test_a_host_heartbeat_on_the_nodes_own_id_is_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                                          command: str, node_id: str) -> None:
    """A node watching the host hears it on 0x700 + host_node_id, its own heartbeat's id when
    the two ids are one: ``check`` and ``analyze`` refuse it before any bus opens, as ``run``
    does, whether the profile or the config's ``drive.node_id`` names the node."""
    config = write_setup(tmp_path, consumer_heartbeat=0.05, host_node_id=5 if node_id == "profile" else 9)
    if node_id == "--set":
        data = yaml.safe_load(config.read_text())
        data["drive"]["node_id"] = 9
        config.write_text(yaml.safe_dump(data))
    err = one_line_exit_2(command, config, capsys)
    assert re.search(r"cia402.host_node_id: expected an id other than the node's \((5|9)\)", err), err


@pytest.mark.parametrize("command", COMMANDS)
def test_an_enable_timeout_shorter_than_the_power_state_machine_is_one_line(
        tmp_path: Path, capsys: pytest.CaptureFixture[str], command: str) -> None:
    """The enable waits for the first statusword and then one SYNC per transition of the
    power state machine (shutdown, switch on, enable operation): 4 SYNC periods at the
    least. enable_timeout 1 ms with a 1 ms SYNC never enabled (and was accepted); 3 ms
    neither, 4 ms does (the emulated node, lockstep)."""
    config = write_setup(tmp_path)
    profile_path = tmp_path / "node.yaml"
    profile = yaml.safe_load(profile_path.read_text())
    profile_path.write_text(yaml.safe_dump({**profile, "enable_timeout": 0.003}))
    err = one_line_exit_2(command, config, capsys)
    assert re.search(r"enable_timeout: expected at least 4 SYNC periods .*0\.004 s.*got 0\.003", err), err
    if command == "run":
        profile_path.write_text(yaml.safe_dump({**profile, "enable_timeout": 0.004}))
        assert main([part.format(config=config) for part in COMMANDS[command]]) == 0


@pytest.mark.parametrize("command", COMMANDS)
def test_a_consumer_heartbeat_0x1016_cannot_hold_is_one_line(
        tmp_path: Path, capsys: pytest.CaptureFixture[str], command: str) -> None:
    """0x1016 holds the consumer time in whole milliseconds: 4.4 ms went to the node as 4 ms,
    a watch shorter than the one the host's period check and heartbeat were made for."""
    err = one_line_exit_2(command, write_setup(tmp_path, consumer_heartbeat=0.0044), capsys)
    assert re.search(r"cia402.consumer_heartbeat: expected 0 \(off\) or a whole number of milliseconds", err), err
