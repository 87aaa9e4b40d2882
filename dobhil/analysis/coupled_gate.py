"""The stability gate of axes joined by couplings: is the coupled closed loop a run is
about to close stable, and by how much may all its force gains grow or shrink together?

The loop judged is the one ``dobhil analyze`` shows for the group
(:func:`~dobhil.analysis.coupled.coupled_loop`: each axis' own controller matrices, its
protocol's command delay through :func:`~dobhil.analysis.coupled.axis_designs`, the coupled
plant sampled at ``loop.period``). Its verdict is the closed-loop poles at the designs'
gains; the margin is read off the stable scales of every force gain along the configured
gains (:func:`~dobhil.analysis.coupled.stable_scales`, ``C_f,i = s C_f,i^design``): how far
s may move from 1, in dB, before it leaves its stable interval -- the single-axis gate's
gain margin (:func:`dobhil.analysis.gate.gain_margin_db`) along that direction. A loop of
several inputs has no one phase margin: the coupled verdict gives none (the single-axis
gate's phase margin stays with each axis no coupling joins).

The verdict speaks the single-axis gate's language (``refuses``, ``refusal``,
``override_text``, ``warning``, ``note``, ``loop_text``, ``as_dict``), so
:func:`dobhil.cli.stability_gate.gate_line` and :func:`~dobhil.cli.stability_gate.gate_metadata`
print and record it as they do one axis' verdict.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from dobhil.analysis.coupled import AxisDesign, GainScales, coupled_loop, stable_scales
from dobhil.analysis.gate import NOT_MODELLED, GateStatus, VerdictLines, gain_margin_db, judged_or_not_computed
from dobhil.analysis.stability import is_stable
from dobhil.config.axes import Coupling
from dobhil.errors import AnalysisError

__all__ = ["CoupledVerdict", "assess_coupled"]


@dataclass(frozen=True, slots=True)
class CoupledVerdict(VerdictLines):
    """The gate's answer for a group of coupled axes at their designs' force gains.

    ``max_scale``: the largest s with every scale of (0, s) stable (inf: unbounded);
    ``gain_margin_db``: how far every force gain may be scaled together, up or down, before
    the loop leaves its stable interval (None when unstable or not judged)."""

    status: GateStatus
    axes: tuple[str, ...]
    force_gains: tuple[float, ...]
    period: float
    delays: tuple[str, ...] = ()
    max_scale: float | None = None
    stable_intervals: tuple[tuple[float, float], ...] = ()
    gain_margin_db: float | None = None
    min_gain_margin_db: float = 0.0
    reason: str = ""

    def _what(self) -> str:
        gains = ", ".join(f"{n} {g:g}" for n, g in zip(self.axes, self.force_gains))
        return (f"coupled sampled loop of axes {', '.join(self.axes)} (T = {self.period:g} s, delay "
                f"{'; '.join(self.delays)}) at C_f = {gains}")

    def loop_text(self) -> str:
        """``the coupled sampled loop of axes a, b (..) at C_f = a 2, b 2 is UNSTABLE; ...``."""
        verdict = {GateStatus.STABLE: "stable", GateStatus.UNSTABLE: "UNSTABLE"}.get(self.status, "not judged")
        k = self.max_scale
        if k is None:
            tail = f"not judged ({self.reason})"
        else:
            tail = "max stable scale of every C_f: " + ("unbounded" if math.isinf(k) else f"{k:.6g}")
            if len(self.stable_intervals) > 1 or (self.stable_intervals and self.stable_intervals[0][0] > 0):
                tail += "; stable scales: " + ", ".join(
                    f"({lo:.4g}, {'inf' if math.isinf(hi) else f'{hi:.4g}'})" for lo, hi in self.stable_intervals)
        return f"the {self._what()} is {verdict}; {tail}"

    def summary(self) -> str:
        note = self.note()
        if note is not None:
            return note
        if not self.stable:
            return self.loop_text()
        gm = self.gain_margin_db
        text = "-" if gm is None else ("unbounded" if math.isinf(gm) else f"{gm:.3g} dB")
        return f"{self.loop_text()}; gain margin (every C_f scaled together) {text}"

    def advice(self) -> str:
        k = self.max_scale or 0.0
        lower = (f"scale the axes' design.force_gain below {k:.6g} times the configured ones" if k > 0 else
                 "no common scale of the force gains is stable: change the gains' ratio, the observers' "
                 "bandwidths or the coupling")
        return f"{lower} (dobhil analyze CONFIG shows the coupled loop), or --allow-unstable for an experiment"

    def low_margins(self) -> list[str]:
        gm = self.gain_margin_db
        if not self.stable or gm is None or gm >= self.min_gain_margin_db:
            return []
        return [f"gain margin {gm:.3g} dB (every C_f scaled together) < analysis.min_gain_margin = "
                f"{self.min_gain_margin_db:g} dB"]

    def as_dict(self) -> dict[str, Any]:
        def num(x: float | None) -> float | None:
            return None if x is None or not math.isfinite(x) else float(x)
        return {"status": self.status.name.lower(), "coupled_axes": list(self.axes),
                "force_gains": dict(zip(self.axes, self.force_gains)),
                "max_stable_scale": num(self.max_scale),
                "stable_scale_intervals": [[lo, num(hi)] for lo, hi in self.stable_intervals],
                "gain_margin_db": num(self.gain_margin_db), "phase_margin_deg": None,
                "min_gain_margin_db": self.min_gain_margin_db, "period": self.period,
                "delays": list(self.delays), "not_modelled": NOT_MODELLED, "reason": self.reason}


def assess_coupled(designs: Sequence[AxisDesign], couplings: Sequence[Coupling]) -> CoupledVerdict:
    """The gate's verdict on the coupled axes ``designs`` (each on its drive:
    :func:`~dobhil.analysis.coupled.axis_designs`) joined by ``couplings``."""
    base = CoupledVerdict(status=GateStatus.NOT_APPLICABLE, axes=tuple(d.name for d in designs),
                          force_gains=tuple(float(d.config.design.force_gain) for d in designs),
                          period=float(designs[0].config.loop.period), delays=tuple(_delay(d) for d in designs),
                          min_gain_margin_db=max(float(d.config.analysis.min_gain_margin) for d in designs))
    torque = [d.name for d in designs if d.config.loop.mode == "torque"]
    if torque:
        return replace(base, reason=f"axis {', '.join(torque)}: loop.mode = torque (no force loop closes)")
    if not any(base.force_gains):
        return replace(base, reason="design.force_gain = 0 on every coupled axis (no force feedback closes a loop)")
    return judged_or_not_computed(base, lambda: _judged(base, designs, couplings))


def _delay(design: AxisDesign) -> str:
    s = design.params.structure
    fraction = f" + {s.input_delay:g} s" if s.input_delay else ""
    return f"{design.name} {s.delay_samples} sample{'' if s.delay_samples == 1 else 's'}{fraction}"


def _judged(base: CoupledVerdict, designs: Sequence[AxisDesign], couplings: Sequence[Coupling]) -> CoupledVerdict:
    lp = coupled_loop(designs, couplings, sampled=True)
    if not np.all(np.isfinite(lp.a)):
        raise AnalysisError("the loop's matrices overflow for this design (a value too large or too small)")
    scales: GainScales = stable_scales(lp)
    stable = bool(is_stable(lp.poles()[None], True)[0])   # the single-axis gate's test
    verdict = replace(base, status=GateStatus.STABLE if stable else GateStatus.UNSTABLE,
                      max_scale=float(scales.max_scale), stable_intervals=tuple(scales.intervals))
    if not stable:
        return verdict
    return replace(verdict, gain_margin_db=gain_margin_db(1.0, verdict.stable_intervals))
