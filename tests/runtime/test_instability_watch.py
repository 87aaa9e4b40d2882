"""The instability watch on signals made here (its rules and bounds, without a plant), its
config keys (one-line errors, exit 2), and a chattering run end to end through the CLI: the
stop line, exit 1, the summary, the MCAP stop event and the report."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from dobhil.cli.main import main
from dobhil.config import load_config
from dobhil.errors import ConfigError
from dobhil.runtime.instability import InstabilityWatch, WatchSettings
from dobhil.runtime.session import watch_settings
from dobhil.runtime.stop import StopReason

from .helpers import DEMO

LIMIT = 2.0


def make(window: int = 100, **kw: float) -> InstabilityWatch:
    values = {"saturation": 0.12, "limit_reversals": 0.03, "hysteresis": 0.25, "growth": 2.0,
              "growth_swings": 8, **kw}
    return InstabilityWatch(WatchSettings(window=window, **values), LIMIT)  # type: ignore[arg-type]


def feed(watch: InstabilityWatch, u_unsat: np.ndarray) -> tuple[int, str]:
    """(cycle, detail) of the first trip, (-1, "") if none."""
    for k, x in enumerate(u_unsat):
        why = watch.cycle(float(x), max(-LIMIT, min(LIMIT, float(x))))
        if why:
            return k, why
    return -1, ""


def test_nyquist_chatter_trips_once_both_counts_are_reached() -> None:
    """+-5 N m asked every other cycle (clipped to +-2): clipped every cycle, a turn back from
    the limit every cycle from the second on; trips when 12 clipped and 3 turns are counted."""
    k, why = feed(make(), np.array([5.0, -5.0] * 100))
    assert k == 12 - 1 and why.startswith("torque at its limit (2 N m) in 12 of the last 12 cycles")
    assert "turned back from it 11 times" in why


def test_chatter_bound_is_the_window() -> None:
    """A limit cycle that only just meets both thresholds (clipped 15 %, a turn back from the
    limit every 20 cycles: 5 % per cycle) after a long quiet start trips within W cycles."""
    period = [3.0, 3.0, 3.0] + [0.0] * 17   # clipped 3 in 20, one turn back from the limit
    quiet = np.zeros(1000)
    k, why = feed(make(window=100), np.concatenate([quiet, np.tile(period, 20)]))
    assert why and 1000 <= k <= 1000 + 100


def test_held_at_the_limit_never_trips() -> None:
    """A stable loop held at its limit (a reference beyond it): clipped all the time, no turn."""
    assert feed(make(), np.full(5000, 7.0)) == (-1, "")


def test_turning_below_the_limit_never_trips_the_chatter_rule() -> None:
    """A fast reference tracked at 0.9 L: turns every cycle, never clipped."""
    w = make(growth_swings=10_000)
    assert feed(w, 0.9 * LIMIT * np.cos(np.pi * np.arange(5000))) == (-1, "")
    assert w.peaks.saturation == 0.0 and w.peaks.limit_reversals == 0.0


def test_noise_below_the_hysteresis_counts_nothing() -> None:
    w = make()
    rng = np.random.default_rng(0)
    assert feed(w, 5.0 + rng.uniform(-0.2, 0.2, 5000)) == (-1, "")   # clipped, but no turn of 0.5
    assert w.peaks.limit_reversals == 0.0 and w.peaks.growth_swings == 0


def test_growing_oscillation_trips_below_the_limit() -> None:
    """z = -1.05: swings from 0.5 N m grow 5 % a cycle; the growth rule stops it at
    max(8, log 2 / log 1.05 = 15) + 3 swings, long before the +-2 N m limit's 2 x 2 N m."""
    x = 0.3 * (-1.05) ** np.arange(200)
    k, why = feed(make(), x)
    onset = int(np.flatnonzero(np.abs(np.diff(x)) >= 0.5)[0])
    assert why.startswith("the command's oscillation grew") and k - onset <= 15 + 3 + 1
    assert np.all(np.abs(x[:k + 1]) < LIMIT)


@settings(max_examples=60, deadline=None)
@given(rate=st.floats(1.002, 1.41), start=st.floats(0.01, 0.5))
def test_any_growth_at_nyquist_trips_within_the_bound(rate: float, start: float) -> None:
    """Growth rule bound for any rate r per swing up to sqrt(SMOOTH) (a faster one reaches the
    limit within a few swings): max(growth_swings, log 2 / log r) + 3 swings after the first
    swing beyond the hysteresis (here one swing per cycle)."""
    x = start * (-rate) ** np.arange(int(math.log(1e6 / start) / math.log(rate)))
    k, why = feed(make(growth_swings=8), x)
    onset = int(np.flatnonzero(np.abs(np.diff(x)) >= 0.25 * LIMIT)[0])
    bound = max(8, math.ceil(math.log(2.0) / math.log(rate))) + 3
    assert why and k - onset <= bound + 1, (k, onset, bound)


@settings(max_examples=60, deadline=None)
@given(cycles_per_period=st.floats(2.0, 80.0), amplitude=st.floats(0.0, 1.98),
       decay=st.floats(0.9, 1.0), phase=st.floats(0.0, 6.3))
def test_bounded_or_decaying_oscillation_never_trips(cycles_per_period: float, amplitude: float,
                                                     decay: float, phase: float) -> None:
    """A sinusoid of any frequency that never reaches the limit and never grows (constant or
    decaying amplitude): neither rule trips, whatever its sampling phase."""
    k = np.arange(3000)
    x = amplitude * decay ** k * np.cos(2 * np.pi * k / cycles_per_period + phase)
    assert feed(make(), x) == (-1, "")


@pytest.mark.parametrize(("key", "value", "words"), [
    ("instability.window", "-1", "must be >= 0"),
    ("instability.saturation", "0", "must be > 0"),
    ("instability.saturation", "1.5", "<= 1"),
    ("instability.limit_reversals", "2", "<= 1"),
    ("instability.hysteresis", "0", "must be > 0"),
    ("instability.growth", "1", "must be > 1"),
    ("instability.growth_swings", "2.5", "whole number"),
    ("instability.growth_swings", "0", "must be > 0"),
])
def test_bad_values_are_one_line_exit_2(key: str, value: str, words: str,
                                        capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(ConfigError, match=words):
        load_config(DEMO, [f"{key}={value}"])
    code = main(["run", str(DEMO), "--emulate", "--lockstep", "--set", f"{key}={value}"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and key in err[0] and words in err[0]


def test_summary_without_a_watch(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["run", str(DEMO), "--emulate", "--lockstep", "--summary-json", "--duration", "0.05",
                 "--set", "instability.window=0"]) == 0
    assert json.loads(capsys.readouterr().out)["instability"] is None


def test_settings_from_the_config() -> None:
    """The window is whole periods (at least 2); 0 and torque mode: no watch."""
    s = watch_settings(load_config(DEMO, ["instability.window=0.0104"]))
    assert s is not None and s.window == 10
    s = watch_settings(load_config(DEMO, ["instability.window=0.0011"]))   # at least two periods
    assert s is not None and s.window == 2
    s = watch_settings(load_config(DEMO, ["loop.period=2", "loop.feedback_timeout=5"]))   # a long period:
    assert s is not None and s.window == 2   # the default 0.5 s window is two periods, not refused
    assert watch_settings(load_config(DEMO, ["instability.window=0"])) is None
    assert watch_settings(load_config(DEMO, ["loop.mode=torque"])) is None


def test_unstable_run_end_to_end(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """The issue's command: one stop line, exit 1, ``unstable`` in the summary, the MCAP
    stop event and the report (which predicts nothing for an unstable design)."""
    log = tmp_path / "run.mcap"
    code = main(["run", str(DEMO), "--emulate", "--lockstep", "--set", "design.force_gain=20", "--allow-unstable",
                 "--log", str(log)])
    out = capsys.readouterr().out
    stops = [line for line in out.splitlines() if line.startswith("stopped:")]
    assert code == 1 and len(stops) == 1 and stops[0].startswith("stopped: unstable at cycle ")
    code = main(["run", str(DEMO), "--emulate", "--lockstep", "--set", "design.force_gain=20", "--allow-unstable",
                 "--summary-json"])
    info = json.loads(capsys.readouterr().out)
    assert code == 1 and info["stop_reason"] == "unstable" and info["drive_disabled"]
    assert info["instability"]["chatter"] >= 1.0 and info["instability"]["saturation"] >= 0.12
    assert info["safe_stop"]["frames"][0]["sent"]
    from dobhil.recording.reader import LogFile
    assert LogFile(log).stop_reason() == StopReason.UNSTABLE.name.lower()
    assert main(["report", str(log), "--out", str(tmp_path / "report"), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["stop"] == "unstable"
    assert summary["prediction"]["available"] is False and summary["prediction"]["unstable"] is True
