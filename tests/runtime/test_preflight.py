"""Preflight: measure the drive on the bus without enabling it.

Deterministic measurements run in lockstep on the simulated clock (exact periods); the
CLI checks run in real time against an emulator thread on a private ``virtual`` channel,
as ``dobhil emulate`` + ``dobhil check``/``dobhil run`` would on vcan0 or can0. Nothing
asserts wall-clock time: real-time checks only assert what a loaded machine cannot change
(node ids, firmware, a 10x rate difference, the refusal).
"""

from __future__ import annotations

import dataclasses
import itertools
import json
import math
import re
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import can
import pytest

from dobhil.cli.main import main
from dobhil.drives import DriveProfile, load_profile
from dobhil.drives.odrive.codec import AxisState, ControlMode
from dobhil.drives.registry import preflight_probe
from dobhil.drives.preflight import PreflightReport, Rate, Severity, run_preflight
from dobhil.drives.odrive.emulator import EmulatedODrive
from dobhil.emulator.plant import Plant
from dobhil.drives.emulated import LockstepBus
from dobhil.errors import PreflightError
from dobhil.runtime.session import RunSession

from .helpers import DEMO, REALTIME_SLACK, demo_config, realtime_profile

_CHANNELS = itertools.count()
EXIT_USAGE = 2


def bare(name: str, **changes: Any) -> DriveProfile:
    return dataclasses.replace(load_profile(name), bus={}, **changes)


def lockstep_preflight(emulated: DriveProfile, expected: DriveProfile, *, window: float = 0.5,
                       period: float = 1e-3, feedback_timeout: float | None = None) -> PreflightReport:
    """The emulator runs ``emulated`` settings; the host expects ``expected``."""
    channel = f"preflight-lock-{next(_CHANNELS)}"
    host = can.Bus(interface="virtual", channel=channel)
    emu = EmulatedODrive(can.Bus(interface="virtual", channel=channel), emulated,
                         Plant.from_config(demo_config()))
    lock = LockstepBus(host, [emu], dt=1e-3)
    try:
        return run_preflight(lock, expected, probe=preflight_probe(expected), period=period,
                             feedback_timeout=feedback_timeout, window=window, bitrate=1_000_000, clock=lock.clock,
                             stamp=lambda _m: lock.clock())
    finally:
        lock.shutdown()
        emu.close()
        host.shutdown()


def texts(report: PreflightReport, severity: Severity = Severity.MISMATCH) -> list[str]:
    return [f.text for f in report.findings if f.severity is severity]


# -- measurements, lockstep (exact) ------------------------------------------------------------

def test_factory_drive_measured_exactly() -> None:
    report = lockstep_preflight(bare("odrive-0.6-factory"), bare("odrive-0.6"))
    (node,) = report.nodes
    assert node.node == 0
    assert node.motion.count == 50 and node.motion.period == pytest.approx(0.010, abs=1e-9)
    assert node.motion.jitter == pytest.approx(0.0, abs=1e-9)
    assert node.status.count == 4 and node.status.period == pytest.approx(0.100, abs=1e-9)
    assert "firmware 0.6.10 (Get_Version)" in node.summary and "IDLE" in node.summary
    found = texts(report)
    assert found == [
        "node 3 is not on the bus, node(s) 0 are: set <axis>.config.can.node_id = 3 on the drive, "
        "or node_id: 0 in profile 'odrive-0.6'",
        "set <axis>.config.can.encoder_msg_rate_ms = 1 (now 10 ms; loop.period 1 ms would use each "
        "sample 10 times)",
        "node 0's watchdog looks off (idle, unfed for 0.5 s, no WATCHDOG_TIMER_EXPIRED): set "
        "<axis>.config.enable_watchdog = True and <axis>.config.watchdog_timeout = 0.05",
    ]
    assert report.stale_feedback and not report.ok


def test_matching_drive_passes_and_its_idle_watchdog_bit_is_expected() -> None:
    report = lockstep_preflight(bare("odrive-0.6"), bare("odrive-0.6"))
    assert report.ok, report.lines()
    (node,) = report.nodes
    assert node.motion.count == 500 and node.motion.period == pytest.approx(1e-3, abs=1e-9)
    assert "WATCHDOG_TIMER_EXPIRED" in node.summary   # idle and unfed: expected, enable clears it
    assert "(expected: the watchdog is on and nothing feeds an idle axis; enable clears it)" in node.summary
    assert report.lines()[-1] == "preflight: ok"
    assert 0 < (report.bus.load or 0) < (report.bus.run_load or 0) < 1
    assert report.lines()[1] == ("bus budget: 271 bits per cycle (torque command 135 + encoder estimates 135 + "
                                 "heartbeat 135 x 0.01) = 27.1 % of 1 Mbit/s at 1 kHz")


@pytest.mark.parametrize(("drive", "profile", "words"), [
    ("odrive-0.5", "odrive-0.6", "runs firmware 0.5 (heartbeat layout; no Get_Version reply), profile "
                                 "'odrive-0.6' is for 0.6: use drive.profile odrive-0.5"),
    ("odrive-0.6", "odrive-0.5", "runs firmware 0.6.10 (Get_Version), profile 'odrive-0.5' is for 0.5: "
                                 "use drive.profile odrive-0.6"),
])
def test_firmware_family_mismatch_names_the_profile_to_use(drive: str, profile: str, words: str) -> None:
    report = lockstep_preflight(bare(drive), bare(profile))
    assert any(words in text for text in texts(report)), report.lines()
    assert not report.stale_feedback


def test_05_drive_with_05_profile_passes() -> None:
    report = lockstep_preflight(bare("odrive-0.5"), bare("odrive-0.5"))
    assert report.ok, report.lines()


def test_slow_heartbeat_and_missing_encoder_stream() -> None:
    report = lockstep_preflight(bare("odrive-0.6", heartbeat_period=0.4), bare("odrive-0.6"), window=1.0)
    assert "set <axis>.config.can.heartbeat_msg_rate_ms = 100 (now 400 ms;" in texts(report)[0]
    assert not report.stale_feedback
    # a window too short to see two heartbeats of the profile's period: a note, not a verdict
    report = lockstep_preflight(bare("odrive-0.6"), bare("odrive-0.6"), window=0.15)
    assert report.ok and texts(report, Severity.NOTE) == [
        "a 150 ms window cannot measure a 100 ms heartbeat: listen at least 0.3 s"]
    # none heard in a window shorter than one period of the profile's heartbeat: not "off"
    slow = bare("odrive-0.6", heartbeat_period=10.0)
    report = lockstep_preflight(slow, slow, window=0.5)
    assert report.ok and texts(report, Severity.NOTE) == [
        "a 500 ms window cannot measure a 10000 ms heartbeat: listen at least 30 s"], report.lines()
    # a period the window cannot resolve at all (one frame)
    report = lockstep_preflight(bare("odrive-0.6", feedback_period=0.4), bare("odrive-0.6"), window=0.5)
    assert any("encoder_msg_rate_ms = 1 (now 1 frame in 500 ms)" in t for t in texts(report)), report.lines()
    assert report.stale_feedback


def test_feedback_gap_above_the_timeout_is_a_mismatch() -> None:
    report = lockstep_preflight(bare("odrive-0.6", feedback_period=4e-3), bare("odrive-0.6", feedback_period=4e-3),
                                period=4e-3, feedback_timeout=3e-3)
    assert any("paused up to 4 ms, longer than loop.feedback_timeout 3 ms" in t for t in texts(report))


def test_a_mismatch_the_run_does_not_refuse_does_not_claim_the_run_would_stop(
        capsys: pytest.CaptureFixture[str]) -> None:
    """A feedback pause in the window is a mismatch the run goes on with;
    neither the finding, nor check's verdict, nor the run's preflight line may say the
    run would stop."""
    from dobhil.cli.run_cmd import report_preflight
    report = lockstep_preflight(bare("odrive-0.6", feedback_period=4e-3), bare("odrive-0.6", feedback_period=4e-3),
                                period=4e-3, feedback_timeout=3e-3)
    assert not report.ok and not report.refuses
    assert not any("would stop" in line for line in report.lines()), report.lines()
    assert report.lines()[-1].endswith("dobhil run does not refuse these: it prints them and runs")
    capsys.readouterr()
    report_preflight(report)
    err = capsys.readouterr().err
    mismatches = [line for line in err.splitlines() if "mismatch" in line]
    assert mismatches and all("the run goes on" in line for line in mismatches), err


def test_an_axis_already_in_closed_loop_refuses_the_run() -> None:
    """'another host may be driving it; set it IDLE first' is acted on: the run refuses."""
    from dobhil.drives.odrive import codec
    from dobhil.drives.preflight import BusReport, NodeReport
    profile = bare("odrive-0.6")
    probe = preflight_probe(profile)
    assert probe is not None
    heartbeat = codec.encode(codec.Heartbeat(0, AxisState.CLOSED_LOOP_CONTROL), node_id=3).data
    node = NodeReport(3, Rate.of([0.0, 1e-3]), Rate.of([0.0, 0.1]), bytes(heartbeat), window=0.5)
    findings = probe.node_findings(node)
    assert [f.refuses for f in findings if "CLOSED_LOOP_CONTROL" in f.text] == [True]
    report = PreflightReport("odrive-0.6", 3, 0.5, (node,), BusReport("ACTIVE", 0, 0, 0.0, None, 0.0),
                             tuple(findings))
    assert report.refuses and not report.stale_feedback
    assert report.lines()[-1].endswith("dobhil run refuses to enable: node 3 is already in CLOSED_LOOP_CONTROL")
    assert report.as_dict()["refuses_run"]


def test_a_bus_that_cannot_be_opened_names_the_emulated_bus(capsys: pytest.CaptureFixture[str]) -> None:
    """Without CAN hardware, check says how to try it anyway."""
    code = main(["check", str(DEMO), "--bus", "socketcan:dobhil-no-such-can"])
    err = capsys.readouterr().err
    assert code == EXIT_USAGE and err.count("\n") == 1
    assert "cannot be opened" in err and "--bus dobhil:demo" in err and "--emulate" in err, err
    code = main(["check", str(DEMO), "--bus", "dobhil:demo", "--window", "0.3", "--json"])
    report = json.loads(capsys.readouterr().out)
    assert code in (0, 1) and [n["node"] for n in report["nodes"]] == [3]  # the hint's bus works


def test_rate_statistics() -> None:
    r = Rate.of([0.0, 0.001, 0.003, 0.004])
    assert r.count == 4 and r.period == pytest.approx(0.004 / 3)
    assert r.max_gap == pytest.approx(0.002) and r.jitter == pytest.approx(math.sqrt(2 / 9) * 1e-3)
    assert Rate.of([1.0]).period is None and Rate.of([]).count == 0


# -- the bus -----------------------------------------------------------------------------------

class StateBus(can.BusABC):
    """A virtual bus that reports a python-can bus state."""

    def __init__(self, channel: str, state: can.BusState) -> None:
        self._inner = can.Bus(interface="virtual", channel=channel)
        self._state = state
        super().__init__(channel=channel)

    @property
    def state(self) -> can.BusState:
        return self._state

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self._inner.send(msg, timeout)

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        return self._inner.recv(timeout), False

    def shutdown(self) -> None:
        self._inner.shutdown()
        super().shutdown()


def test_bus_error_state_and_error_frames_are_mismatches() -> None:
    channel = f"preflight-state-{next(_CHANNELS)}"
    bus = StateBus(channel, can.BusState.PASSIVE)
    other = can.Bus(interface="virtual", channel=channel)
    try:
        other.send(can.Message(is_error_frame=True, arbitration_id=0x20000080, is_extended_id=True))
        profile = bare("odrive-0.6")
        report = run_preflight(bus, profile, probe=preflight_probe(profile), period=1e-3, window=0.05)
    finally:
        bus.shutdown()
        other.shutdown()
    found = " | ".join(texts(report))
    assert "bus state PASSIVE" in found and "1 error frames" in found
    assert "no heartbeat or encoder estimates from any node" in found and report.stale_feedback


def test_bus_too_slow_for_the_loop() -> None:
    """250 kbit/s (an ODrive's default) cannot carry 1 kHz feedback plus 1 kHz commands."""
    channel = f"preflight-slow-{next(_CHANNELS)}"
    host = can.Bus(interface="virtual", channel=channel)
    emu = EmulatedODrive(can.Bus(interface="virtual", channel=channel), bare("odrive-0.6"),
                         Plant.from_config(demo_config()))
    lock = LockstepBus(host, [emu], dt=1e-3)
    try:
        profile = bare("odrive-0.6")
        report = run_preflight(lock, profile, probe=preflight_probe(profile), period=1e-3, window=0.5,
                               bitrate=250_000, clock=lock.clock, stamp=lambda _m: lock.clock())
    finally:
        lock.shutdown()
        emu.close()
        host.shutdown()
    assert any(t.startswith("bus load with the run's commands would be") and "of 250000 bit/s" in t
               for t in texts(report)), report.lines()
    # the budget, computed (tests/drives/test_bus_budget.py: 271.35 bits per 250 = 109 %):
    # its line after the measured one, and a finding that says what to change, not refused
    line = report.lines()[1]
    assert line.startswith("bus budget: 271 bits per cycle") and "108.5 % of 250 kbit/s" in line
    assert any(t.startswith("bus budget 109 % of 250 kbit/s at 1 kHz is over 70 %: use a higher bit rate")
               for t in texts(report)), report.lines()
    assert report.as_dict()["bus_budget"]["over"] and not report.refuses


# -- dobhil check / dobhil run against an emulator thread (real time) --------------------------

@pytest.fixture
def emulated(request: pytest.FixtureRequest) -> Iterator[tuple[str, EmulatedODrive]]:
    """An emulator thread running profile ``request.param`` on a fresh virtual channel."""
    channel = f"preflight-rt-{next(_CHANNELS)}"
    profile = request.param if isinstance(request.param, DriveProfile) else bare(request.param)
    emu = EmulatedODrive(can.Bus(interface="virtual", channel=channel), profile,
                         Plant.from_config(demo_config()))
    emu.start()
    try:
        yield channel, emu
    finally:
        emu.close()


@pytest.mark.parametrize("emulated", ["odrive-0.6-factory"], indirect=True)
def test_check_and_run_against_a_factory_drive(emulated: tuple[str, EmulatedODrive],
                                               capsys: pytest.CaptureFixture[str]) -> None:
    channel, emu = emulated
    code = main(["check", str(DEMO), "--bus", f"virtual:{channel}"])
    out = capsys.readouterr().out
    assert code == 1, out
    assert "mismatch: node 3 is not on the bus, node(s) 0 are: set <axis>.config.can.node_id = 3" in out
    assert re.search(r"mismatch: set <axis>\.config\.can\.encoder_msg_rate_ms = 1 \(now (9\.\d+|10\.?\d*) ms", out), out
    assert out.splitlines()[-1].endswith("a run would sample stale feedback")

    code = main(["check", str(DEMO), "--bus", f"virtual:{channel}", "--json", "--window", "0.3"])
    report = json.loads(capsys.readouterr().out)
    assert code == 1 and report["stale_feedback"] and report["nodes"][0]["node"] == 0

    code = main(["run", str(DEMO), "--bus", f"virtual:{channel}"])
    captured = capsys.readouterr()
    assert code == 1 and captured.out == ""
    lines = captured.err.splitlines()
    assert lines[-1].startswith("dobhil run: refused to enable: node 3 is not on the bus"), captured.err
    assert any("watchdog looks off" in line for line in lines[:-1])   # printed, not the reason
    assert any(re.search(r"encoder_msg_rate_ms = 1 \(now (9\.\d+|10\.?\d*) ms", line) for line in lines)
    # nothing was enabled: the drive never left its power-on mode and state
    assert emu.axis_state is AxisState.IDLE and emu.control_mode == ControlMode.POSITION_CONTROL


#: commands of one check at most, against an emulator thread that keeps its settings only
#: while it is run: one that failed while it skipped ticks (``EmulatedDrive.overruns``, its own
#: count: a tick more than 10 periods late is skipped, its frames never sent) may have heard a
#: drive slower than its settings -- rightly -- and is made again. (A run in this process
#: starves it too: the loop holds the interpreter while it spins for each frame.)
STARVED_COMMANDS = 3


def unstarved(emu: EmulatedODrive, command: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    """``main(command)``, made again while it failed and the emulator thread skipped ticks
    during it (up to :data:`STARVED_COMMANDS`): the last one's exit code, standard output and
    error."""
    for _ in range(STARVED_COMMANDS):
        skipped = emu.overruns
        code = main(command)
        out, err = capsys.readouterr()
        if code == 0 or emu.overruns == skipped:
            break
    return code, out, err


@pytest.mark.parametrize("emulated", ["odrive-0.6"], indirect=True)
def test_check_passes_with_matching_settings(emulated: tuple[str, EmulatedODrive],
                                             capsys: pytest.CaptureFixture[str]) -> None:
    channel, emu = emulated
    code, out, _ = unstarved(emu, ["check", str(DEMO), "--bus", f"virtual:{channel}", "--set", REALTIME_SLACK[0]],
                             capsys)
    assert code == 0, out
    assert out.splitlines()[-1] == "preflight: ok"
    assert "node 3: encoder estimates every" in out and "firmware 0.6.10 (Get_Version)" in out


def test_run_passes_preflight_and_runs(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    profile_path = realtime_profile(tmp_path, "odrive-0.6")
    channel = f"preflight-run-{next(_CHANNELS)}"
    emu = EmulatedODrive(can.Bus(interface="virtual", channel=channel), load_profile(profile_path),
                         Plant.from_config(demo_config()))
    emu.start()
    try:
        code, out, err = unstarved(emu, ["run", str(DEMO), "--bus", f"virtual:{channel}", "--duration", "0.1",
                                         "--set", f"drive.profile={profile_path}", "--set", REALTIME_SLACK[0]],
                                   capsys)
    finally:
        emu.close()
    assert "dobhil run: preflight: node 3: encoder estimates every" in err, err
    assert code == 0, err + out
    assert "stopped: done" in out, out


def test_session_preflight_refuses_before_enable(tmp_path: Path) -> None:
    """The same refusal for a program using RunSession: PreflightError from run(), with
    the report; nothing was sent but the read-only Get_Version request."""
    profile_path = realtime_profile(tmp_path, "odrive-0.6")
    channel = f"preflight-session-{next(_CHANNELS)}"
    config = demo_config(f"drive.profile={profile_path}")
    emu = EmulatedODrive(can.Bus(interface="virtual", channel=channel), bare("odrive-0.6-factory"),
                         Plant.from_config(config))
    emu.start()
    try:
        with RunSession(config, bus=f"virtual:{channel}", preflight_window=0.3) as session:
            with pytest.raises(PreflightError, match="encoder_msg_rate_ms = 1") as info:
                session.run()
            assert info.value.report is session.preflight_report
    finally:
        emu.close()
    # all it sent: Get_Version RTRs to node 3 (nobody there) and to node 0 (found)
    assert emu.frames_received == 2 and emu.frames_rejected == 0
    assert emu.axis_state is AxisState.IDLE and emu.control_mode == ControlMode.POSITION_CONTROL


@pytest.mark.parametrize("argv", [["--window", "0"], ["--window", "nan"], ["--window", "1e400"]])
def test_bad_window_is_one_line_exit_2(argv: list[str], capsys: pytest.CaptureFixture[str]) -> None:
    code = main(["check", str(DEMO), "--bus", "virtual:nobody", *argv])
    err = capsys.readouterr().err.strip()
    assert code == EXIT_USAGE and "\n" not in err and "--window" in err


def test_run_preflight_window_is_validated(capsys: pytest.CaptureFixture[str]) -> None:
    code = main(["run", str(DEMO), "--bus", "virtual:nobody", "--preflight-window", "-1"])
    err = capsys.readouterr().err.strip()
    assert code == EXIT_USAGE and "--preflight-window" in err and "\n" not in err


def test_emulated_runs_skip_the_preflight(capsys: pytest.CaptureFixture[str]) -> None:
    """--emulate builds the emulator from the profile itself: nothing to measure."""
    code = main(["run", str(DEMO), "--emulate", "--lockstep", "--duration", "0.01", "--summary-json"])
    info = json.loads(capsys.readouterr().out)
    assert code == 0 and info["preflight"] is None


# -- SocketCAN link facts (the kernel's JSON, literal) -----------------------------------------

IP_CAN0 = """[{"ifindex":4,"ifname":"can0","flags":["NOARP","UP","LOWER_UP","ECHO"],"mtu":16,
"qdisc":"pfifo_fast","operstate":"UP","linkmode":"DEFAULT","group":"default","txqlen":10,
"link_type":"can","promiscuity":0,"min_mtu":0,"max_mtu":0,"linkinfo":{"info_kind":"can",
"info_data":{"ctrlmode":[],"state":"BUS-OFF","berr_counter":{"tx":248,"rx":0},"restart_ms":0,
"bittiming":{"bitrate":250000,"sample_point":"0.875","tq":250,"prop_seg":6,"phase_seg1":7,
"phase_seg2":2,"sjw":1,"brp":10}}},"num_tx_queues":1,"num_rx_queues":1}]"""
IP_VCAN0 = """[{"ifindex":5,"ifname":"vcan0","flags":["NOARP","UP","LOWER_UP"],"mtu":72,
"qdisc":"noqueue","operstate":"UNKNOWN","txqlen":1000,"link_type":"can",
"linkinfo":{"info_kind":"vcan"}}]"""


def test_socketcan_link_facts_parse_and_compare() -> None:
    from dobhil.drives.socketcan_link import LinkInfo, link_problems, parse_link
    can0 = parse_link(IP_CAN0)
    assert can0 == LinkInfo("can0", "can", 10, "BUS-OFF", 250000, 0, up=True)
    problems = link_problems(can0, 1_000_000)
    assert [bad for bad, _ in problems] == [True, True, False, True]
    texts_ = [t for _, t in problems]
    assert texts_[0].startswith("can0 is BUS-OFF")
    assert texts_[1] == "can0 txqueuelen 10: bursts fail with ENOBUFS; sudo ip link set can0 txqueuelen 1000"
    assert "restart-ms 100" in texts_[2] and "runs at 250000 bit/s, drive.bitrate is 1000000" in texts_[3]
    vcan0 = parse_link(IP_VCAN0)
    assert vcan0 == LinkInfo("vcan0", "vcan", 1000, None, None, None, up=True) and link_problems(vcan0, 1_000_000) == []
    assert parse_link("") is None and parse_link("[]") is None and parse_link('[{"txqlen": "x"}]') is not None
    assert parse_link('[{"ifname": "x"}]') == LinkInfo("x", "", None, None, None, None, up=None)


#: ``ip -details -json link show vxb`` after ``ip link set vxb down`` (Debian 12's kernel 6.1)
IP_VXB_DOWN = """[{"ifindex":3,"link":"vxa","ifname":"vxb","flags":["NOARP"],"mtu":72,"qdisc":"noqueue",
"operstate":"DOWN","linkmode":"DEFAULT","group":"default","txqlen":1000,"link_type":"can","promiscuity":0,
"allmulti":0,"min_mtu":0,"max_mtu":0,"linkinfo":{"info_kind":"vxcan"},"num_tx_queues":1,"num_rx_queues":1}]"""


def test_an_interface_that_is_down_is_its_only_problem() -> None:
    from dobhil.drives.socketcan_link import link_problems, parse_link
    down = parse_link(IP_VXB_DOWN)
    assert down is not None and down.up is False
    assert link_problems(down, 1_000_000) == [
        (True, "vxb is down: nothing can be sent or heard on it; sudo ip link set vxb up")]


def test_a_run_on_an_interface_that_is_down_is_refused_in_one_line(monkeypatch: pytest.MonkeyPatch,
                                                                   capsys: pytest.CaptureFixture[str]) -> None:
    """The kernel says the interface is down: the preflight neither asks nor listens, and
    the run is refused in one line naming what to do (nothing is sent, nothing enabled)."""
    from can.interfaces.virtual import VirtualBus

    from dobhil.drives import preflight
    from dobhil.drives.socketcan_link import parse_link
    sent: list[can.Message] = []
    monkeypatch.setattr(preflight, "link_info", lambda bus: parse_link(IP_VXB_DOWN))
    monkeypatch.setattr(VirtualBus, "send",
                        lambda self, msg, timeout=None: sent.append(msg))
    code = main(["run", str(DEMO), "--bus", f"virtual:down-{next(_CHANNELS)}"])
    err = capsys.readouterr().err
    assert code == 1 and sent == []
    assert err == ("dobhil run: refused to enable: vxb is down: nothing can be sent or heard on it; sudo ip link "
                   "set vxb up (dobhil check CONFIG shows all it measured; --no-preflight skips)\n"), err


def test_forced_preflight_in_lockstep_measures_simulated_time() -> None:
    """preflight=True on a lockstep session listens on the simulated clock (exact periods)."""
    with RunSession(demo_config(), emulate=True, lockstep=True, duration=0.01, preflight=True,
                    preflight_window=0.35) as session:
        result = session.run()
        report = session.preflight_report
    assert report is not None and report.ok, report and report.lines()
    assert report.nodes[0].motion.period == pytest.approx(1e-3, abs=1e-12)
    assert result.stop.reason.name == "DONE"


def test_odrive_advice_is_in_whole_milliseconds_the_drive_takes() -> None:
    """An ODrive takes its rates in whole milliseconds (encoder_msg_rate_ms is an integer; 0
    is off): a loop of 0.5 ms is told to run at the drive's fastest, 1 ms, never to set
    encoder_msg_rate_ms = 0.5; a drive streaming every 4 ms for a 2.5 ms profile is told 2."""
    report = lockstep_preflight(bare("odrive-0.6"), bare("odrive-0.6"), period=5e-4)
    assert texts(report) == [
        "drive profile 'odrive-0.6' has encoder estimates every 0.001 s (feedback_period), slower than "
        "loop.period = 0.0005 s; set loop.period >= 0.001 s (a drive sends its encoder estimates at most "
        "every 0.001 s)",
        "set loop.period and feedback_period >= 1 ms, the drive's fastest (now 1 ms; loop.period 0.5 ms "
        "would use each sample 2 times)"]
    slow = lockstep_preflight(bare("odrive-0.6", feedback_period=4e-3), bare("odrive-0.6", feedback_period=2.5e-3),
                              period=5e-3)
    assert "set <axis>.config.can.encoder_msg_rate_ms = 2 (now 4 ms; the profile's feedback_period is 2.5 ms; " \
        "each loop period still gets a fresh sample)" in texts(slow)


def test_a_drive_slower_than_the_profile_but_fast_enough_for_the_loop_is_not_called_stale() -> None:
    """The profile promises 0.5 ms, the drive sends every 1 ms, the loop runs at 1 ms: a
    mismatch with the profile, but each period gets a fresh sample (no '1 times'), and the
    run is not refused."""
    report = lockstep_preflight(bare("odrive-0.6"), bare("odrive-0.6", feedback_period=5e-4))
    (text,) = [t for t in texts(report) if "feedback_period >= 1 ms, the drive's fastest" in t]
    assert "each loop period still gets a fresh sample" in text and "times" not in text, text
    assert not report.refuses and report.lines()[-1].endswith("it prints them and runs")
