"""The emulated CiA 402 node's object dictionary (drivers/cia402-emulated.eds), read by
canopen's own EDS importer: every object the drive and the emulator use is there, with
the CiA 301 / CiA 402 data type, access and PDO mappability, and CST is supported."""

from __future__ import annotations

import canopen
import pytest
from canopen.objectdictionary import (INTEGER8, INTEGER16, INTEGER32, UNSIGNED8, UNSIGNED16,
                                      UNSIGNED32, ODArray, ODRecord, ODVariable)

from dobhil.data import drivers_dir

EDS = drivers_dir() / "cia402-emulated.eds"
NODE = 5

#: index -> (data type, writable, PDO-mappable), from CiA 301 and CiA 402
VARIABLES = {
    0x1000: (UNSIGNED32, False, False),  # device type
    0x1001: (UNSIGNED8, False, True),    # error register
    0x1005: (UNSIGNED32, True, False),   # COB-ID SYNC
    0x1006: (UNSIGNED32, True, False),   # communication cycle period [us]
    0x1014: (UNSIGNED32, True, False),   # COB-ID EMCY
    0x1017: (UNSIGNED16, True, False),   # producer heartbeat time [ms]
    0x603F: (UNSIGNED16, False, True),   # error code
    0x6040: (UNSIGNED16, True, True),    # controlword
    0x6041: (UNSIGNED16, False, True),   # statusword
    0x605A: (INTEGER16, True, False),    # quick stop option code
    0x6060: (INTEGER8, True, True),      # modes of operation
    0x6061: (INTEGER8, False, True),     # modes of operation display
    0x6064: (INTEGER32, False, True),    # position actual value
    0x606C: (INTEGER32, False, True),    # velocity actual value
    0x6071: (INTEGER16, True, True),     # target torque
    0x6072: (UNSIGNED16, True, True),    # max torque
    0x6076: (UNSIGNED32, True, False),   # motor rated torque
    0x6077: (INTEGER16, False, True),    # torque actual value
    0x6502: (UNSIGNED32, False, False),  # supported drive modes
}


@pytest.fixture(scope="module")
def od() -> canopen.ObjectDictionary:
    return canopen.objectdictionary.import_od(str(EDS), NODE)


@pytest.mark.parametrize("index", sorted(VARIABLES))
def test_each_variable_has_its_standard_type_access_and_mapping(
        od: canopen.ObjectDictionary, index: int) -> None:
    var = od[index]
    assert isinstance(var, ODVariable)
    data_type, writable, mappable = VARIABLES[index]
    assert (var.data_type, var.writable, var.readable, var.pdo_mappable) == (
        data_type, writable, True, mappable)


def test_cst_is_supported_beside_csp_and_csv_only(od: canopen.ObjectDictionary) -> None:
    modes = od[0x6502].default
    assert modes & (1 << 9)            # cyclic synchronous torque
    assert modes == 0b11_1000_0000     # CSP (bit 7), CSV (bit 8), CST (bit 9): what it emulates


def test_defaults_give_a_cia402_servo_with_one_nm_rated_torque(od: canopen.ObjectDictionary) -> None:
    assert od[0x1000].default == 0x0002_0192    # profile 402, servo drive
    assert od[0x1005].default == 0x80           # SYNC consumer on the default COB-ID
    assert od[0x1014].default == 0x80 + NODE    # $NODEID resolved by canopen
    assert od[0x6076].default == 1000           # mNm: 1 Nm
    assert od[0x6072].default > 1000            # peak above rated, per mille
    assert (od[0x608F][1].default, od[0x608F][2].default) == (1 << 20, 1)   # a 20-bit encoder
    assert (od[0x6091][1].default, od[0x6091][2].default) == (1, 1)


def test_identity_and_consumer_heartbeat(od: canopen.ObjectDictionary) -> None:
    identity = od[0x1018]
    assert isinstance(identity, ODRecord)
    assert [identity[s].data_type for s in range(5)] == [UNSIGNED8] + [UNSIGNED32] * 4
    assert identity[3].default == 0x0001_0000   # revision 1.0, the profile's firmware "1.0"
    consumer = od[0x1016]
    assert isinstance(consumer, ODArray)
    assert (consumer[1].data_type, consumer[1].writable, consumer[1].default) == (UNSIGNED32, True, 0)


@pytest.mark.parametrize("base, cob", [(0x1400, 0x200), (0x1800, 0x180)])
def test_four_pdos_each_way_with_eight_mapping_entries(
        od: canopen.ObjectDictionary, base: int, cob: int) -> None:
    for n in range(4):
        com, mapping = od[base + n], od[base + 0x200 + n]
        assert (com[1].data_type, com[1].writable) == (UNSIGNED32, True)
        assert (com[2].data_type, com[2].writable) == (UNSIGNED8, True)
        assert com[1].default & 0x7FF == cob + n * 0x100 + NODE
        assert (mapping[0].data_type, mapping[0].writable) == (UNSIGNED8, True)
        assert [mapping[s].data_type for s in range(1, 9)] == [UNSIGNED32] * 8
        assert all(mapping[s].writable for s in range(1, 9))


def test_default_mapping_is_the_wire_mapping_and_fits_a_frame(od: canopen.ObjectDictionary) -> None:
    def mapped(index: int) -> list[int]:
        return [od[index][s].default for s in range(1, od[index][0].default + 1)]

    assert mapped(0x1600) == [0x6040_0010, 0x6071_0010]
    assert mapped(0x1A00) == [0x6041_0010, 0x6064_0020, 0x6077_0010]
    assert mapped(0x1A01) == [0x606C_0020, 0x6061_0008]
    for index in (0x1600, 0x1A00, 0x1A01):
        assert sum(entry & 0xFF for entry in mapped(index)) <= 64
        for entry in mapped(index):   # each mapped object exists and is PDO-mappable
            var = od[entry >> 16]
            assert isinstance(var, ODVariable) and var.pdo_mappable and len(var) == entry & 0xFF
    # synchronous (type 1), enabled; PDOs 3 and 4 disabled (bit 31 of the COB-ID)
    assert [od[0x1400 + n][2].default for n in range(4)] == [1, 0xFF, 0xFF, 0xFF]
    assert [od[0x1800 + n][2].default for n in range(4)] == [1, 1, 0xFF, 0xFF]
    assert [od[0x1400 + n][1].default >> 31 for n in range(4)] == [0, 1, 1, 1]
    assert [od[0x1800 + n][1].default >> 31 for n in range(4)] == [0, 0, 1, 1]
