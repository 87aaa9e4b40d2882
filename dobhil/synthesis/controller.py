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
returned here -- this is the one source of the sampled observer. The default
discretisation is the zero-order-hold (step-invariant) equivalent of the whole
continuous controller, its inputs held over each period: it is exact for the
torque input (the drive holds the torque command for a period), it maps every
observer pole to ``exp(-g T)`` so the bandwidth is kept and the observers stay
stable for any ``g T`` (``g T = 1`` at 1 kHz and 1000 rad/s), and it keeps the
observer outputs free of direct feedthrough from ``u``, so saturation needs no
algebraic loop. ``euler`` (forward Euler, what many hand-written observers do)
is available for comparison; it goes unstable for ``g T > 2``.
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
    b_all = np.concatenate([cont.b_y, cont.b_u, cont.b_i], axis=-1)
    phi, gamma = discretize(cont.a, b_all, period, params.structure.discretization)
    m = cont.b_y.shape[-1]
    return ControllerSS(a=phi, b_y=gamma[..., :, :m], b_u=gamma[..., :, m:m + 1],
                        b_i=gamma[..., :, m + 1:m + 2], c=cont.c, d_y=cont.d_y,
                        force_gain=cont.force_gain, dt=period,
                        measures_velocity=cont.measures_velocity)


def discretize(a: Array, b: Array, period: float,
               method: Discretization = Discretization.ZOH) -> tuple[Array, Array]:
    """(Phi, Gamma) of ``x' = A x + B w`` with ``w`` held over ``period`` (batched)."""
    n, p = a.shape[-1], b.shape[-1]
    if method is Discretization.EULER:
        return np.eye(n) + a * period, b * period
    block = np.zeros(np.broadcast_shapes(a.shape[:-2], b.shape[:-2]) + (n + p, n + p))
    block[..., :n, :n] = a * period
    block[..., :n, n:] = b * period
    e = scipy.linalg.expm(block)
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
