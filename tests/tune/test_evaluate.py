"""tune's batched metrics against the one-design analysis (``dobhil analyze``'s code and
python-control): the same numbers, computed another way."""

from __future__ import annotations

import numpy as np
import pytest

from dobhil.analysis.quantisation import noise_figures
from dobhil.analysis.report import analyze
from dobhil.config import load_config
from dobhil.tune.evaluate import Quanta, evaluate
from dobhil.tune.problem import DECISION_KEYS

CASES = [  # (overrides, design values)
    ([], [500.0, 500.0, 0.25, 2.0]),
    (["environment.stiffness=2000", "environment.damping=150"], [90.0, 120.0, 0.2, 0.6]),
    (["design.delay_samples=1", "environment.stiffness=30000"], [300.0, 200.0, 0.3, 1.0]),
]


@pytest.mark.parametrize(("overrides", "design"), CASES)
def test_margins_and_step_match_the_analysis_of_one_design(overrides: list[str], design: list[float]) -> None:
    config = load_config("paper/fig3", overrides + [f"{k}={v}" for k, v in zip(DECISION_KEYS, design)])
    flat = config.flat()
    point = {k: np.array([flat[k]]) for k in ("environment.stiffness", "environment.damping")}
    m = evaluate(config, np.array([design]), point, horizon=101)   # t = 0 .. 0.1 s, as analyze
    d = analyze(config).discrete
    assert m.stable[0, 0] == d.stable
    assert 10 ** (m.gm_db[0, 0] / 20) * design[3] == pytest.approx(float(d.gains.max_stable_gain), rel=1e-9)
    assert m.pm_deg[0, 0] == pytest.approx(d.margins["phase_margin_deg"], abs=0.2)
    assert 10 ** (-m.ms_db[0, 0] / 20) == pytest.approx(d.margins["stability_margin"], rel=0.02)
    assert m.rise_time[0, 0] == pytest.approx(d.step_force.rise_time, rel=1e-9)
    assert m.overshoot[0, 0] == pytest.approx(d.step_force.overshoot_pct, rel=1e-6, abs=1e-9)


def test_quantisation_noise_matches_the_quantisation_module() -> None:
    config = load_config("paper/fig3")
    quanta = Quanta(position=2e-4, velocity=5e-3, torque=1e-2)
    m = evaluate(config, np.array([[500.0, 500.0, 0.25, 2.0]]), {}, horizon=20, quanta=quanta)
    from dobhil.synthesis.params import params_from_config
    figures = noise_figures(params_from_config(config), quanta)
    assert figures.closed_loop is not None
    assert m.noise is not None and m.noise[0, 0] == pytest.approx(figures.closed_loop["tau_int_hat"].total, rel=1e-6)


def test_a_batch_equals_its_points_one_by_one() -> None:
    config = load_config("paper/fig3")
    designs = np.array([[500.0, 500.0, 0.25, 2.0], [60.0, 40.0, 0.4, 5.0]])
    points = {"environment.stiffness": np.array([1e3, 2e4, 1e5]), "environment.damping": np.array([10.0, 60.0, 200.0])}
    batch = evaluate(config, designs, points, horizon=60)
    for i in range(2):
        for j in range(3):
            one = evaluate(config, designs[i:i + 1], {k: v[j:j + 1] for k, v in points.items()}, horizon=60)
            for name in ("radius", "gm_db", "pm_deg", "ms_db", "rise_time", "overshoot", "bandwidth"):
                np.testing.assert_allclose(getattr(batch, name)[i, j], getattr(one, name)[0, 0], rtol=1e-9)


def test_a_step_that_never_reaches_10_percent_has_an_infinite_rise_time() -> None:
    """Observers at 1.5 rad/s and C_f 0.0012: stable, but the force creeps to below 10 % of
    its final value in 0.2 s. Its rise time is infinite (the optimiser's worst), not NaN,
    which the search's comparisons cannot rank and the worst-case max would pick."""
    config = load_config("paper/fig3")
    m = evaluate(config, np.array([[1.39, 1.51, 0.248, 0.00124]]), {"environment.stiffness": np.array([1e3])},
                 horizon=201)
    assert m.stable[0, 0]
    assert m.rise_time[0, 0] == np.inf


def test_a_point_unstable_within_the_tolerance_fails_the_stability_constraint() -> None:
    """K_env 1e-9 N m/rad: the largest |pole| is 1 - 2e-14, below 1 but inside the analysis'
    tolerance, so the point is unstable (no margins there). The stability constraint said "ok"
    beside margins that were "none (unstable there)", and the one line of an infeasible
    search named the gain margin ("nan dB") instead of stability."""
    from dobhil.tune.optimise import worsts
    from dobhil.tune.problem import Margins, RobustSet
    config = load_config("paper/fig3")
    points = {"environment.stiffness": np.array([1e-9, 1e3])}
    m = evaluate(config, np.array([[500.0, 500.0, 0.25, 2.0]]), points, horizon=20)
    assert not m.stable[0, 0] and m.radius[0, 0] < 1.0
    held = {w.name: w for w in worsts(m, RobustSet(("environment.stiffness",), points), Margins())}
    assert not held["stability"].ok and held["stability"].point == {"environment.stiffness": 1e-9}
