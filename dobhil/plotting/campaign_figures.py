"""Figures of a Monte-Carlo campaign (``dobhil montecarlo --plot``), from plain arrays: the
command hands the table's columns in (plotting sits below the campaign package).

- :func:`metric_histograms`: one histogram per metric over the runs that have it, the
  median marked;
- tick labels thinned until none touch (:func:`dobhil.plotting.ticks.fit_ticks`);
- :func:`vary_scatter`: each drawn key against the force RMS error, runs coloured by
  success; a run with no RMS error (it raised before any cycle) is drawn at the top edge
  as a cross, so no failed run is invisible.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from dobhil.plotting.figures import _plt, save
from dobhil.plotting.ticks import fit_ticks

if TYPE_CHECKING:
    from matplotlib.figure import Figure

#: axis labels of the metrics a campaign measures (its docs say how each is defined)
LABELS = {"force_rms_error": "force RMS error [N m]", "overshoot_pct": "overshoot [%]",
          "rise_time": "rise time 10-90 % [s]", "settling_time": "settling time 2 % [s]",
          "final_error": "final error (command - true) [N m]",
          "final_tau_int_true": "final true interaction torque [N m]"}

#: what an empty panel says
EMPTY = {"settling_time": "no run settled into\nthe 2 % band"}


def metric_histograms(metrics: Mapping[str, np.ndarray], runs: int, path: Path) -> Path:
    """:func:`metric_figure` saved to ``path``."""
    return save(metric_figure(metrics, runs), path)


def metric_figure(metrics: Mapping[str, np.ndarray], runs: int) -> Figure:
    """A histogram per metric (NaN: the run has no value), titled with how many runs have one."""
    names = list(metrics)
    cols = min(3, max(1, len(names)))
    rows = -(-len(names) // cols) if names else 1
    fig, axes = _plt().subplots(rows, cols, figsize=(4.2 * cols, 3.0 * rows), squeeze=False, layout="constrained")
    for ax, name in zip(axes.flat, names):
        values = np.asarray(metrics[name], float)
        values = values[np.isfinite(values)]
        if values.size:
            ax.hist(values, bins=min(50, max(5, int(np.sqrt(values.size)))), color="tab:blue", alpha=0.8)
            ax.axvline(float(np.median(values)), color="k", lw=1, ls="--", label="median")
            ax.legend(loc="best", fontsize=8)
        else:   # an empty panel says why, not just nothing
            ax.text(0.5, 0.5, EMPTY.get(name, "no run has a value"), ha="center", va="center",
                    transform=ax.transAxes, fontsize=9, wrap=True)
        ax.ticklabel_format(axis="x", useOffset=False)   # 1 N m, not "1e-8 + 1"
        ax.set_xlabel(LABELS.get(name, name))
        ax.set_ylabel("runs")
        ax.set_title(f"{values.size} of {runs} runs", fontsize=9)
        ax.grid(True, alpha=0.3)
    for ax in list(axes.flat)[len(names):]:
        ax.set_visible(False)
    fig.suptitle("Monte-Carlo campaign: metrics")
    fit_ticks(fig)
    return fig


def vary_scatter(draws: Mapping[str, np.ndarray], rms: np.ndarray, ok: np.ndarray, path: Path) -> Path:
    """:func:`vary_figure` saved to ``path``."""
    return save(vary_figure(draws, rms, ok), path)


def vary_figure(draws: Mapping[str, np.ndarray], rms: np.ndarray, ok: np.ndarray) -> Figure:
    """Each drawn key (x) against the force RMS error (y, log when it spans a decade)."""
    keys = list(draws)
    rms = np.asarray(rms, float)
    ok = np.asarray(ok, bool)
    fig, axes = _plt().subplots(1, len(keys), figsize=(4.2 * len(keys), 3.6), squeeze=False, sharey=True,
                                layout="constrained")
    known = rms[np.isfinite(rms)]
    top = float(known.max()) * 1.5 if known.size else 1.0
    log = known.size > 0 and known.min() > 0 and known.max() / known.min() > 10
    for ax, key in zip(axes.flat, keys):
        x = np.asarray(draws[key], float)
        _scatter(ax, x, rms, ok, top)
        ax.set_xlabel(key)
        finite = x[np.isfinite(x)]
        if finite.size and finite.min() > 0 and finite.max() / finite.min() >= 10:
            ax.set_xscale("log")   # a loguniform draw over decades: every decade as wide
        if log:
            ax.set_yscale("log")
        ax.grid(True, alpha=0.3)
    axes.flat[0].set_ylabel(LABELS["force_rms_error"])
    fig.legend(*axes.flat[0].get_legend_handles_labels(), loc="outside lower center", ncols=3, fontsize=8)
    fig.suptitle(f"Monte-Carlo campaign: {int(ok.sum())} of {ok.size} runs succeeded")
    fit_ticks(fig)
    return fig


def _scatter(ax: object, x: np.ndarray, rms: np.ndarray, ok: np.ndarray, top: float) -> None:
    has = np.isfinite(rms)
    ax.scatter(x[ok & has], rms[ok & has], s=10, color="tab:blue", label="succeeded")  # type: ignore[attr-defined]
    ax.scatter(x[~ok & has], rms[~ok & has], s=14, color="tab:red", label="failed")  # type: ignore[attr-defined]
    ax.scatter(x[~has], np.full(int((~has).sum()), top), s=24, marker="x", color="tab:red",  # type: ignore[attr-defined]
               label="failed, no RMS error")


__all__ = ["metric_figure", "metric_histograms", "vary_figure", "vary_scatter"]
