"""CiA402Drive against the test tree's node (canopen's LocalNode + a small state machine,
:mod:`tests.drives.cia402_node`, not dobhil's emulator), pumped in simulated time: start-up,
enable, cycle, faults, safe stop, replay; and every start-up failure as one line with nothing
enabled."""

from __future__ import annotations

import itertools
import math
import re
import time
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from pathlib import Path
from typing import Any

import can
import canopen
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from dobhil.drives.base import Confirmation, DriveState
from dobhil.drives.cia402.drive import CiA402Drive
from dobhil.drives.load import load_profile, profile_from_mapping
from dobhil.errors import ConfigError, DriveError, DriveFaultError, DriveTimeoutError, WaitCancelled

from .cia402_node import EDS, HostSyncPumpBus, NodeState, PumpBus, TestNode402

PROFILE = Path(__file__).resolve().parents[2] / "drivers" / "cia402-emulated.yaml"
#: the mapping the drive must write (CiA 301 mapping entries: index << 16 | sub << 8 | bits)
EXPECTED_MAPS = {0x1600: (0x60400010, 0x60710010), 0x1A00: (0x60410010, 0x60640020, 0x60770010),
                 0x1A01: (0x606C0020, 0x60610008)}
_CHANNELS = itertools.count()


def profile(**section: Any) -> Any:
    import yaml
    data = yaml.safe_load(PROFILE.read_text())
    # the fake node's units: 4096 increments per revolution (it says so in 0x608F), rpm
    data["cia402"] = {**data["cia402"], "eds": str(EDS), "position_per_rev": 4096, "velocity_unit": "rpm",
                      **section}
    return profile_from_mapping(data, source="test profile")


@contextmanager
def pumped(bus_type: type[PumpBus] = PumpBus, *, on_bus: bool = True,
           **node: Any) -> Iterator[tuple[PumpBus, TestNode402]]:
    """A booted node and the host's bus to it, both shut down afterwards. ``on_bus=False``:
    the node listens on another channel, so the host's bus is silent."""
    channel = f"cia402-drive-{next(_CHANNELS)}"
    node_channel = channel if on_bus else f"{channel}-elsewhere"
    the_node = TestNode402(can.Bus(interface="virtual", channel=node_channel), 5, **node)
    bus = bus_type(channel, the_node)
    the_node.boot()
    try:
        yield bus, the_node
    finally:
        bus.shutdown()
        the_node.close()


@pytest.fixture
def stack() -> Iterator[ExitStack]:
    with ExitStack() as exits:
        yield exits


@pytest.fixture
def rig(stack: ExitStack) -> Any:
    """``rig(bus_type=..., reset_faults=..., **node)`` -> (bus, node, drive), closed after the test."""
    def make(*, bus_type: type[PumpBus] = PumpBus, reset_faults: bool = False,
             **node: Any) -> tuple[PumpBus, TestNode402, CiA402Drive]:
        bus, the_node = stack.enter_context(pumped(bus_type, **node))
        drive = CiA402Drive(bus, profile(), clock=bus.clock, reset_faults=reset_faults)
        return bus, the_node, drive
    return make


@pytest.fixture
def idle_bus(stack: ExitStack) -> PumpBus:
    """A bus for drives that are only made (profile and EDS checks) or fed frames by hand."""
    return stack.enter_context(pumped())[0]


def _mapping(node: TestNode402, index: int) -> tuple[int, ...]:
    return tuple(node.raw(index, sub) for sub in range(1, node.raw(index, 0) + 1))


def _periodic_syncs(bus: PumpBus) -> list[float]:
    """The periods of the SYNC tasks running on ``bus``."""
    return [t.period for t in bus.tasks if not t.stopped and t.msg.arbitration_id == 0x80]


# -- start-up and enable ------------------------------------------------------

def test_start_up_maps_the_node_and_enables_cst(rig: Any) -> None:
    bus, node, drive = rig()
    drive.enable()
    assert drive.status.state is DriveState.ENABLED
    raw = node.raw
    for index, entries in EXPECTED_MAPS.items():
        assert _mapping(node, index) == entries
    assert raw(0x1400, 2) == 1 and raw(0x1800, 2) == 1 and raw(0x1801, 2) == 1
    assert not raw(0x1400, 1) & 0x80000000 and not raw(0x1801, 1) & 0x80000000
    assert raw(0x1006) == 1000 and raw(0x1017) == 100 and raw(0x6060) == 10
    assert node.nmt_state == "OPERATIONAL"
    assert node.state is NodeState.OPERATION_ENABLED
    assert [cw for i, cw in enumerate(node.controlwords) if i == 0 or cw != node.controlwords[i - 1]] == [6, 7, 15]
    assert drive.identity and drive.feedback_streams
    assert drive.sample_clock == "bus"   # the SYNC's echo: the clock of the TPDOs' stamps
    # the periodic SYNC runs in the bus (simulated time), not in a thread of this process
    assert _periodic_syncs(bus) == [0.001]


def test_a_node_in_fault_is_refused_with_its_error_code_unless_reset_is_asked(rig: Any) -> None:
    bus, node, drive = rig()
    node.state, node.error_code = NodeState.FAULT, 0x2310
    with pytest.raises(DriveFaultError) as info:
        drive.enable()
    assert str(info.value) == ("node 5 is in fault: EMCY 0x2310 (Current); not reset "
                               "(dobhil run --reset-faults resets it)")
    assert node.state is NodeState.FAULT and 0x80 not in node.controlwords
    assert drive.status.state is DriveState.FAULT


def test_reset_faults_gives_one_rising_edge_then_enables(rig: Any) -> None:
    bus, node, drive = rig(reset_faults=True)
    node.state = NodeState.FAULT
    drive.enable()
    assert node.state is NodeState.OPERATION_ENABLED
    edges = [cw for prev, cw in zip([0, *node.controlwords], node.controlwords) if cw & 0x80 and not prev & 0x80]
    assert edges == [0x80]


def test_a_node_that_stays_in_fault_after_the_reset_ends_the_enable(rig: Any, monkeypatch: pytest.MonkeyPatch) -> None:
    bus, node, drive = rig(reset_faults=True)
    node.state, node.error_code = NodeState.FAULT, 0x5000
    # a node whose fault will not clear: it takes every controlword and changes no state
    monkeypatch.setattr(node, "_controlword", node.controlwords.append)
    with pytest.raises(DriveTimeoutError, match=r"last seen fault with error EMCY 0x5000 \(Device Hardware\)"):
        drive.enable()
    edges = [cw for prev, cw in zip([0, *node.controlwords], node.controlwords) if cw & 0x80 and not prev & 0x80]
    assert edges == [0x80]   # one reset, not one per status frame


def test_without_native_periodic_send_the_drive_sends_sync_itself(rig: Any) -> None:
    bus, node, drive = rig(bus_type=HostSyncPumpBus)
    drive.enable()
    assert not drive.feedback_streams and drive.sample_clock == "sent"
    assert not [t for t in bus.tasks if t.msg.arbitration_id == 0x80]
    before = time.time()
    drive.send_torque(0.25)
    assert [m.arbitration_id for m in bus.sent[-2:]] == [0x205, 0x80]   # the RPDO, then its SYNC
    fb = drive.poll(0.01)
    # sampled at the SYNC the host sent: its send time, on the clock of python-can's stamps
    assert fb is not None and before <= fb.sampled_at <= time.time()
    assert node.torque == pytest.approx(0.25)


# -- cycle ------------------------------------------------------------------

def test_closed_cycle_torque_reaches_the_node_and_feedback_follows(rig: Any) -> None:
    bus, node, drive = rig(inertia=0.01)
    drive.enable()
    first = drive.poll(0.01)
    assert first is not None
    for _ in range(100):
        drive.send_torque(0.5)
        fb = drive.poll(0.01)
        assert fb is not None
        assert fb.sampled_at == node.last_sync            # the SYNC that sampled it
        assert fb.rx_time >= fb.sampled_at
    assert node.torque == pytest.approx(0.5)              # 500 per mille of 1 Nm
    # 100 periods of 0.5 Nm on 0.01 kg m^2 (the first command acts one SYNC later)
    assert fb.velocity == pytest.approx(0.5 / 0.01 * 0.099, rel=0.05)
    assert fb.position == pytest.approx(node.plant.position, abs=2 * math.pi / 4096)   # one increment


def test_safe_stop_is_confirmed_by_the_statusword_then_sync_stops(rig: Any) -> None:
    bus, node, drive = rig()
    drive.enable()
    drive.send_torque(0.3)
    drive.poll(0.01)
    report = drive.safe_stop()
    assert report.confirmation is Confirmation.CONFIRMED and report.safe
    assert [f.what for f in report.frames] == ["zero torque", "quick stop", "SYNC", "disable voltage", "SYNC"]
    assert node.state is NodeState.SWITCH_ON_DISABLED and node.torque == 0.0
    assert not _periodic_syncs(bus)


def test_disable_without_confirmation_still_gets_the_rpdos_applied(rig: Any) -> None:
    bus, node, drive = rig()
    drive.enable()
    assert drive.disable()
    assert node.state is NodeState.SWITCH_ON_DISABLED   # the safe-stop SYNCs applied the RPDOs


# -- faults while running ---------------------------------------------------

def test_emcy_stops_the_run_with_its_code_and_canopens_text(rig: Any) -> None:
    bus, node, drive = rig()
    drive.enable()
    drive.send_torque(0.1)
    drive.poll(0.01)
    node.fault(0x2310)
    with pytest.raises(DriveFaultError) as info:
        for _ in range(5):
            drive.send_torque(0.1)
            drive.poll(0.01)
    assert "EMCY 0x2310 (Current)" in str(info.value)
    assert drive.status.error_code == 0x2310 and drive.status.state is DriveState.FAULT


def test_an_nmt_state_change_is_a_fault(rig: Any) -> None:
    bus, node, drive = rig()
    drive.enable()
    node.network.notify(0, bytearray([0x80, 5]), bus.time)   # someone put it pre-operational
    with pytest.raises(DriveFaultError, match="NMT pre-operational"):
        for _ in range(300):
            drive.send_torque(0.0)
            drive.poll(0.01)


def test_a_lost_heartbeat_is_a_fault(rig: Any) -> None:
    bus, node, drive = rig()
    drive.enable()
    node.node.nmt.stop_heartbeat()
    with pytest.raises(DriveFaultError, match="no heartbeat from node 5"):
        for _ in range(1000):
            drive.send_torque(0.0)
            drive.poll(0.01)
    assert bus.time < 0.5   # three heartbeat periods of 0.1 s, and the enable's few ms


class StalledBus(PumpBus):
    """A bus whose next blocking read stalls the host for :attr:`stall` simulated seconds,
    as a stopped or descheduled process does inside ``recv``: meanwhile the periodic SYNC
    goes on (a kernel's broadcast manager) and the node answers, everything queued; the
    read then returns the oldest frame."""

    stall = 0.0

    def recv(self, timeout: float | None = None) -> can.Message | None:
        if not (self.stall and timeout):
            return super().recv(timeout)
        stall, self.stall = self.stall, 0.0
        self.advance(stall)
        return super().recv(0.0)   # the oldest frame queued, simulated time not moved


def test_a_stalled_read_takes_what_came_meanwhile_not_a_lost_heartbeat(rig: Any) -> None:
    """The host stopped longer than three heartbeat periods inside a read, the SYNC and
    the node going on: the heartbeats and TPDOs waiting in the queue came in time. The
    poll reads them all (not only the first, a SYNC echo) and gives the newest sample;
    nothing is a lost heartbeat or a feedback timeout."""
    bus, node, drive = rig(bus_type=StalledBus)
    drive.enable()
    drive.poll(0.01)
    before = node.syncs
    bus.stall = 0.5   # five heartbeats of 0.1 s, 500 SYNCs of 1 ms
    fb = drive.poll(0.01)
    assert node.syncs - before >= 500 and not bus.pending        # all of it was read
    assert drive.status.state is DriveState.ENABLED
    assert fb is not None and fb.sampled_at == node.last_sync    # the newest sample


def test_a_stalled_confirmation_wait_reads_the_confirmation_that_came_meanwhile(rig: Any) -> None:
    """The host stopped past the whole confirmation wait (three heartbeat periods) inside
    its first read, which returns another node's frame queued first: the node's statusword
    out of Operation enabled waits behind it, and confirms."""
    bus, node, drive = rig(bus_type=StalledBus)
    drive.enable()
    drive.poll(0.01)
    # node 6's heartbeat, on the wire before anything the stall lets through
    node.bus.send(can.Message(arbitration_id=0x706, data=b"\x05", is_extended_id=False))
    bus.stall = 0.5
    report = drive.safe_stop()
    assert report.confirmation is Confirmation.CONFIRMED, report.detail
    assert node.state is NodeState.SWITCH_ON_DISABLED


# -- replay -----------------------------------------------------------------

def test_apply_decodes_recorded_frames_without_start_up(rig: Any) -> None:
    bus, node, drive = rig()
    drive.enable()
    received: list[can.Message] = []
    for _ in range(20):
        drive.send_torque(0.4)
        drive.poll(0.01)
    # every frame the host read: record them by wrapping recv from now on
    original = bus.recv

    def recording(timeout: float | None = None) -> can.Message | None:
        msg = original(timeout)
        if msg is not None:
            received.append(msg)
        return msg

    bus.recv = recording
    live = []
    for _ in range(20):
        drive.send_torque(0.4)
        fb = drive.poll(0.01)
        assert fb is not None
        live.append((fb.position, fb.velocity, fb.sampled_at))
    replayer = CiA402Drive(bus, profile(), clock=lambda: 0.0)
    replayed = []
    for msg in received:
        if replayer.apply(msg):
            fb = replayer.feedback
            assert fb is not None
            replayed.append((fb.position, fb.velocity, fb.sampled_at))
    assert replayed == live


# -- start-up failures: one line, nothing enabled -----------------------------

def _one_line_start_up_failure(drive: CiA402Drive, node: TestNode402 | None) -> str:
    with pytest.raises(DriveError) as info:
        drive.enable()
    text = str(info.value)
    assert "\n" not in text and text.startswith("node 5: ")
    assert drive.status.state is not DriveState.ENABLED
    if node is not None:
        assert node.state is not NodeState.OPERATION_ENABLED and 15 not in node.controlwords
    # nothing was enabled, and the safe stop says so: no "drive may still be enabled"
    report = drive.safe_stop()
    assert report.safe and report.warning() == ""
    return text


def test_a_silent_node_times_out_naming_the_object(stack: ExitStack) -> None:
    bus, _ = stack.enter_context(pumped(on_bus=False))
    drive = CiA402Drive(bus, profile(), clock=bus.clock)
    text = _one_line_start_up_failure(drive, None)
    assert text == "node 5: SDO 0x1018:01 (Vendor-ID) timed out after 0.3 s (reached: pre-operational)"


def test_an_abort_names_the_object_and_what_was_reached(rig: Any, tmp_path: Path) -> None:
    od = canopen.import_od(str(EDS), 5)
    del od[0x6502]  # this node's dictionary lacks it: its SDO server aborts
    canopen.export_od(od, str(tmp_path / "no-6502.eds"))
    bus, node, drive = rig(eds=tmp_path / "no-6502.eds")
    text = _one_line_start_up_failure(drive, node)
    assert re.fullmatch(r"node 5: SDO 0x6502:00 \(Supported drive modes\) aborted by the node: 0x06020000 "
                        r"\(Object does not exist\) \(reached: pre-operational, identity read, "
                        r"statusword read\)", text), text


def test_a_node_without_cst_is_refused(rig: Any) -> None:
    bus, node, drive = rig()
    node.node.sdo[0x6502].raw = 0x00000080
    text = _one_line_start_up_failure(drive, node)
    assert "0x6502 (supported drive modes) = 0x00000080: no cyclic synchronous torque (bit 9)" in text
    assert text.endswith("(reached: pre-operational, identity read, statusword read)")


@pytest.mark.parametrize(("rated_mnm", "says"), [
    (0, "0x6076 (motor rated torque) = 0 mNm: a rated torque of 0"),
    (1020, "= 1020 mNm = 1.02 Nm, the profile's cia402.rated_torque is 1 Nm (more than 1 % apart"),
])
def test_a_rated_torque_of_0_or_another_is_refused(rig: Any, rated_mnm: int, says: str) -> None:
    bus, node, drive = rig()
    node.node.sdo[0x6076].raw = rated_mnm
    assert says in _one_line_start_up_failure(drive, node)


def test_a_rated_torque_within_1_percent_is_the_nodes(rig: Any) -> None:
    bus, node, drive = rig()
    node.node.sdo[0x6076].raw = 1005
    drive.enable()
    assert drive.rated_torque == pytest.approx(1.005)


def test_a_cancel_ends_start_up(stack: ExitStack) -> None:
    bus, _ = stack.enter_context(pumped(on_bus=False))
    drive = CiA402Drive(bus, profile(sdo_timeout=5.0), clock=bus.clock)
    with pytest.raises(WaitCancelled, match="received SIGTERM"):
        drive.enable(cancel=lambda: "received SIGTERM" if bus.time > 0.05 else "")
    assert bus.time < 0.1


# -- bad input in the profile or EDS: ConfigError at construction ----------------

def _eds_variant(tmp_path: Path, change: Any) -> Path:
    text = EDS.read_text()
    path = tmp_path / "variant.eds"
    path.write_text(change(text))
    return path


def _drop_section(text: str, name: str) -> str:
    return re.sub(rf"\[{name}\]\n(?:[^\[\n].*\n|\n)*", "", text)


@pytest.mark.parametrize(("change", "says"), [
    (lambda t: _drop_section(t, "6071"), "object 0x6071 (target torque) missing"),
    (lambda t: re.sub(r"(\[6502\](?:\n.*)*?DefaultValue=)0x00000380", r"\g<1>0x00000180", t),
     "0x6502 (supported drive modes) = 0x00000180 has no cyclic synchronous torque (bit 9)"),
    (lambda t: re.sub(r"(\[6076\](?:\n.*)*?DefaultValue=)1000", r"\g<1>0", t),
     "0x6076 (motor rated torque) = 0: a rated torque of 0"),
    (lambda t: re.sub(r"(\[6077\](?:\n.*)*?DataType=)0x0003", r"\g<1>0x0004", t),
     "TPDO 1 mapping does not fit: 0x6041:00 (statusword) 16 bits + 0x6064:00 (position actual value) "
     "32 bits + 0x6077:00 (torque actual value) 32 bits: PDO mapping needs 80 bits, a PDO carries 64"),
    (lambda t: re.sub(r"(\[6061\](?:\n.*)*?DataType=)0x0002", r"\g<1>0x0003", t),
     "0x6061:00 (modes of operation display) is INTEGER16 in the EDS, CiA 402 has INTEGER8"),
])
def test_a_bad_eds_is_one_config_line(idle_bus: PumpBus, tmp_path: Path, change: Any, says: str) -> None:
    eds = _eds_variant(tmp_path, change)
    with pytest.raises(ConfigError) as info:
        CiA402Drive(idle_bus, profile(eds=str(eds)))
    assert says in str(info.value) and "\n" not in str(info.value)


def test_an_unknown_section_key_is_one_config_line() -> None:
    with pytest.raises(ConfigError, match=r"unknown key 'cia402.rated_torq' \(allowed in cia402: eds, "):
        profile(rated_torq=1.0)


@pytest.mark.parametrize(("key", "value", "says"), [
    ("rated_torque", 0, "cia402.rated_torque: expected a number > 0"),
    ("rated_torque_unit", "Nm", "cia402.rated_torque_unit: expected one of 'mNm', 'uNm', got 'Nm'"),
    ("velocity_unit", "rad/s", "cia402.velocity_unit: expected one of 'rpm', 'increments_per_s', 'milli_rpm'"),
    ("tpdo", 4, "cia402.tpdo: expected a TPDO number from 1 to 3"),
])
def test_section_values_are_checked(key: str, value: Any, says: str) -> None:
    with pytest.raises(ConfigError, match=re.escape(says)):
        profile(**{key: value})


def test_the_shipped_profile_loads_and_finds_its_eds(idle_bus: PumpBus) -> None:
    shipped = load_profile(PROFILE)
    assert shipped.protocol == "cia402" and shipped.options["rated_torque_unit"] == "mNm"
    drive = CiA402Drive(idle_bus, shipped)
    assert drive.frame_ids >= {0x0, 0x80, 0x85, 0x185, 0x285, 0x205, 0x585, 0x605, 0x705}
    assert 0x77F not in drive.frame_ids and 0x706 not in drive.frame_ids and 0x186 not in drive.frame_ids
    watched = CiA402Drive(idle_bus, profile(consumer_heartbeat=0.05))
    assert 0x77F in watched.frame_ids   # the host's own heartbeat


def test_node_id_must_be_a_canopen_one() -> None:
    import yaml
    data = yaml.safe_load(PROFILE.read_text())
    data["node_id"] = 0
    with pytest.raises(ConfigError, match="node_id: expected an integer from 1 to 127"):
        profile_from_mapping(data, source="p")
    del data["feedback_period"]
    data["node_id"] = 5
    with pytest.raises(ConfigError, match="missing key 'feedback_period'"):
        profile_from_mapping(data, source="p")


def test_a_recorded_run_decodes_without_its_eds(idle_bus: PumpBus) -> None:
    """A replay rebuilds the profile from the log (no directory, the EDS maybe elsewhere):
    the drive is made all the same and decodes with the standard layouts; only a start-up
    needs the file, and says so in one line."""
    gone = profile(eds="gone.eds")
    drive = CiA402Drive(idle_bus, gone, clock=lambda: 0.0)
    drive.apply(can.Message(arbitration_id=0x185, data=bytes.fromhex("37 12 00 04 00 00 f4 01"),
                            is_extended_id=False))
    assert drive.apply(can.Message(arbitration_id=0x285, data=bytes.fromhex("3c 00 00 00 0a"),
                                   is_extended_id=False))
    fb = drive.feedback
    assert fb is not None
    assert fb.position == pytest.approx(math.pi / 2) and fb.velocity == pytest.approx(2 * math.pi)
    with pytest.raises(ConfigError, match=r"cia402.eds: file 'gone.eds' not found"):
        drive.enable()


def test_a_profile_file_whose_eds_is_missing_is_refused_when_the_drive_is_made(idle_bus: PumpBus,
                                                                                tmp_path: Path) -> None:
    import dataclasses
    from_file = dataclasses.replace(profile(eds="gone.eds"), directory=str(tmp_path))
    with pytest.raises(ConfigError, match=rf"cia402.eds: file 'gone.eds' not found in {re.escape(str(tmp_path))}"):
        CiA402Drive(idle_bus, from_file)


def test_without_native_periodic_send_the_hosts_heartbeat_rides_with_the_torque_frames(stack: ExitStack) -> None:
    bus, node = stack.enter_context(pumped(HostSyncPumpBus))
    drive = CiA402Drive(bus, profile(consumer_heartbeat=0.05), clock=bus.clock)
    drive.enable()
    assert node.raw(0x1016, 1) == 127 << 16 | 50     # host 127 watched for 50 ms
    for _ in range(120):
        drive.send_torque(0.0)
        drive.poll(0.01)
        bus.advance(0.001)   # the host's loop period (the node answers at once on this bus)
    beats = [m.timestamp for m in bus.sent if m.arbitration_id == 0x77F]
    assert all(bytes(m.data) == b"\x05" for m in bus.sent if m.arbitration_id == 0x77F)
    gaps = [b - a for a, b in zip(beats, beats[1:])]
    assert len(beats) >= 10 and max(gaps) <= 0.0125 + 1e-9   # every 12 SYNC periods (50 ms / 4)


def test_the_hosts_heartbeat_id_must_not_be_the_nodes(idle_bus: PumpBus) -> None:
    with pytest.raises(ConfigError, match="cia402.host_node_id: expected an id other than the node's"):
        CiA402Drive(idle_bus, profile(consumer_heartbeat=0.05, host_node_id=5))


def _od_with_60c2_instead_of_1006() -> Any:
    """The emulated node's dictionary as a maxon EPOS4 has it: no 0x1006, 0x60C2 instead."""
    from canopen.objectdictionary import ODRecord, ODVariable
    od = canopen.import_od(str(EDS), 5)
    del od[0x1006]
    record = ODRecord("Interpolation time period", 0x60C2)
    for sub, name, data_type in ((0, "Highest sub-index supported", 0x05), (1, "Interpolation time period value", 0x05),
                                 (2, "Interpolation time index", 0x02)):
        var = ODVariable(name, 0x60C2, sub)
        var.data_type, var.access_type, var.default = data_type, "rw", 2 if sub == 0 else 0
        record.add_member(var)
    od.add_object(record)
    return od


def test_a_node_without_0x1006_gets_the_sync_period_in_0x60c2(stack: ExitStack, tmp_path: Path) -> None:
    od = _od_with_60c2_instead_of_1006()
    eds = tmp_path / "epos-like.eds"
    canopen.export_od(od, str(eds))
    bus, node = stack.enter_context(pumped(eds=eds))
    drive = CiA402Drive(bus, profile(eds=str(eds)), clock=bus.clock)
    drive.enable()
    assert (node.raw(0x60C2, 1), node.raw(0x60C2, 2)) == (1, -3)   # 1 * 10^-3 s
    with pytest.raises(ConfigError, match=r"feedback_period: interpolation time period 0x60C2"):
        import dataclasses
        CiA402Drive(bus, dataclasses.replace(profile(eds=str(eds)), feedback_period=0.0012345))


def test_a_node_with_neither_0x1006_nor_0x60c2_is_refused(idle_bus: PumpBus, tmp_path: Path) -> None:
    od = canopen.import_od(str(EDS), 5)
    del od[0x1006]
    eds = tmp_path / "no-period.eds"
    canopen.export_od(od, str(eds))
    with pytest.raises(ConfigError, match=r"neither 0x1006 \(communication cycle period\) nor 0x60C2"):
        CiA402Drive(idle_bus, profile(eds=str(eds)))


def test_the_epos4_profile_loads_and_its_eds_passes_the_checks(idle_bus: PumpBus) -> None:
    epos4 = load_profile(PROFILE.parent / "epos4.yaml")
    drive = CiA402Drive(idle_bus, epos4)
    assert drive.profile.options["rated_torque_unit"] == "uNm"


def test_a_bus_that_refuses_a_request_at_start_up_is_one_bus_error_line(rig: Any) -> None:
    from dobhil.errors import BusError
    bus, node, drive = rig()
    sent = bus.send

    def refuse_sdo(msg: can.Message, timeout: float | None = None) -> None:
        if msg.arbitration_id == 0x605 and msg.data[1:3] == bytes.fromhex("02 65"):
            raise can.CanOperationError("Transmit buffer full")
        sent(msg, timeout)

    bus.send = refuse_sdo
    with pytest.raises(BusError) as info:
        drive.enable()
    assert str(info.value) == ("node 5: SDO 0x6502:00 (Supported drive modes): Transmit buffer full "
                               "(reached: pre-operational, identity read, statusword read)")


@settings(deadline=None, max_examples=60)
@given(st.lists(st.tuples(st.sampled_from([0x80, 0x85, 0x185, 0x285, 0x705, 0x585, 0x205, 0x77F, 0x186]),
                          st.binary(max_size=8)), max_size=30))
def test_no_frame_makes_the_decoder_raise(frames: list[tuple[int, bytes]]) -> None:
    """Short, long or garbled frames of this node's ids are ignored or decoded, never raised."""
    with pumped() as (bus, _):
        drive = CiA402Drive(bus, profile(), clock=lambda: 0.0)
        for arb, data in frames:
            drive.apply(can.Message(arbitration_id=arb, data=data, is_extended_id=False))


def test_a_sample_whose_position_tpdo_was_lost_is_no_sample(idle_bus: PumpBus) -> None:
    drive = CiA402Drive(idle_bus, profile(), clock=lambda: 0.0)

    def frame(arb: int, data: str) -> can.Message:
        return can.Message(arbitration_id=arb, data=bytes.fromhex(data), is_extended_id=False)

    assert not drive.apply(frame(0x285, "3c 00 00 00 0a"))           # no TPDO1 before it
    drive.apply(frame(0x185, "37 12 00 04 00 00 00 00"))
    assert drive.apply(frame(0x285, "3c 00 00 00 0a"))               # both: one sample
    assert not drive.apply(frame(0x285, "3c 00 00 00 0a"))           # the next SYNC's TPDO1 lost


def test_a_target_torque_left_from_before_is_zeroed_before_the_node_goes_operational(rig: Any) -> None:
    bus, node, drive = rig()
    node.node.sdo[0x6071].raw = 500   # a previous run's last command
    at_start: list[int] = []
    send = bus.send

    def watch(msg: can.Message, timeout: float | None = None) -> None:
        if msg.arbitration_id == 0 and bytes(msg.data) == b"\x01\x05":   # NMT start node 5
            at_start.append(node.raw(0x6071))
        send(msg, timeout)

    bus.send = watch
    drive.enable()
    assert at_start == [0]


def test_consumer_heartbeat_needs_0x1016_in_the_eds(idle_bus: PumpBus, tmp_path: Path) -> None:
    od = canopen.import_od(str(EDS), 5)
    del od[0x1016]
    eds = tmp_path / "no-consumer.eds"
    canopen.export_od(od, str(eds))
    CiA402Drive(idle_bus, profile(eds=str(eds)))   # not asked for: fine
    with pytest.raises(ConfigError, match=r"cia402.consumer_heartbeat: expected 0, the EDS has no 0x1016"):
        CiA402Drive(idle_bus, profile(eds=str(eds), consumer_heartbeat=0.05))


# -- the sample instant --------------------------------------------------------

def _stamped(arbitration_id: int, data: bytes, stamp: float) -> can.Message:
    return can.Message(arbitration_id=arbitration_id, data=data, timestamp=stamp, is_extended_id=False)


def test_a_sample_is_measured_from_the_sync_stamped_before_it(idle_bus: PumpBus) -> None:
    """Frames that reached the host out of their stamps' order (on two processors a SYNC's
    echo and a TPDO enter the kernel apart): a TPDO stamped before the newest SYNC read was
    sampled by the SYNC before that one -- never a negative latency."""
    drive = CiA402Drive(idle_bus, profile(), clock=lambda: 0.0)
    # TPDO1: statusword 0x0237, position 0, torque 0; TPDO2: velocity 0, mode 10 (CST)
    status = bytes.fromhex("37 02 00 00 00 00 00 00")
    motion = bytes.fromhex("00 00 00 00 0a")

    def sample(*frames: can.Message) -> float:
        fresh = [drive.apply(f) for f in frames]
        assert fresh[-1] and drive.feedback is not None
        return drive.feedback.sampled_at

    sync, tpdo1, tpdo2 = 0x080, 0x185, 0x285   # CiA 301 predefined ids of node 5
    assert sample(_stamped(sync, b"", 1.000), _stamped(tpdo1, status, 1.004), _stamped(tpdo2, motion, 1.005)) == 1.000
    # the next SYNC (1.010) read before this TPDO pair, which the bus stamped at 1.008
    assert sample(_stamped(sync, b"", 1.010), _stamped(tpdo1, status, 1.007), _stamped(tpdo2, motion, 1.008)) == 1.000
    assert sample(_stamped(tpdo1, status, 1.013), _stamped(tpdo2, motion, 1.014)) == 1.010
    assert drive.feedback is not None and drive.feedback.sample_latency == pytest.approx(0.004)
