"""Stability of the continuous force loop over a whole box of plant and environment values.

The closed loop's characteristic polynomial, scaled by the plant inertia J, is affine in
the environment stiffness K and damping D and in the plant inertia J and friction b: the
plant enters as ``J s^2 + (b + D) s + K`` and the controller (built from the design's
nominal and identified values, not the plant's) does not depend on them. A box of those
values is mapped onto a polytope of polynomials of one degree (the leading coefficient is
J > 0). The Edge Theorem (Bartlett, Hollot & Huang, "Root locations of an entire polytope
of polynomials: it suffices to check the edges", Math. Control Signals Systems 1:61-71,
1988) says that such a polytope is Hurwitz stable if and only if its exposed edges are;
every exposed edge of the image of a box is covered by the images of the box's edges, so
checking the ``n 2^(n-1)`` edges of the box decides the whole box.

Along an edge one value moves and the loop matrix moves by a rank-one term (K, D, b enter
one entry of the plant row, 1/J multiplies that row): ``A(t) = A0 + t (A1 - A0)``, t in
[0, 1] (for J, t is affine in 1/J). Its stable range of t is the exact gain map of
:func:`~dobhil.analysis.stability.gain_map` -- the same computation that gives the stable
intervals of C_f. Both facts are checked on the matrices at run time (the rank and the
affinity), not assumed. See docs/certify.md.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from enum import IntEnum

import numpy as np

from dobhil.analysis.stability import gain_map, is_stable
from dobhil.config import key_fields
from dobhil.config.schema import Config, check_maximum, check_minimum
from dobhil.errors import AnalysisError, ConfigError
from dobhil.synthesis.loop import loop
from dobhil.synthesis.params import Array, Params, params_from_config

#: the keys a certificate treats: those the closed loop's polynomial is affine in
CERTIFY_KEYS: tuple[str, ...] = ("environment.stiffness", "environment.damping",
                                 "plant.inertia", "plant.viscous_friction")

#: the key whose affine coordinate is its reciprocal (1/J multiplies the plant's row)
RECIPROCAL_KEYS = frozenset({"plant.inertia"})

#: a key must not go below this (J > 0 keeps the polynomial's degree; K, D, b >= 0)
LOWER_LIMITS = {"environment.stiffness": 0.0, "environment.damping": 0.0,
                "plant.inertia": 0.0, "plant.viscous_friction": 0.0}

#: relative tolerance of the run-time checks (rank one, affine along the edge)
STRUCTURE_RTOL = 1e-8

#: points per edge where the C_f interval is evaluated before its minimum is refined
GAIN_SAMPLES = 33


class Verdict(IntEnum):
    CERTIFIED = 0
    REFUTED = 1
    UNDECIDED = 2

    @property
    def word(self) -> str:
        return self.name.lower()


@dataclass(frozen=True)
class Box:
    """Each key's closed interval [lo, hi] (lo < hi)."""

    keys: tuple[str, ...]
    lo: tuple[float, ...]
    hi: tuple[float, ...]

    def vertices(self) -> list[dict[str, float]]:
        return [dict(zip(self.keys, corner)) for corner in itertools.product(*zip(self.lo, self.hi))]

    def centre(self) -> dict[str, float]:
        return {k: 0.5 * (a + b) for k, a, b in zip(self.keys, self.lo, self.hi)}

    def text(self) -> str:
        return ", ".join(f"{k} {a:g}..{b:g}" for k, a, b in zip(self.keys, self.lo, self.hi))


def parse_range(spec: str) -> tuple[str, float, float]:
    """``KEY=LO:HI`` with KEY one of :data:`CERTIFY_KEYS` and LO < HI (ConfigError otherwise)."""
    key, sep, text = spec.partition("=")
    key = key.strip()
    if key not in CERTIFY_KEYS:
        raise ConfigError(f"--range {spec!r}: the certificate treats only {', '.join(CERTIFY_KEYS)} "
                          "(the keys the loop's polynomial is affine in)")
    lo_text, colon, hi_text = text.partition(":")
    try:
        lo, hi = float(lo_text), float(hi_text)
    except ValueError:
        lo = hi = math.nan
    if not sep or not colon or not (math.isfinite(lo) and math.isfinite(hi)):
        raise ConfigError(f"--range {spec!r}: expected {key}=LO:HI with two finite numbers")
    if not lo < hi:
        raise ConfigError(f"--range {spec!r}: expected LO < HI")
    if key in RECIPROCAL_KEYS and lo <= 0.0:
        raise ConfigError(f"--range {spec!r}: {key} must be > 0 (it is the polynomial's leading "
                          "coefficient: the edge theorem needs one degree over the box)")
    if lo < LOWER_LIMITS[key]:
        raise ConfigError(f"--range {spec!r}: {key} must be >= 0")
    # the config's own ceiling and floor on the key, as --set has them: past them the
    # polynomial's coefficients overflow and no answer could be trusted
    meta = key_fields()[key].metadata
    problem = check_maximum(f"--range {key}", hi, meta) or check_minimum(f"--range {key}", lo, meta)
    if problem is not None:
        raise ConfigError(problem)
    return key, lo, hi


def box_from_specs(specs: Sequence[str]) -> Box:
    parsed = [parse_range(s) for s in specs]
    keys = [k for k, _, _ in parsed]
    for k in keys:
        if keys.count(k) > 1:
            raise ConfigError(f"--range {k}: given more than once; give each key once")
    if not parsed:
        raise ConfigError(f"--range: give at least one of {', '.join(CERTIFY_KEYS)}")
    return Box(tuple(keys), tuple(lo for _, lo, _ in parsed), tuple(hi for _, _, hi in parsed))


def params_at(config: Config, points: Mapping[str, Array | float]) -> Params:
    """The design's Params with the box keys set to ``points`` (arrays broadcast)."""
    return params_from_config(config, **{k.replace(".", "__"): np.asarray(v, float)
                                         for k, v in points.items()})


def closed_loop(config: Config, points: Mapping[str, Array | float], *, sampled: bool) -> Array:
    """The loop's state matrix at the design's C_f (batched over ``points``): the one
    assembled by :func:`dobhil.synthesis.loop.loop`, which the runtime's matrices come from."""
    with np.errstate(all="ignore"):
        return loop(params_at(config, points), sampled=sampled).a


@dataclass(frozen=True)
class Edge:
    """One edge of the box: ``key`` moves from lo to hi, the others fixed at ``fixed``."""

    key: str
    lo: float
    hi: float
    fixed: Mapping[str, float]
    order: tuple[str, ...] = ()    # the box's keys, the order points are given in

    def value(self, t: float | Array) -> Array:
        """The key's value at the affine coordinate t in [0, 1]."""
        t = np.asarray(t, float)
        if self.key in RECIPROCAL_KEYS:
            return np.asarray(1.0 / ((1.0 - t) / self.lo + t / self.hi))
        return np.asarray(self.lo + t * (self.hi - self.lo))

    def point(self, t: float) -> dict[str, float]:
        values = {**self.fixed, self.key: float(self.value(t))}
        return {k: values[k] for k in self.order or values}


def edges(box: Box) -> list[Edge]:
    out = []
    for i, key in enumerate(box.keys):
        others = [j for j in range(len(box.keys)) if j != i]
        for corner in itertools.product(*((box.lo[j], box.hi[j]) for j in others)):
            out.append(Edge(key, box.lo[i], box.hi[i],
                            {box.keys[j]: v for j, v in zip(others, corner)}, box.keys))
    return out


@dataclass(frozen=True)
class EdgeAnswer:
    edge: Edge
    stable: bool
    crossing: float | None   # t where the edge leaves stability (None: stable, or no stable end)
    witness: float | None    # t of an unstable point (None when stable)


@dataclass(frozen=True)
class ContinuousCertificate:
    verdict: Verdict
    box: Box
    edges: tuple[EdgeAnswer, ...]
    point: Mapping[str, float] | None = None          # the refuting point
    spectral_abscissa: float | None = None            # max Re(s) there [1/s]
    boundaries: tuple[Mapping[str, float], ...] = ()  # where the unstable edges leave stability
    gain_margin: GainMarginOverBox | None = None


@dataclass(frozen=True)
class GainMarginOverBox:
    """How far C_f may be scaled up (``up``) or down (``down``) and the loop stay stable at
    every point of the box (factors; inf: unbounded), and where each is smallest."""

    up: float
    down: float
    up_at: Mapping[str, float] = field(default_factory=dict)
    down_at: Mapping[str, float] = field(default_factory=dict)

    @property
    def db(self) -> float:
        return 20.0 * math.log10(min(self.up, self.down))

    @property
    def worst_at(self) -> Mapping[str, float]:
        return self.up_at if self.up <= self.down else self.down_at


def check_edge_structure(a0: Array, a1: Array, a_mid: Array, edge: Edge) -> tuple[Array, Array]:
    """``A1 - A0 = u v^T`` (rank one) and ``A(t=1/2) = (A0 + A1) / 2`` (affine), or an
    AnalysisError: the facts the edge theorem rests on, checked on the loop's matrices."""
    delta = a1 - a0
    scale = max(float(np.abs(a0).max()), float(np.abs(a1).max()), 1e-300)
    if np.abs(a_mid - 0.5 * (a0 + a1)).max() > STRUCTURE_RTOL * scale:
        raise AnalysisError(f"{edge.key}: the loop matrix is not affine along the edge; the edge "
                            "theorem does not apply to this design")
    u, s, vt = np.linalg.svd(delta)
    if s.size > 1 and s[1] > STRUCTURE_RTOL * max(s[0], 1e-300):
        raise AnalysisError(f"{edge.key}: the loop matrix moves by more than a rank-one term along "
                            "the edge; the exact edge check does not apply")
    return u[:, :1] * s[0], vt[:1, :]


def answer_edge(config: Config, edge: Edge) -> EdgeAnswer:
    """Stable for every t in [0, 1]; or the t where it leaves stability (from a stable end;
    None when both ends are unstable) and an unstable t."""
    a0, a_mid, a1 = closed_loop(config, _edge_points(edge, np.array([0.0, 0.5, 1.0])), sampled=False)
    u, v = check_edge_structure(a0, a1, a_mid, edge)
    if not _hurwitz(a0):
        # the boundary seen from the other end: A1 - t' u v^T, t = 1 - t'
        back = _first_crossing(a1, u, v, -1.0) if _hurwitz(a1) else None
        return EdgeAnswer(edge, False, None if back is None else 1.0 - back[0], 0.0)
    t_cross, t_end = _first_crossing(a0, u, v, 1.0)
    if t_cross > 1.0:
        return EdgeAnswer(edge, True, None, None)
    return EdgeAnswer(edge, False, t_cross, _unstable_t(a0, u @ v, t_cross, min(t_end, 1.0)))


def _first_crossing(a: Array, u: Array, v: Array, sign: float) -> tuple[float, float]:
    """The first t > 0 where ``A + sign t u v^T`` (A stable) reaches the axis, exactly (the
    gain map of ``A - t B C`` with ``B = -sign u``, ``C = v``), and the next crossing (inf:
    none)."""
    gm = gain_map(a[None], -sign * u[None], v[None], sampled=False)
    t_cross = float(gm.max_stable_gain[0])
    later = [float(c) for c in gm.crossings[0] if np.isfinite(c) and c > t_cross]
    return t_cross, min(later, default=math.inf)


def _edge_points(edge: Edge, t: Array) -> dict[str, Array]:
    points: dict[str, Array] = {k: np.full(t.shape, v) for k, v in edge.fixed.items()}
    points[edge.key] = edge.value(t)
    return points


def _hurwitz(a: Array) -> bool:
    return bool(is_stable(np.asarray(np.linalg.eigvals(a), dtype=complex)[None], False)[0])


def _unstable_t(a0: Array, delta: Array, t_cross: float, t_end: float) -> float:
    """A t just past the crossing where the eigenvalues themselves show instability."""
    for frac in (0.5, 0.1, 0.01, 0.9, 1.0):
        t = t_cross + frac * (t_end - t_cross)
        if np.max(np.linalg.eigvals(a0 + t * delta).real) > 0.0:
            return t
    return t_end


def certify_continuous(config: Config, box: Box, *, gain_margin: bool = True) -> ContinuousCertificate:
    """Certified (every edge stable) or refuted at a point where an eigenvalue of the
    loop has Re > 0; with the gain margin over the box when certified. An edge not shown
    stable whose most unstable point has no eigenvalue right of the axis (a pole within the
    tolerance of :func:`~dobhil.analysis.stability.is_stable` left of it: the position's, at
    s = -K_env / D_env, of a box from K_env 1e-5) is undecided there: no refutation."""
    answers = tuple(answer_edge(config, e) for e in edges(box))
    failed = [a for a in answers if not a.stable]
    if failed:
        worst, abscissa = _worst_witness(config, failed)
        bounds = tuple(a.edge.point(a.crossing) for a in failed if a.crossing is not None)
        verdict = Verdict.REFUTED if abscissa >= 0 else Verdict.UNDECIDED
        return ContinuousCertificate(verdict, box, answers, worst.edge.point(_t(worst.witness)),
                                     abscissa, bounds)
    margin = gain_margin_over_box(config, box) if gain_margin else None
    return ContinuousCertificate(Verdict.CERTIFIED, box, answers, gain_margin=margin)


def _t(t: float | None) -> float:
    return 0.0 if t is None else t


def _worst_witness(config: Config, failed: Sequence[EdgeAnswer]) -> tuple[EdgeAnswer, float]:
    """The failed edge whose unstable point is the most unstable (largest max Re)."""
    abscissae = [spectral_abscissa(config, a.edge.point(_t(a.witness))) for a in failed]
    i = int(np.argmax(abscissae))
    return failed[i], abscissae[i]


def spectral_abscissa(config: Config, point: Mapping[str, float]) -> float:
    """max Re of the continuous loop's eigenvalues at ``point`` (> 0: unstable)."""
    return float(np.max(np.linalg.eigvals(closed_loop(config, point, sampled=False)).real))


def gain_margin_over_box(config: Config, box: Box) -> GainMarginOverBox:
    """The smallest up and down C_f factors over the box. At a fixed gain the box is stable
    iff its edges are (the edge theorem), so the first gain above (below) C_f at which some
    point loses stability is met on an edge: each edge's C_f interval is evaluated at
    :data:`GAIN_SAMPLES` points and its worst end refined by a bounded 1-D search."""
    cf = float(config.design.force_gain)
    ups, downs = [], []
    for e in edges(box):
        ups.append(_edge_minimum(config, e, cf, 0))
        downs.append(_edge_minimum(config, e, cf, 1))
    up, down = min(ups, key=lambda r: r[0]), min(downs, key=lambda r: r[0])
    return GainMarginOverBox(up[0], down[0], up[1], down[1])


def _edge_minimum(config: Config, edge: Edge, cf: float, side: int) -> tuple[float, dict[str, float]]:
    """The smallest up (side 0) or down (side 1) factor along the edge: the best of
    :data:`GAIN_SAMPLES` points, polished by a bounded Brent search between its neighbours
    (the interval's end moves smoothly with t)."""
    import scipy.optimize
    t = np.linspace(0.0, 1.0, GAIN_SAMPLES)
    values = _factors(config, edge, t, cf)[side]
    i = int(np.argmin(values))
    best_t, best = float(t[i]), float(values[i])
    if math.isfinite(best):
        res = scipy.optimize.minimize_scalar(
            lambda x: float(_factors(config, edge, np.array([x]), cf)[side][0]),
            bounds=(float(t[max(i - 1, 0)]), float(t[min(i + 1, t.size - 1)])), method="bounded",
            options={"xatol": 1e-9})
        if res.success and float(res.fun) < best:
            best_t, best = float(res.x), float(res.fun)
    return best, edge.point(best_t) if math.isfinite(best) else {}


def _factors(config: Config, edge: Edge, t: Array, cf: float) -> tuple[Array, Array]:
    """Up and down factors of C_f at the edge's points t (the stable interval holding C_f)."""
    with np.errstate(all="ignore"):
        a, b, c, _ = loop(params_at(config, _edge_points(edge, t)), sampled=False,
                          force_gain=0.0).siso("tau_per", "tau_int_hat")
    gm = gain_map(a, b, c, sampled=False)
    lo, hi = gm.interval_lo, gm.interval_hi
    with np.errstate(invalid="ignore"):
        holds = (lo < cf) & (cf < hi)
        up = np.where(holds, hi / cf, np.nan)
        down = np.where(holds, np.where(lo > 0, cf / np.where(lo > 0, lo, 1.0), np.inf), np.nan)
    return np.nanmin(np.where(holds, up, np.inf), axis=-1), np.nanmin(np.where(holds, down, np.inf), axis=-1)


__all__ = ["CERTIFY_KEYS", "Box", "ContinuousCertificate", "Edge", "EdgeAnswer", "GainMarginOverBox",
           "Verdict", "answer_edge", "box_from_specs", "certify_continuous", "closed_loop", "edges",
           "gain_margin_over_box", "params_at", "parse_range", "spectral_abscissa"]
