"""Stability of the force loop over the whole range of the force gain C_f, exactly.

The closed loop at gain k has the state matrix ``A(k) = A0 - k B C`` (see
:mod:`dobhil.synthesis.loop`), i.e. the characteristic polynomial
``D(s) + k N(s)`` with ``L = N / D``. Stability can only change at a gain where a
root crosses the stability boundary (the imaginary axis, or the unit circle for
the sampled loop). Those gains are found exactly from the root locus'
boundary crossings: ``D(jw) + k N(jw) = 0`` needs
``Im(D(jw) conj(N(jw))) = 0`` -- a real polynomial in w -- and then
``k = -Re(D conj N) / |N|^2``; a root through infinity (equal degrees) gives
``k = -d_n / n_n``. The sampled loop is mapped onto the same problem by the
bilinear map ``z = (1 + w) / (1 - w)`` (unit circle -> imaginary axis). Between two
consecutive crossing gains the verdict is constant, so one eigenvalue test of
``A(k)`` per interval decides it (no gain grid). Everything is batched.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from math import comb
from typing import TypeVar

import numpy as np
from numpy.typing import NDArray

from dobhil.analysis.polynomials import (Array, CArray, batched_roots, eval_poly,
                                         poly_from_roots, zeros_and_numerator)
from dobhil.errors import AnalysisError, DobhilError, exception_line
from dobhil.synthesis.numerics import balance

_T = TypeVar("_T")


def answered(compute: Callable[[], _T], *, what: str, of: str) -> _T:
    """``compute()``, numpy's warnings silenced; a design whose numbers still overflow
    within the keys' ranges (an inertia of 1e-300: matrices or coefficients not finite) is
    one line, an :class:`AnalysisError` "``what`` cannot answer ``of`` (why)", not a
    traceback: ``dobhil analyze`` and ``dobhil certify`` say it alike."""
    try:
        with np.errstate(all="ignore"):
            return compute()
    except DobhilError:
        raise
    except (np.linalg.LinAlgError, ValueError, ZeroDivisionError, OverflowError) as exc:
        why = exception_line(exc, named=False)[:120]
        raise AnalysisError(f"{what} cannot answer {of} ({why}); check that it is within the keys' ranges") from None

#: a pole counts as stable when Re(s) < -STABILITY_TOL * scale (continuous) or
#: |z| < 1 - STABILITY_TOL (sampled)
STABILITY_TOL = 1e-9

#: an open-loop pole within this (relative) distance of the stability boundary is taken
#: to lie on it exactly (the loop's integrator: structurally at s = 0 / z = 1)
MARGINAL_RTOL = 1e-10


@dataclass(frozen=True)
class GainMap:
    """Batched results; intervals are padded with NaN (``hi = inf`` when unbounded)."""

    poles: CArray                 # open-loop poles, batch + (n,)
    zeros: CArray                 # open-loop zeros, batch + (n-1,), NaN padded
    relative_degree: NDArray[np.int64]
    minimum_phase: NDArray[np.bool_]
    crossings: Array              # boundary-crossing gains, sorted, NaN padded
    interval_lo: Array            # stable intervals (lo, hi), NaN padded
    interval_hi: Array
    max_stable_gain: Array        # largest k with (0, k) all stable; inf: unbounded; 0: none
    sampled: bool

    def intervals(self, index: tuple[int, ...] = ()) -> list[tuple[float, float]]:
        lo, hi = self.interval_lo[index], self.interval_hi[index]
        return [(float(a), float(b)) for a, b in zip(lo, hi) if not np.isnan(a)]


def is_stable(poles: CArray, sampled: bool) -> NDArray[np.bool_]:
    """Every pole strictly inside the stability region (NaN entries ignored)."""
    p = np.where(np.isnan(poles), -1.0 if not sampled else 0.0, poles)
    if sampled:
        return np.all(np.abs(p) < 1.0 - STABILITY_TOL, axis=-1)
    scale = np.maximum(np.nanmax(np.abs(p), axis=-1, initial=0.0), 1.0)
    return np.all(p.real < -STABILITY_TOL * scale[..., None], axis=-1)


#: how near z = 1 (sampled), or how near the real axis (continuous: its real part is within
#: the resolution already), a pole of :func:`unresolved_pole` is the position's drift
DRIFT_ATOL = 1e-6


def _outermost(poles: CArray, sampled: bool) -> tuple[CArray, NDArray[np.bool_]]:
    """Per loop of a batch (poles: batch + (n,)): the pole nearest the outside of the stable
    region (largest |z|, or largest Re(s)), and whether it lies within :data:`STABILITY_TOL`
    of the boundary (scaled as :func:`is_stable` scales it)."""
    p = np.asarray(poles, complex)
    if sampled:
        edge = np.take_along_axis(p, np.argmax(np.abs(p), axis=-1)[..., None], -1)[..., 0]
        return edge, np.abs(np.abs(edge) - 1.0) <= STABILITY_TOL
    scale = np.maximum(np.max(np.abs(p), axis=-1, initial=0.0), 1.0)
    edge = np.take_along_axis(p, np.argmax(p.real, axis=-1)[..., None], -1)[..., 0]
    return edge, np.abs(edge.real) <= STABILITY_TOL * scale


def _at_drift(edge: CArray, sampled: bool) -> NDArray[np.bool_]:
    """Whether poles are the position's drift: real, at z = 1 / s = 0 (within DRIFT_ATOL)."""
    return np.asarray(np.abs(edge - 1.0) <= DRIFT_ATOL if sampled else np.abs(np.imag(edge)) <= DRIFT_ATOL)


def drifts(poles: CArray, sampled: bool) -> NDArray[np.bool_]:
    """Per loop of a batch (poles: batch + (n,)): not stable only by the position's pole at
    z = 1 / s = 0, within the analysis' resolution (:func:`unresolved_pole` and
    :func:`is_position_drift` for every loop at once): K_env = 0, or so small it holds the
    position as little."""
    edge, near = _outermost(poles, sampled)
    return near & _at_drift(edge, sampled)


def unresolved_pole(poles: CArray, sampled: bool) -> complex | None:
    """The outermost of one loop's ``poles`` when no pole lies clearly outside the stable
    region, only within :data:`STABILITY_TOL` of its boundary, where round-off decides the
    side and :func:`is_stable` cannot tell (None: one lies clearly outside, or none near).
    A soft environment puts the position's pole there: s about -K_env / D_env, -2e-11 1/s at
    K_env 1e-9 N m/rad and D_env 50."""
    edge, near = _outermost(np.asarray(poles, complex)[None], sampled)
    return complex(edge[0]) if near[0] else None


def is_position_drift(pole: complex, sampled: bool) -> bool:
    """Whether a pole of :func:`unresolved_pole` is the position's drift (a real pole at
    z = 1 / s = 0) rather than the force gain at an edge of a stable interval (a pole
    crossing at a frequency)."""
    return bool(_at_drift(np.asarray(pole, complex), sampled))


def gain_map(a0: Array, b: Array, c: Array, *, sampled: bool) -> GainMap:
    """Poles, zeros, crossings and stable gain intervals of ``A0 - k B C`` for k > 0."""
    a0, b, c = balance(a0, b, c)
    poles = np.asarray(np.linalg.eigvals(a0), dtype=complex)
    zeros, num, rel = zeros_and_numerator(a0, b, c)
    poles, marginal = _snap_marginal(poles, sampled)
    den = poly_from_roots(poles)
    minimum_phase = _minimum_phase(zeros, sampled)
    if sampled:
        den, num = _bilinear(den), _bilinear(num)
        scale_roots = np.concatenate([_to_w(poles), _to_w(zeros)], axis=-1)
        marginal_w = np.where(marginal, _to_w(poles).imag, np.nan)
    else:
        scale_roots = np.concatenate([poles, zeros], axis=-1)
        marginal_w = np.where(marginal, poles.imag, np.nan)
    crossings = _crossing_gains(den, num, scale_roots, marginal_w)
    lo, hi, kmax = _intervals(a0, b, c, crossings, sampled)
    return GainMap(poles=poles, zeros=zeros, relative_degree=rel, minimum_phase=minimum_phase,
                   crossings=crossings, interval_lo=lo, interval_hi=hi, max_stable_gain=kmax,
                   sampled=sampled)


def _snap_marginal(poles: CArray, sampled: bool) -> tuple[CArray, NDArray[np.bool_]]:
    """Open-loop poles on the stability boundary up to rounding, put on it exactly.

    The loop's integrator sits at s = 0 (z = 1) by construction; eigenvalues return it
    at +-1e-15 or so. Left there, the root locus' crossing at k = 0 shows up as a
    crossing at a tiny positive gain (a spurious unstable sliver). Snapped, the crossing
    at its frequency is known to happen at k = 0 and is dropped."""
    if sampled:
        mag = np.abs(poles)
        marginal = np.abs(mag - 1.0) <= MARGINAL_RTOL
        snapped = np.where(marginal, poles / np.where(marginal, mag, 1.0), poles)
        snapped = np.where(marginal & (np.abs(snapped - 1.0) <= MARGINAL_RTOL), 1.0, snapped)
    else:
        scale = np.maximum(np.max(np.abs(poles), axis=-1, keepdims=True), 1e-300)
        marginal = np.abs(poles.real) <= MARGINAL_RTOL * scale
        snapped = np.where(marginal, 1j * poles.imag, poles)
        snapped = np.where(marginal & (np.abs(snapped) <= MARGINAL_RTOL * scale), 0.0, snapped)
    return snapped.astype(complex), marginal


def _minimum_phase(zeros: CArray, sampled: bool) -> NDArray[np.bool_]:
    z = np.where(np.isnan(zeros), 0.0 if sampled else -1.0, zeros)
    if sampled:
        return np.all(np.abs(z) < 1.0, axis=-1)
    return np.all(z.real < 0.0, axis=-1)


def _to_w(z: CArray) -> CArray:
    with np.errstate(divide="ignore", invalid="ignore"):
        return (z - 1.0) / (z + 1.0)


def _bilinear(coef: Array) -> Array:
    """Coefficients in w of ``(1 - w)^n p((1 + w) / (1 - w))`` (z-coefficients in)."""
    n = coef.shape[-1] - 1
    basis = np.zeros((n + 1, n + 1))
    for p in range(n + 1):  # row for z^p: (1 + w)^p (1 - w)^(n - p)
        basis[n - p] = np.convolve(_binom(p, 1.0), _binom(n - p, -1.0))
    return coef @ basis


def _binom(n: int, sign: float) -> Array:
    """Coefficients of (sign w + 1)^n, highest power first."""
    return np.array([comb(n, j) * sign ** (n - j) for j in range(n + 1)])


def _scaled(den: Array, num: Array, roots: CArray) -> tuple[Array, Array, Array]:
    """Both polynomials in s = w0 s^ with w0 the largest finite root magnitude."""
    mags = np.where(np.isfinite(roots) & (np.abs(roots) < 1e12), np.abs(roots), 0.0)
    w0 = np.maximum(mags.max(axis=-1, initial=0.0), 1e-12)
    n = den.shape[-1] - 1
    powers = w0[..., None] ** np.arange(n, -1, -1)
    d, m = den * powers, num * powers
    norm = np.maximum(np.abs(d).max(axis=-1, keepdims=True), 1e-300)
    return d / norm, m / norm, w0


def _crossing_gains(den: Array, num: Array, roots: CArray, marginal_w: Array) -> Array:
    """Positive gains at which a root of D + k N lies on the imaginary axis (sorted).

    ``marginal_w``: frequencies (NaN padded) of open-loop poles on the axis; a root of
    D + k N there has k = 0 exactly (unless N vanishes too: a cancellation, which the
    interval tests see), so those candidates are not crossings."""
    d, m, w0 = _scaled(den, num, roots)
    n = d.shape[-1] - 1
    jpow = 1j ** np.arange(n, -1, -1)
    dj, nj = d * jpow, m * np.conj(jpow)          # D(jw), conj(N(jw)) as polynomials in w
    prod = np.zeros(d.shape[:-1] + (2 * n + 1,), dtype=complex)
    for i in range(n + 1):
        prod[..., i:i + n + 1] += dj[..., i:i + 1] * nj
    omegas = _odd_roots(prod.imag)
    real = np.abs(omegas.imag) <= 1e-6 * (1.0 + np.abs(omegas.real))
    w = np.where(real & (omegas.real >= 0), omegas.real, np.nan)
    mw = np.abs(marginal_w) / w0[..., None]
    with np.errstate(invalid="ignore"):
        at_pole = np.any(np.abs(w[..., :, None] - mw[..., None, :])
                         <= 1e-6 * (1.0 + mw[..., None, :]), axis=-1)
    w = np.where(at_pole, np.nan, w)
    dv = eval_poly(d, 1j * w)
    nv = eval_poly(m, 1j * w)
    with np.errstate(divide="ignore", invalid="ignore"):
        k = -(dv * np.conj(nv)).real / np.abs(nv) ** 2
        k_inf = np.where(np.abs(m[..., 0]) > 1e-13, -d[..., 0] / m[..., 0], np.nan)
    k = np.concatenate([k, k_inf[..., None]], axis=-1)
    # w = 0 with D(0) = 0 (the integrator) gives k = 0 up to rounding: not a crossing
    k_floor = 1e-9 * np.abs(d).max(axis=-1) / np.maximum(np.abs(m).max(axis=-1), 1e-300)
    k = np.where(np.isfinite(k) & (k > k_floor[..., None]), k, np.nan)
    return np.sort(k, axis=-1)


def _odd_roots(coef: Array) -> CArray:
    """The roots w with Re(w) >= 0 of an odd polynomial (coefficients batch + (2n+1,),
    highest power first, those of the even powers zero) -- ``Im(D(jw) conj(N(jw)))`` for
    real D, N is one: each of its terms is ``d_i m_l j^(l-i)``, imaginary exactly when
    ``l - i``, and so the power of w, is odd. It is ``w q(w^2)``: its roots are 0 and the
    square roots of q's, found as the roots of a polynomial of half the degree (a 3 x 3
    companion matrix for the continuous 4-state loop, not a 7 x 7: a fifth of the time).
    The principal square root keeps Re(w) >= 0; -w, also a root, is no frequency. A
    polynomial with a coefficient not finite, or all zero, has none (as :func:`batched_roots`)."""
    usable = np.all(np.isfinite(coef), axis=-1) & np.any(coef != 0, axis=-1)
    u = batched_roots(np.where(usable[..., None], coef[..., 1::2], np.nan))
    zero = np.where(usable, 0.0, np.nan)[..., None]
    return np.concatenate([np.sqrt(u.astype(complex)), zero], axis=-1)


def _spectral_margin(a: Array, sampled: bool) -> Array:
    """How far outside the stability region the worst pole is (negative: inside),
    relative: ``max |z| - 1`` sampled, ``max Re(s) / max(1, |s|_max)`` continuous."""
    poles = np.linalg.eigvals(a)
    if sampled:
        return np.max(np.abs(poles), axis=-1) - 1.0
    scale = np.maximum(np.max(np.abs(poles), axis=-1), 1.0)
    return np.max(poles.real, axis=-1) / scale


def _margins_at(a0: Array, bc: Array, k: Array, sampled: bool) -> Array:
    """Spectral margin of ``A0 - k BC`` at every finite entry of k (batch + (p,)); NaN
    elsewhere. Only the finite entries are computed."""
    shape = k.shape
    flat = k.reshape(a0.shape[:-2] + (-1,))
    out = np.full(flat.shape, np.nan)
    mask = np.isfinite(flat)
    if mask.any():
        batch_idx = np.nonzero(mask)[:-1]
        acl = a0[batch_idx] - flat[mask][:, None, None] * bc[batch_idx]
        out[mask] = _spectral_margin(acl, sampled)
    return out.reshape(shape)


#: where each bounded interval (lo, hi) between crossings is tested: at these fractions
#: of the way when hi/lo < 10, at these fractions of the log-distance when wider, and for
#: the first interval (0, hi) at ``hi`` times a geometric sequence from
#: ``min(1e-9, 1e-9 kscale / hi)`` up to 0.98 (small gains, however far the first crossing)
TEST_FRACTIONS = (1e-3, 0.02, 0.3, 0.5, 0.7, 0.98)
LOG_FRACTIONS = (0.02, 0.2, 0.4, 0.6, 0.8, 0.98)
#: multiples of the last crossing tested in the unbounded interval, and of the gain
#: scale ``|A0| / |BC|`` when there is no crossing at all
TAIL_FACTORS = (1.0 + 1e-6, 1.001, 1.5, 10.0, 1e3, 1e6)
SCALE_FACTORS = (1e-9, 1e-6, 1e-3, 1.0, 1e3, 1e6)


def _test_gains(crossings: Array, kscale: Array) -> tuple[Array, Array]:
    """Test gains (batch + (m+1, 6)) and the interval edges (batch + (m+1,), lo)."""
    batch = crossings.shape[:-1]
    edges = np.concatenate([np.zeros(batch + (1,)), crossings], axis=-1)
    upper = np.concatenate([crossings, np.full(batch + (1,), np.nan)], axis=-1)
    count = np.sum(~np.isnan(crossings), axis=-1)
    last = np.take_along_axis(edges, count[..., None], axis=-1)
    idx = np.arange(upper.shape[-1])
    tail = idx == count[..., None]
    lo, hi = edges[..., None], upper[..., None]
    with np.errstate(divide="ignore", invalid="ignore"):
        linear = lo + (hi - lo) * np.asarray(TEST_FRACTIONS)
        logs = lo * (hi / lo) ** np.asarray(LOG_FRACTIONS)
        f_min = np.minimum(1e-9, 1e-9 * kscale[..., None, None] / hi)
        geo = hi * f_min ** (1.0 - np.linspace(0.0, 1.0, len(TEST_FRACTIONS))) * np.asarray(
            [1.0] * (len(TEST_FRACTIONS) - 1) + [0.98])
        bounded = np.where(lo == 0, geo, np.where(hi / lo < 10.0, linear, logs))
    unbounded = np.where(last[..., None] > 0, last[..., None] * np.asarray(TAIL_FACTORS),
                         kscale[..., None, None] * np.asarray(SCALE_FACTORS))
    gains = np.where(tail[..., None], unbounded, bounded)
    return gains, edges


def _verify(a0: Array, bc: Array, crossings: Array, sampled: bool,
            kscale: Array) -> tuple[Array, Array | None]:
    """Crossings completed by eigenvalue tests: inside every interval between two
    crossings, six gains must agree (all strictly stable or all strictly unstable).
    Where they do not, the root locus crossed the boundary at a gain the polynomial
    roots missed (high order, clustered roots): it is found by bracketing the spectral
    margin (Brent) and added. Designs that agree -- nearly all -- cost six
    eigenvalue problems per interval and nothing else. Returns the crossings and, when
    they are unchanged, the test margins (batch + (m+1, 6))."""
    gains, _ = _test_gains(crossings, kscale)
    margin = _margins_at(a0, bc, gains, sampled).reshape(gains.shape[:-2] + (-1,))
    flat_k = gains.reshape(margin.shape)
    tol = STABILITY_TOL
    verdict = np.where(margin < -tol, 1, np.where(margin > tol, -1, 0))
    # an interval holding both a strictly stable and a strictly unstable test gain
    per_slot = verdict.reshape(gains.shape)
    bad = np.any(np.any(per_slot > 0, axis=-1) & np.any(per_slot < 0, axis=-1), axis=-1)
    if not bad.any():
        return crossings, margin.reshape(gains.shape)
    out = crossings.copy()
    width = out.shape[-1]
    for index in (i for i in np.ndindex(bad.shape) if bad[i]):
        found = []
        decided = np.nonzero(verdict[index] != 0)[0]     # skip the undecided gains
        slots = decided // gains.shape[-1]
        for j0, j1, s0, s1 in zip(decided[:-1], decided[1:], slots[:-1], slots[1:]):
            if s0 != s1 or verdict[index][j0] == verdict[index][j1]:
                continue
            k0, k1 = float(flat_k[index][j0]), float(flat_k[index][j1])

            # imported here, on this rare path only: the stability gate runs this module at
            # the start of every run, and scipy.optimize costs more than the gate itself
            import scipy.optimize

            def f(k: float, at: tuple[int, ...] = index) -> float:
                return float(_spectral_margin(a0[at] - k * bc[at], sampled))
            try:
                found.append(float(scipy.optimize.brentq(f, k0, k1, xtol=1e-15 * k1,
                                                         rtol=1e-15)))
            except ValueError:
                continue
        merged = np.sort(np.concatenate([out[index][~np.isnan(out[index])], found]))
        row = np.full(max(width, merged.size), np.nan)
        row[:merged.size] = merged
        if row.size > width:   # widen the padded array for everyone
            pad = np.full(out.shape[:-1] + (row.size - width,), np.nan)
            out = np.concatenate([out, pad], axis=-1)
            width = row.size
        out[index] = row
    return out, None


#: relative half-widths tried, in turn, to bracket each crossing for polishing. The first
#: bracket is narrower than the iterations' end width (1e-13, with room for the rounding of
#: its ends): where the polynomial roots are already that close (19 of 20 crossings of a
#: sweep of configs/paper/fig2b.yaml), it is the answer and costs two eigenvalue problems,
#: not the six or more of a wider bracket and its iterations
POLISH_BRACKETS = (4e-14, 1e-6, 1e-3, 0.03, 0.2)
POLISH_ITERATIONS = 30


def _polish(a0: Array, bc: Array, crossings: Array, sampled: bool) -> Array:
    """Each crossing gain refined on the eigenvalues themselves: bracketed where the
    spectral margin of ``A0 - k BC`` changes sign, then regula falsi (Illinois), all
    crossings of all designs at once. The polynomial roots locate a crossing to
    rounding only when the poles are well separated; with clusters near z = 1 (small
    g T) they can be percent off, the eigenvalues stay right to ~1e-12."""
    # only the finite crossings, each with its own matrices: the brackets and the iterations
    # solve for these and no others (most crossings settle in a few steps, a few take all)
    at = np.nonzero(np.isfinite(crossings))
    k = crossings[at]
    a_k = np.broadcast_to(a0[at[:-1]], k.shape + a0.shape[-2:])    # one design: no batch index
    bc_k = np.broadcast_to(bc[at[:-1]], k.shape + bc.shape[-2:])

    def margins(x: Array, which: NDArray[np.intp]) -> Array:
        return _spectral_margin(a_k[which] - x[:, None, None] * bc_k[which], sampled)
    lo, hi = np.full(k.shape, np.nan), np.full(k.shape, np.nan)
    f_lo, f_hi = np.full(k.shape, np.nan), np.full(k.shape, np.nan)
    todo = np.arange(k.size)
    for delta in POLISH_BRACKETS:
        if not todo.size:
            break
        k0, k1 = k[todo] * (1 - delta), k[todo] * (1 + delta)
        m0, m1 = margins(k0, todo), margins(k1, todo)
        found = m0 * m1 < 0
        t = todo[found]
        lo[t], hi[t], f_lo[t], f_hi[t] = k0[found], k1[found], m0[found], m1[found]
        todo = todo[~found]
    active = np.nonzero(np.isfinite(lo) & ((hi - lo) > 1e-13 * hi))[0]   # a first bracket may be done
    side = np.zeros(k.shape, int)
    for _ in range(POLISH_ITERATIONS):
        if not active.size:
            break
        lo_a, hi_a, flo_a, fhi_a, side_a = lo[active], hi[active], f_lo[active], f_hi[active], side[active]
        with np.errstate(invalid="ignore", divide="ignore"):
            x = (lo_a * fhi_a - hi_a * flo_a) / (fhi_a - flo_a)
        x = np.where(~((x > lo_a) & (x < hi_a)), 0.5 * (lo_a + hi_a), x)
        fx = margins(x, active)
        left = fx * flo_a > 0                      # root in [x, hi]
        right = ~left                              # root in [lo, x]
        lo_a, flo_a = np.where(left, x, lo_a), np.where(left, fx, flo_a)
        hi_a, fhi_a = np.where(right, x, hi_a), np.where(right, fx, fhi_a)
        # Illinois: halve the stale end's value when the same end moves twice
        fhi_a = np.where(left & (side_a == 1), 0.5 * fhi_a, fhi_a)
        flo_a = np.where(right & (side_a == -1), 0.5 * flo_a, flo_a)
        lo[active], hi[active], f_lo[active], f_hi[active] = lo_a, hi_a, flo_a, fhi_a
        side[active] = np.where(left, 1, -1)
        active = active[(hi_a - lo_a) > 1e-13 * hi_a]
    polished = crossings.copy()
    polished[at] = np.where(np.isfinite(lo), 0.5 * (lo + hi), k)
    return np.sort(polished, axis=-1)


def _intervals(a0: Array, b: Array, c: Array, crossings: Array,
               sampled: bool) -> tuple[Array, Array, Array]:
    """Stability of every interval between consecutive (polished, verified) crossings."""
    bc = b @ c
    kscale = (np.linalg.norm(a0, axis=(-2, -1))
              / np.maximum(np.linalg.norm(bc, axis=(-2, -1)), 1e-300))
    crossings, margin = _verify(a0, bc, _polish(a0, bc, crossings, sampled), sampled, kscale)
    if margin is None:
        gains, _ = _test_gains(crossings, kscale)
        margin = _margins_at(a0, bc, gains, sampled)
    batch = crossings.shape[:-1]
    edges = np.concatenate([np.zeros(batch + (1,)), crossings], axis=-1)
    count = np.sum(~np.isnan(crossings), axis=-1)
    upper = np.concatenate([crossings, np.full(batch + (1,), np.nan)], axis=-1)
    idx = np.arange(upper.shape[-1])
    upper = np.where(idx == count[..., None], np.inf, upper)
    valid = ~np.isnan(upper)
    # stable: some test gain strictly stable, none strictly unstable (a slow pole within
    # rounding of the boundary at the others does not make it unstable)
    with np.errstate(invalid="ignore"):
        stable = (valid & np.any(margin < -STABILITY_TOL, axis=-1)
                  & ~np.any(margin > STABILITY_TOL, axis=-1))
    lo, hi = _merge(edges, upper, stable)
    first_ok = stable[..., 0]
    kmax = np.where(first_ok, hi[..., 0], 0.0)
    return lo, hi, kmax


def _merge(edges: Array, upper: Array, stable: NDArray[np.bool_]) -> tuple[Array, Array]:
    """Join adjacent stable intervals (a crossing that touches but does not cross)."""
    batch, m = stable.shape[:-1], stable.shape[-1]
    flat_s = stable.reshape(-1, m)
    flat_e, flat_u = edges.reshape(-1, m), upper.reshape(-1, m)
    lo = np.full(flat_s.shape, np.nan)
    hi = np.full(flat_s.shape, np.nan)
    starts = flat_s & ~np.concatenate([np.zeros((flat_s.shape[0], 1), bool), flat_s[:, :-1]], 1)
    ends = flat_s & ~np.concatenate([flat_s[:, 1:], np.zeros((flat_s.shape[0], 1), bool)], 1)
    rank_s = np.cumsum(starts, axis=1) - 1
    rows, cols = np.nonzero(starts)
    lo[rows, rank_s[rows, cols]] = flat_e[rows, cols]
    rows, cols = np.nonzero(ends)
    hi[rows, rank_s[rows, cols]] = flat_u[rows, cols]
    return lo.reshape(batch + (m,)), hi.reshape(batch + (m,))


def phase_margin(a0: Array, b: Array, c: Array, gain: Array | float, *, sampled: bool) -> Array:
    """Phase margin [deg] of ``gain * L`` (:func:`phase_crossover`'s margin)."""
    return phase_crossover(a0, b, c, gain, sampled=sampled)[0]


def phase_crossover(a0: Array, b: Array, c: Array, gain: Array | float, *,
                    sampled: bool) -> tuple[Array, Array]:
    """(phase margin [deg], its crossover) of ``gain * L``: the crossover as w [rad/s]
    (continuous) or as the angle of z on the unit circle [rad] (sampled; w T), NaN where
    there is none. The phase margin of ``gain * L`` (``L = C (sI - A0)^-1 B``, sampled: in z): at the
    gain crossover ``|gain L| = 1`` whose phase comes nearest -180 deg, signed, in
    [-180, 180) (python-control's ``stability_margins`` convention); inf where ``|gain L|``
    never crosses 1.

    The crossovers are found the way :func:`gain_map` finds its crossings: on the
    imaginary axis (the unit circle mapped onto it by the bilinear map, where ``L`` keeps
    its values), ``|D(jw)|^2 - gain^2 |N(jw)|^2`` is a real polynomial in w whose
    non-negative real roots are the crossover frequencies -- every one, without a
    frequency grid and without python-control (a run pays for no import of it). The margin
    at each is ``180 + arg(gain L(jw))`` wrapped to [-180, 180)."""
    a0, b, c = balance(a0, b, c)
    poles = np.asarray(np.linalg.eigvals(a0), dtype=complex)
    zeros, num, _ = zeros_and_numerator(a0, b, c)
    poles, _ = _snap_marginal(poles, sampled)
    den = poly_from_roots(poles)
    roots = np.concatenate([poles, zeros], axis=-1)
    if sampled:
        den, num, roots = _bilinear(den), _bilinear(num), _to_w(roots)
    d, m, w0 = _scaled(den, num, roots)
    k = np.asarray(gain, float)[..., None]
    jpow = 1j ** np.arange(d.shape[-1] - 1, -1, -1)
    cross = _abs_squared(d * jpow) - k ** 2 * _abs_squared(m * jpow)
    omegas = batched_roots(cross)
    real = np.abs(omegas.imag) <= 1e-6 * (1.0 + np.abs(omegas.real))
    w = np.where(real & (omegas.real >= 0), omegas.real, np.nan)
    w = np.where(_off_crossover(a0, b, c, k, w * w0[..., None], sampled), np.nan, w)
    with np.errstate(divide="ignore", invalid="ignore"):
        value = k * eval_poly(m, 1j * w) / eval_poly(d, 1j * w)
    margin = np.mod(np.degrees(np.angle(value)) + 180.0, 360.0)
    margin = np.where(margin >= 180.0, margin - 360.0, margin)
    # the worst crossover is the one whose phase comes nearest -180 deg, from either side
    nearest = np.argmin(np.where(np.isfinite(margin), np.abs(margin), np.inf), axis=-1)
    worst = np.take_along_axis(margin, nearest[..., None], axis=-1)[..., 0]
    crossover = np.take_along_axis(w, nearest[..., None], axis=-1)[..., 0] * w0
    if sampled:   # z = (1 + jv) / (1 - jv) has the angle 2 atan(v)
        crossover = 2.0 * np.arctan(crossover)
    found = np.any(np.isfinite(margin), axis=-1)
    return np.where(found, worst, np.inf), np.where(found, crossover, np.nan)


#: a crossover candidate where ``|gain L|`` read on the state space is further than this
#: (relative) from 1 is a root of rounding, not a crossover: those are off by orders of
#: magnitude (1e14, 1e-7), while a true crossover's root, even a double one where
#: ``|gain L|`` touches 1, reads 1 to far better than this
CROSSOVER_RTOL = 1e-2


def _off_crossover(a: Array, b: Array, c: Array, gain: Array, w: Array, sampled: bool) -> NDArray[np.bool_]:
    """Which candidates ``w`` (rad/s continuous; ``tan(wT / 2)`` sampled, the bilinear
    map's) are no crossover: ``|gain C (xI - A)^-1 B|`` there, solved on the balanced
    realisation itself and not on the polynomials of :func:`phase_crossover`, is not 1.

    At K_env = 0 the loop's integrator (s = 0, z = 1) is cancelled by a zero, and at a
    very soft environment nearly, by the environment's slow pole; eigenvalues resolve such
    a double pole only to about 1e-8 (1 +- 1e-8j for the estimated velocity's loop). The
    coefficients of ``|D|^2 - gain^2 |N|^2`` then carry rounding with roots near w = 0 --
    noise of 1e-15, or an imaginary pair of 1e-7 whose real part of 1e-27 was taken --
    where ``L`` read -180 deg: analyze printed a sampled phase margin of -92.7 deg at
    7.9e-12 rad/s for the demo at K_env = 0 and 0 deg up to K_env = 0.03 N m/rad, and the
    stability gate warned of a phase margin of 0 deg at K_env = 0.01, where ``|L|`` is in
    truth about 1e14 and the crossover is 95.6 deg at 312 rad/s (``tests/test_gate.py``).
    A singular ``xI - A`` is a pole: no crossover."""
    with np.errstate(invalid="ignore"):
        x = (1.0 + 1j * w) / (1.0 - 1j * w) if sampled else 1j * w
    shifted = x[..., :, None, None] * np.eye(a.shape[-1]) - a[..., None, :, :]
    rhs = np.broadcast_to(b[..., None, :, :], shifted.shape[:-1] + (b.shape[-1],))
    try:
        solved = np.linalg.solve(shifted, rhs)
    except np.linalg.LinAlgError:   # one exactly at a pole: each alone, a singular one inf
        solved = np.full(rhs.shape, np.inf, dtype=complex)
        for i in np.ndindex(*shifted.shape[:-2]):
            try:
                solved[i] = np.linalg.solve(shifted[i], rhs[i])
            except np.linalg.LinAlgError:
                pass
    value = np.abs(gain * (c[..., None, :, :] @ solved)[..., 0, 0])
    return ~(np.abs(value - 1.0) <= CROSSOVER_RTOL)


def _abs_squared(p: CArray) -> Array:
    """Coefficients of ``|p(w)|^2 = p(w) conj(p)(w)`` for real w (highest power first)."""
    n = p.shape[-1] - 1
    out = np.zeros(p.shape[:-1] + (2 * n + 1,), dtype=complex)
    for i in range(n + 1):
        out[..., i:i + n + 1] += p[..., i:i + 1] * np.conj(p)
    return out.real
