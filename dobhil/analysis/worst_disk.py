"""The smallest disk margin of the force loop over a box of plant and environment values.

The certificates (:mod:`dobhil.analysis.certify`, :mod:`dobhil.analysis.certify_sampled`)
decide stability over the whole box; the disk margin (:mod:`dobhil.analysis.disk_margin`) is
a number at one point. Where over the box it is smallest is searched, not bounded: a grid
of the box (its faces included; a key spanning a decade or more on the log scale) and any
points the caller knows to be bad (the continuous gain margin's worst) are evaluated, then
a bounded Nelder-Mead search (scipy) moves from the smallest of them. The answer is the smallest margin met: a
margin the box certainly has somewhere, an upper bound on the box's true smallest one.

Why a search: the balanced disk margin is the peak over frequency of ``|S - 1/2|``, a
maximum of smooth functions, so it is not smooth in the plant's values and has no closed
form over a box; python-control's ``disk_margins`` is a pointwise tool too. A point where
the loop is unstable ends the search: the margin there is none.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from dobhil.analysis.certify import Box, params_at
from dobhil.analysis.disk_margin import DiskMargin, disk_margin
from dobhil.analysis.stability import is_stable, unresolved_pole
from dobhil.config.schema import Config
from dobhil.synthesis.loop import loop

#: starting points per key of a box of 1, 2, 3 or more keys (a grid, its ends the box's
#: faces): 5, 16, 27, 3^n
GRID_PER_KEY = {1: 5, 2: 4}
#: most disk margins the local search evaluates after the grid, per key of the box (each
#: ~10 ms continuous, ~40 ms sampled here)
SEARCH_EVALUATIONS_PER_KEY = 10
#: the search stops when its simplex is this small in the box's unit coordinates and
#: its margins (alpha) this close
SEARCH_TOLERANCE = 1e-3
#: a key whose range spans this ratio or more (its low end > 0) is searched on the log
#: scale: a stiffness of 1e2..1e5 has its soft end in the first 1 % of a linear range
LOG_RATIO = 10.0


@dataclass(frozen=True)
class WorstDisk:
    """The smallest disk margin met over a box, where, and how many points were tried."""

    point: dict[str, float]
    margin: DiskMargin | None     # None: the loop is unstable at ``point``
    points: int                   # disk margins evaluated


def _poles(config: Config, point: Mapping[str, float], sampled: bool) -> np.ndarray:
    with np.errstate(all="ignore"):
        return np.linalg.eigvals(loop(params_at(config, point), sampled=sampled).a).astype(complex)


def unresolved_at(config: Config, point: Mapping[str, float], sampled: bool) -> bool:
    """Whether the loop at ``point`` is not stable only by poles within the analysis'
    resolution of the stability boundary (:func:`~dobhil.analysis.stability.unresolved_pole`):
    shown neither stable nor unstable, as the certificates say of such a point."""
    poles = _poles(config, point, sampled)
    return bool(np.all(np.isfinite(poles))) and unresolved_pole(poles, sampled) is not None


def disk_margin_at(config: Config, point: Mapping[str, float], sampled: bool) -> DiskMargin | None:
    """The balanced disk margin of the loop at ``point`` (box keys -> values), None where
    that loop is not stable (:func:`unresolved_at` tells whether it is unstable)."""
    params = params_at(config, point)
    poles = _poles(config, point, sampled)
    if not np.all(np.isfinite(poles)) or not bool(is_stable(poles[None], sampled)[0]):
        return None
    a, b, c, _ = loop(params, sampled=sampled, force_gain=0.0).siso("tau_per", "tau_int_hat")
    return disk_margin(a, b, c, float(config.design.force_gain),
                       period=float(config.loop.period) if sampled else None)


def smallest_disk_margin(config: Config, box: Box, *, sampled: bool,
                         starts: Sequence[Mapping[str, float]] = ()) -> WorstDisk:
    """The smallest disk margin met over ``box`` (see the module docstring); ``starts``:
    points of the box tried besides the grid of :data:`GRID_PER_KEY`."""
    lo, hi = np.array(box.lo, float), np.array(box.hi, float)
    logs = (lo > 0.0) & (hi >= LOG_RATIO * np.maximum(lo, 1e-300))
    a = np.where(logs, np.log(np.where(logs, lo, 1.0)), lo)
    b = np.where(logs, np.log(np.where(logs, hi, 1.0)), hi)
    best: list[tuple[dict[str, float], DiskMargin | None]] = []
    count = 0

    def at(u: np.ndarray) -> dict[str, float]:
        x = a + np.clip(u, 0.0, 1.0) * (b - a)
        x[logs] = np.exp(x[logs])
        # the box's faces exactly (exp(log(10)) is 10.000000000000002)
        x = np.where(u <= 0.0, lo, np.where(u >= 1.0, hi, np.clip(x, lo, hi)))
        return {k: float(v) for k, v in zip(box.keys, x)}

    def alpha(u: np.ndarray) -> float:
        nonlocal count
        point = at(u)
        margin = disk_margin_at(config, point, sampled)
        count += 1
        if margin is None:
            best[:] = [(point, None)]
            raise _Unstable
        if not best or margin.alpha < _alpha(best[0][1]):
            best[:] = [(point, margin)]
        return margin.alpha

    per_key = GRID_PER_KEY.get(lo.size, 3)
    grid = [np.array(u, float) for u in itertools.product(np.linspace(0.0, 1.0, per_key), repeat=lo.size)]
    known = [(np.array([float(p[k]) for k in box.keys]), p) for p in starts]
    unit = [(np.where(logs, np.log(np.maximum(x, 1e-300)), x) - a) / (b - a) for x, _ in known]
    try:
        tried = [(alpha(u), u) for u in [*grid, *unit]]
        _search(alpha, min(tried, key=lambda pair: pair[0])[1], 1.0 / (per_key - 1))
    except _Unstable:
        pass
    return WorstDisk(best[0][0], best[0][1], count)


def _alpha(margin: DiskMargin | None) -> float:
    return -math.inf if margin is None else margin.alpha


class _Unstable(Exception):
    """A point where the loop is unstable: the search has its answer."""


def _search(alpha: Callable[[np.ndarray], float], u0: np.ndarray, step: float) -> None:
    """scipy's bounded Nelder-Mead from ``u0``, its first simplex one grid ``step`` inwards
    along each key (scipy's own steps 5 % of each coordinate, 2.5e-4 of one at 0: from the
    box's face it would search a speck of it)."""
    import scipy.optimize
    inwards = np.where(u0 < 0.5, step, -step)
    simplex = np.vstack([u0, *(u0 + np.diag(inwards))])
    scipy.optimize.minimize(alpha, u0, method="Nelder-Mead", bounds=[(0.0, 1.0)] * u0.size,
                            options={"maxfev": SEARCH_EVALUATIONS_PER_KEY * u0.size, "initial_simplex": simplex,
                                     "xatol": SEARCH_TOLERANCE, "fatol": SEARCH_TOLERANCE})


__all__ = ["SEARCH_EVALUATIONS_PER_KEY", "WorstDisk", "disk_margin_at", "smallest_disk_margin"]
