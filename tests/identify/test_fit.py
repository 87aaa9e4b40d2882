"""The identification's fit on synthetic records from the emulator's Plant with known
parameters (tests/identify/synthetic.py: quantised encoder, noisy velocity, Coulomb friction,
commands applied ``delay`` after their sample)."""

from __future__ import annotations

import math
import os
from dataclasses import asdict, replace

import numpy as np
import pytest
import scipy.optimize
import scipy.stats

from dobhil.emulator.plant import DisturbanceKind
from dobhil.identify.data import IdentData, Segment
from dobhil.identify.fit import (MISFIT_P, PARAMETERS, IdentResult, _partner, _quantum,
                                 _relative_steps, identify, simulate)
from dobhil.identify.model import ModelValues, simulate_torque, split_delay
from dobhil.synthesis.controller import discretize_delayed
from dobhil.synthesis.models import plant_matrices, servo_matrices

from .synthetic import COUNT, PERIOD, Truth, joined, multisine, record, run

TRUTH = Truth()
FITTED = ("inertia", "viscous_friction", "coulomb_friction", "contact_position", "stiffness",
          "damping", "delay")


def truth_values(truth: Truth = TRUTH) -> dict[str, float]:
    return {k: v for k, v in asdict(truth).items() if k in PARAMETERS}


# -- the model --------------------------------------------------------------------------

@pytest.mark.parametrize(("delay", "whole", "fraction"), [
    (0.0, 0, 0.0), (0.3e-3, 0, 0.3e-3), (1.0e-3, 1, 0.0), (1.3e-3, 1, 0.3e-3),
    (2.0e-3 - 1e-13, 2, 0.0)])
def test_split_delay_is_design_delay_samples_plus_input_delay(delay: float, whole: int,
                                                              fraction: float) -> None:
    w, f = split_delay(delay, 1e-3)
    assert w == whole
    assert f == pytest.approx(fraction, abs=1e-15)
    assert 0.0 <= f < 1e-3


@pytest.mark.parametrize("delay", [0.0, 0.4e-3, 1.0e-3, 2.7e-3])
@pytest.mark.parametrize("contact", [False, True])
def test_model_is_the_analysis_sampled_plant(delay: float, contact: bool) -> None:
    """Without Coulomb friction and with the mode fixed the simulation is the analysis'
    sampled plant with a delayed input, x[k+1] = Phi x[k] + G0 u[k-d] + G1 u[k-d-1]
    (discretize_delayed), to rounding: one model, one discretisation."""
    j, b, k, d, qc = 0.25, 0.5, 1.0e4, 50.0, 0.2
    rng = np.random.default_rng(3)
    n = 400
    u = rng.uniform(-5.0, 5.0, n) + (100.0 if contact else 0.0)
    if contact:
        a, bb, _ = plant_matrices(j, b, k, d)
        values = ModelValues(inertia=j, viscous_friction=b, stiffness=k, damping=d,
                             contact_position=qc, delay=delay)
        q0 = qc + 100.0 / k            # at rest in equilibrium with the first torques' mean
    else:
        a, bb = servo_matrices(j, b)
        values = ModelValues(inertia=j, viscous_friction=b, delay=delay)
        q0 = 0.7
    whole, fraction = split_delay(delay, PERIOD)
    phi, g0, g1 = discretize_delayed(a, bb, PERIOD, fraction)
    ext = np.concatenate([np.zeros(whole + 1), u])     # ext[i + whole + 1] = u[i]
    x = np.array([q0 - (qc if contact else 0.0), 0.0])
    expected = [x]
    for i in range(n - 1):
        x = phi @ x + g0[:, 0] * ext[i + 1] + g1[:, 0] * ext[i]
        expected.append(x)
    ref = np.array(expected)
    pos, vel = simulate_torque(values, u, PERIOD, 0, n, q0)
    if contact:
        assert np.all(pos >= qc)                   # it stayed in contact: the linear plant
    np.testing.assert_allclose(pos - (qc if contact else 0.0), ref[:, 0], rtol=0, atol=1e-10)
    np.testing.assert_allclose(vel, ref[:, 1], rtol=0, atol=1e-9)


def test_simulate_uses_commands_sent_before_the_segment() -> None:
    """A segment starting late still feels the commands in transit at its start."""
    u = np.zeros(50)
    u[9] = 1.0    # sent at sample 9, acts from 9 T + delay
    data = IdentData(period=PERIOD, t=np.arange(50) * PERIOD, torque=u, position=np.zeros(50),
                     velocity=np.zeros(50), source="", protocol="", recorded={})
    _, vel = simulate({"inertia": 1.0, "delay": 1.5e-3}, data, Segment(10, 20, "free"))
    # u[9] acts over [9T + 1.5T, 10T + 1.5T] = [10.5T, 11.5T]: velocity 0 at 10, T/2 at 11, T at 12
    np.testing.assert_allclose(vel[:3], [0.0, 0.5 * PERIOD, PERIOD], atol=1e-15)


# -- the fit ----------------------------------------------------------------------------

def within(result_value: float, truth: float, rel: float) -> bool:
    return abs(result_value - truth) <= rel * abs(truth)


def test_recovers_a_known_plant_within_the_issue_targets() -> None:
    data, segments = record(TRUTH, seed=1)
    result = identify(data, segments)
    e = result.estimates
    assert set(e) == set(PARAMETERS)
    for name, rel in (("inertia", 0.02), ("viscous_friction", 0.02), ("stiffness", 0.02),
                      ("damping", 0.10)):
        assert e[name].identifiable, e[name].why
        assert within(e[name].value, getattr(TRUTH, name), rel), (name, e[name])
    assert abs(e["delay"].value - TRUTH.delay) <= 0.05e-3
    for name in FITTED:
        est = e[name]
        assert est.low <= est.value <= est.high and est.stderr > 0, est
    assert not e["torque_gain"].identifiable and math.isnan(e["torque_gain"].value)
    assert not result.residual.misfit and result.residual.warning == ""
    # the residual is the sensor noise: the fit explains everything else
    assert result.residual.rms == pytest.approx(TRUTH.velocity_noise, rel=0.1)
    assert all(-1.0 <= c <= 1.0 for c in result.correlations.values()) and result.correlations
    overlay = result.overlay()
    assert overlay["plant.inertia"] == overlay["design.identified_inertia"] == e["inertia"].value
    assert overlay["environment.stiffness"] == e["stiffness"].value
    assert overlay["design.delay_samples"] == 1
    assert abs(overlay["design.input_delay"] - 0.3e-3) <= 0.05e-3
    assert "plant.torque_gain" not in overlay


def test_no_contact_segment_leaves_the_environment_not_identifiable() -> None:
    data, segments = record(TRUTH, seed=4, contact_s=0.0)
    result = identify(data, segments)
    e = result.estimates
    for name in ("stiffness", "damping", "contact_position"):
        assert not e[name].identifiable and math.isnan(e[name].value)
        assert "no contact" in e[name].why
    assert within(e["inertia"].value, TRUTH.inertia, 0.02)
    overlay = result.overlay()
    assert not any(k.startswith("environment.") for k in overlay)
    assert "plant.inertia" in overlay


def test_a_servo_that_never_breaks_away_gives_flat_profiles_not_numbers() -> None:
    """Torque below the Coulomb friction: the servo never moves, any inertia and delay fit
    the record equally: not identifiable, never a number."""
    data, segments = record(TRUTH, seed=5, contact_s=0.0, free_amplitude=0.2)
    result = identify(data, segments)
    e = result.estimates
    for name in ("inertia", "delay"):
        assert not e[name].identifiable and math.isnan(e[name].value), e[name]
        assert "flat profile" in e[name].why
    assert "plant.inertia" not in result.overlay()


def test_an_unmodelled_disturbance_is_a_misfit_warning() -> None:
    """A 7 Hz disturbance torque the model does not have: the residual is not white."""
    data, segments = record(TRUTH, seed=6, contact_s=0.0,
                            disturbance=DisturbanceKind.SINE, disturbance_amplitude=0.5,
                            disturbance_frequency=7.0)
    result = identify(data, segments)
    assert result.residual.misfit
    assert result.residual.whiteness_p < MISFIT_P
    assert "misfit" in result.residual.warning


def test_bad_segments_are_refused() -> None:
    data, _ = record(TRUTH, seed=7, free_s=0.2, contact_s=0.0)
    n = len(data.torque)
    for segments in ([], [Segment(0, n + 1, "free")], [Segment(5, 5, "free")],
                     [Segment(0, n, "sliding")], [Segment(0, 10, "free")]):
        with pytest.raises(ValueError, match="identify"):
            identify(data, segments)


# -- coverage ---------------------------------------------------------------------------

#: DOBHIL_SLOW=1: the issue's 50 seeded runs, each parameter covered in >= 45 (90 %);
#: by default 8 of them, >= 6 each (a method whose 95 % intervals cover fails that for one
#: of the 7 parameters with probability ~4 %: a real check, in under a minute)
SLOW = bool(os.environ.get("DOBHIL_SLOW"))
RUNS, NEEDED = (50, 45) if SLOW else (8, 6)


def test_the_95_percent_intervals_cover_the_truth_in_90_percent_of_runs() -> None:
    truth = truth_values()
    covered = dict.fromkeys(FITTED, 0)
    for seed in range(100, 100 + RUNS):
        data, segments = record(TRUTH, seed=seed)
        e = identify(data, segments).estimates
        for name in FITTED:
            covered[name] += e[name].identifiable and e[name].low <= truth[name] <= e[name].high
    assert all(c >= NEEDED for c in covered.values()), covered


def test_an_interval_that_would_leave_the_bounds_ends_at_the_bound() -> None:
    """No Coulomb friction: the estimate sits at (or near) its bound 0, value - z stderr
    would be negative; the interval ends at the bound instead, and still covers the truth."""
    truth = Truth(coulomb_friction=0.0)
    data, segments = record(truth, seed=8, contact_s=0.0)
    e = identify(data, segments).estimates["coulomb_friction"]
    assert e.identifiable, e.why
    assert 0.0 <= e.low <= e.value <= e.high
    assert e.low == 0.0 and e.value < 1.96 * e.stderr      # cut at the bound
    assert e.low <= 0.0 + 1e-9 and e.high < 0.01 * 3.0


def test_an_interval_past_a_bound_of_the_search_is_no_number() -> None:
    """The search's own bounds (an inertia or stiffness 20 times its start estimate, every
    maximum) are no bound of the plant: a fit that ran to one (measured: a coupled axis whose
    start estimate was 230 times low gave 0.0215 [0.0196, 0.0215], its search's maximum, for a
    true 0.25) is not identifiable, saying so, while an interval cut at a friction's or
    delay's 0 stays a number; one inside every bound is kept."""
    from types import SimpleNamespace

    import lmfit

    from dobhil.identify.fit import _estimates
    data, segments = joined([(np.sin(np.arange(200.0)), np.zeros(200), np.cos(np.arange(200.0)), "free")])
    params = lmfit.Parameters()
    params.add("inertia", value=0.0215, min=0.001, max=0.02151)
    params.add("viscous_friction", value=1e-6, min=0.0, max=1.0)
    params.add("coulomb_friction", value=0.01, min=0.0, max=1.0)
    params.add("delay", value=2e-4, min=0.0, max=4e-3)
    names = ["inertia", "viscous_friction", "coulomb_friction", "delay"]
    sd = np.array([1e-3, 1e-3, 1e-4, 1e-5])
    result = SimpleNamespace(params=params)
    out = _estimates(None, result, (names, np.diag(sd ** 2)), data, segments)  # type: ignore[arg-type]
    assert not out["inertia"].identifiable and "bound of the fit's search (0.0215" in out["inertia"].why
    assert out["viscous_friction"].identifiable and out["viscous_friction"].low == 0.0   # a bound of the plant
    assert out["coulomb_friction"].identifiable and out["delay"].identifiable
    params["inertia"].set(max=1.0)
    assert _estimates(None, result, (names, np.diag(sd ** 2)), data, segments)["inertia"].identifiable  # type: ignore[arg-type]


@pytest.mark.parametrize("name", ["coulomb_friction", "delay"])
def test_at_a_bound_the_high_end_is_the_profile_likelihood(name: str) -> None:
    """No Coulomb friction, no delay: each estimate sits near its bound 0, its interval
    runs from the bound to where the profile -- the cost with the parameter held and the
    others refitted -- has risen chi2_1(0.95) s^2 above the optimum. Checked here with an
    independent refit (scipy's least_squares through the public simulate): at the high
    end the rise is the threshold, at half of it below."""
    data, segments = record(Truth(coulomb_friction=0.0, delay=0.0), seed=8, contact_s=0.0)
    result = identify(data, segments)
    e = result.estimates[name]
    assert e.identifiable and e.method == "profile", e
    assert e.low == 0.0 and e.value < e.high
    seg = segments[0]
    measured = data.velocity[seg.start:seg.stop]
    base = {k: result.estimates[k].value
            for k in ("inertia", "viscous_friction", "coulomb_friction", "delay")}
    q0, v0 = result.initial[0]

    def residual(values: dict[str, float], v_start: float) -> np.ndarray:
        return measured - simulate(values, data, seg, (q0, v_start))[1]

    r = residual(base, v0)
    best = float(r @ r)
    threshold = scipy.stats.chi2.ppf(0.95, 1) * best / (len(r) - 5)
    others = [k for k in base if k != name]

    def rise(x: float) -> float:
        def held(z: np.ndarray) -> np.ndarray:
            values = {**base, **{k: max(float(v), 0.0) for k, v in zip(others, z)}, name: x}
            return residual(values, float(z[-1]))
        z0 = np.array([base[k] for k in others] + [v0])
        fit = scipy.optimize.least_squares(held, z0, diff_step=1e-3, x_scale=np.abs(z0) + 1e-4)
        return (2.0 * fit.cost - best) / threshold

    assert 0.8 < rise(e.high) < 1.25
    assert rise(0.5 * e.high) < 0.8


# -- numbers only when the record determines them -----------------------------------------

def assert_honest(result: IdentResult, truth: dict[str, float]) -> None:
    """Every value reported identifiable has its 95 % interval around the truth: a
    parameter the record cannot determine is not identifiable, never a confident number."""
    wrong = {name: (e.value, e.low, e.high) for name, e in result.estimates.items()
             if name in truth and e.identifiable and not e.low <= truth[name] <= e.high}
    assert wrong == {}


def test_a_segment_cut_in_motion_fits_its_initial_state() -> None:
    """A segment found in a run starts moving: its true initial velocity is fitted (the
    measured one is noisy), the estimates are as good as from rest."""
    data, _ = record(TRUTH, seed=2, contact_s=0.0)
    clean, _ = record(replace(TRUTH, velocity_noise=0.0), seed=2, contact_s=0.0)
    start = 700
    assert abs(clean.velocity[start]) > 10 * TRUTH.velocity_noise      # really moving
    result = identify(data, [Segment(start, len(data.torque), "free")])
    e = result.estimates
    for name in ("inertia", "viscous_friction"):
        assert within(e[name].value, getattr(TRUTH, name), 0.02), e[name]
    assert abs(e["delay"].value - TRUTH.delay) <= 0.05e-3
    q0, v0 = result.initial[0]
    assert abs(v0 - clean.velocity[start]) < TRUTH.velocity_noise       # better than a reading
    assert q0 == data.position[start]          # a free segment's position is not fitted
    assert_honest(result, truth_values())


def test_a_segment_fits_alike_whatever_the_record_holds_around_it() -> None:
    """The samples outside the segments are none of the fit's business: a free run fitted
    alone and the same run as a segment of a longer record (a CAN capture holds the drive's
    idle stream before the run and the drive coasting after it: here a burst of torque and
    speed larger than the run's own) give the same numbers, bit for bit."""
    data, (segment,) = record(TRUTH, seed=4, free_s=1.0, contact_s=0.0)
    pad = 300
    rng = np.random.default_rng(5)
    around = np.concatenate([np.zeros(pad), data.torque, 5.0 * rng.standard_normal(pad)])
    wide = replace(data, t=np.arange(around.size) * PERIOD, torque=around,
                   position=np.concatenate([np.full(pad, data.position[0]), data.position,
                                            np.full(pad, data.position[-1])]),
                   velocity=np.concatenate([np.zeros(pad), data.velocity, 40.0 * rng.standard_normal(pad)]))
    alone = identify(data, [segment]).estimates
    inside = identify(wide, [Segment(segment.start + pad, segment.stop + pad, "free")]).estimates
    for name in FITTED:
        assert repr(inside[name]) == repr(alone[name])   # every float's shortest repr: bit for bit


def test_a_contact_only_record_does_not_separate_viscous_friction_and_damping() -> None:
    """Pressed all the time, b and D_env act as their sum: neither is reported as a number
    unless its interval covers the truth; the stiffness still is, within 2 %."""
    data, segments = record(TRUTH, seed=9, free_s=0.0)
    result = identify(data, segments)
    e = result.estimates
    assert within(e["stiffness"].value, TRUTH.stiffness, 0.02), e["stiffness"]
    assert_honest(result, truth_values())
    for name, other in (("viscous_friction", "damping"), ("damping", "viscous_friction")):
        assert e[name].identifiable or other in e[name].why, e[name]


def test_a_true_delay_of_zero_is_zero_with_an_interval() -> None:
    """No delay: reported 0 (at its bound) with an interval from 0, not "not identifiable"."""
    data, segments = record(replace(TRUTH, delay=0.0), seed=3, contact_s=0.0)
    result = identify(data, segments)
    e = result.estimates["delay"]
    assert e.identifiable, e.why
    assert 0.0 <= e.low <= e.value <= e.high and e.value <= 0.05e-3, e
    assert e.high - e.low < 0.1e-3
    overlay = result.overlay()
    assert overlay["design.delay_samples"] == 0 and overlay["design.input_delay"] <= 0.05e-3


def test_noise_free_data_is_no_misfit() -> None:
    """Without sensor noise the residual is rounding (and the model's own roughness), not
    a model error: no misfit warning, and the values are the truth."""
    data, segments = record(replace(TRUTH, velocity_noise=0.0), seed=10, contact_s=0.0)
    result = identify(data, segments)
    assert not result.residual.misfit and result.residual.warning == "", result.residual
    assert within(result.estimates["inertia"].value, TRUTH.inertia, 0.001)


@pytest.mark.parametrize("seed", [1, 2])
def test_a_free_multisine_with_coulomb_friction_finds_the_truth(seed: int) -> None:
    """identify-free's excitation (a 0.5 N m multisine, 0.5-20 Hz) on a light-friction
    servo, noise-free: the velocity crosses zero hundreds of times, and every crossing
    switches the Coulomb friction on a sub-step -- the cost is rough on MINPACK's step.
    Levenberg-Marquardt used to stop where the equation-error start put it (seed 1:
    viscous friction 0.046 for 0.02, Coulomb 0.0475, a misfit warning; the 60 s log
    0.078 / 0.0436) though the cost falls all the way to the truth: the staged fit's
    coarse differences walk there."""
    truth = replace(TRUTH, viscous_friction=0.02, coulomb_friction=0.05, delay=0.0,
                    velocity_noise=0.0)
    rng = np.random.default_rng(seed)
    u = multisine(int(10.0 / PERIOD), 0.5, (0.5, 20.0), 40, rng)
    q, v = run(truth, u, 0.0, seed)
    data, segments = joined([(u, q, v, "free")])
    result = identify(data, segments)
    e = result.estimates
    for name in ("inertia", "viscous_friction", "coulomb_friction"):
        assert within(e[name].value, getattr(truth, name), 0.01), (name, e[name])
    assert e["delay"].value <= 0.02e-3, e["delay"]
    assert not result.residual.misfit, result.residual


def test_a_constant_torque_gives_no_confident_wrong_numbers() -> None:
    """A constant torque from rest: the acceleration fixes (u - F_c)/J and the slope b/J,
    not J and F_c apart -- but the few samples after the torque ends do. Whatever the fit
    says: every number it reports covers the truth."""
    n = 800
    u = np.concatenate([np.full(n, 2.0), np.zeros(40)])
    q, v = run(TRUTH, u, 0.0, seed=11)
    data, segments = joined([(u, q, v, "free")])
    result = identify(data, segments)
    assert_honest(result, truth_values())


def test_the_delay_interval_is_the_cost_curvature_on_its_own_scale() -> None:
    """The cost is rough in the delay (stick and slip land on sub-steps): moving it by one
    standard error, the others held, raises the residual sum of squares by about one
    noise variance -- with MINPACK's tiny forward step it rose by 0.05-0.35 (measured:
    the standard error 13x too small, the interval missing the truth in 12 of 50 runs)."""
    data, segments = record(TRUTH, seed=109, contact_s=0.0)
    result = identify(data, segments)
    e = result.estimates
    values = {name: e[name].value for name in ("inertia", "viscous_friction", "coulomb_friction")}
    seg = segments[0]

    def residual(delay: float) -> np.ndarray:
        _, vel = simulate(values | {"delay": delay}, data, seg, result.initial[0])
        return np.asarray(data.velocity[seg.start:seg.stop]) - vel

    r0 = residual(e["delay"].value)
    s2 = float(r0 @ r0) / (r0.size - 5)
    for sign in (-1.0, 1.0):
        r = residual(e["delay"].value + sign * e["delay"].stderr)
        assert float(r @ r - r0 @ r0) / s2 > 0.3


def test_the_encoder_count_is_read_from_the_positions() -> None:
    q = np.array([0.0, 3.0, 2.0, 2.0, 7.0, 6.0]) * COUNT + 400 * COUNT
    assert _quantum(q) == pytest.approx(COUNT, rel=1e-9)
    assert _quantum(np.array([0.0, 0.1, 0.23, 0.3])) == 0.0        # not on a grid
    assert _quantum(np.zeros(5)) == 0.0


@pytest.mark.parametrize(("x0", "step"), [([2.0, -0.5, 1e-4], [0.2, 0.05, 1e-3]),
                                          ([1e4, 3e-3, -7.0], [1e3, 0.01, 0.7])])
def test_scipys_central_differences_take_the_absolute_steps_asked_for(
        x0: list[float], step: list[float]) -> None:
    """_refine hands scipy's least_squares absolute steps (the standard errors) through its
    relative ``diff_step`` (_relative_steps): on ``f(x) = x^3`` the central difference is
    ``3 x^2 + h^2``, so the Jacobian scipy returns shows the step it took -- a scipy that
    computed it otherwise (``max(1, |x|)``, as its docs once said) fails here."""
    x = np.array(x0)
    h = np.array(step)
    fit = scipy.optimize.least_squares(lambda v: v ** 3 - x ** 3 + 1.0, x, jac="3-point",
                                       diff_step=_relative_steps(h, x), max_nfev=1)
    taken = np.sqrt(np.diag(fit.jac) - 3.0 * x ** 2)
    assert np.allclose(taken, h, rtol=1e-3), (taken, h)


@pytest.mark.parametrize(("r", "named"), [(-0.92, True), (0.95, True), (-0.89, False), (0.0, False)])
def test_a_parameter_not_identifiable_names_its_partner_beyond_0_9(r: float, named: bool) -> None:
    """The line of a parameter that is not identifiable names the one it is most correlated
    with when |r| > 0.9 (b and D_env in a pressed record: -0.92), with the correlation; a
    weaker one is no explanation and is not named. A third, uncorrelated parameter is never
    the partner."""
    sd = np.array([2.0, 50.0, 1.0])
    corr = np.array([[1.0, r, 0.0], [r, 1.0, 0.1], [0.0, 0.1, 1.0]])
    line = _partner("viscous_friction", (["viscous_friction", "damping", "inertia"], corr * np.outer(sd, sd)))
    if named:
        assert line == f"; only a combination with damping is determined (correlation {r:+.3f}): " \
                       "the record does not separate them"
    else:
        assert line == ""


def _pressed_result(kind: str = "contact") -> IdentResult:
    """A fit's result as a pressed record gives it: the damping identifiable, the friction
    not (only their sum is determined), fitted b 7 and D 53 (the split along the valley)."""
    from dobhil.identify.fit import Estimate, Residual
    nan = math.nan
    est = {n: Estimate(n, 1.0, 0.01, 0.98, 1.02, True, "") for n in PARAMETERS}
    est["viscous_friction"] = Estimate("viscous_friction", nan, nan, nan, nan, False, "flat profile")
    est["damping"] = Estimate("damping", 53.0, 4.0, 45.0, 61.0, True, "")
    return IdentResult(estimates=est, correlations={}, residual=Residual(1e-3, 0.5, False, ""),
                       segments=(Segment(0, 100, kind),), period=PERIOD,
                       fitted={"viscous_friction": 7.0, "damping": 53.0, "inertia": 1.0})


def test_a_pressed_records_overlay_gives_the_loop_the_fitted_sum_of_friction_and_damping() -> None:
    """Only b + D is determined: the overlay leaves the friction to the config and writes
    the damping that makes the recorded config's friction plus it the fitted sum (60), so the
    loop in contact has the damping the record showed, and says so in a comment line."""
    result = _pressed_result()
    assert result.overlay()["environment.damping"] == pytest.approx(60.0)   # the friction not known
    overlay = result.overlay(0.05)
    assert "plant.viscous_friction" not in overlay
    assert overlay["environment.damping"] == pytest.approx(60.0 - 0.05)
    assert result.overlay(100.0)["environment.damping"] == 0.0
    from dobhil.cli.identify_cmd import damping_note
    assert "less the recorded plant.viscous_friction (0.05)" in damping_note(result, {"plant.viscous_friction": 0.05})
    # a record with free motion separates them: nothing folded, nothing said
    free = _pressed_result("free")
    assert free.overlay(0.05)["environment.damping"] == 53.0 and damping_note(free, {}) == ""


def test_a_pressed_record_reports_the_sum_of_friction_and_damping_with_the_sums_interval() -> None:
    """Pressed all along, the friction not identifiable: the damping reported is the fitted
    b + D_env (what the overlay writes) with the sum's interval, which holds the true sum,
    and the overlay's comment and ``identified:`` box hold the value the overlay sets (the
    sum less the recorded friction), not D alone (docs/identify.md section 5's force1.mcap:
    D 52.65 in [29.9, 60.4] boxed for a written 59.76)."""
    import yaml

    from dobhil.cli.identify_cmd import _less_friction, overlay_text, summary
    from dobhil.identify.data import Part
    data, segments = record(TRUTH, seed=9, free_s=0.0)
    result = identify(data, segments)
    e = result.estimates
    assert not e["viscous_friction"].identifiable and "the damping reported is their sum" in e["viscous_friction"].why
    total = result.damping_sum()
    assert total is not None and e["damping"].value == total
    assert e["damping"].low <= TRUTH.viscous_friction + TRUTH.damping <= e["damping"].high, e["damping"]
    info = summary(result, data, (Part("pressed.mcap", 0, len(data.t), result.segments),))
    friction = 0.5
    text = overlay_text(result.overlay(friction), _less_friction(info, result, friction))
    written = yaml.safe_load(text)
    box = written["identified"]["intervals"]["environment.damping"]
    assert box["estimate"] == written["environment.damping"] == pytest.approx(total - friction)
    assert box["lo"] == pytest.approx(e["damping"].low - friction) and box["stderr"] == e["damping"].stderr
