"""The drives of several axes (:mod:`dobhil.drives.axes`): CAN-id clashes between axes on one
bus, and the bus budget of all the axes of a bus.

The expected budgets are computed by hand from the frame formula (see
tests/drives/test_bus_budget.py: DLC 0 = 55 bits, 1 = 65, 4 = 95, 5 = 105, 8 = 135):
- an ODrive axis at 1 kHz: torque command 135 + encoder estimates 135 (1 ms) + heartbeat
  135 x 1/100 (100 ms) = 271.35 bits per cycle;
- a CiA 402 axis (cia402-emulated): RPDO1 95 + TPDO1 135 + TPDO2 105 + heartbeat 65 x 1/100
  = 335.65 bits, plus one SYNC of 55 bits per bus whatever the number of axes.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import can
import pytest
import yaml

from dobhil.config.axes import load_axes
from dobhil.drives.axes import DEFAULT_BUS, AxisDrive, axes_budget, axis_drives, bus_budgets, check_clashes
from dobhil.drives.load import load_profile
from dobhil.drives.registry import make_drive, protocol
from dobhil.errors import ConfigError

ODRIVE_AXIS = 135 + 135 + 135 / 100
CIA402_AXIS = 95 + 135 + 105 + 65 / 100
SYNC = 55


def axes_file(tmp_path: Path, *drives: dict[str, Any], period: float = 0.001, **top: Any) -> Path:
    data = {"loop": {"period": period}, **top,
            "axes": [{"name": f"a{i}", "drive": d} for i, d in enumerate(drives)]}
    path = tmp_path / "axes.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def drives_of(tmp_path: Path, *drives: dict[str, Any], default_bus: str | None = "virtual:x",
              **top: Any) -> tuple[AxisDrive, ...]:
    return axis_drives(load_axes(axes_file(tmp_path, *drives, **top)), tmp_path, default_bus)


def one_line(exc: pytest.ExceptionInfo[ConfigError]) -> str:
    text = str(exc.value)
    assert "\n" not in text
    return text


def odrive(node: int, **more: Any) -> dict[str, Any]:
    return {"profile": "odrive-0.6", "node_id": node, **more}


def cia402(node: int, **more: Any) -> dict[str, Any]:
    return {"profile": "cia402-emulated", "node_id": node, **more}


# -- the budget ---------------------------------------------------------------------------------


def test_two_odrive_axes_at_1_khz_use_54_percent(tmp_path: Path) -> None:
    (bus,) = axes_budget(drives_of(tmp_path, odrive(1), odrive(2)), 0.001)
    assert bus.budget.bits_per_cycle == pytest.approx(2 * ODRIVE_AXIS)          # 542.7
    assert bus.load == pytest.approx(2 * ODRIVE_AXIS / 1000)                     # 54.3 %
    assert not bus.over and bus.advice() == "" and bus.refusal() == ""
    assert bus.per_axis == (("a0", pytest.approx(ODRIVE_AXIS)), ("a1", pytest.approx(ODRIVE_AXIS)))
    assert bus.line() == ("bus budget virtual:x: 543 bits per cycle (a0 271 + a1 271) = 54.3 % of "
                          "1 Mbit/s at 1 kHz")


def test_three_odrive_axes_at_1_khz_are_over_70_percent_with_what_to_change(tmp_path: Path) -> None:
    (bus,) = axes_budget(drives_of(tmp_path, odrive(1), odrive(2), odrive(3)), 0.001)
    assert bus.load == pytest.approx(3 * ODRIVE_AXIS / 1000)                     # 81.4 %
    assert bus.over and not bus.refused
    advice = bus.advice()
    assert advice.startswith("bus virtual:x (axes a0, a1, a2): 81 % of 1 Mbit/s at 1 kHz is over 70 %: use ")
    # per loop period only the torque commands (3 x 135 bits); the encoder estimates (1 ms)
    # and heartbeats (100 ms) stream whatever the loop: 405 / P + 3 x 135 x (1000 + 10) bit/s
    # <= 0.7 x 1e6 bit/s for P >= 1.392 ms, said rounded up to 10 us: 1.4 ms
    per_cycle, per_second = 3 * 135, 3 * 135 * (1000 + 10)
    assert per_cycle / (0.7e6 - per_second) == pytest.approx(1.392e-3, abs=1e-6)
    assert "use a slower loop (loop.period >= 1.4 ms)" in advice
    assert "fewer axes on this bus" in advice and "another bus" in advice and "CAN FD" in advice
    assert "\n" not in advice


def test_three_cia402_axes_at_1_khz_are_refused_sync_counted_once(tmp_path: Path) -> None:
    drives = drives_of(tmp_path, cia402(1), cia402(2), cia402(3))
    (bus,) = bus_budgets(drives, 0.001)
    assert bus.budget.bits_per_cycle == pytest.approx(SYNC + 3 * CIA402_AXIS)   # 1062 bits: 106 %
    assert bus.shared == SYNC and bus.refused
    with pytest.raises(ConfigError) as exc:
        axes_budget(drives, 0.001)
    text = one_line(exc)
    assert text.startswith("bus virtual:x: axes a0, a1, a2 need 1062 bits per cycle, 106 % of 1 Mbit/s at 1 kHz")
    # the SYNC and TPDOs come every feedback_period (1 ms) whatever the loop where the bus
    # sends the SYNC natively: only both slower help. 1060 bits per period + the heartbeats'
    # 3 x 65 / 0.1 s = 1950 bit/s within 0.7 Mbit/s: P >= 1060 / 698050 = 1.5185 ms -> 1.52 ms
    assert "a slower loop (loop.period and the profile's feedback_period >= 1.52 ms)" in text
    assert "fewer axes on this bus" in text


def test_two_cia402_axes_at_1_khz_are_over_70_percent(tmp_path: Path) -> None:
    (bus,) = axes_budget(drives_of(tmp_path, cia402(1), cia402(2)), 0.001)
    assert bus.load == pytest.approx((SYNC + 2 * CIA402_AXIS) / 1000)           # 72.6 %
    assert bus.over and not bus.refused and "over 70 %" in bus.advice()


def cia402_profile(tmp_path: Path, feedback_period: float) -> Path:
    """cia402-emulated with another SYNC period (its EDS where the shipped one is)."""
    shipped = load_profile("cia402-emulated")
    data = yaml.safe_load(Path(shipped.directory, "cia402-emulated.yaml").read_text())
    data["feedback_period"] = feedback_period
    data["cia402"]["eds"] = str(Path(shipped.directory, data["cia402"]["eds"]))
    path = tmp_path / f"sync-{feedback_period}.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def test_a_slower_loop_and_sync_bring_three_cia402_axes_within_budget(tmp_path: Path) -> None:
    slow = {"profile": str(cia402_profile(tmp_path, 0.002))}
    drives = drives_of(tmp_path, *({**slow, "node_id": n} for n in (1, 2, 3)), period=0.002)
    (bus,) = axes_budget(drives, 0.002)
    # per cycle 55 + 3 x 335 (heartbeat share doubles: 65 x 2/100) at 2000 bits per period
    assert bus.load == pytest.approx((SYNC + 3 * (335 + 65 * 2 / 100)) / 2000)
    assert not bus.over


def test_a_slower_loop_alone_leaves_the_sync_and_its_tpdos_at_their_period(tmp_path: Path) -> None:
    # loop 2 ms, SYNC still every 1 ms (cia402-emulated): per 2 ms the RPDOs once (3 x 95),
    # the SYNC (55) and the TPDOs (3 x 240) twice, the heartbeats 3 x 65 x 2/100
    # = 285 + 2 x 775 + 3.9 = 1838.9 bits of 2000: 91.9 %, over 70 % -- counted per loop as
    # before, it was 53.2 % and called within budget, while the bus carried the SYNC every 1 ms
    (bus,) = axes_budget(drives_of(tmp_path, cia402(1), cia402(2), cia402(3), period=0.002), 0.002)
    assert bus.budget.bits_per_cycle == pytest.approx(3 * 95 + 2 * (SYNC + 3 * 240) + 3 * 65 * 2 / 100)
    assert bus.over and not bus.refused and "loop.period and the profile's feedback_period >= 1.52 ms" in bus.advice()


def test_two_sync_periods_on_one_bus_are_refused_naming_both_axes(tmp_path: Path) -> None:
    # one SYNC per bus: at 1 ms and at 2 ms it would be two SYNC producers, each node
    # answering both (the budget counted the two and the run went on); on two buses, fine
    slow = {"profile": str(cia402_profile(tmp_path, 0.002)), "node_id": 2}
    with pytest.raises(ConfigError) as exc:
        axes_budget(drives_of(tmp_path, cia402(1), slow, period=0.002), 0.002)
    assert one_line(exc).startswith("axes a0 and a1 on virtual:x ask for one SYNC of the bus every 1 ms and every "
                                    "2 ms (the profile's feedback_period)")
    apart = drives_of(tmp_path, cia402(1), {**slow, "interface": "virtual", "channel": "y"}, period=0.002)
    assert len(axes_budget(apart, 0.002)) == 2


def test_each_bus_has_its_own_budget(tmp_path: Path) -> None:
    drives = drives_of(tmp_path, odrive(1, interface="virtual", channel="a"),
                       odrive(1, interface="virtual", channel="b"), odrive(2, interface="virtual", channel="a"))
    budgets = axes_budget(drives, 0.001)
    assert [(b.bus, b.axes) for b in budgets] == [("virtual:a", ("a0", "a2")), ("virtual:b", ("a1",))]
    assert budgets[1].load == pytest.approx(ODRIVE_AXIS / 1000)


def test_axes_without_a_bus_share_the_default_one(tmp_path: Path) -> None:
    drives = drives_of(tmp_path, cia402(1), cia402(2), default_bus=None)
    assert {d.bus for d in drives} == {"socketcan:can0"}            # the profile's bus: section
    assert {d.bus for d in drives_of(tmp_path, odrive(1), default_bus="virtual:z")} == {"virtual:z"}
    no_bus = {"profile": str(write_profile(tmp_path)), "node_id": 1}
    assert drives_of(tmp_path, no_bus, default_bus=None)[0].bus == DEFAULT_BUS


def write_profile(tmp_path: Path) -> Path:
    """odrive-0.6 without its bus: section."""
    data = yaml.safe_load(Path(load_profile("odrive-0.6").directory, "odrive-0.6.yaml").read_text())
    data.pop("bus")
    path = tmp_path / "nobus.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def test_the_bit_rate_is_drive_bitrate_else_the_profiles_else_unknown(tmp_path: Path) -> None:
    (bus,) = axes_budget(drives_of(tmp_path, odrive(1), odrive(2), drive={"bitrate": 0}), 0.001)
    assert bus.budget.bitrate == load_profile("odrive-0.6").bus["bitrate"]
    no_bus = {"profile": str(write_profile(tmp_path))}
    (bus,) = axes_budget(drives_of(tmp_path, {**no_bus, "node_id": 1}, {**no_bus, "node_id": 2},
                                   drive={"bitrate": 0}), 0.001)
    assert bus.load is None and not bus.over and not bus.refused
    assert bus.line() == ("bus budget virtual:x: 543 bits per cycle (a0 271 + a1 271) at 1 kHz; bit rate "
                          "unknown (set drive.bitrate)")


def test_two_bit_rates_on_one_bus_are_refused(tmp_path: Path) -> None:
    with pytest.raises(ConfigError) as exc:
        drives_of(tmp_path, odrive(1), odrive(2, bitrate=500_000))
    assert one_line(exc) == ("axes a0 and a1 are both on virtual:x but at 1 Mbit/s and 500 kbit/s: one bus "
                             "has one bit rate; set the same drive.bitrate on both")


def test_a_node_id_out_of_the_protocols_range_names_the_axis(tmp_path: Path) -> None:
    with pytest.raises(ConfigError) as exc:
        drives_of(tmp_path, odrive(1), odrive(64))
    text = one_line(exc)
    assert text.startswith("axis a1: ") and "node_id" in text and "0..63" in text
    with pytest.raises(ConfigError) as exc:
        drives_of(tmp_path, cia402(128))
    assert one_line(exc).startswith("axis a0: ") and "1 to 127" in str(exc.value)


# -- clashes ------------------------------------------------------------------------------------


def test_one_odrive_node_twice_is_refused_naming_both_axes(tmp_path: Path) -> None:
    with pytest.raises(ConfigError) as exc:
        drives_of(tmp_path, odrive(1), odrive(2), odrive(1))
    assert one_line(exc) == ("axes a0 (odrive node 1) and a2 (odrive node 1) on virtual:x both use CAN id 0x020 "
                             "(and 31 more); give one of them another drive.node_id (or move it to another bus)")


def test_one_node_on_two_buses_is_no_clash(tmp_path: Path) -> None:
    drives_of(tmp_path, odrive(1, interface="virtual", channel="a"), odrive(1, interface="virtual", channel="b"))


def test_equal_node_ids_of_two_protocols_need_not_clash(tmp_path: Path) -> None:
    # ODrive node 1: 0x020-0x03F; CANopen node 1: 0x081, 0x181, ..., 0x701: no id in common
    drives = drives_of(tmp_path, odrive(1), cia402(1))
    assert [d.profile.node_id for d in drives] == [1, 1]


def test_an_odrive_node_on_the_canopen_sync_clashes(tmp_path: Path) -> None:
    # ODrive node 4 uses 0x080-0x09F: SYNC (0x080, shared by every CANopen node) and node 2's EMCY 0x082
    with pytest.raises(ConfigError) as exc:
        drives_of(tmp_path, cia402(2), odrive(4))
    assert one_line(exc).startswith("axes a0 (cia402 node 2) and a1 (odrive node 4) on virtual:x both use "
                                    "CAN id 0x080 (and 1 more)")


def test_canopen_nodes_share_sync_and_nmt(tmp_path: Path) -> None:
    drives_of(tmp_path, cia402(1), cia402(2), period=0.002)


def test_mit_motors_share_their_master_id_but_not_with_canopen(tmp_path: Path) -> None:
    mit = {"profile": "ak80-9"}
    drives_of(tmp_path, {**mit, "node_id": 1}, {**mit, "node_id": 2})       # replies on 0 for both
    with pytest.raises(ConfigError) as exc:   # MIT replies on 0x000: CANopen's NMT
        drives_of(tmp_path, {**mit, "node_id": 1}, cia402(2))
    assert "CAN id 0x000" in one_line(exc)
    with pytest.raises(ConfigError) as exc:   # a command to MIT node 0x20 is one of ODrive node 1's
        drives_of(tmp_path, {**mit, "node_id": 0x20}, odrive(1))
    assert "both use CAN id 0x020" in one_line(exc)


def test_a_protocol_that_lists_no_ids_is_compared_by_node_id(tmp_path: Path) -> None:
    drives = drives_of(tmp_path, odrive(1), odrive(2))
    check_clashes(drives, ids_of=lambda p: None)
    same = (drives[0], AxisDrive("b", drives[0].profile, drives[0].bus))
    with pytest.raises(ConfigError) as exc:
        check_clashes(same, ids_of=lambda p: None)
    assert one_line(exc) == ("axes a0 (odrive node 1) and b (odrive node 1) on virtual:x have one node id; "
                             "give each axis its own drive.node_id")


SHIPPED = ["odrive-0.6", "odrive-0.5", "cia402-emulated", "epos4", "ak80-9", "dm4310", "mini-cheetah",
           "moteus-r4.11"]


@pytest.mark.parametrize("name", SHIPPED)
def test_the_protocols_ids_are_the_ones_its_drive_uses(name: str) -> None:
    """One list of ids: the hook the clash check reads is the drive's own ``frame_ids``."""
    profile = load_profile(name)
    ids = protocol(profile.protocol).frame_ids(profile)
    assert ids is not None and not ids.own & ids.shared
    fd = {"protocol": can.CanProtocol.CAN_FD} if protocol(profile.protocol).fd else {}
    with can.Bus(interface="virtual", channel=f"ids-{name}", **fd) as bus:
        drive = make_drive(bus, profile)
        assert drive.frame_ids == ids.own | ids.shared
