"""Measured vs model of one identified segment (``dobhil identify --plot DIR``): the measured
position and velocity and the fitted model's simulation of them from the same torque."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dobhil.plotting.figures import _plt, save


def measured_vs_model(t: np.ndarray, measured: tuple[np.ndarray, np.ndarray], model: tuple[np.ndarray, np.ndarray],
                      title: str, path: Path) -> Path:
    """Position (top) and velocity (bottom), measured solid and model dashed, to ``path``."""
    fig, axes = _plt().subplots(2, 1, sharex=True, figsize=(8, 6))
    for ax, m, s, label in zip(axes, measured, model, ("position [rad]", "velocity [rad/s]")):
        ax.plot(t, m, label="measured", lw=1)
        ax.plot(t, s, label="model", lw=1, ls="--")
        ax.set_ylabel(label)
        ax.grid(True, alpha=0.3)
        ax.legend(loc="best")
    axes[-1].set_xlabel("time [s]")
    axes[0].set_title(title)
    return save(fig, path)


__all__ = ["measured_vs_model"]
