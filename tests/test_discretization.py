"""The sampled model against independent fine-step simulations: the fractional torque
delay (``design.input_delay``) and the holds of the sampled controller."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.integrate

from dobhil.config import load_config
from dobhil.errors import ConfigError
from dobhil.runtime.controller import ForceController
from dobhil.synthesis.controller import discretize, discretize_delayed
from dobhil.synthesis.loop import loop, plant_of, sampled_plant
from dobhil.synthesis.params import Discretization, params_from_config

T = 1e-3
A = np.array([[0.0, 1.0], [-1e4 / 0.25, -50.0 / 0.25]])
B = np.array([[0.0], [1.0 / 0.25]])


def _fine_step(x0: np.ndarray, w_old: float, w_new: float, tau: float) -> np.ndarray:
    """x(T) by an adaptive ODE solver: w_old on [0, tau), w_new on [tau, T]."""
    def f(t: float, x: np.ndarray, w: float) -> np.ndarray:
        return A @ x + B[:, 0] * w
    x = x0
    for (t0, t1, w) in ((0.0, tau, w_old), (tau, T, w_new)):
        if t1 > t0:
            x = scipy.integrate.solve_ivp(f, (t0, t1), x, args=(w,), rtol=1e-12,
                                          atol=1e-15, method="DOP853").y[:, -1]
    return x


@pytest.mark.parametrize("tau", [0.0, 1e-5, 2.5e-4, 7.7e-4, T])
def test_delayed_sampling_equals_a_fine_simulation(tau: float) -> None:
    phi, g0, g1 = discretize_delayed(A, B, T, tau)
    rng = np.random.default_rng(3)
    x = np.array([1e-3, -0.02])
    w_prev = 0.0
    for _ in range(20):
        w = float(rng.normal())
        expected = _fine_step(x, w_prev, w, tau)
        got = phi @ x + g0[:, 0] * w + g1[:, 0] * w_prev
        np.testing.assert_allclose(got, expected, rtol=1e-9, atol=1e-12)
        x, w_prev = expected, w


def test_zero_delay_is_the_zero_order_hold_and_a_whole_period_one_sample() -> None:
    phi, gamma = discretize(A, B, T, Discretization.ZOH)
    p0, g0, g1 = discretize_delayed(A, B, T, 0.0)
    np.testing.assert_allclose(p0, phi, rtol=1e-14)
    np.testing.assert_allclose(g0, gamma, rtol=1e-14)
    assert np.all(g1 == 0.0)
    p1, g0, g1 = discretize_delayed(A, B, T, T)
    np.testing.assert_allclose(p1, phi, rtol=1e-14)
    assert np.all(g0 == 0.0)
    np.testing.assert_allclose(g1, gamma, rtol=1e-12)
    with pytest.raises(ValueError):
        discretize_delayed(A, B, T, 1.5 * T)


def _poles(*overrides: str) -> np.ndarray:
    ss = loop(params_from_config(load_config("configs/paper/fig2a.yaml", overrides)), sampled=True)
    ev = np.linalg.eigvals(ss.a)
    return np.sort_complex(ev[np.abs(ev) > 1e-9])


def test_loop_with_input_delay_tends_to_the_undelayed_and_the_one_sample_loops() -> None:
    np.testing.assert_allclose(_poles("design.input_delay=1e-12"), _poles(), rtol=1e-6)
    np.testing.assert_allclose(_poles(f"design.input_delay={T * (1 - 1e-12)!r}"),
                               _poles("design.delay_samples=1"), rtol=1e-6)
    between = _poles("design.input_delay=5e-4", "design.delay_samples=1")
    assert between.size == _poles("design.delay_samples=2").size
    assert not np.allclose(between, _poles("design.delay_samples=2"))


@pytest.mark.parametrize("extra", [(), ("design.delay_samples=1",),
                                   ("design.velocity_source=estimated",)])
def test_loop_with_input_delay_equals_runtime_against_a_fine_simulation(
        extra: tuple[str, ...]) -> None:
    """ForceController closed around the plant simulated by an ODE solver, the torque
    switching at t_k + tau: the sampled loop reproduces it sample for sample."""
    tau = 3.3e-4
    config = load_config("configs/paper/fig2a.yaml",
                         ["loop.torque_limit=1e9", f"design.input_delay={tau!r}", *extra])
    params = params_from_config(config)
    ss = loop(params, sampled=True)
    bi, co = ss.b[:, ss.input_index("tau_ref")], ss.c[ss.output_index("tau_int_hat")]
    ctrl = ForceController.from_config(config)
    a_p, b_p, _ = plant_of(params)
    assert np.allclose(a_p, A) and np.allclose(b_p, B)
    x, xs = np.zeros(2), np.zeros(ss.a.shape[0])
    in_transit = [0.0] * (config.design.delay_samples + 1)   # oldest first
    for _ in range(150):
        out = ctrl.step(x[0], x[1] if ctrl.measures_velocity else None, 1.0)
        assert out.tau_int_hat == pytest.approx(float(co @ xs), rel=1e-7, abs=1e-9)
        in_transit.append(out.u)
        d = config.design.delay_samples       # u[k-d-1] until t_k + tau, then u[k-d]
        x = _fine_step(x, in_transit[-2 - d], in_transit[-1 - d], tau)
        in_transit.pop(0)
        xs = ss.a @ xs + bi
    assert abs(float(co @ xs)) > 0.1


def test_sampled_plant_is_discretize_delayed_of_the_plant() -> None:
    config = load_config("configs/paper/fig2a.yaml", ["design.input_delay=2e-4"])
    phi, g0, g1 = sampled_plant(params_from_config(config))
    e_phi, e_g0, e_g1 = discretize_delayed(A, B, T, 2e-4)
    np.testing.assert_array_equal(phi, e_phi)
    np.testing.assert_array_equal(g0, e_g0)
    np.testing.assert_array_equal(g1, e_g1)
    np.testing.assert_allclose(g0 + g1, discretize(A, B, T)[1], rtol=1e-12)


@pytest.mark.parametrize("value", ["1e-3", "0.002", "-1e-4"])
def test_input_delay_must_be_below_the_period(value: str) -> None:
    with pytest.raises(ConfigError, match="input_delay"):
        params_from_config(load_config("configs/paper/fig2a.yaml", [f"design.input_delay={value}"]))
