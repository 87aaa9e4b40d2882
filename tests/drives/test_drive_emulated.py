"""Drive against EmulatedDrive on python-can's virtual bus: one suite over every firmware
and both timing modes (lockstep: simulated clock; real time: emulator thread).

Nothing here asserts wall-clock timing: real-time checks wait for a condition with a
generous bound, lockstep checks count simulated steps.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import can
import pytest

from dobhil.drives import DriveProfile, DriveState, load_profile, make_drive
from dobhil.drives.base import Drive
from dobhil.drives.odrive import codec
from dobhil.drives.odrive.codec import AxisState, CmdId, CmdId06, ControlMode, InputMode
from dobhil.drives.load import profile_from_mapping
from dobhil.drives.registry import drive_class
from dobhil.drives.odrive.emulator import EmulatedODrive
from dobhil.drives.emulated import LockstepBus, PlantLike
from dobhil.errors import ConfigError, DriveError, DriveFaultError, DriveTimeoutError

FIRMWARES = ("odrive-0.6", "odrive-0.5")
MODES = ("lockstep", "realtime")
_CHANNELS = itertools.count()


class FakePlant:
    """Rigid inertia, or a fixed reading when ``frozen`` (for unit checks)."""

    def __init__(self, *, inertia: float = 0.01, position: float = 0.0, velocity: float = 0.0,
                 frozen: bool = False) -> None:
        self.inertia = inertia
        self.position = position
        self.velocity = velocity
        self.frozen = frozen
        self.torques: list[float] = []

    def step(self, torque_nm: float, dt: float) -> None:
        self.torques.append(torque_nm)
        if not self.frozen:
            self.velocity += torque_nm / self.inertia * dt
            self.position += self.velocity * dt


def test_fake_plant_is_plantlike() -> None:
    """The rigs' plant: typed as the emulated drives' PlantLike (mypy checks the assignment),
    and it integrates: 1 N m on 0.01 kg m^2 for 1 ms gives 0.1 rad/s and 0.1 mrad."""
    fake = FakePlant()
    plant: PlantLike = fake
    plant.step(1.0, 0.001)
    assert fake.torques == [1.0]
    assert math.isclose(plant.velocity, 0.1) and math.isclose(plant.position, 1e-4)


def test_profile(name: str, **changes: Any) -> DriveProfile:
    """The shipped profile with rates slow enough for a loaded CI machine in real time."""
    base = dict(feedback_period=0.002, heartbeat_period=0.02, watchdog_timeout=0.1,
                enable_timeout=2.0, bus={})
    return dataclasses.replace(load_profile(name), **{**base, **changes})


test_profile.__test__ = False  # type: ignore[attr-defined]


@dataclasses.dataclass
class Rig:
    mode: str
    drive: Drive
    emu: EmulatedODrive
    plant: FakePlant
    host: can.BusABC  # what the drive talks to (LockstepBus in lockstep)
    clock: Callable[[], float]
    dt: float
    closers: list[Callable[[], None]]

    def run(self, seconds: float, torque: float | None = None) -> None:
        """Host loop: send ``torque`` (if given) and poll, for ``seconds`` of drive time."""
        end = self.clock() + seconds
        while self.clock() < end:
            if torque is not None:
                self.drive.send_torque(torque)
            self.drive.poll(self.dt)

    def wait_for(self, predicate: Callable[[], bool], seconds: float = 2.0) -> bool:
        """Let the emulator run (no host traffic) until ``predicate`` or ``seconds``."""
        end = self.clock() + seconds
        while not predicate() and self.clock() < end:
            if self.mode == "lockstep":
                self.host.step()  # type: ignore[attr-defined]
            else:
                time.sleep(0.001)
        return predicate()

    def send_raw(self, msg: object) -> None:
        self.host.send(codec.encode(msg, node_id=3, firmware=self.emu.firmware))


@pytest.fixture
def make_rig(request: pytest.FixtureRequest) -> Iterator[Callable[..., Rig]]:
    rigs: list[Rig] = []

    def build(mode: str, name: str, *, emu_node: int = 3, plant: FakePlant | None = None,
              latency: float = 0.0, jitter: float = 0.0, **changes: Any) -> Rig:
        profile = test_profile(name, **changes)
        channel = f"dobhil-test-{next(_CHANNELS)}"
        host_bus = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)
        emu_bus = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)
        plant = plant or FakePlant()
        emu_profile = dataclasses.replace(profile, node_id=emu_node)
        emu = EmulatedODrive(emu_bus, emu_profile, plant, latency=latency, jitter=jitter, seed=7)
        closers: list[Callable[[], None]] = [emu.close, host_bus.shutdown]
        if mode == "lockstep":
            host: can.BusABC = LockstepBus(host_bus, [emu], dt=profile.feedback_period)
            clock = host.clock  # type: ignore[attr-defined]
            closers.insert(0, host.shutdown)
        else:
            host, clock = host_bus, time.monotonic
            emu.start()
        drive = make_drive(host, profile, clock=clock)
        rig = Rig(mode, drive, emu, plant, host, clock, profile.feedback_period, closers)
        rigs.append(rig)
        return rig

    yield build
    for rig in rigs:
        for close in rig.closers:
            close()


@pytest.fixture(params=[(m, f) for m in MODES for f in FIRMWARES], ids=lambda p: f"{p[0]}-{p[1]}")
def rig(request: pytest.FixtureRequest, make_rig: Callable[..., Rig]) -> Rig:
    mode, name = request.param
    return make_rig(mode, name)


# ---------------------------------------------------------------------------
# The suite over every firmware and timing mode


def test_enable_reaches_closed_loop_torque_mode(rig: Rig) -> None:
    rig.drive.enable()
    assert rig.drive.status.state is DriveState.ENABLED
    assert rig.emu.axis_state is AxisState.CLOSED_LOOP_CONTROL
    assert rig.emu.control_mode == ControlMode.TORQUE_CONTROL
    assert rig.emu.input_mode == InputMode.PASSTHROUGH
    assert rig.emu.frames_received >= 4


def test_torque_reaches_plant_only_when_enabled(rig: Rig) -> None:
    with pytest.raises(DriveError, match="needs an enabled drive"):
        rig.drive.send_torque(0.5)
    rig.send_raw(codec.SetControllerMode(ControlMode.TORQUE_CONTROL, InputMode.PASSTHROUGH))
    rig.send_raw(codec.SetInputTorque(0.5))
    assert rig.wait_for(lambda: len(rig.plant.torques) >= 10)
    assert set(rig.plant.torques) == {0.0} and rig.emu.applied_torque == 0.0

    rig.drive.enable()
    rig.run(0.02, torque=0.5)
    assert rig.emu.applied_torque == 0.5
    assert rig.wait_for(lambda: rig.plant.torques[-1] == 0.5)


def test_drive_clamps_to_profile_torque_limit(rig: Rig) -> None:
    rig.drive.enable()
    rig.run(0.01, torque=-100.0)
    assert rig.emu.applied_torque == -rig.drive.profile.torque_limit


def test_feedback_is_in_rad_and_rad_per_s(make_rig: Callable[..., Rig], mode: str, name: str) -> None:
    plant = FakePlant(position=1.0, velocity=-2.0, frozen=True)
    rig = make_rig(mode, name, plant=plant)
    first = None
    while first is None:
        first = rig.drive.poll(0.05)
    second = None
    while second is None:
        second = rig.drive.poll(0.05)
    assert math.isclose(second.position, 1.0, rel_tol=1e-6)
    assert math.isclose(second.velocity, -2.0, rel_tol=1e-6)
    assert second.seq > first.seq and second.timestamp >= first.timestamp


def test_disable_goes_idle_with_zero_torque(rig: Rig) -> None:
    rig.drive.enable()
    rig.run(0.01, torque=0.5)
    assert rig.drive.disable() is True
    assert rig.drive.status.state is DriveState.DISABLED
    assert rig.wait_for(lambda: rig.emu.axis_state is AxisState.IDLE)
    assert rig.emu.input_torque == 0.0 and rig.emu.applied_torque == 0.0
    assert rig.wait_for(lambda: rig.plant.torques[-1] == 0.0)


#: rigs of one real-time check at most: an emulator thread the machine did not run for three
#: heartbeat periods sent no heartbeat, and the host rightly calls the drive silent before its
#: watchdog can trip; such a rig (the emulator counts the ticks it skipped) is made again
STARVED_RIGS = 3


def test_watchdog_trips_when_commands_stop(make_rig: Callable[..., Rig], mode: str, name: str) -> None:
    for _ in range(STARVED_RIGS if mode == "realtime" else 1):
        rig = make_rig(mode, name)
        rig.drive.enable()
        rig.run(0.01, torque=0.2)
        skipped = rig.emu.overruns
        with pytest.raises(DriveFaultError) as raised:
            rig.run(1.0)  # polls only: no command feeds the watchdog
        # a stalled emulator counts the ticks it skipped once it runs again: two ticks on
        ticked = rig.emu.time + 2 * rig.dt
        rig.wait_for(lambda emu=rig.emu, at=ticked: emu.time >= at)
        if "WATCHDOG_TIMER_EXPIRED" in str(raised.value) or rig.emu.overruns == skipped:
            break
    assert "WATCHDOG_TIMER_EXPIRED" in str(raised.value), raised.value
    status = rig.drive.status
    assert status.state is DriveState.FAULT and status.watchdog_tripped
    assert status.error_code == codec.watchdog_bit(rig.emu.firmware)
    assert rig.emu.watchdog_tripped and rig.emu.axis_state is AxisState.IDLE
    assert rig.emu.applied_torque == 0.0
    with pytest.raises(DriveFaultError):
        rig.drive.send_torque(0.1)
    rig.drive.enable()  # Clear_Errors recovers
    assert rig.drive.status.state is DriveState.ENABLED and not rig.emu.watchdog_tripped


def test_estop_is_reported_as_fault(rig: Rig) -> None:
    rig.drive.enable()
    rig.send_raw(codec.Estop())
    with pytest.raises(DriveFaultError, match="ESTOP_REQUESTED"):
        rig.run(1.0, torque=0.1)
    assert rig.drive.status.state is DriveState.FAULT
    assert not rig.drive.status.watchdog_tripped


def test_drive_that_never_answers_times_out(make_rig: Callable[..., Rig], mode: str, name: str) -> None:
    rig = make_rig(mode, name, emu_node=4, enable_timeout=0.3)
    with pytest.raises(DriveTimeoutError, match=r"^no heartbeat from node 3 within 0.3 s"):
        rig.drive.enable()
    assert rig.emu.axis_state is AxisState.IDLE


def test_drive_that_stays_idle_names_state_and_error(
    make_rig: Callable[..., Rig], mode: str, name: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    rig = make_rig(mode, name, enable_timeout=0.3)
    monkeypatch.setitem(rig.emu._handlers, codec.SetAxisState, lambda msg: None)
    with pytest.raises(DriveTimeoutError, match=r"last seen IDLE with error 0x00000000 \(none\)"):
        rig.drive.enable()


def test_disable_never_raises_on_a_dead_bus(rig: Rig) -> None:
    rig.drive.enable()
    (rig.host._inner if rig.mode == "lockstep" else rig.host).shutdown()  # type: ignore[attr-defined]
    assert rig.drive.disable() is False
    assert rig.drive.status.state is DriveState.DISABLED
    assert "disable of node 3 failed" in rig.drive.status.detail


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_non_finite_torque_is_rejected(rig: Rig, bad: float) -> None:
    rig.drive.enable()
    with pytest.raises(DriveError, match="expected a finite value"):
        rig.drive.send_torque(bad)


def test_realtime_with_latency_and_jitter(make_rig: Callable[..., Rig], name: str) -> None:
    rig = make_rig("realtime", name, latency=0.002, jitter=0.001)
    rig.drive.enable()
    rig.run(0.03, torque=0.25)
    assert rig.wait_for(lambda: rig.plant.torques[-1] == 0.25)
    assert rig.drive.disable()


@pytest.fixture(params=MODES)
def mode(request: pytest.FixtureRequest) -> str:
    return request.param


@pytest.fixture(params=FIRMWARES)
def name(request: pytest.FixtureRequest) -> str:
    return request.param


# ---------------------------------------------------------------------------
# Lockstep specifics (deterministic step counts)


def test_lockstep_emits_encoder_every_step_and_heartbeat_at_its_rate(
    make_rig: Callable[..., Rig], name: str
) -> None:
    rig = make_rig("lockstep", name)
    for _ in range(20):
        rig.emu.advance(rig.dt)
    assert rig.emu.frames_sent == 20 + 2  # 20 encoder frames, heartbeats at 0.02 and 0.04


def test_lockstep_latency_delays_commands_by_whole_steps(make_rig: Callable[..., Rig], name: str) -> None:
    rig = make_rig("lockstep", name, latency=0.006)
    rig.drive.enable()
    rig.drive.send_torque(0.375)
    applied = []
    for _ in range(5):
        rig.host.step()  # type: ignore[attr-defined]
        applied.append(rig.emu.applied_torque)
    assert applied == [0.0, 0.0, 0.375, 0.375, 0.375]


def test_lockstep_answers_rtr_requests(make_rig: Callable[..., Rig]) -> None:
    rig = make_rig("lockstep", "odrive-0.6")
    rig.drive.enable()
    rig.run(0.004, torque=0.5)
    rig.drive.poll(0.0)  # drain what the drive has not read yet
    inner = rig.host._inner  # type: ignore[attr-defined]
    expected = {
        CmdId06.GET_TORQUES: codec.Torques(0.5, 0.5),
        CmdId06.GET_ERROR: codec.GetError(0, 0),
        CmdId.GET_BUS_VOLTAGE_CURRENT: codec.BusVoltageCurrent(24.0, 0.0),
        CmdId.HEARTBEAT: codec.Heartbeat(0, AxisState.CLOSED_LOOP_CONTROL, trajectory_done=True),
    }
    for cmd, reply in expected.items():
        rig.send_raw(codec.Request(cmd))
        rig.emu.handle_pending()
        frame = inner.recv(0.0)
        assert frame.arbitration_id == codec.arbitration_id(3, cmd)
        assert codec.decode_message(frame) == reply


def test_lockstep_safe_stop_of_06_asks_for_its_heartbeat(make_rig: Callable[..., Rig]) -> None:
    """A 0.6 drive answers a heartbeat RTR (the enable relies on it too): the safe stop asks
    for the heartbeat that confirms IDLE instead of waiting for the cyclic one, which with
    a 10 s heartbeat period came 10 s later (simulated time here)."""
    rig = make_rig("lockstep", "odrive-0.6", heartbeat_period=10.0)
    rig.drive.enable()
    rig.run(0.005, torque=0.25)
    start = rig.clock()
    report = rig.drive.safe_stop()
    assert report.safe, report.detail
    assert rig.emu.axis_state is AxisState.IDLE
    assert rig.clock() - start < 0.1


# ---------------------------------------------------------------------------
# Profiles and registry


def test_shipped_profiles_load() -> None:
    for name, firmware in (("odrive-0.6", "0.6"), ("odrive-0.5", "0.5")):
        profile = load_profile(name)
        assert profile.protocol == "odrive" and profile.firmware == firmware
        assert profile.name == name and profile.bus_kwargs()["interface"] == "socketcan"


def _mapping(**changes: Any) -> dict[str, Any]:
    data = dict(protocol="odrive", firmware="0.6", node_id=3, torque_limit=2.0,
                velocity_limit=50.0, feedback_period=0.001, heartbeat_period=0.1,
                watchdog_timeout=0.05, enable_timeout=1.0)
    data.update(changes)
    return {k: v for k, v in data.items() if v is not None}


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        (dict(torque_limt=1.0), r"unknown key 'torque_limt' \(allowed: protocol, "),
        (dict(node_id=None), r"missing key 'node_id'"),
        (dict(firmware=0.6), r"firmware: expected a quoted version string such as '0.6', got 0.6"),
        (dict(torque_limit=-1), r"torque_limit: expected a number > 0 and <= 10000 Nm, got -1"),
        (dict(node_id=True), r"node_id: expected an integer from 0 to 536870911 \(29-bit CAN id\), got True"),
        (dict(bus="can0"), r"bus: expected a mapping"),
    ],
)
def test_profile_errors_name_key_value_and_rule(changes: dict[str, Any], message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        profile_from_mapping(_mapping(**changes), source="x.yaml")


def test_load_profile_by_path_and_missing_name(tmp_path: Path) -> None:
    path = tmp_path / "mine.yaml"
    path.write_text("\n".join(f"{k}: {v!r}" for k, v in _mapping().items()), encoding="utf-8")
    assert load_profile(path).name == "mine"
    known = (r"\['ak10-9', 'ak10-9-1.1', 'ak70-10', 'ak70-10-1.1', 'ak80-9', 'ak80-9-1.1', 'ak80-9-2.0', "
             r"'cia402-emulated', 'dm4310', 'dm8009', 'epos4', 'mini-cheetah', 'moteus-r4.11', 'odrive-0.5', "
             r"'odrive-0.6', 'odrive-0.6-factory'\]")  # not the MIT model table beside them (dobhil.data.DRIVER_TABLES)
    with pytest.raises(ConfigError, match=rf"drive profile 'nope': expected one of {known}"):
        load_profile("nope")


def test_registry_resolves_lazily_and_rejects_unknown() -> None:
    assert drive_class("odrive").__name__ == "ODriveDrive"
    with pytest.raises(ConfigError, match=r"protocol: expected one of \['cia402', 'mit', 'moteus', 'odrive'\], "
                       r"got 'cia402x'"):
        drive_class("cia402x")


def test_odrive_rejects_bad_firmware_and_node() -> None:
    bus = can.Bus(interface="virtual", channel=f"dobhil-test-{next(_CHANNELS)}")
    try:
        with pytest.raises(ConfigError, match="firmware: expected '0.5' or '0.6' for ODrive, got '0.4'"):
            make_drive(bus, profile_from_mapping(_mapping(firmware="0.4")))
        with pytest.raises(ConfigError, match="node_id: expected 0..63 for ODrive, got 64"):
            make_drive(bus, profile_from_mapping(_mapping(node_id=64)))
    finally:
        bus.shutdown()
