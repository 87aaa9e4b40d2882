"""The model the identification fits: the emulator's plant itself, driven as the emulator
drives it.

No second discretisation: a simulation builds a :class:`dobhil.emulator.plant.Plant` (whose
ZOH matrices come from :func:`dobhil.synthesis.models.servo_matrices` /
:func:`~dobhil.synthesis.models.plant_matrices` and
:func:`dobhil.synthesis.controller.discretize`, Coulomb friction sub-stepped with its
Karnopp band) and steps it the way the emulator's lockstep drive applies a command
``latency`` after the sample it was computed from: with the delay ``d T + tau``
(``d = design.delay_samples`` whole periods, ``0 <= tau < T`` = ``design.input_delay``)
the interval ``[t_k, t_k+1]`` holds ``u[k-d-1]`` over ``[t_k, t_k + tau]`` and ``u[k-d]``
over the rest -- the sampled analysis' ``x[k+1] = Phi x[k] + Gamma0 u[k-d] +
Gamma1 u[k-d-1]`` (:func:`dobhil.synthesis.controller.discretize_delayed`) whenever the
plant is linear.

Fast: stepping the Plant in Python with Coulomb friction (ten sub-steps per call, two calls
per sample with a fractional delay) costs 0.2-0.45 s CPU per 60 s record (measured), and a
fit simulates its records hundreds of times; :func:`simulate_torque`
runs the spans where the Plant is linear (one contact mode, one friction sign, or stuck)
as vectorised recursions with the Plant's own matrices and steps the Plant only at the
samples where it decides something (:class:`_FastSimulation`), with the same numbers
(:func:`_simulate_stepping`, the reference, is kept and the equality tested) -- but for a
friction decision that lands exactly on its threshold (a velocity on the Karnopp band's
edge), which rounding decides and the superposition may decide the other way, one friction
sub-step apart (tests/identify/test_model.py pins such a case). With Coulomb
friction it runs the Plant's own sub-step function
(:func:`dobhil.emulator.plant.coulomb_substeps`) compiled over the whole record instead:
a pressed servo reverses every few samples, too many events for the span method.

The torque reaching the plant is ``torque_gain * u`` (the sent torque scaled). Commands
before the first sample are 0 and every simulation starts at its initial position and
velocity (:meth:`Plant.set_state`; a segment need not start at rest).
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.signal import lfilter

from dobhil.emulator.plant import Plant, Propagator, coulomb_substeps
from dobhil.realtime import one_blas_thread

__all__ = ["ModelValues", "simulate_torque", "split_delay"]

#: a delay fraction below this is no fraction (the emulator rounds its pieces to 1e-12 s too)
_TINY = 1e-12


def split_delay(delay: float, period: float) -> tuple[int, float]:
    """``(whole, fraction)`` of ``delay`` as ``design.delay_samples`` and
    ``design.input_delay`` model it: ``delay = whole * period + fraction``, ``0 <= fraction
    < period`` (a fraction within 1e-12 s of a whole period counts as the next whole one)."""
    if not delay >= 0.0:
        raise ValueError(f"delay: expected >= 0 s, got {delay}")
    whole = math.floor(delay / period)
    fraction = delay - whole * period
    if fraction >= period - _TINY:
        whole, fraction = whole + 1, 0.0
    return whole, max(fraction, 0.0)


@dataclass(frozen=True)
class ModelValues:
    """One set of plant parameters (SI units). With ``stiffness = damping = 0`` and the
    contact position out of reach the plant is the free servo."""

    inertia: float
    viscous_friction: float = 0.0
    coulomb_friction: float = 0.0
    torque_gain: float = 1.0
    contact_position: float = math.inf
    stiffness: float = 0.0
    damping: float = 0.0
    delay: float = 0.0


_LOCAL = threading.local()

#: span lengths (samples) of the fast simulation: the first and the smallest after an event
#: (twice what the last span kept), the largest (doubling while whole spans hold)
_MIN_WINDOW = 64
_MAX_WINDOW = 16384
#: a span holding fewer samples than this costs more than stepping them (measured: one
#: span's array operations ~ 50-150 us, one sample of Plant.step with friction ~ 10-20 us);
#: after one the Plant steps 8, 16, .. up to _MAX_BACKOFF samples before the next attempt,
#: so a record with events every few samples costs about what stepping it costs
_SHORT_SPAN = 8
_MAX_BACKOFF = 1024
#: decisions within this fraction of the states' scale of their threshold are ties (rounding
#: decides them: the Plant steps that sample)
_TIE = 1e-11


def _plant(inertia: float, viscous: float, coulomb: float, stiffness: float, damping: float,
           substeps: int) -> Plant:
    """A Plant of these parameters, the last one reused (per thread): the segments of one
    fit evaluation share it, so its ZOH matrices (matrix exponentials: ~10 ms each on a busy
    machine with multithreaded BLAS, measured) are computed once per parameter set and
    delay, not once per segment. Its contact and initial positions are set by the caller."""
    key = (inertia, viscous, coulomb, stiffness, damping, substeps)
    cached: tuple[tuple[float, ...], Plant] | None = getattr(_LOCAL, "plant", None)
    if cached is not None and cached[0] == key:
        return cached[1]
    plant = Plant(inertia=inertia, viscous_friction=viscous, coulomb_friction=coulomb,
                  stiffness=stiffness, damping=damping, substeps=substeps)
    _LOCAL.plant = (key, plant)
    return plant


def simulate_torque(values: ModelValues, torque: np.ndarray, period: float, start: int,
                    stop: int, initial_position: float, initial_velocity: float = 0.0, *,
                    substeps: int = 10) -> tuple[np.ndarray, np.ndarray]:
    """True position and velocity at samples ``start .. stop-1`` of the plant ``values``
    driven by the sent torques ``torque`` (the whole record: commands sent before
    ``start`` still in transit act too), starting at ``initial_position`` with
    ``initial_velocity`` at sample ``start``.

    The numbers are those of stepping the emulator's Plant call by call
    (:func:`_simulate_stepping`, the reference; equal to rounding, tested), computed the
    fast way: with Coulomb friction and numba installed, the Plant's own sub-step function
    compiled over the whole record (:func:`_compiled_record`, bit for bit); otherwise
    :class:`_FastSimulation`: the Plant is linear between its nonlinear events (friction
    sign, sticking, contact), so whole spans run as one vectorised linear recursion and
    only the samples where an event happens step the Plant itself. Runs with BLAS on one
    thread (:func:`one_blas_thread`).
    """
    n = stop - start
    if n < 1:
        raise ValueError(f"segment [{start}, {stop}): empty")
    return _simulate(values, torque, period, start, stop, initial_position,
                     float(initial_velocity), substeps, "auto")


def _simulate(values: ModelValues, torque: np.ndarray, period: float, start: int, stop: int,
              initial_position: float, initial_velocity: float, substeps: int,
              method: str) -> tuple[np.ndarray, np.ndarray]:
    """:func:`simulate_torque` by ``method``: "spans" (:class:`_FastSimulation`),
    "compiled" (:func:`_compiled_record`: Coulomb friction only, numba needed) or "auto"
    (compiled when it applies and numba is installed)."""
    with one_blas_thread():
        plant, qc, applied, _, fraction = _setup(values, torque, period, start, stop,
                                                 initial_position, substeps)
        sim = _FastSimulation(plant, qc, applied, stop - start, period, fraction, substeps)
        e0 = initial_position - qc
        if method == "compiled" or (method == "auto" and sim.friction):
            kernel = _compiled_record()
            if kernel is not None and sim.friction:
                return sim.run_compiled(kernel, e0, initial_velocity)
            if method == "compiled":
                raise RuntimeError("the compiled path needs numba and Coulomb friction")
        return sim.run(e0, initial_velocity)


def _setup(values: ModelValues, torque: np.ndarray, period: float, start: int, stop: int,
           initial_position: float, substeps: int
           ) -> tuple[Plant, float, np.ndarray, int, float]:
    """The Plant of ``values``, its contact position, the torques acting (``applied[j]`` is
    ``u[start - whole - 1 + j]`` times the gain, zeros before the record) and the delay's
    whole samples and fraction."""
    # no environment: the emulator's plant has no contact position "nowhere", but with zero
    # stiffness and damping its contact mode is the free servo itself (plant_matrices with
    # K = D = 0 is servo_matrices), so the contact goes where the servo starts -- its state is
    # relative to the contact position, and a far one would cost that state its precision
    qc, k, d = values.contact_position, values.stiffness, values.damping
    if not math.isfinite(qc):
        qc, k, d = initial_position, 0.0, 0.0
    plant = _plant(values.inertia, values.viscous_friction, values.coulomb_friction, k, d,
                   substeps)
    plant.contact_position = qc
    whole, fraction = split_delay(values.delay, period)
    first = start - whole - 1
    applied = np.zeros(stop - first)
    lo = max(first, 0)
    applied[lo - first:] = values.torque_gain * np.asarray(torque[lo:stop], float)
    return plant, qc, applied, whole, fraction


def _simulate_stepping(values: ModelValues, torque: np.ndarray, period: float, start: int,
                       stop: int, initial_position: float, initial_velocity: float = 0.0, *,
                       substeps: int = 10) -> tuple[np.ndarray, np.ndarray]:
    """:func:`simulate_torque` by stepping the emulator's Plant call by call: the reference
    the fast path must equal (kept so the equality is tested for ever)."""
    n = stop - start
    if n < 1:
        raise ValueError(f"segment [{start}, {stop}): empty")
    plant, _, arr, _, fraction = _setup(values, torque, period, start, stop, initial_position,
                                        substeps)
    plant.set_state(initial_position, initial_velocity)
    applied = arr.tolist()
    rest = period - fraction
    pos = np.empty(n)
    vel = np.empty(n)
    pos[0], vel[0] = plant.true_position, plant.true_velocity
    step = plant.step
    late = fraction > _TINY
    # applied[j] is u[k - whole - 1], applied[j + 1] is u[k - whole] for sample k = start + j:
    # in [t_k, t_k+1] the first acts over the delay's fraction, the second over the rest
    for j in range(n - 1):
        if late:
            step(applied[j], fraction)
        step(applied[j + 1], rest)
        pos[j + 1] = plant.true_position
        vel[j + 1] = plant.true_velocity
    return pos, vel


_CALL: Any = None    # the compiled coulomb_substeps, for _record_loop (set by _compiled_record)
_KERNEL: dict[str, Any] = {}
_KERNEL_LOCK = threading.Lock()


def _record_loop(e: float, dq: float, w: np.ndarray, substeps: int, m: np.ndarray,
                 bands: np.ndarray, fc: float, k: float, out: np.ndarray) -> None:
    """Every call of every sample as :meth:`Plant.step` takes it with Coulomb friction (no
    clamp, no disturbance, no backlash: the model's Plant): ``w[s, c]`` the torque of call
    ``c`` of sample ``s``, ``m[c]`` its contact and free sub-step propagators, ``bands[c]``
    its Karnopp band; the state after each sample into ``out``. Compiled with numba
    (:func:`_compiled_record`), calling the compiled :func:`coulomb_substeps`."""
    for s in range(w.shape[0]):
        for c in range(w.shape[1]):
            e, dq, _ = _CALL(e, dq, w[s, c], substeps, bands[c], fc, k, True,
                             m[c, 0], m[c, 1], m[c, 2], m[c, 3], m[c, 4], m[c, 5],
                             m[c, 6], m[c, 7], m[c, 8], m[c, 9], m[c, 10], m[c, 11])
        out[s, 0] = e
        out[s, 1] = dq


def _compiled_record() -> Any:
    """:func:`_record_loop` compiled with numba (cached on disk), or None without numba.

    Why: with Coulomb friction a pressed servo under a PRBS reverses every few samples, and
    each reversal is an event the span method must hand to the Plant's Python sub-steps:
    such a record costs what stepping it costs (~0.2-0.4 s CPU per 60 s here), and a fit
    simulates it hundreds of times. The same lines compiled: ~3-10 ms per 60 s (measured),
    bit for bit the Plant's (tested). numba is a core dependency; should it fail to import the
    span method runs, with the same numbers, slower on such records. Compiled without the
    GIL (``nogil``) so simulations may run in threads; such a caller must hold one
    :func:`one_blas_thread` around the whole threaded region (measured: the limit set and
    restored per call from two threads made 8 simulations 8x slower)."""
    global _CALL
    with _KERNEL_LOCK:
        if "record" not in _KERNEL:
            try:
                import numba
            except ImportError:
                _KERNEL["record"] = None
            else:
                _CALL = numba.njit(cache=True, nogil=True)(coulomb_substeps)
                _KERNEL["record"] = numba.njit(cache=True, nogil=True)(_record_loop)
    return _KERNEL["record"]


@dataclass(frozen=True)
class _Linear:
    """One sample of the Plant in one contact mode with one friction sign ``s`` throughout
    (``s`` = +1/-1 while sliding, 0 without friction), as an affine map of the state
    ``x = [e, dq]`` (``e`` relative to the contact position) and the torques ``w`` of the
    sample's calls:

    - the state at the sample's end: ``a x + b w + s q``;
    - the position and velocity where the Plant takes its decisions -- every sub-step start
      with friction, every call's end without (:meth:`Plant.step` then takes one exact
      step per call unless the mode changed) -- ``check_x x + check_w w + s check_s``:
      the first ``len(band)`` rows are velocities (with ``band`` the Karnopp band of each),
      the rest positions.
    """

    a: np.ndarray          # 2 x 2
    b: np.ndarray          # 2 x calls
    q: np.ndarray          # 2
    check_x: np.ndarray    # rows x 2
    check_w: np.ndarray    # rows x calls
    check_s: np.ndarray    # rows
    band: np.ndarray       # velocity rows' Karnopp bands
    band_max: float


def _linear(plant: Plant, calls: tuple[float, ...], contact: bool, friction: bool,
            substeps: int) -> _Linear:
    """The :class:`_Linear` map of ``plant`` composed from the Plant's own propagators
    (:meth:`Plant.matrices`: the ZOH of dobhil.synthesis.controller.discretize), sub-step
    by sub-step with friction (as the Plant steps then), call by call without (one exact ZOH
    step per call, as the Plant steps a linear call)."""
    pieces: list[tuple[Propagator, int, float]] = []
    for c, dt in enumerate(calls):
        zoh = plant.matrices(dt)
        if friction:
            pieces += [(zoh.contact_sub if contact else zoh.free_sub, c, zoh.stiction)] * substeps
        else:
            pieces.append((zoh.contact if contact else zoh.free, c, 0.0))
    ncalls = len(calls)
    # columns: e, dq, w_1 .. w_calls, s (the Coulomb torque is -F_c s)
    affine = np.zeros((2, 3 + ncalls))
    affine[0, 0] = affine[1, 1] = 1.0
    starts, ends = [], []
    for p, c, _ in pieces:
        starts.append(affine)
        gamma = np.array([p.g0, p.g1])
        affine = _matrix(p) @ affine
        affine[:, 2 + c] += gamma
        affine[:, 2 + ncalls] -= plant.coulomb_friction * gamma
        ends.append(affine)
    if friction:
        rows = np.array([a[1] for a in starts] + [a[0] for a in starts])
        band = np.array([b for _, _, b in pieces])
    else:
        rows = np.array([a[0] for a in ends])
        band = np.zeros(0)
    return _Linear(a=affine[:, :2].copy(), b=affine[:, 2:2 + ncalls].copy(),
                   q=affine[:, 2 + ncalls].copy(), check_x=rows[:, :2].copy(),
                   check_w=rows[:, 2:2 + ncalls].copy(), check_s=rows[:, 2 + ncalls].copy(),
                   band=band, band_max=float(band.max(initial=0.0)))


def _matrix(p: Propagator) -> np.ndarray:
    return np.array([[p.p00, p.p01], [p.p10, p.p11]])


def _propagate(a: np.ndarray, x0: tuple[float, float], r: np.ndarray) -> np.ndarray:
    """``x[k+1] = a x[k] + r[k]`` from ``x[0] = x0``: ``x[0 .. len(r)]`` (rows), with
    scipy.signal.lfilter (compiled) instead of a Python loop.

    Upper triangular ``a`` (the free servo: the position integrates the velocity) runs as two
    first-order filters, velocity then position: a second-order direct form of its double
    pole at 1 would let rounding grow with the square of the length. Otherwise (a contact
    mode: stable, distinct poles) the direct form of the characteristic polynomial
    ``1 - tr z^-1 + det z^-2`` with the numerators of the adjugate (Cayley-Hamilton:
    ``x[k+1] - tr x[k] + det x[k-1] = r[k] - adj(a) r[k-1]``), its initial conditions
    from ``x[0]`` and ``x[1]`` (the transposed direct form's state after two outputs)."""
    e0, v0 = x0
    a00, a01, a10, a11 = float(a[0, 0]), float(a[0, 1]), float(a[1, 0]), float(a[1, 1])
    out = np.empty((len(r) + 1, 2))
    out[0] = x0
    if a10 == 0.0:
        v = lfilter([1.0], [1.0, -a11], r[:, 1], zi=[a11 * v0])[0]
        drive = r[:, 0].copy()
        drive[0] += a01 * v0
        drive[1:] += a01 * v[:-1]
        out[1:, 0] = lfilter([1.0], [1.0, -a00], drive, zi=[a00 * e0])[0]
        out[1:, 1] = v
        return out
    d1, d2 = -(a00 + a11), a00 * a11 - a01 * a10
    den = [1.0, d1, d2]
    out[1] = (a00 * e0 + a01 * v0 + r[0, 0], a10 * e0 + a11 * v0 + r[0, 1])
    if len(r) > 1:
        p0, p1 = r[:-1, 0], r[:-1, 1]
        drive_e = r[1:, 0] - a11 * p0 + a01 * p1
        drive_v = r[1:, 1] + a10 * p0 - a00 * p1
        # transposed direct form II with past outputs y[-1] = x[1], y[-2] = x[0]
        for col, drive in ((0, drive_e), (1, drive_v)):
            y1, y2 = out[1, col], out[0, col]
            zi = [-d1 * y1 - d2 * y2, -d2 * y1]
            out[2:, col] = lfilter([1.0], den, drive, zi=zi)[0]
    return out


class _FastSimulation:
    """The Plant's numbers without stepping it sample by sample.

    Hand-written because no library simulates this piecewise-linear system with stiction
    (scipy's lsim/dlsim are linear only, ODE solvers integrate a different, continuous
    model; the emulator's sub-stepped Karnopp friction is what has to be reproduced). The
    Plant is linear as long as its contact mode holds and every sub-step slides with the
    same friction sign (the Coulomb torque is then a constant input). So:

    - for each mode and sign the response of the whole record from rest, ``F``, and the
      powers of the sample's matrix, ``a^j``, are computed once (:func:`_propagate`,
      compiled); a span starting at sample ``i`` in state ``x_i`` is then
      ``x[i + j] = F[i + j] + a^j (x_i - F[i])`` (superposition), a few array operations;
    - the position and velocity at every sub-step start along the span follow from one
      matrix product; the span ends at the first sample where the Plant would decide
      otherwise (the velocity within the Karnopp band or reversed, the contact mode
      changed);
    - that sample steps the Plant itself (:meth:`Plant.step`);
    - a servo at rest stays there while every call's torque is within the Coulomb level
      (stuck spans: one vectorised comparison).
    """

    def __init__(self, plant: Plant, qc: float, applied: np.ndarray, samples: int,
                 period: float, fraction: float, substeps: int) -> None:
        self.plant, self.qc, self.substeps = plant, qc, substeps
        late = fraction > _TINY
        self.calls: tuple[float, ...] = (fraction, period - fraction) if late else (period,)
        # w[k, c]: the torque of call c over sample k (applied[k], then applied[k + 1]),
        # k = 0 .. samples - 2 (later commands are still in transit at the last sample)
        steps = samples - 1
        self.w = (np.column_stack([applied[:steps], applied[1:samples]]) if late
                  else applied[1:samples, None].copy())
        self.fc = plant.coulomb_friction
        self.friction = self.fc != 0.0
        self.k_env = plant.stiffness
        # with K = D = 0 both modes are the same matrices (servo_matrices): no mode to keep
        self.modes = plant.stiffness != 0.0 or plant.damping != 0.0
        self._linear: dict[bool, _Linear] = {}
        self._forced: dict[tuple[bool, float], np.ndarray] = {}
        self._powers: dict[bool, tuple[np.ndarray, np.ndarray]] = {}
        self._scale: dict[tuple[bool, float], tuple[float, float]] = {}
        self._checks: dict[tuple[bool, float], tuple[np.ndarray, np.ndarray, np.ndarray]] = {}

    def linear(self, contact: bool) -> _Linear:
        lin = self._linear.get(contact)
        if lin is None:
            lin = self._linear[contact] = _linear(self.plant, self.calls, contact,
                                                  self.friction, self.substeps)
        return lin

    def forced(self, contact: bool, sign: float) -> np.ndarray:
        """``F``: the states of the whole record from rest at ``e = 0``, this mode and
        friction sign throughout (a fiction: only its differences are used)."""
        key = (contact, sign)
        f = self._forced.get(key)
        if f is None:
            lin = self.linear(contact)
            r = self.w @ lin.b.T
            if sign:
                r += sign * lin.q
            f = self._forced[key] = _propagate(lin.a, (0.0, 0.0), r)
            self._scale[key] = (float(np.max(np.abs(f[:, 0]))), float(np.max(np.abs(f[:, 1]))))
        return f

    def powers(self, contact: bool) -> tuple[np.ndarray, np.ndarray]:
        """The columns of ``a^j`` for ``j = 0 .. steps``: ``a^j [1, 0]`` and ``a^j [0, 1]``
        (rows)."""
        p = self._powers.get(contact)
        if p is None:
            a = self.linear(contact).a
            zero = np.zeros((len(self.w), 2))
            p = self._powers[contact] = (_propagate(a, (1.0, 0.0), zero),
                                         _propagate(a, (0.0, 1.0), zero))
        return p

    def checks(self, contact: bool, sign: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The decision rows of :class:`_Linear` arranged so that every test is ``> 0``
        (sliding: ``sign dq - band``) or ``>= 0`` (the contact mode: ``e``, negated in free
        motion, where ``e < 0`` must hold): state part, torque part, constant."""
        key = (contact, sign)
        c = self._checks.get(key)
        if c is None:
            lin = self.linear(contact)
            nv = len(lin.band)
            scale = np.concatenate([np.full(nv, sign),
                                    np.full(len(lin.check_s) - nv, 1.0 if contact else -1.0)])
            const = scale * sign * lin.check_s
            const[:nv] -= lin.band
            c = self._checks[key] = (lin.check_x * scale[:, None], lin.check_w * scale[:, None],
                                     const)
        return c

    def run_compiled(self, kernel: Any, e0: float,
                     v0: float) -> tuple[np.ndarray, np.ndarray]:
        """Every sample by the compiled record loop (:func:`_compiled_record`): the Plant's
        own sub-step lines (:func:`coulomb_substeps`) compiled, so the numbers are the
        Plant's (no event search needed)."""
        plant = self.plant
        m = np.empty((len(self.calls), 12))
        bands = np.empty(len(self.calls))
        for c, dt in enumerate(self.calls):
            zoh = plant.matrices(dt)
            cs, fs = zoh.contact_sub, zoh.free_sub
            m[c] = (cs.p00, cs.p01, cs.p10, cs.p11, cs.g0, cs.g1,
                    fs.p00, fs.p01, fs.p10, fs.p11, fs.g0, fs.g1)
            bands[c] = zoh.stiction
        out = np.empty((len(self.w) + 1, 2))
        out[0] = (e0, v0)
        kernel(e0, v0, self.w, self.substeps, m, bands, plant.coulomb_friction,
               plant.stiffness, out[1:])
        return out[:, 0] + self.qc, out[:, 1]

    def run(self, e0: float, v0: float) -> tuple[np.ndarray, np.ndarray]:
        """Position and velocity at every sample from ``e0`` (relative to the contact) and
        ``v0`` (the state at the first sample)."""
        steps = len(self.w)             # transitions: samples 0 .. steps
        e_out = np.empty(steps + 1)
        v_out = np.empty(steps + 1)
        e_out[0], v_out[0] = e0, v0
        e, dq, k, size = e0, v0, 0, _MIN_WINDOW
        plain = backoff = 0   # samples to step with the Plant before trying a span again
        while k < steps:
            if plain:
                # events every few samples (a pressed servo reversing under a PRBS, say):
                # a span would cost more than it saves, so the Plant steps on
                count = min(plain, steps - k)
                e, dq = self._plant_steps(k, count, e, dq, e_out, v_out)
                k += count
                plain = 0
                continue
            if self.friction and dq == 0.0:
                r = self._stuck(k, e)
                e_out[k + 1:k + r + 1] = e
                v_out[k + 1:k + r + 1] = 0.0
                k += r
                held = r
            else:
                length = min(size, steps - k)
                x, held = self._span(k, length, e, dq)
                if held:
                    e_out[k + 1:k + held + 1] = x[:held, 0]
                    v_out[k + 1:k + held + 1] = x[:held, 1]
                    e, dq = float(x[held - 1, 0]), float(x[held - 1, 1])
                    k += held
                if held == length:
                    size = min(2 * size, _MAX_WINDOW)
                    continue
                size = max(_MIN_WINDOW, 2 * held)
            if k < steps:               # an event inside sample k: the Plant steps it
                e, dq = self._plant_steps(k, 1, e, dq, e_out, v_out)
                k += 1
            # back off while spans are short: step 8, 16, .. samples between attempts
            backoff = (0 if held >= _SHORT_SPAN
                       else min(max(2 * backoff, _SHORT_SPAN), _MAX_BACKOFF))
            plain = backoff
        return e_out + self.qc, v_out

    def _plant_steps(self, k: int, count: int, e: float, dq: float, e_out: np.ndarray,
                     v_out: np.ndarray) -> tuple[float, float]:
        """Samples ``k .. k + count`` by :meth:`Plant.step`, the reference itself, from
        ``(e, dq)``; the states go to ``e_out``/``v_out``, the last is returned."""
        plant, qc, calls = self.plant, self.qc, self.calls
        plant.set_state(e + qc, dq)
        step = plant.step
        if count == 1:                  # the common case (one event): no lists
            for c, dt in enumerate(calls):
                step(float(self.w[k, c]), dt)
            e, dq = plant.true_position - qc, plant.true_velocity
            e_out[k + 1], v_out[k + 1] = e, dq
            return e, dq
        e_list: list[float] = []
        v_list: list[float] = []
        if len(calls) == 1:
            dt = calls[0]
            for u in self.w[k:k + count, 0].tolist():
                step(u, dt)
                e_list.append(plant.true_position)
                v_list.append(plant.true_velocity)
        else:
            first, rest = calls
            for u1, u2 in self.w[k:k + count].tolist():
                step(u1, first)
                step(u2, rest)
                e_list.append(plant.true_position)
                v_list.append(plant.true_velocity)
        e_out[k + 1:k + count + 1] = e_list
        e_out[k + 1:k + count + 1] -= qc
        v_out[k + 1:k + count + 1] = v_list
        return float(e_out[k + count]), v_list[-1]

    def _stuck(self, k: int, e: float) -> int:
        """How many samples from ``k`` the servo, at rest at ``e``, stays stuck: every
        call's torque (less the spring's in contact) within the Coulomb level, the Plant's
        test at zero velocity (Plant._friction_at with no Stribeck peak)."""
        spring = self.k_env * e if e >= 0.0 else 0.0
        fc, w, steps = self.fc, self.w, len(self.w)
        start, size = k, _MIN_WINDOW
        while start < steps:
            f = w[start:start + size] - spring
            held = np.all((f >= -fc) & (f <= fc), axis=1)
            bad = np.flatnonzero(~held)
            if len(bad):
                return start + int(bad[0]) - k
            start += size
            size = min(4 * size, _MAX_WINDOW)
        return steps - k

    def _span(self, k: int, length: int, e: float, dq: float) -> tuple[np.ndarray, int]:
        """The states ``x[k+1 .. k+length]`` if samples ``k ..`` are linear in the mode of
        ``e`` with the friction sign of ``dq``, and how many of them are the Plant's: the
        samples before the first where a decision differs."""
        contact = self.modes and e >= 0.0
        sign = (1.0 if dq > 0.0 else -1.0) if self.friction else 0.0
        lin = self.linear(contact)
        f = self.forced(contact, sign)
        p0, p1 = self.powers(contact)
        d0, d1 = e - f[k, 0], dq - f[k, 1]
        # x[k + j] = F[k + j] + a^j (x[k] - F[k]), j = 0 .. length (row 0: x[k] itself)
        x = f[k:k + length + 1] + p0[:length + 1] * d0 + p1[:length + 1] * d1
        x[0] = (e, dq)
        cx, cw, const = self.checks(contact, sign)
        z = x[:-1] @ cx.T + self.w[k:k + length] @ cw.T
        z += const
        nv = len(lin.band)
        # a decision this close to its threshold is a tie that rounding decides: the
        # superposition rounds differently from the Plant's sub-steps (by a few eps of the
        # largest state involved), so such a sample goes to the Plant
        fe, fv = self._scale[(contact, sign)]
        tie_v = _TIE * (fv + abs(dq) + lin.band_max)
        tie_e = _TIE * (fe + abs(e))
        # sliding beyond the band with the span's sign; in contact e >= 0, free e < 0 (the
        # rows are arranged so that both read "> 0", see checks)
        bad_rows = (z[:, :nv] <= tie_v).any(axis=1)
        if self.modes:
            bad_rows |= (z[:, nv:] <= tie_e).any(axis=1)
        first = int(np.argmax(bad_rows))
        return x[1:], first if bad_rows[first] else length
