"""The CiA 402 codec against literal bytes from the standard and against canopen's own tables
and PDO decoding (an independent implementation)."""

from __future__ import annotations

import math
import struct
from pathlib import Path

import canopen
import pytest
from canopen.emcy import EmcyConsumer
from canopen.profiles.p402 import State402
from hypothesis import given
from hypothesis import strategies as st

from dobhil.drives.cia402 import codec
from dobhil.drives.cia402.codec import Controlword, PowerState
from dobhil.errors import CodecError

EDS = Path(__file__).resolve().parents[2] / "drivers" / "cia402-emulated.eds"


# -- controlword and statusword ----------------------------------------------

@pytest.mark.parametrize(("command", "torque", "wire"), [
    (Controlword.SHUTDOWN, 0, "06 00 00 00"),
    (Controlword.SWITCH_ON, 0, "07 00 00 00"),
    (Controlword.ENABLE_OPERATION, 500, "0f 00 f4 01"),   # 500 per mille = 0x01F4
    (Controlword.ENABLE_OPERATION, -1, "0f 00 ff ff"),
    (Controlword.QUICK_STOP, 0, "02 00 00 00"),
    (Controlword.DISABLE_VOLTAGE, 0, "00 00 00 00"),
    (Controlword.FAULT_RESET, 0, "80 00 00 00"),
])
def test_rpdo_bytes_are_the_standards(command: Controlword, torque: int, wire: str) -> None:
    assert codec.encode_rpdo(command, torque) == bytes.fromhex(wire)


def test_controlwords_equal_canopens_state402() -> None:
    assert Controlword.SHUTDOWN == State402.CW_SHUTDOWN
    assert Controlword.SWITCH_ON == State402.CW_SWITCH_ON
    assert Controlword.ENABLE_OPERATION == State402.CW_OPERATION_ENABLED
    assert Controlword.QUICK_STOP == State402.CW_QUICK_STOP
    assert Controlword.DISABLE_VOLTAGE == State402.CW_DISABLE_VOLTAGE
    assert Controlword.FAULT_RESET == State402.CW_SWITCH_ON_DISABLED  # canopen's name for 0x80


@pytest.mark.parametrize(("statusword", "state"), [
    (0x0000, PowerState.NOT_READY_TO_SWITCH_ON),
    (0x0250, PowerState.SWITCH_ON_DISABLED),   # 0x40 + remote + voltage enabled
    (0x0231, PowerState.READY_TO_SWITCH_ON),
    (0x0233, PowerState.SWITCHED_ON),
    (0x1237, PowerState.OPERATION_ENABLED),    # bit 12: CST follows 6071
    (0x0217, PowerState.QUICK_STOP_ACTIVE),
    (0x021F, PowerState.FAULT_REACTION_ACTIVE),
    (0x0218, PowerState.FAULT),
    (0x0001, PowerState.UNKNOWN),
])
def test_statusword_literals(statusword: int, state: PowerState) -> None:
    assert codec.power_state(statusword) is state


@given(st.integers(0, 0xFFFF))
def test_power_state_agrees_with_canopens_table(statusword: int) -> None:
    names = [name for name, (mask, value) in State402.SW_MASK.items() if statusword & mask == value]
    got = codec.power_state(statusword)
    assert names == ([] if got is PowerState.UNKNOWN else [got.text.upper()])


def test_state_machine_steps_reach_operation_enabled() -> None:
    """Walking the drive's own transitions with our commands ends in Operation enabled
    (the transitions are canopen's State402.TRANSITIONTABLE, read the other way)."""
    by_command = {}
    for (src, dst), word in State402.TRANSITIONTABLE.items():
        by_command.setdefault((src, word), dst)
    state = "SWITCH ON DISABLED"
    for _ in range(4):
        word = codec.next_controlword(PowerState[state.replace(" ", "_")])
        assert word is not None
        if state == "OPERATION ENABLED":
            break
        state = by_command[(state, int(word))]
    assert state == "OPERATION ENABLED"
    assert codec.next_controlword(PowerState.QUICK_STOP_ACTIVE) is Controlword.DISABLE_VOLTAGE
    assert codec.next_controlword(PowerState.FAULT) is None
    assert codec.next_controlword(PowerState.NOT_READY_TO_SWITCH_ON) is None


def test_fault_reset_is_a_rising_edge() -> None:
    assert codec.fault_reset_edge(0x06) == (0x80,)
    assert codec.fault_reset_edge(0x80) == (0x00, 0x80)
    assert codec.fault_reset_edge(0x8F) == (0x0F, 0x80)


# -- torque -----------------------------------------------------------------

@pytest.mark.parametrize(("tau", "rated", "value"), [
    (0.5, 1.0, 500), (-0.5, 1.0, -500), (0.0005, 1.0, 1), (-0.0005, 1.0, -1),
    (0.00049, 1.0, 0), (0.0015, 1.0, 2), (-0.0015, 1.0, -2),   # half away from zero, both signs
    (40.0, 1.0, 32767), (-40.0, 1.0, -32768), (1e300, 1.0, 32767), (-math.inf, 1.0, -32768),
    (1.5, 0.5129, 2925),
])
def test_per_mille_rounds_and_saturates_like_a_drive(tau: float, rated: float, value: int) -> None:
    assert codec.per_mille(tau, rated) == value


@given(st.integers(-32768, 32767), st.floats(1e-3, 1e3))
def test_per_mille_round_trips_every_count(count: int, rated: float) -> None:
    assert codec.per_mille(codec.torque_from_per_mille(count, rated), rated) == count


# -- units ------------------------------------------------------------------

def test_units_from_the_profile_section() -> None:
    scale = codec.UnitScale.of(position_per_rev=4096, velocity_unit="rpm", gear_ratio=1.0)
    assert 4096 * scale.rad_per_increment == pytest.approx(2 * math.pi)
    assert 60 * scale.rad_s_per_velocity_count == pytest.approx(2 * math.pi)
    geared = codec.UnitScale.of(position_per_rev=4096, velocity_unit="increments_per_s", gear_ratio=4.0)
    assert 4096 * geared.rad_per_increment == pytest.approx(math.pi / 2)
    assert geared.rad_s_per_velocity_count == geared.rad_per_increment
    milli = codec.UnitScale.of(position_per_rev=1, velocity_unit="milli_rpm", gear_ratio=1.0)
    assert 60_000 * milli.rad_s_per_velocity_count == pytest.approx(2 * math.pi)


def test_unit_objects_are_sub_1_per_sub_2_as_cia402_names_them() -> None:
    encoder, gear = codec.UNIT_OBJECTS
    assert (encoder.index, encoder.key, gear.index, gear.key) == (0x608F, "position_per_rev", 0x6091, "gear_ratio")
    assert encoder.stated(4096, 1) == ("0x608F (position encoder resolution) = 4096 encoder increments / "
                                       "1 motor revolutions")
    assert encoder.agrees(1 << 20, 1, 1048576.0) and encoder.agrees(3200, 2, 1600)
    assert not encoder.agrees(4096, 1, 1048576.0) and not gear.agrees(26, 1, 1.0)
    assert gear.agrees(0, 0, 1.0) is None                       # no ratio stated
    assert gear.agrees(37, 10, 3.7) and codec.UnitObject.ratio_of(3.7) == (37, 10)
    assert codec.UnitObject.ratio_of(1 << 20) == (1 << 20, 1) and codec.UnitObject.ratio_of(1.0) == (1, 1)


# -- PDO layouts ------------------------------------------------------------

def test_layouts_bytes() -> None:
    assert codec.RPDO_CST_STRUCT.format == "<Hh"
    assert codec.TPDO_STATUS_STRUCT.format == "<Hih" and codec.TPDO_STATUS_STRUCT.size == 8
    assert codec.TPDO_MOTION_STRUCT.format == "<ib" and codec.TPDO_MOTION_STRUCT.size == 5
    assert codec.TPDO_STATUS_STRUCT.unpack(bytes.fromhex("37 12 00 10 00 00 f4 01")) == (0x1237, 4096, 500)


def test_a_mapping_beyond_64_bits_is_refused() -> None:
    with pytest.raises(CodecError, match="80 bits, a PDO carries 64"):
        codec.layout_struct([codec.DataType.UNSIGNED16, codec.DataType.INTEGER32, codec.DataType.INTEGER32])
    with pytest.raises(CodecError, match="data type 0x09"):
        codec.layout_struct([0x09])  # VISIBLE_STRING


def _mapped_node() -> canopen.RemoteNode:
    node = canopen.RemoteNode(5, canopen.import_od(str(EDS), 5))
    for pdos, number, objects in ((node.rpdo, 1, codec.RPDO_CST), (node.tpdo, 1, codec.TPDO_STATUS),
                                  (node.tpdo, 2, codec.TPDO_MOTION)):
        pdo = pdos[number]
        pdo.clear()
        for obj in objects:
            pdo.add_variable(obj.index, obj.subindex)
    return node


def test_layout_types_are_canopens_of_the_eds() -> None:
    node = _mapped_node()
    for pdo, objects in ((node.rpdo[1], codec.RPDO_CST), (node.tpdo[1], codec.TPDO_STATUS),
                         (node.tpdo[2], codec.TPDO_MOTION)):
        assert [v.od.data_type for v in pdo.map] == [m.data_type for m in objects]
        assert [v.length for v in pdo.map] == [m.bits for m in objects]
        assert [(v.index, v.subindex) for v in pdo.map] == [(m.index, m.subindex) for m in objects]


@given(st.binary(min_size=8, max_size=8), st.binary(min_size=5, max_size=5))
def test_struct_decoding_equals_canopens_pdo_decoding(status: bytes, motion: bytes) -> None:
    node = _mapped_node()
    for pdo, layout, data in ((node.tpdo[1], codec.TPDO_STATUS_STRUCT, status),
                              (node.tpdo[2], codec.TPDO_MOTION_STRUCT, motion)):
        pdo.data = bytearray(data)
        assert list(layout.unpack(data)) == [var.raw for var in pdo.map]


@given(st.integers(0, 0xFFFF), st.integers(-32768, 32767))
def test_rpdo_encoding_equals_canopens(controlword: int, torque: int) -> None:
    pdo = _mapped_node().rpdo[1]
    pdo.data = bytearray(4)
    # canopen's PdoVariable.raw setter calls the map's update(): no periodic task, no I/O
    pdo["Controlword"].raw = controlword
    pdo[1].raw = torque
    assert bytes(pdo.data) == codec.encode_rpdo(controlword, torque)


# -- EMCY -------------------------------------------------------------------

def test_emcy_decoding_equals_canopens() -> None:
    data = bytes.fromhex("10 23 03 00 00 00 00 00")  # 0x2310 current, register 0x03
    consumer = EmcyConsumer()
    consumer.on_emcy(0x85, data, 0.0)
    emcy = codec.decode_emcy(data)
    assert (emcy.code, emcy.register) == (consumer.log[0].code, consumer.log[0].register) == (0x2310, 3)
    assert codec.EMCY_LAYOUT.format == "<HB5s"
    with pytest.raises(CodecError):
        codec.decode_emcy(b"\x10\x23")
    assert struct.unpack("<HB", data[:3]) == (0x2310, 3)


@pytest.mark.parametrize(("period", "value"), [
    (0.001, (1, -3)), (0.0025, (25, -4)), (0.0005, (5, -4)), (0.002, (2, -3)), (0.1, (1, -1)), (2.0, (2, 0)),
])
def test_interpolation_time_period_0x60c2(period: float, value: tuple[int, int]) -> None:
    assert codec.interpolation_period(period) == value
    assert value[0] * 10.0 ** value[1] == pytest.approx(period)


def test_an_interpolation_period_without_a_whole_value_is_refused() -> None:
    with pytest.raises(CodecError, match="0x60C2"):
        codec.interpolation_period(0.0012345)


def test_the_fault_bit() -> None:
    assert codec.is_fault(0x0218) and codec.is_fault(0x021F) and not codec.is_fault(0x1237)


def test_data_types_and_their_formats_are_canopens() -> None:
    """The pure codec's data type table agrees with canopen's object dictionary: the same
    CiA 301 indices, and each one's struct character is the one canopen packs it with."""
    from canopen.objectdictionary import ODVariable, datatypes
    for member in codec.DataType:
        assert member.value == getattr(datatypes, member.name), member.name
    for data_type, char in codec.DATA_TYPE_FORMATS.items():
        theirs, ours = ODVariable.STRUCT_TYPES[data_type], struct.Struct("<" + char)
        assert ours.size == theirs.size, codec.DataType(data_type).name
        for raw in (bytes(range(0x81, 0x81 + ours.size)), bytes(range(1, 1 + ours.size))):
            assert ours.unpack(raw) == theirs.unpack(raw), codec.DataType(data_type).name
