"""The stability gate: is the force loop a run is about to close stable, and by how much?

Before a drive is enabled, the loop that will run -- sampled at ``loop.period``, with the
command delay the drive's protocol imposes (:func:`~dobhil.drives.timing.effective_config`),
at the configured environment -- is judged by the functions ``dobhil analyze`` uses: the
loop's matrices from :func:`~dobhil.synthesis.loop.loop`, the verdict from the closed-loop
poles (:func:`~dobhil.analysis.stability.is_stable`), the largest stable force gain and
every stable interval from the exact gain map (:func:`~dobhil.analysis.stability.gain_map`).
The gain margin is read off that map (how far C_f may move, in dB, before it leaves its
stable interval) and the phase margin from every gain crossover
(:func:`~dobhil.analysis.stability.phase_margin`). No python-control: the gate runs at every
start and costs one synthesis and a few eigenvalue problems.

What the linear analysis leaves out is named in :attr:`Assumptions.not_modelled`: the
codec's quantisation (noise on the estimates, ``dobhil analyze`` reports it), torque
saturation, Coulomb friction and the moment of contact. A design it cannot speak about --
no force loop closes (``loop.mode: torque``, ``C_f = 0``) or no environment holds the
position -- gets :attr:`GateStatus.NOT_APPLICABLE` with the reason, never a refusal.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, replace
from enum import IntEnum
from collections.abc import Callable
from typing import Any, TypeVar

import numpy as np

from dobhil.analysis.stability import gain_map, is_position_drift, is_stable, phase_margin, unresolved_pole
from dobhil.config.schema import Config
from dobhil.drives.profile import DriveProfile
from dobhil.drives.timing import effective_config
from dobhil.errors import AnalysisError, DobhilError, exception_line
from dobhil.synthesis.loop import loop
from dobhil.synthesis.params import params_from_config

#: a verdict dataclass (GateVerdict, or another gate's)
V = TypeVar("V")

#: what the linear loop of the analysis does not contain (said with every verdict)
NOT_MODELLED = "quantisation, torque saturation, Coulomb friction, loss of contact"


class GateStatus(IntEnum):
    """The gate's verdict on a design."""

    STABLE = 0
    UNSTABLE = 1
    NOT_APPLICABLE = 2   # no force loop for the analysis to judge
    NOT_COMPUTED = 3     # the analysis cannot answer this design (the reason says why)


@dataclass(frozen=True, slots=True)
class Assumptions:
    """The loop the verdict is about."""

    sampled: bool
    period: float
    delay_samples: int
    input_delay: float
    delay_source: str          # "the config" or "drive profile 'NAME'"
    discretization: str
    stiffness: float
    damping: float
    not_modelled: str = NOT_MODELLED

    def text(self) -> str:
        """``sampled loop (T = 0.001 s, delay 1 sample: drive profile 'x'; K_env .., D_env ..)``."""
        env = f"K_env {self.stiffness:g} N m/rad, D_env {self.damping:g} N m s/rad"
        if not self.sampled:
            return f"continuous loop ({env})"
        fraction = f" + {self.input_delay:g} s" if self.input_delay else ""
        plural = "" if self.delay_samples == 1 else "s"
        return (f"sampled loop (T = {self.period:g} s, delay {self.delay_samples} sample{plural}{fraction}: "
                f"{self.delay_source}; {env})")


class VerdictLines:
    """The lines every gate verdict speaks, from its ``status``, ``reason``, ``loop_text()``,
    ``advice()`` and ``low_margins()``: one axis' (:class:`GateVerdict`) and a coupled
    group's (:class:`dobhil.analysis.coupled_gate.CoupledVerdict`) alike."""

    __slots__ = ()
    status: GateStatus
    reason: str

    @property
    def stable(self) -> bool:
        return self.status is GateStatus.STABLE

    @property
    def refuses(self) -> bool:
        """Whether a run of this design is refused (unless the gate is overridden)."""
        return self.status is GateStatus.UNSTABLE

    def loop_text(self) -> str:
        raise NotImplementedError

    def advice(self) -> str:
        raise NotImplementedError

    def low_margins(self) -> list[str]:
        raise NotImplementedError

    def refusal(self) -> str:
        return f"refused: {self.loop_text()}; {self.advice()}"

    def override_text(self) -> str:
        return f"stability gate overridden (--allow-unstable): {self.loop_text()}; the run goes on"

    def warning(self) -> str | None:
        """One line when a margin is below its threshold (None: margins fine, or not stable)."""
        low = self.low_margins()
        if not low:
            return None
        return f"low stability margin: {', '.join(low)}; {self.loop_text()}; the run goes on"

    def note(self) -> str | None:
        """One line when the gate could not judge the design (None: it did)."""
        if self.status is GateStatus.NOT_APPLICABLE:
            return f"stability gate not applied: {self.reason}"
        if self.status is GateStatus.NOT_COMPUTED:
            return f"stability gate not computed: {self.reason}"
        return None


@dataclass(frozen=True, slots=True)
class GateVerdict(VerdictLines):
    """The gate's answer for one design at its force gain C_f.

    ``max_stable_gain``: the largest k with every gain of (0, k) stable (inf: unbounded;
    0: not stable for small gains); ``gain_margin_db``: how far C_f may be scaled, up or
    down, before it leaves its stable interval (inf: nowhere; None when unstable or not
    computed); ``phase_margin_deg``: at the gain crossover whose phase comes nearest
    -180 deg (inf: no crossover)."""

    status: GateStatus
    force_gain: float
    max_stable_gain: float | None = None
    stable_intervals: tuple[tuple[float, float], ...] = ()
    gain_margin_db: float | None = None
    phase_margin_deg: float | None = None
    min_gain_margin_db: float = 0.0
    min_phase_margin_deg: float = 0.0
    assumed: Assumptions | None = None
    reason: str = ""

    def low_margins(self) -> list[str]:
        """The margins below their thresholds, as text (empty: none, or not stable)."""
        out: list[str] = []
        if not self.stable:
            return out
        gm, pm = self.gain_margin_db, self.phase_margin_deg
        if gm is not None and gm < self.min_gain_margin_db:
            out.append(f"gain margin {gm:.3g} dB < analysis.min_gain_margin = {self.min_gain_margin_db:g} dB")
        if pm is not None and pm < self.min_phase_margin_deg:
            out.append(f"phase margin {pm:.3g} deg < analysis.min_phase_margin = "
                       f"{self.min_phase_margin_deg:g} deg")
        return out

    def loop_text(self) -> str:
        """``the sampled loop (T = .., delay ..) at C_f = 20 is UNSTABLE; max stable C_f: 8.72``."""
        what = self.assumed.text() if self.assumed is not None else "loop"
        verdict = {GateStatus.STABLE: "stable", GateStatus.UNSTABLE: "UNSTABLE"}.get(self.status, "not judged")
        return f"the {what} at C_f = {self.force_gain:g} is {verdict}; {self._map_text()}"

    def summary(self) -> str:
        """The verdict in one line: the loop, its map and its margins (or why not judged)."""
        note = self.note()
        if note is not None:
            return note
        if not self.stable:
            return self.loop_text()
        def fmt(x: float | None, unit: str, infinite: str) -> str:
            return "-" if x is None else (infinite if math.isinf(x) else f"{x:.3g} {unit}")
        return (f"{self.loop_text()}; gain margin {fmt(self.gain_margin_db, 'dB', 'unbounded')}, "
                f"phase margin {fmt(self.phase_margin_deg, 'deg', 'none (no gain crossover)')}")

    def _map_text(self) -> str:
        k = self.max_stable_gain
        if k is None:
            return f"not judged ({self.reason})"
        text = "max stable C_f: " + ("unbounded" if math.isinf(k) else f"{k:.6g}")
        if len(self.stable_intervals) > 1 or (self.stable_intervals and self.stable_intervals[0][0] > 0):
            text += "; stable C_f intervals: " + ", ".join(
                f"({lo:.4g}, {'inf' if math.isinf(hi) else f'{hi:.4g}'})" for lo, hi in self.stable_intervals)
        return text

    def advice(self) -> str:
        """How to proceed with an unstable design."""
        k = self.max_stable_gain or 0.0
        lower = (f"lower design.force_gain below {k:.6g}" if k > 0 else
                 "choose design.force_gain inside a stable interval" if self.stable_intervals else
                 "no force gain is stable: change the observers' bandwidths or the delay")
        return f"{lower} (dobhil analyze CONFIG shows the stable gains), or --allow-unstable for an experiment"

    def as_dict(self) -> dict[str, Any]:
        """Plain values (JSON-ready: inf as None where unbounded) for a log or a report."""
        def num(x: float | None) -> float | None:
            return None if x is None or not math.isfinite(x) else float(x)
        return {"status": self.status.name.lower(), "force_gain": self.force_gain,
                "max_stable_force_gain": num(self.max_stable_gain),
                "stable_force_gain_intervals": [[lo, num(hi)] for lo, hi in self.stable_intervals],
                "gain_margin_db": num(self.gain_margin_db), "phase_margin_deg": num(self.phase_margin_deg),
                "min_gain_margin_db": self.min_gain_margin_db, "min_phase_margin_deg": self.min_phase_margin_deg,
                "assumed": None if self.assumed is None else asdict(self.assumed), "reason": self.reason}


def assess(config: Config, profile: DriveProfile | None = None, *, sampled: bool = True) -> GateVerdict:
    """The gate's verdict on ``config`` run on ``profile`` (its command delay, when its
    protocol fixes one; None: the config's delay as written). ``sampled=False`` judges the
    continuous loop of the paper instead (what ``dobhil analyze`` shows first)."""
    design, source = config, "the config's"
    if profile is not None:
        design, _ = effective_config(config, profile)
        if profile.command_delay_periods is not None:   # the protocol's latch sets it
            source = f"drive profile {profile.name or profile.protocol!r}"
    base = GateVerdict(status=GateStatus.NOT_APPLICABLE, force_gain=float(design.design.force_gain),
                       min_gain_margin_db=design.analysis.min_gain_margin,
                       min_phase_margin_deg=design.analysis.min_phase_margin,
                       assumed=_assumptions(design, source, sampled))
    reason = not_applicable(design)
    if reason:
        return _with(base, reason=reason)
    return judged_or_not_computed(base, lambda: _judged(base, design, sampled))


def judged_or_not_computed(base: V, judge: Callable[[], V]) -> V:
    """``judge()``'s verdict, or ``base`` (a frozen verdict dataclass with ``status`` and
    ``reason``) NOT_COMPUTED with the reason the analysis could not answer; numpy's
    warnings silenced (a design at the edge of stability gives infinities on the way);
    a DobhilError (bad input) is raised."""
    try:
        with np.errstate(all="ignore"):
            return judge()
    except AnalysisError as exc:
        return replace(base, status=GateStatus.NOT_COMPUTED, reason=str(exc))  # type: ignore[type-var]
    except DobhilError:
        raise
    except (np.linalg.LinAlgError, ValueError, ZeroDivisionError, OverflowError) as exc:
        return replace(base, status=GateStatus.NOT_COMPUTED,  # type: ignore[type-var]
                       reason=f"the analysis cannot answer this design ({exception_line(exc, named=False)[:120]})")


def not_applicable(config: Config) -> str:
    """Why the analysis has no force loop to judge in ``config`` ("" when it has)."""
    if config.loop.mode == "torque":
        return "loop.mode = torque (the reference is the torque command: no force loop closes)"
    if config.design.force_gain == 0:
        return "design.force_gain = 0 (no force feedback closes a loop)"
    if config.environment.stiffness == 0:
        return ("environment.stiffness = 0 (no contact holds the position: it drifts at every "
                "C_f, a pole on the stability boundary no force gain moves)")
    return ""


def _assumptions(config: Config, source: str, sampled: bool) -> Assumptions:
    d = config.design
    return Assumptions(sampled=sampled, period=config.loop.period, delay_samples=d.delay_samples,
                       input_delay=d.input_delay, delay_source=source, discretization=d.discretization,
                       stiffness=config.environment.stiffness, damping=config.environment.damping)


def _with(base: GateVerdict, **changes: Any) -> GateVerdict:
    return replace(base, **changes)


def _judged(base: GateVerdict, config: Config, sampled: bool) -> GateVerdict:
    """The analysis' verdict: the open loop L of the loop that runs, its gain map, the
    closed-loop poles at C_f (``A0 - C_f B C``, :mod:`dobhil.analysis.stability`)."""
    params = params_from_config(config)
    a, b, c, _ = loop(params, sampled=sampled, force_gain=0.0).siso("tau_per", "tau_int_hat")
    if not all(np.all(np.isfinite(m)) for m in (a, b, c)):
        raise AnalysisError("the loop's matrices overflow for this design (a value too large or too small)")
    cf = base.force_gain
    gains = gain_map(a, b, c, sampled=sampled)
    poles = np.linalg.eigvals(a - cf * (b @ c))
    stable = bool(is_stable(poles[None], sampled)[0])
    unresolved = "" if stable else on_the_boundary(poles, sampled, config)
    if unresolved:
        return _with(base, status=GateStatus.NOT_COMPUTED, reason=unresolved)
    intervals = tuple(gains.intervals())
    verdict = _with(base, status=GateStatus.STABLE if stable else GateStatus.UNSTABLE,
                    max_stable_gain=float(gains.max_stable_gain), stable_intervals=intervals)
    if not stable:
        return verdict
    return _with(verdict, gain_margin_db=gain_margin_db(cf, intervals),
                 phase_margin_deg=float(phase_margin(a, b, c, cf, sampled=sampled)))


def on_the_boundary(poles: np.ndarray, sampled: bool, config: Config) -> str:
    """Why closed-loop ``poles`` that :func:`is_stable` calls unstable cannot be judged ("" when
    one lies clearly outside): every pole outside the stable region is within the analysis'
    resolution of its boundary (:func:`~dobhil.analysis.stability.unresolved_pole`). A soft
    environment puts the position's pole there, which drifts as at K_env = 0
    (:func:`not_applicable`); no force gain, bandwidth or delay moves it."""
    edge = unresolved_pole(poles, sampled)
    if edge is None:
        return ""
    where = (f"|z| = 1 {'+' if abs(edge) >= 1 else '-'} {abs(abs(edge) - 1.0):.3g}" if sampled
             else f"Re(s) = {edge.real:.3g} 1/s")
    env = config.environment
    why = (f"the position, held by K_env {env.stiffness:g} N m/rad and D_env {env.damping:g} N m s/rad, "
           "drifts about as freely as at environment.stiffness = 0" if is_position_drift(edge, sampled) else
           f"C_f = {config.design.force_gain:g} is at an edge of a stable interval")
    return (f"a closed-loop pole lies on the stability boundary within the analysis' resolution ({where}), "
            f"so the analysis cannot tell stable from unstable: {why}")


def gain_margin_db(force_gain: float, intervals: tuple[tuple[float, float], ...]) -> float | None:
    """How far ``force_gain`` may be scaled up or down, in dB, and stay in its stable
    interval (inf: unbounded both ways; None: in no stable interval)."""
    for lo, hi in intervals:
        if lo < force_gain < hi:
            up = math.inf if math.isinf(hi) else 20.0 * math.log10(hi / force_gain)
            down = math.inf if lo <= 0 else 20.0 * math.log10(force_gain / lo)
            return min(up, down)
    return None


__all__ = ["Assumptions", "GateStatus", "GateVerdict", "assess", "gain_margin_db", "judged_or_not_computed",
           "not_applicable", "on_the_boundary"]
