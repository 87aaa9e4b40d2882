"""Small numerical tools shared by the synthesis and the analysis (batched).

Balancing is written here because scipy's ``matrix_balance`` works on one
matrix at a time and ignores the input and output vectors.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]


def balance_scaling(a: Array, b: Array | None = None, c: Array | None = None,
                    iterations: int = 12) -> Array:
    """Diagonal ``S`` (powers of two, batch + (n,)) such that ``S^-1 A S`` -- with the
    columns of ``S^-1 B`` and the rows of ``C S`` counted in -- has rows and columns of
    similar size (Osborne's iteration, all states at once). Powers of two keep the
    change of basis exact in floating point."""
    n = a.shape[-1]
    flat = a.reshape(-1, n, n)
    scale = np.ones(flat.shape[:-1])
    off = ~np.eye(n, dtype=bool)
    ab = np.zeros(scale.shape) if b is None else np.broadcast_to(np.abs(b).sum(axis=-1), a.shape[:-1]).reshape(-1, n)
    ac = np.zeros(scale.shape) if c is None else np.broadcast_to(np.abs(c).sum(axis=-2), a.shape[:-1]).reshape(-1, n)
    # each design's iteration is its own; one whose factors are all 1 has settled and would
    # compute the same factors again, so only the others go on (a sweep's batch has a few
    # hundred designs that never settle, which kept all 3600 iterating 12 times)
    moving = np.arange(flat.shape[0])
    for _ in range(iterations):
        s = scale[moving]
        m = np.abs(flat[moving] * s[:, None, :] / s[:, :, None]) * off
        rows = m.sum(axis=-1) + ab[moving] / s
        cols = m.sum(axis=-2) + ac[moving] * s
        ok = (rows > 0) & (cols > 0) & np.isfinite(rows) & np.isfinite(cols)
        ratio = np.where(ok, rows, 1.0) / np.where(ok, cols, 1.0)
        f = np.exp2(np.round(0.5 * np.log2(ratio)))
        still = np.any(f != 1.0, axis=-1)
        if not still.any():
            break
        moving = moving[still]
        scale[moving] = s[still] * f[still]
    return scale.reshape(a.shape[:-1])


def balance(a: Array, b: Array, c: Array) -> tuple[Array, Array, Array]:
    """``(S^-1 A S, S^-1 B, C S)`` with :func:`balance_scaling`: same transfer function."""
    s = balance_scaling(a, b, c)
    return a * s[..., None, :] / s[..., :, None], b / s[..., :, None], c * s[..., None, :]
