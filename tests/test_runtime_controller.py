"""The runtime force controller executes the synthesised sampled controller exactly."""

from __future__ import annotations

from collections import deque

import numpy as np
import pytest

from dobhil.config.schema import Config, DesignConfig, LoopConfig, PlantConfig
from dobhil.emulator.plant import Plant
from dobhil.runtime.controller import ControlOutput, ForceController
from dobhil.synthesis.controller import discretize, sampled_controller
from dobhil.synthesis.loop import loop, plant_of
from dobhil.synthesis.params import Discretization, params_from_config

N = 400
BIG = 1e12  # no saturation

#: stable sampled loops (spectral radius < 0.99) covering every structural choice
DESIGNS = {
    "paper": DesignConfig(),
    "lead-rtob": DesignConfig(identified_inertia=0.125, rtob_bandwidth=1000.0),
    "estimated-delay": DesignConfig(velocity_source="estimated", delay_samples=1,
                                    interaction_model="ramp", dob_bandwidth=200.0,
                                    rtob_bandwidth=200.0, force_gain=0.5,
                                    nominal_friction=0.1, identified_friction=0.2),
    "sinusoids": DesignConfig(disturbance_model="sinusoid", interaction_model="sinusoid",
                              disturbance_frequency=30.0, interaction_frequency=20.0,
                              dob_bandwidth=200.0, rtob_bandwidth=200.0, force_gain=1.0,
                              identified_inertia=0.3),
    "sinusoid-ramp-estimated": DesignConfig(disturbance_model="sinusoid",
                                            interaction_model="ramp",
                                            disturbance_frequency=30.0, dob_bandwidth=200.0,
                                            rtob_bandwidth=200.0, force_gain=0.5,
                                            velocity_source="estimated",
                                            velocity_filter_bandwidth=3000.0),
    "euler": DesignConfig(discretization="euler", dob_bandwidth=300.0, rtob_bandwidth=300.0),
}


def _config(design: DesignConfig, *, torque_limit: float = BIG) -> Config:
    return Config(design=design, plant=PlantConfig(viscous_friction=0.2, torque_limit=BIG),
                  loop=LoopConfig(torque_limit=torque_limit))


def _loop_step_response(config: Config, n: int) -> np.ndarray:
    """tau_int^ from tau_ref = 1, by the analysis' sampled LoopSS."""
    ss = loop(params_from_config(config), sampled=True)
    b = ss.b[:, ss.input_index("tau_ref")]
    c, d = ss.c[ss.output_index("tau_int_hat")], ss.d[ss.output_index("tau_int_hat"),
                                                      ss.input_index("tau_ref")]
    x = np.zeros(ss.a.shape[0])
    out = np.empty(n)
    for k in range(n):
        out[k] = c @ x + d
        x = ss.a @ x + b
    return out


def _runtime_step_response(config: Config, n: int, *, emulator: bool = False) -> np.ndarray:
    """tau_int^ of ForceController closed around the sampled plant (or the emulator)."""
    ctrl = ForceController.from_config(config)
    dt = config.loop.period
    phi, gamma = discretize(*plant_of(params_from_config(config))[:2], dt, Discretization.ZOH)
    plant = Plant.from_config(config)
    in_transit = deque([0.0] * config.design.delay_samples)
    x = np.zeros(2)
    out = np.empty(n)
    for k in range(n):
        q, dq = (plant.position, plant.velocity) if emulator else (x[0], x[1])
        step = ctrl.step(q, dq if ctrl.measures_velocity else None, 1.0)
        out[k] = step.tau_int_hat
        in_transit.append(step.u)
        u = in_transit.popleft()
        if emulator:
            plant.step(u, dt)
            assert plant.in_contact
        else:
            x = phi @ x + gamma[:, 0] * u
    return out


@pytest.mark.parametrize("name", list(DESIGNS))
def test_closed_loop_reproduces_the_sampled_loop(name: str) -> None:
    config = _config(DESIGNS[name])
    expected = _loop_step_response(config, N)
    got = _runtime_step_response(config, N)
    scale = np.max(np.abs(expected))
    assert scale > 0.1
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-9 * scale)


def test_closed_loop_with_the_emulator_reproduces_the_sampled_loop() -> None:
    config = _config(DESIGNS["paper"])
    expected = _loop_step_response(config, N)
    got = _runtime_step_response(config, N, emulator=True)
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-9 * np.max(np.abs(expected)))


def _numpy_reference(ctrl: ForceController, xi: np.ndarray, y: np.ndarray, tau_ref: float,
                     limit: float) -> tuple[np.ndarray, float, float, float]:
    """One sample of the controller equations, straight from the matrices (test oracle)."""
    ss = ctrl.ss
    dis, itn = ss.c @ xi + ss.d_y @ y
    u_unsat = ctrl.force_gain * (tau_ref - itn) + dis
    u = float(np.clip(u_unsat, -limit, limit))
    return ss.a @ xi + ss.b_y @ y + ss.b_u[:, 0] * u, u_unsat, u, itn


@pytest.mark.parametrize("name", ["paper", "sinusoid-ramp-estimated"])
def test_saturation_feeds_the_applied_torque(name: str) -> None:
    ctrl = ForceController.from_config(_config(DESIGNS[name], torque_limit=2.0))
    rng = np.random.default_rng(1)
    xi = np.zeros(ctrl.order)
    saturated = 0
    for k in range(200):
        y = np.array([1e-3 * np.sin(k / 10), 0.05 * np.cos(k / 10)])[:2 if ctrl.measures_velocity
                                                                        else 1]
        tau_ref = 5.0 * rng.standard_normal()
        out = ctrl.step(y[0], y[1] if ctrl.measures_velocity else None, tau_ref)
        xi, u_unsat, u, itn = _numpy_reference(ctrl, xi, y, tau_ref, 2.0)
        assert abs(out.u) <= 2.0
        assert out.u == (out.u_unsat if abs(out.u_unsat) <= 2.0 else np.sign(out.u_unsat) * 2.0)
        np.testing.assert_allclose(out.u, u, rtol=1e-9, atol=1e-9)
        saturated += out.u != out.u_unsat
        np.testing.assert_allclose(out.u_unsat, u_unsat, rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(out.tau_int_hat, itn, rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(ctrl.state, xi, rtol=1e-9, atol=1e-9 * np.abs(xi).max())
    assert saturated > 20


def test_outputs_are_consistent() -> None:
    ctrl = ForceController.from_config(_config(DESIGNS["paper"], torque_limit=3.0))
    out = ctrl.step(np.float64(0.01), np.float64(0.5), 4)
    assert isinstance(out, ControlOutput)
    assert all(type(v) is float for v in out)
    assert out.tau_ref == 4.0
    assert out.tau_per == ctrl.force_gain * (out.tau_ref - out.tau_int_hat)
    assert out.u_unsat == out.tau_per + out.tau_dis_hat
    assert out.u == max(-3.0, min(3.0, out.u_unsat))


def _run(ctrl: ForceController, n: int = 300) -> list[ControlOutput]:
    rng = np.random.default_rng(3)
    return [ctrl.step(*rng.standard_normal(2) * [1e-3, 0.1], float(rng.standard_normal()))
            for _ in range(n)]


def test_deterministic_bit_for_bit() -> None:
    config = _config(DESIGNS["lead-rtob"], torque_limit=20.0)
    a, b = ForceController.from_config(config), ForceController.from_config(config)
    first = _run(a)
    assert first == _run(b)
    a.reset()
    assert _run(a) == first
    state = b.state
    b.load_state(state)
    assert np.array_equal(b.state, state)


@pytest.mark.parametrize("name", list(DESIGNS))
def test_initialize_starts_at_rest_without_a_kick(name: str) -> None:
    ctrl = ForceController.from_config(_config(DESIGNS[name]))
    ctrl.initialize(1.3, 0.0)
    start = ctrl.state
    if not ctrl.measures_velocity and DESIGNS[name].discretization in ("zoh", "euler"):
        assert start[0] == pytest.approx(1.3, rel=1e-12)  # velocity filter z = q
    for _ in range(5):
        out = ctrl.step(1.3, 0.0 if ctrl.measures_velocity else None, 0.0)
        assert abs(out.tau_int_hat) < 1e-6 and abs(out.tau_dis_hat) < 1e-6
        assert abs(out.u) < 1e-6
    # a fixed point up to the rounding of the largest term of the update
    scale = np.abs(ctrl.ss.b_y).max() * 1.3
    np.testing.assert_allclose(ctrl.state, start, rtol=1e-9, atol=1e-12 * scale)


def test_initialize_is_sigma_equal_l_x() -> None:
    # constant models, measured velocity, no friction: sigma = L x, L = [0, g J] (in the
    # coordinates of the step-invariant discretisation; the holds shift them by E0 y)
    ctrl = ForceController.from_config(_config(DesignConfig(discretization="zoh")))
    ctrl.initialize(0.7, 0.1)
    np.testing.assert_allclose(ctrl.state, [500.0 * 0.25 * 0.1, 500.0 * 0.25 * 0.1], rtol=1e-12)
    out = ctrl.step(0.7, 0.1, 0.0)
    assert abs(out.tau_dis_hat) < 1e-12 and abs(out.tau_int_hat) < 1e-12


def test_rejects_bad_use() -> None:
    ctrl = ForceController.from_config(Config())
    with pytest.raises(ValueError, match="dq"):
        ctrl.step(0.0, None, 1.0)
    with pytest.raises(ValueError, match="state"):
        ctrl.load_state([1.0])
    params = params_from_config(Config(), design__force_gain=np.array([1.0, 2.0]))
    with pytest.raises(ValueError, match="batch"):
        ForceController(sampled_controller(params), torque_limit=1.0)


def test_kernel_uses_the_synthesised_matrices() -> None:
    ctrl = ForceController.from_config(Config())
    for value in np.concatenate([ctrl.ss.a, ctrl.ss.b_y, ctrl.ss.b_u], axis=1).reshape(-1):
        if value != 0.0:
            assert repr(float(value)) in ctrl.source
