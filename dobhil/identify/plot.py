"""Measured vs model (``dobhil identify --plot DIR``): per segment, the measured position and
velocity and the fitted model's simulation of them from the same torque."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from dobhil.identify.data import IdentData


def segment_figures(result: Any, data: IdentData, out: Path) -> list[Path]:
    """One PNG per segment in ``out`` (created); the paths written."""
    from dobhil.identify.fit import simulate
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from dobhil.plotting.figures import save
    values = {n: e.value for n, e in result.estimates.items() if e.identifiable}
    out.mkdir(parents=True, exist_ok=True)
    written = []
    for i, seg in enumerate(result.segments):
        position, velocity = simulate(values, data, seg)
        t = data.t[seg.start:seg.stop]
        fig, (ax_q, ax_v) = plt.subplots(2, 1, sharex=True, figsize=(8, 6))
        for ax, measured, model, label in ((ax_q, data.position, position, "position [rad]"),
                                           (ax_v, data.velocity, velocity, "velocity [rad/s]")):
            ax.plot(t, measured[seg.start:seg.stop], label="measured", lw=1)
            ax.plot(t, model, label="model", lw=1, ls="--")
            ax.set_ylabel(label)
            ax.grid(True, alpha=0.3)
            ax.legend(loc="best")
        ax_v.set_xlabel("time [s]")
        ax_q.set_title(f"{data.source}: {seg.kind} segment {t[0]:.3f}-{t[-1]:.3f} s")
        written.append(save(fig, out / f"identify_segment_{i}.png"))
    return written
