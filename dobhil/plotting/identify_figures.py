"""Measured vs model of one identified segment (``dobhil identify --plot DIR``): the torque
sent, the measured position and velocity with the fitted model's simulation of them from that
torque, and the velocity residual (what the fit minimises: a misfit shows there as structure
instead of noise).

An excitation switches far faster than a page shows (a PRBS level every 2 ms over 5 s is
2,500 levels on 1,000 pixels): drawn sample by sample it is a solid block. A long torque is
drawn instead as its min-max band and mean per bin (:func:`envelope`: what the record spans
there, every sample inside it; the mean shows its slow part) with the window a last panel
shows sample by sample (:func:`zoom_window`) shaded on it.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from dobhil.plotting.figures import _plt, save

#: bins of the torque's min-max band: about one per two pixels of the saved figure
ENVELOPE_BINS = 600
#: samples the zoom panel shows: 0.2 s at 1 kHz, 100 levels of a 2 ms PRBS
ZOOM_SAMPLES = 200


def envelope(t: np.ndarray, y: np.ndarray,
             bins: int = ENVELOPE_BINS) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``y`` over ``t`` as ``(edges, lo, hi, mean)``: ``bins`` (fewer for a short record) runs
    of consecutive samples, run i from ``edges[i]`` to ``edges[i + 1]``, with its minimum,
    maximum and mean; every sample lies in its run's band and each band's ends are samples."""
    t, y = np.asarray(t, float), np.asarray(y, float)
    if t.shape != y.shape or t.ndim != 1 or t.size < 2:
        raise ValueError(f"envelope: expected t and y of one equal length >= 2, got {t.shape} and {y.shape}")
    starts = np.unique(np.linspace(0, t.size, min(bins, t.size), endpoint=False).astype(int))
    lo, hi = np.minimum.reduceat(y, starts), np.maximum.reduceat(y, starts)
    mean = np.add.reduceat(y, starts) / np.diff(np.append(starts, t.size))
    edges = np.append(t[starts], 2 * t[-1] - t[-2])   # the last run ends a sample after it
    return edges, lo, hi, mean


def zoom_window(n: int, samples: int = ZOOM_SAMPLES) -> slice | None:
    """The samples of the zoom panel: ``samples`` in the middle of a record of ``n``; None
    when the record is short enough to read whole (at most twice that)."""
    if n <= 2 * samples:
        return None
    start = (n - samples) // 2
    return slice(start, start + samples)


def measured_vs_model(t: np.ndarray, measured: tuple[np.ndarray, np.ndarray], model: tuple[np.ndarray, np.ndarray],
                      title: str, path: Path, torque: np.ndarray | None = None) -> Path:
    """Torque sent (when given), position and velocity (measured solid, model dashed) and the
    velocity residual, over ``t`` [s] (time in the segment's log), to ``path``. A torque of
    more than 2 :data:`ZOOM_SAMPLES` samples is its min-max band, and a last panel shows a
    window of it sample by sample with the measured and model velocity."""
    zoom = None if torque is None else zoom_window(len(t))
    rows = 3 + (torque is not None) + (zoom is not None)
    fig, axes = _plt().subplots(rows, 1, figsize=(8, 2.2 * rows))
    main = list(axes[:rows - (zoom is not None)])
    for ax in main[1:]:
        ax.sharex(main[0])
    top = 0
    if torque is not None:
        _torque_panel(main[0], t, np.asarray(torque, float), zoom)
        top = 1
    for ax, m, s, label in zip(main[top:top + 2], measured, model, ("position [rad]", "velocity [rad/s]")):
        ax.plot(t, m, label="measured", lw=1)
        ax.plot(t, s, label="model", lw=1, ls="--")
        ax.set_ylabel(label)
        ax.grid(True, alpha=0.3)
        ax.legend(loc="best")
    residual = np.asarray(measured[1], float) - np.asarray(model[1], float)
    main[-1].plot(t, residual, lw=0.6, color="tab:red")
    main[-1].set_ylabel("velocity residual\n(measured - model) [rad/s]")
    main[-1].grid(True, alpha=0.3)
    main[-1].set_xlabel("time in the log [s]")
    if zoom is not None and torque is not None:
        _zoom_panel(axes[-1], t, np.asarray(torque, float), measured[1], model[1], zoom)
    main[0].set_title(title)
    fig.tight_layout()
    return save(fig, path)


def _torque_panel(ax: Any, t: np.ndarray, torque: np.ndarray, zoom: slice | None) -> None:
    """The whole record: its min-max band when it is long (a zoom window shaded), else each sample."""
    if zoom is None:
        ax.plot(t, torque, lw=0.8, color="k", drawstyle="steps-post")
    else:
        edges, lo, hi, mean = envelope(t, torque)
        ax.fill_between(edges, np.append(lo, lo[-1]), np.append(hi, hi[-1]), step="post", color="0.75", lw=0,
                        label=f"min-max per {(edges[-1] - edges[0]) / len(lo) * 1e3:.3g} ms")
        ax.stairs(mean, edges, baseline=None, color="k", lw=0.8, label="mean per bin")
        ax.axvspan(t[zoom.start], t[zoom.stop - 1], color="tab:orange", alpha=0.3, lw=0, label="zoomed below")
        ax.legend(loc="best", fontsize="small")
    ax.set_ylabel("torque sent [N m]")
    ax.grid(True, alpha=0.3)


def _zoom_panel(ax: Any, t: np.ndarray, torque: np.ndarray, velocity: np.ndarray, model: np.ndarray,
                zoom: slice) -> None:
    """The zoom window sample by sample: the torque (steps) and, on a second axis, the measured
    and model velocity."""
    tz = t[zoom]
    ax.plot(tz, torque[zoom], lw=0.8, color="k", drawstyle="steps-post", label="torque sent")
    ax.set_ylabel("torque sent [N m]\n(zoom)")
    ax.set_xlabel("time in the log [s] (zoom)")
    ax.grid(True, alpha=0.3)
    right = ax.twinx()
    right.plot(tz, np.asarray(velocity, float)[zoom], lw=1, color="tab:blue", label="velocity measured")
    right.plot(tz, np.asarray(model, float)[zoom], lw=1, ls="--", color="tab:orange", label="velocity model")
    right.set_ylabel("velocity [rad/s]")
    right.legend(loc="upper right", fontsize="small")


__all__ = ["ENVELOPE_BINS", "ZOOM_SAMPLES", "envelope", "measured_vs_model", "zoom_window"]
