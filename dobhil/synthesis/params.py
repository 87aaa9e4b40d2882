"""Numeric parameters of a design, batched.

Every numeric field is a float or a numpy array; all arrays broadcast to one
batch shape, so the whole synthesis runs on a grid of designs at once (the
sweep) or on a single design (batch shape ``()``). Structural choices (model
kinds, velocity source, delay length, discretisation) are shared by the batch.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable
from dataclasses import dataclass
from enum import IntEnum
from typing import Any

import numpy as np
from numpy.typing import NDArray

from dobhil.config.schema import Config
from dobhil.errors import ConfigError

Array = NDArray[np.float64]


class SignalModel(IntEnum):
    """Models (A_D, C_D) / (A_R, C_R) of the disturbance and interaction torques."""

    CONSTANT = 0
    RAMP = 1
    SINUSOID = 2


class VelocitySource(IntEnum):
    MEASURED = 0
    ESTIMATED = 1


class Discretization(IntEnum):
    """How the controller is sampled (see :mod:`dobhil.synthesis.controller`)."""

    ZOH = 0        # everything held: the step-invariant equivalent (the old default)
    EULER = 1      # forward Euler
    FOH = 2        # measured signals by a triangle hold (ramp-invariant), torque by ZOH
    PARABOLIC = 3  # measured signals by a parabola through y[k-1..k+1], torque by ZOH


@dataclass(frozen=True)
class Structure:
    """The choices that fix the dimensions of the synthesised matrices."""

    disturbance_model: SignalModel = SignalModel.CONSTANT
    interaction_model: SignalModel = SignalModel.CONSTANT
    velocity_source: VelocitySource = VelocitySource.MEASURED
    delay_samples: int = 0
    discretization: Discretization = Discretization.PARABOLIC
    input_delay: float = 0.0    # fractional torque delay [s], 0 <= input_delay < period


@dataclass(frozen=True)
class Params:
    """Numeric values of the exact plant, the environment and the design (SI units)."""

    inertia: Any                    # J_m
    viscous_friction: Any           # b_m
    stiffness: Any                  # K_env
    damping: Any                    # D_env
    nominal_inertia: Any            # J_mn
    nominal_friction: Any           # b_mn
    identified_inertia: Any         # J_mi
    identified_friction: Any        # b_mi
    dob_bandwidth: Any              # g_DOb
    rtob_bandwidth: Any             # g_RTOb
    force_gain: Any                 # C_f
    disturbance_frequency: Any      # omega of the DOb's sinusoid model
    interaction_frequency: Any      # omega of the RTOb's sinusoid model
    velocity_filter_bandwidth: Any  # g_v
    period: Any                     # T_s
    structure: Structure = Structure()

    @property
    def batch_shape(self) -> tuple[int, ...]:
        arrays = [np.asarray(getattr(self, f.name)) for f in dataclasses.fields(self)
                  if f.name != "structure"]
        return np.broadcast_shapes(*(a.shape for a in arrays))

    def value(self, name: str) -> Array:
        """Field ``name`` as a float array of the batch shape."""
        return np.broadcast_to(np.asarray(getattr(self, name), dtype=float), self.batch_shape)

    def replace(self, **changes: Any) -> Params:
        return dataclasses.replace(self, **changes)


#: config key -> Params field, for every numeric key the synthesis uses.
PARAM_KEYS: dict[str, str] = {
    "plant.inertia": "inertia",
    "plant.viscous_friction": "viscous_friction",
    "environment.stiffness": "stiffness",
    "environment.damping": "damping",
    "design.nominal_inertia": "nominal_inertia",
    "design.nominal_friction": "nominal_friction",
    "design.identified_inertia": "identified_inertia",
    "design.identified_friction": "identified_friction",
    "design.dob_bandwidth": "dob_bandwidth",
    "design.rtob_bandwidth": "rtob_bandwidth",
    "design.force_gain": "force_gain",
    "design.disturbance_frequency": "disturbance_frequency",
    "design.interaction_frequency": "interaction_frequency",
    "design.velocity_filter_bandwidth": "velocity_filter_bandwidth",
    "loop.period": "period",
}


def unused_keys(config: Config) -> dict[str, tuple[str, str]]:
    """The keys of :data:`PARAM_KEYS` the synthesis reads nowhere with this config's
    structure, each with the structural key and the value that would make it read: a
    model's frequency unless that model is the sinusoid
    (:func:`dobhil.synthesis.models.signal_model`), the velocity filter's bandwidth unless
    the velocity is estimated (:mod:`dobhil.synthesis.controller`). Varying one changes no
    matrix of the loop."""
    d = config.design
    out: dict[str, tuple[str, str]] = {}
    if d.disturbance_model != "sinusoid":
        out["design.disturbance_frequency"] = ("design.disturbance_model", "sinusoid")
    if d.interaction_model != "sinusoid":
        out["design.interaction_frequency"] = ("design.interaction_model", "sinusoid")
    if d.velocity_source != "estimated":
        out["design.velocity_filter_bandwidth"] = ("design.velocity_source", "estimated")
    return out


@dataclass(frozen=True)
class UnusedKey:
    """A key varied where the loop does not read it (:func:`unused_keys`): the structural
    key that decides it, its value in the config, and the value that would make it read."""

    key: str
    choice: str
    value: object
    wanted: str


def first_unused(config: Config, keys: Iterable[str]) -> UnusedKey | None:
    """The first of ``keys`` the loop does not read with ``config``'s structure, or None: a
    sweep or a campaign varying it would give the same loop at every value."""
    unused = unused_keys(config)
    for key in keys:
        if key in unused:
            choice, wanted = unused[key]
            return UnusedKey(key, choice, config.flat()[choice], wanted)
    return None


def structure_from_config(config: Config) -> Structure:
    d = config.design
    return Structure(
        disturbance_model=SignalModel[d.disturbance_model.upper()],
        interaction_model=SignalModel[d.interaction_model.upper()],
        velocity_source=VelocitySource[d.velocity_source.upper()],
        delay_samples=int(d.delay_samples),
        discretization=Discretization[d.discretization.upper()],
        input_delay=float(d.input_delay),
    )


def params_from_config(config: Config, **arrays: Any) -> Params:
    """Params of ``config``; ``arrays`` (config key with dots replaced by ``__``) override
    single values with arrays, e.g. ``environment__stiffness=np.logspace(3, 5, 50)``."""
    check_design(config)
    flat = config.flat()
    values = {field: flat[key] for key, field in PARAM_KEYS.items()}
    for name, value in arrays.items():
        values[PARAM_KEYS[name.replace("__", ".")]] = value
    return Params(**values, structure=structure_from_config(config))


def check_design(config: Config) -> None:
    """Constraints of the sampled model between keys (one line each, ConfigError)."""
    d, period = config.design, config.loop.period
    if not 0.0 <= d.input_delay < period:
        raise ConfigError(f"design.input_delay = {d.input_delay!r}: must be >= 0 and below "
                          f"loop.period = {period!r} (whole samples go in design.delay_samples)")
