"""The shipped two-axis demo (``configs/two-axis-demo.yaml``): run in lockstep, both axes
converge on their references, and every cycle is what the coupled analysis predicts.

The prediction is the sampled coupled closed loop of :mod:`dobhil.analysis.coupled` (the
same controller matrices, the coupled plant sampled exactly) driven by the run's own
recorded references from rest. The emulator steps coupled plants one after the other with
the partner's state held over each piece (:mod:`dobhil.emulator.coupling`, second order in
the step), so the run departs from the exact loop by at most about ``(omega T)^2`` of the
force steps, ``omega = sqrt(K (1/J_a + 1/J_b))`` the coupling's own frequency; without a
coupling the emulator is the analysed plant exactly and the two agree to 1e-6 N m.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import yaml

from dobhil.analysis.coupled import axis_designs, coupled_loop
from dobhil.config.axes import Axes, Coupling, load_axes
from dobhil.drives.profile import DriveProfile
from dobhil.runtime.axes_loop import AxesResult
from dobhil.runtime.axes_session import AxesSession
from dobhil.runtime.stop import StopReason

CONFIGS = Path(__file__).resolve().parents[2] / "configs"
DEMO = CONFIGS / "two-axis-demo.yaml"


def _run(axes: Axes) -> tuple[AxesResult, dict[str, DriveProfile]]:
    with AxesSession(axes, emulate=True, lockstep=True, config_dir=CONFIGS) as session:
        result = session.run()
        profiles = dict(session.profiles)
    assert result.stop.reason is StopReason.DONE, result.stop.line()
    return result, profiles


def _errors(axes: Axes, result: AxesResult, profiles: dict[str, DriveProfile],
            couplings: tuple[Coupling, ...]) -> dict[str, float]:
    """Per axis and signal, the largest difference between the run and the sampled coupled
    loop (with ``couplings``) driven from rest by the run's own references."""
    loop = coupled_loop(axis_designs(axes, profiles), couplings, sampled=True)
    n = result.cycles
    w = np.zeros((loop.b.shape[1], n))
    for name in axes.names:
        w[loop.input_index(name, "tau_ref")] = result.axes[name].trace["tau_ref"][:n]
    x = np.zeros(loop.order)
    y = np.empty((n, loop.c.shape[0]))
    with np.errstate(all="ignore"):   # a wrong loop may blow up: its error is then inf
        for k in range(n):
            y[k] = loop.c @ x + loop.d @ w[:, k]
            x = loop.a @ x + loop.b @ w[:, k]
    errors = {}
    for name in axes.names:
        trace = result.axes[name].trace
        for signal, field in (("tau_int_hat", "tau_int_hat"), ("tau_int", "tau_int_true")):
            diff = np.abs(trace[field][:n] - y[:, loop.output_index(name, signal)])
            errors[f"{name}.{signal}"] = float(np.max(np.where(np.isfinite(diff), diff, np.inf)))
    return errors


def _bound(axes: Axes, result: AxesResult, name: str) -> float:
    """``(omega T)^2`` times every force step the axis took (see the module docstring)."""
    (c,) = axes.couplings
    inertia = {a.name: a.config.plant.inertia for a in axes.axes}
    omega_t = math.sqrt(c.stiffness * (1 / inertia[c.a] + 1 / inertia[c.b])) * axes.period
    ref = result.axes[name].trace["tau_ref"][:result.cycles]
    return omega_t ** 2 * float(np.sum(np.abs(np.diff(ref, prepend=0.0))))


def test_the_coupled_demo_converges_and_runs_as_the_coupled_analysis_predicts() -> None:
    axes = load_axes(DEMO)
    assert axes.couplings, "the demo couples its axes"
    result, profiles = _run(axes)
    errors = _errors(axes, result, profiles, axes.couplings)
    for name in axes.names:
        trace = result.axes[name].trace
        ref = trace["tau_ref"][:result.cycles]
        tail = slice(int(0.9 * result.cycles), result.cycles)
        # converged: the last tenth of the run on the reference, estimate and truth
        for field in ("tau_int_true", "tau_int_hat"):
            assert np.max(np.abs(trace[field][tail] - ref[tail])) < 1e-3 * abs(ref[-1]), (name, field)
        for signal in ("tau_int_hat", "tau_int"):
            error = errors[f"{name}.{signal}"]
            assert error <= _bound(axes, result, name), (name, signal, error)


def test_without_the_coupling_the_emulator_is_the_analysed_loop(tmp_path: Path) -> None:
    """The alignment check of the test above: the same demo with the coupling removed and the
    left axis given the wall too agrees with the analysis to 1e-6 N m (the plants are then the
    analysis' exactly; measured 1.9e-8 N m, the emulator's step pieces are rounded to 1e-12 s),
    five orders below the coupled test's bound: that bound measures the coupling scheme alone."""
    data = yaml.safe_load(DEMO.read_text())
    del data["environment"]["coupling"]
    data["environment"].update(stiffness=10000.0, damping=50.0)
    path = tmp_path / "uncoupled.yaml"
    path.write_text(yaml.safe_dump(data))
    axes = load_axes(path)
    assert not axes.couplings
    result, profiles = _run(axes)
    for what, error in _errors(axes, result, profiles, ()).items():
        assert error < 1e-6, (what, error)


def test_the_comparison_sees_a_coupling_of_the_wrong_sign() -> None:
    """The comparison can fail: against the loop with the coupling's sign flipped (a pull where
    the spring pushes) the run is far outside the coupled test's bound."""
    axes = load_axes(DEMO)
    result, profiles = _run(axes)
    (c,) = axes.couplings
    flipped = (Coupling(c.a, c.b, -c.stiffness, -c.damping),)
    errors = _errors(axes, result, profiles, flipped)
    assert all(errors[f"{n}.tau_int"] > 10 * _bound(axes, result, n) for n in axes.names), errors
