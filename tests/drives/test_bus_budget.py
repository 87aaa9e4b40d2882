"""The bus budget: the frames a run puts on the bus per loop period,
times their bits on the wire, against the bit rate.

Every expected number is computed by hand in the comments from the frame formula
(classic standard frame: 47 bits + 8 per data byte + worst-case stuffing
floor((34 + 8 DLC - 1) / 4); ``frame_bits``), not by the code under test.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest

from dobhil.drives import load_profile
from dobhil.drives.profile import DriveProfile
from dobhil.drives.bus_load import MAX_BUDGET, BusBudget, CycleFrame, budget, frame_bits, rate_text
from dobhil.drives.registry import preflight_probe

# hand-computed frame lengths (standard 11-bit id):
#   DLC 0: 47 + 0  + floor(33 / 4) = 47 + 8  = 55    (SYNC)
#   DLC 1: 47 + 8  + floor(41 / 4) = 55 + 10 = 65    (CANopen heartbeat)
#   DLC 4: 47 + 32 + floor(65 / 4) = 79 + 16 = 95    (RPDO1: controlword + target torque)
#   DLC 5: 47 + 40 + floor(73 / 4) = 87 + 18 = 105   (TPDO2: velocity + mode display)
#   DLC 8: 47 + 64 + floor(97 / 4) = 111 + 24 = 135  (TPDO1; every ODrive frame)
REPO = Path(__file__).resolve().parents[2]
HAND_BITS = {0: 55, 1: 65, 4: 95, 5: 105, 8: 135}

CIA402_FRAMES = (CycleFrame("SYNC", 0), CycleFrame("RPDO1", 4), CycleFrame("TPDO1", 8),
                 CycleFrame("TPDO2", 5), CycleFrame("heartbeat", 1, every=0.1))


@pytest.mark.parametrize(("dlc", "bits"), sorted(HAND_BITS.items()))
def test_frame_bits_by_hand(dlc: int, bits: int) -> None:
    assert frame_bits(dlc) == bits


def test_cia402_budget_at_1_mbit_1_khz() -> None:
    # per cycle: 55 + 95 + 135 + 105 = 390 bits, plus the heartbeat's share: 65 bits every
    # 100 ms = 65 x (1 ms / 100 ms) = 0.65 bits -> 390.65 bits; one 1 ms cycle at 1 Mbit/s
    # holds 1000 bits -> 39.065 % -> "39.1 %"
    b = budget(CIA402_FRAMES, 1e-3, 1_000_000)
    assert b is not None
    assert b.bits_per_cycle == pytest.approx(390.65)
    assert b.load == pytest.approx(0.39065)
    assert b.line() == ("bus budget: 391 bits per cycle (SYNC 55 + RPDO1 95 + TPDO1 135 + TPDO2 105 + "
                        "heartbeat 65 x 0.01) = 39.1 % of 1 Mbit/s at 1 kHz")
    assert not b.over and b.advice() == ""


def test_cia402_budget_over_70_percent_says_what_to_change() -> None:
    # at 250 kbit/s one 1 ms cycle holds 250 bits: 390.65 / 250 = 156.26 % -> over 70 %.
    # higher bit rate: 500 kbit/s -> 390.65 / 500 = 78.1 % (still over); 800 kbit/s ->
    #   390.65 / 800 = 48.8 % -> "49 %".
    # slower loop at 250 kbit/s: the heartbeat is 65 bits / 0.1 s = 650 bit/s whatever the
    #   period; 390 bits per cycle must fit in 0.7 x 250000 - 650 = 174350 bit/s ->
    #   period >= 390 / 174350 = 2.2369 ms -> rounded up to 10 us: 2.24 ms.
    b = budget(CIA402_FRAMES, 1e-3, 250_000, fewer="fewer axes or TPDOs on this bus")
    assert b is not None and b.over and b.load == pytest.approx(1.5626)
    assert b.advice() == ("bus budget 156 % of 250 kbit/s at 1 kHz is over 70 %: use a higher bit rate "
                          "(800 kbit/s on the drive and the interface: 49 %), or a slower loop "
                          "(loop.period >= 2.24 ms), or fewer axes or TPDOs on this bus")


def test_two_cia402_axes_fit_three_do_not() -> None:
    # Only about two CST axes fit on 1 Mbit/s at 1 kHz. One SYNC for
    # all; per axis RPDO1 + TPDO1 + TPDO2 + heartbeat share = 95 + 135 + 105 + 0.65 = 335.65.
    # two axes: 55 + 2 x 335.65 = 726.3 bits = 72.6 % (over 70 %); three: 1061.95 = 106 %.
    axis = CIA402_FRAMES[1:]
    two = budget((CIA402_FRAMES[0], *axis, *axis), 1e-3, 1_000_000)
    assert two is not None and two.bits_per_cycle == pytest.approx(726.3) and two.over
    one = budget(CIA402_FRAMES, 1e-3, 1_000_000)
    assert one is not None and not one.over and MAX_BUDGET == 0.7


def test_odrive_budget_from_its_probe() -> None:
    # odrive-0.6: torque command 135 bits per cycle, encoder estimates 135 bits every 1 ms
    # (= the loop period: 1 per cycle), heartbeat 135 bits every 100 ms (0.01 per cycle:
    # 1.35 bits) -> 271.35 bits per 1000 -> "27.1 %"
    profile = load_profile("odrive-0.6")
    probe = preflight_probe(profile)
    assert probe is not None
    b = probe.budget(1e-3, 1_000_000)
    assert b is not None and b.bits_per_cycle == pytest.approx(271.35)
    assert b.line() == ("bus budget: 271 bits per cycle (torque command 135 + encoder estimates 135 + "
                        "heartbeat 135 x 0.01) = 27.1 % of 1 Mbit/s at 1 kHz")


def test_odrive_factory_bitrate_is_over_budget() -> None:
    # 250 kbit/s (an ODrive's default) at 1 kHz: 271.35 / 250 = 108.5 % -> "109 %".
    # 500 kbit/s: 271.35 / 500 = 54.3 % -> "54 %" fits.
    # slower loop at 250 kbit/s with the drive's streams unchanged: encoder 135 bits / 1 ms
    #   = 135000 bit/s plus heartbeat 135 / 0.1 s = 1350 bit/s; the torque command's 135 bits
    #   per cycle must fit in 0.7 x 250000 - 136350 = 38650 bit/s -> period >= 3.4929 ms ->
    #   3.5 ms (rounded up to 10 us)
    profile = dataclasses.replace(load_profile("odrive-0.6"), bus={})
    probe = preflight_probe(profile)
    assert probe is not None
    b = probe.budget(1e-3, 250_000)
    assert b is not None
    assert b.advice() == ("bus budget 109 % of 250 kbit/s at 1 kHz is over 70 %: use a higher bit rate "
                          "(500 kbit/s on the drive and the interface: 54 %), or a slower loop "
                          "(loop.period >= 3.5 ms), or a slower loop and encoder stream together (loop.period "
                          "and feedback_period, <axis>.config.can.encoder_msg_rate_ms to match)")


def test_unknown_bitrate_and_no_frames() -> None:
    # 55 + 95 = 150 bits per cycle; no bit rate: no percentage, a line that says so
    b = budget((CycleFrame("SYNC", 0), CycleFrame("RPDO1", 4)), 2e-3, None)
    assert b is not None and b.load is None and not b.over
    assert b.line() == ("bus budget: 150 bits per cycle (SYNC 55 + RPDO1 95) at 500 Hz; "
                        "bit rate unknown (set drive.bitrate)")
    assert budget((), 1e-3, 1_000_000) is None
    assert BusBudget((), 1e-3, None).bits_per_cycle == 0


def test_rate_text() -> None:
    assert [rate_text(v, "bit/s") for v in (1_000_000, 250_000, 125_000, 800)] == [
        "1 Mbit/s", "250 kbit/s", "125 kbit/s", "800 bit/s"]
    assert [rate_text(v, "Hz") for v in (1000.0, 500.0, 4000.0)] == ["1 kHz", "500 Hz", "4 kHz"]


def test_analyze_and_an_emulated_run_say_the_budget(capsys: pytest.CaptureFixture[str]) -> None:
    """dobhil analyze prints the budget of the config's drive profile at loop.period and
    drive.bitrate; a run (here emulated, no preflight) says an over-budget bus on stderr,
    and runs."""
    import json

    from dobhil.cli.main import main
    demo = str(REPO / "configs" / "demo.yaml")
    assert main(["analyze", demo]) == 0
    assert capsys.readouterr().out.splitlines()[-1] == (
        "bus budget: 271 bits per cycle (torque command 135 + encoder estimates 135 + heartbeat 135 x 0.01) "
        "= 27.1 % of 1 Mbit/s at 1 kHz")
    assert main(["analyze", demo, "--json", "--set", "drive.bitrate=250000"]) == 0
    info = json.loads(capsys.readouterr().out)["bus_budget"]
    assert info["over"] and info["load"] == pytest.approx(271.35 / 250) and info["bitrate"] == 250_000
    # 271.35 bits per 1 ms cycle at 300 kbit/s (300 bits per cycle): 90 %, over 70 %, within 100 %
    assert main(["run", demo, "--emulate", "--lockstep", "--duration", "0.01", "--set", "drive.bitrate=300000"]) == 0
    err = capsys.readouterr().err
    assert err.splitlines() == ["dobhil run: note (not refused: the run goes on): bus budget 90 % of 300 kbit/s "
                                "at 1 kHz is over 70 %: use a higher bit rate (500 kbit/s on the drive and the "
                                "interface: 54 %), or a slower loop (loop.period >= 1.84 ms), or a slower loop "
                                "and encoder stream together (loop.period and feedback_period, "
                                "<axis>.config.can.encoder_msg_rate_ms to match)"]


# 270 bits per cycle (MIT command 135 + reply 135) at 20 kHz on 1 Mbit/s (50 bits per cycle): 540 %
MIT_OVER = ["--set", "loop.period=5e-5"]
MIT_REFUSAL = ("error: bus socketcan:can0: drive profile 'ak80-9' (node 1) needs 270 bits per cycle, 540 % of "
               "1 Mbit/s at 20 kHz: more than the bus carries in one period; use a slower loop "
               "(loop.period >= 0.39 ms), or drives on CAN FD (protocol moteus)")


@pytest.mark.parametrize("argv", [["run", "--emulate"], ["run", "--emulate", "--lockstep"], ["check"]])
def test_a_single_axis_run_over_100_percent_is_refused_as_several_axes_are(
        argv: list[str], capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch) -> None:
    """Over 100 % the frames of one period do not fit in it (the run would end in a bus
    error): one line, exit 2, in the words of the several-axis refusal, before any bus
    opens -- ``dobhil check`` (its bus the profile's socketcan:can0, absent here) as ``run``."""
    from dobhil.cli.main import main
    from dobhil.runtime import buses, session

    def no_bus(*_: object, **__: object) -> None:
        raise AssertionError("a bus was opened")
    monkeypatch.setattr(buses, "open_bus", no_bus)
    monkeypatch.setattr(session, "open_bus", no_bus)
    code = main([argv[0], str(REPO / "configs" / "mit-demo.yaml"), *argv[1:], "--duration", "1", *MIT_OVER]
                if argv[0] == "run" else [*argv, str(REPO / "configs" / "mit-demo.yaml"), *MIT_OVER])
    captured = capsys.readouterr()
    assert code == 2 and captured.out == ""
    assert captured.err.splitlines() == [f"dobhil {argv[0]}: {MIT_REFUSAL}"]


def test_the_single_axis_refusal_is_the_several_axis_rule(tmp_path: Path) -> None:
    """One drive's budget is the several-axis budget of a bus with that one axis: the same
    bits, the same 100 % rule; only who needs them and the protocol's "fewer" differ."""
    from dobhil.config import load_config
    from dobhil.config.axes import SINGLE_AXIS, Axis
    from dobhil.drives.axes import AxisDrive, axes_budget, drive_budget
    from dobhil.errors import ConfigError
    config = load_config(REPO / "configs" / "mit-demo.yaml", ["loop.period=4e-4"])   # 270 / 400: 67.5 %
    one = drive_budget(Axis(SINGLE_AXIS, config), REPO / "configs")
    (several,) = axes_budget([AxisDrive("a", one_profile("ak80-9"), "socketcan:can0", 1_000_000)], 4e-4)
    assert one.load == several.load == pytest.approx(270 / 400) and not one.refused
    over = load_config(REPO / "configs" / "mit-demo.yaml", ["loop.period=2.6e-4"])   # 270 / 260: 104 %
    with pytest.raises(ConfigError, match="104 % of 1 Mbit/s at 3.846 kHz: more than the bus carries"):
        drive_budget(Axis(SINGLE_AXIS, over), REPO / "configs")


def one_profile(name: str) -> DriveProfile:
    return dataclasses.replace(load_profile(name), node_id=1)


def test_cia402_budget_counts_the_hosts_heartbeat() -> None:
    # drivers/epos4.yaml watches the host (consumer_heartbeat 0.1 s): the host sends its
    # 1-byte heartbeat (65 bits) 4 times per 0.1 s = every 25 ms = 25 cycles -> 2.6 bits per
    # cycle, on top of 390 + 0.65 (the node's own heartbeat): 393.25 bits -> "39.3 %"
    probe = preflight_probe(load_profile("epos4"))
    assert probe is not None
    b = probe.budget(1e-3, 1_000_000)
    assert b is not None and b.bits_per_cycle == pytest.approx(393.25)
    assert b.line() == ("bus budget: 393 bits per cycle (SYNC 55 + RPDO1 95 + TPDO1 135 + TPDO2 105 + "
                        "heartbeat 65 x 0.01 + host heartbeat 65 x 0.04) = 39.3 % of 1 Mbit/s at 1 kHz")


#: CiA 402 per SYNC as the probe lists it: the RPDO once per loop period, the SYNC and both
#: TPDOs once per loop period or every 1 ms (the SYNC period), whichever is more often
SYNC_1MS = "the profile's feedback_period"
CIA402_BY_SYNC = (CycleFrame("SYNC", 0, or_every=1e-3, or_every_key=SYNC_1MS), CycleFrame("RPDO1", 4),
                  CycleFrame("TPDO1", 8, or_every=1e-3, or_every_key=SYNC_1MS),
                  CycleFrame("TPDO2", 5, or_every=1e-3, or_every_key=SYNC_1MS))


def test_frames_with_their_own_period_count_at_the_faster_one() -> None:
    # loop 2 ms: RPDO 95 once, SYNC 55 + TPDOs 135 + 105 = 295 twice: 685 bits of 2000 at 1 Mbit/s
    b = budget(CIA402_BY_SYNC, 2e-3, 1_000_000)
    assert b is not None and b.bits_per_cycle == pytest.approx(95 + 2 * 295) and b.load == pytest.approx(0.3425)
    assert b.line() == ("bus budget: 685 bits per cycle (SYNC 55 x 2 + RPDO1 95 + TPDO1 135 x 2 + TPDO2 105 x 2) "
                        "= 34.2 % of 1 Mbit/s at 500 Hz")
    assert b.loop_bits() == pytest.approx(685)   # all of them come from the run (sent or answering)
    # loop 0.5 ms: once per loop period each (the SYNC sent after each command): 390 bits
    fast = budget(CIA402_BY_SYNC, 0.5e-3, 1_000_000)
    assert fast is not None and fast.bits_per_cycle == pytest.approx(390)


def test_the_slowest_loop_is_solved_where_the_sync_stops_following_it() -> None:
    # 500 kbit/s, loop 1 ms: 390 / 500 = 78 %. Below 1 ms all 390 bits come per loop period:
    # 390 / (0.7 x 500000) = 1.114 ms, not below 1 ms. From 1 ms on, the SYNC and TPDOs are
    # 295 bits every 1 ms = 295000 bit/s whatever the loop, the RPDO's 95 bits per period must
    # fit in 350000 - 295000 = 55000 bit/s: P >= 95 / 55000 = 1.7273 ms -> 1.73 ms
    b = budget(CIA402_BY_SYNC, 1e-3, 500_000)
    assert b is not None and b.over
    assert "a slower loop (loop.period >= 1.73 ms)" in b.advice()
    at = budget(CIA402_BY_SYNC, 1.73e-3, 500_000)
    assert at is not None and not at.over and at.load == pytest.approx((95 / 1.73e-3 + 295000) / 500000)


def test_when_the_sync_alone_fills_the_bus_the_advice_slows_both() -> None:
    # 250 kbit/s: the SYNC and TPDOs every 1 ms are 295000 bit/s, over 0.7 x 250000 = 175000
    # whatever the loop; with the SYNC period following the loop, all 390 bits per period:
    # P >= 390 / 175000 = 2.2286 ms -> 2.23 ms
    b = budget(CIA402_BY_SYNC, 1e-3, 250_000)
    assert b is not None and b.over
    advice = b.advice()
    assert "a slower loop (loop.period and the profile's feedback_period >= 2.23 ms)" in advice
    assert "loop.period >= " not in advice.replace("feedback_period >= ", "")


def test_the_cia402_probe_counts_its_sync_and_tpdos_at_the_sync_period() -> None:
    # drivers/epos4.yaml: SYNC every 1 ms; at loop 2 ms the bus carries two SYNCs and their TPDOs
    # per period, one RPDO, the node's heartbeat (65 x 2/100) and the host's (65 x 2/25: the
    # drive sends it every 25 SYNC periods, whatever the loop's)
    probe = preflight_probe(load_profile("epos4"))
    assert probe is not None
    b = probe.budget(2e-3, 1_000_000)
    assert b is not None and b.bits_per_cycle == pytest.approx(95 + 2 * 295 + 65 * 2 / 100 + 65 * 2 / 25)


def test_the_shortest_loop_period_is_the_shortest_frame_on_the_fastest_bus() -> None:
    """loop.period's floor (dobhil/config/schema.py) is one CAN FD frame of no data, its data
    phase instant, at 1 Mbit/s (drive.bitrate's ceiling): the bits the budget counts."""
    from dobhil.config.schema import MIN_PERIOD, key_fields
    from dobhil.drives.bus_load import fd_frame_bits
    ceiling = key_fields()["drive.bitrate"].metadata["maximum"]
    assert MIN_PERIOD == fd_frame_bits(0, extended=False, data_ratio=0.0) / ceiling
    assert key_fields()["loop.period"].metadata["minimum"] == MIN_PERIOD
