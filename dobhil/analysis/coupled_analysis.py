"""The analysis of coupled axes: both domains' loops, verdicts, gain scales and step responses.

The loop and its stable gain scales come from :mod:`dobhil.analysis.coupled`; the steps are
the single-axis analysis' (:func:`dobhil.analysis.metrics.step_responses`) on the coupled loop.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import control
import numpy as np

from dobhil.analysis.coupled import AxisDesign, CoupledLoop, GainScales, coupled_loop, stable_scales
from dobhil.analysis.metrics import StepMetrics, step_metrics, step_responses
from dobhil.analysis.stability import is_stable
from dobhil.config.axes import Coupling
from dobhil.errors import AnalysisError, DobhilError, exception_line
from dobhil.synthesis.params import Array

__all__ = ["AxisStep", "CoupledAnalysis", "CoupledDomain", "analyze_coupled", "analyze_domain", "axis_steps"]


@dataclass(frozen=True)
class AxisStep:
    """The coupled loop's answer to a unit step of one axis' force reference: every axis'
    estimate ``tau_int^`` and interaction torque ``tau_int`` (the stepped one's and the
    others', which the couplings move), their exact final values, and the stepped axis'
    metrics."""

    axis: str
    t: Array = field(repr=False)
    estimate: dict[str, Array] = field(repr=False)      # axis -> tau_int^
    force: dict[str, Array] = field(repr=False)         # axis -> tau_int
    final_estimate: dict[str, float]
    final_force: dict[str, float]
    metrics: StepMetrics
    metrics_force: StepMetrics


def _system(lp: CoupledLoop, axis: str, out_axis: str, output: str) -> control.StateSpace:
    i, o = lp.input_index(axis, "tau_ref"), lp.output_index(out_axis, output)
    return control.ss(lp.a, lp.b[:, i:i + 1], lp.c[o:o + 1], lp.d[o:o + 1, i:i + 1], lp.dt or 0)


def _dc(lp: CoupledLoop, axis: str, out_axis: str, output: str) -> float:
    i, o = lp.input_index(axis, "tau_ref"), lp.output_index(out_axis, output)
    eye = np.eye(lp.order)
    x = np.linalg.solve(eye - lp.a if lp.sampled else -lp.a, lp.b[:, i])
    return float(lp.c[o] @ x + lp.d[o, i])


def axis_steps(lp: CoupledLoop, duration: float = 0.0) -> tuple[AxisStep, ...]:
    """A unit step of each axis' ``tau_ref`` in turn (the loop must be stable), on the time
    grid of :func:`dobhil.analysis.metrics.step_grid` of the coupled loop."""
    out = []
    for axis in lp.names:
        others = [n for n in lp.names if n != axis]
        order = [(axis, "tau_int_hat"), (axis, "tau_int"),
                 *((n, k) for n in others for k in ("tau_int_hat", "tau_int"))]
        t, ys = step_responses([_system(lp, axis, n, k) for n, k in order], duration)
        values = dict(zip(order, ys))
        finals = {key: _dc(lp, axis, *key) for key in order}
        out.append(AxisStep(
            axis=axis, t=t,
            estimate={n: values[(n, "tau_int_hat")] for n in lp.names},
            force={n: values[(n, "tau_int")] for n in lp.names},
            final_estimate={n: finals[(n, "tau_int_hat")] for n in lp.names},
            final_force={n: finals[(n, "tau_int")] for n in lp.names},
            metrics=step_metrics(t, values[(axis, "tau_int_hat")], final=finals[(axis, "tau_int_hat")]),
            metrics_force=step_metrics(t, values[(axis, "tau_int")], final=finals[(axis, "tau_int")])))
    return tuple(out)


@dataclass(frozen=True)
class CoupledDomain:
    """The coupled loop in one domain (continuous: the paper's, no delay; sampled: what
    runs): its poles, verdict, stable gain scales and step responses (none when unstable)."""

    loop: CoupledLoop
    poles: np.ndarray
    stable: bool
    scales: GainScales
    steps: tuple[AxisStep, ...]

    @property
    def spectral_radius(self) -> float:
        """``max |z|`` sampled; continuous: the spectral abscissa ``max Re(s)``."""
        return float(np.max(np.abs(self.poles)) if self.loop.sampled else np.max(self.poles.real))


@dataclass(frozen=True)
class CoupledAnalysis:
    designs: tuple[AxisDesign, ...]
    couplings: tuple[Coupling, ...]
    continuous: CoupledDomain
    discrete: CoupledDomain


def analyze_domain(designs: Sequence[AxisDesign], couplings: Sequence[Coupling], *, sampled: bool,
                   duration: float = 0.0) -> CoupledDomain:
    lp = coupled_loop(designs, couplings, sampled=sampled)
    if not np.all(np.isfinite(lp.a)):
        raise AnalysisError(f"the {'sampled' if sampled else 'continuous'} coupled loop's matrices "
                            "overflow for this design (a value too large or too small)")
    poles = lp.poles()
    stable = bool(is_stable(poles[None], sampled)[0])
    return CoupledDomain(loop=lp, poles=poles, stable=stable, scales=stable_scales(lp),
                         steps=axis_steps(lp, duration) if stable else ())


def analyze_coupled(designs: Sequence[AxisDesign], couplings: Sequence[Coupling]) -> CoupledAnalysis:
    """Both domains of coupled axes; a design the analysis cannot answer raises
    :class:`~dobhil.errors.AnalysisError` (one line), never a numpy error."""
    duration = max(d.config.analysis.step_duration for d in designs)
    out = {}
    for sampled in (False, True):
        name = "sampled" if sampled else "continuous"
        try:
            with np.errstate(all="ignore"):
                out[name] = analyze_domain(designs, couplings, sampled=sampled, duration=duration)
        except DobhilError:
            raise
        except (np.linalg.LinAlgError, ValueError, ZeroDivisionError, OverflowError) as exc:
            raise AnalysisError(f"the {name} analysis of the coupled axes cannot answer this design "
                                f"({exception_line(exc, named=False)[:120]})") from None
    return CoupledAnalysis(designs=tuple(designs), couplings=tuple(couplings),
                           continuous=out["continuous"], discrete=out["sampled"])
