"""Step-response metrics: overshoot, 10-90 % rise time, 2 % settling time, steady-state error."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass

import control
import numpy as np
import scipy.linalg
import scipy.optimize
from numpy.typing import NDArray

from dobhil.analysis.stability import is_stable
from dobhil.errors import AnalysisError

Array = NDArray[np.float64]


@dataclass(frozen=True)
class StepMetrics:
    overshoot_pct: float | None
    rise_time: float | None
    settling_time: float | None
    steady_state_error: float | None
    final_value: float | None
    peak: float | None

    def as_dict(self) -> dict[str, float | None]:
        return asdict(self)


UNSTABLE = StepMetrics(None, None, None, None, None, None)

#: the settling band's half width, a share of the final value
SETTLING_BAND = 0.02


#: sampled step responses longer than this many samples are refused (memory, time)
MAX_STEP_SAMPLES = 1_000_000

#: points per layer of the continuous step grid (see :func:`step_grid`)
LAYER_POINTS = 2000


def _continuous_rates(poles: np.ndarray, dt: float) -> tuple[float, float]:
    """(slowest decay rate, fastest rate) in rad/s of the stable poles."""
    p = np.asarray(poles, complex)
    if dt:
        p = p[np.abs(p) > 1e-12]
        p = np.log(p) / dt
    re = -p.real
    decaying = re[re > 1e-9 * max(1.0, float(np.max(np.abs(p), initial=0.0)))]
    slowest = float(decaying.min()) if decaying.size else 1.0
    fastest = float(np.max(np.abs(p), initial=1.0))
    return slowest, max(fastest, slowest)


def horizon(sys: control.StateSpace) -> float:
    """A step horizon that shows settling: 10 time constants of the slowest pole."""
    slowest, _ = _continuous_rates(np.asarray(sys.poles()), float(sys.dt or 0.0))
    t = min(10.0 / slowest, 5.0)
    return max(t, 20 * (sys.dt or 0.0))


def step_grid(sys: control.StateSpace, duration: float = 0.0) -> list[tuple[float, int]]:
    """The step response's time grid as uniform layers ``(dt, count)`` from t = 0.

    Sampled: one layer, the sample period. Continuous: the first layer resolves the
    fastest closed-loop dynamics (``dt = 1 / (25 |p|_max)``, a period in 150 points),
    each next one is 8x coarser, the last one reaches the horizon; so a fast
    oscillation riding on a slow settling is seen (the union has a few thousand
    points per decade of time scales)."""
    tf = duration or horizon(sys)
    if sys.dt:
        count = int(np.floor(tf / sys.dt + 0.5)) + 1
        if count > MAX_STEP_SAMPLES:
            raise AnalysisError(f"analysis.step_duration = {tf!r} s is {count} samples at "
                                f"loop.period = {sys.dt!r} s; at most {MAX_STEP_SAMPLES} allowed")
        return [(float(sys.dt), count)]
    _, fastest = _continuous_rates(np.asarray(sys.poles()), 0.0)
    layers: list[tuple[float, int]] = []
    dt = 1.0 / (25.0 * fastest)
    while dt * LAYER_POINTS < tf and len(layers) < 40:
        layers.append((dt, LAYER_POINTS + 1))
        dt *= 8.0
    layers.append((tf / (2 * LAYER_POINTS), 2 * LAYER_POINTS + 1))
    return layers


def _step_states(a: np.ndarray, b: np.ndarray, dt: float, count: int, sampled: bool) -> np.ndarray:
    """States x_0..x_{count-1} (x_0 = 0) of a unit step, by doubling:
    ``x_{m+j} = Phi^m x_j + x_m`` -- log2(count) array operations, no per-step loop."""
    n = a.shape[-1]
    if sampled:
        phi, gamma = a, b[:, 0]
    else:
        block = np.zeros((n + 1, n + 1))
        block[:n, :n] = a * dt
        block[:n, n] = b[:, 0] * dt
        e = scipy.linalg.expm(block)
        phi, gamma = e[:n, :n], e[:n, n]
    xs = np.zeros((1, n))
    power = phi                       # Phi^m with m = len(xs)
    x_m = gamma                       # x_1
    while xs.shape[0] < count:
        xs = np.concatenate([xs, xs @ power.T + x_m], axis=0)
        x_m = x_m @ power.T + x_m     # x_{2m} = Phi^m x_m + x_m
        power = power @ power
    return xs[:count]


def step_responses(systems: Sequence[control.StateSpace],
                   duration: float = 0.0) -> tuple[Array, list[Array]]:
    """(t, [y, ...]) of a unit step into systems sharing A and B (e.g. two outputs of one
    loop), on :func:`step_grid` of the first; the first output's peak is located
    exactly (a local maximisation between grid points) and added to the grid."""
    first = systems[0]
    a, b = np.asarray(first.A, float), np.asarray(first.B, float)
    sampled = bool(first.dt)
    ts, xs = [], []
    for dt, count in step_grid(first, duration):
        ts.append(dt * np.arange(count))
        xs.append(_step_states(a, b, dt, count, sampled))
    t = np.concatenate(ts)
    x = np.concatenate(xs)
    t, keep = np.unique(t, return_index=True)
    x = x[keep]
    cds = [(np.asarray(s.C, float)[0], float(np.asarray(s.D, float)[0, 0])) for s in systems]
    if not sampled and t.size > 2:
        t_peak = _exact_peak(a, b, *cds[0], t, x @ cds[0][0] + cds[0][1])
        if t_peak is not None:
            i = int(np.searchsorted(t, t_peak))
            t = np.insert(t, i, t_peak)
            x = np.insert(x, i, _state_at(a, b, t_peak), axis=0)
    return t, [x @ c + d for c, d in cds]


def _state_at(a: np.ndarray, b: np.ndarray, t: float) -> np.ndarray:
    n = a.shape[-1]
    block = np.zeros((n + 1, n + 1))
    block[:n, :n] = a * t
    block[:n, n] = b[:, 0] * t
    return np.asarray(scipy.linalg.expm(block)[:n, n])


def _exact_peak(a: np.ndarray, b: np.ndarray, c: np.ndarray, d: float, t: Array,
                y: Array) -> float | None:
    """The time of the extremum of y near the grid's, by bounded maximisation."""
    if not np.all(np.isfinite(y)):
        return None
    final = y[-1]
    sign = 1.0 if final >= 0 else -1.0
    i = int(np.argmax(sign * y))
    if i == 0 or i == t.size - 1:
        return None
    res = scipy.optimize.minimize_scalar(lambda s: -sign * float(_state_at(a, b, s) @ c + d),
                                         bounds=(float(t[i - 1]), float(t[i + 1])),
                                         method="bounded", options={"xatol": 1e-12 * t[i]})
    return float(res.x) if res.success and -sign * res.fun >= sign * y[i] else None


def step_response(sys: control.StateSpace, duration: float = 0.0) -> tuple[Array, Array]:
    """(t, y) of a unit step; ``duration`` 0 picks :func:`horizon`."""
    t, (y,) = step_responses([sys], duration)
    return t, y


def step_metrics(t: Array, y: Array, *, target: float = 1.0, stable: bool = True,
                 final: float | None = None) -> StepMetrics:
    """Metrics of a step response towards ``target`` (the reference step height).

    ``final`` is the exact final value (the DC gain) when known; else the last sample.
    """
    if not stable or not np.all(np.isfinite(y)) or y.size == 0:
        return UNSTABLE
    final = float(y[-1]) if final is None else float(final)
    peak = float(y.max()) if final >= 0 else float(y.min())
    overshoot = max(0.0, (peak - final) / final * 100.0) if final != 0 else None
    return StepMetrics(overshoot_pct=overshoot, rise_time=_rise_time(t, y, final),
                       settling_time=_settling_time(t, y, final),
                       steady_state_error=target - final, final_value=final, peak=peak)


def _crossing_time(t: Array, y: Array, level: float, sign: float) -> float | None:
    idx = np.nonzero(sign * y >= sign * level)[0]
    if idx.size == 0:
        return None
    i = int(idx[0])
    if i == 0:
        return float(t[0])
    y0, y1 = y[i - 1], y[i]
    return float(t[i - 1] + (level - y0) / (y1 - y0) * (t[i] - t[i - 1]))


def _rise_time(t: Array, y: Array, final: float) -> float | None:
    sign = 1.0 if final >= 0 else -1.0
    t10 = _crossing_time(t, y, 0.1 * final, sign)
    t90 = _crossing_time(t, y, 0.9 * final, sign)
    return None if t10 is None or t90 is None else t90 - t10


def _settling_time(t: Array, y: Array, final: float) -> float | None:
    band = SETTLING_BAND * abs(final)
    outside = np.nonzero(np.abs(y - final) > band)[0]
    if outside.size == 0:
        return float(t[0])
    i = int(outside[-1])
    if i == t.size - 1:   # still outside the band at the horizon: it has not settled within it, and
        return None       # the horizon's end is no settling time (analysis.step_duration too short)
    return float(t[i + 1])


def system_stable(sys: control.StateSpace) -> bool:
    return bool(is_stable(np.asarray(sys.poles())[None], bool(sys.dt))[0])
