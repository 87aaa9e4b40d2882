"""Stability map, analysis report, sweep and the paper's claims."""

from __future__ import annotations

import json

import numpy as np
import pytest

from dobhil.analysis.stability import gain_map, is_stable
from dobhil.analysis.sweep import parse_vary, sweep
from dobhil.cli.main import main
from dobhil.config import load_config
from dobhil.synthesis.loop import loop
from dobhil.synthesis.params import params_from_config


def brute_force_changes(a, b, c, sampled: bool, lo=-3, hi=4, num=30001):  # type: ignore[no-untyped-def]
    ks = np.logspace(lo, hi, num)
    st = is_stable(np.linalg.eigvals(a[None] - ks[:, None, None] * (b @ c)[None]), sampled)
    return st[0], ks[1:][st[1:] != st[:-1]]


def open_loop(overrides: list[str], sampled: bool, path: str = "configs/paper/fig2c.yaml"):  # type: ignore[no-untyped-def]
    cfg = load_config(path, overrides)
    a, b, c, _ = loop(params_from_config(cfg), sampled=sampled, force_gain=0.0).siso(
        "tau_per", "tau_int_hat")
    return a, b, c


CASES = [
    ([], False), ([], True), (["design.delay_samples=2"], True),
    (["design.identified_inertia=0.24191919191919192", "environment.stiffness=95454.8"], False),
    (["design.identified_inertia=0.13636363636363635", "environment.stiffness=83021.76"], True),
    (["design.velocity_source=estimated", "design.velocity_filter_bandwidth=3000"], True),
    (["design.interaction_model=ramp", "design.disturbance_model=sinusoid"], False),
    (["plant.viscous_friction=0.5", "design.identified_inertia=0.2"], True),
]


@pytest.mark.parametrize("overrides,sampled", CASES)
def test_stable_gain_intervals_agree_with_a_dense_gain_scan(overrides: list[str], sampled: bool) -> None:
    a, b, c = open_loop(overrides, sampled)
    g = gain_map(a, b, c, sampled=sampled)
    first, changes = brute_force_changes(a, b, c, sampled)
    edges = sorted({e for iv in g.intervals() for e in iv if 0 < e < np.inf})
    assert len(edges) == len(changes)
    for e, ch in zip(edges, changes):
        assert e == pytest.approx(ch, rel=1e-3)
    assert bool(first) == (g.intervals()[0][0] == 0.0 if g.intervals() else False)
    # exactness: just inside each bound is stable, just outside is not
    for lo, hi in g.intervals():
        if np.isfinite(hi):
            inside, outside = hi * (1 - 1e-6), hi * (1 + 1e-6)
            st = is_stable(np.linalg.eigvals(np.stack([a - inside * b @ c, a - outside * b @ c])),
                           sampled)
            assert st.tolist() == [True, False]


def test_conditionally_stable_design_is_reported_with_both_intervals() -> None:
    a, b, c = open_loop(CASES[3][0], False)
    g = gain_map(a, b, c, sampled=False)
    assert len(g.intervals()) == 2
    assert np.isfinite(g.max_stable_gain) and np.isinf(g.intervals()[-1][1])


def run_json(capsys: pytest.CaptureFixture[str], *argv: str) -> dict:
    assert main(list(argv)) == 0
    return json.loads(capsys.readouterr().out)


@pytest.mark.parametrize("case,bounded", [("a", False), ("b", False), ("c", True), ("d", False)])
def test_analyze_json_max_stable_gain_of_fig2(case: str, bounded: bool,
                                              capsys: pytest.CaptureFixture[str]) -> None:
    out = run_json(capsys, "analyze", f"configs/paper/fig2{case}.yaml", "--json")
    cont = out["continuous"]
    assert (cont["max_stable_force_gain"] is not None) == bounded
    for dom in ("continuous", "discrete"):
        d = out[dom]
        assert {"open_loop", "closed_loop", "max_stable_force_gain", "stable_force_gain_intervals",
                "margins", "step"} <= set(d)
        assert {"poles", "zeros", "relative_degree", "minimum_phase"} <= set(d["open_loop"])
        assert {"overshoot_pct", "rise_time", "settling_time", "steady_state_error"} <= set(d["step"])
    assert out["discrete"]["sample_time"] == 0.001 and out["discrete"]["delay_samples"] == 0
    if bounded:
        assert cont["max_stable_force_gain"] == pytest.approx(1.1187029, rel=1e-6)
        assert cont["open_loop"]["minimum_phase"] is False


def test_analyze_writes_plots(tmp_path, capsys: pytest.CaptureFixture[str]) -> None:  # type: ignore[no-untyped-def]
    assert main(["analyze", "configs/paper/fig2b.yaml", "--plot", str(tmp_path)]) == 0
    for name in ("root_locus.png", "step.png", "bode.png"):
        assert (tmp_path / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_step_metrics_of_a_closed_loop_match_python_control(capsys: pytest.CaptureFixture[str]) -> None:
    import control
    out = run_json(capsys, "analyze", "configs/paper/fig3.yaml", "--json")["continuous"]["step"]
    cfg = load_config("configs/paper/fig3.yaml")
    from dobhil.analysis.transfer import LoopSystems
    sys = LoopSystems.build(params_from_config(cfg), sampled=False).system("closed_loop")
    info = control.step_info(sys, SettlingTimeThreshold=0.02, RiseTimeLimits=(0.1, 0.9))
    assert out["overshoot_pct"] == pytest.approx(info["Overshoot"], rel=2e-2)
    assert out["rise_time"] == pytest.approx(info["RiseTime"], rel=2e-2)
    assert out["settling_time"] == pytest.approx(info["SettlingTime"], rel=5e-2)
    assert abs(out["steady_state_error"]) < 1e-9


@pytest.mark.parametrize("sampled", [False, True])
def test_sweep_equals_pointwise_analysis(sampled: bool) -> None:
    cfg = load_config("configs/paper/fig2b.yaml")
    axes = [parse_vary("design.identified_inertia=0.1:0.6:4"),
            parse_vary("environment.stiffness=log:1e3:1e5:3")]
    res = sweep(cfg, axes, sampled=sampled, chunk=5)
    for i, ji in enumerate(axes[0].values):
        for j, k in enumerate(axes[1].values):
            a, b, c = open_loop([f"design.identified_inertia={float(ji)!r}", f"environment.stiffness={float(k)!r}"],
                                sampled, "configs/paper/fig2b.yaml")
            g = gain_map(a, b, c, sampled=sampled)
            assert res.max_stable_gain[i, j] == pytest.approx(float(g.max_stable_gain), rel=1e-9)
            assert res.minimum_phase[i, j] == bool(g.minimum_phase)


def test_sweep_cli_writes_csv_and_heatmap(tmp_path, capsys: pytest.CaptureFixture[str]) -> None:  # type: ignore[no-untyped-def]
    csv_path, png = tmp_path / "s.csv", tmp_path / "s.png"
    assert main(["sweep", "configs/paper/fig2b.yaml", "--vary", "design.identified_inertia=0.1:0.5:5",
                 "--vary", "environment.stiffness=log:1e3:1e5:4", "--sampled", "--out", str(csv_path),
                 "--plot", str(png)]) == 0
    lines = csv_path.read_text().splitlines()
    assert len(lines) == 1 + 20 and lines[0].startswith("design.identified_inertia,environment.stiffness")
    assert png.read_bytes()[:4] == b"\x89PNG"


def test_paper_command_checks_every_claim(tmp_path, capsys: pytest.CaptureFixture[str]) -> None:  # type: ignore[no-untyped-def]
    assert main(["paper", "--out", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "FAILS" not in out and out.count("[ok]") >= 11
    assert (tmp_path / "fig2_root_locus.png").exists() and (tmp_path / "fig3_step.png").exists()


BAD = [
    (["--set", "plant.inertia=-1"], "plant.inertia = -1.0: must be > 0"),
    (["--set", "design.dob_bandwidth=0"], "design.dob_bandwidth = 0.0: must be > 0"),
    (["--set", "design.nonsense=1"], "unknown config key 'design.nonsense'"),
    (["--set", "design.force_gain=abc"], "design.force_gain = 'abc': wrong type str"),
    (["--set", "design.interaction_model=cubic"], "allowed: constant, ramp, sinusoid"),
    (["--set", "novalue"], "expected key=value"),
]


@pytest.mark.parametrize("extra,message", BAD)
def test_bad_input_is_one_clear_line(extra: list[str], message: str,
                                     capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["analyze", "configs/paper/fig2a.yaml", *extra]) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1 and "Traceback" not in err


def test_yaml_syntax_error_names_the_line(tmp_path, capsys: pytest.CaptureFixture[str]) -> None:  # type: ignore[no-untyped-def]
    bad = tmp_path / "bad.yaml"
    bad.write_text("plant:\n  inertia: 0.25\n  damping: [1, 2\n")
    assert main(["analyze", str(bad)]) == 2
    err = capsys.readouterr().err
    assert "YAML syntax error at line" in err and err.count("\n") == 1


def test_sweep_rejects_structural_keys(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["sweep", "configs/paper/fig2a.yaml", "--vary", "design.delay_samples=0:2:3"]) == 2
    assert "cannot be swept" in capsys.readouterr().err
