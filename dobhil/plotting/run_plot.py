"""The figure of a run: reference, estimated and true interaction torque, command, position."""

from __future__ import annotations

from pathlib import Path
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from dobhil.plotting.figures import _plt, save


class Columns(Protocol):
    """Per-cycle values by name (the runtime's ``Trace``): plotting sits beside the runtime
    and draws what it is given, so it names the shape, not the loop's class."""

    def __getitem__(self, name: str) -> NDArray[np.float64]: ...


def run_figure(trace: Columns, path: Path, title: str = "") -> Path:
    plt = _plt()
    t = trace["t"]
    fig, ax = plt.subplots(3, 1, figsize=(9, 8), sharex=True,
                           gridspec_kw={"height_ratios": [2.2, 1, 1]})
    ax[0].plot(t, trace["tau_ref"], "k--", lw=1.2, label="reference tau_int^ref")
    ax[0].plot(t, trace["tau_int_hat"], lw=1.4, label="estimated tau_int^ (RTOb)")
    true = trace["tau_int_true"]
    if np.any(np.isfinite(true)):
        ax[0].plot(t, true, lw=1.0, alpha=0.85, label="true tau_int (emulator)")
    ax[0].set_ylabel("interaction torque [N m]")
    ax[0].legend(fontsize=8)
    ax[1].plot(t, trace["u"], lw=1.0, label="u (applied)")
    ax[1].plot(t, trace["tau_dis_hat"], lw=1.0, label="tau_dis^ (DOb)")
    ax[1].set_ylabel("torque [N m]")
    ax[1].legend(fontsize=8)
    ax[2].plot(t, trace["q"] * 1e3, lw=1.0)
    ax[2].set_ylabel("position [mrad]")
    ax[2].set_xlabel("time [s]")
    for a in ax:
        a.grid(True, alpha=0.3)
    ax[0].set_title(title or "Force-control run")
    return save(fig, path)
