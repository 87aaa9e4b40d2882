"""The CiA 402 test node (``cia402_node``) on its own: before dobhil's drive is tested
against it, it must answer as the standard says -- checked with canopen's own SDO
client and PDO configuration (the master side) and against literal frames of CiA 301."""

from __future__ import annotations

import itertools
import math
from collections.abc import Iterator
from dataclasses import dataclass

import can
import canopen
import pytest

from .cia402_node import EDS, NodeState, PumpedNetwork, TestNode402, next_state

NODE = 5
_CHANNELS = itertools.count()


@dataclass
class Pair:
    node: TestNode402
    host: PumpedNetwork
    remote: canopen.RemoteNode
    sniff: can.BusABC

    def frames(self) -> list[can.Message]:
        out = []
        while (msg := self.sniff.recv(0.0)) is not None:
            out.append(msg)
        return out

    def raw(self, can_id: int, data: bytes) -> None:
        self.host.send_message(can_id, data)


@pytest.fixture
def pair() -> Iterator[Pair]:
    channel = f"cia402-node-{next(_CHANNELS)}"
    node = TestNode402(can.Bus(interface="virtual", channel=channel), NODE, inertia=0.01)
    host = PumpedNetwork(can.Bus(interface="virtual", channel=channel), node)
    remote = canopen.RemoteNode(NODE, str(EDS))
    host.add_node(remote)
    sniff = can.Bus(interface="virtual", channel=channel)
    node.boot()
    try:
        yield Pair(node, host, remote, sniff)
    finally:
        sniff.shutdown()
        host.disconnect()
        node.close()


def _map_pdos(remote: canopen.RemoteNode) -> None:
    """SPEC-17's wire mapping, written with canopen's own PDO configuration (master side)."""
    remote.rpdo.read()
    remote.tpdo.read()
    rpdo = remote.rpdo[1]
    rpdo.clear()
    rpdo.add_variable(0x6040)
    rpdo.add_variable(0x6071)
    rpdo.trans_type, rpdo.enabled = 1, True
    tpdo1, tpdo2 = remote.tpdo[1], remote.tpdo[2]
    tpdo1.clear()
    for index in (0x6041, 0x6064, 0x6077):
        tpdo1.add_variable(index)
    tpdo2.clear()
    for index in (0x606C, 0x6061):
        tpdo2.add_variable(index)
    for pdo in (tpdo1, tpdo2):
        pdo.trans_type, pdo.enabled = 1, True
    remote.rpdo.save()
    remote.tpdo.save()


def test_sdo_upload_of_identity_literal_bytes(pair: Pair) -> None:
    pair.frames()
    # CiA 301 expedited upload request of 1018:01, and the 4-byte expedited answer
    pair.raw(0x605, bytes.fromhex("4018100200000000"))
    answer = [m for m in pair.frames() if m.arbitration_id == 0x585]
    assert [bytes(m.data) for m in answer] == [bytes.fromhex("4318100202040000")]
    assert pair.remote.sdo[0x1018][3].raw == 0x00010000
    assert pair.remote.sdo[0x1000].raw == 0x00020192


def test_sdo_abort_for_a_missing_object(pair: Pair) -> None:
    with pytest.raises(canopen.SdoAbortedError) as info:
        _ = pair.remote.sdo.upload(0x6099, 0)
    assert info.value.code == 0x06020000   # object does not exist in the dictionary


def test_boot_up_nmt_start_and_heartbeat(pair: Pair) -> None:
    assert [bytes(m.data) for m in pair.frames() if m.arbitration_id == 0x705] == [b"\x00"]
    pair.raw(0x000, bytes([0x81, NODE]))                 # NMT reset node
    assert [bytes(m.data) for m in pair.frames() if m.arbitration_id == 0x705] == [b"\x00"]
    assert pair.node.nmt_state == "PRE-OPERATIONAL"
    pair.remote.sdo[0x1017].raw = 100                    # producer heartbeat 100 ms
    pair.raw(0x000, bytes([0x01, NODE]))                 # NMT start
    assert pair.node.nmt_state == "OPERATIONAL"
    pair.frames()
    pair.node.run_due(0.35)                              # simulated time: 3 heartbeats
    beats = [bytes(m.data) for m in pair.frames() if m.arbitration_id == 0x705]
    assert beats == [b"\x05"] * 3


def test_nmt_to_another_node_is_ignored(pair: Pair) -> None:
    pair.raw(0x000, bytes([0x01, NODE + 1]))
    assert pair.node.nmt_state == "PRE-OPERATIONAL"


@pytest.mark.parametrize(
    ("steps", "statuswords"),
    [
        # shutdown, switch on, enable operation (CST set first: bit 12 follows 6071)
        ([0x06, 0x07, 0x0F], [0x0231, 0x0233, 0x1237]),
        # enable operation from Ready to switch on: transition 3, then 4
        ([0x06, 0x0F, 0x0F], [0x0231, 0x0233, 0x1237]),
        # quick stop from Operation enabled, then disable voltage
        ([0x06, 0x07, 0x0F, 0x02, 0x00], [0x0231, 0x0233, 0x1237, 0x0217, 0x0240]),
        # disable operation (5) and shutdown (8)
        ([0x06, 0x07, 0x0F, 0x07, 0x06], [0x0231, 0x0233, 0x1237, 0x0233, 0x0231]),
        # switch on from Switch on disabled is refused
        ([0x07, 0x0F], [0x0240, 0x0240]),
    ],
)
def test_statusword_after_controlword_steps_by_sdo(pair: Pair, steps: list[int],
                                                   statuswords: list[int]) -> None:
    pair.remote.sdo[0x6060].raw = 10
    seen = []
    for cw in steps:
        pair.remote.sdo[0x6040].raw = cw
        seen.append(pair.remote.sdo[0x6041].raw)
    assert [hex(s) for s in seen] == [hex(s) for s in statuswords]
    assert pair.remote.sdo[0x6061].raw == 10


def test_statusword_masks_agree_with_canopen_state_table() -> None:
    """Each state's statusword decodes to the same state in canopen's own table."""
    from canopen.profiles.p402 import State402

    names = {NodeState.SWITCH_ON_DISABLED: "SWITCH ON DISABLED",
             NodeState.READY_TO_SWITCH_ON: "READY TO SWITCH ON",
             NodeState.SWITCHED_ON: "SWITCHED ON", NodeState.OPERATION_ENABLED: "OPERATION ENABLED",
             NodeState.QUICK_STOP_ACTIVE: "QUICK STOP ACTIVE", NodeState.FAULT: "FAULT",
             NodeState.FAULT_REACTION_ACTIVE: "FAULT REACTION ACTIVE",
             NodeState.NOT_READY: "NOT READY TO SWITCH ON"}
    node_bus = can.Bus(interface="virtual", channel=f"cia402-node-{next(_CHANNELS)}")
    node = TestNode402(node_bus, NODE)
    try:
        for state, name in names.items():
            node.state = state
            matches = [n for n, (mask, value) in State402.SW_MASK.items()
                       if node.statusword & mask == value]
            assert matches == [name], (state, hex(node.statusword))
    finally:
        node.close()


def test_transition_table_agrees_with_canopen_for_its_commands() -> None:
    """canopen's TRANSITIONTABLE (the master side's reading): every (from, to) it lists
    with its controlword lands in ``to`` here."""
    from canopen.profiles.p402 import State402

    by_name = {"SWITCH ON DISABLED": NodeState.SWITCH_ON_DISABLED,
               "READY TO SWITCH ON": NodeState.READY_TO_SWITCH_ON,
               "SWITCHED ON": NodeState.SWITCHED_ON,
               "OPERATION ENABLED": NodeState.OPERATION_ENABLED,
               "QUICK STOP ACTIVE": NodeState.QUICK_STOP_ACTIVE, "FAULT": NodeState.FAULT}
    checked = 0
    for (src, dst), cw in State402.TRANSITIONTABLE.items():
        if src in by_name and dst in by_name:
            assert next_state(by_name[src], cw, 0) is by_name[dst], (src, dst, hex(cw))
            checked += 1
    assert checked == 13


def test_pdos_on_sync_and_rpdo_applied_at_the_next_sync(pair: Pair) -> None:
    _map_pdos(pair.remote)
    pair.remote.sdo[0x1006].raw = 1000                  # 1 ms cycle
    pair.remote.sdo[0x6060].raw = 10
    pair.remote.nmt.state = "OPERATIONAL"
    assert pair.node.nmt_state == "OPERATIONAL"
    rpdo, tpdo1, tpdo2 = pair.remote.rpdo[1], pair.remote.tpdo[1], pair.remote.tpdo[2]
    states = []
    for cw in (0x06, 0x07, 0x0F):
        rpdo["Controlword"].raw = cw
        rpdo.transmit()
        states.append(pair.node.state)                  # not yet: waits for SYNC
        pair.host.sync.transmit()
    assert states == [NodeState.SWITCH_ON_DISABLED, NodeState.READY_TO_SWITCH_ON,
                      NodeState.SWITCHED_ON]
    assert tpdo1["Statusword"].raw == 0x1237 and tpdo2["Modes of operation display"].raw == 10
    frames = [m for m in pair.frames() if m.arbitration_id in (0x185, 0x285)]
    assert [len(m.data) for m in frames[-2:]] == [8, 5]
    # CST: 500 per mille of 1000 mNm on J = 0.01: 50 rad/s^2 from the SYNC after it
    rpdo["Target torque"].raw = 500
    rpdo.transmit()
    pair.host.sync.transmit()
    assert pair.node.torque == 0.5
    v0 = pair.node.plant.velocity
    for _ in range(10):
        pair.host.sync.transmit()
    assert math.isclose(pair.node.plant.velocity - v0, 0.5 / 0.01 * 0.010, rel_tol=1e-12)
    assert tpdo1["Torque actual value"].raw == 500
    assert tpdo2["Velocity actual value"].raw == round(pair.node.plant.velocity * 60 / (2 * math.pi))


def test_no_pdo_outside_operational(pair: Pair) -> None:
    _map_pdos(pair.remote)
    pair.frames()
    pair.host.sync.transmit()
    assert not [m for m in pair.frames() if m.arbitration_id in (0x185, 0x285)]
    assert pair.node.syncs == 0


def test_fault_sends_emcy_and_needs_a_rising_fault_reset(pair: Pair) -> None:
    pair.remote.sdo[0x6060].raw = 10
    for cw in (0x06, 0x07, 0x0F):
        pair.remote.sdo[0x6040].raw = cw
    pair.frames()
    pair.node.fault(0x2310, register=0x03)
    emcy = [m for m in pair.frames() if m.arbitration_id == 0x85]
    assert [bytes(m.data) for m in emcy] == [bytes.fromhex("1023030000000000")]
    assert pair.remote.sdo[0x6041].raw & 0x4F == 0x08 and pair.remote.sdo[0x603F].raw == 0x2310
    assert pair.node.torque == 0.0
    pair.remote.sdo[0x6040].raw = 0x0F                   # no reset without bit 7's edge
    assert pair.node.state is NodeState.FAULT
    pair.remote.sdo[0x6040].raw = 0x80
    assert pair.node.state is NodeState.SWITCH_ON_DISABLED and pair.remote.sdo[0x603F].raw == 0


def test_real_time_with_canopens_notifier() -> None:
    """The node on canopen's own notifier thread, the host a plain canopen network."""
    channel = f"cia402-node-{next(_CHANNELS)}"
    node = TestNode402(can.Bus(interface="virtual", channel=channel), NODE)
    host = canopen.Network(can.Bus(interface="virtual", channel=channel))
    remote = canopen.RemoteNode(NODE, str(EDS))
    host.add_node(remote)
    host.connect()
    try:
        node.start()
        assert remote.sdo[0x1018][2].raw == 0x402
        remote.sdo[0x1017].raw = 20
        remote.nmt.wait_for_heartbeat(timeout=2.0)
        assert remote.nmt.state == "PRE-OPERATIONAL"
    finally:
        host.disconnect()
        node.close()
