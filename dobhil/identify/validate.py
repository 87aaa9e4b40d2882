"""A fitted model checked on a record the fit did not see (``dobhil identify A.mcap
--validate B.mcap``): how much of each signal it explains, and whether what it leaves is noise.

- **Fit %** per signal, the normalised RMS error as MATLAB's ``compare`` reports it
  (Ljung, *System Identification: Theory for the User*, 2nd ed., Prentice Hall 1999,
  sec. 16.6): ``100 (1 - ||y - yhat|| / ||y - mean(y)||)``; 100 is a perfect fit, 0 no
  better than the mean, negative worse. The model is simulated from the torque alone (output
  error: never fed the measurements), from each segment's initial state fitted to the
  validation record (its velocity, and in contact its position within an encoder count: the
  start of a run is no state the fit saw), as ``compare`` estimates initial conditions.
- **Residual whiteness**: the normalised autocorrelation ``r_e(k)``, ``k = 1 .. L``, of the
  velocity residual against ``+- z / sqrt(N)``, and the Ljung-Box statistic over the same lags.
- **Residual-input independence**: the normalised cross-correlation ``r_eu(k)``, ``k = -L ..
  L``, of the residual and the torque against ``+- z sqrt(P / N)``, ``P = sum_k r_e(k) r_u(k)``
  (its variance when the two are independent, Ljung sec. 16.6: a coloured input widens it).
  A correlation at negative lags is feedback, at positive ones input dynamics the model misses.

``z``: each lag's test at ``MISFIT_P / (number of lags)`` two-sided (Bonferroni), so the
whole test cries misfit on a right model with probability at most :data:`MISFIT_P` (0.1 %,
the identification's own Ljung-Box threshold); the classic per-lag 99 % band ``2.58 / sqrt(N)``
is reported beside it. A residual below :data:`~dobhil.identify.fit.NOISE_FLOOR` of the
velocity is rounding (a noise-free record) and never a misfit.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Final

import numpy as np
import scipy.optimize
import scipy.stats

from dobhil.identify.data import IdentData, Segment
from dobhil.identify.fit import MISFIT_P, NOISE_FLOOR, simulate

__all__ = ["CorrelationTest", "SignalFit", "Validation", "autocorrelation", "cross_correlation", "nrmse_fit",
           "residual_tests", "validate"]

#: lags of the correlation tests
LAGS: Final = 25
#: the per-lag 99 % band of the classic plot (Ljung 1999, sec. 16.6)
PER_LAG_Z: Final = 2.58


@dataclass(frozen=True)
class SignalFit:
    """Fit % of one signal over the segments of one kind."""

    signal: str      # "velocity" | "position"
    kind: str        # "free" | "contact"
    percent: float
    samples: int


@dataclass(frozen=True)
class CorrelationTest:
    """Normalised correlations at ``lags``, the threshold they are held to, and the worst."""

    name: str
    lags: np.ndarray
    values: np.ndarray
    threshold: float        # the decision's bound (Bonferroni over the lags)
    per_lag_99: float       # the classic 2.58 / sqrt(N) band (times sqrt(P) for the cross test)
    worst_lag: int
    worst: float

    @property
    def passed(self) -> bool:
        return abs(self.worst) <= self.threshold

    @property
    def outside_99(self) -> int:
        return int(np.count_nonzero(np.abs(self.values) > self.per_lag_99))


@dataclass(frozen=True)
class Validation:
    fits: tuple[SignalFit, ...]
    whiteness: CorrelationTest
    cross: CorrelationTest
    ljung_box_p: float
    residual_rms: float
    rounding: bool          # the residual is below the noise floor: no verdict on its colour
    samples: int

    @property
    def misfit(self) -> bool:
        return not self.rounding and not (self.whiteness.passed and self.cross.passed)


def nrmse_fit(y: np.ndarray, yhat: np.ndarray) -> float:
    """``100 (1 - ||y - yhat|| / ||y - mean y||)`` [%] (NaN for a constant ``y``)."""
    y, yhat = np.asarray(y, float), np.asarray(yhat, float)
    spread = float(np.linalg.norm(y - y.mean()))
    return math.nan if spread == 0.0 else 100.0 * (1.0 - float(np.linalg.norm(y - yhat)) / spread)


def autocorrelation(x: np.ndarray, lags: int) -> np.ndarray:
    """``r(k) = sum x[t] x[t+k] / sum x^2``, ``k = 1 .. lags``, of ``x`` less its mean."""
    x = np.asarray(x, float) - np.mean(x)
    c0 = float(x @ x)
    if c0 == 0.0:   # a residual of exactly nothing (an exact model of a noise-free run): no colour
        return np.zeros(lags)
    return np.array([float(x[:-k] @ x[k:]) / c0 for k in range(1, lags + 1)])


def cross_correlation(e: np.ndarray, u: np.ndarray, lags: int) -> np.ndarray:
    """``r(k) = sum e[t+k] u[t] / sqrt(sum e^2 sum u^2)``, ``k = -lags .. lags`` (positive:
    the residual after the input), both less their means."""
    e = np.asarray(e, float) - np.mean(e)
    u = np.asarray(u, float) - np.mean(u)
    scale = math.sqrt(float(e @ e) * float(u @ u))
    n = len(e)
    if scale == 0.0:
        return np.zeros(2 * lags + 1)
    out = []
    for k in range(-lags, lags + 1):
        out.append(float(e[k:] @ u[:n - k]) if k >= 0 else float(e[:n + k] @ u[-k:]))
    return np.array(out) / scale


def _initial(values: Mapping[str, float], data: IdentData, segment: Segment) -> tuple[float, float]:
    """The segment's initial true position and velocity that fit its measured velocity best over
    its first samples (the position within half an encoder count in contact, where half a count
    is a large spring torque)."""
    q0 = float(data.position[segment.start])
    short = Segment(segment.start, min(segment.stop, segment.start + 200), segment.kind)
    measured = data.velocity[short.start:short.stop]
    steps = np.abs(np.diff(np.unique(data.position[segment.start:segment.stop])))
    count = float(steps.min()) if steps.size else 0.0
    contact = segment.kind == "contact" and count > 0.0

    def residual(p: np.ndarray) -> np.ndarray:
        q = q0 + (float(p[1]) if contact else 0.0)
        return simulate(values, data, short, (q, float(p[0])))[1] - measured

    x0 = np.array([float(data.velocity[segment.start])] + ([0.0] if contact else []))
    lo = [-np.inf] + ([-count / 2] if contact else [])
    hi = [np.inf] + ([count / 2] if contact else [])
    p = scipy.optimize.least_squares(residual, x0, bounds=(lo, hi)).x
    return q0 + (float(p[1]) if contact else 0.0), float(p[0])


def validate(values: Mapping[str, float], data: IdentData, segments: Sequence[Segment], *,
             lags: int = LAGS) -> Validation:
    """The model ``values`` (named as :data:`dobhil.identify.fit.PARAMETERS`) on ``segments``
    of ``data``: fit % per signal and kind, and the residual tests (module docstring)."""
    residuals, inputs, velocity = [], [], []
    per: dict[tuple[str, str], tuple[list[np.ndarray], list[np.ndarray]]] = {}
    for seg in segments:
        q, v = simulate(values, data, seg, _initial(values, data, seg))
        s = slice(seg.start, seg.stop)
        for name, model, measured in (("velocity", v, data.velocity[s]), ("position", q, data.position[s])):
            ys, yh = per.setdefault((name, seg.kind), ([], []))
            ys.append(measured)
            yh.append(model)
        residuals.append(data.velocity[s] - v)
        inputs.append(data.torque[s])
        velocity.append(data.velocity[s])
    fits = tuple(SignalFit(signal=name, kind=kind, percent=nrmse_fit(np.concatenate(ys), np.concatenate(yh)),
                           samples=sum(len(y) for y in ys)) for (name, kind), (ys, yh) in per.items())
    return residual_tests(fits, np.concatenate(residuals), np.concatenate(inputs), np.concatenate(velocity),
                          lags=lags)


def residual_tests(fits: tuple[SignalFit, ...], e: np.ndarray, u: np.ndarray, velocity: np.ndarray, *,
                   lags: int = LAGS, input_name: str = "input") -> Validation:
    """The :class:`Validation` of the velocity residual ``e``: its whiteness and its
    cross-correlation with ``u`` (the torque of an open-loop record; of a closed loop, the
    reference -- the torque there depends on the noise the residual holds, so only the
    reference is independent of it, Ljung 1999 sec. 16.6), ``velocity`` the measured one."""
    n = len(e)
    lags = min(lags, n // 4)
    r_e, r_u = autocorrelation(e, lags), autocorrelation(u, lags)
    z_white = float(scipy.stats.norm.isf(MISFIT_P / (2 * lags)))
    z_cross = float(scipy.stats.norm.isf(MISFIT_P / (2 * (2 * lags + 1))))
    white = _test("residual autocorrelation", np.arange(1, lags + 1), r_e, z_white / math.sqrt(n),
                  PER_LAG_Z / math.sqrt(n))
    # the cross-correlation's variance with a coloured input and residual: P / N
    p = 1.0 + 2.0 * float(r_e @ r_u)
    p = max(p, 1.0 / n)
    cross = _test(f"residual-{input_name} cross-correlation", np.arange(-lags, lags + 1), cross_correlation(e, u, lags),
                  z_cross * math.sqrt(p / n), PER_LAG_Z * math.sqrt(p / n))
    k = np.arange(1, lags + 1)
    ljung_box = n * (n + 2) * float(np.sum(r_e ** 2 / (n - k)))
    rms = float(np.sqrt(np.mean(e ** 2)))
    v_rms = float(np.sqrt(np.mean(velocity ** 2)))
    return Validation(fits=fits, whiteness=white, cross=cross, ljung_box_p=float(scipy.stats.chi2.sf(ljung_box, lags)),
                      residual_rms=rms, rounding=rms <= NOISE_FLOOR * v_rms, samples=n)


def _test(name: str, lags: np.ndarray, values: np.ndarray, threshold: float, per_lag: float) -> CorrelationTest:
    i = int(np.argmax(np.abs(values)))
    return CorrelationTest(name=name, lags=lags, values=values, threshold=threshold, per_lag_99=per_lag,
                           worst_lag=int(lags[i]), worst=float(values[i]))
