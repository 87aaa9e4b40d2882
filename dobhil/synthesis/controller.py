"""The DOb/RTOb force controller as one linear state-space system, continuous and sampled.

State ``xi = [z, sigma, rho]`` (``z`` only when the velocity is estimated from the
position), inputs ``y`` (measured ``[q, dq]``, or ``[q]`` alone) and the applied
torque ``u`` (plus ``tau_i``, the identified disturbance of Eq. 21, for the
analysis), outputs ``[tau_dis^, tau_int^]``::

    xi' = A xi + B_y y + B_u u + B_i tau_i          (continuous), or
    xi[k+1] = A xi[k] + B_y y[k] + B_u u[k] + ...   (sampled)
    [tau_dis^, tau_int^] = C xi + D_y y

and the force law ``u = C_f (tau_ref - tau_int^) + tau_dis^`` (Fig. 1c), saturated
before it is applied; the *applied* torque is what the observers are fed.

Velocity estimated from position: the pseudo-differentiator
``v = g_v s / (s + g_v) q``, realised as ``z' = g_v (q - z)``, ``v = g_v (q - z)``.

Sampling (:func:`sampled_controller`): the runtime executes exactly the matrices
returned here -- this is the one source of the sampled observer. The torque input
is discretised by zero-order hold, exactly (the drive holds the command for a
period). The measured signals are not held -- they move between samples and the
observers differentiate them -- so by default (``parabolic``) they pass through the
parabola through ``y[k-1], y[k], y[k+1]``: the sampled observers then have exactly
the configured inertia and friction at low frequency, with measured or estimated
velocity (:mod:`dobhil.analysis.effective` computes them from the matrices).
``foh`` (the triangle, ramp-invariant hold) is exact with measured velocity only.
Both keep every observer pole at ``exp(-g T)`` (the bandwidth is kept and the
observers stay stable for any ``g T``) and have no direct feedthrough from ``u``,
so saturation needs no algebraic loop; the outputs do gain a feedthrough from the
measurement. Their state is ``S^-1 (xi - E0 y)`` (S a diagonal balancing in powers of
two), followed by ``y[k-1]`` for the parabola. ``zoh`` (the step-invariant equivalent of the whole controller, the
former default) scales every differentiator by ``gT / (1 - e^-gT)``; ``euler``
(forward Euler) goes unstable for ``g T > 2``. Both are kept for comparison.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg

from dobhil.synthesis.observers import AuxObserver, aux_observer
from dobhil.synthesis.params import Array, Discretization, Params, VelocitySource

DIS, INT = 0, 1  # output rows of the controller


@dataclass(frozen=True)
class ControllerSS:
    """The controller's matrices (batched); ``dt`` is None when continuous."""

    a: Array     # (..., n, n)
    b_y: Array   # (..., n, m)
    b_u: Array   # (..., n, 1)
    b_i: Array   # (..., n, 1)
    c: Array     # (..., 2, n)   rows: tau_dis^, tau_int^
    d_y: Array   # (..., 2, m)
    force_gain: Array
    dt: float | None
    measures_velocity: bool

    @property
    def order(self) -> int:
        return self.a.shape[-1]


def _measurement_map(params: Params) -> tuple[Array, Array, Array, Array]:
    """Velocity estimate: (A_z, B_z, M_z, M_y) with ``x_m = M_z z + M_y y``."""
    shape = params.batch_shape
    if params.structure.velocity_source is VelocitySource.MEASURED:
        return (np.zeros(shape + (0, 0)), np.zeros(shape + (0, 2)),
                np.zeros(shape + (2, 0)), np.broadcast_to(np.eye(2), shape + (2, 2)))
    g = params.value("velocity_filter_bandwidth")
    a_z = -g[..., None, None] * np.ones((1, 1))
    b_z = g[..., None, None] * np.ones((1, 1))
    m_z = np.zeros(shape + (2, 1))
    m_z[..., 1, 0] = -g
    m_y = np.zeros(shape + (2, 1))
    m_y[..., 0, 0] = 1.0
    m_y[..., 1, 0] = g
    return a_z, b_z, m_z, m_y


def _observers(params: Params) -> tuple[AuxObserver, AuxObserver]:
    s = params.structure
    dob = aux_observer(s.disturbance_model, params.value("disturbance_frequency"),
                       params.value("nominal_inertia"), params.value("nominal_friction"),
                       params.value("dob_bandwidth"))
    rtob = aux_observer(s.interaction_model, params.value("interaction_frequency"),
                        params.value("identified_inertia"), params.value("identified_friction"),
                        params.value("rtob_bandwidth"))
    return dob, rtob


def continuous_controller(params: Params) -> ControllerSS:
    """The continuous-time controller (the paper's, generalised)."""
    shape = params.batch_shape
    a_z, b_z, m_z, m_y = _measurement_map(params)
    dob, rtob = _observers(params)
    nz, nd, nr = a_z.shape[-1], dob.order, rtob.order
    n, m = nz + nd + nr, m_y.shape[-1]
    zs, ds, rs = slice(0, nz), slice(nz, nz + nd), slice(nz + nd, n)
    a = np.zeros(shape + (n, n))
    b_y = np.zeros(shape + (n, m))
    b_u = np.zeros(shape + (n, 1))
    b_i = np.zeros(shape + (n, 1))
    c = np.zeros(shape + (2, n))
    d_y = np.zeros(shape + (2, m))
    a[..., zs, zs] = a_z
    if nz:
        b_y[..., zs, :] = b_z
    for obs, sl, row in ((dob, ds, DIS), (rtob, rs, INT)):
        a[..., sl, sl] = obs.a
        a[..., sl, zs] = obs.a_x @ m_z
        b_y[..., sl, :] = obs.a_x @ m_y
        b_u[..., sl, :] = obs.b
        c[..., row:row + 1, sl] = obs.c
        c[..., row:row + 1, zs] = -obs.c @ obs.gain @ m_z
        d_y[..., row:row + 1, :] = -obs.c @ obs.gain @ m_y
    b_i[..., rs, :] = -rtob.b
    return ControllerSS(a=a, b_y=b_y, b_u=b_u, b_i=b_i, c=c, d_y=d_y,
                        force_gain=params.value("force_gain"), dt=None,
                        measures_velocity=m == 2)


def sampled_controller(params: Params) -> ControllerSS:
    """The controller discretised at ``params.period``: what the runtime executes."""
    cont = continuous_controller(params)
    period = float(np.asarray(params.period).reshape(-1)[0])
    if np.ndim(params.period) and np.ptp(np.asarray(params.period)) > 0:
        raise ValueError("a batch of designs must share one loop.period")
    method = params.structure.discretization
    if method in (Discretization.FOH, Discretization.PARABOLIC):
        return _polynomial_hold(balanced(cont), period, 1 if method is Discretization.FOH else 2)
    b_all = np.concatenate([cont.b_y, cont.b_u, cont.b_i], axis=-1)
    phi, gamma = discretize(cont.a, b_all, period, method)
    m = cont.b_y.shape[-1]
    return ControllerSS(a=phi, b_y=gamma[..., :, :m], b_u=gamma[..., :, m:m + 1],
                        b_i=gamma[..., :, m + 1:m + 2], c=cont.c, d_y=cont.d_y,
                        force_gain=cont.force_gain, dt=period,
                        measures_velocity=cont.measures_velocity)


def balanced(ctrl: ControllerSS) -> ControllerSS:
    """The same controller in a diagonally rescaled state (``x = S x~``, S a power of two
    per state) whose rows and columns of A are balanced (Osborne's iteration, batched).

    The position filter state and the observers' torque states differ in scale by
    ``g_v g J`` (about 1e5); unbalanced, ``(I - Phi)`` has a condition number near
    1e10 and the at-rest estimate loses six digits. Powers of two keep it exact."""
    a = ctrl.a
    n = a.shape[-1]
    scale = np.ones(a.shape[:-1])
    off = ~np.eye(n, dtype=bool)
    for _ in range(8):
        m = np.abs(a * scale[..., None, :] / scale[..., :, None]) * off
        rows, cols = m.sum(axis=-1), m.sum(axis=-2)
        ok = (rows > 0) & (cols > 0)
        f = np.where(ok, np.exp2(np.round(0.5 * np.log2(np.where(ok, rows / np.where(ok, cols, 1.0),
                                                                  1.0)))), 1.0)
        if np.all(f == 1.0):
            break
        scale = scale * f
    inv = 1.0 / scale
    return ControllerSS(a=a * scale[..., None, :] * inv[..., :, None],
                        b_y=ctrl.b_y * inv[..., :, None], b_u=ctrl.b_u * inv[..., :, None],
                        b_i=ctrl.b_i * inv[..., :, None], c=ctrl.c * scale[..., None, :],
                        d_y=ctrl.d_y, force_gain=ctrl.force_gain, dt=ctrl.dt,
                        measures_velocity=ctrl.measures_velocity)


def distinct_expm(block: Array) -> Array:
    """``scipy.linalg.expm`` of a batch, computed once per distinct matrix (bit for bit) and
    copied to the others: scipy takes a batch one matrix at a time in Python, and a sweep's
    grid repeats each one -- the controller varies with the design's keys only, the plant
    with the plant's and the environment's -- so a 60 x 60 sweep of the identified inertia
    against the stiffness has at most 60 distinct matrices in each batch of 3600. The same
    bits in give the same bits out, so nothing changes but the count."""
    n = block.shape[-1]
    count = block.size // max(n * n, 1)
    if count < 2:
        return np.asarray(scipy.linalg.expm(block))
    rows = np.ascontiguousarray(block).reshape(count, n * n)
    keys = rows.view(np.dtype((np.void, rows.dtype.itemsize * n * n)))[:, 0]
    _, first, inverse = np.unique(keys, return_index=True, return_inverse=True)
    distinct = np.asarray(scipy.linalg.expm(rows[first].reshape(-1, n, n)))
    return distinct[inverse.reshape(-1)].reshape(block.shape)


def hold_moments(a: Array, b: Array, period: float) -> tuple[Array, Array, Array, Array]:
    """(Phi, G0, G1, G2) with ``G_j = int_0^T e^{A(T-t)} B (t/T)^j dt`` (batched).

    One matrix exponential of the system driven by the polynomial basis
    ``1, t/T, (t/T)^2 / 2`` (a chain of integrators in the time ``t/T``)."""
    n, p = a.shape[-1], b.shape[-1]
    size = n + 3 * p
    block = np.zeros(np.broadcast_shapes(a.shape[:-2], b.shape[:-2]) + (size, size))
    block[..., :n, :n] = a * period
    block[..., :n, n:n + p] = b * period
    eye = np.eye(p)
    block[..., n:n + p, n + p:n + 2 * p] = eye
    block[..., n + p:n + 2 * p, n + 2 * p:] = eye
    e = distinct_expm(block)
    phi = e[..., :n, :n]
    return (phi, e[..., :n, n:n + p], e[..., :n, n + p:n + 2 * p],
            2.0 * e[..., :n, n + 2 * p:])


def _polynomial_hold(cont: ControllerSS, period: float, order: int) -> ControllerSS:
    """The measured signals through a polynomial hold, the torque through a ZOH.

    Between samples the measurement is taken as the polynomial through
    ``y[k+1], y[k]`` (order 1: the triangle hold, exact for ramps) or through
    ``y[k+1], y[k], y[k-1]`` (order 2: exact for parabolas). With
    ``y(kT + theta T) = sum_i l_i(theta) y[k+1-i]``::

        x[k+1] = Phi x[k] + E0 y[k+1] + E1 y[k] + E2 y[k-1] + Gamma_u u[k]

    and the state ``xi = x - E0 y`` (plus ``y[k-1]`` for order 2) removes the
    future sample: ``xi[k+1] = Phi xi + (Phi E0 + E1) y[k] + E2 y[k-1] + Gamma_u u``,
    outputs ``C xi + (D + C E0) y``. The outputs gain a feedthrough from the
    measurement, never from the torque, so saturation stays explicit. The
    observer poles stay at ``exp(-g T)``; the hold's own poles are at z = 0.
    """
    phi, g0, g1, g2 = hold_moments(cont.a, cont.b_y, period)
    _, gamma = discretize(cont.a, np.concatenate([cont.b_u, cont.b_i], axis=-1), period,
                          Discretization.ZOH)
    if order == 1:
        e0, e1, e2 = g1, g0 - g1, np.zeros_like(g0)
    else:
        e0, e1, e2 = 0.5 * (g1 + g2), g0 - g2, 0.5 * (g2 - g1)
    m = cont.b_y.shape[-1]
    flat = np.abs(e2).reshape(-1, *e2.shape[-2:]).max(axis=(0, 1)) if e2.size else np.zeros(m)
    past = [j for j in range(m) if order == 2 and flat[j] > 0.0]   # y[k-1] kept for these
    n, w = cont.order, len(past)
    shape = cont.a.shape[:-2]
    a = np.zeros(shape + (n + w, n + w))
    b_y = np.zeros(shape + (n + w, m))
    b_u = np.zeros(shape + (n + w, 1))
    b_i = np.zeros(shape + (n + w, 1))
    c = np.zeros(shape + (2, n + w))
    a[..., :n, :n] = phi
    b_y[..., :n, :] = phi @ e0 + e1
    for i, j in enumerate(past):
        a[..., :n, n + i] = e2[..., :, j]
        b_y[..., n + i, j] = 1.0
    b_u[..., :n, :] = gamma[..., :, 0:1]
    b_i[..., :n, :] = gamma[..., :, 1:2]
    c[..., :, :n] = cont.c
    return ControllerSS(a=a, b_y=b_y, b_u=b_u, b_i=b_i, c=c, d_y=cont.d_y + cont.c @ e0,
                        force_gain=cont.force_gain, dt=period,
                        measures_velocity=cont.measures_velocity)


def discretize(a: Array, b: Array, period: float | Array,
               method: Discretization = Discretization.ZOH) -> tuple[Array, Array]:
    """(Phi, Gamma) of ``x' = A x + B w`` with ``w`` held over ``period`` (batched; a
    ``period`` of shape ``(..., 1, 1)``: one per matrix of the batch)."""
    n, p = a.shape[-1], b.shape[-1]
    if method is Discretization.EULER:
        return np.eye(n) + a * period, b * period
    block = np.zeros(np.broadcast_shapes(a.shape[:-2], b.shape[:-2]) + (n + p, n + p))
    block[..., :n, :n] = a * period
    block[..., :n, n:] = b * period
    e = distinct_expm(block)
    return e[..., :n, :n], e[..., :n, n:]


def discretize_delayed(a: Array, b: Array, period: float,
                       input_delay: float) -> tuple[Array, Array, Array]:
    """(Phi, Gamma0, Gamma1) of ``x' = A x + B w`` sampled at ``period`` when the command
    computed at ``t_k`` reaches the plant at ``t_k + input_delay`` and is held until the
    next one arrives (the modified z-transform, as an augmented state)::

        x[k+1] = Phi x[k] + Gamma0 w[k] + Gamma1 w[k-1]
        Gamma0 = int_0^{T-tau} e^{A s} ds B
        Gamma1 = e^{A (T-tau)} int_0^{tau} e^{A s} ds B

    ``0 <= input_delay <= period`` (batched in A, B). ``input_delay = 0`` gives the
    zero-order hold (Gamma1 = 0); ``input_delay = period`` one whole sample of delay
    (Gamma0 = 0). Exact: both pieces come from one matrix exponential each.
    """
    if not 0.0 <= input_delay <= period:
        raise ValueError(f"input_delay must lie in [0, period]; got {input_delay!r}")
    rest = period - input_delay
    phi_rest, gamma0 = discretize(a, b, rest, Discretization.ZOH)
    phi_tau, gamma_tau = discretize(a, b, input_delay, Discretization.ZOH)
    return phi_rest @ phi_tau, gamma0, phi_rest @ gamma_tau
