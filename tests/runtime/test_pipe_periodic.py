"""Periodic send on the emulator process's bus: the child sends the frames on its own
clock (like the kernel's broadcast manager), echoes them to the host and its mirror, and
hands them to the emulated drive."""

from __future__ import annotations

import math
import time

import can
import pytest

from dobhil.drives.odrive.codec import CmdId
from dobhil.drives.periodic import native_periodic
from dobhil.drives.load import load_drive_profile
from dobhil.emulator.pipe import PeriodicTable, PipeBus, RecordKind, periodic_record, socket_pair
from dobhil.emulator.process import EmulatorProcess, EmulatorSpec

from .helpers import DEMO, demo_config, wait_until

SYNC = 0x80


def _msg(data: bytes = b"", arbitration_id: int = SYNC) -> can.Message:
    return can.Message(arbitration_id=arbitration_id, is_extended_id=False, data=data)


def test_the_table_sends_at_k_periods_after_the_start_on_the_peers_clock() -> None:
    now = [0.003]
    table = PeriodicTable(lambda: now[0])
    table.record(periodic_record(RecordKind.PERIODIC_START, 1, [_msg(b"a"), _msg(b"b")], 0.002))
    table.record(periodic_record(RecordKind.PERIODIC_START, 2, [_msg(b"x", 0x81)], 0.003, duration=0.006))
    got = []
    for tick in range(3, 16):   # ticks of 1 ms: the peer asks at each tick's start
        got += [(tick, bytes(m.data)) for m in table.due(tick * 1e-3)]
    assert got == [(5, b"a"), (6, b"x"), (7, b"b"), (9, b"a"), (9, b"x"), (11, b"b"), (13, b"a"), (15, b"b")]
    assert len(table) == 1   # the one with a duration ended
    table.record(periodic_record(RecordKind.PERIODIC_MODIFY, 1, [_msg(b"c")], 0.002))
    assert [bytes(m.data) for m in table.due(0.017)] == [b"c"]
    table.record(periodic_record(RecordKind.PERIODIC_STOP, 1))
    assert table.due(0.1) == [] and len(table) == 0


def test_a_long_run_of_ticks_summed_in_floats_never_drops_or_doubles_a_frame() -> None:
    table = PeriodicTable()
    table.record(periodic_record(RecordKind.PERIODIC_START, 1, [_msg()], 1e-3))
    t, counts = 0.0, []
    for _ in range(200_000):   # the emulator's clock: one period added per tick
        t += 1e-3
        counts.append(len(table.due(t)))
    assert set(counts) == {1}


def test_a_pipe_without_a_ticking_peer_uses_python_cans_thread() -> None:
    a, b = socket_pair()
    with PipeBus(a, "host") as host, PipeBus(b, "drive") as drive:
        assert not native_periodic(host)
        task = host.send_periodic(_msg(), 0.001)
        assert type(task).__name__ == "ThreadBasedCyclicSendTask"
        assert drive.recv(5.0) is not None
        task.stop()


def test_the_emulator_process_sends_the_frames_echoes_them_and_its_drive_reads_them() -> None:
    config = demo_config()
    profile = load_drive_profile(config, DEMO.parent)
    period = profile.feedback_period
    estimates = (profile.node_id << 5) | CmdId.GET_ENCODER_ESTIMATES
    with can.Bus(interface="virtual", channel="pipe-periodic-mirror") as mirror, \
            can.Bus(interface="virtual", channel="pipe-periodic-mirror") as observer, \
            EmulatorProcess(EmulatorSpec.of(config, profile), channel="emu", mirror=mirror) as proc:
        bus = proc.bus
        assert native_periodic(bus)
        with pytest.raises(ValueError, match="finite number"):
            bus.send_periodic(_msg(), math.nan)
        received_before = proc.frames_received
        task = bus.send_periodic(_msg(b"\x01"), 2 * period)
        stream: list[can.Message] = []

        def echoes() -> list[can.Message]:
            return [m for m in stream if m.arbitration_id == SYNC]

        def read_until(enough: int) -> bool:
            end = time.monotonic() + 30.0   # a bound for a loaded machine, not a measure
            while len(echoes()) < enough and time.monotonic() < end:
                msg = bus.recv(0.5)
                if msg is not None:
                    stream.append(msg)
            return len(echoes()) >= enough

        assert read_until(6)
        task.modify_data(_msg(b"\x02"))
        assert read_until(len(echoes()) + 6)
        # each echo two of the drive's ticks after the one before: two encoder frames
        # (one per tick) between echoes, on the ordered stream from the child
        where = [i for i, m in enumerate(stream) if m.arbitration_id == SYNC]
        between = [sum(1 for m in stream[i + 1:j] if m.arbitration_id == estimates)
                   for i, j in zip(where, where[1:])]
        assert between and set(between) == {2}
        datas = [bytes(m.data) for m in echoes()]
        assert datas[0] == b"\x01" and datas[-1] == b"\x02" and sorted(datas) == datas
        stamps = [m.timestamp for m in echoes()]
        assert stamps == sorted(stamps)
        task.stop()
        _stop_read(proc, bus, stream)
        # the emulated drive read every one of them and the request (the host sent nothing else)
        assert wait_until(lambda: proc.frames_received - received_before == len(echoes()) + 1, 10.0)
        # the mirror has a copy of each
        copies = []
        while (msg := observer.recv(0.0)) is not None:
            copies.append(msg)
        assert [bytes(m.data) for m in copies if m.arbitration_id == SYNC] == [bytes(m.data) for m in echoes()]


def _stop_read(proc: EmulatorProcess, bus: can.BusABC, stream: list[can.Message]) -> None:
    """After a stop: the child read it once it answers a request sent after it (the stream
    is ordered both ways); then no echo may come, however long the drive ticks on."""
    node = proc.profile.node_id
    bus.send(can.Message(arbitration_id=(node << 5) | CmdId.GET_BUS_VOLTAGE_CURRENT, is_extended_id=False,
                         is_remote_frame=True, dlc=8))
    reply = (node << 5) | CmdId.GET_BUS_VOLTAGE_CURRENT
    end = time.monotonic() + 30.0
    while not any(m.arbitration_id == reply for m in stream) and time.monotonic() < end:
        msg = bus.recv(0.5)
        if msg is not None:
            stream.append(msg)
    answered = next(i for i, m in enumerate(stream) if m.arbitration_id == reply)
    now = proc.time
    assert wait_until(lambda: proc.time >= now + 10 * proc.profile.feedback_period, 30.0)
    while (msg := bus.recv(0.0)) is not None:
        stream.append(msg)
    assert len(stream) > answered + 10   # the drive's own frames went on
    assert [m for m in stream[answered:] if m.arbitration_id == SYNC] == []


def test_shutdown_stops_the_childs_tasks() -> None:
    config = demo_config()
    profile = load_drive_profile(config, DEMO.parent)
    with EmulatorProcess(EmulatorSpec.of(config, profile)) as proc:
        proc.bus.send_periodic(_msg(), profile.feedback_period)
        stream: list[can.Message] = []
        end = time.monotonic() + 30.0
        while sum(m.arbitration_id == SYNC for m in stream) < 3 and time.monotonic() < end:
            if (msg := proc.bus.recv(0.5)) is not None:
                stream.append(msg)
        assert sum(m.arbitration_id == SYNC for m in stream) >= 3   # the task ran before it is stopped
        proc.bus.stop_all_periodic_tasks()   # what the bus's shutdown does first
        _stop_read(proc, proc.bus, stream)


def test_the_dobhil_interface_is_native_too() -> None:
    """``can.Bus(interface="dobhil")``: the emulator's process sends them, the bus reads the echoes."""
    with can.Bus(interface="dobhil", channel="demo") as bus:
        assert native_periodic(bus)
        task = bus.send_periodic(_msg(b"\x07"), 0.002)
        end = time.monotonic() + 30.0
        echoes = 0
        while echoes < 3 and time.monotonic() < end:
            msg = bus.recv(0.5)
            echoes += msg is not None and msg.arbitration_id == SYNC and bytes(msg.data) == b"\x07"
        assert echoes == 3
        task.stop()
