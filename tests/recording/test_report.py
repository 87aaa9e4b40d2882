"""``dobhil report``: figures and summary of a recorded run; the demo's default log."""

from __future__ import annotations

import json
import math
import re
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from dobhil.run_report import RunData, detect_steps, latency_stats, summary_text
from dobhil.drives.bus_load import frame_bits
from dobhil.cli.main import main
from tests.recording.test_run_logging import logged_lockstep_run


def test_detect_steps() -> None:
    t = np.arange(10) * 1e-3
    ref = np.array([0.2] * 5 + [1.0] * 5)
    assert detect_steps(t, ref) == [(0, 0.0, 0.2), (5, 0.2, 1.0)]


def test_a_step_in_a_recovered_logs_gap_has_no_metrics_and_the_prediction_stops_at_it() -> None:
    """A log recovered with cycles 100..149 lost, the reference stepping among them: the first
    sample kept after them is no step's start (no metrics, the cycles named, the text says
    so), and the prediction, a model run cycle by cycle, stops at the gap."""
    from dobhil.config import load_config
    from dobhil.run_report import _step_line, prediction, step_infos
    cycles = np.r_[np.arange(0, 100), np.arange(150, 300)]
    ref = np.where(cycles < 120, 0.2, 1.0)
    data = RunData(path="x", config=load_config("demo"), metadata={}, t=cycles * 1e-3,
                   signals={"cycle": cycles.astype(float), "tau_ref": ref, "tau_int_hat": ref.copy(),
                            "q_true": np.ones(cycles.size)})
    first, lost = step_infos(data)
    assert first.time == 0.0 and first.metrics is not None
    assert lost.time == pytest.approx(0.15) and lost.metrics is None and "cycles 100..149" in lost.why
    assert "not taken in contact" not in _step_line(lost.__dict__)
    y, info = prediction(data)
    assert info["available"] and y is not None
    assert np.isfinite(y[:100]).all() and np.isnan(y[100:]).all()


def test_frame_bits() -> None:
    assert frame_bits(8) == 47 + 64 + 24 and frame_bits(0) == 47 + 8


def test_no_bus_load_from_fd_frames_that_switched_bit_rate_at_an_unrecorded_data_rate() -> None:
    """1000 CAN FD frames of 48 bytes in 1 s at 1 Mbit/s: without the bit rate switch each
    takes 59 + 518 bit times (tests/drives/test_moteus_budget.py), with it at 5 Mbit/s 163;
    with it and no data bit rate in the log the time is unknown, and the report says so."""
    from collections import Counter
    from dobhil.run_report import bus_stats

    def load(brs: bool, bus: dict[str, Any]) -> dict[str, Any]:
        data = RunData(path="x", config=None, metadata={"bus": bus}, t=np.array([0.0, 1.0]),
                       frames={"/can/tx": [48] * 1000},
                       frame_kinds={"/can/tx": Counter({(48, True, True, brs): 1000})}, span_s=1.0)
        return bus_stats(data)

    assert load(False, {"bitrate": "1000000"})["bus_load"] == pytest.approx(0.577)
    assert load(True, {"bitrate": "1000000", "data_bitrate": "5000000"})["bus_load"] == pytest.approx(0.163)
    unknown = load(True, {"bitrate": "1000000"})
    assert unknown["bus_load"] is None and "data bit rate" in unknown["bus_load_why"]


def test_demo_then_report(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["demo", "--out", str(tmp_path), "--set", "loop.duration=0.8"]) == 0
    logs = list(tmp_path.glob("run-*.mcap"))
    assert len(logs) == 1
    capsys.readouterr()
    out = tmp_path / "report"
    assert main(["report", str(logs[0]), "--out", str(out)]) == 0
    text, err = capsys.readouterr()
    # the progress counts to its total: the messages the report reads (README, a line at the end)
    assert re.fullmatch(r"report: (\d+)/\1 messages \(100 %\), .*", err.splitlines()[-1])
    assert "step at 0.600 s" in text and "bus:" in text
    for name in ("force", "tracking_error", "position", "commands", "loop_timing"):
        assert (out / f"{name}.png").stat().st_size > 10000
    summary = json.loads((out / "summary.json").read_text())
    # the first "step" (0 -> 0.2 N m) crosses the gap and hits the environment: no step
    # metrics (they would be an 825 % "overshoot"); the step at 0.6 s is taken in contact
    approach, step = summary["steps"]
    assert approach["time"] == 0.0 and approach["in_contact"] is False and approach["metrics"] is None
    assert "touched the environment at 0.1" in approach["why"]
    assert "step at 0.000 s (0 -> 0.2 N m): not taken in contact" in text
    assert step["time"] == pytest.approx(0.6) and step["in_contact"] and step["metrics"]["overshoot_pct"] < 100
    assert summary["contact"]["source"].startswith("emulator truth") and "only for steps taken in contact" in text
    assert summary["estimation"]["rms_error"] is not None and summary["dropped"] == 0
    # the analysed loop is the loop in contact: from the step in contact on, the prediction
    # is the lockstep run (the emulator is the analysed plant in contact) to rounding
    prediction = summary["prediction"]
    assert prediction["available"] and prediction["from_s"] == pytest.approx(0.6)
    assert prediction["rms_difference"] < 1e-6 and prediction["max_difference"] < 1e-6
    assert 0.1 < summary["bus"]["bus_load"] < 0.5
    assert summary["bus"]["rx_frames_per_s"] == pytest.approx(1010, rel=0.05)


FIGURES = ("commands.png", "force.png", "loop_timing.png", "position.png", "tracking_error.png")


def test_report_without_truth_or_steps(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Also: into the directory of an earlier report of two axes, whose axes' figures would
    read as this log's: they go, and a file of the user's in an axis' directory stays."""
    path = tmp_path / "run.mcap"
    logged_lockstep_run(path, duration=0.2)
    out = tmp_path / "r"
    for axis in ("left", "right"):
        (out / axis).mkdir(parents=True)
        for name in FIGURES:
            (out / axis / name).write_bytes(b"png")
    (out / "left" / "notes.txt").write_text("mine")
    (out / "summary.json").write_text(json.dumps({"axes": {"left": {}, "right": {}}}))
    assert main(["report", str(path), "--out", str(out), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["cycles"] == 200 and summary["stop"] == "done"
    # 200 cycles of 1 ms: the run lasted 0.2 s, as its stop line says ("ran 0.2 s"), not the
    # last cycle's time (0.199 s)
    assert summary["duration_s"] == pytest.approx(0.2)
    assert "cycles: 200 (0.200 s)" in (out / "summary.txt").read_text()
    # the frames of the loop's cycles, over their time: one command a cycle at 1 kHz, the
    # bus budget's 27.1 % (`dobhil check demo`), not diluted by the stop's 0.1 s of heartbeats
    bus = summary["bus"]
    assert bus["tx_frames_per_s"] == pytest.approx(1000) and bus["rx_frames_per_s"] == pytest.approx(1000, rel=0.02)
    assert bus["bus_load"] == pytest.approx(0.271, abs=0.002)
    assert sorted(p.name for p in out.iterdir()) == sorted([*FIGURES, "left", "summary.json", "summary.txt"])
    assert [p.name for p in (out / "left").iterdir()] == ["notes.txt"]


def test_foxglove_layout_names_recorded_fields() -> None:
    from dobhil.recording.schemas import SPECS_BY_NAME
    root = Path(__file__).resolve().parents[2]
    layout = json.loads((root / "tools" / "foxglove-layout-topics.json").read_text())
    assert {"configById", "layout", "globalVariables", "userNodes"} <= set(layout)
    paths = [p["value"] for k, c in layout["configById"].items() if k.startswith(("Plot!", "StateTransitions!"))
             for p in c["paths"]]
    assert "/controller.tau_int_hat" in paths and "/loop.exec_time" in paths
    assert "/drive/feedback.drive_state" in paths  # by name: dobhil's codes read as the drive's
    # and the drive's own codes in its protocol's words, beside dobhil's
    assert {"/drive/feedback.protocol_state_name", "/drive/feedback.protocol_error_text"} <= set(paths)
    for path in paths:
        topic, field = path.rsplit(".", 1)
        assert field in SPECS_BY_NAME[topic].keys, path
    assert layout["configById"]["RawMessages!events"]["topicPath"] == "/events"


def _latency_run(rx_ms: list[float], tx_ms: list[float], *, clock: str, input_delay: float) -> RunData:
    from dobhil.config import load_config
    config = load_config("demo", [f"design.input_delay={input_delay}"])
    return RunData(path="x", config=config, metadata={"run": {"log_clock": clock}}, t=np.zeros(1),
                   frame_times={"/can/rx": [round(x * 1e6) for x in rx_ms],
                                "/can/tx": [round(x * 1e6) for x in tx_ms]})


def test_the_latency_leaves_the_runs_frame_times_as_read() -> None:
    """The frame times a run was read into (arrays, :func:`dobhil.run_report.load_axis`) are
    the log's: measuring the latency sorts a copy, not them."""
    data = _latency_run([2.0, 0.0, 1.0], [0.3, 1.3, 2.3], clock="wall", input_delay=3e-4)
    data.frame_times = {k: np.array(v, dtype=np.int64) for k, v in data.frame_times.items()}
    assert latency_stats(data)["commands"] == 3
    assert data.frame_times["/can/rx"].tolist() == [2_000_000, 0, 1_000_000]


def test_latency_is_measured_against_the_assumed_input_delay() -> None:
    """Each command's latency is its log time since the last received frame; a command later
    than a period after any feedback is not a cycle's answer and is left out."""
    rx = [0.0, 1.0, 1.05, 2.0, 3.0]                 # 1.05: a heartbeat between two feedback frames
    tx = [0.30, 1.30, 2.25, 3.40, 9.0]              # 9.0: long after the last feedback
    lat = latency_stats(_latency_run(rx, tx, clock="wall", input_delay=3e-4))
    assert lat["measured"] and lat["commands"] == 4
    assert lat["p50_s"] == pytest.approx(0.275e-3) and lat["max_s"] == pytest.approx(0.4e-3)
    assert lat["assumed_s"] == pytest.approx(3e-4) and lat["matches"]
    far = latency_stats(_latency_run(rx, tx, clock="wall", input_delay=0.0))
    assert far["measured"] and not far["matches"]    # 0.275 ms off at T = 1 ms: more than 0.1 T
    text = summary_text({"file": "x", "cycles": 0, "duration_s": 0.0, "stop": None, "steps": [],
                         "tracking": {"rms_error_estimated": None, "rms_error_true": None}, "estimation": None,
                         "prediction": {}, "latency": far,
                         "loop_timing": {k: None for k in ("exec_time_p50", "exec_time_p99", "exec_time_max",
                                                           "period_error_p99")} | {"overruns": 0},
                         "bus": {"bus_load": None, "bitrate": None}, "dropped": 0})
    assert "set design.input_delay = 0.000275" in text
    simulated = latency_stats(_latency_run(rx, tx, clock="simulated", input_delay=0.0))
    assert not simulated["measured"] and "lockstep" in simulated["why"]


def _summary_with(latency: dict[str, Any], sample_latency_s: float | None) -> dict[str, Any]:
    """The smallest summary ``summary_text`` takes, with a latency section and a sample latency."""
    timing = {k: None for k in ("exec_time_p50", "exec_time_p99", "exec_time_max", "period_error_p99")}
    if sample_latency_s is not None:
        timing |= {f"sample_latency_{p}": sample_latency_s for p in ("p50", "p99", "max")}
    return {"file": "x", "cycles": 0, "duration_s": 0.0, "stop": None, "steps": [],
            "tracking": {"rms_error_estimated": None, "rms_error_true": None}, "estimation": None,
            "prediction": {}, "latency": latency, "loop_timing": timing | {"overruns": 0},
            "bus": {"bus_load": None, "bitrate": None}, "dropped": 0}


@pytest.mark.parametrize(("recorded", "clock", "words"), [
    ("bus", "bus", "bus receive stamps of both frames: the drive's sample instant and its feedback "
                   "(interface socketcan)"),
    ("sent", "sent", "the feedback's bus receive stamp since the host's wall clock just after it sent"),
    (None, "not recorded", "not recorded in this log"),
])
def test_latency_section_says_which_clock_each_latency_is_on(recorded: str | None, clock: str, words: str) -> None:
    """The command latency is on log times; the drive's sample latency on what the run
    recorded its sample instant to be stamped with (a log from before that: not recorded),
    the bus's stamps named by their interface. Both lines of the text say it."""
    data = _latency_run([0.0, 1.0], [0.3, 1.3], clock="wall", input_delay=3e-4)
    data.metadata = {"run": {"log_clock": "wall", **({"sample_clock": recorded} if recorded else {})},
                     "bus": {"interface": "socketcan"}}
    data.signals["sample_latency"] = np.array([2e-4])
    lat = latency_stats(data)
    assert lat["clock"] == "log" and lat["clock_text"].startswith("log times")
    assert lat["sample_clock"] == clock and lat["sample_clock_text"].startswith(words)
    lines = summary_text(_summary_with(lat, 2e-4)).splitlines()
    assert next(x for x in lines if x.startswith("command latency (log times: feedback frame read"))
    assert next(x for x in lines if x.startswith(f"sample latency (drive sample -> feedback received; {words}"))


def test_no_sample_clock_without_a_sample_latency() -> None:
    """A drive that does not tell its sample instant (ODrive) has no sample latency: the
    section names the clock of the command latency only."""
    data = _latency_run([0.0, 1.0], [0.3, 1.3], clock="wall", input_delay=3e-4)
    data.metadata = {"run": {"log_clock": "wall", "sample_clock": ""}}
    data.signals["sample_latency"] = np.array([np.nan])
    lat = latency_stats(data)
    assert lat["clock"] == "log" and "sample_clock" not in lat
    assert not [x for x in summary_text(_summary_with(lat, None)).splitlines() if x.startswith("sample latency")]


def _contact_run(q: list[float], *, truth: bool) -> RunData:
    """A reference 0 -> 0.2 at cycle 0 and 0.2 -> 1 at cycle 5 (demo config: contact at 0 rad)."""
    from dobhil.config import load_config
    n = len(q)
    ref = np.array([0.2] * 5 + [1.0] * (n - 5))
    position = np.array(q)
    signals = {"tau_ref": ref, "tau_int_hat": ref * 0.9, "q": position, "q_true": position if truth else
               np.full(n, np.nan)}
    return RunData(path="x", config=load_config("demo"), metadata={}, t=np.arange(n) * 1e-3, signals=signals)


@pytest.mark.parametrize("truth", [True, False])
def test_step_metrics_only_for_steps_taken_in_contact(truth: bool) -> None:
    """In contact where the position reaches environment.contact_position: the emulator's
    true position when recorded, else the measured one."""
    from dobhil.run_report import contact_mask, step_infos
    q = [-0.005, -0.003, -0.001, 0.0, 1e-5, 2e-5, 3e-5, 4e-5, 5e-5, 5e-5]
    data = _contact_run(q, truth=truth)
    assert contact_mask(data).source.startswith("emulator truth" if truth else "measured position")
    first, second = step_infos(data)
    assert first.in_contact is False and first.metrics is None and "touched the environment at 0.003 s" in first.why
    assert second.in_contact is True and second.metrics is not None
    # contact lost after the second step: no metrics for it either
    lost = step_infos(_contact_run([*q[:7], -1e-3, *q[8:]], truth=truth))[1]
    assert lost.metrics is None and lost.why == "lost contact at 0.007 s"


def test_latency_verdict_covers_the_spread_with_a_stated_tolerance() -> None:
    """'p99 278 us, assumed 0 us: matches the analysis' would contradict itself: the
    verdict needs p50 and p99 within 0.1 T of the assumed delay and says so."""
    rx = [float(k) for k in range(100)]
    tx = [k + (0.278 if k >= 95 else 0.02) for k in range(100)]   # median 20 us, 5 % slow commands
    lat = latency_stats(_latency_run(rx, tx, clock="wall", input_delay=0.0))
    assert lat["p50_s"] == pytest.approx(20e-6) and lat["p99_s"] > 0.1e-3
    assert lat["tolerance_s"] == pytest.approx(0.1e-3) and not lat["matches"]
    text = summary_text({"file": "x", "cycles": 0, "duration_s": 0.0, "stop": None, "steps": [],
                         "tracking": {"rms_error_estimated": None, "rms_error_true": None}, "estimation": None,
                         "prediction": {}, "latency": lat,
                         "loop_timing": {k: None for k in ("exec_time_p50", "exec_time_p99", "exec_time_max",
                                                           "period_error_p99")} | {"overruns": 0},
                         "bus": {"bus_load": None, "bitrate": None}, "dropped": 0})
    line = next(x for x in text.splitlines() if x.startswith("command latency"))
    assert "does not match the analysis (tolerance +-100 us (0.1 T))" in line and "p99 off by" in line
    assert "p50 off" not in line and "set design.input_delay" not in line  # the median is where it was assumed


def test_no_prediction_compared_for_a_run_never_in_contact() -> None:
    """The analysed loop is the loop in contact: a run that never touched the environment
    gets no prediction comparison (it used to be compared over the whole run)."""
    from dobhil.run_report import prediction
    predicted, info = prediction(_contact_run([-0.005] * 10, truth=True))
    assert predicted is None and not info["available"] and "no reference step taken in contact" in info["why"]


def test_no_prediction_for_a_run_that_ended_at_its_step() -> None:
    """A run stopped (a bus error, say) in the very cycle of its step in contact: nothing to
    compare, said so -- not python-control's ValueError on a single time step."""
    from dobhil.run_report import prediction
    predicted, info = prediction(_contact_run([-0.005, -0.003, -0.001, 0.0, 1e-5, 2e-5], truth=True))
    assert predicted is None and not info["available"] and "ended within a cycle of its first step" in info["why"]


def test_the_report_lists_each_change_of_the_drives_state_in_its_protocols_words(tmp_path: Path) -> None:
    """A run whose ODrive faults at cycle 3 (watchdog, back to IDLE): two state changes, each
    with dobhil's state and the drive's codes named as the writer recorded them."""
    from dobhil.cli.recording import drive_metadata
    from dobhil.drives.load import load_profile
    from dobhil.recording.codes import ProtocolCodes
    from dobhil.recording.schemas import CYCLE
    from dobhil.recording.writer import LogWriter
    from dobhil.run_report import analyse, load_run
    profile = load_profile("odrive-0.6")
    path = tmp_path / "fault.mcap"
    log = LogWriter(open(path, "wb"), metadata={"drive": drive_metadata(profile)}, fsync=False,
                    codes=ProtocolCodes(profile))
    states = [(1, 8, 0)] * 3 + [(2, 1, 0x01000000)] * 3   # DriveState, Axis_State, Axis_Error
    log.write([(CYCLE, 1_000_000 * (k + 1), k, 0.0, 0.0, k, *(0.0,) * 6, 0.0, 1e-5, False, math.nan, *state)
               for k, state in enumerate(states)])
    log.finish("drive_fault")
    data = load_run(path)
    named = [(s["cycle"], s["drive_state"], s["protocol_state_name"], s["protocol_error_text"]) for s in data.states]
    assert named == [
        (0, "enabled", "CLOSED_LOOP_CONTROL", "0x00000000 (none)"),
        (3, "fault", "IDLE", "0x01000000 (WATCHDOG_TIMER_EXPIRED)")]
    assert data.states[1]["time_s"] == pytest.approx(0.003)
    text = summary_text(analyse(data)[0])
    assert ("drive state at 0.003 s (cycle 3): fault; the drive's state 1 (IDLE), "
            "error 0x01000000 (WATCHDOG_TIMER_EXPIRED)") in text


def test_the_force_zoom_keeps_the_predictions_peak(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The zoom on the step in contact fits its y axis to what it compares, the analysis'
    prediction with it: a predicted peak above the measured response stays in view."""
    from dobhil.plotting import report_figures
    figures: list[Any] = []
    monkeypatch.setattr(report_figures, "save", lambda fig, path: figures.append(fig) or path)
    data = _contact_run([0.0] * 40, truth=False)
    data.signals["tau_int_true"] = np.full(40, np.nan)
    predicted = data["tau_int_hat"].copy()
    predicted[8] = 2.0   # overshoots where the measured response does not
    summary = {"steps": [{"time": 0.005, "start": 0.2, "end": 1.0, "metrics": {"settling_time": 0.01}}]}
    report_figures.force_figure(data, predicted, summary, tmp_path / "force.png")
    try:
        zoom = figures[0].axes[1]
        assert zoom.get_xlim()[0] <= 0.008 <= zoom.get_xlim()[1] and zoom.get_ylim()[1] > 2.0
    finally:
        import matplotlib.pyplot as plt
        plt.close(figures[0])


class _StreamedLog:
    """An axis' log (what :func:`dobhil.run_report.load_axis` reads) whose messages are made as
    they are read: ``cycles`` cycles of a /controller record, a feedback frame and a command."""

    path, frame_ids, name, bus, coupled_to = "streamed.mcap", None, "axis", "bus", ()

    def __init__(self, cycles: int) -> None:
        from dobhil.config import load_config
        self.cycles, self.config, self.metadata = cycles, load_config("demo"), {}

    def __enter__(self) -> _StreamedLog:
        return self

    def __exit__(self, *exc: object) -> None:
        pass

    def require_topic(self, topic: str) -> None:
        pass

    def iter_messages(self, topics: Any) -> Any:
        t0 = 1_796_000_000_000_000_000
        frame = {"arbitration_id": 9, "dlc": 8, "is_extended_id": False, "is_fd": False, "bitrate_switch": False}
        for k in range(self.cycles):
            t = t0 + k * 1_000_000
            yield "/can/rx", t, frame
            yield "/controller", t + 1, {"cycle": k, **{name: k * 1e-3 + i for i, name in enumerate(
                ("tau_ref", "tau_int_hat", "tau_dis_hat", "tau_per", "u_unsat", "u_sat"))}}
            yield "/can/tx", t + 2, frame


def test_a_report_keeps_each_frame_and_cycle_as_a_few_numbers_not_python_objects() -> None:
    """A report reads a whole log (a 60 s run at 1 kHz: 60,000 cycles, 120,000 frames): what it
    keeps of each is its numbers (8 bytes each: a cycle's controller record 64, a frame's time
    and kind 33, its time again for the latency), not a Python tuple of objects (about 300
    bytes a cycle, 150 a frame). Measured on this log of 2000 cycles: 939 bytes a cycle at the
    peak with tuples, 327 with columns; the bound is between."""
    import tracemalloc
    from dobhil.run_report import load_axis
    cycles = 2000
    log = _StreamedLog(cycles)
    tracemalloc.start()
    try:
        data = load_axis(log)  # type: ignore[arg-type]
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert data.t.size == cycles and len(data.frames["/can/tx"]) == cycles - 1
    assert peak / cycles < 500, f"{peak / cycles:.0f} bytes a cycle"


def test_the_shared_timing_of_axes_keeps_no_object_per_cycle() -> None:
    """Two axes' timing (cycles 0..4999 and 1..5000: each cycle's worst of the axes there): the
    per-cycle worst is gathered on arrays. Measured here with a list of floats per cycle: 260
    bytes a cycle at the peak; on arrays 106 (the inputs are not counted)."""
    import tracemalloc
    from dobhil.run_report import shared_timing
    n = 5000

    def axis(first: int, exec_time: float, overrun_at: int) -> RunData:
        overrun = np.zeros(n)
        overrun[overrun_at] = 1.0
        return RunData(path="x", config=None, metadata={}, t=np.arange(n) * 1e-3,
                       signals={"cycle": np.arange(first, first + n, dtype=float), "exec_time": np.full(n, exec_time),
                                "period_error": np.full(n, -2e-6), "overrun": overrun})

    a, b = axis(0, 1e-4, 7), axis(1, 3e-4, 7)
    b["exec_time"][0] = np.nan   # cycle 1: only a's time is known
    tracemalloc.start()
    try:
        out = shared_timing([a, b])
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert out["cycles"] == n + 1 and out["overruns"] == 2
    assert out["exec_time_max"] == pytest.approx(3e-4) and out["exec_time_p50"] == pytest.approx(3e-4)
    assert out["period_error_max"] == pytest.approx(2e-6)
    assert peak / n < 200, f"{peak / n:.0f} bytes a cycle"


def _labelled_figure() -> Any:
    """A report-like figure: two panels, titles, labels, a legend placed at draw time, a suptitle."""
    from dobhil.plotting.figures import _plt
    fig, ax = _plt().subplots(2, 1, figsize=(6, 4))
    t = np.linspace(0.0, 2.0, 400)
    for a, scale in zip(ax, (1.0, 1e-3)):
        a.plot(t, scale * np.sin(7 * t), label="$\\hat\\tau_{int}$ (RTOb)")
        a.plot(t, scale * np.cos(3 * t), label="reference $\\tau^{ref}_{int}$")
        a.set_ylabel("interaction torque [N m]")
        a.legend(loc="best", fontsize=8)
    ax[1].set_xlabel("time [s]")
    ax[0].set_title("Force response (lockstep; C_f = 2)")
    fig.suptitle("a suptitle wider than the axes, to be kept whole by the crop")
    return fig


def test_a_saved_figure_is_drawn_once_and_cropped_as_a_tight_bbox_would(tmp_path: Path,
                                                                         monkeypatch: pytest.MonkeyPatch) -> None:
    """``save`` measures the tight box itself: one draw of the figure, not matplotlib's dry draw
    and then the real one (a third of a report's figure time), and the same pixels as
    ``bbox_inches="tight"`` -- no label, title or legend cut."""
    import matplotlib.image
    from matplotlib.figure import Figure

    from dobhil.plotting.figures import save
    reference = _labelled_figure()
    reference.savefig(tmp_path / "tight.png", dpi=150, bbox_inches="tight")
    draws: list[object] = []
    drawn = Figure.draw
    monkeypatch.setattr(Figure, "draw", lambda fig, renderer: draws.append(fig) or drawn(fig, renderer))
    save(_labelled_figure(), tmp_path / "saved.png")
    assert len(draws) == 1
    saved, tight = (matplotlib.image.imread(tmp_path / f"{name}.png") for name in ("saved", "tight"))
    assert saved.shape == tight.shape and np.array_equal(saved, tight)


def test_the_cycle_layouts_foxglove_file_names_the_same_fields_in_cycle_messages() -> None:
    """tools/foxglove-layout.json is tools/foxglove-layout-topics.json on the cycle layout's
    paths (as tools/foxglove_layout_cycle.py writes it), and each path is a field of
    dobhil.Cycle as the protobuf library reads its schema (Foxglove reads it so)."""
    import subprocess
    import sys
    from google.protobuf import descriptor_pb2, descriptor_pool
    from dobhil.recording.cycles import cycle_schema
    root = Path(__file__).resolve().parents[2]
    tool = root / "tools" / "foxglove_layout_cycle.py"
    assert subprocess.run([sys.executable, str(tool), "--check"], check=False).returncode == 0
    pool = descriptor_pool.DescriptorPool()
    for file in descriptor_pb2.FileDescriptorSet.FromString(cycle_schema()).file:
        pool.Add(file)
    layout = json.loads((root / "tools" / "foxglove-layout.json").read_text())
    paths = [p["value"] for k, c in layout["configById"].items() if k.startswith(("Plot!", "StateTransitions!"))
             for p in c["paths"]]
    assert len(paths) == 12 and all(p.startswith("/cycle.") for p in paths)
    for path in paths:
        message = pool.FindMessageTypeByName("dobhil.Cycle")
        *fields, last = path.split(".")[1:]
        for name in fields:
            message = message.fields_by_name[name].message_type
        assert last in message.fields_by_name, path
    assert layout["configById"]["RawMessages!events"]["topicPath"] == "/events"
