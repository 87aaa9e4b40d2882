"""``dobhil check`` on a CiA 402 config, across processes: ``dobhil
emulate configs/cia402-demo.yaml`` in a second process on the project's hub (loopback
python-can-remote), ``dobhil check`` in this one -- as on can0 with a real node. The
check reads the node by SDO and reports identity, modes and the bus budget, without
enabling it; a node id that nobody answers is one line naming the node and the SDO
object, exit 1. Nothing here asserts wall-clock time (the hub adds milliseconds): the
SDO timeout is made generous where the node must answer, and only what the node answered
is checked.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from dobhil.cli.main import main

from .helpers import REPO
from .hub import child_env, stop_process, wait_for_emulator

CIA402_DEMO = REPO / "configs" / "cia402-demo.yaml"
EXIT_MISMATCH = 1


def slow_profile(tmp_path: Path, node_id: int = 5, sdo_timeout: float = 2.0) -> Path:
    """cia402-emulated with an SDO timeout for a hub on a loaded machine (and another node id)."""
    text = (REPO / "drivers" / "cia402-emulated.yaml").read_text()
    text = text.replace("node_id: 5", f"node_id: {node_id}")
    text = text.replace("sdo_timeout: 0.3", f"sdo_timeout: {sdo_timeout:g}")
    text = text.replace("eds: cia402-emulated.eds", f"eds: {REPO / 'drivers' / 'cia402-emulated.eds'}")
    path = tmp_path / f"cia402-node{node_id}.yaml"
    path.write_text(text)
    return path


def test_check_reads_the_emulated_node_in_another_process(tmp_path: Path, hub: int,
                                                          capsys: pytest.CaptureFixture[str]) -> None:
    url = f"remote:ws://127.0.0.1:{hub}/"
    out = tmp_path / "emulate.log"
    with out.open("wb") as log:
        emulate = subprocess.Popen(
            [sys.executable, "-m", "dobhil", "emulate", str(CIA402_DEMO), "--bus", url, "--duration", "60"],
            stdout=log, stderr=subprocess.STDOUT, env=child_env(), cwd=REPO)
    try:
        wait_for_emulator(emulate, out, "cia402")
        profile = slow_profile(tmp_path)
        # the default window: this node sends nothing unasked (heartbeat 0x1017 = 0) and the
        # SDO reads take what they take, whatever the window
        code = main(["check", str(CIA402_DEMO), "--bus", url, "--set", f"drive.profile={profile}"])
        lines = capsys.readouterr().out.splitlines()
        assert code == 0, lines
        (node,) = [line for line in lines if line.startswith("node 5: ")]
        # the emulated node's identity and modes (drivers/cia402-emulated.eds), through SDO
        assert ("identity vendor 0x00000000 product 0x00000402 revision 0x00010000" in node
                and "modes 0x00000380 (CST supported); rated torque 1000 mNm = 1 Nm" in node), node
        assert "PDOs RPDO1 32 bits, TPDO1 64 bits, TPDO2 40 bits" in node
        # the encoder and gear the node states (its 20-bit encoder), as the profile has them: no mismatch
        assert ("0x608F (position encoder resolution) = 1048576 encoder increments / 1 motor revolutions; "
                "0x6091 (gear ratio) = 1 motor revolutions / 1 shaft revolutions") in node, node
        assert ("bus budget: 391 bits per cycle (SYNC 55 + RPDO1 95 + TPDO1 135 + TPDO2 105 + heartbeat 65 x 0.01)"
                " = 39.1 % of 1 Mbit/s at 1 kHz") in lines
        assert lines[-1] == "preflight: ok"

        # a node id nobody has: one line naming the node and the object, exit 1 (the shipped
        # SDO timeout: waited in vain however long, nobody at node 9 answers)
        code = main(["check", str(CIA402_DEMO), "--bus", url,
                     "--set", f"drive.profile={slow_profile(tmp_path, 9, sdo_timeout=0.3)}"])
        lines = capsys.readouterr().out.splitlines()
        assert code == EXIT_MISMATCH, lines
        mismatches = [line for line in lines if line.startswith("mismatch: ")]
        assert len(mismatches) == 1, lines
        assert mismatches[0].startswith("mismatch: node 9 does not answer SDO: no reply to the upload of "
                                        "0x1018:01 (identity: vendor id) within 0.3 s")
        assert lines[-1] == "preflight: 1 mismatch(es) -- dobhil run refuses to enable: node 9 does not answer SDO"
    finally:
        stop_process(emulate)
    assert "emulator stopped" in out.read_text(errors="replace")


def test_the_check_changes_nothing_on_the_emulated_node_in_lockstep() -> None:
    """Against dobhil's emulated node in lockstep (simulated time, exact): what the check
    reads, that it listens the whole window on the simulated clock, and that the node is
    left as it was: NMT pre-operational, switch on disabled, the EDS's heartbeat and
    cycle period (nothing written, no NMT command)."""
    import can

    from dobhil.drives import load_profile
    from dobhil.drives.preflight import run_preflight
    from dobhil.drives.registry import preflight_probe
    from dobhil.drives.cia402.emulator import EmulatedCiA402
    from dobhil.emulator.plant import Plant
    from dobhil.drives.emulated import LockstepBus
    from dobhil.drives.emulated import private_virtual_channel

    profile = load_profile("cia402-emulated")
    channel = private_virtual_channel()
    emu_bus = can.Bus(interface="virtual", channel=channel)
    inner = can.Bus(interface="virtual", channel=channel)
    emu = EmulatedCiA402(emu_bus, profile, Plant(inertia=0.25))
    lock = LockstepBus(inner, [emu], dt=1e-3)
    try:
        written = (emu.node.sdo[0x1017].raw, emu.node.sdo[0x1006].raw)   # the EDS's defaults
        report = run_preflight(lock, profile, period=1e-3, window=0.5, bitrate=1_000_000,
                               probe=preflight_probe(profile), clock=lock.clock, stamp=lambda _m: lock.clock())
        # the node booted (its first tick) and stayed there
        assert (emu.nmt_state, emu.state.name) == ("PRE-OPERATIONAL", "SWITCH_ON_DISABLED")
        assert (emu.node.sdo[0x1017].raw, emu.node.sdo[0x1006].raw) == written == (0, 0)
        assert lock.clock() == pytest.approx(0.5, abs=1e-3)
    finally:
        lock.shutdown()
        emu.close()
        inner.shutdown()
    assert report.ok, report.lines()
    (node,) = report.nodes
    assert node.summary.endswith(
        "identity vendor 0x00000000 product 0x00000402 revision 0x00010000 serial 0x00000001; modes 0x00000380 "
        "(CST supported); rated torque 1000 mNm = 1 Nm; 0x608F (position encoder resolution) = 1048576 encoder "
        "increments / 1 motor revolutions; 0x6091 (gear ratio) = 1 motor revolutions / 1 shaft revolutions; "
        "heartbeat 0x1017 = 0 ms; statusword 0x0250 (switch on "
        "disabled); PDOs RPDO1 32 bits, TPDO1 64 bits, TPDO2 40 bits"), node.summary
