"""The unmodelled plant options reach a lockstep force run through the emulator."""

from __future__ import annotations

import numpy as np

from dobhil.runtime.loop import RunResult
from dobhil.runtime.session import RunSession
from dobhil.runtime.stop import StopReason

from .helpers import demo_config


def run(*overrides: str) -> RunResult:
    config = demo_config("loop.duration=1.0", *overrides)
    with RunSession(config, emulate=True, lockstep=True) as session:
        result = session.run()
    assert result.stop.reason is StopReason.DONE, result.stop.line()
    return result


def first_force(result: RunResult) -> float:
    tr = result.trace
    return float(tr["t"][np.flatnonzero(tr["tau_int_true"] != 0.0)[0]])


def test_backlash_delays_the_contact_and_shifts_the_pressed_motor() -> None:
    """demo: free motion 5 mrad to the environment, then pressing at 0.2 and 1 N m. With a
    2 mrad dead band the motor touches later and ends beta/2 further in, same force."""
    plain, geared = run(), run("plant.backlash=0.002")
    assert first_force(geared) > first_force(plain)
    for result in (plain, geared):
        assert abs(float(np.mean(result.trace["tau_int_true"][-100:])) - 1.0) < 1e-3
    shift = geared.trace["q"][-1] - plain.trace["q"][-1]
    assert abs(shift - 0.001) < 2e-6


def test_stribeck_friction_holds_the_servo_short_of_the_reference() -> None:
    """Static friction F_s = 0.5 N m: the force loop's last torque cannot break the servo
    free, so the true force stays off the 1 N m reference by at most F_s."""
    result = run("plant.coulomb_friction=0.2", "plant.stribeck_friction=0.3")
    tail = result.trace["tau_int_true"][-100:]
    assert float(np.ptp(tail)) == 0.0                  # stuck
    assert 0.01 < abs(float(tail[-1]) - 1.0) <= 0.5
