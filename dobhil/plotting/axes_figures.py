"""The step figure of coupled axes: one panel per stepped axis' force reference, every
axis' estimated interaction torque in it, continuous and sampled.

Computing is in :mod:`dobhil.analysis.coupled`; this only draws.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

from dobhil.plotting.figures import _plt, save

if TYPE_CHECKING:
    from matplotlib.axes import Axes

    from dobhil.analysis.coupled_analysis import CoupledAnalysis, CoupledDomain


def _panel(ax: Axes, domain: CoupledDomain, axis: str, label: str) -> None:
    step = next((s for s in domain.steps if s.axis == axis), None)
    if step is None:
        ax.text(0.5, 0.5, f"{label}: closed loop unstable", transform=ax.transAxes, ha="center")
        return
    style: dict[str, Any] = {"drawstyle": "steps-post"} if domain.loop.sampled else {}
    for name, y in step.estimate.items():
        ax.plot(step.t * 1e3, y, label=f"{name} tau_int^ ({label})", **style)


def coupled_step_figure(result: CoupledAnalysis, path: Path, title: str = "") -> Path:
    """``path``: a unit step of each axis' tau_ref in turn (one panel each)."""
    plt = _plt()
    names = [d.name for d in result.designs]
    fig, axs = plt.subplots(len(names), 1, figsize=(7, 3.2 * len(names)), squeeze=False, layout="constrained")
    for ax, axis in zip(axs[:, 0], names):
        _panel(ax, result.continuous, axis, "continuous")
        _panel(ax, result.discrete, axis, "sampled")
        ax.set_title(f"unit step of {axis}'s tau_ref {title}")
        ax.set_ylabel("torque / reference")
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=7)
    axs[-1, 0].set_xlabel("time [ms]")
    return save(fig, path)
