"""A campaign's metrics against its reference run: the config as given (its nominal values,
no draws), with the campaign's noise and a seed of its own, run like every other run
(:meth:`dobhil.campaign.campaign.Campaign.reference_spec`).

The campaign asks "does the design hold over the drawn plants?"; the reference says what the
design does on the plant it was made for. A metric's median (p50) is *worse* than the
reference's when it is past it by more than the metric's tolerance:

``tolerance = max(RELATIVE x |reference value|, floor)``, the floor by the metric's unit:
:data:`TORQUE_FLOOR` x |the command at the run's end| (at least :data:`TORQUE_MIN` N m) for
torques, :data:`TIME_FLOOR_PERIODS` loop periods for times, :data:`PERCENT_FLOOR` points
for the overshoot. "Past" depends on the metric (:class:`Worse`): larger for errors, times
and overshoot; farther from zero for the signed final error; away from the reference's
either way for the final torque. The final torque's p5 and p95 (and the reference's) are
also compared with the command itself (:class:`CommandCheck`), with the same tolerance.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from enum import IntEnum
from typing import Any


class Worse(IntEnum):
    LARGER = 0       # errors, times, overshoot
    FARTHER = 1      # a signed error: farther from zero
    OFF = 2          # a level: away from the reference's, either way


class Unit(IntEnum):
    TORQUE = 0
    TIME = 1
    PERCENT = 2


#: how each metric is worse, and its unit (an unknown metric: larger is worse, no floor)
RULES: dict[str, tuple[Worse, Unit]] = {
    "force_rms_error": (Worse.LARGER, Unit.TORQUE),
    "final_error": (Worse.FARTHER, Unit.TORQUE),
    "overshoot_pct": (Worse.LARGER, Unit.PERCENT),
    "rise_time": (Worse.LARGER, Unit.TIME),
    "settling_time": (Worse.LARGER, Unit.TIME),
    "final_tau_int_true": (Worse.OFF, Unit.TORQUE),
}

#: the tolerance: this share of the reference's value, or the unit's floor if larger
RELATIVE = 0.10
TORQUE_FLOOR = 0.01
TORQUE_MIN = 1e-3
TIME_FLOOR_PERIODS = 2.0
PERCENT_FLOOR = 1.0

#: the unit's symbol in the printed summary
SYMBOL = {Unit.TORQUE: "N m", Unit.TIME: "s", Unit.PERCENT: "%"}


@dataclass(frozen=True)
class Floors:
    """The tolerance floors of one campaign: they need its loop period and command."""

    torque: float
    time: float
    percent: float = PERCENT_FLOOR

    @staticmethod
    def of(period: float, command: float | None) -> Floors:
        return Floors(torque=max(TORQUE_MIN, TORQUE_FLOOR * abs(command or 0.0)),
                      time=TIME_FLOOR_PERIODS * period)

    def floor(self, unit: Unit) -> float:
        return {Unit.TORQUE: self.torque, Unit.TIME: self.time, Unit.PERCENT: self.percent}[unit]


@dataclass(frozen=True)
class Comparison:
    """One metric's median against the reference's value: how far past it (> 0: worse),
    the tolerance, and whether that is a flag."""

    metric: str
    p50: float
    reference: float
    past: float
    tolerance: float

    @property
    def worse(self) -> bool:
        return self.past > self.tolerance

    def as_dict(self) -> dict[str, Any]:
        return {"metric": self.metric, "p50": self.p50, "reference": self.reference, "past": self.past,
                "tolerance": self.tolerance, "worse": self.worse}


def tolerance(metric: str, reference: float, floors: Floors) -> float:
    _, unit = RULES.get(metric, (Worse.LARGER, Unit.TORQUE))
    return max(RELATIVE * abs(reference), floors.floor(unit))


def past(metric: str, value: float, reference: float) -> float:
    """How far ``value`` is past ``reference`` in the metric's worse direction (< 0: better)."""
    worse, _ = RULES.get(metric, (Worse.LARGER, Unit.TORQUE))
    if worse is Worse.FARTHER:
        return abs(value) - abs(reference)
    if worse is Worse.OFF:
        return abs(value - reference)
    return value - reference


def compare(percentiles: Mapping[str, Mapping[str, float]], reference: Mapping[str, Any],
            floors: Floors) -> list[Comparison]:
    """Each metric that both the campaign (its p50) and the reference have."""
    out = []
    for metric, p in percentiles.items():
        ref = reference.get(metric)
        if ref is None:
            continue
        out.append(Comparison(metric, p["p50"], float(ref), past(metric, p["p50"], float(ref)),
                              tolerance(metric, float(ref), floors)))
    return out


@dataclass(frozen=True)
class CommandCheck:
    """Where the runs' final true torque ends (its p5 and p95) and the reference's, against
    the command at the end: off when farther than ``tolerance`` (that of the torque metrics,
    relative to the command)."""

    p5: float
    p95: float
    reference: float | None
    command: float
    tolerance: float

    @property
    def runs_off(self) -> bool:
        return max(abs(self.p5 - self.command), abs(self.p95 - self.command)) > self.tolerance

    @property
    def reference_off(self) -> bool:
        return self.reference is not None and abs(self.reference - self.command) > self.tolerance

    def as_dict(self) -> dict[str, Any]:
        return {"p5": self.p5, "p95": self.p95, "reference": self.reference, "command": self.command,
                "tolerance": self.tolerance, "runs_off": self.runs_off, "reference_off": self.reference_off}


def command_check(percentiles: Mapping[str, Mapping[str, float]], reference: Mapping[str, Any],
                  floors: Floors) -> CommandCheck | None:
    """The final true torque against the reference run's command at its end (None when
    either is missing)."""
    p = percentiles.get("final_tau_int_true")
    command = reference.get("final_tau_ref")
    if p is None or command is None:
        return None
    return CommandCheck(p["p5"], p["p95"], reference.get("final_tau_int_true"), float(command),
                        tolerance("final_tau_int_true", float(command), floors))


__all__ = ["CommandCheck", "Comparison", "Floors", "RULES", "Unit", "Worse", "command_check", "compare", "past",
           "tolerance"]
