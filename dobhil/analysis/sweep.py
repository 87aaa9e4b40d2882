"""Stability over a grid of designs and environments, vectorised.

The whole grid is one batch through the synthesis (:mod:`dobhil.synthesis`) and
the exact gain map (:mod:`dobhil.analysis.stability`); the only Python loops run
over matrix dimensions and chunks of the grid, never over grid points.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from dobhil.analysis.stability import gain_map, is_stable
from dobhil.config.schema import Config, key_fields
from dobhil.errors import ConfigError
from dobhil.synthesis.loop import loop
from dobhil.synthesis.params import PARAM_KEYS, params_from_config


@dataclass(frozen=True)
class Axis:
    key: str
    values: np.ndarray


@dataclass(frozen=True)
class SweepResult:
    axes: tuple[Axis, ...]
    sampled: bool
    stable: np.ndarray              # at the design's C_f (or the swept one)
    minimum_phase: np.ndarray
    max_stable_gain: np.ndarray     # inf when unbounded
    interval_count: np.ndarray      # number of stable C_f intervals (>1: conditionally stable)

    @property
    def shape(self) -> tuple[int, ...]:
        return tuple(a.values.size for a in self.axes)

    def rows(self) -> list[dict[str, float | bool | None]]:
        out = []
        for idx in itertools.product(*(range(n) for n in self.shape)):
            row: dict[str, float | bool | None] = {a.key: float(a.values[i]) for a, i in zip(self.axes, idx)}
            k = float(self.max_stable_gain[idx])
            row.update(stable=bool(self.stable[idx]), minimum_phase=bool(self.minimum_phase[idx]),
                       max_stable_force_gain=None if np.isinf(k) else k,
                       stable_intervals=int(self.interval_count[idx]))
            out.append(row)
        return out


def parse_vary(spec: str) -> Axis:
    """``key=start:stop:num`` (``log:`` prefix on the range for a log-spaced axis)."""
    name, sep, rng = spec.partition("=")
    name = name.strip()
    if not sep:
        raise ConfigError(f"--vary {spec!r}: expected key=start:stop:num")
    if name not in key_fields():
        raise ConfigError(f"--vary {name!r}: unknown config key")
    if name not in PARAM_KEYS or name == "loop.period":
        allowed = ", ".join(k for k in PARAM_KEYS if k != "loop.period")
        raise ConfigError(f"--vary {name!r}: cannot be swept; allowed: {allowed}")
    log = rng.startswith("log:")
    parts = (rng[4:] if log else rng).split(":")
    try:
        start, stop, num = float(parts[0]), float(parts[1]), int(parts[2])
    except (ValueError, IndexError):
        raise ConfigError(f"--vary {spec!r}: range must be start:stop:num (num a whole number), "
                          "optionally log:start:stop:num") from None
    if num < 1 or len(parts) != 3:
        raise ConfigError(f"--vary {spec!r}: num must be >= 1")
    if log and (start <= 0 or stop <= 0):
        raise ConfigError(f"--vary {spec!r}: a log axis needs positive start and stop")
    values = np.geomspace(start, stop, num) if log else np.linspace(start, stop, num)
    _check_axis(name, values)
    return Axis(name, values)


def _check_axis(name: str, values: np.ndarray) -> None:
    from dobhil.config.schema import Check
    check = key_fields()[name].metadata["check"]
    if check is Check.POSITIVE and np.any(values <= 0):
        raise ConfigError(f"--vary {name}: every value must be > 0 (got min {values.min():g})")
    if check is Check.NONNEGATIVE and np.any(values < 0):
        raise ConfigError(f"--vary {name}: every value must be >= 0 (got min {values.min():g})")


def sweep(config: Config, axes: Sequence[Axis], *, sampled: bool, chunk: int = 4096,
          progress: Callable[[int], None] | None = None) -> SweepResult:
    """Stability, minimum phase and the stable C_f range over the grid of ``axes``."""
    if len({a.key for a in axes}) != len(axes):
        raise ConfigError("--vary: each key may be varied once")
    grids = np.meshgrid(*(a.values for a in axes), indexing="ij")
    flat = {a.key: g.reshape(-1) for a, g in zip(axes, grids)}
    total = grids[0].size
    results = [_chunk(config, {k: v[i:i + chunk] for k, v in flat.items()}, sampled, progress)
               for i in range(0, total, chunk)]
    shape = grids[0].shape
    stacked = [np.concatenate([r[j] for r in results]).reshape(shape) for j in range(4)]
    return SweepResult(tuple(axes), sampled, *stacked)


def _chunk(config: Config, values: dict[str, np.ndarray], sampled: bool,
           progress: Callable[[int], None] | None) -> tuple[np.ndarray, ...]:
    params = params_from_config(config, **{k.replace(".", "__"): v for k, v in values.items()})
    open_loop = loop(params, sampled=sampled, force_gain=0.0)
    a, b, c, _ = open_loop.siso("tau_per", "tau_int_hat")
    gm = gain_map(a, b, c, sampled=sampled)
    cf = params.value("force_gain")
    stable = is_stable(np.linalg.eigvals(a - cf[:, None, None] * (b @ c)), sampled)
    if progress:
        progress(cf.size)
    count = np.sum(~np.isnan(gm.interval_lo), axis=-1)
    return stable, gm.minimum_phase, gm.max_stable_gain, count
