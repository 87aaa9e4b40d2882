"""The paper's Fig. 2 (root loci a-d) and Fig. 3 (step responses) as PNGs.

Drawing only: :mod:`dobhil.paper` (above plotting) makes the cases and their continuous
analyses (``dobhil.paper.continuous``); the figures are given the analyses.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING

from dobhil.plotting.figures import _plt, root_locus, save

if TYPE_CHECKING:
    from dobhil.analysis.report import DomainAnalysis


def fig2(cases: Mapping[str, DomainAnalysis], path: Path) -> Path:
    plt = _plt()
    fig, axes = plt.subplots(2, 2, figsize=(11, 10))
    for ax, (case, a) in zip(axes.flat, cases.items()):
        p = a.params
        root_locus(ax, a, f"({case}) J_mi = {float(p.value('identified_inertia')):g}, "
                   f"g_DOb = {float(p.value('dob_bandwidth')):g}, g_RTOb = {float(p.value('rtob_bandwidth')):g}")
    fig.suptitle("Fig. 2: root loci of 1 + C_f L(s); J_m = J_mn = 0.25, D_env = 50, K_env = 1e4")
    return save(fig, path)


def fig3(cases: Mapping[float, DomainAnalysis], path: Path) -> Path:
    plt = _plt()
    fig, ax = plt.subplots(figsize=(8, 4.5))
    for ratio, a in cases.items():
        label = f"J_mi = {ratio:g} J_m"
        if a.stable:
            ax.plot(a.step_time * 1e3, a.step_estimate, label=label)
        else:
            ax.plot([], [], label=label + " (unstable)")
    ax.axhline(1.0, color="0.5", lw=0.8, ls=":")
    ax.set_xlabel("time [ms]")
    ax.set_ylabel("tau_int^ / tau_int^ref")
    ax.set_title("Fig. 3: force step responses, g_DOb = g_RTOb = 500, C_f = 2")
    ax.grid(True, alpha=0.3)
    ax.legend()
    return save(fig, path)
