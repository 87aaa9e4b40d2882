"""The quantisation noise figures (dobhil.analysis.quantisation) against closed forms and
against simulations fed with quantised signals.

The Monte-Carlo bounds come from the runs themselves: the sample variance of N samples
of a linear process ``y = h * e`` (``e`` white) has ``Var(s^2) <= (2 / N) sum_k gamma(k)^2``
(equality for Gaussian ``e``; uniform noise has a negative fourth cumulant, which only
lowers it), with ``gamma`` the autocovariance computed from the impulse responses; the
sample mean has the variance ``sum_k gamma(k) / N``. Each figure must lie within five of
those standard deviations.
"""

from __future__ import annotations

import functools
import math
from collections import deque
from dataclasses import dataclass

import numpy as np
import pytest

from dobhil.analysis.quantisation import (codec_figures, dc_gain, h2_norm, loop_systems,
                                          noise_figures, observer_systems, quantisation_text)
from dobhil.config import load_config
from dobhil.config.schema import Config, DesignConfig
from dobhil.drives.mit.codec import TorqueFrame, float_to_uint, uint_to_float, unpack_command
from dobhil.drives.mit.models import find_model
from dobhil.drives.mit.plugin import model_quantisation
from dobhil.runtime.controller import ForceController
from dobhil.synthesis.controller import DIS, INT, sampled_controller
from dobhil.synthesis.loop import loop, sampled_plant
from dobhil.synthesis.params import params_from_config

#: AK80-9 ranges (drivers/mit-models.yaml): position, velocity, torque (x_max) and bits
AK80_9 = {"position": (12.5, 16), "velocity": (50.0, 12), "torque": (18.0, 12)}
SIGMAS = 5.0
BIG = 1e12


@dataclass(frozen=True)
class Steps:
    position: float
    velocity: float
    torque: float


def _steps(ranges: dict[str, tuple[float, int]]) -> Steps:
    return Steps(**{k: 2 * x / ((1 << bits) - 1) for k, (x, bits) in ranges.items()})


STEPS = _steps(AK80_9)


def _quantise(values: np.ndarray, channel: str) -> np.ndarray:
    """What the codec decodes for each value (the firmware's formula, by the codec)."""
    x, bits = AK80_9[channel]
    return np.array([uint_to_float(float_to_uint(float(v), -x, x, bits), -x, x, bits)
                     for v in values])


def _impulse(a: np.ndarray, b: np.ndarray, c: np.ndarray, d: np.ndarray, n: int) -> np.ndarray:
    h = np.empty(n)
    h[0] = float(d.reshape(-1)[0])
    x = b[:, 0].copy()
    for k in range(1, n):
        h[k] = float(c[0] @ x)
        x = a @ x
    return h


def _bounds(responses: list[tuple[np.ndarray, float]], n: int) -> tuple[float, float]:
    """(std of the sample variance, std of the sample mean) for ``n`` samples of the sum of
    independent white inputs of standard deviations ``s`` through impulse responses ``h``.
    The mean's includes the window's two edges (an input near an edge reaches the window
    through part of ``h`` only: what is left when the DC gain is zero)."""
    length = max(len(h) for h, _ in responses)
    gamma = np.zeros(length)
    mean_var = 0.0
    for h, s in responses:
        full = np.correlate(h, h, mode="full")[len(h) - 1:]
        gamma[:len(full)] += s * s * full
        partial = np.cumsum(h)
        mean_var += s * s * (n * partial[-1] ** 2 + np.sum((partial[-1] - partial) ** 2)
                             + np.sum(partial ** 2)) / (n * n)
    sum_sq = gamma[0] ** 2 + 2.0 * np.sum(gamma[1:] ** 2)
    return math.sqrt(2.0 * sum_sq / n), math.sqrt(mean_var)


def test_h2_norm_of_a_first_order_system_is_its_closed_form() -> None:
    a, b, c, d = 0.8, 0.3, 2.0, 0.5
    expected = math.sqrt(d * d + (c * b) ** 2 / (1 - a * a))
    got = h2_norm(np.array([[a]]), np.array([[b]]), np.array([[c]]), np.array([[d]]))
    assert got == pytest.approx(expected, rel=1e-12)
    assert dc_gain(np.array([[a]]), np.array([[b]]), np.array([[c]]), np.array([[d]])) == \
        pytest.approx(d + c * b / (1 - a), rel=1e-12)
    assert h2_norm(np.array([[1.0]]), np.array([[b]]), np.array([[c]]), np.array([[d]])) is None


def test_the_conventional_dob_has_the_closed_form_noise_gain() -> None:
    """Constant model, measured velocity, no friction, step-invariant sampling: the DOb is
    ``sigma[k+1] = p sigma + (1 - p)(g J dq + u)``, ``tau^ = sigma - g J dq`` (p = e^-gT),
    so from dq: h = -gJ, gJ(1-p), gJ(1-p)p, ... -> H2 = g J sqrt(2 / (1 + p)); from u:
    H2 = sqrt((1 - p) / (1 + p))."""
    g, j, jmi, t = 400.0, 0.25, 0.1, 1e-3
    config = Config(design=DesignConfig(discretization="zoh", dob_bandwidth=g, rtob_bandwidth=g,
                                        nominal_inertia=j, identified_inertia=jmi))
    ctrl = sampled_controller(params_from_config(config))
    p = math.exp(-g * t)
    for row, inertia in ((DIS, j), (INT, jmi)):
        systems = observer_systems(ctrl, row)
        assert h2_norm(*systems["velocity"]) == pytest.approx(g * inertia * math.sqrt(2 / (1 + p)),
                                                              rel=1e-9)
        assert h2_norm(*systems["torque"]) == pytest.approx(math.sqrt((1 - p) / (1 + p)), rel=1e-9)
        assert h2_norm(*systems["position"]) == 0.0   # not read with a measured velocity
    figures = noise_figures(params_from_config(config), STEPS)
    assert figures.measured == ("velocity",)
    dob = figures.observers["dob"]
    assert dob.rms["velocity"] == pytest.approx(STEPS.velocity / math.sqrt(12) * g * j
                                                * math.sqrt(2 / (1 + p)), rel=1e-9)
    # the truncation's mean -step/2 of the applied torque: the DOb sees +step/2 of disturbance
    assert dob.bias == pytest.approx(STEPS.torque / 2, rel=1e-9)


def test_ak80_9_steps_and_zero_torque_bias() -> None:
    assert STEPS.position == pytest.approx(25 / 65535)
    assert STEPS.velocity * 1e3 == pytest.approx(24.42, abs=0.01)   # the 24 mrad/s
    assert STEPS.torque * 1e3 == pytest.approx(8.79, abs=0.01)      # and 9 mN m
    zero = _quantise(np.array([0.0]), "torque")[0]
    assert zero == pytest.approx(-0.0044, abs=5e-5)
    # half a step below zero, up to the firmware's single precision (dobhil.drives.mit.codec)
    assert zero == pytest.approx(-STEPS.torque / 2, abs=1e-6)
    model = find_model("cubemars", "AK80-9", "manual-1.0.8")
    assert model.quanta.position == pytest.approx(STEPS.position, rel=1e-12)
    assert model.quanta.velocity == pytest.approx(STEPS.velocity, rel=1e-12)
    assert model.quanta.torque == pytest.approx(STEPS.torque, rel=1e-12)
    assert model.torque_bias == zero


@functools.cache
def _moving_servo(n: int, period: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``n`` samples of a servo's position and velocity, seeded, moving across many steps per
    sample (the regime the white-noise model describes), and what the codec decodes of each
    (:func:`_quantise`). Made once per test process: the codec's 240000 scalar calls were
    most of each observer-noise case's time, and both velocity sources read the same
    signals (read-only, so no case can change them for the other)."""
    rng = np.random.default_rng(18)
    t = np.arange(n) * period
    ph = rng.uniform(0, 2 * np.pi, 4)
    q = 10.0 * np.sin(2 * np.pi * 1.37 * t + ph[0]) + 0.5 * np.sin(2 * np.pi * 17.3 * t + ph[1])
    dq = 40.0 * np.sin(2 * np.pi * 3.1 * t + ph[2]) + 3.0 * np.sin(2 * np.pi * 47.7 * t + ph[3])
    signals = (q, dq, _quantise(q, "position"), _quantise(dq, "velocity"))
    for signal in signals:
        signal.setflags(write=False)
    return signals


@pytest.mark.parametrize("velocity_source", ["measured", "estimated"])
def test_observer_noise_matches_a_simulation_fed_with_quantised_signals(velocity_source: str) -> None:
    """The sampled observer run on the codec's decoded position and velocity of a moving
    servo, minus the same observer run on the exact signals (linear: the response to the
    quantisation error alone), has the predicted RMS and mean."""
    config = load_config("configs/cia402-demo.yaml", [f"design.velocity_source={velocity_source}"])
    ctrl = sampled_controller(params_from_config(config))
    figures = noise_figures(params_from_config(config), STEPS)
    n, warm = 60_000, 500
    q, dq, q_quant, dq_quant = _moving_servo(n, config.loop.period)
    y_true = np.stack([q, dq], axis=1)[:, :ctrl.b_y.shape[1]]
    y_quant = np.stack([q_quant, dq_quant], axis=1)[:, :ctrl.b_y.shape[1]]
    err = y_quant - y_true
    # the firmware truncates (up to its single precision's rounding of the decoded value)
    assert np.all(err <= 4 * np.finfo(np.float32).eps * np.array([12.5, 50.0])[:err.shape[1]])
    # the observers, no torque: xi[k+1] = A xi[k] + B_y e[k], out[k] = C xi[k] + D_y e[k]; the
    # state stepped alone, input and output terms as whole-array products (the same sums)
    drive = err @ ctrl.b_y.T
    states = np.empty((n, ctrl.order))
    xi = np.zeros(ctrl.order)
    for k in range(n):
        states[k] = xi
        xi = ctrl.a @ xi + drive[k]
    out = (states @ ctrl.c.T + err @ ctrl.d_y.T)[warm:]
    for key, row in (("dob", DIS), ("rtob", INT)):
        f = figures.observers[key]
        read = list(figures.measured)
        predicted = math.sqrt(sum(f.rms[ch] ** 2 for ch in read))
        systems = observer_systems(ctrl, row)
        responses = [(_impulse(*systems[ch], 400), getattr(STEPS, ch) / math.sqrt(12)) for ch in read]
        var_sd, mean_sd = _bounds(responses, n - warm)
        assert predicted > 0.0
        assert abs(np.var(out[:, row]) - predicted ** 2) <= SIGMAS * var_sd, key
        bias = sum(-0.5 * getattr(STEPS, ch) * dc_gain(*systems[ch]) for ch in read)
        assert abs(np.mean(out[:, row]) - bias) <= SIGMAS * mean_sd, key
        assert SIGMAS * var_sd < 0.1 * predicted ** 2          # the check can tell a 10 % error


#: designs whose command noise does not cancel (the cia402 demo has J_mn = C_f J_mi, so
#: its command carries no velocity noise at all)
LOOPS = {
    "measured": ["design.force_gain=1.5"],
    "estimated": ["design.velocity_source=estimated", "design.velocity_filter_bandwidth=1000",
                  "design.force_gain=1.5"],
}


@pytest.mark.parametrize("name", list(LOOPS))
def test_closed_loop_noise_matches_the_runtime_controller_on_the_sampled_plant(name: str) -> None:
    """The runtime's controller (its generated kernel) closed around the sampled plant
    with the command delay, each measurement and the applied torque offset by an
    independent uniform error on (-step, 0] (seeded): the RMS and mean of the estimates,
    of the true force and of the command are the predicted ones. This is independent of
    the loop's assembly and of the torque column the figures build."""
    config = load_config("configs/cia402-demo.yaml", LOOPS[name] + [f"loop.torque_limit={BIG}"])
    params = params_from_config(config)
    figures = noise_figures(params, STEPS)
    assert figures.closed_loop is not None
    ctrl = ForceController.from_config(config)
    phi, gamma0, gamma1 = sampled_plant(params)
    assert not np.any(gamma1)                                  # input_delay 0 in this config
    n, warm = 40_000, 1000
    rng = np.random.default_rng(7)
    e = {ch: -rng.uniform(0.0, getattr(STEPS, ch), n) for ch in ("position", "velocity", "torque")}
    in_transit = deque([0.0] * params.structure.delay_samples)
    x = np.zeros(2)
    k_env, d_env = config.environment.stiffness, config.environment.damping
    rows = np.empty((n, 4))
    for k in range(n):
        q, dq = x[0] + e["position"][k], x[1] + e["velocity"][k]
        out = ctrl.step(q, dq if ctrl.measures_velocity else None, 0.0)
        rows[k] = (out.tau_int_hat, out.tau_dis_hat, k_env * x[0] + d_env * x[1], out.u)
        in_transit.append(out.u + e["torque"][k])              # the applied torque
        x = phi @ x + gamma0[:, 0] * in_transit.popleft()
    rows = rows[warm:]
    closed = loop(params, sampled=True)
    sampled = sampled_controller(params)
    checked = 0
    for col, output in enumerate(("tau_int_hat", "tau_dis_hat", "tau_int", "u")):
        f = figures.closed_loop[output]
        systems = loop_systems(closed, sampled, output)
        responses = [(_impulse(*systems[ch], 3000), getattr(STEPS, ch) / math.sqrt(12))
                     for ch in systems]
        var_sd, mean_sd = _bounds(responses, n - warm)
        assert abs(np.var(rows[:, col]) - f.total ** 2) <= SIGMAS * var_sd + 1e-18, output
        assert abs(np.mean(rows[:, col]) - f.bias) <= SIGMAS * mean_sd + 1e-9, output
        if f.total > 1e-6:
            assert SIGMAS * var_sd < 0.2 * f.total ** 2
            checked += 1
    assert checked >= 3


def test_the_torque_column_equals_the_disturbance_input_without_fractional_delay() -> None:
    """With ``input_delay`` 0 the applied-torque error is the unknown disturbance torque
    (sign flipped) delayed by the command's whole periods: same H2 norm, opposite DC."""
    params = params_from_config(load_config("configs/cia402-demo.yaml"))
    closed = loop(params, sampled=True)
    systems = loop_systems(closed, sampled_controller(params), "tau_int")
    a, b, c, d = closed.siso("tau_du", "tau_int")
    assert h2_norm(*systems["torque"]) == pytest.approx(h2_norm(a, b, c, d), rel=1e-9)
    assert dc_gain(*systems["torque"]) == pytest.approx(-dc_gain(a, b, c, d), rel=1e-9)


def test_text_names_every_figure() -> None:
    figures = noise_figures(params_from_config(load_config("configs/cia402-demo.yaml")), STEPS)
    text = quantisation_text(figures)
    assert "steps position 0.3815 mrad, velocity 24.42 mrad/s, torque 8.791 mN m" in text
    assert "force tau_int: RMS" in text and "truncation offset -4.4 mN m" in text
    data = figures.as_dict()
    assert data["closed_loop"]["tau_int"]["bias"] == pytest.approx(-STEPS.torque / 2, rel=1e-6)
    assert set(data["observers"]) == {"dob", "rtob"}


def test_analyze_reports_the_quantisation_of_an_mit_profile_only(
        capsys: pytest.CaptureFixture[str]) -> None:
    """``dobhil analyze`` on the AK80-9 demo: the text's last lines and the --json key
    ``quantisation`` carry the figures (the codec's steps, its zero-torque bias, the noise
    of the design as the drive's command delay makes it); on a CiA 402 profile the output
    is what it was (no key, the bus budget line last)."""
    import json

    from dobhil.cli.main import main
    from dobhil.drives.mit.codec import Command
    from dobhil.drives.mit.rules import model_of
    from dobhil.drives.load import load_profile
    from dobhil.drives.timing import effective_config
    demo, mit_demo = "configs/cia402-demo.yaml", "configs/mit-demo.yaml"
    assert main(["analyze", mit_demo, "--json"]) == 0
    data = json.loads(capsys.readouterr().out)
    quant = data["quantisation"]
    model = model_of(load_profile("ak80-9"))
    assert quant["model"] == {"vendor": "cubemars", "model": "AK80-9", "firmware": model.firmware}
    assert quant["steps"] == {"position": pytest.approx(25 / 65535), "velocity": pytest.approx(100 / 4095),
                              "torque": pytest.approx(36 / 4095)}
    assert quant["zero_torque_bias"] == pytest.approx(-0.0044, abs=5e-5)
    torque_frame = TorqueFrame(model)
    frame = bytearray(torque_frame.template)
    torque_frame.fill(frame, 0.0)
    assert quant["zero_torque_bias"] == unpack_command(model, bytes(frame)).torque
    assert isinstance(unpack_command(model, bytes(frame)), Command)
    config, _ = effective_config(load_config(mit_demo), load_profile("ak80-9"))
    expected = noise_figures(params_from_config(config), model.quanta).as_dict()
    # the same computation on the design as the drive's command delay makes it, bit for bit
    assert quant["closed_loop"] == json.loads(json.dumps(expected["closed_loop"]))
    assert quant["observers"] == json.loads(json.dumps(expected["observers"]))
    assert config.design.delay_samples == 1
    assert main(["analyze", mit_demo]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[-8].startswith("quantisation (cubemars AK80-9 firmware ")
    assert lines[-9].startswith("bus budget: ")
    assert lines[-1].startswith("  closed loop at C_f = 2, command u: RMS")
    assert main(["analyze", demo, "--json"]) == 0
    assert "quantisation" not in json.loads(capsys.readouterr().out)
    assert main(["analyze", demo]) == 0
    assert capsys.readouterr().out.splitlines()[-1].startswith("bus budget: ")


def test_a_reversed_axis_truncates_the_other_way() -> None:
    """AK10-9 firmware 1.1 has axis_direction -1: the host's value is the negated decode of
    the negated value, so a zero command applies +step/2 and every offset changes sign;
    the noise is the same."""
    params = params_from_config(load_config("configs/cia402-demo.yaml"))
    reversed_ = find_model("cubemars", "AK10-9", "1.1")
    forward = find_model("cubemars", "AK10-9", "manual-1.0.8")
    assert reversed_.axis_direction == -1 and forward.axis_direction == 1
    back, ahead = (codec_figures(params, model_quantisation(m)) for m in (reversed_, forward))
    assert back.zero_torque_bias == pytest.approx(reversed_.quanta.torque / 2, abs=1e-5)
    assert back.zero_torque_bias == -ahead.zero_torque_bias == reversed_.torque_bias
    assert back.closed_loop is not None and ahead.closed_loop is not None
    assert back.closed_loop["tau_int"].bias == pytest.approx(-ahead.closed_loop["tau_int"].bias)
    assert back.closed_loop["tau_int"].bias == pytest.approx(reversed_.quanta.torque / 2, rel=1e-6)
    assert back.closed_loop["tau_int"].total == pytest.approx(ahead.closed_loop["tau_int"].total)
    # the decoded torque of a command on the reversed axis lies at or above it
    frame = TorqueFrame(reversed_)
    data = bytearray(frame.template)
    for tau in np.linspace(-3.0, 3.0, 101):
        frame.fill(data, float(tau))
        assert -1e-6 <= unpack_command(reversed_, bytes(data)).torque - tau < reversed_.quanta.torque


@pytest.mark.parametrize("name", list(LOOPS))
def test_h2_norms_are_the_impulse_responses_energy(name: str) -> None:
    """Parseval in the time domain: the Gramian's norm equals the sum of the squared
    impulse response (run until it has died out) for every channel and output."""
    params = params_from_config(load_config("configs/cia402-demo.yaml", LOOPS[name]))
    closed, ctrl = loop(params, sampled=True), sampled_controller(params)
    for output in ("tau_int_hat", "tau_dis_hat", "tau_int", "u"):
        for channel, system in loop_systems(closed, ctrl, output).items():
            h = _impulse(*system, 6000)
            norm = h2_norm(*system)
            assert norm is not None
            assert abs(h[-200:]).max() <= 1e-12 * max(abs(h).max(), 1e-300)
            assert norm ** 2 == pytest.approx(float(np.sum(h * h)), rel=1e-7, abs=1e-20), (output, channel)


def test_the_figures_simulation_is_the_lockstep_emulated_run() -> None:
    """tools/fig_mit_quantisation.py simulates the loop with the codec (the emulator's plant,
    the runtime's controller, pack_reply/unpack_reply, TorqueFrame/unpack_command, the
    command delay) and says it is what ``dobhil run --emulate --lockstep`` does: the
    estimates bit for bit, the true force one period on (the run records the plant when
    the command is applied); without the codec it differs."""
    import importlib.util
    from pathlib import Path
    path = Path(__file__).resolve().parents[1] / "tools" / "fig_mit_quantisation.py"
    spec = importlib.util.spec_from_file_location("fig_mit_quantisation", path)
    assert spec is not None and spec.loader is not None
    tool = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(tool)
    config_path = Path("configs/mit-demo.yaml")
    config, model = tool.design_on(config_path, [])
    run = tool.emulated_run(config_path)
    coded, exact = tool.closed_loop(config, model), tool.closed_loop(config, None)
    n = min(len(run.t), len(coded) - 1)
    assert n == round(config.loop.duration / config.loop.period) - 1
    assert np.array_equal(run["tau_int_hat"][:n], coded[:n, tool.INT_HAT])
    assert np.array_equal(run["tau_int_true"][:n], coded[1:n + 1, tool.FORCE])
    assert np.max(np.abs(run["tau_int_hat"][:n] - exact[:n, tool.INT_HAT])) > 1e-3
    # at rest after the step the force sits where the truncated command puts it
    rest = run["tau_int_true"][n - 100:n]
    assert rest == pytest.approx(1.0 + tool.steady_error(model, 1.0), abs=1e-6)


def test_an_unstable_loop_has_no_closed_loop_figures() -> None:
    """Above the largest stable force gain (6.63 for this design) the loop has no finite
    H2 norm: closed_loop is None (null in --json), the text says UNSTABLE; the observers'
    figures do not depend on C_f."""
    stable = noise_figures(params_from_config(load_config("configs/mit-demo.yaml")), STEPS)
    params = params_from_config(load_config("configs/mit-demo.yaml", ["design.force_gain=8"]))
    figures = noise_figures(params, STEPS)
    assert figures.closed_loop is None and figures.as_dict()["closed_loop"] is None
    assert "closed loop at C_f = 8: UNSTABLE, no noise figure" in quantisation_text(figures)
    assert figures.observers["rtob"].total == stable.observers["rtob"].total


def test_the_analysis_takes_any_protocols_codec() -> None:
    """The figures come from the protocol's ``quantisation`` hook, not from a protocol the
    analysis knows: the MIT profile's hook gives its model's steps; a rounding codec of
    another protocol has the same noise and no truncation offset; a protocol without
    quantisation (ODrive, CiA 402: floats and integers at the drive's own scale) gives None."""
    from dobhil.drives.load import load_profile
    from dobhil.drives.plugin import CodecQuantisation
    from dobhil.drives.registry import protocol
    profile = load_profile("ak80-9")
    codec = protocol("mit").quantisation(profile)
    assert codec is not None
    model = find_model("cubemars", "AK80-9", profile.firmware)
    assert (codec.position, codec.velocity, codec.torque) == (model.quanta.position, model.quanta.velocity,
                                                              model.quanta.torque)
    assert protocol("odrive").quantisation(load_profile("odrive-0.6")) is None
    assert protocol("cia402").quantisation(load_profile("cia402-emulated")) is None
    params = params_from_config(load_config("configs/mit-demo.yaml"))
    truncating = codec_figures(params, codec)
    rounding = codec_figures(params, CodecQuantisation(codec.position, codec.velocity, codec.torque,
                                                       truncates=False, source={"model": "X"}))
    assert truncating.closed_loop is not None and rounding.closed_loop is not None
    assert rounding.closed_loop["tau_int"].total == truncating.closed_loop["tau_int"].total
    assert truncating.closed_loop["tau_int"].bias != 0.0 and rounding.closed_loop["tau_int"].bias == 0.0
    assert "rounds" in rounding.as_dict()["noise_model"] and rounding.as_dict()["model"] == {"model": "X"}
