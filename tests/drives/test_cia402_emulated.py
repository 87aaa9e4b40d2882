"""CiA402Drive against the emulated CiA 402 node (dobhil.drives.cia402.emulator) in lockstep, and the
``dobhil run --emulate --lockstep`` path: enable, closed loop, safe stop, faults, bad input."""

from __future__ import annotations

import re
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import can
import pytest
import yaml

from dobhil.cli.main import main
from dobhil.drives.base import Confirmation, DriveState
from dobhil.drives.cia402.drive import CiA402Drive
from dobhil.drives.load import load_profile, profile_from_mapping
from dobhil.drives.profile import DriveProfile
from dobhil.drives.cia402.emulator import EmulatedCiA402
from dobhil.emulator.plant import Plant
from dobhil.drives.emulated import LockstepBus
from dobhil.drives.emulated import private_virtual_channel
from dobhil.errors import ConfigError, DriveError, DriveFaultError

ROOT = Path(__file__).resolve().parents[2]
PROFILE = ROOT / "drivers" / "cia402-emulated.yaml"
EDS = ROOT / "drivers" / "cia402-emulated.eds"
DEMO = ROOT / "configs" / "demo.yaml"


class Rig:
    """The drive and the emulated node on a private virtual channel behind a LockstepBus."""

    def __init__(self, *, inertia: float = 0.01, reset_faults: bool = False,
                 node_profile: DriveProfile | None = None) -> None:
        """``node_profile``: the node's own (its units, its EDS) when not the host's."""
        self.profile = load_profile(PROFILE)
        self.channel = channel = private_virtual_channel()
        self.emu_bus = can.Bus(interface="virtual", channel=channel)
        self.inner = can.Bus(interface="virtual", channel=channel)
        self.plant = Plant(inertia=inertia)
        self.emu = EmulatedCiA402(self.emu_bus, node_profile or self.profile, self.plant)
        self.bus = LockstepBus(self.inner, [self.emu], dt=0.001)
        self.drive = self.new_drive(reset_faults=reset_faults)

    def new_drive(self, *, reset_faults: bool = False) -> CiA402Drive:
        return CiA402Drive(self.bus, self.profile, clock=self.bus.clock, reset_faults=reset_faults)

    def close(self) -> None:
        self.bus.shutdown()
        self.emu.close()
        self.inner.shutdown()


@pytest.fixture
def rig() -> Iterator[Rig]:
    made = Rig()
    try:
        yield made
    finally:
        made.close()


def test_enable_reaches_operation_enabled_in_cst(rig: Rig) -> None:
    rig.drive.enable()
    assert rig.drive.status.state is DriveState.ENABLED
    assert rig.emu.nmt_state == "OPERATIONAL"
    assert rig.emu.statusword & 0x6F == 0x27            # operation enabled
    assert rig.bus.clock() < 0.01                       # shutdown, switch on, enable at three SYNCs


def test_torque_in_per_mille_moves_the_plant_as_tau_over_j(rig: Rig) -> None:
    rig.drive.enable()
    first = rig.drive.poll(0.01)
    assert first is not None
    for _ in range(500):
        rig.drive.send_torque(0.2)
        fb = rig.drive.poll(0.01)
        assert fb is not None and fb.sampled_at <= rig.bus.clock()
    assert rig.emu.target_torque == 200                 # per mille of the 1 Nm rated torque
    # 0.2 Nm / 0.01 kg m^2 for 499 periods: each command acts from the next SYNC on
    assert fb.velocity == pytest.approx(0.2 / 0.01 * 0.499, rel=0.01)


def test_safe_stop_is_confirmed_and_the_node_is_disabled(rig: Rig) -> None:
    rig.drive.enable()
    rig.drive.send_torque(0.3)
    rig.drive.poll(0.01)
    report = rig.drive.safe_stop()
    assert report.confirmation is Confirmation.CONFIRMED, report
    assert rig.emu.statusword & 0x6F != 0x27 and rig.emu.target_torque == 0


def test_an_over_torque_emcy_stops_with_its_code(rig: Rig) -> None:
    rig.drive.enable()
    with pytest.raises(DriveFaultError) as info:
        for _ in range(20):
            rig.drive.send_torque(2.5)   # above the profile's 2 Nm torque limit: EMCY 0x8311
            rig.drive.poll(0.01)
    assert "EMCY 0x8311 (Monitoring)" in str(info.value)
    assert rig.drive.status.error_code == 0x8311


def test_a_faulted_node_is_refused_without_reset_faults_and_reset_with_it(rig: Rig) -> None:
    rig.drive.enable()
    with pytest.raises(DriveFaultError):
        for _ in range(20):
            rig.drive.send_torque(2.5)
            rig.drive.poll(0.01)
    rig.drive.safe_stop()
    again = rig.new_drive()
    with pytest.raises(DriveFaultError, match=r"node 5 is in fault: EMCY 0x8311 \(Monitoring\); not reset"):
        again.enable()
    assert rig.emu.statusword & 0x4F == 0x08             # still in fault: nothing was reset
    reset = rig.new_drive(reset_faults=True)
    reset.enable()
    assert reset.status.state is DriveState.ENABLED


def test_lockstep_cycles_per_second(rig: Rig, record_property: Any) -> None:
    """Measured, not asserted against a number: the bench reports it (tools/bench.py)."""
    rig.drive.enable()
    cycles = 2000
    start = time.perf_counter()
    for _ in range(cycles):
        rig.drive.send_torque(0.0)
        assert rig.drive.poll(0.01) is not None
    rate = cycles / (time.perf_counter() - start)
    record_property("lockstep_cycles_per_s_cia402", round(rate))
    assert rig.bus.clock() == pytest.approx(cycles * 0.001, abs=0.02)   # one SYNC per cycle


# -- the command line -------------------------------------------------------

def _run(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    code = main(argv)
    out, err = capsys.readouterr()
    return code, out, err


def _config(tmp_path: Path, profile: str) -> Path:
    config = tmp_path / "cia402.yaml"
    config.write_text(DEMO.read_text().replace("profile: odrive-0.6", f"profile: {profile}"))
    return config


def test_run_emulate_lockstep_converges(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code, out, err = _run(["run", str(_config(tmp_path, "cia402-emulated")), "--emulate", "--lockstep"], capsys)
    assert code == 0, err
    final = re.search(r"tau_ref ([-\d.]+) N m, tau_int\^ ([-\d.]+) N m, true tau_int ([-\d.]+) N m", out)
    assert final is not None, out
    ref, estimate, true = map(float, final.groups())
    assert true == pytest.approx(ref, abs=0.01) and estimate == pytest.approx(ref, abs=0.01)


def _variant(tmp_path: Path, eds_change: Any = None, **section: Any) -> Path:
    eds = tmp_path / "node.eds"
    text = EDS.read_text()
    eds.write_text(eds_change(text) if eds_change else text)
    data = yaml.safe_load(PROFILE.read_text())
    data["cia402"] = {**data["cia402"], "eds": str(eds), **section}
    profile = tmp_path / "node.yaml"
    profile.write_text(yaml.safe_dump(data))
    return profile


@pytest.mark.parametrize(("eds_change", "section", "says"), [
    (lambda t: re.sub(r"\[6071\]\n(?:[^\[\n].*\n|\n)*", "", t), {}, "object 0x6071 (target torque) missing"),
    (lambda t: re.sub(r"(\[6502\](?:\n.*)*?DefaultValue=)0x00000380", r"\g<1>0x00000180", t), {},
     "has no cyclic synchronous torque (bit 9)"),
    (lambda t: re.sub(r"(\[6076\](?:\n.*)*?DefaultValue=)1000", r"\g<1>0", t), {},
     "0x6076 (motor rated torque) = 0: a rated torque of 0"),
    (lambda t: re.sub(r"(\[6077\](?:\n.*)*?DataType=)0x0003", r"\g<1>0x0004", t), {},
     "PDO 1 mapping does not fit"),
    (None, {"rated_torque": 0}, "cia402.rated_torque: expected a number > 0"),
    (None, {"gear": 2}, "unknown key 'cia402.gear' (allowed in cia402: eds, "),
])
def test_bad_input_is_one_line_and_exit_2(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                           eds_change: Any, section: dict[str, Any], says: str) -> None:
    config = _config(tmp_path, str(_variant(tmp_path, eds_change, **section)))
    code, out, err = _run(["run", str(config), "--emulate", "--lockstep"], capsys)
    assert code == 2
    assert len(err.strip().splitlines()) == 1 and says in err, err
    assert "cycles" not in out   # no loop ran: nothing was enabled


def test_a_node_reporting_no_cst_ends_start_up_in_one_line(rig: Rig) -> None:
    """The EDS says CST, the node (its 0x6502 changed at run time) does not."""
    rig.emu.node.sdo[0x6502].raw = 0x00000080
    with pytest.raises(DriveError) as info:
        rig.drive.enable()
    assert str(info.value) == ("node 5: 0x6502 (supported drive modes) = 0x00000080: no cyclic synchronous "
                               "torque (bit 9), the only mode dobhil drives (reached: pre-operational, "
                               "identity read, statusword read)")
    assert rig.emu.statusword & 0x6F != 0x27
    assert rig.drive.safe_stop().warning() == ""   # never operational: nothing to cut power for


def test_a_node_stating_another_encoder_resolution_is_refused_in_one_line() -> None:
    """The node encodes 0x6064 at 4096 increments per revolution and says so in 0x608F; the
    host's profile says 2^20. Trusting the config would scale every position and velocity
    by 1/256: the start-up refuses before anything is enabled."""
    import dataclasses
    shipped = load_profile(PROFILE)
    made = Rig(node_profile=dataclasses.replace(shipped, options={**shipped.options, "position_per_rev": 4096}))
    try:
        with pytest.raises(DriveError) as info:
            made.drive.enable()
        assert str(info.value) == (
            "node 5: 0x608F (position encoder resolution) = 4096 encoder increments / 1 motor revolutions = 4096, "
            "the profile's cia402.position_per_rev is 1048576: every position and velocity would be off by a "
            "factor 0.00390625; set cia402.position_per_rev: 4096 (or fix the drive) (reached: pre-operational, "
            "identity read, statusword read, supported modes read, rated torque read)")
        assert made.emu.nmt_state != "OPERATIONAL" and made.emu.statusword & 0x6F != 0x27   # nothing enabled
        assert made.drive.safe_stop().warning() == ""
    finally:
        made.close()


def test_a_node_without_the_encoder_object_is_a_note_and_runs(tmp_path: Path) -> None:
    """The host's EDS lists 0x608F; this node has none (its EDS lacks it) and aborts the
    read: noted, not refused (the units cannot be checked on it)."""
    import dataclasses
    eds = tmp_path / "no-608f.eds"
    eds.write_text(re.sub(r"\[608F(?:sub\d)?\]\n(?:[^\[\n].*\n|\n)*", "", EDS.read_text()))
    shipped = load_profile(PROFILE)
    made = Rig(node_profile=dataclasses.replace(shipped, options={**shipped.options, "eds": str(eds)}))
    try:
        assert 0x608F not in made.emu.node.object_dictionary
        made.drive.enable()
        assert made.drive.status.state is DriveState.ENABLED
        assert made.drive.notes == [
            "node 5: 0x608F (position encoder resolution) not read, aborted 0x06020000 (Object does not exist): "
            "cia402.position_per_rev 1048576 not checked"]
        made.drive.safe_stop()
    finally:
        made.close()


def test_dobhil_run_prints_the_drives_notes(capsys: pytest.CaptureFixture[str]) -> None:
    from dobhil.cli.run_cmd import report
    report({"cycles": 0, "drive_notes": ["node 5: 0x608F not read"]}, "stop: x", as_json=False)
    assert capsys.readouterr().err.splitlines() == [
        "dobhil run: note (not refused: the run went on): node 5: 0x608F not read", "dobhil run: stop: x"]


def test_the_shipped_demo_matches_the_analysis_within_the_torque_quantum(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """configs/cia402-demo.yaml in lockstep: the emulated plant is the analysis' exact model,
    so ``dobhil report``'s prediction differs from the measured tau_int^ only by what the
    drive quantises. With a 20-bit encoder that is the torque command's per mille of the
    rated torque (1 N m / 1000 = 1e-3 N m): the RMS difference stays below one quantum.
    (With 4096 increments per revolution and rpm the position and velocity quanta made it
    0.0216 N m; with the 20-bit encoder it is about 2e-5 N m.)"""
    import json
    log = tmp_path / "demo.mcap"
    code, out, err = _run(["run", str(ROOT / "configs" / "cia402-demo.yaml"), "--emulate", "--lockstep",
                           "--log", str(log)], capsys)
    assert code == 0, err
    code, out, err = _run(["report", str(log), "--out", str(tmp_path / "report"), "--json"], capsys)
    assert code == 0, err
    prediction = json.loads(out)["prediction"]
    assert prediction["available"], prediction
    quantum = float(load_profile(PROFILE).options["rated_torque"]) / 1000.0   # 0x6071 per mille
    assert 0 < prediction["rms_difference"] < quantum, prediction


def test_profile_built_in_code_needs_the_feedback_period() -> None:
    data = yaml.safe_load(PROFILE.read_text())
    del data["feedback_period"]
    with pytest.raises(ConfigError, match="missing key 'feedback_period'"):
        profile_from_mapping(data, source="p")


def _consumer_rig(consumer: float) -> Rig:
    import dataclasses
    made = Rig()
    made.profile = dataclasses.replace(made.profile, options={**made.profile.options,
                                                              "consumer_heartbeat": consumer})
    made.drive = made.new_drive()
    return made


def test_the_node_watches_the_hosts_heartbeat_and_stops_watching_after_a_clean_stop() -> None:
    made = _consumer_rig(0.05)
    try:
        made.drive.enable()
        for _ in range(300):   # 0.3 s: six consumer times
            made.drive.send_torque(0.1)
            assert made.drive.poll(0.01) is not None
        assert made.emu._last_host_heartbeat is not None          # it heard the host
        assert made.drive.safe_stop().confirmation is Confirmation.CONFIRMED
        made.bus.recv(0.5)     # the host's heartbeat has stopped: the node must not care
        assert made.emu.protocol_error == 0 and made.emu.statusword & 0x4F != 0x08
    finally:
        made.close()


def test_a_host_heartbeat_that_stops_is_a_fault_on_the_node() -> None:
    made = _consumer_rig(0.05)
    try:
        made.drive.enable()
        for _ in range(30):   # the node watches from the first heartbeat it hears on
            made.drive.send_torque(0.1)
            made.drive.poll(0.01)
        made.drive._stop_host_heartbeat()   # the host as if its process had died
        with pytest.raises(DriveFaultError) as info:
            for _ in range(300):
                made.drive.send_torque(0.1)
                made.drive.poll(0.01)
        assert "EMCY 0x8130" in str(info.value)
        assert made.drive.status.watchdog_tripped
    finally:
        made.close()


def test_a_recorded_lockstep_run_replays_bit_for_bit(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """The drive decodes the recorded frames again (without its start-up: the layouts are
    the standard's), so the replayed controller sees exactly what the run's saw."""
    log = tmp_path / "run.mcap"
    config = _config(tmp_path, "cia402-emulated")
    code, out, err = _run(["run", str(config), "--emulate", "--lockstep", "--duration", "0.3", "--log", str(log)],
                          capsys)
    assert code == 0, err
    code, out, err = _run(["replay", str(log), "--verify"], capsys)
    assert code == 0, err
    assert "identical: every command and estimate reproduced bit for bit" in out, out




def test_in_real_time_the_node_answers_the_newest_of_queued_syncs(rig: Rig) -> None:
    """SYNCs that queued while the node was busy: a drive runs its cycle from the newest one;
    answering each in turn would put the node ever further behind the host (in a slow guest
    at 1 kHz: a disable acknowledged after the host had given up). Real time only: lockstep
    reads one frame at a time, deterministically."""
    rig.drive.enable()
    host = can.Bus(interface="virtual", channel=rig.channel)
    try:
        while host.recv(0.0) is not None:
            pass
        answered_before = rig.emu.sync_count
        for _ in range(5):    # queued before the node's thread reads its bus: one batch
            host.send(can.Message(arbitration_id=0x080, is_extended_id=False, data=b""))
        rig.emu.start()
        tpdo1 = []
        end = time.monotonic() + 5.0
        while time.monotonic() < end and len(tpdo1) < 1:
            msg = host.recv(0.1)
            if msg is not None and msg.arbitration_id == 0x185:
                tpdo1.append(msg)
        assert wait_until_quiet(host, 0x185, 0.3) == 0     # no answers to the older four
        assert len(tpdo1) == 1
        assert rig.emu.sync_count - answered_before == 1
        assert rig.emu.syncs_missed == 4
    finally:
        rig.emu.stop()
        host.shutdown()


def wait_until_quiet(bus: can.BusABC, arbitration_id: int, quiet: float) -> int:
    """Frames with ``arbitration_id`` seen on ``bus`` during ``quiet`` s."""
    seen = 0
    end = time.monotonic() + quiet
    while time.monotonic() < end:
        msg = bus.recv(0.02)
        seen += msg is not None and msg.arbitration_id == arbitration_id
    return seen
