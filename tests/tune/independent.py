"""An independent stability check of a design at a point: the closed loop built with
python-control from its parts -- the sampled controller's matrices, the plant with its
environment sampled by ``control.c2d`` (zero-order hold; not dobhil's discretisation),
a unit delay per ``design.delay_samples``, and the force law as a summing junction
(``control.interconnect``, once per design: the measurements q, q' to the plant's input) --
the loop closed around each point's plant by ``control.feedback``, and its eigenvalues
tested against the unit circle.

Nothing here goes through :func:`dobhil.synthesis.loop.loop`, the gain map or tune's own
metrics. Only ``design.input_delay = 0`` is covered (c2d has no fractional input delay)."""

from __future__ import annotations

from collections.abc import Mapping
from functools import cache

import control
import numpy as np

from dobhil.config.schema import Config
from dobhil.synthesis.controller import sampled_controller
from dobhil.synthesis.params import params_from_config


class IndependentLoop:
    """One design's closed loop at any point: its controller and force law built once."""

    def __init__(self, config: Config, design: Mapping[str, float]) -> None:
        if config.design.input_delay:
            raise ValueError("the independent check covers design.input_delay = 0 only")
        self.config = config
        self.design = dict(design)
        self.dt = float(config.loop.period)
        params = params_from_config(config, **_arrays(design))
        controller = _controller(params, self.dt)
        parts = [controller, _force_law(float(params.value("force_gain")), self.dt)]
        delay = config.design.delay_samples
        if delay:
            parts.append(_delay(delay, self.dt))
        self.plant_input = "u_late" if delay else "u"
        self.measured = controller.input_labels[:-1]
        # the poles do not depend on tau_ref: the feedback path alone, measurements -> input
        self.feedback = control.interconnect(parts, inplist=self.measured, outlist=[self.plant_input],
                                             check_unused=False)

    def poles(self, point: Mapping[str, float]) -> np.ndarray:
        params = params_from_config(self.config, **_arrays({**self.design, **point}))
        plant = _plant(*(float(params.value(k)) for k in ("inertia", "viscous_friction", "stiffness", "damping")),
                       self.dt, self.plant_input)
        # u = feedback(q, q'): a positive feedback of the plant's measured outputs
        system = control.feedback(plant[self.measured, :], self.feedback, sign=1)
        return np.asarray(system.poles())


def _arrays(values: Mapping[str, float]) -> dict[str, float]:
    return {k.replace(".", "__"): float(v) for k, v in values.items()}


def closed_loop_poles(config: Config, design: Mapping[str, float], point: Mapping[str, float]) -> np.ndarray:
    return IndependentLoop(config, design).poles(point)


@cache   # a pure result: the designs checked on one grid share its points' plants
def _plant(inertia: float, friction: float, stiffness: float, damping: float, dt: float,
           inp: str) -> control.StateSpace:
    """J q'' = u - (b + D) q' - K q, outputs q, q' and the true interaction K q + D q'."""
    a = [[0.0, 1.0], [-stiffness / inertia, -(friction + damping) / inertia]]
    b = [[0.0], [1.0 / inertia]]
    c = [[1.0, 0.0], [0.0, 1.0], [stiffness, damping]]
    continuous = control.ss(a, b, c, np.zeros((3, 1)), inputs=[inp], outputs=["q", "dq", "tau_int"])
    return control.c2d(continuous, dt, method="zoh", inputs=[inp], outputs=["q", "dq", "tau_int"],
                       name="plant")


def _controller(params: object, dt: float) -> control.StateSpace:
    ctrl = sampled_controller(params)  # type: ignore[arg-type]
    measured = ["q", "dq"][: ctrl.b_y.shape[-1]]
    b = np.concatenate([ctrl.b_y, ctrl.b_u], axis=-1)
    d = np.concatenate([ctrl.d_y, np.zeros((2, 1))], axis=-1)
    return control.ss(ctrl.a, b, ctrl.c, d, dt, inputs=[*measured, "u"],
                      outputs=["tau_dis_hat", "tau_int_hat"], name="controller")


def _force_law(cf: float, dt: float) -> control.StateSpace:
    """u = tau_dis^ + C_f (tau_ref - tau_int^): a static system."""
    return control.ss([], [], [], [[1.0, -cf, cf]], dt, inputs=["tau_dis_hat", "tau_int_hat", "tau_ref"],
                      outputs=["u"], name="force_law")


def _delay(samples: int, dt: float) -> control.StateSpace:
    a = np.eye(samples, k=-1)
    b = np.zeros((samples, 1))
    b[0, 0] = 1.0
    c = np.zeros((1, samples))
    c[0, -1] = 1.0
    return control.ss(a, b, c, [[0.0]], dt, inputs=["u"], outputs=["u_late"], name="delay")


def stable(poles: np.ndarray) -> bool:
    return bool(np.max(np.abs(poles)) < 1.0)
