"""The identified uncertainty as what ``dobhil tune`` and ``dobhil montecarlo`` take: an
overlay's 95 % intervals as tune's box (``--uncertainty-from``), its estimates and covariance as
a campaign's joint draw (``--draw-from``). The overlay is read by
:func:`dobhil.identify.intervals.read_identified`."""

from __future__ import annotations

import math
import sys
from typing import Any

from dobhil.tune.problem import IntervalUncertainty, Uncertainty


def identified_box(path: str, notes: list[str] | None = None) -> list[Uncertainty]:
    """Each identified key the tuned loop depends on as an :class:`IntervalUncertainty`; the
    keys and bounds taken, and the keys left out (the linear loop has no Coulomb friction or
    contact position), in one line on stderr -- or appended to ``notes``, for the command to
    print once its other inputs are checked (a refusal after it stays one line)."""
    from dobhil.identify.intervals import read_identified
    from dobhil.synthesis.params import PARAM_KEYS
    from dobhil.tune.problem import UNCERTAIN_PREFIXES
    identified = read_identified(path, "--uncertainty-from")
    used = [i for i in identified.intervals if i.key in PARAM_KEYS and i.key.startswith(UNCERTAIN_PREFIXES)]
    left = [i.key for i in identified.intervals if i not in used]
    if not used:
        from dobhil.errors import ConfigError
        raise ConfigError(f"--uncertainty-from {path}: none of its identified keys ({', '.join(identified.keys)}) is "
                          "one the tuned loop depends on; allowed: plant.inertia, plant.viscous_friction, "
                          "environment.stiffness, environment.damping")
    # a friction fitted at its bound 0 has no relative half-width: its interval alone is the box
    box: list[Uncertainty] = [IntervalUncertainty(i.key, max(i.hi - i.estimate, i.estimate - i.lo) / abs(i.estimate)
                                                  if i.estimate else math.inf, lo=i.lo, hi=i.hi, estimate=i.estimate)
                              for i in used]
    shown = ", ".join(f"{i.key} [{i.lo:.6g}, {i.hi:.6g}]" for i in used)
    note = f"; left out (not in the linear loop): {', '.join(left)}" if left else ""
    _say(f"tune: uncertainty box from {path} ({identified.level * 100:g} % intervals): {shown}{note}", notes)
    return box


def _say(line: str, notes: list[str] | None) -> None:
    if notes is None:
        print(line, file=sys.stderr)
    else:
        notes.append(line)


#: keys a physical quantity keeps at or above 0 (a draw below is drawn again); the contact
#: position is a place, any sign
_NONNEGATIVE = ("plant.inertia", "plant.viscous_friction", "plant.coulomb_friction", "environment.stiffness",
                "environment.damping")
#: a joint distribution accepting fewer of its draws than this is refused (the truncation would
#: be most of the distribution, no longer what the fit found)
MIN_ACCEPTANCE = 0.01


def joint_varies(path: str, notes: list[str] | None = None) -> tuple[Any, ...]:
    """The overlay's identified keys as one joint normal (estimates and covariance) truncated to
    physical values, a :class:`~dobhil.campaign.draws.Vary` per key; how, in one line on stderr
    (or appended to ``notes``, as :func:`identified_box` does)."""
    from dobhil.campaign.draws import JointNormal, Kind, Vary
    from dobhil.errors import ConfigError
    from dobhil.identify.intervals import read_identified
    identified = read_identified(path, "--draw-from")
    lower = tuple(0.0 if k in _NONNEGATIVE else -math.inf for k in identified.keys)
    joint = JointNormal(keys=identified.keys, mean=tuple(i.estimate for i in identified.intervals),
                        covariance=tuple(tuple(float(x) for x in row) for row in identified.covariance),
                        lower=lower, source=path)
    accepted = joint.acceptance()
    if accepted < MIN_ACCEPTANCE:
        raise ConfigError(f"--draw-from {path}: only {accepted:.2%} of its normal draws are physical (>= 0); the "
                          "truncation would be the distribution -- vary these keys with --vary instead")
    bounded = [k for k, lo in zip(identified.keys, lower) if lo == 0.0]
    _say(f"montecarlo: drawing {', '.join(identified.keys)} jointly from {path}: normal with the fitted estimates "
         f"and covariance, truncated to >= 0 for {', '.join(bounded) or 'none'} by redrawing the whole vector "
         f"(exact truncation; {accepted:.2%} of draws accepted)", notes)
    sd = [i.stderr for i in identified.intervals]
    return tuple(Vary(k, Kind.JOINT_NORMAL, m, s, False, joint)
                 for k, m, s in zip(identified.keys, joint.mean, sd))
