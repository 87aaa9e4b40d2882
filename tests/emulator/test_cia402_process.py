"""The emulated CiA 402 node in its own process (EmulatorProcess, as ``dobhil run --emulate``
and ``can.Bus(interface="dobhil")`` run it): SDO, NMT, a SYNC sent by the test answered with
the TPDOs, and the protocol state published through shared memory.

Waits poll with a generous bound; nothing asserts wall-clock timing."""

from __future__ import annotations

import os
import signal
import struct
import threading
import time

import can
import canopen
import pytest

from dobhil.cli.main import main
from dobhil.config import load_config
from dobhil.data import drivers_dir
from dobhil.drives.cia402.codec import PowerState
from dobhil.drives.waits import WAIT_SLICE
from dobhil.emulator.process import EmulatorProcess, EmulatorSpec
from dobhil.drives.emulated import private_virtual_channel

from .cia402_rig import HEARTBEAT, NODE, RPDO1, SDO_RX, SDO_TX, SYNC, TPDO1, TPDO2, cia402_profile, download, upload

BOUND = 20.0


def _frames(bus: can.BusABC, until: set[int]) -> dict[int, bytes]:
    """Frames read until one of each id in ``until`` came (the last of each id kept)."""
    out: dict[int, bytes] = {}
    end = time.monotonic() + BOUND
    while not until <= set(out):
        assert time.monotonic() < end, f"waited for {sorted(until - set(out))}, got {sorted(out)}"
        msg = bus.recv(0.1)
        if msg is not None:
            out[msg.arbitration_id] = bytes(msg.data)
    return out


def _send(bus: can.BusABC, can_id: int, data: bytes | list[int] = b"") -> None:
    bus.send(can.Message(arbitration_id=can_id, data=bytes(data), is_extended_id=False))


def test_emulator_process_answers_sdo_nmt_and_sync() -> None:
    spec = EmulatorSpec.of(load_config("demo"), cia402_profile(feedback_period=0.002))
    with EmulatorProcess(spec) as process:
        bus = process.bus
        _send(bus, SDO_RX, upload(0x6502))
        assert _frames(bus, {HEARTBEAT, SDO_TX})[SDO_TX] == bytes.fromhex("4302650080030000")
        _send(bus, SYNC)                   # pre-operational: no PDO
        _send(bus, SDO_RX, download(0x6060, 0, 10, 1))
        assert download(0x6060, 0, 10, 1) == bytes.fromhex("2f6060000a000000")   # mode 10 = CST
        assert _frames(bus, {SDO_TX})[SDO_TX] == bytes.fromhex("6060600000000000")
        _send(bus, 0x000, [0x01, NODE])    # NMT start; the EDS's default mapping is the wire mapping
        for controlword in (0x06, 0x07, 0x0F):
            _send(bus, RPDO1, struct.pack("<Hh", controlword, 200))
            _send(bus, SYNC)
            frames = _frames(bus, {TPDO1, TPDO2})
        assert struct.unpack_from("<H", frames[TPDO1])[0] == 0x1237       # operation enabled, CST
        assert frames[TPDO2][4] == 10
        end = time.monotonic() + BOUND
        while process.protocol_state != PowerState.OPERATION_ENABLED or process.applied_torque != 0.2:
            assert time.monotonic() < end, (process.protocol_state, process.applied_torque)
            time.sleep(0.01)
        assert process.protocol_error == 0 and process.frame_errors == 0 and not process.watchdog_tripped


def test_can_bus_interface_dobhil_with_a_cia402_config() -> None:
    # python-can's own entry: the demo's plant on the emulated CiA 402 node (its profile
    # from the shipped drivers/cia402-emulated.yaml), SYNCs sent by this test
    with can.Bus(interface="dobhil", channel="demo", overrides="drive.profile=cia402-emulated") as bus:
        assert "cia402" in bus.channel_info
        _send(bus, SDO_RX, upload(0x1018, 2))
        assert _frames(bus, {SDO_TX})[SDO_TX] == bytes.fromhex("4318100202040000")   # product 0x402
        _send(bus, 0x000, [0x01, NODE])
        _send(bus, SYNC)
        frames = _frames(bus, {TPDO1, TPDO2})
        assert struct.unpack_from("<H", frames[TPDO1])[0] == 0x0250   # switch on disabled
        assert len(frames[TPDO1]) == 8 and len(frames[TPDO2]) == 5


def test_sync_sent_periodically_by_the_emulator_process_is_answered_each_time() -> None:
    # the host's PipeBus.send_periodic: the child sends the SYNC at its own tick starts (as
    # SocketCAN's broadcast manager would), echoes it to the host, then its node answers it
    spec = EmulatorSpec.of(load_config("demo"), cia402_profile(feedback_period=0.002))
    with EmulatorProcess(spec) as process:
        bus = process.bus
        _send(bus, 0x000, [0x01, NODE])
        _frames(bus, {HEARTBEAT})                                  # booted
        task = bus.send_periodic(can.Message(arbitration_id=SYNC, data=b"", is_extended_id=False), 0.002)
        try:
            order: list[int] = []
            end = time.monotonic() + BOUND
            while order.count(TPDO2) < 20:
                assert time.monotonic() < end, order
                msg = bus.recv(0.1)
                if msg is not None:
                    order.append(msg.arbitration_id)
        finally:
            task.stop()
        first = order.index(SYNC)
        cycles = order[first:first + 3 * 19]
        assert cycles == [SYNC, TPDO1, TPDO2] * 19             # every SYNC, then its two TPDOs


def test_canopens_client_drives_the_node_behind_a_dobhil_bus() -> None:
    # canopen connects to the bus by name, as to any python-can interface; its SYNC producer
    # (python-can send_periodic) is sent by the emulator's process itself
    network = canopen.Network()
    network.NOTIFIER_CYCLE = WAIT_SLICE   # its reader thread stops within a slice at disconnect, not its 1 s default
    network.connect(interface="dobhil", channel="cia402-demo")
    try:
        node = canopen.BaseNode402(NODE, str(drivers_dir() / "cia402-emulated.eds"))
        network.add_node(node)
        node.sdo.RESPONSE_TIMEOUT = 5.0
        assert node.sdo[0x1018][2].raw == 0x402 and node.sdo[0x6502].raw >> 9 & 1
        node.tpdo.read()
        node.rpdo.read()
        node.rpdo[1].trans_type = 255      # BaseNode402 sends the controlword itself
        node.rpdo[1].save()
        node.nmt.state = "OPERATIONAL"
        node.setup_402_state_machine(read_pdos=False)
        network.sync.start(0.01)
        node.op_mode = "CYCLIC SYNCHRONOUS TORQUE"
        for _ in range(5):   # each transition has 0.4 s of wall time: a loaded machine may need more
            try:
                node.state = "OPERATION ENABLED"
                break
            except RuntimeError:
                continue
        assert node.state == "OPERATION ENABLED"
        node.rpdo[1][0x6071].raw = 100
        node.rpdo[1].transmit()
        end = time.monotonic() + BOUND
        while node.tpdo[1][0x6077].raw != 100 or network.bus.emulator.applied_torque != 0.1:
            assert time.monotonic() < end
            time.sleep(0.01)
        assert network.bus.emulator.protocol_state == PowerState.OPERATION_ENABLED
    finally:
        network.sync.stop()
        network.disconnect()


def test_dobhil_emulate_serves_a_cia402_config(capsys: pytest.CaptureFixture[str]) -> None:
    # `dobhil emulate` on a virtual channel of this process, the test's client on another
    # thread: boot-up, SDO, NMT start and a SYNC answered with the TPDOs; then Ctrl-C's
    # way, SIGINT, ends it (--duration: a bound past the client's own, not reached)
    channel = private_virtual_channel()
    got: dict[int, bytes] = {}
    client_bus = can.Bus(interface="virtual", channel=channel)

    def client() -> None:
        try:
            got.update(_frames(client_bus, {HEARTBEAT}))
            _send(client_bus, SDO_RX, upload(0x6502))
            _send(client_bus, 0x000, [0x01, NODE])
            _send(client_bus, SYNC)
            got.update(_frames(client_bus, {SDO_TX, TPDO1, TPDO2}))
        finally:
            client_bus.shutdown()
            if HEARTBEAT in got:   # the node booted: emulate runs, its handler takes the signal
                os.kill(os.getpid(), signal.SIGINT)

    thread = threading.Thread(target=client)
    thread.start()
    code = main(["emulate", "demo", "--set", "drive.profile=cia402-emulated", "--bus", f"virtual:{channel}",
                 "--duration", f"{3 * BOUND:g}"])
    thread.join()
    assert code == 0 and "emulating cia402 node 5" in capsys.readouterr().out
    assert got[HEARTBEAT] == b"\x00" and got[SDO_TX] == bytes.fromhex("4302650080030000")
    assert len(got[TPDO1]) == 8 and len(got[TPDO2]) == 5
