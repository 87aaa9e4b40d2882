"""Heat-map of the largest stable force gain over a swept grid."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dobhil.analysis.sweep import SweepResult
from dobhil.plotting.figures import _plt, save


def heatmap(result: SweepResult, path: Path) -> Path:
    plt = _plt()
    from matplotlib.colors import LogNorm
    k = result.max_stable_gain.astype(float)
    finite = k[np.isfinite(k) & (k > 0)]
    fig, ax = plt.subplots(figsize=(8, 6))
    kind = "sampled" if result.sampled else "continuous"
    # a key held at one value (NUM 1, or START = STOP) is no axis of the picture: the contours
    # need two values of each key, so two keys of which one is held draw the line over the
    # other one (a held key given NUM > 1 repeats its points: its first is drawn; as an axis of
    # the map its cells had no height, an empty picture)
    varied = [a for a in result.axes if np.unique(a.values).size > 1]
    if len(result.axes) == 1 or len(varied) < 2:
        line = varied[0] if varied else result.axes[0]
        at = next(i for i, a in enumerate(result.axes) if a is line)
        k = k[tuple(slice(None) if i == at else 0 for i in range(k.ndim))]
        # a max stable C_f of 0 (unstable at small gains, or a drifting position) has no place on a
        # log axis: a gap alone would read as "unbounded", the opposite; a cross on the bottom
        # edge marks it
        none = k.reshape(-1) == 0
        ax.semilogy(line.values, np.where(np.isinf(k) | (k == 0), np.nan, k).reshape(-1), "-o", ms=3)
        if none.any():
            ax.plot(line.values[none], np.zeros(int(none.sum())), "x", ms=7, mew=1.5, color="tab:red",
                    transform=ax.get_xaxis_transform(), clip_on=False,
                    label="max stable C_f 0 (unstable at small C_f, or the position drifts)")
        # an unbounded C_f has no place on the axis either: its gap alone left the x axis on the
        # finite points only (or, all unbounded, on matplotlib's default -0.05..0.05), the swept
        # range out of sight; a triangle on the top edge marks it, in the swept range
        unbounded = np.isinf(k.reshape(-1))
        if unbounded.any():
            ax.plot(line.values[unbounded], np.ones(int(unbounded.sum())), "^", ms=7, color="tab:green",
                    transform=ax.get_xaxis_transform(), clip_on=False, label="unbounded max stable C_f")
        if none.any() or unbounded.any():
            ax.legend(fontsize=8, loc="best")
        if _log_spaced(line.values):   # a log: axis as the map of two keys draws it: on a linear
            ax.set_xscale("log")       # one its first decades crowd into the left edge
        held = [f"{a.key} = {a.values[0]:g}" for a in result.axes if a is not line]
        ax.set_xlabel(line.key + (f" ({', '.join(held)})" if held else ""))
        ax.set_ylabel("max stable C_f (gaps: unbounded)")
    else:
        x, y = result.axes[0], result.axes[1]
        shown = np.where(np.isinf(k), np.nan, np.where(k > 0, k, np.nan))
        norm = LogNorm(finite.min(), finite.max()) if finite.size and finite.max() > finite.min() else None
        mesh = ax.pcolormesh(y.values, x.values, shown, shading="auto", cmap="viridis", norm=norm)
        unb = np.isinf(k)
        if unb.any():
            ax.contourf(y.values, x.values, unb.astype(float), levels=[0.5, 1.5], colors="none",
                        hatches=["//"])
        none = k == 0   # unstable at small C_f: blank as an unbounded cell would be, so crossed
        if none.any():
            ax.contourf(y.values, x.values, none.astype(float), levels=[0.5, 1.5], colors="none",
                        hatches=["xx"])
        if (result.interval_count > 1).any():
            ax.contour(y.values, x.values, (result.interval_count > 1).astype(float), levels=[0.5],
                       colors="red", linewidths=1.0)
        ax.contour(y.values, x.values, result.stable.astype(float), levels=[0.5], colors="white",
                   linewidths=1.5)
        if finite.size:   # no point coloured (all unbounded or 0): a colour bar would show -0.1..0.1
            fig.colorbar(mesh, ax=ax, label="max stable C_f")
        ax.set_xlabel(y.key)
        ax.set_ylabel(x.key)
        if _log_spaced(y.values):
            ax.set_xscale("log")
        if _log_spaced(x.values):
            ax.set_yscale("log")
    ax.set_title(f"Max stable force gain ({kind}); hatched: unbounded; crossed: 0; white: "
                 f"stability at the design C_f; red: conditionally stable", fontsize=9)
    return save(fig, path)


def _log_spaced(v: np.ndarray) -> bool:
    return v.size > 2 and bool(np.all(v > 0)) and np.allclose(np.diff(np.log(v)), np.log(v[1] / v[0]))
