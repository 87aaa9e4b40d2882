"""The MIT drive against a hand-written motor (tests/drives/mit_fake.py) on a python-can
virtual bus: the frames it sends and the replies it reads are literal bytes, written
from the layouts of the reference firmware (github.com/bgkatz/motorcontrol,
``CAN/CAN_com.cpp``) -- not from dobhil's codec.

Decoding is checked with the firmware formula written out here:
``x = u (hi - lo) / (2^bits - 1) + lo``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import can
import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st

from dobhil.drives import DriveState
from dobhil.drives.base import Confirmation
from dobhil.drives.mit.drive import MitDrive
from dobhil.drives.mit.replies import MitFault
from dobhil.drives.mit.models import load_models, shipped_models_path
from dobhil.drives.load import profile_from_mapping
from dobhil.drives.profile import DriveProfile
from dobhil.errors import ConfigError, DriveFaultError, DriveTimeoutError

from tests.drives.mit_fake import (CLEAR, ENTER, EXIT, ZERO_TORQUE, fake_motor, reply_cheetah, reply_cubemars,
                                   reply_damiao)

NODE = 1


def row(vendor: str, model: str) -> Any:
    """The table's row of ``vendor model`` whose reply layout is the vendor's own (CubeMars:
    the 8-byte reply with temperature and error)."""
    rows = [m for (v, mo, _), m in sorted(load_models().items())
            if v == vendor and mo == model and m.layout.name == vendor]
    assert rows, f"no {vendor} {model} in the model table"
    return rows[0]


def mit_profile(vendor: str = "cubemars", model: str = "AK80-9", *, node: int = NODE, **changes: Any) -> DriveProfile:
    m = row(vendor, model)
    data: dict[str, Any] = {"protocol": "mit", "firmware": m.firmware, "node_id": node,
                            "torque_limit": min(5.0, m.t_max), "velocity_limit": min(20.0, m.v_max),
                            "enable_timeout": 0.5, "command_delay_periods": 1,
                            "mit": {"vendor": vendor, "model": model}}
    section = changes.pop("mit", {})
    data["mit"].update(section)
    data.update(changes)
    return profile_from_mapping(data, source="test profile")


def decode(u: int, hi: float, bits: int) -> float:
    return u * (2 * hi) / ((1 << bits) - 1) - hi


def answer_all(reply: bytes) -> Any:
    return lambda data: reply


# ---------------------------------------------------------------------------
# Enable


def test_enable_sends_enter_then_zero_torque_and_a_reply_confirms() -> None:
    with fake_motor(NODE, answer_all(reply_cubemars(NODE))) as (bus, motor):
        drive = MitDrive(bus, mit_profile())
        drive.enable()
        assert drive.status.state is DriveState.ENABLED
        got = motor.frames()
        assert got[0] == ENTER
        assert all(f == ZERO_TORQUE for f in got[1:])   # nothing that could move the motor
        drive.disable()


def test_a_silent_motor_times_out_saying_mit_mode_bit_rate_id_and_power() -> None:
    with fake_motor(NODE, lambda data: None) as (bus, motor):
        drive = MitDrive(bus, mit_profile(enable_timeout=0.1))
        with pytest.raises(DriveTimeoutError) as info:
            drive.enable()
    text = str(info.value)
    assert "\n" not in text
    for words in ("not in MIT mode", "CubeMars", "bit rate", "node_id 1", "power"):
        assert words in text
    assert motor.frames()[0] == ENTER


def test_a_reply_queued_before_the_enter_frame_does_not_confirm_it() -> None:
    with fake_motor(NODE, lambda data: None) as (bus, motor):
        motor.send(reply_cubemars(NODE))         # late, from before
        drive = MitDrive(bus, mit_profile(enable_timeout=0.1))
        with pytest.raises(DriveTimeoutError, match="a motor not in MIT mode answers nothing"):
            drive.enable()
    assert drive.status.state is DriveState.DISABLED
    assert drive.feedback is not None and drive.feedback.seq == 1   # read (and decoded) all the same


def test_a_cubemars_error_in_the_reply_ends_the_enable_at_once_with_its_code() -> None:
    with fake_motor(NODE, answer_all(reply_cubemars(NODE, error=1))) as (bus, _):
        drive = MitDrive(bus, mit_profile(enable_timeout=5.0))
        with pytest.raises(DriveFaultError, match=r"node 1 reports error 1 \(over temperature\)"):
            drive.enable()


def damiao_motor(state_after: dict[bytes, int], start: int = 0) -> Any:
    """A Damiao whose state nibble follows the special frames it got."""
    state = [start]

    def answer(data: bytes) -> bytes:
        state[0] = state_after.get(data, state[0])
        return reply_damiao(NODE, state[0])
    return answer


def test_a_damiao_enable_waits_for_state_1() -> None:
    with fake_motor(NODE, damiao_motor({ENTER: 1, EXIT: 0})) as (bus, motor):
        drive = MitDrive(bus, mit_profile("damiao", "DM4310"))
        drive.enable()
        assert drive.status.state is DriveState.ENABLED
        assert drive.feedback is not None
        report = drive.safe_stop(timeout=0.5)
        assert motor.wait_for(EXIT)[-1] == EXIT
    assert report.confirmation is Confirmation.CONFIRMED and report.safe


def test_a_damiao_fault_ends_the_enable_naming_reset_faults_and_reset_faults_clears_it_first() -> None:
    with fake_motor(NODE, damiao_motor({ENTER: 0xB}, start=0xB)) as (bus, _):
        with pytest.raises(DriveFaultError, match="reset-faults"):
            MitDrive(bus, mit_profile("damiao", "DM4310")).enable()
    with fake_motor(NODE, damiao_motor({CLEAR: 0, ENTER: 1}, start=0xB)) as (bus, motor):
        drive = MitDrive(bus, mit_profile("damiao", "DM4310"), reset_faults=True)
        drive.enable()
        drive.disable()
        assert motor.wait_for(EXIT)[:2] == [CLEAR, ENTER]


# ---------------------------------------------------------------------------
# Torque: the preallocated frame, literal bytes


def test_torque_fills_only_the_torque_bits_of_one_preallocated_frame() -> None:
    with fake_motor(NODE, answer_all(reply_cubemars(NODE))) as (bus, motor):
        drive = MitDrive(bus, mit_profile())
        drive.enable()
        first = drive._torque_frame(9.0)
        # AK80-9: t = int((9 + 18) * 4095 / 36) = 3071 = 0xBFF
        assert bytes(first.data) == bytes.fromhex("7FFF7FF000000BFF")
        assert drive._torque_frame(-18.0) is first
        assert bytes(first.data) == bytes.fromhex("7FFF7FF000000000")
        drive.send_torque(18.0)   # t = 4095 = 0xFFF
        drive.disable()
        frames = motor.wait_for(EXIT)
    assert bytes.fromhex("7FFF7FF000000FFF") in frames
    assert frames[-2:] == [ZERO_TORQUE, EXIT]   # safe stop: zero torque, then exit


# ---------------------------------------------------------------------------
# Decoding: unwrap, errors, the rail, other nodes


def frame(data: bytes, reply_id: int = 0) -> can.Message:
    return can.Message(arbitration_id=reply_id, data=data, is_extended_id=False)


def test_position_is_unwrapped_across_the_wrap_both_ways() -> None:
    drive = MitDrive(None, mit_profile())   # type: ignore[arg-type]  # decoding needs no bus
    codes = [0xFFF0, 0x0010, 0x8000, 0xFFF0, 0x0010, 0xFFF0, 0x0010, 0x0005]
    positions = []
    for p in codes:
        assert drive.apply(frame(reply_cubemars(NODE, p=p)))
        assert drive.feedback is not None
        positions.append(drive.feedback.position)
    span = 65536 * 25.0 / 65535   # the 16-bit field rolls over: 2^16 steps
    expected = [decode(0xFFF0, 12.5, 16), decode(0x0010, 12.5, 16) + span, decode(0x8000, 12.5, 16) + span,
                decode(0xFFF0, 12.5, 16) + span, decode(0x0010, 12.5, 16) + 2 * span,
                decode(0xFFF0, 12.5, 16) + span, decode(0x0010, 12.5, 16) + 2 * span,
                decode(0x0005, 12.5, 16) + 2 * span]
    # 0x0010 -> 0x8000 is less than half a span: no crossing
    # the codec decodes in IEEE single precision, as the firmware does: 1 ulp at 12.5 is 1e-6
    assert positions == pytest.approx(expected, abs=2e-6)
    # the other way round: from +... down through the wrap
    down = MitDrive(None, mit_profile())  # type: ignore[arg-type]
    for p in (0x0010, 0xFFF0):
        down.apply(frame(reply_cubemars(NODE, p=p)))
    assert down.feedback is not None
    assert down.feedback.position == pytest.approx(decode(0xFFF0, 12.5, 16) - span, abs=2e-6)


def test_replaying_the_same_replies_rebuilds_the_same_positions() -> None:
    frames = [frame(reply_cubemars(NODE, p=p, v=v)) for p, v in
              ((0xF000, 0x900), (0xFFF0, 0x900), (0x0100, 0x900), (0x1000, 0x900))]
    seen = []
    for _ in range(2):
        drive = MitDrive(None, mit_profile())  # type: ignore[arg-type]
        seen.append([(drive.apply(f), drive.feedback) for f in frames])
    assert [(a, b.position, b.velocity, b.seq) for a, b in seen[0]] == \
        [(a, b.position, b.velocity, b.seq) for a, b in seen[1]]
    assert seen[0][-1][1].velocity == pytest.approx(decode(0x900, 50.0, 12))


def test_replies_of_other_nodes_ids_and_lengths_are_not_ours() -> None:
    drive = MitDrive(None, mit_profile())  # type: ignore[arg-type]
    assert drive._decode(frame(reply_cubemars(2))) == ()
    assert drive._decode(frame(reply_cubemars(NODE), reply_id=5)) == ()
    assert drive._decode(can.Message(arbitration_id=0, data=reply_cubemars(NODE), is_extended_id=True)) == ()
    short = drive._decode(frame(reply_cubemars(NODE)[:6]))
    assert len(short) == 1 and short[0].error_code == MitFault.BAD_LAYOUT   # type: ignore[union-attr]
    assert "6 bytes" in short[0].error_text   # type: ignore[union-attr]


def test_a_non_zero_error_code_faults_a_running_drive_with_its_text() -> None:
    replies = [reply_cubemars(NODE)]

    with fake_motor(NODE, lambda data: replies[0]) as (bus, _):
        drive = MitDrive(bus, mit_profile())
        drive.enable()
        replies[0] = reply_cubemars(NODE, error=2)
        drive.send_torque(0.5)
        with pytest.raises(DriveFaultError, match=r"node 1 fault: error 2 \(over current\)"):
            for _ in range(100):
                drive.poll(0.05)
        assert drive.status.state is DriveState.FAULT
        drive.disable()


def saturating_table(directory: Path) -> str:
    """A model table of our own (``mit.models``): the shipped one with the DM4310 row's
    position saturating at its range ends instead of wrapping."""
    table = yaml.safe_load(shipped_models_path().read_text(encoding="utf-8"))
    for entry in table["models"]:
        if entry["vendor"] == "damiao" and entry["model"] == "DM4310":
            entry["position_at_limit"] = "saturate"
    path = directory / "saturating.yaml"
    path.write_text(yaml.safe_dump(table), encoding="utf-8")
    return str(path)


def test_a_saturating_reading_on_the_rail_is_a_fault(tmp_path: Path) -> None:
    profile = mit_profile("damiao", "DM4310", mit={"models": saturating_table(tmp_path)})
    assert profile.options["models"]
    drive = MitDrive(None, profile)  # type: ignore[arg-type]
    events = drive._decode(frame(reply_damiao(NODE, 1, p=0xFFFF)))
    state = events[1]
    assert state.error_code == MitFault.AT_RAIL   # type: ignore[union-attr]
    assert "end of the encodable range (+12.5 rad)" in state.error_text   # type: ignore[union-attr]
    inside = drive._decode(frame(reply_damiao(NODE, 1, p=0xFFFE)))
    assert inside[1].error_code == 0   # type: ignore[union-attr]


# ---------------------------------------------------------------------------
# Safe stop


@pytest.mark.parametrize(("vendor", "model", "reply"), [
    ("cubemars", "AK80-9", reply_cubemars(NODE)),
    ("mini-cheetah", "motorcontrol", reply_cheetah(NODE)),
])
def test_a_safe_stop_sends_zero_torque_then_exit_and_says_when_it_cannot_be_confirmed(
        vendor: str, model: str, reply: bytes) -> None:
    with fake_motor(NODE, answer_all(reply)) as (bus, motor):
        drive = MitDrive(bus, mit_profile(vendor, model))
        drive.enable()
        report = drive.safe_stop()
        frames = motor.wait_for(EXIT)
    assert [f.what for f in report.frames] == ["zero torque", "exit motor mode"]
    assert frames[-2:] == [ZERO_TORQUE, EXIT]
    assert report.confirmation is Confirmation.UNCONFIRMABLE and not report.safe
    warning = report.warning()
    assert "cannot be confirmed" in warning and "carries no motor mode" in warning and "cut power" in warning
    assert f"a {vendor} {model} reply" in warning
    assert drive.status.state is DriveState.DISABLED


# ---------------------------------------------------------------------------
# Bad input: one line each


@pytest.mark.parametrize(("changes", "words"), [
    ({"torque_limit": 18.5}, "torque_limit: expected a number > 0 and <= 18 Nm"),
    ({"mit": {"model": "AK99-1"}}, "no row for cubemars AK99-1"),
    ({"mit": {"reply_id": 0x800}}, "mit.reply_id: expected an integer from 0 to 2047"),
    ({"node_id": 0}, "node_id: expected an integer from 1 to 255"),
    ({"mit": {"colour": "red"}}, "unknown key 'mit.colour'"),
])
def test_bad_profiles_are_one_line(changes: dict[str, Any], words: str) -> None:
    with pytest.raises(ConfigError) as info:
        mit_profile(**changes)
    assert words in str(info.value) and "\n" not in str(info.value)


def test_a_damiao_node_id_must_fit_its_nibble() -> None:
    with pytest.raises(ConfigError, match="node_id: expected an integer from 1 to 15"):
        mit_profile("damiao", "DM4310", node=16)


# ---------------------------------------------------------------------------
# Every shipped MIT profile: the drive follows the codec's wrapping replies


def shipped_mit_profiles() -> list[str]:
    drivers = Path(__file__).resolve().parents[2] / "drivers"
    names = []
    for path in sorted(drivers.glob("*.yaml")):
        data = yaml.safe_load(path.read_text(encoding="utf-8"))
        if isinstance(data, dict) and data.get("protocol") == "mit":
            names.append(path.stem)
    return names


@pytest.mark.parametrize("name", shipped_mit_profiles())
def test_the_unwrapped_position_follows_a_motor_turning_many_times(name: str) -> None:
    """The motor's side packs each reply with the codec (``pack_reply``: the 16-bit
    position rolls over past +-p_max, as the firmware's does); the drive's continuous
    position stays within one step of the true angle over several wraps, both ways."""
    from dobhil.drives.mit.codec import pack_reply
    from dobhil.drives.load import load_profile
    profile = load_profile(name)
    drive = MitDrive(None, profile)  # type: ignore[arg-type]
    model = drive.model
    if model.position_at_limit != "wrap":
        pytest.skip(f"{name}: its position saturates")
    node = profile.node_id
    reply_id = int(profile.options["reply_id"])
    step = 0.4 * model.p_max        # less than half a wrap between two replies
    turns = 3 * model.wrap_period   # three wraps out, then back past the start
    angles = [k * step for k in range(int(turns / step))]
    angles += [angles[-1] - k * step for k in range(1, 2 * len(angles))]
    worst = 0.0
    for q in angles:
        data = pack_reply(model, node, q, 0.0, 0.0)
        assert drive.apply(can.Message(arbitration_id=reply_id, data=data, is_extended_id=False))
        assert drive.feedback is not None
        worst = max(worst, abs(drive.feedback.position - q))
    assert worst <= model.quanta.position


@settings(max_examples=200, deadline=None)
@given(start=st.floats(-200.0, 200.0),
       steps=st.lists(st.floats(-0.49, 0.49), min_size=1, max_size=60))
def test_the_unwrap_tracks_any_motion_slower_than_half_a_wrap_per_reply(start: float, steps: list[float]) -> None:
    """Any path whose steps between two replies stay under half the wrap period (here in
    units of it): the continuous position is the true angle less the first reading's
    whole wraps, within two position steps -- each reading is off by less than one, on
    either side: inside the range the firmware's cast floors, below it (the C cast
    truncating toward zero) it rounds up."""
    from dobhil.drives.mit.codec import pack_reply
    drive = MitDrive(None, mit_profile())  # type: ignore[arg-type]
    model = drive.model
    q = start
    first: float | None = None
    for k in range(len(steps) + 1):
        if k:
            q += steps[k - 1] * model.wrap_period
        drive.apply(frame(pack_reply(model, NODE, q, 0.0, 0.0)))
        assert drive.feedback is not None
        if first is None:
            first = q - drive.feedback.position   # whole wraps the first reading cannot show
        assert abs(drive.feedback.position + first - q) < 2 * model.quanta.position


def test_the_profiles_velocity_limit_stops_a_run_before_the_reading_clamps(
        capsys: pytest.CaptureFixture[str]) -> None:
    """A DM4310's velocity reading saturates at its range's v_max (30 rad/s): the run's bound
    is the lower of loop.velocity_limit and the profile's velocity_limit (25 rad/s, below
    v_max). With loop.velocity_limit 100 alone the reading never passed it: an open-loop run
    spun the free motor to about 50 rad/s and ended 'done'."""
    from dobhil.cli.main import main
    code = main(["run", "mit-demo", "--emulate", "--lockstep", "--duration", "0.05",
                 "--set", "drive.profile=dm4310", "--set", "loop.mode=torque", "--set", "reference.offset=1",
                 "--set", "reference.amplitude=0", "--set", "environment.contact_position=1000",
                 "--set", "loop.position_max=1000", "--set", "loop.position_min=-1000",
                 "--set", "loop.velocity_limit=100", "--set", "plant.inertia=0.001"])
    out = capsys.readouterr().out
    assert code == 1 and "stopped: velocity_limit" in out, out
    assert "above 25 (the drive profile's velocity_limit, below loop.velocity_limit 100)" in out, out
