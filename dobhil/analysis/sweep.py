"""Stability over a grid of designs and environments, vectorised.

The whole grid is one batch through the synthesis (:mod:`dobhil.synthesis`) and
the exact gain map (:mod:`dobhil.analysis.stability`); the only Python loops run
over matrix dimensions and chunks of the grid, never over grid points.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import partial

import numpy as np

from dobhil.analysis.stability import drifts, gain_map, is_stable
from dobhil.config.schema import Config, key_fields
from dobhil.errors import ConfigError
from dobhil.realtime import one_blas_thread
from dobhil.synthesis.loop import loop
from dobhil.synthesis.params import PARAM_KEYS, first_unused, params_from_config


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
    #: inf when unbounded, NaN where the point was not answered, 0 where none is (and where drifting)
    max_stable_gain: np.ndarray
    interval_count: np.ndarray      # number of stable C_f intervals (>1: conditionally stable)
    #: K_env = 0, or unstable at C_f only by the position's pole at z = 1 / s = 0 (K_env so
    #: small that this pole is within the analysis' resolution): no C_f is stable there
    drifting: np.ndarray

    @property
    def shape(self) -> tuple[int, ...]:
        return tuple(a.values.size for a in self.axes)

    @property
    def unanswered(self) -> int:
        return int(np.isnan(self.max_stable_gain).sum())

    def rows(self) -> list[dict[str, float | bool | None]]:
        out = []
        for idx in itertools.product(*(range(n) for n in self.shape)):
            row: dict[str, float | bool | None] = {a.key: float(a.values[i]) for a, i in zip(self.axes, idx)}
            k = float(self.max_stable_gain[idx])
            answered = not np.isnan(k)
            row.update(stable=bool(self.stable[idx]) if answered else None,
                       minimum_phase=bool(self.minimum_phase[idx]) if answered else None,
                       max_stable_force_gain=None if np.isinf(k) or not answered else k,
                       stable_intervals=int(self.interval_count[idx]) if answered else None,
                       position_drifts=bool(self.drifting[idx]) if answered else None)
            out.append(row)
        return out


def parse_vary(spec: str) -> Axis:
    """``key=start:stop:num`` (``log:`` prefix on the range for a log-spaced axis)."""
    name, sep, rng = spec.partition("=")
    name = name.strip()
    if not sep or not name:
        raise ConfigError(f"--vary {spec!r}: {'no KEY before =' if sep else 'no ='}; {vary_forms()}")
    if name not in key_fields():
        raise ConfigError(f"--vary {name!r}: unknown config key")
    if name not in PARAM_KEYS or name == "loop.period":
        allowed = ", ".join(k for k in PARAM_KEYS if k != "loop.period")
        raise ConfigError(f"--vary {name!r}: cannot be swept; allowed: {allowed}")
    log, start, stop, num = _vary_range(spec, rng)
    if log and (start <= 0 or stop <= 0):
        raise ConfigError(f"--vary {spec!r}: a log axis needs positive start and stop")
    values = np.geomspace(start, stop, num) if log else np.linspace(start, stop, num)
    _check_axis(name, values)
    return Axis(name, values)


def vary_forms() -> str:
    """The forms ``--vary`` takes, for a refusal (the metavar and help of ``dobhil sweep --vary``)."""
    return (f"allowed: KEY=START:STOP:NUM or KEY=log:START:STOP:NUM (START and STOP finite numbers, "
            f"NUM a whole number of values from 1 to {MAX_AXIS_POINTS})")


def _vary_range(spec: str, rng: str) -> tuple[bool, float, float, int]:
    """``(log, start, stop, num)`` of the range after ``=``; each refusal names the part at
    fault (their count, an empty one, one that is no number) and the forms allowed."""
    def refuse(problem: str) -> ConfigError:
        return ConfigError(f"--vary {spec!r}: {problem}; {vary_forms()}")
    log = rng.startswith("log:")
    body = rng[4:] if log else rng
    if not body.strip():
        raise refuse("no range after " + ("log:" if log else "="))
    parts = body.split(":")
    if len(parts) != 3:
        raise refuse(f"the range has {len(parts)} part{'s' if len(parts) != 1 else ''}, not 3")
    for label, text in zip(("START", "STOP", "NUM"), parts):
        if not text.strip():
            raise refuse(f"{label} is empty")
    numbers: list[float] = []
    for label, text in zip(("START", "STOP"), parts):
        try:
            numbers.append(float(text))
        except ValueError:
            raise refuse(f"{label} {text.strip()!r} is not a number") from None
    start, stop = numbers
    if not (np.isfinite(start) and np.isfinite(stop)):
        raise refuse("START and STOP must be finite numbers")
    try:
        num = int(parts[2])
    except ValueError:
        raise refuse(f"NUM {parts[2].strip()!r} is not a whole number") from None
    if num < 1:
        raise refuse(f"NUM must be at least 1 (got {num})")
    if num > MAX_AXIS_POINTS:
        raise refuse(f"NUM must be at most {MAX_AXIS_POINTS} values per axis (got {num})")
    return log, start, stop, num


#: largest number of values on one axis, and of points in a grid
MAX_AXIS_POINTS = 100_000
MAX_GRID_POINTS = 5_000_000


def _check_axis(name: str, values: np.ndarray) -> None:
    from dobhil.config.schema import span_problem
    problem = span_problem(f"--vary {name}", float(values.min()), float(values.max()), key_fields()[name].metadata)
    if problem is not None:
        raise ConfigError(problem)


#: a chunk of the grid: each swept key's values at the chunk's points
Chunk = dict[str, np.ndarray]
#: a chunk's answer: stable, minimum phase, max stable gain, interval count, drifting (one value per point)
ChunkAnswer = tuple[np.ndarray, ...]
#: runs ``fn`` on every chunk, the answers in the order of the chunks, ``done(1)`` after each
#: (e.g. as Dask tasks: the CLI's ``--scheduler``); this module knows no scheduler
ChunkMap = Callable[[Callable[[Chunk], ChunkAnswer], Sequence[Chunk], Callable[[int], None]], list[ChunkAnswer]]


def sweep(config: Config, axes: Sequence[Axis], *, sampled: bool, chunk: int = 4096,
          progress: Callable[[int], None] | None = None, map_chunks: ChunkMap | None = None) -> SweepResult:
    """Stability, minimum phase and the stable C_f range over the grid of ``axes``, in chunks
    of ``chunk`` points, each answered by :func:`sweep_chunk` -- here, one after the other,
    or through ``map_chunks`` (the same chunks, the same function: the same numbers).
    ``progress(n)``: n more points answered."""
    if len({a.key for a in axes}) != len(axes):
        raise ConfigError("--vary: each key may be varied once")
    _check_used(config, axes)
    total = int(np.prod([a.values.size for a in axes]))
    if total > MAX_GRID_POINTS:
        raise ConfigError(f"--vary: the grid has {total} points; at most {MAX_GRID_POINTS}")
    grids = np.meshgrid(*(a.values for a in axes), indexing="ij")
    flat = {a.key: g.reshape(-1) for a, g in zip(axes, grids)}
    total = grids[0].size
    chunks = [{k: v[i:i + chunk] for k, v in flat.items()} for i in range(0, total, chunk)]
    results = (map_chunks or _one_by_one)(partial(sweep_chunk, config, sampled), chunks,
                                          _points_done(progress, chunk, total))
    shape = grids[0].shape
    stacked = [np.concatenate([r[j] for r in results]).reshape(shape) for j in range(5)]
    return SweepResult(tuple(axes), sampled, *stacked)


def _check_used(config: Config, axes: Sequence[Axis]) -> None:
    """A swept key the loop does not read with this config (:func:`unused_keys`) would give
    the same row at every value, which reads as a key that does not matter; it is refused,
    naming the choice that would make it matter."""
    u = first_unused(config, (a.key for a in axes))
    if u is not None:
        raise ConfigError(f"--vary {u.key}: the loop does not use it ({u.choice} is {u.value}, not {u.wanted}), "
                          f"so every value would give the same row; --set {u.choice}={u.wanted} to sweep it")


def _one_by_one(fn: Callable[[Chunk], ChunkAnswer], chunks: Sequence[Chunk],
                done: Callable[[int], None]) -> list[ChunkAnswer]:
    answers = []
    for c in chunks:
        answers.append(fn(c))
        done(1)
    return answers


def _points_done(progress: Callable[[int], None] | None, chunk: int, total: int) -> Callable[[int], None]:
    """``done(n)`` (n more chunks answered) as ``progress`` in points. Chunks may finish in
    any order and only the last is short, so k chunks count min(k * chunk, total) points:
    exact one by one, and exact at the end in any order."""
    finished = [0]

    def done(n: int) -> None:
        before = min(finished[0] * chunk, total)
        finished[0] += n
        if progress:
            progress(min(finished[0] * chunk, total) - before)
    return done


def sweep_chunk(config: Config, sampled: bool, values: Chunk) -> ChunkAnswer:
    """One chunk of the grid (pure data in and out: a Dask worker runs it too). A point
    whose matrices overflow, or that numpy cannot decompose, is answered as unknown (NaN
    gain, not stable) without stopping the rest.

    BLAS on one thread: the work is thousands of 5 x 5 to 8 x 8 matrices, for which a
    multithreaded OpenBLAS wakes its pool every time -- one 4096-point chunk took 2.1 s with
    the default pool and 1.0 s on one thread on this busy 2-core machine (a 40,000-point
    sweep: 228-280 s against 18-20 s)."""
    params = params_from_config(config, **{k.replace(".", "__"): v for k, v in values.items()})
    with one_blas_thread(), np.errstate(all="ignore"):
        open_loop = loop(params, sampled=sampled, force_gain=0.0)
        a, b, c, _ = open_loop.siso("tau_per", "tau_int_hat")
        cf = params.value("force_gain")
        ok = np.all(np.isfinite(a), axis=(-2, -1)) & np.all(np.isfinite(b * c.swapaxes(-1, -2)),
                                                             axis=(-2, -1))
        stable, minimum_phase, kmax, count, drifting = _answer(a, b, c, cf, ok, sampled)
    # K_env = 0: the position's pole stays at z = 1 / s = 0 at every C_f (as analyze says, even
    # at C_f = 0); the gain map's intervals there are decided by which side of the boundary
    # rounding puts that pole (the estimated velocity's demo read 5.09 or 0 by the damping),
    # so a drifting point has no stable C_f: 0, no interval
    drifting = drifting | (params.value("stiffness") == 0.0)
    answered = ~np.isnan(kmax)
    kmax = np.where(drifting & answered, 0.0, kmax)
    count = np.where(drifting, 0, count)
    return stable, minimum_phase, kmax, count, drifting & answered


def _answer(a: np.ndarray, b: np.ndarray, c: np.ndarray, cf: np.ndarray, ok: np.ndarray,
            sampled: bool) -> tuple[np.ndarray, ...]:
    n = cf.size
    stable = np.zeros(n, bool)
    minimum_phase = np.zeros(n, bool)
    kmax = np.full(n, np.nan)
    count = np.zeros(n, int)
    drifting = np.zeros(n, bool)
    idx = np.nonzero(ok)[0]
    try:
        parts = [(idx, _points(a[idx], b[idx], c[idx], cf[idx], sampled))] if idx.size else []
    except (np.linalg.LinAlgError, ValueError):   # one bad point: answer the rest one by one
        parts = []
        for i in idx:
            try:
                parts.append((np.array([i]), _points(a[i:i + 1], b[i:i + 1], c[i:i + 1],
                                                     cf[i:i + 1], sampled)))
            except (np.linalg.LinAlgError, ValueError):
                continue
    for where, (st, mp, km, cnt, dr) in parts:
        stable[where], minimum_phase[where], kmax[where], count[where], drifting[where] = st, mp, km, cnt, dr
    return stable, minimum_phase, kmax, count, drifting


def _points(a: np.ndarray, b: np.ndarray, c: np.ndarray, cf: np.ndarray,
            sampled: bool) -> tuple[np.ndarray, ...]:
    gm = gain_map(a, b, c, sampled=sampled)
    poles = np.asarray(np.linalg.eigvals(a - cf[:, None, None] * (b @ c)), dtype=complex)
    stable = is_stable(poles, sampled)
    count = np.sum(~np.isnan(gm.interval_lo), axis=-1)
    # at C_f = 0 the loop is the open loop, whose integrator is on the boundary: no drift
    return stable, gm.minimum_phase, gm.max_stable_gain, count, ~stable & (cf > 0) & drifts(poles, sampled)
