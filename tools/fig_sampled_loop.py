#!/usr/bin/env python3
"""Write docs/img/sampled_loop_fig3.png: the paper's Fig. 3 step responses (tau_int^),
continuous vs sampled at 1 ms with the parabolic-hold controller (the default) and the
step-invariant (zoh) one it replaced. Run from the repository root:

    python tools/fig_sampled_loop.py [OUT.png]
"""

from __future__ import annotations

import sys
from pathlib import Path

import control
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from dobhil.analysis.transfer import LoopSystems  # noqa: E402
from dobhil.config import load_config  # noqa: E402
from dobhil.plotting.figures import _plt, save  # noqa: E402
from dobhil.synthesis.params import params_from_config  # noqa: E402

RATIOS = (0.5, 1.0, 1.5)        # J_mi / J_m (2 J_m is unstable in every domain)
DURATION = 0.06


def step(ratio: float, *, sampled: bool, discretization: str = "parabolic") -> tuple[np.ndarray,
                                                                                     np.ndarray,
                                                                                     bool]:
    config = load_config(ROOT / "configs/paper/fig3.yaml",
                         [f"design.identified_inertia={0.25 * ratio!r}",
                          f"design.discretization={discretization}"])
    sys_ = LoopSystems.build(params_from_config(config), sampled=sampled).system("closed_loop")
    t = (np.arange(0.0, DURATION + 1e-9, config.loop.period) if sampled
         else np.linspace(0.0, DURATION, 6001))
    poles = np.asarray(sys_.poles())
    stable = bool(np.all(np.abs(poles) < 1.0) if sampled else np.all(poles.real < 0.0))
    return t, np.squeeze(control.step_response(sys_, T=t).outputs), stable


def main() -> int:
    out = Path(sys.argv[1]) if len(sys.argv) > 1 else ROOT / "docs/img/sampled_loop_fig3.png"
    plt = _plt()
    fig, axes = plt.subplots(1, len(RATIOS), figsize=(14, 4.2))
    for ax, ratio in zip(axes, RATIOS):
        t, y, _ = step(ratio, sampled=False)
        ax.plot(t * 1e3, y, color="k", lw=1.6, label="continuous (paper)")
        for disc, color, ls, name in (("parabolic", "tab:blue", "-", "parabolic hold (default)"),
                                      ("zoh", "tab:red", "--", "zoh (old)")):
            t, y, stable = step(ratio, sampled=True, discretization=disc)
            ax.step(t * 1e3, y, where="post", color=color, lw=1.1, ls=ls,
                    label=f"1 ms, {name}" + ("" if stable else ": UNSTABLE"))
        ax.set_ylim(-0.6, 2.8)
        ax.legend(loc="upper right", fontsize=8)
        ax.axhline(1.0, color="0.5", lw=0.8, ls=":")
        ax.set_title(f"J_mi = {ratio:g} J_m")
        ax.set_xlabel("time [ms]")
        ax.grid(True, alpha=0.3)
    axes[0].set_ylabel("tau_int^ / tau_int^ref")
    fig.suptitle("Fig. 3 (g_DOb = g_RTOb = 500 rad/s, C_f = 2): continuous vs sampled at 1 ms")
    print(f"wrote {save(fig, out)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
