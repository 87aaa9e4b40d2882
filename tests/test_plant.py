"""The emulated plant: exactly the analysis' model when linear, accurate when not."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from dobhil.config.schema import Config, EnvironmentConfig, PlantConfig, SensorConfig
from dobhil.emulator.plant import DisturbanceKind, Plant, PlantTruth, Propagator, mode_propagators
from dobhil.synthesis.controller import discretize
from dobhil.synthesis.loop import plant_of
from dobhil.synthesis.models import plant_matrices
from dobhil.synthesis.params import Discretization, params_from_config

DT = 1e-3


def _config(**plant: object) -> Config:
    return Config(plant=PlantConfig(**plant))  # type: ignore[arg-type]


def _inputs(n: int) -> list[float]:
    """A torque sequence that keeps the default servo pressed into the environment."""
    return [5.0 + 3.0 * math.sin(k / 7.0) for k in range(n)]


def _analysis_zoh(config: Config, dt: float) -> tuple[np.ndarray, np.ndarray]:
    a, b, _ = plant_of(params_from_config(config))
    return discretize(a, b, dt, Discretization.ZOH)


def test_plant_matrices_are_the_analysis_ones_bit_for_bit() -> None:
    config = _config(viscous_friction=0.3)
    plant = Plant.from_config(config)
    plant.step(0.0, DT)
    phi, gamma = _analysis_zoh(config, DT)
    p = plant._load(DT).contact
    assert (p.p00, p.p01, p.p10, p.p11) == tuple(phi.reshape(-1))
    assert (p.g0, p.g1) == tuple(gamma.reshape(-1))


def test_exact_step_in_contact_is_the_analysis_plant_bit_for_bit() -> None:
    config = _config(viscous_friction=0.3, disturbance="constant", disturbance_amplitude=0.7)
    plant = Plant.from_config(config)
    phi, gamma = _analysis_zoh(config, DT)
    (p00, p01), (p10, p11) = phi.tolist()
    g0, g1 = gamma[:, 0].tolist()
    q, dq = 0.0, 0.0
    x = np.zeros(2)
    for u in _inputs(500):
        w = u - 0.7                                   # u - tau_d^u, held over the period
        q, dq = p00 * q + p01 * dq + g0 * w, p10 * q + p11 * dq + g1 * w
        x = phi @ x + gamma[:, 0] * w                 # the same in numpy (BLAS may use FMA)
        plant.step(u, DT)
        assert plant.in_contact
        assert (plant.true_position, plant.true_velocity) == (q, dq)
    np.testing.assert_allclose([q, dq], x, rtol=1e-12, atol=1e-15)


def test_contact_position_offset_is_an_exact_change_of_variables() -> None:
    base = Plant.from_config(_config())
    shifted = Plant.from_config(Config(
        plant=PlantConfig(initial_position=0.5),
        environment=EnvironmentConfig(contact_position=0.5)))
    for u in _inputs(300):
        base.step(u, DT)
        shifted.step(u, DT)
    assert shifted.true_position - 0.5 == pytest.approx(base.true_position, abs=1e-15)
    assert shifted.true_velocity == base.true_velocity
    assert shifted.interaction_torque == base.interaction_torque


def _reference(plant: Plant, u: float, t_end: float, *, coulomb: bool) -> object:
    """solve_ivp of the same plant (piecewise: free, then contact) at tight tolerance."""
    j, b, k, d = plant.inertia, plant.viscous_friction, plant.stiffness, plant.damping
    fc, qc = plant.coulomb_friction, plant.contact_position

    def rhs(contact: bool) -> Callable[[float, np.ndarray], list[float]]:
        def f(t: float, x: np.ndarray) -> list[float]:
            tau = u - (math.copysign(fc, x[1]) if coulomb else 0.0) - b * x[1]
            if contact:
                tau -= k * (x[0] - qc) + d * x[1]
            return [x[1], tau / j]
        return f

    def touch(t: float, x: np.ndarray) -> float:
        return x[0] - qc
    touch.terminal = True  # type: ignore[attr-defined]
    touch.direction = 1    # type: ignore[attr-defined]
    free = solve_ivp(rhs(False), (0.0, t_end), [plant.true_position, 0.0], events=touch,
                     rtol=1e-12, atol=1e-14, dense_output=True)
    t_hit = float(free.t_events[0][0])
    contact = solve_ivp(rhs(True), (t_hit, t_end), free.y[:, -1], rtol=1e-12, atol=1e-14,
                        dense_output=True)
    return lambda t: free.sol(t) if t <= t_hit else contact.sol(t)


@pytest.mark.parametrize("coulomb", [0.0, 0.5])
def test_contact_engaging_mid_run_matches_solve_ivp(coulomb: float) -> None:
    # free at -10 mrad, pushed with 2 N m: touches the environment after ~55 ms.
    config = Config(plant=PlantConfig(viscous_friction=0.1, coulomb_friction=coulomb,
                                      initial_position=-0.01))
    errors = {}
    for substeps in (10, 100):
        plant = Plant.from_config(config, substeps=substeps)
        ref = _reference(plant, 2.0, 0.1, coulomb=coulomb > 0)
        err, k = 0.0, 0
        # compare until the velocity comes back near zero (the reference has no stiction)
        while k < 40 or ref((k + 1) * DT)[1] > 0.02:  # type: ignore[operator]
            k += 1
            plant.step(2.0, DT)
            err = max(err, abs(plant.true_position - ref(k * DT)[0]))  # type: ignore[operator]
        assert k * DT > 0.055   # well into the contact
        assert plant.in_contact
        errors[substeps] = err
    # the contact is placed within a sub-step: first order in the sub-step; with 10
    # sub-steps per ms about 1 % of the ~1.5 mrad penetration into the environment
    assert errors[10] < 1.5e-5
    assert errors[100] < 0.15 * errors[10]


def test_exact_when_linear_free_motion_matches_solve_ivp() -> None:
    config = Config(plant=PlantConfig(viscous_friction=0.2, initial_position=-1.0))
    plant = Plant.from_config(config)
    ref = solve_ivp(lambda t, x: [x[1], (1.5 - 0.2 * x[1]) / 0.25], (0.0, 0.2), [-1.0, 0.0],
                    rtol=1e-12, atol=1e-14, dense_output=True)
    for _ in range(200):
        plant.step(1.5, DT)
    np.testing.assert_allclose([plant.true_position, plant.true_velocity], ref.sol(0.2),
                               rtol=1e-9)
    assert plant.interaction_torque == 0.0


def test_sine_disturbance_matches_solve_ivp() -> None:
    config = _config(disturbance="sine", disturbance_amplitude=2.0, disturbance_frequency=30.0,
                     disturbance_start=0.01)
    plant = Plant.from_config(config)
    j, k, d, w = 0.25, 1e4, 50.0, 2 * math.pi * 30.0

    def rhs(t: float, x: np.ndarray) -> list[float]:
        dist = 2.0 * math.sin(w * (t - 0.01)) if t >= 0.01 else 0.0
        return [x[1], (5.0 - dist - k * x[0] - d * x[1]) / j]

    ref = solve_ivp(rhs, (0.0, 0.1), [0.0, 0.0], rtol=1e-12, atol=1e-14, dense_output=True,
                    max_step=1e-4)
    worst = 0.0
    for i in range(1, 101):
        plant.step(5.0, DT)
        worst = max(worst, abs(plant.interaction_torque
                               - float(np.array([k, d]) @ ref.sol(i * DT))))
    assert worst < 2e-3 * 2.0   # midpoint-sampled disturbance, 10 sub-steps per period
    assert plant.disturbance_torque == pytest.approx(2.0 * math.sin(w * (0.1 - 0.01)))


def test_step_disturbance_profile_and_balance() -> None:
    plant = Plant.from_config(_config(disturbance="step", disturbance_amplitude=1.0,
                                      disturbance_start=0.0105, initial_position=-1.0))
    assert plant.disturbance_at(0.0104) == 0.0 and plant.disturbance_at(0.0105) == 1.0
    for _ in range(10):
        plant.step(1.0, DT)  # free, accelerated by 1 N m until the disturbance starts
    v10 = plant.true_velocity
    assert v10 == pytest.approx(1.0 / 0.25 * 0.01, rel=1e-12)
    plant.step(1.0, DT)      # half the period with the disturbance cancelling the torque
    assert plant.true_velocity == pytest.approx(v10 + 1.0 / 0.25 * 0.0005, rel=1e-12)
    plant.step(1.0, DT)
    assert plant.true_velocity == pytest.approx(v10 + 1.0 / 0.25 * 0.0005, rel=1e-12)


def test_coulomb_friction_sticks_and_breaks_away() -> None:
    config = _config(coulomb_friction=0.5, initial_position=-1.0)
    plant = Plant.from_config(config)
    for _ in range(50):
        plant.step(0.4, DT)  # below the Coulomb level: stays put
    assert plant.true_position == -1.0 and plant.true_velocity == 0.0
    for _ in range(100):
        plant.step(1.5, DT)  # breaks away with (1.5 - 0.5) / J
    assert plant.true_velocity == pytest.approx(1.0 / 0.25 * 0.1, rel=1e-9)
    assert plant.true_position == pytest.approx(-1.0 + 0.5 * 4.0 * 0.1 ** 2, rel=1e-9)


def test_coulomb_friction_brings_the_servo_to_rest_without_chatter() -> None:
    plant = Plant.from_config(_config(coulomb_friction=0.5, initial_position=-1.0))
    for _ in range(100):
        plant.step(1.5, DT)
    for _ in range(400):   # decelerates at 2 rad/s^2 from 0.4 rad/s: rest after 0.2 s
        plant.step(0.0, DT)
    q = plant.true_position
    for _ in range(100):
        plant.step(0.2, DT)
        assert plant.true_velocity == 0.0 and plant.true_position == q


def test_motor_torque_is_clamped() -> None:
    limited = Plant.from_config(_config(torque_limit=5.0))
    exact = Plant.from_config(_config())
    for u in (100.0, -100.0, 3.0):
        limited.step(u, DT)
        exact.step(max(-5.0, min(5.0, u)), DT)
        assert limited.motor_torque == max(-5.0, min(5.0, u))
    assert limited.truth() == exact.truth()


def test_encoder_quantisation() -> None:
    config = Config(plant=PlantConfig(initial_position=0.1234),
                    environment=EnvironmentConfig(contact_position=1.0),
                    sensor=SensorConfig(encoder_resolution=8192))
    plant = Plant.from_config(config)
    count = 2 * math.pi / 8192
    for _ in range(20):
        plant.step(3.0, DT)
        assert plant.position != plant.true_position
        assert abs(plant.position - plant.true_position) <= 0.5 * count + 1e-15
        assert plant.position / count == pytest.approx(round(plant.position / count), abs=1e-9)
    assert Plant.from_config(_config(initial_position=0.1234)).position == 0.1234


def test_velocity_noise_is_seeded_and_deterministic() -> None:
    def run(seed: int, noise: float = 0.01) -> list[float]:
        plant = Plant.from_config(Config(sensor=SensorConfig(velocity_noise=noise, seed=seed)))
        out = [plant.velocity - plant.true_velocity]
        for u in _inputs(2000):
            plant.step(u, DT)
            out.append(plant.velocity - plant.true_velocity)
        return out

    a, b, c = run(7), run(7), run(8)
    assert a == b and a != c
    assert np.std(a) == pytest.approx(0.01, rel=0.1)
    assert set(run(7, noise=0.0)) == {0.0}


def test_truth_and_reset() -> None:
    plant = Plant.from_config(_config(disturbance="constant", disturbance_amplitude=0.5))
    for u in _inputs(10):
        plant.step(u, DT)
    truth = plant.truth()
    assert isinstance(truth, PlantTruth)
    assert truth.t == pytest.approx(10 * DT)
    assert truth.tau_int == pytest.approx(1e4 * truth.q + 50.0 * truth.dq)
    assert truth.tau_motor == _inputs(10)[-1]
    assert plant.disturbance_torque == 0.5
    assert plant.disturbance is DisturbanceKind.CONSTANT
    with pytest.raises(dataclasses.FrozenInstanceError):
        truth.q = 1.0  # type: ignore[misc]
    plant.reset()
    assert (plant.true_position, plant.true_velocity, plant.time) == (0.0, 0.0, 0.0)


def test_rejects_bad_dt() -> None:
    plant = Plant.from_config(Config())
    with pytest.raises(ValueError, match="dt"):
        plant.step(0.0, 0.0)


def test_exact_plant_matches_direct_matrices_helper() -> None:
    # the helper used by the analysis and plant_matrices agree (same call, same bits)
    config = _config(viscous_friction=0.3)
    a, b, _ = plant_matrices(0.25, 0.3, 1e4, 50.0)
    phi, gamma = discretize(a, b, DT)
    phi2, gamma2 = _analysis_zoh(config, DT)
    assert np.array_equal(phi, phi2) and np.array_equal(gamma, gamma2)


def test_initial_velocity_and_set_state_free_decay_closed_form() -> None:
    """A free servo launched at v0 with no torque: v0 exp(-b t / J), q0 + v0 J/b (1 - exp)
    (closed form), whether launched by the constructor or by set_state mid-run."""
    j, b, q0, v0 = 0.2, 0.8, 0.3, -1.7
    launched = Plant(inertia=j, viscous_friction=b, contact_position=50.0, initial_position=q0,
                     initial_velocity=v0)
    moved = Plant(inertia=j, viscous_friction=b, contact_position=50.0, velocity_noise=0.1,
                  seed=4)
    moved.step(1.0, DT)
    noise = moved.velocity - moved.true_velocity
    t0 = moved.time
    moved.set_state(q0, v0)
    # the state is kept relative to the contact position: q0 to its rounding
    assert moved.true_position == pytest.approx(q0, abs=1e-14)
    assert (moved.true_velocity, moved.time) == (v0, t0)
    assert moved.velocity - moved.true_velocity == pytest.approx(noise)   # no draw
    assert launched.true_position == pytest.approx(q0, abs=1e-14)
    assert launched.true_velocity == v0
    for k in range(1, 50):
        launched.step(0.0, DT)
        moved.step(0.0, DT)
        t = k * DT
        decay = math.exp(-b * t / j)
        for plant in (launched, moved):
            assert plant.true_velocity == pytest.approx(v0 * decay, rel=1e-12)
            assert plant.true_position == pytest.approx(q0 + v0 * j / b * (1 - decay),
                                                        rel=1e-12, abs=1e-13)
    launched.reset()
    assert launched.true_position == pytest.approx(q0, abs=1e-14)
    assert launched.true_velocity == v0


def test_matrices_are_what_step_uses() -> None:
    """Plant.matrices(dt) is the ZOH of discretize for dt and its sub-step."""
    plant = Plant.from_config(_config(coulomb_friction=0.1))
    m = plant.matrices(DT)
    phi, gamma = discretize(plant._a_contact, plant._b_contact, DT, Discretization.ZOH)
    assert (m.contact.p01, m.contact.g1) == (float(phi[0, 1]), float(gamma[1, 0]))
    phi, gamma = discretize(plant._a_free, plant._b_free, DT / 10, Discretization.ZOH)
    assert (m.free_sub.p11, m.free_sub.g0) == (float(phi[1, 1]), float(gamma[0, 0]))
    assert m.h == DT / 10
    assert m.stiction == 2 * 0.1 * (DT / 10) / plant.inertia


def test_propagators_batched_and_shared_are_each_ones_own_bit_for_bit() -> None:
    """A plant's propagators are computed in one batched exponential and the recent ones are
    shared between plants (dobhil/emulator/plant.py, _propagators), and mode_propagators
    gives them without a Plant: each is still Propagator.of of its own mode and span,
    exactly -- a fresh plant, one that shares the free mode (another environment), one whose
    inertia differs by 1e-12."""
    def own(plant: Plant, dt: float) -> list[Propagator]:
        h = dt / plant.substeps
        return [Propagator.of(plant._a_free, plant._b_free, dt), Propagator.of(plant._a_contact, plant._b_contact, dt),
                Propagator.of(plant._a_free, plant._b_free, h), Propagator.of(plant._a_contact, plant._b_contact, h)]
    j = 0.3123456789     # not the inertia of another test: each plant's first call computes
    plants = [Plant(inertia=j, viscous_friction=0.05, stiffness=k, damping=60.0) for k in (15000.0, 9000.0)]
    plants.append(Plant(inertia=j * (1 + 1e-12), viscous_friction=0.05, stiffness=9000.0, damping=60.0))
    dts = [7e-4, 3e-4]
    for plant in plants:
        alone = mode_propagators(plant.inertia, plant.viscous_friction, plant.stiffness, plant.damping, dts)
        for dt, props in zip(dts, alone):
            m = plant.matrices(dt)
            assert [m.free, m.contact, m.free_sub, m.contact_sub] == own(plant, dt) == list(props), (plant.inertia, dt)
    assert plants[0].matrices(7e-4).free is plants[1].matrices(7e-4).free      # shared
    assert plants[1].matrices(7e-4).free != plants[2].matrices(7e-4).free      # its own


@pytest.mark.parametrize("environment", [False, True])
def test_coulomb_loop_is_the_general_loop_bit_for_bit(environment: bool) -> None:
    """The written-out Coulomb sub-step loop gives the general loop's numbers exactly:
    sliding, sticking, breaking away, in and out of contact."""
    rng = np.random.default_rng(11)
    press = 2.5 if environment else 0.0      # into the environment, and out now and then
    torques = np.concatenate([press + rng.uniform(-3, 3, 300), np.full(50, 0.05), np.zeros(50),
                              rng.choice([-2.0, 2.0], 300)]).tolist()
    plants = [Plant(inertia=0.2, viscous_friction=0.1, coulomb_friction=0.3,
                    stiffness=1e4 if environment else 0.0, damping=30.0 if environment else 0.0,
                    contact_position=0.0 if environment else 10.0) for _ in range(2)]
    plants[1]._coulomb_only = False          # the general loop (what Stribeck takes)
    states = [], []
    for u in torques:
        for plant, seen in zip(plants, states):
            plant.step(u, DT)
            seen.append((plant.true_position, plant.true_velocity, plant.friction_torque))
    assert states[0] == states[1]
    assert any(s[1] == 0.0 for s in states[0][300:])                 # it stuck
    if environment:
        assert any(s[0] >= 0.0 for s in states[0]) and any(s[0] < 0.0 for s in states[0])
