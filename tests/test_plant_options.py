"""The emulator's unmodelled plant options: Stribeck friction and gear backlash.

Off (the default) they change nothing, bit for bit; on, they follow their closed
forms (breakaway at the static level, no environment torque inside the dead band)
and never create energy.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.integrate import solve_ivp

from dobhil.config import Config, load_config
from dobhil.config.schema import EnvironmentConfig, PlantConfig, SensorConfig
from dobhil.emulator.plant import Plant
from dobhil.errors import ConfigError

DT = 1e-3
FC, FST, VST = 0.5, 0.3, 0.05        # Coulomb, Stribeck peak above it, Stribeck velocity
BETA = 0.004                          # backlash [rad]


def _trace(plant: Plant, torques: list[float]) -> list[tuple[float, ...]]:
    out = []
    for u in torques:
        plant.step(u, DT)
        out.append((plant.true_position, plant.true_velocity, plant.position, plant.velocity,
                    plant.interaction_torque, plant.friction_torque))
    return out


def _torques(n: int) -> list[float]:
    """Free motion into the default environment and back out, with reversals."""
    return [1.5 + 3.0 * math.sin(k / 37.0) + (4.0 if (k // 300) % 2 else -3.0) for k in range(n)]


# -- off: nothing changes ------------------------------------------------------------

@pytest.mark.parametrize("coulomb", [0.0, 0.4])
def test_options_off_leave_every_number_as_it_was(coulomb: float) -> None:
    """The keys at their defaults, or a Stribeck velocity with no Stribeck peak, take the
    same code path as before they existed: the same numbers, bit for bit (the linear
    case is the analysis' exact ZOH, tests/test_plant.py)."""
    base = dict(viscous_friction=0.1, coulomb_friction=coulomb, initial_position=-0.01)
    sensor = SensorConfig(encoder_resolution=8192, velocity_noise=0.01)
    plain = Plant.from_config(Config(plant=PlantConfig(**base), sensor=sensor))  # type: ignore[arg-type]
    inert = Plant.from_config(Config(plant=PlantConfig(**base, stribeck_velocity=0.7,  # type: ignore[arg-type]
                                                       stribeck_friction=0.0, backlash=0.0),
                                     sensor=sensor))
    assert _trace(plain, _torques(1500)) == _trace(inert, _torques(1500))
    assert not plain._friction if coulomb == 0.0 else plain._friction


def test_off_the_linear_plant_still_takes_one_exact_step_per_call() -> None:
    plant = Plant.from_config(Config(plant=PlantConfig(stribeck_velocity=0.2)))
    called = []
    plant._substeps = lambda *a: called.append(a)  # type: ignore[method-assign]
    _trace(plant, [5.0] * 20)                      # stays in contact: linear
    assert called == []


# -- Stribeck friction ------------------------------------------------------------------

def _stribeck(**kw: float) -> Plant:
    return Plant.from_config(Config(plant=PlantConfig(  # type: ignore[arg-type]
        coulomb_friction=FC, stribeck_friction=FST, stribeck_velocity=VST,
        initial_position=-1.0, **kw)))


def test_stribeck_holds_below_the_static_level_where_coulomb_alone_slides() -> None:
    coulomb = Plant.from_config(Config(plant=PlantConfig(coulomb_friction=FC,
                                                         initial_position=-1.0)))
    stribeck = _stribeck()
    for _ in range(50):
        coulomb.step(0.75, DT)      # FC < 0.75 < FC + FST
        stribeck.step(0.75, DT)
    assert coulomb.true_velocity > 0.0
    assert (stribeck.true_position, stribeck.true_velocity) == (-1.0, 0.0)
    assert stribeck.friction_torque == 0.75          # static friction balances the torque


def test_stribeck_breakaway_torque_is_the_static_level() -> None:
    """A slow torque ramp (1 mN m per period) breaks away on the first period whose torque
    exceeds F_s = F_c + F_St, the closed-form breakaway torque."""
    plant = _stribeck()
    ramp = 1e-3
    k = 0
    while plant.true_velocity == 0.0:
        k += 1
        plant.step(k * ramp, DT)
        assert k < 2000
    assert FC + FST < k * ramp <= FC + FST + ramp
    assert (k - 1) * ramp <= FC + FST


def _sliding_reference(u: float, b: float, t_end: float) -> object:
    """J dv/dt = u - b v - F_c - F_St exp(-(v/v_St)^2), from rest (sliding forward)."""
    def f(t: float, v: np.ndarray) -> list[float]:
        return [(u - b * v[0] - FC - FST * math.exp(-(v[0] / VST) ** 2)) / 0.25]
    return solve_ivp(f, (0.0, t_end), [0.0], rtol=1e-12, atol=1e-14, dense_output=True).sol


def test_stribeck_sliding_matches_solve_ivp_and_converges_with_substeps() -> None:
    """Past breakaway the velocity follows the Stribeck ODE; the friction is held over a
    sub-step, so the error is first order in the sub-step."""
    u, b, n = 1.0, 0.2, 300
    ref = _sliding_reference(u, b, n * DT)
    errors = {}
    for substeps in (10, 100):
        plant = Plant.from_config(Config(plant=PlantConfig(
            viscous_friction=b, coulomb_friction=FC, stribeck_friction=FST,
            stribeck_velocity=VST, initial_position=-1.0)), substeps=substeps)
        err = 0.0
        for k in range(1, n + 1):
            plant.step(u, DT)
            err = max(err, abs(plant.true_velocity - float(ref(k * DT)[0])))  # type: ignore[operator]
        errors[substeps] = err
    v_end = float(ref(n * DT)[0])  # type: ignore[operator]
    assert v_end > 5 * VST                           # well past the Stribeck dip
    assert errors[10] < 1e-3 * v_end
    assert errors[100] < 0.2 * errors[10]


def test_stribeck_friction_only_removes_energy_and_comes_to_rest_for_good() -> None:
    plant = _stribeck(viscous_friction=0.05)
    for _ in range(200):
        plant.step(2.0, DT)
    v = plant.true_velocity
    assert v > 0.5
    speeds = []
    for _ in range(2000):
        plant.step(0.0, DT)
        assert 0.0 <= plant.true_velocity <= v        # never reverses, never speeds up
        v = plant.true_velocity
        speeds.append(v)
    assert speeds[-1] == 0.0
    rest = plant.true_position
    for _ in range(100):
        plant.step(0.7, DT)                           # below F_s: stays stuck
    assert (plant.true_position, plant.true_velocity) == (rest, 0.0)


# -- backlash -----------------------------------------------------------------------

def _backlash(**kw: float) -> Plant:
    return Plant.from_config(Config(plant=PlantConfig(backlash=BETA, **kw)))  # type: ignore[arg-type]


def test_no_environment_torque_until_the_dead_band_is_crossed() -> None:
    """From rest at the contact position with the load centred, the motor moves freely
    (q = u t^2 / 2J exactly) and feels nothing until it has travelled beta/2."""
    plant = _backlash()
    u, j = 2.0, 0.25
    k = 0
    while plant.interaction_torque == 0.0:
        k += 1
        plant.step(u, DT)
        free = u * (k * DT) ** 2 / (2 * j)
        if free < 0.5 * BETA:
            assert plant.true_position == pytest.approx(free, rel=1e-12)
            assert plant.load_position == 0.0
        assert k < 1000
    crossing = math.sqrt(2 * j * 0.5 * BETA / u)       # closed form: 31.6 ms
    assert (k - 1) * DT < crossing <= k * DT + DT / plant.substeps
    assert plant.true_position - plant.load_position == pytest.approx(0.5 * BETA, abs=1e-15)


def test_pressed_steady_state_is_the_plain_one_shifted_by_half_the_band() -> None:
    plain = Plant.from_config(Config(plant=PlantConfig(viscous_friction=1.0)))
    geared = _backlash(viscous_friction=1.0)
    for _ in range(3000):
        plain.step(3.0, DT)
        geared.step(3.0, DT)
    assert geared.interaction_torque == pytest.approx(3.0, rel=1e-9)
    assert plain.interaction_torque == pytest.approx(3.0, rel=1e-9)
    assert geared.true_position - plain.true_position == pytest.approx(0.5 * BETA, rel=1e-9)


def test_reversing_opens_the_gap_and_the_torque_vanishes() -> None:
    plant = _backlash(viscous_friction=0.5)
    for _ in range(1000):
        plant.step(3.0, DT)
    assert plant.interaction_torque > 2.9
    pressed = plant.true_position
    crossed = False
    for _ in range(400):
        plant.step(-1.0, DT)
        gap = plant.true_position - plant.load_position
        if plant.interaction_torque != 0.0:
            assert abs(gap) == pytest.approx(0.5 * BETA, abs=1e-12)
        crossed |= plant.true_position < pressed - BETA
    assert crossed
    assert plant.interaction_torque <= 0.0 or not plant.in_contact


def _energy(plant: Plant) -> float:
    e = max(plant.load_position - plant.contact_position, 0.0)
    return 0.5 * plant.inertia * plant.true_velocity ** 2 + 0.5 * plant.stiffness * e ** 2


def test_backlash_never_creates_energy() -> None:
    """Thrown at the environment and let go: kinetic plus spring energy only decreases
    (up to the contact placement within a sub-step, K (v h)^2 / 2 at most per step)."""
    plant = _backlash(viscous_friction=0.1, initial_position=-0.02)
    for _ in range(40):
        plant.step(10.0, DT)
    released = energy = _energy(plant)
    h = DT / plant.substeps
    touched = bounced = False
    for _ in range(1500):
        v = abs(plant.true_velocity)
        plant.step(0.0, DT)
        now = _energy(plant)
        assert now <= energy + 0.5 * plant.stiffness * (v * h) ** 2 + 1e-15
        energy = now
        touched |= plant.interaction_torque > 0.0
        bounced |= touched and plant.true_velocity < 0.0
    assert touched and bounced
    assert energy < 0.9 * released            # the environment's damper and b took their share


def test_a_face_never_pulls_the_load_out_of_the_environment() -> None:
    """Pressed, then backed away faster than the environment relaxes: a face can only push,
    so it lets go, and the massless load's depth decays as a spring and damper alone make it,
    by exp(-K T / D) per period (0.82 here), while the motor's face runs ahead of it."""
    plant = Plant.from_config(Config(plant=PlantConfig(backlash=BETA, initial_position=-0.001),
                                     environment=EnvironmentConfig(damping=50.0)))
    for _ in range(40):
        plant.step(4.0, DT)
    assert plant.interaction_torque > 0.0
    plant.step(-8.0, DT)
    plant.step(-8.0, DT)       # the face has let go during these
    depth = plant.load_position - plant.contact_position
    for _ in range(6):
        plant.step(-8.0, DT)
        gap = plant.true_position - plant.load_position
        assert abs(gap) < 0.5 * BETA - 1e-6 and plant.interaction_torque == 0.0
    decay = math.exp(-plant.stiffness * 6 * DT / plant.damping)
    assert plant.load_position - plant.contact_position == pytest.approx(depth * decay, rel=1e-9)


@settings(max_examples=40, deadline=None)
@given(st.lists(st.floats(-8.0, 8.0), min_size=1, max_size=200),
       st.floats(0.0, 0.6), st.floats(0.0, 50.0))
def test_play_operator_invariants(torques: list[float], coulomb: float, damping: float) -> None:
    """Whatever the torque: the load never leaves the dead band, and a torque reaches the
    motor only with the load against a face of the band, inside the environment, in the
    direction that face can carry. Each example first pushes the servo into the environment
    (30 ms at 4 N m: contact after ~22 ms), so the drawn torques start from a pressed load
    and the checks of a transmitted torque run in every example."""
    plant = Plant.from_config(Config(plant=PlantConfig(backlash=BETA, coulomb_friction=coulomb,
                                                       initial_position=-0.001),
                                     environment=EnvironmentConfig(damping=damping)))
    transmitted = 0
    for u in [4.0] * 30 + torques:
        plant.step(u, DT)
        gap = plant.true_position - plant.load_position
        assert abs(gap) <= 0.5 * BETA + 1e-12
        tau = plant.interaction_torque
        if tau != 0.0:
            transmitted += 1
            assert plant.in_contact
            assert abs(gap) == pytest.approx(0.5 * BETA, abs=1e-12)
            assert tau * gap > 0.0
        assert math.isfinite(plant.true_velocity)
    assert transmitted > 0


# -- configuration ------------------------------------------------------------------

def test_keys_reach_the_plant_and_bad_values_are_one_line() -> None:
    config = load_config(None, ["plant.stribeck_friction=0.3", "plant.stribeck_velocity=0.02",
                                "plant.backlash=0.001"])
    plant = Plant.from_config(config)
    assert (plant.stribeck_friction, plant.stribeck_velocity, plant.backlash) == (0.3, 0.02, 0.001)
    for bad, allowed in (("plant.backlash=2", "<= 1"), ("plant.backlash=-0.1", ">= 0"),
                         ("plant.stribeck_velocity=0", "> 0"),
                         ("plant.stribeck_friction=-1", ">= 0")):
        with pytest.raises(ConfigError, match=allowed) as info:
            load_config(None, [bad])
        assert "\n" not in str(info.value) and bad.split("=")[0] in str(info.value)
    with pytest.raises(ValueError, match="stribeck_velocity"):
        Plant(inertia=1.0, stribeck_velocity=0.0)
    with pytest.raises(ValueError, match="backlash"):
        Plant(inertia=1.0, backlash=-1.0)
