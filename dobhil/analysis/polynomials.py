"""Batched polynomial tools for SISO state-space systems ``(A, B, C, 0)``.

Written here because numpy and python-control work one system at a time; the
sweep needs poles, zeros and root-locus crossings of thousands of designs at
once. Coefficient arrays are highest power first; everything broadcasts over a
leading batch shape.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from dobhil.synthesis.numerics import balance

Array = NDArray[np.float64]
CArray = NDArray[np.complex128]

#: a Markov parameter C A^j B counts as zero below this fraction of |C| |A|^j |B|
MARKOV_RTOL = 1e-9


def poly_from_roots(roots: CArray, gain: Array | float = 1.0, degree: int | None = None) -> Array:
    """Real coefficients of ``gain * prod(s - r)`` padded on the left to ``degree``."""
    n = roots.shape[-1]
    deg = n if degree is None else degree
    coef = np.zeros(roots.shape[:-1] + (n + 1,), dtype=complex)
    coef[..., 0] = 1.0
    for j in range(n):
        coef[..., 1:j + 2] = coef[..., 1:j + 2] - roots[..., j:j + 1] * coef[..., 0:j + 1]
    out = np.zeros(roots.shape[:-1] + (deg + 1,))
    out[..., deg - n:] = coef.real * np.asarray(gain, float)[..., None]
    return out


def markov_parameters(a: Array, b: Array, c: Array) -> Array:
    """``C A^j B`` for j = 0..n-1, shape batch + (n,)."""
    n = a.shape[-1]
    out = []
    v = b
    for _ in range(n):
        out.append((c @ v)[..., 0, 0])
        v = a @ v
    return np.stack(out, axis=-1)


def relative_degree(a: Array, b: Array, c: Array) -> NDArray[np.int64]:
    """First j+1 with ``C A^j B`` not zero (n+1 when the transfer function is zero).

    On a balanced realisation (:func:`~dobhil.synthesis.numerics.balance`), so that
    ``|C| |A|^j |B|`` -- the size of the rounding in ``C A^j B`` -- is the system's own
    scale and not that of an ill-scaled basis (a state in rad next to one in N m)."""
    a, b, c = balance(a, b, c)
    n = a.shape[-1]
    h = markov_parameters(a, b, c)
    an = np.maximum(np.linalg.norm(a, ord=2, axis=(-2, -1)), 1e-300)
    scale = (np.linalg.norm(c, axis=(-2, -1)) * np.linalg.norm(b, axis=(-2, -1)))[..., None]
    tol = MARKOV_RTOL * scale * an[..., None] ** np.arange(n)
    nonzero = np.abs(h) > tol
    first = np.where(nonzero.any(axis=-1), nonzero.argmax(axis=-1), n)
    return first + 1


def zeros_and_numerator(a: Array, b: Array, c: Array) -> tuple[CArray, Array, NDArray[np.int64]]:
    """(zeros padded with NaN to n-1, numerator coefficients (n+1,), relative degree).

    The numerator N(s) of ``C (sI - A)^{-1} B`` is ``C A^{r-1} B * prod(s - z)``.
    """
    n = a.shape[-1]
    batch = a.shape[:-2]
    a, b, c = balance(a, b, c)
    rel = relative_degree(a, b, c)
    h = markov_parameters(a, b, c)
    zeros = np.full(batch + (max(n - 1, 0),), np.nan + 0j)
    num = np.zeros(batch + (n + 1,))
    for r in np.unique(rel):
        mask = rel == r
        if r > n:
            continue
        am, bm, cm = a[mask], b[mask], c[mask]
        lead = h[mask][:, r - 1]
        car = cm @ np.linalg.matrix_power(am, int(r))
        m = am - bm @ (car / lead[:, None, None])
        ev = np.linalg.eigvals(m)
        order = np.argsort(np.abs(ev), axis=-1)
        z = np.take_along_axis(ev, order[:, r:], axis=-1)
        zeros_m = np.full((z.shape[0], max(n - 1, 0)), np.nan + 0j)
        zeros_m[:, :n - r] = z
        zeros[mask] = zeros_m
        num[mask] = poly_from_roots(z, lead, degree=n)
    return zeros, num, rel


def eval_poly(coef: Array, x: CArray) -> CArray:
    """Horner evaluation: coefficients batch + (n+1,) at points batch + (m,)."""
    out = np.zeros(x.shape, dtype=complex)
    for j in range(coef.shape[-1]):
        out = out * x + coef[..., j, None]
    return out


def batched_roots(coef: Array) -> CArray:
    """Roots of each polynomial, padded with NaN (leading near-zero terms dropped)."""
    batch, width = coef.shape[:-1], coef.shape[-1]
    flat = coef.reshape(-1, width)
    valid = np.all(np.isfinite(flat), axis=-1)
    flat = np.where(valid[:, None], flat, 0.0)
    big = np.abs(flat).max(axis=-1, keepdims=True)
    lead = np.argmax(np.abs(flat) > 1e-13 * np.maximum(big, 1e-300), axis=-1)
    lead = np.where(valid & (big[:, 0] > 0), lead, width - 1)   # no roots for those
    out = np.full((flat.shape[0], width - 1), np.nan + 0j)
    for first in np.unique(lead):
        rows = np.nonzero(lead == first)[0]
        deg = width - 1 - first
        if deg < 1:
            continue
        p = flat[rows, first:]
        comp = np.zeros((rows.size, deg, deg))
        comp[:, 0, :] = -p[:, 1:] / p[:, :1]
        comp[:, np.arange(1, deg), np.arange(deg - 1)] = 1.0
        out[rows, :deg] = np.linalg.eigvals(comp)
    return out.reshape(batch + (width - 1,))
