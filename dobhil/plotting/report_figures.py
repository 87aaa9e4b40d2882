"""Figures of ``dobhil report`` (a recorded run) and ``dobhil replay --plot``; drawing only."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np
from numpy.typing import NDArray

from dobhil.plotting.figures import _plt, save

if TYPE_CHECKING:
    from matplotlib.axes import Axes

    from dobhil.config.schema import Config

# The shapes drawn here, named rather than imported: the report and the replay are above
# plotting (they read logs, run the controller); mypy checks their classes against these.


class RecordedRun(Protocol):
    """A recorded run (``dobhil.run_report.RunData``): per-cycle arrays by name."""

    @property
    def t(self) -> NDArray[np.float64]: ...
    @property
    def config(self) -> Config | None: ...
    @property
    def metadata(self) -> Mapping[str, Mapping[str, str]]: ...
    def has(self, name: str) -> bool: ...
    def __getitem__(self, name: str) -> NDArray[np.float64]: ...


class Timed(Protocol):
    @property
    def time(self) -> NDArray[np.float64]: ...


class Replayed(Protocol):
    """A replay (``dobhil.replay.ReplayResult``): recorded and replayed outputs by name."""

    @property
    def recording(self) -> Timed: ...
    @property
    def overrides(self) -> Sequence[str]: ...
    def column(self, name: str, which: str = "replayed") -> NDArray[np.float64]: ...


def _finish(ax: Axes, ylabel: str, legend: bool = True) -> None:
    ax.set_ylabel(ylabel)
    ax.grid(True, alpha=0.3)
    if legend:
        ax.legend(fontsize=8, loc="best")


def _zoom_window(summary: Mapping[str, Any], t: np.ndarray) -> tuple[float, float] | None:
    steps = [s for s in summary.get("steps") or [] if s.get("metrics") is not None]  # those taken in contact
    if not steps:
        return None
    main = max(steps, key=lambda s: abs(s["end"] - s["start"]))
    settle = (main["metrics"].get("settling_time") or 0.05)
    return main["time"] - 0.1 * max(settle, 0.02), main["time"] + min(3 * max(settle, 0.02), float(t[-1]))


def open_loop(data: RecordedRun) -> bool:
    """A ``loop.mode: torque`` run: the reference is the torque command, nothing tracks a force."""
    return data.config is not None and data.config.loop.mode == "torque"


def labels(data: RecordedRun) -> dict[str, str]:
    """The names the figures give the reference and the force loop's parts: in an open-loop
    torque run the reference is the torque sent, and the observers run without commanding."""
    if open_loop(data):
        return {"force_title": "Interaction torque of an open-loop torque run (loop.mode: torque)",
                "tau_ref": "torque command (the reference, open loop)",
                "tau_per": "$\\tau_{per}$ = 0 (open loop: no force feedback)",
                "tau_dis_hat": "$\\hat\\tau_{dis}$ (DOb: estimated, not sent)",
                "u_sat": "$u$ sent = the torque reference (saturated)",
                "commands_title": "Torque command (open loop: the reference itself)"}
    return {"force_title": "Force response", "tau_ref": "reference $\\tau^{ref}_{int}$",
            "tau_per": "$\\tau_{per} = C_f(\\tau^{ref} - \\hat\\tau_{int})$",
            "tau_dis_hat": "$\\hat\\tau_{dis}$ (DOb)", "u_sat": "$u$ sent (saturated)",
            "commands_title": "Torque command and its parts"}


def force_figure(data: RecordedRun, predicted: np.ndarray | None, summary: Mapping[str, Any], path: Path) -> Path:
    plt = _plt()
    t = data.t
    zoom = _zoom_window(summary, t)
    names = labels(data)
    fig, axes = plt.subplots(2 if zoom else 1, 1, figsize=(9, 7.5 if zoom else 4.5), squeeze=False)
    for k, ax in enumerate(axes[:, 0]):
        ax.plot(t, data["tau_ref"], "k--", lw=1.2, label=names["tau_ref"], drawstyle="steps-post")
        ax.plot(t, data["tau_int_hat"], lw=1.5, label="estimated $\\hat\\tau_{int}$ (RTOb)")
        if data.has("tau_int_true"):
            ax.plot(t, data["tau_int_true"], lw=1.0, alpha=0.85, label="true $\\tau_{int}$ (emulator)")
        if predicted is not None:
            ax.plot(t, predicted, ":", lw=1.4, color="tab:red",
                    label="analysis prediction (sampled closed loop, in contact)")
        _finish(ax, "interaction torque [N m]")
        if k == 1 and zoom:
            ax.set_xlim(*zoom)
            # the prediction too: it is what the zoom compares the response with, and a peak
            # of it above the measured one would be cut off
            _fit_y(ax, t, zoom, [data["tau_ref"], data["tau_int_hat"], data["tau_int_true"],
                                 *([] if predicted is None else [predicted])])
            ax.set_title("zoom on the largest reference step taken in contact", fontsize=9)
    axes[-1, 0].set_xlabel("time [s]")
    axes[0, 0].set_title(_title(data, names["force_title"]))
    return save(fig, path)


def _fit_y(ax: Axes, t: np.ndarray, window: tuple[float, float], series: list[np.ndarray]) -> None:
    inside = (t >= window[0]) & (t <= window[1])
    values = np.concatenate([y[inside] for y in series])
    values = values[np.isfinite(values)]
    if values.size:
        lo, hi = float(values.min()), float(values.max())
        pad = 0.08 * (hi - lo or 1.0)
        ax.set_ylim(lo - pad, hi + pad)


def _title(data: RecordedRun, what: str) -> str:
    run = data.metadata.get("run", {})
    timing = run.get("timing", "")
    cfg = data.config
    design = (f"; C_f = {cfg.design.force_gain:g}, g_RTOb = {cfg.design.rtob_bandwidth:g} rad/s, "
              f"J_mi = {cfg.design.identified_inertia:g} kg m²") if cfg is not None else ""
    return f"{what} ({timing}{design})"


def error_figure(data: RecordedRun, path: Path) -> Path:
    plt = _plt()
    t = data.t
    rows = 2 if data.has("tau_int_true") else 1
    fig, axes = plt.subplots(rows, 1, figsize=(9, 3.2 * rows + 0.6), sharex=True, squeeze=False)
    ax = axes[0, 0]
    ax.plot(t, data["tau_ref"] - data["tau_int_hat"], lw=1.0, label="$\\tau^{ref} - \\hat\\tau_{int}$")
    if data.has("tau_int_true"):
        ax.plot(t, data["tau_ref"] - data["tau_int_true"], lw=1.0, alpha=0.8,
                label="$\\tau^{ref} - \\tau_{int}$ (true)")
    if open_loop(data):  # the reference is a torque: no force is tracked, the difference is no error
        _finish(ax, "torque reference - interaction torque [N m]")
        ax.set_title(_title(data, "Open-loop torque run: nothing tracks a force (loop.mode: torque)"))
    else:
        _finish(ax, "tracking error [N m]")
        ax.set_title(_title(data, "Force tracking error"))
    if rows == 2:
        ax = axes[1, 0]
        ax.plot(t, data["tau_int_hat"] - data["tau_int_true"], lw=1.0, color="tab:purple",
                label="$\\hat\\tau_{int} - \\tau_{int}$")
        _finish(ax, "estimation error [N m]")
    axes[-1, 0].set_xlabel("time [s]")
    return save(fig, path)


def position_figure(data: RecordedRun, path: Path) -> Path:
    plt = _plt()
    t = data.t
    fig, ax = plt.subplots(2, 1, figsize=(9, 6), sharex=True)
    ax[0].plot(t, data["q"] * 1e3, lw=1.2, label="measured q")
    if data.has("q_true"):
        ax[0].plot(t, data["q_true"] * 1e3, "--", lw=1.0, label="true q (emulator)")
    if data.config is not None:
        ax[0].axhline(data.config.environment.contact_position * 1e3, color="0.5", lw=0.8, ls=":",
                      label="contact position")
    _finish(ax[0], "position [mrad]")
    ax[1].plot(t, data["dq"], lw=1.0, label="measured dq")
    if data.has("dq_true"):
        ax[1].plot(t, data["dq_true"], "--", lw=1.0, label="true dq (emulator)")
    _finish(ax[1], "velocity [rad/s]")
    ax[1].set_xlabel("time [s]")
    ax[0].set_title(_title(data, "Motor position and velocity"))
    return save(fig, path)


def command_figure(data: RecordedRun, path: Path) -> Path:
    plt = _plt()
    t = data.t
    fig, ax = plt.subplots(figsize=(9, 4.5))
    ax.plot(t, data["u_unsat"], lw=1.0, alpha=0.7, label="$u$ before saturation")
    names = labels(data)
    ax.plot(t, data["u_sat"], lw=1.3, label=names["u_sat"])
    ax.plot(t, data["tau_dis_hat"], lw=1.0, label=names["tau_dis_hat"])
    ax.plot(t, data["tau_per"], lw=1.0, label=names["tau_per"])
    limit = data.metadata.get("run", {}).get("torque_limit")
    if limit:
        for s in (1, -1):
            ax.axhline(s * float(limit), color="0.4", lw=0.8, ls="--")
    _finish(ax, "torque [N m]")
    ax.set_xlabel("time [s]")
    ax.set_title(_title(data, names["commands_title"]))
    return save(fig, path)


def timing_figure(data: RecordedRun, path: Path) -> Path:
    plt = _plt()
    fig, ax = plt.subplots(1, 2, figsize=(10, 4))
    ex = data["exec_time"][np.isfinite(data["exec_time"])] * 1e6
    pe = data["period_error"][np.isfinite(data["period_error"])] * 1e6
    ax[0].hist(ex, bins=80, color="tab:blue", log=True)
    ax[0].set_xlabel("execution time [µs]")
    ax[0].set_ylabel("cycles")
    for q, ls in ((50, "-"), (99, "--")):
        if ex.size:
            v = float(np.percentile(ex, q))
            ax[0].axvline(v, color="k", ls=ls, lw=0.8, label=f"p{q} = {v:.0f} µs")
    ax[0].legend(fontsize=8)
    ax[1].hist(pe, bins=80, color="tab:orange", log=True)
    ax[1].set_xlabel("period error (actual - nominal start) [µs]")
    overruns = int(np.nansum(data["overrun"]))
    ax[1].set_title(f"overruns: {overruns}", fontsize=9)
    for a in ax:
        a.grid(True, alpha=0.3)
    timing = data.metadata.get("run", {}).get("timing", "")
    fig.suptitle(f"Loop timing ({timing}; lockstep times are host compute time, not real-time behaviour)"
                 if timing == "lockstep" else "Loop timing (real time)")
    return save(fig, path)


def report_figures(data: RecordedRun, predicted: np.ndarray | None, summary: Mapping[str, Any],
                   out: Path) -> list[Path]:
    """force.png, tracking_error.png, position.png, commands.png, loop_timing.png."""
    return [force_figure(data, predicted, summary, out / "force.png"),
            error_figure(data, out / "tracking_error.png"),
            position_figure(data, out / "position.png"),
            command_figure(data, out / "commands.png"),
            timing_figure(data, out / "loop_timing.png")]


def replay_figure(result: Replayed, path: Path) -> Path:
    """Recorded vs replayed command and estimates over the same measured feedback."""
    plt = _plt()
    t = result.recording.time
    over = ", ".join(result.overrides) or "recorded config"
    fig, ax = plt.subplots(3, 1, figsize=(9, 8), sharex=True)
    for a, name, label in ((ax[0], "u_sat", "command u [N m]"), (ax[1], "tau_int_hat", "$\\hat\\tau_{int}$ [N m]"),
                           (ax[2], "tau_dis_hat", "$\\hat\\tau_{dis}$ [N m]")):
        a.plot(t, result.column(name, "recorded"), lw=1.3, label="recorded")
        a.plot(t, result.column(name), "--", lw=1.1, label=f"replayed ({over})")
        _finish(a, label)
    ax[0].plot(t, result.column("tau_ref", "recorded"), "k:", lw=1.0, label="reference")
    ax[0].legend(fontsize=8)
    ax[2].set_xlabel("time [s]")
    ax[0].set_title("Replay on the recorded feedback: recorded vs replayed")
    path.parent.mkdir(parents=True, exist_ok=True)
    return save(fig, path)


__all__ = ["report_figures", "replay_figure"]
