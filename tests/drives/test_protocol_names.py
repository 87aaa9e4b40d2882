"""Each protocol names the drive's own state and error codes (``DriveProtocol.state_name``,
``error_text``: the log's ``protocol_state_name``/``protocol_error_text``) in its documented
words: ODrive's Axis_State and per-firmware Axis_Error bits (ODrive docs, ``fibre_types``),
CiA 402's power states (CiA 402-2, statusword table) and EMCY codes (canopen's CiA 301
classes), the MIT models' state nibble and error byte (``drivers/mit-models.yaml``)."""

from __future__ import annotations

import dataclasses
import pickle

import pytest
from hypothesis import given
from hypothesis import strategies as st

from dobhil.drives.cia402 import codec as cia402_codec
from dobhil.drives.load import load_profile
from dobhil.drives.profile import DriveProfile
from dobhil.drives.registry import protocol
from dobhil.recording.codes import ProtocolCodes


def _names(profile_name: str) -> tuple[DriveProfile, ProtocolCodes]:
    profile = load_profile(profile_name)
    return profile, ProtocolCodes(profile)


@pytest.mark.parametrize(("profile_name", "states", "errors"), [
    ("odrive-0.6", {1: "IDLE", 8: "CLOSED_LOOP_CONTROL", 99: "99"},
     {0: "0x00000000 (none)", 0x01000000: "0x01000000 (WATCHDOG_TIMER_EXPIRED)"}),
    ("odrive-0.5", {8: "CLOSED_LOOP_CONTROL"},   # 0.5's watchdog bit is 0x800, its 0x01000000 is another
     {0x800: "0x00000800 (WATCHDOG_TIMER_EXPIRED)"}),
    ("cia402-emulated", {int(cia402_codec.power_state(0x0627)): "operation enabled",
                         int(cia402_codec.power_state(0x0008)): "fault",
                         int(cia402_codec.power_state(0x0040)): "switch on disabled"},
     {0: "none", 0x8130: "EMCY 0x8130 (Monitoring)"}),
    ("dm4310", {0: "disabled", 1: "enabled", 13: "communication lost", 5: "state 0x5"},
     {0: "none", 13: "communication lost", 0x100: "at rail", 0x101: "bad layout"}),
    ("ak80-9", {-1: "none (the reply carries no mode)"}, {2: "over current", 77: "0x4D"}),
    # a log with no mode recorded (before protocol_state: an old log) says so, not "mode -1"
    ("moteus-r4.11", {-1: "not reported", 10: "POSITION", 0: "STOPPED"}, {0: "0 (none)"}),
])
def test_each_protocol_names_its_codes_in_its_own_words(profile_name: str, states: dict[int, str],
                                                       errors: dict[int, str]) -> None:
    _, codes = _names(profile_name)
    assert {code: codes.state_name(code) for code in states} == states
    assert {code: codes.error_text(code) for code in errors} == errors


@given(st.integers(0, 2**32 - 1), st.sampled_from(["odrive-0.5", "odrive-0.6"]))
def test_an_odrive_error_text_names_every_bit_of_its_firmware(error: int, profile_name: str) -> None:
    """The code in hex, then the name of each set bit the firmware's Axis_Error enum names
    (bits it does not name are left to the hex)."""
    from dobhil.drives.odrive import codec
    profile, codes = _names(profile_name)
    enum = codec.AxisError05 if profile.firmware.startswith("0.5") else codec.ODriveError06
    text = codes.error_text(error)
    assert text.startswith(f"0x{error:08X} (")
    named = {m.name for m in enum if m.value & error and m.name}
    assert named <= set(text[text.index("(") + 1:].rstrip(")").replace(" ", "|").split("|"))
    assert (text == "0x00000000 (none)") == (error == 0)


def test_codes_without_a_protocol_to_name_them_stay_numbers() -> None:
    """A log read where its protocol is not installed (or with no profile): the numbers;
    no state frame yet: "not reported"."""
    profile = load_profile("odrive-0.6")
    for codes in (ProtocolCodes(), ProtocolCodes(dataclasses.replace(profile, protocol="no-such-protocol"))):
        assert (codes.state_name(8), codes.error_text(0), codes.error_text(0x800)) == ("8", "none", "0x800")
        assert codes.state_name(-1) == "not reported"
    assert ProtocolCodes(profile).state_name(-1) == "not reported"
    assert protocol("odrive").state_name(profile, 8) == "CLOSED_LOOP_CONTROL"


def test_codes_travel_to_the_writer_process_without_their_names() -> None:
    """Pickled (the writer process gets it with the log's metadata): the profile only."""
    profile, codes = _names("cia402-emulated")
    codes.state_name(4)
    copy = pickle.loads(pickle.dumps(codes))
    assert copy.profile == profile and copy._states == {} and copy.state_name(4) == "operation enabled"
