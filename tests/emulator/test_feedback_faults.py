"""A corrupted feedback value lands where each protocol's codec puts it: the fault asks the
protocol (``DriveProtocol.feedback_field``) for the frame id, byte offset and format, and
the protocol's own decoder reads the corrupted value back -- no id or offset written here."""

from __future__ import annotations

import dataclasses
import math

import can
import pytest
from hypothesis import given
from hypothesis import strategies as st

from dobhil.drives.cia402 import codec as cia402_codec
from dobhil.drives.cia402.codec import Cob
from dobhil.drives.load import load_profile
from dobhil.drives.odrive import codec as odrive_codec
from dobhil.emulator.faults import CorruptFeedback

ODRIVE = {fw: load_profile(f"odrive-{fw}") for fw in ("0.5", "0.6")}
CIA402 = load_profile("cia402-emulated")


def corrupt(fault: CorruptFeedback, msg: can.Message) -> can.Message:
    (out,) = fault(msg, 0.0)
    return out


@pytest.mark.parametrize("fw", sorted(ODRIVE))
@given(position=st.floats(-1e3, 1e3), velocity=st.floats(-1e3, 1e3), node=st.integers(0, 63))
def test_odrive_estimates_corrupted_field_by_field(fw: str, position: float, velocity: float, node: int) -> None:
    profile = dataclasses.replace(ODRIVE[fw], node_id=node)
    firmware = odrive_codec.Firmware.parse(fw)
    frame = odrive_codec.encode(odrive_codec.EncoderEstimates(position, velocity), node_id=node, firmware=firmware)
    pos = odrive_codec.decode_message(corrupt(CorruptFeedback.of_profile(profile, "position"), frame), firmware)
    vel = odrive_codec.decode_message(corrupt(CorruptFeedback.of_profile(profile, "velocity", value=7.0), frame),
                                      firmware)
    clean = odrive_codec.decode_message(frame, firmware)
    assert math.isnan(pos.position_rad) and pos.velocity_rad_s == clean.velocity_rad_s
    assert vel.position_rad == clean.position_rad and vel.velocity_rad_s == pytest.approx(7.0 * 2 * math.pi)


@given(position=st.integers(-2**31, 2**31 - 1), velocity=st.integers(-2**31, 2**31 - 1),
       value=st.integers(-2**31, 2**31 - 1), tpdo=st.sampled_from([1, 3]))
def test_cia402_pdos_corrupted_field_by_field(position: int, velocity: int, value: int, tpdo: int) -> None:
    profile = dataclasses.replace(CIA402, options={**CIA402.options, "tpdo": tpdo})
    status = can.Message(arbitration_id=Cob.tpdo(tpdo, profile.node_id), is_extended_id=False,
                         data=cia402_codec.TPDO_STATUS_STRUCT.pack(0x0237, position, 12))
    motion = can.Message(arbitration_id=Cob.tpdo(tpdo + 1, profile.node_id), is_extended_id=False,
                         data=cia402_codec.TPDO_MOTION_STRUCT.pack(velocity, 10))
    pos_fault = CorruptFeedback.of_profile(profile, "position", value=value)
    vel_fault = CorruptFeedback.of_profile(profile, "velocity", value=value)
    assert cia402_codec.TPDO_STATUS_STRUCT.unpack(bytes(corrupt(pos_fault, status).data)) == (0x0237, value, 12)
    assert cia402_codec.TPDO_MOTION_STRUCT.unpack(bytes(corrupt(vel_fault, motion).data)) == (value, 10)
    assert corrupt(pos_fault, motion) is motion and corrupt(vel_fault, status) is status   # other ids pass


def test_what_a_protocol_cannot_lay_out_is_one_line() -> None:
    with pytest.raises(ValueError, match=r"^CorruptFeedback: field: protocol 'mit' offers no feedback field "
                                         r"'position' to corrupt"):
        CorruptFeedback.of_profile(load_profile("ak80-9"), "position")
    with pytest.raises(ValueError, match=r"offers no feedback field 'torque'"):
        CorruptFeedback.of_profile(ODRIVE["0.6"], "torque")
    with pytest.raises(ValueError, match=r"^CorruptFeedback: value: expected a value '<i' holds, got nan$"):
        CorruptFeedback.of_profile(CIA402, "position")   # NaN is no 32-bit integer
