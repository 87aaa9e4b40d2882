"""Closed-loop identification: the recorded controller simulated in closed loop with a
candidate plant and environment, driven by the recorded reference.

Why: in a force-control run the torque the controller sent depends on the measurement noise
(the observers feed the noisy velocity back), so an output-error fit that takes the recorded
torque as a noise-free input (:mod:`dobhil.identify.fit`) is biased -- the direct method with
a wrong noise model (Ljung, *System Identification*, 2nd ed., section 13.4). The reference is
independent of the noise; so the whole loop is simulated from it (Ljung's "indirect" route in
its simulation form, also called closed-loop output error, Landau and Zito, *Digital Control
Systems*, 2006, chapter 9) and the simulated velocity and torque are compared with the
measured ones.

What the simulation knows of the runtime:

- the controller: the very matrices the runtime executes and ``dobhil replay`` rebuilds,
  :func:`dobhil.runtime.session.build_controller` (the sampled synthesis, the protocol's
  command delay, the tighter torque limit, torque mode open loop), its state started as
  ``controller.initialize`` started it from the recorded feedback of cycle -1;
- the sensor: the position it feeds the controller quantised to the recorded
  ``sensor.encoder_resolution`` (the emulator's rounding, :class:`dobhil.emulator.plant.Plant`);
  the velocity noise is not simulated (it is what the fit must not follow);
- the plant: the emulator's ZOH propagators (:meth:`Plant.matrices`' numbers,
  :func:`dobhil.emulator.plant.mode_propagators`, contact and free modes,
  sub-stepped where the mode changes within a call), the motor's torque clamp
  (``plant.torque_limit``), the command applied ``delay`` after the sample it was computed
  from (whole periods and a fraction, as :mod:`dobhil.identify.model`). Coulomb friction is
  not in this model (held at 0): the closed-loop simulation is kept linear per mode.

The fit (:func:`identify_closed_loop`): inertia, viscous friction, stiffness, damping, contact
position and delay by scipy's bounded trust-region least squares on the residuals of the
velocity and of the torque, each in units of its own noise (the RMS of the previous round's
residual). Those residuals are the loop's response to the noise: coloured and correlated with
each other, so the covariance is the sandwich ``(J^T J)^-1 J^T S J (J^T J)^-1`` with ``S``
from the per-sample scores by Newey and West (*Econometrica* 55, 1987: Bartlett weights) --
``s^2 (J^T J)^-1`` would assume white residuals and cover far less than 95 %. The intervals
of the inertia, stiffness and damping are that covariance's on the log scale
(:func:`_interval`: their standard errors grow with the estimates). The delay's
interval is the profile likelihood's instead (:class:`_Profile`): its cost is not quadratic
over the interval (a truth within a standard error of its bound 0, a fraction of a period
that moves the plant's ZOH calls).
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable, Mapping
from dataclasses import dataclass, replace
from functools import cached_property
from types import MappingProxyType
from typing import Any

import numpy as np
import scipy.optimize
import scipy.stats
from numpy.typing import NDArray

from dobhil.identify.fit import LEVEL, NOISE_FLOOR, WIDEST, Estimate, IdentResult, _whiteness, fold_covariance
from dobhil.identify.data import Segment
from dobhil.identify.model import split_delay

Array = NDArray[np.float64]

__all__ = ["CLOSED_LOOP", "OPEN_LOOP", "FITTED", "LoopRecord", "LoopModel", "closed_loop_record",
           "identify_closed_loop", "simulate_loop", "validate_loop"]

#: the method names identify reports
CLOSED_LOOP = "closed-loop (simulated controller)"
OPEN_LOOP = "open-loop output error"
#: the parameters the closed-loop fit varies, in this order
FITTED = ("inertia", "viscous_friction", "stiffness", "damping", "contact_position", "delay")
#: what the fit varies: :data:`FITTED` and the true initial position (a nuisance parameter,
#: not reported: the recorded one is quantised, and half a count is a sizeable part of a
#: servo's approach to its contact -- 4 % of the demo's 5 mrad with a 14-bit encoder)
_VARIED = (*FITTED, "initial_position")
#: sub-steps of a call in which the contact mode changes (the emulator's default)
_SUBSTEPS = 10


@dataclass(frozen=True)
class LoopModel:
    """The runtime's controller and sensor as the simulation runs them (see the module
    docstring): the sampled controller's matrices, its gain and limit, the encoder count."""

    a: Array           # (n, n)
    b_y: Array         # (n, m): m = 2 (q, dq measured) or 1 (q only)
    b_u: Array         # (n,)
    c: Array           # (2, n) rows tau_dis^, tau_int^
    d_y: Array         # (2, m)
    force_gain: float
    torque_limit: float        # the controller's saturation [N m]
    plant_limit: float         # the motor's clamp [N m] (inf: none)
    open_loop: bool            # torque mode: the reference is the command
    count: float               # encoder count [rad] (0: not quantised)
    period: float

    @classmethod
    def of(cls, ctrl: Any, config: Any) -> LoopModel:
        """The model of the runtime's controller ``ctrl`` (a
        :class:`dobhil.runtime.controller.ForceController` built by
        :func:`dobhil.runtime.session.build_controller`, the runtime's and replay's own: the
        caller builds it, this layer does not import the runtime) on the run of ``config``."""
        ss = ctrl.ss
        res = int(config.sensor.encoder_resolution)
        limit = float(config.plant.torque_limit)
        return cls(a=np.ascontiguousarray(ss.a, float), b_y=np.ascontiguousarray(ss.b_y, float),
                   b_u=np.ascontiguousarray(ss.b_u[:, 0], float), c=np.ascontiguousarray(ss.c, float),
                   d_y=np.ascontiguousarray(ss.d_y, float), force_gain=float(ctrl.force_gain),
                   torque_limit=float(ctrl.torque_limit),
                   plant_limit=limit if limit > 0 else math.inf, open_loop=bool(ctrl.open_loop),
                   count=2.0 * math.pi / res if res > 0 else 0.0, period=float(ctrl.period))

    def initial_state(self, q: float, dq: float) -> Array:
        """The observer state ``controller.initialize(q, dq)`` sets: ``(I - A)^-1 B_y y``."""
        y = np.array([q, dq][: self.b_y.shape[1]], float)
        return np.linalg.solve(np.eye(self.a.shape[0]) - self.a, self.b_y @ y)


@dataclass(frozen=True)
class LoopRecord:
    """What the closed-loop fit needs from one force run: the reference each cycle used,
    the measured motion, the torque sent, the feedback ``controller.initialize`` used, and
    the runtime's :class:`LoopModel`."""

    model: LoopModel
    reference: Array       # tau_ref per cycle [N m]
    position: Array        # measured [rad]
    velocity: Array        # measured [rad/s]
    torque: Array          # u_sat sent [N m]
    initial: tuple[float, float]   # feedback of cycle -1 (q, dq)
    source: str
    mode: str              # loop.mode of the run
    recorded: Mapping[str, float]

    @property
    def samples(self) -> int:
        return int(self.reference.size)

    @cached_property
    def initial_state(self) -> Array:
        """The controller's state at the start (:meth:`LoopModel.initial_state` of the
        initial feedback): the same for every simulation of the record, so solved once."""
        return self.model.initial_state(*self.initial)


def closed_loop_record(path: str, build: Callable[[Any, Any], Any], *,
                       axis: str | None = None) -> LoopRecord:
    """The :class:`LoopRecord` of a dobhil run's log (``/drive/feedback`` and ``/controller``
    of every cycle from 0 without a gap, the recorded config and drive profile).
    LogFileError (one line) for a log that is not a run's, or whose cycles have a gap
    before the end (a late real-time cycle: the loop it recorded is not one the simulation
    can follow from the start -- the cycles up to the gap are used). ``build(config, profile)``:
    the runtime's controller of the recorded config and profile
    (:func:`dobhil.runtime.session.build_controller`)."""
    import os

    from dobhil.drives.decode import recorded_profile
    from dobhil.errors import LogFileError, exception_line
    from dobhil.recording.axes import axis_log, is_axes_log
    from dobhil.recording.reader import open_log
    name = os.fspath(path)
    fb: dict[int, tuple[float, float]] = {}
    ctl: dict[int, tuple[float, float]] = {}
    with open_log(path) as whole:
        log: Any = axis_log(whole, axis) if axis is not None or is_axes_log(whole) else whole
        if log.config is None or not {"/drive/feedback", "/controller"} <= set(log.topics()):
            raise LogFileError(f"{name}: not a dobhil run's log (no config or no loop records); "
                               "closed-loop identification needs the recorded controller")
        profile = recorded_profile(log.metadata.get("drive"), name)
        config = log.config
        try:
            # whatever the log's encoding; a number that was not finite reads as None
            for topic, _, p in log.iter_messages(("/drive/feedback", "/controller")):
                if topic == "/controller":
                    ctl[int(p["cycle"])] = (_number(p["tau_ref"]), _number(p["u_sat"]))
                else:
                    fb[int(p["cycle"])] = (_number(p["position"]), _number(p["velocity"]))
        except (KeyError, TypeError, ValueError) as exc:
            raise LogFileError(f"{name}: a recorded message does not match its schema "
                               f"({exception_line(exc)})") from None
    n = 0
    while n in ctl and n in fb and all(math.isfinite(v) for v in (*ctl[n], *fb[n])):
        n += 1
    if n < 50 or -1 not in fb:
        raise LogFileError(f"{name}: {n} consecutive cycles from cycle 0 with the initial feedback "
                           "(cycle -1); closed-loop identification needs at least 50")
    rows = np.array([[*fb[k], *ctl[k]] for k in range(n)], float)
    recorded = {k: float(v) for k, v in config.flat().items()
                if k.split(".")[0] in ("plant", "environment", "design")
                and isinstance(v, (int, float)) and not isinstance(v, bool)}
    return LoopRecord(model=LoopModel.of(build(config, profile), config), reference=rows[:, 2],
                      position=rows[:, 0], velocity=rows[:, 1], torque=rows[:, 3],
                      initial=fb[-1], source=os.path.basename(name), mode=str(config.loop.mode),
                      recorded=MappingProxyType(recorded))


def _number(value: Any) -> float:
    """A recorded number; NaN for one that was not finite (read as None)."""
    return math.nan if value is None else float(value)


# -- the simulation ----------------------------------------------------------------------


def _loop_kernel(ref: Array, q0: float, v0: float, xi0: Array, a: Array, b_y: Array, b_u: Array,
                 c: Array, d_y: Array, kf: float, limit: float, plant_limit: float, open_loop: bool,
                 count: float, qc: float, whole: int, calls: Array, props: Array, subs: Array,
                 substeps: int, out: Array) -> None:
    """Every sample of the closed loop (compiled with numba, :func:`_compiled`): the sensor,
    the controller (:mod:`dobhil.runtime.controller`'s equations on its matrices), the
    command queue and the plant's ZOH calls. ``props[c]`` / ``subs[c]``: call ``c``'s
    contact and free propagators over the call / over one sub-step, rows
    ``p00 p01 p10 p11 g0 g1``. ``out[k]``: true position, true velocity, sent torque."""
    n = ref.shape[0]
    order = a.shape[0]
    m = b_y.shape[1]
    xi = xi0.copy()
    nxt = np.empty(order)
    sent = np.zeros(n + whole + 2)
    e = q0 - qc
    dq = v0
    y = np.empty(2)
    for k in range(n):
        q = e + qc
        y[0] = np.rint(q / count) * count if count > 0.0 else q
        y[1] = dq
        dis = 0.0
        inter = 0.0
        for i in range(order):
            dis += c[0, i] * xi[i]
            inter += c[1, i] * xi[i]
        for j in range(m):
            dis += d_y[0, j] * y[j]
            inter += d_y[1, j] * y[j]
        if open_loop:
            u = ref[k]
        else:
            u = kf * (ref[k] - inter) + dis
        u = min(max(u, -limit), limit)
        for i in range(order):
            s = b_u[i] * u
            for j in range(order):
                s += a[i, j] * xi[j]
            for j in range(m):
                s += b_y[i, j] * y[j]
            nxt[i] = s
        xi[:] = nxt
        sent[k + whole + 1] = u
        out[k, 0] = e + qc
        out[k, 1] = dq
        out[k, 2] = u
        # sample k's interval: the command of k - whole - 1 over the fraction, then k - whole's
        for ci in range(calls.shape[0]):
            w = sent[k + ci] if calls.shape[0] == 2 else sent[k + 1]
            w = min(max(w, -plant_limit), plant_limit)
            contact = e >= 0.0
            r = 0 if contact else 6
            ne = props[ci, r] * e + props[ci, r + 1] * dq + props[ci, r + 4] * w
            if (ne >= 0.0) == contact:
                dq = props[ci, r + 2] * e + props[ci, r + 3] * dq + props[ci, r + 5] * w
                e = ne
                continue
            for _ in range(substeps):
                r = 0 if e >= 0.0 else 6
                ne = subs[ci, r] * e + subs[ci, r + 1] * dq + subs[ci, r + 4] * w
                dq = subs[ci, r + 2] * e + subs[ci, r + 3] * dq + subs[ci, r + 5] * w
                e = ne


_KERNEL: dict[str, Any] = {}
_LOCK = threading.Lock()


def _compiled() -> Callable[..., None]:
    """:func:`_loop_kernel` compiled with numba (cached on disk); the Python function
    itself without numba (the same numbers, ~100x slower)."""
    with _LOCK:
        if "loop" not in _KERNEL:
            try:
                import numba
            except ImportError:
                _KERNEL["loop"] = _loop_kernel
            else:
                _KERNEL["loop"] = numba.njit(cache=True, nogil=True)(_loop_kernel)
    kernel: Callable[..., None] = _KERNEL["loop"]
    return kernel


def _rows(p: Any, s: Any) -> list[float]:
    return [p.p00, p.p01, p.p10, p.p11, p.g0, p.g1, s.p00, s.p01, s.p10, s.p11, s.g0, s.g1]


def simulate_loop(values: Mapping[str, float], record: LoopRecord) -> Array:
    """The closed loop of ``record``'s controller with the plant ``values`` (names of
    :data:`FITTED`; missing: 0, no environment), driven by its reference from its initial
    feedback: ``(samples, 3)`` true position, true velocity, torque sent."""
    from dobhil.realtime import one_blas_thread
    with one_blas_thread():     # 2x2 matrix exponentials: ~15x slower on threaded BLAS (measured)
        return _simulate_loop(values, record)


def _simulate_loop(values: Mapping[str, float], record: LoopRecord) -> Array:
    from dobhil.emulator.plant import mode_propagators
    m = record.model
    k_env, d_env = float(values.get("stiffness", 0.0)), float(values.get("damping", 0.0))
    qc = float(values.get("contact_position", math.inf))
    q0 = float(values.get("initial_position", record.initial[0]))
    if not math.isfinite(qc):
        qc, k_env, d_env = q0 - 1.0, 0.0, 0.0
    whole, fraction = split_delay(float(values.get("delay", 0.0)), m.period)
    durations = [fraction, m.period - fraction] if fraction > 1e-12 else [m.period]
    # the Plant's own propagators (Plant(...).matrices of each call), without a Plant's set-up
    mats = mode_propagators(float(values["inertia"]), float(values.get("viscous_friction", 0.0)), k_env, d_env,
                            durations, _SUBSTEPS)
    props = np.array([_rows(contact, free) for free, contact, _, _ in mats])
    subs = np.array([_rows(contact_sub, free_sub) for _, _, free_sub, contact_sub in mats])
    out = np.empty((record.samples, 3))
    _compiled()(np.ascontiguousarray(record.reference, float), q0, 0.0,
                record.initial_state, m.a, m.b_y, m.b_u, m.c, m.d_y, m.force_gain,
                m.torque_limit, m.plant_limit, m.open_loop, m.count, qc, whole,
                np.array(durations), props, subs, _SUBSTEPS, out)
    return out


def validate_loop(values: Mapping[str, float], record: LoopRecord) -> Any:
    """The model ``values`` (names of :data:`FITTED`) checked on another force run: its
    closed loop simulated from that run's reference, with that run's controller
    (:func:`simulate_loop`), against what it measured -- a
    :class:`dobhil.identify.validate.Validation` of the velocity and position over the whole
    run, the residual's whiteness and its cross-correlation with the reference. The true
    initial position, within half an encoder count of the recorded one, is fitted to the first
    samples' velocity, as the fit does (a nuisance: the start of a run is no state the fit saw)."""
    from dobhil.realtime import one_blas_thread
    with one_blas_thread():     # as the fit (identify_closed_loop): small products on one thread
        return _validate_loop(values, record)


def _validate_loop(values: Mapping[str, float], record: LoopRecord) -> Any:
    from dobhil.identify.validate import SignalFit, nrmse_fit, residual_tests
    start = dict(values)
    half = record.model.count / 2.0
    if half > 0.0:
        head = _head(record, 200)
        q0 = record.initial[0]

        def cost(dq0: float) -> float:
            r = head.velocity - simulate_loop({**start, "initial_position": q0 + dq0}, head)[:, 1]
            return float(r @ r)
        best = scipy.optimize.minimize_scalar(cost, bounds=(-half, half), method="bounded")
        start["initial_position"] = q0 + float(best.x)
    out = simulate_loop(start, record)
    fits = tuple(SignalFit(signal=name, kind="run", percent=nrmse_fit(measured, out[:, col]),
                           samples=record.samples)
                 for name, col, measured in (("velocity", 1, record.velocity), ("position", 0, record.position)))
    return residual_tests(fits, record.velocity - out[:, 1], record.reference, record.velocity,
                          input_name="reference")


# -- the fit -----------------------------------------------------------------------------

#: relative step of the central differences. Not small: every change of contact mode is
#: found at a sub-step's end (the emulator's rule, :class:`dobhil.emulator.plant.Plant`), so
#: each of a run's contacts and lift-offs (85 in the 4 s test record) puts a kink in the
#: residual wherever a parameter moves it across a sub-step; the cost is a washboard of
#: ~0.1-0.2 (chi-square units) a few 0.1 % apart (measured along J, K, contact and delay).
#: At 1e-3 the differences saw the kinks: the fits stopped on them (cost above the truth's
#: by chi-square 5-70), and the standard errors scattered 10x between seeds of one record;
#: 1e-2 differences across them (the secant the slope of the cost's trend)
_DIFF_STEP = 1e-2
#: the local fits' relative tolerances of cost and step (scipy's default 1e-8 refines the
#: cost to 6e-4 chi-square units on 60000 samples, far below the washboard above: the
#: iterations past 1e-6 move the estimates by a small part of their standard error)
_TOL = 1e-6
#: fits on the whole record after the probe's (each signal's weight from the previous
#: fit's residual; one: the probe's weights are already the noise's)
_ROUNDS = 1
#: samples the start grid and the local fits from its best points see (the record's first
#: ones): a long log's search costs what a 8 s one costs, the whole record then refines
#: (measured: a 60 s force run took 200 s with the search on every sample, on a loaded machine)
_PROBE = 8000


def _x0(record: LoopRecord) -> dict[str, float]:
    """The start: the design's own beliefs (nominal inertia, its command delay) and, for
    the environment, a grid over the stiffness (:func:`_grid_starts`); the contact position
    where the servo rests in the second half of the run (pressed: a few counts from it)."""
    rec = record.recorded
    period = record.model.period
    delay = rec.get("design.delay_samples", 0.0) * period + rec.get("design.input_delay", 0.0)
    half = record.position[record.samples // 2:]
    return {"inertia": rec.get("design.nominal_inertia", rec.get("plant.inertia", 1.0)),
            "viscous_friction": max(rec.get("design.nominal_friction", 0.0), 0.0),
            "stiffness": 1.0, "damping": 0.0, "contact_position": float(np.median(half)),
            "delay": delay, "initial_position": record.initial[0]}


class _Problem:
    """The residual of :func:`identify_closed_loop` over the parameters of :data:`FITTED`,
    in units scaled by ``scale`` (the optimiser sees numbers near 1)."""

    def __init__(self, record: LoopRecord, scale: Array, vary: Array,
                 progress: Callable[[str], object] | None) -> None:
        self.record, self.scale, self.vary, self.progress = record, scale, vary, progress
        self.weights = (1.0, 1.0)
        self.stage = "closed-loop fit"

    def values(self, x: Array) -> dict[str, float]:
        """The plant of the varied ``x`` (scaled); the held environment of a free run: none."""
        full = dict(zip(_VARIED, self.scale.tolist()))
        full.update(zip((_VARIED[i] for i in self.vary), (x * self.scale[self.vary]).tolist()))
        if "stiffness" not in (_VARIED[i] for i in self.vary):
            full.update(stiffness=0.0, damping=0.0, contact_position=math.inf)
        return full

    def parts(self, x: Array) -> tuple[Array, Array]:
        out = simulate_loop(self.values(x), self.record)
        if self.progress is not None:
            self.progress(self.stage)
        return self.record.velocity - out[:, 1], self.record.torque - out[:, 2]

    def __call__(self, x: Array) -> Array:
        rv, ru = self.parts(x)
        return np.concatenate([rv / self.weights[0], ru / self.weights[1]])


#: the start grid: inertia factors around the design's nominal one, stiffnesses [N m/rad]
_GRID_INERTIA = np.geomspace(0.25, 4.0, 9)
_GRID_STIFFNESS = np.geomspace(1e2, 1e7, 16)
#: damping ratios of the contact in the grid (measured: at 0.2 of critical alone every start
#: of seed 4 of the test record lay at K 1e6-1e7 and its fit ended there; at 0.5 the grid's
#: best points were the truth's neighbours on each of three seeds)
_GRID_DAMPING = (0.2, 0.5, 1.0)
#: local fits started from the best grid points (measured: from the best one alone the fit
#: of a noisy 4 s run ended at J 0.50, K 4.7e4 for 0.37, 1.5e4 -- a valley the truth's
#: cost lies below)
_STARTS = 4


def _grid_starts(problem: _Problem, x: Array) -> list[Array]:
    """The :data:`_STARTS` grid points of least velocity cost -- the inertia from a quarter
    to 4 times the design's nominal one, the stiffness 1e2 .. 1e7 N m/rad, the damping ratios
    :data:`_GRID_DAMPING`: the cost is far from quadratic in them (the inertia decides when the servo
    reaches the contact, the stiffness where the loop's resonance lies), and no recorded
    value of the environment is to be trusted (an emulated run records the truth, a real
    one a guess). 432 simulations, ~1 ms each on 4000 samples."""
    scored: list[tuple[float, Array]] = []
    contact = len(problem.vary) == len(_VARIED)
    for f in _GRID_INERTIA:
        j = x[0] * f * problem.scale[0]
        for k, zeta in ([(k, z) for k in _GRID_STIFFNESS for z in _GRID_DAMPING] if contact
                        else [(_GRID_STIFFNESS[0], 0.0)]):
            trial = x.copy()
            trial[0] = x[0] * f
            trial[2] = k / problem.scale[2]
            trial[3] = 2.0 * zeta * math.sqrt(k * j) / problem.scale[3]
            sub = trial[problem.vary]
            rv, _ = problem.parts(sub)
            scored.append((float(rv @ rv), sub))
    scored.sort(key=lambda item: item[0])
    return [trial for _, trial in scored[:_STARTS]]


def _bounds(record: LoopRecord, start: Mapping[str, float]) -> tuple[Array, Array]:
    period = record.model.period
    span = max(float(np.ptp(record.position)), 1e-3)
    j = start["inertia"]
    q0, count = record.initial[0], record.model.count
    lo = np.array([j / 50.0, 0.0, 1.0, 0.0, float(np.min(record.position)) - span, 0.0, q0 - count])
    hi = np.array([j * 50.0, 1e3, 1e8, 1e6, float(np.max(record.position)) + span, 4.0 * period,
                   q0 + count + 1e-12])
    return lo, hi


def _sandwich(jac: Array, r: Array, samples: int) -> Array | None:
    """``(J^T J)^-1 J^T S J (J^T J)^-1``: ``S`` the Newey-West estimate of the scores'
    long-run covariance (Bartlett weights over ``~3 n^(1/3)`` lags), the scores summed per
    sample over the signals (rows ``t`` and ``samples + t`` are the same sample)."""
    if not np.all(np.isfinite(jac)):
        return None
    norms = np.linalg.norm(jac, axis=0)
    norms = np.where(norms > 0, norms, 1.0)
    js = jac / norms
    g = js * r[:, None]
    g = g[:samples] + g[samples:2 * samples]
    g = g - g.mean(axis=0)
    lags = min(int(3 * samples ** (1 / 3)), samples - 1)
    s = g.T @ g
    for lag in range(1, lags + 1):
        w = 1.0 - lag / (lags + 1)
        gamma = g[lag:].T @ g[:-lag]
        s += w * (gamma + gamma.T)
    w_eig, v = np.linalg.eigh(js.T @ js)
    w_eig = np.maximum(w_eig, 1e-12 * max(float(w_eig[-1]), 1e-300))
    bread = (v / w_eig) @ v.T
    cov = bread @ s @ bread
    return cov / np.outer(norms, norms)


def identify_closed_loop(record: LoopRecord, *, contact: bool = True,
                         progress: Callable[[str], object] | None = None) -> IdentResult:
    """Fit the plant and environment to a force run by simulating its controller in closed
    loop (see the module docstring). The estimates are those of :func:`dobhil.identify.fit.identify`
    (Coulomb friction and the torque gain reported not identifiable: held at 0 and 1).
    ``contact`` False: a run that never reached its environment (no contact segment found,
    :func:`dobhil.identify.data.find_segments`): the servo alone is fitted, the environment
    reported not identifiable.

    BLAS runs on one thread throughout (:func:`dobhil.realtime.one_blas_thread`, as the
    open-loop fit does): the trust region's SVDs and the Jacobian's products are of a few
    columns, and a threaded OpenBLAS woke its pool for each (measured on the 2-core machine
    under load: seeds 0-3 of tests/identify/test_closedloop.py's record took 9.0-9.6 s of
    CPU with the default pool, 2.6-2.8 s on one thread; the same estimates bit for bit)."""
    from dobhil.realtime import one_blas_thread
    with one_blas_thread():
        return _identify_closed_loop(record, contact, progress)


def _identify_closed_loop(record: LoopRecord, contact: bool,
                          progress: Callable[[str], object] | None) -> IdentResult:
    start = _x0(record)
    scale = np.array([abs(start[n]) or 1.0 for n in _VARIED])
    scale[4] = max(abs(start["contact_position"]), 1e-3)
    scale[5] = record.model.period
    scale[2], scale[3] = 1e4, 1e2
    scale[6] = max(record.model.count, 1e-6)
    vary = np.array([i for i, n in enumerate(_VARIED)
                     if contact or n not in ("stiffness", "damping", "contact_position")])
    problem = _Problem(record, scale, vary, progress)
    probe = _Problem(_head(record, _PROBE), scale, vary, progress)
    full_lo, full_hi = _bounds(record, start)
    lo, hi = full_lo[vary], full_hi[vary]
    scale_v = scale[vary]
    x = np.clip(np.array([start[n] for n in _VARIED]) / scale, full_lo / scale, full_hi / scale)
    starts = _grid_starts(probe, x)
    rv, ru = probe.parts(starts[0])
    probe.weights = _weights(rv, ru, probe.record)
    fits = [_local(probe, start_x, lo / scale_v, hi / scale_v) for start_x in starts]
    fit = min(fits, key=lambda f: float(f.cost))
    x = fit.x
    for _ in range(_ROUNDS):
        rv, ru = problem.parts(x)
        problem.weights = _weights(rv, ru, record)
        fit = _local(problem, x, lo / scale_v, hi / scale_v)
        x = fit.x
    if _rms(problem.parts(x)[0]) <= NOISE_FLOOR * _rms(record.velocity):
        fit = _polished(problem, fit, lo / scale_v, hi / scale_v)
        x = fit.x
    for attempt in range(_REFITS + 1):
        # the residual in the weights the Jacobian was taken in: the sandwich is invariant to
        # the weights' scale only when both carry the same
        r = problem(x)
        rv = r[:record.samples] * problem.weights[0]
        jac = np.asarray(fit.jac, float)
        cov = _sandwich(jac, r, record.samples)
        values = problem.values(x)
        sd = np.full(len(_VARIED), math.nan)
        full_cov = np.full((len(_VARIED), len(_VARIED)), math.nan)
        if cov is not None:
            with np.errstate(invalid="ignore"):   # a rounding-negative variance: NaN, not identifiable
                sd[vary] = np.sqrt(np.diag(cov)) * scale_v
            full_cov[np.ix_(vary, vary)] = cov * np.outer(scale_v, scale_v)   # the parameters' own units
        folded = contact and _fold_friction(values, sd, full_cov)
        estimates = _estimates(values, sd, record, full_lo, full_hi, contact, folded)
        profile = _Profile(problem, x, lo / scale_v, hi / scale_v, r, record.samples)
        estimates = _profiled(estimates, profile, values, sd, vary, record, folded)
        if profile.lower is None or attempt == _REFITS:
            break
        # a held refit ended below the fit: the fit had stopped short of the minimum, and
        # intervals measured from its cost would be wrong; fit again from there
        fit = _local(problem, profile.lower, lo / scale_v, hi / scale_v)
        x = fit.x
    return IdentResult(estimates=estimates,
                       correlations=_correlations(full_cov if cov is not None else None),
                       residual=_whiteness(rv, _rms(record.velocity)),
                       segments=(Segment(0, record.samples, "contact" if contact else "free"),),
                       period=record.model.period,
                       initial=((record.initial[0], 0.0),),
                       fitted=MappingProxyType({n: float(values[n]) for n in FITTED}))


#: the correlation of the servo's friction and the environment's damping beyond which the
#: record tells only their sum (a run pressed all along: both act on the same velocity)
_SUM_CORRELATION = 0.99
_FRICTION, _DAMPING = FITTED.index("viscous_friction"), FITTED.index("damping")


def _fold_friction(values: dict[str, float], sd: Array, cov: Array) -> bool:
    """Whether the record determines only ``viscous_friction + damping`` (their estimates'
    correlation below -:data:`_SUM_CORRELATION`, ``cov`` in the parameters' own units); if so
    the sum is reported as the damping, with its standard error
    ``sqrt(var_b + var_D + 2 cov_bD)``, and the friction held at 0 (``values``, ``sd`` and
    ``cov`` changed in place): a linear combination the data fix, rather than two numbers the fit
    traded against each other along a flat valley (measured: b 13.4 and D 46.6 for a true
    0.05 and 60 on the pressed run of tests/identify/test_closedloop.py).

    The covariance becomes the sum's, ``T cov T^T`` with ``T`` adding the friction's row to the
    damping's, and the friction's row and column NaN (held): the correlations reported and the
    overlay's covariance (what ``dobhil montecarlo --draw-from`` draws from) are then of the
    damping reported, not of D alone, which moves against b (on docs/identify.md section 5's
    force1.mcap D alone is correlated -0.40 with the inertia, -0.62 with the contact position
    and +0.69 with the delay; the sum -0.05, -0.02 and +0.29)."""
    var_b, var_d, c = cov[_FRICTION, _FRICTION], cov[_DAMPING, _DAMPING], cov[_FRICTION, _DAMPING]
    if not (np.isfinite(c) and var_b > 0.0 and var_d > 0.0) or c / math.sqrt(var_b * var_d) > -_SUM_CORRELATION:
        return False
    values["damping"] += values["viscous_friction"]
    values["viscous_friction"] = 0.0
    fold_covariance(cov, _FRICTION, _DAMPING)
    sd[_DAMPING] = math.sqrt(cov[_DAMPING, _DAMPING])
    return True


# -- the profile-likelihood intervals ----------------------------------------------------

#: secant rounds per end of a profile interval (:meth:`_Profile.end`)
_PROFILE_ROUNDS = 3
#: a held refit below the fit's cost by more than this part of the interval's rise means the
#: fit stopped short of the minimum (measured: seed 7 of tools/closed_loop_coverage.py's
#: records, its stiffness fitted at 1.03e4 and the cost lower at the true 1.5e4)
_LOWER = 0.05
#: fits again from such a point before the intervals are kept as they are
_REFITS = 2
#: the parameters whose interval is the profile likelihood's, or for the scale parameters
#: the hull of it and the sandwich's (:func:`_profiled`; the others: the sandwich's)
PROFILED = ("delay", "inertia", "stiffness", "damping")


class _Held(_Problem):
    """:class:`_Problem` with varied parameter ``k`` (of ``base.vary``) held at ``value``
    (scaled): the others vary."""

    def __init__(self, base: _Problem, k: int, value: float) -> None:
        super().__init__(base.record, base.scale, np.delete(base.vary, k), None)
        self.weights, self.base, self.k, self.value = base.weights, base, k, value

    def values(self, x: Array) -> dict[str, float]:
        return self.base.values(np.insert(x, self.k, self.value))


@dataclass
class _Profile:
    """The profile likelihood of the fit at ``x`` (scaled, varied parameters) on ``problem``:
    for a parameter held at a value, the least sum of squares over the others (a fit, as
    the fit's own, from the fit's values); the 95 % interval is where it stays within
    ``chi2_1(0.95) s^2`` of the best (Bates and Watts, *Nonlinear Regression Analysis and
    Its Applications*, 1988, section 6.1; each end followed as Venzon and Moolgavkar,
    *Applied Statistics* 37, 1988, do). ``s^2``: the velocity rows' mean square over
    ``samples - p`` (each signal is in units of its own noise, :func:`_weights`).

    For the delay (:data:`PROFILED`), whose cost is not quadratic over its interval: its
    truth (0.3 ms on the 1 ms period of tools/closed_loop_coverage.py's records) lies within
    a standard error of its bound 0, and the command's fraction of a period moves the
    plant's ZOH calls, not a smooth gain. Measured on those 50 seeded records: the
    linearised intervals held it in 38 of 44; the likelihood ratio at the true delay (the
    others refitted) stayed within chi2_1(0.95) on 48 of 50, and these intervals held it in
    39 of the 41 where they are narrow enough to report (docs/identify.md). For the inertia,
    stiffness and damping the profile and the sandwich each miss records the other holds;
    their hull is reported (:func:`_profiled`)."""

    problem: _Problem
    x: Array
    lo: Array
    hi: Array
    r: Array
    samples: int

    def __post_init__(self) -> None:
        rv = self.r[:self.samples]
        self.lower: Array | None = None
        self.lowest = math.inf
        self.best = float(self.r @ self.r)
        s2 = float(rv @ rv) / max(self.samples - self.x.size, 1)
        self.rise = float(scipy.stats.chi2.ppf(LEVEL, 1)) * s2

    def held_cost(self, k: int, value: float) -> float:
        """The least sum of squares with varied parameter ``k`` held at ``value`` (scaled),
        the others refitted from the fit's values (:func:`_local`). One below the fit's own
        by more than :data:`_LOWER` of :attr:`rise` is kept in :attr:`lower` (all the varied
        parameters, scaled): the fit was not the minimum."""
        held = _Held(self.problem, k, value)
        rest = np.delete(self.x, k)
        lo, hi = np.delete(self.lo, k), np.delete(self.hi, k)
        fit = _local(held, rest, lo, hi)
        cost = 2.0 * float(fit.cost)
        if cost < self.best - _LOWER * self.rise and (self.lower is None or cost < self.lowest):
            self.lower, self.lowest = np.insert(fit.x, k, value), cost
        return cost

    def end(self, k: int, guess: float, *, beyond: bool = False) -> float:
        """The end of ``k``'s 95 % profile interval on the side of ``guess`` (scaled; the
        linearised end): where the held cost rises :attr:`rise` above the best, found as
        :func:`dobhil.identify.fit._profile_high` finds its (the square root of the rise
        about linear in the distance, exact for a quadratic profile), capped at the search's
        bound. ``beyond``: only an end beyond ``guess`` is wanted (a hull with the interval
        ``guess`` ends): where the profile has risen past its threshold at ``guess`` already,
        ``guess`` is returned after that one refit."""
        value = float(self.x[k])
        d = guess - value
        for i in range(_PROFILE_ROUNDS):
            d = min(max(value + d, self.lo[k]), self.hi[k]) - value
            if d == 0.0:
                break
            rise = self.held_cost(k, value + d) - self.best
            if beyond and i == 0 and rise >= self.rise:
                break
            nxt = d * (4.0 if rise <= 0.01 * self.rise else min(math.sqrt(self.rise / rise), 4.0))
            done = abs(nxt - d) <= 0.05 * abs(d)
            d = nxt
            if done:
                break
        return min(max(value + d, float(self.lo[k])), float(self.hi[k]))


def _profiled(estimates: dict[str, Estimate], profile: _Profile, values: Mapping[str, float],
              sd: Array, vary: Array, record: LoopRecord, folded: bool = False) -> dict[str, Estimate]:
    """The estimates with the interval of each of :data:`PROFILED` from the profile
    likelihood (:class:`_Profile`), each end followed from the sandwich's, and judged by
    :func:`_estimates`' width rule again: one the sandwich called too wide is profiled too (its
    interval may be narrower), one on its search's bound is not (the record does not
    determine it), nor a damping reported as the sum with the friction (``folded``: D alone
    slides along the sum's valley, and the sum's interval is the sandwich's).

    The delay's interval is the profile's, the standard error its width over ``2 z``. Those of
    :data:`LOG_SCALE` are the hull of the profile's and the log-linearised one
    (method "hull"), judged on the log scale (the sandwich's rule on the log scale: half the
    log of ``high / low`` within :data:`WIDEST`); their standard error stays the
    sandwich's. Why the hull, from the seeded records of tools/closed_loop_coverage.py
    (docs/identify.md, "Coverage"): neither interval covers the other's records. On the
    4 s records at 0.05 rad/s of noise the log-linearised intervals held J, K, D in 45, 44, 44
    of 50 and the profile's in 43, 39, 44; on 16 s records at 0.01 rad/s, where the errors
    are within 2 %, the log-linearised held 44, 50, 43 and the profile's 47, 48, 46. Where the
    two disagree the cost is not quadratic over the interval and neither approximation is the
    better one. The hull, judged as here and with a fit that stopped short fitted again
    (:data:`_LOWER`), held 46, 46, 45 and 48, 50, 46."""
    z = float(scipy.stats.norm.ppf(0.5 + LEVEL / 2))
    out = dict(estimates)
    position = {int(i): j for j, i in enumerate(vary)}
    for name in PROFILED:
        e, i = estimates[name], FITTED.index(name)
        k = position.get(i)
        if (k is None or not math.isfinite(float(sd[i])) or (folded and i == _DAMPING)
                or not (e.identifiable or e.why.startswith("flat profile"))):
            continue
        value, s = float(values[name]), float(profile.problem.scale[vary[k]])
        hull = name in LOG_SCALE
        down, up = ((e.low, e.high) if hull and e.identifiable
                    else (value - z * float(sd[i]), value + z * float(sd[i])))
        beyond = hull and e.identifiable
        low = profile.end(k, down / s, beyond=beyond) * s
        high = profile.end(k, up / s, beyond=beyond) * s
        if hull and e.identifiable:
            low, high = min(low, e.low), max(high, e.high)
        half = max(high - value, value - low)
        wide = (not low > 0.0 or 0.5 * math.log(high / low) > WIDEST if hull
                else half > WIDEST * abs(value) + _floors(record).get(name, 0.0))
        if wide:
            out[name] = Estimate(name, math.nan, math.nan, math.nan, math.nan, False,
                                 f"flat profile: the 95 % profile interval (+-{half:.3g}) is too "
                                 f"wide for the value ({value:.3g}) on this run")
            continue
        stderr = float(sd[i]) if hull else (high - low) / (2.0 * z)
        out[name] = Estimate(name, value, stderr, low, high, True, "", method="hull" if hull else "profile")
    return out


def _floors(record: LoopRecord) -> dict[str, float]:
    """The absolute part of the width rule: a friction or delay near 0 is judged against
    these, not against its own value."""
    return {"viscous_friction": 0.01 * (float(np.max(np.abs(record.torque))) or 1.0)
            / (float(np.max(np.abs(record.velocity))) or 1.0), "delay": record.model.period}


def _head(record: LoopRecord, samples: int) -> LoopRecord:
    """The record's first ``samples`` cycles (the whole record when shorter)."""
    if record.samples <= samples:
        return record
    return replace(record, reference=record.reference[:samples], position=record.position[:samples],
                   velocity=record.velocity[:samples], torque=record.torque[:samples])


def _local(problem: _Problem, x: Array, lo: Array, hi: Array, *, step: float = _DIFF_STEP,
           tol: float = _TOL) -> Any:
    """scipy's bounded trust-region least squares from ``x``, central differences (the
    exact trust-region solver: LSMR's steps, measured, saved the SVDs -- 5 of 23 s on a
    53 s record -- but stopped short: J 0.391 [0.377, 0.404] for 0.37)."""
    return scipy.optimize.least_squares(problem, np.clip(x, lo, hi), bounds=(lo, hi),
                                        jac=_differences(problem, lo, hi, step), x_scale="jac",
                                        method="trf", ftol=tol, xtol=tol)


#: the difference steps of :func:`_polished`, each fit started where the coarser one ended
_POLISH_STEPS = (1e-3, 1e-4, 1e-5)
#: and their relative tolerances (the cost of a noise-free record falls by orders of
#: magnitude on the way: 1e-6 of it stops on the first plateau)
_POLISH_TOL = 1e-12


def _polished(problem: _Problem, fit: Any, lo: Array, hi: Array) -> Any:
    """The fit of a record whose residual is rounding (:data:`NOISE_FLOOR`: a noise-free
    emulated run), refined with ever finer differences; each kept only if it lowers the
    cost. The 1 % secant of :data:`_DIFF_STEP` spans the contact's washboard, right under
    noise, but on a noise-free record the cost is smooth at finer scales and the secant's
    error is what stops the fit (measured: a 0.5 s lockstep demo run ended at J 0.250524,
    K 10046.7 for 0.25 and 10000, residual 1.6e-5 rad/s, the truth's 3.3e-9, with 95 %
    intervals of +-0.04 % that excluded it; polished: residual 5.9e-10, every interval
    holding the truth)."""
    for step in _POLISH_STEPS:
        finer = _local(problem, fit.x, lo, hi, step=step, tol=_POLISH_TOL)
        if float(finer.cost) < float(fit.cost):
            fit = finer
    return fit


def _differences(problem: _Problem, lo: Array, hi: Array, step: float = _DIFF_STEP) -> Callable[[Array], Array]:
    """The Jacobian by central differences of ``step`` times ``max(1, |x|)`` in the
    scaled parameters (each near 1 at the start), shortened to one side at a bound. Not
    scipy's ``diff_step``: that step is relative to ``|x|`` alone, so a parameter near 0 (a
    friction or delay at its bound, the contact at the origin) got steps of 1e-12 and a
    derivative of the cost's kinks (measured: b's standard error 2e-9 for an estimate of
    1e-10 and a truth of 0.05)."""
    def jac(x: Array) -> Array:
        h = step * np.maximum(1.0, np.abs(x))
        cols = []
        for i in range(x.size):
            up, down = x.copy(), x.copy()
            up[i], down[i] = min(x[i] + h[i], hi[i]), max(x[i] - h[i], lo[i])
            cols.append((problem(up) - problem(down)) / (up[i] - down[i]))
        return np.column_stack(cols)
    return jac


def _weights(rv: Array, ru: Array, record: LoopRecord) -> tuple[float, float]:
    """Each signal's residual RMS: its rows in units of its own noise. The torque's floored:
    a design whose torque does not depend on the measurement (the demo's, C_f J_mi = J_mn)
    leaves it ~0 at the optimum."""
    return (max(_rms(rv), 1e-12), max(_rms(ru), 1e-6 * (_rms(record.torque) or 1.0)))


def _rms(x: Array) -> float:
    return float(np.sqrt(np.mean(np.square(x)))) if x.size else 0.0


def _estimates(values: Mapping[str, float], sd: Array, record: LoopRecord, lo: Array,
               hi: Array, contact: bool, folded: bool = False) -> dict[str, Estimate]:
    from dobhil.identify.fit import PARAMETERS
    z = float(scipy.stats.norm.ppf(0.5 + LEVEL / 2))
    floors = _floors(record)
    nan = math.nan
    out: dict[str, Estimate] = {}
    for name in PARAMETERS:
        if name not in FITTED:
            why = ("held at 1: torque and motion alone cannot tell it" if name == "torque_gain"
                   else "held at 0: the closed-loop model has no Coulomb friction")
            out[name] = Estimate(name, nan, nan, nan, nan, False, why)
            continue
        if not contact and name in ("stiffness", "damping", "contact_position"):
            out[name] = Estimate(name, nan, nan, nan, nan, False, "no contact segment in the record")
            continue
        if folded and name == "viscous_friction":
            out[name] = Estimate(name, nan, nan, nan, nan, False,
                                 "acts with the environment's damping as their sum on this run (pressed "
                                 "all along): held at 0, the damping reported is the sum")
            continue
        i = FITTED.index(name)
        value, s = values[name], float(sd[i])
        if _at_bound(value, float(lo[i]), float(hi[i])):
            out[name] = Estimate(name, nan, nan, nan, nan, False, _bound_reason(name, value))
            continue
        low, high, method = _interval(name, value, s, z, float(lo[i]), float(hi[i]))
        half = z * s
        wide = (half > float(np.ptp(record.position)) if name == "contact_position"
                else half > WIDEST * abs(value) + floors.get(name, 0.0))
        if not math.isfinite(s) or wide:
            out[name] = Estimate(name, nan, nan, nan, nan, False,
                                 f"flat profile: the 95 % interval (+-{half:.3g}) is too wide for "
                                 f"the value ({value:.3g}) on this run")
            continue
        out[name] = Estimate(name, value, s, low, high, True, "", method=method)
    return out


#: the parameters whose sandwich interval is taken on the log scale (:func:`_interval`)
LOG_SCALE = ("inertia", "stiffness", "damping")


def _interval(name: str, value: float, s: float, z: float, lo: float,
              hi: float) -> tuple[float, float, str]:
    """The 95 % interval of an estimate ``value`` with standard error ``s`` (the sandwich's),
    capped at the search's bounds ``lo``, ``hi``, and how it was found.

    Of :data:`LOG_SCALE` -- the inertia, stiffness and damping, positive scale parameters --
    the linearisation is that of ``log value``, whose standard error is ``s / value`` (the
    delta method): ``value * exp(+-z s / value)``, longer above the estimate than below.
    Why: a linearised interval is only as good as the parametrisation is close to linear
    (Bates and Watts, *Nonlinear Regression Analysis and Its Applications*, 1988, chapter 7,
    parameter-effects curvature; Ratkowsky, *Nonlinear Regression Modeling*, 1983), and the
    standard error of these grows with the estimate -- the spread of a scale, not a location:
    over the 50 seeded records of tools/closed_loop_coverage.py the correlation of the
    estimate and its standard error was +0.54 for the stiffness and +0.43 for the damping
    (a low estimate got a short interval, which then missed the truth above it: K's misses
    were 8 low of 10); the inertia's was -0.24, it is on the same scale as the positive
    scale parameter it is (its interval's low end stays above 0 however wide). Measured
    (docs/identify.md, "Coverage"): J, K, D held in 45, 44, 44 of those 50 (linear: 44, 40,
    43) and in 41, 45, 42 of seeds 100-149, not looked at before (linear: 40, 45, 42). The
    estimate and its standard error are unchanged. Others (the friction and delay near 0,
    the contact position, a location): ``value +- z s``."""
    if name in LOG_SCALE and value > 0.0 and math.isfinite(s):
        f = math.exp(z * s / value)
        return max(value / f, lo), min(value * f, hi), "log-linearised"
    return max(value - z * s, lo), min(value + z * s, hi), "linearised"


def _at_bound(value: float, lo: float, hi: float) -> bool:
    """Whether the fit ended on a bound of its search (within 1e-9 of the search's span:
    the solver keeps its iterates strictly inside, by ~1e-10 of a scaled unit)."""
    tol = 1e-9 * (hi - lo)
    return value - lo <= tol or hi - value <= tol


def _bound_reason(name: str, value: float) -> str:
    """Why an estimate on its bound is no number: the sandwich interval is a local quadratic
    approximation about an interior minimum; on a bound the cost's slope is not zero and the
    interval it gives is meaningless (measured: a viscous friction of 1e-10 with a 95 %
    interval of +-3e-11 on a pressed run whose true friction is 0.05)."""
    why = f"the fit ran to the bound of its search ({value:.3g}): the record does not determine it"
    if name == "viscous_friction":
        why += " (while pressed it acts with the environment's damping as their sum)"
    return why


def _correlations(cov: Array | None) -> dict[tuple[str, str], float]:
    if cov is None:
        return {}
    with np.errstate(invalid="ignore"):
        sd = np.sqrt(np.diag(cov))
    # the nuisance (the initial position) and held parameters (NaN) left out
    return {(a, b): float(np.clip(cov[i, j] / (sd[i] * sd[j]), -1.0, 1.0))
            for i, a in enumerate(FITTED) for j, b in enumerate(FITTED)
            if i < j and np.isfinite(sd[i] * sd[j]) and sd[i] * sd[j] > 0}
