"""``dobhil run`` and ``dobhil demo`` through ``dobhil.cli.main.main`` (in process):
the JSON summary, the demo PNG, and one-line errors with the right exit codes."""

from __future__ import annotations

import errno
import io
import json
import os
import sys
from pathlib import Path

import pytest

from dobhil.cli.main import main
from dobhil.config import load_config
from dobhil.errors import ConfigError

from .helpers import DEMO, HOST_WATCHES, host_watch_cases, realtime_profile, write_profile

EXIT_USAGE = 2


def one_line(text: str) -> str:
    lines = text.strip().splitlines()
    assert len(lines) == 1, text
    return lines[0]


def test_run_summary_json(capsys: pytest.CaptureFixture[str]) -> None:
    """``run --emulate --lockstep --summary-json`` prints exactly one JSON object with
    cycles, overruns, stop reason and the final values; the demo reaches its 1 N m."""
    code = main(["run", str(DEMO), "--emulate", "--lockstep", "--summary-json"])
    out = capsys.readouterr().out
    info = json.loads(one_line(out))
    assert code == 0
    assert info["cycles"] == 1200 and info["overruns"] == 0
    assert info["stop_reason"] == "done"
    final = info["final"]
    assert set(final) >= {"tau_ref", "tau_int_hat", "tau_int_true", "q"}
    assert final["tau_ref"] == 1.0
    assert final["tau_int_true"] == pytest.approx(1.0, abs=1e-3)
    assert final["tau_int_hat"] == pytest.approx(1.0, abs=1e-3)


def test_demo_writes_the_png(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``dobhil demo --out DIR`` runs and writes DIR/demo_run.png."""
    assert main(["demo", "--out", str(tmp_path)]) == 0
    png = tmp_path / "demo_run.png"
    assert png.is_file() and png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert str(png) in capsys.readouterr().out


def test_bad_key_is_one_line_exit_2(capsys: pytest.CaptureFixture[str]) -> None:
    code = main(["run", str(DEMO), "--emulate", "--lockstep", "--set", "loop.nokey=1"])
    err = one_line(capsys.readouterr().err)
    assert code == EXIT_USAGE and "loop.nokey" in err


def test_unknown_interface_is_one_line_exit_2(capsys: pytest.CaptureFixture[str]) -> None:
    code = main(["run", str(DEMO), "--bus", "nosuchif:x"])
    err = one_line(capsys.readouterr().err)
    assert code == EXIT_USAGE and "'nosuchif'" in err


@pytest.mark.parametrize("command", ["run", "check", "analyze"])
def test_a_channel_without_its_interface_is_one_line_exit_2(command: str,
                                                           capsys: pytest.CaptureFixture[str]) -> None:
    """An empty drive.interface with a channel names what was given, not the profile's bus
    (socketcan:can0) that an empty interface stands for."""
    code = main([command, str(DEMO), "--set", "drive.interface=", "--set", "drive.channel=x"])
    err = one_line(capsys.readouterr().err)
    assert code == EXIT_USAGE, err
    assert "drive.channel = 'x' with drive.interface = ''" in err and "socketcan:can0" not in err, err
    assert "give drive.interface too" in err


def test_lockstep_needs_emulate(capsys: pytest.CaptureFixture[str]) -> None:
    code = main(["run", str(DEMO), "--lockstep"])
    err = one_line(capsys.readouterr().err)
    assert code == EXIT_USAGE and "--emulate" in err


def test_no_drive_answers(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Real time on a channel where nobody answers: one clear line saying the drive did
    not answer, a non-zero exit, no thread or bus left (conftest). The preflight finds
    no drive and refuses before enabling (nothing was enabled: no warning); without it, the
    enable handshake times out after CLOSED_LOOP_CONTROL went out, which a drive whose
    heartbeat never reached the host may have taken: the loud line follows the stop line."""
    profile = realtime_profile(tmp_path, "odrive-0.6", enable_timeout=0.3)
    code = main(["run", str(DEMO), "--bus", f"virtual:nobody-{os.getpid()}",
                 "--set", f"drive.profile={profile}", "--preflight-window", "0.2"])
    captured = capsys.readouterr()
    lines = captured.err.splitlines()
    assert code == 1 and captured.out == ""
    assert len(lines) == 1 and "refused to enable" in lines[0] and "no heartbeat" in lines[0], captured.err
    code = main(["run", str(DEMO), "--bus", f"virtual:nobody-{os.getpid()}",
                 "--set", f"drive.profile={profile}", "--no-preflight"])
    captured = capsys.readouterr()
    lines = captured.err.splitlines()
    assert code != 0
    assert captured.out == ""
    assert len(lines) == 2 and "enable_failed" in lines[0] and "no heartbeat from node 3" in lines[0], captured.err
    assert lines[1].startswith("WARNING: drive may still be enabled: node 3 never answered: ") and \
        lines[1].endswith("; cut power"), captured.err


@pytest.mark.parametrize("value", ["inf", "nan", "-1", "0", "-inf"])
def test_bad_run_duration_is_one_line_exit_2(value: str, capsys: pytest.CaptureFixture[str]) -> None:
    code = main(["run", str(DEMO), "--emulate", "--lockstep", f"--duration={value}"])
    err = one_line(capsys.readouterr().err)
    assert code == EXIT_USAGE and "--duration" in err and "finite number of seconds > 0" in err


@pytest.mark.parametrize("value", ["-1", "nan", "inf"])
def test_bad_emulate_duration_is_one_line_exit_2(value: str,
                                                 capsys: pytest.CaptureFixture[str]) -> None:
    code = main(["emulate", str(DEMO), "--bus", "virtual:never-opened", f"--duration={value}"])
    err = one_line(capsys.readouterr().err)
    assert code == EXIT_USAGE and "--duration" in err


def test_ctrl_c_while_the_cli_starts_is_one_line(monkeypatch: pytest.MonkeyPatch,
                                                 capsys: pytest.CaptureFixture[str]) -> None:
    """SIGINT while the subcommands are still being imported (the first tens of ms)."""
    import importlib

    def interrupted(name: str) -> object:
        raise KeyboardInterrupt

    monkeypatch.setattr(importlib, "import_module", interrupted)
    code = main(["run", str(DEMO), "--emulate", "--lockstep"])
    assert code == 130 and one_line(capsys.readouterr().err) == "dobhil: interrupted"


def test_bus_error_is_a_stop_with_the_loud_line(monkeypatch: pytest.MonkeyPatch,
                                                capsys: pytest.CaptureFixture[str]) -> None:
    """The bus refuses every frame from the 500th on (ENOBUFS for good): a stop line
    ``bus_error``, exit 1 (not 2: not bad input), the summary has the safe-stop frames
    and the one loud line names the node and what to do."""
    import errno

    import can

    from dobhil.drives.emulated import LockstepBus
    sent = [0]
    original = LockstepBus.send

    def failing(self: LockstepBus, msg: can.Message, timeout: float | None = None) -> None:
        sent[0] += 1
        if sent[0] >= 500:
            raise can.CanOperationError("Failed to transmit: No buffer space available",
                                        error_code=errno.ENOBUFS)
        original(self, msg, timeout)

    monkeypatch.setattr(LockstepBus, "send", failing)
    code = main(["run", str(DEMO), "--emulate", "--lockstep", "--summary-json"])
    captured = capsys.readouterr()
    info = json.loads(one_line(captured.out))
    assert code == 1
    assert info["stop_reason"] == "bus_error" and "not sent" in info["stop_detail"]
    assert info["drive_disabled"] is False
    assert [f["what"] for f in info["safe_stop"]["frames"]] == ["zero torque", "IDLE"]
    assert not any(f["sent"] for f in info["safe_stop"]["frames"])
    # each frame retried while the bus refused it (SAFE_STOP_RETRY), every attempt counted
    assert all(f["refused"] >= 1 for f in info["safe_stop"]["frames"])
    warning = one_line(captured.err)
    assert warning.startswith("WARNING: drive may still be enabled: node 3 ")
    assert warning.endswith("; cut power")


def test_summary_counts_cycles_run_and_skipped(capsys: pytest.CaptureFixture[str]) -> None:
    """Cycles run and frames skipped are reported apart (lost feedback frames here:
    the cycles of frames never received did not run)."""
    assert main(["run", str(DEMO), "--emulate", "--lockstep", "--summary-json"]) == 0
    info = json.loads(one_line(capsys.readouterr().out))
    assert info["cycles"] == 1200 and info["skipped"] == 0 and info["timing"] == "lockstep"


def test_a_duration_too_long_to_count_is_one_line(capsys: pytest.CaptureFixture[str]) -> None:
    code = main(["run", str(DEMO), "--emulate", "--lockstep", "--duration", "1e15"])   # within loop.duration's range
    err = one_line(capsys.readouterr().err)
    assert code == EXIT_USAGE and "too many cycles" in err


@pytest.mark.parametrize("argv", [
    ["emulate", str(DEMO), "--bus", "virtual:never-opened"],
    ["run", str(DEMO), "--emulate", "--lockstep"],
    ["run", "two-axis-demo", "--emulate", "--lockstep"],
    ["montecarlo", str(DEMO), "--runs", "2", "--vary", "plant.inertia=uniform:0.2:0.3"],
])
def test_a_duration_past_loop_durations_ceiling_is_one_line(argv: list[str],
                                                            capsys: pytest.CaptureFixture[str]) -> None:
    """--duration is loop.duration given another way: held to the key's ceiling (emulate ran
    until stopped with 1e300), the ceiling read from the key as the message says it."""
    from dobhil.runtime.session import max_duration
    assert main([*argv, "--duration", "1e300"]) == EXIT_USAGE
    err = one_line(capsys.readouterr().err)
    assert f"--duration 1e+300: expected a finite number of seconds > 0 and <= {max_duration():g}" in err, err
    with pytest.raises(ConfigError, match="loop.duration"):   # the same ceiling as the key's
        load_config(DEMO, [f"loop.duration={max_duration() * 10}"])


@pytest.mark.parametrize("argv", [
    ["run", str(DEMO), "--emulate", "--lockstep", "--duration", "1e-300"],
    ["run", str(DEMO), "--emulate", "--duration", "0.0005"],
    ["run", str(DEMO), "--emulate", "--lockstep", "--set", "loop.duration=0.0005"],
    ["run", "two-axis-demo", "--emulate", "--lockstep", "--duration", "1e-300"],
    ["montecarlo", str(DEMO), "--runs", "2", "--vary", "plant.inertia=uniform:0.2:0.3", "--duration", "1e-300"],
])
def test_a_run_shorter_than_one_period_is_one_line(argv: list[str], capsys: pytest.CaptureFixture[str]) -> None:
    """A run shorter than loop.period would enable the drive and disable it without a
    command: refused in one line before anything opens."""
    assert main(argv) == EXIT_USAGE
    err = one_line(capsys.readouterr().err)
    assert "is shorter than one period (loop.period = 0.001 s); allowed: a duration of at least loop.period" in err, err


@pytest.mark.skipif(not hasattr(os, "getpriority"), reason="POSIX nice values")
def test_run_log_writer_runs_below_the_loop(tmp_path: Path) -> None:
    """``dobhil run --log``: the writer process gets nice +10 (it may lag; the loop not)."""
    from dobhil.cli.recording import abort, open_run_log
    from dobhil.cli.run_cmd import lower_writer
    from dobhil.realtime import WRITER_PRIORITY_DROP
    log = open_run_log(tmp_path / "run.mcap")
    assert log is not None and log.writer_pid is not None
    lower_writer(log)
    try:
        own = os.getpriority(os.PRIO_PROCESS, 0)
        assert os.getpriority(os.PRIO_PROCESS, log.writer_pid) == min(own + WRITER_PRIORITY_DROP, 19)
    finally:
        abort(log, KeyboardInterrupt())


@pytest.mark.skipif(not hasattr(os, "SCHED_IDLE"), reason="Linux scheduling policies")
@pytest.mark.parametrize("lockstep", [False, True])
def test_a_real_time_writer_only_gets_idle_cpu(tmp_path: Path, lockstep: bool) -> None:
    """Real time (lossy): the writer process runs SCHED_IDLE, so a waking loop preempts it at
    once; lockstep (back-pressure, the loop waits for it): normal scheduling."""
    from dobhil.cli.recording import open_run_log, record_run
    from dobhil.config import load_config
    from dobhil.runtime.session import RunSession
    config = load_config(DEMO, ["loop.duration=0.05", "loop.timing=host"])
    log = open_run_log(tmp_path / "run.mcap", fsync=False)
    assert log is not None and log.writer_pid is not None
    pid = log.writer_pid
    seen: list[int] = []
    with RunSession(config, emulate=True, lockstep=lockstep, sink=log, bus_wrapper=log.wrap_bus) as session:
        record_run(session, log, on_begin=lambda _: seen.append(os.sched_getscheduler(pid)))
    assert seen == [os.SCHED_OTHER if lockstep else os.SCHED_IDLE]


class _GoneStdout(io.StringIO):
    """A stdout that fails as ``failure`` (a reader gone from the pipe, a full device)."""

    def __init__(self, failure: OSError) -> None:
        super().__init__()
        self.failure = failure

    def write(self, text: str) -> int:
        raise self.failure


@pytest.mark.parametrize("failure", [BrokenPipeError(errno.EPIPE, "Broken pipe"),
                                     OSError(errno.ENOSPC, "No space left on device")], ids=["pipe", "full"])
@pytest.mark.parametrize("as_json", [False, True], ids=["text", "json"])
def test_the_stop_line_and_the_warning_get_out_whatever_stdout_does(
        failure: OSError, as_json: bool, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    """``dobhil run ... | head`` or ``> /dev/full``: the run's account cannot be written, yet
    its stop line and the loud line reach stderr, before stdout's error goes on to main()
    (which ends as documented: exit 141 or 2)."""
    from dobhil.cli.run_cmd import report
    from dobhil.runtime.session import RunSession, summary
    with RunSession(load_config(DEMO, ["loop.duration=0.05"]), emulate=True, lockstep=True) as session:
        result = session.run()
        info = summary(session, result)
    info["drive_warning"] = "drive may still be enabled: node 3 did not acknowledge IDLE; cut power"
    monkeypatch.setattr(sys, "stdout", _GoneStdout(failure))
    with pytest.raises(type(failure)):
        report(info, result.stop.line(), as_json=as_json)
    err = capsys.readouterr().err.splitlines()
    assert err == [f"dobhil run: {result.stop.line()}", f"WARNING: {info['drive_warning']}"]


#: the demo's design slowed to a loop period of 60 ms (stable there), every cycle in time
SLOW = ["--set", "loop.timing=host", "--set", "loop.feedback_timeout=0.5", "--set", "design.dob_bandwidth=10",
        "--set", "design.rtob_bandwidth=10", "--set", "design.force_gain=0.5"]


@pytest.mark.parametrize("period", ["0.06", "0.025"])
@pytest.mark.parametrize("argv", [["run", "--emulate", "--lockstep"], ["run", "--emulate"], ["check"]])
def test_a_period_the_drives_watchdog_cannot_tolerate_is_one_line_exit_2(
        argv: list[str], period: str, capsys: pytest.CaptureFixture[str]) -> None:
    """odrive-0.6's watchdog allows 50 ms; a command every 60 ms trips it at once (a lockstep
    run stopped host_too_slow at cycle 0: a false blame), and one every 25 ms may reach the
    drive 50 ms apart: refused, naming loop.period, watchdog_timeout and what is allowed."""
    code = main([argv[0], str(DEMO), *argv[1:], *(["--bus", "dobhil:demo"] if argv[0] == "check" else []),
                 "--set", f"loop.period={period}", *SLOW])
    captured = capsys.readouterr()
    err = one_line(captured.err)
    assert code == EXIT_USAGE and captured.out == "", err
    assert err == (f"dobhil {argv[0]}: error: loop.period = {float(period):g} s is too long for the command "
                   "watchdog of drive profile 'odrive-0.6' (watchdog_timeout = 0.05 s; a command every period "
                   "may reach the drive up to two periods apart); allowed: loop.period < 0.025 s (half of "
                   "watchdog_timeout), or a longer watchdog_timeout (on the drive too)")


@pytest.mark.parametrize("argv", [["run", "--emulate", "--lockstep"], ["run", "--emulate"], ["check"]])
@pytest.mark.parametrize("case", HOST_WATCHES)
def test_a_period_a_drives_timeout_on_the_host_cannot_tolerate_is_one_line_exit_2(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str], case: str,
        argv: list[str]) -> None:
    """One rule for every protocol whose drive times the host out (a command watchdog, a
    CiA 402 heartbeat consumer, an MIT command timeout): a period of half the timeout is
    refused in one line naming the timeout, its setting and what is allowed, exit 2, in run
    and check alike, before any bus opens."""
    def no_bus(*args: object, **kwargs: object) -> None:
        raise AssertionError("a bus was opened for a refused period")

    monkeypatch.setattr("dobhil.runtime.buses.open_bus", no_bus)
    monkeypatch.setattr("dobhil.runtime.session.open_bus", no_bus)
    watch = host_watch_cases(tmp_path)[case]
    code = main([argv[0], str(DEMO), *argv[1:], *(["--bus", "virtual:nobody"] if argv[0] == "check" else []),
                 "--set", f"drive.profile={watch.profile}", "--set", f"loop.period={watch.period}", *SLOW])
    captured = capsys.readouterr()
    err = one_line(captured.err)
    assert code == EXIT_USAGE and captured.out == "", err
    assert err.startswith(watch.refusal(f"dobhil {argv[0]}: error: ")), err
    assert "; a " in err and " every period may reach the drive up to two periods apart); " in err, err
    assert watch.allowed() in err, err


def test_a_period_within_half_the_watchdog_runs(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    # a lockstep run takes one cycle per feedback frame: the encoder estimates at the loop's period
    profile = write_profile(tmp_path, "odrive-0.6", feedback_period=0.024)
    code = main(["run", str(DEMO), "--emulate", "--lockstep", "--duration", "0.5", "--set", "loop.period=0.024",
                 "--set", f"drive.profile={profile}", *SLOW, "--summary-json"])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    summary = json.loads(captured.out)
    assert (summary["cycles"], summary["skipped"]) == (21, 0)   # every cycle of 0.5 s run, none skipped


def test_a_profile_with_its_watchdog_off_has_no_such_limit(tmp_path: Path,
                                                           capsys: pytest.CaptureFixture[str]) -> None:
    profile = realtime_profile(tmp_path, "odrive-0.6", watchdog_timeout=0, feedback_period=0.06)
    code = main(["run", str(DEMO), "--emulate", "--lockstep", "--duration", "0.5", "--set", "loop.period=0.06",
                 "--set", f"drive.profile={profile}", *SLOW])
    assert code == 0, capsys.readouterr().err


@pytest.mark.parametrize("argv", [
    ["run", "moteus-demo", "--bus", "virtual:classic-run"],
    ["check", "moteus-demo", "--bus", "virtual:classic-check"],
    ["emulate", "moteus-demo", "--bus", "virtual:classic-emulate", "--duration", "5"],
], ids=["run", "check", "emulate"])
def test_a_can_fd_protocol_on_a_classic_bus_is_one_line_everywhere(argv: list[str],
                                                                   capsys: pytest.CaptureFixture[str]) -> None:
    """A CAN FD protocol's frames cannot travel on a bus opened as classic CAN: run, check
    and emulate refuse it alike, in one line saying why (not 'no replies: check power',
    nor an emulator that answers nothing for its whole duration)."""
    assert main(argv) == EXIT_USAGE
    err = one_line(capsys.readouterr().err)
    assert "protocol moteus needs a CAN FD bus, but Virtual bus channel classic-" in err, err


@pytest.mark.parametrize("period", ["0.03", "0.002", "0.0025"])
@pytest.mark.parametrize("profile", ["epos4", "cia402-emulated"])
@pytest.mark.parametrize("argv", [["run", "--emulate", "--lockstep"],
                                  ["run", "--emulate", "--set", "loop.timing=lockstep"], ["demo"]],
                         ids=["run", "run-timing-lockstep", "demo"])
def test_a_lockstep_period_the_drives_sync_cannot_follow_is_one_line_exit_2(
        argv: list[str], profile: str, period: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str]) -> None:
    """A CiA 402 drive sends SYNC every feedback_period (1 ms in both profiles; epos4 also its
    heartbeat every 25 ms, for the node's consumer 0x1016), and the lockstep bus sends a
    periodic frame only every whole number of its steps, one per loop period: any other
    period would stop at cycle 0 with the bus and the emulator open. Refused in one line
    naming the rule and the one period allowed, exit 2, no bus opened, nothing written, and
    before the stability gate's lines (the demo's design is unstable at most of these periods)."""
    def no_bus(*args: object, **kwargs: object) -> None:
        raise AssertionError("a bus was opened for a refused lockstep period")

    monkeypatch.setattr("dobhil.runtime.session.open_bus", no_bus)
    out = tmp_path / "out"
    code = main([argv[0], str(DEMO), *argv[1:], *(["--out", str(out)] if argv[0] == "demo" else []),
                 "--set", f"drive.profile={profile}", "--set", f"loop.period={period}",
                 "--set", "loop.feedback_timeout=0.5", "--allow-unstable"])
    captured = capsys.readouterr()
    err = one_line(captured.err)
    assert code == EXIT_USAGE and captured.out == "", err
    assert err == (f"dobhil {argv[0]}: error: lockstep timing steps the emulated bus once per loop.period = "
                   f"{float(period):g} s and sends a periodic frame only every whole number of steps, but drive "
                   f"profile '{profile}' sends SYNC every 0.001 s (feedback_period); allowed in lockstep: "
                   "loop.period = 0.001 s (feedback_period), or a run in real time")
    assert not out.exists() or not any(out.iterdir())


@pytest.mark.parametrize("period", ["0.002", "0.024"])
@pytest.mark.parametrize("argv", [["run", "--emulate", "--lockstep"], ["demo"]], ids=["run", "demo"])
def test_a_lockstep_period_slower_than_streamed_feedback_is_one_line_exit_2(
        argv: list[str], period: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str]) -> None:
    """A single-axis lockstep run takes one cycle per feedback frame: an ODrive's encoder
    estimates every 1 ms under a longer loop period counted each step's extra frames as
    skipped cycles (at 24 ms: no cycle run at all, and the run said done). Refused like
    feedback timing, in one line, exit 2, no bus opened."""
    def no_bus(*args: object, **kwargs: object) -> None:
        raise AssertionError("a bus was opened for a refused lockstep period")

    monkeypatch.setattr("dobhil.runtime.session.open_bus", no_bus)
    out = tmp_path / "out"
    code = main([argv[0], str(DEMO), *argv[1:], *(["--out", str(out)] if argv[0] == "demo" else []),
                 "--set", f"loop.period={period}", "--set", "loop.feedback_timeout=0.5", "--allow-unstable"])
    captured = capsys.readouterr()
    err = one_line(captured.err)
    assert code == EXIT_USAGE and captured.out == "", err
    assert err == (f"dobhil {argv[0]}: error: lockstep timing runs one cycle per feedback frame, but drive profile "
                   f"'odrive-0.6' has encoder estimates every 0.001 s (feedback_period) and loop.period = "
                   f"{float(period):g} s; make them equal (a profile of its own with feedback_period = loop.period), "
                   "or a run in real time")
    assert not out.exists() or not any(out.iterdir())


@pytest.mark.parametrize("profile", ["mini-cheetah", "moteus-r4.11"])
def test_a_drive_that_answers_each_command_runs_lockstep_at_any_period(
        profile: str, capsys: pytest.CaptureFixture[str]) -> None:
    """No feedback frame to keep pace with: one reply per command, every cycle run."""
    code = main(["run", str(DEMO), "--emulate", "--lockstep", "--duration", "0.1", "--set", f"drive.profile={profile}",
                 "--set", "loop.period=0.005", "--set", "loop.feedback_timeout=0.5", "--allow-unstable",
                 "--summary-json"])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    summary = json.loads(captured.out)
    assert (summary["cycles"], summary["skipped"]) == (20, 0)
