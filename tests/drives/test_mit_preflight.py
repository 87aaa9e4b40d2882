"""The MIT preflight probe and set-zero against the hand-written motor of
tests/drives/mit_fake.py (literal reply bytes; Damiao register answers as damiao-motor's
``decode_register_reply`` reads them: ``[id_lo, id_hi, 0x33, rid, float32 LE]``)."""

from __future__ import annotations

import json
import struct
import time
from pathlib import Path
from typing import Any

import can
import pytest

from dobhil.cli.main import main
from dobhil.drives.mit.preflight import ASK_AGAIN, MitPreflight, set_zero
from dobhil.drives.preflight import PreflightReport, run_preflight
from dobhil.drives.registry import preflight_probe
from dobhil.errors import ConfigError, DriveTimeoutError

from tests.drives.mit_fake import ZERO, ZERO_TORQUE, FakeMotor, fake_motor, reply_cubemars, reply_damiao
from tests.drives.test_mit_drive import NODE, decode, mit_profile, saturating_table

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
    """Answers register reads on 0x7FF with the given values (float32; register 10,
    CTRL_MODE, a uint32; None: no answer)."""

    registers: dict[int, float | None] = {}

    def answer_other(self, msg: can.Message) -> bytes | None:
        data = bytes(msg.data)
        if msg.arbitration_id != 0x7FF or data[2] != 0x33 or data[0] | data[1] << 8 != self.node:
            return None
        value = self.registers.get(data[3])
        if value is None:
            return None
        return data[:4] + (struct.pack("<I", int(value)) if data[3] == 10 else struct.pack("<f", value))


def damiao_preflight(registers: dict[int, float | None], state: int = 0, p: int = 0x7FFF, silent: bool = False,
                     **section: Any) -> PreflightReport:
    profile = mit_profile("damiao", "DM4310", mit=section)
    bus = can.Bus(interface="virtual", channel="mit-damiao-registers")
    motor = DamiaoWithRegisters("mit-damiao-registers", NODE,
                                lambda data: None if silent else reply_damiao(NODE, state, p=p))
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


def test_a_damiao_silent_in_another_control_mode_is_told_so() -> None:
    """Silent to MIT frames but answering register reads: CTRL_MODE (register 10) says
    position-velocity (2), so the one line names it instead of guessing."""
    other = damiao_preflight({10: 2}, silent=True)
    text = next(f.text for f in other.findings if f.refuses)
    assert "its control mode (register 10, CTRL_MODE) is 2, not 1 (MIT): set CTRL_MODE = 1" in text
    mit = damiao_preflight({10: 1}, silent=True)
    assert "a motor not in MIT mode answers nothing" in next(f.text for f in mit.findings if f.refuses)


def test_a_damiao_already_in_motor_mode_or_on_its_rail_refuses_the_run(tmp_path: Path) -> None:
    enabled = damiao_preflight({21: 12.5, 22: 30.0, 23: 10.0}, state=1)
    assert any("already in motor mode" in f.text and f.refuses for f in enabled.findings)
    wraps = damiao_preflight({21: 12.5, 22: 30.0, 23: 10.0}, p=0x0000)
    assert not wraps.refuses   # a wrapping position has no rail
    rail = damiao_preflight({21: 12.5, 22: 30.0, 23: 10.0}, p=0x0000, models=saturating_table(tmp_path))
    assert any("end of the encodable range" in f.text and f.refuses for f in rail.findings)


# ---------------------------------------------------------------------------
# Set zero


class Stamped:
    """The host's bus, stamping each frame it sends (the host's own clock)."""

    def __init__(self, bus: can.BusABC) -> None:
        self.bus = bus
        self.sent: list[tuple[float, bytes]] = []

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self.sent.append((time.monotonic(), bytes(msg.data)))
        self.bus.send(msg, timeout)

    def recv(self, timeout: float | None = None) -> can.Message | None:
        return self.bus.recv(timeout)


def test_set_zero_sends_zero_waits_its_silence_then_reads_the_new_position() -> None:
    def answer(data: bytes) -> bytes | None:
        return None if data == ZERO else reply_cubemars(NODE, p=0x8001)   # silent after zero

    profile = mit_profile(mit={"zero_silence": 0.05})
    with fake_motor(NODE, answer) as (bus, motor):
        host = Stamped(bus)
        result = set_zero(host, profile, clock=time.monotonic)  # type: ignore[arg-type]
        frames = motor.wait_for(ZERO_TORQUE)
    assert frames == [ZERO, ZERO_TORQUE]
    assert [data for _, data in host.sent] == [ZERO, ZERO_TORQUE]
    # the host asked again only after the silence, by its own clock
    assert host.sent[1][0] - host.sent[0][0] >= 0.05
    # decoded in single precision, as the firmware does
    assert result.position == pytest.approx(decode(0x8001, 12.5, 16), abs=2e-6)
    assert "set zero sent; after 0.05 s the position reads" in result.line()


def test_set_zero_asks_again_when_the_motor_is_silent_longer_than_zero_silence() -> None:
    """A motor whose flash write outlasts ``zero_silence`` drops the first ask: the host asks
    again (every ASK_AGAIN s) and reads the position once the motor answers."""
    silent_asks = [2]

    def answer(data: bytes) -> bytes | None:
        if data == ZERO:
            return None
        if silent_asks[0]:
            silent_asks[0] -= 1
            return None
        return reply_cubemars(NODE, p=0x8001)

    with fake_motor(NODE, answer) as (bus, motor):
        host = Stamped(bus)
        result = set_zero(host, mit_profile(mit={"zero_silence": 0.0}), clock=time.monotonic,  # type: ignore[arg-type]
                          timeout=5.0)
    assert [data for _, data in host.sent] == [ZERO, ZERO_TORQUE, ZERO_TORQUE, ZERO_TORQUE]
    asked = [t for t, data in host.sent if data == ZERO_TORQUE]
    assert all(b - a >= ASK_AGAIN for a, b in zip(asked, asked[1:]))
    assert result.position == pytest.approx(decode(0x8001, 12.5, 16), abs=2e-6)


def test_set_zero_without_a_reply_times_out_in_one_line() -> None:
    with fake_motor(NODE, lambda data: None) as (bus, _):
        with pytest.raises(DriveTimeoutError, match="no reply within 0.05 s after set zero"):
            set_zero(bus, mit_profile(mit={"zero_silence": 0.0}), clock=time.monotonic, timeout=0.05)


def test_check_set_zero_refuses_a_profile_that_is_not_mit(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["check", "configs/demo.yaml", "--set-zero"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0
    assert "--set-zero: expected a profile of protocol 'mit'" in err and "'odrive'" in err


def mit_config(directory: Path, name: str, profile: str) -> Path:
    """configs/cia402-demo.yaml on an MIT profile (host timing: MIT motors do not stream)."""
    text = (Path(__file__).resolve().parents[2] / "configs" / "cia402-demo.yaml").read_text(encoding="utf-8")
    text = text.replace("profile: cia402-emulated", f"profile: {profile}")
    text = text.replace("loop:\n  period: 0.001\n", "loop:\n  period: 0.001\n  timing: host\n")
    path = directory / name
    path.write_text(text, encoding="utf-8")
    return path


@pytest.mark.parametrize("command", ["run", "check"])
def test_a_motor_whose_ranges_are_not_the_profiles_is_bad_input_before_any_enable(
        command: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A DM4310 profile on a bus whose (emulated) motor is a DM8009: its registers say
    VMAX 45, TMAX 54 where the DM4310 row says 30, 10. The preflight reads them before
    anything is enabled: one line, exit 2."""
    host = mit_config(tmp_path, "host.yaml", "dm4310")
    motor = mit_config(tmp_path, "motor.yaml", "dm8009")
    assert main([command, str(host), "--bus", f"dobhil:{motor}"]) == 2
    out = capsys.readouterr()
    err = out.err.strip()
    assert err.count("\n") == 0, err
    assert "ranges do not match: node 1's registers say VMAX 45 (table 30), TMAX 54 (table 10)" in err
    assert "cycles" not in out.out   # no run happened


def test_check_set_zero_on_an_emulated_ak80_9_prints_the_new_position(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """The emulated motor starts at the plant's -5 mrad; after set zero it reads the code
    nearest 0 (0x7FFF: -0.19 mrad on an AK80-9, one step below zero)."""
    config = mit_config(tmp_path, "mit.yaml", "ak80-9")
    assert main(["check", str(config), "--bus", f"dobhil:{config}", "--set-zero", "--json"]) == 0
    said = json.loads(capsys.readouterr().out)
    assert said["node_id"] == 1 and said["zero_silence"] == 1.0
    assert said["position"] == pytest.approx(decode(0x7FFF, 12.5, 16), abs=2e-6)
