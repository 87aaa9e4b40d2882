"""The force-control loop assembled in state space (Eqs. 18-20), continuous or sampled.

State ``[x_p, xi, w]``: the plant with its environment (``x_p = [q, dq]``), the
controller of :mod:`dobhil.synthesis.controller`, and -- sampled only -- a chain
of ``delay_samples`` torque commands in transit. Inputs and outputs are named
(:data:`INPUTS`, :data:`OUTPUTS`). ``tau_per`` is an extra input added to the
performance torque: with ``force_gain = 0`` the loop from ``tau_per`` to
``tau_int^`` is the open loop L of Eq. (26) with the inner DOb loop closed, and
``A(C_f) = A(0) - C_f B_per C_int^`` exactly.

The sampled loop is what the runtime does against the emulator in lockstep: at
sample k the controller reads ``x_p(kT)``, computes ``u_k``; the plant integrates
``u_{k-d}`` exactly (zero-order hold) over ``[kT, (k+1)T]`` -- or, with a fractional
``design.input_delay`` tau, ``u_{k-d-1}`` over ``[kT, kT + tau]`` and ``u_{k-d}`` over
``[kT + tau, (k+1)T]`` (:func:`sampled_plant`; one more command in transit).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dobhil.synthesis.controller import (DIS, INT, ControllerSS, continuous_controller,
                                         discretize_delayed, sampled_controller)
from dobhil.synthesis.models import plant_matrices
from dobhil.synthesis.params import Array, Params

INPUTS: tuple[str, ...] = ("tau_ref", "tau_per", "tau_du", "tau_i", "eta_q", "eta_dq")
OUTPUTS: tuple[str, ...] = ("tau_int_hat", "tau_dis_hat", "tau_int", "q", "dq", "u")


@dataclass(frozen=True)
class LoopSS:
    """Batched state-space matrices of the loop; ``dt`` None when continuous."""

    a: Array
    b: Array
    c: Array
    d: Array
    dt: float | None

    def input_index(self, name: str) -> int:
        return INPUTS.index(name)

    def output_index(self, name: str) -> int:
        return OUTPUTS.index(name)

    def siso(self, inp: str, out: str) -> tuple[Array, Array, Array, Array]:
        i, o = INPUTS.index(inp), OUTPUTS.index(out)
        return self.a, self.b[..., :, i:i + 1], self.c[..., o:o + 1, :], self.d[..., o:o + 1, i:i + 1]


def plant_of(params: Params) -> tuple[Array, Array, Array]:
    return plant_matrices(params.value("inertia"), params.value("viscous_friction"),
                          params.value("stiffness"), params.value("damping"))


def loop(params: Params, *, sampled: bool, force_gain: Array | float | None = None,
         controller: ControllerSS | None = None,
         plant: tuple[Array, Array, Array] | None = None) -> LoopSS:
    """The loop at ``force_gain`` (default: the design's C_f; 0 gives the open loop).

    ``controller`` (and, sampled, ``plant``: :func:`sampled_plant`): the controller and
    the sampled plant of ``params`` already computed, with batch shapes that broadcast to
    ``params``'. Over designs x plant points the controller depends on the design only
    and the plant on the point only, and their matrix exponentials are the costly part:
    ``dobhil tune`` computes each once per design or per point, not per pair."""
    if controller is None:
        controller = sampled_controller(params) if sampled else continuous_controller(params)
    ctrl = _broadcast(controller, params.batch_shape)
    cf = params.value("force_gain") if force_gain is None else np.asarray(force_gain, float)
    a_p, b_p, c_int = plant_of(params)
    b_late = np.zeros_like(b_p)
    delay = 0
    if sampled:
        shape = params.batch_shape
        a_p, b_p, b_late = (np.broadcast_to(m, shape + m.shape[-2:])
                            for m in (plant if plant is not None else sampled_plant(params)))
        delay = params.structure.delay_samples
    return _assemble(a_p, b_p, b_late, c_int, ctrl, np.broadcast_to(cf, params.batch_shape),
                     delay, late=sampled and params.structure.input_delay > 0)


def _broadcast(ctrl: ControllerSS, shape: tuple[int, ...]) -> ControllerSS:
    """``ctrl``'s matrices as views of the batch ``shape`` (no copies)."""
    def to(m: Array) -> Array:
        return np.broadcast_to(m, shape + m.shape[-2:])
    return ControllerSS(a=to(ctrl.a), b_y=to(ctrl.b_y), b_u=to(ctrl.b_u), b_i=to(ctrl.b_i),
                        c=to(ctrl.c), d_y=to(ctrl.d_y),
                        force_gain=np.broadcast_to(ctrl.force_gain, shape), dt=ctrl.dt,
                        measures_velocity=ctrl.measures_velocity)


def sampled_plant(params: Params) -> tuple[Array, Array, Array]:
    """(Phi, Gamma0, Gamma1) of the plant with its environment, sampled at ``loop.period``
    with the torque arriving ``design.input_delay`` after each feedback sample::

        x[k+1] = Phi x[k] + Gamma0 u[k-d] + Gamma1 u[k-d-1]     (d = design.delay_samples)

    (:func:`~dobhil.synthesis.controller.discretize_delayed`). This is the one sampled
    plant: the sampled loop below uses it, and an emulator stepping in lockstep can too.
    """
    a_p, b_p, _ = plant_of(params)
    period = float(np.asarray(params.period).reshape(-1)[0])
    return discretize_delayed(a_p, b_p, period, params.structure.input_delay)


def _assemble(a_p: Array, b_p: Array, b_late: Array, c_int: Array, ctrl: ControllerSS,
              cf: Array, delay: int, *, late: bool) -> LoopSS:
    shape = cf.shape
    nc, m = ctrl.order, ctrl.b_y.shape[-1]
    chain = delay + (1 if late else 0)   # commands in transit: u[k-1] .. u[k-chain]
    n = 2 + nc + chain
    xp, xc = slice(0, 2), slice(2, 2 + nc)
    c_y = np.eye(2)[:m]        # y = C_y x_p + E_eta eta (eta = [eta_q, eta_dq])
    e_eta = np.eye(2)[:m]
    cfe = cf[..., None, None]
    # u = G y + K_xi xi + C_f tau_ref + tau_per
    g = ctrl.d_y[..., DIS:DIS + 1, :] - cfe * ctrl.d_y[..., INT:INT + 1, :]
    u_state = np.zeros(shape + (1, n))
    u_state[..., :, xp] = g @ c_y
    u_state[..., :, xc] = ctrl.c[..., DIS:DIS + 1, :] - cfe * ctrl.c[..., INT:INT + 1, :]
    u_in = np.zeros(shape + (1, len(INPUTS)))
    u_in[..., 0, 0] = cf
    u_in[..., 0, 1] = 1.0
    u_in[..., :, 4:6] = g @ e_eta

    def command(age: int) -> tuple[Array, Array]:
        """State and input rows of u[k - age]."""
        if age == 0:
            return u_state, u_in
        return _select(shape, n, 2 + nc + age - 1), np.zeros(shape + (1, len(INPUTS)))

    a = np.zeros(shape + (n, n))
    b = np.zeros(shape + (n, len(INPUTS)))
    p_state, p_in = command(delay)
    a[..., xp, :] = b_p @ p_state
    b[..., xp, :] = b_p @ p_in
    if late:
        l_state, l_in = command(delay + 1)
        a[..., xp, :] += b_late @ l_state
        b[..., xp, :] += b_late @ l_in
    a[..., xp, xp] += a_p
    b[..., xp, 2:3] -= b_p + b_late   # tau_du held over the period like the torque
    a[..., xc, :] = ctrl.b_u @ u_state
    a[..., xc, xp] += ctrl.b_y @ c_y
    a[..., xc, xc] += ctrl.a
    b[..., xc, :] = ctrl.b_u @ u_in
    b[..., xc, 3:4] += ctrl.b_i
    b[..., xc, 4:6] += ctrl.b_y @ e_eta
    if chain:
        a[..., 2 + nc:2 + nc + 1, :] = u_state
        b[..., 2 + nc:2 + nc + 1, :] = u_in
        for j in range(1, chain):
            a[..., 2 + nc + j, 2 + nc + j - 1] = 1.0
    c = np.zeros(shape + (len(OUTPUTS), n))
    d = np.zeros(shape + (len(OUTPUTS), len(INPUTS)))
    for row in (INT, DIS):
        out = 0 if row == INT else 1
        c[..., out, xc] = ctrl.c[..., row, :]
        c[..., out:out + 1, xp] = ctrl.d_y[..., row:row + 1, :] @ c_y
        d[..., out:out + 1, 4:6] = ctrl.d_y[..., row:row + 1, :] @ e_eta
    c[..., 2:3, xp] = c_int
    c[..., 3, 0] = 1.0
    c[..., 4, 1] = 1.0
    c[..., 5:6, :] = u_state
    d[..., 5:6, :] = u_in
    return LoopSS(a=a, b=b, c=c, d=d, dt=ctrl.dt)


def _select(shape: tuple[int, ...], n: int, index: int) -> Array:
    row = np.zeros(shape + (1, n))
    row[..., 0, index] = 1.0
    return row
