"""Synthetic force runs for the closed-loop identification tests: the runtime's controller
(:func:`dobhil.runtime.session.build_controller`, stepped as the runtime steps it) in closed
loop with the emulator's Plant (quantised encoder, noisy velocity), each command applied
``delay`` after the sample it was computed from -- an event queue as in
tests/identify/synthetic.py, written independently of dobhil.identify.closedloop's kernel.
Far faster than a lockstep emulated run (no bus), so fifty seeded records fit in a test."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from types import MappingProxyType

import numpy as np

from dobhil.config.load import load_config
from dobhil.drives.load import load_profile
from dobhil.emulator.plant import Plant
from dobhil.identify.closedloop import LoopModel, LoopRecord
from dobhil.runtime.session import build_controller

PERIOD = 1e-3


@dataclass(frozen=True)
class Hidden:
    """The plant the record hides (the issue's example) and the sensor."""

    inertia: float = 0.37
    viscous_friction: float = 0.05
    stiffness: float = 15000.0
    damping: float = 60.0
    contact_position: float = 0.0
    delay: float = 0.3e-3
    counts: int = 2 ** 14
    velocity_noise: float = 0.05


#: the demo's force run, its design with J_mi = J_mn (the torque then depends on the measured
#: velocity: the closed loop feeds the noise back), torque limits with room for that noise,
#: the design's own delay the hidden one
SETS = ("design.identified_inertia=0.25", "loop.torque_limit=20", "plant.torque_limit=20")


def chirp(n: int, f0: float, f1: float, offset: float, amplitude: float) -> np.ndarray:
    t = np.arange(n) * PERIOD
    span = t[-1] or 1.0
    return offset + amplitude * np.sin(2 * np.pi * (f0 * t + (f1 - f0) * t ** 2 / (2 * span)))


def config(hidden: Hidden, *extra: str) -> object:
    return load_config("demo", overrides=(*SETS, f"design.input_delay={hidden.delay}",
                                          f"sensor.encoder_resolution={hidden.counts}", *extra))


def record(hidden: Hidden, seed: int, reference: np.ndarray, *extra: str) -> LoopRecord:
    """One force run of ``reference`` [N m per sample] on ``hidden``, noise seeded by ``seed``."""
    cfg = config(hidden, *extra)
    # the shipped profile clamps at 2 N m; the noise this loop feeds back needs room
    profile = dataclasses.replace(load_profile(cfg.drive.profile), torque_limit=20.0)  # type: ignore[attr-defined]
    ctrl = build_controller(cfg, profile)  # type: ignore[arg-type]
    start = float(cfg.plant.initial_position)  # type: ignore[attr-defined]
    plant = Plant(inertia=hidden.inertia, viscous_friction=hidden.viscous_friction,
                  stiffness=hidden.stiffness, damping=hidden.damping,
                  contact_position=hidden.contact_position, initial_position=start,
                  encoder_resolution=hidden.counts, velocity_noise=hidden.velocity_noise,
                  seed=seed, torque_limit=20.0)
    initial = (plant.position, plant.velocity)
    ctrl.initialize(*initial)
    n = len(reference)
    rows = np.empty((n, 3))
    pending: list[tuple[float, float]] = []
    held, now = 0.0, 0.0
    for k in range(n):
        q, dq = plant.position, plant.velocity
        u = ctrl.step(q, dq, float(reference[k])).u
        rows[k] = (q, dq, u)
        pending.append((k * PERIOD + hidden.delay, u))
        end = (k + 1) * PERIOD
        while pending and pending[0][0] < end - 1e-12:
            at, w = pending.pop(0)
            if at - now > 1e-12:
                plant.step(held, round(at - now, 12))
                now = at
            held = w
        plant.step(held, round(end - now, 12))
        now = end
    recorded = {k: float(v) for k, v in cfg.flat().items()  # type: ignore[attr-defined]
                if k.split(".")[0] == "design" and isinstance(v, (int, float)) and not isinstance(v, bool)}
    return LoopRecord(model=LoopModel.of(ctrl, cfg), reference=np.asarray(reference, float),
                      position=rows[:, 0], velocity=rows[:, 1], torque=rows[:, 2], initial=initial,
                      source="", mode="force", recorded=MappingProxyType(recorded))


def count(hidden: Hidden) -> float:
    return 2 * math.pi / hidden.counts
