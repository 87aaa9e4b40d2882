"""python-can's ``set_filters`` on every bus class of dobhil (found by walking the package),
and, on the buses whose time is simulated, that a frame the filters reject does not move
the end of a ``recv`` wait (:mod:`dobhil.drives.clocked`)."""

from __future__ import annotations

import collections
import importlib
import inspect
import pkgutil
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from types import SimpleNamespace
from typing import Any

import can
import pytest
from can.typechecking import CanFilter

import dobhil
from dobhil.drives import load_profile
from dobhil.drives.clocked import ClockedBus
from dobhil.drives.emulated import LockstepBus
from dobhil.drives.emulated_nodes import EmulatedNodes
from dobhil.drives.odrive.emulator import EmulatedODrive
from dobhil.emulator.faults import FaultyBus
from dobhil.emulator.pipe import PipeBus, socket_pair
from dobhil.drives.emulated import private_virtual_channel
from dobhil.recording.runlog import RecordingBus
from dobhil.runtime.shared_bus import SharedBus

DT = 1e-3
ACCEPT, REJECT = 0x123, 0x124
#: no frame of any rig has this id
NOTHING: list[CanFilter] = [{"can_id": 0x7FE, "can_mask": 0x7FF}]


def dobhil_bus_classes() -> set[type[can.BusABC]]:
    """Every concrete ``can.BusABC`` subclass defined in ``dobhil/``."""
    found: set[type[can.BusABC]] = set()
    for info in pkgutil.walk_packages(dobhil.__path__, "dobhil."):
        if info.name == "dobhil.__main__":
            continue
        module = importlib.import_module(info.name)
        found |= {c for _, c in inspect.getmembers(module, inspect.isclass)
                  if issubclass(c, can.BusABC) and c.__module__.startswith("dobhil.")
                  and c is not ClockedBus}
    return found


class _Plant:
    inertia, position, velocity = 0.01, 0.0, 0.0

    def step(self, torque_nm: float, dt: float) -> None:
        pass


@dataclass
class Rig:
    bus: can.BusABC
    clock: Callable[[], float]
    #: sends REJECT frames then one ACCEPT frame (None: an emulator streams frames of its own)
    feed: Callable[[], None] | None
    lockstep: bool
    closers: list[Callable[[], None]] = field(default_factory=list)


def _virtual(closers: list[Callable[[], None]]) -> tuple[can.BusABC, Callable[[], None]]:
    channel = private_virtual_channel()
    mine, peer = (can.Bus(interface="virtual", channel=channel) for _ in range(2))
    closers += [mine.shutdown, peer.shutdown]

    def feed() -> None:
        for arb in (REJECT, REJECT, REJECT, ACCEPT):
            peer.send(can.Message(arbitration_id=arb, is_extended_id=False, data=b"\x01"))
    return mine, feed


def _lockstep(closers: list[Callable[[], None]]) -> LockstepBus:
    """An emulated ODrive (node 3) in lockstep: estimates (0x69) every step, a heartbeat
    (0x61) every 0.1 s."""
    channel = private_virtual_channel()
    host, drive = (can.Bus(interface="virtual", channel=channel) for _ in range(2))
    emu = EmulatedODrive(drive, load_profile("odrive-0.6"), _Plant())
    bus = LockstepBus(host, [emu], dt=DT)
    closers += [bus.shutdown, emu.close, drive.shutdown, host.shutdown]
    return bus


def _recording(inner: can.BusABC) -> RecordingBus:
    log: Any = SimpleNamespace(received=lambda topic, msg: None, sent=lambda topic, msg: None)
    return RecordingBus(inner, log)


def lockstep_rig() -> Rig:
    closers: list[Callable[[], None]] = []
    bus = _lockstep(closers)
    return Rig(bus, bus.clock, None, True, closers)


def faulty_lockstep_rig() -> Rig:
    closers: list[Callable[[], None]] = []
    bus = FaultyBus(_lockstep(closers), [])
    return Rig(bus, bus.clock, None, True, [bus.shutdown, *closers])


def recording_lockstep_rig() -> Rig:
    closers: list[Callable[[], None]] = []
    bus = _recording(_lockstep(closers))
    return Rig(bus, bus.clock, None, True, [bus.shutdown, *closers])


def faulty_virtual_rig() -> Rig:
    closers: list[Callable[[], None]] = []
    inner, feed = _virtual(closers)
    bus = FaultyBus(inner, [])
    return Rig(bus, time.monotonic, feed, False, [bus.shutdown, *closers])


def recording_virtual_rig() -> Rig:
    closers: list[Callable[[], None]] = []
    inner, feed = _virtual(closers)
    bus = _recording(inner)
    return Rig(bus, time.monotonic, feed, False, [bus.shutdown, *closers])


def shared_lockstep_rig() -> Rig:
    """A drive's view of a lockstep bus shared by several drives (it takes every frame)."""
    closers: list[Callable[[], None]] = []
    shared = SharedBus(_lockstep(closers))
    view = shared.view("drive")
    return Rig(view, view.clock, None, True, [view.shutdown, shared.shutdown, *closers])


def shared_virtual_rig() -> Rig:
    closers: list[Callable[[], None]] = []
    inner, feed = _virtual(closers)
    shared = SharedBus(inner)
    view = shared.view("drive")
    return Rig(view, time.monotonic, feed, False, [view.shutdown, shared.shutdown, *closers])


def pipe_rig() -> Rig:
    a, b = socket_pair()
    bus, peer = PipeBus(a, "host"), PipeBus(b, "drive")

    def feed() -> None:
        for arb in (REJECT, REJECT, REJECT, ACCEPT):
            peer.send(can.Message(arbitration_id=arb, is_extended_id=False, data=b"\x01"))
    return Rig(bus, time.monotonic, feed, False, [bus.shutdown, peer.shutdown])


def node_tap_rig() -> Rig:
    """A node's tap of EmulatedNodes: it reads what another node of the bus sends."""
    sink = can.Bus(interface="virtual", channel=private_virtual_channel())
    nodes = EmulatedNodes(sink)
    bus, peer = nodes.tap(), nodes.tap()

    def feed() -> None:
        for arb in (REJECT, REJECT, REJECT, ACCEPT):
            peer.send(can.Message(arbitration_id=arb, is_extended_id=False, data=b"\x01"))
    return Rig(bus, time.monotonic, feed, False, [bus.shutdown, peer.shutdown, sink.shutdown])


def dobhil_rig() -> Rig:
    bus = can.Bus(interface="dobhil")
    return Rig(bus, time.monotonic, None, False, [bus.shutdown])


#: every bus class of dobhil, each with the rigs it is tried on
RIGS: dict[str, tuple[str, Callable[[], Rig]]] = {
    "lockstep": ("LockstepBus", lockstep_rig),
    "faulty-lockstep": ("FaultyBus", faulty_lockstep_rig),
    "faulty-virtual": ("FaultyBus", faulty_virtual_rig),
    "recording-lockstep": ("RecordingBus", recording_lockstep_rig),
    "recording-virtual": ("RecordingBus", recording_virtual_rig),
    "shared-lockstep": ("BusView", shared_lockstep_rig),
    "shared-virtual": ("BusView", shared_virtual_rig),
    "pipe": ("PipeBus", pipe_rig),
    "node-tap": ("NodeTap", node_tap_rig),
    "dobhil": ("DobhilBus", dobhil_rig),
}


def test_every_bus_class_of_dobhil_has_a_rig() -> None:
    assert {c.__name__ for c in dobhil_bus_classes()} == {name for name, _ in RIGS.values()}


@pytest.fixture(params=sorted(RIGS))
def rig(request: pytest.FixtureRequest) -> Iterator[Rig]:
    made = RIGS[request.param][1]()
    yield made
    for close in made.closers:
        close()


def _listen(rig: Rig, seconds: float) -> list[can.Message]:
    """Every frame ``rig.bus`` returns for ``seconds`` of its clock."""
    end, frames = rig.clock() + seconds, []
    while (left := end - rig.clock()) > 0:
        msg = rig.bus.recv(left)
        if msg is not None:
            frames.append(msg)
    return frames


def test_set_filters_is_honoured(rig: Rig) -> None:
    if rig.feed is not None:
        rig.bus.set_filters([{"can_id": ACCEPT, "can_mask": 0x7FF}])
        rig.feed()
        msg = rig.bus.recv(10.0)
        assert msg is not None and msg.arbitration_id == ACCEPT
        assert rig.bus.recv(0.05) is None   # the rejected frames never come
        return
    ids = collections.Counter(m.arbitration_id for m in _listen(rig, 0.35))
    (busy, _), *_, (rare, _) = ids.most_common()   # estimates, heartbeats
    assert busy != rare
    rig.bus.set_filters([{"can_id": rare, "can_mask": 0x7FF}])
    got = {m.arbitration_id for m in _listen(rig, 0.35)}
    assert got == {rare}


def test_a_filter_matching_nothing_ends_the_wait_at_its_timeout(rig: Rig) -> None:
    """Rejected frames keep coming; the wait ends at its timeout: never earlier, and in
    lockstep not later than the step that reaches it."""
    if rig.feed is not None:
        rig.feed()
    rig.bus.set_filters(NOTHING)
    timeout = 0.0305
    start = rig.clock()
    assert rig.bus.recv(timeout) is None
    waited = rig.clock() - start
    assert waited >= timeout - 1e-12
    if rig.lockstep:
        assert waited < timeout + DT


@pytest.mark.parametrize("name", [n for n, (_, made) in RIGS.items() if "lockstep" in n])
def test_a_rejected_frame_does_not_move_the_frame_that_passes(name: str) -> None:
    """In lockstep the heartbeat (0x61) comes at the same simulated instant whether the
    estimates before it are read or filtered away."""
    reference, filtered = RIGS[name][1](), RIGS[name][1]()
    try:
        start, seen = reference.clock(), list[int]()
        while not seen or seen[-1] != 0x61:
            msg = reference.bus.recv(0.3)
            assert msg is not None
            seen.append(msg.arbitration_id)
        arrival = reference.clock() - start
        assert len(seen) > 50   # the estimates before it
        start = filtered.clock()
        filtered.bus.set_filters([{"can_id": 0x61, "can_mask": 0x7FF}])
        msg = filtered.bus.recv(0.3)
        assert msg is not None and msg.arbitration_id == 0x61
        assert filtered.clock() - start == arrival
    finally:
        for close in (*reference.closers, *filtered.closers):
            close()
