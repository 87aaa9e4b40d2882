"""The CiA 402 preflight probe: SDO reads of identity, CST support,
rated torque and its unit, the PDO mapping and the heartbeat, and the bus budget.

The node is canopen's own ``LocalNode`` (its SDO server, on its own notifier, serving
the project's EDS: not dobhil's emulator) on a private ``virtual`` channel, in real time:
nothing here asserts wall-clock time, only what the node answered. A node that never
answers runs on a scripted bus whose clock moves only while it is read: exact.
"""

from __future__ import annotations

import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import can
import canopen
import pytest

from dobhil.drives.cia402.preflight import CiA402Preflight
from dobhil.drives.preflight import PreflightReport, Severity, run_preflight
from dobhil.drives.profile import DriveProfile
from dobhil.drives.waits import WAIT_SLICE
from dobhil.errors import ConfigError

REPO = Path(__file__).resolve().parents[2]
EMULATED_EDS = REPO / "drivers" / "cia402-emulated.eds"
EPOS4_EDS = REPO / "drivers" / "epos4.eds"
NODE = 5


def profile(node_id: int = NODE, eds: Path = EMULATED_EDS, **options: Any) -> DriveProfile:
    """A CiA 402 profile as SPEC-17's drivers/cia402-emulated.yaml has it (built in code)."""
    section = {"eds": str(eds), "rated_torque": 1.0, "rated_torque_unit": "mNm", "position_per_rev": 1 << 20,
               "velocity_unit": "increments_per_s", "gear_ratio": 1.0, "rpdo": 1, "tpdo": 1, "sdo_timeout": 0.3,
               "consumer_heartbeat": 0.0, **options}
    return DriveProfile(protocol="cia402", firmware="1.0", node_id=node_id, torque_limit=2.0,
                        velocity_limit=50.0, enable_timeout=2.0, feedback_period=1e-3, heartbeat_period=0.1,
                        command_delay_periods=1, name="cia402-emulated", options=section)


@pytest.fixture
def node() -> Iterator[tuple[str, canopen.LocalNode]]:
    """canopen's LocalNode serving the emulated EDS on a fresh virtual channel, heartbeat
    every 100 ms (its NMT slave's producer)."""
    channel = f"cia402-preflight-{uuid.uuid4().hex}"
    network = canopen.Network()
    network.NOTIFIER_CYCLE = WAIT_SLICE   # its reader thread stops within a slice at disconnect
    network.connect(interface="virtual", channel=channel)
    local = network.create_node(NODE, canopen.import_od(str(EMULATED_EDS), NODE))
    local.nmt.start_heartbeat(100)
    try:
        yield channel, local
    finally:
        local.nmt.stop_heartbeat()
        network.disconnect()


def check(channel: str, expected: DriveProfile, *, window: float = 0.5, bitrate: int = 1_000_000) -> PreflightReport:
    host = can.Bus(interface="virtual", channel=channel)
    try:
        return run_preflight(host, expected, period=1e-3, window=window, bitrate=bitrate,
                             probe=CiA402Preflight(expected))
    finally:
        host.shutdown()


def texts(report: PreflightReport, severity: Severity = Severity.MISMATCH) -> list[str]:
    return [f.text for f in report.findings if f.severity is severity]


def test_a_matching_node_passes_with_what_it_answered(node: tuple[str, canopen.LocalNode]) -> None:
    channel, local = node
    local.sdo[0x1018][4].raw = 0x00C0FFEE
    local.sdo[0x1017].raw = 100            # the start-up would write it: here it already is
    report = check(channel, profile())
    assert report.ok, report.lines()
    (seen,) = report.nodes
    # the EDS's values, as canopen's SDO server gives them (cia402-emulated.eds)
    assert ("identity vendor 0x00000000 product 0x00000402 revision 0x00010000 serial 0x00C0FFEE; "
            "modes 0x00000380 (CST supported); rated torque 1000 mNm = 1 Nm; 0x608F (position encoder "
            "resolution) = 1048576 encoder increments / 1 motor revolutions; 0x6091 (gear ratio) = 1 motor "
            "revolutions / 1 shaft revolutions; heartbeat 0x1017 = 100 ms; "
            "statusword 0x0000 (not ready to switch on); PDOs RPDO1 32 bits, TPDO1 64 bits, TPDO2 40 bits"
            ) in seen.summary, seen.summary
    assert seen.status.count >= 2 and "heartbeat every" in seen.summary   # heard while listening
    # SYNC 55 + RPDO1 (4 B) 95 + TPDO1 (8 B) 135 + TPDO2 (5 B) 105 = 390 bits per cycle, plus
    # the 1-byte heartbeat (65 bits) every 100 cycles: 0.65 -> 390.65 bits of 1000 = 39.1 %
    assert report.lines()[1] == ("bus budget: 391 bits per cycle (SYNC 55 + RPDO1 95 + TPDO1 135 + TPDO2 105 + "
                                 "heartbeat 65 x 0.01) = 39.1 % of 1 Mbit/s at 1 kHz")
    assert report.as_dict()["bus_budget"]["bits_per_cycle"] == pytest.approx(390.65)


def test_rated_torque_in_another_unit_is_a_refusing_mismatch(node: tuple[str, canopen.LocalNode]) -> None:
    """An EPOS4 stores 0x6076 in uNm (512871 for an EC 90 flat): read as mNm it would be
    512.871 Nm, and every torque command 513 times too small."""
    channel, local = node
    local.sdo[0x6076].raw = 512871
    report = check(channel, profile())
    assert texts(report) == [
        "node 5's motor rated torque 0x6076 = 512871 mNm = 512.871 Nm is not the profile's cia402.rated_torque "
        "1 Nm: every torque would be scaled by 512.9; set cia402.rated_torque: 512.871 (or, if 0x6076 is in uNm "
        "on this drive, cia402.rated_torque_unit: uNm = 0.512871 Nm)"]
    assert report.refuses and report.lines()[-1].endswith(
        "dobhil run refuses to enable: node 5's motor rated torque 0x6076 = 512871 mNm = 512.871 Nm is not the "
        "profile's cia402.rated_torque 1 Nm")
    # the same node with the unit and value it has: no mismatch
    report = check(channel, profile(rated_torque=0.512871, rated_torque_unit="uNm"))
    assert report.ok, report.lines()


def test_an_encoder_resolution_other_than_the_profiles_is_a_refusing_mismatch(
        node: tuple[str, canopen.LocalNode]) -> None:
    """The drive states 4096 increments per revolution, the profile 2^20: every position
    and velocity would be 256 times too small."""
    channel, local = node
    local.sdo[0x608F][1].raw = 4096
    report = check(channel, profile())
    assert "0x608F (position encoder resolution) = 4096 encoder increments / 1 motor revolutions" in \
        report.nodes[0].summary
    assert texts(report) == [
        "node 5's 0x608F (position encoder resolution) = 4096 encoder increments / 1 motor revolutions = 4096 is "
        "not the profile's cia402.position_per_rev 1048576: every position and velocity would be off by a factor "
        "0.00390625; set cia402.position_per_rev: 4096 (or fix the drive)"]
    assert report.refuses
    # the gear the same way: 0x6091 = 26 / 1 against the profile's 1
    local.sdo[0x608F][1].raw = 1 << 20
    local.sdo[0x6091][1].raw = 26
    assert texts(check(channel, profile())) == [
        "node 5's 0x6091 (gear ratio) = 26 motor revolutions / 1 shaft revolutions = 26 is not the profile's "
        "cia402.gear_ratio 1: every position and velocity would be off by a factor 26; set cia402.gear_ratio: 26 "
        "(or fix the drive)"]
    assert check(channel, profile(gear_ratio=26)).ok


def test_an_encoder_resolution_the_node_lacks_is_a_note(node: tuple[str, canopen.LocalNode]) -> None:
    """The EDS lists 0x608F, the drive aborts its read (object does not exist): not checked,
    not refused."""
    channel, local = node

    def absent(index: int, subindex: int, od: Any) -> None:
        if index == 0x608F:
            raise canopen.SdoAbortedError(0x06020000)

    local.add_read_callback(absent)
    local.sdo[0x1017].raw = 100            # (no heartbeat note: only the encoder's)
    report = check(channel, profile())
    assert report.ok, report.lines()
    assert texts(report, Severity.NOTE) == [
        "node 5 aborted the SDO upload of 0x608F (position encoder resolution): Code 0x06020000, Object does "
        "not exist: cia402.position_per_rev not checked against the drive"]
    assert "0x608F" not in report.nodes[0].summary and "0x6091 (gear ratio) = 1 motor" in report.nodes[0].summary


def test_no_cst_and_an_enabled_drive_refuse(node: tuple[str, canopen.LocalNode]) -> None:
    channel, local = node
    local.sdo[0x6502].raw = 0x180          # CSP and CSV (bits 7, 8), no CST (bit 9)
    local.sdo[0x6041].raw = 0x0637         # operation enabled: 0x37 & 0x6F = 0x27
    found = texts(check(channel, profile()))
    assert found == [
        "node 5 does not support cyclic synchronous torque: 0x6502 = 0x00000180, bit 9 (CST) clear; dobhil "
        "runs CiA 402 drives in CST",
        "node 5 is in operation enabled (statusword 0x0637): another host may be driving it; disable it first"]


@pytest.mark.parametrize("statusword", [0x0218, 0x021F], ids=["fault", "fault-reaction-active"])
def test_a_node_in_fault_is_a_mismatch_the_reset_clears(node: tuple[str, canopen.LocalNode], statusword: int) -> None:
    """The enable refuses a node in fault unless --reset-faults: the check says so, not 'ok'."""
    channel, local = node
    local.sdo[0x6041].raw = statusword
    report = check(channel, profile(), window=0.05)
    state = "fault" if statusword == 0x0218 else "fault reaction active"
    assert not report.ok and not report.refuses and texts(report) == [
        f"node 5 is in {state} (statusword 0x{statusword:04X}): dobhil run --reset-faults resets it "
        "(controlword bit 7) once the cause is gone"]


def test_the_heartbeat_setting_differs_a_note(node: tuple[str, canopen.LocalNode]) -> None:
    channel, local = node
    local.sdo[0x1017].raw = 0
    report = check(channel, profile())
    assert report.ok and texts(report, Severity.NOTE) == [
        "node 5's producer heartbeat 0x1017 is off, the profile's heartbeat_period 100 ms: the drive's "
        "start-up writes it"]


def test_a_pdo_mapping_that_does_not_fit_is_bad_input(tmp_path: Path) -> None:
    """An EDS that types 0x6077 as INTEGER32 makes TPDO1 16 + 32 + 32 = 80 bits: over a
    PDO's 64. The drive's own check refuses it in one line before anything is sent."""
    text = EMULATED_EDS.read_text()
    start = text.index("[6077]")
    end = text.index("\n[", start + 1)
    section = text[start:end].replace("DataType=0x0003", "DataType=0x0004")
    assert section != text[start:end]
    wide = tmp_path / "wide.eds"
    wide.write_text(text[:start] + section + text[end:])
    bus = SilentBus()
    expected = profile(eds=wide)
    try:
        with pytest.raises(ConfigError, match="PDO 1 mapping does not fit") as info:
            run_preflight(bus, expected, period=1e-3, window=0.5, probe=CiA402Preflight(expected),
                          clock=bus.clock)
    finally:
        bus.shutdown()
    assert "\n" not in str(info.value) and "80 bits" in str(info.value) and bus.sent == []


def test_over_budget_at_250_kbit(node: tuple[str, canopen.LocalNode]) -> None:
    # 390.65 bits per 1 ms at 250 kbit/s = 156 %; 800 kbit/s: 49 %; 2.24 ms at 250 kbit/s
    # (tests/drives/test_bus_budget.py works the numbers by hand), for the loop and the SYNC:
    # the SYNC and its TPDOs every 1 ms alone are over 70 % of 250 kbit/s
    channel, _ = node
    report = check(channel, profile(), bitrate=250_000)
    assert ("bus budget 156 % of 250 kbit/s at 1 kHz is over 70 %: use a higher bit rate (800 kbit/s on the "
            "drive and the interface: 49 %), or a slower loop (loop.period and the profile's feedback_period "
            ">= 2.24 ms), or fewer TPDOs") in texts(report)
    assert not report.refuses   # said, not refused


class SilentBus(can.BusABC):
    """Nobody answers; its clock moves only while it is read (exact, whatever the load)."""

    def __init__(self) -> None:
        self.now = 0.0
        self.sent: list[can.Message] = []
        super().__init__(channel="silent")

    def clock(self) -> float:
        return self.now

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self.sent.append(msg)

    def recv(self, timeout: float | None = None) -> can.Message | None:
        # recv itself, not _recv_internal: BusABC.recv would call that again and again
        # until the WALL clock says the timeout passed
        assert timeout is not None and timeout <= WAIT_SLICE + 1e-12   # sliced waits only
        self.now += timeout
        return None

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        raise AssertionError("recv is overridden")


def test_a_node_that_never_answers_is_one_line() -> None:
    bus = SilentBus()
    expected = profile(node_id=9)
    try:
        report = run_preflight(bus, expected, period=1e-3, window=0.5, bitrate=1_000_000,
                               probe=CiA402Preflight(expected), clock=bus.clock, stamp=lambda _m: bus.clock())
    finally:
        bus.shutdown()
    assert texts(report) == ["node 9 does not answer SDO: no reply to the upload of 0x1018:01 (identity: "
                             "vendor id) within 0.3 s"]
    assert texts(report, Severity.NOTE) == [] and report.refuses and report.nodes == ()
    assert report.lines()[-1] == ("preflight: 1 mismatch(es) -- dobhil run refuses to enable: node 9 does not "
                                  "answer SDO")
    # it asked once (initiate upload 0x40 of 0x1018:01 to 0x600 + 9), then canopen's own
    # abort (0x80, code 0x05040000 "SDO protocol timed out"; canopen leaves the index 0)
    assert [(m.arbitration_id, bytes(m.data).hex()) for m in bus.sent] == [
        (0x609, "4018100100000000"), (0x609, "8000000000000405")]
    # and listened out the window: the SDO wait (0.3 s) was part of it
    assert bus.now == pytest.approx(0.5, abs=WAIT_SLICE)


def test_a_stop_request_ends_the_sdo_wait_within_a_slice() -> None:
    bus = SilentBus()
    expected = profile(node_id=9, sdo_timeout=5.0)
    try:
        report = run_preflight(bus, expected, period=1e-3, window=10.0, probe=CiA402Preflight(expected),
                               clock=bus.clock, stamp=lambda _m: bus.clock(),
                               cancel=lambda: "received SIGINT" if bus.now > 0.1 else "")
    finally:
        bus.shutdown()
    assert bus.now <= 0.1 + 2 * WAIT_SLICE
    assert report.nodes == ()


def test_the_epos4_profile_against_a_node_serving_its_eds() -> None:
    """drivers/epos4.yaml with drivers/epos4.eds (maxon's DCF values) served by canopen's
    LocalNode: the identity is maxon's (vendor 0xFB), CST is supported (0x6502 = 0x3A5:
    bits 0, 2, 5, 7, 8, 9), and 0x6076 = 512871 read in uNm is the profile's 0.512871 Nm."""
    from dobhil.drives import load_profile
    epos4 = load_profile("epos4")
    channel = f"cia402-preflight-{uuid.uuid4().hex}"
    network = canopen.Network()
    network.NOTIFIER_CYCLE = WAIT_SLICE
    network.connect(interface="virtual", channel=channel)
    network.create_node(epos4.node_id, canopen.import_od(str(EPOS4_EDS), epos4.node_id))
    try:
        report = check(channel, epos4)
    finally:
        network.disconnect()
    assert report.ok, report.lines()
    (node,) = report.nodes
    assert ("identity vendor 0x000000FB product 0x65520000 revision 0x01700000 serial 0x00000000; modes "
            "0x000003A5 (CST supported); rated torque 512871 uNm = 0.512871 Nm") in node.summary, node.summary
    assert "statusword 0x0040 (switch on disabled)" in node.summary   # the DCF's statusword
