"""The shared bus under several drives: dispatch by arbitration id, bounded queues with
counted loss, sends straight through, one periodic task per identical periodic frame."""

from __future__ import annotations

from collections.abc import Iterator

import can
import pytest

from dobhil.drives.emulated import private_virtual_channel
from dobhil.drives.periodic import native_periodic
from dobhil.runtime.shared_bus import BusView, SharedBus


class Channel:
    """The inner bus and a peer on one private virtual channel, and the shared buses a
    test opens on the inner bus (their views are shut down after it)."""

    def __init__(self) -> None:
        name = private_virtual_channel()
        self.inner = can.Bus(interface="virtual", channel=name)
        self.peer = can.Bus(interface="virtual", channel=name)
        self.opened: list[SharedBus] = []

    def share(self, **kwargs: int) -> SharedBus:
        shared = SharedBus(self.inner, **kwargs)
        self.opened.append(shared)
        return shared

    def close(self) -> None:
        for shared in self.opened:
            for view in shared.views:
                view.shutdown()
        self.inner.shutdown()
        self.peer.shutdown()


@pytest.fixture
def channel() -> Iterator[Channel]:
    bus = Channel()
    yield bus
    bus.close()


def frame(arbitration_id: int, *data: int) -> can.Message:
    return can.Message(arbitration_id=arbitration_id, is_extended_id=False, data=bytes(data))


def ids_data(view: BusView) -> list[tuple[int, bytes]]:
    out = []
    while (msg := view.recv(0.0)) is not None:
        out.append((msg.arbitration_id, bytes(msg.data)))
    return out


def test_one_pass_dispatches_each_frame_to_its_views(channel: Channel) -> None:
    peer = channel.peer
    shared = channel.share()
    a = shared.view("a", {0x021, 0x029})     # an ODrive node 1's encoder and heartbeat, say
    b = shared.view("b", {0x041, 0x049})
    every = shared.view("every")             # no ids: takes every frame
    for msg in (frame(0x029, 1, 2), frame(0x049, 3), frame(0x021, 4), frame(0x7FF, 5)):
        peer.send(msg)
    assert shared.receive_pass(0.0) == 4
    assert ids_data(a) == [(0x029, b"\x01\x02"), (0x021, b"\x04")]
    assert ids_data(b) == [(0x049, b"\x03")]
    assert [i for i, _ in ids_data(every)] == [0x029, 0x049, 0x021, 0x7FF]
    assert shared.unclaimed == 0   # the catch-all view took 0x7FF
    every.accept({0x100})
    peer.send(frame(0x7FF, 6))
    shared.receive_pass(0.0)
    assert shared.unclaimed == 1 and ids_data(every) == []


def test_a_view_reads_through_passes_and_keeps_the_others_frames(channel: Channel) -> None:
    peer = channel.peer
    shared = channel.share()
    a, b = shared.view("a", {0x1}), shared.view("b", {0x2})
    peer.send(frame(0x2, 9))
    peer.send(frame(0x1, 8))
    msg = a.recv(0.5)   # reads b's frame on the way, and queues it for b
    assert msg is not None and msg.arbitration_id == 0x1
    assert b.pending == 1 and ids_data(b) == [(0x2, b"\x09")]
    assert a.recv(0.0) is None and b.recv(0.01) is None   # nothing left: a timeout, not a hang


def test_queues_are_bounded_and_count_their_loss(channel: Channel) -> None:
    peer = channel.peer
    shared = channel.share(queue_frames=3)
    a, b = shared.view("a", {0x10}), shared.view("b", {0x20})
    for i in range(5):
        peer.send(frame(0x10, i))
    peer.send(frame(0x20, 7))
    shared.receive_pass(0.0)
    assert a.lost == 2 and [d for _, d in ids_data(a)] == [b"\x02", b"\x03", b"\x04"]   # the newest kept
    assert b.lost == 0 and ids_data(b) == [(0x20, b"\x07")]


def test_sends_go_straight_through_in_order(channel: Channel) -> None:
    peer = channel.peer
    shared = channel.share()
    a, b = shared.view("a", {0x1}), shared.view("b", {0x2})
    a.send(frame(0x201, 1))
    b.send(frame(0x202, 2))
    a.send(frame(0x203, 3))
    got = [peer.recv(0.5) for _ in range(3)]
    assert [(m.arbitration_id, bytes(m.data)) for m in got if m is not None] == [
        (0x201, b"\x01"), (0x202, b"\x02"), (0x203, b"\x03")]


def test_filters_of_a_view_apply_to_its_frames(channel: Channel) -> None:
    peer = channel.peer
    shared = channel.share()
    a = shared.view("a")
    a.set_filters([{"can_id": 0x5, "can_mask": 0x7FF}])
    peer.send(frame(0x6, 1))
    peer.send(frame(0x5, 2))
    msg = a.recv(0.5)
    assert msg is not None and (msg.arbitration_id, bytes(msg.data)) == (0x5, b"\x02")


class CountingBus(can.BusABC):
    """A bus that counts the periodic tasks started on it (and their stops)."""

    def __init__(self) -> None:
        super().__init__(channel="counting")
        self.started: list[tuple[int, bytes, float]] = []
        self.stopped = 0
        self.channel_info = "counting"

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        pass

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        return None, True

    def _send_periodic_internal(self, msgs, period, duration=None, autostart=True,  # type: ignore[no-untyped-def]
                                modifier_callback=None):
        msg = msgs[0] if isinstance(msgs, (list, tuple)) else msgs
        self.started.append((msg.arbitration_id, bytes(msg.data), period))
        owner = self

        class Task(can.broadcastmanager.CyclicSendTaskABC):
            def stop(self) -> None:
                owner.stopped += 1
        return Task(msgs, period)


def test_identical_periodic_frames_share_one_task() -> None:
    inner = CountingBus()
    shared = SharedBus(inner)
    a, b, c = shared.view("a"), shared.view("b"), shared.view("c")
    sync = frame(0x080)
    ta = a.send_periodic(sync, 0.001)
    tb = b.send_periodic(frame(0x080), 0.001)      # the same SYNC: shared
    tc = c.send_periodic(frame(0x080), 0.002)      # another period: its own task
    td = c.send_periodic(frame(0x701, 0x05), 0.1)  # another frame: its own task
    assert inner.started == [(0x080, b"", 0.001), (0x080, b"", 0.002), (0x701, b"\x05", 0.1)]
    assert shared.shared_tasks == 3
    ta.stop()
    assert inner.stopped == 0          # b still has it
    ta.stop()                          # a second stop of one handle is no second release
    assert inner.stopped == 0
    tb.stop()
    assert inner.stopped == 1 and shared.shared_tasks == 2
    c.shutdown()                       # a view's shutdown stops its tasks (python-can's contract)
    assert inner.stopped == 3 and shared.shared_tasks == 0
    del tc, td
    a.shutdown()
    b.shutdown()
    inner.shutdown()


def test_a_view_is_as_native_as_its_bus() -> None:
    inner = CountingBus()
    view = SharedBus(inner).view("a")
    assert not native_periodic(view)
    inner.native_periodic = True  # type: ignore[attr-defined]
    assert native_periodic(view)
    view.shutdown()
    inner.shutdown()


def test_a_burst_sends_the_bus_frames_once_after_every_command(channel: Channel) -> None:
    """Two nodes that each send a SYNC (0x080) after their command, on a bus without a
    periodic send of its own: one SYNC, after both commands."""
    shared = channel.share()
    a, b = shared.view("a", {0x080, 0x181, 0x201}), shared.view("b", {0x080, 0x182, 0x202})
    assert shared.bus_wide == {0x080}
    shared.burst_begin()
    for view, command in ((a, frame(0x201, 1, 0)), (b, frame(0x202, 2, 0))):
        view.send(command)
        view.send(frame(0x080))
    shared.burst_end()
    a.send(frame(0x080))   # outside a burst: straight through
    got = []
    while (msg := channel.peer.recv(0.2)) is not None:
        got.append((msg.arbitration_id, bytes(msg.data)))
    assert got == [(0x201, b"\x01\x00"), (0x202, b"\x02\x00"), (0x080, b""), (0x080, b"")]
