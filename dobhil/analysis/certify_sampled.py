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

import heapq
import itertools
import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
import scipy.linalg

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
DEFAULT_REFINEMENTS = 2000

#: a sub-box is split at its geometric mean along a positive key at least this wide (HI / LO)
LOG_SPLIT_RATIO = 4.0


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

    def at_point(self, point: Mapping[str, float]) -> Array:
        """The runtime's loop matrix at ``point``: :func:`sampled_plant` there, assembled by
        the loop (through the affine map read off it, equal to it to rounding)."""
        values = {PARAM_KEYS[k]: v for k, v in point.items()}
        plant = sampled_plant(self.params.replace(**values))
        return self.offset + self.basis @ np.concatenate([m.reshape(-1) for m in plant])

    def enclose(self, phi: iv.IMat, g0: iv.IMat, g1: iv.IMat) -> iv.IMat:
        mid = np.concatenate([m.mid.reshape(-1) for m in (phi, g0, g1)])
        rad = np.concatenate([m.rad.reshape(-1) for m in (phi, g0, g1)])
        centre = self.offset + self.basis @ mid
        radius = np.abs(self.basis) @ rad
        return iv.IMat(centre, radius * (1.0 + 1e-12) + 16 * iv.EPS * np.abs(centre))


def plant_enclosure(config: Config, lo: Mapping[str, float], hi: Mapping[str, float]) -> tuple[iv.IMat, ...]:
    """``(Phi, Gamma0, Gamma1)`` enclosed for every plant in the sub-box [lo, hi]."""
    flat = config.flat()

    def bounds(key: str) -> tuple[float, float]:
        return (lo[key], hi[key]) if key in lo else (float(flat[key]), float(flat[key]))
    j = bounds("plant.inertia")
    k = bounds("environment.stiffness")
    d = bounds("environment.damping")
    b = bounds("plant.viscous_friction")
    a_lo = np.array([[0.0, 1.0], [-k[1] / j[0], -(b[1] + d[1]) / j[0]]])
    a_hi = np.array([[0.0, 1.0], [-k[0] / j[1], -(b[0] + d[0]) / j[1]]])
    a = iv.from_bounds(a_lo, a_hi)
    g = iv.from_bounds(np.array([[0.0], [1.0 / j[1]]]), np.array([[0.0], [1.0 / j[0]]]))
    s = balance_scaling(a.mid)
    a_s, g_s = iv.scaled(a, g, s)
    period, delay = float(config.loop.period), float(config.design.input_delay)
    if delay > 0.0:
        phi, g0, g1 = iv.hold_delayed(a_s, g_s, period, delay)
    else:
        phi, g0 = iv.hold(a_s, g_s, period)
        g1 = iv.IMat(np.zeros((2, 1)), np.zeros((2, 1)))
    return iv.unscaled(phi, s, True), iv.unscaled(g0, s, False), iv.unscaled(g1, s, False)


def lyapunov_closes(enclosure: iv.IMat) -> bool:
    """Step 2 of the module's argument on one enclosure ``A_m +- R``: with ``P = L L^T``
    from the Lyapunov equation of ``A_m / r`` (r between the spectral radius and 1), the
    induced norm ``||A||_P = ||L^T A L^-T||_2`` bounds the spectral radius of every member:
    ``||A_m + E||_P <= ||A_m||_P + || |L^T| R |L^-T| ||_2 < 1`` closes the sub-box."""
    s = balance_scaling(enclosure.mid)
    f = s[None, :] / s[:, None]
    a, r = enclosure.mid * f, enclosure.rad * f
    rho = float(np.max(np.abs(np.linalg.eigvals(a))))
    if rho >= 1.0:
        return False
    target = 0.5 * (1.0 + rho)
    p = scipy.linalg.solve_discrete_lyapunov(a.T / target, np.eye(a.shape[0]))
    try:
        chol = np.linalg.cholesky(0.5 * (p + p.T))
    except np.linalg.LinAlgError:
        return False
    left, right = chol.T, np.linalg.inv(chol.T)
    norm_a = float(np.linalg.norm(left @ a @ right, 2))
    norm_e = float(np.linalg.norm(np.abs(left) @ r @ np.abs(right), 2))
    # the floating-point error of the products and of the inverse, a few ulps each
    slack = 64 * a.shape[0] * iv.EPS * float(np.linalg.cond(chol)) * (1.0 + float(np.linalg.norm(a, 2)))
    return norm_a + norm_e < 1.0 - slack


def spectral_radius(config: Config, point: Mapping[str, float]) -> float:
    """Of the runtime's sampled loop at ``point`` (>= 1: unstable)."""
    with np.errstate(all="ignore"):
        a = loop(params_at(config, point), sampled=True).a
    return float(np.max(np.abs(np.linalg.eigvals(a))))


def certify_sampled(config: Config, box: Box, *, refinements: int = DEFAULT_REFINEMENTS) -> SampledCertificate:
    """Bisect the box until every sub-box closes (certified), a centre or vertex is unstable
    (refuted) or ``refinements`` bisections are spent (undecided)."""
    with one_blas_thread(), np.errstate(all="ignore"):
        witness = _unstable_vertex(config, box)
        if witness is not None:
            return SampledCertificate(Verdict.REFUTED, box, 0, 0, witness[0], witness[1])
        return _refine(config, box, _AffineLoop(config, box.centre()), refinements)


def _refine(config: Config, box: Box, affine: _AffineLoop, refinements: int) -> SampledCertificate:
    """Sub-boxes in order of their centre's spectral radius, largest first: the ones nearest
    instability are split first, so an unstable pocket is found early."""
    count = itertools.count()   # ties broken by age: the heap never compares dicts
    heap: list[tuple[float, int, dict[str, float], dict[str, float]]] = []

    def push(lo: dict[str, float], hi: dict[str, float]) -> float:
        rho = float(np.max(np.abs(np.linalg.eigvals(affine.at_point(_split_point(lo, hi))))))
        heapq.heappush(heap, (-rho, next(count), lo, hi))
        return rho
    worst = push(dict(zip(box.keys, box.lo)), dict(zip(box.keys, box.hi)))
    done = closed = 0
    while heap:
        neg_rho, _, lo, hi = heapq.heappop(heap)
        if -neg_rho >= 1.0:
            centre = _split_point(lo, hi)
            return SampledCertificate(Verdict.REFUTED, box, done, closed, centre,
                                      spectral_radius(config, centre))
        if lyapunov_closes(affine.enclose(*plant_enclosure(config, lo, hi))):
            closed += 1
            continue
        if done >= refinements:
            return SampledCertificate(Verdict.UNDECIDED, box, done, closed, None, worst)
        done += 1
        for half in _bisect(lo, hi):
            worst = max(worst, push(*half))
    return SampledCertificate(Verdict.CERTIFIED, box, done, closed, None, worst)


def _unstable_vertex(config: Config, box: Box) -> tuple[dict[str, float], float] | None:
    for vertex in box.vertices():
        rho = spectral_radius(config, vertex)
        if rho >= 1.0:
            return vertex, rho
    return None


def _split_point(lo: Mapping[str, float], hi: Mapping[str, float]) -> dict[str, float]:
    return {k: _middle(k, lo[k], hi[k]) for k in lo}


def _middle(key: str, lo: float, hi: float) -> float:
    if lo > 0.0 and (hi / lo >= LOG_SPLIT_RATIO or key in RECIPROCAL_KEYS):
        return math.sqrt(lo * hi)
    return 0.5 * (lo + hi)


def _bisect(lo: Mapping[str, float], hi: Mapping[str, float]) -> list[tuple[dict[str, float], dict[str, float]]]:
    """Two halves along the key widest relative to its size."""
    def width(k: str) -> float:
        return math.log(hi[k] / lo[k]) if lo[k] > 0.0 else math.inf if hi[k] > lo[k] else 0.0
    key = max(lo, key=width)
    m = _middle(key, lo[key], hi[key])
    return [(dict(lo), {**hi, key: m}), ({**lo, key: m}, dict(hi))]


__all__ = ["DEFAULT_REFINEMENTS", "SampledCertificate", "certify_sampled", "lyapunov_closes",
           "plant_enclosure", "spectral_radius"]
