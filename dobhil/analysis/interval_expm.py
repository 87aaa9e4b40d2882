"""Enclosures of the sampled plant over a box of plant and environment values.

Midpoint-radius interval matrices (Rump, "Fast and parallel interval arithmetic", BIT 39(3),
1999): a matrix known to lie in ``[M - R, M + R]`` entrywise is the pair ``(M, R)``. Products
enclose every product of members, with the floating-point rounding of the midpoint product
added to the radius. The exponential ``e^X`` of an interval matrix is enclosed by scaling,
a Taylor polynomial with a bound on its remainder, and squaring (every step an enclosure).

Written here because the certificate needs thousands of small enclosures at once, batched in
numpy; mpmath's interval context (``mpmath.iv``) computes in software, one matrix at a time. Used by
:mod:`dobhil.analysis.certify_sampled` to bound how far the runtime's sampled matrices
(:func:`dobhil.synthesis.loop.sampled_plant`) can move over a sub-box.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from dobhil.synthesis.params import Array

#: unit roundoff of float64
EPS = np.finfo(float).eps

#: Taylor terms of the scaled exponential (its argument's norm is at most 1/2 there)
TAYLOR_TERMS = 18


@dataclass(frozen=True)
class IMat:
    """An interval matrix: every matrix within ``rad`` of ``mid``, entry by entry."""

    mid: Array
    rad: Array

    def __add__(self, other: IMat) -> IMat:
        s = self.mid + other.mid
        return IMat(s, self.rad + other.rad + EPS * np.abs(s))

    def __matmul__(self, other: IMat) -> IMat:
        m = self.mid @ other.mid
        n = self.mid.shape[-1]
        r = (np.abs(self.mid) @ other.rad + self.rad @ (np.abs(other.mid) + other.rad)
             + (n + 2) * EPS * (np.abs(self.mid) @ np.abs(other.mid)))
        return IMat(m, r * (1.0 + 4.0 * EPS))

    def scale(self, factor: float) -> IMat:
        m = self.mid * factor
        return IMat(m, self.rad * abs(factor) + EPS * np.abs(m))

    def magnitude(self) -> Array:
        """The largest absolute value of each entry over the interval."""
        return np.abs(self.mid) + self.rad

    def contains(self, m: Array) -> bool:
        return bool(np.all(np.abs(m - self.mid) <= self.rad))


def from_bounds(lo: Array, hi: Array) -> IMat:
    mid = 0.5 * (lo + hi)
    return IMat(mid, (0.5 * (hi - lo)) * (1.0 + 2.0 * EPS) + EPS * np.abs(mid))


def expm(x: IMat) -> IMat:
    """An enclosure of ``e^X`` for every X in the interval matrix (batched over leading axes:
    every matrix of the batch is scaled by the same power of two)."""
    n = x.mid.shape[-1]
    norm = float(x.magnitude().sum(axis=-1).max())            # infinity norm bound, all of the batch
    squarings = max(0, math.ceil(math.log2(norm / 0.5))) if norm > 0.5 else 0
    y = x.scale(2.0 ** -squarings)
    theta = y.magnitude().sum(axis=-1).max(axis=-1)            # per matrix, <= 1/2
    eye = IMat(np.broadcast_to(np.eye(n), x.mid.shape), np.zeros(x.mid.shape))
    term, total = eye, eye
    for k in range(1, TAYLOR_TERMS + 1):
        term = (term @ y).scale(1.0 / k)
        total = total + term
    # remainder: sum over k > N of theta^k / k! <= theta^(N+1) / (N+1)! / (1 - theta / (N+2))
    rest = theta ** (TAYLOR_TERMS + 1) / math.factorial(TAYLOR_TERMS + 1) / (1.0 - theta / (TAYLOR_TERMS + 2))
    out = IMat(total.mid, total.rad + np.asarray(rest)[..., None, None])
    for _ in range(squarings):
        out = out @ out
    return out


def hold(a: IMat, b: IMat, period: float) -> tuple[IMat, IMat]:
    """Enclosures of ``(Phi, Gamma)`` of ``x' = A x + B w``, w held over ``period`` -- the
    block exponential :func:`dobhil.synthesis.controller.discretize` takes, for every
    member of the interval matrices A and B (batched)."""
    n, p = a.mid.shape[-1], b.mid.shape[-1]
    shape = a.mid.shape[:-2] + (n + p, n + p)
    mid, rad = np.zeros(shape), np.zeros(shape)
    mid[..., :n, :n], rad[..., :n, :n] = a.mid, a.rad
    mid[..., :n, n:], rad[..., :n, n:] = b.mid, b.rad
    e = expm(IMat(mid, rad).scale(period))
    return (IMat(e.mid[..., :n, :n], e.rad[..., :n, :n]),
            IMat(e.mid[..., :n, n:], e.rad[..., :n, n:]))


def hold_delayed(a: IMat, b: IMat, period: float, input_delay: float) -> tuple[IMat, IMat, IMat]:
    """Enclosures of ``(Phi, Gamma0, Gamma1)`` of
    :func:`dobhil.synthesis.controller.discretize_delayed` (torque ``input_delay`` late)."""
    phi_rest, gamma0 = hold(a, b, period - input_delay)
    phi_tau, gamma_tau = hold(a, b, input_delay)
    return phi_rest @ phi_tau, gamma0, phi_rest @ gamma_tau


def scaled(a: IMat, b: IMat, s: Array) -> tuple[IMat, IMat]:
    """``(S^-1 A S, S^-1 B)`` for a diagonal S of powers of two (exact in floating point)."""
    f = s[..., None, :] / s[..., :, None]
    return IMat(a.mid * f, a.rad * f), IMat(b.mid / s[..., :, None], b.rad / s[..., :, None])


def unscaled(m: IMat, s: Array, square: bool) -> IMat:
    """``S M S^-1`` (square) or ``S M`` (a column block), exact for powers of two."""
    if square:
        f = s[..., :, None] / s[..., None, :]
        return IMat(m.mid * f, m.rad * f)
    return IMat(m.mid * s[..., :, None], m.rad * s[..., :, None])


__all__ = ["IMat", "expm", "from_bounds", "hold", "hold_delayed", "scaled", "unscaled"]
