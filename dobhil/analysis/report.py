"""The analysis of one design, continuous (the paper) and sampled (the runtime).

:func:`analyze` computes; :func:`as_json` and :func:`as_text` present. Plots are
in :mod:`dobhil.plotting` and take the same :class:`DomainAnalysis` objects.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field
from typing import Any

import control
import numpy as np

from dobhil.analysis.effective import EffectiveObserver, effective_observers
from dobhil.analysis.metrics import StepMetrics, step_metrics, step_responses
from dobhil.analysis.stability import (GainMap, answered, gain_map, is_position_drift, is_stable, phase_crossover,
                                       unresolved_pole)
from dobhil.analysis.transfer import LoopSystems
from dobhil.config.schema import Config
from dobhil.errors import AnalysisError, ConfigError
from dobhil.synthesis.controller import continuous_controller, sampled_controller
from dobhil.synthesis.params import Params, params_from_config


@dataclass(frozen=True)
class DomainAnalysis:
    """Everything computed for one domain (continuous or sampled)."""

    sampled: bool
    params: Params
    systems: LoopSystems
    gains: GainMap
    closed_loop_poles: np.ndarray
    stable: bool
    margins: dict[str, float | None]
    step: StepMetrics
    step_force: StepMetrics
    step_time: np.ndarray = field(repr=False)
    step_estimate: np.ndarray = field(repr=False)
    step_true: np.ndarray = field(repr=False)
    observers: dict[str, EffectiveObserver] = field(default_factory=dict)
    #: K_env = 0: the position, held by no spring, drifts at every C_f (a closed-loop pole at
    #: s = 0 / z = 1 no gain moves), so no C_f is stable and no gain margin is one; also a K_env
    #: so small that this pole is within the analysis' resolution of the boundary (1e-9 N m/rad)
    position_drifts: bool = False

    @property
    def sample_time(self) -> float | None:
        return self.systems.closed.dt


@dataclass(frozen=True)
class Analysis:
    config: Config
    continuous: DomainAnalysis
    discrete: DomainAnalysis


#: shortest step horizon that may be asked for (0 means automatic)
MIN_STEP_DURATION = 1e-6


def analyze(config: Config) -> Analysis:
    """Both domains of one design; a design the analysis cannot answer raises
    :class:`~dobhil.errors.AnalysisError` (one line), never a numpy error."""
    duration = config.analysis.step_duration
    if 0.0 < duration < MIN_STEP_DURATION:
        raise ConfigError(f"analysis.step_duration = {duration!r}: must be 0 (automatic) or at "
                          f"least {MIN_STEP_DURATION:g} s")
    params = params_from_config(config)
    return Analysis(config=config,
                    continuous=_answered(params, sampled=False, duration=duration),
                    discrete=_answered(params, sampled=True, duration=duration))


def _answered(params: Params, *, sampled: bool, duration: float) -> DomainAnalysis:
    return answered(lambda: analyze_domain(params, sampled=sampled, duration=duration),
                    what=f"the {'sampled' if sampled else 'continuous'} analysis", of="this design")


def analyze_domain(params: Params, *, sampled: bool, duration: float = 0.0) -> DomainAnalysis:
    systems = LoopSystems.build(params, sampled=sampled)
    if not all(np.all(np.isfinite(m)) for m in (systems.closed.a, systems.closed.b,
                                               systems.closed.c)):
        raise AnalysisError(f"the {'sampled' if sampled else 'continuous'} loop's matrices "
                            "overflow for this design (a value too large or too small)")
    a, b, c, _ = systems.open.siso("tau_per", "tau_int_hat")
    gains = gain_map(a, b, c, sampled=sampled)
    cl_poles = np.asarray(np.linalg.eigvals(systems.closed.a), dtype=complex)
    stable = bool(is_stable(cl_poles[None], sampled)[0])
    closed, force = systems.system("closed_loop"), systems.system("force")
    # K_env = 0, or so small that the position's pole is within the resolution of the boundary
    # (at C_f = 0 the loop is the open loop, whose integrator is there: no drift)
    edge = None if stable or float(params.value("force_gain")) <= 0 else unresolved_pole(cl_poles, sampled)
    drifts = bool(np.all(params.value("stiffness") == 0.0)) or (edge is not None and is_position_drift(edge, sampled))
    if stable:
        t, (y_hat, y_true) = step_responses([closed, force], duration)
    else:
        t, y_hat, y_true = np.zeros(0), np.zeros(0), np.zeros(0)
    return DomainAnalysis(
        sampled=sampled, params=params, systems=systems, gains=gains,
        closed_loop_poles=cl_poles, stable=stable,
        margins=margins(systems.system("open_loop"), float(params.value("force_gain")), gains, drifts),
        step=step_metrics(t, y_hat, stable=stable, final=_dc(closed) if stable else None),
        step_force=step_metrics(t, y_true, stable=stable, final=_dc(force) if stable else None),
        step_time=t, step_estimate=y_hat, step_true=y_true,
        observers=effective_observers(sampled_controller(params) if sampled
                                      else continuous_controller(params)),
        position_drifts=drifts)


def _dc(sys: control.StateSpace) -> float:
    return float(np.real(control.dcgain(sys)))


def margins(open_loop: control.StateSpace, force_gain: float, gains: GainMap,
            drifts: bool = False) -> dict[str, float | None]:
    """Gain and phase margins of the loop ``C_f L``: the stability margin (smallest
    ``|1 + C_f L|``) from python-control, at most 1 for a continuous loop, the phase margin
    from the exact crossovers (:func:`_phase_margin`), the gain margin from the exact gain
    map (:func:`_gain_margin`). ``drifts`` (K_env = 0): no gain margin -- the loop is
    unstable at every C_f, and the map's crossing gains (15.08 dB on paper/fig3's sampled
    loop) are the other poles', not a distance to instability."""
    if force_gain <= 0:
        return {k: None for k in ("gain_margin", "gain_margin_db", "phase_margin_deg",
                                  "phase_crossover_freq", "gain_crossover_freq",
                                  "stability_margin")}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        _, _, sm, _, _, _ = control.stability_margins(force_gain * open_loop)
    if not open_loop.isdtime(strict=True) and not np.any(open_loop.D):
        # python-control gives the smallest |1 + C_f L| at a stationary point of it, but a
        # strictly proper L tends to 0 at high frequency: |1 + C_f L(jw)| -> 1, so the
        # distance to -1 is at most 1 (the peak sensitivity at least 0 dB). It gave 1.26
        # for the demo's continuous loop and none (inf) where there is no stationary point.
        sm = min(float(sm), 1.0)
    gm, wpc = (math.nan, math.nan) if drifts else _gain_margin(open_loop, force_gain, gains)
    pm, wgc = _phase_margin(open_loop, force_gain)
    return {"gain_margin": _finite(gm),
            "gain_margin_db": _finite(20 * math.log10(gm)) if gm and gm > 0 and math.isfinite(gm) else None,
            "phase_margin_deg": _finite(pm), "phase_crossover_freq": _finite(wpc),
            "gain_crossover_freq": _finite(wgc), "stability_margin": _finite(sm)}


def _phase_margin(open_loop: control.StateSpace, force_gain: float) -> tuple[float, float]:
    """(phase margin [deg], gain crossover [rad/s]) of ``C_f L`` from every exact crossover
    of ``|C_f L| = 1`` (:func:`dobhil.analysis.stability.phase_crossover`: the roots of a
    polynomial in w, the margin nearest -180 deg, python-control's choice), the figure the
    stability gate uses. python-control 0.10.2's crossovers are not used: it evaluates ``L``
    at the roots of its polynomial, not on the unit circle, and reported 110 deg at 313
    rad/s for a sampled loop whose ``|L|`` is at least 5.67 everywhere (5.84 there), and
    76.7 deg where ``|L| = 0.107`` instead of the one true crossover's 97.6 deg
    (``tests/test_analysis.py``); it misses others (``tests/test_gate.py``). inf, nan: no
    crossover."""
    a, b, c = (np.asarray(m, float) for m in (open_loop.A, open_loop.B, open_loop.C))
    sampled = open_loop.isdtime(strict=True)
    pm, crossover = phase_crossover(a, b, c, force_gain, sampled=sampled)
    return float(pm), float(crossover) / float(open_loop.dt) if sampled else float(crossover)


def _gain_margin(open_loop: control.StateSpace, force_gain: float, gains: GainMap) -> tuple[float, float]:
    """(gain margin, phase crossover frequency) of ``C_f L`` from the exact crossing gains.

    ``L`` is real and negative at w exactly where ``1 + k L = 0`` has a root on the
    stability boundary at ``k = -1 / L``: the gain margins are the gain map's crossing gains
    over C_f (:func:`dobhil.analysis.stability.gain_map`, found on the polynomials, no
    frequency grid), and of them the one nearest 1 in log is taken, as python-control's
    ``stability_margins`` picks. Its crossing frequency is that of the closed-loop pole on
    the boundary at that gain. python-control's own phase crossings (0.10.2) are not used:
    they come from the roots of a crossing polynomial, and it reported crossings where L is
    not real -- w = 0 at the integrator (``gm = 1.5e-11`` on the demo's sampled loop with
    numpy 2.4.6), a phase that comes within 0.72 deg of -180 without reaching it (-22 dB on a
    loop stable for every gain in (0, 52.5)), ``L ~ 1e-15`` at 1.7e10 rad/s from a
    round-off leading coefficient (297 dB on paper/fig2b, stable for every gain) -- and
    missed the sampled loop's crossing at the Nyquist frequency (the demo's). inf: no
    crossing (``tests/test_analysis.py``)."""
    k = np.asarray(gains.crossings, float).ravel()
    k = k[np.isfinite(k) & (k > 0)]
    if not k.size:
        return math.inf, math.nan
    ratios = k / force_gain
    gm = float(ratios[int(np.argmin(np.abs(np.log(ratios))))])
    a, b, c = (np.asarray(m, float) for m in (open_loop.A, open_loop.B, open_loop.C))
    poles = np.linalg.eigvals(a - gm * force_gain * (b @ c))
    if open_loop.isdtime(strict=True):
        pole = poles[int(np.argmin(np.abs(np.abs(poles) - 1.0)))]
        return gm, abs(float(np.angle(pole))) / float(open_loop.dt)
    return gm, abs(float(poles[int(np.argmin(np.abs(poles.real)))].imag))


#: closed-loop transfer functions summarised in the report (all exist as python-control
#: objects through :class:`LoopSystems`)
SENSITIVITIES = ("disturbance", "disturbance_force", "identified_disturbance", "noise_q",
                 "noise_dq", "noise_q_force", "noise_dq_force")


def sensitivities(d: DomainAnalysis) -> dict[str, dict[str, float | None]]:
    """DC gain and peak gain (with its frequency) of the disturbance and noise responses."""
    out: dict[str, dict[str, float | None]] = {}
    for name in SENSITIVITIES:
        try:
            sys = d.systems.system(name)
        except KeyError:
            continue
        out[name] = _gain_summary(sys) if d.stable else {"dc_gain": None, "peak_gain": None,
                                                         "peak_frequency": None}
    return out


def _gain_summary(sys: control.StateSpace) -> dict[str, float | None]:
    top = np.pi / sys.dt if sys.dt else 1e6
    w = np.logspace(-1, np.log10(top * 0.999), 800)
    mag = np.abs(np.asarray(control.frequency_response(sys, w).complex).reshape(-1))
    i = int(np.argmax(mag))
    return {"dc_gain": _finite(_dc(sys)), "peak_gain": float(mag[i]), "peak_frequency": float(w[i])}


def _finite(x: Any) -> float | None:
    try:
        v = float(x)
    except (TypeError, ValueError):
        return None
    return v if math.isfinite(v) else None


def _pairs(values: np.ndarray) -> list[list[float]]:
    v = values[~np.isnan(values)]
    return [[float(z.real), float(z.imag)] for z in sorted(v, key=lambda z: (z.real, z.imag))]


def domain_json(d: DomainAnalysis, with_sensitivities: bool = True) -> dict[str, Any]:
    """The domain's report; ``with_sensitivities=False`` leaves out ``sensitivities``, the
    costly part (an 800-point frequency response each: most of an analysis' time), for
    :func:`as_text`, which shows none of them."""
    g = d.gains
    # the position drifts: no C_f is stable (as the text says); the map's own figures there are
    # decided by which side of the boundary rounding puts the position's pole (5.09 or 0 for the
    # estimated velocity's demo at K_env = 0, by the damping), as dobhil sweep's are not
    kmax = 0.0 if d.position_drifts else float(g.max_stable_gain)
    intervals = [] if d.position_drifts else g.intervals()
    out: dict[str, Any] = {
        "open_loop": {"poles": _pairs(g.poles), "zeros": _pairs(g.zeros),
                      "relative_degree": int(g.relative_degree),
                      "minimum_phase": bool(g.minimum_phase)},
        "closed_loop": {"force_gain": float(d.params.value("force_gain")),
                        "poles": _pairs(d.closed_loop_poles), "stable": d.stable,
                        "position_drifts": d.position_drifts},
        "max_stable_force_gain": None if math.isinf(kmax) else kmax,
        "stable_force_gain_intervals": [[lo, None if math.isinf(hi) else hi]
                                        for lo, hi in intervals],
        "margins": d.margins,
        "step": {k: v for k, v in d.step.as_dict().items()},
        "step_true_force": d.step_force.as_dict(),
        **({"sensitivities": sensitivities(d)} if with_sensitivities else {}),
        "observers": {k: v.as_dict() for k, v in d.observers.items()},
    }
    if d.sampled:
        s = d.params.structure
        out["sample_time"] = d.sample_time
        out["delay_samples"] = s.delay_samples
        out["input_delay"] = s.input_delay
        out["discretization"] = s.discretization.name.lower()
    return out


def as_json(a: Analysis, with_sensitivities: bool = True) -> dict[str, Any]:
    return {"continuous": domain_json(a.continuous, with_sensitivities),
            "discrete": domain_json(a.discrete, with_sensitivities)}


def _fmt(x: float | None, unit: str = "", digits: int = 4) -> str:
    return "-" if x is None else f"{x:.{digits}g}{unit}"


def _domain_text(name: str, d: dict[str, Any]) -> list[str]:
    ol, cl, st = d["open_loop"], d["closed_loop"], d["step"]
    kmax = d["max_stable_force_gain"]
    intervals = ", ".join(f"({lo:.4g}, {'inf' if hi is None else f'{hi:.4g}'})"
                          for lo, hi in d["stable_force_gain_intervals"]) or "none"
    m = d["margins"]
    if cl["position_drifts"]:   # no C_f is stable: the figures of the gain map would mislead
        pole = "z = 1" if "sample_time" in d else "s = 0"
        gains = (f"  max stable C_f: none: the position drifts at every C_f (a closed-loop pole at {pole}, within "
                 "the analysis' resolution, that no C_f moves: environment.stiffness is 0 or too small to hold it)")
    else:
        gains = (f"  max stable C_f: {'unbounded' if kmax is None else f'{kmax:.6g}'}; "
                 f"stable C_f intervals: {intervals}")
    return [
        f"{name}:",
        f"  open loop L: relative degree {ol['relative_degree']}, "
        f"{'minimum phase' if ol['minimum_phase'] else 'NON-minimum phase'}; "
        f"zeros {', '.join(_complex_str(z) for z in ol['zeros']) or 'none'}",
        f"  closed loop at C_f = {cl['force_gain']:.4g}: {'stable' if cl['stable'] else 'UNSTABLE'}",
        gains,
        f"  margins: gain {_fmt(m['gain_margin_db'], ' dB')}, phase {_fmt(m['phase_margin_deg'], ' deg')}",
        f"  step (tau_int^): overshoot {_fmt(st['overshoot_pct'], ' %')}, rise {_fmt(st['rise_time'], ' s')}, "
        f"settling {_fmt(st['settling_time'], ' s')}, steady-state error {_fmt(st['steady_state_error'])}",
        *(_observer_text(label, d["observers"][key])
          for key, label in (("dob", "DOb  (J_mn, b_mn)"), ("rtob", "RTOb (J_mi, b_mi)"))),
    ]


def _observer_text(label: str, o: dict[str, float | None]) -> str:
    bw, friction = o["bandwidth"], o["friction"]
    if friction is not None and o["inertia"] is not None and abs(friction) < 1e-9 * max(
            1.0, abs(o["inertia"]) * (bw or 1.0)):
        friction = 0.0   # rounding of a zero
    return (f"  {label} as it runs: inertia {_fmt(o['inertia'], ' kg m^2', 6)}, friction "
            f"{_fmt(friction, ' N m s/rad', 4)}, torque gain {_fmt(o['torque_gain'], '', 6)}, "
            f"bandwidth (-3 dB) {'above Nyquist' if bw is None else _fmt(bw, ' rad/s')}")


def _complex_str(z: list[float]) -> str:
    re, im = z
    return f"{re:.4g}" if abs(im) < 1e-9 else f"{re:.4g}{'+' if im >= 0 else '-'}{abs(im):.4g}j"


def as_text(a: Analysis) -> str:
    j = as_json(a, with_sensitivities=False)   # the text shows no sensitivity
    ts = j["discrete"]["sample_time"]
    lines = _domain_text("continuous (paper)", j["continuous"])
    dj = j["discrete"]
    delay = f"delay {dj['delay_samples']} samples" + (f" + {dj['input_delay']:g} s"
                                                      if dj["input_delay"] else "")
    lines += _domain_text(f"sampled (T = {ts:g} s, {delay}, {dj['discretization']} controller)", dj)
    return "\n".join(lines)
