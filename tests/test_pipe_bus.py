"""The bus between the host and an emulated drive in its own process (a socket pair)."""

from __future__ import annotations

import time

import can
import pytest

from dobhil.emulator.pipe import PipeBus, socket_pair


def test_frames_cross_with_their_fields_and_the_senders_stamp() -> None:
    a, b = socket_pair()
    with PipeBus(a, "host") as host, PipeBus(b, "drive") as drive:
        sent = [can.Message(arbitration_id=0x123, is_extended_id=False, data=b"\x01\x02"),
                can.Message(arbitration_id=0x1ABCDE, is_extended_id=True, is_remote_frame=True, dlc=8),
                can.Message(arbitration_id=0x7, is_extended_id=False, is_fd=True, bitrate_switch=True,
                            data=bytes(range(12)))]
        before = time.time()
        for msg in sent:
            host.send(msg)
        got = [drive.recv(1.0) for _ in sent]
        assert drive.recv(0.0) is None
        for want, msg in zip(sent, got):
            assert msg is not None and msg.is_rx and msg.channel == "drive"
            assert msg.equals(want, timestamp_delta=None, check_channel=False, check_direction=False)
            assert before <= msg.timestamp <= time.time()


def test_own_messages_and_a_closed_peer() -> None:
    a, b = socket_pair()
    host = PipeBus(a, "host", receive_own_messages=True, gone=lambda: "the drive is gone")
    drive = PipeBus(b, "drive")
    try:
        host.send(can.Message(arbitration_id=5, is_extended_id=False))
        own = host.recv(0.0)
        assert own is not None and own.arbitration_id == 5 and not own.is_rx
        drive.shutdown()
        with pytest.raises(can.CanOperationError, match="the drive is gone"):
            host.recv(1.0)
        with pytest.raises(can.CanOperationError, match="the drive is gone"):
            host.send(can.Message(arbitration_id=5, is_extended_id=False))
    finally:
        host.shutdown()
        drive.shutdown()


def test_a_peer_that_does_not_read_never_blocks_the_sender() -> None:
    """The drive's end refuses at once (counted by the emulator, as a full CAN queue
    drops); the host's end waits at most its bound, even without a timeout."""
    a, b = socket_pair()
    with PipeBus(a, "host", send_wait=0.02) as host, PipeBus(b, "drive", send_wait=0.0) as drive:
        msg = can.Message(arbitration_id=1, is_extended_id=False, data=bytes(8))
        with pytest.raises(can.CanOperationError, match="not reading"):
            for _ in range(1_000_000):
                drive.send(msg)
        with pytest.raises(can.CanOperationError, match="not reading"):
            for _ in range(1_000_000):
                host.send(msg)   # timeout None: bounded by send_wait


def test_the_drives_end_holds_the_newest_frame_of_each_id_while_the_host_stalls() -> None:
    """A host that stopped reading finds, once it reads again, the drive's newest frame
    of each id after the ones that fitted in the buffer (not only the oldest of its stall)."""
    a, b = socket_pair()
    with PipeBus(a, "host") as host, PipeBus(b, "drive", send_wait=0.0, coalesce=True) as drive:
        filler = can.Message(arbitration_id=0x10, is_extended_id=False, data=bytes(8))
        fitted = 0
        while drive.replaced == 0:   # full once a held frame of id 0x10 is superseded
            drive.send(filler)
            fitted += 1
        drive.send(can.Message(arbitration_id=0x20, is_extended_id=False, data=b"old"))
        drive.send(can.Message(arbitration_id=0x20, is_extended_id=False, data=b"new"))
        assert drive.replaced == 2
        got = []
        msg = host.recv(0.0)
        while msg is not None:
            got.append(msg)
            msg = host.recv(0.0)
        drive.recv(0.0)   # the drive's next look at its bus sends what it held
        msg = host.recv(1.0)
        while msg is not None:
            got.append(msg)
            msg = host.recv(0.0)
        assert [bytes(m.data) for m in got[-1:]] == [b"new"]
        assert [m.arbitration_id for m in got[-2:]] == [0x10, 0x20]
        assert len(got) == fitted   # the ones that fitted, and the two held (one of each id)
