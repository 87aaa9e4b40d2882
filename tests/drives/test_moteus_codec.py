"""dobhil's moteus codec against the official library's own builders and parsers
(PyPI ``moteus`` 1.1.1: ``moteus.multiplex``, ``moteus.protocol``, ``Controller.make_*``),
and against the literal bytes mjbots' documentation shows."""

from __future__ import annotations

import math
import struct

import moteus
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from moteus import multiplex as mp
from moteus import protocol as mprot

from dobhil.drives.moteus.codec import (Mode, Opcode, Parser, Register, Resolution, arbitration_id, decode_value,
                                        encode_value, pad, parse, read_subframe, reply_subframe, split_id,
                                        varuint, read_varuint, write_subframe)
from dobhil.drives.moteus.frames import CommandFrame, Query, reply_values, stop_payload
from dobhil.errors import CodecError

RESOLUTIONS = st.sampled_from(list(Resolution))
#: scaled registers of every quantity (position, velocity, torque, current, voltage, temperature, time, scale)
SCALED = st.sampled_from([Register.POSITION, Register.VELOCITY, Register.TORQUE, Register.Q_CURRENT,
                          Register.VOLTAGE, Register.TEMPERATURE, Register.COMMAND_TIMEOUT,
                          Register.COMMAND_KP_SCALE, Register.COMMAND_FEEDFORWARD_TORQUE, Register.POWER])
VALUES = st.one_of(st.floats(-1e6, 1e6, allow_nan=False, width=32), st.just(math.nan), st.just(math.inf),
                   st.just(-math.inf), st.floats(-300, 300, width=32))


def _library_scale(register: int, resolution: Resolution) -> float:
    """The step the library itself uses: scale_register of code 1."""
    if resolution is Resolution.F32:
        return 1.0
    return float(mprot.scale_register(register, int(resolution), 1))


@settings(max_examples=400, deadline=None)
@given(register=SCALED, resolution=RESOLUTIONS, value=VALUES)
def test_a_value_encodes_to_the_librarys_code_and_decodes_as_its_parser_does(register: Register,
                                                                                resolution: Resolution,
                                                                                value: float) -> None:
    ours = encode_value(register, resolution, value)
    theirs = mp.saturate(value, int(resolution), _library_scale(register, resolution))
    if resolution is Resolution.F32:
        assert struct.pack("<f", ours) == struct.pack("<f", theirs)
    else:
        assert ours == theirs
    frame = reply_subframe(register, resolution, (value,))
    parsed = mprot.parse_reply(frame)
    assert set(parsed) == {int(register)}
    mine = reply_values(frame)[register]
    assert (math.isnan(mine) and math.isnan(parsed[register])) or mine == pytest.approx(parsed[register], rel=1e-12)


@settings(max_examples=200, deadline=None)
@given(start=st.integers(0, 0x3FFF), resolution=RESOLUTIONS, count=st.integers(1, 9),
       kind=st.sampled_from(["write", "read", "reply"]))
def test_subframes_parse_the_same_in_the_library(start: int, resolution: Resolution, count: int, kind: str) -> None:
    values = [float(i) for i in range(count)]
    data = {"write": lambda: write_subframe(start, resolution, values),
            "read": lambda: read_subframe(start, resolution, count),
            "reply": lambda: reply_subframe(start, resolution, values)}[kind]()
    theirs = list(mp.parse_frame(pad(data)))
    ours = list(parse(pad(data)))
    assert [s.register for s in theirs] == [s.register for s in ours] == list(range(start, start + count))
    assert all(s.resolution == int(resolution) for s in theirs)
    if kind != "read":
        assert [decode_value(s.register, resolution, s.value) for s in theirs] == \
            pytest.approx([s.value for s in ours], nan_ok=True)


@given(st.integers(0, (1 << 35) - 1))
def test_varuint_round_trips_and_reads_as_the_librarys(value: int) -> None:
    data = varuint(value)
    assert read_varuint(data, 0) == (value, len(data))
    assert mp.read_varuint(0, data) == (value, len(data))


def test_the_torque_command_is_byte_for_byte_the_librarys_make_position() -> None:
    """Controller.make_position of torque by position mode (kp = kd = 0, position NaN), with
    the watchdog and a query of mode, position, velocity, torque and fault."""
    query = moteus.QueryResolution()
    query.voltage = query.temperature = moteus.IGNORE
    ctrl = moteus.Controller(id=1, query_resolution=query)
    cmd = ctrl.make_position(position=math.nan, velocity=0.0, feedforward_torque=0.75, kp_scale=0.0,
                             kd_scale=0.0, watchdog_timeout=0.05, query=True)
    frame = CommandFrame(resolution=Resolution.F32, timeout=0.05,
                         query=Query.motion(Resolution.F32, Resolution.F32, Resolution.F32))
    data = bytearray(frame.payload)
    frame.fill(data, 0.75)
    assert bytes(data) == pad(cmd.data)
    # transport.py builds the id from the command's fields
    assert arbitration_id(cmd.source, cmd.destination, reply=cmd.reply_required, prefix=cmd.can_prefix) == 0x8001


@pytest.mark.parametrize("res,lib", [(Resolution.INT8, moteus.INT8), (Resolution.INT16, moteus.INT16),
                                     (Resolution.INT32, moteus.INT32)])
def test_integer_command_resolutions_match_the_library(res: Resolution, lib: int) -> None:
    pos = moteus.PositionResolution()
    for name in ("position", "velocity", "feedforward_torque", "kp_scale", "kd_scale"):
        setattr(pos, name, lib)
    query = moteus.QueryResolution()
    query.voltage = query.temperature = moteus.IGNORE
    ctrl = moteus.Controller(id=1, position_resolution=pos, query_resolution=query)
    cmd = ctrl.make_position(position=math.nan, velocity=0.0, feedforward_torque=-1.234, kp_scale=0.0,
                             kd_scale=0.0, watchdog_timeout=0.1, query=True)
    frame = CommandFrame(resolution=res, timeout=0.1, query=Query.motion(Resolution.F32, Resolution.F32,
                                                                        Resolution.F32))
    data = bytearray(frame.payload)
    frame.fill(data, -1.234)
    assert bytes(data) == pad(cmd.data)


def test_stop_and_literal_bytes_from_the_documentation() -> None:
    """``make_stop()`` is ``01 00 00``; docs/protocol/can.md's example frame and reply."""
    assert moteus.Controller(id=1).make_stop().data == stop_payload(Query({}))[:3] == bytes.fromhex("010000")
    # make_position(position=nan, velocity=0, kp_scale=0, kd_scale=0, feedforward_torque=0.5, query=True)
    doc = bytes.fromhex("01000a" "0c0520" "0000c07f" "00000000" "0000003f" "00000000" "00000000" "11001f01130d")
    ours = (write_subframe(Register.MODE, Resolution.INT8, (Mode.POSITION,))
            + write_subframe(Register.COMMAND_POSITION, Resolution.F32, (math.nan, 0.0, 0.5, 0.0, 0.0))
            + read_subframe(Register.MODE, Resolution.INT8, 1) + read_subframe(Register.POSITION, Resolution.F32, 3)
            + read_subframe(Register.VOLTAGE, Resolution.INT8, 3))
    assert ours == doc
    reply = bytes.fromhex("2404000a005000000170ff230d181400")
    values = reply_values(reply)
    assert values[Register.MODE] == 10 and values[Register.POSITION] == pytest.approx(0.008)
    assert values[Register.VELOCITY] == pytest.approx(0.00025 * 256)
    assert values[Register.TORQUE] == pytest.approx(-1.44)
    assert values[Register.VOLTAGE] == 12.0 and values[Register.TEMPERATURE] == 20.0
    assert values == pytest.approx(mprot.parse_reply(reply))


def test_nan_codes_and_truncation_toward_zero() -> None:
    assert encode_value(Register.POSITION, Resolution.INT16, math.nan) == -32768
    assert decode_value(Register.POSITION, Resolution.INT16, -32768) != decode_value(
        Register.POSITION, Resolution.INT16, -32768)   # NaN
    assert encode_value(Register.TORQUE, Resolution.INT16, 0.0199) == 1
    assert encode_value(Register.TORQUE, Resolution.INT16, -0.0199) == -1   # toward zero, not floor
    assert encode_value(Register.TORQUE, Resolution.INT8, 1e9) == 127      # saturates at +max, never -128


def test_ids_and_padding() -> None:
    assert split_id(arbitration_id(3, 0x45, reply=True, prefix=0x12)) == (0x12, 3, 0x45, True)
    assert pad(b"\x01\x00\x00" * 3) == b"\x01\x00\x00" * 3 + b"\x50" * 3   # 9 -> 12 bytes
    with pytest.raises(CodecError):
        pad(bytes(65))
    with pytest.raises(CodecError, match="opcode 0x40"):
        list(parse(bytes((0x40, 0, 0))))
    assert list(parse(b"\x50\x50")) == [] and Opcode.NOP == mp.NOP


@settings(max_examples=200, deadline=None)
@given(torques=st.lists(st.floats(-100, 100, allow_nan=False), min_size=2, max_size=5),
       res=RESOLUTIONS, other=st.booleans())
def test_the_shape_keeping_parser_reads_as_parse_does(torques: list[float], res: Resolution, other: bool) -> None:
    """Frames of one shape (the torque alone changes), and a frame of another shape between
    them: the kept shape gives what the byte-by-byte parse gives, every time."""
    parser = Parser()
    frame = CommandFrame(resolution=res, timeout=0.1, query=Query.motion(res, Resolution.F32, res))
    for i, tau in enumerate(torques):
        data = bytearray(frame.payload)
        frame.fill(data, tau)
        if other and i == 1:
            data = bytearray(stop_payload(Query.motion(res, res, res)))
        ours, plain = parser.parse(bytes(data)), tuple(parse(bytes(data)))
        assert [(s.opcode, s.register, s.resolution) for s in ours] == \
            [(s.opcode, s.register, s.resolution) for s in plain]
        assert [s.value for s in ours] == pytest.approx([s.value for s in plain], nan_ok=True)
