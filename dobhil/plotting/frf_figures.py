"""A measured frequency response with the fitted model's over it (``dobhil identify --frf
--plot DIR``): gain and phase with their 95 % bands, and the coherence. Takes arrays, not
dobhil.identify's objects (the plotting layer draws what it is given: :mod:`dobhil.identify.frf`
computes)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dobhil.plotting.figures import _plt, save


@dataclass(frozen=True)
class FrfCurves:
    """What one figure draws: frequency [Hz], measured response (complex) and its bands (gain
    ``low .. high``, phase ``+- phase_band`` [rad]), coherence, the model's response (complex),
    and the labels."""

    frequency: np.ndarray
    measured: np.ndarray
    low: np.ndarray
    high: np.ndarray
    phase_band: np.ndarray
    coherence: np.ndarray
    model: np.ndarray
    unit: str           # the gain's unit, e.g. "rad/s / N m"
    method: str         # how it was measured, for the legend
    title: str
    #: the linear part of the model (no Coulomb friction), drawn dashed; None: not drawn
    linear: np.ndarray | None = None


def _db(x: np.ndarray) -> np.ndarray:
    with np.errstate(divide="ignore"):
        return 20.0 * np.log10(np.asarray(x, float))


def frf_figure(c: FrfCurves, path: Path) -> Path:
    """Three panels sharing a logarithmic frequency axis: gain [dB] (measured points with their
    band, model line), phase [deg] (the measured phase unwrapped from the model's: a delay
    shows as a growing gap), coherence."""
    fig, (gain, phase, coh) = _plt().subplots(3, 1, figsize=(8, 8), sharex=True,
                                              gridspec_kw={"height_ratios": [3, 3, 1.5]})
    f = np.asarray(c.frequency, float)
    order = np.argsort(f)
    f = f[order]
    meas, model = np.asarray(c.measured)[order], np.asarray(c.model)[order]
    many = len(f) > 80   # Welch bins: a line with a shaded band; a multisine's lines: points with bars
    mag_db = _db(np.abs(meas))
    lo_db, hi_db = _db(np.asarray(c.low)[order]), _db(np.asarray(c.high)[order])
    lo_db = np.where(np.isfinite(lo_db), lo_db, np.nanmin(mag_db) - 20.0)
    label = f"measured ({c.method})"
    if many:
        gain.fill_between(f, lo_db, hi_db, color="tab:blue", alpha=0.25, lw=0, label="95 % band")
        gain.plot(f, mag_db, color="tab:blue", lw=0.8, label=label)
    else:
        gain.errorbar(f, mag_db, yerr=[mag_db - lo_db, hi_db - mag_db], fmt="o", ms=3, color="tab:blue",
                      elinewidth=0.8, capsize=2, label=f"{label}, 95 % band")
    gain.plot(f, _db(np.abs(model)), color="tab:orange", lw=1.4, label="fitted model (simulated, same estimator)")
    linear = None if c.linear is None else np.asarray(c.linear)[order]
    if linear is not None:
        gain.plot(f, _db(np.abs(linear)), color="0.3", lw=1.0, ls="--", label="its linear part (no Coulomb friction)")
    gain.set_ylabel(f"gain [dB re 1 {c.unit}]")
    # the phase relative to the model's unwrapped, then the model's added back: no 360 deg jumps
    # between neighbouring points where the two agree
    model_phase = np.unwrap(np.angle(model))
    measured_phase = model_phase + np.angle(meas / model)
    band = np.degrees(np.asarray(c.phase_band)[order])
    if many:
        phase.fill_between(f, np.degrees(measured_phase) - band, np.degrees(measured_phase) + band,
                           color="tab:blue", alpha=0.25, lw=0)
        phase.plot(f, np.degrees(measured_phase), color="tab:blue", lw=0.8)
    else:
        phase.errorbar(f, np.degrees(measured_phase), yerr=band, fmt="o", ms=3, color="tab:blue",
                       elinewidth=0.8, capsize=2)
    phase.plot(f, np.degrees(model_phase), color="tab:orange", lw=1.4)
    if linear is not None:
        phase.plot(f, np.degrees(model_phase + np.angle(linear / model)), color="0.3", lw=1.0, ls="--")
    phase.set_ylabel("phase [deg]")
    coh.plot(f, np.asarray(c.coherence)[order], "o" if not many else "-", ms=3, lw=0.8, color="tab:green")
    coh.set_ylim(0.0, 1.05)
    coh.set_ylabel("coherence")
    coh.set_xlabel("frequency [Hz]")
    coh.set_xscale("log")
    for ax in (gain, phase, coh):
        ax.grid(True, which="both", alpha=0.3)
    gain.legend(loc="best", fontsize="small")
    gain.set_title(c.title)
    fig.tight_layout()
    return save(fig, path)
