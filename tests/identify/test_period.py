"""The period of a CAN log imported without one (dobhil/identify/period.py): the round
period its stamps scatter around, never their biased median spacing."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from hypothesis import assume, example, given, settings
from hypothesis import strategies as st

from dobhil.cli.main import main
from dobhil.drives.ticks import MAX_LAG_PERIODS
from dobhil.identify.period import SNAP, frame_lattice, nominal_period
from tests.late_sender import catch_up_sends


@settings(max_examples=200, deadline=None)
@given(micro=st.integers(100, 20_000), jitter=st.floats(0.0, 0.1), skew=st.floats(-1e-4, 1e-4),
       seed=st.integers(0, 2 ** 31))
@example(micro=17859, jitter=0.09375, skew=-1.2737585375207708e-05, seed=1)
def test_jittered_stamps_give_their_round_period(micro: int, jitter: float, skew: float, seed: int) -> None:
    """Stamps of a loop of a whole number of microseconds, skewed (a host clock off by up to
    1e-4), jittered (up to a tenth of a period), one frame in 50 lost, at an epoch time held
    in a double (1.8e9 s: every stamp a multiple of 2.4e-7 s): the period is the loop's own
    exactly while the skew and the fit's largest possible error together stay under half a
    microsecond, else the whole microsecond the skewed clock saw, no further off than those two
    and half a microsecond. (The example: a 17.859 ms loop with 1.7 ms of jitter, whose slope
    the 400 stamps pin only to ~0.2 us, 0.23 us of skew on top: 17.858 ms is what they show.)"""
    period = micro * 1e-6
    rng = np.random.default_rng(seed)
    t = np.arange(400) * period * (1 + skew) + rng.uniform(0, jitter * period, 400)
    kept = np.sort(t)[np.arange(400) % 50 != 7]
    stamps = 1.8e9 + kept
    found, how = nominal_period(stamps)
    assert how == "nominal"
    # the least-squares slope moves by at most max|noise| sum|c| / sum(c^2) (c: the centred
    # frame numbers); the noise: the jitter and the epoch's 2.4e-7 s steps
    c = np.arange(400)[np.arange(400) % 50 != 7].astype(float)
    c -= c.mean()
    fit = (jitter * period + 2.4e-7) * np.abs(c).sum() / (c ** 2).sum()
    if abs(skew) * period + fit < 0.5e-6:
        assert found == pytest.approx(period, rel=1e-12)
    else:
        assert abs(found - period) <= abs(skew) * period + fit + 0.5e-6 + 1e-12


def _ticks(period: float, frames: int, stalls: list[tuple[float, float]], jitter: float, skew: float,
           seed: int) -> tuple[np.ndarray, np.ndarray]:
    """(receive stamps, tick numbers) of the catching-up sender of tests/late_sender.py, 5 us
    per frame, on a clock skewed by ``skew``; every frame received ``[0, jitter)`` periods
    later, in the order sent."""
    rng = np.random.default_rng(seed)
    step = period * (1 + skew)
    sent = catch_up_sends(frames, stalls, 5e-6 / step)
    numbers = np.arange(1, frames + 1)
    # more than MAX_LAG_PERIODS behind, run_ticks skips ticks: their frames are never sent,
    # and one sent that late cannot be told from the one after it
    assume(bool(np.all(sent + 5e-6 / step - (numbers + 1) <= MAX_LAG_PERIODS)))
    received = np.maximum.accumulate(sent * step + rng.uniform(0.0, jitter * period, frames))
    return received, numbers


@settings(max_examples=200, deadline=None)
@given(micro=st.integers(100, 20_000), jitter=st.floats(0.0, 0.1), skew=st.floats(-1e-5, 1e-5),
       stalls=st.lists(st.tuples(st.floats(1.0, 380.0), st.floats(0.5, MAX_LAG_PERIODS - 0.5)), max_size=4),
       lost=st.sets(st.integers(1, 398), max_size=8), seed=st.integers(0, 2 ** 31))
@example(micro=100, jitter=0.0625, skew=0.0, stalls=[(1.0, 9.5)], lost=set(), seed=12668)
def test_bursts_after_a_stall_keep_the_period_and_the_numbers(micro: int, jitter: float, skew: float,
                                                              stalls: list[tuple[float, float]], lost: set[int],
                                                              seed: int) -> None:
    """A sender that was not scheduled for a while sends what it missed in a burst (the
    emulated drive, ``run_ticks``); frames lost on the bus: every frame gets the deadline it
    was sent for, and the period is found as when no stall happened (the bound of
    :func:`test_jittered_stamps_give_their_round_period`). One case cannot be told: the frame
    after a burst lost -- the burst's last frame, late by more than half a period, then
    looks like that lost one on time; none is lost there. (The example: the log starts with
    a burst of ten frames, the first 9.5 periods late -- a lattice through it puts the frames
    on time half a period off.)"""
    period = micro * 1e-6
    stamps, numbers = _ticks(period, 400, stalls, jitter, skew, seed)
    late = np.flatnonzero(stamps - numbers * period * (1 + skew) > (jitter + 0.01) * period)
    keep = np.ones(400, dtype=bool)
    keep[[i for i in lost if i - 1 not in late]] = False
    stamps, numbers = 1.8e9 + stamps[keep], numbers[keep]
    found = frame_lattice(stamps)
    assert found.number.tolist() == (numbers - numbers[0]).tolist()
    assert found.how == "nominal"
    c = numbers.astype(float) - numbers.mean()
    fit = (jitter * period + 2.4e-7) * np.abs(c).sum() / (c ** 2).sum()
    if abs(skew) * period + fit < 0.5e-6:
        assert found.period == pytest.approx(period, rel=1e-12)
    else:
        assert abs(found.period - period) <= abs(skew) * period + fit + 0.5e-6 + 1e-12


def test_a_period_of_no_whole_microsecond_is_the_mean_spacing() -> None:
    """333.33 us (a 3 kHz loop) is 1e-3 from 333 us: the mean spacing itself, not snapped."""
    period = 1e-3 / 3
    rng = np.random.default_rng(1)
    stamps = np.sort(np.arange(1000) * period + rng.uniform(0, 0.1 * period, 1000))
    found, how = nominal_period(stamps)
    assert how == "mean" and found == pytest.approx(period, rel=SNAP / 10)
    assert np.isnan(nominal_period(np.zeros(10))[0])


def test_imported_candump_log_identifies_the_true_inertia(logs: dict[str, Path], tmp_path: Path,
                                                          capsys: pytest.CaptureFixture[str]) -> None:
    """The free run (demo, J = 0.25) exported to candump and imported: its frames' median
    spacing is 0.999928 ms, which moved J to 0.249982 with an interval excluding 0.25; with
    the nominal period the interval covers the truth."""
    log, mcap = tmp_path / "free.log", tmp_path / "free-imported.mcap"
    assert main(["log", "export", str(logs["free"]), "--can", "--format", "candump", "-o", str(log)]) == 0
    assert main(["log", "import", str(log), "-o", str(mcap)]) == 0
    capsys.readouterr()
    assert main(["identify", str(mcap), "--drive", "odrive-0.6", "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["period"] == 0.001
    j = info["estimates"]["inertia"]
    assert j["identifiable"] and j["low"] <= 0.25 <= j["high"]
    # a --period that is none, or one the frames' stamps contradict: one line, exit 2
    for period, says in (("0", "expected a control period in seconds, > 0 and <= 10"),
                         ("1e300", "expected a control period in seconds, > 0 and <= 10"),
                         ("nan", "expected a control period in seconds, > 0 and <= 10"),
                         ("1e-300", "motion frames come every 0.001 s"),
                         ("0.003", "motion frames come every 0.001 s")):
        assert main(["identify", str(mcap), "--drive", "odrive-0.6", "--period", period]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and says in err, (period, err)
    # the drive profile is an input: --out never overwrites it
    from dobhil.data import drivers_dir
    profile = tmp_path / "my-odrive.yaml"
    profile.write_bytes((drivers_dir() / "odrive-0.6.yaml").read_bytes())
    assert main(["identify", str(mcap), "--drive", str(profile), "--out", str(profile)]) == 2
    assert "input" in capsys.readouterr().err
    assert profile.read_bytes() == (drivers_dir() / "odrive-0.6.yaml").read_bytes()
