"""Stability of the sampled, delayed force loop over a whole box: a validated argument.

The sampled loop is not affine in the plant's values (they enter through matrix
exponentials), so the edge theorem does not apply. The argument used instead, per sub-box:

1. The sampled plant ``(Phi, Gamma0, Gamma1)`` -- what :func:`dobhil.synthesis.loop.sampled_plant`
   computes for the runtime -- is enclosed for every value in the sub-box by interval
   arithmetic (:mod:`dobhil.analysis.interval_expm`), and the loop matrix, which the loop's
   assembly makes affine in those three matrices (checked at run time), is enclosed entry by
   entry: ``A(p) = A_m + E`` with ``|E| <= R`` for every p of the sub-box.
2. At the midpoint, ``P = L L^T`` solves the discrete Lyapunov equation
   ``(A_m / r)^T P (A_m / r) - P = -I`` with r halfway between A_m's spectral radius and 1
   (balanced coordinates), so that the induced norm ``||A||_P = ||L^T A L^-T||_2`` of A_m is
   below 1. Every member satisfies ``rho(A_m + E) <= ||A_m + E||_P <= ||A_m||_P +
   || |L^T| R |L^-T| ||_2`` (the 2-norm grows with the entries' absolute values); below 1
   (with a margin for rounding), every loop of the sub-box is Schur stable -- and
   ``x^T P x`` even decreases along any switching among them.
3. A sub-box where the bound does not close is bisected; a centre whose spectral radius
   (the runtime's matrices, evaluated) is >= 1 refutes the box.

The answer is "certified" (every sub-box closed), "refuted at (point)" or "undecided
after N refinements" (the budget ran out). See docs/certify.md.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from dobhil.analysis import interval_expm as iv
from dobhil.analysis.certify import RECIPROCAL_KEYS, Box, Verdict, params_at
from dobhil.config.schema import Config
from dobhil.errors import AnalysisError
from dobhil.synthesis.controller import ControllerSS, sampled_controller
from dobhil.synthesis.loop import loop, sampled_plant
from dobhil.synthesis.numerics import balance_scaling
from dobhil.synthesis.params import PARAM_KEYS, Array
from dobhil.realtime import one_blas_thread

#: the default number of bisections before the answer is "undecided"
DEFAULT_REFINEMENTS = 20000

#: a sub-box is split at its geometric mean along a positive key at least this wide (HI / LO)
LOG_SPLIT_RATIO = 4.0

#: sub-boxes decided together (numpy's batched linear algebra; bounds the memory)
CHUNK = 512


@dataclass(frozen=True)
class SampledCertificate:
    verdict: Verdict
    box: Box
    refinements: int                      # bisections made
    closed: int                           # sub-boxes whose bound closed
    point: Mapping[str, float] | None = None
    spectral_radius: float | None = None  # at the refuting point, or the largest seen


class _AffineLoop:
    """The sampled loop matrix as an affine function of (Phi, Gamma0, Gamma1), read off
    :func:`dobhil.synthesis.loop.loop` itself (so the assembly is not written twice)."""

    def __init__(self, config: Config, centre: Mapping[str, float]) -> None:
        self.params = params_at(config, centre)
        self.ctrl: ControllerSS = sampled_controller(self.params)
        self.offset = self._at(np.zeros(8))
        self.basis = np.stack([self._at(np.eye(8)[i]) - self.offset for i in range(8)], axis=-1)
        self._check(sampled_plant(self.params))

    def _at(self, theta: Array) -> Array:
        phi, g0, g1 = theta[:4].reshape(2, 2), theta[4:6].reshape(2, 1), theta[6:8].reshape(2, 1)
        return loop(self.params, sampled=True, controller=self.ctrl, plant=(phi, g0, g1)).a

    def _check(self, plant: tuple[Array, Array, Array]) -> None:
        theta = np.concatenate([m.reshape(-1) for m in plant])
        direct = self._at(theta)
        if np.abs(self.offset + self.basis @ theta - direct).max() > 1e-9 * max(np.abs(direct).max(), 1.0):
            raise AnalysisError("the sampled loop matrix is not affine in the sampled plant; the "
                                "sampled certificate does not apply to this design")

    def _apply(self, theta: Array) -> Array:
        return self.offset + np.einsum("ijk,...k->...ij", self.basis, theta)

    def at_points(self, points: Mapping[str, Array]) -> Array:
        """The runtime's loop matrices at ``points`` (batched): :func:`sampled_plant` there,
        assembled by the loop (through the affine map read off it, equal to it to rounding)."""
        plant = sampled_plant(self.params.replace(**{PARAM_KEYS[k]: v for k, v in points.items()}))
        return self._apply(_flat(plant, lambda m: m))

    def enclose(self, phi: iv.IMat, g0: iv.IMat, g1: iv.IMat) -> iv.IMat:
        centre = self._apply(_flat((phi, g0, g1), lambda m: m.mid))
        radius = np.einsum("ijk,...k->...ij", np.abs(self.basis), _flat((phi, g0, g1), lambda m: m.rad))
        return iv.IMat(centre, radius * (1.0 + 1e-12) + 16 * iv.EPS * np.abs(centre))


def _flat(parts: Any, get: Any) -> Array:
    """The 8 entries of (Phi, Gamma0, Gamma1) in a row (batched)."""
    arrays = [get(m) for m in parts]
    batch = np.broadcast_shapes(*(a.shape[:-2] for a in arrays))
    return np.concatenate([np.broadcast_to(a, batch + a.shape[-2:]).reshape(batch + (-1,))
                           for a in arrays], axis=-1)


def plant_enclosure(config: Config, lo: Mapping[str, Any], hi: Mapping[str, Any]) -> tuple[iv.IMat, ...]:
    """``(Phi, Gamma0, Gamma1)`` enclosed for every plant in the sub-box [lo, hi] (values or
    arrays of sub-boxes; the keys not given at their config values)."""
    flat = config.flat()

    def bounds(key: str) -> tuple[Array, Array]:
        if key in lo:
            return np.asarray(lo[key], float), np.asarray(hi[key], float)
        return np.asarray(float(flat[key])), np.asarray(float(flat[key]))
    (j0, j1), (k0, k1) = bounds("plant.inertia"), bounds("environment.stiffness")
    (d0, d1), (b0, b1) = bounds("environment.damping"), bounds("plant.viscous_friction")
    shape = np.broadcast_shapes(j0.shape, k0.shape, d0.shape, b0.shape)
    a_lo, a_hi = np.zeros(shape + (2, 2)), np.zeros(shape + (2, 2))
    a_lo[..., 0, 1] = a_hi[..., 0, 1] = 1.0
    a_lo[..., 1, 0], a_hi[..., 1, 0] = -k1 / j0, -k0 / j1
    a_lo[..., 1, 1], a_hi[..., 1, 1] = -(b1 + d1) / j0, -(b0 + d0) / j1
    g_lo, g_hi = np.zeros(shape + (2, 1)), np.zeros(shape + (2, 1))
    g_lo[..., 1, 0], g_hi[..., 1, 0] = 1.0 / j1, 1.0 / j0
    a, g = iv.from_bounds(a_lo, a_hi), iv.from_bounds(g_lo, g_hi)
    s = balance_scaling(a.mid)
    a_s, g_s = iv.scaled(a, g, s)
    period, delay = float(config.loop.period), float(config.design.input_delay)
    if delay > 0.0:
        phi, g0, g1 = iv.hold_delayed(a_s, g_s, period, delay)
    else:
        phi, g0 = iv.hold(a_s, g_s, period)
        g1 = iv.IMat(np.zeros(shape + (2, 1)), np.zeros(shape + (2, 1)))
    return iv.unscaled(phi, s, True), iv.unscaled(g0, s, False), iv.unscaled(g1, s, False)


def lyapunov_closes(enclosure: iv.IMat) -> NDArray[np.bool_]:
    """Step 2 of the module's argument on each enclosure ``A_m +- R`` (batched): with
    ``P = L L^T`` from the Lyapunov equation of ``A_m / r`` (r halfway between the spectral
    radius and 1), ``||A_m||_P + || |L^T| R |L^-T| ||_2 < 1`` closes the sub-box."""
    # a sub-box too wide for its enclosure to stay finite (the exponential of an interval matrix
    # over a box of friction 0..1e7 overflows) does not close: it is halved again, and the budget
    # ends undecided (numpy's SVD failed on it: "the certificate cannot answer this box")
    finite = np.all(np.isfinite(enclosure.mid) & np.isfinite(enclosure.rad), axis=(-2, -1))
    mid = np.where(finite[..., None, None], enclosure.mid, 0.0)
    s = balance_scaling(mid)
    f = s[..., None, :] / s[..., :, None]
    a, r = mid * f, np.where(finite[..., None, None], enclosure.rad, 0.0) * f
    n = a.shape[-1]
    rho = np.max(np.abs(np.linalg.eigvals(a)), axis=-1)
    ok = finite & (rho < 1.0)
    m = a.swapaxes(-1, -2) / np.where(ok, 0.5 * (1.0 + rho), 1.0)[..., None, None]
    # X - M X M^T = I, row-major vec: (I - kron(M, M)) vec X = vec I
    kron = np.einsum("...ij,...kl->...ikjl", m, m).reshape(m.shape[:-2] + (n * n, n * n))
    rhs = np.broadcast_to(np.eye(n).reshape(-1), m.shape[:-2] + (n * n,))[..., None]
    x = np.linalg.solve(np.eye(n * n) - kron, rhs)
    p = x[..., 0].reshape(m.shape)
    p = 0.5 * (p + p.swapaxes(-1, -2))
    ok &= np.all(np.isfinite(p), axis=(-2, -1))
    ok &= np.linalg.eigvalsh(np.where(ok[..., None, None], p, np.eye(n)))[..., 0] > 0.0
    chol = np.linalg.cholesky(np.where(ok[..., None, None], p, np.eye(n)))
    left = chol.swapaxes(-1, -2)
    right = np.linalg.inv(left)
    norm_a = np.linalg.norm(left @ a @ right, 2, axis=(-2, -1))
    norm_e = np.linalg.norm(np.abs(left) @ r @ np.abs(right), 2, axis=(-2, -1))
    # the floating-point error of the products and of the inverse, a few ulps each
    cond = np.linalg.norm(left, 2, axis=(-2, -1)) * np.linalg.norm(right, 2, axis=(-2, -1))
    slack = 64 * n * iv.EPS * cond * (1.0 + np.linalg.norm(a, 2, axis=(-2, -1)))
    return np.asarray(ok & (norm_a + norm_e < 1.0 - slack))


def spectral_radius(config: Config, point: Mapping[str, float]) -> float:
    """Of the runtime's sampled loop at ``point`` (>= 1: unstable)."""
    with np.errstate(all="ignore"):
        a = loop(params_at(config, point), sampled=True).a
    return float(np.max(np.abs(np.linalg.eigvals(a))))


def certify_sampled(config: Config, box: Box, *, refinements: int = DEFAULT_REFINEMENTS) -> SampledCertificate:
    """Bisect the box until every sub-box closes (certified), a vertex or a sub-box's centre
    is unstable (refuted) or ``refinements`` bisections are spent (undecided)."""
    with one_blas_thread(), np.errstate(all="ignore"):
        affine = _AffineLoop(config, box.centre())
        vertices = np.array([[v[k] for k in box.keys] for v in box.vertices()])
        rho = _radii(affine, box.keys, vertices)
        if np.max(rho) >= 1.0:
            point = dict(zip(box.keys, vertices[int(np.argmax(rho))].tolist()))
            return SampledCertificate(Verdict.REFUTED, box, 0, 0, point, spectral_radius(config, point))
        return _refine(config, box, affine, refinements, float(np.max(rho)))


def _radii(affine: _AffineLoop, keys: tuple[str, ...], points: Array) -> Array:
    a = affine.at_points({k: points[:, i] for i, k in enumerate(keys)})
    return np.max(np.abs(np.linalg.eigvals(a)), axis=-1)


def _refine(config: Config, box: Box, affine: _AffineLoop, refinements: int, worst: float) -> SampledCertificate:
    """Level by level: every open sub-box's centre evaluated and its bound tried at once;
    those that do not close are halved for the next level."""
    lo, hi = np.array([box.lo]), np.array([box.hi])
    done = closed = 0
    while lo.shape[0]:
        keep = np.zeros(lo.shape[0], bool)
        for i in range(0, lo.shape[0], CHUNK):
            part = slice(i, i + CHUNK)
            centres = _middle(box.keys, lo[part], hi[part])
            rho = _radii(affine, box.keys, centres)
            worst = max(worst, float(rho.max()))
            if rho.max() >= 1.0:
                point = dict(zip(box.keys, centres[int(np.argmax(rho))].tolist()))
                return SampledCertificate(Verdict.REFUTED, box, done, closed, point,
                                          spectral_radius(config, point))
            enclosure = affine.enclose(*plant_enclosure(
                config, {k: lo[part, j] for j, k in enumerate(box.keys)},
                {k: hi[part, j] for j, k in enumerate(box.keys)}))
            keep[part] = ~lyapunov_closes(enclosure)
        closed += int(np.sum(~keep))
        if not keep.any():
            return SampledCertificate(Verdict.CERTIFIED, box, done, closed, None, worst)
        if done + int(keep.sum()) > refinements:
            return SampledCertificate(Verdict.UNDECIDED, box, done, closed, None, worst)
        done += int(keep.sum())
        lo, hi = _bisect(box.keys, lo[keep], hi[keep])
    return SampledCertificate(Verdict.CERTIFIED, box, done, closed, None, worst)


def _middle(keys: tuple[str, ...], lo: Array, hi: Array) -> Array:
    """Where each sub-box is split along each key: the geometric mean along a positive key
    that is wide (or the reciprocal key), the arithmetic mean otherwise."""
    reciprocal = np.array([k in RECIPROCAL_KEYS for k in keys])
    with np.errstate(divide="ignore", invalid="ignore"):
        geometric = (lo > 0.0) & ((hi / lo >= LOG_SPLIT_RATIO) | reciprocal)
        return np.where(geometric, np.sqrt(np.abs(lo * hi)), 0.5 * (lo + hi))


def _bisect(keys: tuple[str, ...], lo: Array, hi: Array) -> tuple[Array, Array]:
    """Two halves of each sub-box along the key widest relative to its size."""
    with np.errstate(divide="ignore", invalid="ignore"):
        width = np.where(lo > 0.0, np.log(hi / lo), np.where(hi > lo, np.inf, 0.0))
    axis = np.argmax(width, axis=-1)
    rows = np.arange(lo.shape[0])
    mid = _middle(keys, lo, hi)[rows, axis]
    lo2, hi1 = lo.copy(), hi.copy()
    lo2[rows, axis] = mid
    hi1[rows, axis] = mid
    return np.concatenate([lo, lo2]), np.concatenate([hi1, hi])


__all__ = ["DEFAULT_REFINEMENTS", "SampledCertificate", "certify_sampled", "lyapunov_closes",
           "plant_enclosure", "spectral_radius"]
