"""The identification's model (dobhil.identify.model): the emulator's Plant, stepped the way
the lockstep emulator applies delayed commands, and its fast path equal to that reference."""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st
from threadpoolctl import threadpool_info, threadpool_limits

from dobhil.emulator.plant import Plant
from dobhil.identify.model import (ModelValues, _compiled_record, _setup, _simulate,
                                   _simulate_stepping, simulate_torque)
from dobhil.realtime import one_blas_thread

PERIOD = 1e-3


@pytest.mark.parametrize("delay", [0.0, 0.4e-3, 2.0e-3])
def test_initial_velocity_free_decay_closed_form(delay: float) -> None:
    """No torque, launched at v0: v0 exp(-b t / J) and q0 + v0 J / b (1 - exp(-b t / J))
    (closed form, independent of the discretisation), whatever the delay."""
    j, b, q0, v0 = 0.05, 0.2, -0.4, 2.5
    n = 300
    pos, vel = simulate_torque(ModelValues(inertia=j, viscous_friction=b, delay=delay),
                               np.zeros(n), PERIOD, 0, n, q0, v0)
    t = np.arange(n) * PERIOD
    decay = np.exp(-b * t / j)
    np.testing.assert_allclose(vel, v0 * decay, rtol=1e-12)
    np.testing.assert_allclose(pos, q0 + v0 * j / b * (1 - decay), rtol=1e-12, atol=1e-14)


def test_initial_velocity_against_coulomb_friction_stops_at_the_closed_form_time() -> None:
    """Coulomb friction alone (b = 0) decelerates v0 at F_c / J: at rest by t = J v0 / F_c,
    after q0 + J v0^2 / (2 F_c), and stays there (no torque)."""
    j, fc, q0, v0 = 0.1, 0.5, 0.0, 1.0
    n = 400
    pos, vel = simulate_torque(ModelValues(inertia=j, coulomb_friction=fc), np.zeros(n),
                               PERIOD, 0, n, q0, v0)
    stop = j * v0 / fc                                # 0.2 s
    k = int(stop / PERIOD)
    np.testing.assert_allclose(vel[:k - 2], v0 - fc / j * np.arange(k - 2) * PERIOD, rtol=1e-9)
    assert np.all(vel[k + 2:] == 0.0)
    # the Karnopp band stops the servo within one sub-step of the exact time
    assert pos[-1] == pytest.approx(q0 + j * v0 ** 2 / (2 * fc), abs=v0 * PERIOD / 10)
    assert math.isfinite(pos[-1])


# -- the fast path equals stepping the Plant ----------------------------------------------

def _torque(style: str, n: int, seed: int, amplitude: float, offset: float) -> np.ndarray:
    """Excitations that exercise every event of the Plant: PRBS levels (frequent velocity
    reversals), a few sines (slow ones), steps with rests below the Coulomb level and at
    zero (sticking, breakaway), and an offset that reverses (pressing into the
    environment, pulling out of it, pressing again)."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) * PERIOD
    if style == "prbs":
        clock = int(rng.integers(1, 8))
        levels = np.sign(rng.standard_normal(n // clock + 1)).repeat(clock)[:n]
        return offset + amplitude * levels
    if style == "sines":
        freqs = rng.uniform(0.5, 30.0, 4)
        phases = rng.uniform(0.0, 2 * np.pi, 4)
        return offset + amplitude / 2 * np.sin(2 * np.pi * freqs[:, None] * t
                                                + phases[:, None]).sum(axis=0)
    if style == "steps":
        edges = np.sort(rng.integers(0, n, 8))
        u = np.zeros(n)
        for lo, hi in zip(edges[:-1], edges[1:]):
            u[lo:hi] = amplitude * rng.choice([0.0, 0.1, -0.2, 1.0, -1.0, 3.0])
        return offset + u
    # "reverse": press, pull out, press again, with a ripple
    sign = np.where((t > t[-1] / 3) & (t < 2 * t[-1] / 3), -1.0, 1.0)
    return offset * sign + amplitude * np.sin(2 * np.pi * 7.0 * t)


_GENERIC = 1.0 + math.pi * 1e-4


@st.composite
def _cases(draw: st.DrawFn) -> tuple[ModelValues, np.ndarray, int, int, float, float]:
    inertia = draw(st.floats(0.01, 1.0))
    viscous = draw(st.sampled_from([0.0, draw(st.floats(0.001, 2.0))]))
    # times an irrational factor: with Coulomb level and torques in a rational ratio (0.5 and
    # 1.0, say, as shrinking finds) a velocity can land exactly on the Karnopp band's edge in
    # exact arithmetic, a tie the reference itself decides by rounding; any other order of
    # the same arithmetic (the fast path's superposition) may round it the other way, one
    # sub-step's friction apart. Generic values have no such ties (the fast path sends the
    # near-ties it can see, within 1e-11 of the states' scale, to the Plant)
    coulomb = draw(st.sampled_from([0.0, draw(st.floats(0.005, 0.5))])) * _GENERIC
    period = PERIOD
    delay = draw(st.sampled_from([0.0, 1.0, 2.0, draw(st.floats(0.05, 0.95)),
                                  draw(st.floats(1.05, 2.95))])) * period
    style = draw(st.sampled_from(["prbs", "sines", "steps", "reverse"]))
    n = draw(st.integers(2, 1500))
    start = draw(st.integers(0, 20))
    amplitude = draw(st.floats(0.05, 2.0))
    seed = draw(st.integers(0, 2 ** 16))
    q0 = draw(st.floats(-1.0, 1.0))
    v0 = draw(st.sampled_from([0.0, draw(st.floats(-2.0, 2.0))]))
    if draw(st.booleans()):       # an environment
        stiffness = draw(st.floats(1e3, 1e5))
        damping = draw(st.floats(0.0, 100.0))
        offset = draw(st.floats(0.0, 3.0))
        # start pressed (in equilibrium with the offset) or just short of the contact
        inside = draw(st.booleans())
        qc = q0 - offset / stiffness if inside else q0 + draw(st.floats(1e-6, 1e-2))
        values = ModelValues(inertia=inertia, viscous_friction=viscous,
                             coulomb_friction=coulomb, contact_position=qc,
                             stiffness=stiffness, damping=damping, delay=delay)
    else:
        offset = draw(st.floats(-0.5, 0.5))
        values = ModelValues(inertia=inertia, viscous_friction=viscous,
                             coulomb_friction=coulomb, delay=delay)
    gain = draw(st.sampled_from([1.0, draw(st.floats(0.5, 2.0))]))
    values = dataclasses.replace(values, torque_gain=gain)
    torque = _torque(style, start + n, seed, amplitude, offset)
    return values, torque, start, start + n, q0, v0


def _assert_same(fast: tuple[np.ndarray, np.ndarray],
                 ref: tuple[np.ndarray, np.ndarray]) -> None:
    """Equal to 1e-9 relative: of the largest |position| (the Plant rounds relative to the
    contact position) and of the largest |velocity|."""
    for got, want in zip(fast, ref):
        scale = float(np.max(np.abs(want)))
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-9 * scale + 1e-15)


def _assert_plant_steps(fast: tuple[np.ndarray, np.ndarray], values: ModelValues,
                        torque: np.ndarray, start: int, stop: int) -> None:
    """Every sample of ``fast`` is the Plant's step from the sample before (set_state, then
    Plant.step as the reference calls it), to 1e-9 of the largest |position| / |velocity|:
    the fast path is the Plant's map sample by sample, whatever the dynamics does with
    rounding over many samples.

    A position exactly on the contact (``pos == q_c``) hides on which side the state was:
    its offset from the contact may be below the position's rounding (a servo resting on
    the environment's surface, 1e-214 rad from it, as Hypothesis found), and the step's
    first sub-step takes the contact or the free mode by its sign. There the step from
    either side is the Plant's."""
    pos, vel = fast
    plant, qc, applied, _, fraction = _setup(values, torque, PERIOD, start, stop,
                                             float(pos[0]), 10)
    late = fraction > 1e-12

    def steps(positions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        stepped_pos = np.empty(len(pos) - 1)
        stepped_vel = np.empty(len(pos) - 1)
        for j in range(len(pos) - 1):
            plant.set_state(float(positions[j]), float(vel[j]))
            if late:
                plant.step(float(applied[j]), fraction)
            plant.step(float(applied[j + 1]), PERIOD - fraction)
            stepped_pos[j], stepped_vel[j] = plant.true_position, plant.true_velocity
        return stepped_pos, stepped_vel

    stepped = steps(pos)
    surface = (pos[:-1] == qc) & bool(values.stiffness or values.damping)
    if surface.any():   # those samples also from just outside: either side may be it
        outside = steps(np.where(pos == qc, np.nextafter(qc, -np.inf), pos))
        for got, want, other in zip((pos[1:], vel[1:]), stepped, outside):
            tol = 1e-9 * float(np.max(np.abs(want))) + 1e-15
            near = np.abs(got - want) <= tol
            choose = surface & ~near & (np.abs(got - other) <= tol)
            want[choose] = other[choose]
    _assert_same((pos[1:], vel[1:]), stepped)


def _chaotic(values: ModelValues, ref: tuple[np.ndarray, np.ndarray]) -> bool:
    """The servo hits or leaves the environment: an impact oscillator, whose trajectories
    separate exponentially (measured: a difference of 1e-12 of rounding grew x10 per ~100
    samples on a damped servo bouncing under a PRBS) -- the reference's own numbers are
    then one rounding's trajectory, and only the step-by-step equality means anything."""
    if not math.isfinite(values.contact_position):
        return False
    inside = ref[0] >= values.contact_position
    return bool(inside.any() and not inside.all())


def _plant_step(values: ModelValues, torque: np.ndarray, start: int, stop: int, j: int,
                state: tuple[float, float]) -> tuple[float, float]:
    """The state at sample ``start + j + 1``: the Plant stepped once from ``state`` at
    sample ``start + j`` (as the reference steps it)."""
    plant, _, applied, _, fraction = _setup(values, torque, PERIOD, start, stop, state[0], 10)
    plant.set_state(*state)
    if fraction > 1e-12:
        plant.step(float(applied[j]), fraction)
    plant.step(float(applied[j + 1]), PERIOD - fraction)
    return plant.true_position, plant.true_velocity


def _parted_at_a_tie(got: tuple[np.ndarray, np.ndarray], ref: tuple[np.ndarray, np.ndarray],
                     values: ModelValues, torque: np.ndarray, start: int, stop: int) -> bool:
    """``got`` leaves ``ref`` at a decision that rounding takes: at the last sample where
    the two still agree their states are a rounding apart (1e-12 of the scale), yet the
    Plant's own step from each lands a friction sub-step apart or more (more than the
    1e-9 equality allows). A velocity exactly on the Karnopp band's edge does this: a
    +-2 N m square wave whose pushes cancel leaves the servo at exactly ``-2 F_c h / J``,
    the band's edge, and the superposition rounds it a few 1e-18 outside, the Plant's
    sub-steps inside. No method but the reference's own arithmetic decides such a tie the
    reference's way; the sample-by-sample check still holds on both sides of it."""
    scale = [float(np.max(np.abs(r))) for r in ref]
    apart = np.zeros(len(ref[0]), bool)
    for g, r, s in zip(got, ref, scale):
        apart |= np.abs(g - r) > 1e-9 * s + 1e-15
    if not apart.any():
        return False
    j = int(np.argmax(apart)) - 1
    if j < 0:
        return False
    a = (float(got[0][j]), float(got[1][j]))
    b = (float(ref[0][j]), float(ref[1][j]))
    if any(abs(x - y) > 1e-12 * s + 1e-18 for x, y, s in zip(a, b, scale)):
        return False
    stepped_a = _plant_step(values, torque, start, stop, j, a)
    stepped_b = _plant_step(values, torque, start, stop, j, b)
    return any(abs(x - y) > 1e-9 * s + 1e-15 for x, y, s in zip(stepped_a, stepped_b, scale))


# found by Hypothesis: a servo resting on the environment's surface, 1e-214 rad from it
# (below the position's rounding), pushed into it after 61 samples
_SURFACE_CASE = (ModelValues(inertia=0.25, contact_position=1.0, stiffness=1000.0),
                 np.array([0.0] * 61 + [0.1] * 18 + [-0.2] * 117 + [1.0] * 74 + [-0.2] * 3
                          + [0.1] * 19 + [0.0] * 45), 0, 337, 1.0,
                 1.7296023471567848e-214)

# found by Hypothesis: the velocity lands exactly on the band's edge (-2 F_c h / J)
_TIE_CASE = (ModelValues(inertia=1.0, coulomb_friction=0.06251963495408494),
             np.array([2.0] * 7 + [-2.0] * 14 + [2.0] * 7 + [-2.0] * 7 + [2.0] * 14
                      + [-2.0] * 7 + [2.0] * 2), 0, 58, 0.0, 0.0)


@settings(max_examples=80, deadline=None)
@given(_cases())
@example(_TIE_CASE)
@example(_SURFACE_CASE)
def test_fast_path_equals_stepping_the_plant(case: tuple[ModelValues, np.ndarray, int, int,
                                                         float, float]) -> None:
    """simulate_torque (the compiled loop with friction and numba, else spans run as one
    linear recursion and the Plant stepped at the events only) gives the numbers of
    stepping the Plant call by call: free and in contact, with and without Coulomb
    friction, delays of whole samples, fractions and none, at rest or moving at the start,
    records that stick, reverse, break away, leave the contact. With friction the default
    (compiled) path is the reference bit for bit. The span method: sample by sample always;
    over the whole record unless the servo hits or leaves the environment (chaotic) or the
    reference passes a friction decision exactly at its threshold (a tie rounding takes)."""
    values, torque, start, stop, q0, v0 = case
    ref = _simulate_stepping(values, torque, PERIOD, start, stop, q0, v0)
    fast = simulate_torque(values, torque, PERIOD, start, stop, q0, v0)
    if values.coulomb_friction:            # the compiled loop: the Plant's own lines
        np.testing.assert_array_equal(fast[0], ref[0])
        np.testing.assert_array_equal(fast[1], ref[1])
    # the span method whatever "auto" chose
    spans = _simulate(values, torque, PERIOD, start, stop, q0, v0, 10, "spans")
    for got in (fast, spans):
        assert got[0][0] == pytest.approx(q0, abs=1e-15 + 1e-15 * abs(q0)) and got[1][0] == v0
        _assert_plant_steps(got, values, torque, start, stop)
        if not (_chaotic(values, ref)
                or _parted_at_a_tie(got, ref, values, torque, start, stop)):
            _assert_same(got, ref)


def test_the_tie_case_parts_by_one_friction_sub_step() -> None:
    """The tie above, pinned: the span method and the reference agree to rounding up to
    the tie and part there by two sub-steps of friction against each other
    (``2 F_c h / J`` in velocity, ``h = T / 10``) -- the size of a rounding-decided
    friction sign, nothing larger."""
    values, torque, start, stop, q0, v0 = _TIE_CASE
    ref = _simulate_stepping(values, torque, PERIOD, start, stop, q0, v0)
    spans = _simulate(values, torque, PERIOD, start, stop, q0, v0, 10, "spans")
    assert _parted_at_a_tie(spans, ref, values, torque, start, stop)
    # not an excuse for any other difference: the same states stepped to another value
    wrong = (ref[0].copy(), ref[1].copy())
    wrong[1][-1] += 1e-6
    assert not _parted_at_a_tie(wrong, ref, values, torque, start, stop)
    assert not _parted_at_a_tie(ref, ref, values, torque, start, stop)
    _assert_same((spans[0][:-1], spans[1][:-1]), (ref[0][:-1], ref[1][:-1]))
    band = 2 * values.coulomb_friction * (PERIOD / 10) / values.inertia
    assert abs(ref[1][-2]) == pytest.approx(band, rel=1e-12)
    assert abs(spans[1][-1] - ref[1][-1]) == pytest.approx(band, rel=1e-6)


@pytest.mark.parametrize("substeps", [1, 3, 10])
@pytest.mark.parametrize("style", ["prbs", "sines", "steps", "reverse"])
def test_fast_path_equals_stepping_for_other_substeps_and_long_records(substeps: int,
                                                                      style: str) -> None:
    """Long records (20 s: windows of every length, precomputed responses far from their
    start) with friction, in contact and out, and the sub-step count the caller chose."""
    n = 20_000
    for values, offset, q0 in (
            (ModelValues(inertia=0.25, viscous_friction=0.02, coulomb_friction=0.05,
                         delay=0.4e-3), 0.0, 0.3),
            (ModelValues(inertia=0.25, viscous_friction=0.02, coulomb_friction=0.05,
                         contact_position=0.0, stiffness=1e4, damping=50.0, delay=1.0e-3),
             1.0, 1.0e-4)):
        torque = _torque(style, n, 7, 0.5, offset)
        ref = _simulate_stepping(values, torque, PERIOD, 0, n, q0, 0.1, substeps=substeps)
        for method in ("spans", "compiled"):
            fast = _simulate(values, torque, PERIOD, 0, n, q0, 0.1, substeps, method)
            _assert_same(fast, ref)


def _count_plant_steps(monkeypatch: pytest.MonkeyPatch) -> list[int]:
    """``[n]``: how many times Plant.step is called from now on (the test counts work, not time)."""
    steps = [0]
    original = Plant.step

    def counting(self: Plant, torque_nm: float, dt: float) -> None:
        steps[0] += 1
        original(self, torque_nm, dt)

    monkeypatch.setattr(Plant, "step", counting)
    return steps


def test_the_span_method_does_not_step_the_plant_through_a_sliding_record(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """A free multisine with Coulomb friction: the Plant steps only the samples with an
    event (velocity reversals), a small part of the record -- the point of the fast path
    (counted, not timed)."""
    n = 20_000
    steps = _count_plant_steps(monkeypatch)
    values = ModelValues(inertia=0.25, viscous_friction=0.02, coulomb_friction=0.05)
    torque = _torque("sines", n, 3, 0.5, 0.0)
    pos, vel = _simulate(values, torque, PERIOD, 0, n, 0.0, 0.0, 10, "spans")
    reversals = int(np.count_nonzero(np.diff(np.sign(vel)) != 0))
    assert reversals > 10
    assert steps[0] <= 4 * reversals + 10 < n // 20


def _blas_threads() -> list[int]:
    return [lib["num_threads"] for lib in threadpool_info() if lib["user_api"] == "blas"]


def test_one_blas_thread_limits_nests_and_restores() -> None:
    """Inside one_blas_thread (and simulate_torque) every BLAS pool threadpoolctl sees has one
    thread; nested uses keep it; the outermost exit restores what was there before (two
    threads, set here so the test means something whatever OPENBLAS_NUM_THREADS says)."""
    with threadpool_limits(limits=2, user_api="blas"):
        _check_one_blas_thread()


def _check_one_blas_thread() -> None:
    before = _blas_threads()
    assert before and set(before) == {2}    # numpy's and scipy's OpenBLAS are loaded
    seen: list[list[int]] = []
    original = Plant.matrices

    def spying(self: Plant, dt: float) -> Any:
        seen.append(_blas_threads())
        return original(self, dt)

    with one_blas_thread():
        assert set(_blas_threads()) == {1}
        with one_blas_thread():
            assert set(_blas_threads()) == {1}
        assert set(_blas_threads()) == {1}
    assert _blas_threads() == before
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(Plant, "matrices", spying)
        simulate_torque(ModelValues(inertia=0.3, viscous_friction=0.123456), np.ones(10),
                        PERIOD, 0, 10, 0.0)
    assert seen and all(set(s) == {1} for s in seen)   # the ZOH ran on one thread
    assert _blas_threads() == before


@pytest.mark.parametrize("delay", [0.0, 0.4e-3, 1.0e-3])
@pytest.mark.parametrize("contact", [False, True])
def test_compiled_record_is_the_plant_bit_for_bit(delay: float, contact: bool,
                                                  monkeypatch: pytest.MonkeyPatch) -> None:
    """A record with Coulomb friction runs the Plant's own sub-step lines
    (coulomb_substeps) compiled: the Plant's numbers exactly, and Plant.step is never
    called (pressed PRBS: a reversal every few samples, the span method's worst case)."""
    assert _compiled_record() is not None       # numba is a core dependency
    n = 5000
    values = ModelValues(inertia=0.25, viscous_friction=0.02, coulomb_friction=0.05,
                         delay=delay)
    q0 = 0.2
    if contact:
        values = dataclasses.replace(values, contact_position=0.2, stiffness=1e4,
                                     damping=50.0)
        q0 = 0.2 + 1e-4
    torque = _torque("prbs", n, 5, 0.5, 1.0 if contact else 0.0)
    ref = _simulate_stepping(values, torque, PERIOD, 0, n, q0, 0.0)
    steps = _count_plant_steps(monkeypatch)
    fast = simulate_torque(values, torque, PERIOD, 0, n, q0, 0.0)
    assert steps[0] == 0
    np.testing.assert_array_equal(fast[0], ref[0])
    np.testing.assert_array_equal(fast[1], ref[1])
