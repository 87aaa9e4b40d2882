"""Safety across axes (lockstep, every protocol): one axis' fault stops every axis, each
safe stop attempted and confirmed on its own; an enable that fails leaves the axes
already enabled confirmed disabled; the stop line names the axis, the loud line lists
every axis not confirmed disabled."""

from __future__ import annotations

from collections.abc import Callable, Collection, Sequence
from pathlib import Path

import can
import pytest

from dobhil.drives.emulated import private_virtual_channel
from dobhil.drives.load import load_drive_profile
from dobhil.drives.registry import make_drive, protocol
from dobhil.drives.base import Feedback
from dobhil.emulator.faults import Direction, Fault, faulty
from dobhil.runtime.controller import ControlOutput
from dobhil.runtime.axes_session import AxesSession
from dobhil.runtime.loop import StopRequest
from dobhil.runtime.stop import Stop, StopReason

from .axes_helpers import CONFIGS, assert_all_stopped, load_two

PROTOCOLS = ("odrive", "cia402", "mit", "moteus")
AT = 100   # the fault strikes around cycle 100 of 300


class LoseNode(Fault):
    """Frames of one node lost: matching ``ids`` (and, on a reply id every node shares, the
    node id in byte 0), from the ``at``-th on, ``count`` of them (None: for good)."""

    def __init__(self, ids: Collection[int], *, at: int, count: int | None = None, byte0: int | None = None) -> None:
        super().__init__(ids)
        self.at, self.count, self.byte0 = at, count, byte0

    def heal(self) -> None:
        """The frames come through again from now on (a transient loss)."""
        self.count = max(self.matched - self.at, 0)

    def matches(self, msg: can.Message) -> bool:
        return super().matches(msg) and (self.byte0 is None or (len(msg.data) > 0 and msg.data[0] == self.byte0))

    def apply(self, msg: can.Message, index: int, now: float) -> Sequence[can.Message]:
        if index >= self.at and (self.count is None or index < self.at + self.count):
            self.applied += 1
            return ()
        return (msg,)


def _node(session_axes: object, config_dir: Path, name: str) -> tuple[frozenset[int], int | None, bool]:
    """An axis' frame ids, the byte-0 node id when its replies share one id, whether its
    drive can confirm a disable (a drive built on a throwaway bus: nothing is sent)."""
    axis = session_axes.axis(name)  # type: ignore[attr-defined]
    profile = load_drive_profile(axis.config, config_dir)
    fd = {"protocol": can.CanProtocol.CAN_FD} if protocol(profile.protocol).fd else {}
    bus = can.Bus(interface="virtual", channel=private_virtual_channel(), **fd)
    try:
        drive = make_drive(bus, profile)
        ids, confirms = drive.frame_ids or frozenset(), drive.confirms_disable
    finally:
        bus.shutdown()
    byte0 = profile.node_id if profile.protocol == "mit" else None
    return frozenset(ids), byte0, confirms


def _motion_ids(axes: object, name: str) -> frozenset[int]:
    """The arbitration ids of the frames carrying the axis' motion feedback: its protocol's
    velocity (else position) frame where it lays one out apart from the state, else every
    frame of the node (a drive whose one reply carries both)."""
    axis = axes.axis(name)  # type: ignore[attr-defined]
    profile = load_drive_profile(axis.config, CONFIGS)
    plugin = protocol(profile.protocol)
    where = plugin.feedback_field(profile, "velocity") or plugin.feedback_field(profile, "position")
    return frozenset({where.arbitration_id}) if where is not None else _node(axes, CONFIGS, name)[0]


class HealOnStop:
    """A sink that ends a transient loss when the run stops (its safe stop is then heard)."""

    def __init__(self, fault: LoseNode) -> None:
        self.fault = fault
        self.stops: list[Stop] = []

    def started(self, fb: Feedback) -> None:
        pass

    def cycle(self, k: int, t: float, fb: Feedback, out: ControlOutput, period_error: float,
              exec_time: float, overrun: bool) -> None:
        pass

    def stop(self, stop: Stop) -> None:
        self.stops.append(stop)
        self.fault.heal()


def _run(tmp_path: Path, proto: str, make_fault: Callable[[object], LoseNode]):  # type: ignore[no-untyped-def]
    axes = load_two(tmp_path, (proto, proto))
    fault = make_fault(axes)
    with AxesSession(axes, emulate=True, lockstep=True, config_dir=CONFIGS, sinks={"left": HealOnStop(fault)},
                     bus_wrapper=lambda bus, name: faulty(fault)(bus)) as session:
        result = session.run()
        applied = [getattr(e, "applied_torque", None) for e in session.emulators]
    return axes, fault, result, applied


@pytest.mark.parametrize("proto", PROTOCOLS)
def test_feedback_loss_of_one_axis_stops_both(tmp_path: Path, proto: str) -> None:
    def fault(axes: object) -> LoseNode:
        _, byte0, _ = _node(axes, CONFIGS, "left")
        # lost until the run stops (a transient loss: the drive is heard again for its safe stop)
        return LoseNode(_motion_ids(axes, "left"), at=AT, byte0=byte0)

    axes, lost, result, applied = _run(tmp_path, proto, fault)
    assert lost.applied > 0
    line = result.stop.line()
    assert result.stop.reason is StopReason.FEEDBACK_TIMEOUT, line
    assert result.axis == "left" and "axis left" in line and "\n" not in line
    # (the fault counts the frames of the enable too: it strikes a little before cycle AT)
    assert AT // 2 < result.stop.cycle < 300 and result.cycles < 300
    confirmable = {n: _node(axes, CONFIGS, n)[2] for n in ("left", "right")}
    assert_all_stopped(result, confirmable=confirmable)
    assert applied == [0.0, 0.0]   # both emulated drives hold no torque after the run
    # the right axis ran every cycle the left one did, and stopped with it
    assert result.axes["right"].cycles == result.axes["left"].cycles == result.cycles
    warned = result.warning()
    assert all(f"axis {n}" in warned for n, ok in confirmable.items() if not ok)
    assert all(f"axis {n}" not in warned for n, ok in confirmable.items() if ok)


@pytest.mark.parametrize("proto", PROTOCOLS)
def test_enable_failure_of_the_second_axis_stops_the_first(tmp_path: Path, proto: str) -> None:
    def fault(axes: object) -> LoseNode:
        ids, byte0, _ = _node(axes, CONFIGS, "right")
        return LoseNode(ids, at=0, byte0=byte0)   # the host never hears the right axis

    axes, _, result, applied = _run(tmp_path, proto, fault)
    line = result.stop.line()
    assert result.stop.reason is StopReason.ENABLE_FAILED, line
    assert result.axis == "right" and "axis right" in line and result.cycles == 0
    left, right = result.axes["left"], result.axes["right"]
    assert left.safe_stop is not None and left.safe_stop.sent
    if _node(axes, CONFIGS, "left")[2]:
        assert left.disabled, left.safe_stop   # enabled, then confirmed disabled
    else:   # cannot confirm by design: answered, and said loudly (not a planned end)
        assert left.safe_stop.confirmation.name == "UNCONFIRMABLE"
    # the right one's frames went out too (what it confirms is its protocol's word for a
    # drive never heard of); the emulated drives both hold no torque
    assert right.safe_stop is not None and right.safe_stop.sent
    assert "axis left" not in result.warning() or not _node(axes, CONFIGS, "left")[2]
    assert applied == [0.0, 0.0]


class RequestStopAt:
    """A sink that asks the run to stop (as SIGINT does) at cycle ``at``."""

    def __init__(self, request: StopRequest, at: int) -> None:
        self.request, self.at = request, at

    def started(self, fb: Feedback) -> None:
        pass

    def cycle(self, k: int, t: float, fb: Feedback, out: ControlOutput, period_error: float,
              exec_time: float, overrun: bool) -> None:
        if k == self.at:
            self.request.set("SIGINT")

    def stop(self, stop: Stop) -> None:
        pass


def test_a_stop_request_stops_every_axis(tmp_path: Path) -> None:
    axes = load_two(tmp_path, ("odrive", "odrive"))
    request = StopRequest()
    with AxesSession(axes, emulate=True, lockstep=True, config_dir=CONFIGS, stop_request=request,
                     sinks={"right": RequestStopAt(request, AT)}) as session:
        result = session.run()
    assert result.stop.reason is StopReason.SIGNAL and result.axis == "", result.stop.line()
    assert "SIGINT" in result.stop.line() and "axis" not in result.stop.line()
    assert result.cycles == AT + 1   # the cycle that asked ran to its end; the next did not
    assert_all_stopped(result, confirmable={"left": True, "right": True})


def test_one_axis_limit_stops_both(tmp_path: Path) -> None:
    # the right axis starts 5 mrad before contact and moves towards it: its own limit trips
    axes = load_two(tmp_path, ("odrive", "odrive"), "axes.right.loop.position_max=-0.004")
    with AxesSession(axes, emulate=True, lockstep=True, config_dir=CONFIGS) as session:
        result = session.run()
        applied = [e.applied_torque for e in session.emulators]  # type: ignore[union-attr]
    line = result.stop.line()
    assert result.stop.reason is StopReason.POSITION_LIMIT and result.axis == "right", line
    assert "axis right: q = " in line and "-0.004" in line
    assert 0 < result.cycles < 300
    assert_all_stopped(result, confirmable={"left": True, "right": True})
    assert applied == [0.0, 0.0]


class ReadsFail(Fault):
    """After ``after`` frames received, every read of the bus fails as a python-can-remote
    hub killed mid-run makes it fail (its websocket reset); sending still works, so the
    failure is met where the loop reads, not where it sends."""

    def __init__(self, *, after: int) -> None:
        super().__init__()
        self.after = after

    def apply(self, msg: can.Message, index: int, now: float) -> Sequence[can.Message]:
        return (msg,)

    def check(self, direction: Direction, now: float) -> None:
        if direction is Direction.RECV and self.matched >= self.after:
            self.applied += 1
            raise ConnectionResetError(104, "Connection reset by peer")


@pytest.mark.parametrize("proto", PROTOCOLS)
def test_a_bus_whose_reads_fail_mid_run_is_a_bus_error(tmp_path: Path, proto: str) -> None:
    """The bus' reads fail: the run's stop is bus_error, as for one axis, not an exception
    (the several-axis loop reads the shared bus itself, not through a drive), and every
    axis' safe stop is attempted, loudly unconfirmed (nothing can be read back)."""
    axes = load_two(tmp_path, (proto, proto))
    fails = ReadsFail(after=2 * AT)   # both nodes' frames count: about cycle AT
    with AxesSession(axes, emulate=True, lockstep=True, config_dir=CONFIGS,
                     bus_wrapper=lambda bus, name: faulty(fails)(bus)) as session:
        result = session.run()
    line = result.stop.line()
    assert result.stop.reason is StopReason.BUS_ERROR, line
    assert "Connection reset by peer" in line and "\n" not in line
    assert fails.applied > 0 and 0 < result.stop.cycle < 300
    warned = result.warning()
    assert all(f"axis {n}" in warned for n in ("left", "right")), warned


def test_foreign_frames_are_counted_unclaimed_in_the_summary(tmp_path: Path) -> None:
    """Foreign traffic on the axes' bus (other nodes' frames): no drive takes it, the run
    goes on, and the summary counts every such frame the loop read (``frames_unclaimed``);
    no axis lost a frame of its own (``frames_lost``)."""
    from dobhil.emulator.faults import Flood
    from dobhil.runtime.axes_session import axes_summary
    axes = load_two(tmp_path, ("odrive", "odrive"))
    own = {node << 5 | cmd for node in (1, 2) for cmd in range(32)}   # ODrive: node id << 5 | command
    flood = Flood(2, avoid=own, seed=3)
    with AxesSession(axes, emulate=True, lockstep=True, config_dir=CONFIGS,
                     bus_wrapper=lambda bus, name: faulty(flood)(bus)) as session:
        result = session.run()
        info = axes_summary(session, result)
    assert result.stop.reason is StopReason.DONE, result.stop.line()
    (unclaimed,) = info["frames_unclaimed"].values()
    assert unclaimed == flood.applied > 0
    assert [a["frames_lost"] for a in info["axes"].values()] == [0, 0]
    # each axis names the bus it ran on: the emulator's private channel, not the configured one
    assert [a["bus"].split(":")[0] for a in info["axes"].values()] == ["virtual", "virtual"], info["axes"]
