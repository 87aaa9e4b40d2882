"""dobhil's CiA 402 drive against the test tree's node (``cia402_node``: canopen's
LocalNode + a state machine of its own, NOT dobhil's emulator): start-up, the enable
handshake to Operation enabled in CST, feedback decoding, a torque reaching the node at
the next SYNC, safe stop confirmed by the statusword, faults by statusword + EMCY.

Pumped (simulated time, deterministic) with both SYNC sources -- ``send_periodic`` in
simulated time (a bus with native periodic send, as SocketCAN's broadcast manager) and
the drive's own SYNC after each torque frame -- plus one real-time run on canopen's
notifier thread.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import can
import pytest

from dobhil.config import load_config
from dobhil.drives import DriveState, load_profile, make_drive
from dobhil.drives.base import Confirmation, Drive
from dobhil.errors import DriveError, DriveFaultError
from dobhil.runtime.loop import ForceLoop, Timing
from dobhil.runtime.references import make_reference
from dobhil.runtime.session import build_controller, loop_settings
from dobhil.runtime.stop import StopReason

from .cia402_node import HostSyncPumpBus, NodeState, PumpBus, TestNode402, with_rig_units

NODE = 5
PERIOD = 0.001   # the profile's feedback_period (SYNC period)
DEMO = Path(__file__).resolve().parents[2] / "configs" / "demo.yaml"
RAD_PER_INC = 2 * math.pi / 4096
RAD_S_PER_RPM = 2 * math.pi / 60
_CHANNELS = itertools.count()
SYNC_SOURCES = {"native-sync": PumpBus, "host-sync": HostSyncPumpBus}


@dataclass
class Rig:
    node: TestNode402
    bus: PumpBus
    drive: Drive

    def run(self, seconds: float, torque: float | None = None) -> None:
        """Host loop of 1 ms cycles for ``seconds`` of simulated time (torque sent each
        cycle if given): without periodic SYNC the feedback answers the command at once,
        so each cycle also waits for its deadline."""
        end = self.bus.clock() + seconds
        while self.bus.clock() < end - 1e-9:
            deadline = self.bus.clock() + PERIOD
            if torque is not None:
                self.drive.send_torque(torque)
            self.drive.poll(PERIOD)
            if self.bus.clock() < deadline:
                self.bus.advance(deadline - self.bus.clock())

    def next_feedback(self) -> Any:
        fb = None
        while fb is None:
            if not self.drive.feedback_streams:
                self.drive.send_torque(0.0)   # the host's SYNC comes with the command
            fb = self.drive.poll(0.002)
        return fb


@pytest.fixture
def make_rig() -> Iterator[Callable[..., Rig]]:
    made: list[tuple[TestNode402, PumpBus, Drive]] = []

    def build(sync: str = "native-sync", *, node_id: int = NODE, inertia: float = 0.01,
              reset_faults: bool = False, **changes: Any) -> Rig:
        channel = f"cia402-drive-{next(_CHANNELS)}"
        node = TestNode402(can.Bus(interface="virtual", channel=channel), NODE, inertia=inertia)
        bus = SYNC_SOURCES[sync](channel, node)
        node.boot()
        profile = dataclasses.replace(with_rig_units(load_profile("cia402-emulated")), node_id=node_id, **changes)
        drive = make_drive(bus, profile, clock=bus.clock, reset_faults=reset_faults)
        made.append((node, bus, drive))
        return Rig(node, bus, drive)

    yield build
    for node, bus, drive in made:
        drive.disable()
        getattr(drive, "close", lambda: None)()
        bus.shutdown()
        node.close()


@pytest.fixture(params=sorted(SYNC_SOURCES))
def rig(request: pytest.FixtureRequest, make_rig: Callable[..., Rig]) -> Rig:
    return make_rig(request.param)


def _dedup(words: list[int]) -> list[int]:
    return [w for i, w in enumerate(words) if i == 0 or words[i - 1] != w]


def test_enable_reaches_operation_enabled_in_cst(rig: Rig) -> None:
    rig.drive.enable()
    node = rig.node
    assert rig.drive.status.state is DriveState.ENABLED
    assert node.state is NodeState.OPERATION_ENABLED and node.mode == 10
    assert node.nmt_state == "OPERATIONAL"
    assert _dedup(node.controlwords) == [0x06, 0x07, 0x0F]
    # SPEC-17's wire mapping, written by SDO into the node's object dictionary
    raw = node.raw
    assert [raw(0x1600, s) for s in (1, 2)] == [0x60400010, 0x60710010]
    assert [raw(0x1A00, s) for s in (1, 2, 3)] == [0x60410010, 0x60640020, 0x60770010]
    assert [raw(0x1A01, s) for s in (1, 2)] == [0x606C0020, 0x60610008]
    assert [raw(0x1400, 2), raw(0x1800, 2), raw(0x1801, 2)] == [1, 1, 1]
    assert raw(0x1006) == 1000 and raw(0x1017) == 100          # 1 ms SYNC, 100 ms heartbeat
    assert rig.drive.identity == (0, 0x402, 0x00010000, 1)     # type: ignore[attr-defined]


def test_feedback_is_decoded_from_both_tpdos(make_rig: Callable[..., Rig]) -> None:
    rig = make_rig()
    rig.node.plant.position, rig.node.plant.velocity = 1.0, -2.0
    rig.drive.enable()
    fb = rig.next_feedback()
    node = rig.node
    # what the node put in its TPDOs at this SYNC, in rad and rad/s
    assert math.isclose(fb.position, node.position_increments * RAD_PER_INC, rel_tol=1e-12)
    assert math.isclose(fb.velocity, node.velocity_rpm * RAD_S_PER_RPM, rel_tol=1e-12)
    # and the plant within the quanta of 0x6064 and 0x606C
    assert abs(fb.position - node.plant.position) <= RAD_PER_INC / 2
    assert abs(fb.velocity - node.plant.velocity) <= RAD_S_PER_RPM / 2
    # sampled at the SYNC, whose echo (simulated stamp) came just before the TPDOs
    assert fb.sampled_at == rig.bus.clock() and fb.rx_time == fb.sampled_at


def test_torque_reaches_the_node_at_the_next_sync(rig: Rig) -> None:
    rig.drive.enable()
    rig.next_feedback()
    syncs = rig.node.syncs
    rig.drive.send_torque(0.5)
    if rig.drive.feedback_streams:   # periodic SYNC: the RPDO waits in the node for it
        assert rig.node.per_mille == 0 and rig.node.syncs == syncs
        rig.next_feedback()
    # (without periodic SYNC the drive sent its own right after the RPDO)
    assert rig.node.syncs == syncs + 1
    assert rig.node.torques[-2:] == [0.0, 0.5] and rig.node.torque == 0.5


@pytest.mark.parametrize(("tau", "per_mille"), [(0.12345, 123), (0.1236, 124), (-0.1236, -124),
                                                (1.5, 1500)])
def test_torque_is_quantised_to_per_mille_of_rated(make_rig: Callable[..., Rig], tau: float,
                                                   per_mille: int) -> None:
    rig = make_rig()
    rig.drive.enable()
    rig.run(0.005, torque=tau)
    assert rig.node.per_mille == per_mille


def test_safe_stop_is_confirmed_by_the_statusword(rig: Rig) -> None:
    rig.drive.enable()
    rig.run(0.01, torque=0.3)
    report = rig.drive.safe_stop()
    assert report.confirmation is Confirmation.CONFIRMED and report.warning() == ""
    assert [f.what for f in report.frames][0] == "zero torque" and report.sent
    assert rig.node.state is NodeState.SWITCH_ON_DISABLED and rig.node.torque == 0.0
    assert _dedup(rig.node.controlwords)[-2:] == [0x02, 0x00]     # quick stop, disable voltage
    assert rig.drive.status.state is DriveState.DISABLED


def test_unconfirmed_safe_stop_gives_the_loud_warning(make_rig: Callable[..., Rig],
                                                      monkeypatch: pytest.MonkeyPatch) -> None:
    rig = make_rig()
    rig.drive.enable()
    rig.run(0.005, torque=0.3)
    monkeypatch.setattr(rig.node, "_controlword", lambda cw: None)   # a node that ignores it
    report = rig.drive.safe_stop(timeout=0.05)
    assert report.confirmation is Confirmation.NOT_ACKNOWLEDGED and not report.safe
    warning = report.warning()
    assert warning.startswith("drive may still be enabled: node 5 ") and warning.endswith("cut power")
    assert "\n" not in warning and rig.node.state is NodeState.OPERATION_ENABLED
    assert "disable of node 5 failed" in rig.drive.status.detail


def test_fault_with_emcy_is_a_drive_fault_with_its_code(rig: Rig) -> None:
    rig.drive.enable()
    rig.run(0.005, torque=0.2)
    rig.node.fault(0x2310)
    with pytest.raises(DriveFaultError, match="0x2310"):
        rig.run(0.01, torque=0.2)
    assert rig.drive.status.state is DriveState.FAULT and rig.drive.status.error_code == 0x2310
    assert rig.node.torque == 0.0


class FaultAtCycle:
    """A cycle sink that puts the node in fault (statusword fault bit + EMCY) at cycle ``at``."""

    def __init__(self, node: TestNode402, at: int, code: int) -> None:
        self.node, self.at, self.code = node, at, code

    def started(self, fb: Any) -> None:
        pass

    def cycle(self, k: int, *args: Any) -> None:
        if k == self.at:
            self.node.fault(self.code)

    def stop(self, stop: Any) -> None:
        pass


def test_node_fault_stops_a_run_as_drive_fault(make_rig: Callable[..., Rig]) -> None:
    config = load_config(DEMO, ["drive.profile=cia402-emulated", "loop.duration=0.5"])
    rig = make_rig(inertia=config.plant.inertia)
    loop = ForceLoop(drive=rig.drive, controller=build_controller(config, rig.drive.profile),
                     reference=make_reference(config.reference, None, duration=0.5),
                     settings=loop_settings(config, Timing.LOCKSTEP, None, rig.drive.profile), clock=rig.bus.clock,
                     sink=FaultAtCycle(rig.node, 100, 0x7500))
    result = loop.run()
    assert result.stop.reason is StopReason.DRIVE_FAULT, result.stop.line()
    assert "EMCY 0x7500" in result.stop.detail and result.stop.cycle == 101
    assert result.safe_stop is not None and result.safe_stop.safe
    assert rig.node.torque == 0.0 and rig.node.state is NodeState.FAULT


def test_node_booting_while_the_host_listens_enables_at_once(make_rig: Callable[..., Rig]) -> None:
    """The node's boot-up frame (NMT state 0) reaches the host during start-up (the rig
    boots it after the host's bus is open); after the host's own NMT start the drive must
    not wait for the next heartbeat to believe the node operational: the enable is
    confirmed at the SYNC whose statusword says Operation enabled."""
    rig = make_rig()
    rig.drive.enable()
    assert rig.node.syncs == 3      # shutdown, switch on, enable operation: one SYNC each


def test_node_in_fault_is_not_enabled_unless_reset_is_asked(make_rig: Callable[..., Rig]) -> None:
    rig = make_rig()
    rig.node.fault(0x2310)
    with pytest.raises(DriveFaultError, match=r"node 5 is in fault: EMCY 0x2310"):
        rig.drive.enable()
    assert rig.node.state is NodeState.FAULT and 0x80 not in rig.node.controlwords
    reset = make_rig(reset_faults=True)
    reset.node.fault(0x2310)
    reset.drive.enable()
    assert reset.node.state is NodeState.OPERATION_ENABLED
    assert [w & 0x80 for w in _dedup(reset.node.controlwords)].count(0x80) == 1   # one edge


def test_start_up_refuses_a_node_without_cst(make_rig: Callable[..., Rig]) -> None:
    rig = make_rig()
    rig.node.node.data_store[0x6502] = {0: (0x080).to_bytes(4, "little")}   # CSP only
    with pytest.raises(DriveError, match=r"^node 5: 0x6502 .*no cyclic synchronous torque.*"
                                         r"\(reached: pre-operational, identity read"):
        rig.drive.enable()
    assert rig.node.controlwords == [] and rig.node.nmt_state == "PRE-OPERATIONAL"


def test_start_up_names_node_and_object_when_nobody_answers(make_rig: Callable[..., Rig]) -> None:
    rig = make_rig(node_id=NODE + 1)
    with pytest.raises(DriveError, match=r"^node 6: SDO 0x1018:01 \(.*\) timed out after .* "
                                         r"\(reached: pre-operational\)$"):
        rig.drive.enable()


def test_realtime_against_the_node_on_canopens_notifier() -> None:
    """Wall-clock time: the node on canopen's notifier thread; the drive on a plain
    virtual bus (no native periodic send: it sends SYNC after each torque frame)."""
    channel = f"cia402-drive-{next(_CHANNELS)}"
    node = TestNode402(can.Bus(interface="virtual", channel=channel), NODE, inertia=0.01)
    host = can.Bus(interface="virtual", channel=channel)
    profile = dataclasses.replace(with_rig_units(load_profile("cia402-emulated")), enable_timeout=5.0)
    drive = make_drive(host, profile)
    try:
        node.start()
        drive.enable()
        assert node.state is NodeState.OPERATION_ENABLED and not drive.feedback_streams
        end = time.monotonic() + 5.0   # a bound for a loaded machine, not a measurement
        while node.torque != 0.25 and time.monotonic() < end:
            drive.send_torque(0.25)
            drive.poll(0.002)
        assert node.torque == 0.25
        report = drive.safe_stop(timeout=2.0)
        assert report.confirmation is Confirmation.CONFIRMED
        assert node.state is NodeState.SWITCH_ON_DISABLED and node.torque == 0.0
    finally:
        drive.disable()
        getattr(drive, "close", lambda: None)()
        host.shutdown()
        node.close()
