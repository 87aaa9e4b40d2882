"""The grey-box fit: the emulator's plant (:mod:`dobhil.identify.model`) fitted to a record
of sent torque and measured motion with lmfit.

What is fitted, and why so:

- the residual is the measured velocity minus the simulated one (output error: the model
  is simulated from each segment's start, never fed the noisy measurements, so the
  sensor noise does not bias the estimates). The position is not a residual: its
  quantisation error is correlated whenever the servo moves slowly, which would make the
  intervals too narrow;
- each segment's initial state is fitted too (nuisance parameters, not reported): its
  velocity (a segment found in a run starts moving, and a reading is noisy) and, in
  contact, its position within the encoder's count (half a count is a large spring
  torque); see "each segment's initial state" below;
- the free parameters are bounded lmfit Parameters fitted by lmfit's Levenberg-Marquardt,
  then refined by lmfit's ``least_squares`` (scipy's trust region) on a central-difference
  Jacobian whose steps are the standard errors themselves (:func:`_refine`: the cost is
  rough on MINPACK's scale); the covariance is ``s^2 (J^T J)^-1`` of the Jacobian scipy
  returns, ``s^2`` the velocity residual's variance. A 95 %
  interval is ``value +- z stderr``; where that leaves a bound the parameter cannot pass
  (a friction or delay near 0) it runs from the bound to the profile likelihood's high
  end (refits with the parameter held, :func:`_profile_high`: 1-6 refits, 0.1-1.6 s on a
  60 s record, measured) -- asymmetric, as a bounded parameter's likelihood is. Levenberg-Marquardt runs
  coarse to fine from the equation-error start, plus a second start (:func:`_staged`);
  a second end within the profile threshold of the best widens the interval to it
  (:func:`_rivals`); on a noise-free record the fit is restarted with the delay held at a
  whole sample (:func:`_whole_delay`: the contact's washboard);
- the delay is one continuous parameter ``delay = whole T + fraction`` (the model is
  continuous in it: a fraction of a whole period is the next whole sample); a grid search
  over half periods up to ``max_delay_samples`` picks where the local fit starts, so a
  whole-sample delay is found by search, its fraction by the fit;
- the torque gain is never identifiable from torque and motion alone (inertia, friction,
  stiffness, damping and gain scaled together give the same motion): it is held at 1 and
  reported not identifiable. Without a contact segment the environment (stiffness,
  damping, contact position) is not fitted and reported not identifiable; a parameter
  whose 95 % interval is wider than half its value (friction: plus 1 % of the torque the
  record used; the delay: than a period; the contact position: than the motion in
  contact) has a flat profile and is reported not identifiable too, naming the parameter
  it is confounded with (a contact-only record: viscous friction and environment damping
  act as their sum);
- the residual's whiteness is the Ljung-Box test; a p-value below :data:`MISFIT_P` is a
  misfit: the model cannot represent the record and the numbers are not to be trusted --
  unless the residual is below :data:`NOISE_FLOOR` of the velocity (noise-free data: the
  residual is rounding, coloured but no model error).
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from types import MappingProxyType
from typing import Any

import lmfit
import numpy as np
import scipy.stats

from dobhil.identify.data import IdentData, Segment, contact_mask
from dobhil.identify.intervals import CONFIG_KEYS
from dobhil.identify.model import ModelValues, simulate_torque, split_delay
from dobhil.realtime import one_blas_thread

__all__ = ["MISFIT_P", "NOISE_FLOOR", "PARAMETERS", "WIDEST", "Estimate", "IdentResult",
           "Residual", "identify", "simulate"]

PARAMETERS = ("inertia", "viscous_friction", "coulomb_friction", "torque_gain",
              "contact_position", "stiffness", "damping", "delay")   # delay [s] = whole + fraction

#: Ljung-Box p-value below which the residual is not white: the model misfits the record
MISFIT_P = 1e-3
#: lags of the Ljung-Box test
WHITENESS_LAGS = 20
#: confidence level of the intervals
LEVEL = 0.95
#: a 95 % interval wider than this fraction of the value either side is no number: the
#: linearised interval is not to be trusted that far (measured: a barely moving contact
#: record fitted to J = 0.0027 for 0.25 gave K = 1125 +- 790 for 1e4, the truth's cost
#: only 3.2 noise variances above the fit's -- another valley, not the interval's)
WIDEST = 0.5

_ENVIRONMENT = ("contact_position", "stiffness", "damping")
#: parameters whose search minimum is a search bound, not the plant's (a friction, a damping
#: or a delay of 0 is a bound the truth cannot pass: its interval ends there)
_SEARCH_FLOOR = ("inertia", "stiffness", "contact_position")
#: MINPACK's forward-difference step is ``sqrt(epsfcn)`` relative: the fine stage ~3e-4,
#: the coarse one ~1 % (see :func:`_staged`)
_EPSFCN = 1e-7
_EPSFCN_COARSE = 1e-4
#: evaluations per varied parameter (+1) the coarse stage may spend
_COARSE_EVALUATIONS = 100
#: MINPACK's stopping tolerances: the cost changing by less than this (relative) ends
#: Levenberg-Marquardt -- its default 1.5e-8 chases the roughness for dozens of
#: evaluations; :func:`_refine` finishes the optimum on the interval's own scale
_TOLERANCES = {"ftol": 1e-6, "xtol": 1e-6}
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
    #: how ``high`` was found: "linearised" (value + z stderr), "log-linearised" (value
    #: exp(z stderr / value), the closed-loop fit's inertia, stiffness and damping,
    #: dobhil.identify.closedloop._interval) or "profile" (a parameter whose linearised
    #: interval leaves its bound: the profile likelihood, see _profile_high; in the
    #: closed-loop fit the delay's both ends, dobhil.identify.closedloop._Profile) or "hull"
    #: (the closed-loop fit's inertia, stiffness and damping: the hull of the
    #: log-linearised and the profile interval, dobhil.identify.closedloop._profiled)
    method: str = "linearised"


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
    #: per segment, the fitted true ``(position, velocity)`` at its first sample (the
    #: measured ones are quantised and noisy): pass to :func:`simulate` as ``initial``
    initial: tuple[tuple[float, float], ...] = ()
    #: every fitted parameter's value, identifiable or not (the closed-loop fit's: the model
    #: it simulated, which its validation and figure simulate again; empty: not recorded)
    fitted: Mapping[str, float] = field(default_factory=dict)

    def damping_sum(self) -> float | None:
        """The servo's viscous friction plus the environment's damping the fit ended at, when
        the record determines only that sum: every segment in contact, the damping
        identifiable and the friction not (both act on the one velocity while the servo is
        pressed: the closed-loop fit folds them, ``dobhil.identify.closedloop._fold_friction``;
        the open-loop fit finds the friction's profile flat along the damping); else None. A
        contact segment that also moves free with the friction still flat gets the same sum:
        the friction's share of it is then within that flat interval."""
        b, d = self.estimates["viscous_friction"], self.estimates["damping"]
        if (b.identifiable or not d.identifiable or not self.segments
                or any(s.kind != "contact" for s in self.segments)
                or "viscous_friction" not in self.fitted or "damping" not in self.fitted):
            return None
        return float(self.fitted["viscous_friction"] + self.fitted["damping"])

    def overlay(self, friction: float | None = None) -> dict[str, Any]:
        """The config overlay of the identifiable values: ``plant.*``, ``environment.*``,
        ``design.delay_samples``/``design.input_delay`` and ``design.identified_inertia``.

        Where the record determines only friction plus damping (:meth:`damping_sum`) the
        friction is left out -- the config's own stays -- and the damping written is the sum
        less ``friction`` (the recorded config's ``plant.viscous_friction``; None: not known,
        the sum), at least 0: in contact the loop then has the fitted total damping, as a
        config of the recorded run's friction plus the written damping, and in free motion
        the friction the config had. Why not the fitted friction and damping each: the record
        fixes only their sum, the split is where the fit stopped along a flat valley
        (docs/identify.md section 5's force1.mcap, open loop: b 7.16 and D 52.65 for a true
        0.05 and 60), and a b of 7 is wrong wherever the servo moves free. Why not the damping
        estimate alone: the config's friction, not the fitted one, is then added to it, and the
        loop in contact lacks the rest (measured: force1.mcap's open-loop D alone, run with that
        section's chirp and seed 1, stopped ``unstable`` at cycle 2858 of 3000; the sum written
        as here ran the 3000). The overlay is for a config of the recorded friction (the run's
        own, on a real drive); another friction moves the contact's total by the difference."""
        out: dict[str, Any] = {}
        for name, key in CONFIG_KEYS.items():
            e = self.estimates[name]
            if e.identifiable:
                out[key] = e.value
        total = self.damping_sum()
        if total is not None:
            out["environment.damping"] = max(total - (friction or 0.0), 0.0)
        if self.estimates["inertia"].identifiable:
            out["design.identified_inertia"] = self.estimates["inertia"].value
        delay = self.estimates["delay"]
        if delay.identifiable and self.period > 0:
            whole, fraction = split_delay(delay.value, self.period)
            out["design.delay_samples"] = whole
            out["design.input_delay"] = fraction
        return out


def simulate(values: Mapping[str, float], data: IdentData, segment: Segment,
             initial: tuple[float, float] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Position and velocity [rad, rad/s] of the model ``values`` (names of
    :data:`PARAMETERS`; missing ones: no friction, gain 1, no environment, no delay) over
    ``segment`` of ``data``, driven by ``data.torque``, from ``initial`` (true position and
    velocity at the segment's first sample, :attr:`IdentResult.initial`; default: at rest
    at the measured position). A free segment is simulated without the environment (it is
    free by definition; records joined from several runs put their free motion anywhere,
    also where another run's environment was)."""
    if segment.kind != "contact":
        values = {k: v for k, v in values.items() if k not in _ENVIRONMENT}
    q0, v0 = initial if initial is not None else (float(data.position[segment.start]), 0.0)
    return simulate_torque(_model(values), data.torque, data.period, segment.start,
                           segment.stop, q0, v0)


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


# -- each segment's initial state: nuisance parameters -------------------------------------
#
# A segment cut from a run starts moving, at a quantised position and a noisy velocity:
# simulating it from those readings puts their errors into every parameter (half a count
# of an encoder at K = 1e4 N m/rad is a 2 N m spring error: measured, the contact position
# 3-6 standard errors off). So each segment's true initial velocity is fitted, and each
# contact segment's true initial position, within what the encoder says: the velocity
# residual sees only the penetration q0 - q_c, so one more row per contact segment,
# ``(q0 - measured) / (count / sqrt 12)`` in units of the velocity noise, ties q0 to its
# reading with the quantisation's own spread (uniform over a count) -- the contact
# position's interval then holds the encoder's resolution too, as it must.


def _q0(i: int) -> str:
    return f"initial_position_{i}"


def _v0(i: int) -> str:
    return f"initial_velocity_{i}"


def _quantum(position: np.ndarray) -> float:
    """The encoder count of a quantised position record (every step a whole multiple of
    the smallest one), else 0 (a continuous position)."""
    steps = np.abs(np.diff(np.asarray(position, float)))
    scale = max(float(np.max(np.abs(position))), 1.0) if len(position) else 1.0
    steps = steps[steps > 1e-12 * scale]
    if steps.size == 0:
        return 0.0
    count = float(np.min(steps))
    ratio = steps / count
    return count if float(np.max(np.abs(ratio - np.round(ratio)))) < 1e-3 else 0.0


def _initial(values: Mapping[str, float], data: IdentData, i: int,
             segment: Segment) -> tuple[float, float]:
    """The initial (position, velocity) of segment ``i``: fitted when a parameter, else
    the measured position and rest."""
    q0 = values.get(_q0(i), float(data.position[segment.start]))
    return float(q0), float(values.get(_v0(i), 0.0))


def _residual(params: lmfit.Parameters, data: IdentData, segments: Sequence[Segment],
              fixed: Mapping[str, float]) -> np.ndarray:
    """Measured minus simulated velocity over every segment, one after the other, then
    the initial positions' ties to their readings (weight ``fixed["prior_weight"]``)."""
    values = {**fixed, **params.valuesdict()}
    parts = []
    for i, s in enumerate(segments):
        _, vel = simulate(values, data, s, _initial(values, data, i, s))
        parts.append(np.asarray(data.velocity[s.start:s.stop], float) - vel)
    weight = fixed.get("prior_weight", 0.0)
    ties = [weight * (values[_q0(i)] - float(data.position[s.start]))
            for i, s in enumerate(segments) if _q0(i) in values]
    return np.concatenate([*parts, np.asarray(ties, float)])


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
    # a contact segment may leave the environment and come back: its rows count as in
    # contact where the data say so (the spring that best explains the acceleration), all
    # of them if the data find no spring
    engaged = contact_mask(data) if contact else np.zeros(len(q), dtype=bool)
    in_contact = np.concatenate([
        (engaged[s.start + _SMOOTH:s.stop - _SMOOTH]
         if s.kind == "contact" and engaged[s.start:s.stop].any()
         else np.full(max(0, s.stop - s.start - 2 * _SMOOTH), s.kind == "contact"))
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
    bind on a plant the start estimate saw, narrow enough to keep the simulation sane).
    The scales are the segments' own samples: lmfit maps a bounded parameter through its
    bounds (``lmfit/parameter.py``, MINUIT's transformation), so bounds taken from samples
    outside the segments -- a capture's idle minutes before and after the run -- would move
    where the fit ends on the very same segment."""
    period = data.period
    torque = np.concatenate([data.torque[s.start:s.stop] for s in segments])
    velocity = np.concatenate([data.velocity[s.start:s.stop] for s in segments])
    u_max = float(np.max(np.abs(torque))) or 1.0
    v_max = float(np.max(np.abs(velocity))) or 1.0
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


class _Counted:
    """:func:`_residual`, telling ``progress`` of each evaluation (one simulation of every
    segment: the unit of the fit's work) and which stage of the fit asked for it."""

    def __init__(self, progress: Callable[[str], object] | None) -> None:
        self.progress = progress
        self.stage = "first fit"

    def __call__(self, params: lmfit.Parameters, data: IdentData, segments: Sequence[Segment],
                 fixed: Mapping[str, float]) -> np.ndarray:
        out = _residual(params, data, segments, fixed)
        if self.progress is not None:
            self.progress(self.stage)
        return out


def identify(data: IdentData, segments: Sequence[Segment], *, max_delay_samples: int = 3,
             progress: Callable[[str], object] | None = None) -> IdentResult:
    """Fit the plant to ``data`` over ``segments`` (see the module docstring).
    ``progress(stage)`` after each simulation of the segments (a long log: seconds each).

    Runs with BLAS on one thread (:func:`~dobhil.realtime.one_blas_thread`): besides the
    simulations' tiny matrices, the fit's own linear algebra is tall and thin -- scipy's
    trust-region step takes an SVD of the Jacobian, one row per sample (60001 x 9 for a
    minute of log) -- and a threaded OpenBLAS took 0.25 s for it on this 2-core machine
    under load, against 0.03 s on one thread (measured, ``scipy.linalg.svd``)."""
    with one_blas_thread(), warnings.catch_warnings():
        # lmfit takes its own standard errors after each leastsq fit (np.sqrt of its
        # covariance's diagonal); of a record that determines some direction only to
        # rounding (a noise-free emulated run in contact) that diagonal has a rounding-
        # negative entry, and numpy warned "invalid value encountered in sqrt" on the
        # user's terminal. That standard error is then NaN, which _first_step passes over;
        # the intervals are from the fit's own covariance (_inverse_normal), never lmfit's.
        # Only that warning, only from lmfit's modules, is silenced.
        warnings.filterwarnings("ignore", message="invalid value encountered in sqrt", category=RuntimeWarning,
                                module=r"lmfit\.")
        return _identify(data, tuple(segments), max_delay_samples, progress)


def _identify(data: IdentData, segments: tuple[Segment, ...], max_delay_samples: int,
              progress: Callable[[str], object] | None) -> IdentResult:
    """:func:`identify` inside one BLAS thread."""
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
    count = _quantum(data.position)
    # the ties' weight turns a position error into velocity-noise units: sigma_v / sigma_q,
    # sigma_v first from the velocity's sample-to-sample scatter (an upper bound), then from
    # the fit's residual
    fixed = {"torque_gain": 1.0}
    for i, s in enumerate(segments):
        params.add(_v0(i), value=float(data.velocity[s.start]))
    if count > 0.0:
        for i, s in enumerate(segments):
            if s.kind == "contact":
                q = float(data.position[s.start])
                params.add(_q0(i), value=q, min=q - count, max=q + count)
        fixed["prior_weight"] = _noise_guess(data, segments) / (count / math.sqrt(12.0))
    counted = _Counted(progress)
    minimizer = lmfit.Minimizer(counted, params, fcn_args=(data, segments, fixed))
    result, other = _staged(minimizer)
    counted.stage = "delay search"
    result = _search_delay(minimizer, result, data.period)
    rows = sum(s.stop - s.start for s in segments)
    if "prior_weight" in fixed:
        velocity = np.asarray(result.residual, float)[:rows]
        fixed["prior_weight"] = (float(np.sqrt(np.mean(velocity ** 2)))
                                 / (count / math.sqrt(12.0)))
    counted.stage = "refinement"
    refined = _refine(minimizer, result, rows)
    if _noise_free(refined.residual[:rows], data, segments):
        counted.stage = "whole-sample delay"
        refined = _whole_delay(minimizer, refined, data.period, rows)
    # the refined optimum is the result
    result.params = refined.params
    result.residual = refined.residual
    result.chisqr = float(refined.residual @ refined.residual)
    velocity_residual = refined.residual[:rows]
    covariance = refined.covariance
    rivals = _rivals(minimizer, other, result.chisqr, velocity_residual,
                     len(covariance[0]) if covariance is not None else 0)
    counted.stage = "intervals"
    estimates = _estimates(minimizer, result, covariance, data, segments, rivals)
    estimates = _profiled(minimizer, result, estimates, velocity_residual, data, segments)
    estimates, covariance = _fold_damping(estimates, covariance, result.params.valuesdict(), segments)
    fitted = [k for k in PARAMETERS if estimates[k].identifiable]
    correlations: dict[tuple[str, str], float] = {}
    if covariance is not None:
        names, cov = covariance
        sd = np.sqrt(np.diag(cov))
        for i, a in enumerate(names):
            for j, b in enumerate(names):
                if a in fitted and b in fitted and PARAMETERS.index(a) < PARAMETERS.index(b):
                    correlations[(a, b)] = float(np.clip(cov[i, j] / (sd[i] * sd[j]), -1.0, 1.0))
    return IdentResult(estimates=estimates, correlations=correlations,
                       residual=_whiteness(velocity_residual, _velocity_rms(data, segments)),
                       segments=segments, period=data.period,
                       initial=tuple(_initial(result.params.valuesdict(), data, i, s)
                                     for i, s in enumerate(segments)),
                       # the model the fit ended at, every fitted parameter: what the segments'
                       # initial states were fitted with, and what determines the motion where the
                       # record confounds two (a pressed servo's b and D_env act as their sum)
                       fitted=MappingProxyType({k: float(result.params[k].value) for k in PARAMETERS
                                                if k in result.params}))


def _staged(minimizer: lmfit.Minimizer
            ) -> tuple[lmfit.minimizer.MinimizerResult, lmfit.minimizer.MinimizerResult]:
    """Levenberg-Marquardt from the start values, coarse to fine: forward differences of
    ~1 % relative step (:data:`_EPSFCN_COARSE`) first, then of ~3e-4 (:data:`_EPSFCN`);
    and, as a second start, the fine one alone. Returns (the lower, the other): where the
    two end in different valleys of about the same cost, the record does not decide
    between them (:func:`_rivals`).

    Why two scales: stick-slip makes the output-error cost rough -- every velocity zero
    crossing switches the Coulomb friction on a sub-step, and a parameter moving one by a
    sub-step makes the residual jump. The roughness is larger, the more crossings the
    record has: on a 60 s free multisine with Coulomb friction (thousands of crossings,
    noise-free) a 3e-4 step measures the jumps, not the slope, and points nowhere --
    Levenberg-Marquardt stopped after 10 evaluations where the equation-error start put
    it (viscous friction 0.078 for 0.02, Coulomb 0.0436 for 0.05, residual RMS 1.1e-3
    rad/s, the truth's 1e-8; measured, the cost falls monotonically on the straight line
    between them, so no other valley, only a blind gradient). A 1 % step is a secant over
    the roughness and walks to the truth (1e-3 ... 1e-5 all did); the fine stage then
    settles where MINPACK's scale can. MINPACK's default step (1.5e-8) is worse still:
    it stops the fit short even on short records (tested)."""
    # a copy: a fit leaves the minimizer's own parameters at its end
    start = minimizer.params.copy()
    # bounded: the coarse stage only has to reach the right valley (measured: 33 evaluations
    # on the 60 s free multisine, 357 on a 60 s pressed PRBS with Coulomb friction, 2.4 s)
    varied = sum(1 for p in start.values() if p.vary)
    coarse = minimizer.minimize(method="leastsq", params=start.copy(), epsfcn=_EPSFCN_COARSE,
                                max_nfev=_COARSE_EVALUATIONS * (varied + 1), **_TOLERANCES)
    fine = minimizer.minimize(method="leastsq", params=coarse.params, epsfcn=_EPSFCN,
                              **_TOLERANCES)
    staged = fine if fine.chisqr <= coarse.chisqr else coarse
    alone = minimizer.minimize(method="leastsq", params=start, epsfcn=_EPSFCN, **_TOLERANCES)
    return (staged, alone) if staged.chisqr <= alone.chisqr else (alone, staged)


def _rivals(minimizer: lmfit.Minimizer, other: lmfit.minimizer.MinimizerResult,
            best: float, velocity: np.ndarray, varied: int) -> list[dict[str, float]]:
    """The other start's end, when its cost (recomputed: the ties' weight may have changed)
    is within the 95 % profile threshold of the best, ``chi2_1(0.95) s^2`` above it:
    every parameter's value there then lies inside its profile-likelihood interval (the
    profile at that value is at most that cost), so the interval must reach it.

    Why: a record that barely moves has valleys the linearised interval knows nothing of
    (measured: a pressed record, 0.002 rad/s of motion under 0.01 of noise, ended at
    K = 2950 [1671, 4229] from one start and 1123 from the other, 1.3 noise variances
    apart in cost, truth 1e4): the second start is a cheap look at the profile's width."""
    r = np.asarray(minimizer.userfcn(other.params, *minimizer.userargs), float)
    s2 = float(velocity @ velocity) / max(velocity.size - varied, 1)
    threshold = best + float(scipy.stats.chi2.ppf(LEVEL, 1)) * s2
    return [other.params.valuesdict()] if float(r @ r) <= threshold else []


def _noise_guess(data: IdentData, segments: Sequence[Segment]) -> float:
    """The velocity noise's standard deviation, from above: the RMS of second differences
    over sqrt 6 (white noise's; the motion's own curvature adds to it)."""
    v = np.concatenate([np.diff(np.asarray(data.velocity[s.start:s.stop], float), 2)
                        for s in segments])
    return float(np.sqrt(np.mean(v ** 2) / 6.0)) or 1e-12


def _velocity_rms(data: IdentData, segments: Sequence[Segment]) -> float:
    v = np.concatenate([np.asarray(data.velocity[s.start:s.stop], float) for s in segments])
    return float(np.sqrt(np.mean(v ** 2)))


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
        again = minimizer.minimize(method="leastsq", params=params, epsfcn=_EPSFCN,
                                   **_TOLERANCES)
        if not again.chisqr < best.chisqr:
            return best
        best = again
    return best


# -- the covariance: a Jacobian on the scale of the uncertainty ---------------------------

#: rounds of :func:`_refine` (each: one least_squares fit whose Jacobian steps are the
#: standard errors at its start)
_REFINE_ROUNDS = 4
#: a round lowering the cost by less than this many noise variances is the last
_SETTLED = 0.01


@dataclass(frozen=True)
class _Refined:
    params: lmfit.Parameters
    residual: np.ndarray                                    # velocity rows, then the ties
    covariance: tuple[list[str], np.ndarray] | None         # (names, matrix) of the varied ones


def _refine(minimizer: lmfit.Minimizer, result: lmfit.minimizer.MinimizerResult,
            rows: int) -> _Refined:
    """The optimum and the covariance ``s^2 (J^T J)^-1`` on the interval's own scale:
    rounds of lmfit's ``least_squares`` (scipy's trust-region reflective, bounded) with
    central differences (``jac='3-point'``) whose step is each parameter's standard error
    (from lmfit's at first, then from the previous round's covariance), the variables
    scaled by it (``x_scale``); ``J`` is the Jacobian scipy returns at the round's end,
    ``s^2`` the variance of the ``rows`` velocity residuals (the ties are no noise).

    Why not lmfit's optimum and covariance alone: they come from MINPACK's forward
    differences at ~3e-4 relative (epsfcn). The output-error cost is rough on that scale --
    every stick, slip and contact change sits on a sub-step, and a parameter moving one of
    them by a sub-step makes the residual jump -- so a tiny step measures the jumps, not
    the curvature the interval is about: the delay's standard error came out 13x too
    small (measured: the cost rises by one noise variance at +-10 us, lmfit said 0.75 us;
    its interval missed the truth in 12 of 50 runs), and Levenberg-Marquardt stops in a
    dent of the roughness (a record cut in motion: the truth's cost 10 sigma^2 below the
    fit's, viscous friction 3.4 standard errors off). A step the size of the standard
    error is a secant over the interval itself, through the roughness, and the trust
    region on that Jacobian leaves the dent.

    scipy's ``diff_step`` is relative: the absolute step is ``diff_step * |x|``
    (:func:`_relative_steps`), so each round sets it from the values it starts at; a
    value that moves far within a round (relative to itself) changes its step, which the
    next round puts right -- rounds run until one lowers the cost by less than
    :data:`_SETTLED` noise variances."""
    params = result.params.copy()
    names = [n for n, p in params.items() if p.vary]
    steps = np.array([_first_step(params[n]) for n in names])
    r0 = np.asarray(result.residual, float)
    velocity = r0[:rows]
    s2 = float(velocity @ velocity) / max(velocity.size - len(names), 1)
    cov = None
    for round_ in range(_REFINE_ROUNDS):
        lo = np.array([params[n].min for n in names])
        hi = np.array([params[n].max for n in names])
        x0 = np.array([params[n].value for n in names])
        steps = np.minimum(steps, 0.25 * (hi - lo))
        cost = float(r0 @ r0)
        # ftol: scipy stops when a step lowers 0.5 sum r^2 by less than ftol of it
        fit = minimizer.minimize(method="least_squares", params=params.copy(), jac="3-point",
                                 diff_step=_relative_steps(_central(steps, x0, lo, hi), x0),
                                 x_scale=steps,
                                 ftol=max(_SETTLED * s2 / max(cost, 1e-300), 1e-15),
                                 xtol=1e-12, gtol=1e-12)
        jac = getattr(fit, "jac", None)
        if jac is None:                       # aborted: no Jacobian at its end
            break
        x = np.array([fit.params[n].value for n in names])
        collapsed = _collapsed(x0, x, lo, hi)
        if collapsed.any():
            jac = np.array(jac, float)
            jac[:, collapsed] = _columns(minimizer, fit.params, names, _central(steps, x, lo, hi), lo, hi,
                                         np.flatnonzero(collapsed))
        inverse = _inverse_normal(np.asarray(jac, float))
        if inverse is None:
            return _Refined(params, r0, None)
        r = np.asarray(fit.residual, float)
        if float(r @ r) <= cost:
            params, r0 = fit.params, r
        velocity = r0[:rows]
        s2 = float(velocity @ velocity) / max(velocity.size - len(names), 1)
        cov = s2 * inverse
        steps = np.sqrt(np.diag(cov))
        if cost - float(r0 @ r0) < _SETTLED * s2 and round_ > 0:
            break
    return _Refined(params, r0, (names, cov) if cov is not None else None)


def _noise_free(velocity: np.ndarray, data: IdentData, segments: Sequence[Segment]) -> bool:
    """Whether the velocity residual is below :data:`NOISE_FLOOR` of the velocity: a
    noise-free record (an emulated run), whose residual is the model's rounding at the truth."""
    return float(np.sqrt(np.mean(velocity ** 2))) <= NOISE_FLOOR * _velocity_rms(data, segments)


#: tolerances of the held fit of :func:`_whole_delay` (a noise-free record's cost falls by
#: orders of magnitude on the way: a relative 1e-6 stops on the first plateau)
_WHOLE_TOL = 1e-12
#: a delay within this fraction of a period of a whole sample is one: no restart (the
#: refinement's misplaced delay is about a sub-step, a tenth of a period)
_WHOLE_NEAR = 1e-3


def _whole_delay(minimizer: lmfit.Minimizer, refined: _Refined, period: float,
                 rows: int) -> _Refined:
    """The refined fit of a noise-free record, or -- when lower -- the fit restarted with the
    delay held at the nearest whole number of periods (the others refitted by scipy's trust
    region), then released and refined again (:func:`_refine`).

    Why: a contact the servo leaves and enters again within a segment switches the Plant's
    mode at a sub-step start (:mod:`dobhil.emulator.plant`), so a parameter moving a crossing
    over a sub-step boundary makes the residual jump: the cost is a washboard whose washes
    are ~0.1 % of the stiffness wide, and the refinement stops in a neighbour of the truth's,
    the delay off by about a sub-step to place the crossings there (measured: the 0.5 s
    lockstep demo run, separated 0.131-0.150 s, ended at delay 0.091 ms for 0, K 9987.9, D
    49.988, residual 6.8e-6 rad/s, every interval excluding the truth; the truth's residual
    1e-9). Under noise the washes are far below the noise variance and this stage is not run.
    A whole-sample delay is what a lockstep emulator with no input delay, and a drive latching
    its commands on a SYNC, apply; held there, the other parameters have no washboard in the
    delay to cross (measured: 36 evaluations to the truth, residual 1e-9)."""
    params = refined.params
    d = params["delay"]
    whole = min(max(round(d.value / period) * period, d.min), d.max)
    if abs(whole - d.value) <= _WHOLE_NEAR * period:
        return refined   # there already: the held fit would start where the refinement ended
    trial = params.copy()
    trial["delay"].set(value=whole, vary=False)
    held = minimizer.minimize(method="least_squares", params=trial, ftol=_WHOLE_TOL,
                              xtol=_WHOLE_TOL, gtol=_WHOLE_TOL)
    if not float(held.chisqr) < float(refined.residual @ refined.residual):
        return refined
    held.params["delay"].set(vary=True)
    again = _refine(minimizer, held, rows)
    return again if float(again.residual @ again.residual) < float(refined.residual @ refined.residual) else refined


def _collapsed(x0: np.ndarray, x: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Which columns of scipy's Jacobian at ``x``, the end of a round that started at ``x0``,
    were taken with a step collapsed far below the round's own (:func:`_relative_steps`): scipy scales
    the relative ``diff_step`` by ``|x|`` where it evaluates the Jacobian, and a value that
    ended within scipy's own 1e-10 of a bound (``make_strictly_feasible``) -- a delay or a
    friction of 0 at 3.9e-13 s from a start of 1e-10 s, measured -- gets its step shrunk by
    the same factor, far below the cost's roughness: its column came out ~0, the standard
    error of a delay of 0 +-3.4 s, and the delay "not identifiable" in 3 of 12 windows of
    one free run where its neighbours said 0 [0, 67 us]. A value that moved inside the
    bounds keeps scipy's step, which the next round puts right."""
    at_bound = ((x - lo <= 1e-10 * np.maximum(1.0, np.abs(lo)))
                | (hi - x <= 1e-10 * np.maximum(1.0, np.abs(hi))))
    shrunk = np.abs(x) < 0.5 * np.maximum(np.abs(x0), 1e-10)
    return at_bound & shrunk


def _columns(minimizer: lmfit.Minimizer, params: lmfit.Parameters, names: Sequence[str],
             steps: np.ndarray, lo: np.ndarray, hi: np.ndarray, which: np.ndarray) -> np.ndarray:
    """Columns ``which`` of the residual's Jacobian at ``params`` with the absolute ``steps``, by scipy's
    '3-point' scheme: central where both sides fit within the bounds, else the one-sided
    three-point formula toward the wider side (as ``scipy.optimize.least_squares`` does at a
    bound). Written here because scipy's differencing (``_numdiff.approx_derivative``) is
    private and takes relative steps only; see :func:`_collapsed` for when it is needed."""
    def at(i: int, value: float) -> np.ndarray:
        trial = params.copy()
        trial[names[i]].set(value=value)
        return np.asarray(minimizer.userfcn(trial, *minimizer.userargs), float)

    f0 = np.asarray(minimizer.userfcn(params, *minimizer.userargs), float)
    x = np.array([params[n].value for n in names])
    columns = []
    for i in (int(j) for j in which):
        h = float(steps[i])
        if x[i] - h >= lo[i] and x[i] + h <= hi[i]:
            columns.append((at(i, x[i] + h) - at(i, x[i] - h)) / (2.0 * h))
            continue
        h = h if hi[i] - x[i] >= x[i] - lo[i] else -h
        h = math.copysign(min(abs(h), 0.5 * max(hi[i] - x[i], x[i] - lo[i])), h)
        columns.append((-3.0 * f0 + 4.0 * at(i, x[i] + h) - at(i, x[i] + 2.0 * h)) / (2.0 * h))
    return np.column_stack(columns)


def _relative_steps(steps: np.ndarray, x: np.ndarray) -> np.ndarray:
    """scipy's ``diff_step`` for absolute steps ``steps`` at ``x``: scipy (1.17,
    ``_numdiff._compute_absolute_step``) takes ``diff_step * sign(x) * |x|``; at ``x = 0``
    it falls back to its own tiny step, so a value at 0 gets its step relative to the
    point the trust-region method moves it to first (``make_strictly_feasible``: 1e-10
    off its bound) -- within a round, see :func:`_refine`."""
    return steps / np.maximum(np.abs(x), 1e-10)


def _central(steps: np.ndarray, x: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """The steps, shortened to fit between ``x`` and its bounds where they can (to no
    less than 5 %). Why: where ``x +- step`` leaves a bound scipy switches to the
    one-sided three-point formula on ``x, x + h, x + 2h`` -- a parabola extrapolated to
    ``x`` through the cost's roughness, not a secant (measured on a pressed record that
    barely moves: the viscous friction / damping correlation -0.89 instead of -0.92); a
    value at its bound (a delay or friction of 0) keeps its step, one-sided as it must."""
    room = np.minimum(x - lo, hi - x)
    return np.where(room >= 0.05 * steps, np.minimum(steps, room), steps)


def _first_step(p: lmfit.Parameter) -> float:
    """lmfit's standard error when it has one, else a thousandth of the value or range."""
    if p.stderr is not None and math.isfinite(p.stderr) and p.stderr > 0:
        return float(p.stderr)
    return 1e-3 * (abs(p.value) or (p.max - p.min if math.isfinite(p.max - p.min) else 1.0))


#: eigenvalues of the scaled normal matrix below this (relative to the largest) are
#: directions the record does not determine
_RANK_TOL = 1e-12


def _inverse_normal(jac: np.ndarray) -> np.ndarray | None:
    """``(J^T J)^-1`` with the columns scaled to unit norm first (parameters of very
    different units); None when the Jacobian is not finite.

    A direction the record does not determine (two parameters acting as their sum, as
    viscous friction and environment damping do in a contact-only record) has an
    eigenvalue ~0: it is floored at :data:`_RANK_TOL` of the largest, so the parameters
    along it get a huge standard error -- reported not identifiable, with the partner
    named -- while the others keep theirs (a pseudo-inverse would drop the direction and
    make them all look determined)."""
    if not np.all(np.isfinite(jac)):
        return None
    norms = np.linalg.norm(jac, axis=0)
    norms = np.where(norms > 0, norms, 1.0)     # a column without effect: eigenvalue 0 below
    scaled = jac / norms
    w, v = np.linalg.eigh(scaled.T @ scaled)
    w = np.maximum(w, _RANK_TOL * max(float(w[-1]), 1e-300))
    inv = (v / w) @ v.T
    return inv / np.outer(norms, norms)


def _estimates(minimizer: lmfit.Minimizer, result: lmfit.minimizer.MinimizerResult,
               covariance: tuple[list[str], np.ndarray] | None, data: IdentData,
               segments: Sequence[Segment],
               rivals: Sequence[Mapping[str, float]] = ()) -> dict[str, Estimate]:
    contact = any(s.kind == "contact" for s in segments)
    z = float(scipy.stats.norm.ppf(0.5 + LEVEL / 2))
    u_max = float(np.max(np.abs(data.torque))) or 1.0
    v_max = float(np.max(np.abs(data.velocity))) or 1.0
    # a value near 0 is still determined when its interval is narrow on the scale that
    # matters: friction against the torque the record used, the delay against a period
    floors = {"viscous_friction": 0.01 * u_max / v_max, "coulomb_friction": 0.01 * u_max,
              "delay": data.period}
    # a position has no natural zero: the contact position is determined when its interval
    # is narrower than the range the servo moved through in contact
    span = max((float(np.ptp(data.position[s.start:s.stop])) for s in segments
                if s.kind == "contact"), default=0.0)
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
        value = float(p.value)
        stderr = None
        if covariance is not None:
            names, cov = covariance
            stderr = float(np.sqrt(cov[names.index(name), names.index(name)]))
        if stderr is None or not math.isfinite(stderr):
            out[name] = _not(name, "flat profile: the record does not determine it "
                                   "(singular covariance)")
            continue
        # another fit within the profile threshold (_rivals): the interval reaches it
        others = [float(r[name]) for r in rivals]
        low = min([value - z * float(stderr), *others])
        high = max([value + z * float(stderr), *others])
        half = max(value - low, high - value)
        if name == "contact_position" and half > span:
            out[name] = _not(name, f"flat profile: the 95 % interval (+-{half:.3g}) is wider "
                                   f"than the motion in contact ({span:.3g})"
                                   + _partner(name, covariance))
            continue
        if name != "contact_position" and half > WIDEST * abs(value) + floors.get(name, 0.0):
            out[name] = _not(name, f"flat profile: the 95 % interval (+-{half:.3g}) is wider "
                                   f"than {WIDEST:g} of the value ({value:.3g})"
                                   + _partner(name, covariance))
            continue
        # the search's own bounds (every maximum, and the minimum of a parameter with no
        # natural 0: _parameters) are no bound of the plant: an interval reaching past one
        # says the record's answer may lie where the fit did not look, not a number
        edge = p.max if high > p.max else (p.min if low < p.min and name in _SEARCH_FLOOR else None)
        if edge is not None:
            out[name] = _not(name, f"its 95 % interval (+-{half:.3g} about {value:.3g}) reaches past the bound "
                                   f"of the fit's search ({edge:.3g}): the record's answer may lie where the "
                                   "fit did not look")
            continue
        # at a bound (a friction or a delay that may be 0) the interval ends there: the
        # truth cannot lie beyond it (its high end then from the profile: _profiled);
        # inside the bounds the linearised interval on the secant Jacobian (_refine) is
        # what the coverage test checks
        low, high = max(low, p.min), min(high, p.max)
        out[name] = Estimate(name=name, value=value, stderr=float(stderr), low=low, high=high,
                             identifiable=True, why="")
    return out


def _profiled(minimizer: lmfit.Minimizer, result: lmfit.minimizer.MinimizerResult,
              estimates: dict[str, Estimate], velocity: np.ndarray, data: IdentData,
              segments: Sequence[Segment]) -> dict[str, Estimate]:
    """The estimates, where a linearised interval was cut at its bound (a friction or a
    delay near 0: ``value - z stderr`` below it) with the high end from the profile
    likelihood instead (:func:`_profile_high`) -- an asymmetric interval. The
    width rule of :func:`_estimates` then judges the profiled interval."""
    z = float(scipy.stats.norm.ppf(0.5 + LEVEL / 2))
    varied = sum(1 for p in result.params.values() if p.vary)
    s2 = float(velocity @ velocity) / max(velocity.size - varied, 1)
    rise = float(scipy.stats.chi2.ppf(LEVEL, 1)) * s2
    best = float(result.chisqr)
    u_max = float(np.max(np.abs(data.torque))) or 1.0
    v_max = float(np.max(np.abs(data.velocity))) or 1.0
    floors = {"viscous_friction": 0.01 * u_max / v_max, "coulomb_friction": 0.01 * u_max,
              "delay": data.period}
    out = dict(estimates)
    for name, e in estimates.items():
        p = result.params.get(name)
        if p is None or not e.identifiable or not e.value - z * e.stderr < p.min:
            continue
        high = _profile_high(minimizer, result.params, name, e.value,
                             max(e.high, e.value + z * e.stderr),
                             best, rise)
        if high - e.value > WIDEST * abs(e.value) + floors.get(name, 0.0):
            out[name] = _not(name, f"flat profile: the 95 % profile interval reaches {high:.3g}, "
                                   f"wider than {WIDEST:g} of the value ({e.value:.3g})")
            continue
        out[name] = replace(e, high=high, method="profile")
    return out


#: refits of :func:`_profile_high`
_PROFILE_ROUNDS = 4


def _profile_high(minimizer: lmfit.Minimizer, params: lmfit.Parameters, name: str, value: float,
                  guess: float, best: float, rise: float) -> float:
    """Where the profile of ``name`` -- the cost with ``name`` held and every other
    parameter refitted (lmfit, coarse then fine steps as in :func:`_staged`) -- rises
    ``rise`` (``chi2_1(0.95) s^2``) above ``best``, above ``value``: the high end of the
    95 % profile-likelihood interval (its low end is the bound).

    Found by the square root of the rise being about linear in the distance (exact for a
    quadratic profile), from ``guess`` (the linearised high end), a few refits. Not
    lmfit's conf_interval: it refits at each of its many trial points with MINPACK's
    tiny steps, which stall in the cost's stick-slip roughness ("rel_change=0.0"
    warnings; 171 s for one delay of a 2 s record with the slow simulation); here 2-4
    refits of ~0.1-0.3 s each on a 60 s record (measured, compiled simulation)."""
    bound = params[name].max
    x = min(guess, bound)
    for _ in range(_PROFILE_ROUNDS):
        d = _profile_cost(minimizer, params, name, x) - best
        if d <= 0.01 * rise:
            nxt = value + 4.0 * (x - value)
        else:
            nxt = value + (x - value) * min(math.sqrt(rise / d), 4.0)
        nxt = min(nxt, bound)
        done = abs(nxt - x) <= 0.05 * (x - value)
        x = nxt
        if done or x >= bound:
            break
    return float(x)


def _profile_cost(minimizer: lmfit.Minimizer, params: lmfit.Parameters, name: str,
                  x: float) -> float:
    """The least cost with ``name`` held at ``x``, the others refitted from ``params``."""
    trial = params.copy()
    trial[name].set(value=x, vary=False)
    coarse = minimizer.minimize(method="leastsq", params=trial, epsfcn=_EPSFCN_COARSE,
                                **_TOLERANCES)
    fine = minimizer.minimize(method="leastsq", params=coarse.params, epsfcn=_EPSFCN,
                              **_TOLERANCES)
    return float(min(coarse.chisqr, fine.chisqr))


#: a correlation beyond this names the partner of a parameter that is not identifiable
#: (measured: a pressed record that barely moves, 0.002 rad/s under 0.01 of noise, b and
#: D_env flat, correlates them -0.92 on the Jacobian of :func:`_refine` -- its steps are
#: the huge standard errors, a secant far into the nonlinearity -- the sum still all the
#: record determines; tests/identify/test_misfit.py, and the rule itself in
#: tests/identify/test_fit.py)
_CONFOUNDED = 0.9


def _fold_damping(estimates: dict[str, Estimate], covariance: tuple[list[str], np.ndarray] | None,
                  values: Mapping[str, float], segments: Sequence[Segment]
                  ) -> tuple[dict[str, Estimate], tuple[list[str], np.ndarray] | None]:
    """On a record pressed all along whose friction is not identifiable and whose damping
    is (:meth:`IdentResult.damping_sum`: both act on the one velocity, the profile of the
    friction flat along the damping), the damping reported is their sum ``b + D_env``, with
    the linearised interval of its standard error ``sqrt(var_b + var_D + 2 cov_bD)``, and the
    covariance the sum's (``T cov T^T``, ``T`` adding the friction's row to the damping's;
    the friction's row and column NaN), as the closed-loop fit reports it
    (dobhil/identify/closedloop.py, ``_fold_friction``): the overlay writes that sum as
    ``environment.damping`` (less the recorded friction), so its interval, correlations and
    the ``identified:`` section's box are the sum's, not those of D alone, which the fit
    traded against the friction (docs/identify.md section 5's force1.mcap: D 52.65 in
    [29.9, 60.4] for the sum 59.81 written). Anything else: unchanged."""
    b, d = estimates["viscous_friction"], estimates["damping"]
    if (b.identifiable or not d.identifiable or covariance is None or not segments
            or any(s.kind != "contact" for s in segments)):
        return estimates, covariance
    names, cov = covariance
    if "viscous_friction" not in names or "damping" not in names:
        return estimates, covariance
    i, j = names.index("viscous_friction"), names.index("damping")
    out = np.array(cov, float)
    var = fold_covariance(out, i, j)
    if not (math.isfinite(var) and var > 0.0):
        return estimates, covariance
    value, s = float(values["viscous_friction"] + values["damping"]), math.sqrt(var)
    z = float(scipy.stats.norm.ppf(0.5 + LEVEL / 2))
    folded = dict(estimates)
    folded["damping"] = Estimate("damping", value, s, max(value - z * s, 0.0), value + z * s, True, "",
                                 method="linearised")
    folded["viscous_friction"] = _not("viscous_friction", f"{b.why}; the damping reported is their sum")
    return folded, (names, out)


def fold_covariance(cov: np.ndarray, source: int, into: int) -> float:
    """Make ``cov`` (in place) the covariance with parameter ``into`` replaced by the sum
    of ``source`` and ``into`` -- ``T cov T^T``, ``T`` adding row ``source`` to row ``into``
    -- and ``source`` held (its row and column NaN); returns the sum's variance
    ``var_s + var_i + 2 cov_si`` (its diagonal entry, at least 0 there). Shared by both fits'
    folding of a pressed record's friction into its damping."""
    var = float(cov[source, source] + cov[into, into] + 2.0 * cov[source, into])
    cov[into, :] += cov[source, :]
    cov[:, into] += cov[:, source]
    cov[source, :] = cov[:, source] = math.nan
    cov[into, into] = max(var, 0.0)
    return var


def _partner(name: str, covariance: tuple[list[str], np.ndarray] | None) -> str:
    """``; only a combination with X is determined (correlation r)`` for the parameter
    most correlated with ``name``, when beyond :data:`_CONFOUNDED`; else empty."""
    if covariance is None:
        return ""
    names, cov = covariance
    i = names.index(name)
    sd = np.sqrt(np.diag(cov))
    r = cov[i] / (sd[i] * sd)
    r[i] = 0.0
    j = int(np.argmax(np.abs(r)))
    if not abs(r[j]) > _CONFOUNDED:
        return ""
    return (f"; only a combination with {names[j]} is determined (correlation {r[j]:+.3f}): "
            "the record does not separate them")


def _not(name: str, why: str) -> Estimate:
    nan = math.nan
    return Estimate(name=name, value=nan, stderr=nan, low=nan, high=nan, identifiable=False, why=why)


#: a residual RMS below this fraction of the measured velocity's RMS is rounding, not a
#: model error: no misfit however coloured. A drive reports float32 velocities and takes
#: float32 torques (~1e-7 relative), but the larger floor is the stick-slip's: on a
#: noise-free record every stick the simulation misses by a sub-step leaves a velocity
#: offset that decays only with J/b (measured: 4e-5 rad/s for a relative 1e-4 change of b,
#: 12 s long), so the cost is a needle at the truth and the fit ends 1e-5 .. 1.6e-5 rad/s
#: RMS off it = 1.5e-4 .. 2.5e-4 of the velocity RMS (free multisines with Coulomb
#: friction, 3-60 s; the values then within 0.5 % of the truth)
NOISE_FLOOR = 1e-3


def _whiteness(r: np.ndarray, velocity_rms: float = 0.0, lags: int = WHITENESS_LAGS) -> Residual:
    """RMS and the Ljung-Box test of the residual ``r``; a residual below
    :data:`NOISE_FLOOR` of ``velocity_rms`` (noise-free data) is never a misfit."""
    rms = float(np.sqrt(np.mean(r ** 2)))
    x = r - r.mean()
    c0 = float(x @ x)
    n = len(x)
    lags = min(lags, n - 1)
    if c0 == 0.0 or lags < 1 or rms <= NOISE_FLOOR * velocity_rms:
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

