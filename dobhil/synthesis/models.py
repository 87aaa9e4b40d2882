"""Servo models (Eqs. 1-3, 22, 28) and the disturbance / interaction torque models
(Eqs. 5-6, 12-13), batched over a leading batch shape.

Servo model with viscous friction (Eq. 28), state ``x = [q, dq]``::

    A = [[0, 1], [0, -b/J]],  B = D = [0, 1/J]^T

The environment (Eq. 21: tau_d = tau_d^u + D_env dq + K_env q) is folded into the
exact plant: ``A_env = [[0, 1], [-K/J, -(b + D)/J]]``, and the true interaction
torque is ``tau_int = K q + D dq``.
"""

from __future__ import annotations

import numpy as np

from dobhil.errors import SynthesisError
from dobhil.synthesis.params import Array, SignalModel


def servo_matrices(inertia: Array, friction: Array) -> tuple[Array, Array]:
    """(A, B) of Eq. (28) for inertia J and viscous friction b (D equals B)."""
    inertia, friction = np.broadcast_arrays(np.asarray(inertia, float), np.asarray(friction, float))
    a = np.zeros(inertia.shape + (2, 2))
    a[..., 0, 1] = 1.0
    a[..., 1, 1] = -friction / inertia
    b = np.zeros(inertia.shape + (2, 1))
    b[..., 1, 0] = 1.0 / inertia
    return a, b


def plant_matrices(inertia: Array, friction: Array, stiffness: Array,
                   damping: Array) -> tuple[Array, Array, Array]:
    """The exact servo in contact with the environment: (A, B, C_int).

    ``x' = A x + B (u - tau_d^u)`` and ``tau_int = C_int x``. This is the one
    plant model: the analysis uses it and the emulator integrates it.
    """
    inertia, friction, stiffness, damping = np.broadcast_arrays(
        *(np.asarray(v, float) for v in (inertia, friction, stiffness, damping)))
    a, b = servo_matrices(inertia, friction)
    a[..., 1, 0] = -stiffness / inertia
    a[..., 1, 1] = -(friction + damping) / inertia
    c_int = np.zeros(inertia.shape + (1, 2))
    c_int[..., 0, 0] = stiffness
    c_int[..., 0, 1] = damping
    return a, b, c_int


def signal_model(kind: SignalModel, omega: Array, scale: Array | float = 1.0) -> tuple[Array, Array]:
    """(A_S, C_S) of a torque model ``x_S' = A_S x_S, tau = C_S x_S``.

    - CONSTANT: the paper's model, d tau/dt = 0.
    - RAMP: d^2 tau/dt^2 = 0 (a torque changing at a constant rate).
    - SINUSOID: a bias plus a sinusoid of frequency omega [rad/s],
      d^3 tau/dt^3 = -omega^2 d tau/dt; the bias keeps a constant interaction
      torque observable, which a pure sinusoid model would reject.

    The state is the torque and its derivatives in units of ``scale`` [rad/s]:
    ``x_S = [tau, tau_dot / h, tau_ddot / h^2]`` with ``h = scale``. With ``h`` the
    observer bandwidth every entry of A_S and of the observer gain is of order
    ``h`` (a ``[bias, sin, cos]`` basis gives gains of order ``g^3 / omega^2`` and
    eigenvalues numpy cannot resolve). Any basis gives the same observer transfer
    functions: for one output, the observer with all its poles at ``-g`` is
    unique up to a change of basis.
    """
    omega, h = np.broadcast_arrays(np.asarray(omega, float), np.asarray(scale, float))
    k = {SignalModel.CONSTANT: 1, SignalModel.RAMP: 2, SignalModel.SINUSOID: 3}[kind]
    a = np.zeros(omega.shape + (k, k))
    for j in range(k - 1):
        a[..., j, j + 1] = h
    if kind is SignalModel.SINUSOID:
        a[..., 2, 1] = -omega ** 2 / h
    c = np.zeros(omega.shape + (1, k))
    c[..., 0, 0] = 1.0
    return a, c


def observer_gain(a_s: Array, c_s: Array, bandwidth: Array) -> Array:
    """Gain l (k x 1) placing every eigenvalue of ``A_S - l C_S`` at ``-bandwidth``.

    Ackermann's formula for the observer (dual) problem,
    ``l = phi(A_S) O^{-1} e_k`` with ``phi(s) = (s + g)^k`` and ``O`` the
    observability matrix of (A_S, C_S). The rule: all observer poles at the
    bandwidth g (binomial placement), which gives the paper's conventional
    observer ``l = g`` for the constant model. Ackermann is written here
    because scipy's ``place_poles`` refuses repeated poles for single outputs.
    """
    k = a_s.shape[-1]
    g = np.asarray(bandwidth, float)
    rows = [c_s]
    for _ in range(k - 1):
        rows.append(rows[-1] @ a_s)
    obs = np.concatenate(rows, axis=-2)
    if np.any(np.abs(np.linalg.det(obs)) < 1e-12 * np.maximum(1.0, np.abs(obs).max())):
        raise SynthesisError("torque model (A, C) is not observable; choose another model")
    coeffs = _binomial_coefficients(g, k)  # phi(s) = sum coeffs[j] s^(k-j)
    eye = np.broadcast_to(np.eye(k), a_s.shape)
    phi = np.zeros(np.broadcast_shapes(a_s.shape, g.shape + (1, 1)))
    power = eye
    for j in range(k, -1, -1):
        phi = phi + coeffs[..., j, None, None] * power
        power = power @ a_s
    e_k = np.zeros((k, 1))
    e_k[-1, 0] = 1.0
    return phi @ np.linalg.solve(obs, np.broadcast_to(e_k, obs.shape[:-1] + (1,)))


def _binomial_coefficients(g: Array, k: int) -> Array:
    """Coefficients of (s + g)^k, highest power first, shape g.shape + (k+1,)."""
    from math import comb
    return np.stack([comb(k, j) * g ** j for j in range(k + 1)], axis=-1)
