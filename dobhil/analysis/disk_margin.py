"""Disk margins of the force loop (Seiler, Packard & Gahinet, "An introduction to disk
margins", IEEE Control Systems Magazine 40(5):78-95, 2020).

The loop is broken where the package breaks it for its gain margin: at the performance torque,
``L = C_f * (tau_per -> tau_int^)`` with the inner DOb loop closed
(:mod:`dobhil.synthesis.loop`), negative feedback ``1 + L``. The balanced (skew sigma = 0)
disk margin is ``alpha = 1 / max_w |S(jw) - 1/2|`` with ``S = 1 / (1 + L)``
(their Eq. (11) with sigma = 0, ``S + (sigma - 1)/2``): the loop stays stable for every
simultaneous gain and phase change ``f = (1 + delta/2) / (1 - delta/2)``, ``|delta| < alpha``;
as a pure gain that is the factor range ``[(2 - alpha)/(2 + alpha), (2 + alpha)/(2 - alpha)]``
and as a pure phase ``+-2 atan(alpha / 2)``. A disk margin is never larger than the classical
margins: it is what one disk of simultaneous gain and phase variation leaves.

The peak is found on a log frequency grid (continuous: around the loop's poles and zeros;
sampled: up to the Nyquist frequency) refined by a bounded search around the largest sample.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from dobhil.synthesis.numerics import balance
from dobhil.synthesis.params import Array

#: frequencies on the grid before the peak is refined
GRID_POINTS = 2000


@dataclass(frozen=True)
class DiskMargin:
    alpha: float            # the balanced disk's size
    frequency: float        # where |S - 1/2| peaks [rad/s]

    @property
    def gain_factors(self) -> tuple[float, float]:
        if self.alpha >= 2.0:
            return 0.0, math.inf
        return (2.0 - self.alpha) / (2.0 + self.alpha), (2.0 + self.alpha) / (2.0 - self.alpha)

    @property
    def gain_db(self) -> float:
        return 20.0 * math.log10(self.gain_factors[1])

    @property
    def phase_deg(self) -> float:
        return math.degrees(2.0 * math.atan(self.alpha / 2.0))


def loop_response(a: Array, b: Array, c: Array, gain: float, w: Array, period: float | None) -> Array:
    """``gain * C (xI - A)^-1 B`` at x = jw (continuous) or e^{jwT} (sampled)."""
    a, b, c = balance(a, b, c)
    x = 1j * w if period is None else np.exp(1j * w * period)
    n = a.shape[-1]
    m = x[:, None, None] * np.eye(n) - a[None]
    return np.asarray(gain * (c[None] @ np.linalg.solve(m, np.broadcast_to(b, (w.size,) + b.shape)))[:, 0, 0])


def disk_margin(a: Array, b: Array, c: Array, gain: float, *, period: float | None) -> DiskMargin:
    """The balanced disk margin of ``gain * C (xI - A)^-1 B`` (one loop, unbatched)."""
    w = _grid(a, period)

    def peak(x: Array) -> Array:
        return np.asarray(np.abs(1.0 / (1.0 + loop_response(a, b, c, gain, x, period)) - 0.5))
    values = peak(w)
    i = int(np.argmax(values))
    best_w, best = float(w[i]), float(values[i])
    lo, hi = math.log(w[max(i - 1, 0)]), math.log(w[min(i + 1, w.size - 1)])
    if hi > lo:
        import scipy.optimize
        res = scipy.optimize.minimize_scalar(lambda x: -float(peak(np.array([math.exp(x)]))[0]),
                                             bounds=(lo, hi), method="bounded", options={"xatol": 1e-10})
        if -float(res.fun) > best:
            best_w, best = math.exp(float(res.x)), -float(res.fun)
    return DiskMargin(alpha=1.0 / best if best > 0 else math.inf, frequency=best_w)


def _grid(a: Array, period: float | None) -> Array:
    mags = np.abs(np.linalg.eigvals(a))
    if period is not None:
        return np.geomspace(1e-4 / period, math.pi / period, GRID_POINTS)
    finite = mags[(mags > 0) & np.isfinite(mags)]
    lo = float(finite.min()) / 1e3 if finite.size else 1e-3
    hi = float(finite.max()) * 1e3 if finite.size else 1e6
    return np.geomspace(lo, hi, GRID_POINTS)


__all__ = ["DiskMargin", "disk_margin", "loop_response"]
