"""What ``dobhil tune`` says: text, JSON, the tuned config (YAML), and the one line of a
design that cannot meet a constraint. Pure functions of the results."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import yaml

from dobhil.analysis.stability import STABILITY_TOL
from dobhil.tune.evaluate import Metrics
from dobhil.tune.optimise import Objective, TuneResult, Worst
from dobhil.tune.problem import DECISION_KEYS, Margins, Range, RobustSet, Uncertainty

#: units of the decision keys and of the constraints' values, for the text
UNITS = {"design.dob_bandwidth": "rad/s", "design.rtob_bandwidth": "rad/s",
         "design.identified_inertia": "kg m^2", "design.force_gain": ""}
CONSTRAINT_TEXT = {"stability": ("stability", "largest |pole|", "", "<"),
                   "gain_margin": ("gain margin", "", " dB", ">="),
                   "phase_margin": ("phase margin", "", " deg", ">="),
                   "peak_sensitivity": ("peak sensitivity", "", " dB", "<="),
                   "overshoot": ("force step overshoot", "", " %", "<="),
                   "noise": ("quantisation noise of tau_int^", "RMS", " N m", "<=")}


@dataclass(frozen=True)
class Baseline:
    """The config's own design on the same grid, for comparison."""

    design: Mapping[str, float]
    worst_objective: float
    worst_at: Mapping[str, float]
    stable_worst_objective: float        # over the points where it is stable (NaN: none)
    stable_worst_at: Mapping[str, float]
    unstable: int
    worst_radius: float
    radius_at: Mapping[str, float]
    unstable_points: tuple[Mapping[str, float], ...]   # a few of them, for the text
    constraints: tuple[Worst, ...]
    stable: np.ndarray = field(repr=False)                # per grid point


def baseline(design: Mapping[str, float], m: Metrics, grid: RobustSet, objective: Objective,
             worsts: tuple[Worst, ...]) -> Baseline:
    worst, where = objective.worst(m)
    unstable = np.nonzero(~m.stable[0])[0]
    values = m.rise_time[0] if objective.name == "rise_time" else m.bandwidth[0]
    pick = np.argmax if objective.name == "rise_time" else np.argmin
    inside = np.nonzero(m.stable[0])[0]
    j = int(inside[pick(values[inside])]) if inside.size else -1
    i = int(np.argmax(m.radius[0]))
    return Baseline(design=dict(design), worst_objective=float(worst[0]),
                    worst_at=grid.point(int(where[0])),
                    stable_worst_objective=float(values[j]) if inside.size else math.nan,
                    stable_worst_at=grid.point(j) if inside.size else {},
                    unstable=int(unstable.size),
                    worst_radius=float(m.radius[0][i]), radius_at=grid.point(i),
                    unstable_points=tuple(grid.point(int(j)) for j in unstable[:3]),
                    constraints=worsts, stable=m.stable[0])


def _at(point: Mapping[str, float]) -> str:
    return ", ".join(f"{k}={v:.4g}" for k, v in point.items()) or "the config's values"


def objective_text(name: str, value: float) -> str:
    """A worst-case objective in its unit (ms of rise time, rad/s of bandwidth)."""
    if name == "rise_time":
        return "inf (unstable or not within the horizon)" if not math.isfinite(value) else f"{value * 1e3:.4g} ms"
    return f"{value:.4g} rad/s"


def _value(w: Worst) -> str:
    unit = CONSTRAINT_TEXT[w.name][2]
    if w.name == "stability" and f"{w.value:.4g}" == "1":   # not "1 (need < 1)": say how near
        return f"{w.value:.15g}"
    return ("unbounded" if math.isinf(w.value) else "none (unstable there)" if math.isnan(w.value)
            else f"{w.value:.4g}{unit}")


def _constraint_line(w: Worst) -> str:
    label, what, unit, op = CONSTRAINT_TEXT[w.name]
    value = _value(w)
    if math.isinf(w.limit):   # reported, not a constraint (the noise without --margin noise=X)
        return f"  {label}: {(what + ' ') if what else ''}{value} at {_at(w.point)} (not bounded: --margin noise=X)"
    flags = ("ok" if w.ok else "NOT MET") + (", active" if w.active else "")
    return f"  {label}: {(what + ' ') if what else ''}{value} (need {op} {w.limit:g}{unit}) at {_at(w.point)}: {flags}"


def set_text(ranges: Sequence[Range], uncertainties: Sequence[Uncertainty], grid: int) -> str:
    parts = [f"{r.key} {r.lo:g}..{r.hi:g} ({'log' if r.log else 'linear'}, {grid} values)" for r in ranges]
    parts += [u.describe() for u in uncertainties]
    return "; ".join(parts)


def as_text(result: TuneResult, base: Baseline, set_description: str) -> str:
    obj = "rise time (10-90 %)" if result.objective == "rise_time" else "bandwidth (-3 dB)"
    lines = [f"robust set: {set_description} = {result.grid_points} points; sampled loop with its delay",
             "tuned design:"]
    lines += [f"  {k} = {result.design[k]:.6g} {UNITS[k]}".rstrip() for k in DECISION_KEYS]
    lines.append(f"worst-case force {obj}: {objective_text(result.objective, result.worst_objective)} "
                 f"at {_at(result.worst_at)}")
    lines.append("constraints (worst over the grid):")
    lines += [_constraint_line(w) for w in result.constraints]
    lines.append("the config's design (" + ", ".join(f"{k.split('.')[1]} {v:.4g}" for k, v in base.design.items())
                 + f"): worst-case force {obj} {objective_text(result.objective, base.worst_objective)} at "
                 f"{_at(base.worst_at)}; " + _unstable_text(base, result.objective))
    lines.append(f"search: {result.rounds} round(s), {result.generations} generations, "
                 f"{result.set_points} points in the optimiser's set")
    return "\n".join(lines)


def _unstable_text(base: Baseline, objective: str) -> str:
    failed = [w for w in base.constraints if not w.ok and w.name != "stability"]
    fails = ("; fails " + ", ".join(f"{CONSTRAINT_TEXT[w.name][0]} ({w.value:.4g}{CONSTRAINT_TEXT[w.name][2]} "
                                    f"at {_at(w.point)})" for w in failed)) if failed else "; meets every margin"
    if not base.unstable:
        return f"stable at every point (largest |pole| {base.worst_radius:.4g}){fails}"
    inside = ("" if not base.stable_worst_at else
              f"; where stable, its worst is {objective_text(objective, base.stable_worst_objective)} at "
              f"{_at(base.stable_worst_at)}")
    return (f"UNSTABLE at {base.unstable} of {base.stable.size} point(s) (largest |pole| {base.worst_radius:.4g} at "
            f"{_at(base.radius_at)}){inside}{fails} (where stable)")


def _finite(x: float) -> float | None:
    return x if math.isfinite(x) else None


def _worst_json(w: Worst) -> dict[str, Any]:
    return {"value": _finite(w.value), "limit": _finite(w.limit), "at": dict(w.point), "ok": w.ok, "active": w.active}


def as_json(result: TuneResult, base: Baseline, margins: Margins) -> dict[str, Any]:
    return {
        "design": dict(result.design), "objective": result.objective,
        "worst_objective": _finite(result.worst_objective), "worst_at": dict(result.worst_at),
        "constraints": {w.name: _worst_json(w) for w in result.constraints},
        "feasible": result.feasible, "grid_points": result.grid_points,
        "margins": {"gm_db": margins.gm_db, "pm_deg": margins.pm_deg, "ms_db": margins.ms_db,
                    "overshoot_pct": margins.overshoot_pct, "noise": margins.noise},
        "search": {"rounds": result.rounds, "generations": result.generations,
                   "set_points": result.set_points},
        "config_design": {"design": dict(base.design), "worst_objective": _finite(base.worst_objective),
                          "worst_at": dict(base.worst_at),
                          "worst_objective_where_stable": _finite(base.stable_worst_objective),
                          "worst_where_stable_at": dict(base.stable_worst_at), "unstable_points": base.unstable,
                          "largest_pole_radius": base.worst_radius, "largest_at": dict(base.radius_at),
                          "constraints": {w.name: _worst_json(w) for w in base.constraints}},
    }


def infeasible_line(result: TuneResult, step_duration: float) -> str:
    """The first constraint the chosen design (the least violating one found) does not meet,
    or, when it meets them all, that its force step does not rise within ``step_duration``
    seconds (the simulated horizon) somewhere."""
    w = next((w for w in result.constraints if not w.ok), None)
    if w is None:
        return (f"no design within the bounds makes the force step reach 90 % of its final value within "
                f"{step_duration:g} s (analysis.step_duration) at every point: the best found does not at "
                f"{_at(result.worst_at)} (widen --bound, or a longer analysis.step_duration)")
    if w.name == "stability" and abs(w.value - 1.0) <= STABILITY_TOL:
        # a pole on the unit circle within round-off: no bound or margin moves it (the position,
        # held by too soft an environment, drifts as at K_env = 0)
        return (f"no design within the bounds is shown stable at {_at(w.point)}: its largest |pole| {_value(w)} "
                f"is within the analysis' resolution of the unit circle ({STABILITY_TOL:g}), where no design "
                f"can be judged (an environment this soft holds the position about as little as K_env = 0); "
                f"leave such points out of the set")
    label, what, unit, op = CONSTRAINT_TEXT[w.name]
    return (f"no design within the bounds meets {label} {op} {w.limit:g}{unit} at every point: the best "
            f"found has {_value(w)} at {_at(w.point)} (widen --bound or relax --margin)")


def tuned_yaml(source: Mapping[str, Any], result: TuneResult, command: str) -> str:
    """``source`` (the input's mapping, overrides applied) with the design keys replaced,
    each followed by a comment of the worst-case margins the design holds."""
    nested = {section: dict(values) if isinstance(values, Mapping) else values
              for section, values in source.items()}
    design = nested.setdefault("design", {})
    for key in DECISION_KEYS:
        design[key.split(".")[1]] = float(result.design[key])   # as checked: no rounding
    text = yaml.safe_dump(nested, sort_keys=False)
    summary = "; ".join(f"{CONSTRAINT_TEXT[w.name][0]} {w.value:.3g}{CONSTRAINT_TEXT[w.name][2]}"
                        for w in result.constraints)
    out = [f"# tuned by: {command}", f"# worst case over {result.grid_points} points: {summary}"]
    section = ""
    for line in text.splitlines():
        name = line.strip().split(":")[0]
        if not line.startswith(" "):
            section = name
        elif f"{section}.{name}" in DECISION_KEYS:
            line += "  # tuned"
        out.append(line)
    return "\n".join(out) + "\n"
