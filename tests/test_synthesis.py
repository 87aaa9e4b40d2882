"""Cross-checks of the state-space synthesis against independent calculations."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest
import scipy.integrate

from dobhil.config import load_config
from dobhil.synthesis.loop import loop
from dobhil.synthesis.params import params_from_config


def closed_form_l(p: dict[str, float]) -> tuple[np.ndarray, np.ndarray]:
    """L(s) = num/den from the block diagram of Fig. 1 (Eq. 26, with viscous friction).

    Derived in the Laplace domain, independently of the state space:
    plant P = J s^2 + (b + D) s + K, DOb tau_dis^ = g_D/(s+g_D) (u - (J_n s + b_n) s q),
    RTOb tau_int^ = g_R/(s+g_R) (u - (J_i s + b_i) s q), u = v + tau_dis^.
    """
    j, b, k, d = p["J"], p["b"], p["K"], p["D"]
    jn, bn, ji, bi, gd, gr = p["Jn"], p["bn"], p["Ji"], p["bi"], p["gD"], p["gR"]
    num = gr * np.polymul([1, gd], [j - ji, b + d - bi, k])
    den = np.polymul(np.polymul([1, 0], [1, gr]), [j, b + d + gd * jn, k + gd * bn])
    return num, den


def overrides(p: dict[str, float], cf: float, extra: tuple[str, ...] = ()) -> list[str]:
    names = {"J": "plant.inertia", "b": "plant.viscous_friction", "K": "environment.stiffness",
             "D": "environment.damping", "Jn": "design.nominal_inertia",
             "bn": "design.nominal_friction", "Ji": "design.identified_inertia",
             "bi": "design.identified_friction", "gD": "design.dob_bandwidth",
             "gR": "design.rtob_bandwidth"}
    return [f"{names[k]}={v!r}" for k, v in p.items()] + [f"design.force_gain={cf!r}", *extra]


def random_design(rng: np.random.Generator) -> dict[str, float]:
    j = rng.uniform(0.05, 1.0)
    return {"J": j, "b": rng.uniform(0.01, 2.0), "K": 10 ** rng.uniform(2, 5),
            "D": rng.uniform(1, 100), "Jn": j * rng.uniform(0.5, 1.5),
            "bn": rng.uniform(0.0, 2.0), "Ji": j * rng.uniform(0.3, 1.7),
            "bi": rng.uniform(0.0, 2.0), "gD": rng.uniform(100, 2000), "gR": rng.uniform(100, 2000)}


PAPER = {"J": 0.25, "b": 0.0, "K": 1e4, "D": 50.0, "Jn": 0.25, "bn": 0.0}


@pytest.mark.parametrize("ji,gd,gr", [(0.25, 500, 500), (0.25, 500, 1000), (0.5, 500, 1000),
                                      (0.125, 500, 1000)])
def test_open_loop_equals_eq26_on_the_paper_cases(ji: float, gd: float, gr: float) -> None:
    p = {**PAPER, "Ji": ji, "bi": 0.0, "gD": gd, "gR": gr}
    a, b, c, d = loop(params_from_config(load_config(None, overrides(p, 2.0))), sampled=False,
                      force_gain=0.0).siso("tau_per", "tau_int_hat")
    num, den = closed_form_l(p)
    for w in (0.3, 3.0, 30.0, 300.0, 3000.0):
        s = 1j * w
        ss = (c @ np.linalg.solve(s * np.eye(a.shape[-1]) - a, b))[0, 0] + d[0, 0]
        assert ss == pytest.approx(np.polyval(num, s) / np.polyval(den, s), rel=1e-9)


@pytest.mark.parametrize("seed", range(8))
def test_closed_loop_poles_are_the_roots_of_one_plus_cf_l(seed: int) -> None:
    rng = np.random.default_rng(seed)
    p = random_design(rng)
    cf = rng.uniform(0.1, 5.0)
    lp = loop(params_from_config(load_config(None, overrides(p, cf))), sampled=False)
    poles = np.sort_complex(np.linalg.eigvals(lp.a))
    num, den = closed_form_l(p)
    roots = np.sort_complex(np.roots(np.polyadd(den, cf * num)))
    # the state space also holds q's integrator and the estimate's own mode: the
    # characteristic polynomial has exactly the roots of 1 + C_f L (minimal here)
    assert poles.size == roots.size
    for r in roots:
        assert np.min(np.abs(poles - r)) <= 1e-6 * max(1.0, abs(r))


@pytest.mark.parametrize("seed", range(4))
def test_step_from_transfer_function_equals_time_domain_simulation(seed: int) -> None:
    import control
    rng = np.random.default_rng(100 + seed)
    while True:
        p = random_design(rng)
        num, den = closed_form_l(p)
        cf = 0.5
        cl = control.feedback(cf * control.tf(num, den))
        if np.all(np.real(cl.poles()) < 0):
            break
    t = np.linspace(0.0, 0.05, 501)
    y_tf = control.step_response(cl, T=t).outputs.reshape(-1)
    lp = loop(params_from_config(load_config(None, overrides(p, cf))), sampled=False)
    i, o = lp.input_index("tau_ref"), lp.output_index("tau_int_hat")
    sol = scipy.integrate.solve_ivp(lambda _t, x: lp.a @ x + lp.b[:, i], (0, t[-1]),
                                    np.zeros(lp.a.shape[0]), t_eval=t, method="Radau",
                                    rtol=1e-10, atol=1e-12)
    y_sim = lp.c[o] @ sol.y + lp.d[o, i]
    assert np.max(np.abs(y_sim - y_tf)) < 1e-6 * max(1.0, np.max(np.abs(y_tf)))


@pytest.mark.parametrize("seed", range(3))
@pytest.mark.parametrize("velocity", ["measured", "estimated"])
def test_sampled_loop_converges_to_continuous(velocity: str, seed: int) -> None:
    """Closed-loop poles of the sampled loop, mapped by log(z)/T, tend to the continuous ones."""
    p = random_design(np.random.default_rng(200 + seed))
    extra = (f"design.velocity_source={velocity}", "design.velocity_filter_bandwidth=3000.0")
    cont_cfg = load_config(None, overrides(p, 1.0, extra))
    cont = np.linalg.eigvals(loop(params_from_config(cont_cfg), sampled=False).a)
    errors = []
    for period in (1e-4, 1e-5, 1e-6, 1e-7):
        # periods below what a CAN bus can carry (loop.period's floor): the limit T -> 0 is
        # mathematics, not a config, so the period is set past the config's check
        cfg = dataclasses.replace(cont_cfg, loop=dataclasses.replace(cont_cfg.loop, period=period))
        z = np.linalg.eigvals(loop(params_from_config(cfg), sampled=True).a)
        s = np.log(z.astype(complex)) / period
        errors.append(max(np.min(np.abs(s - c)) for c in cont) / np.abs(cont).max())
    assert errors == sorted(errors, reverse=True)
    # the zero-order hold adds about half a sample of lag: first-order convergence in T
    assert errors[-2] / errors[-1] > 5.0
    assert errors[-1] < 1e-3


def test_observer_filters_of_every_disturbance_model() -> None:
    """With an exact nominal model and no environment, tau_du -> tau_dis^ is the
    observer's filter Q(s): g/(s+g) for constant, (2 g s + g^2)/(s+g)^2 for ramp,
    and unit gain at the model frequency (and DC) for the sinusoid model."""
    import control
    g, w0 = 300.0, 40.0
    common = ["environment.stiffness=0", "environment.damping=0", "plant.viscous_friction=0.2",
              "design.nominal_friction=0.2", f"design.dob_bandwidth={g}",
              f"design.disturbance_frequency={w0}"]
    expect = {"constant": lambda s: g / (s + g),
              "ramp": lambda s: (2 * g * s + g * g) / (s + g) ** 2}
    for model in ("constant", "ramp", "sinusoid"):
        cfg = load_config(None, common + [f"design.disturbance_model={model}"])
        lp = loop(params_from_config(cfg), sampled=False, force_gain=0.0)
        a, b, c, d = lp.siso("tau_du", "tau_dis_hat")
        q = _frequency_response(control.ss(a, b, c, d))
        if model in expect:
            for w in (1.0, 100.0, 1000.0):
                assert q(1j * w) == pytest.approx(expect[model](1j * w), rel=1e-7)
        else:
            assert q(1j * w0) == pytest.approx(1.0, rel=1e-7)
            assert q(1e-9j) == pytest.approx(1.0, rel=1e-6)


def _frequency_response(sys: Any) -> Callable[[complex], complex]:
    """``s -> sys(s)`` bound to this system (a lambda in the loop would see the last one)."""
    return lambda s: complex(sys(s))


@pytest.mark.parametrize("model", ["constant", "ramp", "sinusoid"])
def test_observer_error_poles_are_at_the_bandwidth(model: str) -> None:
    from dobhil.synthesis.observers import aux_observer
    from dobhil.synthesis.params import SignalModel
    obs = aux_observer(SignalModel[model.upper()], 25.0, 0.3, 0.1, 800.0)
    k = obs.order
    # characteristic polynomial (s + g)^k (eigenvalues of a repeated root are ill-conditioned)
    assert np.allclose(np.poly(obs.a), np.poly(np.full(k, -800.0)), rtol=1e-9)


def test_estimated_velocity_tends_to_measured_as_filter_speeds_up() -> None:
    def l_at(src: str, gv: float) -> complex:
        cfg = load_config("configs/paper/fig2b.yaml", [f"design.velocity_source={src}",
                                                        f"design.velocity_filter_bandwidth={gv}"])
        a, b, c, d = loop(params_from_config(cfg), sampled=False, force_gain=0.0).siso(
            "tau_per", "tau_int_hat")
        s = 200j
        return complex((c @ np.linalg.solve(s * np.eye(a.shape[-1]) - a, b))[0, 0])
    ref = l_at("measured", 1.0)
    slow, fast = abs(l_at("estimated", 500.0) - ref), abs(l_at("estimated", 1e6) - ref)
    assert fast < 1e-3 * abs(ref) < slow


@pytest.mark.parametrize("model", ["ramp", "sinusoid"])
@pytest.mark.parametrize("ratio", [1.0, 1000.0])
def test_torque_model_basis_is_well_conditioned(model: str, ratio: float) -> None:
    """Every entry of the observer's matrices is of order g (not g^3 / omega^2), so numpy
    resolves its (repeated) poles: the characteristic polynomial is (s + g)^k to 1e-12."""
    from dobhil.synthesis.observers import aux_observer
    from dobhil.synthesis.params import SignalModel
    g = 2000.0
    obs = aux_observer(SignalModel[model.upper()], g / ratio, 0.3, 0.0, g)
    assert np.abs(obs.a).max() <= 10 * g and np.abs(obs.gain).max() <= 10 * g * 0.3
    k = obs.order
    np.testing.assert_allclose(np.poly(obs.a) / g ** np.arange(k + 1), np.poly(np.full(k, -1.0)),
                               rtol=0, atol=1e-12)


def test_balancing_iterates_only_the_designs_not_yet_settled(monkeypatch: pytest.MonkeyPatch) -> None:
    """[[0, 4], [1, 0]] never settles (both states' factors overshoot: 2 and 1/2, then
    1/2 and 2, ...); in a batch with 999 designs that settle at once, the others are
    scaled as alone and are not scaled 12 times along with it (a sweep's batch has a few
    hundred such designs among thousands)."""
    from dobhil.synthesis import numerics
    cycling = np.array([[0.0, 4.0], [1.0, 0.0]])
    settled = np.array([[-1.0, 2.0], [2.0, -3.0]])
    batch = np.concatenate([np.broadcast_to(settled, (999, 2, 2)), cycling[None]])
    alone = [numerics.balance_scaling(m) for m in (settled, cycling)]
    ratios = [0]
    log2 = np.log2

    def counted(x: np.ndarray) -> np.ndarray:
        ratios[0] += np.size(x)
        return log2(x)
    monkeypatch.setattr(numerics.np, "log2", counted)
    scale = numerics.balance_scaling(batch)
    assert np.array_equal(scale[:999], np.broadcast_to(alone[0], (999, 2)))
    assert np.array_equal(scale[999], alone[1])
    assert ratios[0] <= (999 + 12) * 2       # the settled ones once, the cycling one 12 times


def test_a_sampled_grid_exponentiates_each_distinct_matrix_once(monkeypatch: pytest.MonkeyPatch) -> None:
    """A J_i x K_env grid's controller varies with J_i only and its plant with K_env only:
    6 x 5 designs need the controller's two exponentials for at most 6 and the plant's two
    for at most 5, not 4 x 30 -- and give, bit for bit, the matrices of each design built
    alone."""
    import scipy.linalg
    ji, k = np.meshgrid(np.linspace(0.1, 0.6, 6), np.geomspace(1e2, 1e5, 5), indexing="ij")
    cfg = load_config("configs/paper/fig2b.yaml")
    alone = [loop(params_from_config(cfg, design__identified_inertia=float(j), environment__stiffness=float(s)),
                  sampled=True, force_gain=0.0).siso("tau_per", "tau_int_hat")[:3]
             for j, s in zip(ji.reshape(-1), k.reshape(-1))]
    exponentiated = [0]
    expm = scipy.linalg.expm

    def counted(block: np.ndarray) -> np.ndarray:
        exponentiated[0] += int(np.prod(block.shape[:-2]))
        return expm(block)
    monkeypatch.setattr(scipy.linalg, "expm", counted)
    params = params_from_config(cfg, design__identified_inertia=ji.reshape(-1), environment__stiffness=k.reshape(-1))
    grid = loop(params, sampled=True, force_gain=0.0).siso("tau_per", "tau_int_hat")[:3]
    assert exponentiated[0] <= 2 * 6 + 2 * 5
    for i, one in enumerate(alone):
        assert all(g[i].tobytes() == m.tobytes() for g, m in zip(grid, one))
