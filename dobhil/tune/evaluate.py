"""Every metric tune needs, for a batch of designs times a batch of plant/environment points.

One batch through the synthesis (:func:`~dobhil.synthesis.loop.loop` of the sampled,
delayed loop at C_f = 0, the open loop L of Eq. 26), then, all vectorised over
``designs x points``:

- stability at C_f: eigenvalues of ``A(C_f) = A(0) - C_f B_per C_int^`` inside the unit circle;
- gain margin: the largest gain k with ``(0, k)`` all stable (the exact gain map of
  :mod:`dobhil.analysis.stability`) over C_f, in dB;
- phase margin and peak sensitivity ``max |1 / (1 + C_f L)|``: from L's frequency response
  on :data:`FREQUENCIES` points up to Nyquist (L = N / D from its poles and zeros);
- the force step: reference to the TRUE interaction torque ``tau_int`` (what the robot
  applies, not the estimate), simulated sample by sample for the whole batch at once; its
  10-90 % rise time;
- the force loop's bandwidth: the lowest frequency where ``|tau_int / tau_ref|`` falls
  3 dB below its DC gain;
- optionally the quantisation noise of the estimate ``tau_int^`` (RMS, N m) from
  per-channel H2 norms (:mod:`dobhil.analysis.quantisation`'s model, batched here).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from dobhil.analysis.polynomials import poly_from_roots, zeros_and_numerator
from dobhil.analysis.stability import gain_map, is_stable
from dobhil.config.schema import Config
from dobhil.synthesis.controller import sampled_controller
from dobhil.synthesis.loop import LoopSS, loop, sampled_plant
from dobhil.synthesis.params import params_from_config
from dobhil.tune.problem import DECISION_KEYS

Array = np.ndarray

#: frequency points of L's response (log spaced from 1e-3 / T to Nyquist)
FREQUENCIES = 300

#: what an unanswerable metric counts as: clearly violating, finite (the optimiser compares)
WORST = {"gm_db": -100.0, "pm_deg": -180.0, "ms_db": 100.0}


@dataclass(frozen=True)
class Metrics:
    """Per design (axis 0) and point (axis 1). A point that is unstable at C_f has the
    :data:`WORST` values for everything but ``radius`` and ``gm_db`` (gm_db < 0 there)."""

    radius: Array       # largest closed-loop pole magnitude at C_f
    stable: Array
    gm_db: Array        # 20 log10(max stable gain / C_f); inf: unbounded
    pm_deg: Array       # worst phase margin over the gain crossings; inf: no crossing
    ms_db: Array        # peak sensitivity
    rise_time: Array    # 10-90 % of the force step [s]; inf: not within the horizon
    overshoot: Array    # of the force step over its final value [%] (within the horizon)
    bandwidth: Array    # -3 dB of reference -> force [rad/s]
    noise: Array | None  # RMS of tau_int^ from the quantisation [N m]


@dataclass(frozen=True)
class Quanta:
    """Quantisation steps the drive puts on the measurements and the torque (0: none)."""

    position: float
    velocity: float
    torque: float


def evaluate(config: Config, designs: Array, points: Mapping[str, Array], *,
             horizon: int, quanta: Quanta | None = None, bandwidth: bool = True,
             plant: tuple[Array, Array, Array] | None = None) -> Metrics:
    """Metrics of ``designs`` (S x 4, the values of :data:`DECISION_KEYS`) at every point
    (``bandwidth`` False: not computed, NaN -- a frequency response of the closed loop is
    the costliest metric, and the rise-time search does not need it). ``plant``: the
    points' :func:`point_plant`, when the caller evaluates the same points many times."""
    arrays = {k.replace(".", "__"): np.asarray(designs[:, i], float)[:, None]
              for i, k in enumerate(DECISION_KEYS)}
    arrays.update({k.replace(".", "__"): np.asarray(v, float)[None, :] for k, v in points.items()})
    params = params_from_config(config, **arrays)
    with np.errstate(all="ignore"):
        design_only = params_from_config(config, **{k: v for k, v in arrays.items()
                                                    if k.startswith("design__")})
        open_loop = loop(params, sampled=True, force_gain=0.0,
                         controller=sampled_controller(design_only),
                         plant=plant if plant is not None else point_plant(config, points))
        a, b, c, _ = open_loop.siso("tau_per", "tau_int_hat")
        _, _, c_force, _ = open_loop.siso("tau_per", "tau_int")
        cf = params.value("force_gain")
        return _metrics(a, b, c, c_force, cf, float(config.loop.period), horizon, bandwidth,
                        _noise_inputs(open_loop, quanta, _controller_rows(config, a.shape[-1])))


def point_plant(config: Config, points: Mapping[str, Array]) -> tuple[Array, Array, Array]:
    """The sampled plant (:func:`~dobhil.synthesis.loop.sampled_plant`) at each point, batch
    ``(1, P)``: it depends on the points only, not on the design."""
    arrays = {k.replace(".", "__"): np.asarray(v, float)[None, :] for k, v in points.items()}
    with np.errstate(all="ignore"):
        return sampled_plant(params_from_config(config, **arrays))


def _controller_rows(config: Config, order: int) -> slice:
    """The controller's states in the loop's ``[x_p, xi, commands in transit]``."""
    d = config.design
    chain = d.delay_samples + (1 if d.input_delay > 0 else 0)
    return slice(2, order - chain)


def _metrics(a: Array, b: Array, c: Array, c_force: Array, cf: Array, period: float, horizon: int,
             want_bandwidth: bool,
             noise_in: tuple[Array, Array, Array] | None) -> Metrics:
    cfe = cf[..., None, None]
    a_cl = a - cfe * (b @ c)
    ok = np.all(np.isfinite(a_cl), axis=(-2, -1))
    a_cl = np.where(ok[..., None, None], a_cl, 0.0)
    poles = np.linalg.eigvals(a_cl)
    radius = np.where(ok, np.max(np.abs(poles), axis=-1), np.inf)
    stable = ok & is_stable(poles, True)
    gm = _gain_margin_db(a, b, c, cf, stable)
    pm, ms = _loop_shape(a, b, c, cf, period, stable)
    rise, overshoot = _step(a_cl, cfe * b, c_force, period, horizon, stable)
    bw = (_bandwidth(a_cl, cfe * b, c_force, period, stable) if want_bandwidth
          else np.full(cf.shape, np.nan))
    noise = None if noise_in is None else _noise(a_cl, *_closed(noise_in, b, cf), c, stable)
    return Metrics(radius=radius, stable=stable, gm_db=gm, pm_deg=pm, ms_db=ms, rise_time=rise,
                   overshoot=overshoot, bandwidth=bw, noise=noise)


def _gain_margin_db(a: Array, b: Array, c: Array, cf: Array, stable: Array) -> Array:
    """From the exact gain map, computed for the points stable at C_f only (the others
    have no margin: the largest stable gain is below C_f)."""
    out = np.full(cf.shape, WORST["gm_db"])
    if stable.any():
        kmax = _max_stable_gain(a[stable], b[stable], c[stable])
        with np.errstate(divide="ignore"):
            out[stable] = np.where(kmax > 0, 20.0 * np.log10(kmax / cf[stable]), WORST["gm_db"])
    return out


def _max_stable_gain(a: Array, b: Array, c: Array) -> Array:
    """The gain map's largest stable gain; a batch numpy cannot decompose is answered point
    by point, and a point it cannot answer has none (0: no margin), as the sweep does."""
    try:
        return np.asarray(gain_map(a, b, c, sampled=True).max_stable_gain)
    except (np.linalg.LinAlgError, ValueError):
        out = np.zeros(a.shape[0])
        for i in range(a.shape[0]):   # only after a failure: find the point(s) at fault
            try:
                out[i] = gain_map(a[i:i + 1], b[i:i + 1], c[i:i + 1], sampled=True).max_stable_gain[0]
            except (np.linalg.LinAlgError, ValueError):
                continue
        return out


def frequency_grid(period: float) -> Array:
    return np.geomspace(1e-3 / period, np.pi / period, FREQUENCIES)


def _open_loop_response(a: Array, b: Array, c: Array, period: float) -> Array:
    """L(e^{jwT}) on :func:`frequency_grid`, batch + (F,), from L = N / D."""
    _, num, _ = zeros_and_numerator(a, b, c)
    den = poly_from_roots(np.linalg.eigvals(a))
    z = np.exp(1j * frequency_grid(period) * period)
    powers = z[:, None] ** np.arange(num.shape[-1] - 1, -1, -1)      # (F, n+1)
    return (num @ powers.T) / (den @ powers.T)


def _loop_shape(a: Array, b: Array, c: Array, cf: Array, period: float,
                stable: Array) -> tuple[Array, Array]:
    """(phase margin [deg], peak sensitivity [dB]) of C_f L at the stable points."""
    pm = np.full(cf.shape, WORST["pm_deg"])
    ms = np.full(cf.shape, WORST["ms_db"])
    if not stable.any():
        return pm, ms
    loop_f = cf[stable][:, None] * _open_loop_response(a[stable], b[stable], c[stable], period)
    ms[stable] = 20.0 * np.log10(np.max(1.0 / np.abs(1.0 + loop_f), axis=-1))
    pm[stable] = _phase_margin(loop_f)
    return pm, ms


def _phase_margin(loop_f: Array) -> Array:
    """Worst phase margin over every crossing of |L| = 1 on the grid (interpolated in
    log |L|); inf where |L| never crosses 1."""
    mag = np.log(np.abs(loop_f))
    cross = (mag[:, :-1] > 0) != (mag[:, 1:] > 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        w = mag[:, :-1] / (mag[:, :-1] - mag[:, 1:])
    value = loop_f[:, :-1] + np.nan_to_num(w) * (loop_f[:, 1:] - loop_f[:, :-1])
    margin = np.mod(np.degrees(np.angle(value)) + 180.0, 360.0)
    margin = np.where(margin > 180.0, margin - 360.0, margin)
    return np.min(np.where(cross, margin, np.inf), axis=-1)


def _step(a_cl: Array, b_ref: Array, c_out: Array, period: float, horizon: int,
          stable: Array) -> tuple[Array, Array]:
    """(10-90 % rise time, overshoot [%]) of the unit step from reference to force,
    ``horizon`` samples simulated for the whole batch; inf where unstable (the rise time
    also where 90 % is not reached within the horizon)."""
    out = np.full(stable.shape, np.inf)
    over = np.full(stable.shape, np.inf)
    if not stable.any():
        return out, over
    ys, final = simulate_step(a_cl[stable], b_ref[stable][..., 0], c_out[stable][..., 0, :], horizon)
    # a step that reaches neither 10 % nor 90 % would give inf - inf = NaN, which no
    # comparison ranks: it has not risen, so its rise time is infinite
    rise90 = _crossing(ys, 0.9 * final)
    out[stable] = np.where(np.isfinite(rise90), (rise90 - _crossing(ys, 0.1 * final)) * period, np.inf)
    with np.errstate(divide="ignore", invalid="ignore"):
        peak = np.where(final >= 0, ys.max(axis=-1), ys.min(axis=-1))
        over[stable] = np.where(final != 0, np.maximum(0.0, (peak - final) / final * 100.0), np.inf)
    return out, over


def simulate_step(a: Array, b: Array, c: Array, horizon: int) -> tuple[Array, Array]:
    """(outputs y_0 .. y_{horizon-1}, final value) of ``x+ = A x + b, y = c x`` from rest,
    a batch of stable systems (a: batch x n x n; b, c: batch x n): a loop over time, each
    step one batched product."""
    n = a.shape[-1]
    final = np.einsum("bi,bi->b", c, np.linalg.solve(np.eye(n) - a, b[..., None])[..., 0])
    x = np.zeros_like(b)
    ys = np.empty((a.shape[0], horizon))
    for k in range(horizon):
        ys[:, k] = np.einsum("bi,bi->b", c, x)
        x = np.einsum("bij,bj->bi", a, x) + b
    return ys, final


def force_step(config: Config, design: Array, point: Mapping[str, float],
               horizon: int) -> tuple[Array, Array] | None:
    """(t, force) of the unit reference step for one design at one point (None: unstable),
    for the report's figure."""
    arrays = {k.replace(".", "__"): float(v) for k, v in zip(DECISION_KEYS, design)}
    arrays.update({k.replace(".", "__"): float(v) for k, v in point.items()})
    params = params_from_config(config, **arrays)
    with np.errstate(all="ignore"):
        closed = loop(params, sampled=True)
    a, b, c, _ = closed.siso("tau_ref", "tau_int")
    if not is_stable(np.linalg.eigvals(a)[None], True)[0]:
        return None
    ys, _ = simulate_step(a[None], b[None, :, 0], c[None, 0, :], horizon)
    return np.arange(horizon) * float(config.loop.period), ys[0]


def _crossing(ys: Array, level: Array) -> Array:
    """First (fractional) sample index where ys reaches ``level`` (inf: never)."""
    sign = np.where(level >= 0, 1.0, -1.0)[:, None]
    above = sign * ys >= sign * level[:, None]
    first = np.argmax(above, axis=-1)
    reached = above.any(axis=-1) & (level != 0)
    i = np.maximum(first, 1)
    y0 = np.take_along_axis(ys, (i - 1)[:, None], -1)[:, 0]
    y1 = np.take_along_axis(ys, i[:, None], -1)[:, 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        frac = np.where(first == 0, 0.0, (level - y0) / (y1 - y0))
    return np.where(reached, i - 1 + frac, np.inf)


def _bandwidth(a_cl: Array, b_ref: Array, c_out: Array, period: float, stable: Array) -> Array:
    """Lowest frequency of :func:`frequency_grid` where |reference -> force| is 3 dB below
    its DC gain (Nyquist when it never is)."""
    out = np.zeros(stable.shape)
    if not stable.any():
        return out
    a_s, b_s, c_s = a_cl[stable], b_ref[stable], c_out[stable]
    w = frequency_grid(period)
    n = a_s.shape[-1]
    z = np.exp(1j * w * period)[None, :, None, None]
    resp = c_s[:, None] @ np.linalg.solve(z * np.eye(n) - a_s[:, None], b_s[:, None])
    mag = np.abs(resp[..., 0, 0])
    dc = np.abs(c_s @ np.linalg.solve(np.eye(n) - a_s, b_s))[:, 0, 0]
    below = mag < dc[:, None] / np.sqrt(2.0)
    out[stable] = np.where(below.any(axis=-1), w[np.argmax(below, axis=-1)], np.pi / period)
    return out


def _noise_inputs(open_loop: LoopSS, quanta: Quanta | None,
                  controller_rows: slice) -> tuple[Array, Array, Array] | None:
    """The loop's input columns (B and the estimate's D) of each quantised channel and its
    white-noise RMS (step / sqrt(12), the truncation's variance): the measurement noise
    inputs, and the applied-torque error, which reaches the plant but not the observers
    (tau_per's column with the controller's rows zeroed, as
    :func:`dobhil.analysis.quantisation.torque_error_column` does for one design)."""
    if quanta is None:
        return None
    names = ("eta_q", "eta_dq", "tau_per")
    b = np.stack([open_loop.b[..., :, open_loop.input_index(k)] for k in names], axis=-1)
    b[..., controller_rows, 2] = 0.0
    row = open_loop.output_index("tau_int_hat")
    d = np.stack([open_loop.d[..., row, open_loop.input_index(k)] for k in names], axis=-1)[..., None, :]
    d[..., 2] = 0.0
    steps = np.array([quanta.position, quanta.velocity, quanta.torque]) / np.sqrt(12.0)
    return b, d, steps


def _closed(noise_in: tuple[Array, Array, Array], b_per: Array,
            cf: Array) -> tuple[Array, Array, Array]:
    """The noise columns at C_f: a measurement reaches the command through the estimate
    too (``u = ... - C_f tau_int^``), so its column is the open loop's minus
    ``C_f B_per D_est`` -- as ``A(C_f) = A(0) - C_f B_per C_est``."""
    b, d, steps = noise_in
    b = b.copy()
    b[..., :2] -= cf[..., None, None] * b_per * d[..., :, :2]
    return b, d, steps


def _noise(a_cl: Array, columns: Array, feedthrough: Array, steps: Array, c_est: Array,
           stable: Array) -> Array:
    """RMS of tau_int^ in the closed loop from the channels' white noise: the H2 norm
    ``sqrt(C P C' + D D')`` with P the Gramian (the discrete Lyapunov equation, solved
    for the whole batch as one linear system in vec(P))."""
    out = np.full(stable.shape, np.inf)
    if not stable.any():
        return out
    a_s = a_cl[stable]
    n = a_s.shape[-1]
    bw = columns[stable] * steps
    dw = feedthrough[stable] * steps
    q = bw @ bw.swapaxes(-1, -2)
    kron = np.eye(n * n) - np.einsum("bij,bkl->bikjl", a_s, a_s).reshape(-1, n * n, n * n)
    gram = np.linalg.solve(kron, q.reshape(-1, n * n, 1)).reshape(-1, n, n)
    c_s = c_est[stable]
    value = (c_s @ gram @ c_s.swapaxes(-1, -2) + dw @ dw.swapaxes(-1, -2))[:, 0, 0]
    out[stable] = np.sqrt(np.maximum(value, 0.0))
    return out
