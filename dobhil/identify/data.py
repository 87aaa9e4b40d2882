"""The data an identification fits: one uniformly sampled record of torque and motion.

Minimal seam (SPEC-19); the readers (MCAP loop records, imported CAN logs) and the
segment finder live here too once written.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

__all__ = ["IdentData", "Segment"]


@dataclass(frozen=True)
class IdentData:
    period: float              # [s]
    t: np.ndarray              # [s] k * period, uniform
    torque: np.ndarray         # [Nm] torque sent at t_k (after saturation), held to t_{k+1}
    position: np.ndarray       # [rad] measured at t_k, as the controller saw it
    velocity: np.ndarray       # [rad/s] measured at t_k
    source: str                # file name ("" when synthetic)
    protocol: str              # the drive profile's protocol
    recorded: Mapping[str, float]   # config keys recorded in the log (plant.*, environment.*, design.*)


@dataclass(frozen=True)
class Segment:
    start: int; stop: int      # sample indices, half-open  # noqa: E702
    kind: str                  # "free" | "contact"
