"""The coupled loop of several axes (dobhil/analysis/coupled.py) against three references:
each axis' own analysis when nothing couples them, the common and differential modes of two
identical axes, and the loop built again by python-control's ``interconnect``."""

from __future__ import annotations

import dataclasses
import json
import warnings
from pathlib import Path

import numpy as np
import pytest
import scipy.linalg
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from dobhil.analysis.coupled import (AxisDesign, axis_designs, coupled_groups, coupled_loop, sampled_coupled_plant,
                                     spectral_margin, stable_scales)
from dobhil.analysis.coupled_analysis import analyze_coupled
from dobhil.analysis.coupled_check import CheckUnavailable, check_loop
from dobhil.analysis.gate import assess
from dobhil.analysis.report import analyze_domain
from dobhil.cli.main import main
from dobhil.config import load_config
from dobhil.config.axes import Coupling, load_axes
from dobhil.synthesis.controller import discretize_delayed
from dobhil.synthesis.loop import plant_of
from dobhil.synthesis.params import params_from_config

TWO_AXES = """\
loop: {period: 0.001, duration: 0.5, timing: lockstep}
axes:
  - name: left
    drive: {profile: odrive-0.6, node_id: 1}
  - name: right
    drive: {profile: odrive-0.6, node_id: 2}
    plant: {inertia: 0.3}
environment:
  coupling:
    - {axes: [left, right], stiffness: 2000.0, damping: 20.0}
"""

#: designs that differ from one axis to the other: delays (whole and fractional), the
#: velocity source, torque models, frictions
VARIANTS = [
    [],
    ["axes.right.design.delay_samples=1"],
    ["axes.left.design.input_delay=0.0003", "axes.right.design.delay_samples=2"],
    ["axes.left.design.velocity_source=estimated", "axes.right.design.interaction_model=ramp"],
    ["axes.right.plant.viscous_friction=0.4", "axes.left.design.force_gain=3.5",
     "axes.left.environment.stiffness=40000"],
]


def write(tmp_path: Path, text: str = TWO_AXES) -> Path:
    path = tmp_path / "axes.yaml"
    path.write_text(text)
    return path


def designs_of(tmp_path: Path, overrides: list[str], text: str = TWO_AXES) -> tuple[tuple[AxisDesign, ...],
                                                                                     tuple[Coupling, ...]]:
    axes = load_axes(write(tmp_path, text), overrides)
    return axis_designs(axes), axes.couplings


def radius(a: np.ndarray, sampled: bool) -> float:
    p = np.linalg.eigvals(a)
    return float(np.max(np.abs(p)) if sampled else np.max(p.real))


def exact_step(a: np.ndarray, b: np.ndarray, c: np.ndarray, d: float, t: float) -> float:
    """A continuous unit step's output at time t, from one matrix exponential."""
    n = a.shape[0]
    block = np.zeros((n + 1, n + 1))
    block[:n, :n], block[:n, n] = a * t, b[:, 0] * t
    return float(c[0] @ scipy.linalg.expm(block)[:n, n] + d)


@pytest.mark.parametrize("zero_coupling", [False, True], ids=["no-coupling", "coupling-K0-D0"])
@pytest.mark.parametrize("overrides", VARIANTS)
@pytest.mark.parametrize("sampled", [True, False], ids=["sampled", "continuous"])
def test_uncoupled_axes_are_each_axis_alone(tmp_path: Path, overrides: list[str], sampled: bool,
                                            zero_coupling: bool) -> None:
    designs, _ = designs_of(tmp_path, overrides)
    couplings = (Coupling("left", "right", 0.0, 0.0),) if zero_coupling else ()
    domain = analyze_coupled(designs, couplings).discrete if sampled else \
        analyze_coupled(designs, couplings).continuous
    singles = {d.name: analyze_domain(d.params, sampled=sampled) for d in designs}
    # the spectral radius (abscissa) of the coupled loop is the worst axis' own
    own = {n: radius(s.systems.closed.a, sampled) for n, s in singles.items()}
    assert domain.spectral_radius == pytest.approx(max(own.values()), rel=0, abs=1e-12)
    # every axis' own closed-loop poles are poles of the coupled loop
    for s in singles.values():
        for p in s.closed_loop_poles:
            assert np.min(np.abs(domain.poles - p)) <= 1e-9 * max(1.0, abs(p))
    for step in domain.steps:
        single = singles[step.axis]
        other = next(n for n in singles if n != step.axis)
        assert np.all(step.estimate[other] == 0.0) and np.all(step.force[other] == 0.0)
        if sampled:    # one grid, every period: the common samples equal
            k = min(step.t.size, single.step_time.size)
            assert k > 20
            np.testing.assert_allclose(step.t[:k], single.step_time[:k], rtol=1e-15)
            np.testing.assert_allclose(step.estimate[step.axis][:k], single.step_estimate[:k], rtol=0, atol=1e-12)
            np.testing.assert_allclose(step.force[step.axis][:k], single.step_true[:k], rtol=0, atol=1e-12)
        else:          # grids differ (they follow the loop's poles): the single loop at the coupled times
            a, b, c, dd = single.systems.closed.siso("tau_ref", "tau_int_hat")
            for i in np.linspace(1, step.t.size - 1, 40).astype(int):
                assert step.estimate[step.axis][i] == pytest.approx(
                    exact_step(a, b, c, float(dd[0, 0]), float(step.t[i])), abs=1e-12)
        assert step.metrics.final_value == pytest.approx(1.0, abs=1e-12)


@pytest.mark.parametrize("overrides", VARIANTS[:3])
def test_uncoupled_gain_scale_is_the_tightest_axis(tmp_path: Path, overrides: list[str]) -> None:
    """Every C_f scaled by s: the largest stable s is the smallest of each axis' own largest
    stable C_f (the single-axis gate's exact gain map) over its C_f."""
    designs, _ = designs_of(tmp_path, overrides)
    scales = stable_scales(coupled_loop(designs, (), sampled=True))
    own = [assess(d.config).max_stable_gain / float(d.params.value("force_gain")) for d in designs]
    assert scales.max_scale == pytest.approx(min(own), rel=1e-9)


@pytest.mark.parametrize("overrides", [[], ["design.delay_samples=1"], ["design.input_delay=0.0004"],
                                       ["design.velocity_source=estimated", "environment.damping=0"]])
@pytest.mark.parametrize("sampled", [True, False], ids=["sampled", "continuous"])
def test_identical_axes_split_into_common_and_differential_modes(tmp_path: Path, overrides: list[str],
                                                                 sampled: bool) -> None:
    """Two identical axes, one symmetric coupling (K, D): the common mode is one axis with
    its environment, the differential one sees K_env + 2K and D_env + 2D."""
    text = TWO_AXES.replace("    plant: {inertia: 0.3}\n", "")
    designs, couplings = designs_of(tmp_path, overrides, text)
    (cp,) = couplings
    d = designs[0]
    k_env, d_env = float(d.params.value("stiffness")), float(d.params.value("damping"))
    from dobhil.synthesis.loop import loop
    modes = [loop(d.params.replace(stiffness=k, damping=c), sampled=sampled)
             for k, c in ((k_env, d_env), (k_env + 2 * cp.stiffness, d_env + 2 * cp.damping))]
    expected = np.concatenate([np.linalg.eigvals(m.a) for m in modes])
    lp = coupled_loop(designs, couplings, sampled=sampled)
    got = lp.poles()
    assert got.size == expected.size
    for p in expected:     # each mode's pole is a pole of the coupled loop, and back
        assert np.min(np.abs(got - p)) <= 1e-9 * max(1.0, abs(p))
    for p in got:
        assert np.min(np.abs(expected - p)) <= 1e-9 * max(1.0, abs(p))
    # the gain scale: the tighter of the two modes' own (continuous: unbounded, both)
    own = []
    for k, c in ((k_env, d_env), (k_env + 2 * cp.stiffness, d_env + 2 * cp.damping)):
        cfg = dataclasses.replace(d.config, environment=dataclasses.replace(
            d.config.environment, stiffness=k, damping=c))
        own.append(assess(cfg, sampled=sampled).max_stable_gain / float(d.params.value("force_gain")))
    assert stable_scales(lp).max_scale == pytest.approx(min(own), rel=1e-9)


@pytest.mark.parametrize("overrides", [o for o in VARIANTS if not any("input_delay" in x for x in o)]
                         + [["axes.left.design.delay_samples=3", "axes.right.design.disturbance_model=sinusoid"]])
@pytest.mark.parametrize("sampled", [True, False], ids=["sampled", "continuous"])
def test_interconnect_check_agrees(tmp_path: Path, overrides: list[str], sampled: bool) -> None:
    designs, couplings = designs_of(tmp_path, overrides)
    with warnings.catch_warnings():
        warnings.simplefilter("error")    # python-control must not complain about the wiring
        check = check_loop(coupled_loop(designs, couplings, sampled=sampled), designs, couplings)
    assert check.pole_error <= 1e-9 and check.step_error <= 1e-9, check.text()


THREE_AXES = """\
loop: {period: 0.001}
design: {force_gain: 1.5}
axes:
  - {name: hip, drive: {profile: odrive-0.6, node_id: 1}, plant: {inertia: 0.4}}
  - {name: knee, drive: {profile: odrive-0.6, node_id: 2}, design: {delay_samples: 1}}
  - {name: ankle, drive: {profile: odrive-0.6, node_id: 3}, environment: {stiffness: 3000.0}}
environment:
  coupling:
    - {axes: [hip, knee], stiffness: %(k1)s, damping: %(d1)s}
    - {axes: [ankle, knee], stiffness: %(k2)s, damping: %(d2)s}
"""


@settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(k1=st.floats(0.0, 2e4), d1=st.floats(0.0, 50.0), k2=st.floats(0.0, 2e4), d2=st.floats(0.0, 50.0),
       sampled=st.booleans())
def test_interconnect_check_agrees_on_a_chain_of_three(tmp_path: Path, k1: float, d1: float, k2: float,
                                                       d2: float, sampled: bool) -> None:
    values = {"k1": k1, "d1": d1, "k2": k2, "d2": d2}   # YAML 1.1 reads 1e-12 as text: write 1.0e-12
    designs, couplings = designs_of(tmp_path, [], THREE_AXES % {k: f"{v:.17e}" for k, v in values.items()})
    check = check_loop(coupled_loop(designs, couplings, sampled=sampled), designs, couplings)
    assert check.agrees(1e-9), check.text()


def test_check_says_when_it_cannot_build_the_loop(tmp_path: Path) -> None:
    designs, couplings = designs_of(tmp_path, ["axes.left.design.input_delay=0.0003"])
    with pytest.raises(CheckUnavailable, match="input_delay"):
        check_loop(coupled_loop(designs, couplings, sampled=True), designs, couplings)


@pytest.mark.parametrize("overrides", [[], ["axes.right.design.delay_samples=2"],
                                       ["design.force_gain=9", "axes.left.design.delay_samples=1"]])
def test_stable_scales_match_eigenvalues_on_a_grid(tmp_path: Path, overrides: list[str]) -> None:
    """The stable intervals against brute force: eigenvalues at 3000 scales."""
    designs, couplings = designs_of(tmp_path, overrides)
    lp = coupled_loop(designs, couplings, sampled=True)
    scales = stable_scales(lp)
    assert np.isfinite(scales.max_scale) and scales.max_scale > 0
    for s in np.geomspace(1e-3, 1e3, 3000):
        if min(abs(s - c) for c in scales.crossings) <= 1e-6 * s:
            continue
        margin = spectral_margin(lp.a_at(s), True)
        if abs(margin) > 1e-9:
            assert (margin < 0) == scales.stable_at(s), s
    s = scales.max_scale
    assert spectral_margin(lp.a_at(s * (1 - 1e-7)), True) < 0 < spectral_margin(lp.a_at(s * (1 + 1e-7)), True)


@pytest.mark.parametrize("overrides", [[], ["axes.right.design.delay_samples=2", "design.force_gain=7"],
                                       ["design.velocity_source=estimated", "design.interaction_model=sinusoid",
                                        "axes.left.design.delay_samples=1"]])
@pytest.mark.parametrize("sampled", [True, False], ids=["sampled", "continuous"])
def test_pencil_finds_every_crossing(tmp_path: Path, overrides: list[str], sampled: bool) -> None:
    """The Kronecker pencil's own eigenvalues hold each crossing (to 1e-9): the refinement
    polishes them, it does not find them; and at each crossing a pole is on the boundary."""
    from dobhil.analysis.coupled import _candidates
    designs, couplings = designs_of(tmp_path, overrides + ["axes.left.environment.stiffness=60000"])
    lp = coupled_loop(designs, couplings, sampled=sampled)
    candidates = _candidates(lp.a + lp.m, lp.b_per * lp.gains, lp.c_hat.T, sampled)
    scales = stable_scales(lp)
    assert scales.crossings or not sampled
    for x in scales.crossings:
        assert np.min(np.abs(candidates - x)) <= 1e-9 * x
        assert abs(spectral_margin(lp.a_at(x), sampled)) <= 1e-9


def test_a_direction_of_gains_is_each_axis_own_limit_over_its_component(tmp_path: Path) -> None:
    """Along (1, 0.25), with no coupling: s_max = min(k_left / 1, k_right / 0.25), each k the
    axis' own largest stable C_f (the single-axis gate)."""
    designs, _ = designs_of(tmp_path, ["axes.right.design.delay_samples=1"])
    lp = coupled_loop(designs, (), sampled=True)
    scales = stable_scales(lp, (1.0, 0.25))
    own = [assess(d.config).max_stable_gain for d in designs]
    assert scales.max_scale == pytest.approx(min(own[0] / 1.0, own[1] / 0.25), rel=1e-9)
    assert scales.max_gains() == (scales.max_scale, 0.25 * scales.max_scale)
    with pytest.raises(ValueError, match="direction"):
        stable_scales(lp, (0.0, 0.0))


def test_coupling_sign_is_a_spring(tmp_path: Path) -> None:
    """Axis a pushed by K (q_b - q_a): with the force loops open, a stiff coupling raises the
    differential mode's frequency and a negative one would not be stable (a check of the
    sign the mechanics, not the code, fixes)."""
    designs, couplings = designs_of(tmp_path, [])
    from dobhil.analysis.coupled import coupled_plant
    a, _, c = coupled_plant(designs, couplings)
    assert np.all(np.linalg.eigvals(a).real < 0)
    # the reaction on left when only right moves: -K (it pulls left towards right)
    assert c[0, 2] == -couplings[0].stiffness and c[1, 0] == -couplings[0].stiffness
    assert c[0, 0] == float(designs[0].params.value("stiffness")) + couplings[0].stiffness


@pytest.mark.parametrize("tau", [0.0, 0.0003, 0.001])
def test_one_input_sampled_plant_is_discretize_delayed(tau: float) -> None:
    a, b, _ = plant_of(params_from_config(load_config(None)))
    got = sampled_coupled_plant(a, b, 0.001, [tau])
    for x, y in zip(got, discretize_delayed(a, b, 0.001, tau)):
        assert np.array_equal(x, y)


@settings(max_examples=20, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(tau_a=st.floats(0.0, 1e-3), tau_b=st.floats(0.0, 1e-3), stiffness=st.floats(0.0, 1e4))
def test_sampled_plant_with_two_delays_is_the_ode(tmp_path: Path, tau_a: float, tau_b: float,
                                                   stiffness: float) -> None:
    """Each axis' command switching at its own time within the period: the sampled coupled
    plant against the ODE integrated through the period (scipy's DOP853, tight tolerances)
    for each unit input, old and new, and each initial state."""
    from scipy.integrate import solve_ivp

    from dobhil.analysis.coupled import coupled_plant
    designs, _ = designs_of(tmp_path, [])
    a, b, _ = coupled_plant(designs, (Coupling("left", "right", stiffness, 20.0),))
    period, delays = 1e-3, (tau_a, tau_b)
    phi, g_new, g_old = sampled_coupled_plant(a, b, period, delays)

    def through(x0: np.ndarray, old: np.ndarray, new: np.ndarray) -> np.ndarray:
        cuts = sorted({0.0, period, *delays})
        x = x0
        for t0, t1 in zip(cuts[:-1], cuts[1:]):
            u = np.where(np.asarray(delays) <= t0, new, old)
            x = solve_ivp(lambda _, y, u=u: a @ y + b @ u, (t0, t1), x, method="DOP853", rtol=1e-13,
                          atol=1e-16).y[:, -1] if t1 > t0 else x
        return np.asarray(x)
    eye2 = np.eye(2)
    for j in range(2):
        zero = np.zeros(2)
        np.testing.assert_allclose(through(np.zeros(4), zero, eye2[j]), g_new[:, j], rtol=1e-9, atol=1e-15)
        np.testing.assert_allclose(through(np.zeros(4), eye2[j], zero), g_old[:, j], rtol=1e-9, atol=1e-15)
    for i in range(4):
        np.testing.assert_allclose(through(np.eye(4)[i], np.zeros(2), np.zeros(2)), phi[:, i], rtol=1e-9,
                                   atol=1e-12)


def test_the_loop_and_its_gain_scales_import_no_python_control() -> None:
    """A stability gate before a run may use them: python-control costs more than the verdict."""
    import subprocess
    import sys
    code = ("import sys, dobhil.analysis.coupled as c; "
            "print('control' in sys.modules, 'scipy.optimize' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.split() == ["False", "False"]


def test_groups_follow_the_couplings(tmp_path: Path) -> None:
    text = THREE_AXES % {"k1": 1.0, "d1": 0.0, "k2": 1.0, "d2": 0.0}
    assert coupled_groups(load_axes(write(tmp_path, text))) == (("hip", "knee", "ankle"),)
    alone = text.replace("    - {axes: [ankle, knee], stiffness: 1.0, damping: 0.0}\n", "")
    assert coupled_groups(load_axes(write(tmp_path, alone))) == (("hip", "knee"), ("ankle",))


def run_json(capsys: pytest.CaptureFixture[str], *argv: str) -> dict:  # type: ignore[type-arg]
    assert main(list(argv)) == 0
    return json.loads(capsys.readouterr().out)


def test_cli_coupled_axes(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = write(tmp_path)
    out = run_json(capsys, "analyze", str(path), "--json")
    assert out["axes"] == {}
    (group,) = out["coupled"]
    designs = axis_designs(load_axes(path))
    scales = stable_scales(coupled_loop(designs, load_axes(path).couplings, sampled=True))
    disc = group["discrete"]
    assert disc["max_stable_gain_scale"] == scales.max_scale
    assert disc["max_stable_force_gains"] == {"left": 2 * scales.max_scale, "right": 2 * scales.max_scale}
    assert disc["closed_loop"]["stable"] and disc["check"]["agrees_1e-9"]
    assert set(disc["steps"]) == {"left", "right"}
    assert main(["analyze", str(path), "--plot", str(tmp_path / "fig")]) == 0
    text = capsys.readouterr().out
    assert "coupled axes left, right" in text and "max stable gain scale: " in text
    assert (tmp_path / "fig" / "coupled_step_left_right.png").stat().st_size > 0


def test_cli_independent_axes_are_each_single_axis(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    text = TWO_AXES.split("environment:")[0]
    path = write(tmp_path, text)
    out = run_json(capsys, "analyze", str(path), "--json")
    assert out["coupled"] == [] and set(out["axes"]) == {"left", "right"}
    for name in ("left", "right"):
        alone = tmp_path / f"{name}.yaml"
        cfg = load_axes(path).axis(name).config
        alone.write_text(f"plant: {{inertia: {cfg.plant.inertia}}}\ndrive: {{profile: odrive-0.6}}\n")
        single = run_json(capsys, "analyze", str(alone), "--json")
        assert out["axes"][name] == {k: single[k] for k in ("continuous", "discrete")}
    assert main(["analyze", str(path), "--plot", str(tmp_path / "fig")]) == 0
    assert "axis right (no coupling):" in capsys.readouterr().out
    for name in ("left", "right"):
        assert {p.name for p in (tmp_path / "fig" / name).iterdir()} == {"root_locus.png", "step.png", "bode.png"}


@pytest.mark.parametrize("extra, says", [
    (["--set", "axes.middle.design.force_gain=1"], "no axis 'middle'"),
    (["--set", "axes.left.design.force_gain=-1"], "axis left"),
])
def test_cli_bad_input_is_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str], extra: list[str],
                                   says: str) -> None:
    assert main(["analyze", str(write(tmp_path)), *extra]) == 2
    err = capsys.readouterr().err
    assert says in err and len(err.strip().splitlines()) == 1


def test_cli_coupling_to_a_missing_axis(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = write(tmp_path, TWO_AXES.replace("[left, right]", "[left, elbow]"))
    assert main(["analyze", str(path)]) == 2
    assert "elbow" in capsys.readouterr().err
