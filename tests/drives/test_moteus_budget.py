"""The bus budget of a moteus run counts CAN FD frames: the arbitration phase at the nominal
rate, the data phase at the data rate (ISO 11898-1:2015 frame format, worst-case stuffing)."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from dobhil.config.axes import load_axes
from dobhil.drives import load_profile
from dobhil.drives.axes import axes_budget, axis_drives
from dobhil.drives.bus_load import frame_bits
from dobhil.drives.moteus.preflight import MoteusPreflight, fd_frame_bits


def test_fd_frame_bits_by_hand() -> None:
    # 48 bytes, 29-bit id, 1/5 Mbit/s. Nominal rate: SOF 1, base id 11, SRR 1, IDE 1, id
    # extension 18, RRS 1, FDF 1, res 1, BRS 1 = 37 bits, 9 stuff bits, CRC delimiter 1, ACK 2,
    # EOF 7, IFS 3 = 59. Data rate: ESI 1 + DLC 4 + 384 = 389, 97 stuff bits, stuff count 4,
    # CRC 21 with 7 fixed stuff bits = 518 bits = 103.6 nominal bit times.
    assert fd_frame_bits(48, extended=True, data_ratio=0.2) == 163
    # without the bit rate switch the data phase runs at the nominal rate too
    assert fd_frame_bits(48, extended=True, data_ratio=1.0) == 59 + 518
    # an FD frame of 8 bytes at one rate is longer than a classic one (stuff count, longer CRC)
    assert fd_frame_bits(8, extended=False, data_ratio=1.0) > frame_bits(8, extended=False)


def test_the_run_budget_of_the_shipped_profile() -> None:
    budget = MoteusPreflight(load_profile("moteus-r4.11")).budget(0.001, 1_000_000)
    assert budget is not None
    assert [f.name for f in budget.frames] == ["moteus command", "reply"]
    assert [f.dlc for f in budget.frames] == [48, 20]   # 38 bytes padded to 48; a 20-byte reply
    assert budget.bits_per_cycle == 163 + 82 and not budget.over
    # at 500 kbit/s nominal the 5 Mbit/s data phase takes 0.1 nominal bit times per bit, not
    # 0.2: command 59 + 518 x 0.1 -> 111, reply 34 + 238 x 0.1 -> 58; 33.8 %, not 49 %
    slow = MoteusPreflight(load_profile("moteus-r4.11")).budget(0.001, 500_000)
    assert slow is not None and slow.bits_per_cycle == 111 + 58 and slow.load == pytest.approx(0.338)
    assert "(moteus command 111 + reply 58)" in slow.line()


def test_two_moteus_axes_on_one_bus_count_their_fd_frames(tmp_path: Path) -> None:
    # each axis 163 + 82 = 245 bits as above: 490 of 1000 at 1 kHz. A several-axis budget
    # that rebuilt each frame as a classic one counted 1630 bits (a 48-byte "classic" frame)
    # and refused the run at 163 %.
    (tmp_path / "axes.yaml").write_text(yaml.safe_dump(
        {"loop": {"period": 0.001},
         "axes": [{"name": f"a{n}", "drive": {"profile": "moteus-r4.11", "node_id": n}} for n in (1, 2)]}))
    drives = axis_drives(load_axes(tmp_path / "axes.yaml"), tmp_path, "virtual:x")
    (bus,) = axes_budget(drives, 0.001)
    assert bus.budget.bits_per_cycle == 2 * (163 + 82) and bus.per_axis == (("a1", 245.0), ("a2", 245.0))
    assert not bus.over and not bus.refused
    # the axes' bus at 500 kbit/s: each axis 111 + 58 (above), 67.6 %: within the budget
    drives = axis_drives(load_axes(tmp_path / "axes.yaml", ["drive.bitrate=500000"]), tmp_path, "virtual:x")
    (bus,) = axes_budget(drives, 0.001)
    assert bus.per_axis == (("a1", 169.0), ("a2", 169.0)) and bus.load == pytest.approx(0.676) and not bus.refused


def test_the_preflight_times_the_fd_frames_it_hears_as_the_budget_does() -> None:
    """Ten 48-byte FD commands of another host with the bit rate switch, heard in a 50 ms
    window at 1 Mbit/s: 163 bit times each (above), 3.26 % of the bus; counted as classic
    frames of 48 bytes (560 bits) they read 11.2 %."""
    import can

    from dobhil.drives.preflight import run_preflight
    channel = "moteus-preflight-fd-load"
    profile = load_profile("moteus-r4.11")
    bus, other = can.Bus(interface="virtual", channel=channel), can.Bus(interface="virtual", channel=channel)
    try:
        for _ in range(10):
            other.send(can.Message(arbitration_id=0x8002, is_extended_id=True, is_fd=True, bitrate_switch=True,
                                   data=bytes(48)))
        report = run_preflight(bus, profile, period=1e-3, window=0.05, bitrate=1_000_000,
                               probe=MoteusPreflight(profile))
    finally:
        bus.shutdown()
        other.shutdown()
    assert report.bus.frames == 10 and report.bus.load == pytest.approx(10 * 163 / 0.05 / 1e6)
