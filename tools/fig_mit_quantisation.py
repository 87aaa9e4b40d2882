#!/usr/bin/env python3
"""Write docs/img/mit_quantisation.png: what an MIT-mode codec's quantisation does to the
force loop of the demo design on an AK80-9 (configs/mit-demo.yaml). Run from the
repository root:

    python tools/fig_mit_quantisation.py [CONFIG] [OUT.png]

Four panels, every number printed as well:

a) the force step response (the true interaction torque) of the demo design and of the
   same design at a higher force gain (VARIANT), the sampled loop with exact measurements
   and torque and with the codec in the loop: the emulator's plant
   (dobhil.emulator.plant, the analysis' exact model), the runtime's controller
   (ForceController, the generated kernel), the profile's command delay, the replies
   packed and decoded by the codec as the motor and the drive do (pack_reply /
   unpack_reply), the torque packed by the drive's TorqueFrame and decoded as the
   firmware does (unpack_command); plus `dobhil run --emulate --lockstep` of the demo
   (the emulated motor and the real drive), which the simulation reproduces bit for bit;
b) the force with the codec minus the exact one, both designs, with the closed loop's H2
   prediction for a moving servo (dobhil.analysis.quantisation) as a band;
c) the steady force of the demo, codec minus exact: the truncated torque command;
d) the noise on the DOb and RTOb estimates of a moving servo (the observers fed with the
   codec's decoded position and velocity of sinusoids spanning most of the range, minus
   the same observers fed the exact signals), against the H2 prediction (dashed: +-1 RMS).
"""

from __future__ import annotations

import contextlib
import io
import math
import sys
import tempfile
from collections import deque
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from dobhil.analysis.quantisation import codec_figures, quantisation_text  # noqa: E402
from dobhil.config import load_config, resolve_config  # noqa: E402
from dobhil.config.schema import Config  # noqa: E402
from dobhil.drives.mit.codec import (TorqueFrame, pack_reply, unpack_command,  # noqa: E402
                                     unpack_reply)
from dobhil.drives.mit.plugin import model_quantisation  # noqa: E402
from dobhil.drives.mit.rules import model_of  # noqa: E402
from dobhil.drives.load import load_drive_profile  # noqa: E402
from dobhil.drives.timing import effective_config  # noqa: E402
from dobhil.emulator.plant import Plant  # noqa: E402
from dobhil.plotting.figures import _plt, save  # noqa: E402
from dobhil.runtime.controller import ForceController  # noqa: E402
from dobhil.runtime.references import make_reference  # noqa: E402
from dobhil.synthesis.controller import DIS, INT, sampled_controller  # noqa: E402
from dobhil.synthesis.params import params_from_config  # noqa: E402

#: columns of a simulated run
T, REF, FORCE, INT_HAT, DIS_HAT, U = range(6)
MOVING_SECONDS = 20.0    # length of the moving-servo record of panel c
SEED = 18
#: the same design with a higher force gain: the demo's C_f = 2 with J_mi = J_mn / 2 and equal
#: observer bandwidths makes the measured velocity cancel out of the command exactly
#: (tau_dis^ - C_f tau_int^ has (J_mn - C_f J_mi) s dq = 0); any other gain lets it in
VARIANT = ["design.force_gain=3"]


def closed_loop(config: Config, model: Any | None) -> np.ndarray:
    """One run of the sampled loop (columns T..U), with the codec when ``model`` is given."""
    plant = Plant.from_config(config)
    ctrl = ForceController.from_config(config)
    ref = make_reference(config.reference, duration=config.loop.duration)
    period = config.loop.period
    n = int(round(config.loop.duration / period))
    frame = TorqueFrame(model) if model is not None else None
    data = bytearray(frame.template) if frame is not None else bytearray(8)

    def measured() -> tuple[float, float]:
        if model is None:
            return plant.position, plant.velocity
        reply = unpack_reply(model, pack_reply(model, 1, plant.position, plant.velocity, 0.0))
        return reply.position, reply.velocity

    q, dq = measured()
    ctrl.initialize(q, dq)
    in_transit = deque([0.0] * config.design.delay_samples)
    out = np.zeros((n, 6))
    for k in range(n):
        q, dq = measured()
        step = ctrl.step(q, dq if ctrl.measures_velocity else None, ref(k * period))
        out[k] = (k * period, step.tau_ref, plant.truth().tau_int, step.tau_int_hat,
                  step.tau_dis_hat, step.u)
        applied = step.u
        if frame is not None:
            frame.fill(data, applied)
            applied = unpack_command(model, bytes(data)).torque
        in_transit.append(applied)
        plant.step(in_transit.popleft(), period)
    return out


def emulated_run(config_path: Path) -> Any:
    """``dobhil run CONFIG --emulate --lockstep --log ...`` in this process, read back
    (:func:`dobhil.run_report.load_run`): the emulated MIT motor, the real drive, the codec
    in both directions."""
    from dobhil.cli.main import main as dobhil
    from dobhil.run_report import load_run
    with tempfile.TemporaryDirectory() as tmp:
        log = Path(tmp) / "run.mcap"
        with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
            code = dobhil(["run", str(config_path), "--emulate", "--lockstep", "--log", str(log)])
        if code != 0:
            raise SystemExit(f"the lockstep run of {config_path} ended with exit code {code}")
        return load_run(log)


def steady_error(model: Any, tau: float) -> float:
    """The torque the motor applies minus ``tau`` commanded (the steady force error of a
    loop whose estimate has converged to the reference: it holds the command at ``tau``)."""
    frame = TorqueFrame(model)
    data = bytearray(frame.template)
    frame.fill(data, tau)
    return float(unpack_command(model, bytes(data)).torque) - tau


def moving_observer_noise(config: Config, model: Any) -> np.ndarray:
    """(n, 2) DOb and RTOb estimate errors of a moving servo from the codec's decoded
    position and velocity (the observers are linear: decoded minus exact input)."""
    ctrl = sampled_controller(params_from_config(config))
    period = config.loop.period
    n = int(MOVING_SECONDS / period)
    t = np.arange(n) * period
    ph = np.random.default_rng(SEED).uniform(0.0, 2.0 * math.pi, 2)
    q = 0.8 * model.p_max * np.sin(2 * math.pi * 0.37 * t + ph[0])
    dq = 0.8 * model.v_max * np.sin(2 * math.pi * 1.1 * t + ph[1])
    decoded = [unpack_reply(model, pack_reply(model, 1, float(a), float(b), 0.0))
               for a, b in zip(q, dq)]
    err = np.stack([[r.position for r in decoded] - q, [r.velocity for r in decoded] - dq],
                   axis=1)[:, :ctrl.b_y.shape[1]]
    out = np.empty((n, 2))
    xi = np.zeros(ctrl.order)
    for k in range(n):
        out[k] = ctrl.c @ xi + ctrl.d_y @ err[k]
        xi = ctrl.a @ xi + ctrl.b_y @ err[k]
    return out[500:]


def design_on(config_path: Path, overrides: list[str]) -> tuple[Config, Any]:
    """The config as it runs on its drive profile (the drive's command delay) and the model."""
    raw = load_config(config_path, overrides)
    profile = load_drive_profile(raw, resolve_config(str(config_path)).parent)
    config, _ = effective_config(raw, profile)
    return config, model_of(profile)


def main() -> int:
    config_path = Path(sys.argv[1]) if len(sys.argv) > 1 else ROOT / "configs/mit-demo.yaml"
    out = Path(sys.argv[2]) if len(sys.argv) > 2 else ROOT / "docs/img/mit_quantisation.png"
    config, model = design_on(config_path, [])
    variant, _ = design_on(config_path, VARIANT)
    figures = codec_figures(params_from_config(config), model_quantisation(model))
    figures_v = codec_figures(params_from_config(variant), model_quantisation(model))
    print(quantisation_text(figures))
    exact, coded = closed_loop(config, None), closed_loop(config, model)
    exact_v, coded_v = closed_loop(variant, None), closed_loop(variant, model)
    run = emulated_run(config_path)
    # the run's cycle k uses the reply to command k-1 (host timing): its feedback is this
    # simulation's sample k; its recorded truth is the plant one period later
    n = min(len(run.t), len(coded) - 1)
    same_estimate = float(np.max(np.abs(run["tau_int_hat"][:n] - coded[:n, INT_HAT])))
    same_force = float(np.nanmax(np.abs(run["tau_int_true"][:n] - coded[1:n + 1, FORCE])))
    step_at = config.reference.start
    t_ms = (exact[:, T] - step_at) * 1e3
    window = (t_ms > -20) & (t_ms < 120)
    after = exact[:, T] > step_at + 0.3 * (config.loop.duration - step_at)
    offset = coded[after, FORCE] - exact[after, FORCE]
    diff, diff_v = coded[:, FORCE] - exact[:, FORCE], coded_v[:, FORCE] - exact_v[:, FORCE]
    noise = moving_observer_noise(config, model)
    gain, gain_v = config.design.force_gain, variant.design.force_gain
    force_v = figures_v.closed_loop["tau_int"] if figures_v.closed_loop else None

    plt = _plt()
    fig, axes = plt.subplots(2, 2, figsize=(13, 8.6))
    ax = axes[0, 0]
    ax.plot(t_ms[window], exact[window, REF], color="0.5", lw=0.9, ls=":", label="reference")
    ax.step(t_ms[window], exact[window, FORCE], where="post", color="k", lw=1.6,
            label=f"$C_f$ = {gain:g} (the demo), exact signals")
    ax.step(t_ms[window], coded[window, FORCE], where="post", color="tab:red", lw=1.0,
            label=f"$C_f$ = {gain:g}, {model.model} codec in the loop")
    run_ms = (np.arange(1, n + 1) * config.loop.period - step_at) * 1e3
    shown = (run_ms > -20) & (run_ms < 120)
    ax.plot(run_ms[shown][::2], run["tau_int_true"][:n][shown][::2], ls="none", marker="o", ms=2.5,
            mfc="none", color="tab:red", label=f"$C_f$ = {gain:g}, dobhil run --emulate --lockstep")
    ax.step(t_ms[window], exact_v[window, FORCE], where="post", color="0.45", lw=1.4,
            label=f"$C_f$ = {gain_v:g}, exact signals")
    ax.step(t_ms[window], coded_v[window, FORCE], where="post", color="tab:orange", lw=1.0,
            label=f"$C_f$ = {gain_v:g}, codec in the loop")
    ax.set_xlabel("time after the step [ms]")
    ax.set_ylabel(r"interaction torque $\tau_{int}$ [N m]")
    ax.set_title("a) force step response")
    ax.legend(loc="lower right", fontsize=8)
    ax.grid(True, alpha=0.3)

    ax = axes[0, 1]
    ax.step(t_ms[window], diff_v[window] * 1e3, where="post", color="tab:orange", lw=1.0,
            label=f"$C_f$ = {gain_v:g}: at most {np.max(np.abs(diff_v[window])) * 1e3:.3g} mN m")
    ax.step(t_ms[window], diff[window] * 1e3, where="post", color="tab:red", lw=1.2,
            label=f"$C_f$ = {gain:g}: at most {np.max(np.abs(diff[window])) * 1e3:.2g} mN m")
    if force_v is not None:
        ax.axhspan((force_v.bias - force_v.total) * 1e3, (force_v.bias + force_v.total) * 1e3,
                   color="tab:orange", alpha=0.12,
                   label=f"$C_f$ = {gain_v:g}: H2 prediction for a moving servo (RMS {force_v.total * 1e3:.3g} mN m)")
    ax.axhline(0.0, color="k", lw=0.6)
    ax.set_xlabel("time after the step [ms]")
    ax.set_ylabel("force, codec minus exact [mN m]")
    ax.set_title("b) what the codec changes in the force")
    ax.legend(loc="lower right", fontsize=8)
    ax.grid(True, alpha=0.3)

    ax = axes[1, 0]
    q_t = figures.steps["torque"]
    settled = exact[:, T] >= 0.5 * step_at      # the approach to contact left out
    t_all = (exact[settled, T] - step_at) * 1e3
    ax.plot(t_all, diff[settled] * 1e3, color="tab:red", lw=1.0,
            label=f"$C_f$ = {gain:g}: force, codec minus exact")
    for level, lo, hi in ((float(exact[0, REF]), t_all[0], 0.0),
                          (float(exact[-1, REF]), 0.0, t_all[-1])):
        ax.hlines(steady_error(model, level) * 1e3, lo, hi, color="k", lw=1.4, ls="--",
                  label="decoded minus commanded torque at the reference" if lo < 0 else None)
    ax.axhline(-q_t * 1e3, color="0.4", lw=0.8, ls=":", label=f"one torque step ({q_t * 1e3:.2f} mN m)")
    ax.axhline(0.0, color="k", lw=0.6)
    ax.set_ylim(-1.4 * q_t * 1e3, 0.6 * q_t * 1e3)
    ax.set_xlabel("time after the step [ms]")
    ax.set_ylabel("force error [mN m]")
    ax.set_title("c) the steady force: the truncated torque command")
    ax.legend(loc="upper right", fontsize=8)
    ax.grid(True, alpha=0.3)

    ax = axes[1, 1]
    rows = []
    for col, key, color, label, plain in (
            (DIS, "dob", "tab:green", r"DOb $\hat\tau_{dis}$", "DOb tau_dis^"),
            (INT, "rtob", "tab:blue", r"RTOb $\hat\tau_{int}$", "RTOb tau_int^")):
        predicted = math.sqrt(sum(figures.observers[key].rms[ch] ** 2 for ch in figures.measured))
        measured = float(np.std(noise[:, col]))
        rows.append((plain, measured, predicted))
        ax.hist(noise[:, col] * 1e3, bins=120, density=True, histtype="step", color=color,
                label=f"{label}: RMS {measured * 1e3:.3g} ({predicted * 1e3:.3g}) mN m")
        for sign in (-1, 1):
            ax.axvline(sign * predicted * 1e3, color=color, lw=0.8, ls="--")
    ax.set_xlabel("estimate error [mN m]")
    ax.set_ylabel("density")
    ax.set_title(f"d) estimate noise of a moving servo ({len(noise)} samples)")
    ax.set_ylim(0.0, ax.get_ylim()[1] * 1.3)
    ax.legend(loc="upper right", fontsize=8, title="measured (H2 prediction, dashed)",
              title_fontsize=8)
    ax.grid(True, alpha=0.3)
    fig.suptitle(f"{config_path.name} on a {model.vendor} {model.model}: the codec's quantisation "
                 f"in the force loop (T = {config.loop.period * 1e3:g} ms)", fontsize=11)
    fig.tight_layout()
    save(fig, out)

    print(f"steady force offset after the step: mean {offset.mean() * 1e3:.3f} mN m, "
          f"std {offset.std() * 1e3:.3g} mN m (decoded minus commanded at the reference "
          f"{exact[-1, REF]:g} N m: {steady_error(model, float(exact[-1, REF])) * 1e3:.3f} mN m)")
    for g, d in ((gain, diff), (gain_v, diff_v)):
        print(f"C_f = {g:g}: force, codec minus exact, in the step window: at most "
              f"{np.max(np.abs(d[window])) * 1e3:.3g} mN m, RMS {np.sqrt(np.mean(d[window] ** 2)) * 1e3:.3g} mN m")
    for g, f in ((gain, figures), (gain_v, figures_v)):
        if f.closed_loop is not None:
            print(f"C_f = {g:g}: H2 prediction (moving servo): force RMS {f.closed_loop['tau_int'].total * 1e3:.3g}"
                  f" mN m, command RMS {f.closed_loop['u'].total * 1e3:.3g} mN m")
    for label, measured, predicted in rows:
        print(f"{label} noise of a moving servo: measured RMS {measured * 1e3:.4g} mN m, "
              f"H2 prediction {predicted * 1e3:.4g} mN m")
    print(f"lockstep emulated run vs this simulation with the codec: tau_int^ max difference "
          f"{same_estimate:.3g} N m, true force {same_force:.3g} N m over {n} cycles")
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
