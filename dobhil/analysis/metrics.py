"""Step-response metrics: overshoot, 10-90 % rise time, 2 % settling time, steady-state error."""

from __future__ import annotations

from dataclasses import asdict, dataclass

import control
import numpy as np
from numpy.typing import NDArray

from dobhil.analysis.stability import is_stable

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


def horizon(sys: control.StateSpace) -> float:
    """A step horizon that shows settling: 10 time constants of the slowest pole."""
    poles = np.asarray(sys.poles())
    if sys.dt:
        with np.errstate(divide="ignore"):
            poles = np.log(poles[np.abs(poles) > 1e-12].astype(complex)) / sys.dt
    re = -poles.real
    re = re[re > 1e-9]
    slowest = re.min() if re.size else 1.0
    t = min(10.0 / slowest, 5.0)
    return max(t, 20 * (sys.dt or 0.0))


def step_response(sys: control.StateSpace, duration: float = 0.0) -> tuple[Array, Array]:
    """(t, y) of a unit step; ``duration`` 0 picks :func:`horizon`."""
    tf = duration or horizon(sys)
    if sys.dt:
        t = np.arange(0.0, tf + sys.dt / 2, sys.dt)
    else:
        t = np.linspace(0.0, tf, 4001)
    res = control.step_response(sys, T=t)
    return np.asarray(res.time), np.asarray(res.outputs).reshape(-1)


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
    band = 0.02 * abs(final)
    outside = np.nonzero(np.abs(y - final) > band)[0]
    if outside.size == 0:
        return float(t[0])
    i = int(outside[-1])
    return float(t[min(i + 1, t.size - 1)])


def system_stable(sys: control.StateSpace) -> bool:
    return bool(is_stable(np.asarray(sys.poles())[None], bool(sys.dt))[0])
