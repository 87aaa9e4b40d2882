"""What ``dobhil tune`` is asked: the robust set, the decision variables' bounds, the margins.

Everything here is parsed from the command line's text and checked before any work starts:
a bad key, an empty range, a bound the config refuses is one :class:`ConfigError` line.
"""

from __future__ import annotations

import itertools
import math
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from types import MappingProxyType
from typing import ClassVar

import numpy as np

from dobhil.config.schema import Config, key_fields
from dobhil.errors import ConfigError
from dobhil.synthesis.params import PARAM_KEYS

#: the design keys tune chooses, in the order of the optimiser's vector
DECISION_KEYS: tuple[str, ...] = ("design.dob_bandwidth", "design.rtob_bandwidth",
                                  "design.identified_inertia", "design.force_gain")

#: keys a --range or --uncertainty may name: what the design cannot choose (plant, environment)
UNCERTAIN_PREFIXES = ("plant.", "environment.")

#: a range this wide (HI / LO) or wider is spaced logarithmically
LOG_SPACING_RATIO = 10.0

#: default margins: gain margin [dB], phase margin [deg], peak sensitivity [dB], and the
#: force step's overshoot [%] (without it the fastest rise is a wild overshoot: a slow RTOb
#: and a large C_f make the true force leap while the estimate lags)
DEFAULT_MARGINS = {"gm": 6.0, "pm": 30.0, "ms": 6.0, "os": 20.0}


@dataclass(frozen=True)
class Range:
    """A swept environment or plant key: LO..HI (log spaced when HI / LO >= 10)."""

    key: str
    lo: float
    hi: float

    @property
    def log(self) -> bool:
        return self.lo > 0 and self.hi / self.lo >= LOG_SPACING_RATIO

    def values(self, count: int) -> np.ndarray:
        if count == 1 or self.lo == self.hi:
            return np.array([math.sqrt(self.lo * self.hi) if self.log else 0.5 * (self.lo + self.hi)])
        return np.geomspace(self.lo, self.hi, count) if self.log else np.linspace(self.lo, self.hi, count)


@dataclass(frozen=True)
class Uncertainty:
    """A plant or environment key known to ±fraction of its config value."""

    key: str
    fraction: float
    #: the option that gives it, as a refusal names it
    option: ClassVar[str] = "--uncertainty"

    def values(self, centre: float) -> np.ndarray:
        """Its ends and centre: the box's corners and middle are where margins are checked."""
        return np.array([centre * (1.0 - self.fraction), centre, centre * (1.0 + self.fraction)])

    def describe(self) -> str:
        return f"{self.key} ±{self.fraction * 100:g} % (ends and centre)"


@dataclass(frozen=True)
class IntervalUncertainty(Uncertainty):
    """A key known to lie in ``[lo, hi]`` around ``estimate`` (an identified 95 % interval,
    ``dobhil tune --uncertainty-from``): its ends and the estimate, whatever the config says.
    ``fraction`` is the larger relative half-width (for what reads it as ±)."""

    lo: float = 0.0
    hi: float = 0.0
    estimate: float = 0.0
    option: ClassVar[str] = "--uncertainty-from"

    def values(self, centre: float) -> np.ndarray:
        return np.array([self.lo, self.estimate, self.hi])

    def describe(self) -> str:
        return f"{self.key} {self.lo:.6g}..{self.hi:.6g} (identified 95 %, ends and estimate {self.estimate:.6g})"


@dataclass(frozen=True)
class Margins:
    """Constraints at every point of the set; ``noise`` None: no noise constraint."""

    gm_db: float = DEFAULT_MARGINS["gm"]
    pm_deg: float = DEFAULT_MARGINS["pm"]
    ms_db: float = DEFAULT_MARGINS["ms"]
    overshoot_pct: float = DEFAULT_MARGINS["os"]
    noise: float | None = None


@dataclass(frozen=True)
class Bounds:
    """Search bounds of each decision key (positive; the search runs on their logarithms)."""

    lo: Mapping[str, float]
    hi: Mapping[str, float]

    def log10(self) -> list[tuple[float, float]]:
        return [(math.log10(self.lo[k]), math.log10(self.hi[k])) for k in DECISION_KEYS]


@dataclass(frozen=True)
class RobustSet:
    """The points the design must hold at: the product of the range keys' values and the
    uncertainty keys' ends and centre. ``points`` maps each key to a flat array."""

    keys: tuple[str, ...]
    points: Mapping[str, np.ndarray]

    @property
    def size(self) -> int:
        return int(next(iter(self.points.values())).size) if self.points else 1

    def point(self, index: int) -> dict[str, float]:
        return {k: float(v[index]) for k, v in self.points.items()}

    def extended(self, extra: Mapping[str, np.ndarray]) -> RobustSet:
        """This set with more points (the fine check's worst ones), duplicates dropped."""
        stacked = np.stack([np.concatenate([self.points[k], extra[k]]) for k in self.keys])
        _, first = np.unique(stacked, axis=1, return_index=True)
        keep = np.sort(first)
        return RobustSet(self.keys, MappingProxyType({k: stacked[i, keep] for i, k in enumerate(self.keys)}))


def robust_set(config: Config, ranges: Sequence[Range], uncertainties: Sequence[Uncertainty],
               count: int) -> RobustSet:
    """``count`` values per range key times the uncertainty box (3 values per key)."""
    flat = config.flat()
    boxes = [u.values(float(flat[u.key])) for u in uncertainties]
    for u, ends in zip(uncertainties, boxes):
        # the box's ends are values of the key, as --range's are: within its floor and ceiling
        # (an inertia ±99.99999999999999 % ends at 3e-17 kg m^2, where the matrices overflow)
        _check_values(u.option, u.key, float(ends.min()), float(ends.max()))
    axes = [r.values(count) for r in ranges] + boxes
    keys = tuple(r.key for r in ranges) + tuple(u.key for u in uncertainties)
    grid = list(itertools.product(*axes)) if axes else [()]
    columns = np.array(grid, dtype=float).reshape(len(grid), len(keys)).T
    return RobustSet(keys, MappingProxyType({k: columns[i] for i, k in enumerate(keys)}))


def _check_uncertain_key(option: str, name: str) -> None:
    if name not in key_fields():
        raise ConfigError(f"{option} {name!r}: unknown config key")
    allowed = [k for k in PARAM_KEYS if k.startswith(UNCERTAIN_PREFIXES)]
    if name not in allowed:
        raise ConfigError(f"{option} {name!r}: not a plant or environment key; allowed: {', '.join(allowed)}")


def _numbers(option: str, spec: str, text: str) -> tuple[float, float]:
    parts = text.split(":")
    try:
        if len(parts) != 2:
            raise ValueError
        lo, hi = float(parts[0]), float(parts[1])
    except ValueError:
        raise ConfigError(f"{option} {spec!r}: expected KEY=LO:HI (two numbers)") from None
    if not (math.isfinite(lo) and math.isfinite(hi)):
        raise ConfigError(f"{option} {spec!r}: LO and HI must be finite numbers")
    if not lo < hi:
        raise ConfigError(f"{option} {spec!r}: empty range; LO must be below HI")
    return lo, hi


def _check_values(option: str, name: str, lo: float, hi: float) -> None:
    """The config's own constraint on the key, at both ends."""
    from dobhil.config.schema import span_problem
    problem = span_problem(f"{option} {name}", lo, hi, key_fields()[name].metadata)
    if problem is not None:
        raise ConfigError(problem)


def parse_range(spec: str) -> Range:
    """``KEY=LO:HI`` for a plant or environment key."""
    name, sep, text = spec.partition("=")
    name = name.strip()
    if not sep:
        raise ConfigError(f"--range {spec!r}: expected KEY=LO:HI")
    _check_uncertain_key("--range", name)
    lo, hi = _numbers("--range", spec, text)
    _check_values("--range", name, lo, hi)
    return Range(name, lo, hi)


_PERCENT = re.compile(r"^\s*(?:±|\+-|\+/-)?\s*([0-9.eE+-]+)\s*%\s*$")


def parse_uncertainty(spec: str) -> Uncertainty:
    """``KEY=±P%`` (also ``+-P%`` or ``P%``), 0 < P < 100."""
    name, sep, text = spec.partition("=")
    name = name.strip()
    if not sep:
        raise ConfigError(f"--uncertainty {spec!r}: expected KEY=±P% (e.g. plant.inertia=±20%)")
    _check_uncertain_key("--uncertainty", name)
    match = _PERCENT.match(text)
    try:
        percent = float(match.group(1)) if match else math.nan
    except ValueError:
        percent = math.nan
    if not 0.0 < percent < 100.0:
        raise ConfigError(f"--uncertainty {spec!r}: expected ±P% with 0 < P < 100 (e.g. ±20%)")
    return Uncertainty(name, percent / 100.0)


def parse_margins(specs: Sequence[str]) -> Margins:
    """``gm=DB,pm=DEG,ms=DB,os=PCT,noise=X`` (any subset, repeatable); the rest keep their
    defaults. A margin given twice is refused, as a key twice in --range / --uncertainty is:
    which of two limits was meant is not for the command to guess."""
    values: dict[str, float] = {}
    for spec in specs:
        for item in filter(None, (s.strip() for s in spec.split(","))):
            name, sep, text = item.partition("=")
            if name not in ("gm", "pm", "ms", "os", "noise") or not sep:
                raise ConfigError(f"--margin {item!r}: expected gm=DB, pm=DEG, ms=DB, os=PCT or noise=N_M")
            if name in values:
                raise ConfigError(f"--margin {name}: given more than once ({name}={values[name]:g}, {item}); "
                                  "give each margin once")
            try:
                values[name] = float(text)
            except ValueError:
                raise ConfigError(f"--margin {item!r}: {text!r} is not a number") from None
            if not math.isfinite(values[name]):
                raise ConfigError(f"--margin {item!r}: must be a finite number")
    _check_margins(values)
    return Margins(gm_db=values.get("gm", DEFAULT_MARGINS["gm"]), pm_deg=values.get("pm", DEFAULT_MARGINS["pm"]),
                   ms_db=values.get("ms", DEFAULT_MARGINS["ms"]),
                   overshoot_pct=values.get("os", DEFAULT_MARGINS["os"]), noise=values.get("noise"))


def _check_margins(values: Mapping[str, float]) -> None:
    if values.get("gm", 1.0) < 0:
        raise ConfigError(f"--margin gm={values['gm']:g}: a gain margin below 0 dB is an unstable loop")
    if not 0 <= values.get("pm", 1.0) < 180:
        raise ConfigError(f"--margin pm={values['pm']:g}: expected 0 <= pm < 180 degrees")
    if values.get("ms", 1.0) <= 0:
        raise ConfigError(f"--margin ms={values['ms']:g}: peak sensitivity is above 0 dB for any loop")
    if values.get("os", 1.0) < 0:
        raise ConfigError(f"--margin os={values['os']:g}: an overshoot is >= 0 %")
    if values.get("noise", 1.0) <= 0:
        raise ConfigError(f"--margin noise={values['noise']:g}: must be > 0 (N m RMS)")


def default_bounds(config: Config) -> Bounds:
    """Observer bandwidths 0.01/T .. 1.5/T (a sampled observer's pole exp(-gT) is still
    resolved at the low end and not yet at z = 0.2 at the top); J_mi 0.5 .. 2 times the
    config's (the paper's Fig. 3 range); C_f 1/20 .. 20 times the config's (0.05 .. 50 when
    it is 0)."""
    t = config.loop.period
    jmi, cf = config.design.identified_inertia, config.design.force_gain
    cf = cf if cf > 0 else 1.0
    lo = {"design.dob_bandwidth": 0.01 / t, "design.rtob_bandwidth": 0.01 / t,
          "design.identified_inertia": 0.5 * jmi, "design.force_gain": cf / 20.0}
    hi = {"design.dob_bandwidth": 1.5 / t, "design.rtob_bandwidth": 1.5 / t,
          "design.identified_inertia": 2.0 * jmi, "design.force_gain": cf * 20.0}
    return Bounds(MappingProxyType(lo), MappingProxyType(hi))


def parse_bounds(config: Config, specs: Sequence[str]) -> Bounds:
    """The default bounds with ``KEY=LO:HI`` overrides (KEY a decision key, 0 < LO < HI; each
    key once, as in --range)."""
    bounds = default_bounds(config)
    lo, hi = dict(bounds.lo), dict(bounds.hi)
    given: set[str] = set()
    for spec in specs:
        name, sep, text = spec.partition("=")
        name = name.strip()
        if not sep or name not in DECISION_KEYS:
            raise ConfigError(f"--bound {spec!r}: expected KEY=LO:HI with KEY one of {', '.join(DECISION_KEYS)}")
        if name in given:
            raise ConfigError(f"--bound {name}: given more than once; give each key once")
        given.add(name)
        a, b = _numbers("--bound", spec, text)
        if a <= 0:
            raise ConfigError(f"--bound {spec!r}: LO must be > 0 (the search is logarithmic)")
        _check_values("--bound", name, a, b)
        lo[name], hi[name] = a, b
    return Bounds(MappingProxyType(lo), MappingProxyType(hi))
