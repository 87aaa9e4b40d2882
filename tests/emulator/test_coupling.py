"""Coupled plants (dobhil/emulator/coupling.py) against the stacked continuous system.

The reference is independent of dobhil's own discretisation: the 4-state linear system of
both servos (inertias, viscous frictions, one in contact with its environment spring) and
the coupling spring/damper, integrated exactly by ``scipy.linalg.expm`` of the augmented
matrix over each interval where both torques are constant -- the very piecewise-constant
torques the coupled plants are stepped with, axis ``a`` first and cut inside each step at a
command's latch instant, as :class:`dobhil.drives.emulated.LockstepBus` steps them.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.linalg import expm

from dobhil.config.axes import Coupling
from dobhil.emulator.coupling import CoupledPlant, couple_plants, step_limit
from dobhil.emulator.plant import Plant

Torque = Callable[[str, float], float]

JA, JB = 0.25, 0.3            # inertias [kg m^2]
BA, BB = 0.2, 0.1             # viscous frictions [N m s/rad]
KE, DE, QC = 1000.0, 5.0, -1.0   # axis a's environment (in contact throughout: e ~ 0.05)
Q0 = -0.95                    # both start here, at rest
SPLIT = 0.3                   # axis a's command latches 0.3 of the way into each step
T_END = 0.2


def pair(k: float, d: float) -> tuple[CoupledPlant, CoupledPlant]:
    pa = Plant(inertia=JA, viscous_friction=BA, stiffness=KE, damping=DE, contact_position=QC,
               initial_position=Q0)
    pb = Plant(inertia=JB, viscous_friction=BB, initial_position=Q0)
    plants = couple_plants({"a": pa, "b": pb}, [Coupling("a", "b", k, d)])
    a, b = plants["a"], plants["b"]
    assert isinstance(a, CoupledPlant) and isinstance(b, CoupledPlant)
    return a, b


def emulated(dt: float, k: float, d: float, torque: Torque) -> np.ndarray:
    a, b = pair(k, d)
    out = []
    for i in range(round(T_END / dt)):
        t = i * dt
        a.step(torque("a", t), SPLIT * dt)
        a.step(torque("a", t + SPLIT * dt), dt - SPLIT * dt)
        b.step(torque("b", t), dt)
        out.append((a.true_position, a.true_velocity, b.true_position, b.true_velocity))
    return np.array(out)


def reference(dt: float, k: float, d: float, torque: Torque) -> np.ndarray:
    """x = [q_a, dq_a, q_b, dq_b]; inputs [u_a, u_b, 1] (the 1 carries K_e q_c)."""
    a = np.array([[0.0, 1.0, 0.0, 0.0],
                  [-(KE + k) / JA, -(BA + DE + d) / JA, k / JA, d / JA],
                  [0.0, 0.0, 0.0, 1.0],
                  [k / JB, d / JB, -k / JB, -(BB + d) / JB]])
    b = np.array([[0.0, 0.0, 0.0], [1 / JA, 0.0, KE * QC / JA], [0.0, 0.0, 0.0], [0.0, 1 / JB, 0.0]])

    def zoh(h: float) -> tuple[np.ndarray, np.ndarray]:
        m = np.zeros((7, 7))
        m[:4, :4], m[:4, 4:] = a, b
        e = expm(m * h)
        return e[:4, :4], e[:4, 4:]

    (p1, g1), (p2, g2) = zoh(SPLIT * dt), zoh(dt - SPLIT * dt)
    x = np.array([Q0, 0.0, Q0, 0.0])
    out = []
    for i in range(round(T_END / dt)):
        t = i * dt
        x = p1 @ x + g1 @ np.array([torque("a", t), torque("b", t), 1.0])
        x = p2 @ x + g2 @ np.array([torque("a", t + SPLIT * dt), torque("b", t), 1.0])
        out.append(x.copy())
    return np.array(out)


def smooth(axis: str, t: float) -> float:
    return 60.0 + 5.0 * math.sin(20.0 * t) if axis == "a" else math.cos(13.0 * t)


def jumps(seed: int) -> Torque:
    """Random torque steps every 2 ms (a slower loop's commands), on both axes."""
    steps = np.random.default_rng(seed).uniform(-3.0, 3.0, (2, 1 + round(T_END / 0.002)))
    return lambda axis, t: (60.0 if axis == "a" else 0.0) + float(steps[int(axis == "b"), int(t / 0.002 + 1e-9)])


@pytest.mark.parametrize(("k", "d", "torque"), [(2e4, 0.0, smooth), (2e4, 20.0, smooth),
                                                (2e3, 20.0, smooth), (2e4, 20.0, jumps(3))])
def test_second_order_against_the_stacked_system(k: float, d: float, torque: Torque) -> None:
    """The scheme is second order (coupling.py): halving the step divides the largest error
    over the run by 4 in the limit. The bound for each step is the error measured at twice
    the step times (1/2)^2, with 1.5 for the approach to the limit; the first step is also
    bounded by a plain physical check (the errors are small against the motion)."""
    steps = (2e-3, 1e-3, 5e-4, 2.5e-4)
    errors = [float(np.abs(emulated(h, k, d, torque) - reference(h, k, d, torque)).max()) for h in steps]
    for coarse, fine in zip(errors, errors[1:]):
        assert fine <= coarse * 0.25 * 1.5, errors
    motion = float(np.abs(np.diff(reference(steps[-1], k, d, torque), axis=0)).sum(axis=0).max())
    assert errors[1] < 1e-2 * motion, (errors, motion)


def test_stiff_coupling_does_not_gain_energy() -> None:
    """K = 2e4 N m/rad between two 0.25 kg m^2 servos stepped at 1 ms (omega dt = 0.4), no
    physical damping: the stored energy never grows over windows of 0.5 s (the scheme's
    own small damping takes some, coupling.py), and never exceeds the start by more than
    1 % (the first steps' extrapolation, measured 0.9 %)."""
    pa, pb = Plant(inertia=0.25, initial_position=0.01), Plant(inertia=0.25)
    plants = couple_plants({"a": pa, "b": pb}, [Coupling("a", "b", 2e4, 0.0)])
    a, b = plants["a"], plants["b"]

    def energy() -> float:
        return 0.5 * 0.25 * (pa.true_velocity ** 2 + pb.true_velocity ** 2) + \
            0.5 * 2e4 * (pa.true_position - pb.true_position) ** 2

    start = window = energy()
    for i in range(1, 5001):
        a.step(0.0, 0.3e-3)
        a.step(0.0, 0.7e-3)
        b.step(0.0, 1e-3)
        assert energy() <= 1.01 * start
        if i % 500 == 0:
            assert energy() < window
            window = energy()


def test_uncoupled_axes_are_the_plain_plants_bit_for_bit() -> None:
    def plant() -> Plant:
        return Plant(inertia=0.2, coulomb_friction=0.05, stiffness=500.0, damping=2.0,
                     contact_position=0.01, velocity_noise=0.01, encoder_resolution=8192, seed=4)

    alone, third, zero_a, zero_b = plant(), plant(), plant(), plant()
    plants = couple_plants({"a": Plant(inertia=0.3), "b": Plant(inertia=0.3), "c": third,
                            "x": zero_a, "y": zero_b},
                           [Coupling("a", "b", 2e3, 1.0), Coupling("x", "y", 0.0, 0.0)])
    assert plants["c"] is third and plants["x"] is zero_a and plants["y"] is zero_b
    # a plant coupled with nothing (couple(0, 0)) runs the very lines of a plain plant
    undone = plant()
    undone.couple(0.0, 0.0)
    rng = np.random.default_rng(2)
    for u in rng.uniform(-3.0, 3.0, 400):
        for p in (alone, third, undone):
            p.step(float(u), 1e-3)
        plants["a"].step(float(u), 1e-3)
        plants["b"].step(-float(u), 1e-3)
        assert third.truth() == alone.truth() == undone.truth()
        assert (third.position, third.velocity) == (alone.position, alone.velocity)


finite = st.floats(-0.5, 0.5)


@settings(max_examples=60, deadline=None)
@given(k=st.floats(1.0, 5e4), d=st.floats(0.0, 50.0), qa=finite, qb=finite, va=finite, vb=finite,
       torques=st.lists(st.tuples(st.floats(-5, 5), st.floats(-5, 5)), min_size=1, max_size=20),
       split=st.floats(0.05, 0.95))
def test_torques_are_equal_and_opposite_and_naming_order_does_not_matter(
        k: float, d: float, qa: float, qb: float, va: float, vb: float,
        torques: list[tuple[float, float]], split: float) -> None:
    def build(pair: tuple[str, str]) -> dict[str, object]:
        plants = {n: Plant(inertia=j, initial_position=q, initial_velocity=v, viscous_friction=0.1)
                  for n, j, q, v in (("a", 0.2, qa, va), ("b", 0.4, qb, vb))}
        return dict(couple_plants(plants, [Coupling(*pair, k, d)]))

    for pair in (("a", "b"), ("b", "a")):
        plants = build(pair)
        a, b = plants["a"], plants["b"]
        assert isinstance(a, CoupledPlant) and isinstance(b, CoupledPlant)
        tau = k * (qb - qa) + d * (vb - va)
        assert a.coupling_torque == tau and b.coupling_torque == -tau
        assert a.interaction_torque == -tau and a.truth().tau_int == -tau
        for ua, ub in torques:
            a.step(ua, split * 1e-3)
            a.step(ua, (1 - split) * 1e-3)
            b.step(ub, 1e-3)
            assert a.coupling_torque == -b.coupling_torque
            assert a.interaction_torque == -b.interaction_torque   # no environment here
        finals = (a.true_position, a.true_velocity, b.true_position, b.true_velocity)
        if pair == ("a", "b"):
            first = finals
        else:
            assert finals == first


@settings(max_examples=60, deadline=None)
@given(k=st.floats(1.0, 5e4), d=st.floats(0.0, 50.0), gap=st.floats(1e-4, 0.1))
def test_a_stretched_coupling_pulls_the_axes_together(k: float, d: float, gap: float) -> None:
    """b ahead of a, both at rest and free: a is pulled forward, b back; a's force sensor
    reads the spring's pull (negative: it pulls, it does not push), b's the same force
    from the other side."""
    plants = couple_plants({"a": Plant(inertia=0.2), "b": Plant(inertia=0.3, initial_position=gap)},
                           [Coupling("a", "b", k, d)])
    a, b = plants["a"], plants["b"]
    assert isinstance(a, CoupledPlant) and isinstance(b, CoupledPlant)
    assert a.interaction_torque == -b.interaction_torque == -k * gap
    a.step(0.0, 1e-4)
    b.step(0.0, 1e-4)
    assert a.true_velocity > 0.0 > b.true_velocity
    assert a.true_position > 0.0 and b.true_position < gap


def test_refuses_a_coupling_it_cannot_build() -> None:
    with pytest.raises(ValueError, match="no axis 'c'"):
        couple_plants({"a": Plant(inertia=1.0), "b": Plant(inertia=1.0)}, [Coupling("a", "c", 1.0, 0.0)])
    with pytest.raises(ValueError, match="backlash"):
        couple_plants({"a": Plant(inertia=1.0, backlash=0.01), "b": Plant(inertia=1.0)},
                      [Coupling("a", "b", 1.0, 0.0)])


def test_three_axes_in_a_chain_match_the_stacked_system() -> None:
    """a - b - c: the middle axis sums both couplings (its own part exact, both partners'
    at the step's middle); the largest error over 0.2 s at 0.5 ms is second order against
    1 ms (the same bound as the pair's)."""
    ks, j = (3e3, 5e3), (0.2, 0.3, 0.25)

    def emulated(dt: float) -> np.ndarray:
        plants = couple_plants({n: Plant(inertia=ji, initial_position=0.01 * i) for i, (n, ji)
                                in enumerate(zip("abc", j))},
                               [Coupling("a", "b", ks[0], 1.0), Coupling("b", "c", ks[1], 2.0)])
        out = []
        for i in range(round(T_END / dt)):
            for n, u in zip("abc", (math.sin(30 * i * dt), 0.0, -1.0)):
                plants[n].step(u, dt)
            out.append([plants[n].true_position for n in "abc"])
        return np.array(out)

    def reference(dt: float) -> np.ndarray:
        k1, k2 = ks
        stiff = np.array([[-k1, k1, 0.0], [k1, -k1 - k2, k2], [0.0, k2, -k2]])
        damp = np.array([[-1.0, 1.0, 0.0], [1.0, -3.0, 2.0], [0.0, 2.0, -2.0]])
        jinv = np.diag(1 / np.array(j))
        a = np.block([[np.zeros((3, 3)), np.eye(3)], [jinv @ stiff, jinv @ damp]])
        m = np.zeros((9, 9))
        m[:6, :6], m[3:6, 6:] = a, jinv
        e = expm(m * dt)
        x = np.array([0.0, 0.01, 0.02, 0.0, 0.0, 0.0])
        out = []
        for i in range(round(T_END / dt)):
            x = e[:6, :6] @ x + e[:6, 6:] @ np.array([math.sin(30 * i * dt), 0.0, -1.0])
            out.append(x[:3].copy())
        return np.array(out)

    coarse, fine = (float(np.abs(emulated(h) - reference(h)).max()) for h in (1e-3, 5e-4))
    assert fine <= coarse * 0.25 * 1.5, (coarse, fine)


def test_friction_holds_a_coupled_axis_until_the_spring_exceeds_it() -> None:
    """Axis a (Coulomb friction 1 N m) is dragged by b through a 100 N m/rad spring; b moves at
    a constant 0.5 rad/s (a heavy servo on a steady torque). a sticks, exactly, while the
    spring's pull is below 1 N m and slides once it is above: the Karnopp decision sees the
    coupling's own spring (Plant.couple), not only the environment's."""
    # both start at 0.3 rad: the spring's own part of the torque there, -K q_a, is large
    pa = Plant(inertia=0.05, coulomb_friction=1.0, initial_position=0.3)
    pb = Plant(inertia=1e6, initial_velocity=0.5, initial_position=0.3)
    plants = couple_plants({"a": pa, "b": pb}, [Coupling("a", "b", 100.0, 0.0)])
    slid_at = None
    for _ in range(400):
        plants["a"].step(0.0, 1e-3)
        plants["b"].step(0.0, 1e-3)
        pull = 100.0 * (pb.true_position - pa.true_position)
        if slid_at is None and pa.true_position != 0.3:
            slid_at = pull
        if slid_at is None:
            assert pa.true_velocity == 0.0
    # it broke away in the step the pull crossed 1 N m (b moves 0.05 N m of pull per step)
    assert slid_at is not None and 1.0 <= slid_at <= 1.0 + 0.05 + 1e-9, slid_at


@pytest.mark.parametrize(("ja", "jb"), [(0.25, 0.25), (0.01, 1.0), (1.0, 0.01)])
def test_the_step_limit_is_a_stable_step(ja: float, jb: float) -> None:
    """At the step :func:`step_limit` gives, the undamped pair loses energy over 20 s."""
    k = 2e4
    dt = step_limit({"a": ja, "b": jb}, [Coupling("a", "b", k, 0.0), Coupling("a", "b", 0.0, 5.0)])
    assert dt == pytest.approx(2.0 / math.sqrt(k * (1 / ja + 1 / jb)), rel=1e-15)
    pa, pb = Plant(inertia=ja, initial_position=0.01), Plant(inertia=jb)
    plants = couple_plants({"a": pa, "b": pb}, [Coupling("a", "b", k, 0.0)])

    def energy() -> float:
        return 0.5 * (ja * pa.true_velocity ** 2 + jb * pb.true_velocity ** 2) + \
            0.5 * k * (pa.true_position - pb.true_position) ** 2

    start = energy()
    for _ in range(round(20.0 / dt)):
        plants["a"].step(0.0, dt)
        plants["b"].step(0.0, dt)
    assert energy() < start
    assert step_limit({"a": ja, "b": jb}, [Coupling("a", "b", 0.0, 5.0)]) == math.inf
