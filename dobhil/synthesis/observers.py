"""The auxiliary-variable observers of Eqs. (10) and (16), derived afresh.

A model ``x' = A_m x + B_m u - D_m C_S x_S`` with the torque model
``x_S' = A_S x_S`` gives the (derivative-free) "measurement"
``y_S = A_m x + B_m u - x' = D_m C_S x_S`` and the observer
``x̂_S' = A_S x̂_S + L (y_S - D_m C_S x̂_S)``. With the auxiliary variable
``sigma = x̂_S + L x`` the derivative of x cancels::

    sigma' = A_aux sigma + A_aux_x x + B_aux u
    A_aux   = A_S - L D_m C_S
    A_aux_x = L A_m - A_aux L  (= L A_m - A_S L + L D_m C_S L)
    B_aux   = L B_m
    tau^    = C_S (sigma - L x)

For the DOb (Eq. 10) the model is the nominal one (A_n, B_n); for the RTOb
(Eq. 16) it is the *identified* one (A_i, B_i), and the identified disturbance
enters as ``u - tau_i`` (Eq. 21). The print of Eq. (16) has A_n, B_n, and a
minus sign on ``L D C L`` -- both wrong; this derivation is checked against the
closed-form L(s) of Eq. (26) in the tests.

The gain acts on the velocity row only: ``L = J l [0, 1]`` with ``l`` from
:func:`observer_gain`, so that ``L D_m C_S = l C_S`` and the error dynamics
``A_S - l C_S`` have every pole at ``-g`` (the paper's L = [0, g J]).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dobhil.synthesis.models import observer_gain, servo_matrices, signal_model
from dobhil.synthesis.params import Array, SignalModel


@dataclass(frozen=True)
class AuxObserver:
    """Matrices of one auxiliary-variable observer (batched)."""

    a: Array      # A_aux, (..., k, k)
    a_x: Array    # A_aux_x, (..., k, 2)
    b: Array      # B_aux, (..., k, 1)
    gain: Array   # L, (..., k, 2)
    c: Array      # C_S, (..., 1, k)

    @property
    def order(self) -> int:
        return self.a.shape[-1]


def aux_observer(model: SignalModel, omega: Array, inertia: Array, friction: Array,
                 bandwidth: Array) -> AuxObserver:
    """The observer of the torque ``model`` acting on the servo model (inertia, friction)."""
    a_m, b_m = servo_matrices(inertia, friction)
    g = np.asarray(bandwidth, float)
    a1, c_s = signal_model(model, np.asarray(omega, float) / g)   # time in units of 1/g
    ell = g[..., None, None] * observer_gain(a1, c_s, np.ones_like(g))
    a_s = g[..., None, None] * a1
    row = np.array([[0.0, 1.0]])
    gain = np.asarray(inertia, float)[..., None, None] * ell * row
    a_aux = a_s - ell @ c_s
    a_aux_x = gain @ a_m - a_aux @ gain
    return AuxObserver(a=a_aux, a_x=a_aux_x, b=gain @ b_m, gain=gain,
                       c=np.broadcast_to(c_s, a_aux.shape[:-2] + c_s.shape[-2:]))
