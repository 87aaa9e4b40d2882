"""The identified uncertainty in the overlay ``dobhil identify --out`` writes: beside the
``key: value`` lines (what ``--set-file`` applies), an ``identified:`` section with each
identified config key's estimate, 95 % interval and standard error, and the estimates'
covariance -- what ``dobhil tune --uncertainty-from`` takes as its box and ``dobhil montecarlo
--draw-from`` draws from. ``--set-file`` skips the section (:func:`dobhil.config.load.read_set_file`).

The covariance is the fit's ``s^2 (J^T J)^-1`` (:mod:`dobhil.identify.fit`), rebuilt from the
standard errors and correlations the fit reports: ``C_ij = r_ij s_i s_j``; a key whose interval
is cut at its bound 0 has ``s`` from that interval instead (:func:`_spread`).
"""

from __future__ import annotations

import math
import os
from statistics import NormalDist
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Final

import numpy as np

from dobhil.errors import ConfigError

__all__ = ["SECTION", "Identified", "Interval", "read_identified", "section_text"]

#: the overlay's top-level key of the identified uncertainty (not a config section)
SECTION: Final = "identified"
#: estimate name -> the config key it sets (the delay is two keys, whole samples and fraction:
#: it stays in the comments)
CONFIG_KEYS: Final = {"inertia": "plant.inertia", "viscous_friction": "plant.viscous_friction",
                      "coulomb_friction": "plant.coulomb_friction",
                      "contact_position": "environment.contact_position",
                      "stiffness": "environment.stiffness", "damping": "environment.damping"}


@dataclass(frozen=True)
class Interval:
    """One identified config key: its estimate, 95 % interval ``[lo, hi]`` and standard error."""

    key: str
    estimate: float
    lo: float
    hi: float
    stderr: float


@dataclass(frozen=True)
class Identified:
    """The intervals of an overlay (in its order) and the covariance of their estimates (rows
    and columns in the same order)."""

    source: str
    level: float
    intervals: tuple[Interval, ...]
    covariance: np.ndarray

    @property
    def keys(self) -> tuple[str, ...]:
        return tuple(i.key for i in self.intervals)


def section_text(info: Mapping[str, Any]) -> str:
    """The ``identified:`` section of an identification's summary (``info``: its JSON, with
    ``estimates`` and ``correlations``) as YAML lines ("" when nothing was identified)."""
    est = info["estimates"]
    names = [n for n in CONFIG_KEYS if est.get(n, {}).get("identifiable")]
    if not names:
        return ""
    r = {(c["a"], c["b"]): c["r"] for c in info.get("correlations", [])}
    sd = np.array([_spread(est[n]) if n != "contact_position" else float(est[n]["stderr"]) for n in names])
    corr = np.eye(len(names))
    for i, a in enumerate(names):
        for j, b in enumerate(names):
            value = r.get((a, b), r.get((b, a)))
            if i != j and value is not None:
                corr[i, j] = float(value)
    cov = corr * np.outer(sd, sd)
    lines = [f"{SECTION}:   # the fit's uncertainty (dobhil tune --uncertainty-from, dobhil montecarlo "
             "--draw-from); --set-file skips it",
             "  level: 0.95",
             "  intervals:   # config key: estimate, 95 % interval lo..hi, standard error"]
    for n, s in zip(names, sd):
        e = est[n]
        lines.append(f"    {CONFIG_KEYS[n]}: {{estimate: {float(e['value'])!r}, lo: {float(e['low'])!r}, "
                     f"hi: {float(e['high'])!r}, stderr: {float(s)!r}}}")
    lines.append("  covariance:   # of the estimates, rows and columns in the order of keys")
    lines.append(f"    keys: [{', '.join(CONFIG_KEYS[n] for n in names)}]")
    lines.append("    matrix:")
    lines += [f"      - [{', '.join(repr(float(x)) for x in row)}]" for row in cov]
    return "\n".join(lines) + "\n"


#: the two-sided normal quantile of the overlay's 95 % intervals
_Z: Final = NormalDist().inv_cdf(0.975)


def _spread(e: Mapping[str, Any]) -> float:
    """The standard error a draw of a physical key uses: the fit's, but for an interval cut at
    the bound 0 (a friction or delay near 0: ``value - z s`` below it), whose high end is the
    profile likelihood's (dobhil/identify/fit.py ``_profiled``), not ``value + z s``: there
    ``(hi - value) / z``, so the normal truncated at 0 that ``montecarlo --draw-from`` draws
    from puts its 95 % inside the interval the overlay gives, as a half-normal's 95 % point
    is ``z s`` (an AK80-9 free run's Coulomb friction: interval [0, 3.2e-4], the fit's s
    5.5e-4, with which over half the draws lay above the interval)."""
    value, low, high, stderr = (float(e[k]) for k in ("value", "low", "high", "stderr"))
    if low == 0.0 and value - _Z * stderr < 0.0 <= value <= high:
        return (high - value) / _Z
    return stderr


def read_identified(path: str | os.PathLike[str], option: str) -> Identified:
    """The ``identified:`` section of an overlay; ConfigError (one line, naming ``option``)
    when the file is no overlay with one, or the section is malformed."""
    from dobhil.config.load import read_yaml
    name = os.fspath(path)
    data = read_yaml(name, name=f"{option} {name}", expected="an overlay written by dobhil identify --out")
    section = data.get(SECTION) if isinstance(data, Mapping) else None
    if not isinstance(section, Mapping) or not section.get("intervals"):
        raise ConfigError(f"{option} {name}: no identified intervals (an '{SECTION}:' section with intervals, "
                          "as dobhil identify --out writes); allowed: an overlay of dobhil identify with at least "
                          "one identified plant or environment key")
    try:
        intervals = tuple(_interval(k, v) for k, v in section["intervals"].items())
        cov = section["covariance"]
        order = [str(k) for k in cov["keys"]]
        matrix = np.array(cov["matrix"], dtype=float)
        level = float(section.get("level", 0.95))
    except (KeyError, TypeError, ValueError, AttributeError) as exc:
        raise ConfigError(f"{option} {name}: a malformed '{SECTION}:' section ({exc}); expected intervals of "
                          "key: {estimate, lo, hi, stderr} and a covariance of keys and matrix") from None
    keys = [i.key for i in intervals]
    if not 0.0 < level < 1.0:
        raise ConfigError(f"{option} {name}: the '{SECTION}:' level {level:g} is no confidence level; "
                          "expected a fraction between 0 and 1 (dobhil identify writes 0.95)")
    if order != keys or matrix.shape != (len(keys), len(keys)) or not np.all(np.isfinite(matrix)) \
            or not np.allclose(matrix, matrix.T, rtol=1e-9, atol=0.0):
        raise ConfigError(f"{option} {name}: the '{SECTION}:' covariance does not match its intervals (expected a "
                          f"symmetric {len(keys)} x {len(keys)} matrix over keys {', '.join(keys)})")
    # a covariance is positive semi-definite: a draw from one that is not is no normal at all
    # (the tolerance: rounding of the 6-7 digits the overlay is written with)
    if np.linalg.eigvalsh(matrix).min() < -1e-6 * max(float(np.abs(matrix).max()), np.finfo(float).tiny):
        raise ConfigError(f"{option} {name}: the '{SECTION}:' covariance is not positive semi-definite "
                          "(a negative variance along some direction); expected dobhil identify's covariance")
    return Identified(source=name, level=level, intervals=intervals, covariance=matrix)


def _interval(key: Any, v: Mapping[str, Any]) -> Interval:
    i = Interval(key=str(key), estimate=float(v["estimate"]), lo=float(v["lo"]), hi=float(v["hi"]),
                 stderr=float(v["stderr"]))
    if not all(math.isfinite(x) for x in (i.estimate, i.lo, i.hi, i.stderr)) or not i.lo <= i.estimate <= i.hi:
        raise ValueError(f"{key}: expected finite lo <= estimate <= hi")
    if not i.stderr >= 0.0:
        raise ValueError(f"{key}: stderr {i.stderr:g}: expected a standard error >= 0")
    return i
