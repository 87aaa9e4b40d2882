"""Closed-loop identification (dobhil/identify/closedloop.py): the runtime's controller
simulated in closed loop with the candidate plant, driven by the recorded reference."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from dobhil.cli.main import main
from dobhil.config.load import load_config
from dobhil.identify.closedloop import CLOSED_LOOP, OPEN_LOOP, identify_closed_loop, simulate_loop, validate_loop
from dobhil.identify.data import IdentData, find_segments
from dobhil.identify.fit import identify

from .closed_synthetic import Hidden, chirp, record
from tests.identify.conftest import emulated_log

TRUTH = {"inertia": 0.37, "viscous_friction": 0.05, "stiffness": 15000.0, "damping": 60.0,
         "contact_position": 0.0, "delay": 0.3e-3, "initial_position": -0.005}


def test_the_simulated_loop_is_the_runtime_controller_bit_for_bit() -> None:
    """A noise-free run whose torque feeds the measurement back (J_mi = J_mn), stepped by the
    runtime's ForceController: the kernel, given the hidden plant, sends the same torques (to
    rounding) and moves the same way; a 3 % different inertia does not."""
    run = record(Hidden(velocity_noise=0.0), 0, chirp(1500, 1, 60, 1.0, 0.9))
    out = simulate_loop(TRUTH, run)
    assert np.max(np.abs(out[:, 2] - run.torque)) < 1e-12 * np.max(np.abs(run.torque)) * 100
    assert np.max(np.abs(out[:, 1] - run.velocity)) < 1e-12
    other = simulate_loop({**TRUTH, "inertia": 0.38}, run)
    assert np.max(np.abs(other[:, 2] - run.torque)) > 0.1


def _open_loop(run: object) -> dict[str, tuple[bool, float, float, float]]:
    data = IdentData(period=1e-3, t=np.arange(run.samples) * 1e-3, torque=run.torque,  # type: ignore[attr-defined]
                     position=run.position, velocity=run.velocity, source="",  # type: ignore[attr-defined]
                     protocol="odrive", recorded={})
    result = identify(data, find_segments(data))
    return {n: (e.identifiable, e.value, e.low, e.high) for n, e in result.estimates.items()}


def test_closed_loop_covers_a_noisy_force_run_the_open_loop_fit_misses() -> None:
    """The demo's force run (its design: C_f J_mi = J_mn) in contact with a 1-60 Hz chirp
    around 1 N m, 4 s, the hidden plant of TRUTH, a 14-bit encoder and 0.05 rad/s of
    velocity noise (seed 1): the closed-loop intervals of J, K and D hold the truth; the
    open-loop fit of the same record finds no inertia, or one whose interval misses it, or
    misses the friction or the delay.

    One record, not a coverage: that is :func:`test_closed_loop_intervals_cover_the_truth_over_seeds`."""
    run = record(Hidden(), 1, chirp(4000, 1, 60, 1.0, 0.9), "design.identified_inertia=0.125")
    closed = identify_closed_loop(run).estimates
    for name in ("inertia", "stiffness", "damping"):
        e = closed[name]
        assert e.identifiable and e.low <= TRUTH[name] <= e.high, (name, e)
    opened = _open_loop(run)
    missed = [n for n in ("inertia", "viscous_friction", "stiffness", "damping", "delay")
              if not opened[n][0] or not opened[n][2] <= TRUTH[n] <= opened[n][3]]
    assert missed, opened


def test_identify_picks_the_method_and_reports_it(logs: dict[str, Path], tmp_path: Path,
                                                  capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["identify", str(logs["contact"]), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["method"] == CLOSED_LOOP
    assert main(["identify", str(logs["contact"]), "--json", "--method", "open-loop"]) == 0
    assert json.loads(capsys.readouterr().out)["method"] == OPEN_LOOP
    assert main(["identify", str(logs["contact"]), "--segment", "0:0.4", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["method"] == OPEN_LOOP
    # the measured responses go with the open-loop fit: auto picks it for them
    assert main(["identify", str(logs["contact"]), "--frf", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["method"] == OPEN_LOOP


def test_closed_loop_refuses_what_it_cannot_fit(logs: dict[str, Path], tmp_path: Path,
                                                capsys: pytest.CaptureFixture[str]) -> None:
    for args in ([str(logs["contact"]), str(logs["free"])], [str(logs["contact"]), "--segment", "0:0.4"],
                 [str(logs["contact"]), "--frf"]):
        assert main(["identify", *args, "--method", "closed-loop"]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "--method closed-loop" in err[0] and "open-loop" in err[0]
    can_log, imported = tmp_path / "c.log", tmp_path / "c.mcap"
    assert main(["log", "export", str(logs["contact"]), "--can", "--format", "candump", "-o", str(can_log)]) == 0
    assert main(["log", "import", str(can_log), "-o", str(imported)]) == 0
    capsys.readouterr()
    assert main(["identify", str(imported), "--drive", "odrive-0.6", "--method", "closed-loop"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no recorded controller" in err[0]
    # a closed-loop fit validated on a CAN log: the refusal names --validate and the way out
    # (it said "closed-loop identification needs the recorded controller", of the log validated)
    assert main(["identify", str(logs["contact"]), "--validate", str(imported)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"--validate {imported}" in err[0] and "--method open-loop" in err[0], err


def test_a_noise_free_emulated_run_is_fitted_to_its_truth(logs: dict[str, Path],
                                                         capsys: pytest.CaptureFixture[str]) -> None:
    """The demo's own 0.5 s lockstep run, no noise: every 95 % interval of J, b, K and D
    holds the config's value, and the values are within 1e-6 of it. Its residual is rounding
    (the drive's float32 frames), below the whiteness test's floor: an interval the fit's
    search stops short of the truth by, and no misfit line says so."""
    assert main(["identify", str(logs["contact"]), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["method"] == CLOSED_LOOP
    demo = load_config("demo")
    truth = {"inertia": demo.plant.inertia, "viscous_friction": demo.plant.viscous_friction,
             "stiffness": demo.environment.stiffness, "damping": demo.environment.damping}
    for name, value in truth.items():
        e = out["estimates"][name]
        assert e["low"] <= value <= e["high"], (name, e)
        assert abs(e["value"] - value) <= 1e-6 * value, (name, e)


def test_a_noise_free_emulated_run_is_fitted_to_its_truth_open_loop(logs: dict[str, Path],
                                                                   capsys: pytest.CaptureFixture[str]) -> None:
    """The same run by the open-loop output-error fit: the servo leaves the environment and
    enters it again within the contact segment, and the Plant switches modes at sub-step
    starts, so the cost is a washboard the refinement stopped in beside the truth's (delay
    0.09 ms, K 9987.9 [9983.7, 9992.2], residual 6.8e-6 rad/s where the truth's is 1e-9:
    dobhil/identify/fit.py, _whole_delay). Every 95 % interval holds the config's value,
    the true delay (the lockstep emulator's: design.delay_samples and input_delay, 0 here)
    included."""
    assert main(["identify", str(logs["contact"]), "--method", "open-loop", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["method"] == OPEN_LOOP
    demo = load_config("demo")
    truth = {"inertia": demo.plant.inertia, "viscous_friction": demo.plant.viscous_friction,
             "stiffness": demo.environment.stiffness, "damping": demo.environment.damping,
             "contact_position": demo.environment.contact_position,
             "delay": demo.design.delay_samples * demo.loop.period + demo.design.input_delay}
    for name, value in truth.items():
        e = out["estimates"][name]
        assert e["identifiable"] and e["low"] <= value <= e["high"], (name, e)
    assert out["residual"]["rms"] < 1e-8


#: seeds of the coverage test (~2.5 s of CPU each, idle machine); the 50-seed figure is in
#: docs/identify.md with its command
COVERAGE_SEEDS = 20


def test_closed_loop_intervals_cover_the_truth_over_seeds() -> None:
    """The record of the test above on seeds 0-19: the 95 % intervals of J, K and D hold the
    truth in at least 17 of 20 (binomial(20, 0.95) falls below 17 with probability 1.6 %),
    and the standard errors are near the spread, neither far narrower nor wider: the RMS of
    (estimate - truth) / standard error lies in [0.8, 1.6] (1 for calibrated errors; measured
    1.07-1.26 here and 1.37-1.40 over seeds 0-49, docs/identify.md; it was 34 for J and 377
    for K with the fits stopped on the cost's kinks, dobhil/identify/closedloop.py,
    _DIFF_STEP). The intervals are the hull of the profile's and the log-linearised ones
    (closedloop._profiled): 46, 46, 45 of seeds 0-49 against 45, 44, 44 for the latter alone.
    Seed 7's fit stops short of the minimum and is fitted again from the profile's lower point
    (closedloop._LOWER); without that its stiffness was reported not identifiable. The open-loop
    fit of the first four of the same records misses J each time (not identifiable, or an
    interval without the truth).

    The delay's intervals, the profile likelihood's (closedloop._Profile), miss the truth on
    at most 2 of the seeds where it is identifiable; the linearised ones missed it on 3 of
    18 here (seeds 0, 4, 14) and held it in 38 of 44 over seeds 0-49 (docs/identify.md)."""
    z: dict[str, list[float]] = {n: [] for n in ("inertia", "stiffness", "damping")}
    covered = dict.fromkeys(z, 0)
    opened = []
    delays: list[bool] = []
    for seed in range(COVERAGE_SEEDS):
        run = record(Hidden(), seed, chirp(4000, 1, 60, 1.0, 0.9), "design.identified_inertia=0.125")
        closed = identify_closed_loop(run).estimates
        for name in z:
            e = closed[name]
            assert e.identifiable, (seed, e)
            z[name].append((e.value - TRUTH[name]) / e.stderr)
            covered[name] += e.low <= TRUTH[name] <= e.high
        delay = closed["delay"]
        if delay.identifiable:
            assert delay.method == "profile", delay
            delays.append(delay.low <= TRUTH["delay"] <= delay.high)
        if seed < 4:
            ok, _, low, high = _open_loop(run)["inertia"]
            opened.append(ok and low <= TRUTH["inertia"] <= high)
    assert all(c >= 17 for c in covered.values()), (covered, z)
    assert len(delays) >= COVERAGE_SEEDS // 2 and delays.count(False) <= 2, delays
    rms = {n: float(np.sqrt(np.mean(np.square(v)))) for n, v in z.items()}
    assert all(0.8 <= r <= 1.6 for r in rms.values()), rms
    assert not any(opened), opened


#: the docs' walk-through rig (docs/identify.md, "The closed-loop workflow"): the demo's own
#: design, pressed from the start, a 20-bit encoder and 1 mrad/s of velocity noise
PRESSED = Hidden(inertia=0.3, counts=2 ** 20, velocity_noise=0.001)


def test_a_validation_run_passes_the_true_plant_and_fails_a_stiffer_one() -> None:
    """validate_loop simulates the validation run's own loop from its reference: the hidden
    plant leaves a white residual at the noise (fit % well above 0, the tests pass); the
    same plant with K 20 % off is a misfit on the same record."""
    truth = {**TRUTH, "inertia": PRESSED.inertia, "initial_position": 0.0}
    run = record(PRESSED, 2, chirp(2000, 1, 60, 0.8, 0.4), "design.identified_inertia=0.125",
                 "plant.initial_position=0")
    good = validate_loop(truth, run)
    assert not good.misfit and good.whiteness.passed and good.cross.passed
    assert abs(good.residual_rms - PRESSED.velocity_noise) < 0.1 * PRESSED.velocity_noise
    assert all(f.percent > 50 for f in good.fits), good.fits
    bad = validate_loop({**truth, "stiffness": 1.2 * TRUTH["stiffness"]}, run)
    assert bad.misfit and bad.residual_rms > 1.1 * good.residual_rms


def test_friction_and_damping_pressed_all_along_are_reported_as_their_sum() -> None:
    """Pressed all along, the servo's viscous friction and the environment's damping act as
    their sum: the fit trades one against the other (their correlation near -1), so the
    friction is reported not identifiable and held at 0, and the damping carries the sum and
    holds the true sum."""
    run = record(PRESSED, 1, chirp(3000, 1, 60, 0.8, 0.4), "design.identified_inertia=0.125",
                 "plant.initial_position=0")
    result = identify_closed_loop(run)
    friction = result.estimates["viscous_friction"]
    assert result.fitted["viscous_friction"] < 1e-6
    assert not friction.identifiable and "sum" in friction.why
    damping = result.estimates["damping"]
    total = TRUTH["damping"] + TRUTH["viscous_friction"]
    assert damping.identifiable and damping.low <= total <= damping.high, damping


def test_validate_goes_with_the_closed_loop_fit(logs: dict[str, Path], tmp_path: Path,
                                                capsys: pytest.CaptureFixture[str]) -> None:
    """--validate on a force run keeps the closed-loop fit and validates it in the validation
    run's loop: the residual is tested against the reference, not the fed-back torque."""
    for method in ("auto", "closed-loop"):
        assert main(["identify", str(logs["contact"]), "--validate", str(logs["contact"]), "--json",
                     "--method", method]) == 0
        info = json.loads(capsys.readouterr().out)
        assert info["method"] == CLOSED_LOOP
        assert info["validation"]["against"] == "reference"
        assert [f["signal"] for f in info["validation"]["fits"]] == ["velocity", "position"]
        # the fitted log itself validates nothing: said
        assert "validation is on data the fit has seen" in info["note"]
    assert main(["identify", str(logs["contact"]), "--validate", str(logs["free"]), "--json",
                 "--method", "open-loop"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["validation"]["against"] == "input" and "note" not in info
    # a validation run of another drive, or firmware: refused in one line before the fit
    for profile, match in (("mini-cheetah", "validate on a log of the same drive"), ("odrive-0.5", "firmware '0.5'")):
        other = emulated_log(tmp_path / f"{profile}.mcap", f"drive.profile={profile}")
        capsys.readouterr()
        assert main(["identify", str(logs["contact"]), "--validate", str(other)]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and match in err[0], err


def test_an_estimate_on_its_search_bound_is_not_identifiable() -> None:
    """A fit that ends on a bound of its search has no interior minimum there: the sandwich
    interval is meaningless (it was +-3e-11 for a true friction of 0.05), so the estimate is
    reported not identifiable, with the value it ran to; one just inside is kept."""
    from types import SimpleNamespace

    from dobhil.identify.closedloop import FITTED, _estimates
    rng = np.random.default_rng(0)
    rec = SimpleNamespace(torque=rng.normal(size=100), velocity=rng.normal(size=100),
                          position=rng.normal(size=100), model=SimpleNamespace(period=1e-3))
    lo, hi = np.zeros(len(FITTED) + 1), np.full(len(FITTED) + 1, 100.0)
    sd = np.full(len(FITTED) + 1, 1e-3)
    values = {"inertia": 0.3, "viscous_friction": 0.0, "stiffness": 50.0, "damping": 60.0,
              "contact_position": 0.5, "delay": 3e-4}
    out = _estimates(values, sd, rec, lo, hi, True)  # type: ignore[arg-type]
    assert not out["viscous_friction"].identifiable and "bound of its search" in out["viscous_friction"].why
    assert out["damping"].identifiable and out["damping"].value == 60.0
    inside = _estimates({**values, "viscous_friction": 1e-6}, sd, rec, lo, hi, True)  # type: ignore[arg-type]
    assert inside["viscous_friction"].identifiable


def test_scale_parameters_get_their_interval_on_the_log_scale() -> None:
    """The inertia, stiffness and damping, whose standard error grows with the estimate
    (dobhil/identify/closedloop.py, _interval), get ``value exp(+-z s / value)``: the same
    standard error, an interval longer above the estimate than below, both ends positive
    however wide; the friction and the contact position keep ``value +- z s``. A bound of
    the search still caps an end."""
    import math
    from types import SimpleNamespace

    import scipy.stats

    from dobhil.identify.closedloop import FITTED, _estimates
    z = float(scipy.stats.norm.ppf(0.975))
    rng = np.random.default_rng(0)
    rec = SimpleNamespace(torque=rng.normal(size=100), velocity=rng.normal(size=100),
                          position=rng.normal(size=100), model=SimpleNamespace(period=1e-3))
    lo, hi = np.full(len(FITTED) + 1, -1e9), np.full(len(FITTED) + 1, 1e9)
    values = {"inertia": 0.3, "viscous_friction": 0.5, "stiffness": 15000.0, "damping": 60.0,
              "contact_position": 0.5, "delay": 3e-4}
    sd = np.array([0.03, 0.05, 2000.0, 6.0, 0.01, 1e-4, 0.0])
    out = _estimates(values, sd, rec, lo, hi, True)  # type: ignore[arg-type]
    for name in ("inertia", "stiffness", "damping"):
        e, s = out[name], sd[FITTED.index(name)]
        assert e.method == "log-linearised" and e.stderr == s and e.value == values[name]
        assert e.low == pytest.approx(values[name] * math.exp(-z * s / values[name]), rel=1e-12)
        assert e.high == pytest.approx(values[name] * math.exp(z * s / values[name]), rel=1e-12)
        assert e.high - e.value > e.value - e.low > 0
    for name in ("viscous_friction", "contact_position"):
        e, s = out[name], sd[FITTED.index(name)]
        assert e.method == "linearised"
        assert (e.low, e.high) == pytest.approx((values[name] - z * s, values[name] + z * s), rel=1e-12)
    capped = _estimates(values, sd, rec, lo, np.where(np.arange(len(lo)) == 2, 16000.0, hi), True)  # type: ignore[arg-type]
    assert capped["stiffness"].high == 16000.0


def _linear_problem(monkeypatch: pytest.MonkeyPatch, seed: int) -> tuple[Any, np.ndarray, np.ndarray, np.ndarray]:
    """The closed-loop fit's problem on a model linear in its parameters, ``velocity = A theta
    + noise`` (the simulation replaced): the problem, ``A``, the velocity and the least-squares
    ``theta``. The columns are correlated: a held parameter's end depends on refitting the others."""
    from types import SimpleNamespace

    from dobhil.identify import closedloop as cl
    rng = np.random.default_rng(seed)
    n, p = 400, len(cl._VARIED)
    a = rng.normal(size=(n, p)) + 2.0 * rng.normal(size=(n, 1))
    y = a @ rng.uniform(1.0, 2.0, size=p) + 0.3 * rng.normal(size=n)

    def linear(values: dict[str, float], _: object) -> np.ndarray:
        out = np.zeros((n, 3))
        out[:, 1] = a @ np.array([values[v] for v in cl._VARIED])
        return out
    monkeypatch.setattr(cl, "simulate_loop", linear)
    rec = SimpleNamespace(velocity=y, torque=np.zeros(n), samples=n)
    problem = cl._Problem(rec, np.ones(p), np.arange(p), None)  # type: ignore[arg-type]
    return problem, a, y, np.linalg.lstsq(a, y, rcond=None)[0]


def test_the_profile_interval_of_a_linear_model_is_its_exact_interval(monkeypatch: pytest.MonkeyPatch) -> None:
    """The profile likelihood's end (dobhil/identify/closedloop.py, _Profile) on a model linear
    in its parameters, ``velocity = A theta + noise``, where the profile is exactly quadratic:
    each end lies ``sqrt(chi2_1(0.95) s^2 [(A^T A)^-1]_kk)`` from the least-squares estimate
    (Bates and Watts 1988, section 6.1), and the held cost there rises by that threshold."""
    import scipy.stats

    from dobhil.identify import closedloop as cl
    problem, a, y, best = _linear_problem(monkeypatch, 3)
    n, p = a.shape
    lo, hi = np.full(p, -10.0), np.full(p, 10.0)
    profile = cl._Profile(problem, best, lo, hi, problem(best), n)
    r = y - a @ best
    rise = float(scipy.stats.chi2.ppf(0.95, 1)) * float(r @ r) / (n - p)
    assert profile.rise == pytest.approx(rise)
    for k in (0, cl._VARIED.index("delay")):
        half = np.sqrt(rise * np.linalg.inv(a.T @ a)[k, k])
        # started from a guess off by 2x: the secant must find the end, not keep the guess
        for sign in (-1.0, 1.0):
            end = profile.end(k, best[k] + sign * 2.0 * half)
            assert end == pytest.approx(best[k] + sign * half, rel=0, abs=0.02 * half), (k, sign)
            assert profile.held_cost(k, end) - profile.best == pytest.approx(rise, rel=0.05)
            # a hull's end (beyond=True): a guess past the end is kept, one short of it followed
            far = best[k] + sign * 2.0 * half
            assert profile.end(k, far, beyond=True) == far
            end = profile.end(k, best[k] + sign * 0.5 * half, beyond=True)
            assert end == pytest.approx(best[k] + sign * half, rel=0, abs=0.02 * half), (k, sign)


def test_scale_parameters_report_the_hull_of_the_profile_and_the_sandwich() -> None:
    """The inertia, stiffness and damping (dobhil/identify/closedloop.py, _profiled): the
    interval is the hull of the log-linearised one and the profile likelihood's, whichever
    end is further out on each side, the standard error the sandwich's; judged too wide on
    the log scale (half the log of high / low beyond WIDEST); a damping reported as the sum
    with the friction keeps the sum's interval. The delay's stays the profile's own."""
    import math
    from types import SimpleNamespace

    from dobhil.identify.closedloop import FITTED, _estimates, _profiled
    from dobhil.identify.fit import WIDEST
    values = {"inertia": 0.3, "viscous_friction": 0.5, "stiffness": 15000.0, "damping": 60.0,
              "contact_position": 0.5, "delay": 3e-4}
    sd = np.array([0.03, 0.05, 2000.0, 6.0, 0.01, 1e-4, 0.0])
    rng = np.random.default_rng(0)
    rec = SimpleNamespace(torque=rng.normal(size=100), velocity=rng.normal(size=100),
                          position=rng.normal(size=100), model=SimpleNamespace(period=1e-3))
    lo, hi = np.full(len(FITTED) + 1, -1e9), np.full(len(FITTED) + 1, 1e9)
    sandwich = _estimates(values, sd, rec, lo, hi, True)  # type: ignore[arg-type]
    vary = np.arange(len(FITTED) + 1)

    class Ends:
        """A profile whose ends are given (scale 1: scaled units are the parameters' own)."""

        def __init__(self, ends: dict[str, tuple[float, float]]) -> None:
            self.ends = ends
            self.problem = SimpleNamespace(scale=np.ones(len(vary)))
            self.x = np.array([values[n] for n in FITTED] + [0.0])
            self.asked: list[str] = []

        def end(self, k: int, guess: float, *, beyond: bool = False) -> float:
            name = FITTED[k]
            self.asked.append(name)
            low, high = self.ends[name]
            return low if guess < values[name] else high

    ends = {"inertia": (0.25, 0.34),            # wider below, narrower above than the sandwich
            "stiffness": (12000.0, 30000.0),    # wider above
            "damping": (50.0, 70.0),            # inside the sandwich's
            "delay": (1e-4, 4e-4)}
    out = _profiled(sandwich, Ends(ends), values, sd, vary, rec)  # type: ignore[arg-type]
    for name in ("inertia", "stiffness", "damping"):
        e, s = out[name], sandwich[name]
        assert e.method == "hull" and e.stderr == s.stderr and e.value == s.value, e
        assert (e.low, e.high) == (min(s.low, ends[name][0]), max(s.high, ends[name][1])), (name, e, s)
    assert (out["delay"].method, out["delay"].low, out["delay"].high) == ("profile", 1e-4, 4e-4)
    # too wide on the log scale: a profile end past e^(2 WIDEST) times the other
    flat = _profiled(sandwich, Ends({**ends, "stiffness": (5000.0, 5000.0 * math.exp(2 * WIDEST) * 1.01)}),
                     values, sd, vary, rec)  # type: ignore[arg-type]
    assert not flat["stiffness"].identifiable and flat["stiffness"].why.startswith("flat profile")
    folded = Ends(ends)
    kept = _profiled(sandwich, folded, values, sd, vary, rec, folded=True)  # type: ignore[arg-type]
    assert kept["damping"] == sandwich["damping"] and "damping" not in folded.asked


def test_a_profile_refit_below_the_fit_is_kept_to_fit_again(monkeypatch: pytest.MonkeyPatch) -> None:
    """A fit that stopped short of the minimum (closedloop._Profile.lower): on the linear model
    of the test above, a profile taken at a point off the least-squares one finds, holding a
    parameter at its least-squares value, a cost lower than the point's; that refit's
    parameters (all of them, the held one in its place) are kept for the fit to start again
    from, the lowest of several. At the least-squares point itself no refit is lower."""
    from dobhil.identify import closedloop as cl
    problem, a, _, best = _linear_problem(monkeypatch, 4)
    n, p = a.shape
    lo, hi = np.full(p, -10.0), np.full(p, 10.0)
    at_best = cl._Profile(problem, best, lo, hi, problem(best), n)
    at_best.held_cost(0, best[0] + 0.01)
    assert at_best.lower is None
    short = best + 0.05
    profile = cl._Profile(problem, short, lo, hi, problem(short), n)
    first = profile.held_cost(0, best[0])
    assert profile.lower is not None and profile.lower[0] == best[0]
    assert np.allclose(profile.lower, best, atol=1e-4) and profile.lowest == first
    profile.held_cost(1, short[1])     # a worse point: the lowest stays
    assert profile.lowest == first and profile.lower[0] == best[0]


def test_the_folded_damping_carries_the_sums_covariance() -> None:
    """Where b and D_env are told only as their sum, the damping reported is the sum, and so
    are its correlations (and the overlay's covariance, montecarlo --draw-from's normal): those
    of D alone, which moves against b, are another quantity's. Here D alone is correlated
    -0.5 with the inertia and the sum 0."""
    from dobhil.identify.closedloop import _VARIED, _correlations, _fold_friction
    n = len(_VARIED)
    j, b, d = _VARIED.index("inertia"), _VARIED.index("viscous_friction"), _VARIED.index("damping")
    cov = np.eye(n)
    cov[b, b] = cov[d, d] = 100.0
    cov[b, d] = cov[d, b] = -99.9   # correlation -0.999
    cov[j, d] = cov[d, j] = -5.0    # the inertia with D alone: -0.5
    cov[j, b] = cov[b, j] = 5.0     # and with b: +0.5, so with b + D: 0
    t = np.eye(n)
    t[d, b] = 1.0                   # D' = b + D
    summed = t @ cov @ t.T
    values = {name: 1.0 for name in _VARIED}
    sd = np.sqrt(np.diag(cov))
    assert _fold_friction(values, sd, cov)
    assert (values["viscous_friction"], values["damping"]) == (0.0, 2.0)
    assert sd[d] == pytest.approx(np.sqrt(summed[d, d]), rel=1e-12)
    keep = [i for i in range(n) if i != b]
    assert np.allclose(cov[np.ix_(keep, keep)], summed[np.ix_(keep, keep)], rtol=1e-12, atol=1e-12)
    r = _correlations(cov)
    assert r[("inertia", "damping")] == pytest.approx(0.0, abs=1e-12)
    assert not any("viscous_friction" in pair for pair in r)   # held at 0: no correlation


class _Seen(Exception):
    """Raised by a spy once it has seen what it looks for: the rest of the fit is not needed."""


def test_the_closed_loop_fit_and_validation_run_blas_on_one_thread(monkeypatch: pytest.MonkeyPatch) -> None:
    """The whole fit runs BLAS on one thread, not only its simulations: its trust region's
    SVDs and products too (dobhil/identify/closedloop.py, identify_closed_loop: a threaded
    OpenBLAS made a fit ~3x dearer), and so does the validation; the pool is restored after.
    Two threads set here, so the test means something whatever OPENBLAS_NUM_THREADS says;
    each spy stops its call at the first point it sees."""
    from threadpoolctl import threadpool_info, threadpool_limits

    from dobhil.identify import closedloop as cl
    from dobhil.identify import validate

    def threads() -> set[int]:
        return {lib["num_threads"] for lib in threadpool_info() if lib["user_api"] == "blas"}
    seen: list[set[int]] = []

    def spy(*_: object, **__: object) -> None:
        seen.append(threads())
        raise _Seen
    run = record(Hidden(), 0, chirp(300, 1, 60, 1.0, 0.9), "design.identified_inertia=0.125")
    monkeypatch.setattr(cl, "_x0", spy)
    monkeypatch.setattr(validate, "residual_tests", spy)
    with threadpool_limits(limits=2, user_api="blas"):
        with pytest.raises(_Seen):
            identify_closed_loop(run)
        with pytest.raises(_Seen):
            validate_loop(TRUTH, run)
        assert threads() == {2}
    assert seen == [{1}, {1}]
