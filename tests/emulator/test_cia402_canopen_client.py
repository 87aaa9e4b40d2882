"""canopen's own client against the emulated CiA 402 node running in real time (its thread),
on python-can's virtual bus: SDO uploads, the PDO mapping with canopen's PDO API, NMT,
the controlword by explicit RPDOs and SYNCs, and BaseNode402's own state machine.

Nothing here asserts wall-clock timing: waits poll for a condition with a generous bound."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator

import can
import canopen
import pytest

from dobhil.data import drivers_dir
from dobhil.drives.cia402.codec import PowerState
from dobhil.drives.cia402.emulator import EmulatedCiA402
from dobhil.drives.waits import WAIT_SLICE
from dobhil.emulator.plant import Plant
from dobhil.drives.emulated import private_virtual_channel

from .cia402_rig import NODE, cia402_profile

EDS = str(drivers_dir() / "cia402-emulated.eds")
BOUND = 10.0   # [s] generous: a loaded 2-core machine


class Client:
    def __init__(self) -> None:
        channel = private_virtual_channel()
        self.emu = EmulatedCiA402(can.Bus(interface="virtual", channel=channel),
                                  cia402_profile(feedback_period=0.002), Plant(inertia=0.01))
        self.emu.start()
        self.network = canopen.Network()
        # its reader thread stops within a slice at disconnect, not its 1 s default
        self.network.NOTIFIER_CYCLE = WAIT_SLICE
        self.network.connect(interface="virtual", channel=channel)
        self.node = canopen.BaseNode402(NODE, EDS)
        self.network.add_node(self.node)
        self.node.sdo.RESPONSE_TIMEOUT = 2.0   # the emulator shares this interpreter

    def close(self) -> None:
        try:
            self.network.sync.stop()
            self.network.disconnect()
        finally:
            self.emu.close()

    def until(self, condition: Callable[[], bool], *, sync: bool = True) -> None:
        """Send SYNCs (a SYNC producer's job) until ``condition``; fail after BOUND s."""
        end = time.monotonic() + BOUND
        while not condition():
            assert time.monotonic() < end, "condition not reached"
            if sync:
                self.network.sync.transmit()
            time.sleep(0.005)


@pytest.fixture
def client() -> Iterator[Client]:
    client = Client()
    try:
        yield client
    finally:
        client.close()


def map_wire(node: canopen.BaseNode402, *, rpdo_type: int = 1) -> None:
    """SPEC-17's wire mapping with canopen's PDO API (read, clear, add_variable, save)."""
    node.rpdo.read()
    node.tpdo.read()
    for pdo, indices, trans_type in ((node.rpdo[1], (0x6040, 0x6071), rpdo_type),
                                     (node.tpdo[1], (0x6041, 0x6064, 0x6077), 1),
                                     (node.tpdo[2], (0x606C, 0x6061), 1)):
        pdo.clear()
        for index in indices:
            pdo.add_variable(index)
        pdo.trans_type = trans_type
        pdo.enabled = True
        pdo.save()


def test_canopen_client_reads_identity_maps_pdos_and_enables_cst(client: Client) -> None:
    node = client.node
    assert node.sdo[0x1018][2].raw == 0x0402 and node.sdo[0x1018][3].raw == 0x0001_0000
    assert node.sdo[0x6502].raw >> 9 & 1                        # CST supported
    assert node.sdo["Manufacturer device name"].raw == "dobhil emulated CiA 402 drive"   # segmented
    map_wire(node)
    # what the node now holds, read back by SDO
    assert [node.sdo[0x1A00][s].raw for s in range(4)] == [3, 0x60410010, 0x60640020, 0x60770010]
    assert [node.sdo[0x1A01][s].raw for s in range(3)] == [2, 0x606C0020, 0x60610008]
    node.nmt.state = "OPERATIONAL"
    node.setup_402_state_machine(read_pdos=False)
    node.sdo[0x6060].raw = 10
    for controlword, state in ((0x06, "READY TO SWITCH ON"), (0x07, "SWITCHED ON"),
                               (0x0F, "OPERATION ENABLED")):
        node.rpdo[1][0x6040].raw = controlword
        node.rpdo[1].transmit()                  # latched by the node until the next SYNC
        client.until(lambda state=state: node.state == state)   # type: ignore[misc]
    assert client.emu.state is PowerState.OPERATION_ENABLED
    client.until(lambda: node.tpdo[2][0x6061].raw == 10)
    node.rpdo[1][0x6071].raw = 300
    node.rpdo[1].transmit()
    client.until(lambda: node.tpdo[1][0x6077].raw == 300)      # torque actual, per mille
    assert client.emu.applied_torque == pytest.approx(0.3)
    client.until(lambda: node.tpdo[2][0x606C].raw > 0)          # it turns
    node.sdo[0x6040].raw = 0x00                                # disable voltage by SDO
    assert client.emu.applied_torque == 0.0


def test_base_node_402_state_machine_drives_it_to_operation_enabled(client: Client) -> None:
    node = client.node
    map_wire(node, rpdo_type=255)        # asynchronous RPDO: BaseNode402 transmits it itself
    node.nmt.state = "OPERATIONAL"
    node.setup_402_state_machine(read_pdos=False)
    client.network.sync.start(0.01)      # canopen's SYNC producer: TPDOs every 10 ms
    node.op_mode = "CYCLIC SYNCHRONOUS TORQUE"
    for _ in range(3):   # BaseNode402 gives each transition 0.4 s of wall time: a loaded machine may need more
        try:
            node.state = "OPERATION ENABLED"
            break
        except RuntimeError:
            continue
    assert node.state == "OPERATION ENABLED" and node.op_mode == "CYCLIC SYNCHRONOUS TORQUE"
    assert client.emu.state is PowerState.OPERATION_ENABLED
    node.state = "SWITCH ON DISABLED"
    assert client.emu.state is PowerState.SWITCH_ON_DISABLED
