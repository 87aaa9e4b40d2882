"""Transfer functions of Eqs. (25)-(27) from the state space, as python-control objects.

Every function takes a single design (batch shape ``()``) and returns
``control.StateSpace`` systems with named signals, continuous or sampled
(``dt = loop.period``), so users can go on with ``control.bode_plot``,
``control.margin``, ``control.feedback`` and the rest.
"""

from __future__ import annotations

from dataclasses import dataclass

import control
import numpy as np

from dobhil.synthesis.loop import LoopSS, loop
from dobhil.synthesis.params import Params, VelocitySource

#: name -> (input, output, at C_f (True) or open loop (False))
TRANSFER_FUNCTIONS: dict[str, tuple[str, str, bool]] = {
    "open_loop": ("tau_per", "tau_int_hat", False),          # L, Eq. (26)
    "open_loop_disturbance": ("tau_du", "tau_int_hat", False),
    "open_loop_identified": ("tau_i", "tau_int_hat", False),
    "open_loop_noise_dq": ("eta_dq", "tau_int_hat", False),
    "closed_loop": ("tau_ref", "tau_int_hat", True),          # C_f L / (1 + C_f L), Eq. (27)
    "force": ("tau_ref", "tau_int", True),                    # reference -> true interaction
    "disturbance": ("tau_du", "tau_int_hat", True),
    "disturbance_force": ("tau_du", "tau_int", True),
    "identified_disturbance": ("tau_i", "tau_int_hat", True),
    "noise_q": ("eta_q", "tau_int_hat", True),
    "noise_dq": ("eta_dq", "tau_int_hat", True),
    "noise_q_force": ("eta_q", "tau_int", True),
    "noise_dq_force": ("eta_dq", "tau_int", True),
}


@dataclass(frozen=True)
class LoopSystems:
    """The open loop (C_f = 0) and closed loop (C_f of the design) of one design."""

    open: LoopSS
    closed: LoopSS
    measures_velocity: bool

    @classmethod
    def build(cls, params: Params, *, sampled: bool) -> LoopSystems:
        if params.batch_shape != ():
            raise ValueError("transfer functions are built for a single design")
        measured = params.structure.velocity_source is VelocitySource.MEASURED
        return cls(open=loop(params, sampled=sampled, force_gain=0.0),
                   closed=loop(params, sampled=sampled), measures_velocity=measured)

    def system(self, name: str) -> control.StateSpace:
        inp, out, closed = TRANSFER_FUNCTIONS[name]
        if inp == "eta_dq" and not self.measures_velocity:
            raise KeyError(f"{name}: no velocity measurement noise when the velocity is estimated")
        a, b, c, d = (self.closed if closed else self.open).siso(inp, out)
        dt = self.closed.dt if self.closed.dt is not None else 0
        return control.ss(a, b, c, d, dt, inputs=[inp], outputs=[out], name=name)

    def all_systems(self) -> dict[str, control.StateSpace]:
        out = {}
        for name in TRANSFER_FUNCTIONS:
            try:
                out[name] = self.system(name)
            except KeyError:
                continue
        return out


def as_tf(sys: control.StateSpace) -> control.TransferFunction:
    """Minimal transfer function of a SISO system (cancelled pole/zero pairs removed)."""
    return control.ss2tf(control.minreal(sys, verbose=False))


def dc_gain(sys: control.StateSpace) -> float:
    return float(np.real(control.dcgain(sys)))
