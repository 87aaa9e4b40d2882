"""Synthetic records for the identification tests: the emulator's Plant (quantised encoder,
noisy velocity, Coulomb friction) driven the way the emulator's lockstep drive applies
commands -- each one ``delay`` after the sample it was computed from (an event queue here,
written independently of dobhil.identify.model's index arithmetic)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from dobhil.emulator.plant import Plant
from dobhil.identify.data import IdentData, Segment

PERIOD = 1e-3
COUNTS = 2 ** 14                 # encoder counts per revolution
COUNT = 2 * math.pi / COUNTS     # [rad]
PRELOAD = 20.0                   # [N m] the contact run's mean torque


@dataclass(frozen=True)
class Truth:
    inertia: float = 0.25
    viscous_friction: float = 0.5
    coulomb_friction: float = 0.3
    stiffness: float = 1.0e4
    damping: float = 50.0
    # off a count, as a real one is: the quantised first sample of a pressed segment is
    # then up to half a count off its true position (K * count / 2 ~ 2 N m of spring)
    contact_position: float = 400.37 * COUNT
    delay: float = 1.3e-3
    velocity_noise: float = 0.01


def multisine(n: int, amplitude: float, band: tuple[float, float], lines: int,
              rng: np.random.Generator) -> np.ndarray:
    """Random-phase multisine, ``lines`` log-spaced frequencies in ``band``, peak ~``amplitude``."""
    t = np.arange(n) * PERIOD
    f = np.geomspace(*band, lines)
    x = np.sum(np.sin(2 * np.pi * f[:, None] * t + rng.uniform(0, 2 * np.pi, lines)[:, None]), axis=0)
    return amplitude * x / np.max(np.abs(x))


def prbs(n: int, amplitude: float, clock: int, rng: np.random.Generator) -> np.ndarray:
    """Random binary torque +-``amplitude``, a new coin every ``clock`` samples (PRBS-like:
    its steps excite the delay and the inertia over the whole band)."""
    bits = rng.integers(0, 2, -(-n // clock)) * 2.0 - 1.0
    return amplitude * np.repeat(bits, clock)[:n]


def run(truth: Truth, torque: np.ndarray, initial_position: float, seed: int,
        **unmodelled: Any) -> tuple[np.ndarray, np.ndarray]:
    """Measured position and velocity at each sample of a run sending ``torque``
    (``unmodelled``: more Plant options, a disturbance say)."""
    plant = Plant(**unmodelled, inertia=truth.inertia, viscous_friction=truth.viscous_friction,
                  coulomb_friction=truth.coulomb_friction, stiffness=truth.stiffness,
                  damping=truth.damping, contact_position=truth.contact_position,
                  initial_position=initial_position, encoder_resolution=COUNTS,
                  velocity_noise=truth.velocity_noise, seed=seed)
    n = len(torque)
    pos, vel = np.empty(n), np.empty(n)
    pending: list[tuple[float, float]] = []    # (time it acts from, torque)
    held, now = 0.0, 0.0
    for k in range(n):
        pos[k], vel[k] = plant.position, plant.velocity
        pending.append((k * PERIOD + truth.delay, float(torque[k])))
        end = (k + 1) * PERIOD
        while pending and pending[0][0] < end - 1e-12:
            at, u = pending.pop(0)
            if at - now > 1e-12:
                plant.step(held, round(at - now, 12))
                now = at
            held = u
        plant.step(held, round(end - now, 12))
        now = end
    return pos, vel


def record(truth: Truth, seed: int, *, free_s: float = 2.0, contact_s: float = 1.5,
           rest: int = 20, free_amplitude: float = 3.0,
           **unmodelled: Any) -> tuple[IdentData, tuple[Segment, ...]]:
    """A free-motion run far from the contact, then (if ``contact_s``) a run pressed into
    the environment -- starting at rest about where the spring balances the pre-load
    :data:`PRELOAD` its torque swings around (an off-count position, as in a real
    record); each ends with ``rest`` samples of zero torque, so the next one's history
    is zeros, as the model assumes."""
    rng = np.random.default_rng(seed)
    parts = []
    if free_s:
        nf = int(round(free_s / PERIOD))
        uf = np.concatenate([prbs(nf, free_amplitude, 15, rng), np.zeros(rest)])
        qf, vf = run(truth, uf, truth.contact_position - 50.0, seed, **unmodelled)
        parts.append((uf, qf, vf, "free"))
    if contact_s:
        nc = int(round(contact_s / PERIOD))
        uc = np.concatenate([PRELOAD + prbs(nc, 8.0, 5, rng), np.zeros(rest)])
        # where the spring balances the pre-load, moved by up to half a count: each seed
        # has its own quantisation error of the first sample, as real records do
        pressed = (truth.contact_position + PRELOAD / truth.stiffness
                   + rng.uniform(-0.5, 0.5) * COUNT)
        qc, vc = run(truth, uc, pressed, seed + 10_000, **unmodelled)
        parts.append((uc, qc, vc, "contact"))
    return joined(parts)


def joined(parts: list[tuple[np.ndarray, np.ndarray, np.ndarray, str]]
           ) -> tuple[IdentData, tuple[Segment, ...]]:
    """One record of runs ``(torque, position, velocity, kind)`` one after the other."""
    segments, k = [], 0
    for u, _, _, kind in parts:
        segments.append(Segment(start=k, stop=k + len(u), kind=kind))
        k += len(u)
    torque = np.concatenate([p[0] for p in parts])
    data = IdentData(period=PERIOD, t=np.arange(len(torque)) * PERIOD, torque=torque,
                     position=np.concatenate([p[1] for p in parts]),
                     velocity=np.concatenate([p[2] for p in parts]), source="",
                     protocol="odrive", recorded={})
    return data, tuple(segments)
