"""The DOb/RTOb force controller as the runtime executes it, one call per sample.

It runs the sampled controller of :func:`dobhil.synthesis.controller.sampled_controller`
-- the one source of the observer matrices -- and nothing else. Per sample, with
``y = [q, dq]`` (or ``[q]`` when the velocity is estimated from the position)::

    [tau_dis^, tau_int^] = C xi + D_y y
    tau_per  = C_f (tau_ref - tau_int^)
    u_unsat  = tau_per + tau_dis^
    u        = clip(u_unsat, -limit, +limit)      (loop.torque_limit)
    xi      <- A xi + B_y y + B_u u               (the *applied* torque)

In torque mode (``loop.mode: torque``, open loop for identification) the same
observers run, but the command is the reference itself::

    tau_per  = 0
    u_unsat  = tau_ref
    u        = clip(tau_ref, -limit, +limit)

so the recorded estimates stay meaningful and replay rebuilds the run the same way.

The outputs do not depend on ``u`` (no direct feedthrough), so saturation needs
no algebraic loop, and feeding the saturated torque keeps the observers
consistent with what the drive applies. The identified-disturbance input
``B_i tau_i`` of the analysis is zero at run time (tau_i is not measured).

Speed. The matrices are small (order 2 to 7), where numpy's per-call overhead
dominates: a preallocated-buffer version with ``np.dot(..., out=)`` measured
about 2 us per step, row-wise ``sum(map(mul, row, v))`` on Python floats about
1.5 us, and straight-line scalar code about 0.3 us. The controller therefore
*generates* that straight-line code from the matrices once, at construction:
each coefficient is written with ``repr`` (which round-trips a float exactly),
zero coefficients are left out (adding ``0.0 * x`` changes nothing but the sign
of a zero), and the sums run left to right over ``[xi, y, u]``. The matrices are
still the synthesis' ones, bit for bit; :attr:`ForceController.source` shows the
code. Same inputs give bit-identical outputs, which replay relies on.

Start-up (:meth:`ForceController.initialize`): the fixed point of the observer for
a constant measurement and zero torque, ``xi = (I - A)^-1 B_y y``. For the
auxiliary-variable observers this is ``sigma = L x`` -- zero estimates -- and
for the velocity filter ``z = q``; it is the same for the ZOH and the Euler
discretisation (both have the continuous fixed point ``-A_c^-1 B_c y``). So a
loop started at any position does not kick.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from dobhil.config.schema import Config
from dobhil.errors import SynthesisError
from dobhil.synthesis.controller import DIS, INT, ControllerSS, sampled_controller
from dobhil.synthesis.params import params_from_config

__all__ = ["ControlOutput", "ForceController"]


class ControlOutput(NamedTuple):
    """What one control cycle computed (immutable; a NamedTuple because it is cheap)."""

    tau_ref: float      # interaction torque reference [N m]
    tau_int_hat: float  # RTOb estimate of the interaction torque [N m]
    tau_dis_hat: float  # DOb estimate of the disturbance torque [N m]
    tau_per: float      # performance torque C_f (tau_ref - tau_int^) [N m]
    u_unsat: float      # commanded torque before saturation [N m]
    u: float            # commanded torque after saturation (applied, fed back) [N m]


Kernel = Callable[[list[float], float, float, float], ControlOutput]


class ForceController:
    """Executes a sampled :class:`ControllerSS` (one design, batch shape ``()``)."""

    def __init__(self, ss: ControllerSS, *, torque_limit: float, open_loop: bool = False) -> None:
        if ss.dt is None:
            raise ValueError("ForceController needs a sampled controller (sampled_controller)")
        if ss.a.ndim != 2:
            raise ValueError(f"ForceController runs one design, got batch shape {ss.a.shape[:-2]}")
        if not torque_limit > 0:
            raise ValueError(f"torque_limit: expected > 0 N m, got {torque_limit}")
        self.ss = ss
        self.period = float(ss.dt)
        self.torque_limit = float(torque_limit)
        self.force_gain = float(ss.force_gain)
        self.order = ss.order
        self.measures_velocity = bool(ss.measures_velocity)
        #: torque mode: the reference is the torque command (see the module docstring)
        self.open_loop = bool(open_loop)
        self._init_map = _fixed_point_map(ss)
        self.source = _kernel_source(ss, self.force_gain, self.torque_limit, self.open_loop)
        self._kernel = _compile(self.source)
        self._xi: list[float] = [0.0] * self.order

    @classmethod
    def from_config(cls, config: Config) -> ForceController:
        """The controller of ``config.design`` at ``config.loop.period``, saturated at
        ``config.loop.torque_limit``, open loop when ``config.loop.mode`` is torque."""
        return cls(sampled_controller(params_from_config(config)),
                   torque_limit=config.loop.torque_limit, open_loop=config.loop.mode == "torque")

    def step(self, q: float, dq: float | None, tau_ref: float) -> ControlOutput:
        """One sample: outputs from the current state, then the state update."""
        if dq is None:
            if self.measures_velocity:
                raise ValueError("this controller measures the velocity: dq must be given")
            dq = 0.0
        return self._kernel(self._xi, float(q), float(dq), float(tau_ref))

    def reset(self) -> None:
        """Observer state to zero."""
        self._xi[:] = [0.0] * self.order

    def initialize(self, q: float, dq: float | None = 0.0) -> None:
        """Observer at rest at ``y``: the fixed point ``(I - A)^-1 B_y y`` (zero estimates
        for ``dq = 0``; ``dq`` is ignored when the velocity is estimated)."""
        y = [float(q), 0.0 if dq is None else float(dq)][:self._init_map.shape[1]]
        self._xi[:] = (self._init_map @ np.asarray(y, dtype=float)).tolist()

    @property
    def state(self) -> NDArray[np.float64]:
        """A copy of the observer state xi."""
        return np.array(self._xi, dtype=float)

    def load_state(self, xi: Sequence[float] | NDArray[np.float64]) -> None:
        """Set the observer state (e.g. to resume a recorded run)."""
        values = [float(v) for v in np.asarray(xi, dtype=float).reshape(-1)]
        if len(values) != self.order:
            raise ValueError(f"state: expected {self.order} values, got {len(values)}")
        self._xi[:] = values


def _fixed_point_map(ss: ControllerSS) -> NDArray[np.float64]:
    """``(I - A)^-1 B_y``: the state at rest for a constant measurement and u = 0."""
    n = ss.order
    try:
        return np.asarray(np.linalg.solve(np.eye(n) - ss.a, ss.b_y), dtype=np.float64)
    except np.linalg.LinAlgError:
        raise SynthesisError("sampled observer has a pole at z = 1: no state at rest") from None


def _kernel_source(ss: ControllerSS, force_gain: float, limit: float,
                   open_loop: bool = False) -> str:
    """Straight-line Python for one sample of ``ss`` (see the module docstring)."""
    n, m = ss.order, ss.b_y.shape[-1]
    for name in ("a", "b_y", "b_u", "c", "d_y"):
        if not np.all(np.isfinite(getattr(ss, name))):
            raise SynthesisError(f"controller matrix {name} is not finite")
    xs = [f"x{i}" for i in range(n)]
    ys = ["q", "dq"][:m]
    out = np.concatenate([ss.c, ss.d_y], axis=1)
    upd = np.concatenate([ss.a, ss.b_y, ss.b_u], axis=1)
    lines = ["def kernel(s, q, dq, r):"]
    if n:
        lines.append(f"    {', '.join(xs)}, = s")
    lines.append(f"    dis = {_dot(out[DIS], xs + ys)}")
    lines.append(f"    itn = {_dot(out[INT], xs + ys)}")
    if open_loop:  # torque mode: the reference is the command, no force feedback
        lines.append("    per = 0.0")
        lines.append("    uu = r")
    else:
        lines.append(f"    per = {float(force_gain)!r} * (r - itn)")
        lines.append("    uu = per + dis")
    lines.append(f"    u = {limit!r} if uu > {limit!r} else ({-limit!r} if uu < {-limit!r} else uu)")
    if n:
        rows = ", ".join(_dot(row, xs + ys + ["u"]) for row in upd)
        lines.append(f"    s[:] = ({rows},)")
    lines.append("    return Out(r, itn, dis, per, uu, u)")
    return "\n".join(lines) + "\n"


def _dot(row: NDArray[np.float64], names: list[str]) -> str:
    terms = [f"{float(c)!r} * {v}" for c, v in zip(row, names) if c != 0.0]
    return " + ".join(terms) if terms else "0.0"


def _compile(source: str) -> Kernel:
    namespace: dict[str, object] = {"Out": ControlOutput}
    exec(compile(source, "<dobhil.runtime.controller kernel>", "exec"), namespace)
    kernel: Kernel = namespace["kernel"]  # type: ignore[assignment]
    return kernel
