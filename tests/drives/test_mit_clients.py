"""dobhil's MIT codec (:mod:`dobhil.drives.mit.codec`, rows of ``drivers/mit-models.yaml``)
against the published client of each vendor family, used as its code shows
(:mod:`tests.drives.mit_clients`): ``damiao-motor`` for the Damiao rows, ``tmotorcancontrol``
for the CubeMars AK rows, ``mini-cheetah-motor-driver-socketcan`` (canmotorlib) for the AK
firmware variants of its tables. Thousands of hypothesis inputs per row (fixed seed): random
values inside and far outside each range, the range ends and their neighbouring doubles,
every code boundary; every reply code exhaustively.

The reference is the firmware's formula (bgkatz/motorcontrol ``math_ops.c``, copied by the
CubeMars and Damiao firmware), here in exact rational arithmetic (:func:`firmware_code`):
clamp to ``[lo, hi]``, ``floor((x - lo) (2^n - 1) / (hi - lo))``. dobhil computes it in single
precision as the firmware does; damiao-motor and canmotorlib in double. Where each differs
from the reference, and so from dobhil -- each shown exactly below:

- damiao-motor, canmotorlib and dobhil: a different code only within ``(2^n - 1) 2^-21``
  of a code boundary (single against double rounding), and then by one
  (:func:`assert_firmware_code`); in the middle of every code's interval all three give
  that code;
- tmotorcancontrol 1.2.6 does not use the firmware's formula: it scales by ``2^n / span``
  and clamps to ``x_max - 2 span / 2^n``. Below that clamp its code is the firmware's or
  one above -- one above in the middle of every code's interval of the upper half of the
  range, exactly -- and from there up it stays at ``2^n - 2``, never the firmware's top
  code. 0 N m is 2048 on an AK80-9 where the firmware's is 2047, 18 N m is 4094 where the
  firmware's is 4095 (:func:`tmotor_code`, ``test_tmotor_commands_differ_exactly_by_its_formula``,
  ``test_in_the_middle_of_every_code_the_clients_agree_but_tmotorcancontrol``);
- canmotorlib's module ``float_to_uint`` does not clamp (its controller clips before it):
  beyond the range its code leaves 0 .. 2^n - 1 (bitstring then refuses to pack it);
- a NaN: dobhil refuses it (CodecError); damiao-motor and tmotorcancontrol fail with a
  ValueError from ``int(nan)``; canmotorlib's clipping turns a NaN position, velocity or
  gain into the range's low end and sends it;
- the one command that spells a special frame (every field at its top, torque code 0xFFB ..
  0xFFE): damiao-motor and canmotorlib send it, so the motor would enter, exit, zero or
  clear; dobhil lowers the position code by one.

Replies decode to the same raw codes bit for bit; the values differ only by single
against double rounding (a few single-precision steps at the range's end).
"""

from __future__ import annotations

import functools
import inspect
import math
import re
from fractions import Fraction

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from dobhil.drives.mit import codec
from dobhil.drives.mit.codec import Command, MitModel, Special, TorqueFrame
from dobhil.drives.mit.models import find_model, load_models
from dobhil.errors import CodecError

from . import mit_clients as clients
from .mit_clients import Ranges

#: inputs per row and test (fixed seed, no example database: the same inputs every run); a
#: command is five values, so a row's command tests check thousands of values
MANY = settings(max_examples=400, derandomize=True, deadline=None, database=None,
                suppress_health_check=[HealthCheck.too_slow])
SCALAR = settings(MANY, max_examples=200)   # per range, over the 27 ranges of the table
REPLIES = settings(MANY, max_examples=250)  # the raw codes; every code's value: exhaustively

POSITION_BITS, FIELD_BITS = 16, 12

# -- the rows each client has -------------------------------------------------------
# (vendor, model, firmware) of drivers/mit-models.yaml -> the client's name for that motor

_MANUAL, _FACTORY = "manual-1.0.8", "factory"

#: damiao-motor's MOTOR_TYPE_PRESETS
DAMIAO_ROWS: dict[tuple[str, str, str], str] = {
    ("damiao", f"DM{name}", _FACTORY): name for name in ("4310", "4310P", "4340", "6006", "8006", "8009", "10010L")}
#: tmotorcancontrol's MIT_Params: the current firmware's ranges (CubeMars manual V1.0.8)
TMOTOR_ROWS: dict[tuple[str, str, str], str] = {
    ("cubemars", name, _MANUAL): name for name in ("AK80-9", "AK70-10", "AK10-9", "AK80-6", "AK60-6", "AK80-64")}
#: canmotorlib's firmware tables (its names: <model>_V<version>)
CANMOTORLIB_ROWS: dict[tuple[str, str, str], str] = {
    ("cubemars", "AK80-9", "2.0"): "AK80_9_V2", ("cubemars", "AK80-9", "1.1"): "AK80_9_V1p1",
    ("cubemars", "AK70-10", "1.1"): "AK70_10_V1p1", ("cubemars", "AK10-9", "1.1"): "AK10_9_V1p1",
    ("cubemars", "AK80-6", "2.0"): "AK80_6_V2", ("cubemars", "AK80-6", "1.1"): "AK80_6_V1p1",
    ("cubemars", "AK80-6", "1.0"): "AK80_6_V1",
    # the manual's AK80-6 is canmotorlib's V2 (same ranges, direction and all)
    ("cubemars", "AK80-6", _MANUAL): "AK80_6_V2",
}

#: where a row's ranges are not its client's: (client, client's row, key) -> (dobhil's, client's).
#: AK60-6: the CubeMars manual V1.0.8 (p. 50) says V +-45 rad/s, tmotorcancontrol 50; the
#: table follows the vendor.
RANGE_DIFFERENCES: dict[tuple[str, str, str], tuple[float, float]] = {
    ("tmotorcancontrol", "AK60-6", "v_max"): (45.0, 50.0),
}
#: damiao-motor's presets that dobhil's table has no row for (a user adds one: drivers/README.md)
DAMIAO_NOT_IN_TABLE = frozenset({"3507", "4340P", "10010", "H3510", "G6215", "H6220", "JH11", "6248P"})


def model(key: tuple[str, str, str]) -> MitModel:
    return find_model(*key)


# -- the firmware's formula in exact arithmetic ----------------------------------------

def scaled(x: float, lo: float, hi: float, bits: int) -> Fraction:
    """``(clamp(x) - lo) (2^n - 1) / (hi - lo)``, exactly (a double is a rational)."""
    xc = min(max(Fraction(x), Fraction(lo)), Fraction(hi))
    return (xc - Fraction(lo)) * ((1 << bits) - 1) / (Fraction(hi) - Fraction(lo))


def firmware_code(x: float, lo: float, hi: float, bits: int) -> int:
    """``math_ops.c``'s ``float_to_uint`` after its callers' clamp, without rounding."""
    return math.floor(scaled(x, lo, hi, bits))


def near_boundary(exact: Fraction, bits: int) -> bool:
    """Within single-precision rounding of an integer: ``(2^n - 1) 2^-21`` codes bounds the
    error of ``fl(fl(fl(x) - lo) (2^n - 1)) / span`` (three roundings of at most 2^-24
    relative each, plus the input's own, |x| and |lo| <= span), with margin."""
    tolerance = Fraction((1 << bits) - 1, 1 << 21)
    return abs(exact - round(exact)) <= tolerance


def assert_firmware_code(code: int, x: float, lo: float, hi: float, bits: int, who: str) -> None:
    """``code`` is the firmware's code of ``x``, or one off within rounding of a boundary."""
    exact = scaled(x, lo, hi, bits)
    expected = math.floor(exact)
    if code != expected:
        assert near_boundary(exact, bits) and abs(code - expected) == 1, (
            f"{who}: code {code} of {x!r} in [{lo}, {hi}] ({bits} bits); the firmware's is {expected} "
            f"(exactly {float(exact)!r}, not at a code boundary)")


def tmotor_scaled(x: float, lo: float, hi: float, bits: int) -> Fraction:
    """tmotorcancontrol's ``float_to_uint`` before its ``int()``, exactly: x clamped to
    ``[lo, hi - 2 span / 2^n]``, times ``2^n / span`` (its final clamp to ``[0, 2^n]``
    never acts)."""
    span = Fraction(hi) - Fraction(lo)
    top = Fraction(hi) - 2 * span / (1 << bits)
    xc = min(max(Fraction(x), Fraction(lo)), top)
    return (xc - Fraction(lo)) * (1 << bits) / span


def tmotor_code(x: float, lo: float, hi: float, bits: int) -> int:
    return math.floor(tmotor_scaled(x, lo, hi, bits))


# -- inputs ---------------------------------------------------------------------------

def values(lo: float, hi: float, bits: int) -> st.SearchStrategy[float]:
    """Inside the range, up to a span beyond it (clamping), the ends and their neighbours,
    huge values, and the code boundaries themselves (where rounding decides)."""
    span, steps = hi - lo, (1 << bits) - 1
    edges = [lo, hi, 0.0, -0.0, math.nextafter(lo, -math.inf), math.nextafter(lo, math.inf),
             math.nextafter(hi, -math.inf), math.nextafter(hi, math.inf), lo - 1e9, hi + 1e9,
             -1e300, 1e300, 5e-324, -5e-324, (lo + hi) / 2]
    return st.one_of(st.floats(lo, hi), st.floats(lo - span, hi + span), st.sampled_from(edges),
                     st.integers(0, steps).map(lambda u: lo + u * span / steps))


def commands(r: Ranges) -> st.SearchStrategy[Command]:
    return st.builds(Command, values(-r.p_max, r.p_max, POSITION_BITS), values(-r.v_max, r.v_max, FIELD_BITS),
                     values(0.0, r.kp_max, FIELD_BITS), values(0.0, r.kd_max, FIELD_BITS),
                     values(-r.t_max, r.t_max, FIELD_BITS))


def fields(data: bytes) -> tuple[int, int, int, int, int]:
    """The codes of an 8-byte command (the reference firmware's layout), p v kp kd t."""
    return ((data[0] << 8) | data[1], (data[2] << 4) | (data[3] >> 4), ((data[3] & 0xF) << 8) | data[4],
            (data[5] << 4) | (data[6] >> 4), ((data[6] & 0xF) << 8) | data[7])


def channels(r: Ranges) -> tuple[tuple[float, float, int], ...]:
    """(lo, hi, bits) of p, v, kp, kd, t."""
    return ((-r.p_max, r.p_max, POSITION_BITS), (-r.v_max, r.v_max, FIELD_BITS), (0.0, r.kp_max, FIELD_BITS),
            (0.0, r.kd_max, FIELD_BITS), (-r.t_max, r.t_max, FIELD_BITS))


def on_the_wire(cmd: Command, direction: int) -> tuple[float, ...]:
    """What the firmware is asked for: position, velocity, torque in its own axis sense."""
    return (direction * cmd.position, direction * cmd.velocity, cmd.kp, cmd.kd, direction * cmd.torque)


def spells_special(codes: tuple[int, ...]) -> bool:
    return codes[:4] == (0xFFFF, 0xFFF, 0xFFF, 0xFFF) and 0xFFB <= codes[4] <= 0xFFE


def ranges_of(row: MitModel) -> Ranges:
    return Ranges(row.p_max, row.v_max, row.t_max, row.kp_max, row.kd_max, row.axis_direction)


def all_channels() -> list[tuple[float, float, int]]:
    """Every distinct (lo, hi, bits) of dobhil's table (the clients' rows it has are checked
    against it in test_the_tables_ranges_are_the_clients_but_where_named)."""
    return sorted({(float(lo), float(hi), bits) for row in load_models().values()
                   for lo, hi, bits in channels(ranges_of(row))})


# ---------------------------------------------------------------------------
# Scaling: float_to_uint and uint_to_float, one range at a time


@pytest.mark.parametrize(("lo", "hi", "bits"), all_channels())
def test_float_to_uint_is_the_firmwares_and_the_clients_differ_where_shown(lo: float, hi: float,
                                                                           bits: int) -> None:
    steps = (1 << bits) - 1

    @SCALAR
    @given(x=values(lo, hi, bits))
    def check(x: float) -> None:
        ours = codec.float_to_uint(x, lo, hi, bits)
        assert_firmware_code(ours, x, lo, hi, bits, "dobhil")
        assert_firmware_code(clients.damiao_float_to_uint(x, lo, hi, bits), x, lo, hi, bits, "damiao-motor")
        # tmotorcancontrol: its own formula (2^n / span, clamped below the top code)
        theirs, exact = clients.tmotor_float_to_uint(x, lo, hi, bits), tmotor_code(x, lo, hi, bits)
        assert theirs == exact or abs(theirs - exact) == 1 and near_boundary(
            tmotor_scaled(x, lo, hi, bits), bits), (x, theirs, exact)
        # canmotorlib's module function: the firmware's formula without the clamp
        unclamped = clients.canmotorlib.float_to_uint(x, lo, hi, bits)
        if lo <= x <= hi:
            assert_firmware_code(unclamped, x, lo, hi, bits, "canmotorlib")
        elif x > hi:
            assert unclamped >= steps and (unclamped > steps or x < hi + (hi - lo) / steps), (x, unclamped)
        else:
            assert unclamped <= 0 and (unclamped < 0 or x > lo - (hi - lo) / steps), (x, unclamped)

    check()


@pytest.mark.parametrize(("lo", "hi", "bits"), all_channels())
def test_every_code_decodes_as_the_clients_within_single_precision(lo: float, hi: float, bits: int) -> None:
    """All 2^n codes: the three clients compute ``u span / (2^n - 1) + lo`` in double, in
    the same order, and agree bit for bit with each other; dobhil computes it in single
    precision, as the firmware: a float32 value within four float32 steps (at the range's
    end) of theirs -- half a step each for lo and hi rounded to float32 (25.64 is not a
    float32), a step each for the product and the quotient (up to twice the range's end),
    half a step for the sum."""
    step32 = 4 * float(np.spacing(np.float32(max(abs(lo), abs(hi)))))
    for u in range(1 << bits):
        ours = codec.uint_to_float(u, lo, hi, bits)
        theirs = clients.damiao_uint_to_float(u, lo, hi, bits)
        assert clients.tmotor_uint_to_float(u, lo, hi, bits) == theirs
        assert clients.canmotorlib.uint_to_float(u, lo, hi, bits) == theirs
        assert float(np.float32(ours)) == ours and abs(ours - theirs) <= step32, (u, ours, theirs)


@pytest.mark.parametrize(("lo", "hi", "bits"), all_channels())
def test_in_the_middle_of_every_code_the_clients_agree_but_tmotorcancontrol(lo: float, hi: float,
                                                                             bits: int) -> None:
    """The exact disagreement set, over every code u: in the middle of its interval
    (``lo + (u + 1/2) span / (2^n - 1)``, far from rounding) dobhil, damiao-motor and
    canmotorlib all give u; tmotorcancontrol gives
    ``floor((u + 1/2) 2^n / (2^n - 1)) = u + 1`` exactly when ``u >= 2^(n-1) - 1``
    (the upper half of the range), capped at its top code 2^n - 2."""
    steps, span = (1 << bits) - 1, hi - lo
    differs = set()
    for u in range(steps):
        x = lo + (u + 0.5) * span / steps
        assert (codec.float_to_uint(x, lo, hi, bits), clients.damiao_float_to_uint(x, lo, hi, bits),
                clients.canmotorlib.float_to_uint(x, lo, hi, bits)) == (u, u, u), x
        theirs = clients.tmotor_float_to_uint(x, lo, hi, bits)
        assert theirs in (u, u + 1), (x, theirs)
        if theirs != u:
            differs.add(u)
    assert differs == set(range((1 << (bits - 1)) - 1, steps - 1))


def test_literal_codes_of_an_ak80_9_where_tmotorcancontrol_differs() -> None:
    """By hand, from the two formulas: 0 N m is (0 + 18) 4095 / 36 = 2047.5 -> 2047 for the
    firmware, (0 + 18) 4096 / 36 = 2048 for tmotorcancontrol; 18 N m is 4095, and 4094 for
    tmotorcancontrol (its clamp at 18 - 2 * 36 / 4096); the position's zero 32767 / 32768."""
    assert [codec.float_to_uint(x, -18.0, 18.0, 12) for x in (-18.0, 0.0, 18.0)] == [0, 2047, 4095]
    assert [clients.tmotor_float_to_uint(x, -18.0, 18.0, 12) for x in (-18.0, 0.0, 18.0)] == [0, 2048, 4094]
    assert codec.float_to_uint(0.0, -12.5, 12.5, 16) == 32767
    assert clients.tmotor_float_to_uint(0.0, -12.5, 12.5, 16) == 32768
    # what each code means to the firmware: 2047 -> -0.0044 N m, 2048 -> +0.0044 N m
    assert codec.uint_to_float(2047, -18.0, 18.0, 12) == pytest.approx(-18 + 2047 * 36 / 4095, abs=1e-6)
    assert codec.uint_to_float(2048, -18.0, 18.0, 12) == pytest.approx(0.0043956, abs=1e-6)


# ---------------------------------------------------------------------------
# Special frames


def test_special_frames_are_the_clients() -> None:
    with clients.damiao_motor("4310") as motor:
        assert motor.encode_enable_msg() == codec.special_frame(Special.ENTER)
        assert motor.encode_disable_msg() == codec.special_frame(Special.EXIT)
        assert motor.encode_save_position_zero_msg() == codec.special_frame(Special.ZERO)
        assert motor.encode_clear_error_msg() == codec.special_frame(Special.CLEAR_ERROR)
    for method, kind in ((clients.CAN_Manager.power_on, Special.ENTER), (clients.CAN_Manager.power_off, Special.EXIT),
                         (clients.CAN_Manager.zero, Special.ZERO)):
        stand_in, _ = clients.tmotor_unbound(method, 7)
        assert stand_in.sent == [(7, codec.special_frame(kind))]
    # canmotorlib's disable: a zero command, then the exit frame (dobhil's safe stop order)
    controller = clients.SocketlessController("AK80_9_V1p1")
    controller.disable_motor()
    assert controller.sent[1:] == [codec.special_frame(Special.EXIT)]
    assert fields(controller.sent[0]) == (32767, 2047, 0, 0, 2047)
    assert all(codec.is_special(codec.special_frame(kind)) is kind for kind in Special)


def test_the_tmotor_stand_in_has_what_the_methods_use() -> None:
    """The workaround of :func:`mit_clients.tmotor_unbound` holds for this release: the
    methods called unbound use nothing of ``self`` but ``debug`` and ``send_MIT_message``."""
    for method in (clients.CAN_Manager.MIT_controller, clients.CAN_Manager.parse_MIT_message,
                   clients.CAN_Manager.power_on, clients.CAN_Manager.power_off, clients.CAN_Manager.zero):
        used = set(re.findall(r"self\.(\w+)", inspect.getsource(method)))
        assert used <= {"debug", "send_MIT_message"}, (method.__name__, used)


def test_no_client_touched_a_real_bus() -> None:
    """After every use above (same process, same modules): tmotorcancontrol's singleton,
    whose creation runs ``sudo ip link``, was never made, and canmotorlib never opened its
    AF_CAN socket (the class-level flags both set when they do)."""
    clients.tmotor_command("AK80-9", 0.0, 0.0, 0.0, 0.0, 0.0)
    clients.canmotorlib_command("AK80_9_V1p1", 0.0, 0.0, 0.0, 0.0, 0.0)
    assert clients.CAN_Manager._instance is None
    assert clients.canmotorlib.CanMotorController.can_socket_declared is False
    assert clients.canmotorlib.CanMotorController.motor_socket is None


# ---------------------------------------------------------------------------
# The model table against the clients' tables


def _differences(client: str, name: str, ours: Ranges,
                 theirs: Ranges) -> dict[tuple[str, str, str], tuple[float, float]]:
    return {(client, name, key): (getattr(ours, key), getattr(theirs, key))
            for key in ("p_max", "v_max", "t_max", "kp_max", "kd_max", "axis_direction")
            if getattr(ours, key) != getattr(theirs, key)}


def test_the_tables_ranges_are_the_clients_but_where_named() -> None:
    """Every row a client also has: the same five ranges and axis direction, except the
    differences named in RANGE_DIFFERENCES (and no other)."""
    found: dict[tuple[str, str, str], tuple[float, float]] = {}
    for rows, client, ranges in ((DAMIAO_ROWS, "damiao-motor", clients.damiao_ranges),
                                 (TMOTOR_ROWS, "tmotorcancontrol", clients.tmotor_ranges),
                                 (CANMOTORLIB_ROWS, "canmotorlib", clients.canmotorlib_ranges)):
        for key, name in rows.items():
            found.update(_differences(client, name, ranges_of(model(key)), ranges(name)))
    assert found == RANGE_DIFFERENCES


def test_every_client_row_has_a_row_in_the_table() -> None:
    """The AK rows of both AK clients are all in the table (tmotorcancontrol's as the
    current firmware, canmotorlib's per firmware version); damiao-motor has presets the table
    has not (named); the table's Damiao rows are all damiao-motor's."""
    assert set(TMOTOR_ROWS.values()) == {name for name in clients.MIT_Params if name != "ERROR_CODES"}
    assert set(CANMOTORLIB_ROWS.values()) == set(clients.CANMOTORLIB_TABLES)
    assert set(clients.MOTOR_TYPE_PRESETS) - set(DAMIAO_ROWS.values()) == DAMIAO_NOT_IN_TABLE
    table = load_models()
    assert {key for key in table if key[0] == "damiao"} == set(DAMIAO_ROWS)
    for key in (*DAMIAO_ROWS, *TMOTOR_ROWS, *CANMOTORLIB_ROWS):
        assert key in table, key


def _words(text: str) -> str:
    return re.sub(r"\s+", " ", text.lower().replace("_", " ").replace(" fault", "")).strip()


def test_reply_codes_are_the_clients() -> None:
    """CubeMars error codes 1-6 are tmotorcancontrol's (the same texts, less its word
    "fault"); the Damiao state nibble's codes are damiao-motor's (0, 1, and the faults 8-14)."""
    cubemars = model(("cubemars", "AK80-9", _MANUAL)).layout
    tm = {code: _words(text) for code, text in clients.MIT_Params["ERROR_CODES"].items() if code}
    assert {code: _words(text) for code, text in cubemars.errors.items()} == tm
    damiao = model(("damiao", "DM4310", _FACTORY)).layout
    assert set(damiao.states) == set(clients.DM_STATES)
    assert damiao.first_error_state == min(code for code in clients.DM_STATES if code > 1)


# ---------------------------------------------------------------------------
# Commands: the 8 bytes each client sends, field by field


def assert_fields_are_the_firmwares(codes: tuple[int, ...], cmd: Command, r: Ranges, who: str) -> None:
    """Every code is the firmware's code of ``cmd``'s field (on the wire's axis), or one
    off within rounding of a code boundary."""
    for code, x, (lo, hi, bits) in zip(codes, on_the_wire(cmd, r.axis_direction), channels(r)):
        assert_firmware_code(code, x, lo, hi, bits, who)


@functools.cache
def _torque_frame(key: tuple[str, str, str]) -> TorqueFrame:
    return TorqueFrame(model(key))


def torque_frame_of(row: MitModel) -> TorqueFrame:
    """One per row (its threshold table is built once)."""
    return _torque_frame(row.key)


def assert_ours(row: MitModel, cmd: Command) -> tuple[int, ...]:
    """dobhil's command: the firmware's codes; where they spell a special frame, the
    position one code lower (the only change). The hot path's TorqueFrame agrees with
    pack_command for the torque alone. Returns the firmware's codes."""
    ours = codec.pack_command(row, cmd)
    assert codec.is_special(ours) is None
    codes = fields(ours)
    if spells_special((codes[0] + 1, *codes[1:])):   # lowered from a special frame
        codes = (codes[0] + 1, *codes[1:])
    assert_fields_are_the_firmwares(codes, cmd, ranges_of(row), "dobhil")
    torque_frame = torque_frame_of(row)
    frame = bytearray(torque_frame.template)
    torque_frame.fill(frame, cmd.torque)
    assert bytes(frame) == codec.pack_command(row, Command(0.0, 0.0, 0.0, 0.0, cmd.torque))
    return codes


@pytest.mark.parametrize("key", list(DAMIAO_ROWS), ids=lambda k: k[1])
def test_damiao_commands_are_the_firmwares_as_dobhils(key: tuple[str, str, str]) -> None:
    """``DaMiaoMotor.encode_cmd_msg(pos, vel, torq, kp, kd)``: the firmware's formula in
    double, clamped; the same bytes as dobhil's but where rounding differs at a code
    boundary (one code) and where the codes spell a special frame (damiao-motor sends it)."""
    row = model(key)
    r = ranges_of(row)
    with clients.damiao_motor(DAMIAO_ROWS[key]) as motor:

        @MANY
        @given(cmd=commands(r))
        def check(cmd: Command) -> None:
            theirs = motor.encode_cmd_msg(cmd.position, cmd.velocity, cmd.torque, cmd.kp, cmd.kd)
            codes = fields(theirs)
            assert_fields_are_the_firmwares(codes, cmd, r, "damiao-motor")
            ours = assert_ours(row, cmd)
            same = ours == codes
            assert same or any(near_boundary(scaled(x, lo, hi, bits), bits) for x, (lo, hi, bits)
                               in zip(on_the_wire(cmd, 1), channels(r))), (cmd, ours, codes)
            assert (codec.pack_command(row, cmd) == theirs) == (same and not spells_special(codes))

        check()


@pytest.mark.parametrize("key", list(TMOTOR_ROWS), ids=lambda k: k[1])
def test_tmotor_commands_differ_exactly_by_its_formula(key: tuple[str, str, str]) -> None:
    """``CAN_Manager.MIT_controller``: each field is tmotorcancontrol's own formula's code
    (2^n / span, clamped to x_max - 2 span / 2^n), which is the firmware's plus 0 or 1
    below that clamp, and 2^n - 2 above it (where the firmware's is 2^n - 3 to 2^n - 1);
    dobhil's is the firmware's. So the two differ exactly where the two formulas do."""
    row = model(key)
    r = ranges_of(row)
    if RANGE_DIFFERENCES.keys() & {("tmotorcancontrol", TMOTOR_ROWS[key], k) for k in ("p_max", "v_max", "t_max")}:
        r_theirs = clients.tmotor_ranges(TMOTOR_ROWS[key])   # the client scales by its own ranges
    else:
        r_theirs = r

    @MANY
    @given(cmd=commands(r))
    def check(cmd: Command) -> None:
        theirs = fields(clients.tmotor_command(TMOTOR_ROWS[key], cmd.position, cmd.velocity, cmd.kp, cmd.kd,
                                               cmd.torque))
        ours = assert_ours(row, cmd)
        for i, (x, (lo, hi, bits), (tlo, thi, _)) in enumerate(zip(on_the_wire(cmd, 1), channels(r),
                                                                    channels(r_theirs))):
            exact = tmotor_scaled(x, tlo, thi, bits)
            assert theirs[i] == math.floor(exact) or abs(theirs[i] - math.floor(exact)) == 1 and near_boundary(
                exact, bits), (i, x, theirs[i], exact)
            if r_theirs is not r:
                continue
            firmware, top = firmware_code(x, lo, hi, bits), (1 << bits) - 2
            if x > hi - 2 * (hi - lo) / (1 << bits):
                assert math.floor(exact) == top and firmware in (top - 1, top, top + 1)
            else:
                assert math.floor(exact) - firmware in (0, 1)
            if not (near_boundary(exact, bits) or near_boundary(scaled(x, lo, hi, bits), bits)):
                assert (ours[i] != theirs[i]) == (firmware != math.floor(exact)), (i, x, ours[i], theirs[i])

    check()


def test_tmotor_and_dobhil_on_literal_ak80_9_commands() -> None:
    """The zero command and the all-maximum command of an AK80-9, bytes by hand: dobhil
    sends the firmware's codes (32767, 2047, 0, 0, 2047) and (65535, 4095 x 4),
    tmotorcancontrol (32768, 2048, 0, 0, 2048) and (65534, 4094 x 4)."""
    row = model(("cubemars", "AK80-9", _MANUAL))
    assert codec.pack_command(row, Command(0.0, 0.0, 0.0, 0.0, 0.0)) == bytes.fromhex("7fff7ff0000007ff")
    assert clients.tmotor_command("AK80-9", 0.0, 0.0, 0.0, 0.0, 0.0) == bytes.fromhex("8000800000000800")
    assert codec.pack_command(row, Command(12.5, 50.0, 500.0, 5.0, 18.0)) == bytes.fromhex("ffffffffffffffff")
    assert clients.tmotor_command("AK80-9", 12.5, 50.0, 500.0, 5.0, 18.0) == bytes.fromhex("fffeffeffeffeffe")


@pytest.mark.parametrize("key", list(CANMOTORLIB_ROWS), ids=lambda k: f"{k[1]}-{k[2]}")
def test_canmotorlib_commands_are_the_firmwares_as_dobhils(key: tuple[str, str, str],
                                                           capsys: pytest.CaptureFixture[str]) -> None:
    """``CanMotorController.send_rad_command`` (clip to the table, times AXIS_DIRECTION,
    the firmware's formula in double, bitstring packing): the same bytes as dobhil's --
    whose axis direction is the table's -- but where rounding differs at a code boundary
    (one code) and where the codes spell a special frame (canmotorlib sends it)."""
    row = model(key)
    r = ranges_of(row)

    @MANY
    @given(cmd=commands(r))
    def check(cmd: Command) -> None:
        theirs, _ = clients.canmotorlib_command(CANMOTORLIB_ROWS[key], cmd.position, cmd.velocity, cmd.kp,
                                                cmd.kd, cmd.torque)
        codes = fields(theirs)
        assert_fields_are_the_firmwares(codes, cmd, r, "canmotorlib")
        ours = assert_ours(row, cmd)
        assert ours == codes or any(near_boundary(scaled(x, lo, hi, bits), bits) for x, (lo, hi, bits)
                                    in zip(on_the_wire(cmd, r.axis_direction), channels(r))), (cmd, ours, codes)

    check()
    capsys.readouterr()   # its "Clipping Torque..." prints


@pytest.mark.parametrize(("client", "key"), [("damiao-motor", ("damiao", "DM4310", _FACTORY)),
                                             ("canmotorlib", ("cubemars", "AK80-9", "1.1"))])
def test_the_command_that_spells_a_special_frame(client: str, key: tuple[str, str, str],
                                                 capsys: pytest.CaptureFixture[str]) -> None:
    """Every field at its top and a torque whose code is 0xFFD: the clients send
    FF FF FF FF FF FF FF FD, the exit frame -- a command that switches the motor off. dobhil
    sends the position one code lower (0.4 mrad on 12.5 rad) and never a special frame."""
    row = model(key)
    r = ranges_of(row)
    for kind in (Special.ENTER, Special.EXIT, Special.ZERO, Special.CLEAR_ERROR):
        tau = codec.uint_to_float(0xF00 | kind, -r.t_max, r.t_max, FIELD_BITS) + r.t_max / 4095 / 2
        cmd = Command(r.p_max, r.v_max, r.kp_max, r.kd_max, tau)
        if client == "damiao-motor":
            with clients.damiao_motor(DAMIAO_ROWS[key]) as motor:
                theirs = motor.encode_cmd_msg(cmd.position, cmd.velocity, cmd.torque, cmd.kp, cmd.kd)
        else:
            theirs, _ = clients.canmotorlib_command(CANMOTORLIB_ROWS[key], cmd.position, cmd.velocity, cmd.kp,
                                                    cmd.kd, cmd.torque)
        assert theirs == codec.special_frame(kind)
        assert codec.pack_command(row, cmd) == b"\xff\xfe" + codec.special_frame(kind)[2:]
    capsys.readouterr()


# ---------------------------------------------------------------------------
# NaN and infinities


@pytest.mark.parametrize("field", ["position", "velocity", "kp", "kd", "torque"])
@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_nan_and_infinities_are_refused_where_clients_fail_or_send_something(
        field: str, bad: float, capsys: pytest.CaptureFixture[str]) -> None:
    """dobhil: CodecError, nothing packed (TorqueFrame too). damiao-motor and
    tmotorcancontrol: a NaN fails in ``int()`` (ValueError); an infinity is clamped and sent.
    canmotorlib's clipping (``min(max(lo, x), hi)``) turns a NaN position, velocity or gain
    into the range's low end and sends it; a NaN torque fails in ``int()``."""
    values = {"position": 0.5, "velocity": 1.0, "kp": 0.0, "kd": 0.0, "torque": 0.25} | {field: bad}
    cmd = Command(**values)
    for key in (("damiao", "DM4310", _FACTORY), ("cubemars", "AK80-9", _MANUAL), ("cubemars", "AK80-9", "1.1")):
        with pytest.raises(CodecError, match="not a finite number"):
            codec.pack_command(model(key), cmd)
    if field == "torque":
        with pytest.raises(CodecError, match="not a finite number"):
            TorqueFrame(model(("cubemars", "AK80-9", _MANUAL))).fill(bytearray(8), bad)

    args = (cmd.position, cmd.velocity, cmd.kp, cmd.kd, cmd.torque)
    with clients.damiao_motor("4310") as motor:
        if math.isnan(bad):
            with pytest.raises(ValueError):
                motor.encode_cmd_msg(cmd.position, cmd.velocity, cmd.torque, cmd.kp, cmd.kd)
        else:
            motor.encode_cmd_msg(cmd.position, cmd.velocity, cmd.torque, cmd.kp, cmd.kd)   # clamped, sent
    if math.isnan(bad):
        with pytest.raises(ValueError):
            clients.tmotor_command("AK80-9", *args)
    else:
        clients.tmotor_command("AK80-9", *args)
    index = ("position", "velocity", "kp", "kd", "torque").index(field)
    if math.isnan(bad) and field == "torque":
        with pytest.raises(ValueError):
            clients.canmotorlib_command("AK80_9_V1p1", *args)
    elif math.isnan(bad):
        sent, _ = clients.canmotorlib_command("AK80_9_V1p1", *args)
        assert fields(sent)[index] == 0   # the range's low end, sent as if asked for
    capsys.readouterr()


# ---------------------------------------------------------------------------
# Replies: what each client makes of the bytes a motor sends


def reply_codes(data: bytes) -> tuple[int, int, int]:
    """Position, velocity, torque codes of a reply (the reference firmware's layout)."""
    return (data[1] << 8) | data[2], (data[3] << 4) | (data[4] >> 4), ((data[4] & 0xF) << 8) | data[5]


def assert_values(ours: codec.Reply, theirs: tuple[float, float, float], r: Ranges) -> None:
    """The same raw codes decode to the same value but for single against double rounding
    (see test_every_code_decodes_as_the_clients_within_single_precision)."""
    for value, other, limit in zip((ours.position, ours.velocity, ours.torque), theirs, (r.p_max, r.v_max, r.t_max)):
        assert abs(value - other) <= 4 * float(np.spacing(np.float32(limit))), (value, other)


def replies(lengths: tuple[int, ...]) -> st.SearchStrategy[bytes]:
    """Any bytes of one of the layout's lengths."""
    return st.sampled_from(lengths).flatmap(lambda n: st.binary(min_size=n, max_size=n))


@pytest.mark.parametrize("key", list(DAMIAO_ROWS), ids=lambda k: k[1])
def test_damiao_replies_decode_as_damiao_motor(key: tuple[str, str, str]) -> None:
    """``decode_sensor_feedback``: id (low nibble), state (high nibble: dobhil's ``state``,
    and its ``error`` when a fault, 8 and up), position, velocity, torque, MOS and rotor
    temperatures -- for every byte 0 and random rest."""
    row = model(key)
    r = ranges_of(row)
    with clients.damiao_motor(DAMIAO_ROWS[key]) as motor:

        @REPLIES
        @given(data=replies(row.layout.lengths))
        def check(data: bytes) -> None:
            ours, theirs = codec.unpack_reply(row, data), motor.decode_sensor_feedback(data)
            assert (ours.raw_position, ours.raw_velocity, ours.raw_torque) == reply_codes(data)
            assert_values(ours, (theirs["pos"], theirs["vel"], theirs["torq"]), r)
            assert ours.motor_id == theirs["can_id"] and ours.state == theirs["status_code"]
            status = theirs["status_code"]
            assert ours.error == (status if status >= 8 else 0)
            assert (ours.error_text == "") == (ours.error == 0)
            assert ours.extra["mos_temperature"] == theirs["t_mos"] and ours.temperature == theirs["t_rotor"]

        check()


@pytest.mark.parametrize("key", list(TMOTOR_ROWS), ids=lambda k: k[1])
def test_cubemars_replies_decode_as_tmotorcancontrol(key: tuple[str, str, str]) -> None:
    """``parse_MIT_message``: position, velocity, torque (its "current"), temperature and
    error code of an 8-byte reply; its decoding is the firmware's formula (2^n - 1), so
    only rounding differs. Its id check (the listener's ``data[0] == motor.ID``) is byte 0."""
    row = model(key)
    r = ranges_of(row)
    if RANGE_DIFFERENCES.keys() & {("tmotorcancontrol", TMOTOR_ROWS[key], k) for k in ("p_max", "v_max", "t_max")}:
        r = clients.tmotor_ranges(TMOTOR_ROWS[key])   # compare codes only where ranges differ
    assert row.layout.lengths == (8,)

    @REPLIES
    @given(data=replies(row.layout.lengths))
    def check(data: bytes) -> None:
        ours, theirs = codec.unpack_reply(row, data), clients.tmotor_reply(TMOTOR_ROWS[key], data)
        assert (ours.raw_position, ours.raw_velocity, ours.raw_torque) == reply_codes(data)
        if r.v_max == row.v_max:
            assert_values(ours, (theirs.position, theirs.velocity, theirs.current), r)
        assert ours.motor_id == data[0]
        assert (ours.temperature, ours.error) == (theirs.temperature, theirs.error)

    check()


@pytest.mark.parametrize("key", list(CANMOTORLIB_ROWS), ids=lambda k: f"{k[1]}-{k[2]}")
def test_replies_decode_as_canmotorlib(key: tuple[str, str, str], capsys: pytest.CaptureFixture[str]) -> None:
    """``decode_motor_status`` and ``convert_raw_to_physical_rad`` (the reply path of
    ``send_rad_command``), AXIS_DIRECTION applied: dobhil's values, on the output axis too."""
    row = model(key)
    r = ranges_of(row)

    @REPLIES
    @given(data=replies(row.layout.lengths))
    def check(data: bytes) -> None:
        _, theirs = clients.canmotorlib_command(CANMOTORLIB_ROWS[key], 0.0, 0.0, 0.0, 0.0, 0.0, reply=data)
        ours = codec.unpack_reply(row, data)
        assert (ours.raw_position, ours.raw_velocity, ours.raw_torque) == reply_codes(data)
        assert_values(ours, theirs, r)

    check()
    capsys.readouterr()
