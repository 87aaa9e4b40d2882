"""The model the identification fits: the emulator's plant itself, driven as the emulator
drives it.

No second discretisation: a simulation builds a :class:`dobhil.emulator.plant.Plant` (whose
ZOH matrices come from :func:`dobhil.synthesis.models.servo_matrices` /
:func:`~dobhil.synthesis.models.plant_matrices` and
:func:`dobhil.synthesis.controller.discretize`, Coulomb friction sub-stepped with its
Karnopp band) and steps it the way the emulator's lockstep drive applies a command
``latency`` after the sample it was computed from: with the delay ``d T + tau``
(``d = design.delay_samples`` whole periods, ``0 <= tau < T`` = ``design.input_delay``)
the interval ``[t_k, t_k+1]`` holds ``u[k-d-1]`` over ``[t_k, t_k + tau]`` and ``u[k-d]``
over the rest -- the sampled analysis' ``x[k+1] = Phi x[k] + Gamma0 u[k-d] +
Gamma1 u[k-d-1]`` (:func:`dobhil.synthesis.controller.discretize_delayed`) whenever the
plant is linear.

The torque reaching the plant is ``torque_gain * u`` (the sent torque scaled). Commands
before the first sample are 0 and every simulation starts at its initial position and
velocity (:meth:`Plant.set_state`; a segment need not start at rest).
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass

import numpy as np

from dobhil.emulator.plant import Plant

__all__ = ["ModelValues", "simulate_torque", "split_delay"]

#: a delay fraction below this is no fraction (the emulator rounds its pieces to 1e-12 s too)
_TINY = 1e-12


def split_delay(delay: float, period: float) -> tuple[int, float]:
    """``(whole, fraction)`` of ``delay`` as ``design.delay_samples`` and
    ``design.input_delay`` model it: ``delay = whole * period + fraction``, ``0 <= fraction
    < period`` (a fraction within 1e-12 s of a whole period counts as the next whole one)."""
    if not delay >= 0.0:
        raise ValueError(f"delay: expected >= 0 s, got {delay}")
    whole = math.floor(delay / period)
    fraction = delay - whole * period
    if fraction >= period - _TINY:
        whole, fraction = whole + 1, 0.0
    return whole, max(fraction, 0.0)


@dataclass(frozen=True)
class ModelValues:
    """One set of plant parameters (SI units). With ``stiffness = damping = 0`` and the
    contact position out of reach the plant is the free servo."""

    inertia: float
    viscous_friction: float = 0.0
    coulomb_friction: float = 0.0
    torque_gain: float = 1.0
    contact_position: float = math.inf
    stiffness: float = 0.0
    damping: float = 0.0
    delay: float = 0.0


_LOCAL = threading.local()


def _plant(inertia: float, viscous: float, coulomb: float, stiffness: float, damping: float,
           substeps: int) -> Plant:
    """A Plant of these parameters, the last one reused (per thread): the segments of one
    fit evaluation share it, so its ZOH matrices (matrix exponentials: ~10 ms each on a busy
    machine with multithreaded BLAS, measured) are computed once per parameter set and
    delay, not once per segment. Its contact and initial positions are set by the caller."""
    key = (inertia, viscous, coulomb, stiffness, damping, substeps)
    cached: tuple[tuple[float, ...], Plant] | None = getattr(_LOCAL, "plant", None)
    if cached is not None and cached[0] == key:
        return cached[1]
    plant = Plant(inertia=inertia, viscous_friction=viscous, coulomb_friction=coulomb,
                  stiffness=stiffness, damping=damping, substeps=substeps)
    _LOCAL.plant = (key, plant)
    return plant


def simulate_torque(values: ModelValues, torque: np.ndarray, period: float, start: int,
                    stop: int, initial_position: float, initial_velocity: float = 0.0, *,
                    substeps: int = 10) -> tuple[np.ndarray, np.ndarray]:
    """True position and velocity at samples ``start .. stop-1`` of the plant ``values``
    driven by the sent torques ``torque`` (the whole record: commands sent before
    ``start`` still in transit act too), starting at ``initial_position`` with
    ``initial_velocity`` at sample ``start``."""
    return _simulate_stepping(values, torque, period, start, stop, initial_position,
                              initial_velocity, substeps=substeps)


def _simulate_stepping(values: ModelValues, torque: np.ndarray, period: float, start: int,
                       stop: int, initial_position: float, initial_velocity: float = 0.0, *,
                       substeps: int = 10) -> tuple[np.ndarray, np.ndarray]:
    """:func:`simulate_torque` by stepping the emulator's Plant call by call: the reference
    the fast path must equal (kept so the equality is tested for ever)."""
    n = stop - start
    if n < 1:
        raise ValueError(f"segment [{start}, {stop}): empty")
    # no environment: the emulator's plant has no contact position "nowhere", but with zero
    # stiffness and damping its contact mode is the free servo itself (plant_matrices with
    # K = D = 0 is servo_matrices), so the contact goes where the servo starts -- its state is
    # relative to the contact position, and a far one would cost that state its precision
    qc, k, d = values.contact_position, values.stiffness, values.damping
    if not math.isfinite(qc):
        qc, k, d = initial_position, 0.0, 0.0
    plant = _plant(values.inertia, values.viscous_friction, values.coulomb_friction, k, d,
                   substeps)
    plant.contact_position = qc
    plant.set_state(initial_position, initial_velocity)
    whole, fraction = split_delay(values.delay, period)
    g = values.torque_gain
    pad = whole + 1
    # u[i] for i >= start - pad: zeros before the record, the gain applied once
    first = start - pad
    lead = [0.0] * max(0, -first)
    applied = lead + (g * np.asarray(torque[max(first, 0):stop], float)).tolist()
    rest = period - fraction
    pos = np.empty(n)
    vel = np.empty(n)
    pos[0], vel[0] = plant.true_position, plant.true_velocity
    step = plant.step
    late = fraction > _TINY
    # applied[j] is u[first + j]; in [t_k, t_k+1] u[k-whole-1] then u[k-whole] act
    for j in range(n - 1):
        k = start + j
        i = k - whole - first      # index of u[k - whole]
        if late:
            step(applied[i - 1], fraction)
        step(applied[i], rest)
        pos[j + 1] = plant.true_position
        vel[j + 1] = plant.true_velocity
    return pos, vel
