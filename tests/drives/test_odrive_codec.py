"""ODrive codec against literal bytes, by round trip, and its error messages."""

from __future__ import annotations

import itertools
import math
import struct

import pytest

from dobhil.drives.odrive import codec
from dobhil.drives.odrive.codec import AxisState, CmdId, CmdId06, ControlMode, Firmware, InputMode
from dobhil.errors import CodecError

BOTH = (Firmware.V0_5, Firmware.V0_6)


def frame(msg: object, node_id: int = 3, firmware: Firmware = Firmware.V0_6) -> tuple[int, str]:
    m = codec.encode(msg, node_id=node_id, firmware=firmware)
    return m.arbitration_id, m.data.hex(" ")


@pytest.mark.parametrize("firmware", BOTH)
@pytest.mark.parametrize(
    ("msg", "node_id", "expected"),
    [
        (codec.SetInputTorque(1.5), 3, (0x06E, "00 00 c0 3f 00 00 00 00")),
        (codec.SetInputTorque(-2.0), 0, (0x00E, "00 00 00 c0 00 00 00 00")),
        (codec.SetAxisState(AxisState.CLOSED_LOOP_CONTROL), 3, (0x067, "08 00 00 00 00 00 00 00")),
        (codec.SetAxisState(AxisState.IDLE), 63, (0x7E7, "01 00 00 00 00 00 00 00")),
        (
            codec.SetControllerMode(ControlMode.TORQUE_CONTROL, InputMode.PASSTHROUGH), 3,
            (0x06B, "01 00 00 00 01 00 00 00"),
        ),
        (codec.EncoderEstimates(2 * math.pi, -math.pi), 1, (0x029, "00 00 80 3f 00 00 00 bf")),
        (codec.SetInputVel(math.pi, 0.25), 2, (0x04D, "00 00 00 3f 00 00 80 3e")),
        (codec.Estop(), 3, (0x062, "")),
    ],
)
def test_encode_literal_bytes(msg: object, node_id: int, expected: tuple[int, str], firmware: Firmware) -> None:
    assert frame(msg, node_id, firmware) == expected


def test_heartbeat_layouts_differ() -> None:
    hb = codec.Heartbeat(
        0x01000000, AxisState.CLOSED_LOOP_CONTROL, procedure_result=2, trajectory_done=True
    )
    assert frame(hb, 3, Firmware.V0_6) == (0x061, "00 00 00 01 08 02 01 00")
    hb5 = codec.Heartbeat(
        0x800, AxisState.IDLE, trajectory_done=True, motor_error_flag=True,
        encoder_error_flag=False, controller_error_flag=True,
    )
    assert frame(hb5, 3, Firmware.V0_5) == (0x061, "00 08 00 00 01 01 00 81")


def test_clear_errors_and_reboot_dlc_per_firmware() -> None:
    assert frame(codec.ClearErrors(), 3, Firmware.V0_5) == (0x078, "")
    assert frame(codec.ClearErrors(identify=1), 3, Firmware.V0_6) == (0x078, "01")
    assert frame(codec.Reboot(), 3, Firmware.V0_5) == (0x076, "")
    assert frame(codec.Reboot(action=1), 3, Firmware.V0_6) == (0x076, "01")


def test_decode_literal_bytes_to_si() -> None:
    est = codec.decode(0x069, bytes.fromhex("0000803f000000bf"))
    assert est == codec.EncoderEstimates(2 * math.pi, -math.pi)
    hb = codec.decode(0x061, bytes.fromhex("0000000108000000"))
    assert hb.axis_state is AxisState.CLOSED_LOOP_CONTROL and hb.axis_error == 0x01000000


ROUND_TRIP = [
    codec.Heartbeat(0x1234, AxisState.IDLE, trajectory_done=True),
    codec.Estop(),
    codec.SetAxisState(AxisState.CLOSED_LOOP_CONTROL),
    codec.EncoderEstimates(1.25, -3.5),
    codec.SetControllerMode(ControlMode.TORQUE_CONTROL, InputMode.TORQUE_RAMP),
    codec.SetInputVel(4.0, -0.5),
    codec.SetInputTorque(0.125),
    codec.SetLimits(10.0, 20.0),
    codec.Iq(1.5, 1.25),
    codec.Reboot(),
    codec.BusVoltageCurrent(24.0, 0.5),
    codec.ClearErrors(),
]
ONLY_06 = [codec.GetError(0x01000000, 7), codec.Torques(0.5, 0.25), codec.Reboot(2)]


def _close(a: object, b: object) -> bool:
    return all(
        math.isclose(x, y, rel_tol=1e-6) if isinstance(x, float) else x == y
        for x, y in zip(vars_of(a), vars_of(b))
    ) and type(a) is type(b)


def vars_of(msg: object) -> tuple[object, ...]:
    return tuple(getattr(msg, n) for n in codec.message_fields(type(msg)))


@pytest.mark.parametrize("firmware", BOTH)
@pytest.mark.parametrize("msg", ROUND_TRIP, ids=lambda m: type(m).__name__)
def test_round_trip(msg: object, firmware: Firmware) -> None:
    m = codec.encode(msg, node_id=5, firmware=firmware)
    assert codec.split_id(m.arbitration_id)[0] == 5
    assert _close(codec.decode_message(m, firmware), msg)


@pytest.mark.parametrize("msg", ONLY_06, ids=lambda m: type(m).__name__)
def test_round_trip_06_only(msg: object) -> None:
    m = codec.encode(msg, node_id=5, firmware=Firmware.V0_6)
    assert _close(codec.decode_message(m, Firmware.V0_6), msg)
    if not isinstance(msg, codec.Reboot):
        with pytest.raises(CodecError, match="firmware 0.5"):
            codec.encode(msg, node_id=5, firmware=Firmware.V0_5)


def test_requests_are_rtr_or_zero_length() -> None:
    rtr = codec.encode(codec.Request(CmdId.GET_ENCODER_ESTIMATES), node_id=3)
    assert rtr.is_remote_frame and rtr.arbitration_id == 0x069
    assert codec.decode_message(rtr) == codec.Request(CmdId.GET_ENCODER_ESTIMATES)
    assert codec.decode(0x061, b"") == codec.Request(CmdId.HEARTBEAT)
    assert codec.decode(0x062, b"") == codec.Estop()  # Estop has no payload: not a request


def test_padding_to_dbc_length_is_accepted() -> None:
    assert codec.decode(0x06E, bytes.fromhex("0000c03f00000000")) == codec.SetInputTorque(1.5)


def test_errors_are_one_line_and_say_what_came() -> None:
    with pytest.raises(CodecError, match=r"Set_Input_Torque \(0x0E\) needs 4 data bytes, got 2"):
        codec.decode(0x06E, b"\x00\x00")
    with pytest.raises(CodecError, match=r"unknown ODrive command id 0x1F"):
        codec.decode(0x07F, b"")
    with pytest.raises(CodecError, match=r"command id 0x1C for firmware 0.5"):
        codec.decode(0x07C, bytes(8), Firmware.V0_5)
    with pytest.raises(CodecError, match="node_id: expected 0..63, got 64"):
        codec.encode(codec.Estop(), node_id=64)
    with pytest.raises(CodecError, match="11-bit"):
        codec.decode(0x800, b"")
    with pytest.raises(CodecError, match="cannot encode"):
        codec.encode(codec.SetAxisState(-1), node_id=1)


def test_unknown_axis_state_decodes_as_int() -> None:
    hb = codec.decode(0x061, struct.pack("<IBBBx", 0, 200, 0, 0))
    assert hb.axis_state == 200 and not isinstance(hb.axis_state, AxisState)


def test_error_bits_and_descriptions() -> None:
    assert codec.watchdog_bit(Firmware.V0_5) == 0x800
    assert codec.watchdog_bit(Firmware.V0_6) == 0x01000000
    assert codec.describe_errors(0x01000000, Firmware.V0_6) == "0x01000000 (WATCHDOG_TIMER_EXPIRED)"
    assert "ESTOP_REQUESTED" in codec.describe_errors(0x4000, Firmware.V0_5)
    assert "unknown 0x20000000" in codec.describe_errors(0x20000000, Firmware.V0_6)
    assert codec.describe_errors(0, Firmware.V0_6) == "0x00000000 (none)"


def test_firmware_parse() -> None:
    assert Firmware.parse("0.6.10") is Firmware.V0_6
    assert Firmware.parse("0.5") is Firmware.V0_5
    with pytest.raises(CodecError, match="got '0.4'"):
        Firmware.parse("0.4")


def test_hot_path_pack_into_matches_encode() -> None:
    spec = codec.spec_for(CmdId.SET_INPUT_TORQUE)
    buf = spec.new_frame_data()
    spec.pack_into(buf, 1.5)
    assert bytes(buf) == codec.encode_data(codec.SetInputTorque(1.5))
    assert len(buf) == 8


@pytest.mark.parametrize("firmware", BOTH)
def test_hot_paths_are_the_dataclass_codec_bit_for_bit(firmware: Firmware) -> None:
    """pack_into and unpack_si (what every lockstep cycle runs: the emulated drive's encoder
    estimates, the host's torque) give the bytes and SI values of encode and decode, on a
    message scaled to SI (turns -> rad) and an unscaled one."""
    estimates = codec.spec_for(CmdId.GET_ENCODER_ESTIMATES, firmware)
    torque = codec.spec_for(CmdId.SET_INPUT_TORQUE, firmware)
    values = (0.0, -0.0, 1e-3, -0.7391, math.pi, 12.5, -1e4)
    for position, velocity in itertools.product(values, values[::-1]):
        buf = estimates.new_frame_data()
        estimates.pack_into(buf, position, velocity)
        whole = codec.encode(codec.EncoderEstimates(position, velocity), node_id=3, firmware=firmware)
        assert bytes(buf) == bytes(whole.data)
        decoded = codec.decode_message(whole, firmware)
        assert estimates.unpack_si(buf) == (decoded.position_rad, decoded.velocity_rad_s)
    for tau in values:
        buf = torque.new_frame_data()
        torque.pack_into(buf, tau)
        whole = codec.encode(codec.SetInputTorque(tau), node_id=3, firmware=firmware)
        assert bytes(buf) == bytes(whole.data)
        assert torque.unpack_si(buf) == (codec.decode_message(whole, firmware).torque_nm,)


@pytest.mark.parametrize("firmware", BOTH)
def test_every_data_message_is_sent_with_dlc_8_zero_padded(firmware: Firmware) -> None:
    """The DBCs give every data message DLC 8 (Clear_Errors/Reboot: 0 on 0.5, 1 on 0.6)."""
    short = {CmdId.ESTOP: 0, CmdId.CLEAR_ERRORS: 0 if firmware is Firmware.V0_5 else 1,
             CmdId.REBOOT: 0 if firmware is Firmware.V0_5 else 1}
    for spec in codec.specs(firmware):
        assert spec.dlc == short.get(spec.cmd, 8), spec.name
    frame_ = codec.encode(codec.SetAxisState(AxisState.IDLE), node_id=3, firmware=firmware)
    assert frame_.dlc == 8 and bytes(frame_.data) == bytes.fromhex("0100000000000000")


def test_requests_carry_the_data_frames_dlc() -> None:
    rtr = codec.encode(codec.Request(CmdId.HEARTBEAT), node_id=3)
    assert rtr.is_remote_frame and rtr.dlc == 8 and rtr.arbitration_id == 0x061
    version = codec.encode(codec.Request(CmdId06.GET_VERSION), node_id=3)
    assert version.arbitration_id == 0x060 and version.is_remote_frame


def test_get_version_literal_bytes_06_only() -> None:
    v = codec.decode(0x060, bytes([2, 4, 4, 58, 0, 6, 10, 0]))
    assert v == codec.Version(2, 4, 4, 58, 0, 6, 10, 0)
    assert v.firmware_text == "0.6.10" and v.hardware_text == "4.4.58"
    with pytest.raises(CodecError, match="0x00 for firmware 0.5"):
        codec.decode(0x060, bytes(8), Firmware.V0_5)


def test_05_component_error_messages() -> None:
    m = codec.decode(0x063, (0x00010000).to_bytes(8, "little"), Firmware.V0_5)
    assert m == codec.MotorErrorMsg(0x10000)
    assert codec.describe_flags(m.motor_error, codec.MotorError05) == "0x00010000 (MODULATION_IS_NAN)"
    assert codec.decode(0x064, bytes([4, 0, 0, 0, 0, 0, 0, 0]), Firmware.V0_5) == codec.EncoderErrorMsg(4)
    assert codec.decode(0x07D, bytes([1]) + bytes(7), Firmware.V0_5) == codec.ControllerErrorMsg(1)
    assert frame(codec.MotorErrorMsg(0x800000000), 3, Firmware.V0_5) == (0x063, "00 00 00 00 08 00 00 00")


def test_complete_05_axis_error_table() -> None:
    """The 0.5 axis error bits of the motor, estimator, encoder and controller name
    themselves; nothing is 'unknown'."""
    for bit, name in ((0x40, "MOTOR_FAILED"), (0x80, "SENSORLESS_ESTIMATOR_FAILED"),
                      (0x100, "ENCODER_FAILED"), (0x200, "CONTROLLER_FAILED")):
        assert codec.describe_errors(bit, Firmware.V0_5) == f"0x{bit:08X} ({name})"


def test_heartbeat_description_per_firmware() -> None:
    hb6 = codec.decode(0x061, bytes.fromhex("0000000101030100"))
    assert hb6.procedure_result == codec.ProcedureResult06.DISARMED
    assert codec.describe_heartbeat(hb6, Firmware.V0_6) == (
        "0x01000000 (WATCHDOG_TIMER_EXPIRED); last state request DISARMED")
    hb5 = codec.decode(0x061, bytes.fromhex("4000000001010080"), Firmware.V0_5)
    assert hb5.trajectory_done and hb5.motor_error_flag
    assert codec.describe_heartbeat(hb5, Firmware.V0_5) == (
        "0x00000040 (MOTOR_FAILED); motor error flag set")
    assert codec.procedure_result_name(99) == "procedure result 99"


def test_float32_overflow_is_a_codec_error() -> None:
    with pytest.raises(CodecError, match="Get_Encoder_Estimates: cannot encode"):
        codec.encode(codec.EncoderEstimates(1e308, 0.0), node_id=3)
    spec = codec.spec_for(CmdId.GET_ENCODER_ESTIMATES)
    with pytest.raises(CodecError, match="cannot encode"):
        spec.pack_into(spec.new_frame_data(), 1e308, 0.0)
    inf = codec.encode(codec.SetInputTorque(math.inf), node_id=3)  # inf is a float32 value
    assert codec.decode_message(inf).torque_nm == math.inf
