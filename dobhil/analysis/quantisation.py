"""What a drive codec's quantisation does to the force loop, as noise figures.

A protocol whose codec packs values into a few bits says so through its
:meth:`~dobhil.drives.plugin.DriveProtocol.quantisation` hook: a
:class:`~dobhil.drives.plugin.CodecQuantisation` with one step per channel, the sense in
which the codec truncates and the torque a zero command applies. The host then measures the
position and velocity one step apart, and the drive applies the commanded torque one step
apart. A codec that truncates (``int()`` of a non-negative number, as in C firmware) gives a
decoded value between one step below the true one and the true one. For a signal that moves
across several steps per sample the error is white and uniform on ``(-step, 0]``: mean
``-step / 2``, variance ``step^2 / 12`` (``direction`` -1, a reversed axis, truncates in
the drive's sense of rotation: the host sees the mean ``+step / 2``; a rounding codec has
mean 0). That is the noise model here, per channel, the channels independent:

- ``position`` and ``velocity``: the controller's measurements ``y`` (``[q, dq]``, or
  ``[q]`` when ``design.velocity_source`` is ``estimated``: the velocity filter then
  differentiates the quantised position). With a measured velocity and no friction or
  stiffness in the observers' models the position is multiplied by zero everywhere, and
  only the velocity counts (``measured`` lists what does). The reply's torque is not
  used by the controller.
- ``torque``: the torque the drive applies minus the one commanded. The observers are
  fed the commanded torque (what the controller computed), the plant gets the applied
  one. What a zero command applies (``CodecQuantisation.zero_torque``, the protocol's
  codec decodes it) is the zero-torque bias.

Each channel's contribution to an output is ``step / sqrt(12)`` times the H2 norm of the
discrete system from that channel to the output (``sqrt(C P C' + D D')`` with ``P`` the
controllability Gramian of the balanced realisation); the total is the root sum of
squares. The mean error gives a steady offset through the DC gain.

Two views, both from the matrices of the one synthesis
(:func:`~dobhil.synthesis.controller.sampled_controller`, and :func:`~dobhil.synthesis.loop.loop`
built on it):

- ``observers``: the DOb and RTOb alone, no feedback -- the noise on the disturbance and
  interaction-torque estimates. The torque channel reaches an observer only through the
  motion it causes; against a plant equal to the observer's own model that is exactly
  the observer's torque-to-estimate transfer, which is what is used.
- ``closed_loop``: the sampled force loop at the design's ``C_f`` with the exact plant
  and environment, the command delay included: the RMS of the estimates, of the true
  interaction torque (the force loop's output) and of the command. Here the noise moves
  the plant, and the torque channel enters where the applied torque does (after the
  command delay), not where the observers see the command.

What it does not cover: at rest the error is not white (a still position sits on one
code; a still velocity reads ``-step / 2``), so the figures describe a moving servo;
the step response with a codec in the loop (the quantisation figure script in ``tools/``)
shows both.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass
from types import MappingProxyType
from typing import Any, Protocol

import numpy as np
import scipy.linalg

from dobhil.drives.plugin import CodecQuantisation
from dobhil.synthesis.controller import DIS, INT, ControllerSS, sampled_controller
from dobhil.synthesis.loop import LoopSS, loop
from dobhil.synthesis.numerics import balance
from dobhil.synthesis.params import Array, Params

__all__ = ["ChannelFigures", "QuantisationFigures", "Steps", "codec_figures", "dc_gain",
           "h2_norm", "noise_figures", "quantisation_text", "torque_error_column"]

#: closed-loop outputs reported (names of :data:`dobhil.synthesis.loop.OUTPUTS`)
LOOP_OUTPUTS: tuple[str, ...] = ("tau_int_hat", "tau_dis_hat", "tau_int", "u")

#: a pole counts as stable when |z| < 1 - STABLE_MARGIN
STABLE_MARGIN = 1e-9


class Steps(Protocol):
    """The quantisation steps of a codec (a :class:`~dobhil.drives.plugin.CodecQuantisation`,
    or any object with these three steps)."""

    @property
    def position(self) -> float: ...   # [rad]

    @property
    def velocity(self) -> float: ...   # [rad/s]

    @property
    def torque(self) -> float: ...     # [N m]


@dataclass(frozen=True)
class ChannelFigures:
    """One output's response to the quantisation of each channel (N m)."""

    rms: Mapping[str, float]    # channel -> RMS contribution (step/sqrt(12) * H2)
    total: float                # root sum of squares of ``rms``
    bias: float                 # steady offset from the truncation's mean (-step/2 per channel; 0 rounding)

    def as_dict(self) -> dict[str, Any]:
        return {"rms": dict(self.rms), "total_rms": self.total, "bias": self.bias}


@dataclass(frozen=True)
class QuantisationFigures:
    """The noise figures of one design on one codec (see the module docstring)."""

    steps: Mapping[str, float]              # channel -> step [rad, rad/s, N m]
    measured: tuple[str, ...]               # the measurements the controller uses
    observers: Mapping[str, ChannelFigures]     # "dob", "rtob"
    closed_loop: Mapping[str, ChannelFigures] | None   # LOOP_OUTPUTS; None: loop unstable
    force_gain: float
    zero_torque_bias: float | None = None   # [N m] what a zero command applies (set by the caller)
    model: Mapping[str, str] | None = None  # vendor, model, firmware (set by the caller)
    truncates: bool = True                  # False: the codec rounds (error mean 0)

    def as_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {}
        if self.model is not None:
            out["model"] = dict(self.model)
        out["steps"] = dict(self.steps)
        out["zero_torque_bias"] = self.zero_torque_bias
        out["measured"] = list(self.measured)
        out["noise_model"] = (("per channel white, uniform over the step below the value (the "
                               "firmware truncates): variance step^2/12, mean -step/2 "
                               "(+step/2 on a model with axis_direction -1)") if self.truncates else
                              "per channel white, uniform over one step about the value (the codec "
                              "rounds): variance step^2/12, mean 0")
        out["observers"] = {k: v.as_dict() for k, v in self.observers.items()}
        out["closed_loop"] = (None if self.closed_loop is None else
                              {"force_gain": self.force_gain,
                               **{k: v.as_dict() for k, v in self.closed_loop.items()}})
        return out


def h2_norm(a: Array, b: Array, c: Array, d: Array) -> float | None:
    """H2 norm of the discrete system ``(A, B, C, D)`` (one input, one output, one design):
    the RMS of the output for a unit-variance white input. None when ``A`` has a pole on
    or outside the unit circle (no finite norm)."""
    a, b, c = (np.asarray(m, float) for m in (a, b, c))
    d = np.asarray(d, float).reshape(1, 1)
    if a.shape[-1] == 0:
        return float(abs(d[0, 0]))
    if np.max(np.abs(np.linalg.eigvals(a))) >= 1.0 - STABLE_MARGIN:
        return None
    a, b, c = balance(a, b, c)   # the loop's states differ in scale by ~1e5
    gram = scipy.linalg.solve_discrete_lyapunov(a, b @ b.T)
    value = float((c @ gram @ c.T + d @ d.T)[0, 0])
    return math.sqrt(max(value, 0.0))


def dc_gain(a: Array, b: Array, c: Array, d: Array) -> float:
    """``C (I - A)^-1 B + D`` of a stable discrete system (one input, one output)."""
    a = np.asarray(a, float)
    n = a.shape[-1]
    value = np.asarray(d, float).reshape(1, 1)
    if n:
        value = value + np.asarray(c, float) @ np.linalg.solve(np.eye(n) - a, np.asarray(b, float))
    return float(value[0, 0])


def _figures(systems: Mapping[str, tuple[Array, Array, Array, Array]],
             steps: Mapping[str, float], mean: float) -> ChannelFigures | None:
    """Combine one output's per-channel systems; None when any has no H2 norm. ``mean``:
    the error's mean in steps (see :func:`_mean`)."""
    rms: dict[str, float] = {}
    bias = 0.0
    for channel, (a, b, c, d) in systems.items():
        norm = h2_norm(a, b, c, d)
        if norm is None:
            return None
        rms[channel] = steps[channel] / math.sqrt(12.0) * norm
        bias += mean * steps[channel] * dc_gain(a, b, c, d)
    total = math.sqrt(sum(v * v for v in rms.values()))
    return ChannelFigures(rms=MappingProxyType(rms), total=total, bias=bias)


def observer_systems(ctrl: ControllerSS, row: int) -> dict[str, tuple[Array, Array, Array, Array]]:
    """Per channel, the observer output ``row`` (DIS or INT) as a system of that channel."""
    out: dict[str, tuple[Array, Array, Array, Array]] = {}
    for j, channel in enumerate(_measured(ctrl)):
        out[channel] = (ctrl.a, ctrl.b_y[:, j:j + 1], ctrl.c[row:row + 1], ctrl.d_y[row:row + 1, j:j + 1])
    # the applied-torque error e: the plant moves as if by u + e while the observer is
    # told u; against a plant equal to the observer's model the estimate moves by -H_u e
    # (H_u its torque-to-estimate transfer: the motion of u + e minus the u it was told)
    out["torque"] = (ctrl.a, -ctrl.b_u, ctrl.c[row:row + 1], np.zeros((1, 1)))
    return out


def torque_error_column(closed: LoopSS, controller_order: int) -> Array:
    """The input column of the loop for ``applied - commanded`` torque.

    The loop's ``tau_per`` input is added to the command, so it reaches the plant (through
    the command delay chain) AND the observers (through ``B_u``). The applied torque's
    error reaches the plant only: the same column with the controller's rows (the
    states ``2 .. 2 + order`` of the loop's ``[x_p, xi, w]``) zeroed."""
    column = np.array(closed.b[:, closed.input_index("tau_per"):closed.input_index("tau_per") + 1])
    column[2:2 + controller_order, :] = 0.0
    return column


def loop_systems(closed: LoopSS, ctrl: ControllerSS,
                 output: str) -> dict[str, tuple[Array, Array, Array, Array]]:
    """Per channel, the closed loop from that channel's error to ``output``."""
    o = closed.output_index(output)
    c, out = closed.c[o:o + 1], {}
    for channel, name in zip(_measured(ctrl), ("eta_q", "eta_dq")):
        i = closed.input_index(name)
        out[channel] = (closed.a, closed.b[:, i:i + 1], c, closed.d[o:o + 1, i:i + 1])
    out["torque"] = (closed.a, torque_error_column(closed, ctrl.order), c, np.zeros((1, 1)))
    return out


def _measured(ctrl: ControllerSS) -> tuple[str, ...]:
    """The measurement channels of ``y`` (``[q, dq]``, or ``[q]`` with an estimated velocity)."""
    return ("position", "velocity") if ctrl.measures_velocity else ("position",)


def _read(ctrl: ControllerSS) -> tuple[str, ...]:
    """The channels of ``y`` the controller actually uses (a non-zero column): with a
    measured velocity and no friction or stiffness in the observers' models, the position
    is in ``y`` but multiplied by zero everywhere."""
    used = np.any(ctrl.b_y != 0.0, axis=0) | np.any(ctrl.d_y != 0.0, axis=0)
    return tuple(ch for ch, u in zip(_measured(ctrl), used) if u)


def _mean(direction: int, truncates: bool) -> float:
    """The error's mean in steps: ``-1/2`` for a truncating codec in the drive's sense of
    rotation (``direction`` -1: the host's value is the negated decode of the negated value,
    so ``+1/2``); 0 for a rounding codec."""
    if direction not in (1, -1):
        raise ValueError(f"direction: expected 1 or -1, got {direction!r}")
    return -0.5 * direction if truncates else 0.0


def noise_figures(params: Params, steps: Steps, *, direction: int = 1,
                  truncates: bool = True) -> QuantisationFigures:
    """The noise figures of one design (batch shape ``()``) on a codec with ``steps``;
    ``direction``: the codec's axis direction (the sign of the truncation's mean);
    ``truncates`` False: the codec rounds to nearest."""
    mean = _mean(direction, truncates)
    if params.batch_shape != ():
        raise ValueError("quantisation figures are computed for a single design")
    ctrl = sampled_controller(params)
    step_map = {"position": float(steps.position), "velocity": float(steps.velocity),
                "torque": float(steps.torque)}
    observers: dict[str, ChannelFigures] = {}
    for key, row in (("dob", DIS), ("rtob", INT)):
        figures = _figures(observer_systems(ctrl, row), step_map, mean)
        if figures is None:   # cannot happen: the observers' poles are exp(-g T) and 0
            raise ValueError("the sampled observer is not stable")
        observers[key] = figures
    closed = loop(params, sampled=True)
    looped: dict[str, ChannelFigures] = {}
    for output in LOOP_OUTPUTS:
        figures = _figures(loop_systems(closed, ctrl, output), step_map, mean)
        if figures is None:
            break
        looped[output] = figures
    return QuantisationFigures(
        steps=MappingProxyType(step_map), measured=_read(ctrl),
        observers=MappingProxyType(observers),
        closed_loop=MappingProxyType(looped) if len(looped) == len(LOOP_OUTPUTS) else None,
        force_gain=float(params.value("force_gain")), truncates=truncates)


#: in the text, a figure below this [N m] is a rounding of zero (an exact cancellation
#: -- e.g. the command's velocity noise when J_mn = C_f J_mi -- leaves ~1e-12 N m)
TEXT_ZERO = 1e-9


def _mnm(x: float | None) -> str:
    """A torque in mN m (N m from 1 N m on)."""
    if x is None:
        return "-"
    if abs(x) < TEXT_ZERO:
        return "0 mN m"
    return f"{x:.3g} N m" if abs(x) >= 1.0 else f"{x * 1e3:.3g} mN m"


def _channels(f: ChannelFigures) -> str:
    return ", ".join(f"{k} {_mnm(v)}" for k, v in f.rms.items())


def quantisation_text(q: QuantisationFigures) -> str:
    """The lines ``dobhil analyze`` prints."""
    m = q.model or {}
    name = " ".join(v for v in (m.get("vendor"), m.get("model")) if v)
    firmware = f" firmware {m['firmware']!r}" if m.get("firmware") else ""
    s = q.steps
    lines = [
        f"quantisation ({name}{firmware}): steps position {s['position'] * 1e3:.4g} mrad, "
        f"velocity {s['velocity'] * 1e3:.4g} mrad/s, torque {s['torque'] * 1e3:.4g} mN m; "
        f"a zero torque command applies {_mnm(q.zero_torque_bias)}",
        f"  noise model: white, uniform over one step per channel (RMS step/sqrt(12)); "
        f"the controller reads the {' and '.join(q.measured) or 'nothing'} (of the reply) and "
        f"the torque error is the applied minus the commanded",
    ]
    for key, label in (("dob", "DOb  tau_dis^"), ("rtob", "RTOb tau_int^")):
        f = q.observers[key]
        lines.append(f"  {label} noise, observer alone: RMS {_mnm(f.total)} ({_channels(f)})")
    if q.closed_loop is None:
        lines.append(f"  closed loop at C_f = {q.force_gain:.4g}: UNSTABLE, no noise figure")
    else:
        for key, label in (("tau_int_hat", "tau_int^"), ("tau_dis_hat", "tau_dis^"),
                           ("tau_int", "force tau_int"), ("u", "command u")):
            f = q.closed_loop[key]
            lines.append(f"  closed loop at C_f = {q.force_gain:.4g}, {label}: RMS {_mnm(f.total)} "
                         f"({_channels(f)}); truncation offset {_mnm(f.bias)}")
    return "\n".join(lines)


def codec_figures(params: Params, codec: CodecQuantisation) -> QuantisationFigures:
    """The figures of one design on a protocol's codec (``DriveProtocol.quantisation`` of
    the drive's profile): its steps, truncation sense, zero-command torque and the model it
    describes (``codec.source``, for the report)."""
    figures = noise_figures(params, codec, direction=codec.direction, truncates=codec.truncates)
    return dataclasses.replace(figures, zero_torque_bias=codec.zero_torque,
                               model=MappingProxyType({str(k): str(v) for k, v in codec.source.items()}))
