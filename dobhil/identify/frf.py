"""Frequency responses measured from a record (``dobhil identify --frf``): the torque sent
to the velocity measured (free motion) and to the contact force (in contact), with their
coherence and a 95 % band, the fitted model's response beside them and the delay read from
the phase slope.

Two estimators:

- **at a multisine's lines** (:func:`multisine_frf`) when the record is one (the run's
  ``reference.kind: multisine`` on a grid of ``k / P``): the record is cut into whole periods
  ``P`` (the first dropped: its transient), each period's DFT taken at the excited lines, and
  ``H = mean(Y) / mean(U)``; its variance from the scatter of the periods (Pintelon &
  Schoukens, *System Identification: A Frequency Domain Approach*, 2nd ed., Wiley 2012,
  sec. 2.4: ``var H = |H|^2 (s_Y^2/|Y|^2 + s_U^2/|U|^2 - 2 Re(s_YU / (Y conj U))) / M``),
  the band with Student's t of ``M - 1`` degrees of freedom. No leakage: every line falls on
  a DFT bin of a whole period.
- **Welch / H1** (:func:`welch_frf`) otherwise: ``H1 = S_uy / S_uu`` from
  :func:`scipy.signal.csd` and :func:`scipy.signal.welch` (Hann windows, half overlapping),
  coherence ``|S_uy|^2 / (S_uu S_yy)``, and the normalised random error of the gain factor
  ``eps = sqrt(1 - g^2) / (|g| sqrt(2 n_d))`` (Bendat & Piersol, *Random Data*, 4th ed.,
  Wiley 2010, sec. 9.2.4; the phase's standard deviation in radians is the same ``eps``),
  ``n_d`` counted as the disjoint blocks (the overlapped ones are not independent: this
  errs wide).

No force sensor: the contact force is what the environment pushes with, ``K (q - q_c) +
D dq`` of the measured position and velocity with the fitted ``K`` and ``D``; its model
counterpart is the plant's ``C_int`` (:func:`dobhil.synthesis.models.plant_matrices`).

The model's response is that of the sampled plant the fit simulates: the ZOH matrices with
the delay's fraction (:func:`dobhil.synthesis.controller.discretize_delayed`) and its whole
samples as ``z^-d``. Coulomb friction is no linear term and is left out of it (a record
dominated by it shows as low coherence at the low lines, where the servo sticks).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Final

import numpy as np
import scipy.signal
import scipy.stats

from dobhil.identify.data import IdentData, Segment
from dobhil.identify.model import split_delay
from dobhil.synthesis.controller import discretize_delayed
from dobhil.synthesis.models import plant_matrices

__all__ = ["DelayEstimate", "Excitation", "FrequencyResponse", "model_response", "multisine_frf",
           "SegmentResponse", "Simulator", "phase_delay", "segment_response", "welch_frf"]

LEVEL: Final = 0.95
#: lines with at least this coherence enter the phase-slope delay
DELAY_COHERENCE: Final = 0.9
#: Welch: at least this many disjoint blocks (the band's n_d), at most this long a block
MIN_AVERAGES: Final = 8
MAX_BLOCK: Final = 4096
#: a frequency this close (relative) to a DFT bin of one period is on it
_ON_GRID: Final = 1e-6


@dataclass(frozen=True)
class Excitation:
    """A multisine's lines [Hz] and when it ran [s from the run's first cycle]."""

    frequencies: tuple[float, ...]
    start: float
    stop: float

    @property
    def period(self) -> float:
        """The multisine's period ``P`` [s] (the lines' spacing's inverse; one line: its own),
        NaN when the lines are not all on the grid ``k / P``."""
        f = np.asarray(self.frequencies)
        p = 1.0 / (f[1] - f[0]) if len(f) > 1 else 1.0 / f[0]
        k = f * p
        return p if np.all(np.abs(k - np.round(k)) <= _ON_GRID * np.maximum(k, 1.0)) else math.nan


@dataclass(frozen=True)
class FrequencyResponse:
    """One measured response: ``response[i]`` (complex) at ``frequency[i]`` [Hz], its
    coherence, and the 95 % band of the gain ``[low, high]`` and of the phase
    ``phase +- phase_band`` [rad]."""

    output: str                 # "velocity" [rad/s per N m] | "force" [N m per N m]
    method: str                 # "multisine" | "welch"
    frequency: np.ndarray
    response: np.ndarray
    coherence: np.ndarray
    low: np.ndarray
    high: np.ndarray
    phase_band: np.ndarray
    averages: int               # periods (multisine) or disjoint blocks (Welch)

    def within(self, exact: np.ndarray) -> np.ndarray:
        """Whether ``exact`` (complex, at these frequencies) lies in the band, gain and phase."""
        gain = (np.abs(exact) >= self.low) & (np.abs(exact) <= self.high)
        phase = np.abs(np.angle(exact / self.response)) <= self.phase_band
        return gain & phase


@dataclass(frozen=True)
class DelayEstimate:
    """The delay [s] from the slope of the residual phase, its 95 % interval and the lines used."""

    value: float
    low: float
    high: float
    lines: int


def _band(h: np.ndarray, sd: np.ndarray, quantile: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Gain band ``|H| -+ q sd`` (floored at 0) and phase band ``arcsin(q sd / |H|)``: the
    moduli and the angles of the disc of radius ``q sd`` about ``H``, the whole circle (pi)
    when the disc holds 0 -- as the gain band's low end is then 0 (Koopmans, *The Spectral
    Analysis of Time Series*, 1974, pp. 284-287: the phase interval ``arcsin``, all angles where
    its argument passes 1). ``q sd / |H|`` alone, cut at pi, was too narrow where the error is
    not small: at coherence 0.05 (a chirp's bins beyond its band) it gave +-109 deg, and the
    true phase of white noise through a unit gain at coherence 0.05 fell outside it in 19 % of
    the bins of 20 records, not 5 %."""
    mag = np.abs(h)
    rel = np.divide(sd, mag, out=np.full_like(mag, np.inf), where=mag > 0)
    radius = quantile * rel
    phase = np.where(radius < 1.0, np.arcsin(np.minimum(radius, 1.0)), math.pi)
    return np.maximum(mag - quantile * sd, 0.0), mag + quantile * sd, phase


def multisine_frf(u: np.ndarray, y: np.ndarray, period: float, lines: tuple[float, ...],
                  excitation_period: float, *, output: str = "velocity") -> FrequencyResponse | None:
    """The response at the multisine's ``lines`` from whole periods of ``u`` and ``y``
    (sampled at ``period``, the excitation running over all of them); None when fewer than
    two periods remain after the first or a period is no whole number of samples."""
    per = excitation_period / period
    n_p = int(round(per))
    if n_p < 2 or abs(per - n_p) > _ON_GRID * per:
        return None
    m = len(u) // n_p - 1
    if m < 2:
        return None
    bins = np.round(np.asarray(lines) * excitation_period).astype(int)
    keep = bins < n_p / 2
    blocks = slice(n_p, (m + 1) * n_p)
    uu = np.fft.rfft(np.asarray(u[blocks], float).reshape(m, n_p), axis=1)[:, bins[keep]]
    yy = np.fft.rfft(np.asarray(y[blocks], float).reshape(m, n_p), axis=1)[:, bins[keep]]
    mu, my = uu.mean(axis=0), yy.mean(axis=0)
    h = my / mu
    su = np.sum(np.abs(uu - mu) ** 2, axis=0) / (m - 1)
    sy = np.sum(np.abs(yy - my) ** 2, axis=0) / (m - 1)
    syu = np.sum((yy - my) * np.conj(uu - mu), axis=0) / (m - 1)
    var = np.abs(h) ** 2 * (sy / np.abs(my) ** 2 + su / np.abs(mu) ** 2
                            - 2.0 * np.real(syu / (my * np.conj(mu)))) / m
    sd = np.sqrt(np.maximum(var, 0.0))
    cross = np.abs(np.sum(np.conj(uu) * yy, axis=0)) ** 2
    coherence = cross / (np.sum(np.abs(uu) ** 2, axis=0) * np.sum(np.abs(yy) ** 2, axis=0))
    q = float(scipy.stats.t.ppf(0.5 + LEVEL / 2, m - 1))
    low, high, phase = _band(h, sd, q)
    return FrequencyResponse(output=output, method="multisine", frequency=np.asarray(lines)[keep], response=h,
                             coherence=coherence, low=low, high=high, phase_band=phase, averages=m)


def welch_frf(u: np.ndarray, y: np.ndarray, period: float, *, output: str = "velocity",
              block: int | None = None) -> FrequencyResponse:
    """H1 by Welch's method (see the module docstring), every bin above 0 Hz; ``block``
    samples a window (default: a power of two giving at least :data:`MIN_AVERAGES` disjoint
    blocks, at most :data:`MAX_BLOCK`)."""
    n = len(u)
    if block is None:
        block = int(min(MAX_BLOCK, 2 ** math.floor(math.log2(max(n // MIN_AVERAGES, 16)))))
    if n < 2 * block:
        raise ValueError(f"welch_frf: {n} samples, fewer than two blocks of {block}")
    fs = 1.0 / period
    kw = {"fs": fs, "nperseg": block, "noverlap": block // 2, "window": "hann", "detrend": "constant"}
    f, suy = scipy.signal.csd(u, y, **kw)
    _, suu = scipy.signal.welch(u, **kw)
    _, syy = scipy.signal.welch(y, **kw)
    sel = f > 0
    f, suy, suu, syy = f[sel], suy[sel], suu[sel], syy[sel]
    h = suy / suu
    coherence = np.clip(np.abs(suy) ** 2 / (suu * syy), 0.0, 1.0)
    nd = n // block
    eps = np.sqrt(1.0 - coherence) / (np.sqrt(coherence) * math.sqrt(2 * nd))
    low, high, phase = _band(h, eps * np.abs(h), float(scipy.stats.norm.ppf(0.5 + LEVEL / 2)))
    return FrequencyResponse(output=output, method="welch", frequency=f, response=h, coherence=coherence,
                             low=low, high=high, phase_band=phase, averages=nd)


def model_response(values: Mapping[str, float], frequency: np.ndarray, period: float, *,
                   contact: bool, output: str = "velocity", delay: bool = True) -> np.ndarray:
    """The sampled model's response at ``frequency`` [Hz]: torque to velocity, or (contact)
    to the force ``K e + D dq``; ``values`` named as :data:`dobhil.identify.fit.PARAMETERS`
    (no environment in free motion); ``delay=False``: without the delay (its non-delay phase)."""
    k = float(values.get("stiffness", 0.0)) if contact else 0.0
    d = float(values.get("damping", 0.0)) if contact else 0.0
    a, b, c_int = plant_matrices(float(values["inertia"]), float(values.get("viscous_friction", 0.0)), k, d)
    c = c_int[0] if output == "force" else np.array([0.0, 1.0])
    whole, fraction = split_delay(float(values.get("delay", 0.0)) if delay else 0.0, period)
    phi, g0, g1 = discretize_delayed(a, b, period, fraction)
    z = np.exp(2j * math.pi * np.asarray(frequency, float) * period)
    out = np.empty(len(z), complex)
    for i, zi in enumerate(z):
        x = np.linalg.solve(zi * np.eye(2) - phi, (g0 + g1 / zi)[:, 0])
        out[i] = (c @ x) * zi ** -whole
    return out


def phase_delay(frf: FrequencyResponse, undelayed: np.ndarray, *,
                min_coherence: float = DELAY_COHERENCE) -> DelayEstimate | None:
    """The delay from the phase slope: the measured phase less the model's without its delay
    (``undelayed``, :func:`model_response` with ``delay=False``) is ``-2 pi f tau`` for a
    model right but for its delay; fitted through the origin, weighted by each line's phase
    variance, over the lines of coherence >= ``min_coherence``. None with fewer than 3 lines."""
    use = (frf.coherence >= min_coherence) & np.isfinite(frf.phase_band) & (frf.phase_band > 0)
    if np.count_nonzero(use) < 3:
        return None
    f = frf.frequency[use]
    order = np.argsort(f)
    f = f[order]
    residual = np.unwrap(np.angle(frf.response[use] / undelayed[use])[order])
    # unwrapping starts at the lowest line: its phase must be near 0, not a whole turn off
    residual -= 2 * math.pi * np.round(residual[0] / (2 * math.pi))
    z = float(scipy.stats.norm.ppf(0.5 + LEVEL / 2))
    sd = (frf.phase_band[use] / z)[order] if frf.method == "welch" else (frf.phase_band[use] / _t(frf))[order]
    w = 1.0 / sd ** 2
    x = -2 * math.pi * f
    tau = float(np.sum(w * x * residual) / np.sum(w * x * x))
    # the slope's error from the scatter about the line (the bands' scale may be off: noise is
    # not the only misfit), never below the bands' own
    dof = len(f) - 1
    chi = float(np.sum(w * (residual - x * tau) ** 2)) / dof
    se = math.sqrt(max(chi, 1.0) / float(np.sum(w * x * x)))
    q = float(scipy.stats.t.ppf(0.5 + LEVEL / 2, dof))
    return DelayEstimate(value=tau, low=tau - q * se, high=tau + q * se, lines=len(f))


def _t(frf: FrequencyResponse) -> float:
    return float(scipy.stats.t.ppf(0.5 + LEVEL / 2, max(frf.averages - 1, 1)))


#: ``simulate(values)``: the true position and velocity over a segment of the model ``values``
#: driven by the record's torque (:func:`dobhil.identify.fit.simulate` with the segment's fitted
#: initial state)
Simulator = Callable[[Mapping[str, float]], tuple[np.ndarray, np.ndarray]]


@dataclass(frozen=True)
class SegmentResponse:
    """A segment's measured response; the fitted model's at the same frequencies -- ``model``
    estimated from its simulation by the same estimator (with Coulomb friction: its best linear
    approximation, as the measured one is), ``linear`` the sampled linear plant's exact response;
    and the delay its phase slope gives (None: too few coherent lines)."""

    kind: str
    measured: FrequencyResponse
    model: np.ndarray
    linear: np.ndarray
    delay: DelayEstimate | None


def segment_response(data: IdentData, segment: Segment, values: Mapping[str, float],
                     excitation: Excitation | None = None, *,
                     simulate: Simulator | None = None,
                     fitted: Mapping[str, float] | None = None) -> SegmentResponse:
    """The response of ``segment`` of ``data``: torque to velocity in free motion, torque to
    the contact force in contact (torque to velocity when the fit gave no K and D), at the
    multisine's lines when ``excitation`` is one and covers two whole periods after the first
    in the segment, by Welch otherwise; with the model of ``values`` (the fitted estimates).

    ``simulate`` given: the model's response is estimated from its simulation, by the same
    estimator over the same samples, and the phase-slope delay is read against the simulation
    without delay -- what a nonlinearity (Coulomb friction) does to the measured response it
    does to the simulated one alike, and only the delay is left in the phase. Without it: the
    linear sampled model's exact response (no Coulomb friction).

    ``fitted``: every parameter the fit ended at, under ``values`` in the model's responses --
    a pressed servo's viscous friction and D_env are not identifiable apart, yet their sum is
    what the record determined and what the torque-to-velocity response needs; ``values``
    alone choose the output (the force only with K and D identified)."""
    contact = segment.kind == "contact"
    force = contact and all(math.isfinite(values.get(k, math.nan)) for k in ("stiffness", "damping"))
    output = "force" if force else "velocity"
    start, stop = segment.start, segment.stop

    def signal(position: np.ndarray, velocity: np.ndarray) -> np.ndarray:
        if not force:
            return np.asarray(velocity, float)
        return values["stiffness"] * (position - position.mean()) + values["damping"] * velocity

    y = signal(data.position[start:stop], data.velocity[start:stop])
    u = data.torque[start:stop]
    window = slice(0, stop - start)
    lines: tuple[float, ...] = ()
    per = math.nan
    if excitation is not None and math.isfinite(excitation.period):
        # samples of the segment inside the excitation: sample i is run time (first_cycle + i) T
        lo = max(math.ceil(excitation.start / data.period - 1e-9) - data.first_cycle, start)
        hi = min(math.floor(excitation.stop / data.period + 1e-9) - data.first_cycle, stop)
        if hi > lo:
            window, lines, per = slice(lo - start, hi - start), excitation.frequencies, excitation.period

    def estimate(out: np.ndarray) -> FrequencyResponse:
        if lines:
            r = multisine_frf(u[window], out[window], data.period, lines, per, output=output)
            if r is not None:
                return r
        return welch_frf(u, out, data.period, output=output)

    measured = estimate(y)
    nan = np.full(len(measured.frequency), complex(math.nan))
    if not math.isfinite(values.get("inertia", math.nan)):   # no model to draw or to take the phase from
        return SegmentResponse(kind=segment.kind, measured=measured, model=nan, linear=nan, delay=None)
    plant = {**(fitted or {}), **values}
    linear = model_response(plant, measured.frequency, data.period, contact=contact, output=output)
    if simulate is None:
        undelayed = model_response(plant, measured.frequency, data.period, contact=contact, output=output,
                                   delay=False)
        return SegmentResponse(kind=segment.kind, measured=measured, model=linear, linear=linear,
                               delay=phase_delay(measured, undelayed))
    model = estimate(signal(*simulate(plant))).response
    undelayed = estimate(signal(*simulate({**plant, "delay": 0.0}))).response
    return SegmentResponse(kind=segment.kind, measured=measured, model=model, linear=linear,
                           delay=phase_delay(measured, undelayed))
