"""Root locus, step response, Bode and sweep heat-map figures for reports.

Computing is elsewhere (:mod:`dobhil.analysis`); these functions only draw.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    import control
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

    from dobhil.analysis.report import DomainAnalysis


def _plt() -> Any:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt


#: resolution of every saved figure
DPI = 150


def save(fig: Figure, path: Path) -> Path:
    from dobhil.files import atomic_path
    try:
        with atomic_path(path) as tmp:  # a complete file or none
            fig.savefig(tmp, dpi=DPI, bbox_inches=tight_box(fig, path))
    finally:
        _plt().close(fig)
    return path


def tight_box(fig: Figure, path: Path) -> Any:
    """The box ``bbox_inches="tight"`` would crop a PNG of ``fig`` to, measured without the
    dry draw matplotlib makes first (``FigureCanvasBase.print_figure``: a whole draw with
    rendering off, then the real one; a third of a run report's figure time), so each figure
    is drawn once: the same pixels, as the figure's own tight box, with the same padding,
    taken by the same Agg renderer at the saved dpi. ``"tight"`` itself where the dry draw
    does something: a layout engine to run (constrained layout) or a vector format (its own
    renderer's text metrics)."""
    get_renderer = getattr(fig.canvas, "get_renderer", None)
    if fig.get_layout_engine() is not None or Path(path).suffix.lower() != ".png" or get_renderer is None:
        return "tight"
    import matplotlib as mpl
    fig.set_dpi(DPI)
    return fig.get_tightbbox(get_renderer()).padded(mpl.rcParams["savefig.pad_inches"])


def locus_points(d: DomainAnalysis, num: int = 1500) -> tuple[np.ndarray, np.ndarray]:
    """(gains, closed-loop poles per gain) covering the crossings of the design."""
    a, b, c, _ = d.systems.open.siso("tau_per", "tau_int_hat")
    cross = d.gains.crossings[~np.isnan(d.gains.crossings)]
    ref = float(np.median(cross)) if cross.size else max(float(d.params.value("force_gain")), 1.0)
    k = np.unique(np.concatenate([np.logspace(np.log10(ref) - 4, np.log10(ref) + 3, num), cross]))
    return k, np.linalg.eigvals(a[None] - k[:, None, None] * (b @ c)[None])


def root_locus(ax: Axes, d: DomainAnalysis, title: str = "") -> None:
    k, poles = locus_points(d)
    g = d.gains
    if d.sampled:
        th = np.linspace(0, 2 * np.pi, 400)
        ax.plot(np.cos(th), np.sin(th), color="0.6", lw=0.8, ls="--", label="unit circle")
    else:
        ax.axvline(0.0, color="0.6", lw=0.8, ls="--")
    ax.plot(poles.real, poles.imag, ".", ms=1.2, color="tab:blue")
    ol, zz = g.poles, g.zeros[~np.isnan(g.zeros)]
    ax.plot(ol.real, ol.imag, "x", ms=8, mew=2, color="k", label="open-loop poles")
    ax.plot(zz.real, zz.imag, "o", ms=8, mfc="none", mew=1.5, color="tab:red", label="zeros")
    cf = float(d.params.value("force_gain"))
    ax.plot(d.closed_loop_poles.real, d.closed_loop_poles.imag, "s", ms=5, color="tab:green",
            label=f"poles at C_f = {cf:g}")
    kmax = float(g.max_stable_gain)
    sub = ("the position drifts at every C_f (K_env 0 or too small to hold it)" if d.position_drifts
           else "unbounded C_f" if np.isinf(kmax) else f"max stable C_f = {kmax:.4g}")
    ax.set_title(f"{title}\n{sub}" if title else sub, fontsize=9)
    ax.set_xlabel("Re(z)" if d.sampled else "Re(s) [rad/s]")
    ax.set_ylabel("Im(z)" if d.sampled else "Im(s) [rad/s]")
    _limits(ax, np.concatenate([ol, zz, d.closed_loop_poles]), d.sampled)
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=7, loc="best")


def _limits(ax: Axes, pts: np.ndarray, sampled: bool) -> None:
    if sampled:
        r = max(1.2, float(np.abs(pts).max()) * 1.1)
        ax.set_xlim(-r, r)
        ax.set_ylim(-r, r)
        ax.set_aspect("equal")
        return
    r = float(np.abs(pts).max()) * 1.3 or 1.0
    # the right half-plane is drawn narrower (a stable design has nothing there) but never
    # so narrow that it cuts off a right-half-plane zero or an unstable closed-loop pole:
    # those are what bound C_f (paper Fig. 2c), and a plot without them reads as stable
    ax.set_xlim(-r, max(0.6 * r, 1.3 * float(pts.real.max())))
    ax.set_ylim(-r, r)


def step_plot(ax: Axes, d: DomainAnalysis, label: str = "") -> None:
    if not d.stable:
        # named: beside the other domain's stable step, a bare "closed loop unstable" read as
        # that curve's (the sampled loop, the one the runtime runs, is the one that often is)
        what = f"{label or 'estimated interaction torque'}: closed loop unstable, no step"
        ax.text(0.5, 0.5 if d.sampled else 0.6, what, transform=ax.transAxes, ha="center", color="tab:red")
        return
    t = d.step_time * 1e3
    style: dict[str, Any] = {"drawstyle": "steps-post"} if d.sampled else {}
    ax.plot(t, d.step_estimate, label=label or "estimated interaction torque", **style)


def bode(axes: tuple[Axes, Axes], sys: control.LTI, label: str) -> None:
    import control
    nyq = np.pi / sys.dt if sys.dt else 1e5
    # from 1 rad/s up; a sampled loop whose Nyquist frequency is below that (loop.period above
    # pi s) from three decades below it: a grid from 1 rad/s ran down through frequencies above
    # Nyquist (python-control's warning, and an aliased curve)
    top = nyq * 0.999
    w = np.logspace(0 if top > 1.0 else np.log10(top) - 3, np.log10(top), 600)
    resp = control.frequency_response(sys, w)
    mag = np.abs(np.asarray(resp.complex).reshape(-1))
    ph = np.unwrap(np.angle(np.asarray(resp.complex).reshape(-1))) * 180 / np.pi
    axes[0].semilogx(w, 20 * np.log10(np.maximum(mag, 1e-300)), label=label)
    axes[1].semilogx(w, ph, label=label)


def step_figure(continuous: DomainAnalysis, discrete: DomainAnalysis, out: Path, title: str = "") -> Path:
    """step.png: the unit step of tau_int^ref in both domains; an unstable one is said in
    words naming its curve (:func:`step_plot`), and with no curve at all no legend is drawn
    (matplotlib warns of a legend without curves)."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(7, 4.5))
    step_plot(ax, continuous, "estimated tau_int (continuous)")
    step_plot(ax, discrete, "estimated tau_int (sampled)")
    if continuous.stable:
        ax.plot(continuous.step_time * 1e3, continuous.step_true, "--", label="true tau_int (continuous)")
    ax.set_xlabel("time [ms]")
    ax.set_ylabel("interaction torque / reference")
    ax.set_title(f"Unit step of tau_int^ref {title}")
    ax.grid(True, alpha=0.3)
    if ax.get_legend_handles_labels()[0]:
        ax.legend(fontsize=8)
    return save(fig, out / "step.png")


def analysis_figures(continuous: DomainAnalysis, discrete: DomainAnalysis, out: Path,
                     title: str = "") -> list[Path]:
    """root_locus.png, step.png and bode.png for a design, continuous beside sampled."""
    plt = _plt()
    paths = []
    fig, ax = plt.subplots(1, 2, figsize=(11, 5))
    root_locus(ax[0], continuous, "continuous (paper)")
    root_locus(ax[1], discrete, f"sampled, T = {discrete.sample_time:g} s")
    fig.suptitle(f"Root locus of 1 + C_f L {title}")
    paths.append(save(fig, out / "root_locus.png"))
    paths.append(step_figure(continuous, discrete, out, title))
    fig, ax = plt.subplots(2, 1, figsize=(7, 6), sharex=True)
    cf = float(continuous.params.value("force_gain")) or 1.0
    bode((ax[0], ax[1]), cf * continuous.systems.system("open_loop"), "C_f L(s)")
    bode((ax[0], ax[1]), cf * discrete.systems.system("open_loop"), "C_f L(z)")
    ax[0].set_ylabel("magnitude [dB]")
    ax[1].set_ylabel("phase [deg]")
    ax[1].set_xlabel("frequency [rad/s]")
    for a in ax:
        a.grid(True, which="both", alpha=0.3)
    ax[0].legend(fontsize=8)
    ax[0].set_title(f"Open loop C_f L {title}")
    paths.append(save(fig, out / "bode.png"))
    return paths
