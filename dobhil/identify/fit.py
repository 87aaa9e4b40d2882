"""The grey-box fit: the emulator's plant (:mod:`dobhil.identify.model`) fitted to a record
of sent torque and measured motion with lmfit.

What is fitted, and why so:

- the residual is the measured velocity minus the simulated one (output error: the model
  is simulated from each segment's start, never fed the noisy measurements, so the
  sensor noise does not bias the estimates). The position is not a residual: its
  quantisation error is correlated whenever the servo moves slowly, which would make the
  intervals too narrow; it still sets each segment's initial position;
- the free parameters are bounded lmfit Parameters; lmfit's Levenberg-Marquardt gives the
  standard errors and correlations (covariance scaled by the reduced chi-square: the noise
  level is estimated from the fit). A 95 % interval is ``value +- z stderr`` unless that
  leaves the bounds: then lmfit's profile likelihood (:func:`lmfit.conf_interval`) gives
  the asymmetric interval;
- the delay is one continuous parameter ``delay = whole T + fraction`` (the model is
  continuous in it: a fraction of a whole period is the next whole sample); a grid search
  over half periods up to ``max_delay_samples`` picks where the local fit starts, so a
  whole-sample delay is found by search, its fraction by the fit;
- the torque gain is never identifiable from torque and motion alone (inertia, friction,
  stiffness, damping and gain scaled together give the same motion): it is held at 1 and
  reported not identifiable. Without a contact segment the environment (stiffness,
  damping, contact position) is not fitted and reported not identifiable; a parameter
  whose 95 % interval is wider than its own value (friction: than 1 % of the torque the
  record used) has a flat profile and is reported not identifiable too;
- the residual's whiteness is the Ljung-Box test; a p-value below :data:`MISFIT_P` is a
  misfit: the model cannot represent the record and the numbers are not to be trusted.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import lmfit
import numpy as np
import scipy.stats

from dobhil.identify.data import IdentData, Segment
from dobhil.identify.model import ModelValues, simulate_torque, split_delay

__all__ = ["MISFIT_P", "PARAMETERS", "Estimate", "IdentResult", "Residual", "identify",
           "simulate"]

PARAMETERS = ("inertia", "viscous_friction", "coulomb_friction", "torque_gain",
              "contact_position", "stiffness", "damping", "delay")   # delay [s] = whole + fraction

#: Ljung-Box p-value below which the residual is not white: the model misfits the record
MISFIT_P = 1e-3
#: lags of the Ljung-Box test
WHITENESS_LAGS = 20
#: confidence level of the intervals
LEVEL = 0.95

_ENVIRONMENT = ("contact_position", "stiffness", "damping")
_EPSFCN = 1e-7
_FRICTION = ("viscous_friction", "coulomb_friction")


@dataclass(frozen=True)
class Estimate:
    """One parameter: value, standard error and the 95 % interval ``[low, high]``; not
    identifiable -> value NaN and ``why`` says why."""

    name: str
    value: float
    stderr: float
    low: float
    high: float
    identifiable: bool
    why: str


@dataclass(frozen=True)
class Residual:
    """The velocity residual: RMS [rad/s], Ljung-Box p-value, and the misfit verdict."""

    rms: float
    whiteness_p: float
    misfit: bool
    warning: str


@dataclass(frozen=True)
class IdentResult:
    estimates: Mapping[str, Estimate]
    correlations: Mapping[tuple[str, str], float]
    residual: Residual
    segments: tuple[Segment, ...]
    period: float = math.nan   # [s] of the record (splits the delay into whole samples and fraction)

    def overlay(self) -> dict[str, Any]:
        """The config overlay of the identifiable values: ``plant.*``, ``environment.*``,
        ``design.delay_samples``/``design.input_delay`` and ``design.identified_inertia``."""
        keys = {"inertia": "plant.inertia", "viscous_friction": "plant.viscous_friction",
                "coulomb_friction": "plant.coulomb_friction",
                "contact_position": "environment.contact_position",
                "stiffness": "environment.stiffness", "damping": "environment.damping"}
        out: dict[str, Any] = {}
        for name, key in keys.items():
            e = self.estimates[name]
            if e.identifiable:
                out[key] = e.value
        if self.estimates["inertia"].identifiable:
            out["design.identified_inertia"] = self.estimates["inertia"].value
        delay = self.estimates["delay"]
        if delay.identifiable and self.period > 0:
            whole, fraction = split_delay(delay.value, self.period)
            out["design.delay_samples"] = whole
            out["design.input_delay"] = fraction
        return out


def simulate(values: Mapping[str, float], data: IdentData,
             segment: Segment) -> tuple[np.ndarray, np.ndarray]:
    """Position and velocity [rad, rad/s] of the model ``values`` (names of
    :data:`PARAMETERS`; missing ones: no friction, gain 1, no environment, no delay) over
    ``segment`` of ``data``, driven by ``data.torque``, from rest at the measured position
    of the segment's first sample. A free segment is simulated without the environment: it
    is out of reach there (a free run need not be where the contact run was)."""
    if segment.kind == "free":
        values = {k: v for k, v in values.items() if k not in _ENVIRONMENT}
    return simulate_torque(_model(values), data.torque, data.period, segment.start,
                           segment.stop, float(data.position[segment.start]))


def _model(values: Mapping[str, float]) -> ModelValues:
    get = values.get
    return ModelValues(inertia=float(values["inertia"]),
                       viscous_friction=float(get("viscous_friction", 0.0)),
                       coulomb_friction=float(get("coulomb_friction", 0.0)),
                       torque_gain=float(get("torque_gain", 1.0)),
                       contact_position=float(get("contact_position", math.inf)),
                       stiffness=float(get("stiffness", 0.0)),
                       damping=float(get("damping", 0.0)),
                       delay=float(get("delay", 0.0)))


def _residual(params: lmfit.Parameters, data: IdentData, segments: Sequence[Segment],
              fixed: Mapping[str, float]) -> np.ndarray:
    """Measured minus simulated velocity over every segment, one after the other."""
    values = {**fixed, **params.valuesdict()}
    parts = []
    for s in segments:
        _, vel = simulate(values, data, s)
        parts.append(np.asarray(data.velocity[s.start:s.stop], float) - vel)
    return np.concatenate(parts)


# -- the start of the fit: an equation-error least squares on smoothed data -------------

_SMOOTH = 9   # samples of the moving average the start estimate differentiates through


def _smooth(x: np.ndarray) -> np.ndarray:
    return np.convolve(x, np.ones(_SMOOTH) / _SMOOTH, mode="same")


def _shifted(u: np.ndarray, half_samples: int) -> np.ndarray:
    """``u`` delayed by ``half_samples / 2`` periods (a half sample: the mean of two)."""
    whole, half = divmod(half_samples, 2)
    a = np.concatenate([np.zeros(whole), u])[: len(u)]
    if not half:
        return a
    b = np.concatenate([np.zeros(whole + 1), u])[: len(u)]
    return 0.5 * (a + b)


def _start(data: IdentData, segments: Sequence[Segment], contact: bool,
           max_delay_samples: int) -> dict[str, float]:
    """Start values: ``u = J a + b v + F_c sign v (+ K q - K q_c + D v in contact)`` by
    linear least squares on smoothed data, for every delay on a half-period grid; the
    delay with the smallest equation error wins (its whole-sample part is the search)."""
    period = data.period
    v = _smooth(np.asarray(data.velocity, float))
    q = np.asarray(data.position, float)
    acc = np.gradient(v, period)
    rows = np.concatenate([np.arange(s.start + _SMOOTH, s.stop - _SMOOTH) for s in segments])
    in_contact = np.concatenate([np.full(max(0, s.stop - s.start - 2 * _SMOOTH), s.kind == "contact")
                                 for s in segments]).astype(float)
    columns = [acc[rows], v[rows], np.sign(v[rows])]
    if contact:
        columns += [q[rows] * in_contact, in_contact, v[rows] * in_contact]
    x = np.column_stack(columns)
    best: tuple[float, int, np.ndarray] | None = None
    for half in range(2 * max_delay_samples + 3):
        u = _smooth(_shifted(np.asarray(data.torque, float), half))[rows]
        coef, *_ = np.linalg.lstsq(x, u, rcond=None)
        cost = float(np.sum((x @ coef - u) ** 2))
        if best is None or cost < best[0]:
            best = (cost, half, coef)
    assert best is not None
    _, half, coef = best
    # the smoothing delays nothing (centred); the acceleration at t_k is that of the command
    # held over the sample before it, so the equation's shift is the delay plus about half
    # a sample (and up to a whole one): the fit starts half a sample earlier
    out = {"inertia": abs(float(coef[0])), "viscous_friction": max(float(coef[1]), 0.0),
           "coulomb_friction": max(float(coef[2]), 0.0),
           "delay": max(0.5 * (half - 1) * period, 0.0)}
    if contact:
        k = abs(float(coef[3]))
        out["stiffness"] = k
        out["contact_position"] = -float(coef[4]) / k if k > 0 else float(np.median(q[rows]))
        out["damping"] = max(float(coef[5]), 0.0)
    return out


# -- the fit ----------------------------------------------------------------------------

def _parameters(start: dict[str, float], data: IdentData, segments: Sequence[Segment],
                max_delay_samples: int) -> lmfit.Parameters:
    """Bounded lmfit Parameters around the start values (bounds wide enough never to
    bind on a plant the start estimate saw, narrow enough to keep the simulation sane)."""
    period = data.period
    u_max = float(np.max(np.abs(data.torque))) or 1.0
    v_max = float(np.max(np.abs(data.velocity))) or 1.0
    j0 = start["inertia"] or u_max * period
    p = lmfit.Parameters()
    p.add("inertia", value=j0, min=j0 / 20.0, max=j0 * 20.0)
    b_max = 10.0 * u_max / v_max
    p.add("viscous_friction", value=min(start["viscous_friction"], b_max / 2), min=0.0, max=b_max)
    p.add("coulomb_friction", value=min(start["coulomb_friction"], u_max / 2), min=0.0, max=u_max)
    if "stiffness" in start:
        qs = np.concatenate([data.position[s.start:s.stop] for s in segments if s.kind == "contact"])
        span = max(float(np.ptp(qs)), 1e-3)
        lo, hi = float(np.min(qs)) - span, float(np.max(qs)) + span
        k0 = start["stiffness"] or u_max / span
        p.add("stiffness", value=k0, min=k0 / 20.0, max=k0 * 20.0)
        p.add("contact_position", value=min(max(start["contact_position"], lo), hi), min=lo, max=hi)
        d_max = 10.0 * u_max / v_max + 10.0 * start["damping"]
        p.add("damping", value=min(start["damping"], d_max / 2), min=0.0, max=d_max)
    d0 = start["delay"]
    p.add("delay", value=d0, min=0.0, max=(max_delay_samples + 1) * period)
    return p


def identify(data: IdentData, segments: Sequence[Segment], *,
             max_delay_samples: int = 3) -> IdentResult:
    """Fit the plant to ``data`` over ``segments`` (see the module docstring)."""
    segments = tuple(segments)
    if not segments:
        raise ValueError("identify: no segment to fit")
    n = len(data.torque)
    for s in segments:
        if not 0 <= s.start < s.stop <= n or s.kind not in ("free", "contact"):
            raise ValueError(f"identify: segment {s} outside the record of {n} samples "
                             "or of an unknown kind (free | contact)")
        if s.stop - s.start <= 2 * _SMOOTH + 2:
            raise ValueError(f"identify: segment {s} too short (at least {2 * _SMOOTH + 3} samples)")
    contact = any(s.kind == "contact" for s in segments)
    start = _start(data, segments, contact, max_delay_samples)
    params = _parameters(start, data, segments, max_delay_samples)
    fixed = {"torque_gain": 1.0}
    minimizer = lmfit.Minimizer(_residual, params, fcn_args=(data, segments, fixed))
    # Levenberg-Marquardt with forward differences of ~3e-4 relative step (epsfcn): stick-slip
    # makes the cost rough on the scale of MINPACK's default step (1.5e-8), which stops the
    # fit short of the optimum; a step above that roughness finds it (tested)
    result = minimizer.minimize(method="leastsq", epsfcn=_EPSFCN)
    result = _search_delay(minimizer, result, data.period)
    estimates = _estimates(minimizer, result, data, contact)
    fitted = [k for k in PARAMETERS if estimates[k].identifiable]
    correlations: dict[tuple[str, str], float] = {}
    for a in fitted:
        for b, c in (result.params[a].correl or {}).items():
            if b in fitted and PARAMETERS.index(a) < PARAMETERS.index(b):
                correlations[(a, b)] = float(c)
    return IdentResult(estimates=estimates, correlations=correlations,
                       residual=_whiteness(np.asarray(result.residual, float)),
                       segments=segments, period=data.period)


def _search_delay(minimizer: lmfit.Minimizer, result: lmfit.minimizer.MinimizerResult,
                  period: float) -> lmfit.minimizer.MinimizerResult:
    """The whole-sample part of the delay by search: the cost is rough in the delay (each
    whole sample is its own valley when the record is short), so the fit is tried again
    from a quarter, a half and a whole period either side whenever the cost there, the
    other parameters held, is lower; the lowest fit wins."""
    best = result
    for _ in range(3):
        params = best.params.copy()
        d = params["delay"]
        cost, start = best.chisqr, None
        for shift in (-1.0, -0.5, -0.25, 0.25, 0.5, 1.0):
            trial = d.value + shift * period
            if not d.min <= trial <= d.max:
                continue
            params["delay"].set(value=trial)
            c = float(np.sum(minimizer.userfcn(params, *minimizer.userargs) ** 2))
            if c < cost:
                cost, start = c, trial
        if start is None:
            return best
        params["delay"].set(value=start)
        again = minimizer.minimize(method="leastsq", params=params, epsfcn=_EPSFCN)
        if not again.chisqr < best.chisqr:
            return best
        best = again
    return best


def _estimates(minimizer: lmfit.Minimizer, result: lmfit.minimizer.MinimizerResult,
               data: IdentData, contact: bool) -> dict[str, Estimate]:
    z = float(scipy.stats.norm.ppf(0.5 + LEVEL / 2))
    u_max = float(np.max(np.abs(data.torque))) or 1.0
    v_max = float(np.max(np.abs(data.velocity))) or 1.0
    floors = {"viscous_friction": 0.01 * u_max / v_max, "coulomb_friction": 0.01 * u_max}
    out: dict[str, Estimate] = {}
    for name in PARAMETERS:
        if name == "torque_gain":
            out[name] = _not(name, "scales with inertia, friction and environment alike: torque "
                                   "and motion alone cannot tell it (held at 1)")
            continue
        if name in _ENVIRONMENT and not contact:
            out[name] = _not(name, "no contact segment in the record")
            continue
        p = result.params[name]
        value, stderr = float(p.value), p.stderr
        if stderr is None or not math.isfinite(stderr):
            out[name] = _not(name, "flat profile: the record does not determine it "
                                   "(singular covariance)")
            continue
        half = z * float(stderr)
        if half > abs(value) + floors.get(name, 0.0):
            out[name] = _not(name, f"flat profile: the 95 % interval (+-{half:.3g}) is wider "
                                   f"than the value ({value:.3g})")
            continue
        low, high = value - half, value + half
        if low < p.min or high > p.max:
            low, high = _profile(minimizer, result, name, low, high)
        out[name] = Estimate(name=name, value=value, stderr=float(stderr), low=low, high=high,
                             identifiable=True, why="")
    return out


def _profile(minimizer: lmfit.Minimizer, result: lmfit.minimizer.MinimizerResult, name: str,
             low: float, high: float) -> tuple[float, float]:
    """The profile-likelihood interval of ``name`` (lmfit's F-test on the chi-square),
    for a parameter whose symmetric interval leaves its bounds; the symmetric one clipped
    to the bounds if the profile cannot be traced."""
    p = result.params[name]
    try:
        with warnings.catch_warnings():
            # lmfit warns when the profile reaches a bound before the level: the interval
            # then ends at that bound (a friction that may be 0), which is what we report
            warnings.filterwarnings("ignore", message="Bound reached", category=UserWarning)
            ci = lmfit.conf_interval(minimizer, result, p_names=[name], sigmas=[LEVEL])
    except (lmfit.minimizer.MinimizerException, ValueError, RuntimeError):
        return max(low, p.min), min(high, p.max)
    values = [v for _, v in ci[name]]
    lo, hi = float(values[0]), float(values[-1])
    return (lo if math.isfinite(lo) else max(low, p.min)), (hi if math.isfinite(hi) else min(high, p.max))


def _not(name: str, why: str) -> Estimate:
    nan = math.nan
    return Estimate(name=name, value=nan, stderr=nan, low=nan, high=nan, identifiable=False, why=why)


def _whiteness(r: np.ndarray, lags: int = WHITENESS_LAGS) -> Residual:
    """RMS and the Ljung-Box test of the residual ``r``."""
    rms = float(np.sqrt(np.mean(r ** 2)))
    x = r - r.mean()
    c0 = float(x @ x)
    n = len(x)
    lags = min(lags, n - 1)
    if c0 == 0.0 or lags < 1:
        return Residual(rms=rms, whiteness_p=1.0, misfit=False, warning="")
    k = np.arange(1, lags + 1)
    acf = np.array([float(x[:-j] @ x[j:]) for j in k]) / c0
    q = n * (n + 2) * float(np.sum(acf ** 2 / (n - k)))
    p = float(scipy.stats.chi2.sf(q, lags))
    if p >= MISFIT_P:
        return Residual(rms=rms, whiteness_p=p, misfit=False, warning="")
    return Residual(rms=rms, whiteness_p=p, misfit=True,
                    warning=f"model misfit: the velocity residual is not white (Ljung-Box "
                            f"p = {p:.2g} < {MISFIT_P:g} over {lags} lags, RMS {rms:.3g} rad/s): "
                            "the plant model cannot represent this record; do not trust the "
                            "estimates")
