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


# --- the sampled controller: effective inertia and friction from the matrices' DC behaviour


def _controller(discretization: str, source: str, g: float, period: float = T):
    from dobhil.synthesis.controller import sampled_controller
    config = load_config(None, [f"design.discretization={discretization}",
                                f"design.velocity_source={source}", f"design.dob_bandwidth={g}",
                                f"design.rtob_bandwidth={g}", "design.nominal_inertia=0.25",
                                "design.identified_inertia=0.125", f"loop.period={period}",
                                "design.nominal_friction=0.0", "design.identified_friction=0.0",
                                "design.velocity_filter_bandwidth=1000"])
    return sampled_controller(params_from_config(config))


def _steady_estimates(ctrl, accel: float, vel: float, torque: float, steps: int = 400):
    """Run the controller's matrices on q = vel t + accel t^2/2 (and its velocity), a
    constant torque; the estimates [tau_dis^, tau_int^] at the end (transients gone)."""
    x = np.zeros(ctrl.order)
    for k in range(steps + 1):
        t = k * ctrl.dt
        y = np.array([vel * t + 0.5 * accel * t * t, vel + accel * t])[:ctrl.b_y.shape[-1]]
        out = ctrl.c @ x + ctrl.d_y @ y
        x = ctrl.a @ x + ctrl.b_y @ y + ctrl.b_u[:, 0] * torque
    return out


@pytest.mark.parametrize("g", [500.0, 1000.0])
@pytest.mark.parametrize("source", ["measured", "estimated"])
def test_sampled_observers_have_the_configured_inertia_and_no_friction(g: float,
                                                                       source: str) -> None:
    """At T = 1 ms the default (parabolic) controller's observers read, in steady state,
    tau^ = u - J a - b v with the configured J (DOb 0.25, RTOb 0.125) and b = 0, to float
    rounding: measured here 3e-14 and less with the measured velocity, up to 1.5e-11 with the
    estimated one (b at g = 1000), so 1e-9 leaves room for another BLAS's rounding."""
    ctrl = _controller("parabolic", source, g)
    gain = _steady_estimates(ctrl, 0.0, 0.0, 1.0)
    np.testing.assert_allclose(gain, [1.0, 1.0], rtol=1e-9)
    inertia = -_steady_estimates(ctrl, 1.0, 0.0, 0.0) / gain
    np.testing.assert_allclose(inertia, [0.25, 0.125], rtol=1e-9)
    friction = -_steady_estimates(ctrl, 0.0, 1.0, 0.0) / gain
    np.testing.assert_allclose(friction, [0.0, 0.0], atol=1e-9)


@pytest.mark.parametrize("g", [500.0, 1000.0])
def test_step_invariant_controller_scales_the_differentiator(g: float) -> None:
    """The old ZOH equivalent: J gT/(1 - e^-gT) with measured velocity (1.27x at 500 rad/s,
    1.58x at 1000), and viscous friction read at constant velocity when it is estimated;
    the triangle hold (foh) is exact with measured velocity only."""
    factor = g * T / (1.0 - np.exp(-g * T))
    zoh = _controller("zoh", "measured", g)
    np.testing.assert_allclose(-_steady_estimates(zoh, 1.0, 0.0, 0.0), [0.25 * factor,
                                                                       0.125 * factor], rtol=1e-9)
    if g == 500.0:   # the defaults (g_v = 2000 rad/s): the 174 N m s/rad
        from dobhil.synthesis.controller import sampled_controller
        defaults = load_config(None, ["design.discretization=zoh",
                                      "design.velocity_source=estimated"])
        friction = -_steady_estimates(sampled_controller(params_from_config(defaults)),
                                      0.0, 1.0, 0.0)
        assert friction[0] == pytest.approx(173.7, abs=0.1)
    foh = _controller("foh", "measured", g)
    np.testing.assert_allclose(-_steady_estimates(foh, 1.0, 0.0, 0.0), [0.25, 0.125], rtol=1e-6)
    foh_est = _controller("foh", "estimated", g)
    assert abs(-_steady_estimates(foh_est, 1.0, 0.0, 0.0)[0] / 0.25 - 1.0) > 0.01
    np.testing.assert_allclose(_steady_estimates(foh_est, 0.0, 1.0, 0.0), [0.0, 0.0], atol=1e-6)


@pytest.mark.parametrize("discretization", ["parabolic", "foh", "zoh", "euler"])
@pytest.mark.parametrize("source", ["measured", "estimated"])
def test_effective_observer_report_matches_the_simulation(discretization: str,
                                                          source: str) -> None:
    from dobhil.analysis.effective import effective_observers
    ctrl = _controller(discretization, source, 300.0)
    eff = effective_observers(ctrl)
    sim_b = -_steady_estimates(ctrl, 0.0, 1.0, 0.0)
    sim_j = -_steady_estimates(ctrl, 1.0, 0.0, 0.0) - sim_b * 400 * ctrl.dt  # minus b v(t_end)
    assert eff["dob"].inertia == pytest.approx(sim_j[0], rel=1e-7)
    assert eff["rtob"].inertia == pytest.approx(sim_j[1], rel=1e-7)
    assert eff["dob"].friction == pytest.approx(sim_b[0], rel=1e-7, abs=1e-6)
    assert eff["rtob"].friction == pytest.approx(sim_b[1], rel=1e-7, abs=1e-6)


def test_effective_bandwidth_of_the_continuous_observer_is_g() -> None:
    from dobhil.analysis.effective import effective_observers
    from dobhil.synthesis.controller import continuous_controller
    params = params_from_config(load_config("configs/paper/fig2b.yaml"))
    eff = effective_observers(continuous_controller(params))
    assert eff["dob"].bandwidth == pytest.approx(500.0, rel=1e-9)
    assert eff["rtob"].bandwidth == pytest.approx(1000.0, rel=1e-9)
    assert eff["rtob"].inertia == pytest.approx(0.25, rel=1e-12)


@pytest.mark.parametrize("discretization", ["parabolic", "foh"])
def test_hold_controllers_have_no_torque_feedthrough_and_stable_observers(
        discretization: str) -> None:
    """The runtime's explicit saturation needs outputs free of u: the ControllerSS form
    has no D_u at all, and the state update is the only place u enters."""
    for source in ("measured", "estimated"):
        ctrl = _controller(discretization, source, 1000.0)
        assert np.max(np.abs(np.linalg.eigvals(ctrl.a))) < 1.0
        assert not hasattr(ctrl, "d_u")
