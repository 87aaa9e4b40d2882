"""The canopen link alone: canopen's SDO client on the drive's bus with no thread of its own,
against a scripted bus (literal SDO bytes, a simulated clock) and against canopen's own SDO
server (``LocalNode``) on a virtual bus."""

from __future__ import annotations

import threading
import time
import uuid
from collections import deque
from pathlib import Path

import can
import canopen
import pytest

from dobhil.drives.cia402.link import CanopenLink
from dobhil.drives.waits import WAIT_SLICE
from dobhil.errors import WaitCancelled

EDS = Path(__file__).resolve().parents[2] / "drivers" / "cia402-emulated.eds"
NODE = 5


class ScriptedBus:
    """A bus whose node answers from a script; its clock only moves while recv waits."""

    def __init__(self, answers: dict[bytes, list[can.Message]]) -> None:
        self.answers = answers
        self.sent: list[can.Message] = []
        self.inbox: deque[can.Message] = deque()
        self.now = 0.0
        self.waits: list[float] = []
        self.channel_info = "scripted"

    def clock(self) -> float:
        return self.now

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self.sent.append(msg)
        self.inbox.extend(self.answers.get(bytes(msg.data[:4]), []))

    def recv(self, timeout: float | None = None) -> can.Message | None:
        assert timeout is not None and timeout <= WAIT_SLICE + 1e-12   # sliced waits only
        self.waits.append(timeout)
        if self.inbox:
            return self.inbox.popleft()
        self.now += timeout
        return None


def frame(arb: int, data: str) -> can.Message:
    return can.Message(arbitration_id=arb, data=bytes.fromhex(data), is_extended_id=False)


def link_on(bus: object, seen: list[can.Message], clock: object, timeout: float = 0.3) -> CanopenLink:
    return CanopenLink(bus, canopen.import_od(str(EDS), NODE), node_id=NODE,  # type: ignore[arg-type]
                       clock=clock, sdo_timeout=timeout, on_frame=seen.append)  # type: ignore[arg-type]


def test_an_sdo_read_finds_its_answer_queued_and_hands_other_frames_on() -> None:
    heartbeat, tpdo = frame(0x705, "7f"), frame(0x185, "37 12 00 10 00 00 f4 01")
    short_emcy = frame(0x85, "10 23")                   # canopen's EMCY consumer cannot unpack it
    answer = frame(0x585, "43 18 10 01 78 56 34 12")   # expedited upload, 4 bytes: 0x12345678
    bus = ScriptedBus({bytes.fromhex("40 18 10 01"): [heartbeat, short_emcy, tpdo, answer]})
    seen: list[can.Message] = []
    link = link_on(bus, seen, bus.clock)
    threads = threading.active_count()
    with link.session(None):
        vendor = link.node.sdo[0x1018][1].raw
    assert vendor == 0x12345678
    assert bytes(bus.sent[0].data) == bytes.fromhex("40 18 10 01 00 00 00 00")
    assert bus.sent[0].arbitration_id == 0x605
    assert seen == [heartbeat, short_emcy, tpdo]         # the drive's frames, in order
    assert link.node.nmt.state == "PRE-OPERATIONAL"      # and canopen saw them too (notify)
    assert link.adapter.last_object == (0x1018, 1)
    assert threading.active_count() == threads           # nothing ran in another thread


def test_an_sdo_write_is_answered() -> None:
    bus = ScriptedBus({bytes.fromhex("2b 17 10 00"): [frame(0x585, "60 17 10 00 00 00 00 00")]})
    link = link_on(bus, [], bus.clock)
    with link.session(None):
        link.node.sdo[0x1017].raw = 100
    assert bytes(bus.sent[0].data) == bytes.fromhex("2b 17 10 00 64 00 00 00")


def test_a_missing_answer_is_canopens_timeout_on_the_drives_clock() -> None:
    bus = ScriptedBus({})
    link = link_on(bus, [], bus.clock, timeout=5.0)
    start = time.monotonic()
    with link.session(None), pytest.raises(canopen.SdoCommunicationError, match="No SDO response"):
        link.node.sdo[0x6502].read()
    assert time.monotonic() - start < 2.0   # 5 s on the simulated clock, not the wall's
    assert bus.now == pytest.approx(5.0, abs=WAIT_SLICE)
    # canopen sent its own abort (0x05040000: SDO protocol timed out) and did not wait for it
    assert bytes(bus.sent[-1].data) == bytes.fromhex("80 00 00 00 00 00 04 05")
    assert link.adapter.last_object == (0x6502, 0)


def test_an_abort_from_the_node_is_canopens_abort() -> None:
    bus = ScriptedBus({bytes.fromhex("40 02 65 00"): [frame(0x585, "80 02 65 00 00 00 02 06")]})
    link = link_on(bus, [], bus.clock)
    with link.session(None), pytest.raises(canopen.SdoAbortedError) as info:
        link.node.sdo[0x6502].read()
    assert info.value.code == 0x06020000


def test_a_cancel_ends_the_wait_within_a_slice() -> None:
    bus = ScriptedBus({})
    link = link_on(bus, [], bus.clock, timeout=10.0)
    with link.session(lambda: "received SIGINT" if bus.now > 0.1 else ""), \
            pytest.raises(WaitCancelled, match="received SIGINT while waiting for an SDO answer"):
        link.node.sdo[0x6502].read()
    assert bus.now <= 0.1 + 2 * WAIT_SLICE


def test_against_canopens_own_sdo_server() -> None:
    """canopen's LocalNode (its SDO server and PDO objects, on its own notifier) as the
    node; the link reads, writes and maps a PDO over a virtual bus."""
    channel = f"cia402-link-{uuid.uuid4().hex}"
    server = canopen.Network()
    server.NOTIFIER_CYCLE = WAIT_SLICE   # its reader thread stops within a slice at disconnect, not its 1 s default
    server.connect(interface="virtual", channel=channel)
    host = can.Bus(interface="virtual", channel=channel)
    try:
        local = server.create_node(NODE, canopen.import_od(str(EDS), NODE))
        local.sdo[0x1018][1].raw = 0xCAFE
        link = link_on(host, [], time.monotonic, timeout=1.0)
        with link.session(None):
            assert link.node.sdo[0x1018][1].raw == 0xCAFE
            # a segmented upload: one answer awaited per segment request
            assert link.node.sdo[0x1008].raw == local.sdo[0x1008].raw and len(local.sdo[0x1008].raw) > 4
            assert link.node.sdo[0x6502].raw & (1 << 9)
            link.node.sdo[0x1006].raw = 1000
            pdo = link.node.tpdo[2]
            pdo.read()
            pdo.clear()
            pdo.add_variable(0x606C)
            pdo.add_variable(0x6061)
            pdo.trans_type = 1
            pdo.enabled = True
            pdo.save()
        assert local.sdo[0x1006].raw == 1000
        assert local.sdo[0x1A01][1].raw == 0x606C0020 and local.sdo[0x1A01][2].raw == 0x60610008
        assert local.sdo[0x1A01][0].raw == 2 and local.sdo[0x1801][2].raw == 1
    finally:
        host.shutdown()
        server.disconnect()


def test_a_bus_that_cannot_be_read_is_a_bus_error() -> None:
    from dobhil.errors import BusError

    class Broken(ScriptedBus):
        def recv(self, timeout: float | None = None) -> can.Message | None:
            raise ConnectionResetError("hub gone")

    bus = Broken({})
    link = link_on(bus, [], bus.clock)
    with link.session(None), pytest.raises(BusError, match="bus read failed: ConnectionResetError: hub gone"):
        link.node.sdo[0x6502].read()
