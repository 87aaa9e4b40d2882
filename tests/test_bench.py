"""tools/bench.py measures fairly: pairs interleaved and warmed before their clocks start,
the bare loop waiting with the runtime's own code, every run's stop reason checked (a run
that stops early fails its key, it never counts as a figure), targets labelled by kind.

The benches' own figures are timing of this machine and are not asserted; these tests run
the bench's machinery on fakes (a counting clock, results built here) or on very short real
runs, so they take no wall-clock bound."""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path
from types import ModuleType, SimpleNamespace
from typing import Any

import pytest
from tool_module import load_tool

from dobhil.runtime.stop import Stop, StopReason

BENCH = Path(__file__).resolve().parents[1] / "tools" / "bench.py"


def _load() -> ModuleType:
    return load_tool(BENCH, "bench_under_test")


bench = _load()


class CountingClock:
    """A clock that moves only when told: each fake call advances it by its cost."""

    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now

    def spend(self, seconds: float) -> None:
        self.now += seconds


def test_interleaved_warms_every_side_untimed_then_alternates() -> None:
    clock = CountingClock()

    def side(name: str, warm_cost: float, cost: float) -> Any:
        return bench.Side(name, warm=lambda: clock.spend(warm_cost), run=lambda: clock.spend(cost))

    pair = bench.interleaved([side("ours", 50.0, 1.0), side("base", 1000.0, 3.0)], 3, clock=clock)
    assert pair.order == ("warm:ours", "warm:base", "ours", "base", "ours", "base", "ours", "base")
    # the warm-ups (the import's 1000 s) are in no timed run; both sides timed 3 times
    assert pair.times == {"ours": [1.0, 1.0, 1.0], "base": [3.0, 3.0, 3.0]}
    assert pair.best("base") == 3.0


def test_python_control_is_warmed_before_its_clock_starts(monkeypatch: pytest.MonkeyPatch) -> None:
    """The first python-control point pays for ``import control`` (here 1000 s on the fake
    clock): the pair's python-control times must not contain it."""
    clock = CountingClock()
    calls: list[tuple[float, float]] = []

    def point(config: object, ji: float, k: float) -> tuple[bool, bool, float]:
        clock.spend(1000.0 if not calls else 1.0)
        calls.append((ji, k))
        return True, True, math.inf

    monkeypatch.setattr(bench, "python_control_point", point)
    config = bench.load_config(bench.ROOT / "configs/paper/fig2b.yaml")
    pair = bench.interleaved(bench.sweep_sides(config, n=3, n_base=2), 2, clock=clock)
    assert pair.order == ("warm:dobhil", "warm:python-control", "dobhil", "python-control",
                          "dobhil", "python-control")
    assert pair.times["python-control"] == [4.0, 4.0]   # 2 x 2 points at 1 s, no import
    assert len(calls) == 1 + 2 * 4


def test_python_control_answers_the_sweeps_question() -> None:
    """The baseline is a speed-up only if it answers what dobhil's sweep answers at every
    point: stable at C_f, minimum phase, the largest stable C_f (infinite where every gain
    is stable, not the open loop's verdict at gain 0)."""
    config = bench.load_config(bench.ROOT / "configs/paper/fig2b.yaml")
    assert bench.sweep_disagreements(config, n_base=3) == []


def _result(reason: StopReason, *, overruns: int = 2, cycles: int = 1000) -> SimpleNamespace:
    timing = SimpleNamespace(period_error_p99=4e-5, latency_p99=3e-4)
    return SimpleNamespace(stop=Stop(reason, "no fresh feedback" if reason else "", 400, 0.4),
                           overruns=overruns, cycles=cycles, skipped=3, timing=timing)


def _fake_realtime(monkeypatch: pytest.MonkeyPatch, fails: str | None) -> list[str]:
    """bench_realtime on results built here: every run lasts but ``fails`` (a feedback
    timeout at cycle 400); the bare loop's p99 is 20 us. Returns the runs made, in order."""
    made: list[str] = []

    def run(duration: float, timing: str, path: Path | None) -> SimpleNamespace:
        name = "feedback" if timing == "feedback" else "logged" if path is not None else "plain"
        made.append(name)
        warm = duration < 1.5
        return _result(StopReason.FEEDBACK_TIMEOUT if name == fails and not warm else StopReason.DONE)

    monkeypatch.setattr(bench, "_realtime_run", run)
    monkeypatch.setattr(bench, "_bare_loop_period_errors", lambda seconds: [2e-5] * 100)
    return made


@pytest.mark.parametrize("fails", ["plain", "logged", "feedback"])
def test_a_realtime_run_that_stopped_early_fails_the_keys_it_feeds(
        monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str], fails: str) -> None:
    _fake_realtime(monkeypatch, fails)
    out = bench.bench_realtime(rounds=2, seconds=2.0)
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 2 and all("stopped: feedback_timeout at cycle 400" in line for line in err)
    assert all(f"({fails})" in line for line in err)
    for key, runs in bench._RT_KEYS.items():
        assert math.isnan(out[key]) == (fails in runs), key
    if fails == "plain":   # a target key: missed, never met by a run that did not last
        assert bench.targets_met(out)["rt_vs_bare_period_error_p99_ratio"]["met"] is False


def test_realtime_rounds_are_interleaved_and_pooled_with_their_spread(monkeypatch: pytest.MonkeyPatch) -> None:
    made = _fake_realtime(monkeypatch, None)
    tally = bench._RtTally()
    for i in range(3):
        bench._realtime_round(i, 2.0, Path("unused"), tally)
    assert tally.order == ["bare", "plain", "logged", "feedback", "bare", "logged", "plain", "feedback",
                           "bare", "plain", "logged", "feedback"]
    assert made == [n for n in tally.order if n != "bare"]
    out = bench._realtime_figures(tally)
    assert out["rt_vs_bare_period_error_p99_ratio"] == pytest.approx(2.0)   # 40 us / 20 us
    per_10k = 1e4 * 2 / 1003
    assert out["rt_overruns_per_10k"] == pytest.approx(per_10k)
    assert (out["rt_overruns_per_10k_min"], out["rt_overruns_per_10k_median"],
            out["rt_overruns_per_10k_max"]) == pytest.approx((per_10k,) * 3)
    assert out["rt_deadlines_each"] == 3 * 1003


def test_repeat_sets_the_realtime_rounds(monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    made = _fake_realtime(monkeypatch, None)
    assert bench.main(["--only", "realtime", "--repeat", "4", "--json"]) == 0
    assert made.count("plain") == 1 + 4   # the warm-up and 4 rounds
    out = capsys.readouterr().out
    assert '"rt_vs_bare_period_error_p99_ratio_max": 2.0' in out
    assert '"rt_vs_bare_period_error_p99_ratio": {"kind": "ratio", "max": 2.0, "met": true}' in out


def test_a_lockstep_run_that_stopped_early_is_not_a_rate(monkeypatch: pytest.MonkeyPatch,
                                                         capsys: pytest.CaptureFixture[str]) -> None:
    """A real emulated run that hits its velocity limit after a few cycles: fast, and no figure."""
    real = bench.load_config

    def limited(path: Path, sets: list[str] | None = None) -> Any:
        return real(path, [*(sets or []), "loop.velocity_limit=1e-6"])

    monkeypatch.setattr(bench, "load_config", limited)
    assert math.isnan(bench._lockstep_1axis_cycles_per_s(2.0))
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "stopped: velocity_limit" in err and "not counted" in err


def test_a_montecarlo_batch_with_a_run_that_did_not_last_is_not_a_rate(
        monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    import dobhil.campaign.campaign as campaign
    rows = [{"stop_reason": "done", "error": ""}, {"stop_reason": "unstable", "error": ""}]
    monkeypatch.setattr(campaign, "execute", lambda client, specs: rows)
    assert math.isnan(bench._montecarlo_batch(None, [1, 2], "round 1 on 2 worker(s)"))
    assert "1 of 2 runs did not last" in capsys.readouterr().err
    rows[1]["stop_reason"] = "done"
    assert bench._montecarlo_batch(None, [1, 2], "round 1 on 2 worker(s)") > 0


def test_the_bare_loop_waits_with_the_runtimes_code(monkeypatch: pytest.MonkeyPatch) -> None:
    """Same deadlines, same skip after an overrun, same sleep-then-spin at the demo's loop.spin."""
    spins: list[float] = []
    steps: list[int] = []

    def spy(fn: Callable[..., Any], seen: list[Any], pick: Callable[..., Any]) -> Callable[..., Any]:
        def wrapped(*args: Any, **kwargs: Any) -> Any:
            seen.append(pick(*args, **kwargs))
            return fn(*args, **kwargs)
        return wrapped

    monkeypatch.setattr(bench, "sleep_until", spy(bench.sleep_until, spins, lambda d, **kw: kw["spin"]))
    monkeypatch.setattr(bench, "next_deadline", spy(bench.next_deadline, steps, lambda k, *a: k))
    errors = bench._bare_loop_period_errors(0.01)
    demo_spin = bench.load_config(bench.ROOT / "configs/demo.yaml").loop.spin
    assert spins and set(spins) == {demo_spin}
    assert len(errors) == len(steps) == len(spins) <= 10   # one wake per deadline kept, skips included


def test_targets_say_their_kind() -> None:
    assert not (bench.ABSOLUTE_TARGETS - set(bench.TARGETS) - set(bench.TARGETS_MAX))   # no stale names
    met = bench.targets_met({"lockstep_cycles_per_s": 6000.0, "sweep_speedup_vs_python_control": 30.0,
                             "identify_seconds_per_minute_of_log": math.nan})
    assert met["lockstep_cycles_per_s"] == {"kind": "absolute", "min": 5000.0, "met": True}
    assert met["sweep_speedup_vs_python_control"] == {"kind": "ratio", "min": 100.0, "met": False}
    assert met["identify_seconds_per_minute_of_log"]["met"] is False
    line = bench._line("sweep_speedup_vs_python_control", 30.0, met["sweep_speedup_vs_python_control"])
    assert line.endswith("(ratio target >= 100: MISSED)")
    assert bench._line("lockstep_cycles_per_s", 6000.0, met["lockstep_cycles_per_s"]).endswith(
        "(absolute target >= 5000)")


def test_log_encodings_are_interleaved_warmed_and_a_short_run_fails_the_size_keys(
        monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    """Each log format warmed once, then rounds in a turning order, a lockstep and a
    real-time recording each; the size keys are the medians' ratio; one recording that did
    not last (NaN) fails every size key of its timing, never a figure."""
    made: list[tuple[str, float, bool]] = []
    bytes_of = {"topics": (60.0, 20.0), "json": (180.0, 100.0), "cycle": (45.0, 21.0)}
    realtime = {"topics": (90.0, 20.0), "json": (240.0, 100.0), "cycle": (96.0, 21.0)}

    def run(duration: float, path: Path, form: str, lockstep: bool = True) -> tuple[float, float]:
        made.append((form, duration, lockstep))
        return (bytes_of if lockstep else realtime)[form]

    monkeypatch.setattr(bench, "_encoded_run", run)
    cost = {"topics": 0.5, "json": 1.0, "cycle": 0.25}
    monkeypatch.setattr(bench, "_writer_cpu_us", lambda records, form, path: 1000.0 * len(records) * cost[form])
    monkeypatch.setattr(bench, "replay_by_encoding", lambda seconds, folder: {"replay_protobuf_vs_json": 1.5})
    out = bench.bench_log_encoding(pairs=2, seconds=4.0, cycles=10, realtime_seconds=3.0)
    assert made == [("topics", 0.5, True), ("cycle", 0.5, True), ("json", 0.5, True),
                    *[(form, duration, lockstep) for form in ("topics", "cycle", "json", "cycle", "json", "topics")
                      for duration, lockstep in ((4.0, True), (3.0, False))]]
    # the unsuffixed keys are the default layout's (cycle), the topics layout's are named
    assert out["log_bytes_per_cycle"] == 45.0 and out["log_bytes_per_cycle_vs_json"] == pytest.approx(0.25)
    assert out["log_payload_bytes_per_cycle_vs_json"] == pytest.approx(0.21)
    assert out["log_bytes_per_cycle_topics_layout_vs_json"] == pytest.approx(1 / 3)
    assert out["log_payload_bytes_per_cycle_topics_layout_vs_json"] == pytest.approx(0.2)
    assert out["log_bytes_per_cycle_realtime_vs_json"] == pytest.approx(0.4)
    assert out["log_bytes_per_cycle_realtime_topics_layout_vs_json"] == pytest.approx(0.375)
    # 3 records a cycle (frame, cycle, frame) at a fake 250 us (cycle) and 500 us (topics) each
    assert (out["writer_cpu_us_per_cycle"], out["writer_cpu_vs_json"]) == (750.0, 0.25)
    assert (out["writer_cpu_us_per_cycle_topics_layout"], out["writer_cpu_topics_layout_vs_json"]) == (1500.0, 0.5)
    met = bench.targets_met(out)
    assert met["log_bytes_per_cycle_vs_json"] == {"kind": "ratio", "max": 0.33, "met": True}
    assert met["log_bytes_per_cycle_realtime_vs_json"] == {"kind": "ratio", "max": 0.33, "met": False}
    assert "log_bytes_per_cycle_topics_layout_vs_json" not in met   # a figure, not a target
    assert out["replay_protobuf_vs_json"] == 1.5
    bytes_of["json"] = (math.nan, math.nan)   # a JSON recording stopped early
    out = bench.bench_log_encoding(pairs=2, seconds=4.0, cycles=10)
    assert math.isnan(out["log_bytes_per_cycle_vs_json"]) and math.isnan(out["log_bytes_per_cycle_json"])
    assert math.isnan(out["log_bytes_per_cycle_topics_layout_vs_json"])
    assert out["log_bytes_per_cycle_realtime_vs_json"] == pytest.approx(0.4)
    assert bench.targets_met(out)["log_bytes_per_cycle_vs_json"]["met"] is False


def test_replay_by_encoding_is_interleaved_warmed_and_a_short_run_fails_its_key(
        monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    """Each encoding's log replayed once untimed, then alternating; the ratio is JSON's best
    time over protobuf's; a recording that did not last fails the key (NaN), never a figure."""
    clock, calls = CountingClock(), []
    cost = {"replay-topics.mcap": 2.0, "replay-json.mcap": 3.0, "replay-cycle.mcap": 1.25}
    lasted = {"topics": 190.0, "json": 210.0, "cycle": 60.0}
    monkeypatch.setattr(bench, "_encoded_run", lambda seconds, path, form: (lasted[form], 0.0))

    def replayed(path: Path) -> int:
        calls.append(path.name)
        clock.spend(cost[path.name])
        cost[path.name] -= 0.5   # the first (warm-up) run is the slowest
        return 4000
    monkeypatch.setattr(bench, "_replayed", replayed)
    out = bench.replay_by_encoding(4.0, tmp_path, repeat=2, clock=clock)
    assert calls == ["replay-topics.mcap", "replay-cycle.mcap", "replay-json.mcap"] * 3
    # best of the timed runs (1.0, 0.25 and 2.0 s), not the warm-ups' 2.0, 1.25 and 3.0; the
    # unsuffixed rate is the default layout's (cycle)
    assert out == {"replay_cycles_per_cpu_s": 4000 / 0.25, "replay_cycles_per_cpu_s_json": 4000 / 2.0,
                   "replay_cycles_per_cpu_s_topics_layout": 4000 / 1.0,
                   "replay_protobuf_vs_json": 8.0, "replay_cycle_layout_vs_topics": 4.0}
    assert bench.targets_met(out)["replay_protobuf_vs_json"] == {"kind": "ratio", "min": 1.0, "met": True}
    lasted["json"] = math.nan
    out = bench.replay_by_encoding(4.0, tmp_path, repeat=2, clock=clock)
    assert math.isnan(out["replay_protobuf_vs_json"])
    assert bench.targets_met(out)["replay_protobuf_vs_json"]["met"] is False


def test_json_output_is_one_object_whatever_the_runs_print(monkeypatch: pytest.MonkeyPatch,
                                                          capsys: pytest.CaptureFixture[str]) -> None:
    """A measured run prints its stop line (the in-process ``dobhil run`` of the identify
    benches): with --json it goes to stderr and stdout stays one JSON object."""
    import json

    def noisy() -> dict[str, float]:
        print("stopped: done at cycle 10 (t = 0.0100 s): ran 0.01 s")
        return {"replay_cycles_per_s": 1.0}
    monkeypatch.setitem(bench.BENCHES, "logging", noisy)
    assert bench.main(["--only", "logging", "--json"]) == 0
    out, err = capsys.readouterr()
    assert json.loads(out)["replay_cycles_per_s"] == 1.0
    assert "stopped: done" in err
