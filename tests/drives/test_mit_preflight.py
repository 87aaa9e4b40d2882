"""The MIT preflight probe and set-zero against the hand-written motor of
tests/drives/mit_fake.py (literal reply bytes; Damiao register answers as damiao-motor's
``decode_register_reply`` reads them: ``[id_lo, id_hi, 0x33, rid, float32 LE]``)."""

from __future__ import annotations

import struct
import time
from typing import Any

import can
import pytest

from dobhil.cli.main import main
from dobhil.drives.mit.preflight import MitPreflight, set_zero
from dobhil.drives.preflight import PreflightReport, run_preflight
from dobhil.drives.registry import preflight_probe
from dobhil.errors import ConfigError, DriveTimeoutError

from tests.drives.mit_fake import ZERO, ZERO_TORQUE, FakeMotor, fake_motor, reply_cubemars, reply_damiao
from tests.drives.test_mit_drive import NODE, decode, mit_profile

WINDOW = 0.15


def preflight(bus: can.BusABC, profile: Any) -> PreflightReport:
    return run_preflight(bus, profile, period=0.001, window=WINDOW, probe=preflight_probe(profile))


def test_the_probe_asks_with_one_zero_torque_command_and_reads_the_reply() -> None:
    profile = mit_profile()
    with fake_motor(NODE, lambda data: reply_cubemars(NODE, p=0x8000, temp=31)) as (bus, motor):
        report = preflight(bus, profile)
        assert motor.frames() == [ZERO_TORQUE]   # one harmless question, nothing else
    assert report.ok, report.lines()
    summary = report.nodes[0].summary
    assert f"position {decode(0x8000, 12.5, 16):.4f} rad" in summary and "temperature 31 degC" in summary
    assert report.budget is not None
    assert [f.name for f in MitPreflight(profile).cycle_frames(0.001)] == ["MIT command", "reply"]


def test_a_silent_motor_is_one_finding_saying_mit_mode_and_the_run_refuses() -> None:
    with fake_motor(NODE, lambda data: None) as (bus, _):
        report = preflight(bus, mit_profile())
    refusing = [f for f in report.findings if f.refuses]
    assert len(refusing) == 1 and report.refuses
    text = refusing[0].text
    assert "no reply from node 1" in text and "a motor not in MIT mode answers nothing" in text
    assert "CubeMars: set MIT mode" in text


def test_another_node_answering_is_named() -> None:
    profile = mit_profile()
    with fake_motor(NODE, lambda data: None) as (bus, motor):
        motor.send(reply_cubemars(7))   # someone else's reply on the shared master id
        report = preflight(bus, profile)
    assert report.refuses
    assert "node(s) 7 replied" in next(f.text for f in report.findings if f.refuses)


def test_a_reply_length_the_layout_lacks_is_bad_input_in_one_line() -> None:
    with fake_motor(NODE, lambda data: reply_cubemars(NODE)[:6]) as (bus, _):
        with pytest.raises(ConfigError) as info:
            preflight(bus, mit_profile())
    text = str(info.value)
    assert "replied in 6 bytes" in text and "do not describe this motor" in text and "\n" not in text


def test_an_error_in_the_reply_refuses_the_run() -> None:
    with fake_motor(NODE, lambda data: reply_cubemars(NODE, error=4)) as (bus, _):
        report = preflight(bus, mit_profile())
    assert report.refuses
    assert any("reports error 4 (under voltage)" in f.text for f in report.findings)


class DamiaoWithRegisters(FakeMotor):
    """Answers register reads on 0x7FF with the given floats (None: no answer)."""

    registers: dict[int, float | None] = {}

    def answer_other(self, msg: can.Message) -> bytes | None:
        data = bytes(msg.data)
        if msg.arbitration_id != 0x7FF or data[2] != 0x33 or data[0] | data[1] << 8 != self.node:
            return None
        value = self.registers.get(data[3])
        return None if value is None else data[:4] + struct.pack("<f", value)


def damiao_preflight(registers: dict[int, float | None], state: int = 0, p: int = 0x7FFF) -> PreflightReport:
    profile = mit_profile("damiao", "DM4310")
    bus = can.Bus(interface="virtual", channel="mit-damiao-registers")
    motor = DamiaoWithRegisters("mit-damiao-registers", NODE, lambda data: reply_damiao(NODE, state, p=p))
    motor.registers = registers
    try:
        return preflight(bus, profile)
    finally:
        motor.close()
        bus.shutdown()


def test_damiao_ranges_read_from_its_registers_agree_with_the_table() -> None:
    report = damiao_preflight({21: 12.5, 22: 30.0, 23: 10.0})
    assert report.ok, report.lines()
    assert "registers PMAX 12.5, VMAX 30, TMAX 10" in report.nodes[0].summary


def test_damiao_ranges_that_do_not_match_the_table_are_bad_input() -> None:
    with pytest.raises(ConfigError) as info:
        damiao_preflight({21: 12.5, 22: 45.0, 23: 54.0})
    text = str(info.value)
    assert "ranges do not match" in text and "VMAX 45 (table 30)" in text and "TMAX 54 (table 10)" in text


def test_a_damiao_that_does_not_answer_register_reads_leaves_them_unchecked() -> None:
    report = damiao_preflight({21: None})
    assert any("did not answer the register read of PMAX" in f.text for f in report.findings)
    assert not report.refuses


def test_a_damiao_already_in_motor_mode_or_on_its_rail_refuses_the_run() -> None:
    enabled = damiao_preflight({21: 12.5, 22: 30.0, 23: 10.0}, state=1)
    assert any("already in motor mode" in f.text and f.refuses for f in enabled.findings)
    rail = damiao_preflight({21: 12.5, 22: 30.0, 23: 10.0}, p=0x0000)
    assert any("end of the encodable range" in f.text and f.refuses for f in rail.findings)


# ---------------------------------------------------------------------------
# Set zero


def test_set_zero_sends_zero_waits_its_silence_then_reads_the_new_position() -> None:
    zeroed: list[float] = []

    def answer(data: bytes) -> bytes | None:
        if data == ZERO:
            zeroed.append(time.monotonic())
            return None          # silent while it stores the offset
        return reply_cubemars(NODE, p=0x8001)

    profile = mit_profile(mit={"zero_silence": 0.05})
    with fake_motor(NODE, answer) as (bus, motor):
        result = set_zero(bus, profile, clock=time.monotonic)
        asked = time.monotonic()
        frames = motor.frames()
    assert frames == [ZERO, ZERO_TORQUE]
    assert result.position == pytest.approx(decode(0x8001, 12.5, 16))
    assert "set zero sent; after 0.05 s the position reads" in result.line()
    # the host waited at least its silence by its own clock before it asked again
    assert asked - zeroed[0] >= 0.05


def test_set_zero_without_a_reply_times_out_in_one_line() -> None:
    with fake_motor(NODE, lambda data: None) as (bus, _):
        with pytest.raises(DriveTimeoutError, match="no reply within 0.05 s after set zero"):
            set_zero(bus, mit_profile(mit={"zero_silence": 0.0}), clock=time.monotonic, timeout=0.05)


def test_check_set_zero_refuses_a_profile_that_is_not_mit(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["check", "configs/demo.yaml", "--set-zero"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0
    assert "--set-zero: expected a profile of protocol 'mit'" in err and "'odrive'" in err
