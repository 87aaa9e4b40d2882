"""The analysis of coupled axes as plain values (:func:`coupled_json`) and as text
(:func:`coupled_text`); :mod:`dobhil.analysis.coupled` computes."""

from __future__ import annotations

import math
from typing import Any

from dobhil.analysis.coupled_analysis import AxisStep, CoupledAnalysis, CoupledDomain
from dobhil.analysis.coupled_check import LoopCheck

__all__ = ["coupled_json", "coupled_text"]


def _num(x: float) -> float | None:
    return float(x) if math.isfinite(x) else None


def _step_json(step: AxisStep) -> dict[str, Any]:
    others = {n: {"final_estimate": step.final_estimate[n], "final_force": step.final_force[n],
                  "peak_estimate": float(step.estimate[n][abs(step.estimate[n]).argmax()])
                  if step.estimate[n].size else None}
              for n in step.estimate if n != step.axis}
    return {"step": step.metrics.as_dict(), "step_true_force": step.metrics_force.as_dict(),
            "other_axes": others}


def _domain_json(d: CoupledDomain) -> dict[str, Any]:
    s = d.scales
    out: dict[str, Any] = {
        "force_gains": dict(zip(d.loop.names, map(float, d.loop.gains))),
        "closed_loop": {"poles": [[float(p.real), float(p.imag)] for p in
                                  sorted(d.poles, key=lambda z: (z.real, z.imag))],
                        "stable": d.stable,
                        ("spectral_radius" if d.loop.sampled else "spectral_abscissa"): d.spectral_radius},
        "max_stable_gain_scale": _num(s.max_scale),
        "max_stable_force_gains": {n: _num(g) for n, g in zip(d.loop.names, s.max_gains())},
        "stable_gain_scale_intervals": [[lo, _num(hi)] for lo, hi in s.intervals],
        "gain_scale_method": s.method,
        "steps": {st.axis: _step_json(st) for st in d.steps},
    }
    return out


def coupled_json(a: CoupledAnalysis, checks: dict[str, LoopCheck | str]) -> dict[str, Any]:
    """Plain values (JSON-ready; inf as None) of one group of coupled axes; ``checks`` by
    domain ("continuous", "discrete"): the python-control check, or why it was not run."""
    def check(c: LoopCheck | str) -> dict[str, Any]:
        if isinstance(c, str):
            return {"computed": False, "reason": c}
        return {"computed": True, "pole_error": c.pole_error, "step_error": c.step_error,
                "samples": c.samples, "agrees_1e-9": c.agrees()}
    disc = a.discrete.loop
    delays = {d.name: {"delay_samples": d.params.structure.delay_samples,
                       "input_delay": d.params.structure.input_delay} for d in a.designs}
    return {"axes": [d.name for d in a.designs],
            "couplings": [{"axes": [c.a, c.b], "stiffness": c.stiffness, "damping": c.damping}
                          for c in a.couplings],
            "continuous": {**_domain_json(a.continuous), "check": check(checks["continuous"])},
            "discrete": {**_domain_json(a.discrete), "sample_time": disc.dt, "delays": delays,
                         "check": check(checks["discrete"])}}


def _fmt(x: float | None, unit: str = "", digits: int = 4) -> str:
    return "-" if x is None else f"{x:.{digits}g}{unit}"


def _final(x: float) -> str:
    """A final value of a step of another axis' reference (0 up to rounding: shown as 0)."""
    return _fmt(0.0 if abs(x) < 1e-12 else x)


def _domain_text(title: str, d: dict[str, Any]) -> list[str]:
    cl = d["closed_loop"]
    radius = (f"spectral radius {cl['spectral_radius']:.6g}" if "spectral_radius" in cl
              else f"spectral abscissa {cl['spectral_abscissa']:.6g} 1/s")
    gains = ", ".join(f"{n} {g:.4g}" for n, g in d["force_gains"].items())
    scale = d["max_stable_gain_scale"]
    if scale is None:
        limit = "max stable gain scale: unbounded"
    elif scale == 0:
        limit = "not stable for small gains (max stable gain scale 0)"
    else:
        at = ", ".join(f"{n} {_fmt(g, '', 6)}" for n, g in d["max_stable_force_gains"].items())
        limit = f"max stable gain scale: {scale:.6g} (C_f: {at})"
    intervals = ", ".join(f"({lo:.4g}, {'inf' if hi is None else f'{hi:.4g}'})"
                          for lo, hi in d["stable_gain_scale_intervals"]) or "none"
    lines = [f"{title}:",
             f"  closed loop at C_f = {gains}: {'stable' if cl['stable'] else 'UNSTABLE'}, {radius}",
             f"  every C_f scaled by s: {limit}; stable s: {intervals}"]
    zero = [n for n, g in d["force_gains"].items() if g == 0]
    if zero:
        lines.append(f"  note: design.force_gain = 0 on {', '.join(zero)}: no force loop closes there (the "
                     "DOb cancels every external torque, the servo drifts: a pole on the stability boundary)")
    for axis, st in d["steps"].items():
        m = st["step"]
        cross = "; ".join(f"{n} tau_int^ final {_final(o['final_estimate'])}, peak {_fmt(o['peak_estimate'])}"
                          for n, o in st["other_axes"].items())
        lines.append(f"  step of {axis}'s tau_ref: overshoot {_fmt(m['overshoot_pct'], ' %')}, rise "
                     f"{_fmt(m['rise_time'], ' s')}, settling {_fmt(m['settling_time'], ' s')}, "
                     f"steady-state error {_fmt(m['steady_state_error'])}" + (f"; {cross}" if cross else ""))
    check = d["check"]
    if check["computed"]:
        lines.append(f"  independent check (python-control interconnect): poles agree to "
                     f"{check['pole_error']:.1e}, step responses to {check['step_error']:.1e}")
    else:
        lines.append(f"  independent check (python-control interconnect): not run ({check['reason']})")
    return lines


def coupled_text(j: dict[str, Any]) -> str:
    """The text of :func:`coupled_json`'s dict."""
    couplings = ", ".join(f"{c['axes'][0]}-{c['axes'][1]} K {c['stiffness']:g} N m/rad, "
                          f"D {c['damping']:g} N m s/rad" for c in j["couplings"])
    disc = j["discrete"]
    delays = ", ".join(f"{n} {v['delay_samples']}" + (f" + {v['input_delay']:g} s" if v["input_delay"] else "")
                       for n, v in disc["delays"].items())
    lines = [f"coupled axes {', '.join(j['axes'])} ({couplings}):"]
    lines += ["  " + line for line in _domain_text("continuous (paper)", j["continuous"])]
    lines += ["  " + line for line in _domain_text(
        f"sampled (T = {disc['sample_time']:g} s, delay samples: {delays})", disc)]
    return "\n".join(lines)
