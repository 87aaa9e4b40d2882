"""The MIT codec (dobhil.drives.mit.codec) against literal bytes worked out by hand from the
firmware's formula (bgkatz/motorcontrol math_ops.c / can.c), and its properties: clamping,
NaN refused, round trips, wrap vs saturate, axis direction, reply layouts, Damiao nibbles,
the hot path's table against the formula, and what single precision changes."""

from __future__ import annotations

import dataclasses
import math
import random

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from dobhil.drives.mit.codec import (
    Channel,
    Command,
    MitModel,
    Special,
    TorqueFrame,
    float_to_uint,
    is_special,
    pack_command,
    pack_reply,
    special_frame,
    uint_to_float,
    unpack_command,
    unpack_reply,
)
from dobhil.drives.mit.models import find_model, load_models
from dobhil.errors import CodecError

AK80_9 = find_model("cubemars", "AK80-9", "manual-1.0.8")
AK80_9_V2 = find_model("cubemars", "AK80-9", "2.0")  # 6-byte replies (mbed layout)
AK10_9 = find_model("cubemars", "AK10-9", "manual-1.0.8")
AK10_9_V11 = find_model("cubemars", "AK10-9", "1.1")  # axis direction -1, same ranges
DM4310 = find_model("damiao", "DM4310", "factory")
CHEETAH = find_model("mini-cheetah", "motorcontrol", "3586419")
MODELS = list(load_models().values())
FINITE = st.floats(allow_nan=False, allow_infinity=False, width=64)


def f32_firmware(x: float, lo: float, hi: float, bits: int) -> int:
    """math_ops.c float_to_uint written out step by step in numpy float32 (the clamp first)."""
    x = min(max(x, lo), hi)
    span = np.float32(np.float32(hi) - np.float32(lo))
    return int(np.float32(np.float32(np.float32(x) - np.float32(lo)) * np.float32((1 << bits) - 1)) / span)


# ---------------------------------------------------------------------------
# Literal bytes


def test_special_frames_are_seven_ff_and_the_code() -> None:
    assert special_frame(Special.ENTER) == bytes.fromhex("ffffffffffffff fc")
    assert special_frame(Special.EXIT) == bytes.fromhex("ffffffffffffff fd")
    assert special_frame(Special.ZERO) == bytes.fromhex("ffffffffffffff fe")
    assert special_frame(Special.CLEAR_ERROR) == bytes.fromhex("ffffffffffffff fb")
    for kind in Special:
        assert is_special(special_frame(kind)) is kind
        assert is_special(bytearray(special_frame(kind))) is kind
    assert is_special(bytes.fromhex("ffffffffffffff fa")) is None
    assert is_special(bytes.fromhex("ffffffffffff fc")) is None  # 7 bytes
    assert is_special(pack_command(AK80_9, Command(0, 0, 0, 0, 0))) is None


def test_zero_command_of_an_ak80_9_by_hand() -> None:
    """p: (0 + 12.5) * 65535 / 25 = 32767.5 -> 0x7FFF; v: 50 * 4095 / 100 = 2047.5 -> 0x7FF;
    kp = kd = 0; t: 18 * 4095 / 36 = 2047.5 -> 0x7FF."""
    assert pack_command(AK80_9, Command(0.0, 0.0, 0.0, 0.0, 0.0)) == bytes.fromhex("7fff 7f f0 00 00 07 ff")
    assert TorqueFrame(AK80_9).template == bytes.fromhex("7fff7ff0000007ff")


def test_a_full_command_of_an_ak80_9_by_hand() -> None:
    """p 1.0: 13.5 * 65535 / 25 = 35388.9 -> 35388 = 0x8A3C; v -5: 45 * 4095 / 100 = 1842.75 ->
    0x732; kp 100: 100 * 4095 / 500 = 819 = 0x333; kd 1: 4095 / 5 = 819 = 0x333;
    t 2: 20 * 4095 / 36 = 2275 = 0x8E3 (all exact in single precision)."""
    data = pack_command(AK80_9, Command(1.0, -5.0, 100.0, 1.0, 2.0))
    assert data == bytes.fromhex("8a3c 73 23 33 33 38 e3")
    back = unpack_command(AK80_9, data)
    assert back.kp == 100.0 and back.kd == 1.0 and back.torque == 2.0
    assert 1.0 - AK80_9.quanta.position < back.position <= 1.0
    assert -5.0 - AK80_9.quanta.velocity < back.velocity <= -5.0


def test_the_zero_torque_bias_of_an_ak80_9() -> None:
    """Zero torque encodes to 2047 (2047.5 truncated), which decodes to 2047 * 36 / 4095 - 18
    = -0.0044 Nm: the bias a disturbance observer sees."""
    assert float_to_uint(0.0, -18.0, 18.0, 12) == 2047
    bias = uint_to_float(2047, -18.0, 18.0, 12)
    assert bias == pytest.approx(-0.0044, abs=5e-5)
    # the firmware's float arithmetic step by step: 2047 * 36 in float, / 4095, + (-18)
    f = np.float32
    assert bias == float(f(f(f(2047) * f(36.0)) / f(4095.0)) + f(-18.0))
    assert AK80_9.torque_bias == bias
    assert AK10_9_V11.torque_bias == -AK10_9.torque_bias  # axis -1: the host sees the sign flipped


def test_a_cubemars_reply_by_hand() -> None:
    """id 1, p 0x8000, v 0x800, t 0x800, 40 degC, error 2 (over current)."""
    reply = unpack_reply(AK80_9, bytes.fromhex("01 8000 80 08 00 28 02"))
    assert (reply.motor_id, reply.raw_position, reply.raw_velocity, reply.raw_torque) == (1, 0x8000, 0x800, 0x800)
    assert reply.position == pytest.approx(32768 * 25 / 65535 - 12.5, abs=1e-6)
    assert reply.velocity == pytest.approx(2048 * 100 / 4095 - 50, abs=1e-5)
    assert reply.torque == pytest.approx(2048 * 36 / 4095 - 18, abs=1e-5)
    assert (reply.error, reply.error_text, reply.temperature, reply.state) == (2, "over current", 40.0, -1)
    assert dict(reply.extra) == {"temperature": 40, "error": 2}
    assert unpack_reply(AK80_9, bytes.fromhex("01 8000 80 08 00 28 00")).error_text == ""
    assert "unknown" in unpack_reply(AK80_9, bytes.fromhex("01 8000 80 08 00 28 63")).error_text


def test_a_damiao_reply_splits_byte_0_into_state_and_id() -> None:
    enabled = unpack_reply(DM4310, bytes.fromhex("13 8000 80 08 00 2a 30"))
    assert (enabled.motor_id, enabled.state, enabled.error, enabled.error_text) == (3, 1, 0, "")
    assert enabled.temperature == 48.0 and dict(enabled.extra) == {"mos_temperature": 42, "rotor_temperature": 48}
    fault = unpack_reply(DM4310, bytes.fromhex("b3 8000 80 08 00 2a 30"))
    assert (fault.motor_id, fault.state, fault.error, fault.error_text) == (3, 0xB, 0xB, "MOS over temperature")
    assert unpack_reply(DM4310, bytes.fromhex("03 8000 80 08 00 2a 30")).state == 0
    # packing: the state nibble, or the error nibble when there is one
    assert pack_reply(DM4310, 5, 0.0, 0.0, 0.0, state=1)[0] == 0x15
    assert pack_reply(DM4310, 5, 0.0, 0.0, 0.0, state=0)[0] == 0x05
    assert pack_reply(DM4310, 5, 0.0, 0.0, 0.0, error=0xA)[0] == 0xA5
    with pytest.raises(CodecError, match="motor id 16: expected 0 to 15"):
        pack_reply(DM4310, 16, 0.0, 0.0, 0.0)


def test_mini_cheetah_replies_with_and_without_the_bus_voltage() -> None:
    seven = unpack_reply(CHEETAH, bytes.fromhex("01 8000 80 08 00 c0"))
    assert dict(seven.extra) == {"bus_voltage": 0xC0} and seven.error == -1 and math.isnan(seven.temperature)
    six = unpack_reply(CHEETAH, bytes.fromhex("01 8000 80 08 00"))
    assert dict(six.extra) == {} and six.position == seven.position
    packed = pack_reply(CHEETAH, 1, 0.0, 0.0, 0.0, extra={"bus_voltage": 0xC0})
    assert len(packed) == 7 and packed[6] == 0xC0


@pytest.mark.parametrize(("model", "good", "bad"), [
    (AK80_9, (8,), (6, 7)), (AK80_9_V2, (6,), (7, 8)), (CHEETAH, (6, 7), (5, 8)), (DM4310, (8,), (6, 7)),
])
def test_reply_lengths_per_layout(model: MitModel, good: tuple[int, ...], bad: tuple[int, ...]) -> None:
    for n in good:
        assert unpack_reply(model, bytes(n)).raw_position == 0
    for n in bad:
        with pytest.raises(CodecError, match=f"reply of {n} bytes, expected"):
            unpack_reply(model, bytes(n))
    assert len(pack_reply(model, 1, 0.0, 0.0, 0.0)) == max(good)


# ---------------------------------------------------------------------------
# Refusals and clamping


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_nan_and_infinities_are_refused_everywhere(bad: float) -> None:
    with pytest.raises(CodecError, match="not a finite number"):
        float_to_uint(bad, -18.0, 18.0, 12)
    for field in ("position", "velocity", "kp", "kd", "torque"):
        values = dict(position=0.0, velocity=0.0, kp=0.0, kd=0.0, torque=0.0)
        values[field] = bad
        with pytest.raises(CodecError, match=f"{field} .*not a finite number"):
            pack_command(AK80_9, Command(**values))
    frame = TorqueFrame(AK80_9)
    data = bytearray(frame.template)
    with pytest.raises(CodecError, match="not a finite number"):
        frame.fill(data, bad)
    assert data == frame.template  # nothing written
    with pytest.raises(CodecError, match="not a finite number"):
        pack_reply(AK80_9, 1, bad, 0.0, 0.0)


def test_values_clamp_at_the_range_ends() -> None:
    assert float_to_uint(-18.0, -18.0, 18.0, 12) == 0
    assert float_to_uint(18.0, -18.0, 18.0, 12) == 4095
    assert float_to_uint(-1e300, -18.0, 18.0, 12) == 0
    assert float_to_uint(1e300, -18.0, 18.0, 12) == 4095
    assert float_to_uint(12.5, -12.5, 12.5, 16) == 0xFFFF
    top = pack_command(AK80_9, Command(1e9, 1e9, 1e9, 1e9, 1e9))
    low = pack_command(AK80_9, Command(-1e9, -1e9, -1e9, -1e9, -1e9))
    assert low == bytes(8)  # every field at code 0 (kp, kd clamp to 0)
    assert top == b"\xff" * 8 and is_special(top) is None  # 0xFF is no special code (0xFB..0xFE are)
    assert unpack_command(AK80_9, low) == Command(-12.5, -50.0, 0.0, 0.0, -18.0)
    assert uint_to_float(4095, -18.0, 18.0, 12) == 18.0
    with pytest.raises(CodecError, match="code 4096"):
        uint_to_float(4096, -18.0, 18.0, 12)


def test_a_command_never_spells_a_special_frame() -> None:
    """Every field at its top and the torque code 0xFFC is the enter frame's bytes: the
    position code is lowered by one step instead."""
    t_ffc = AK80_9.torque.decode(0xFFC)
    data = pack_command(AK80_9, Command(12.5, 50.0, 500.0, 5.0, t_ffc))
    assert data == bytes.fromhex("fffe ff ff ff ff ff fc") and is_special(data) is None
    for code in range(0xFF0, 0x1000):
        assert is_special(pack_command(AK80_9, Command(12.5, 50.0, 500.0, 5.0, AK80_9.torque.decode(code)))) is None
    with pytest.raises(CodecError, match="special frame"):
        unpack_command(AK80_9, special_frame(Special.ENTER))
    with pytest.raises(CodecError, match="7 bytes"):
        unpack_command(AK80_9, bytes(7))


# ---------------------------------------------------------------------------
# Wrap vs saturate, axis direction


def test_position_past_the_range_wraps_as_the_firmware_int_arithmetic_does() -> None:
    """pack_reply of can.c: (int)((p + 12.5) * 65535 / 25) stored in 16 bits."""
    over = unpack_reply(AK80_9, pack_reply(AK80_9, 1, 12.6, 0.0, 0.0))
    assert over.raw_position == int((25.1) * 65535 / 25) - 65536 == 261
    assert over.position + AK80_9.wrap_period == pytest.approx(12.6, abs=AK80_9.quanta.position)
    under = unpack_reply(AK80_9, pack_reply(AK80_9, 1, -12.6, 0.0, 0.0))
    assert under.raw_position == (-262) & 0xFFFF  # (int)(-262.14) truncates toward zero
    assert under.position - AK80_9.wrap_period == pytest.approx(-12.6, abs=AK80_9.quanta.position)
    # just below -p_max the cast truncates toward zero: code 0, not 65535 (the firmware's quirk)
    assert unpack_reply(AK80_9, pack_reply(AK80_9, 1, -12.5001, 0.0, 0.0)).raw_position == 0
    # many turns: the reading is the angle modulo the wrap period (2^16 codes)
    for angle in (30.0, -77.7, 1000.0):
        reading = unpack_reply(AK80_9, pack_reply(AK80_9, 1, angle, 0.0, 0.0)).position
        turns = round((angle - reading) / AK80_9.wrap_period)
        assert reading + turns * AK80_9.wrap_period == pytest.approx(angle, abs=2 * AK80_9.quanta.position + 1e-4)
    assert AK80_9.wrap_period == pytest.approx(25.0 * 65536 / 65535)


def test_position_past_the_range_saturates_on_a_saturating_row() -> None:
    saturating = dataclasses.replace(AK80_9, position_at_limit="saturate")
    assert unpack_reply(saturating, pack_reply(saturating, 1, 12.6, 0.0, 0.0)).raw_position == 0xFFFF
    assert unpack_reply(saturating, pack_reply(saturating, 1, -40.0, 0.0, 0.0)).raw_position == 0
    # velocity and torque clamp on every row
    reply = unpack_reply(AK80_9, pack_reply(AK80_9, 1, 0.0, 99.0, -99.0))
    assert (reply.raw_velocity, reply.raw_torque) == (4095, 0)


def test_axis_direction_negates_position_velocity_and_torque_at_the_wire() -> None:
    """AK10-9 firmware 1.1 turns the other way (canmotorlib AXIS_DIRECTION -1); its ranges
    are the current firmware's, so its bytes are the current firmware's of the negated values."""
    cmd = Command(1.0, 2.0, 10.0, 0.5, 3.0)
    mirrored = Command(-1.0, -2.0, 10.0, 0.5, -3.0)
    assert pack_command(AK10_9_V11, cmd) == pack_command(AK10_9, mirrored)
    back = unpack_command(AK10_9_V11, pack_command(AK10_9_V11, cmd))
    assert back.position == pytest.approx(1.0, abs=2e-3) and back.torque == pytest.approx(3.0, abs=0.04)
    data = pack_reply(AK10_9, 1, 0.5, -1.0, 2.0)
    ours, theirs = unpack_reply(AK10_9_V11, data), unpack_reply(AK10_9, data)
    assert (ours.position, ours.velocity, ours.torque) == (-theirs.position, -theirs.velocity, -theirs.torque)
    assert unpack_reply(AK10_9_V11, pack_reply(AK10_9_V11, 1, 0.5, -1.0, 2.0)).position == \
        pytest.approx(0.5, abs=AK10_9.quanta.position)


# ---------------------------------------------------------------------------
# Properties


@settings(max_examples=300, deadline=None)
@given(st.sampled_from(MODELS), FINITE, FINITE, FINITE, FINITE, FINITE)
def test_command_round_trip_is_the_clamped_value_truncated(model: MitModel, p: float, v: float, kp: float,
                                                           kd: float, t: float) -> None:
    back = unpack_command(model, pack_command(model, Command(p, v, kp, kd, t)))
    d = model.axis_direction
    for channel, value, got, signed in ((model.position, p, back.position, True),
                                        (model.velocity, v, back.velocity, True), (model.kp, kp, back.kp, False),
                                        (model.kd, kd, back.kd, False), (model.torque, t, back.torque, True)):
        wire = min(max(d * value if signed else value, channel.lo), channel.hi)
        decoded = d * got if signed else got
        slack = 4 * np.spacing(np.float32(max(abs(channel.lo), abs(channel.hi))))  # float32 rounding
        # truncation: the decoded value is at most one step below the wire value, never above
        # (one more step where the special-frame guard lowered the position code)
        extra = channel.step if channel is model.position else 0.0
        assert wire - channel.step - extra - slack <= decoded <= wire + slack


@settings(max_examples=300, deadline=None)
@given(st.sampled_from(MODELS), st.floats(-1.0, 1.0), st.floats(-1.0, 1.0), st.floats(-1.0, 1.0),
       st.integers(0, 15), st.integers(0, 255))
def test_reply_round_trip(model: MitModel, p: float, v: float, t: float, node: int, temp: int) -> None:
    position, velocity, torque = p * model.p_max, v * model.v_max, t * model.t_max
    reply = unpack_reply(model, pack_reply(model, node, position, velocity, torque, temperature=temp))
    assert reply.motor_id == node
    for channel, want, got in ((model.position, position, reply.position), (model.velocity, velocity, reply.velocity),
                               (model.torque, torque, reply.torque)):
        # one code's step, plus the rounding of the firmware's single-precision arithmetic
        # (a few float32 spacings at the range's end: 1e-6 at 12.5 rad, not a fraction of a step)
        rounding = 4 * float(np.spacing(np.float32(max(abs(channel.lo), abs(channel.hi)))))
        assert abs(got - want) <= channel.step + rounding
    if model.layout.temperature:
        assert reply.temperature == temp


@settings(max_examples=500, deadline=None)
@given(st.sampled_from(MODELS), FINITE)
def test_torque_frame_fill_is_pack_command(model: MitModel, tau: float) -> None:
    frame = TorqueFrame(model)
    data = bytearray(frame.template)
    frame.fill(data, tau)
    assert bytes(data) == pack_command(model, Command(0.0, 0.0, 0.0, 0.0, tau))


def test_torque_frame_fill_writes_only_the_torque_bits() -> None:
    frame = TorqueFrame(AK80_9)
    data = bytearray(b"\xaa" * 8)
    frame.fill(data, 1.0)  # code 0x871
    assert data == bytearray(b"\xaa" * 6 + b"\xa8\x71")


@pytest.mark.parametrize("model", [AK80_9, AK10_9_V11, DM4310, CHEETAH], ids=lambda m: m.name)
def test_torque_frame_at_every_code_boundary(model: MitModel) -> None:
    """At, just below and just above every threshold of the table, the hot path gives the
    firmware formula's code (both axis directions)."""
    frame = TorqueFrame(model)
    data = bytearray(frame.template)
    for threshold in model.torque.thresholds:
        for x in (threshold, math.nextafter(threshold, -math.inf), math.nextafter(threshold, math.inf)):
            for tau in (x, -x):
                frame.fill(data, tau)
                assert (data[6] & 0xF) << 8 | data[7] == model.torque.reference_encode(model.axis_direction * tau)


#: every distinct field range of the table (many rows share one: p_max 12.5, kp, kd)
CHANNELS = sorted({c for m in MODELS for c in (m.position, m.velocity, m.kp, m.kd, m.torque)},
                  key=lambda c: (c.bits, c.lo, c.hi))


@pytest.mark.parametrize("channel", CHANNELS, ids=lambda c: f"{c.bits}bit[{c.lo:g},{c.hi:g}]")
def test_the_tables_are_the_firmware_formula(channel: Channel) -> None:
    """Channel.encode / decode (tables) agree with the formula computed one float32
    operation at a time: every code of the 12-bit fields, sampled 16-bit ones, random values
    and the neighbours of each threshold."""
    rng = random.Random(18)
    codes = range(channel.mask + 1) if channel.bits <= 12 else rng.sample(range(channel.mask + 1), 3000)
    for u in codes:
        assert channel.decode(u) == channel.reference_decode(u) == uint_to_float(u, channel.lo, channel.hi,
                                                                                  channel.bits)
    thresholds = channel.thresholds if channel.bits <= 12 else rng.sample(channel.thresholds, 3000)
    for t in thresholds:
        for x in (t, math.nextafter(t, -math.inf)):
            assert channel.encode(x) == channel.reference_encode(x) == f32_firmware(x, channel.lo, channel.hi,
                                                                                     channel.bits)
    for _ in range(2000):
        x = rng.uniform(channel.lo - 1, channel.hi + 1)
        assert channel.encode(x) == channel.reference_encode(x)


@given(st.integers(0, 4095))
def test_a_decoded_code_encodes_to_itself_or_one_below(u: int) -> None:
    """Decoding then encoding a code gives it back, or one less where the float32 value of
    the code lies a rounding below the boundary (the firmware's truncation)."""
    for channel in (AK80_9.velocity, AK80_9.torque, AK80_9.kp, DM4310.torque):
        assert channel.encode(channel.decode(u)) in (u, u - 1 if u else 0)


def test_single_precision_changes_codes() -> None:
    """The decision documented in the codec: the firmware's single precision and a double-
    precision formula (the Python clients') give different codes near code boundaries, and
    different decoded values. Counted over random AK80-9 positions and at the boundaries."""
    rng = random.Random(7)
    channel = AK80_9.position

    def double(x: float) -> int:
        return int((x + 12.5) * 65535 / 25.0)

    xs = [rng.uniform(-12.5, 12.5) for _ in range(20000)]
    differ = [x for x in xs if channel.encode(x) != double(x)]
    assert 0 < len(differ) < len(xs) / 50  # rare (about 1 in 600), but there
    for x in differ:
        assert abs(channel.encode(x) - double(x)) == 1  # never more than one code apart
    # every threshold's own double value: single precision moves some boundaries
    moved = sum(channel.encode(t) != double(t) for t in channel.thresholds)
    assert moved > 0
    # decoded values: the zero-torque code of an AK80-9
    assert uint_to_float(2047, -18.0, 18.0, 12) != 2047 * 36 / 4095 - 18
    assert uint_to_float(2047, -18.0, 18.0, 12) == pytest.approx(2047 * 36 / 4095 - 18, abs=2e-6)


def test_models_replies_and_commands_are_hashable_values() -> None:
    assert len({*MODELS, *MODELS}) == len(MODELS) and {AK80_9: 1}[find_model("cubemars", "AK80-9", "manual-1.0.8")]
    data = pack_reply(AK80_9, 1, 0.5, 1.0, -2.0)
    assert hash(unpack_reply(AK80_9, data)) == hash(unpack_reply(AK80_9, bytearray(data)))
    assert unpack_reply(AK80_9, data) == unpack_reply(AK80_9, bytearray(data))
    assert hash(Command(1, 2, 3, 4, 5)) == hash(Command(1, 2, 3, 4, 5))


def test_quanta_and_the_generic_functions() -> None:
    q = AK80_9.quanta
    assert q.position == pytest.approx(25 / 65535) and q.position == pytest.approx(0.38e-3, abs=0.01e-3)
    assert q.velocity == pytest.approx(0.0244, abs=1e-4) and q.torque == pytest.approx(0.0088, abs=1e-4)
    assert DM4310.quanta.velocity == pytest.approx(0.0147, abs=1e-4)
    assert DM4310.quanta.torque == pytest.approx(0.0049, abs=1e-4)
    with pytest.raises(CodecError, match="expected finite lo < hi"):
        float_to_uint(0.0, 1.0, 1.0, 12)
    with pytest.raises(CodecError, match="bits 25"):
        float_to_uint(0.0, -1.0, 1.0, 25)
    assert Channel(-1.0, 1.0, 8).encode(0.0) == 127


@given(st.binary(min_size=8, max_size=8))
def test_any_command_bytes_decode_within_range(data: bytes) -> None:
    assume(is_special(data) is None)
    cmd = unpack_command(AK80_9, data)
    assert -12.5 <= cmd.position <= 12.5 and 0.0 <= cmd.kp <= 500.0 and -18.0 <= cmd.torque <= 18.0
    again = pack_command(AK80_9, cmd)
    # a decoded command re-encodes to the same bytes, or a code one below (float32 truncation)
    for a, b in zip(_fields(again), _fields(data)):
        assert b - 1 <= a <= b


def _fields(data: bytes) -> tuple[int, ...]:
    return ((data[0] << 8) | data[1], (data[2] << 4) | (data[3] >> 4), ((data[3] & 0xF) << 8) | data[4],
            (data[5] << 4) | (data[6] >> 4), ((data[6] & 0xF) << 8) | data[7])
