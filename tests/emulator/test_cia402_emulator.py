"""The emulated CiA 402 node in lockstep, frame by frame: literal bytes of CiA 301 / CiA 402
(their COB-IDs, objects and state bits), the TPDOs also decoded by canopen's own PDO map."""

from __future__ import annotations

import struct
from collections.abc import Iterator
from pathlib import Path

import can
import canopen
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from dobhil.data import drivers_dir
from dobhil.drives.cia402.codec import Controlword, EmcyCode, PowerState
from dobhil.drives.cia402.emulator import TRANSITIONS, decode_command, statusword
from dobhil.emulator.plant import Plant
from dobhil.drives.registry import make_emulated_drive
from dobhil.errors import ConfigError

from .cia402_rig import (EMCY, HEARTBEAT, NODE, OPTIONS, RPDO1, SDO_TX, SYNC, TPDO1, TPDO2, Lockstep,
                         cia402_profile, configure_wire_mapping, download, enable_cst, upload)

# statuswords with CiA 402's state bits, plus voltage enabled (0x10) and
# remote (0x200); operation enabled in CST also bit 12 (the target torque is followed)
SW_SWITCH_ON_DISABLED = 0x0250
SW_READY = 0x0231
SW_SWITCHED_ON = 0x0233
SW_ENABLED_CST = 0x1237
SW_FAULT = 0x0218


@pytest.fixture
def rig() -> Iterator[Lockstep]:
    rig = Lockstep()
    try:
        yield rig
    finally:
        rig.close()


def tpdo1(frames: dict[int, bytes]) -> tuple[int, int, int]:
    """(statusword, position, torque actual) of TPDO1."""
    return struct.unpack("<HiH", frames[TPDO1])[0], *struct.unpack("<ih", frames[TPDO1][2:])


# -- pure tables ---------------------------------------------------------------------

@pytest.mark.parametrize("controlword, command", [
    (0x06, Controlword.SHUTDOWN), (0x0E, Controlword.SHUTDOWN), (0x07, Controlword.SWITCH_ON),
    (0x0F, Controlword.ENABLE_OPERATION), (0x00, Controlword.DISABLE_VOLTAGE), (0x0D, Controlword.DISABLE_VOLTAGE),
    (0x02, Controlword.QUICK_STOP), (0x0B, Controlword.QUICK_STOP), (0x8F, Controlword.ENABLE_OPERATION)])
def test_controlword_commands_follow_the_cia402_table(controlword: int, command: Controlword) -> None:
    assert decode_command(controlword) is command


def test_statusword_masks_of_drive_protocols_md() -> None:
    masks = {PowerState.NOT_READY_TO_SWITCH_ON: (0x4F, 0x00), PowerState.SWITCH_ON_DISABLED: (0x4F, 0x40),
             PowerState.READY_TO_SWITCH_ON: (0x6F, 0x21), PowerState.SWITCHED_ON: (0x6F, 0x23),
             PowerState.OPERATION_ENABLED: (0x6F, 0x27), PowerState.QUICK_STOP_ACTIVE: (0x6F, 0x07),
             PowerState.FAULT_REACTION_ACTIVE: (0x4F, 0x0F), PowerState.FAULT: (0x4F, 0x08)}
    states = list(masks)     # PowerState.UNKNOWN is the host's, never the node's
    for state, (mask, value) in masks.items():
        assert [other for other in states if statusword(other) & mask == value] == [state]
    # and canopen's own table reads each state back by name
    from canopen.profiles.p402 import State402
    for state in states:
        names = [name for name, (mask, value) in State402.SW_MASK.items() if statusword(state) & mask == value]
        assert names == [state.name.replace("_", " ")]


def test_every_transition_leaves_the_fault_states_alone() -> None:
    assert not {state for state, _ in TRANSITIONS} & {PowerState.FAULT, PowerState.FAULT_REACTION_ACTIVE}


# -- start-up, SDO, NMT, heartbeat --------------------------------------------------------

def test_boots_with_a_boot_up_frame_and_answers_sdo_in_pre_operational(rig: Lockstep) -> None:
    assert rig.read() == []
    assert rig.run(0.001) == [(HEARTBEAT, b"\x00")]    # boot-up at the first tick
    assert rig.emu.nmt_state == "PRE-OPERATIONAL"
    # identity 0x1018 and supported modes 0x6502 (CST bit 9), literal responses
    assert rig.sdo(upload(0x1018, 2)) == bytes.fromhex("4318100202040000")
    assert rig.sdo(upload(0x1018, 3)) == bytes.fromhex("4318100300000100")
    assert rig.sdo(upload(0x6502)) == bytes.fromhex("4302650080030000")
    assert rig.sdo(upload(0x6076)) == bytes.fromhex("43766000e8030000")   # 1000 mNm
    # its own units (the rig's profile: 4096 increments per revolution, gear 1:1), not the EDS's 2^20
    assert rig.sdo(upload(0x608F, 1)) == bytes.fromhex("438f600100100000")
    assert rig.sdo(upload(0x608F, 2)) == bytes.fromhex("438f600201000000")
    assert rig.sdo(upload(0x6091, 1)) == bytes.fromhex("4391600101000000")
    assert rig.sdo(upload(0x6041)) == bytes.fromhex("4b41600050020000")   # switch on disabled
    # segmented upload of 0x1008 (29 bytes: "dobhil emulated CiA 402 drive")
    assert rig.sdo(upload(0x1008)) == bytes.fromhex("410810001d000000")
    text, toggle = b"", 0x00
    while True:
        segment = rig.sdo(bytes([0x60 | toggle]) + bytes(7))
        assert segment[0] & 0xE0 == 0x00 and segment[0] & 0x10 == toggle
        text += segment[1:8 - (segment[0] >> 1 & 7)]
        toggle ^= 0x10
        if segment[0] & 0x01:
            break
    assert text == b"dobhil emulated CiA 402 drive"


@pytest.mark.parametrize("request_, abort", [
    (download(0x6041, 0, 0x0F, 2), 0x06010002),       # statusword is read-only
    (download(0x2000, 0, 1, 1), 0x06020000),          # no such object
    (download(0x6060, 0, 1, 1), 0x06090030),          # profile position: not in 0x6502
    (download(0x1600, 1, 0x60760020, 4), 0x06040041),  # rated torque is not PDO-mappable
    (download(0x1600, 1, 0x60400020, 4), 0x06040041),  # controlword mapped with the wrong size
    (download(0x6076, 0, 0, 4), 0x06090032),          # a rated torque of 0
    (download(0x608F, 1, 1 << 20, 4), 0x06010002),    # its encoder is its profile's: read only
])
def test_sdo_writes_the_drive_refuses_are_aborted_with_cia301_codes(
        rig: Lockstep, request_: bytes, abort: int) -> None:
    response = rig.sdo(request_)
    assert response[:4] == bytes([0x80]) + request_[1:4]
    assert struct.unpack("<I", response[4:])[0] == abort


def test_a_mapping_longer_than_a_frame_is_refused(rig: Lockstep) -> None:
    rig.write(0x1A00, 0, 0, 1)
    for sub, entry in enumerate([0x60640020, 0x606C0020, 0x60410010], 1):
        rig.write(0x1A00, sub, entry, 4)
    response = rig.sdo(download(0x1A00, 0, 3, 1))   # 80 bits
    assert response[0] == 0x80 and struct.unpack("<I", response[4:])[0] == 0x06040042
    rig.write(0x1A00, 0, 2, 1)   # 64 bits fit


def test_heartbeat_runs_on_emulated_time_with_the_period_written_by_sdo(rig: Lockstep) -> None:
    rig.run(0.5)
    assert [f for f in rig.seen if f[1] == HEARTBEAT] == [(0.001, HEARTBEAT, b"\x00")]   # 0x1017 = 0: none
    rig.write(0x1017, 0, 100, 2)
    start = rig.emu.time
    rig.run(0.35)
    rig.send(0x000, [0x01, NODE])          # NMT start: the state byte follows
    rig.run(0.2)
    beats = [(round(t - start, 9), data) for t, can_id, data in rig.seen if can_id == HEARTBEAT][1:]
    assert beats == [(0.1, b"\x7f"), (0.2, b"\x7f"), (0.3, b"\x7f"), (0.4, b"\x05"), (0.5, b"\x05")]


def test_nmt_reset_node_boots_again_with_the_eds_values(rig: Lockstep) -> None:
    rig.write(0x1017, 0, 50, 2)
    rig.write(0x6060, 0, 10, 1)
    rig.send(0x000, [0x01, NODE])
    rig.read()
    assert rig.emu.nmt_state == "OPERATIONAL"
    rig.send(0x000, [0x81, 0])             # reset node, broadcast
    assert rig.read() == [(HEARTBEAT, b"\x00")]
    assert rig.emu.nmt_state == "PRE-OPERATIONAL"
    assert rig.value(0x1017, fmt="<H") == 0 and rig.value(0x6060, fmt="<b") == 0
    assert not [can_id for can_id, _ in rig.run(0.2) if can_id == HEARTBEAT]   # 0x1017 = 0 again


# -- PDOs, SYNC, the state machine ------------------------------------------------------------

def test_no_pdo_outside_operational(rig: Lockstep) -> None:
    configure_wire_mapping(rig)
    rig.rpdo(0x06)
    assert rig.sync() == {}
    assert rig.emu.state is PowerState.SWITCH_ON_DISABLED   # the RPDO was not taken either
    rig.send(0x000, [0x01, NODE])
    assert set(rig.sync()) == {TPDO1, TPDO2}


def test_controlword_by_rpdo_reaches_operation_enabled_in_cst_at_the_syncs(rig: Lockstep) -> None:
    configure_wire_mapping(rig)
    rig.send(0x000, [0x01, NODE])
    rig.write(0x6060, 0, 10, 1)
    assert tpdo1(rig.sync())[0] == SW_SWITCH_ON_DISABLED
    seen = []
    for controlword in (0x06, 0x07, 0x0F):
        rig.rpdo(controlword)
        assert rig.read(0.01) == []       # no SYNC: nothing applied, nothing sent
        seen.append(tpdo1(rig.sync())[0])
    assert seen == [SW_READY, SW_SWITCHED_ON, SW_ENABLED_CST]
    assert rig.emu.protocol_state == PowerState.OPERATION_ENABLED   # the drive's code, published as an int


class HeldPlant:
    """A plant that holds its reading whatever the torque (for the units of the TPDOs)."""

    def __init__(self, position: float, velocity: float) -> None:
        self.position, self.velocity = position, velocity

    def step(self, torque_nm: float, dt: float) -> None:
        pass


def test_tpdos_decoded_by_canopens_own_pdo_map() -> None:
    rig = Lockstep(HeldPlant(1.5, -2.0))
    try:
        _tpdos_decoded_by_canopen(rig)
    finally:
        rig.close()


def _tpdos_decoded_by_canopen(rig: Lockstep) -> None:
    enable_cst(rig)
    rig.rpdo(0x0F, 250)
    frames = rig.sync()
    # canopen's client-side view: a RemoteNode with the same EDS and mapping, fed the frames
    network = canopen.Network()
    node = network.add_node(NODE, str(drivers_dir() / "cia402-emulated.eds"))
    for number, cob, names in ((1, TPDO1, (0x6041, 0x6064, 0x6077)), (2, TPDO2, (0x606C, 0x6061))):
        pdo = node.tpdo[number]
        pdo.clear()
        for index in names:
            pdo.add_variable(index)
        pdo.cob_id, pdo.enabled, pdo.trans_type = cob, True, 1
        pdo.subscribe()
    for cob in (TPDO1, TPDO2):
        network.notify(cob, bytearray(frames[cob]), 0.0)
    assert node.tpdo[1][0x6041].raw == SW_ENABLED_CST
    assert node.tpdo[1][0x6064].raw == round(1.5 / (2 * 3.141592653589793) * 4096)   # 978
    assert node.tpdo[1][0x6077].raw == 250       # per mille of 1 Nm
    assert node.tpdo[2][0x606C].raw == round(-2.0 * 60 / (2 * 3.141592653589793))   # -19 rpm
    assert node.tpdo[2][0x6061].raw == 10
    assert frames[TPDO1] == bytes.fromhex("3712" "d2030000" "fa00")
    assert frames[TPDO2] == bytes.fromhex("edffffff" "0a")


def test_torque_reaches_the_plant_at_the_next_sync_and_accelerates_it_by_tau_over_j(rig: Lockstep) -> None:
    enable_cst(rig)
    rig.rpdo(0x0F, 500)                     # 0.5 Nm
    rig.run(0.01)
    assert rig.emu.applied_torque == 0.0    # latched, not applied: no SYNC yet
    rig.sync()
    assert rig.emu.applied_torque == 0.5
    v0, t0 = rig.plant.velocity, rig.emu.time
    rig.run(0.1)
    acceleration = (rig.plant.velocity - v0) / (rig.emu.time - t0)
    assert acceleration == pytest.approx(0.5 / 0.01, rel=1e-9)
    assert tpdo1(rig.sync())[2] == 500      # torque actual, per mille


def test_target_torque_is_clamped_to_max_torque_and_the_profile_limit(rig: Lockstep) -> None:
    enable_cst(rig)
    rig.write(0x6072, 0, 1500, 2)
    rig.rpdo(0x0F, -1800)
    sw, _, torque = tpdo1(rig.sync())
    assert rig.emu.applied_torque == -1.5 and torque == -1500 and sw & 0x0800   # internal limit
    rig.write(0x6072, 0, 3000, 2)
    rig.rpdo(0x0F, 2000)                     # the profile's 2 Nm: at the limit, no fault
    for _ in range(5):
        sw, _, torque = tpdo1(rig.sync())
    assert rig.emu.applied_torque == 2.0 and not sw & 0x0800 and rig.emu.state is PowerState.OPERATION_ENABLED


def test_over_torque_faults_with_an_emcy_and_a_fault_reset_clears_it(rig: Lockstep) -> None:
    enable_cst(rig)
    rig.rpdo(0x0F, 3100)                     # above 0x6072 = 3000
    for _ in range(2):
        assert EMCY not in rig.sync()
    frames = rig.sync()                      # the third SYNC in a row
    assert frames[EMCY] == bytes.fromhex("1183" "21" "0000000000")   # 0x8311, register 0x21
    assert tpdo1(frames)[0] == SW_FAULT and tpdo1(frames)[2] == 0
    assert rig.emu.applied_torque == 0.0 and rig.emu.protocol_error == EmcyCode.EXCESS_TORQUE
    assert rig.value(0x603F, fmt="<H") == 0x8311 and rig.value(0x1001, fmt="<B") == 0x21
    rig.rpdo(0x0F, 0)
    assert tpdo1(rig.sync())[0] == SW_FAULT  # no way out but a fault reset
    rig.rpdo(0x80)
    frames = rig.sync()
    assert frames[EMCY] == bytes(8) and tpdo1(frames)[0] == SW_SWITCH_ON_DISABLED
    assert rig.emu.protocol_error == 0 and rig.value(0x603F, fmt="<H") == 0


def test_disable_voltage_takes_the_torque_away_at_once(rig: Lockstep) -> None:
    enable_cst(rig)
    rig.rpdo(0x0F, 400)
    rig.sync()
    assert rig.emu.applied_torque == 0.4
    rig.rpdo(0x00, 400)                      # by RPDO: from the SYNC that applies it
    assert tpdo1(rig.sync())[0] == SW_SWITCH_ON_DISABLED and rig.emu.applied_torque == 0.0
    for controlword in (0x06, 0x0F):
        rig.rpdo(controlword, 400)
        rig.sync()
    assert rig.emu.applied_torque == 0.4
    rig.write(0x6040, 0, 0x00, 2)            # by SDO: at once, no SYNC needed
    assert rig.emu.applied_torque == 0.0 and rig.emu.state is PowerState.SWITCH_ON_DISABLED


@pytest.mark.parametrize("option, after", [(2, PowerState.SWITCH_ON_DISABLED), (6, PowerState.QUICK_STOP_ACTIVE)])
def test_quick_stop_follows_the_quick_stop_option_code(option: int, after: PowerState) -> None:
    rig = Lockstep()
    try:
        rig.write(0x605A, 0, option, 2)
        enable_cst(rig)
        rig.rpdo(0x0F, 300)
        rig.sync()
        rig.rpdo(0x02, 300)                  # quick stop
        rig.sync()
        assert rig.emu.state is PowerState.QUICK_STOP_ACTIVE and rig.emu.applied_torque == 0.0
        rig.run(0.002)
        assert rig.emu.state is after
    finally:
        rig.close()


def test_heartbeat_consumer_timeout_faults_and_trips_the_watchdog(rig: Lockstep) -> None:
    enable_cst(rig)
    rig.write(0x1016, 1, 0x7F << 16 | 50, 4)   # host node 0x7F, 50 ms
    rig.rpdo(0x0F, 100)
    rig.sync()
    rig.run(0.2)
    assert rig.emu.state is PowerState.OPERATION_ENABLED   # watched only from the first heartbeat on
    for _ in range(3):
        rig.send(0x77F, [0x05])
        rig.run(0.04)
    assert rig.emu.state is PowerState.OPERATION_ENABLED and not rig.emu.watchdog_tripped
    frames = rig.run(0.02)
    assert (EMCY, bytes.fromhex("3081110000000000")) in frames       # 0x8130, register 0x11
    assert rig.emu.state is PowerState.FAULT and rig.emu.watchdog_tripped and rig.emu.applied_torque == 0.0


def test_leaving_operational_while_enabled_faults(rig: Lockstep) -> None:
    enable_cst(rig)
    rig.send(0x000, [0x80, NODE])            # pre-operational
    frames = rig.read()
    assert (EMCY, bytes.fromhex("0081110000000000")) in frames
    assert rig.emu.state is PowerState.FAULT and rig.emu.applied_torque == 0.0


def test_a_short_rpdo_is_dropped_with_an_emcy(rig: Lockstep) -> None:
    enable_cst(rig)
    rig.send(RPDO1, [0x0F, 0x00, 0xF4])       # 3 of 4 bytes
    assert (EMCY, bytes.fromhex("1082100000000000")) in rig.read()
    assert rig.emu.frames_rejected == 1 and rig.emu.state is PowerState.OPERATION_ENABLED


def test_made_by_the_registry_from_the_profile_protocol() -> None:
    channel_bus = can.Bus(interface="virtual", channel="cia402-registry-test-x")
    emulator = make_emulated_drive(channel_bus, cia402_profile(), Plant(inertia=0.01))
    try:
        assert type(emulator).__name__ == "EmulatedCiA402"
    finally:
        emulator.close()


_SDO_LIKE = st.builds(
    lambda command, index, sub, data: bytes([command]) + index.to_bytes(2, "little") + bytes([sub]) + data,
    st.integers(0, 255), st.sampled_from([0x1400, 0x1600, 0x1A00, 0x1A01, 0x1800, 0x1005, 0x1016, 0x1017,
                                         0x6040, 0x6060, 0x6071, 0x6072, 0x6076, 0x605A, 0x1008]),
    st.integers(0, 9), st.binary(min_size=4, max_size=4))


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.lists(st.one_of(
    st.tuples(st.sampled_from([0x000, SYNC, RPDO1, 0x605, 0x77F, 0x123, 0x7FF]), st.binary(max_size=8),
              st.booleans()),
    st.tuples(st.just(0x605), _SDO_LIKE, st.just(False))), max_size=30))
def test_no_frame_makes_the_node_raise(frames: list[tuple[int, bytes, bool]]) -> None:
    rig = Lockstep()
    try:
        enable_cst(rig)
        for can_id, data, remote in frames:
            if remote:
                rig.bus.send(can.Message(arbitration_id=can_id, is_remote_frame=True, dlc=len(data),
                                         is_extended_id=False))
            else:
                rig.send(can_id, data)
            rig.read(0.001)
        assert rig.emu.frame_errors == 0, rig.emu.last_frame_error
    finally:
        rig.close()


def test_a_frame_before_the_first_tick_boots_the_node_first(rig: Lockstep) -> None:
    rig.send(0x605, upload(0x1000))        # device type: profile 402, servo drive
    assert rig.read() == [(HEARTBEAT, b"\x00"), (SDO_TX, bytes.fromhex("4300100092010200"))]


@pytest.mark.parametrize("drop, says", [("[6071]", "0x6071"), ("DefaultValue=0x00000380", "cyclic synchronous torque")])
def test_an_eds_the_drive_would_refuse_ends_in_its_one_line(tmp_path: Path, drop: str, says: str) -> None:
    text = (drivers_dir() / "cia402-emulated.eds").read_text()
    if drop.startswith("["):   # the whole object
        head, _, rest = text.partition(drop + "\n")
        text = head + rest.partition("\n\n")[2]
    else:                      # 0x6502 without CST
        text = text.replace(drop, "DefaultValue=0x00000180")
    eds = tmp_path / "bad.eds"
    eds.write_text(text)
    profile = cia402_profile(options={**OPTIONS, "eds": str(eds)})
    bus = can.Bus(interface="virtual", channel="cia402-bad-eds-x")
    try:
        with pytest.raises(ConfigError, match=says) as info:
            make_emulated_drive(bus, profile, Plant(inertia=0.01))
    finally:
        bus.shutdown()
    assert "\n" not in str(info.value)


def test_sync_from_the_lockstep_bus_periodic_send_is_answered_at_each_period(rig: Lockstep) -> None:
    enable_cst(rig)
    task = rig.bus.send_periodic(can.Message(arbitration_id=SYNC, data=b"", is_extended_id=False), 0.002)
    try:
        start = rig.emu.time
        rig.run(0.0105)
        after = [(round(t - start, 9), can_id) for t, can_id, _ in rig.seen if t > start]
        # each SYNC (echoed to the host first, as SocketCAN loops BCM frames back), then its TPDOs
        assert after == [(k * 0.002, can_id) for k in range(1, 6) for can_id in (SYNC, TPDO1, TPDO2)]
        assert round(rig.emu.time - start, 9) == 0.011    # between the SYNCs of 10 and 12 ms
        rig.rpdo(0x0F, 200)
        rig.read()
        assert rig.emu.applied_torque == 0.0  # received, latched until the next SYNC
        rig.run(0.001)
        assert round(rig.emu.time - start, 9) == 0.012 and rig.emu.applied_torque == 0.2
    finally:
        task.stop()


@pytest.mark.parametrize("request_", ["6000000000000000", "0000000000000000", "c000000000000000"])
def test_an_sdo_segment_outside_a_transfer_is_aborted_not_raised_nor_printed(
        rig: Lockstep, request_: str, capsys: pytest.CaptureFixture[str]) -> None:
    response = rig.sdo(bytes.fromhex(request_))
    assert response[0] == 0x80 and struct.unpack("<I", response[4:])[0] in (0x05040001, 0x05040005)
    assert rig.emu.frame_errors == 0 and capsys.readouterr().err == ""
    assert rig.value(0x6502) == 0x380      # and the server still answers


def test_a_stopped_node_answers_nmt_only_and_keeps_its_heartbeat(rig: Lockstep) -> None:
    rig.write(0x1017, 0, 10, 2)
    configure_wire_mapping(rig)
    rig.send(0x000, [0x02, NODE])            # NMT stop
    rig.send(0x605, upload(0x1018, 1))
    assert rig.sync() == {}                  # neither SDO nor PDO
    assert (HEARTBEAT, b"\x04") in rig.run(0.01)
    rig.send(0x000, [0x01, NODE])
    assert set(rig.sync()) == {TPDO1, TPDO2} and rig.value(0x1018, 1) == 0


def _reach(rig: Lockstep, name: str) -> None:
    """Drive the node into canopen's state ``name`` by SDO controlwords (quick stop option 6:
    quick stop active holds)."""
    rig.write(0x605A, 0, 6, 2)
    steps = {"SWITCH ON DISABLED": [], "READY TO SWITCH ON": [0x06], "SWITCHED ON": [0x06, 0x07],
             "OPERATION ENABLED": [0x06, 0x07, 0x0F], "QUICK STOP ACTIVE": [0x06, 0x07, 0x0F, 0x02],
             "FAULT": [0x06, 0x07, 0x0F]}[name]
    for controlword in steps:
        rig.write(0x6040, 0, controlword, 2)
    if name == "FAULT":                       # enabled, then NMT operational left: a fault
        rig.send(0x000, [0x01, NODE])
        rig.send(0x000, [0x80, NODE])
        rig.read()


def test_every_commanded_transition_of_canopens_state402_table() -> None:
    from canopen.profiles.p402 import State402
    automatic = {"START", "NOT READY TO SWITCH ON", "FAULT REACTION ACTIVE"}
    checked = 0
    for (source, target), controlword in State402.TRANSITIONTABLE.items():
        if source in automatic:
            continue
        rig = Lockstep()
        try:
            _reach(rig, source)
            assert PowerState(rig.emu.protocol_state).name.replace("_", " ") == source
            rig.write(0x6040, 0, controlword, 2)
            reached = PowerState(rig.emu.protocol_state).name.replace("_", " ")
            assert reached == target, (source, hex(controlword), reached)
            checked += 1
        finally:
            rig.close()
    assert checked == 13


def test_an_eds_without_max_torque_is_clamped_by_the_profile_alone() -> None:
    # maxon's EPOS4 object dictionary (drivers/epos4.eds) has no 0x6072: the node runs,
    # its torque bounded by the profile's torque_limit (1 Nm), 0x6076 in uNm
    from dobhil.drives.load import load_profile
    rig = Lockstep(profile=load_profile("epos4"))
    try:
        assert rig.node == 1
        assert rig.sdo(upload(0x6076)) == bytes([0x43, 0x76, 0x60, 0]) + (512871).to_bytes(4, "little")
        abort = rig.sdo(upload(0x6072))
        assert abort[0] == 0x80 and struct.unpack("<I", abort[4:])[0] == 0x06020000
        enable_cst(rig)
        rig.rpdo(0x0F, 1000)                     # 0.513 Nm
        assert struct.unpack_from("<H", rig.sync()[0x181])[0] == SW_ENABLED_CST
        assert rig.emu.applied_torque == pytest.approx(0.512871)
        rig.rpdo(0x0F, 1900)                     # 0.97 Nm: within the profile's 1 Nm
        rig.sync()
        assert rig.emu.applied_torque == pytest.approx(1.9 * 0.512871)
        rig.rpdo(0x0F, 3000)                     # 1.54 Nm: the profile's 1 Nm
        rig.sync()
        assert rig.emu.applied_torque == 1.0
    finally:
        rig.close()
