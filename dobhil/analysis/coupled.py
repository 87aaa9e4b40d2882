"""Several axes coupled through their environment, analysed as one closed loop.

Each axis keeps its own controller -- the matrices of
:func:`~dobhil.synthesis.controller.sampled_controller`, the ones the runtime executes,
inside the single-axis loop of :func:`~dobhil.synthesis.loop.loop` -- and its own
command delay (``design.delay_samples`` whole periods plus ``design.input_delay``, or its
protocol's, :func:`~dobhil.drives.timing.effective_config`). What joins the axes is the
plant: a coupling (:class:`~dobhil.config.axes.Coupling`) between axes a and b pushes a with
``tau_c = K (q_b - q_a) + D (dq_b - dq_a)`` and b with ``-tau_c``, on top of each axis' own
environment ``K_env q + D_env dq``. The servos with their environments and the couplings
are one linear plant ``x_p' = A_p x_p + B_p u`` (``x_p = [q_1, dq_1, q_2, dq_2, ...]``),
and the loop the runtime closes samples it exactly: zero-order hold, each axis' command
arriving ``input_delay`` after the sample (:func:`sampled_coupled_plant`, the multi-input
form of :func:`~dobhil.synthesis.controller.discretize_delayed`).

The coupled loop's state is the single-axis loops' states side by side (``[x_p, xi, w]``
per axis, the layout of :mod:`dobhil.synthesis.loop`); only the plant rows differ, so with
no coupling the loop is block diagonal in the single-axis loops and every figure below is
each axis' own (tests/analysis/test_coupled.py checks that to 1e-12).

Stability along a direction of gains: scaling every axis' force gain by ``s``
(``C_f,i = s C_f,i^design``) gives ``A(s) = A0 - s M`` with ``M = sum_i C_f,i B_per,i
C_int^,i`` (rank <= number of axes). A pole of A(s) is on the unit circle (sampled) only
where ``A(s) (x) A(s) - I`` is singular (a pole pair with ``z1 z2 = 1``), and on the
imaginary axis (continuous) where ``A(s) (+) A(s)`` is (``s1 + s2 = 0``): a quadratic,
resp. linear, matrix pencil in ``s`` whose generalised eigenvalues contain every gain
where stability can change (Kronecker-product pencils; Fu & Barmish, "Maximal
unidirectional perturbation bounds for stability of polynomials and matrices", Systems &
Control Letters 11, 1988). Each candidate is refined by Brent's method on the spectral
margin; between consecutive crossings the verdict is constant and is read from
eigenvalues (:func:`stable_scales`). No grid of gains.

This module imports no python-control (a stability gate before a run can use it at the
cost of the eigenvalue problems); the step responses and the whole analysis are in
:mod:`dobhil.analysis.coupled_analysis`.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
import scipy.linalg

from dobhil.analysis.stability import STABILITY_TOL
from dobhil.config.axes import Axes, Coupling
from dobhil.config.schema import Config
from dobhil.drives.profile import DriveProfile
from dobhil.drives.timing import effective_config
from dobhil.synthesis.controller import discretize
from dobhil.synthesis.loop import INPUTS, OUTPUTS, LoopSS, loop
from dobhil.synthesis.models import plant_matrices
from dobhil.synthesis.numerics import balance_scaling
from dobhil.synthesis.params import Array, Discretization, Params, params_from_config

__all__ = ["AXIS_INPUTS", "AXIS_OUTPUTS", "MAX_SCALE", "AxisDesign", "CoupledLoop", "GainScales",
           "axis_designs", "coupled_groups", "coupled_loop", "coupled_plant", "sampled_coupled_plant",
           "spectral_margin", "stable_scales"]

#: per-axis inputs and outputs of the coupled loop (names of :mod:`dobhil.synthesis.loop`;
#: ``tau_int`` is the torque the axis feels from its environment and every coupling)
AXIS_INPUTS: tuple[str, ...] = ("tau_ref", "tau_per")
AXIS_OUTPUTS: tuple[str, ...] = ("tau_int_hat", "tau_int", "q", "u")


@dataclass(frozen=True)
class AxisDesign:
    """One axis as its loop runs: its name, the config on its drive, its parameters, and the
    note :func:`~dobhil.drives.timing.effective_config` gave ("" when nothing changed)."""

    name: str
    config: Config
    params: Params
    note: str = ""


def axis_designs(axes: Axes, profiles: Mapping[str, DriveProfile] | None = None) -> tuple[AxisDesign, ...]:
    """Every axis' design on its drive: its profile's command delay where the protocol fixes
    one (``profiles`` by axis name; an axis without one keeps its config's delay)."""
    out = []
    for axis in axes.axes:
        config, note = axis.config, ""
        if profiles is not None and axis.name in profiles:
            config, note = effective_config(axis.config, profiles[axis.name])
        out.append(AxisDesign(axis.name, config, params_from_config(config), note))
    return tuple(out)


def coupled_plant(designs: Sequence[AxisDesign],
                  couplings: Sequence[Coupling]) -> tuple[Array, Array, Array]:
    """The servos, their environments and the couplings as one continuous plant
    ``(A_p, B_p, C_int)``: ``x_p = [q_1, dq_1, ...]``, ``u = [u_1, ...]``, and ``C_int x_p``
    each axis' interaction torque (its environment's ``K_env q + D_env dq`` minus the
    couplings' push ``tau_c``). Each axis' own block is
    :func:`~dobhil.synthesis.models.plant_matrices`, the emulator's plant."""
    names = [d.name for d in designs]
    n = len(designs)
    a = np.zeros((2 * n, 2 * n))
    b = np.zeros((2 * n, n))
    c = np.zeros((n, 2 * n))
    for i, d in enumerate(designs):
        a_i, b_i, c_i = plant_matrices(*(d.params.value(k) for k in
                                         ("inertia", "viscous_friction", "stiffness", "damping")))
        a[2 * i:2 * i + 2, 2 * i:2 * i + 2] = a_i
        b[2 * i:2 * i + 2, i:i + 1] = b_i
        c[i:i + 1, 2 * i:2 * i + 2] = c_i
    for cp in couplings:
        ia, ib = names.index(cp.a), names.index(cp.b)
        for me, other in ((ia, ib), (ib, ia)):
            # reaction on ``me``: K (q_me - q_other) + D (dq_me - dq_other)
            row = np.zeros(2 * n)
            row[2 * me:2 * me + 2] += (cp.stiffness, cp.damping)
            row[2 * other:2 * other + 2] -= (cp.stiffness, cp.damping)
            c[me] += row
            a[2 * me + 1] -= row / float(designs[me].params.value("inertia"))
    return a, b, c


def sampled_coupled_plant(a: Array, b: Array, period: float,
                          input_delays: Sequence[float]) -> tuple[Array, Array, Array]:
    """(Phi, Gamma_new, Gamma_old) of ``x' = A x + B u`` sampled at ``period`` when input j
    switches from its previous command to the new one ``input_delays[j]`` after the sample::

        x[k+1] = Phi x[k] + Gamma_new u_new[k] + Gamma_old u_old[k]

    Exact: the period is cut at every input's switching time and each piece is a
    zero-order hold (:func:`~dobhil.synthesis.controller.discretize`). One input with
    delay tau gives :func:`~dobhil.synthesis.controller.discretize_delayed`'s matrices."""
    delays = np.asarray(input_delays, float)
    if np.any(delays < 0) or np.any(delays > period):
        raise ValueError(f"input delays must lie in [0, period]; got {list(delays)!r}")
    times = sorted({0.0, period, *map(float, delays)})
    n, m = a.shape[-1], b.shape[-1]
    phi, g_new, g_old = np.eye(n), np.zeros((n, m)), np.zeros((n, m))
    for t0, t1 in zip(times[:-1], times[1:]):
        p, g = discretize(a, b, t1 - t0, Discretization.ZOH)
        new = delays <= t0
        phi, g_new, g_old = p @ phi, p @ g_new + g * new, p @ g_old + g * ~new
    return phi, g_new, g_old


@dataclass(frozen=True)
class CoupledLoop:
    """The closed loop of every axis at its design's force gain.

    ``x[k+1] = A x[k] + B w`` (sampled; ``x' = A x + B w`` continuous), ``v = C x + D w``;
    inputs :data:`AXIS_INPUTS` per axis (``w = [tau_ref_1, tau_per_1, tau_ref_2, ...]``),
    outputs :data:`AXIS_OUTPUTS` per axis. ``b_per`` (n x axes) and ``c_hat`` (axes x n)
    are the columns of ``tau_per`` and the rows of ``tau_int^``: ``A(s) = A - (s - 1) M``,
    ``M = b_per diag(gains) c_hat``, is the loop with every force gain scaled by s."""

    names: tuple[str, ...]
    a: Array
    b: Array
    c: Array
    d: Array
    b_per: Array
    c_hat: Array
    gains: Array
    dt: float | None
    states: tuple[slice, ...] = field(repr=False)

    @property
    def sampled(self) -> bool:
        return self.dt is not None

    @property
    def order(self) -> int:
        return int(self.a.shape[-1])

    def input_index(self, axis: str, name: str) -> int:
        return self.names.index(axis) * len(AXIS_INPUTS) + AXIS_INPUTS.index(name)

    def output_index(self, axis: str, name: str) -> int:
        return self.names.index(axis) * len(AXIS_OUTPUTS) + AXIS_OUTPUTS.index(name)

    @property
    def m(self) -> Array:
        """``M`` of ``A(s) = A - (s - 1) M``."""
        return np.asarray(self.b_per @ (self.gains[:, None] * self.c_hat))

    def a_at(self, scale: float) -> Array:
        """The state matrix with every force gain scaled by ``scale`` (1: the design)."""
        return self.a - (scale - 1.0) * self.m

    def poles(self, scale: float = 1.0) -> np.ndarray:
        return np.asarray(np.linalg.eigvals(self.a_at(scale)), dtype=complex)


def coupled_loop(designs: Sequence[AxisDesign], couplings: Sequence[Coupling], *,
                 sampled: bool) -> CoupledLoop:
    """The coupled closed loop of ``designs`` (:func:`axis_designs`) and ``couplings``."""
    loops = [loop(d.params, sampled=sampled) for d in designs]
    sizes = [lp.a.shape[-1] for lp in loops]
    starts = np.concatenate([[0], np.cumsum(sizes)]).astype(int)
    n, k = int(starts[-1]), len(designs)
    states = tuple(slice(int(s), int(s) + z) for s, z in zip(starts, sizes))
    ins = [INPUTS.index(x) for x in AXIS_INPUTS]
    outs = [OUTPUTS.index(x) for x in AXIS_OUTPUTS]
    a = np.zeros((n, n))
    b = np.zeros((n, k * len(ins)))
    c = np.zeros((k * len(outs), n))
    d = np.zeros((k * len(outs), k * len(ins)))
    for i, (lp, st) in enumerate(zip(loops, states)):
        a[st, st] = lp.a
        b[st, i * len(ins):(i + 1) * len(ins)] = lp.b[:, ins]
        c[i * len(outs):(i + 1) * len(outs), st] = lp.c[outs]
        d[i * len(outs):(i + 1) * len(outs), i * len(ins):(i + 1) * len(ins)] = lp.d[np.ix_(outs, ins)]
    a_p, b_p, c_int = coupled_plant(designs, couplings)
    plant_rows = np.concatenate([np.arange(st.start, st.start + 2) for st in states])
    # each axis' tau_int row: its environment and the couplings, on the plant states
    for i in range(k):
        row = i * len(outs) + AXIS_OUTPUTS.index("tau_int")
        c[row] = 0.0
        c[row, plant_rows] = c_int[i]
    if sampled:
        _sampled_plant_rows(a, b, designs, loops, states, a_p, b_p)
    else:   # the single-axis loops hold each plant alone: add what the couplings change
        a[np.ix_(plant_rows, plant_rows)] += a_p - coupled_plant(designs, ())[0]
    b_per = b[:, [i * len(ins) + AXIS_INPUTS.index("tau_per") for i in range(k)]]
    c_hat = c[[i * len(outs) + AXIS_OUTPUTS.index("tau_int_hat") for i in range(k)]]
    gains = np.array([float(dd.params.value("force_gain")) for dd in designs])
    return CoupledLoop(names=tuple(dd.name for dd in designs), a=a, b=b, c=c, d=d,
                       b_per=b_per.copy(), c_hat=c_hat.copy(), gains=gains, dt=loops[0].dt,
                       states=states)


def _chain(design: AxisDesign) -> tuple[int, bool]:
    """(delay_samples, whether the previous command is still in transit at the sample)."""
    s = design.params.structure
    return s.delay_samples, s.input_delay > 0


def _sampled_plant_rows(a: Array, b: Array, designs: Sequence[AxisDesign], loops: Sequence[LoopSS],
                        states: Sequence[slice], a_p: Array, b_p: Array) -> None:
    """The plant rows of the sampled coupled loop (in place): ``x_p[k+1] = Phi x_p[k] +
    sum_j Gamma_new[:, j] u_j[k - d_j] + Gamma_old[:, j] u_j[k - d_j - 1]``, each command
    read where its axis' loop keeps it (the ``u`` output row at age 0, its delay chain after)."""
    period = float(loops[0].dt or 0.0)
    phi, g_new, g_old = sampled_coupled_plant(
        a_p, b_p, period, [float(d.params.structure.input_delay) for d in designs])
    n_in = len(AXIS_INPUTS)
    ins = [INPUTS.index(x) for x in AXIS_INPUTS]
    u_row = OUTPUTS.index("u")
    plant_rows = np.concatenate([np.arange(st.start, st.start + 2) for st in states])
    new_a = np.zeros((plant_rows.size, a.shape[1]))
    new_b = np.zeros((plant_rows.size, b.shape[1]))
    new_a[:, plant_rows] = phi
    for j, (design, lp, st) in enumerate(zip(designs, loops, states)):
        delay, late = _chain(design)
        chain_start = st.stop - delay - (1 if late else 0)     # u[k-1] is kept here
        for age, gamma in ((delay, g_new[:, j:j + 1]), (delay + 1, g_old[:, j:j + 1])):
            if age == delay + 1 and not late:
                continue
            if age == 0:
                new_a[:, st] += gamma @ lp.c[u_row:u_row + 1]
                new_b[:, j * n_in:(j + 1) * n_in] += gamma @ lp.d[u_row:u_row + 1, ins]
            else:
                new_a[:, chain_start + age - 1] += gamma[:, 0]
    a[plant_rows] = new_a
    b[plant_rows] = new_b


def spectral_margin(a: Array, sampled: bool) -> float:
    """How far outside the stability region the worst pole of ``a`` lies (negative:
    inside): ``max |z| - 1`` sampled, ``max Re(s) / max(1, max |s|)`` continuous -- the
    measure of :mod:`dobhil.analysis.stability`."""
    poles = np.linalg.eigvals(a)
    if sampled:
        return float(np.max(np.abs(poles)) - 1.0)
    return float(np.max(poles.real) / max(1.0, float(np.max(np.abs(poles)))))


@dataclass(frozen=True)
class GainScales:
    """Stability along a direction of force gains (by default the designs'): ``C_f,i = s direction_i``.

    ``intervals``: the stable ranges of s (``hi = inf``: unbounded); ``max_scale``: the
    largest s with every scale in (0, s) stable (inf: unbounded, 0: unstable for small
    gains); ``crossings``: every s where a pole crosses the stability boundary. Scales up to
    :data:`MAX_SCALE` are judged; stable up to there counts as unbounded."""

    direction: tuple[float, ...]
    crossings: tuple[float, ...]
    intervals: tuple[tuple[float, float], ...]
    max_scale: float
    method: str = ("crossing scales from the generalised eigenvalues of the Kronecker pencil "
                   "A(s) (x) A(s) - I (sampled) / A(s) (+) A(s) (continuous) on symmetric matrices, "
                   "refined by Brent's method on the spectral radius; verdicts from eigenvalues")

    def stable_at(self, scale: float) -> bool:
        return any(lo < scale < hi for lo, hi in self.intervals)

    def max_gains(self) -> tuple[float, ...]:
        """Each axis' force gain at :attr:`max_scale`."""
        return tuple(self.max_scale * g for g in self.direction)


def _symmetric_part(n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rows ``r1, r2`` (positions of ``e_i (x) e_j`` and ``e_j (x) e_i``) and weights of the
    orthonormal basis of symmetric vectors ``(e_i (x) e_j + e_j (x) e_i) / norm``, i <= j."""
    i, j = np.triu_indices(n)
    return i * n + j, j * n + i, np.where(i == j, 0.5, np.sqrt(0.5))


def _restricted(k: Array, basis: tuple[np.ndarray, np.ndarray, np.ndarray]) -> Array:
    """``Q^T K Q`` for the symmetric basis Q (:func:`_symmetric_part`), by indexing."""
    r1, r2, w = basis
    rows = k[r1] + k[r2]
    return np.asarray(w[:, None] * (rows[:, r1] + rows[:, r2]) * w[None, :])


def _candidates(a0: Array, u: Array, v: Array, sampled: bool) -> np.ndarray:
    """Real s > :data:`MIN_SCALE` where ``A0 - s M`` (``M = u v^T``) may have a pole on the
    stability boundary: the finite real generalised eigenvalues of the Kronecker pencil (a
    superset: pole pairs with ``z1 z2 = 1`` or ``s1 + s2 = 0`` off the boundary come too).

    Both products map symmetric ``n x n`` matrices (vectorised) to symmetric ones, and a
    pole pair on the boundary -- ``z, conj(z)`` or a real pole with itself -- has a symmetric
    eigenvector, so the pencil is restricted to that subspace (``n (n + 1) / 2``). The
    sampled pencil is quadratic, ``Q0 + s Q1 + s^2 (u (x) u)(v (x) v)^T``; its quadratic term
    has rank (axes)^2, so ``w = s (v (x) v)^T x`` linearises it with that many extra rows."""
    scale = balance_scaling(a0, u, v.T)     # same poles, entries of like size: sharper roots
    a0, u, v = a0 * scale[None, :] / scale[:, None], u / scale[:, None], v * scale[:, None]
    n = a0.shape[-1]
    basis = _symmetric_part(n)
    m = u @ v.T
    if sampled:   # (A0 - s M) (x) (A0 - s M) - I
        q0 = _restricted(np.asarray(np.kron(a0, a0), float), basis) - np.eye(basis[0].size)
        q1 = -_restricted(np.kron(a0, m) + np.kron(m, a0), basis)
        r1, r2, w = basis
        uu, vv = np.kron(u, u), np.kron(v, v)
        big_u = w[:, None] * (uu[r1] + uu[r2])      # Q^T (u (x) u)
        big_v = w[:, None] * (vv[r1] + vv[r2])      # Q^T (v (x) v)
        p, r = q0.shape[0], big_u.shape[1]
        left = np.block([[q0, np.zeros((p, r))], [np.zeros((r, p)), np.eye(r)]])
        right = -np.block([[q1, big_u], [-big_v.T, np.zeros((r, r))]])
    else:         # (A0 - s M) (+) (A0 - s M) = P0 - s P1
        eye = np.eye(n)
        left = _restricted(np.kron(a0, eye) + np.kron(eye, a0), basis)
        right = _restricted(np.kron(m, eye) + np.kron(eye, m), basis)
    with np.errstate(all="ignore"):
        s = scipy.linalg.eigvals(left, right, overwrite_a=True)
    ok = np.isfinite(s) & (np.abs(s.imag) <= 1e-6 * np.abs(s)) & (s.real > MIN_SCALE) & (s.real < MAX_SCALE)
    return np.unique(s.real[ok])


#: candidate crossings below this scale are the loop's pole at the boundary for zero gains
#: (the force loop's integrator: z = 1, s = 0) returned off by rounding, not crossings
MIN_SCALE = 1e-9
#: the largest scale judged: a loop stable up to a million times its design's gains is
#: reported unbounded (beyond, the eigenvalues of ``A0 - s M`` are rounding, not poles)
MAX_SCALE = 1e6
#: scales tested whatever the candidates (the design is 1)
_AROUND = (1e-6, 1e-3, 0.1, 1.0, 10.0, 1e3, 1e6)
#: where each interval between two candidate crossings is tested (fractions of the way)
_FRACTIONS = (1e-6, 1e-3, 0.02, 0.5, 0.98, 0.999, 1 - 1e-6)
#: multiples of the last candidate (or of the design's scale 1) tested beyond it
_TAIL = (1.0 + 1e-6, 1.001, 1.5, 10.0, 1e3, 1e6)


def stable_scales(lp: CoupledLoop, direction: Sequence[float] | None = None) -> GainScales:
    """The stable scales s along ``direction`` in the space of the axes' force gains
    (``C_f,i = s direction_i``; default: the designs' gains, so s = 1 is the design),
    exactly up to the refinement's tolerance (module docstring). Verdicts are eigenvalues
    of ``A(s)``."""
    gains = lp.gains if direction is None else np.asarray(direction, float)
    if gains.shape != lp.gains.shape or not np.all(np.isfinite(gains)) or not np.any(gains):
        raise ValueError(f"direction: expected {lp.gains.size} finite gains, not all 0; got {gains!r}")
    a0 = lp.a + lp.m                  # the loop with every force gain at 0
    m = lp.b_per @ (gains[:, None] * lp.c_hat)
    candidates = _candidates(a0, lp.b_per * gains[None, :], lp.c_hat.T, lp.sampled)
    edges = np.concatenate([[0.0], candidates])
    inner = [lo + (hi - lo) * f for lo, hi in zip(edges[:-1], edges[1:]) for f in _FRACTIONS]
    # beyond the last candidate, and scales around the design's (1) whatever the candidates
    tail = [float(edges[-1]) * f for f in _TAIL] + list(_AROUND)
    tests = np.unique(np.asarray(inner + tail, float))
    tests = tests[(tests > 0) & (tests <= MAX_SCALE)]
    margins = np.array([spectral_margin(a0 - s * m, lp.sampled) for s in tests])
    verdict = np.where(margins < -STABILITY_TOL, 1, np.where(margins > STABILITY_TOL, -1, 0))
    crossings = _crossings(a0, m, lp.sampled, tests, verdict)
    intervals = _stable_intervals(crossings, tests, verdict)
    max_scale = intervals[0][1] if intervals and intervals[0][0] == 0.0 else 0.0
    return GainScales(direction=tuple(float(g) for g in gains), crossings=tuple(crossings),
                      intervals=tuple(intervals), max_scale=max_scale)


def _crossings(a0: Array, m: Array, sampled: bool, tests: np.ndarray,
               verdict: np.ndarray) -> list[float]:
    """Each change of verdict between consecutive decided test scales, refined (Brent)."""
    decided = np.nonzero(verdict != 0)[0]
    out = []
    for i0, i1 in zip(decided[:-1], decided[1:]):
        if verdict[i0] == verdict[i1]:
            continue
        lo, hi = float(tests[i0]), float(tests[i1])
        # imported here: without crossings to refine (a gate's usual case) it is not needed
        import scipy.optimize

        def f(s: float) -> float:
            return spectral_margin(a0 - s * m, sampled)
        out.append(float(scipy.optimize.brentq(f, lo, hi, xtol=1e-15 * hi, rtol=1e-15)))
    return out


def _stable_intervals(crossings: Sequence[float], tests: np.ndarray,
                      verdict: np.ndarray) -> list[tuple[float, float]]:
    """The stable ranges between the crossings: a range is stable when its decided test
    scales are stable (a range whose tests are all undecided counts as not stable)."""
    edges = [0.0, *crossings, math.inf]
    out: list[tuple[float, float]] = []
    for lo, hi in zip(edges[:-1], edges[1:]):
        inside = verdict[(tests > lo) & (tests < hi)]
        if np.any(inside == 1) and not np.any(inside == -1):
            if out and out[-1][1] == lo:
                out[-1] = (out[-1][0], hi)
            else:
                out.append((lo, hi))
    return out


def coupled_groups(axes: Axes) -> tuple[tuple[str, ...], ...]:
    """The axes in groups joined by couplings (connected components, in the axes' order):
    a group of one is an independent axis, analysed alone."""
    group = {name: {name} for name in axes.names}
    for cp in axes.couplings:
        joined = group[cp.a] | group[cp.b]
        for name in joined:
            group[name] = joined
    seen: list[tuple[str, ...]] = []
    for name in axes.names:
        members = tuple(n for n in axes.names if n in group[name])
        if members not in seen:
            seen.append(members)
    return tuple(seen)
