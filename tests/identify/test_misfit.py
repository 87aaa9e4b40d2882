"""What identify says when the model is wrong.

Logs of emulated plants the fitted model cannot represent -- Stribeck friction, gear
backlash (dobhil.emulator.plant options, unmodelled by the analysis) -- must come out
with a visible misfit (the residual's statistics, a warning line), while the same
experiment on a plant the model does represent (Coulomb friction only, no backlash)
fits cleanly: the control that lets these tests fail.

The records are made here from the emulator's Plant directly (torque held over each
period, no delay, quantised encoder, noisy velocity), independent of how the fit
simulates it, and fitted through ``identify(IdentData, segments)
-> IdentResult`` with ``residual.misfit`` / ``.warning`` / ``.rms`` / ``.whiteness_p``.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest

from dobhil.emulator.plant import Plant


PERIOD = 1e-3
COUNTS = 2 ** 14
TRUTH = dict(inertia=0.25, viscous_friction=0.5, coulomb_friction=0.3, stiffness=1.0e4,
             damping=50.0, contact_position=0.0)


def multisine(n: int, amplitude: float, band: tuple[float, float], lines: int,
              seed: int) -> np.ndarray:
    """Random-phase multisine with log-spaced lines in ``band`` [Hz], peak ``amplitude``."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) * PERIOD
    f = np.geomspace(*band, lines)
    x = np.sum(np.sin(2 * np.pi * f[:, None] * t + rng.uniform(0, 2 * np.pi, lines)[:, None]),
               axis=0)
    return amplitude * x / np.max(np.abs(x))


def record(torque: np.ndarray, kind: str, initial_position: float, **unmodelled: float) -> Any:
    """``(IdentData, segments)`` of one run of the emulated plant (one segment of ``kind``)."""
    from dobhil.identify.data import IdentData, Segment
    plant = Plant(**TRUTH, initial_position=initial_position, encoder_resolution=COUNTS,
                  velocity_noise=0.01, seed=3, **unmodelled)
    n = len(torque)
    position, velocity = np.empty(n), np.empty(n)
    for k in range(n):
        position[k], velocity[k] = plant.position, plant.velocity   # sampled at t_k ...
        plant.step(float(torque[k]), PERIOD)                        # ... then u_k held
    data = IdentData(period=PERIOD, t=np.arange(n) * PERIOD, torque=np.asarray(torque, float),
                     position=position, velocity=velocity, source="", protocol="odrive",
                     recorded={})
    return data, (Segment(start=0, stop=n, kind=kind),)


def fitted(torque: np.ndarray, kind: str, initial_position: float, **unmodelled: float) -> Any:
    from dobhil.identify.fit import identify
    return identify(*record(torque, kind, initial_position, **unmodelled))


def assert_misfit_is_visible(clean: Any, wrong: Any) -> None:
    """The control fits (white residual, no warning); the unmodelled plant does not, and
    says so: the misfit flag, a warning line naming it, a residual both larger and less
    white than the control's."""
    assert not clean.residual.misfit, clean.residual.warning
    assert clean.residual.warning == ""
    assert wrong.residual.misfit
    warning = wrong.residual.warning
    assert "misfit" in warning.lower() and "\n" not in warning.strip()
    assert wrong.residual.rms > 1.5 * clean.residual.rms
    assert wrong.residual.whiteness_p < clean.residual.whiteness_p
    assert math.isfinite(wrong.residual.rms)


def test_stribeck_friction_gives_a_visible_misfit() -> None:
    """Free motion (far from the environment), a multisine that reverses the velocity
    often: the Stribeck peak at low speed is what a Coulomb + viscous model cannot bend
    to. Measured when written: the control p = 0.15 and no misfit; Stribeck (F_St = 2 F_c,
    v_St = 0.05 rad/s) p = 0, RMS 3x."""
    torque = np.concatenate([multisine(2000, 3.0, (0.3, 30.0), 40, seed=1), np.zeros(20)])
    clean = fitted(torque, "free", -50.0)
    wrong = fitted(torque, "free", -50.0, stribeck_friction=0.6, stribeck_velocity=0.05)
    assert_misfit_is_visible(clean, wrong)


@pytest.mark.xfail(   # run, and strict: the day it discriminates, XPASS fails the suite
    raises=AssertionError, strict=True,
    reason="not discriminating yet: the linear contact model fits this backlash record within its "
           "noise (measured: RMS 0.0099 for noise 0.01, whiteness p 0.16, no misfit; K 11400 and "
           "D 47 for 1e4 and 50, the contact 0.46 mrad further in, a fitted delay of 0.45 ms: "
           "the gap's opening is absorbed by wrong numbers, not shown as a misfit). The CLI-level "
           "leave/re-enter record does discriminate: tests/identify/test_workflow.py::"
           "test_backlash_shows_as_a_misfit_when_the_contact_opens")
def test_backlash_gives_a_visible_misfit() -> None:
    """Pressed on the environment with a torque that swings hard enough for the damper to
    want to pull: through the backlash nothing pulls (the gap opens and the load relaxes
    on its own), which the linear contact model cannot follow. (A record that only ever
    pushes is explained exactly by a contact position beta/2 further in: no misfit, and
    rightly so -- that is the motor's real contact position.)"""
    torque = np.concatenate([1.5 + multisine(1500, 2.5, (3.0, 40.0), 30, seed=2), np.zeros(20)])
    clean = fitted(torque, "contact", 0.0)
    wrong = fitted(torque, "contact", 0.0, backlash=0.001)
    assert_misfit_is_visible(clean, wrong)


def test_no_confident_wrong_numbers_from_a_contact_only_record() -> None:
    """The plant the model represents exactly, pressed from the start (a contact segment
    only): every value identify reports as identifiable has its 95 % interval around the
    truth, unless identify warns of a misfit. (In contact b and D_env act as their sum:
    reported both, they come out as confident wrong values -- viscous friction 822
    [262, 1106] for 0.5, contact 1.34 mrad for 0 -- so neither may be reported. This
    record barely moves -- 0.002 rad/s RMS under 0.01 of noise -- so little else is.)"""
    from dobhil.identify.data import IdentData, Segment
    from dobhil.identify.fit import identify
    truth = dict(TRUTH, damping=300.0)
    torque = np.concatenate([1.5 + multisine(1500, 2.5, (3.0, 40.0), 30, seed=2), np.zeros(20)])
    plant = Plant(**truth, initial_position=0.0, encoder_resolution=COUNTS, velocity_noise=0.01,
                  seed=3)
    n = len(torque)
    position, velocity = np.empty(n), np.empty(n)
    for k in range(n):
        position[k], velocity[k] = plant.position, plant.velocity
        plant.step(float(torque[k]), PERIOD)
    data = IdentData(period=PERIOD, t=np.arange(n) * PERIOD, torque=torque, position=position,
                     velocity=velocity, source="", protocol="odrive", recorded={})
    result = identify(data, (Segment(start=0, stop=n, kind="contact"),))
    if result.residual.misfit:
        return
    # neither is reported; why each is not depends on where in the flat valley the fit ends
    # (newest numpy/scipy/lmfit: correlation -0.92 with the other, named; at the floors of
    # pyproject.toml: only the flat profile), so the line is not asserted
    for name in ("viscous_friction", "damping"):
        assert not result.estimates[name].identifiable, result.estimates[name]
    truth_of = {**truth, "delay": 0.0, "torque_gain": 1.0}
    wrong = {name: (e.value, e.low, e.high) for name, e in result.estimates.items()
             if e.identifiable and not e.low <= truth_of[name] <= e.high}
    assert wrong == {}
