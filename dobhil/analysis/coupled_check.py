"""The coupled loop built a second way, with python-control, to check :mod:`dobhil.analysis.coupled`.

Nothing here reuses the assembly of :mod:`dobhil.synthesis.loop` or of the coupled loop:
each axis is three python-control systems joined by signal name with
``control.interconnect`` -- its observers (the matrices of
:func:`~dobhil.synthesis.controller.sampled_controller` or
:func:`~dobhil.synthesis.controller.continuous_controller` as ``control.ss``, inputs the
measurement and the applied torque), its force law ``u = tau_dis^ + C_f (tau_ref - tau_int^) +
tau_per`` (a static system) and, sampled, ``delay_samples`` unit delays -- and the plant is one
system written from the mechanics, ``J q'' + (b + D_env) q' + K_env q = u + sum of the
couplings' pushes``, in the coordinates ``[q_1 .. q_N, dq_1 .. dq_N]`` (the coupled loop keeps
``[q_i, dq_i]`` per axis), sampled by ``control.sample_system`` (zero-order hold).

A fractional ``design.input_delay`` moves the command within the period; python-control
samples a held input only at the sample instants, so the check covers whole-sample delays
(``input_delay = 0``) and says so otherwise (:class:`CheckUnavailable`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import control
import numpy as np
import scipy.linalg

from dobhil.analysis.coupled import AxisDesign, CoupledLoop
from dobhil.config.axes import Coupling
from dobhil.errors import AnalysisError
from dobhil.synthesis.controller import continuous_controller, sampled_controller

__all__ = ["CheckUnavailable", "LoopCheck", "check_loop", "interconnected_loop"]


class CheckUnavailable(AnalysisError):
    """The python-control check cannot build this loop (a fractional input delay)."""


def _plant(designs: Sequence[AxisDesign], couplings: Sequence[Coupling], dt: float | None) -> control.StateSpace:
    """The mechanics in second-order form: ``M q'' + Dm q' + Km q = u``."""
    names = [d.name for d in designs]
    n = len(designs)
    mass = np.diag([float(d.params.value("inertia")) for d in designs])
    stiff = np.diag([float(d.params.value("stiffness")) for d in designs])
    damp = np.diag([float(d.params.value("damping")) for d in designs])
    friction = np.diag([float(d.params.value("viscous_friction")) for d in designs])
    for cp in couplings:
        e = np.zeros(n)
        e[names.index(cp.a)], e[names.index(cp.b)] = 1.0, -1.0
        stiff = stiff + cp.stiffness * np.outer(e, e)   # a spring between two positions
        damp = damp + cp.damping * np.outer(e, e)
    inv = np.linalg.inv(mass)
    a = np.block([[np.zeros((n, n)), np.eye(n)], [-inv @ stiff, -inv @ (friction + damp)]])
    b = np.vstack([np.zeros((n, n)), inv])
    c = np.vstack([np.eye(2 * n), np.hstack([stiff, damp])])   # q, dq, then the reaction torques
    outputs = [f"q{i}" for i in range(n)] + [f"dq{i}" for i in range(n)] + [f"tauint{i}" for i in range(n)]
    plant = control.ss(a, b, c, np.zeros((3 * n, n)), inputs=[f"u{i}" for i in range(n)],
                       outputs=outputs, name="plant")
    if dt is None:
        return plant
    return control.sample_system(plant, dt, method="zoh", name="plant_sampled")


def _axis_systems(i: int, design: AxisDesign, sampled: bool) -> list[control.StateSpace]:
    ctrl = sampled_controller(design.params) if sampled else continuous_controller(design.params)
    dt = ctrl.dt or 0
    measured = [f"q{i}", f"dq{i}"][:ctrl.b_y.shape[-1]]
    delay = design.params.structure.delay_samples if sampled else 0
    command = f"cmd{i}" if delay else f"u{i}"
    # the observers are fed the command as the controller computes it (the runtime knows
    # no other); the plant gets it ``delay`` periods later
    observers = control.ss(ctrl.a, np.hstack([ctrl.b_y, ctrl.b_u]), ctrl.c,
                           np.hstack([ctrl.d_y, np.zeros((2, 1))]), dt,
                           inputs=[*measured, command], outputs=[f"dis{i}", f"hat{i}"], name=f"observers_{i}")
    cf = float(design.params.value("force_gain"))
    law = control.ss(np.zeros((0, 0)), np.zeros((0, 4)), np.zeros((2, 0)),
                     np.array([[1.0, -cf, cf, 1.0], [1.0, -cf, cf, 1.0]]), dt,
                     inputs=[f"dis{i}", f"hat{i}", f"ref{i}", f"per{i}"],
                     outputs=[command, f"law{i}"], name=f"force_law_{i}")
    systems = [observers, law]
    if delay:
        shift = control.ss(control.tf([1.0], [1.0] + [0.0] * delay, dt))
        systems.append(control.ss(shift.A, shift.B, shift.C, shift.D, dt, inputs=[command],
                                  outputs=[f"u{i}"], name=f"delay_{i}"))
    return systems


def interconnected_loop(designs: Sequence[AxisDesign], couplings: Sequence[Coupling], *,
                        sampled: bool) -> control.StateSpace:
    """The coupled closed loop by ``control.interconnect``: inputs ``ref<i>, per<i>``,
    outputs ``hat<i>, tauint<i>, q<i>, law<i>`` per axis ``i`` (the order of
    :data:`~dobhil.analysis.coupled.AXIS_INPUTS` / ``AXIS_OUTPUTS``)."""
    if sampled and any(d.params.structure.input_delay > 0 for d in designs):
        raise CheckUnavailable("the python-control check covers whole-sample delays only "
                               "(design.input_delay = 0)")
    dt = float(designs[0].params.period) if sampled else None
    systems = [_plant(designs, couplings, dt)]
    for i, d in enumerate(designs):
        systems += _axis_systems(i, d, sampled)
    n = len(designs)
    inputs = [s for i in range(n) for s in (f"ref{i}", f"per{i}")]
    outputs = [s for i in range(n) for s in (f"hat{i}", f"tauint{i}", f"q{i}", f"law{i}")]
    return control.interconnect(systems, inplist=inputs, outlist=outputs, inputs=inputs,
                                outputs=outputs, name="coupled_check", check_unused=False)


@dataclass(frozen=True)
class LoopCheck:
    """How far the two constructions differ: the closed-loop poles (each pole of one
    matched to the nearest of the other, relative to ``max(1, |pole|)``) and the step
    responses of every output to every axis' reference (relative to the largest value)."""

    pole_error: float
    step_error: float
    samples: int

    def agrees(self, tol: float = 1e-9) -> bool:
        return self.pole_error <= tol and self.step_error <= tol

    def text(self) -> str:
        return (f"independent check (python-control interconnect): closed-loop poles agree to "
                f"{self.pole_error:.1e}, step responses to {self.step_error:.1e} ({self.samples} samples)")


def _pole_error(p: np.ndarray, q: np.ndarray) -> float:
    """Largest distance from a pole of either set to the nearest of the other."""
    dist = np.abs(p[:, None] - q[None, :]) / np.maximum(1.0, np.abs(p))[:, None]
    return float(max(dist.min(axis=1).max(), dist.min(axis=0).max()))


def _responses(a: np.ndarray, b: np.ndarray, c: np.ndarray, d: np.ndarray, sampled: bool,
               step: float, count: int) -> np.ndarray:
    """Unit-step responses (count, outputs, inputs) sampled every ``step`` (exact
    zero-order-hold propagation, continuous or sampled)."""
    if sampled:
        phi, gam = a, b
    else:
        n, m = a.shape[0], b.shape[1]
        block = np.zeros((n + m, n + m))
        block[:n, :n], block[:n, n:] = a * step, b * step
        e = scipy.linalg.expm(block)
        phi, gam = e[:n, :n], e[:n, n:]
    x = np.zeros((a.shape[0], b.shape[1]))
    out = np.empty((count, c.shape[0], b.shape[1]))
    for k in range(count):
        out[k] = c @ x + d
        x = phi @ x + gam
    return out


def _continuous_step(poles: np.ndarray, samples: int) -> float:
    """A time step whose ``samples`` span 10 time constants of the slowest nonzero pole."""
    moving = np.abs(poles[np.abs(poles) > 1e-9])
    slowest = float(moving.min()) if moving.size else 1.0
    return 10.0 / max(1e-3, slowest) / samples


def check_loop(lp: CoupledLoop, designs: Sequence[AxisDesign], couplings: Sequence[Coupling],
               samples: int = 400) -> LoopCheck:
    """Compare ``lp`` (:func:`~dobhil.analysis.coupled.coupled_loop`) with
    :func:`interconnected_loop`: poles, and ``samples`` steps of every reference's unit step
    (sampled: every period; continuous: 400 points over 10 / |slowest pole|)."""
    ref = interconnected_loop(designs, couplings, sampled=lp.sampled)
    a, b, c, d = (np.asarray(m, float) for m in (ref.A, ref.B, ref.C, ref.D))
    poles = np.linalg.eigvals(a)
    step = lp.dt or _continuous_step(lp.poles(), samples)
    mine = _responses(lp.a, lp.b, lp.c, lp.d, lp.sampled, step, samples)
    theirs = _responses(a, b, c, d, lp.sampled, step, samples)
    scale = max(1e-300, float(np.max(np.abs(mine))))
    return LoopCheck(pole_error=_pole_error(lp.poles(), poles),
                     step_error=float(np.max(np.abs(mine - theirs))) / scale, samples=samples)
