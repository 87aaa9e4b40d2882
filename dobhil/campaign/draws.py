"""``--vary KEY=DIST``: which config keys a campaign draws, from which distribution.

Every draw of run ``i`` comes from ``numpy.random.SeedSequence(seed).spawn(runs)[i]``
alone (rebuilt as ``SeedSequence(seed, spawn_key=(i,))``, the same child without spawning
the others), so a run's values depend on ``(seed, i)`` only -- never on how many workers
ran the campaign or in which order the runs finished.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import IntEnum

import numpy as np

from dobhil.config.schema import key_fields, span_problem
from dobhil.errors import ConfigError


class Kind(IntEnum):
    NORMAL = 0
    UNIFORM = 1
    LOGUNIFORM = 2
    #: one key of a joint normal (:class:`JointNormal`, ``--draw-from``)
    JOINT_NORMAL = 3


#: the spelling of each distribution on the command line, and what its two numbers are
SPELLING: dict[Kind, tuple[str, str]] = {
    Kind.NORMAL: ("normal", "MEAN:STD"),
    Kind.UNIFORM: ("uniform", "LO:HI"),
    Kind.LOGUNIFORM: ("loguniform", "LO:HI"),
    Kind.JOINT_NORMAL: ("joint-normal", "MEAN:STD"),
}
ALLOWED = ", ".join(f"{name}:{args}" for kind, (name, args) in SPELLING.items() if kind is not Kind.JOINT_NORMAL)

#: keys a campaign sets itself (each run's emulator seed comes from its SeedSequence child)
RESERVED = ("sensor.seed",)
#: numeric keys a lockstep emulated run never reads (real-time scheduling, the real bus, the
#: analysis' horizon): drawing them would only look like a campaign
UNUSED = ("loop.realtime_priority", "loop.spin", "loop.cpu_affinity", "drive.bitrate",
          "drive.latency", "drive.jitter", "analysis.step_duration")


@dataclass(frozen=True)
class Vary:
    """One ``--vary``: ``key`` drawn from ``kind`` with parameters ``a``, ``b`` (mean and
    standard deviation, or the bounds); ``integer`` keys are rounded to the nearest whole number."""

    key: str
    kind: Kind
    a: float
    b: float
    integer: bool = False
    #: the joint distribution this key is drawn from with others (kind JOINT_NORMAL)
    joint: JointNormal | None = None

    def text(self) -> str:
        if self.joint is not None:
            others = ", ".join(self.joint.keys)
            return f"{self.key}=joint-normal:{self.a!r}:{self.b!r} (with {others} from {self.joint.source})"
        return f"{self.key}={SPELLING[self.kind][0]}:{self.a!r}:{self.b!r}"


#: a joint draw may be rejected (outside its physical bounds) this many times per run; a
#: distribution that rejects so often is refused up front (:meth:`JointNormal.acceptance`)
MAX_REJECTIONS = 1000


@dataclass(frozen=True)
class JointNormal:
    """A multivariate normal over ``keys`` (``mean``, ``covariance``: an identification's
    estimates and their covariance), truncated to the physical bounds: a key with ``lower[i]``
    finite is drawn again (the whole vector) while below it. Rejection keeps the truncated
    distribution exact: the normal conditioned on every key within its bound. The square root
    of the covariance is its symmetric eigen-root (a covariance rounded to slightly indefinite
    still draws; its negative eigenvalues count as 0)."""

    keys: tuple[str, ...]
    mean: tuple[float, ...]
    covariance: tuple[tuple[float, ...], ...]
    lower: tuple[float, ...]
    source: str

    def root(self) -> np.ndarray:
        w, v = np.linalg.eigh(np.array(self.covariance, float))
        return np.asarray(v * np.sqrt(np.clip(w, 0.0, None)), float)

    def sample(self, rng: np.random.Generator) -> dict[str, float]:
        root, mean, lower = self.root(), np.array(self.mean), np.array(self.lower)
        for _ in range(MAX_REJECTIONS):
            x = mean + root @ rng.standard_normal(len(self.keys))
            if np.all(x >= lower):
                return dict(zip(self.keys, (float(v) for v in x)))
        raise ValueError(f"{self.source}: {MAX_REJECTIONS} joint draws in a row below the physical bounds")

    def acceptance(self, draws: int = 20_000, seed: int = 0) -> float:
        """The fraction of untruncated draws within the bounds (estimated from ``draws``)."""
        x = np.array(self.mean) + np.random.default_rng(seed).standard_normal((draws, len(self.keys))) @ self.root().T
        return float(np.mean(np.all(x >= np.array(self.lower), axis=1)))


def numeric_keys() -> list[str]:
    """Config keys a campaign may draw: numbers, not choices."""
    return [name for name, f in key_fields().items()
            if (str(f.type) in ("float", "int") or f.type in (float, int)) and name not in UNUSED]


def parse_vary(item: str) -> Vary:
    """``"plant.inertia=normal:0.25:0.02"`` -> :class:`Vary`; ConfigError (one line naming what
    is allowed) for anything else."""
    name, sep, dist = item.partition("=")
    name = name.strip()
    if not sep:
        raise ConfigError(f"--vary {item!r}: expected KEY=DIST with DIST one of {ALLOWED}")
    integer = _check_key(name, item)
    kind_text, _, numbers = dist.strip().partition(":")
    kinds = {spelled: kind for kind, (spelled, _) in SPELLING.items()}
    if kind_text not in kinds:
        raise ConfigError(f"--vary {item!r}: unknown distribution {kind_text!r}; allowed: {ALLOWED}")
    kind = kinds[kind_text]
    a, b = _two_numbers(item, numbers, SPELLING[kind][1])
    _check_parameters(item, kind, a, b)
    _check_support(item, name, kind, a, b)
    return Vary(name, kind, a, b, integer)


def _check_key(name: str, item: str) -> bool:
    """Whether ``name`` is an integer key; ConfigError if it cannot be drawn."""
    if name in RESERVED:
        raise ConfigError(f"--vary {item!r}: {name} is set by the campaign (each run's own seed, "
                          "from --seed); vary another key")
    field = key_fields().get(name)
    allowed = numeric_keys()
    if field is None or name not in allowed:
        # a key of UNUSED is a number: saying it is none would send the user looking for a typo
        what = ("a key a lockstep emulated run never reads" if name in UNUSED
                else "not a numeric config key" if field is not None else "unknown config key")
        raise ConfigError(f"--vary {item!r}: {what} {name!r}; allowed: "
                          f"{', '.join(k for k in allowed if k not in RESERVED)}")
    return field.type in (int, "int")


def _two_numbers(item: str, text: str, spelled: str) -> tuple[float, float]:
    parts = text.split(":")
    try:
        if len(parts) != 2:
            raise ValueError
        a, b = float(parts[0]), float(parts[1])
    except ValueError:
        raise ConfigError(f"--vary {item!r}: expected two numbers {spelled} after the "
                          f"distribution; allowed: {ALLOWED}") from None
    if not (math.isfinite(a) and math.isfinite(b)):
        raise ConfigError(f"--vary {item!r}: {spelled} must be finite numbers")
    return a, b


def _check_parameters(item: str, kind: Kind, a: float, b: float) -> None:
    if kind is Kind.NORMAL and not b >= 0:
        raise ConfigError(f"--vary {item!r}: the standard deviation must be >= 0")
    if kind is not Kind.NORMAL and not b > a:
        raise ConfigError(f"--vary {item!r}: an empty range; HI must be above LO")
    if kind is Kind.LOGUNIFORM and not a > 0:
        raise ConfigError(f"--vary {item!r}: loguniform needs LO > 0")


def _check_support(item: str, name: str, kind: Kind, a: float, b: float) -> None:
    """A uniform or loguniform range must lie within the key's allowed values, a normal's
    mean too: else every run (or the typical one) would fail on its own config error, one
    row at a time, instead of the campaign refusing once. A normal's tails may still reach
    past a bound; such a run fails alone, its row says why."""
    lo, hi = (a, a) if kind is Kind.NORMAL else (a, b)
    problem = span_problem(name, lo, hi, key_fields()[name].metadata)
    if problem is not None:
        raise ConfigError(f"--vary {item!r}: {problem}")


def child(seed: int, index: int) -> np.random.SeedSequence:
    """``SeedSequence(seed).spawn(n)[index]`` for any ``n > index``, without spawning the rest."""
    return np.random.SeedSequence(seed, spawn_key=(index,))


def draw(varies: tuple[Vary, ...], seed: int, index: int) -> tuple[dict[str, float | int], int]:
    """Run ``index``'s drawn values (in ``--vary`` order) and its emulator seed
    (``sensor.seed``), from SeedSequence child ``index`` of ``seed`` only."""
    sequence = child(seed, index)
    rng = np.random.default_rng(sequence)
    joint: dict[JointNormal, dict[str, float]] = {}
    values: dict[str, float | int] = {}
    for v in varies:
        if v.joint is None:
            values[v.key] = _one(v, rng)
        else:   # the first key of a joint distribution draws all of its keys, in --vary order
            if v.joint not in joint:
                joint[v.joint] = v.joint.sample(rng)
            values[v.key] = joint[v.joint][v.key]
    # the emulator's seed from the same child, independently of how many keys were drawn
    sensor_seed = int(sequence.generate_state(1, np.uint32)[0])
    return values, sensor_seed


def _one(v: Vary, rng: np.random.Generator) -> float | int:
    if v.kind is Kind.NORMAL:
        x = float(rng.normal(v.a, v.b))
    elif v.kind is Kind.UNIFORM:
        x = float(rng.uniform(v.a, v.b))
    else:
        x = float(math.exp(rng.uniform(math.log(v.a), math.log(v.b))))
    return int(round(x)) if v.integer else x
