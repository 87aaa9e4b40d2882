"""Measured vs model of one identified segment (``dobhil identify --plot DIR``): the torque
sent, the measured position and velocity with the fitted model's simulation of them from that
torque, and the velocity residual (what the fit minimises: a misfit shows there as structure
instead of noise)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dobhil.plotting.figures import _plt, save


def measured_vs_model(t: np.ndarray, measured: tuple[np.ndarray, np.ndarray], model: tuple[np.ndarray, np.ndarray],
                      title: str, path: Path, torque: np.ndarray | None = None) -> Path:
    """Torque sent (when given), position and velocity (measured solid, model dashed) and the
    velocity residual, over ``t`` [s] (time in the segment's log), to ``path``."""
    rows = 3 + (torque is not None)
    fig, axes = _plt().subplots(rows, 1, sharex=True, figsize=(8, 2.2 * rows))
    top = 0
    if torque is not None:
        axes[0].plot(t, torque, lw=0.8, color="k", drawstyle="steps-post")
        axes[0].set_ylabel("torque sent [N m]")
        axes[0].grid(True, alpha=0.3)
        top = 1
    for ax, m, s, label in zip(axes[top:top + 2], measured, model, ("position [rad]", "velocity [rad/s]")):
        ax.plot(t, m, label="measured", lw=1)
        ax.plot(t, s, label="model", lw=1, ls="--")
        ax.set_ylabel(label)
        ax.grid(True, alpha=0.3)
        ax.legend(loc="best")
    residual = np.asarray(measured[1], float) - np.asarray(model[1], float)
    axes[-1].plot(t, residual, lw=0.6, color="tab:red")
    axes[-1].set_ylabel("velocity residual\n(measured - model) [rad/s]")
    axes[-1].grid(True, alpha=0.3)
    axes[-1].set_xlabel("time in the log [s]")
    axes[0].set_title(title)
    return save(fig, path)


__all__ = ["measured_vs_model"]
