"""The emulated MIT motor in lockstep, frame by frame: literal bytes of the MIT protocol
(the reference firmware, github.com/bgkatz/motorcontrol: the special frames, the 16/12-bit packing, its
``int((x - min) * (2^bits - 1) / (max - min))``, reply layouts), worked out by hand here,
not by the codec under test; the timing of replies and torque in simulated time; the
firmware's command timeout; set zero and its silence; the thermal and over-current faults."""

from __future__ import annotations

import dataclasses
import struct
from collections.abc import Iterator

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from dobhil.drives.mit.codec import unpack_reply
from dobhil.drives.mit.rules import model_of
from dobhil.drives.mit.emulator import EmulatedMit, Fault, Thermal
from dobhil.emulator.plant import Plant

from .mit_rig import AK80_9, DAMIAO, MINI_CHEETAH, Lockstep, mit_profile

ENTER = bytes.fromhex("FFFFFFFFFFFFFFFC")
EXIT = bytes.fromhex("FFFFFFFFFFFFFFFD")
ZERO = bytes.fromhex("FFFFFFFFFFFFFFFE")
CLEAR = bytes.fromhex("FFFFFFFFFFFFFFFB")
# AK80-9 (P 12.5, V 50, T 18, Kp 500, Kd 5): p = v = kp = kd = 0, t_ff = 1 N m.
# p: int(12.5 * 65535 / 25) = 32767 = 0x7FFF; v: int(50 * 4095 / 100) = 2047 = 0x7FF;
# t: int(19 * 4095 / 36) = int(2161.25) = 2161 = 0x871 -> bytes 6, 7 = 0x08, 0x71
AK_ONE_NM = bytes.fromhex("7FFF7FF000000871")


def f32_decode(code: int, lo: float, hi: float, bits: int) -> float:
    """The firmware's uint_to_float in single precision, in its order (math_ops.c)."""
    f = np.float32
    return float(f(f(code) * f(f(hi) - f(lo)) / f((1 << bits) - 1)) + f(lo))


AK_ONE_NM_DECODED = f32_decode(2161, -18, 18, 12)    # 0.99780 N m: what the motor applies
# t_ff = 0: int(18 * 4095 / 36) = 2047 -> decodes to -0.0044 N m (zero is not a code)
AK_ZERO_DECODED = f32_decode(2047, -18, 18, 12)
AK_ZERO_TORQUE = bytes.fromhex("7FFF7FF0000007FF")
# kp = 500 (code 4095), p_des = 1 rad: int(13.5 * 65535 / 25) = 35388 = 0x8A3C; t_ff 0
AK_STIFF_1RAD = bytes.fromhex("8A3C7FFFFF0007FF")
# reply of node 1 at q = dq = 0, torque 0, 25 degC, no error (CubeMars 8 bytes)
AK_REPLY_AT_REST = bytes.fromhex("017FFF7FF7FF1900")


@pytest.fixture
def ak() -> Iterator[Lockstep]:
    rig = Lockstep(AK80_9)
    try:
        yield rig
    finally:
        rig.close()


@pytest.fixture
def dm() -> Iterator[Lockstep]:
    rig = Lockstep(DAMIAO)
    try:
        yield rig
    finally:
        rig.close()


# -- frames ----------------------------------------------------------------------------

def test_every_frame_to_the_node_is_answered_with_the_literal_reply(ak: Lockstep) -> None:
    # (no command applied before each: the torque field is 0; a reply after a command
    # carries the applied torque re-encoded, whose code the codec's tests own)
    for frame in (AK_ZERO_TORQUE, ENTER, EXIT, ZERO[:7] + b"\xfd", ENTER):
        assert ak.ask(frame) == [AK_REPLY_AT_REST]
    assert ak.emu.replies == 5 and ak.emu.frame_errors == 0 and ak.emu.protocol_state == 1


def test_a_pure_torque_command_is_applied_in_motor_mode_only(ak: Lockstep) -> None:
    ak.ask(AK_ONE_NM)                       # at rest: answered, not applied
    ak.read(0.002)
    assert ak.emu.applied_torque == 0.0 and ak.plant.motor_torque == 0.0
    ak.ask(ENTER)
    assert ak.emu.applied_torque == 0.0     # entering does not reuse the command before
    ak.ask(AK_ONE_NM)
    assert ak.emu.applied_torque == AK_ONE_NM_DECODED
    ak.read(0.001)
    assert ak.plant.motor_torque == AK_ONE_NM_DECODED
    ak.ask(EXIT)
    assert ak.emu.applied_torque == 0.0 and ak.emu.protocol_state == 0


def test_a_cubemars_motor_applies_its_last_command_again_at_the_next_enter(ak: Lockstep) -> None:
    """The users' "initial kick" (canmotorlib's enable/disable comments): the command
    survives exit and enter on a CubeMars; a Damiao starts from zero."""
    ak.ask(ENTER)
    ak.ask(AK_ONE_NM)
    ak.ask(EXIT)
    assert ak.emu.applied_torque == 0.0
    ak.read(0.01)
    ak.ask(ENTER)
    assert ak.emu.applied_torque == AK_ONE_NM_DECODED
    ak.ask(AK_ZERO_TORQUE)                  # what a safe stop sends before the exit
    ak.ask(EXIT)
    ak.ask(ENTER)
    assert ak.emu.applied_torque == AK_ZERO_DECODED


def test_a_damiao_motor_starts_from_zero_at_each_enter(dm: Lockstep) -> None:
    dm.ask(ENTER)
    dm.ask(AK_ONE_NM)
    assert dm.emu.applied_torque != 0.0
    dm.ask(EXIT)
    dm.ask(ENTER)
    assert dm.emu.applied_torque == 0.0


def test_zero_torque_is_the_codes_bias(ak: Lockstep) -> None:
    ak.ask(ENTER)
    ak.ask(AK_ZERO_TORQUE)
    assert ak.emu.applied_torque == AK_ZERO_DECODED == pytest.approx(-0.0044, abs=1e-4)


def test_the_reply_carries_the_state_at_the_instant_the_frame_applies(ak: Lockstep) -> None:
    """Lockstep, latency 0: the reply to a command sent at t carries the torque applied up
    to t (the old command's) and the position of t; the new torque acts from t on."""
    ak.ask(ENTER)
    ak.ask(AK_ONE_NM)
    ak.read(0.010)                                     # 10 ms of 0.9978 N m
    position, velocity = ak.plant.position, ak.plant.velocity
    [reply] = ak.ask(AK_ZERO_TORQUE)
    decoded = unpack_reply(ak.emu.model, reply)
    q = ak.emu.model.quanta
    assert abs(decoded.torque - AK_ONE_NM_DECODED) <= q.torque
    assert abs(decoded.position - position) <= q.position and abs(decoded.velocity - velocity) <= q.velocity
    assert velocity == pytest.approx(AK_ONE_NM_DECODED * 0.010 / 0.01, rel=1e-3)   # J = 0.01
    assert ak.emu.applied_torque == AK_ZERO_DECODED


def test_frames_not_for_the_node_are_not_answered(ak: Lockstep) -> None:
    assert ak.ask(ENTER, can_id=2) == []
    assert ak.ask(ENTER[:7]) == [] and ak.emu.frames_rejected == 1   # wrong length
    ak.send(ENTER, is_remote_frame=False, dlc=8)
    assert len(ak.read()) == 1 and ak.emu.protocol_state == 1


def test_damiao_state_nibble_and_temperatures(dm: Lockstep) -> None:
    # byte 0: state << 4 | id (rest 0, motor 1); bytes 6, 7: MOS and rotor at 25 degC
    assert dm.ask(AK_ZERO_TORQUE) == [bytes.fromhex("017FFF7FF7FF1919")]
    assert dm.ask(ENTER) == [bytes.fromhex("117FFF7FF7FF1919")]
    assert dm.ask(EXIT) == [bytes.fromhex("017FFF7FF7FF1919")]


def test_damiao_register_reads_give_the_rows_ranges(dm: Lockstep) -> None:
    """damiao-motor's register read (0x7FF: id_l id_h 0x33 rid), answered on the master id."""
    for rid, value in ((21, 12.5), (22, 30.0), (23, 10.0)):
        frame = bytes([1, 0, 0x33, rid, 0, 0, 0, 0])
        dm.send(frame, 0x7FF)
        [(_, can_id, data)] = dm.read()
        assert can_id == 0 and data[:4] == frame[:4] and struct.unpack("<f", data[4:])[0] == value


# -- timeout, zero ---------------------------------------------------------------------

@pytest.fixture
def timed() -> Iterator[Lockstep]:
    """An AK80-9 with the reference firmware's 25 ms command timeout (the table's AK80-9
    row has none: CubeMars documents none; the Mini-Cheetah row has this one)."""
    rig = Lockstep(AK80_9)
    rig.close()
    rig = Lockstep(AK80_9, model=dataclasses.replace(rig.emu.model, command_timeout=0.025))
    try:
        yield rig
    finally:
        rig.close()


def test_the_command_timeout_zeroes_kp_kd_and_torque(timed: Lockstep) -> None:
    ak = timed
    timeout = ak.emu.model.command_timeout
    assert timeout == 0.025
    ak.ask(ENTER)
    ak.ask(AK_ONE_NM)
    ak.read(timeout - 0.002)
    assert ak.emu.applied_torque == pytest.approx(AK_ONE_NM_DECODED) and not ak.emu.watchdog_tripped
    ak.read(0.003)
    assert ak.emu.applied_torque == 0.0 and ak.emu.watchdog_tripped
    assert ak.emu.protocol_state == 1                     # still in motor mode: a command resumes
    ak.ask(AK_ONE_NM)
    assert ak.emu.applied_torque == pytest.approx(AK_ONE_NM_DECODED)


def test_any_frame_to_the_node_feeds_the_timeout(timed: Lockstep) -> None:
    ak = timed
    timeout = ak.emu.model.command_timeout
    assert timeout is not None
    ak.ask(ENTER)
    ak.ask(AK_ONE_NM)
    for _ in range(5):
        ak.read(timeout * 0.8)
        ak.ask(ENTER)                                 # not a command, but to the node
    assert ak.emu.applied_torque == pytest.approx(AK_ONE_NM_DECODED)


def test_the_mini_cheetah_rows_timeout_and_bus_voltage() -> None:
    """The Mini-Cheetah firmware (motorcontrol): 25 ms timeout; 7-byte reply, byte 6 the bus
    voltage as float_to_uint(24, 0, 40, 8) = int(24 * 255 / 40) = 153."""
    rig = Lockstep(MINI_CHEETAH)
    try:
        assert rig.emu.model.command_timeout == 0.025
        [reply] = rig.ask(ENTER)
        assert len(reply) == 7 and reply[0] == 1 and reply[6] == 153
        rig.ask(AK_ONE_NM)                            # t code 2161 of +-40 N m: 2.2 N m
        assert rig.emu.applied_torque == f32_decode(2161, -40, 40, 12)
        rig.read(0.030)
        assert rig.emu.applied_torque == 0.0 and rig.emu.watchdog_tripped and rig.emu.protocol_state == 1
    finally:
        rig.close()


def test_damiao_timeout_is_lost_communication(dm: Lockstep) -> None:
    rig = Lockstep(DAMIAO, model=dataclasses.replace(dm.emu.model, command_timeout=0.01))
    try:
        rig.ask(ENTER)
        rig.read(0.02)
        assert rig.emu.protocol_state == 0 and rig.emu.watchdog_tripped
        [reply] = rig.ask(AK_ZERO_TORQUE)
        assert reply[0] == 0xD1 and rig.emu.protocol_error == 0xD
        assert rig.ask(ENTER)[0][0] == 0xD1           # refused until cleared
        assert rig.ask(CLEAR)[0][0] == 0x01 and rig.ask(ENTER)[0][0] == 0x11
    finally:
        rig.close()


def test_set_zero_makes_the_motor_silent_then_reads_zero() -> None:
    rig = Lockstep(AK80_9, plant=Plant(inertia=0.01, initial_position=0.3),
                   profile=mit_profile(AK80_9, zero_silence=0.05))
    try:
        [before] = rig.ask(AK_ZERO_TORQUE)
        assert unpack_reply(rig.emu.model, before).position == pytest.approx(0.3, abs=4e-4)
        assert rig.ask(ZERO) == []
        rig.read(0.045)
        assert rig.ask(ENTER) == [] and rig.emu.protocol_state == 0 and rig.emu.frames_ignored == 1
        rig.read(0.006)
        [after] = rig.ask(AK_ZERO_TORQUE)
        assert after == AK_REPLY_AT_REST              # position 0 (code 0x7FFF), at rest
    finally:
        rig.close()


# -- faults ----------------------------------------------------------------------------

FAST = Thermal(time_constant=0.05)   # the winding in 50 ms, so a test heats it in simulated ms


def test_over_temperature_stops_the_motor_with_its_code() -> None:
    """At 1 N m of 18 the steady state is 25 + 250/324 K: no fault; at t_max it is 275 degC,
    above the 100 degC limit: the fault, the reply's error byte 1, torque off."""
    full = bytes.fromhex("7FFF7FF000000FFF")         # t_ff = +18 N m (code 4095)
    rig = Lockstep(AK80_9, thermal=FAST, plant=Plant(inertia=10.0))
    try:
        rig.ask(ENTER)
        rig.ask(AK_ONE_NM)
        rig.read(0.02)
        assert rig.emu.fault == "" and rig.emu.temperature < 27
        rig.ask(full)
        for _ in range(100):
            rig.read(0.001)
            rig.ask(full)                             # keep commanding (no timeout)
            if rig.emu.fault:
                break
        assert rig.emu.fault == Fault.OVER_TEMPERATURE and rig.emu.protocol_state == 0
        assert rig.emu.applied_torque == 0.0
        [reply] = rig.ask(full)
        assert reply[7] == 1 and reply[6] >= 100      # error 1, temperature byte
        assert rig.ask(ENTER)[0][7] == 1 and rig.emu.protocol_state == 0   # refused while hot
        rig.read(0.2)                                 # cools towards 25 degC
        assert rig.ask(ENTER)[0][7] == 0 and rig.emu.protocol_state == 1
    finally:
        rig.close()


def test_over_current_when_the_torque_law_demands_far_beyond_t_max(ak: Lockstep) -> None:
    ak.ask(ENTER)
    [reply] = ak.ask(AK_STIFF_1RAD)                   # 500 N m/rad * 1 rad >> 1.5 * 18 N m
    assert reply[7] == 2 and ak.emu.fault == Fault.OVER_CURRENT and ak.emu.protocol_state == 0


def test_a_stiff_command_within_range_holds_the_clamped_torque() -> None:
    # kp = 500 * 0.0244 = 12.2 N m/rad (code 100), p_des = 1 rad: 12.2 N m < 27: no fault
    frame = bytes([0x8A, 0x3C, 0x7F, 0xF0, 100, 0x00, 0x07, 0xFF])
    rig = Lockstep(AK80_9)
    try:
        rig.ask(ENTER)
        rig.ask(frame)
        kp, p = f32_decode(100, 0, 500, 12), f32_decode(35388, -12.5, 12.5, 16)
        assert rig.emu.applied_torque == pytest.approx(kp * p + AK_ZERO_DECODED, rel=1e-12)
        assert rig.emu.fault == ""
    finally:
        rig.close()


def test_every_emulated_class_is_found_by_the_registry() -> None:
    from dobhil.drives.registry import emulator_class
    assert emulator_class("mit") is EmulatedMit


# -- any frame -------------------------------------------------------------------------

_FRAMES = st.lists(st.tuples(st.sampled_from([1, 1, 1, 2, 0, 0x7FF, 0x101]), st.binary(min_size=0, max_size=8),
                             st.booleans()), min_size=1, max_size=30)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(frames=_FRAMES, row=st.sampled_from([AK80_9, DAMIAO, MINI_CHEETAH]))
def test_any_frame_is_answered_once_or_not_at_all_and_never_breaks_it(
        frames: list[tuple[int, bytes, bool]], row: tuple[str, str, str]) -> None:
    """Whatever arrives (ids, lengths, bytes; a set zero among them makes it silent): no
    frame raises inside the emulator, an 8-byte data frame to the node gets exactly one
    reply of the layout's length unless the motor is silent, nothing else gets one (a
    Damiao's register read on 0x7FF aside), and the torque stays within +-t_max."""
    rig = Lockstep(row, thermal=FAST)
    try:
        model = rig.emu.model
        for can_id, data, step in frames:
            silent = rig.emu.time < rig.emu.silent_until - 1e-9
            rig.send(data, can_id)
            replies = rig.read()
            to_node = can_id == rig.node and len(data) == 8 and not silent
            register = can_id == 0x7FF and bool(model.layout.state_field)
            if to_node:
                assert len(replies) == 1 and len(replies[0][2]) == model.layout.length
            elif not register:
                assert replies == []
            assert abs(rig.emu.applied_torque) <= model.t_max
            if step:
                rig.read(0.001)
        assert rig.emu.frame_errors == 0, rig.emu.last_frame_error
    finally:
        rig.close()


def test_damiao_faults_are_state_nibbles_cleared_by_clear_error() -> None:
    """Damiao: over current is state 10 (0xA), rotor over temperature 12 (0xC), the table's
    codes; enter is refused until clear error (0xFB), which works once the cause is gone."""
    rig = Lockstep(DAMIAO, thermal=FAST, plant=Plant(inertia=10.0))
    try:
        rig.ask(ENTER)
        [reply] = rig.ask(AK_STIFF_1RAD)              # kp 500 x 1 rad >> 1.5 x 10 N m
        assert reply[0] == 0xA1 and rig.emu.protocol_state == 0
        assert rig.ask(ENTER)[0][0] == 0xA1           # refused
        assert rig.ask(CLEAR)[0][0] == 0x01 and rig.ask(ENTER)[0][0] == 0x11
        full = bytes.fromhex("7FFF7FF000000FFF")      # t_ff = +10 N m (code 4095)
        for _ in range(200):
            rig.ask(full)
            rig.read(0.001)
            if rig.emu.fault:
                break
        [reply] = rig.ask(full)
        assert reply[0] == 0xC1 and reply[7] >= 100 and rig.emu.applied_torque == 0.0
        assert rig.ask(CLEAR)[0][0] == 0xC1           # still hot: the cause is not gone
        rig.read(0.2)
        assert rig.ask(CLEAR)[0][0] == 0x01 and rig.ask(ENTER)[0][0] == 0x11
    finally:
        rig.close()


def test_a_position_past_p_max_wraps_as_the_firmwares_16_bit_field() -> None:
    """12.6 rad on an AK80-9 (P 12.5): int(25.1 * 65535 / 25) = 65797, past 2^16: the
    field holds 65797 - 65536 = 261 = 0x0105 (the firmware's int arithmetic rolls over)."""
    rig = Lockstep(AK80_9, plant=Plant(inertia=0.01, initial_position=12.6))
    try:
        [reply] = rig.ask(AK_ZERO_TORQUE)
        assert reply[1:3] == bytes([0x01, 0x05])
        assert unpack_reply(rig.emu.model, reply).position == pytest.approx(12.6 - 2 * 12.5, abs=1e-3)
    finally:
        rig.close()


def test_a_prepared_motor_builds_nothing_at_its_first_frame(monkeypatch: pytest.MonkeyPatch) -> None:
    """The code tables are built by ``prepare()`` (``start()`` calls it), not at the first
    frame: built there they cost tens of ms on a host and most of a second in a slow guest,
    where a host gave up waiting for the first reply and refused to enable."""
    from dobhil.drives.mit import codec
    codec._channel.cache_clear()   # fresh channels: tables built earlier by other tests are gone
    builds: list[object] = []
    real = codec._thresholds

    def counting(channel: codec.Channel) -> tuple[float, ...]:
        builds.append(channel)
        return real(channel)

    monkeypatch.setattr(codec, "_thresholds", counting)
    profile = mit_profile(AK80_9)
    # a model of its own: the table's rows are cached, their channels built by earlier tests
    model = dataclasses.replace(model_of(profile))
    rig = Lockstep(AK80_9, profile=profile, model=model)
    try:
        rig.emu.prepare()
        prepared = len(builds)
        rig.send(bytes.fromhex("7FFF7FF000000800"))   # a zero-torque command (kp = kd = 0)
        assert len(rig.read(0.01)) == 1
        assert prepared == 5 and len(builds) == prepared   # all five fields, nothing more later
    finally:
        rig.close()
