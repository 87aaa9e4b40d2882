"""The figures of ``dobhil tune --plot DIR``: the tuned design's gain margin over the robust
set (with the config's own design's unstable region), the worst-case force step of both
designs, and each constraint's worst value against its limit.

Plain arrays in (the CLI passes them): this module knows nothing of the search.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from dobhil.analysis.stability import STABILITY_TOL
from dobhil.plotting.figures import _plt, save

Step = tuple[np.ndarray, np.ndarray] | None


@dataclass(frozen=True)
class TunePlotData:
    keys: tuple[str, ...]                     # the set's keys, range keys first
    points: Mapping[str, np.ndarray]          # flat grid, one array per key
    gm_db: np.ndarray = field(repr=False)     # tuned design's gain margin per point
    baseline_stable: np.ndarray = field(repr=False)   # the config's design: stable per point
    worst_at: Mapping[str, float]
    tuned_step: Step
    config_step: Step
    constraints: Sequence[tuple[str, float, float]]   # (name, worst value, limit)
    #: the tuned design stable per point (where not, ``gm_db`` is the search's stand-in, no margin)
    tuned_stable: np.ndarray | None = field(default=None, repr=False)


def tune_figures(data: TunePlotData, directory: Path) -> list[Path]:
    directory.mkdir(parents=True, exist_ok=True)
    return [stability_map(data, directory / "stability_map.png"),
            worst_step(data, directory / "worst_step.png"),
            margins_figure(data, directory / "margins.png")]


def _axis_values(data: TunePlotData, key: str) -> np.ndarray:
    return np.unique(data.points[key])


def stability_map(data: TunePlotData, path: Path) -> Path:
    """Gain margin (worst over the other keys) over the first one or two keys."""
    plt = _plt()
    from matplotlib.patches import Patch
    fig, ax = plt.subplots(figsize=(8, 6.4), layout="constrained")
    keys = data.keys[:2]
    # an unstable point has no gain margin: the search's stand-in there (-100 dB,
    # dobhil.tune.evaluate.WORST) drawn as one read as a measured margin, and stretched the
    # colour scale over the real ones; such a point is marked unstable instead
    unstable = np.zeros(data.gm_db.shape, bool) if data.tuned_stable is None else ~np.asarray(data.tuned_stable)
    gm = np.where(np.isinf(data.gm_db) | unstable, np.nan, data.gm_db)
    if len(keys) == 1:
        x = _axis_values(data, keys[0])
        at = [data.points[keys[0]] == v for v in x]
        worst = [np.nan if unstable[m].any() else np.nanmin(gm[m], initial=np.inf) for m in at]
        ax.semilogx(x, worst, "-o", ms=3, label="tuned: worst gain margin")
        bad = np.array([unstable[m].any() for m in at])
        if bad.any():
            ax.plot(x[bad], np.zeros(int(bad.sum())), "x", ms=8, mew=1.5, color="tab:red", clip_on=False,
                    transform=ax.get_xaxis_transform(), label="tuned design unstable (no margin)")
        ax.set_xlabel(keys[0])
        ax.set_ylabel("gain margin [dB] (max stable C_f / C_f)")
        ax.axvline(data.worst_at[keys[0]], color="k", ls="--", label="worst objective")
        ax.legend()
    else:
        x, y = _axis_values(data, keys[0]), _axis_values(data, keys[1])
        grid, stable = _on_grid(data, keys, x, y, gm)
        tuned_ok = _on_grid(data, keys, x, y, gm, ~unstable)[1]
        grid = np.where(tuned_ok, grid, np.nan)   # a cell's worst is no margin where any point is unstable
        mesh = ax.pcolormesh(y, x, grid, shading="auto", cmap="viridis")
        fig.colorbar(mesh, ax=ax, label="tuned design: gain margin [dB] (worst over other keys)")
        handles = []
        if not tuned_ok.all():
            ax.contourf(y, x, (~tuned_ok).astype(float), levels=[0.5, 1.5], colors="none", hatches=["xx"])
            handles.append(Patch(facecolor="none", edgecolor="black", hatch="xx",
                                 label="the tuned design unstable (no margin)"))
        if not stable.all():   # hatched, not filled: the gain margin's colours stay readable
            ax.contourf(y, x, (~stable).astype(float), levels=[0.5, 1.5], colors="none", hatches=["//"])
            ax.contour(y, x, stable.astype(float), levels=[0.5], colors="red", linewidths=1.5)
            handles.append(Patch(facecolor="none", edgecolor="black", hatch="//",
                                 label="the config's design unstable (red: its edge)"))
        handles += ax.plot([data.worst_at[keys[1]]], [data.worst_at[keys[0]]], "w*", ms=14, mec="k",
                           label="tuned design's worst-case objective")
        for axis, values in ((ax.set_xscale, y), (ax.set_yscale, x)):
            axis("log" if values.min() > 0 and values.max() / values.min() >= 10 else "linear")
        ax.set_xlabel(keys[1])
        ax.set_ylabel(keys[0])
        fig.legend(handles=handles, loc="outside lower center", ncols=2, fontsize=9)
    ax.set_title("robust set: tuned design's gain margin")
    return save(fig, path)


def _on_grid(data: TunePlotData, keys: tuple[str, ...], x: np.ndarray, y: np.ndarray,
             gm: np.ndarray, stable_at: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(worst gain margin, stable everywhere) per (x, y) cell: the config's design, or
    ``stable_at`` per point when given."""
    ix = np.searchsorted(x, data.points[keys[0]])
    iy = np.searchsorted(y, data.points[keys[1]])
    grid = np.full((x.size, y.size), np.inf)
    stable = np.ones((x.size, y.size), bool)
    np.minimum.at(grid, (ix, iy), np.nan_to_num(gm, nan=np.inf))
    np.logical_and.at(stable, (ix, iy), data.baseline_stable if stable_at is None else stable_at)
    return np.where(np.isinf(grid), np.nan, grid), stable


def worst_step(data: TunePlotData, path: Path) -> Path:
    plt = _plt()
    fig, ax = plt.subplots(figsize=(8, 4.5))
    for step, label, style in ((data.tuned_step, "tuned", "-"), (data.config_step, "config's design", "--")):
        if step is None:
            ax.plot([], [], style, label=f"{label}: unstable here")
            continue
        t, y = step
        ax.step(t * 1e3, y, style, where="post", label=label)
    where = ", ".join(f"{k}={v:.4g}" for k, v in data.worst_at.items())
    ax.set_title(f"force step at the tuned design's worst point ({where})", fontsize=9)
    ax.set_xlabel("time [ms]")
    ax.set_ylabel("true interaction torque / reference")
    ax.axhline(1.0, color="grey", lw=0.8)
    ax.legend()
    return save(fig, path)


def margins_figure(data: TunePlotData, path: Path) -> Path:
    """Each constraint's worst value as a fraction of its limit (>= 1: met, for lower
    bounds; <= 1 for upper bounds: drawn as limit / value so that right of 1 is good); a
    margin with no value (the design unstable at its worst point) at 0, not met."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(8, 3.5))
    lower = {"gain_margin", "phase_margin"}
    names, ratios = [], []
    for name, value, limit in data.constraints:
        if np.isnan(value):   # a margin at an unstable worst point: there is none, so not met
            names.append(f"{name}\nnone (unstable) vs {limit:.3g}")   # (NaN would pass the cap
            ratios.append(0.0)                                         # below as a full green bar)
            continue
        # stable only inside 1 - STABILITY_TOL, as the text judges it
        limit_at = limit - STABILITY_TOL if name == "stability" else limit
        ratio = value / limit if name in lower else limit_at / value if value else np.inf
        names.append(f"{name}\n{value:.3g} vs {limit:.3g}")
        ratios.append(min(ratio, 5.0) if np.isfinite(ratio) else 5.0)
    colors = ["tab:green" if r >= 1 else "tab:red" for r in ratios]
    ax.barh(names, ratios, color=colors)
    ax.axvline(1.0, color="k", lw=1)
    ax.set_xlabel("worst value relative to its limit (right of 1: met; capped at 5)")
    ax.tick_params(axis="y", labelsize=8)
    return save(fig, path)
