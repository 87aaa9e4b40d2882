"""The force loop against the emulated ODrive: one suite over every emulator mode
(lockstep and real time x firmware 0.6 and 0.5), then lockstep against the analysis.

Real-time checks look at behaviour (the steady state the loop reaches), never at the
wall clock; lockstep checks compare number for number with the sampled analysis.
"""

from __future__ import annotations

from pathlib import Path

import control
import numpy as np
import pytest

from dobhil.analysis.transfer import LoopSystems
from dobhil.config import Config
from dobhil.runtime.loop import RunResult
from dobhil.runtime.session import RunSession
from dobhil.runtime.stop import StopReason
from dobhil.synthesis import params_from_config

from .helpers import (FIRMWARES, REALTIME_SLACK, STEP_FROM_ZERO, demo_config, finite_tail,
                      realtime_profile, write_profile)

#: odrive-0.6 reaches the reference in tests/drives/test_drive_suite.py (with CiA 402)
MODES = [(timing, fw) for timing in ("lockstep", "realtime") for fw in FIRMWARES
         if fw != "odrive-0.6"]


def run(config: Config, *, lockstep: bool) -> RunResult:
    with RunSession(config, emulate=True, lockstep=lockstep) as session:
        return session.run()


def mode_config(tmp_path: Path, timing: str, firmware: str, *overrides: str) -> Config:
    """demo.yaml (no Coulomb friction, no disturbance) on ``firmware``'s profile."""
    if timing == "lockstep":
        return demo_config(f"drive.profile={firmware}", *overrides)
    profile = realtime_profile(tmp_path, firmware)
    return demo_config(f"drive.profile={profile}", *REALTIME_SLACK, *overrides)


@pytest.mark.parametrize(("timing", "firmware"), MODES, ids=[f"{t}-{f}" for t, f in MODES])
def test_true_interaction_torque_reaches_reference(tmp_path: Path, timing: str,
                                                   firmware: str) -> None:
    """Without unmodelled friction the TRUE interaction torque settles on the reference
    (demo: contact from 5 mrad away at 0.2 N m, then a step to 1 N m at 0.6 s), in
    every emulator mode; the estimate agrees."""
    config = mode_config(tmp_path, timing, firmware, "loop.duration=1.0")
    assert config.plant.coulomb_friction == 0.0 and config.plant.disturbance == "none"
    result = run(config, lockstep=timing == "lockstep")
    assert result.stop.reason is StopReason.DONE, result.stop.line()
    assert result.disabled
    tr = result.trace
    tail_true = finite_tail(tr["tau_int_true"], tr["t"], 0.1)
    tail_hat = finite_tail(tr["tau_int_hat"], tr["t"], 0.1)
    # the last 100 ms, or the last 10 cycles that ran when the host was starved in them
    assert tail_true.size >= 10
    assert tr["tau_ref"][-1] == 1.0
    tol = 1e-3 if timing == "lockstep" else 0.03
    assert abs(float(np.mean(tail_true)) - 1.0) < tol
    assert abs(float(np.mean(tail_hat)) - 1.0) < tol


def step_run(*overrides: str) -> tuple[Config, np.ndarray, np.ndarray]:
    """Lockstep run of the analysed loop: contact from the start, unit step at t = 0."""
    config = demo_config(*STEP_FROM_ZERO, "loop.duration=0.3", *overrides)
    result = run(config, lockstep=True)
    assert result.stop.reason is StopReason.DONE, result.stop.line()
    return config, result.trace["t"], result.trace["tau_int_hat"]


def analysis_step(config: Config, t: np.ndarray, *, sampled: bool) -> np.ndarray:
    systems = LoopSystems.build(params_from_config(config), sampled=sampled)
    return np.squeeze(control.step_response(systems.system("closed_loop"), T=t).outputs)


@pytest.mark.parametrize("firmware", FIRMWARES)
@pytest.mark.parametrize("variant", [(), ("design.velocity_source=estimated",
                                          "design.delay_samples=0")],
                         ids=["measured-velocity", "estimated-velocity"])
def test_lockstep_is_the_sampled_analysis(firmware: str, variant: tuple[str, ...]) -> None:
    """Lockstep with no noise or quantisation is the sampled closed loop of the analysis:
    tau_int^ of the trace equals its step response sample for sample (float32 on the
    wire is the only difference)."""
    config, t, tau_hat = step_run(f"drive.profile={firmware}", *variant)
    assert config.sensor.encoder_resolution == 0 and config.sensor.velocity_noise == 0.0
    expected = analysis_step(config, t, sampled=True)
    assert t.size == 300 and expected.shape == tau_hat.shape
    error = np.max(np.abs(tau_hat - expected)) / np.max(np.abs(expected))
    assert error < 1e-4


@pytest.mark.parametrize("delay", [("design.input_delay=3e-4",),
                                   ("design.input_delay=7.5e-4",),
                                   ("design.delay_samples=1",),
                                   ("design.delay_samples=1", "design.input_delay=4e-4")],
                         ids=["0.3T", "0.75T", "1T", "1.4T"])
def test_lockstep_with_input_delay_is_the_delayed_analysis(delay: tuple[str, ...]) -> None:
    """Feedback-synchronous timing with the command acting ``design.input_delay`` after
    its sample (plus ``delay_samples`` whole periods): the lockstep emulator holds the
    previous torque for the delay, then the new one, each piece an exact ZOH step of the
    plant; the run is the analysis' sampled loop with that delay (modified z-transform /
    augmented state), sample for sample, to 1e-4 of the step."""
    config, t, tau_hat = step_run(*delay)
    expected = analysis_step(config, t, sampled=True)
    assert t.size == 300 and expected.shape == tau_hat.shape
    error = np.max(np.abs(tau_hat - expected)) / np.max(np.abs(expected))
    assert error < 1e-4
    undelayed = analysis_step(demo_config(*STEP_FROM_ZERO, "loop.duration=0.3"), t, sampled=True)
    assert np.max(np.abs(tau_hat - undelayed)) / np.max(np.abs(expected)) > 1e-2


def test_fast_sampling_approaches_the_continuous_loop(tmp_path: Path) -> None:
    """At 20 kHz (drive sending encoder estimates every 50 us) the run follows the
    continuous (paper) step response within 2 % of the step."""
    profile = write_profile(tmp_path, "odrive-0.6", feedback_period=5e-5)
    config, t, tau_hat = step_run("loop.period=5e-5", "loop.feedback_timeout=1e-3",
                                  f"drive.profile={profile}")
    continuous = analysis_step(config, t, sampled=False)
    assert np.max(np.abs(tau_hat - continuous)) < 0.02 * 1.0


def test_1khz_differs_from_the_continuous_loop() -> None:
    """At 1 kHz the run is far (> 2 % of the step) from the continuous response: that
    gap is what the sampled analysis is for."""
    config, t, tau_hat = step_run()
    continuous = analysis_step(config, t, sampled=False)
    assert np.max(np.abs(tau_hat - continuous)) > 0.02 * 1.0
