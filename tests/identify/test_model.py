"""The identification's model (dobhil.identify.model): the emulator's Plant, stepped the way
the lockstep emulator applies delayed commands, and its fast path equal to that reference."""

from __future__ import annotations

import math

import numpy as np
import pytest

from dobhil.identify.model import ModelValues, simulate_torque

PERIOD = 1e-3


@pytest.mark.parametrize("delay", [0.0, 0.4e-3, 2.0e-3])
def test_initial_velocity_free_decay_closed_form(delay: float) -> None:
    """No torque, launched at v0: v0 exp(-b t / J) and q0 + v0 J / b (1 - exp(-b t / J))
    (closed form, independent of the discretisation), whatever the delay."""
    j, b, q0, v0 = 0.05, 0.2, -0.4, 2.5
    n = 300
    pos, vel = simulate_torque(ModelValues(inertia=j, viscous_friction=b, delay=delay),
                               np.zeros(n), PERIOD, 0, n, q0, v0)
    t = np.arange(n) * PERIOD
    decay = np.exp(-b * t / j)
    np.testing.assert_allclose(vel, v0 * decay, rtol=1e-12)
    np.testing.assert_allclose(pos, q0 + v0 * j / b * (1 - decay), rtol=1e-12, atol=1e-14)


def test_initial_velocity_against_coulomb_friction_stops_at_the_closed_form_time() -> None:
    """Coulomb friction alone (b = 0) decelerates v0 at F_c / J: at rest by t = J v0 / F_c,
    after q0 + J v0^2 / (2 F_c), and stays there (no torque)."""
    j, fc, q0, v0 = 0.1, 0.5, 0.0, 1.0
    n = 400
    pos, vel = simulate_torque(ModelValues(inertia=j, coulomb_friction=fc), np.zeros(n),
                               PERIOD, 0, n, q0, v0)
    stop = j * v0 / fc                                # 0.2 s
    k = int(stop / PERIOD)
    np.testing.assert_allclose(vel[:k - 2], v0 - fc / j * np.arange(k - 2) * PERIOD, rtol=1e-9)
    assert np.all(vel[k + 2:] == 0.0)
    # the Karnopp band stops the servo within one sub-step of the exact time
    assert pos[-1] == pytest.approx(q0 + j * v0 ** 2 / (2 * fc), abs=v0 * PERIOD / 10)
    assert math.isfinite(pos[-1])
