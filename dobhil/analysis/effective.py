"""What the observers actually are once sampled: effective inertia, friction, bandwidth.

At low frequency the DOb computes ``tau_dis^ = u - J_n q'' - b_n q'`` and the RTOb
``tau_int^ = u - J_i q'' - b_i q'`` (each through its low-pass filter). For any
linear controller -- continuous or sampled -- the steady response of an output to
a polynomial motion ``q(t)`` is ``sum_j c_j d^j/dt^j`` of its inputs, where
``c_j`` are the Taylor coefficients in ``s`` of the transfer function ``H(s)``
(continuous) or ``H(e^{sT})`` (sampled). So, per output, with ``c^q``, ``c^v``
and ``c^u`` the coefficients from the position, the measured velocity and the
torque::

    torque gain           c0^u                     (1 for a faithful observer)
    effective inertia     -(c2^q + c1^v) / c0^u
    effective friction    -(c1^q + c0^v) / c0^u
    position leak         c0^q                     (0: no stiffness read)

computed from the matrices alone (resolvents at s = 0 or z = 1), whatever built
them. The effective bandwidth is where the torque-to-estimate response has
fallen 3 dB below its DC gain (``g`` for the paper's constant-model observer).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np
import scipy.optimize

from dobhil.synthesis.controller import DIS, INT, ControllerSS
from dobhil.synthesis.params import Array


@dataclass(frozen=True)
class EffectiveObserver:
    """Low-frequency behaviour of one observer output (tau_dis^ or tau_int^)."""

    inertia: float
    friction: float
    torque_gain: float
    position_leak: float
    bandwidth: float | None     # rad/s; None when not reached below the Nyquist frequency

    def as_dict(self) -> dict[str, float | None]:
        return asdict(self)


def taylor_coefficients(ctrl: ControllerSS, row: int) -> Array:
    """``c_j`` for j = 0, 1, 2 (rows) of output ``row`` from every input (columns:
    the measurements ``y``, then ``u``); ``ctrl`` a single design."""
    a = np.asarray(ctrl.a, float)
    b = np.concatenate([ctrl.b_y, ctrl.b_u], axis=-1)
    c = ctrl.c[row:row + 1]
    d = np.concatenate([ctrl.d_y[row:row + 1], np.zeros((1, 1))], axis=-1)
    n = a.shape[-1]
    if ctrl.dt is None:
        r1 = np.linalg.solve(-a, b) if n else b[:0]            # (sI - A)^-1 at s = 0: -A^-1
        r2 = np.linalg.solve(-a, r1) if n else r1
        r3 = np.linalg.solve(-a, r2) if n else r2
        return np.vstack([c @ r1 + d, -(c @ r2), c @ r3])
    t = float(ctrl.dt)
    eye = np.eye(n)
    r1 = np.linalg.solve(eye - a, b) if n else b[:0]          # (zI - A)^-1 at z = 1
    r2 = np.linalg.solve(eye - a, r1) if n else r1
    r3 = np.linalg.solve(eye - a, r2) if n else r2
    return np.vstack([c @ r1 + d, -t * (c @ r2), t * t * (c @ r3) - 0.5 * t * t * (c @ r2)])


def effective_observer(ctrl: ControllerSS, row: int) -> EffectiveObserver:
    co = taylor_coefficients(ctrl, row)
    m = ctrl.b_y.shape[-1]
    gain = float(co[0, m])
    acc = co[2, 0] + (co[1, 1] if m == 2 else 0.0)
    vel = co[1, 0] + (co[0, 1] if m == 2 else 0.0)
    return EffectiveObserver(inertia=float(-acc / gain), friction=float(-vel / gain),
                             torque_gain=gain, position_leak=float(co[0, 0]),
                             bandwidth=_bandwidth(ctrl, row, gain))


def effective_observers(ctrl: ControllerSS) -> dict[str, EffectiveObserver]:
    """``{"dob": ..., "rtob": ...}`` of one design's controller."""
    return {"dob": effective_observer(ctrl, DIS), "rtob": effective_observer(ctrl, INT)}


def torque_response(ctrl: ControllerSS, row: int, w: Array) -> Array:
    """|H_u| of the torque-to-estimate response at frequencies ``w`` [rad/s]."""
    a, b, c = ctrl.a, ctrl.b_u, ctrl.c[row:row + 1]
    points = np.exp(1j * w * ctrl.dt) if ctrl.dt else 1j * w
    eye = np.eye(a.shape[-1])
    mats = points[:, None, None] * eye - a
    return np.abs((c @ np.linalg.solve(mats, np.broadcast_to(b, mats.shape[:-1] + (1,))))[:, 0, 0])


def _bandwidth(ctrl: ControllerSS, row: int, gain: float) -> float | None:
    if not gain or not math.isfinite(gain):
        return None
    top = math.pi / ctrl.dt if ctrl.dt else 1e9
    w = np.geomspace(top * 1e-9, top * (1 - 1e-9), 2000)
    below = torque_response(ctrl, row, w) < abs(gain) / math.sqrt(2.0)
    if not below.any():
        return None
    i = int(np.argmax(below))
    if i == 0:
        return float(w[0])

    def f(x: float) -> float:
        return float(torque_response(ctrl, row, np.array([x]))[0] - abs(gain) / math.sqrt(2.0))
    return float(scipy.optimize.brentq(f, w[i - 1], w[i], xtol=1e-12 * w[i], rtol=1e-12))
